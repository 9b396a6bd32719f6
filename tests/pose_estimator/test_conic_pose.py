"""Closed-form circle pose and conic utilities against exact projections."""

from __future__ import annotations

import numpy as np
import pytest

from armourcam.render import Target, rotation_from_slant_tilt, target_truth
from pose_estimator.camera import CameraModel
from pose_estimator.conic_pose import (
    axes_from_params,
    axes_to_params_jacobian,
    circle_params,
    circle_params_jacobian_t,
    circle_params_t,
    circle_pose,
    conic_from_params,
    ellipse_points,
    fit_conic_entries_t,
    fit_conics,
    fit_ellipse_params_t,
    params_from_axes,
    params_from_conic,
    plane_basis,
)

CAMERA = CameraModel.ideal(3008, 2000, 5769.0)


def _normalised_cone(conic: np.ndarray) -> np.ndarray:
    return CAMERA.K.T @ conic @ CAMERA.K


@pytest.mark.parametrize("slant_deg", [0.0, 1.0, 20.0, 45.0, 70.0, 85.0])
@pytest.mark.parametrize(
    "position", [(0.0, 0.0, 700.0), (180.0, -120.0, 650.0), (-90.0, 60.0, 900.0)]
)
def test_circle_pose_recovers_truth_as_one_of_two(
    slant_deg: float, position: tuple[float, float, float]
) -> None:
    """One of the two closed-form solutions is the true centre and normal."""
    R = rotation_from_slant_tilt(np.radians(slant_deg), tilt=0.7, spin=0.3)
    target = Target(3, "ring", 7.1, R, np.array(position))
    truth = target_truth(CAMERA, target)
    if truth.normal @ truth.position_mm >= 0:
        # At 85 deg and far off axis this tilt turns the printed face away from the camera.
        R = rotation_from_slant_tilt(np.radians(slant_deg), tilt=0.7 + np.pi, spin=0.3)
        target = Target(3, "ring", 7.1, R, np.array(position))
        truth = target_truth(CAMERA, target)
    assert truth.normal @ truth.position_mm < 0
    centers, normals = circle_pose(_normalised_cone(truth.conics[0]), 3.55)
    err = np.linalg.norm(centers - truth.position_mm, axis=1)
    i = int(np.argmin(err))
    assert err[i] < 1e-6 * position[2]
    assert np.degrees(np.arccos(min(1.0, normals[i] @ truth.normal))) < 1e-4
    # Both solutions lie in front of the camera with normals facing it.
    assert np.all(centers[:, 2] > 0)
    assert np.all(np.einsum("ij,ij->i", normals, centers) < 0)


def test_circle_pose_batch_and_scale_invariance() -> None:
    """Batched input equals per-item results; the conic's scale and sign do not matter."""
    cones = []
    for slant in (10.0, 50.0):
        R = rotation_from_slant_tilt(np.radians(slant), 1.1)
        t = target_truth(CAMERA, Target(1, "dot", 7.1, R, np.array([30.0, 20.0, 800.0])))
        cones.append(_normalised_cone(t.conics[0]))
    c_batch, n_batch = circle_pose(np.stack(cones), np.array([1.065, 1.065]))
    for k, cone in enumerate(cones):
        c1, n1 = circle_pose(-3.7 * cone, 1.065)
        np.testing.assert_allclose(c_batch[k], c1, atol=1e-9)
        np.testing.assert_allclose(n_batch[k], n1, atol=1e-9)


@pytest.mark.parametrize("slant_deg", [0.0, 1e-6, 86.0, 88.0, 89.0])
@pytest.mark.parametrize("position", [(0.0, 0.0, 700.0), (150.0, 100.0, 1400.0)])
def test_circle_pose_ill_conditioned_cones(
    slant_deg: float, position: tuple[float, float, float]
) -> None:
    """Exactly fronto-parallel and far, steep circles: the closed-form eigen-decomposition stays
    as accurate as the cone's conditioning allows (l2 and l3 tiny against l1 at 89 deg)."""
    R = rotation_from_slant_tilt(np.radians(slant_deg), tilt=2.0, spin=0.5)
    target = Target(3, "ring", 7.1, R, np.array(position))
    truth = target_truth(CAMERA, target)
    if truth.normal @ truth.position_mm >= 0:
        R = rotation_from_slant_tilt(np.radians(slant_deg), tilt=2.0 + np.pi, spin=0.5)
        target = Target(3, "ring", 7.1, R, np.array(position))
        truth = target_truth(CAMERA, target)
    centers, normals = circle_pose(_normalised_cone(truth.conics[0]), 3.55)
    err = np.linalg.norm(centers - truth.position_mm, axis=1)
    i = int(np.argmin(err))
    # Rounding of the cone itself limits a 89 deg circle at 1.4 m to a few parts in 1e6.
    tol = 1e-5 if slant_deg > 85 else 1e-9
    assert err[i] < tol * position[2]
    assert np.degrees(np.arccos(min(1.0, normals[i] @ truth.normal))) < (
        0.01 if tol > 1e-9 else 1e-6
    )


