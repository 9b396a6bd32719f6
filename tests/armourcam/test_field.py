"""Synthetic armour fields: counts, visibility and exact ground-truth motion."""

from __future__ import annotations

import numpy as np
import pytest

from armourcam.field import dolos_geometry, field_camera, make_field


def test_field_counts_and_truth() -> None:
    """Moved/overturned fractions, still units exactly still, truth motion reproduces positions."""
    f = make_field(100, seed=11)
    assert f.n_units == 100
    assert f.moved.sum() == 10 and f.overturned.sum() == 2
    assert not np.any(f.moved & f.overturned)
    k = len(f.geometry.codes)
    for u in range(f.n_units):
        sl = slice(u * k, (u + 1) * k)
        R, t = f.motion(u)
        np.testing.assert_allclose(f.before.position_mm[sl] @ R.T + t, f.after.position_mm[sl])
        if not (f.moved[u] or f.overturned[u]):
            np.testing.assert_allclose(f.after.position_mm[sl], f.before.position_mm[sl])
    # Moves are at most 2 Dn (plus the small out-of-slope component).
    d = np.linalg.norm(f.after.centres_mm - f.before.centres_mm, axis=1)
    assert d.max() <= 2.05 * f.geometry.dn_mm
    assert np.all(d[~(f.moved | f.overturned)] == 0)


def test_visibility_and_overturning() -> None:
    """Upright dolosse show about three faces; overturned ones show their fourth face."""
    f = make_field(200, seed=4, hidden_fraction=0.0)
    vis = f.before.visible.reshape(200, 4)
    assert 2.0 <= vis.sum(axis=1).mean() <= 3.0
    for u in np.flatnonzero(f.overturned):
        assert f.after.visible.reshape(200, 4)[u, 3] or not vis[u, 3]
        assert not vis[u, 3]  # the underside was hidden before
    uv = f.camera.project(f.before.position_mm)
    assert np.all((uv >= 0) & (uv < [f.camera.width, f.camera.height]))


def test_targets_and_poses_agree_with_truth() -> None:
    """Render targets sit at the truth, face along the normals; noisy poses scatter as declared."""
    f = make_field(30, seed=1)
    ids = f.before.visible_ids
    targets = f.before.targets("ring", 7.1)
    assert len(targets) == len(ids)
    for t, i in zip(targets, ids.tolist(), strict=True):
        np.testing.assert_allclose(t.position_mm, f.before.position_mm[i])
        np.testing.assert_allclose(t.rotation[:, 2], f.before.normal[i], atol=1e-12)
        np.testing.assert_allclose(t.rotation.T @ t.rotation, np.eye(3), atol=1e-12)
    rng = np.random.default_rng(0)
    errs, sig = [], []
    for _ in range(20):
        poses = f.before.poses(rng)
        errs += [p.position_mm - f.before.position_mm[i] for p, i in zip(poses, ids, strict=True)]
        sig += [p.sigma_mm for p in poses]
    ratio = np.std(np.array(errs), axis=0) / np.sqrt(np.mean(np.array(sig) ** 2, axis=0))
    assert np.all((ratio > 0.8) & (ratio < 1.2))


def test_camera_and_bad_arguments() -> None:
    """The paper's camera; fractions out of range are refused."""
    cam = field_camera()
    assert (cam.width, cam.height) == (3008, 2000)
    assert cam.K[0, 0] == pytest.approx(45.0 / 0.0078)
    assert dolos_geometry(38.0).dn_mm == pytest.approx(0.54 * 38.0)
    with pytest.raises(ValueError, match="moved_fraction"):
        make_field(10, moved_fraction=1.5)
    with pytest.raises(ValueError, match="n_units"):
        make_field(0)
