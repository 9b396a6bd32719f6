"""Fiducial detection: armourcam's circular coded fiducials found in camera images.

Public API: :func:`detect` (paper section 3, steps 1-4), the designs in :mod:`.design`, the codebook
in :mod:`.codebook` and the result types in :mod:`.types`.
"""

from __future__ import annotations

from .codebook import code_bits, code_count, decode
from .design import DESIGNS, FiducialDesign, get_design, reflectance

# Imported eagerly: a lazy import would leave the package attribute ``detect`` bound to the
# submodule of that name whenever the submodule is imported first.
from .detect import detect
from .errors import DetectorError
from .types import Ellipse, FiducialDetection

__all__ = [
    "DESIGNS",
    "DetectorError",
    "Ellipse",
    "FiducialDesign",
    "FiducialDetection",
    "code_bits",
    "code_count",
    "decode",
    "detect",
    "get_design",
    "reflectance",
]
