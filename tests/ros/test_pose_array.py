"""The pose estimator's PoseArray: metres, and an orientation that turns +z onto the normal."""

from __future__ import annotations

import numpy as np
import pytest

from pose_estimator.node import normal_quaternions


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
