"""Synthetic fiducial pose sets for the matcher tests (camera frame, mm)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from pose_estimator.types import FiducialPose


def realistic_cov(position_mm: NDArray[np.float64], sigma_xy: float, sigma_z: float) -> NDArray:
    """Covariance with ``sigma_z`` along the viewing ray and ``sigma_xy`` across it (mm^2)."""
    r = position_mm / np.linalg.norm(position_mm)
    return sigma_xy**2 * np.eye(3) + (sigma_z**2 - sigma_xy**2) * np.outer(r, r)


def make_pose(
    code: int,
    position_mm: NDArray[np.float64] | list[float],
    sigma_xy: float = 0.1,
    sigma_z: float = 0.6,
    normal: NDArray[np.float64] | None = None,
) -> FiducialPose:
    """A synthetic fiducial pose with a realistic (depth-elongated) covariance."""
    p = np.asarray(position_mm, dtype=np.float64)
    n = np.array([0.0, 0.0, -1.0]) if normal is None else np.asarray(normal, dtype=np.float64)
    return FiducialPose(int(code), p, n, realistic_cov(p, sigma_xy, sigma_z))


def rotation(axis: list[float], deg: float) -> NDArray[np.float64]:
    """Rotation matrix of ``deg`` degrees about ``axis``."""
    import cv2

    a = np.asarray(axis, dtype=np.float64)
    r, _ = cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))
    return np.asarray(r, dtype=np.float64)


def facing_poses(
    geometry: Any, R: NDArray[np.float64], centre: NDArray[np.float64]
) -> list[FiducialPose]:
    """Exact poses (covariance 0.01 mm^2 per axis) of the fiducials of a unit of ``geometry``
    (:class:`armourcam.field.UnitGeometry`) at ``R``, ``centre`` that face the camera."""
    out = []
    for k, code in enumerate(geometry.codes):
        p = centre + R @ geometry.positions_mm[k]
        n = R @ geometry.normals[k]
        if n @ (-p / np.linalg.norm(p)) > 0.3:
            out.append(FiducialPose(code, p, n, np.eye(3) * 0.01))
    return out
