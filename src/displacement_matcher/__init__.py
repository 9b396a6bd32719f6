"""Displacement matching: optimal before/after correspondence, per-unit motion and damage.

Public API: :func:`match` (paper section 2.2 and section 3, steps 5-6), the unit analysis in
:mod:`.units`, damage counts in :mod:`.damage`, report files in :mod:`.report`, and the result types
in :mod:`.types`. Positions are in the camera frame (x right, y down, z forward), millimetres.
"""

from __future__ import annotations

from .errors import MatcherError
from .match import cost_matrix, match
from .types import (
    DamageSummary,
    DamageThresholds,
    Displacement,
    FiducialMatch,
    MatchParams,
    MatchResult,
    RejectedPose,
    UnitMotion,
)

__all__ = [
    "DamageSummary",
    "DamageThresholds",
    "Displacement",
    "FiducialMatch",
    "MatchParams",
    "MatchResult",
    "MatcherError",
    "RejectedPose",
    "UnitMotion",
    "cost_matrix",
    "match",
]
