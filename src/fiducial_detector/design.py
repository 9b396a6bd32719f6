"""Printed fiducial designs: geometry in units of the outer printed radius.

Every length here is a fraction of the radius ``R`` of the outermost printed circle, whose diameter
is the fiducial's nominal diameter (7.1 mm in the paper). The target frame has x to the right on the
printed sheet, y up on the sheet and z out of the printed face; polar angles are counter-clockwise
from +x (see :mod:`fiducial_detector.codebook` for the bit layout).

Two designs (paper section 3, and its section 6 advice):

``dot``
    The paper's fiducial: a black central dot that carries the pose, a wide white ring, and an outer
    coding track of 16 sectors reaching the outer radius.
``ring``
    The largest printed circle carries the pose: a black outer annulus whose outer edge (radius 1)
    is the pose circle and whose inner edge is a second concentric circle; inside it a white gap,
    the coding track, a white ring and a black central dot (a third concentric circle). The
    concentric circles let the pose estimator find the image of the true centre and resolve the
    two-fold pose ambiguity of a single circle.

The same :func:`reflectance` function drives printing and the synthetic renderer, so what is
printed, what is rendered and what the detector expects cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .codebook import BITS, code_bits

DesignName = Literal["dot", "ring"]


@dataclass(frozen=True, slots=True)
class Circle:
    """A printed circle of a design (an edge between black and white).

    Attributes
    ----------
    radius : float
        Radius as a fraction of the outer printed radius.
    dark_inside : bool
        True when the inside of the edge is black.
    """

    radius: float
    dark_inside: bool


@dataclass(frozen=True, slots=True)
class FiducialDesign:
    """Geometry of one printed fiducial design (all radii as fractions of the outer radius).

    Attributes
    ----------
    name : {"dot", "ring"}
    circles : tuple of Circle
        Full printed circles, largest first. ``circles[0]`` is the pose circle.
    dot_radius : float
        Radius of the black central dot.
    track_inner, track_outer : float
        Radial extent of the coding track.
    annulus_inner : float or None
        Inner radius of the black outer annulus (``ring`` only).
    arcs : tuple of Circle
        Circular limits of the coding track larger than the pose circle, which the detector
        fits as partial edges (printed only where a sector is black; ``dark_inside`` as seen
        there): the ``dot`` design's track's outer edge, 3.3 times its dot, which tells the
        depth far better than the dot. (The track's inner edge, where the sectors' corners
        crowd, is not used; the ``ring`` design's pose circle is its largest edge.)
    """

    name: DesignName
    circles: tuple[Circle, ...]
    dot_radius: float
    track_inner: float
    track_outer: float
    annulus_inner: float | None
    arcs: tuple[Circle, ...] = ()

    @property
    def pose_circle(self) -> Circle:
        """The circle that carries the pose (the largest full circle)."""
        return self.circles[0]

    @property
    def track_mid(self) -> float:
        """Radius at which the coding track is read."""
        return 0.5 * (self.track_inner + self.track_outer)

    def neighbour_edges(self, radius: float) -> tuple[float, float]:
        """Radii of the nearest printed edges inside and outside a circle of this design.

        Every printed edge counts (circles, the coding track's limits, the annulus) and the paper's
        edge at :data:`PAPER_RADIUS` outside; 0 inside the central dot.
        """
        edges = {c.radius for c in self.circles} | {self.track_inner, self.track_outer, 1.0}
        if self.annulus_inner is not None:
            edges.add(self.annulus_inner)
        inner = max((e for e in edges if e < radius - 1e-9), default=0.0)
        outer = min((e for e in edges if e > radius + 1e-9), default=PAPER_RADIUS)
        return inner, outer

    def half_way(self, radius: float) -> tuple[float, float]:
        """Half-way to the nearest printed edges inside and outside a circle of this design, in
        units of its own radius (the ``rho_range`` an edge fit's pixels or lines stay within)."""
        inner, outer = self.neighbour_edges(radius)
        return 1.0 - 0.5 * (radius - inner) / radius, 1.0 + 0.5 * (outer - radius) / radius


#: Radius (fraction of the outer radius) of the white paper left around every printed target: the
#: sheet's cut marks leave 15 % of the diameter on each side (``armourcam.printing.CUT_MARGIN``).
PAPER_RADIUS = 1.3

DOT = FiducialDesign(
    name="dot",
    circles=(Circle(0.30, True),),
    dot_radius=0.30,
    track_inner=0.56,
    track_outer=1.0,
    annulus_inner=None,
    arcs=(Circle(1.0, True),),
)

RING = FiducialDesign(
    name="ring",
    circles=(Circle(1.0, True), Circle(0.80, False), Circle(0.24, True)),
    dot_radius=0.24,
    track_inner=0.38,
    track_outer=0.70,
    annulus_inner=0.80,
)

DESIGNS: dict[str, FiducialDesign] = {"dot": DOT, "ring": RING}


def get_design(name: str) -> FiducialDesign:
    """Look up a design by name.

    Raises
    ------
    ValueError
        If ``name`` is not a known design.
    """
    try:
        return DESIGNS[name]
    except KeyError:
        raise ValueError(f"unknown fiducial design {name!r}; known: {sorted(DESIGNS)}") from None


def reflectance(
    design: FiducialDesign, code: int, x: ArrayLike, y: ArrayLike
) -> NDArray[np.float64]:
    """Printed reflectance (0 black, 1 white) at target-frame points.

    Parameters
    ----------
    design : FiducialDesign
    code : int
        Code number in the codebook.
    x, y : array_like
        Target-frame coordinates in units of the outer radius (x right, y up on the sheet).
        Points outside the outer radius are white paper.

    Returns
    -------
    ndarray of float64
        Reflectance at each point, the broadcast shape of ``x`` and ``y``.
    """
    xa, ya = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    r = np.hypot(xa, ya)
    kind = _band_kinds(design)[np.searchsorted(edge_radii(design), r, side="right")]
    value = np.asarray(kind, dtype=np.float64)
    track = kind == _TRACK
    if np.any(track):
        value[track] = _track_value(code, xa[track], ya[track])
    return value


#: Band kinds of :func:`_band_kinds`: printed black, white paper, the coding track.
_BLACK, _WHITE, _TRACK = 0, 1, 2


@cache
def _band_kinds(design: FiducialDesign) -> NDArray[np.int8]:
    """What is printed in each band between consecutive :func:`edge_radii` (band ``k`` holds
    radii from ``edge_radii[k - 1]`` up to ``edge_radii[k]``; the last band the paper outside)."""
    radii = edge_radii(design)
    mids = np.concatenate([[0.5 * radii[0]], 0.5 * (radii[:-1] + radii[1:]), [radii[-1] + 1.0]])
    kinds = np.full(len(mids), _WHITE, dtype=np.int8)
    kinds[mids < design.dot_radius] = _BLACK
    if design.annulus_inner is not None:
        kinds[(mids >= design.annulus_inner) & (mids < 1.0)] = _BLACK
    kinds[(mids >= design.track_inner) & (mids < design.track_outer)] = _TRACK
    return kinds


def _polar_angle(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Polar angle in ``[0, 2 pi)``, counter-clockwise from +x."""
    return np.arctan2(y, x) % (2.0 * np.pi)


def _sectors(theta: NDArray[np.float64]) -> NDArray[np.int64]:
    """Coding-track sector (0..BITS-1, counter-clockwise from +x) at polar angle ``theta``."""
    return np.minimum((theta * (BITS / (2.0 * np.pi))).astype(np.int64), BITS - 1)


def _track_value(code: int, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Reflectance of the coding track at points of it: a black sector where its bit is 1."""
    return 1.0 - code_bits(code)[_sectors(_polar_angle(x, y))].astype(np.float64)


@cache
def edge_radii(design: FiducialDesign) -> NDArray[np.float64]:
    """Radii of every printed circle boundary of ``design`` (where the printing may change
    between black and white), ascending, in units of the outer radius."""
    radii = {design.dot_radius, design.track_inner, design.track_outer, 1.0}
    if design.annulus_inner is not None:
        radii.add(design.annulus_inner)
    return np.array(sorted(radii))


def reflectance_near_edges(
    design: FiducialDesign, code: int, x: ArrayLike, y: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Printed reflectance at target-frame points, with the distance to the nearest printed edge.

    Only edges across which the printing changes count: a circle between a white sector and a
    white ring is no edge, nor a boundary between two sectors of the same bit. The edges
    considered are the circles where the printing changes at the point's polar angle and, in the
    coding track, its sector's two boundaries (as lines through the centre). Near a sector's
    corner the result is approximate: the corner itself may be nearer (outside the track) or
    the boundary's line nearer than its segment (inside). Parameters as :func:`reflectance`.

    Returns
    -------
    value : ndarray of float64
        Reflectance (0 black, 1 white), as :func:`reflectance`.
    distance : ndarray of float64
        Distance to the nearest edge, units of the outer radius (``inf`` where there is none).
    normal_x, normal_y : ndarray of float64
        Unit normal of that edge (either sign; zero where there is none).
    """
    xa, ya = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    r = np.hypot(xa, ya)
    radii = edge_radii(design)
    kinds = _band_kinds(design)
    band = np.searchsorted(radii, r, side="right")
    bits = code_bits(code)
    theta = _polar_angle(xa, ya)
    sector = _sectors(theta)
    track_value = 1.0 - bits[sector].astype(np.float64)

    kind = kinds[band]
    value = np.where(kind == _TRACK, track_value, kind.astype(np.float64))
    # Circles: circle k lies between bands k and k + 1 and is an edge at this angle where they
    # print differently (every band between the point and its nearest such circle prints what
    # the point does); the nearest along the radius.
    circle = np.full(r.shape, np.inf)
    for k, radius in enumerate(radii.tolist()):
        inside, outside = int(kinds[k]), int(kinds[k + 1])
        if _TRACK in (inside, outside):
            other = outside if inside == _TRACK else inside
            circle = np.where(track_value != other, np.minimum(circle, np.abs(r - radius)), circle)
        elif inside != outside:
            circle = np.minimum(circle, np.abs(r - radius))
    distance = circle
    safe = np.where(r > 0, r, 1.0)
    nx, ny = np.where(r > 0, xa / safe, 1.0), np.where(r > 0, ya / safe, 0.0)
    in_track = kind == _TRACK
    if np.any(in_track):
        step = 2.0 * np.pi / BITS
        for side in (0, 1):
            # The sector's start (side 0) or end (side 1), a line through the centre: an edge
            # where the neighbouring sector's bit differs.
            angle = (sector + side) * step
            edge = in_track & (bits[(sector + 2 * side - 1) % BITS] != bits[sector])
            d = np.where(edge, r * np.abs(np.sin(theta - angle)), np.inf)
            nearer = d < distance
            distance = np.where(nearer, d, distance)
            nx = np.where(nearer, -np.sin(angle), nx)
            ny = np.where(nearer, np.cos(angle), ny)
    return value, distance, nx, ny
