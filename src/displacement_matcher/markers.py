"""One comparison as the graph publishes it: report dict, marker specs and displacement rows.

Pure glue between the matcher's cores (:func:`displacement_matcher.match`, units, damage and
report modules) and the outputs of the ``displacement_matcher`` node and ``armourcam analyze``:

- the report dict (the keys of ``armourcam compare --json``),
- :class:`~displacement_matcher.session.MarkerSpec` arrows (green same-code, red cross-code, the
  paper's Figure 8 colours) and unit labels, in the camera frame (mm),
- ``DisplacementRecord`` rows (field names of ``msg/DisplacementRecord.msg``).

No message library is imported here; the node and the bag writer turn specs into MarkerArrays.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pose_estimator.types import FiducialPose

from .compare import compare_poses
from .damage import DEFAULT_MOVED_MM, thresholds
from .errors import MatcherError
from .session import Comparison, MarkerSpec
from .types import DamageThresholds, Displacement, MatchResult, UnitMotion
from .units import UnitMap

DEFAULT_DN_MM = 20.5  # a 38 mm model dolos (Dn ~ 0.54 H)

_LABEL_CODE = {"same_code": 0, "cross_code": 1, "vanished": 2, "appeared": 3}


def _vec(v: Any) -> list[float]:
    if v is None:
        return [math.nan] * 3
    return [float(x) for x in np.asarray(v, dtype=np.float64).reshape(3)]


def displacement_rows(
    result: MatchResult, unit_of: dict[tuple[str, int], int] | None = None
) -> list[dict[str, Any]]:
    """``DisplacementRecord`` rows of a match result (NaN / -1 on the missing side)."""
    rows: list[dict[str, Any]] = []
    unit_of = unit_of or {}
    for d in result.displacements:
        disp = d.displacement_mm
        cov = np.full(6, math.nan)
        if d.is_match and d.baseline_index is not None and d.current_index is not None:
            c = np.asarray(result.baseline[d.baseline_index].covariance_mm2) + np.asarray(
                result.current[d.current_index].covariance_mm2
            )
            cov = c[np.triu_indices(3)]
        unit = -1
        if d.baseline_index is not None:
            unit = unit_of.get(("b", d.baseline_index), -1)
        rows.append(
            {
                "before_mm": _vec(d.before_mm),
                "after_mm": _vec(d.after_mm),
                "displacement_mm": _vec(disp),
                "displacement_covariance": [float(x) for x in cov],
                "distance_mm": d.distance_mm if d.distance_mm is not None else math.nan,
                "cost": float(d.cost) if d.is_match else math.nan,
                "code_before": -1 if d.code_before is None else int(d.code_before),
                "code_after": -1 if d.code_after is None else int(d.code_after),
                "index_before": -1 if d.baseline_index is None else int(d.baseline_index),
                "index_after": -1 if d.current_index is None else int(d.current_index),
                "unit": unit,
                "label": _LABEL_CODE[d.label],
            }
        )
    return rows


def displacement_records(rows: Sequence[dict[str, Any]]) -> Any:
    """``DisplacementRecord`` structured array of ``rows`` (empty for no rows)."""
    from armourcam import records

    return records.rows_to_records(records.DISPLACEMENT, rows)


def arrow_specs(displacements: Sequence[Displacement]) -> list[MarkerSpec]:
    """Arrows baseline -> current for every matched pair (green same-code, red cross-code)."""
    out: list[MarkerSpec] = []
    for d in displacements:
        if not d.is_match or d.before_mm is None or d.after_mm is None:
            continue
        b, a = _vec(d.before_mm), _vec(d.after_mm)
        out.append(
            MarkerSpec("arrow", (b[0], b[1], b[2]), (a[0], a[1], a[2]), d.label == "same_code")
        )
    return out


@dataclass(frozen=True, slots=True)
class Comparer:
    """Compare two pose sets the way ``armourcam compare`` does (units, damage, report).

    Attributes
    ----------
    dn_mm : float
        Nominal unit size Dn, mm.
    displaced_dn : float
        A unit displaced this many Dn or more counts as displaced.
    section_width_mm : float or None
        Width of the section (for N_od).
    unit_map : UnitMap or None
        Unit id -> codes (and positions); None groups fiducials automatically.
    """

    dn_mm: float = DEFAULT_DN_MM
    displaced_dn: float = 1.0
    section_width_mm: float | None = None
    unit_map: UnitMap | None = None

    def __post_init__(self) -> None:
        # Checked here, where the settings are given (a command line, a node's parameters),
        # not at the first wave run, whose comparison would otherwise fail.
        self.thresholds()
        w = self.section_width_mm
        if w is not None and not (math.isfinite(w) and w > 0):
            raise MatcherError(f"section width must be a positive length in mm, got {w!r}")

    def thresholds(self) -> DamageThresholds:
        """The damage thresholds; the movement threshold is the default one
        (:data:`.damage.DEFAULT_MOVED_MM`) or the displacement threshold where that is smaller.

        Raises
        ------
        MatcherError
            For a Dn or displacement threshold that is not a positive length.
        """
        limit = self.dn_mm * self.displaced_dn
        moved = DEFAULT_MOVED_MM
        if math.isfinite(limit) and 0 < limit < moved:
            moved = limit
        return thresholds(self.dn_mm, displaced_dn=self.displaced_dn, moved_mm=moved)

    def __call__(self, before: Sequence[FiducialPose], after: Sequence[FiducialPose]) -> Comparison:
        """Match ``after`` against ``before``; report, markers and displacement rows."""
        limits = self.thresholds()
        a = compare_poses(
            list(before),
            list(after),
            limits,
            unit_map=self.unit_map,
            section_width_mm=self.section_width_mm,
        )
        report = a.report()
        # What the comparison doubts (a camera moved between the two states, a unit map that does
        # not fit), as compare --json reports it.
        report["warnings"] = list(a.warnings)
        unit_of: dict[tuple[str, int], int] = {}
        for k, u in enumerate(a.units):
            for i in u.baseline_indices:
                unit_of[("b", int(i))] = k
        markers = arrow_specs(a.result.displacements) + unit_labels(a.units)
        return Comparison(report, tuple(markers), tuple(displacement_rows(a.result, unit_of)))


def unit_labels(units: Sequence[UnitMotion]) -> list[MarkerSpec]:
    """A text label per unit that moved: id, status and displacement (mm)."""
    out = []
    for u in units:
        if u.status == "still" or not np.all(np.isfinite(u.reference_before_mm)):
            continue
        p = _vec(u.reference_before_mm)
        dist = u.distance_mm
        text = f"{u.unit} {u.status}" + (f" {dist:.1f} mm" if math.isfinite(dist) else "")
        # Labels sit 8 mm towards the camera of the unit's reference point, so they are not
        # hidden inside it.
        q = (p[0], p[1], p[2] - 8.0)
        out.append(MarkerSpec("label", q, q, True, text))
    return out


def compare(before: Sequence[FiducialPose], after: Sequence[FiducialPose]) -> Comparison:
    """:class:`Comparer` with the default thresholds."""
    return Comparer()(before, after)
