"""Component boundaries of the thresholded image (paper section 3, step 2).

The outer boundary of every black connected component is traced once at full resolution (OpenCV's
Suzuki-Abe border following, a contour-tracing labeller in the family of Chang et al.'s). Each
boundary is reduced to the ellipse with the same area moments as the polygon it encloses, and
everything after that is vectorised over all boundaries.

Only *outer* boundaries are used: a fiducial's pose circle is the outer edge of a black region
(the ``ring`` design's annulus, with whatever code sectors blur merges into it, or the ``dot``
design's central dot), so neither holes nor merged inner parts disturb it.

Pixel convention: ``(u, v)`` = (column, row), pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

#: Paper step 2: boundaries shorter than this (pixels) are discarded.
MIN_BOUNDARY_PX = 10.0
#: Half a pixel: the polygon joins the centres of the outermost black pixels, the edge lies
#: half a pixel further out.
_EDGE_OFFSET_PX = 0.5


@dataclass(frozen=True, slots=True, eq=False)
class Boundaries:
    """Outer boundaries of black components, each summarised by its moment ellipse.

    Attributes
    ----------
    centre : (n, 2) ndarray
        Centroid ``(u, v)`` of the region enclosed by each boundary.
    axes : (n, 2) ndarray
        Semi-axes ``(a, b)``, ``a >= b``, of the ellipse with the region's second moments,
        widened by half a pixel to the edge.
    angle : (n,) ndarray
        Major-axis angle, radians in ``[0, pi)`` from +u towards +v.
    area : (n,) ndarray
        Area enclosed by the boundary polygon, pixels.
    ellipticity : (n,) ndarray
        ``area / (pi a b)`` before widening: 1 for an ellipse, smaller for arcs and other shapes
        whose spread exceeds their area.
    """

    centre: NDArray[np.float64]
    axes: NDArray[np.float64]
    angle: NDArray[np.float64]
    area: NDArray[np.float64]
    ellipticity: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.area.shape[0])

    def select(self, keep: NDArray[np.bool_]) -> Boundaries:
        """The boundaries where ``keep`` is true."""
        return Boundaries(
            self.centre[keep],
            self.axes[keep],
            self.angle[keep],
            self.area[keep],
            self.ellipticity[keep],
        )


def outer_boundaries(
    binary: NDArray[np.uint8], *, max_extent: float, min_hull_extent: float = 0.0
) -> Boundaries:
    """Outer boundaries of the black (non-zero) regions of ``binary``, with size limits.

    A boundary that is not itself elliptical (a broken thin ring traced as a "C") is replaced by
    its convex hull when most of its points lie in the outer part of the hull's moment ellipse:
    small, slanted ``ring`` fiducials often lose a pixel of their annulus where it is thinnest.

    Parameters
    ----------
    binary : (H, W) ndarray of uint8
        Thresholded image, non-zero = black.
    max_extent : float
        Largest accepted major axis (diameter), pixels; longer boundaries are discarded.
    min_hull_extent : float
        Only boundaries at least this long (major axis, pixels) get the convex-hull retry.

    Returns
    -------
    Boundaries
        Boundaries at least ``MIN_BOUNDARY_PX`` long (by point count and by their ellipse's
        perimeter) and at most ``max_extent`` across.
    """
    # RETR_CCOMP puts the outer boundary of every component at the top level, including
    # components that sit inside another one's hole. With unapproximated chains the point count
    # is the boundary length, so step 2's short-boundary limit costs nothing per contour.
    contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if hierarchy is None:
        return _empty()
    top = (hierarchy[0][:, 3] < 0).tolist()
    min_len = int(MIN_BOUNDARY_PX)
    kept = [c for c, is_top in zip(contours, top, strict=True) if is_top and len(c) >= min_len]
    if not kept:
        return _empty()
    ell = _moment_ellipses(np.array([_moment_row(c) for c in kept]))
    keep = _size_ok(ell, max_extent)
    retry = np.nonzero(
        keep & (ell[:, 6] < HULL_RETRY_BELOW) & (2.0 * ell[:, 2] >= min_hull_extent)
    )[0]
    if retry.size:
        # Broken rings: the convex hull's ellipse, accepted where the boundary hugs its outer part.
        hull = _moment_ellipses(np.array([_moment_row(cv2.convexHull(kept[i])) for i in retry]))
        frac = _on_ellipse([kept[i] for i in retry.tolist()], hull)
        good = (hull[:, 5] > 0) & (frac >= HULL_MIN_ON_ELLIPSE)
        hull[:, 6] = 1.0  # the hull's own ellipticity says nothing; the point test passed
        ell[retry[good]] = hull[good]
    keep &= _size_ok(ell, max_extent)
    ell = ell[keep]
    return Boundaries(ell[:, 0:2], ell[:, 2:4], ell[:, 4], ell[:, 5], ell[:, 6])


def _moment_row(contour: NDArray[Any]) -> tuple[float, ...]:
    m = cv2.moments(contour)
    return (m["m00"], m["m10"], m["m01"], m["mu20"], m["mu11"], m["mu02"])


#: Boundaries less elliptical than this get the convex-hull retry.
HULL_RETRY_BELOW = 0.85
#: Fraction of a boundary's points that must lie in the outer part of its hull's ellipse (a thin
#: broken ring: the outer edge at radius 1, the inner edge at 0.8 of it).
HULL_MIN_ON_ELLIPSE = 0.6


def _moment_ellipses(mom: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows ``(u, v, a, b, angle, area, ellipticity)`` from polygon moments
    ``(m00, m10, m01, mu20, mu11, mu02)``; semi-axes widened by half a pixel to the edge."""
    m00 = np.maximum(mom[:, 0], 1e-9)
    cu = mom[:, 1] / m00
    cv = mom[:, 2] / m00
    cxx, cxy, cyy = mom[:, 3] / m00, mom[:, 4] / m00, mom[:, 5] / m00
    # Eigenvalues of the 2x2 covariance, closed form.
    half_tr = 0.5 * (cxx + cyy)
    root = np.sqrt(np.maximum(0.25 * (cxx - cyy) ** 2 + cxy**2, 0.0))
    a = 2.0 * np.sqrt(np.maximum(half_tr + root, 1e-9))
    b = 2.0 * np.sqrt(np.maximum(half_tr - root, 1e-9))
    angle = (0.5 * np.arctan2(2.0 * cxy, cxx - cyy)) % np.pi
    ellipticity = mom[:, 0] / (np.pi * a * b)
    return np.column_stack(
        [cu, cv, a + _EDGE_OFFSET_PX, b + _EDGE_OFFSET_PX, angle, mom[:, 0], ellipticity]
    )


