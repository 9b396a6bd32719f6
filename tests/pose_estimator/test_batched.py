"""Batched small-matrix linear algebra against numpy.linalg."""

from __future__ import annotations

import numpy as np
import pytest

from pose_estimator.batched import spd_inverse


@pytest.mark.parametrize("m", [3, 5, 7])
def test_spd_inverse_matches_numpy(m: int) -> None:
    """Inverses of badly scaled SPD matrices (matrix axes first) equal numpy's."""
    rng = np.random.default_rng(1234)
    G = rng.normal(size=(200, m, m))
    scale = 10.0 ** rng.uniform(-4, 4, size=(200, m))
    A = scale[:, :, None] * (G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(m)) * scale[:, None, :]
    got = np.moveaxis(spd_inverse(np.moveaxis(A, 0, -1)), -1, 0)
    want = np.linalg.inv(A)
    err = np.abs(got - want) / np.sqrt(
        np.abs(
            np.diagonal(want, axis1=1, axis2=2)[:, :, None]
            * np.diagonal(want, axis1=1, axis2=2)[:, None, :]
        )
    )
    assert np.max(err) < 1e-8