def test_fit_conics_is_the_algebraic_least_squares_solution() -> None:
    """Off-conic points: the fit equals the smallest right singular vector of the design matrix
    (the definition of the algebraic fit), for a batch of round and very elongated ellipses."""
    rng = np.random.default_rng(1234)
    params = np.array(
        [
            params_from_axes(
                rng.uniform(0, 3000), rng.uniform(0, 2000), a, b, rng.uniform(0, np.pi)
            )
            for a, b in [(40.0, 39.0), (40.0, 20.0), (60.0, 5.0), (12.0, 1.0)]
        ]
    )
    pts = ellipse_points(params, 32) + rng.normal(0.0, 0.05, (4, 32, 2))
    got = fit_conics(pts)
    for k in range(4):
        P = pts[k]
        mean = P.mean(axis=0)
        scale = np.sqrt(np.mean(np.sum((P - mean) ** 2, axis=1)))
        x, y = ((P - mean) / scale).T
        A = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
        c = np.linalg.svd(A)[2][-1]
        Cn = np.array(
            [[c[0], c[1] / 2, c[3] / 2], [c[1] / 2, c[2], c[4] / 2], [c[3] / 2, c[4] / 2, c[5]]]
        )
        T = np.array(
            [[1 / scale, 0, -mean[0] / scale], [0, 1 / scale, -mean[1] / scale], [0, 0, 1]]
        )
        want = T.T @ Cn @ T
        # Same conic up to scale and sign.
        g = got[k] / np.linalg.norm(got[k])
        w = want / np.linalg.norm(want) * np.sign(np.sum(g * want))
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-11)


