"""3-D position, normal and position covariance of detected fiducials (paper section 4, improved).

The paper takes each fiducial's 3-D position from the ellipse of its central dot alone (its step 4,
the TRIP method). Here every fitted concentric circle of the design contributes:

1. **Undistort the boundaries, not the image.** Each fitted ellipse (in distorted pixels) is
   sampled at 32 points, the points are undistorted through the lens model and a conic is refitted:
   the ideal-camera image of that circle. Its covariance is carried through the local affine part of
   the undistortion.
2. **Closed form, both solutions.** The pose circle's cone gives the two candidate poses
   (:func:`pose_estimator.conic_pose.circle_pose`), each fitting the pose circle exactly.
3. **Ambiguity from the concentric circles.** Each candidate predicts the images of the other
   printed circles; the chi-square of the fitted ellipses against those predictions (weighted by
   the fits' covariances) gives the candidates' likelihood weights. The false candidate's
   concentric circles are inconsistent (its pole of the vanishing line differs between circles).
4. **Joint refinement over all circles.** Gauss-Newton adjusts the better candidate's centre (3-D)
   and normal (2 angles) to all circles at once. Because the model predicts whole conics, the image
   of the true centre (not the ellipse centre, under perspective) is used implicitly: no
   eccentricity bias. Depth comes from the pose circle, the largest: the inner circles' radii are
   nuisance parameters and their fits carry a systematic floor (:data:`INNER_FLOOR_PX`), so that
   their edge biases (coding track nearby, toner spread) cannot pull z while they still fix the
   centre's image and the normal.
5. **Honest covariance.** The position covariance is the estimator's own (sandwich) covariance
   under the fits' covariances. When the two candidates fit (almost) equally well - a design with a
   single circle, or a nearly fronto-parallel view - the result is their likelihood-weighted
   mixture, whose covariance includes the spread between them.

Conventions: pixels ``(u, v)`` with pixel centres at integer coordinates; camera frame OpenCV
(x right, y down, z forward), millimetres; normals point out of the printed face, towards the
camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fiducial_detector.types import FiducialDetection

from .camera import CameraModel
from .conic_pose import (
    axes_to_params_jacobian,
    circle_params,
    circle_pose,
    conic_from_params,
    ellipse_points,
    fit_conics,
    params_from_axes,
    params_from_conic,
)
from .errors import PoseError
from .types import FiducialPose

F64 = NDArray[np.float64]

#: Standard deviation (pixels) assumed for each ellipse parameter when a fit reports no usable
#: covariance; the pose covariance is then only nominal.
DEFAULT_SIGMA_PX = 0.05
#: Systematic floor (pixels, per ellipse parameter) added to the inner circles' fit covariances:
#: the coding track next to them and toner spread bias inner edges by several hundredths of a
#: pixel at small sizes, which a noise-only covariance does not cover. They still resolve the
#: ambiguity and refine the normal, without pulling the depth.
INNER_FLOOR_PX = 0.05
_UNDISTORT_SAMPLES = 32
_GN_ITERATIONS = 1


def estimate(
    detections: Sequence[FiducialDetection],
    camera: CameraModel,
    diameter_mm: float,
) -> list[FiducialPose]:
    """Pose of each detected fiducial.

    Parameters
    ----------
    detections : sequence of FiducialDetection
        Detections in one image of ``camera`` (ellipses in distorted pixels, ``(u, v)``, pixel
        centres at integer coordinates).
    camera : CameraModel
        Intrinsics and lens distortion of the image.
    diameter_mm : float
        Printed diameter of the outermost circle (the design's radius 1.0), millimetres.

    Returns
    -------
    list of FiducialPose
        One per detection whose pose circle gives a real pose, in the order given; degenerate
        detections (pose ellipse not an ellipse) are left out.

    Raises
    ------
    PoseError
        If ``diameter_mm`` is not a positive finite number or an item is not a detection.
    """
    if not np.isfinite(diameter_mm) or diameter_mm <= 0:
        raise PoseError(f"diameter_mm must be a positive finite number, got {diameter_mm!r}")
    dets = list(detections)
    for d in dets:
        if not isinstance(d, FiducialDetection):
            raise PoseError(f"expected FiducialDetection, got {type(d).__name__}")
        if not d.ellipses:
            raise PoseError(f"detection of code {d.code} has no ellipses")
    if not dets:
        return []
    obs, cov, radius = detections_to_arrays(dets, 0.5 * float(diameter_mm))
    result = estimate_arrays(obs, cov, radius, camera)
    poses = []
    for i, d in enumerate(dets):
        if not result.valid[i]:
            continue
        poses.append(
            FiducialPose(
                code=d.code,
                position_mm=result.position_mm[i],
                normal=result.normal[i],
                covariance_mm2=result.covariance_mm2[i],
                detection=d,
            )
        )
    return poses


@dataclass(frozen=True, slots=True, eq=False)
class PoseArrays:
    """Vectorised pose results for ``N`` fiducials (camera frame, mm).

    Attributes
    ----------
    position_mm : (N, 3) ndarray
    normal : (N, 3) ndarray
    covariance_mm2 : (N, 3, 3) ndarray
    valid : (N,) bool ndarray
    ambiguity : (N,) ndarray
        Likelihood weight of the rejected candidate (0 when the concentric circles resolved the
        ambiguity decisively, 0.5 when the two candidates fit equally well).
    center_px : (N, 2) ndarray
        Ideal (undistorted) image of the true circle centre.
    chi2 : (N,) ndarray
        Weighted squared residual of the chosen candidate's fit.
    """

    position_mm: F64
    normal: F64
    covariance_mm2: F64
    valid: NDArray[np.bool_]
    ambiguity: F64
    center_px: F64
    chi2: F64


def detections_to_arrays(
    dets: Sequence[FiducialDetection], outer_radius_mm: float
) -> tuple[F64, F64, F64]:
    """Observation arrays ``(N, K, 5)``, covariances ``(N, K, 5, 5)`` and radii ``(N, K)`` (mm).

    Missing circles (fewer ellipses than ``K``) get NaN observations.
    """
    n = len(dets)
    counts = [len(d.ellipses) for d in dets]
    kmax = max(counts)
    ells = [e for d in dets for e in d.ellipses]
    rows = np.array(
        [(*e.center_px, e.semi_major, e.semi_minor, e.angle, e.radius) for e in ells],
        dtype=np.float64,
    )
    try:
        covs = np.array([e.covariance for e in ells], dtype=np.float64).reshape(-1, 5, 5)
    except ValueError:
        covs = np.stack([_cov_or_nan(e.covariance) for e in ells])
    if min(counts) == kmax:
        raw = rows[:, :5].reshape(n, kmax, 5)
        rawcov = covs.reshape(n, kmax, 5, 5)
        radius = rows[:, 5].reshape(n, kmax) * outer_radius_mm
    else:
        raw = np.full((n, kmax, 5), np.nan)
        rawcov = np.full((n, kmax, 5, 5), np.nan)
        radius = np.full((n, kmax), np.nan)
        det_index = np.repeat(np.arange(n), counts)
        circle_index = np.concatenate([np.arange(c) for c in counts])
        raw[det_index, circle_index] = rows[:, :5]
        rawcov[det_index, circle_index] = covs
        radius[det_index, circle_index] = rows[:, 5] * outer_radius_mm
    obs = params_from_axes(raw[..., 0], raw[..., 1], raw[..., 2], raw[..., 3], raw[..., 4])
    J = axes_to_params_jacobian(raw[..., 2], raw[..., 3], raw[..., 4])
    cov = J @ rawcov @ np.swapaxes(J, -1, -2)
    return obs, cov, radius


def _cov_or_nan(cov: object) -> F64:
    """A 5x5 covariance as float64, or NaNs when it has the wrong shape."""
    c = np.asarray(cov, dtype=np.float64)
    return c if c.shape == (5, 5) else np.full((5, 5), np.nan)


def estimate_arrays(
    obs: F64,
    cov: F64,
    radius_mm: F64,
    camera: CameraModel,
    *,
    iterations: int = _GN_ITERATIONS,
    free_scale: bool = True,
    inner_floor_px: float = INNER_FLOOR_PX,
) -> PoseArrays:
    """Vectorised core of :func:`estimate`.

    Parameters
    ----------
    obs : (N, K, 5) ndarray
        Fitted ellipses ``(u, v, s11, s12, s22)`` in distorted pixels; circle 0 is the pose circle.
        NaN rows mark circles that were not fitted.
    cov : (N, K, 5, 5) ndarray
        Their covariances (NaN or non-positive-definite: :data:`DEFAULT_SIGMA_PX` is assumed).
    radius_mm : (N, K) ndarray
        Printed radius of each circle.
    camera : CameraModel
    iterations : int
        Gauss-Newton steps from the closed-form solution (the problem is nearly linear there).
    free_scale : bool
        Estimate the inner circles' radii instead of trusting their printed values: depth then
        comes from the pose circle alone, immune to size biases of inner edges (see
        :func:`_gauss_newton`); False uses every circle's printed radius.
    inner_floor_px : float
        Systematic standard deviation added to each inner circle's parameters, pixels.

    Returns
    -------
    PoseArrays
    """
    obs = np.asarray(obs, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    radius_mm = np.asarray(radius_mm, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[2] != 5 or cov.shape != (*obs.shape, 5):
        raise PoseError(f"obs must be (N, K, 5) and cov (N, K, 5, 5); got {obs.shape}, {cov.shape}")
    if radius_mm.shape != obs.shape[:2]:
        raise PoseError(f"radius_mm must be {obs.shape[:2]}, got {radius_mm.shape}")
    n, kc = obs.shape[:2]
    K = camera.K
    present = np.all(np.isfinite(obs), axis=-1) & np.isfinite(radius_mm) & (radius_mm > 0)
    present &= (obs[..., 2] * obs[..., 4] - obs[..., 3] ** 2) > 0
    cov = _sanitise_covariance(cov, present)
    if camera.has_distortion:
        obs, cov = _undistort(obs, cov, present, camera)
        present &= np.all(np.isfinite(obs), axis=-1)
    safe_obs = np.where(present[..., None], obs, np.array([0.0, 0.0, 1.0, 0.0, 1.0]))
    safe_r = np.where(present, radius_mm, 1.0)
    # Work in normalised coordinates (K = I): an affine change of the observations.
    obs_n, W = _to_normalised(safe_obs, _information(cov), K)
    W = np.where(present[..., None, None], W, 0.0)
    # The ambiguity test uses the fits' own covariances (the inner circles' geometry relative to
    # the pose circle is what tells the candidates apart); the refinement adds the systematic
    # floor to the inner circles, as a scalar deflation (sigma^2 / (sigma^2 + floor^2)).
    lam = np.ones((n, kc))
    if kc > 1 and inner_floor_px > 0:
        var = np.trace(cov[:, 1:], axis1=-2, axis2=-1) / 5.0
        lam[:, 1:] = var / (var + inner_floor_px**2)
    # Closed form from the pose circle (index 0), both candidates.
    centers, normals = circle_pose(conic_from_params(obs_n[:, 0]), safe_r[:, 0])  # (N, 2, 3)
    valid = present[:, 0] & np.all(np.isfinite(centers), axis=(1, 2))
    centers = np.where(valid[:, None, None], centers, np.array([0.0, 0.0, 1000.0]))
    normals = np.where(valid[:, None, None], normals, np.array([0.0, 0.0, -1.0]))
    # Both fit the pose circle exactly; the other circles tell them apart. Their likelihood
    # weights: a decisive chi2 gap gives (1, 0), a single circle or a fronto-parallel view ~ 0.5.
    chi2_cf = _chi2(obs_n[:, None], W[:, None], safe_r[:, None], centers, normals)
    dchi = chi2_cf[:, 1] - chi2_cf[:, 0]
    w0 = 1.0 / (1.0 + np.exp(np.clip(-0.5 * dchi, -700.0, 700.0)))
    best = np.where(w0 >= 0.5, 0, 1)
    idx = np.arange(n)
    # Joint refinement of the better candidate over all circles.
    # Circles whose floored weight is below 1 % of their own fit's add nothing measurable to
    # the refinement (they already did their job in the ambiguity test): leave them out.
    keep = np.ones(kc, dtype=bool)
    keep[1:] = np.any(lam[:, 1:] >= 0.01, axis=0)
    c_best, normal, cov_c, chi2 = _gauss_newton(
        obs_n[:, keep],
        W[:, keep],
        lam[:, keep],
        safe_r[:, keep],
        centers[idx, best],
        normals[idx, best],
        iterations,
        free_scale,
    )
    cov_best = 0.5 * (cov_c + np.swapaxes(cov_c, -1, -2))
    c = centers.copy()
    c[idx, best] = c_best
    w = np.stack([w0, 1.0 - w0], axis=1)
    mean = w[:, 0, None] * c[:, 0] + w[:, 1, None] * c[:, 1]
    dev = c - mean[:, None]
    # Mixture covariance: the refined candidate's covariance stands for both.
    mix = cov_best + np.sum(w[..., None, None] * dev[..., :, None] * dev[..., None, :], axis=1)
    p = mean @ K.T
    center_px = p[:, :2] / p[:, 2:3]
    ok = valid & np.all(np.isfinite(mean), axis=1) & np.all(np.isfinite(mix), axis=(1, 2))
    ok &= mean[:, 2] > 0
    return PoseArrays(mean, normal, mix, ok, np.minimum(w0, 1.0 - w0), center_px, chi2)


def _to_normalised(obs: F64, W: F64, K: F64) -> tuple[F64, F64]:
    """Ellipse parameters and information matrices in normalised coordinates ``K^-1 (u, v, 1)``."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    shifted = obs - np.array([cx, cy, 0.0, 0.0, 0.0])
    if fx == fy:
        return shifted / fx, W * (fx * fx)
    A = np.broadcast_to(np.diag([1.0 / fx, 1.0 / fy]), (*obs.shape[:-1], 2, 2))
    Jinv = np.linalg.inv(_affine_params_jacobian(shifted, A))
    return _affine_params(shifted, A), np.swapaxes(Jinv, -1, -2) @ W @ Jinv


def _sanitise_covariance(cov: F64, present: NDArray[np.bool_]) -> F64:
    """Replace unusable covariances (non-finite, non-positive variances) by the nominal one."""
    out = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    nominal = np.eye(5) * DEFAULT_SIGMA_PX**2
    diag = np.diagonal(out, axis1=-2, axis2=-1)
    good = np.all(np.isfinite(out), axis=(-2, -1)) & np.all(diag > 0, axis=-1) & present
    if not np.all(good):
        out = np.where(good[..., None, None], out, nominal)
    # A tiny floor keeps the inverse well conditioned without changing honest covariances.
    return out + np.eye(5) * (1e-9 * np.sum(diag, axis=-1, where=good[..., None]))[..., None, None]


def _information(cov: F64) -> F64:
    """Inverse covariances; the nominal one where a covariance is not positive definite."""
    W = _inv(cov)
    diag = np.diagonal(W, axis1=-2, axis2=-1)
    good = np.all(np.isfinite(W), axis=(-2, -1)) & np.all(diag > 0, axis=-1)
    if np.all(good):
        return W
    out: F64 = np.where(good[..., None, None], W, np.eye(5) / DEFAULT_SIGMA_PX**2)
    return out


def _undistort(
    obs: F64, cov: F64, present: NDArray[np.bool_], camera: CameraModel
) -> tuple[F64, F64]:
    """Ideal-camera ellipses of fitted (distorted) ellipses, with propagated covariances."""
    safe = np.where(present[..., None], obs, np.array([0.0, 0.0, 1.0, 0.0, 1.0]))
    pts = ellipse_points(safe, _UNDISTORT_SAMPLES)
    und = camera.undistort_pixels(pts.reshape(-1, 2)).reshape(pts.shape)
    new = params_from_conic(fit_conics(und))
    # Local affine part of the undistortion at the centre (central differences, 0.5 px).
    h = 0.5
    c = safe[..., :2].reshape(-1, 2)
    du, dv = np.array([h, 0.0]), np.array([0.0, h])
    probe = np.concatenate([c + du, c - du, c + dv, c - dv])
    m = camera.undistort_pixels(probe).reshape(4, -1, 2)
    A = np.stack([(m[0] - m[1]) / (2 * h), (m[2] - m[3]) / (2 * h)], axis=-1)
    A = A.reshape((*obs.shape[:-1], 2, 2))
    J = _affine_params_jacobian(safe, A)
    newcov = J @ cov @ np.swapaxes(J, -1, -2)
    new = np.where(present[..., None], new, np.nan)
    return new, newcov


def _affine_params(p: F64, A: F64) -> F64:
    """Parameters of the ellipse ``p`` mapped by the linear map ``A`` (centre and shape)."""
    S = np.empty((*p.shape[:-1], 2, 2))
    S[..., 0, 0], S[..., 0, 1], S[..., 1, 0], S[..., 1, 1] = (
        p[..., 2],
        p[..., 3],
        p[..., 3],
        p[..., 4],
    )
    AS = A @ S
    M = AS @ np.swapaxes(AS, -1, -2)
    m11, m12, m22 = M[..., 0, 0], M[..., 0, 1], M[..., 1, 1]
    root = np.sqrt(m11 * m22 - m12 * m12)
    t = np.sqrt(m11 + m22 + 2.0 * root)
    c = np.einsum("...ij,...j->...i", A, p[..., :2])
    return np.stack([c[..., 0], c[..., 1], (m11 + root) / t, m12 / t, (m22 + root) / t], axis=-1)


def _affine_params_jacobian(p: F64, A: F64) -> F64:
    """Numerical Jacobian of :func:`_affine_params` w.r.t. ``p``, shape ``(..., 5, 5)``."""
    J = np.empty((*p.shape, 5))
    for j in range(5):
        step = np.zeros(5)
        step[j] = 1e-4
        J[..., :, j] = (_affine_params(p + step, A) - _affine_params(p - step, A)) / 2e-4
    return J


def _basis(n: F64) -> tuple[F64, F64]:
    """Two unit vectors orthogonal to each unit ``n`` (``(..., 3)``) and to each other."""
    n0, n1, n2 = n[..., 0], n[..., 1], n[..., 2]
    use_x = np.abs(n0) < 0.9
    # e1 = n x (1, 0, 0) = (0, n2, -n1), or n x (0, 1, 0) = (-n2, 0, n0).
    e1 = np.stack(
        [np.where(use_x, 0.0, -n2), np.where(use_x, n2, 0.0), np.where(use_x, -n1, n0)], axis=-1
    )
    e1 /= np.sqrt(np.sum(e1 * e1, axis=-1))[..., None]
    e10, e11, e12 = e1[..., 0], e1[..., 1], e1[..., 2]
    e2 = np.stack([n1 * e12 - n2 * e11, n2 * e10 - n0 * e12, n0 * e11 - n1 * e10], axis=-1)
    return e1, e2


def _chi2(obs: F64, W: F64, radius: F64, center: F64, normal: F64) -> F64:
    """Weighted squared residual of all circles for poses ``(..., 3)``."""
    res = obs - circle_params(center[..., None, :], normal[..., None, :], radius)
    res = np.where(np.isfinite(res), res, 0.0)
    return _quadratic(res, W)


def _quadratic(res: F64, W: F64) -> F64:
    """Sum over circles of ``res^T W res`` (``(..., K, 5)``, ``(..., K, 5, 5)`` -> ``(...)``)."""
    out: F64 = np.sum(res * (W @ res[..., None])[..., 0], axis=(-2, -1))
    return out


def _inv(A: F64) -> F64:
    """Inverses of a stack of symmetric positive-definite matrices ``(..., m, m)``.

    Gauss-Jordan without pivoting (stable for SPD matrices) with the stack as the fast axis: for
    thousands of 5x5 matrices this is several times faster than :func:`numpy.linalg.inv`.
    """
    m = A.shape[-1]
    B = np.ascontiguousarray(np.moveaxis(A, (-2, -1), (0, 1)), dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(m):
            p = 1.0 / B[k, k]
            B[k, k] = 1.0
            B[k] *= p
            for i in range(m):
                if i != k:
                    f = B[i, k].copy()
                    B[i, k] = 0.0
                    B[i] -= f * B[k]
    out: F64 = np.moveaxis(B, (0, 1), (-2, -1))
    return out


def _gauss_newton(
    obs: F64,
    W: F64,
    lam: F64,
    radius: F64,
    center: F64,
    normal: F64,
    iterations: int,
    free_scale: bool = True,
) -> tuple[F64, F64, F64, F64]:
    """Refine circle centres and normals (``(N, 3)``) against all circles of each fiducial.

    ``obs`` ``(N, K, 5)`` and ``W`` ``(N, K, 5, 5)`` (inverse covariances of the fits) are in
    normalised coordinates, ``radius`` ``(N, K)``. Circle ``k`` is weighted by ``lam[..., k] * W``
    (``lam < 1`` deflates circles with a systematic floor); the covariance returned is then the
    sandwich ``A^-1 B A^-1`` with ``A = sum lam J^T W J`` and ``B = sum lam^2 J^T W J``, which is
    the estimator's actual covariance under the fits' own covariances.

    With ``free_scale`` the radii of circles ``1..K-1`` are nuisance parameters (their scale
    relative to the printed value is estimated): they still fix the centre's image and the normal,
    but depth comes from the pose circle alone, so a size bias of the inner edges (toner spread,
    blur of a nearby track) cannot leak into z. ``iterations >= 1``.

    Returns centres, normals, the 3x3 covariances of the centres and the final weighted
    chi-square.
    """
    c = center.copy()
    n = normal.copy()
    rad = radius.copy()
    kc = radius.shape[-1]
    extra = kc - 1 if free_scale else 0
    npar = 5 + extra
    cov = np.zeros((*c.shape[:-1], 3, 3))
    chi2 = np.zeros(c.shape[:-1])
    Wl = W * lam[..., None, None]
    for _ in range(iterations):
        e1, e2 = _basis(n)
        # The base pose and perturbed ones (forward differences: steps far below the noise, far
        # above round-off), evaluated in one vectorised call; the last one scales circles 1..K-1.
        h = 1e-6 * c[..., 2]
        da = 1e-6
        m = 7 if extra else 6
        cs = np.broadcast_to(c, (m, *c.shape)).copy()
        ns = np.broadcast_to(n, (m, *n.shape)).copy()
        rs = np.broadcast_to(rad, (m, *rad.shape)).copy()
        for j in range(3):
            cs[1 + j, ..., j] += h
        ns[4] += da * e1
        ns[5] += da * e2
        ns[4:6] /= np.sqrt(np.sum(ns[4:6] * ns[4:6], axis=-1))[..., None]
        if extra:
            rs[6, ..., 1:] *= 1.0 + da
        pred = circle_params(cs[..., None, :], ns[..., None, :], rs)  # (m, N, K, 5)
        base = pred[0]
        steps = np.stack([h, h, h, np.full_like(h, da), np.full_like(h, da)])
        J = np.zeros((*base.shape, npar))
        J[..., :5] = np.moveaxis((pred[1:6] - base) / steps[..., None, None], 0, -1)
        if extra:
            ds = (pred[6] - base) / da  # (N, K, 5): each circle's own scale column
            for k in range(1, kc):
                J[..., k, :, 4 + k] = ds[..., k, :]
        J = np.where(np.isfinite(J), J, 0.0)
        res = obs - base
        res = np.where(np.isfinite(res), res, 0.0)
        JtW = np.ascontiguousarray(np.swapaxes(J, -1, -2)) @ Wl
        terms = JtW @ J  # (N, K, P, P), lam_k J^T W J
        info = np.sum(terms, axis=-3)
        grad = np.sum(JtW @ res[..., None], axis=-3)
        chi2_lin = _quadratic(res, Wl)
        # A tiny damping only guards against singular steps (e.g. a missing inner circle).
        damp = (1e-12 * np.trace(info, axis1=-2, axis2=-1) + 1e-300)[..., None, None] * np.eye(npar)
        inv_info = _inv(info + damp)
        delta = (inv_info @ grad)[..., 0]
        if np.all(lam == 1.0):
            cov = inv_info[..., :3, :3]
        else:
            # Sandwich covariance of the position block only (what is reported).
            B = np.sum(terms * lam[..., None, None], axis=-3)
            cov = inv_info[..., :3, :] @ B @ inv_info[..., :, :3]
        delta = np.where(np.isfinite(delta), delta, 0.0)
        chi2 = np.maximum(chi2_lin - np.sum(grad[..., 0] * delta, axis=-1), 0.0)
        c = c + delta[..., :3]
        n = n + delta[..., 3:4] * e1 + delta[..., 4:5] * e2
        n /= np.sqrt(np.sum(n * n, axis=-1))[..., None]
        if extra:
            rad[..., 1:] *= 1.0 + delta[..., 5:]
    # The covariance of the last linearisation serves the final point, and its chi-square is the
    # linearised one (res^T W res - grad^T delta): the step is far below the scale on which the
    # Jacobian changes.
    return c, n, cov, chi2
