"""Synthetic armour fields: counts, visibility, occlusion and exact ground-truth motion."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from armourcam.field import dolos_geometry, field_camera, make_field
from armourcam.render import MARGIN, render
from pose_estimator.camera import CameraModel


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
    with pytest.raises(ValueError, match="occlusion truth"):
        f.before.targets("ring", 10.0)
    for t, i in zip(targets, ids.tolist(), strict=True):
        np.testing.assert_allclose(t.position_mm, f.before.position_mm[i])
        np.testing.assert_allclose(t.rotation[:, 2], f.before.normal[i], atol=1e-12)
        np.testing.assert_allclose(t.rotation.T @ t.rotation, np.eye(3), atol=1e-12)
    rng = np.random.default_rng(0)
    errs, sig = [], []
    ids = f.before.observable_ids
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
    with pytest.raises(ValueError, match="diameter_mm"):
        make_field(10, diameter_mm=0.0)


def _disc_radius_at(
    camera: CameraModel, position: NDArray, normal: NDArray, uv: NDArray
) -> NDArray:
    """Distance (mm) from a disc's centre of where the rays through pixels ``uv`` meet its plane.

    The brute-force ray cast of the renderer (ideal camera): ray ``(x, y, 1)`` meets the plane
    ``n . (P - p) = 0`` at ``P = s (x, y, 1)``, ``s = n . p / n . (x, y, 1)``.
    """
    K = camera.K
    d = np.column_stack(
        [(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))]
    )
    s = (normal @ position) / (d @ normal)
    return np.asarray(np.linalg.norm(s[:, None] * d - position, axis=1))


@pytest.mark.parametrize("seed", [0])
def test_occlusion_matches_brute_force_ray_cast(seed: int) -> None:
    """Occluded fractions agree with a dense ray cast under the renderer's painting order."""
    cam = CameraModel.ideal(480, 320, 1500.0)
    f = make_field(40, seed=seed, camera=cam, diameter_mm=14.0, hidden_fraction=0.0)
    for st in (f.before, f.after):
        ids = st.visible_ids
        assert st.occluded.sum() >= 3  # the check below is not vacuous
        assert not np.any(st.occluded & ~st.visible)
        np.testing.assert_array_equal(st.observable, st.visible & ~st.occluded)
        r = st.diameter_mm / 2.0
        # Painting order: farthest centre first, ties in id order (the renderer's stable sort).
        rank = np.empty(len(ids), dtype=int)
        rank[np.argsort(-st.position_mm[ids, 2], kind="stable")] = np.arange(len(ids))
        centre = cam.project(st.position_mm[ids])
        for a, i in enumerate(ids.tolist()):
            # A 0.15 px lattice over the printed disc's image (radius < f r / z / cos).
            reach = 1.6 * cam.K[0, 0] * r / st.position_mm[i, 2]
            g = np.arange(-reach, reach, 0.15)
            uv = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2) + centre[a]
            uv = uv[_disc_radius_at(cam, st.position_mm[i], st.normal[i], uv) <= r]
            covered = np.zeros(len(uv), dtype=bool)
            n_over = 0
            for b, j in enumerate(ids.tolist()):
                if rank[b] > rank[a]:
                    rho = _disc_radius_at(cam, st.position_mm[j], st.normal[j], uv)
                    n_over += bool(np.any(rho <= MARGIN * r))
                    covered |= rho <= MARGIN * r
            frac = covered.mean()
            if n_over <= 1:
                assert st.occluded_fraction[i] == pytest.approx(frac, abs=0.01)
            else:  # the sum over occluders bounds their union from above
                assert st.occluded_fraction[i] >= frac - 0.01
            if frac > 0.01:
                assert st.occluded[i]
            if st.occluded_fraction[i] > 0.01:
                assert frac > 0


def test_occluded_printed_pixels_are_overwritten() -> None:
    """In the rendered image an observable fiducial's printed disc is exactly as drawn alone;
    an occluded one's is partly painted over by a nearer fiducial."""
    cam = CameraModel.ideal(480, 320, 1500.0)
    f = make_field(40, seed=2, camera=cam, diameter_mm=14.0, hidden_fraction=0.0)
    st = f.after
    targets = st.targets("ring")
    full = render(cam, targets).image
    r = st.diameter_mm / 2.0
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    checked = 0
    for t, i in zip(targets, st.visible_ids.tolist(), strict=True):
        if st.occluded[i] and st.occluded_fraction[i] < 0.05:
            continue  # a graze may cover less than one whole pixel
        alone = render(cam, [t]).image
        # Pixels lying wholly inside the printed disc (all four corners within it).
        inside = np.ones(u.shape, dtype=bool)
        for du, dv in ((-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5)):
            uv = np.column_stack([u.ravel() + du, v.ravel() + dv])
            rho = _disc_radius_at(cam, st.position_mm[i], st.normal[i], uv)
            inside &= (rho <= r).reshape(u.shape)
        assert inside.sum() > 20
        same = np.array_equal(full[inside], alone[inside])
        assert same == bool(st.observable[i]), (i, st.occluded_fraction[i])
        checked += 1
    assert checked >= 20 and st.occluded.sum() >= 3


def test_moved_units_do_not_interpenetrate() -> None:
    """Settled fields keep every unit's core and fiducials clear of the others after the run."""
    for seed in range(3):
        f = make_field(300, seed=seed)
        dn, k = f.geometry.dn_mm, len(f.geometry.codes)
        c = f.after.centres_mm
        assert np.min(np.linalg.norm(c[:, None] - c[None], axis=2) + 1e9 * np.eye(len(c))) >= dn
        p = f.after.position_mm
        gap = np.linalg.norm(p[:, None] - p[None], axis=2)
        same_unit = np.kron(np.eye(f.n_units, dtype=bool), np.ones((k, k), dtype=bool))
        assert gap[~same_unit].min() >= 9.0
        # Unsettled draws do collide (what settling is for); still units never move.
        raw = make_field(300, seed=seed, settle=False)
        rc = raw.after.centres_mm
        assert np.min(np.linalg.norm(rc[:, None] - rc[None], axis=2) + 1e9 * np.eye(len(c))) < dn
        still = ~(f.moved | f.overturned)
        np.testing.assert_array_equal(f.after.centres_mm[still], raw.after.centres_mm[still])
