"""Outer boundaries and their moment ellipses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from binary_scenes import random_binary

from fiducial_detector.components import (
    _diagonal_parts,
    _on_ellipse,
    _polygon_moments,
    outer_boundaries,
)
from fiducial_detector.threshold import block_means


def _ellipse_mask(shape: tuple[int, int], centre, axes, angle_deg, thickness=-1):  # type: ignore[no-untyped-def]
    img = np.zeros(shape, np.uint8)
    # Draw with sub-pixel precision (shift=4) for an accurate reference.
    c = (round(centre[0] * 16), round(centre[1] * 16))
    ax = (round(axes[0] * 16), round(axes[1] * 16))
    cv2.ellipse(img, c, ax, angle_deg, 0, 360, 255, thickness, cv2.LINE_8, 4)
    return img


def test_filled_ellipse_moments() -> None:
    mask = _ellipse_mask((120, 160), (80.3, 60.6), (30.0, 14.0), 25.0)
    b = outer_boundaries(mask, max_extent=200)
    assert len(b) == 1
    assert np.allclose(b.centre[0], (80.3, 60.6), atol=0.1)
    assert np.allclose(b.axes[0], (30.0, 14.0), atol=0.6)
    assert abs(np.degrees(b.angle[0]) - 25.0) < 1.5
    assert b.ellipticity[0] > 0.95


def test_broken_ring_recovered_by_hull_and_size_limits() -> None:
    ring = _ellipse_mask((120, 160), (80.0, 60.0), (30.0, 15.0), -10.0, thickness=2)
    ring[:, 48:53] = 0  # break the ring: its boundary becomes a "C"
    b = outer_boundaries(ring, max_extent=200)
    assert len(b) == 1
    assert np.allclose(b.centre[0], (80.0, 60.0), atol=1.0)
    assert abs(b.axes[0, 0] - 31.0) < 1.5 and abs(b.axes[0, 1] - 16.0) < 1.5
    assert outer_boundaries(ring, max_extent=40).centre.shape == (0, 2)
    speck = np.zeros((20, 20), np.uint8)
    speck[5:7, 5:7] = 255  # boundary far shorter than 10 px
    assert len(outer_boundaries(speck, max_extent=100)) == 0


def test_vectorised_moments_equal_opencv_bit_for_bit() -> None:
    """Green's theorem over compressed chains gives cv2.moments of the full chains exactly, and
    the chain length (unit steps) equals the full chain's point count."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        img = random_binary(rng)
        full, _ = cv2.findContours(img, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
        compressed, _ = cv2.findContours(img, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        rows, length = _polygon_moments(list(compressed))
        for c, row, n in zip(full, rows, length, strict=True):
            m = cv2.moments(c)
            assert tuple(row) == (m["m00"], m["m10"], m["m01"], m["mu20"], m["mu11"], m["mu02"])
            assert n == len(c)


def test_on_ellipse_counts_every_pixel_of_compressed_runs() -> None:
    """The hull retry's point test sees the same pixels from compressed chains as from full ones."""
    rng = np.random.default_rng(8)
    img = random_binary(rng, (120, 160))
    full, _ = cv2.findContours(img, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    compressed, _ = cv2.findContours(img, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    rows = np.zeros((len(full), 7))
    for i, c in enumerate(full):
        pts = c.reshape(-1, 2).astype(float)
        rows[i, :2] = pts.mean(axis=0)
        rows[i, 2:4] = (pts.std(axis=0).max() * 1.5 + 1.0, pts.std(axis=0).min() * 1.5 + 1.0)
        rows[i, 4] = rng.uniform(0, np.pi)
    got = _on_ellipse(list(compressed), rows)
    for c, row, frac in zip(full, rows, got, strict=True):
        d = c.reshape(-1, 2) - row[:2]
        co, si = np.cos(row[4]), np.sin(row[4])
        rho = np.hypot(
            (d[:, 0] * co + d[:, 1] * si) / row[2], (d[:, 1] * co - d[:, 0] * si) / row[3]
        )
        assert frac == pytest.approx(np.mean((rho > 0.55) & (rho < 1.12)), abs=1e-12)


def test_dot_touching_a_stroke_diagonally_is_split_out() -> None:
    """A thin dot whose corner touches a parallel stroke's (a slanted ``dot`` fiducial's dot and
    a code sector one white pixel apart) is one 8-connected component, whose boundary is
    neither elliptical nor centred on the dot; its 4-connected parts come out as well, the dot
    with the same moment ellipse as when drawn alone."""
    centre = np.array([30.3, 29.8])
    normal = np.array([-np.sin(np.radians(45.0)), np.cos(np.radians(45.0))])
    dot = _ellipse_mask((60, 60), centre, (6.0, 2.0), 45.0)
    bar = _ellipse_mask((60, 60), centre + 4.75 * normal, (11.0, 1.6), 45.0)
    both = dot | bar
    assert not (dot & bar).any()
    assert cv2.connectedComponents(both, connectivity=8)[0] == 2  # background + one
    assert cv2.connectedComponents(both, connectivity=4)[0] == 3
    alone = outer_boundaries(dot, max_extent=60)
    b = outer_boundaries(both, max_extent=60)
    assert len(b) == 3  # the merged boundary, the dot, the stroke
    near = np.hypot(*(b.centre - alone.centre[0]).T) < 1e-9
    assert near.sum() == 1
    assert np.allclose(b.axes[near], alone.axes, atol=1e-9)
    assert b.ellipticity[near][0] > 0.9
    # The merged boundary alone is what the 8-connected tracing gives: centred off the dot.
    assert np.hypot(*(b.centre[~near] - centre).T).max() > 1.5


def test_diagonal_parts_are_the_four_connected_components() -> None:
    """Every part split off is exactly one 4-connected component of the image (same moments),
    at least two come from each split component, and components without diagonal contacts
    (filled ellipses drawn apart) give none."""
    rng = np.random.default_rng(9)
    total = 0
    for _ in range(10):
        img = random_binary(rng)
        contours, hierarchy = cv2.findContours(img, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        outer = [c for c, h in zip(contours, hierarchy[0], strict=True) if h[3] < 0]
        parts = _diagonal_parts(img, outer)
        _, labels = cv2.connectedComponents(img, connectivity=4)
        for part in parts:
            p = part.reshape(-1, 2)
            label = labels[p[0, 1], p[0, 0]]
            assert label > 0
            own, _ = cv2.findContours(
                (labels == label).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
            )
            assert len(own) == 1
            assert cv2.moments(own[0]) == cv2.moments(part)
        total += len(parts)
    assert total >= 10
    apart = _ellipse_mask((60, 80), (20.0, 30.0), (8.0, 3.0), 30.0)
    apart |= _ellipse_mask((60, 80), (50.0, 30.0), (8.0, 3.0), 30.0)
    contours, _ = cv2.findContours(apart, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    assert _diagonal_parts(apart, list(contours)) == []


def test_boundaries_on_a_reduced_image_are_enlarged_to_full_pixels() -> None:
    """An ellipse traced on the image reduced by 2x2 and 3x3 block means, enlarged, has the
    full image's centre and axes (within the reduced pixel's quantisation)."""
    centre, axes = (161.3, 97.8), (44.0, 21.0)
    mask = _ellipse_mask((240, 330), centre, axes, 35.0)
    full = outer_boundaries(mask, max_extent=400)
    perimeter = np.pi * (axes[0] + axes[1]) * 1.1
    for f in (2, 3):
        small = np.where(block_means(mask, f) >= 128, 255, 0).astype(np.uint8)
        b = outer_boundaries(small, max_extent=400 / f).enlarged(f)
        assert len(b) == 1
        assert np.allclose(b.centre[0], centre, atol=0.1 * f), (f, b.centre[0])
        assert np.allclose(b.axes[0], axes, atol=0.6 * f), (f, b.axes[0])
        assert abs(np.degrees(b.angle[0]) - 35.0) < 1.5
        # The polygon joins the outermost pixels' centres: a reduced pixel's half-width along
        # the boundary at most separates it from the full image's.
        assert abs(b.area[0] - full.area[0]) <= 0.5 * f * perimeter
