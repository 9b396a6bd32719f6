"""Synthetic detections for pose tests: ground-truth conics perturbed with honest covariances.

Each printed circle's exact image (through the lens model when it has distortion) is perturbed as
if its ellipse had been fitted to edge points with independent normal errors of ``sigma_px`` per
pixel of boundary length; the covariance stored in the :class:`Ellipse` is exactly the one the
perturbation was drawn from, so pose covariances can be checked against empirical scatter.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from armourcam.render import Target, target_truth
from fiducial_detector.design import get_design
from fiducial_detector.types import Ellipse, FiducialDetection
from pose_estimator.camera import CameraModel
from pose_estimator.conic_pose import (
    axes_from_params,
    axes_to_params_jacobian,
    ellipse_points,
    fit_conics,
    params_from_conic,
)


def edge_fit_covariance(params: NDArray[np.float64], sigma_px: float) -> NDArray[np.float64]:
    """Covariance of ``(u, v, s11, s12, s22)`` of an ellipse fitted to its whole boundary."""
    t = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
    w = np.stack([np.cos(t), np.sin(t)], axis=1)
    S = np.array([[params[2], params[3]], [params[3], params[4]]])
    tangent = np.stack([-np.sin(t), np.cos(t)], axis=1) @ S.T
    ds = np.linalg.norm(tangent, axis=1) * (2.0 * np.pi / t.size)
    nrm = w @ np.linalg.inv(S).T
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    # Normal component of d x(t) / d(u, v, s11, s12, s22).
    J = np.stack(
        [
            nrm[:, 0],
            nrm[:, 1],
            nrm[:, 0] * w[:, 0],
            nrm[:, 0] * w[:, 1] + nrm[:, 1] * w[:, 0],
            nrm[:, 1] * w[:, 1],
        ],
        axis=1,
    )
    info = (J * ds[:, None]).T @ J / sigma_px**2
    cov: NDArray[np.float64] = np.linalg.inv(info)
    return cov


def true_ellipse_params(camera: CameraModel, conic: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(u, v, s11, s12, s22)`` of an ideal conic as seen through the camera's lens."""
    p = params_from_conic(conic)
    if not camera.has_distortion:
        return p
    pts = ellipse_points(p, 64)
    norm = (pts - camera.K[:2, 2]) / np.diag(camera.K)[:2]
    dist = camera.distort_normalized(norm)
    return params_from_conic(fit_conics(dist))


def synthetic_detection(
    camera: CameraModel,
    target: Target,
    sigma_px: float,
    rng: np.random.Generator,
) -> FiducialDetection:
    """A detection of ``target`` whose ellipses carry honest, randomly drawn fitting errors."""
    truth = target_truth(camera, target)
    design = get_design(target.design)
    ellipses = []
    for circle, conic in zip(design.circles, truth.conics, strict=True):
        p = true_ellipse_params(camera, conic)
        # Noise-free ellipses still carry a (nominal) covariance, as a real fit would.
        cov_s = edge_fit_covariance(p, max(sigma_px, 0.01))
        q = p + rng.multivariate_normal(np.zeros(5), cov_s) if sigma_px > 0 else p
        u, v, a, b, ang = axes_from_params(q)
        # An exact circle has no axis angle; a real fit never reports exactly a == b.
        a = max(a, b + 1e-7 * b)
        J = axes_to_params_jacobian(a, b, ang)
        Jinv = np.linalg.inv(J)
        cov = Jinv @ cov_s @ Jinv.T
        ellipses.append(
            Ellipse((float(u), float(v)), float(a), float(b), float(ang), cov, circle.radius)
        )
    return FiducialDetection(
        code=target.code,
        hamming=0,
        center_px=ellipses[0].center_px,
        ellipses=tuple(ellipses),
        contrast=0.7,
        design=target.design,
    )
