"""Component boundaries of the thresholded image (paper section 3, step 2).

The outer boundary of every black connected component is traced once (Suzuki & Abe's border
following, as in OpenCV's ``findContours``, a contour-tracing labeller in the family of Chang et
al.'s), by a compiled kernel (:mod:`._border_kernel`) that sums each outer boundary's moments on
the way round: ``findContours`` would hand every border, holes included, to Python as an array of
its own, thousands of them on a frame of fiducials. Each boundary is reduced to the ellipse with
the same area moments as the polygon it encloses, and everything after that is vectorised over
all boundaries.

Thin components that touch only at pixel corners (a steeply slanted ``dot`` design's dot and a
code sector beside it) are also split into their 4-connected parts (:func:`_diagonal_parts`).

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

from . import _border_kernel

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

    def enlarged(self, factor: int) -> Boundaries:
        """These boundaries, traced on an image reduced by ``factor`` x ``factor`` block means,
        in the full image's pixels (a reduced pixel ``i`` covers full pixels ``factor * i`` to
        ``factor * i + factor - 1``, so its centre lies at ``factor * (i + 1/2) - 1/2``)."""
        f = float(factor)
        return Boundaries(
            f * (self.centre + 0.5) - 0.5,
            f * self.axes,
            self.angle,
            f * f * self.area,
            self.ellipticity,
        )

    def select(self, keep: NDArray[np.bool_]) -> Boundaries:
        """The boundaries where ``keep`` is true."""
        return Boundaries(
            self.centre[keep],
            self.axes[keep],
            self.angle[keep],
            self.area[keep],
            self.ellipticity[keep],
        )


@dataclass(frozen=True, slots=True, eq=False)
class _OuterBorders:
    """The outer border of every black component, as :func:`_outer_borders` traces them.

    ``sums`` rows are the six unscaled edge sums of :func:`_polygon_moments` and the length in
    unit steps; border ``i``'s chain, compressed to the ends of its straight runs, is
    ``points[starts[i]:ends[i]]``.
    """

    sums: NDArray[np.float64]
    points: NDArray[np.int32]
    starts: NDArray[np.int64]
    ends: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.sums.shape[0])

    def __getitem__(self, i: int) -> NDArray[np.int32]:
        """Border ``i``'s chain, an ``(n, 1, 2)`` array of ``(u, v)`` as ``cv2.findContours``
        gives it."""
        return self.points[self.starts[i] : self.ends[i]].reshape(-1, 1, 2)


def _outer_borders(binary: NDArray[np.uint8]) -> _OuterBorders:
    """Outer borders of the non-zero components of ``binary``, traced by the compiled kernel
    (:mod:`._border_kernel`): the same chains, in the same order, as the top level of
    ``cv2.findContours(binary, RETR_CCOMP, CHAIN_APPROX_SIMPLE)`` (OpenCV lists the borders in
    the reverse of their raster order, the kernel in raster order: reversed here), with their
    moment sums."""
    image = np.ascontiguousarray(binary, dtype=np.uint8)
    h, w = image.shape
    sums, points, starts = _border_kernel.outer_borders(image, h, w)
    first = np.frombuffer(starts, dtype=np.int64)
    return _OuterBorders(
        np.frombuffer(sums, dtype=np.float64).reshape(-1, 7)[::-1],
        np.frombuffer(points, dtype=np.int32).reshape(-1, 2),
        first[-2::-1],
        first[:0:-1],
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
        Boundaries at least ``MIN_BOUNDARY_PX`` long (by pixel count and by their ellipse's
        perimeter) and at most ``max_extent`` across.
    """
    borders = _outer_borders(binary)
    if len(borders) == 0:
        return _empty()
    ell = _moment_ellipses(_moments(borders.sums[:, :6].T))
    keep = (borders.sums[:, 6] >= MIN_BOUNDARY_PX) & _size_ok(ell, max_extent)
    split = keep & (ell[:, 6] < SPLIT_BELOW) & (ell[:, 3] <= SPLIT_MAX_MINOR_PX)
    which = np.nonzero(split & (ell[:, 5] >= 2 * SPLIT_MIN_AREA))[0].tolist()
    parts = _diagonal_parts(binary, [borders[i] for i in which])
    if parts:
        # The merged boundary stays too (a thin ring may pass through such a contact itself).
        moments, length = _polygon_moments(parts)
        more = _moment_ellipses(moments)
        ell = np.concatenate([ell, more])
        keep = np.concatenate([keep, (length >= MIN_BOUNDARY_PX) & _size_ok(more, max_extent)])
    retry = np.nonzero(
        keep & (ell[:, 6] < HULL_RETRY_BELOW) & (2.0 * ell[:, 2] >= min_hull_extent)
    )[0].tolist()
    if retry:
        # Broken rings: the convex hull's ellipse, accepted where the boundary hugs its outer part.
        n = len(borders)
        chains = [borders[i] if i < n else parts[i - n] for i in retry]
        hull = _moment_ellipses(_polygon_moments([cv2.convexHull(c) for c in chains])[0])
        frac = _on_ellipse(chains, hull)
        good = (hull[:, 5] > 0) & (frac >= HULL_MIN_ON_ELLIPSE)
        hull[:, 6] = 1.0  # the hull's own ellipticity says nothing; the point test passed
        ell[np.array(retry)[good]] = hull[good]
    keep &= _size_ok(ell, max_extent)
    ell = ell[keep]
    return Boundaries(ell[:, 0:2], ell[:, 2:4], ell[:, 4], ell[:, 5], ell[:, 6])


