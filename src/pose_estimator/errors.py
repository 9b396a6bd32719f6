"""Errors raised by the pose estimator package."""

from __future__ import annotations


class PoseError(ValueError):
    """An input to the pose estimator is malformed."""


class CalibrationError(PoseError):
    """A camera calibration is malformed or does not match the image it is used with."""
