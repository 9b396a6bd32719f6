"""Unit-aware matching: match, find units and their motion, re-match knowing how units moved.

The first pass is the plain global matching (:func:`displacement_matcher.match`). Units are then
found (:func:`displacement_matcher.units.assign_units`) and their motion estimated; each unit whose
same-code matches agree on a motion predicts where its baseline fiducials are now, and the next
pass measures costs from there with a tight gate across the line of sight (depth, which a single
camera measures with heavy tails, gets slack), while pairs that contradict the current state's own
grouping are excluded and baseline units that the current grouping shows to be one are merged.
Every pass is still one exact global matching. Camera frame, millimetres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pose_estimator.types import FiducialPose

from .errors import MatcherError
from .match import match
from .rigid import across_line_of_sight
from .types import MatchResult, UnitMotion
from .units import (
    DEFAULT_OVERTURN_DEG,
    DEFAULT_RIGID_TOL_MM,
    DEFAULT_SPAN_MM,
    UnitMap,
    assign_units,
    group_fiducials,
    unit_motions,
)


@dataclass(frozen=True, slots=True, eq=False)
class UnitAnalysis:
    """A unit-aware matching: the final fiducial matching, unit motions and leftovers.

    Attributes
    ----------
    result : MatchResult
        The last pass's matching.
    units : tuple of UnitMotion
    unassigned : tuple of int
        Baseline indices that belong to no unit.
    passes : int
        Matching passes run (1 = no unit-aware refinement).
    """

    result: MatchResult
    units: tuple[UnitMotion, ...]
    unassigned: tuple[int, ...]
    passes: int


def match_units(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    *,
    unit_map: UnitMap | None = None,
    span_mm: float | None = None,
    rigid_tol_mm: float = DEFAULT_RIGID_TOL_MM,
    overturn_deg: float = DEFAULT_OVERTURN_DEG,
    refine_passes: int = 2,
    rigid_gate_mm: float = 8.0,
    translation_gate_mm: float = 15.0,
    depth_slack_mm: float = 100.0,
    **match_kw: Any,
) -> UnitAnalysis:
    """Match fiducials, find units and their motion, then re-match knowing how units moved.

    The first pass is :func:`displacement_matcher.match` alone. A unit whose same-code matches
    agree on a rigid motion predicts where each of its baseline fiducials is now; the next pass
    measures costs from those predictions with a tight gate for them (``rigid_gate_mm`` after a
    rigid fit, ``translation_gate_mm`` after a translation, which ignores the unit's rotation).
    So a still unit's fiducial that is hidden now no longer grabs a stranger 40 mm away, and a
    moved unit's fiducials find their new places. Each pass is still one exact global matching.

    Parameters
    ----------
    baseline, current : sequence of FiducialPose
    unit_map : UnitMap, optional
    span_mm, rigid_tol_mm, overturn_deg
        See :func:`unit_motions`.
    refine_passes : int
        Unit-aware passes after the first (0 for the plain matching).
    rigid_gate_mm, translation_gate_mm : float
        Gates of predicted fiducials (across the line of sight).
    depth_slack_mm : float
        Depth discrepancy of a predicted fiducial that is not counted (see
        :func:`displacement_matcher.match`): identity follows the image, where a monocular pose
        is precise, while the unit motion (:func:`unit_motions`) screens out the depth outliers.
    **match_kw
        Passed to :func:`displacement_matcher.match` (``gate_mm``, ``code_penalty_mm``...).
    """
    if refine_passes < 0:
        raise MatcherError(f"refine_passes must be >= 0, got {refine_passes}")
    result = match(baseline, current, **match_kw)
    groups = assign_units(result, unit_map=unit_map, span_mm=span_mm, rigid_tol_mm=rigid_tol_mm)
    kw: dict[str, Any] = {
        "unit_map": unit_map,
        "span_mm": span_mm,
        "rigid_tol_mm": rigid_tol_mm,
        "overturn_deg": overturn_deg,
        "groups": groups,
        "centres": {},
    }
    units, unassigned = unit_motions(result, **kw)
    span = span_mm if span_mm is not None else (unit_map.span_mm if unit_map else DEFAULT_SPAN_MM)
    template = unit_map.template if unit_map is not None else None
    explicit = unit_map is not None and bool(unit_map.units)
    # The current state's own units: fiducials seen together now belong to one unit.
    cur_groups: list[list[int]] = []
    if not explicit:
        cur_ok = [j for j, p in enumerate(current) if np.all(np.isfinite(p.position_mm))]
        found = group_fiducials(
            [current[j] for j in cur_ok], span_mm=span, template=template, tol_mm=rigid_tol_mm
        )
        cur_groups = [[cur_ok[k] for k in g] for g in found]
    excluded: set[tuple[int, int]] = set()
    passes = 1
    last_inputs: tuple[Any, ...] | None = None
    for _ in range(refine_passes):
        pred = np.full((len(baseline), 3), np.nan)
        gate = np.full(len(baseline), np.nan)
        for u in units:
            if u.overturned:
                continue
            if u.method == "none" or u.n_matched == 0:
                # Nothing matched. A unit of several fiducials may have moved far and lost its
                # partners to a wrong first guess: it searches the full gate again. A lone
                # fiducial is weak evidence (far off, a same-code stranger is as likely as its
                # partner; most units do not move): it is looked for where it was, with the
                # depth slack (its depth may be far off while the image shows it in place).
                if len(u.baseline_indices) == 1:
                    i = u.baseline_indices[0]
                    pred[i] = baseline[i].position_mm
                    gate[i] = translation_gate_mm
                continue
            ref = u.reference_before_mm
            for i in u.baseline_indices:
                p = np.asarray(baseline[i].position_mm, dtype=np.float64)
                pred[i] = u.rotation @ (p - ref) + ref + u.translation_mm
                gate[i] = rigid_gate_mm if u.method == "rigid" else translation_gate_mm
        merged = _merge_fragments(result, groups[0], cur_groups, span)
        if merged is not None:
            groups = (merged, groups[1])
            kw["groups"] = groups
            kw["centres"] = {}
        excluded |= _unit_conflicts(result, groups[0], cur_groups)
        inputs = (pred, gate, sorted(excluded), groups[0])
        if last_inputs is not None and _same_inputs(inputs, last_inputs):
            # The pass would repeat the last one exactly (same predictions, gates, exclusions
            # and units): the matching has settled.
            break
        last_inputs = inputs
        result = match(
            baseline,
            current,
            prediction_mm=pred,
            row_gate_mm=gate,
            depth_slack_mm=depth_slack_mm,
            exclude_pairs=sorted(excluded),
            **match_kw,
        )
        units, unassigned = unit_motions(result, **kw)
        passes += 1
    return UnitAnalysis(result, units, unassigned, passes)


def _same_inputs(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    """Whether two passes' inputs (predictions, gates, excluded pairs, units) are identical."""
    return (
        np.array_equal(a[0], b[0], equal_nan=True)
        and np.array_equal(a[1], b[1], equal_nan=True)
        and a[2] == b[2]
        and a[3] == b[3]
    )


def _merge_fragments(
    result: MatchResult,
    base_units: list[tuple[str, list[int]]],
    cur_groups: list[list[int]],
    span_mm: float,
) -> list[tuple[str, list[int]]] | None:
    """Baseline units joined where the current state's grouping shows they are one unit.

    A baseline unit split in two (one fiducial's depth far off fails the template's distance
    check) is whole again when one current unit holds same-code partners of both parts, their
    codes are all different and every pair of them lies within ``span_mm`` across the line of
    sight (depth is what went wrong). Returns the new unit list (the merged unit keeps the first
    part's id), or None when nothing merges.
    """
    base = result.baseline
    unit_of = {i: n for n, (_, ix) in enumerate(base_units) for i in ix}
    pair_of: dict[int, int] = {
        int(d.current_index): int(d.baseline_index)
        for d in result.displacements
        if d.label == "same_code" and d.current_index is not None and d.baseline_index is not None
    }
    parent = list(range(len(base_units)))

    def root(n: int) -> int:
        while parent[n] != n:
            n = parent[n]
        return n

    members = {n: list(ix) for n, (_, ix) in enumerate(base_units)}
    changed = False
    for g in cur_groups:
        parts = sorted(
            {root(unit_of[pair_of[j]]) for j in g if j in pair_of and pair_of[j] in unit_of}
        )
        if len(parts) < 2:
            continue
        ix = [i for n in parts for i in members[n]]
        codes = [int(base[i].code) for i in ix]
        if len(set(codes)) != len(codes):
            continue
        pos = np.array([base[i].position_mm for i in ix], dtype=np.float64)
        lateral = across_line_of_sight(pos[:, None] - pos[None], pos.mean(axis=0))
        if np.max(np.linalg.norm(lateral, axis=2)) > span_mm:
            continue
        for n in parts[1:]:
            parent[n] = parts[0]
            members[parts[0]] += members.pop(n)
        changed = True
    if not changed:
        return None
    return [(name, sorted(members[n])) for n, (name, _) in enumerate(base_units) if n in members]


def _unit_conflicts(
    result: MatchResult,
    base_units: list[tuple[str, list[int]]],
    cur_groups: list[list[int]],
) -> set[tuple[int, int]]:
    """Pairs that contradict the current state's grouping.

    When one current unit's fiducials are matched to several baseline units, the baseline unit
    with most of them is that unit; pairs into it from baseline units with fewer are wrong (a
    still unit's hidden fiducial grabbing a moved neighbour's newly visible one, say).
    """
    unit_of = {i: n for n, (_, ix) in enumerate(base_units) for i in ix}
    pair_of: dict[int, int] = {
        int(d.current_index): int(d.baseline_index)
        for d in result.displacements
        if d.is_match and d.current_index is not None and d.baseline_index is not None
    }
    out: set[tuple[int, int]] = set()
    for g in cur_groups:
        members = [(pair_of[j], j) for j in g if j in pair_of]
        owners = [unit_of.get(i, -1 - i) for i, _ in members]
        if len(set(owners)) < 2:
            continue
        counts = {o: owners.count(o) for o in owners}
        top = max(counts.values())
        winners = [o for o, c in counts.items() if c == top]
        if len(winners) != 1:
            continue
        for (i, j), o in zip(members, owners, strict=True):
            if o != winners[0]:
                out.add((i, j))
    return out