#: Boundaries less elliptical than this are split at diagonal-only contacts
#: (:func:`_diagonal_parts`).
SPLIT_BELOW = 0.85
#: Largest semi-minor axis (pixels) of a boundary split so: a ``dot`` fiducial's dot touches its
#: track only when seen so obliquely that the gap between them is under two pixels, the dot's
#: semi-minor axis then under about 2.5 px, and the merged component's under about 5 px (the
#: code sectors and rings of the 400-target speed frames are wider and are not searched).
SPLIT_MAX_MINOR_PX = 6.0
#: Smallest part (pixels) kept from such a split.
SPLIT_MIN_AREA = 4


def _diagonal_parts(binary: NDArray[np.uint8], chains: list[NDArray[Any]]) -> list[NDArray[Any]]:
    """Outer boundaries of the 4-connected parts of the components bounded by ``chains`` that
    touch each other only diagonally.

    Border following joins black pixels through their corners (8-connectivity). Two dark
    strokes running diagonally one white pixel apart then touch at a pixel corner and are
    traced as one component: the ``dot`` design's central dot and a code sector beside it, a
    pixel and a half apart on a 35 px fiducial slanted 70 deg (through a gap as white as the
    paper), whose merged boundary is neither elliptical nor centred on the dot. A contact that
    joins two parts into one outer boundary lies on that boundary (both of its pixels have
    white 4-neighbours outside), so only boundary pixels are tested, vectorised over all
    boundaries; the few components with a contact are labelled again with
    4-connectivity in their bounding box.

    Returns
    -------
    list of (n_i, 1, 2) int32 arrays
        Compressed outer chains ``(u, v)`` of the parts (at least two per split component, each
        at least :data:`SPLIT_MIN_AREA` pixels), as ``cv2.findContours`` gives them.
    """
    if not chains:
        return []
    fu, fv, idx, _ = _chain_pixels(chains)
    u, v = fu.astype(np.intp), fv.astype(np.intp)
    h, w = binary.shape
    flat = binary.reshape(-1)
    # A contact below pixel (u, v): (u +- 1, v + 1) black, (u +- 1, v) and (u, v + 1) white.
    pix = v * w + u
    below = np.flatnonzero(v + 1 < h)
    below = below[flat[pix[below] + w] == 0]
    contact = np.zeros(len(u), dtype=bool)
    for side in (-1, 1):
        on = below[(u[below] + side >= 0) & (u[below] + side < w)]
        side_pix = pix[on] + side
        contact[on[(flat[side_pix + w] != 0) & (flat[side_pix] == 0)]] = True
    out: list[NDArray[Any]] = []
    starts = np.searchsorted(idx, np.arange(len(chains) + 1))
    for j in np.unique(idx[contact]).tolist():
        x, y, bw, bh = cv2.boundingRect(chains[j])
        n, labels, stats, _ = cv2.connectedComponentsWithStats(
            binary[y : y + bh, x : x + bw], connectivity=4
        )
        if n < 3:
            continue
        # Parts of this component: the 4-connected labels its boundary pixels carry.
        mine = slice(starts[j], starts[j + 1])
        hit = np.bincount(labels[v[mine] - y, u[mine] - x], minlength=n)
        own = np.flatnonzero((hit > 0) & (stats[:, cv2.CC_STAT_AREA] >= SPLIT_MIN_AREA))
        if len(own) < 2:
            continue
        for k in own.tolist():
            found, _ = cv2.findContours(
                (labels == k).view(np.uint8),
                cv2.RETR_EXTERNAL,
                cv2.CHAIN_APPROX_SIMPLE,
                offset=(x, y),
            )
            out.extend(found)
    return out


