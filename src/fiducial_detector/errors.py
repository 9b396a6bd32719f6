"""Errors raised by the fiducial detector package."""

from __future__ import annotations


class DetectorError(ValueError):
    """An input to the detector is malformed (wrong shape, dtype, parameter or unreadable file)."""
