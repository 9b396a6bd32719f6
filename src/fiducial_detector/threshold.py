"""Adaptive threshold of Bradley & Roth (paper section 3, step 1).

A pixel is black when it is darker than ``(1 - t)`` times the mean of a square window around it.
The window mean comes from a box filter, which OpenCV evaluates with running sums (the
integral-image idea of Bradley & Roth: constant cost per pixel whatever the window size).

Pixel convention: arrays are indexed ``[v, u]`` (row, column); pixel centres at integer coordinates.

References
----------
D. Bradley and G. Roth, "Adaptive thresholding using the integral image", Journal of Graphics
Tools 12(2), 2007.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import DetectorError

#: Default relative darkness ``t``. Bradley & Roth use 15 %; our fiducials are toner black on
#: white paper (far below any mean), while a mid-grey background next to many white targets sits
#: near the 15 % line and turns into a carpet of noise specks (a 400-target frame traced 115 000
#: boundaries at 15 %, 4 000 at 20 %). Thin, blurred black lines are caught by the thin-line test.
DEFAULT_T = 0.2
#: Smallest default large-window side, pixels; larger than the biggest black region of a target.
MIN_WINDOW = 101
#: Default side of the closing that finds thin dark lines, pixels (0 disables it), and their
#: relative darkness below the closing.
THIN_PX = 5
THIN_T = 0.25


def default_window(shape: tuple[int, ...]) -> int:
    """Bradley & Roth's window: an eighth of the larger image side, odd, at least ``MIN_WINDOW``."""
    side = max(MIN_WINDOW, max(shape[:2]) // 8)
    return side | 1


def bradley_threshold(
    grey: NDArray[np.uint8],
    *,
    window: int | tuple[int, ...] | None = None,
    t: float = DEFAULT_T,
    thin_px: int = THIN_PX,
    thin_t: float = THIN_T,
) -> NDArray[np.uint8]:
    """Binary image of the dark regions: 255 where ``grey < (1 - t) * local mean``, else 0.

    With several windows a pixel is black when it is dark relative to any of them. A single large
    window is the default: a window smaller than a black dot calls the dot's middle white, and
    one smaller than a fiducial's white paper turns the background around the paper into a halo
    of noise specks (each one a boundary to trace).

    Beyond Bradley & Roth, a pixel is also black when it lies on a dark line thinner than
    ``thin_px``: darker by ``thin_t`` than the image's morphological closing (a "black-hat"
    test). The annulus of a small, slanted ``ring`` fiducial is such a line: blurred to a mid
    grey between two white bands, it is darker than its surround but not than a window mean that
    includes the background, and without this test it breaks into arcs.

    Parameters
    ----------
    grey : (H, W) ndarray of uint8
        Grey image indexed ``[v, u]``.
    window : int or tuple of int, optional
        Side(s) of the square averaging windows in pixels (made odd); default
        ``default_window(grey.shape)``.
    t : float
        Relative darkness in ``(0, 1)`` below the local mean that makes a pixel black.
    thin_px : int
        Side of the square closing for thin dark lines, pixels (0 disables the test).
    thin_t : float
        Relative darkness in ``(0, 1)`` below the closing that makes a thin-line pixel black.

    Returns
    -------
    (H, W) ndarray of uint8
        255 for black (foreground) pixels, 0 elsewhere.

    Raises
    ------
    DetectorError
        If ``grey`` is not a 2-D uint8 array or a parameter is out of range.
    """
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise DetectorError(f"threshold needs a 2-D uint8 image, got {grey.dtype} {grey.shape}")
    if not 0.0 < t < 1.0:
        raise DetectorError(f"threshold t must be in (0, 1), got {t}")
    if window is None:
        sides: tuple[int, ...] = (default_window(grey.shape),)
    elif isinstance(window, int | np.integer):
        sides = (int(window),)
    else:
        sides = tuple(int(s) for s in window)
    if not sides or min(sides) < 3:
        raise DetectorError(f"threshold windows must be at least 3 pixels, got {window}")
    # (1 - t) * mean through a lookup table: an 8-bit LUT is far cheaper than float arithmetic.
    lut = np.ceil(np.arange(256) * (1.0 - t)).astype(np.uint8)
    limit: NDArray[Any] | None = None
    for side in sides:
        mean = cv2.boxFilter(grey, -1, (side | 1, side | 1), borderType=cv2.BORDER_REPLICATE)
        lim = cv2.LUT(mean, lut)
        limit = lim if limit is None else cv2.max(limit, lim)
    assert limit is not None
    black = cv2.compare(grey, limit, cv2.CMP_LT)
    if thin_px >= 3:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (thin_px, thin_px))
        closed = cv2.morphologyEx(grey, cv2.MORPH_CLOSE, kernel)
        depth = cv2.subtract(closed, grey)
        thin_lut = np.ceil(np.arange(256) * thin_t).astype(np.uint8)
        black = cv2.bitwise_or(black, cv2.compare(depth, cv2.LUT(closed, thin_lut), cv2.CMP_GT))
    return np.asarray(black, dtype=np.uint8)
