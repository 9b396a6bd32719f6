"""Outer boundaries and their moment ellipses."""

from __future__ import annotations

import cv2
import numpy as np

from fiducial_detector.components import outer_boundaries


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
