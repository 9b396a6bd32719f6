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
    xa = np.asarray(x, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    r2 = xa * xa + ya * ya
    black = r2 < design.dot_radius**2
    in_track = (r2 >= design.track_inner**2) & (r2 < design.track_outer**2)
    if np.any(in_track):
        bits = code_bits(code).astype(bool)
        theta = np.arctan2(ya, xa) % (2.0 * np.pi)
        sector = np.minimum((theta * (BITS / (2.0 * np.pi))).astype(np.int64), BITS - 1)
        black |= in_track & bits[sector]
    if design.annulus_inner is not None:
        black |= (r2 >= design.annulus_inner**2) & (r2 < 1.0)
    return np.where(black, 0.0, 1.0)
