"""The designs' reflectance function against their documented radii and bit layout."""

from __future__ import annotations

import numpy as np
import pytest

from fiducial_detector.codebook import BITS, code_bits, code_count
from fiducial_detector.design import (
    DESIGNS,
    DOT,
    RING,
    FiducialDesign,
    get_design,
    reflectance,
    reflectance_near_edges,
)

EPS = 1e-6

# The documented layouts (design.py docstring and docs/architecture.md), outermost last:
# (inner radius, outer radius, what is printed) with "track" meaning the code sector's bit.
LAYOUT = {
    "dot": [(0.0, 0.30, "black"), (0.30, 0.56, "white"), (0.56, 1.0, "track")],
    "ring": [
        (0.0, 0.24, "black"),
        (0.24, 0.38, "white"),
        (0.38, 0.70, "track"),
        (0.70, 0.80, "white"),
        (0.80, 1.0, "black"),
    ],
}


def _expected(kind: str, bit: int) -> float:
    if kind == "black":
        return 0.0
    if kind == "white":
        return 1.0
    return 0.0 if bit else 1.0


@pytest.mark.parametrize("name", ["dot", "ring"])
@pytest.mark.parametrize("code", [0, 17, 65])
def test_reflectance_follows_documented_radii(name: str, code: int) -> None:
    """Along the middle of every sector, each band between documented radii prints as stated."""
    design = get_design(name)
    bits = code_bits(code)
    for k in range(BITS):
        theta = 2.0 * np.pi * (k + 0.5) / BITS
        for r0, r1, kind in LAYOUT[name]:
            r = np.linspace(r0 + EPS, r1 - EPS, 50)
            got = reflectance(design, code, r * np.cos(theta), r * np.sin(theta))
            np.testing.assert_array_equal(got, _expected(kind, int(bits[k])))
        r_out = np.linspace(1.0 + EPS, 3.0, 20)
        np.testing.assert_array_equal(
            reflectance(design, code, r_out * np.cos(theta), r_out * np.sin(theta)), 1.0
        )


@pytest.mark.parametrize("design", [DOT, RING])
def test_circles_are_edges_with_documented_sides(design: FiducialDesign) -> None:
    """Each full circle is a black/white edge all the way round, dark on the documented side."""
    theta = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
    for circle in design.circles:
        inside = reflectance(
            design, 3, (circle.radius - EPS) * np.cos(theta), (circle.radius - EPS) * np.sin(theta)
        )
        outside = reflectance(
            design, 3, (circle.radius + EPS) * np.cos(theta), (circle.radius + EPS) * np.sin(theta)
        )
        np.testing.assert_array_equal(inside, 0.0 if circle.dark_inside else 1.0)
        np.testing.assert_array_equal(outside, 1.0 if circle.dark_inside else 0.0)
    radii = [c.radius for c in design.circles]
    assert radii == sorted(radii, reverse=True)
    assert design.pose_circle is design.circles[0]


def test_ring_pose_circle_is_the_outer_edge() -> None:
    """The ring design's pose circle is the printed outline, several times the dot's."""
    assert RING.pose_circle.radius == 1.0
    assert RING.pose_circle.radius / DOT.pose_circle.radius > 3.0
    assert len(RING.circles) >= 2  # a concentric circle to resolve the pose ambiguity


@pytest.mark.parametrize("name", ["dot", "ring"])
def test_sector_angles_are_counter_clockwise_from_x(name: str) -> None:
    """Bit k covers polar angles [2 pi k / 16, 2 pi (k + 1) / 16), y up, counter-clockwise."""
    design = get_design(name)
    r = design.track_mid
    for code in range(code_count()):
        bits = code_bits(code)
        k = np.arange(BITS)
        for frac in (0.02, 0.5, 0.98):
            theta = 2.0 * np.pi * (k + frac) / BITS
            got = reflectance(design, code, r * np.cos(theta), r * np.sin(theta))
            np.testing.assert_array_equal(got, np.where(bits == 1, 0.0, 1.0))


def test_reflectance_broadcasts() -> None:
    """x and y broadcast against each other."""
    x = np.linspace(-1.2, 1.2, 7)[None, :]
    y = np.linspace(-1.2, 1.2, 5)[:, None]
    assert reflectance(RING, 0, x, y).shape == (5, 7)


def test_unknown_design_is_rejected() -> None:
    """The error names the design and the known ones."""
    with pytest.raises(ValueError, match=r"'star'.*dot.*ring"):
        get_design("star")
    assert set(DESIGNS) == {"dot", "ring"}


@pytest.mark.parametrize("name", ["dot", "ring"])
@pytest.mark.parametrize("code", [0, 23, 63])
def test_nearest_edge_is_an_edge_and_none_is_nearer(name: str, code: int) -> None:
    """Brute force over random points: the printing changes a hair beyond the reported distance
    along the reported normal (on one side), and it is the same everywhere within 0.9 of that
    distance, except where a sector's corner is nearer (there the nearest edge is approximate)."""
    design = get_design(name)
    rng = np.random.default_rng(code)
    x, y = rng.uniform(-1.25, 1.25, (2, 20000))
    value, distance, nx, ny = reflectance_near_edges(design, code, x, y)
    assert np.array_equal(value, reflectance(design, code, x, y))
    near = np.isfinite(distance)
    assert near.mean() > 0.4
    x, y, value, distance, nx, ny = (a[near] for a in (x, y, value, distance, nx, ny))
    step = distance + 1e-9
    plus = reflectance(design, code, x + step * nx, y + step * ny)
    minus = reflectance(design, code, x - step * nx, y - step * ny)
    assert np.mean((plus != value) | (minus != value)) > 0.99
    angles = np.arange(BITS) * 2.0 * np.pi / BITS
    corners = np.concatenate(
        [rho * np.exp(1j * angles) for rho in (design.track_inner, design.track_outer)]
    )
    clear = np.abs((x + 1j * y)[:, None] - corners[None, :]).min(axis=1) > distance
    assert clear.sum() > 5000
    for angle in np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False):
        r = 0.9 * distance
        around = reflectance(design, code, x + r * np.cos(angle), y + r * np.sin(angle))
        assert np.array_equal(around[clear], value[clear])