def _size_ok(ell: NDArray[np.float64], max_extent: float) -> NDArray[np.bool_]:
    """Step 2's boundary-length limits, with Ramanujan's perimeter of the moment ellipse."""
    a, b = ell[:, 2], ell[:, 3]
    h = ((a - b) / (a + b)) ** 2
    perimeter = np.pi * (a + b) * (1.0 + 3.0 * h / (10.0 + np.sqrt(4.0 - 3.0 * h)))
    return (ell[:, 5] > 2.0) & (perimeter >= MIN_BOUNDARY_PX) & (2.0 * a <= max_extent)


def _on_ellipse(contours: list[NDArray[Any]], rows: NDArray[np.float64]) -> NDArray[np.float64]:
    """For each boundary, the fraction of its points between 0.55 and 1.12 times the radius of
    its ellipse ``rows[i]`` (vectorised over all points of all boundaries)."""
    counts = np.array([len(c) for c in contours])
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64)
    idx = np.repeat(np.arange(len(contours)), counts)
    r = rows[idx]
    d = pts - r[:, :2]
    c, s = np.cos(r[:, 4]), np.sin(r[:, 4])
    x = (d[:, 0] * c + d[:, 1] * s) / r[:, 2]
    y = (-d[:, 0] * s + d[:, 1] * c) / r[:, 3]
    rho = np.sqrt(x * x + y * y)
    inside = ((rho > 0.55) & (rho < 1.12)).astype(np.float64)
    return np.bincount(idx, weights=inside, minlength=len(contours)) / np.maximum(counts, 1)


def _empty() -> Boundaries:
    z = np.zeros(0)
    return Boundaries(np.zeros((0, 2)), np.zeros((0, 2)), z, z, z)
