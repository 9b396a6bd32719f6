"""Displacement matching: optimal before/after correspondence, per-unit motion and damage.

Public API: :func:`match` (paper section 2.2 and section 3, steps 5-6: one exact global matching
over partial matchings), :func:`match_units` (units, their rigid motion, unit-aware re-matching),
:func:`assess` and :func:`thresholds` (damage counts), :func:`write_report`,
:func:`write_report_files` and :func:`report_dict` (JSON, CSV, overlay and plot),
:func:`compare_poses` (all of it), and the result types in :mod:`.types`. Positions are in the
camera frame (x right, y down, z forward), millimetres.
"""

from __future__ import annotations

from .compare import Assessment, compare_poses, poses_from_images
from .damage import assess, cumulative, thresholds
from .errors import MatcherError
from .match import cost_matrix, match
from .refine import UnitAnalysis, match_units
from .report import report_dict, write_report, write_report_files
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
from .units import UnitMap, UnitSpec, load_unit_map, parse_unit_map

__all__ = [
    "Assessment",
    "DamageSummary",
    "DamageThresholds",
    "Displacement",
    "FiducialMatch",
    "MatchParams",
    "MatchResult",
    "MatcherError",
    "RejectedPose",
    "UnitAnalysis",
    "UnitMap",
    "UnitMotion",
    "UnitSpec",
    "assess",
    "compare_poses",
    "cost_matrix",
    "cumulative",
    "load_unit_map",
    "match",
    "match_units",
    "parse_unit_map",
    "poses_from_images",
    "report_dict",
    "thresholds",
    "write_report",
    "write_report_files",
]