#: Green's-theorem weights turning the edge sums into moments (as ``cv2.moments`` scales them).
_MOMENT_SCALE = np.array([0.5, 1.0 / 6.0, 1.0 / 6.0, 1.0 / 12.0, 1.0 / 24.0, 1.0 / 12.0])


def _polygon_moments(
    polygons: list[NDArray[Any]],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Moments of closed integer polygons as ``cv2.moments`` gives them, and their chain lengths.

    ``cv2.moments`` costs a Python call per boundary (most of this stage's time with thousands of
    boundaries); here Green's theorem runs over the edges of all polygons at once, each vertex
    joined to its predecessor in the same polygon, and ``np.add.reduceat`` sums the edge terms
    per polygon. The edge terms are integers and, on frames of a few thousand pixels, their sums
    stay far below 2**53, so the sums are exact: the results equal ``cv2.moments``'s bit for bit,
    for a compressed chain as for the full one. Degenerate polygons (zero area) get zero moments, as
    in OpenCV.

    Parameters
    ----------
    polygons : list of (n_i, 1, 2) int32 arrays
        Vertices ``(u, v)``, as returned by ``cv2.findContours`` or ``cv2.convexHull``.

    Returns
    -------
    moments : (len(polygons), 6) ndarray
        Rows ``(m00, m10, m01, mu20, mu11, mu02)``.
    length : (len(polygons),) ndarray
        Unit 8-connected steps around each polygon (each edge counts its Chebyshev length): the
        pixel count of an uncompressed boundary chain.
    """
    counts = np.fromiter(map(len, polygons), dtype=np.int64, count=len(polygons))
    ends = np.cumsum(counts)
    starts = ends - counts
    xy = np.concatenate(polygons).reshape(-1, 2).T.astype(np.float64)
    x, y = xy[0], xy[1]
    # Predecessors: the previous vertex, and the last one for each polygon's first vertex.
    xp, yp = np.empty_like(x), np.empty_like(y)
    xp[1:], yp[1:] = x[:-1], y[:-1]
    xp[starts], yp[starts] = x[ends - 1], y[ends - 1]
    # Buffers are reused (out=): with ~10^5 points, fresh temporaries cost more than arithmetic.
    tmp = np.abs(x - xp)
    term = np.abs(y - yp)
    np.maximum(tmp, term, out=term)
    np.maximum(term, 1.0, out=term)  # a zero step only for a lone pixel, which is one pixel long
    length = np.add.reduceat(term, starts)
    cross = xp * y
    cross -= np.multiply(x, yp, out=tmp)
    xs, ys = xp + x, yp + y
    sums = np.empty((6, len(polygons)))
    sums[0] = np.add.reduceat(cross, starts)
    sums[1] = np.add.reduceat(np.multiply(cross, xs, out=tmp), starts)
    sums[2] = np.add.reduceat(np.multiply(cross, ys, out=tmp), starts)
    # x'^2 + x' x + x^2 = xs^2 - x' x, and likewise for y.
    np.multiply(xs, xs, out=term)
    term -= np.multiply(xp, x, out=tmp)
    sums[3] = np.add.reduceat(np.multiply(term, cross, out=term), starts)
    np.multiply(ys, ys, out=term)
    term -= np.multiply(yp, y, out=tmp)
    sums[5] = np.add.reduceat(np.multiply(term, cross, out=term), starts)
    # 2 x'y' + x'y + x y' + 2 x y = xs ys + x'y' + x y.
    np.multiply(xs, ys, out=term)
    term += np.multiply(xp, yp, out=tmp)
    term += np.multiply(x, y, out=tmp)
    sums[4] = np.add.reduceat(np.multiply(term, cross, out=term), starts)
    return _moments(sums), length


def _moments(edge_sums: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows ``(m00, m10, m01, mu20, mu11, mu02)`` (see :func:`_polygon_moments`) from the six
    unscaled Green's-theorem edge sums of each polygon, ``edge_sums`` of shape (6, n)."""
    degenerate = np.abs(edge_sums[0]) <= np.finfo(np.float32).eps
    sums = edge_sums * np.where(edge_sums[0] < 0, -1.0, 1.0)  # either orientation
    sums *= _MOMENT_SCALE[:, None]
    m00, m10, m01, m20, m11, m02 = sums
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / m00
        cu, cv = m10 * inv, m01 * inv
        rows = np.column_stack([m00, m10, m01, m20 - m10 * cu, m11 - m10 * cv, m02 - m01 * cv])
    rows[degenerate] = 0.0
    return rows


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


def _chain_pixels(
    polygons: list[NDArray[Any]],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp], NDArray[np.int64]]:
    """Every pixel ``(u, v)`` of compressed boundary chains (vectorised over all of them).

    Returns the pixels' columns and rows, the index of the polygon each belongs to, and each
    polygon's pixel count.
    """
    counts = np.fromiter(map(len, polygons), dtype=np.int64, count=len(polygons))
    ends = np.cumsum(counts)
    vert = np.concatenate(polygons).reshape(-1, 2).T.astype(np.float64)
    nxt = np.arange(1, vert.shape[1] + 1)
    nxt[ends - 1] = ends - counts  # the last vertex runs back to the first
    step = vert[:, nxt] - vert
    run = np.maximum(np.abs(step).max(axis=0), 1).astype(np.int64)  # a lone pixel: 1 pixel
    # Every pixel of every run: the run's start plus k unit steps, k = 0 .. run - 1.
    src = np.repeat(np.arange(vert.shape[1]), run)
    k = np.arange(len(src)) - np.repeat(np.cumsum(run) - run, run)
    unit = np.sign(step)
    pu = vert[0, src] + unit[0, src] * k
    pv = vert[1, src] + unit[1, src] * k
    pixels = np.add.reduceat(run, ends - counts)
    idx = np.repeat(np.arange(len(polygons)), pixels)
    return pu, pv, idx, pixels


def _on_ellipse(polygons: list[NDArray[Any]], rows: NDArray[np.float64]) -> NDArray[np.float64]:
    """For each boundary, the fraction of its pixels between 0.55 and 1.12 times the radius of
    its ellipse ``rows[i]`` (vectorised over all pixels of all boundaries).

    The boundaries come as compressed chains (straight runs); every pixel of each run counts.
    """
    pu, pv, idx, pixels = _chain_pixels(polygons)
    du, dv = pu - rows[idx, 0], pv - rows[idx, 1]
    c, s = np.cos(rows[:, 4])[idx], np.sin(rows[:, 4])[idx]
    x = (du * c + dv * s) / rows[idx, 2]
    y = (-du * s + dv * c) / rows[idx, 3]
    rho = np.sqrt(x * x + y * y)
    inside = ((rho > 0.55) & (rho < 1.12)).astype(np.float64)
    return np.bincount(idx, weights=inside, minlength=len(polygons)) / pixels


def _empty() -> Boundaries:
    z = np.zeros(0)
    return Boundaries(np.zeros((0, 2)), np.zeros((0, 2)), z, z, z)
