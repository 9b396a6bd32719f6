"""Result types of the pose estimator (camera frame, millimetres)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fiducial_detector.types import FiducialDetection


@dataclass(frozen=True, slots=True, eq=False)
class FiducialPose:
    """3-D pose of one fiducial in the camera frame (x right, y down, z forward; millimetres).

    Attributes
    ----------
    code : int
        Code number of the fiducial.
    position_mm : (3,) ndarray
        Centre of the printed fiducial.
    normal : (3,) ndarray
        Unit normal of the printed face, pointing out of the face (towards the camera side).
    covariance_mm2 : (3, 3) ndarray
        Covariance of ``position_mm``.
    detection : FiducialDetection or None
        The detection it was estimated from (None for fused or synthetic poses).
    n_frames : int
        Number of frames fused into this pose.
    """

    code: int
    position_mm: NDArray[np.float64]
    normal: NDArray[np.float64]
    covariance_mm2: NDArray[np.float64]
    detection: FiducialDetection | None = None
    n_frames: int = 1

    @property
    def sigma_mm(self) -> NDArray[np.float64]:
        """Standard deviations of x, y and z, mm."""
        return np.sqrt(np.clip(np.diag(self.covariance_mm2), 0.0, None))
