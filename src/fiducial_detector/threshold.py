"""Adaptive threshold of Bradley & Roth (paper section 3, step 1).

A pixel is black when it is darker than ``(1 - t)`` times the mean of a square window around it.
The window mean comes from a box filter, which OpenCV evaluates with running sums (the
integral-image idea of Bradley & Roth: constant cost per pixel whatever the window size); a window
hundreds of pixels wide is averaged on a reduced image and interpolated back (``_window_limit``).

Pixel convention: arrays are indexed ``[v, u]`` (row, column); pixel centres at integer coordinates.

References
----------
D. Bradley and G. Roth, "Adaptive thresholding using the integral image", Journal of Graphics
Tools 12(2), 2007.
"""

from __future__ import annotations

from functools import lru_cache
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
    limit: NDArray[Any] = _window_limit(grey, sides, lut)
    if thin_px >= 3:
        # The black-hat test closed - grey > ceil(thin_t * closed) is the same as
        # grey < closed - ceil(thin_t * closed) (saturating subtraction included), so it folds
        # into the limit, a pixel being black below either: one comparison instead of a
        # subtraction, two comparisons and an OR.
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (thin_px, thin_px))
        closed = cv2.morphologyEx(grey, cv2.MORPH_CLOSE, kernel)
        values = np.arange(256)
        thin_lut = (values - np.ceil(values * thin_t)).astype(np.uint8)
        # In place (dst=): full-frame temporaries cost page faults and cache misses.
        cv2.max(limit, _apply_scale_table(closed, thin_lut, 1.0 - thin_t), dst=limit)
    black = cv2.compare(grey, limit, cv2.CMP_LT, dst=limit)
    return np.asarray(black, dtype=np.uint8)


#: The window mean is taken on an image reduced by the largest power of two that keeps at least
#: this many cells across the smallest window.
MEAN_CELLS = 64


def block_means(image: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
    """``image`` reduced by the means of ``factor`` x ``factor`` blocks (``INTER_AREA`` at an
    integer factor; an incomplete last row or column of blocks is dropped, which moves a mean
    by nothing visible). Reduced pixel ``i`` covers full pixels ``factor * i`` to
    ``factor * i + factor - 1``."""
    h, w = image.shape
    return np.asarray(
        cv2.resize(
            image[: h - h % factor, : w - w % factor],
            (w // factor, h // factor),
            interpolation=cv2.INTER_AREA,
        ),
        dtype=np.uint8,
    )


def _window_limit(
    grey: NDArray[np.uint8], sides: tuple[int, ...], lut: NDArray[np.uint8]
) -> NDArray[np.uint8]:
    """``lut`` of the window mean (the largest over ``sides``) at every pixel of ``grey``.

    A full-resolution box filter costs ~12 ms on a 6 Mpx frame. The mean of a window hundreds
    of pixels wide is a smooth function of position, so it is taken on the image reduced by
    ``2**k`` (exact block means by ``INTER_AREA`` halving), with a window of as many blocks, and
    interpolated back bilinearly: the limit differs from the full-resolution one by at most a
    grey level, so only pixels within a level of it can change (a few noise pixels on paper
    and the odd pixel of a blurred edge, about 1e-4 of a frame; detections are unchanged).
    Windows narrower than ``2 * MEAN_CELLS`` pixels (small images) are filtered at full
    resolution.
    """
    h, w = grey.shape
    factor = 1
    while min(sides) >= 2 * factor * MEAN_CELLS and min(h, w) >= 4 * factor:
        factor *= 2
    small: NDArray[Any] = grey
    for _ in range(factor.bit_length() - 1):
        small = block_means(small, 2)  # exact 2x2 block means, halving after halving
    limit: NDArray[Any] | None = None
    for side in sides:
        cells = max(3, round(side / factor)) | 1
        mean = cv2.boxFilter(small, -1, (cells, cells), borderType=cv2.BORDER_REPLICATE)
        lim = cv2.LUT(mean, lut)
        limit = lim if limit is None else cv2.max(limit, lim)
    assert limit is not None
    if factor > 1:
        limit = cv2.resize(limit, (w, h), interpolation=cv2.INTER_LINEAR)
    return np.asarray(limit, dtype=np.uint8)


def _apply_scale_table(
    image: NDArray[Any], table: NDArray[np.uint8], scale: float
) -> NDArray[np.uint8]:
    """``table[image]``, in place, for a table that rounds ``scale * x`` down.

    OpenCV's SIMD scaling (``convertScaleAbs``, which rounds to nearest) is a third faster than
    ``cv2.LUT`` on a full frame; shifted by an offset it reproduces such a table exactly. It is
    used only when it does, as checked once per table over all 256 values; otherwise the
    lookup table is applied.
    """
    offset = _table_offset(table.tobytes(), scale)
    if offset is None:
        return np.asarray(cv2.LUT(image, table, dst=image), dtype=np.uint8)
    return np.asarray(
        cv2.convertScaleAbs(image, dst=image, alpha=scale, beta=-offset), dtype=np.uint8
    )


@lru_cache(maxsize=8)
def _table_offset(table: bytes, scale: float) -> float | None:
    """Offset making ``convertScaleAbs(x, scale, -offset)`` equal ``table[x]`` for every 8-bit
    ``x``, or None when the middle of the feasible range does not (see
    :func:`_apply_scale_table`)."""
    values = np.arange(256)
    exact = np.frombuffer(table, dtype=np.uint8)
    offset = 0.5 * float((values * scale - exact).max())
    got = cv2.convertScaleAbs(values.astype(np.uint8)[None, :], alpha=scale, beta=-offset)
    return offset if np.array_equal(got[0], exact) else None
