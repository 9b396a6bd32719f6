"""Fiducial detection: armourcam's circular coded fiducials found in camera images.

Public API: :func:`detect` (paper section 3, steps 1-4), the designs in :mod:`.design`, the codebook
in :mod:`.codebook` and the result types in :mod:`.types`.
"""

from __future__ import annotations

from .codebook import code_bits, code_count, decode
from .design import DESIGNS, FiducialDesign, get_design, reflectance
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


def __getattr__(name: str) -> object:
    # The detector pulls in OpenCV; import it lazily so that light users (codebook, design) stay fast.
    if name == "detect":
        from .detect import detect

        return detect
    raise AttributeError(name)
