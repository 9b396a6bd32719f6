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


def outer_boundaries(binary: NDArray[np.uint8], *, max_extent: float) -> Boundaries:
    """Outer boundaries of the black (non-zero) regions of ``binary``, with size limits.

    A boundary that is not itself elliptical (a broken thin ring traced as a "C") is replaced by
    its convex hull when most of its points lie on the hull's moment ellipse: small, slanted
    ``ring`` fiducials often lose a pixel of their annulus where it is thinnest.

    Parameters
    ----------
    binary : (H, W) ndarray of uint8
        Thresholded image, non-zero = black.
    max_extent : float
        Largest accepted major axis (diameter), pixels; longer boundaries are discarded.

    Returns
    -------
    Boundaries
        Boundaries at least ``MIN_BOUNDARY_PX`` long (by their ellipse's perimeter) and at most
        ``max_extent`` across.
    """
    # RETR_CCOMP puts the outer boundary of every component at the top level, including
    # components that sit inside another one's hole; SIMPLE chains keep the same polygon.
    contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return _empty()
    top = hierarchy[0][:, 3] < 0
    kept = []
    moments = []
    for contour, is_top in zip(contours, top.tolist(), strict=True):
        # Fewer than 4 corners: a speck or a straight sliver, never a boundary of 10 pixels.
        if is_top and len(contour) >= 4:
            m = cv2.moments(contour)
            kept.append(contour)
            moments.append((m["m00"], m["m10"], m["m01"], m["mu20"], m["mu11"], m["mu02"]))
    if not moments:
        return _empty()
    ell = _moment_ellipses(np.array(moments))
    keep = _size_ok(ell, max_extent)
    # Broken rings: retry with the convex hull where the boundary is big enough but not an ellipse.
    for i in np.nonzero(keep & (ell[:, 6] < HULL_RETRY_BELOW))[0].tolist():
        hull = cv2.convexHull(kept[i])
        m = cv2.moments(hull)
        row = _moment_ellipses(
            np.array([[m["m00"], m["m10"], m["m01"], m["mu20"], m["mu11"], m["mu02"]]])
        )[0]
        if row[5] > 0 and _on_ellipse(kept[i], row) >= HULL_MIN_ON_ELLIPSE:
            row[6] = 1.0  # the hull's own ellipticity says nothing; the point test passed
            ell[i] = row
    keep &= _size_ok(ell, max_extent)
    ell = ell[keep]
    return Boundaries(ell[:, 0:2], ell[:, 2:4], ell[:, 4], ell[:, 5], ell[:, 6])


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


def _on_ellipse(contour: NDArray[np.int32], row: NDArray[np.float64]) -> float:
    """Fraction of a boundary's points between 0.55 and 1.12 times the ellipse ``row``'s radius."""
    pts = contour.reshape(-1, 2).astype(np.float64) - row[:2]
    c, s = np.cos(row[4]), np.sin(row[4])
    x = (pts[:, 0] * c + pts[:, 1] * s) / row[2]
    y = (-pts[:, 0] * s + pts[:, 1] * c) / row[3]
    rho = np.sqrt(x * x + y * y)
    return float(np.mean((rho > 0.55) & (rho < 1.12)))


def _empty() -> Boundaries:
    z = np.zeros(0)
    return Boundaries(np.zeros((0, 2)), np.zeros((0, 2)), z, z, z)
