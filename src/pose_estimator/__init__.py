"""Pose estimation: 3-D position, normal and calibrated uncertainty of each detected fiducial."""

from __future__ import annotations

from .camera import CameraModel
from .conic_pose import circle_pose
from .errors import CalibrationError, PoseError
from .estimate import PoseArrays, estimate, estimate_arrays, estimate_ellipses
from .fusion import fuse, fuse_poses
from .types import FiducialPose

__all__ = [
    "CalibrationError",
    "CameraModel",
    "FiducialPose",
    "PoseArrays",
    "PoseError",
    "circle_pose",
    "estimate",
    "estimate_arrays",
    "estimate_ellipses",
    "fuse",
    "fuse_poses",
]