def test_points_first_fits_equal_fit_conics() -> None:
    """The points-first fits (coordinates as ``(M, ...)`` arrays, as the lens correction keeps
    them) give fit_conics' conics, and ellipse parameters at least as accurate: on exact
    ellipses far from the origin to 1e-12 px."""
    rng = np.random.default_rng(1234)
    params = np.array(
        [
            params_from_axes(
                rng.uniform(0, 3000), rng.uniform(0, 2000), a, b, rng.uniform(0, np.pi)
            )
            for a, b in [(40.0, 39.0), (40.0, 20.0), (60.0, 5.0), (12.0, 1.0), (3.0, 2.5)]
        ]
    )
    pts = ellipse_points(params, 32)
    noisy = pts + rng.normal(0.0, 0.05, pts.shape)
    u, v = (np.ascontiguousarray(noisy[..., i].T) for i in range(2))
    entries = np.stack(fit_conic_entries_t(u, v), axis=-1)
    C = fit_conics(noisy)
    want = C[:, [0, 0, 1, 0, 1, 2], [0, 1, 1, 2, 2, 2]]
    np.testing.assert_allclose(entries, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    # The route through the absolute conic loses digits to the centre's distance from 0.
    np.testing.assert_allclose(
        fit_ellipse_params_t(u, v).T, params_from_conic(C), rtol=0, atol=1e-7
    )
    u, v = (np.ascontiguousarray(pts[..., i].T) for i in range(2))
    np.testing.assert_allclose(fit_ellipse_params_t(u, v).T, params, rtol=0, atol=1e-12)


def test_circle_params_matches_homography_conic() -> None:
    """The basis-free cone of a 3-D circle equals the homography projection."""
    R = rotation_from_slant_tilt(np.radians(37.0), 0.4, 0.2)
    target = Target(2, "ring", 7.1, R, np.array([-40.0, 25.0, 750.0]))
    truth = target_truth(CAMERA, target)
    for conic, rho in zip(truth.conics, (1.0, 0.8, 0.24), strict=True):
        expect = params_from_conic(conic)
        p = circle_params(target.position_mm, truth.normal, rho * 3.55)
        # Normalised -> pixels (fx = fy).
        got = np.concatenate([p[:2] * 5769.0 + CAMERA.K[:2, 2], p[2:] * 5769.0])
        np.testing.assert_allclose(got, expect, rtol=0, atol=1e-8)


def _random_circles(count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres and normals ``(3, N)`` over a wide field (300-1500 mm, slant 0-89 deg, facing the
    camera) and the ring design's radii ``(3, N)``."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(300.0, 1500.0, count)
    c = np.stack([rng.uniform(-0.3, 0.3, count) * z, rng.uniform(-0.2, 0.2, count) * z, z])
    n = np.empty((3, count))
    for i in range(count):
        R = rotation_from_slant_tilt(np.radians(rng.uniform(0.0, 89.0)), rng.uniform(0, 2 * np.pi))
        n[:, i] = -R[:, 2] * np.sign(R[2, 2])
    r = np.array([3.55, 2.84, 0.85])[:, None] * np.ones(count)
    return c, n, r


def test_circle_params_fit_projected_circle_points() -> None:
    """Each image ellipse passes through the projections of its circle's points, also for small,
    far, steeply slanted circles off the axis (where inverting the cone lost up to 8 % of the
    shape)."""
    c, n, r = _random_circles(400, 1)
    p = circle_params_t(c[:, None], n[:, None], r)  # (5, K, N)
    e1, e2 = (np.stack(e) for e in plane_basis((n[0], n[1], n[2])))
    t = np.linspace(0.0, 2.0 * np.pi, 36, endpoint=False)[:, None, None]  # (T, 1, 1)
    ring = e1[:, None, None] * np.cos(t) + e2[:, None, None] * np.sin(t)  # (3, T, 1, N)
    pts = c[:, None, None] + r * ring  # (3, T, K, N)
    x, y = pts[0] / pts[2], pts[1] / pts[2]  # (36, K, N)
    # w = S^-1 (x - m) must be a unit vector.
    det = p[2] * p[4] - p[3] ** 2
    dx, dy = x - p[0], y - p[1]
    wx, wy = (p[4] * dx - p[3] * dy) / det, (p[2] * dy - p[3] * dx) / det
    # (To rounding amplified by S^-1, up to ~1e-7 for 89 deg views' slivers.)
    np.testing.assert_allclose(np.hypot(wx, wy), 1.0, rtol=0, atol=1e-6)


def test_circle_params_jacobian_equals_central_differences() -> None:
    """The analytic Jacobian of the image ellipses in the centre, the normal's two tilts and
    the log radius equals central differences of :func:`circle_params_t`."""
    c, n, r = _random_circles(200, 2)
    e1, e2 = (np.stack(e) for e in plane_basis((n[0], n[1], n[2])))
    params, jac = circle_params_jacobian_t(c, n, r, e1, e2, scale=True)
    assert jac.shape == (5, 6, 3, 200)
    np.testing.assert_array_equal(params, circle_params_t(c[:, None], n[:, None], r))
    assert np.isfinite(jac).all()

    def pred(cc: np.ndarray, nn: np.ndarray, rr: np.ndarray) -> np.ndarray:
        return circle_params_t(cc[:, None], nn[:, None], rr)

    h, da = 1e-3 * c[2], 1e-3
    num = []
    for k in range(3):
        dc = np.zeros_like(c)
        dc[k] = h
        num.append((pred(c + dc, n, r) - pred(c - dc, n, r)) / (2.0 * h))
    for e in (e1, e2):  # exact rotations of the normal by +-da towards e
        plus = pred(c, n * np.cos(da) + e * np.sin(da), r)
        num.append((plus - pred(c, n * np.cos(da) - e * np.sin(da), r)) / (2.0 * da))
    num.append((pred(c, n, r * np.exp(da)) - pred(c, n, r * np.exp(-da))) / (2.0 * da))
    want = np.stack(num, axis=1)
    # Truncation (h^2) and rounding of the differences: up to ~3e-6 of each column's size for
    # the slivers of 89 deg views (smaller steps only trade truncation for rounding there).
    scale = np.abs(want).max(axis=0, keepdims=True)
    assert np.all(np.abs(jac - want) <= 1e-5 * scale)


@pytest.mark.parametrize("angle", np.linspace(0.0, np.pi, 7, endpoint=False))
def test_parameter_round_trips(angle: float) -> None:
    """Axes <-> square-root shape <-> conic conversions invert each other over all angles."""
    p = params_from_axes(101.5, -33.25, 40.0, 17.5, angle)
    np.testing.assert_allclose(axes_from_params(p), [101.5, -33.25, 40.0, 17.5, angle], atol=1e-12)
    np.testing.assert_allclose(params_from_conic(conic_from_params(p)), p, atol=1e-9)
    np.testing.assert_allclose(params_from_conic(fit_conics(ellipse_points(p, 12))), p, atol=1e-7)
    # Numerical check of the axes -> parameters Jacobian.
    x = np.array([101.5, -33.25, 40.0, 17.5, angle])
    J = axes_to_params_jacobian(40.0, 17.5, angle)
    for j in range(5):
        dx = np.zeros(5)
        dx[j] = 1e-6
        num = (params_from_axes(*(x + dx)) - params_from_axes(*(x - dx))) / 2e-6
        np.testing.assert_allclose(J[:, j], num, atol=1e-7)


def test_not_an_ellipse_gives_nan() -> None:
    """A hyperbola has no ellipse parameters."""
    hyperbola = np.diag([1.0, -1.0, -1.0])
    assert np.all(np.isnan(params_from_conic(hyperbola)))
