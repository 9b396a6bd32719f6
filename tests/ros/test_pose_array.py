"""The pose estimator's PoseArray: metres, and an orientation that turns +z onto the normal and,
where the printed axis was read, +x onto it."""

from __future__ import annotations

import numpy as np
import pytest

from pose_estimator.node import frame_quaternions, normal_quaternions


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    u = np.array([x, y, z])
    return 2.0 * (u @ v) * u + (w * w - u @ u) * v + 2.0 * w * np.cross(u, v)


def test_quaternions_turn_z_onto_each_normal_including_minus_z() -> None:
    rng = np.random.default_rng(7)
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.vstack([normals, [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    quats = normal_quaternions(normals)
    assert np.allclose(np.linalg.norm(quats, axis=1), 1.0)
    for q, n in zip(quats, normals, strict=True):
        assert _rotate(q, np.array([0.0, 0.0, 1.0])) == pytest.approx(n, abs=1e-12)


def test_frame_quaternions_turn_x_onto_the_axis_and_z_onto_the_normal() -> None:
    rng = np.random.default_rng(8)
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    axes = np.cross(normals, rng.normal(size=(50, 3)))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    axes[7] = np.nan  # no axis read: the normal's quaternion
    quats = frame_quaternions(normals, axes)
    np.testing.assert_allclose(quats[7], normal_quaternions(normals[7:8])[0])
    for k, (q, n, a) in enumerate(zip(quats, normals, axes, strict=True)):
        assert _rotate(q, np.array([0.0, 0.0, 1.0])) == pytest.approx(n, abs=1e-9)
        if k != 7:
            assert _rotate(q, np.array([1.0, 0.0, 0.0])) == pytest.approx(a, abs=1e-9)
