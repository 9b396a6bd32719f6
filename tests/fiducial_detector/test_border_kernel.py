"""The compiled border follower against OpenCV's ``findContours``, which it replaces."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from binary_scenes import random_binary

from fiducial_detector import _border_kernel
from fiducial_detector.components import _moments, _outer_borders, _polygon_moments


def _opencv_outer(binary: np.ndarray) -> list[np.ndarray]:
    """The top level of RETR_CCOMP (every component's outer border), compressed chains."""
    contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return []
    return [c for c, h in zip(contours, hierarchy[0], strict=True) if h[3] < 0]


def _binaries() -> list[np.ndarray]:
    """Speckle of every density (holes in holes, components in holes, lone pixels, diagonal
    contacts), drawn shapes, and the degenerate images: empty, full, one row, one column,
    a checkerboard, black along the image's edge."""
    rng = np.random.default_rng(41)
    out = []
    for density in (0.02, 0.1, 0.3, 0.5, 0.7, 0.9):
        for shape in ((37, 53), (64, 17), (5, 120)):
            out.append((rng.random(shape) < density).astype(np.uint8) * 255)
    out += [random_binary(rng) for _ in range(12)]
    out.append(np.zeros((20, 30), np.uint8))
    out.append(np.full((20, 30), 255, np.uint8))
    out.append((rng.random((1, 40)) < 0.5).astype(np.uint8))
    out.append((rng.random((40, 1)) < 0.5).astype(np.uint8))
    out.append(np.full((1, 1), 7, np.uint8))
    checker = (np.indices((16, 21)).sum(axis=0) % 2).astype(np.uint8)
    out.append(checker)
    frame = np.zeros((12, 15), np.uint8)
    frame[0, :] = frame[-1, :] = frame[:, 0] = frame[:, -1] = 200
    frame[5:7, 6:9] = 1
    out.append(frame)
    return out


@pytest.mark.parametrize("index", range(len(_binaries())))
def test_outer_borders_are_opencvs_chains_with_their_moment_sums(index: int) -> None:
    """Every outer border, chain for chain and point for point, in findContours' order (the
    holes are followed but not listed); the sums taken on the way round give the numpy moments
    of those chains exactly, and the lengths their unit steps."""
    binary = _binaries()[index]
    expected = _opencv_outer(binary)
    borders = _outer_borders(binary)
    assert len(borders) == len(expected)
    for i, chain in enumerate(expected):
        assert np.array_equal(borders[i], chain), i
    if expected:
        rows, length = _polygon_moments(expected)
        assert np.array_equal(_moments(borders.sums[:, :6].T), rows)
        assert np.array_equal(borders.sums[:, 6], length)


def test_a_frame_of_fiducials_and_clutter() -> None:
    """A thresholded speed-benchmark-like frame: thousands of borders, all of OpenCV's."""
    rng = np.random.default_rng(5)
    img = np.zeros((400, 600), np.uint8)
    for _ in range(120):
        c = (int(rng.integers(0, 600)), int(rng.integers(0, 400)))
        ax = (int(rng.integers(3, 30)), int(rng.integers(2, 20)))
        angle = float(rng.uniform(0, 180))
        cv2.ellipse(img, c, ax, angle, 0, 360, 255, int(rng.choice([-1, 1, 2, 3])))
        cv2.ellipse(img, c, (ax[0] // 2, ax[1] // 2), angle, 0, 360, 0, -1)
        cv2.ellipse(img, c, (ax[0] // 4, ax[1] // 4), angle, 0, 360, 255, -1)
    img |= ((rng.random(img.shape) < 0.04) * 255).astype(np.uint8)
    expected = _opencv_outer(img)
    borders = _outer_borders(img)
    assert len(borders) == len(expected) > 1000
    assert all(np.array_equal(borders[i], c) for i, c in enumerate(expected))


def test_inputs_other_than_a_contiguous_uint8_image() -> None:
    """A view with strides and a boolean mask are traced as their uint8 copies."""
    rng = np.random.default_rng(2)
    binary = (rng.random((50, 80)) < 0.3).astype(np.uint8)
    view = binary[::2, 1::3]
    assert not view.flags.c_contiguous
    expected = _opencv_outer(np.ascontiguousarray(view))
    got = _outer_borders(view)
    assert len(got) == len(expected)
    assert all(np.array_equal(got[i], c) for i, c in enumerate(expected))
    mask = binary.astype(bool)
    assert np.array_equal(_outer_borders(mask).sums, _outer_borders(binary).sums)


def test_a_buffer_of_the_wrong_size_is_refused() -> None:
    with pytest.raises(ValueError, match="not 4 x 5"):
        _border_kernel.outer_borders(np.zeros(19, np.uint8), 4, 5)
