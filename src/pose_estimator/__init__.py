"""Pose estimation: 3-D position, normal and calibrated uncertainty of each detected fiducial."""

from __future__ import annotations

from .camera import CameraModel
from .errors import CalibrationError, PoseError
from .types import FiducialPose

__all__ = ["CalibrationError", "CameraModel", "FiducialPose", "PoseError"]
