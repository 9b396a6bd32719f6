"""Unit-aware matching: match, find units and their motion, re-match knowing how units moved.

The first pass is the plain global matching (:func:`displacement_matcher.match`). Units are then
found (:func:`displacement_matcher.units.assign_units`) and their motion estimated; each unit whose
same-code matches agree on a motion predicts where its baseline fiducials are now, and the next
pass measures costs from there with a tight gate across the line of sight (depth, which a single
camera measures with heavy tails, gets slack), while pairs that contradict the current state's own
grouping are excluded and baseline units that the current grouping shows to be one are merged.
Whole units are also matched one to one to the current state's units
(:func:`assign_unit_groups`): a unit whose faces are found together elsewhere is predicted
there, even where single fiducials found cheaper strangers. Every pass is still one exact
global matching. Camera frame, millimetres.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from pose_estimator.types import FiducialPose

from .errors import MatcherError
from .learned_template import learn_template
from .match import match
from .rigid import across_line_of_sight, rigid_fit
from .types import MatchResult, UnitMotion
from .units import (
    APART_IN_DEPTH_MM,
    DEFAULT_OVERTURN_DEG,
    DEFAULT_RIGID_TOL_MM,
    DEFAULT_SPAN_MM,
    FRAME_TURN_TOL_DEG,
    MAX_FACE_TURN_DEG,
    STILL_SHOWN_MM,
    UnitMap,
    UnitSpec,
    assign_units,
    branch_fit,
    close_template_pose,
    faces_shown_in_place,
    fits_template,
    frames_apart,
    learn_pair_distances,
    least_turn,
    mirror_normals,
    one_body,
    opposed_faces,
    places_every_code,
    seen_in_place,
    still_in_place,
    template_pose,
    template_span,
    unit_motions,
    unit_normals,
    units_of,
)

#: A pair whose displacement is within its own noise (chi-square, 3 degrees of freedom, p =
#: 0.05, from both poses' covariances) or shorter than :data:`UNMOVED_MM` has not moved.
UNMOVED_CHI2 = 7.81
#: Length below which a pair has not moved whatever its covariances say (compression artefacts
#: and model misfit that differ between two images shift a pose by microns, beyond a clean
#: image's noise-only covariance); far below any motion the damage count tells apart.
UNMOVED_MM = 0.5
#: A face seen again in place across the line of sight and within this distance in depth
#: breaks a one-against-one tie with a pair that moved (:func:`_mostly_in_place`), whatever
#: depth sd the two poses claim (the distance beyond which a face with precise depths is another
#: unit's, :func:`.units.still_in_place`).
TIE_DEPTH_MM = APART_IN_DEPTH_MM
#: In front of a baseline face: within this distance of it across the line of sight (a face of
#: the unit resting over it) ...
COVER_MM = 10.0
#: ... and nearer the camera by this much plus three standard deviations of the two depths.
COVER_DEPTH_MM = 5.0
#: A current unit whose other faces all lie this far from a baseline unit's faces of their codes
#: is not that unit seen in place through a face it shows there (:func:`_coherent_in_place`;
#: on the 30 dolos fields such stand-ins' other faces lie 24-61 mm away, a still unit's posed
#: off 16 mm). A stranger's lone pair from nearer than this into a face that a unit shows in
#: place may be the stranger's own after a small move, and stands (:func:`_hidden_face_shown`).
ELSEWHERE_MM = 20.0
#: Share of a candidate unit motion's scatter (its pairs' offsets from the one translation,
#: across the line of sight, summed) added to its length in :func:`assign_unit_groups`. A
#: neighbour's faces reached only through a turn cost more than a unit's own reached straight
#: (30 dolos fields: a unit moved 0.7 Dn towards the camera lost its group to a neighbour 40 mm
#: away, turned 24 deg, on a tie; false displaced 19 -> 17). At full weight it also cost a mover
#: that truly turned 20-30 deg its group (seed 17).
SCATTER_WEIGHT = 0.5


@dataclass(frozen=True, slots=True)
class GroupAssignment:
    """A baseline unit found whole in a current group (:func:`assign_unit_groups`).

    Attributes
    ----------
    baseline_indices : tuple of int
        The unit's baseline fiducials.
    translation_mm : (3,) ndarray
        Its translation, camera frame (mm).
    current_indices : tuple of int
        The current group's fiducials.
    misfit_mm : float
        How far one rigid motion of the shared faces (positions and normals) misses the worst
        of them, across the line of sight (mm): 8 mm off is not one body.
    """

    baseline_indices: tuple[int, ...]
    translation_mm: NDArray[np.float64]
    current_indices: tuple[int, ...]
    misfit_mm: float


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
    learned_template : UnitSpec or None
        The template learned from the baseline when no unit map, or a template of codes alone,
        was given (:func:`.learned_template.learn_template`), None otherwise or when none
        could be.
    """

    result: MatchResult
    units: tuple[UnitMotion, ...]
    unassigned: tuple[int, ...]
    passes: int
    learned_template: UnitSpec | None = None


def match_units(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    *,
    unit_map: UnitMap | None = None,
    span_mm: float | None = None,
    rigid_tol_mm: float = DEFAULT_RIGID_TOL_MM,
    overturn_deg: float = DEFAULT_OVERTURN_DEG,
    refine_passes: int = 12,
    rigid_gate_mm: float = 8.0,
    translation_gate_mm: float = 15.0,
    depth_slack_mm: float = 100.0,
    learn: bool = True,
    **match_kw: Any,
) -> UnitAnalysis:
    """Match fiducials, find units and their motion, then re-match knowing how units moved.

    The first pass is :func:`displacement_matcher.match` alone. A unit whose same-code matches agree
    on a rigid motion predicts where each of its baseline fiducials is now; the next pass measures
    costs from those predictions with a tight gate for them (``rigid_gate_mm`` after a rigid fit,
    ``translation_gate_mm`` after a translation, which ignores the unit's rotation). So a still
    unit's fiducial that is hidden now no longer grabs a stranger 40 mm away, and a moved unit's
    fiducials find their new places. Without an explicit unit map, baseline units are also matched
    one to one to the current state's units (:func:`assign_unit_groups`); where that places a unit
    elsewhere than its own matches do, its fiducials are predicted there (translation gate), and the
    pairs other units made into that group are ruled out. Faces still seen where they were (across
    the line of sight, where one image measures precisely) outweigh pairs that moved: a unit most of
    whose faces are in place (or one, at its depth too, against one pair that moved) is looked for
    there, and so is a unit measured through one pair that moved while a face of its code is in
    place. A lone pair is ruled out where its fiducial is another unit's face, by that unit's own
    matches (:func:`_contested_lone_pairs`; where that unit is itself measured through one pair, by
    the rotation its pair's normals and the fiducial's own fix, :func:`_turned_onto`) or by the
    template fitted to a still neighbour's faces (:func:`_neighbour_faces_taken`), or where the unit
    shows now, in place, a face it hid before (:func:`_hidden_face_shown`), or where the current
    unit it moved into holds, by the template, another of its unit's faces where that face was
    (:func:`_pair_into_unit_at_rest`). A unit's pairs whose faces turned otherwise than the
    rest of its pairs' (their printed frames) are a stranger's and ruled out
    (:func:`_strangers_in_units`). A face of a code the template lists as hidden is no unit's
    whose other faces are all seen where they were (:func:`_hidden_faces_apart`: a unit at rest
    does not show it). A unit none of whose faces matched is found again where the
    faces it shows now, none matched either (or only on weak evidence), fit the template
    (:func:`.units.unit_motions`); other units' pairs into those faces are then ruled out and its
    old faces are looked for where the template puts them. Each pass is still one exact global
    matching.

    Parameters
    ----------
    baseline, current : sequence of FiducialPose
    unit_map : UnitMap, optional
    span_mm, rigid_tol_mm, overturn_deg
        See :func:`unit_motions`.
    refine_passes : int
        Unit-aware passes after the first (0 for the plain matching). A pass that rules out a
        pair (a neighbour's face, :func:`_neighbour_faces_taken`) can free a fiducial whose
        unit's motion the next pass then measures, which can take several passes to settle
        (30 dolos-field seeds end to end: 3-10 passes; one still unit stayed displaced until
        the fourth ruled out its lone stranger by the neighbour's template). Passes stop early
        once one would repeat the last; where they cycle through two or more states instead,
        the pairs the states disagree on are ruled out for one last pass.
    rigid_gate_mm, translation_gate_mm : float
        Gates of predicted fiducials (across the line of sight).
    depth_slack_mm : float
        Depth discrepancy of a predicted fiducial that is not counted (see
        :func:`displacement_matcher.match`): identity follows the image, where a monocular pose
        is precise, while the unit motion (:func:`unit_motions`) screens out the depth outliers.
    learn : bool
        Without a unit map, or with a template of codes alone, learn the template from the
        baseline's units (:func:`.learned_template.learn_template`: positions and normals of the
        faces the baseline shows together) and match as with a template; where none can be
        learned, or with ``learn=False``, units are grouped by the distances between codes
        learned from the baseline (:func:`.units.learn_pair_distances`).
    **match_kw
        Passed to :func:`displacement_matcher.match` (``gate_mm``, ``code_penalty_mm``...).
    """
    if refine_passes < 0:
        raise MatcherError(f"refine_passes must be >= 0, got {refine_passes}")
    if unit_map is not None and unit_map.units:
        # An explicit map puts every code on one fiducial: seen once before and once now, it is
        # that fiducial however far it went (match's identity_codes).
        match_kw.setdefault("identity_codes", frozenset(c for u in unit_map.units for c in u.codes))
    result = match(baseline, current, **match_kw)
    span = span_mm if span_mm is not None else (unit_map.span_mm if unit_map else DEFAULT_SPAN_MM)
    learned_template = None
    given = unit_map.template if unit_map is not None and not unit_map.units else None
    bare = given is not None and not given.positions_mm and not given.normals
    if learn and (unit_map is None or bare):
        # The paper's case, every unit carrying the same codes with no map given (or a template
        # of codes alone): the units the baseline shows whole say where the codes sit on a unit.
        learned_template = learn_template(
            result.baseline,
            span,
            other_state=result.current,
            codes=None if given is None else given.codes,
        )
        if learned_template is not None:
            # Without a map, its own extent, as a unit map's template without a span (40 mm let
            # a neighbour's face join a unit's fragments, seed 23).
            if span_mm is None and unit_map is None:
                span = template_span(learned_template)
            unit_map = UnitMap((), learned_template, span)
    template = unit_map.template if unit_map is not None else None
    explicit = unit_map is not None and bool(unit_map.units)
    # Where no template places them, the distances between a unit's codes are learned from the
    # baseline, for the baseline's and the current state's grouping alike.
    learned: dict[tuple[int, int], float] = (
        learn_pair_distances(result.baseline, span)
        if not explicit and not places_every_code(template)
        else {}
    )
    groups = assign_units(
        result,
        unit_map=unit_map,
        span_mm=span_mm,
        rigid_tol_mm=rigid_tol_mm,
        pair_distances=learned,
    )
    kw: dict[str, Any] = {
        "unit_map": unit_map,
        "span_mm": span_mm,
        "rigid_tol_mm": rigid_tol_mm,
        "overturn_deg": overturn_deg,
        "groups": groups,
        "centres": {},
    }
    # Faces still seen where they were (depth aside): baseline index -> current index.
    in_place = still_in_place(baseline, current)
    kw["in_place"] = in_place
    # The current state's own units: fiducials seen together now belong to one unit.
    cur_groups: list[list[int]] = []
    if not explicit:
        cur_groups = units_of(current, span, template, rigid_tol_mm, learned)
        if template is not None and template.hidden:
            cur_groups = _hidden_faces_apart(current, cur_groups, in_place, template)
        kw["cur_groups"] = cur_groups
    # Of those, the faces seen again as they were in every respect: their pairs stand whatever
    # the rules below say of the units they join (:func:`_identical_pairs`).
    identical = _identical_pairs(baseline, current, in_place)
    units, unassigned = unit_motions(result, **kw)
    gate_used = float(match_kw.get("gate_mm", result.params.gate_mm))
    excluded: set[tuple[int, int]] = set()
    held: set[str] = set()  # units looked for where they were (below)
    passes = 1
    # Each pass's inputs and the pairs its matching made, to tell a settled matching from
    # one that cycles.
    history: list[tuple[tuple[Any, ...], frozenset[tuple[int, int]]]] = []
    pair_of: dict[int, int] = dict(result.pairs().tolist())  # the last matching's pairs
    for _ in range(refine_passes):
        pred = np.full((len(baseline), 3), np.nan)
        gate = np.full(len(baseline), np.nan)
        # Units whose motion is one pair's own offset: (baseline, current) of that pair.
        lone: dict[int, int] = {}
        # The same of units called overturned (one pair across codes, most often).
        lone_turned: dict[int, int] = {}
        for u in units:
            if u.n_matched == 1:
                (lone_turned if u.overturned else lone).update(
                    (i, pair_of[i]) for i in u.baseline_indices if i in pair_of
                )
        # Units seen in place, for the template's rules (found once per pass).
        still = _whole_in_place(units, baseline, current, pair_of) if template is not None else []
        covered = (
            _still_neighbours_faces(baseline, current, still, template, span, lone)
            if template is not None
            else set()
        )
        shown_in_place = (
            _hidden_face_shown(
                baseline, current, units, lone | lone_turned, template, span, pair_of
            )
            if template is not None
            else set()
        )
        covered |= {i for i, _ in shown_in_place}
        if template is not None and cur_groups:
            covered |= _pair_into_unit_at_rest(baseline, current, units, lone, cur_groups, template)
        excluded |= shown_in_place
        for u in units:
            if u.method == "template":
                # Found again whole where its faces now fit the template (none of them matched):
                # its old faces are looked for where that puts them, for their own pairs.
                for i in u.baseline_indices:
                    p = np.asarray(baseline[i].position_mm, dtype=np.float64)
                    pred[i] = u.rotation @ (p - u.reference_before_mm) + u.reference_before_mm
                    pred[i] += u.translation_mm
                    gate[i] = rigid_gate_mm
                continue
            if u.method == "none" or u.n_matched == 0:
                # Nothing matched. A unit of several fiducials may have moved far and lost its
                # partners to a wrong first guess: it searches the full gate again. A lone
                # fiducial is weak evidence (far off, a same-code stranger is as likely as its
                # partner; most units do not move): it is looked for where it was, with the
                # depth slack (its depth may be far off while the image shows it in place).
                # (Overturned units are left to the plain matching, below.)
                if len(u.baseline_indices) == 1 and not u.overturned:
                    i = u.baseline_indices[0]
                    pred[i] = baseline[i].position_mm
                    gate[i] = translation_gate_mm
                continue
            stays = u.unit in held or _mostly_in_place(
                u.baseline_indices, in_place, pair_of, baseline, current
            )
            if u.overturned and not (u.n_matched >= 2 and stays):
                # Overturned units are left to the plain matching (their fitted rotation
                # predicts poorly), except one whose faces are mostly seen where they were: a
                # still unit the fit turned about its face in place, through a pair into a
                # neighbour's face beside it (30 dolos-field seeds: still units counted
                # displaced 6 -> 5).
                continue
            ref = u.reference_before_mm
            if stays:
                # Most of its faces are still seen where they were (across the line of sight;
                # their pairs' depth may be far off, partly covered fiducials), or one, at its
                # depth too, against one pair that moved: the motion rests on the rest, a
                # neighbour's face taken. The unit is looked for where it was, and
                # held there in later passes (the pairs that moved it would otherwise outvote
                # its faces again once those are claimed).
                held.add(u.unit)
                for i in u.baseline_indices:
                    pred[i] = baseline[i].position_mm
                    gate[i] = rigid_gate_mm
                continue
            for i in u.baseline_indices:
                if i in covered or (i in lone and in_place.get(i, lone[i]) != lone[i]):
                    # A lone pair that moved while a face of its code is still seen where the
                    # fiducial was, or while a still neighbour's template puts its own face of
                    # that code there (a partly covered fiducial whose depth is off, its pair a
                    # neighbour's face): it is looked for where it was, as a lone fiducial.
                    pred[i] = baseline[i].position_mm
                    gate[i] = translation_gate_mm
                    continue
                p = np.asarray(baseline[i].position_mm, dtype=np.float64)
                pred[i] = u.rotation @ (p - ref) + ref + u.translation_mm
                gate[i] = rigid_gate_mm if u.method == "rigid" else translation_gate_mm
        merged = _merge_fragments(result, groups[0], cur_groups, span)
        if merged is not None:
            groups = (merged, groups[1])
            kw["groups"] = groups
            kw["centres"] = {}
        if cur_groups:
            # Whole units found in their new places (two or more faces moving together, one to
            # one) override what single fiducials suggested where the two disagree (across the
            # line of sight, beyond the rigid gate).
            assigned = assign_unit_groups(
                baseline,
                current,
                groups[0],
                cur_groups,
                gate_mm=gate_used,
                tol_mm=rigid_gate_mm,
                shown=in_place,
                template=template,
            )
            for a in assigned:
                for i in a.baseline_indices:
                    p = np.asarray(baseline[i].position_mm, dtype=np.float64) + a.translation_mm
                    if seen_in_place(pred[i], p, rigid_gate_mm):
                        continue
                    pred[i] = p
                    gate[i] = translation_gate_mm
            # Pairs into a group another unit was assigned, whose shared faces one rigid motion
            # carries within STILL_SHOWN_MM: that unit came to rest there, and this one (a still
            # unit hidden behind it, most often) is looked for where it was (30 dolos-field
            # seeds: still units counted displaced 14 -> 11, missed displaced 59 -> 55).
            owner = {
                j: k
                for k, a in enumerate(assigned)
                if a.misfit_mm <= STILL_SHOWN_MM
                for j in a.current_indices
            }
            own = {i: k for k, a in enumerate(assigned) for i in a.baseline_indices}
            for i, j in pair_of.items():
                if j in owner and own.get(i) != owner[j]:
                    excluded.add((i, j))
                    pred[i] = baseline[i].position_mm
                    gate[i] = translation_gate_mm
        excluded |= _unit_conflicts(result, groups[0], cur_groups)
        excluded |= _pairs_into_relocated(units, pair_of)
        excluded |= _contested_lone_pairs(baseline, current, units, pred, lone, span)
        excluded |= _turned_too_far(baseline, current, lone | lone_turned)
        excluded |= _strangers_in_units(baseline, current, units, pair_of)
        if template is not None:
            excluded |= _neighbour_faces_taken(result, units, still, template, span, pair_of)
        if template is None:
            # Without a template a group may join two neighbours' faces (learned distances
            # leave 10-20 % of the dolos fields' groups mixed), and the rules above, judging
            # pairs by the units they join, then cost still faces their partners: a face still
            # seen where it was is not ruled out. (With a template, whose groups are pure, the
            # same rule gave one more still unit displaced over 30 seeds.)
            excluded -= set(in_place.items())
        excluded -= identical
        inputs = (pred, gate, sorted(excluded), groups[0])
        again = next(
            (k for k, (earlier, _) in enumerate(history) if _same_inputs(inputs, earlier)), None
        )
        if again == len(history) - 1:
            # The pass would repeat the last one exactly (same predictions, gates, exclusions
            # and units): the matching has settled.
            break
        if again is not None:
            # The passes cycle: two or more states, each leading to the next (rivals for the
            # same faces taking them in turn). Pairs made in some states of the cycle but not
            # in all are unstable; they are ruled out and one last pass is run: a unit
            # measured through them is reported lost rather than displaced by a coin toss.
            made = [pairs for _, pairs in history[again:]]
            excluded |= frozenset.union(*made) - frozenset.intersection(*made)
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
        pair_of = dict(result.pairs().tolist())
        passes += 1
        if again is not None:
            break
        history.append((inputs, frozenset(pair_of.items())))
    return UnitAnalysis(result, units, unassigned, passes, learned_template)


def assign_unit_groups(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    base_units: Sequence[tuple[str, list[int]]],
    cur_groups: Sequence[list[int]],
    *,
    gate_mm: float,
    tol_mm: float,
    shown: dict[int, int] | None = None,
    template: UnitSpec | None = None,
) -> list[GroupAssignment]:
    """Baseline units matched one to one to the current state's units, by their shared codes.

    Fiducial by fiducial, a moved unit loses to a still neighbour it landed on: the neighbour's
    hidden face grabs the mover's same-code face 10-20 mm away, cheaper than the mover's own
    30-40 mm (mostly along depth, the weakest axis of a monocular pose), and the mover's motion
    is lost. A unit is one rigid body, and each current unit belongs to one baseline unit only:
    a baseline unit and a current group (:func:`.units.group_fiducials` on the current poses)
    are candidates when at least two codes are on both and their same-code pairs agree on one
    translation within ``tol_mm`` across the line of sight (two coherent fiducials are evidence
    one stranger is not) and, where the poses carry printed axes, their faces turned alike
    (:func:`.units.one_body`: every dolos carries its codes alike, so a neighbour's faces fit a
    unit's by one motion as well as its own, but not their glue spins). Costs follow the
    fiducial matching's (:func:`displacement_matcher.match`, where a fiducial left unmatched
    costs half of ``gate_mm``): the motion costs its length plus :data:`SCATTER_WEIGHT` of its
    pairs' scatter about it, each shared pair saves the current face's half gate and the
    baseline face's, except that a unit every shared face of which has a current fiducial now in
    front of it (:func:`_covered`) is hidden there, not gone: its faces cost nothing unmatched,
    so its pairs save only the current halves. (Judged face by face, one covered face of a unit
    that moved 19 mm let a neighbour that moved 31 mm take its group, seed 21.) A unit left
    unassigned costs nothing. The assignment (exact, minimum cost, each unit and group used at
    most once, no match allowed) prefers more shared faces, then the smallest motion, and of two
    units whose faces fit one group, it gives the group to the one whose place is now empty (a
    mover come to rest 20 mm in front of a neighbour showing the same codes; 30 dolos-field
    seeds: still units counted displaced 5 -> 4). A baseline unit with a face still seen in
    place (:func:`.units.still_in_place`) did not move: it takes no part, and
    the current unit holding that face is its own, so no other unit may claim it; the mover
    then gets the group it moved to. A face another current unit shows in place does not count
    so (:func:`_coherent_in_place`: a mover come to rest in front of a still unit's hidden face
    would hold the still unit and keep the mover from its own faces). A unit may also have
    turned over where it was: a group within the gate showing a face opposite to its old ones
    and none of their codes is explained by it, saving the group's half gates less the distance
    between the faces then and now (:func:`_turned_over_here`), so a unit turned over beside a
    mover no longer takes the mover's group by a slightly shorter translation. (A neighbour
    hidden entirely is not told apart from a mover by the pairs' positions alone, nor a unit
    that moved straight towards the camera, in front of its own old faces, from a mover come to
    rest there: the face counts and lengths decide.) Units seen through one fiducial take part
    with the groups holding its code, but their assignments are not returned (one face is weak
    evidence: the fiducial matching pairs it): they only keep a two-faced unit from a group that
    is theirs (a mover whose pair lands on a neighbour's new pair after a shorter motion than its
    own). Translations are limited to ``2 * gate_mm`` (``gate_mm`` across the line of sight).

    Parameters
    ----------
    baseline, current : sequence of FiducialPose
    base_units : sequence of (str, list of int)
        Baseline units (id, baseline indices), as from :func:`assign_units`.
    cur_groups : sequence of list of int
        The current state's units (current indices), as from :func:`.units.units_of`.
    gate_mm : float
        The matching gate (mm).
    tol_mm : float
        Largest disagreement (mm, across the line of sight) of a shared face with the unit's
        translation.
    shown : dict of int to int, optional
        :func:`.units.still_in_place` of ``baseline`` and ``current``, where the caller has it.

    Returns
    -------
    list of GroupAssignment
        One per assigned baseline unit: its fiducials, translation and current group.
    """
    cur_of: list[dict[int, int]] = []
    for g in cur_groups:
        cur_of.append({int(current[j].code): j for j in g})
    cpos = np.array(
        [np.mean([current[j].position_mm for j in g], axis=0) for g in cur_groups]
    ).reshape(-1, 3)
    if not len(cpos) or not base_units:
        return []
    tree = cKDTree(cpos)
    # Baseline fiducials with a same-code fiducial still seen where they were (in the image,
    # where one camera measures precisely): their unit did not move, whatever its neighbours
    # now show around it, and the current unit holding that face is its own (one to one: no
    # other baseline unit may claim it). Such units are left to the fiducial matching.
    if shown is None:
        shown = still_in_place(baseline, current)
    group_of = {j: c for c, g in enumerate(cur_groups) for j in g}
    if template is not None:
        shown = _coherent_in_place(
            baseline, current, base_units, cur_groups, group_of, shown, template
        )
    still_units = {n for n, (_, ix) in enumerate(base_units) if any(i in shown for i in ix)}
    owned = {group_of[j] for j in shown.values() if j in group_of}

    rows: list[int] = []
    cols: list[int] = []
    motions: list[NDArray[np.float64]] = []
    shares: list[list[tuple[int, int]]] = []
    spreads: list[float] = []
    for n, (_, ix) in enumerate(base_units):
        if not ix or n in still_units:
            continue
        bpos = np.array([baseline[i].position_mm for i in ix], dtype=np.float64)
        centre = bpos.mean(axis=0)
        for c in tree.query_ball_point(centre, 2.0 * gate_mm + DEFAULT_SPAN_MM):
            if c in owned:
                continue
            shared = [
                (i, cur_of[c][int(baseline[i].code)])
                for i in ix
                if int(baseline[i].code) in cur_of[c]
            ]
            if len(shared) < min(2, len(ix)):
                continue
            v = np.array(
                [
                    np.asarray(current[j].position_mm, dtype=np.float64)
                    - np.asarray(baseline[i].position_mm, dtype=np.float64)
                    for i, j in shared
                ]
            )
            t = v.mean(axis=0)
            spread = np.linalg.norm(across_line_of_sight(v - t, centre), axis=1)
            if np.max(spread) > tol_mm:
                continue
            if len(shared) >= 2 and _turned_apart(baseline, current, shared):
                # Faces whose own turns disagree are a neighbour's, glued at other spins.
                continue
            length = float(np.linalg.norm(t))
            lateral = float(np.linalg.norm(across_line_of_sight(t, centre)))
            if length > 2.0 * gate_mm or lateral > gate_mm:
                continue
            rows.append(n)
            cols.append(c)
            motions.append(t)
            shares.append(shared)
            spreads.append(float(np.sum(spread)))
    if not rows:
        return []
    ur = sorted(set(rows))
    # A baseline face not seen now is either hidden (behind a unit that may have come to rest in
    # front of it: a candidate group's faces) or gone; a unit with a gone face is gone from its
    # place, and only then do its faces cost their half gates.
    occluders = list({j for c in set(cols) for j in cur_groups[c]})
    turned = (
        _turned_over_here(
            baseline, current, base_units, ur, cur_groups, (cpos, tree), owned, template, gate_mm
        )
        if template is not None
        else []
    )
    uc = sorted(set(cols) | {c for (_, c), _ in turned})
    rpos = {n: k for k, n in enumerate(ur)}
    cpos_k = {c: k for k, c in enumerate(uc)}
    # Square matrix with a no-match column per row so every unit may stay unassigned.
    big = 1e9
    cost = np.full((len(ur), len(uc) + len(ur)), big)
    front = np.array([current[j].position_mm for j in occluders], dtype=np.float64)
    front_sd = np.array([current[j].sigma_mm[2] for j in occluders], dtype=np.float64)
    shared_faces = {i for pairs in shares for i, _ in pairs}
    gone = {i: not _covered(baseline, [i], front, front_sd) for i in shared_faces}
    costs = [
        float(np.linalg.norm(t))
        + SCATTER_WEIGHT * sp
        - 0.5 * gate_mm * len(pairs) * (1 + any(gone[i] for i, _ in pairs))
        for t, pairs, sp in zip(motions, shares, spreads, strict=True)
    ]
    cost[:, len(uc) :] = np.where(np.eye(len(ur), dtype=bool), 0.0, big)
    # Turned over where it was: the faces opposite to its old ones it shows now are explained,
    # each saving its half gate as in the matching, against the distance between the faces'
    # centroids then and now (a unit turned over in place shows its other side within its own
    # extent; a mover's neighbour that turned 30 mm away is no alternative to its own group).
    # (Its cells are not shared pairs' cells: it shows none of the unit's codes.)
    for (n, c), x in turned:
        cost[rpos[n], cpos_k[c]] = x - 0.5 * gate_mm * len(cur_groups[c])
    which: dict[tuple[int, int], int] = {}
    for k, (n, c, x) in enumerate(zip(rows, cols, costs, strict=True)):
        cost[rpos[n], cpos_k[c]] = x
        which[(rpos[n], cpos_k[c])] = k
    ri, ci = linear_sum_assignment(cost)
    out: list[GroupAssignment] = []
    for r, c in zip(ri.tolist(), ci.tolist(), strict=True):
        hit = which.get((r, c))
        if hit is not None and len(shares[hit]) >= 2:
            out.append(
                GroupAssignment(
                    tuple(base_units[ur[r]][1]),
                    motions[hit],
                    tuple(cur_groups[uc[c]]),
                    _rigid_misfit(baseline, current, shares[hit]),
                )
            )
    return out


def _turned_over_here(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    base_units: Sequence[tuple[str, list[int]]],
    candidates: Sequence[int],
    cur_groups: Sequence[list[int]],
    centroids: tuple[NDArray[np.float64], cKDTree],
    owned: set[int],
    template: UnitSpec,
    gate_mm: float,
) -> list[tuple[tuple[int, int], float]]:
    """(baseline unit, current group) pairs where the unit may have turned over in place, with
    the distance between their faces' centroids (mm).

    The group shows none of the unit's old codes and at least one face whose template normal
    points away from one the unit showed before, which only the unit turned over can show
    (:func:`.units.opposed_faces`), within ``gate_mm`` of the unit's old faces. ``centroids``:
    the groups' centroids and their k-d tree.
    """
    out: list[tuple[tuple[int, int], float]] = []
    cpos, tree = centroids
    for n in candidates:
        ix = base_units[n][1]
        codes = {int(baseline[i].code) for i in ix}
        bpos = np.array([baseline[i].position_mm for i in ix], dtype=np.float64)
        centre = bpos.mean(axis=0)
        # A group's faces lie within the span of its centroid.
        for c in tree.query_ball_point(centre, gate_mm + DEFAULT_SPAN_MM):
            g = cur_groups[c]
            now = {int(current[j].code) for j in g}
            if c in owned or now & codes:
                continue
            if not any(opposed_faces(template, code, codes) for code in now):
                continue
            gpos = np.array([current[j].position_mm for j in g], dtype=np.float64)
            if float(np.min(np.linalg.norm(bpos[:, None] - gpos[None], axis=2))) < gate_mm:
                out.append(((n, c), float(np.linalg.norm(cpos[c] - centre))))
    return out


def _coherent_in_place(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    base_units: Sequence[tuple[str, list[int]]],
    cur_groups: Sequence[list[int]],
    group_of: dict[int, int],
    shown: dict[int, int],
    template: UnitSpec,
) -> dict[int, int]:
    """``shown`` without faces seen in place by a current unit that is not theirs.

    A face seen in place (:func:`.units.still_in_place`) stands for its unit unless the current
    unit holding it is another one: its other faces of the baseline unit's codes all lie at
    least :data:`ELSEWHERE_MM` from that unit's faces of those codes, and either it is a whole
    unit (three or more faces fitting the template, :func:`.units.fits_template`) or those faces
    of the baseline unit are seen in place by other current units. The face is then another
    unit's of the same code that happens to lie within a few millimetres across the line of
    sight: a mover come to rest in front of a still neighbour's hidden face, or a neighbour's
    face uncovered where a mover's was (30 dolos fields: 9 of the 11 such faces, against 6 of
    the 16,400 faces truly seen again in place, all of units grouped with a neighbour's face).
    The unit's other faces seen in place by other current units do not discredit a face that
    fits the template together with them: they are the unit's faces in place, and the current
    grouping that parted them is mixed (30 dolos fields, learned template: a still unit's two
    faces each grouped with a stranger of the other's code, each discrediting the other, and
    the unit given a mover's faces 30 mm away). A whole unit holding the face still does: a
    mover's face come to rest in front of a still unit's hidden one fits with the still unit's
    face in place as well, across the line of sight.
    """
    unit_of = {i: n for n, (_, ix) in enumerate(base_units) for i in ix}
    together: dict[int, bool] = {}

    def held_together(n: int) -> bool:
        # Whether unit n's faces in place fit the template together (fitted only for the few
        # faces the test below would discredit, once per unit).
        if n not in together:
            held = [current[shown[k]] for k in base_units[n][1] if k in shown]
            together[n] = len(held) >= 2 and fits_template(held, template)
        return together[n]

    out = dict(shown)
    for i, j in shown.items():
        if i not in unit_of or j not in group_of:
            continue
        group = cur_groups[group_of[j]]
        codes = {int(baseline[k].code): k for k in base_units[unit_of[i]][1] if k != i}
        others = [
            (codes[int(current[g].code)], g)
            for g in group
            if g != j and int(current[g].code) in codes
        ]
        if not others or any(
            np.linalg.norm(np.asarray(current[g].position_mm) - np.asarray(baseline[k].position_mm))
            < ELSEWHERE_MM
            for k, g in others
        ):
            continue
        elsewhere = all(shown.get(k) not in (None, *group) for k, _ in others)
        if (elsewhere and not held_together(unit_of[i])) or (
            len(group) >= 3 and fits_template([current[g] for g in group], template)
        ):
            del out[i]
    return out


def _hidden_faces_apart(
    current: Sequence[FiducialPose],
    cur_groups: list[list[int]],
    in_place: dict[int, int],
    template: UnitSpec,
) -> list[list[int]]:
    """The current groups with each face of a code the template lists as hidden split off, as a
    group of its own, where every other face of its group is seen where it was (and it is not).

    A learned template's hidden codes are those its units' resting pose hides
    (:mod:`.learned_template`); it places no such face, and the baseline shows too few for a
    distance between codes to be learned, so the grouping checks such a face against others by
    the span alone and may join a neighbour's. A unit whose faces all lie where they were has
    not turned, so it does not show its hidden face: that face is another unit's, most often
    one turned over beside it (seed 1, default blur: an overturned unit's code-41 face joined a
    still neighbour's two faces in place; the group was the still unit's, so the turn-over was
    not seen, and the overturned unit took a mover's group 1 mm cheaper than the mover's
    own).
    """
    at_rest = set(in_place.values())
    out: list[list[int]] = []
    for g in cur_groups:
        # A hidden face itself seen where it was is the unit's own, shown at rest both times.
        stray = [j for j in g if int(current[j].code) in template.hidden and j not in at_rest]
        rest = [j for j in g if j not in stray]
        if not stray or not rest or not all(j in at_rest for j in rest):
            out.append(g)
            continue
        out.append(rest)
        out.extend([j] for j in stray)
    return sorted(out, key=lambda g: g[0])


def _pairs_into_relocated(
    units: Sequence[UnitMotion], pair_of: dict[int, int]
) -> set[tuple[int, int]]:
    """Pairs of other units' fiducials into the faces of units found again whole
    (:func:`.units.unit_motions`, method ``template``): those faces are the found unit's, whose
    fit to the template outweighs one pair (a still unit's hidden face that took a mover's)."""
    found = {
        j: set(u.baseline_indices)
        for u in units
        if u.method == "template"
        for j in u.current_indices
    }
    return {(i, j) for i, j in pair_of.items() if j in found and i not in found[j]}


def _rigid_misfit(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    pairs: Sequence[tuple[int, int]],
) -> float:
    """How far one rigid motion (fitted to the pairs' positions and normals, each current
    normal on its better branch: :func:`.units.branch_fit`) misses the worst pair, across the
    line of sight (mm; inf without usable normals)."""
    geometry = _paired_geometry([baseline[i] for i, _ in pairs], [current[j] for _, j in pairs])
    if geometry is None:
        return float("inf")
    pb, pa, nb, na = geometry
    R, t, _ = branch_fit(pb, pa, np.ones(len(pairs)), nb, na)
    off = pb @ R.T + t - pa
    return max(
        float(np.linalg.norm(across_line_of_sight(o, q))) for o, q in zip(off, pa, strict=True)
    )


def _paired_geometry(
    before: Sequence[FiducialPose], after: Sequence[FiducialPose]
) -> tuple[NDArray[np.float64], ...] | None:
    """Positions and unit normals of paired poses, before and after (``pb, pa, nb, na``), or
    None when a normal is unusable or a position not finite."""
    nb, na = unit_normals(before), unit_normals(after)
    if nb is None or na is None:
        return None
    pb = np.array([p.position_mm for p in before], dtype=np.float64)
    pa = np.array([p.position_mm for p in after], dtype=np.float64)
    if not (np.all(np.isfinite(pb)) and np.all(np.isfinite(pa))):
        return None
    return pb, pa, nb, na


def _covered(
    baseline: Sequence[FiducialPose],
    members: Sequence[int],
    cpos: NDArray[np.float64],
    csd: NDArray[np.float64],
) -> bool:
    """Whether one of the current fiducials at ``cpos`` (depth sds ``csd``) lies in front of a
    baseline unit's faces (``members``): within :data:`COVER_MM` of one across the line of sight
    and nearer the camera by more than :data:`COVER_DEPTH_MM` plus three standard deviations of
    the depths."""
    for i in members:
        b = np.asarray(baseline[i].position_mm, dtype=np.float64)
        if not (np.all(np.isfinite(b)) and np.any(b)):
            continue
        v = cpos - b
        nearer = -(v @ b) / float(np.linalg.norm(b))
        lateral = np.linalg.norm(across_line_of_sight(v, b), axis=1)
        margin = COVER_DEPTH_MM + 3.0 * np.hypot(csd, float(baseline[i].sigma_mm[2]))
        with np.errstate(invalid="ignore"):
            if np.any((lateral <= COVER_MM) & (nearer > margin)):
                return True
    return False


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
    sight (depth is what went wrong), and the group's pairs turned alike (their printed frames,
    :func:`.units.one_body`): a neighbour's face paired into the group, glued at another spin,
    turned otherwise, and the parts are two units (the 60 end-to-end dolos fields, true
    template: 58 such merges refused, every one of two units; of the 14 left, 3 are of one
    unit, and 11 of two whose stranger's face turned within 27 deg of the rest, its glue spin
    near theirs). Returns the new unit list (the merged unit keeps the first part's id), or None
    when nothing merges.
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
        shared = [(pair_of[j], j) for j in g if j in pair_of and pair_of[j] in unit_of]
        if _turned_apart(base, result.current, shared):
            # The group's faces turned otherwise than each other (their printed frames): a
            # stranger's pair joins them, not one unit's two fragments.
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


def _pairs_apart(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    pairs: Sequence[tuple[int, int]],
) -> NDArray[np.float64]:
    """:func:`.units.frames_apart` of ``(baseline, current)`` index pairs."""
    return frames_apart([baseline[i] for i, _ in pairs], [current[j] for _, j in pairs])


def _turned_apart(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    pairs: Sequence[tuple[int, int]],
) -> bool:
    """Whether some of the ``(baseline, current)`` index pairs turned otherwise than the rest
    (:func:`.units.one_body` leaves some out): faces of more than one unit."""
    return len(one_body(_pairs_apart(baseline, current, pairs))) < len(pairs)


def _unit_conflicts(
    result: MatchResult,
    base_units: list[tuple[str, list[int]]],
    cur_groups: list[list[int]],
) -> set[tuple[int, int]]:
    """Pairs that contradict the current state's grouping.

    When one current unit's fiducials are matched to several baseline units, the baseline unit
    with most of them is that unit; pairs into it from baseline units with fewer are wrong (a
    still unit's hidden fiducial grabbing a moved neighbour's newly visible one, say). A tie
    rules nothing out: one claim each cannot tell a hidden still unit's grab from a mover that
    landed beside a still neighbour (the current grouping then joins the two; seen on the
    bundled session bag, where preferring the claim still in place discarded a true 40 mm move).
    Nor is a pair wrong whose baseline unit is matched where it was as a whole (every fiducial
    of it, :func:`_unmoved`): it grabbed nothing, and where the two groupings disagree about
    fiducials that all stayed put (targets on a flat sheet, grouped by distance alone) it is
    the grouping that is in doubt. (One pair in place is not enough: a baseline unit that
    wrongly holds a still neighbour's face beside a mover's is taken apart by this rule, as on
    the bundled session bag.)
    """
    unit_of = {i: n for n, (_, ix) in enumerate(base_units) for i in ix}
    pair_of: dict[int, int] = {
        int(d.current_index): int(d.baseline_index)
        for d in result.displacements
        if d.is_match and d.current_index is not None and d.baseline_index is not None
    }
    # Baseline units every fiducial of which is matched where it was.
    match_of = {i: j for j, i in pair_of.items()}
    whole_in_place = {
        n
        for n, (_, ix) in enumerate(base_units)
        if all(
            i in match_of and _unmoved(result.baseline[i], result.current[match_of[i]]) for i in ix
        )
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
            if o != winners[0] and o not in whole_in_place:
                out.add((i, j))
    return out


def _identical_pairs(
    baseline: Sequence[FiducialPose], current: Sequence[FiducialPose], in_place: dict[int, int]
) -> set[tuple[int, int]]:
    """Pairs of faces seen again as they were: in place within their noise, depth included
    (:func:`_unmoved`), and turned by no more than :data:`.units.FRAME_TURN_TOL_DEG`, spin
    included (:func:`.units.least_turn`; poses with printed axes only). A stranger of the same
    code cannot lie there so (two printed discs do not overlap, and its code would have to be
    printed at the same spin), so such a pair is the same fiducial whatever the groupings say:
    where a rule built on them would rule it out (a baseline unit wrongly joined to a
    neighbour's face, 30 e2e fields: a still unit's face 0.4 mm and 0.1 deg from where it was,
    ruled out by :func:`_unit_conflicts`), the grouping is what is wrong.
    """
    out: set[tuple[int, int]] = set()
    for i, j in in_place.items():
        if not _unmoved(baseline[i], current[j]):
            continue
        turn = least_turn(baseline[i], current[j])
        if turn is not None and turn <= FRAME_TURN_TOL_DEG:
            out.add((i, j))
    return out


def _unmoved(before: FiducialPose, after: FiducialPose) -> bool:
    """Whether a pair of the same code lies where it was, within its noise (see
    :data:`UNMOVED_CHI2`, :data:`UNMOVED_MM`)."""
    if int(before.code) != int(after.code):
        return False
    d = np.asarray(after.position_mm, dtype=np.float64) - np.asarray(
        before.position_mm, dtype=np.float64
    )
    if float(np.linalg.norm(d)) <= UNMOVED_MM:
        return True
    cov = np.asarray(before.covariance_mm2, dtype=np.float64) + np.asarray(
        after.covariance_mm2, dtype=np.float64
    )
    try:
        chi2 = float(d @ np.linalg.solve(cov, d))
    except np.linalg.LinAlgError:
        return False
    return bool(np.isfinite(chi2) and 0.0 <= chi2 <= UNMOVED_CHI2)


def _neighbour_faces_taken(
    result: MatchResult,
    units: Sequence[UnitMotion],
    still: Sequence[UnitMotion],
    template: UnitSpec,
    span_mm: float,
    match_of: dict[int, int],
) -> set[tuple[int, int]]:
    """Single-fiducial moves onto a still neighbour's own face.

    A unit whose motion rests on one same-code match can have taken a face of a neighbour that
    the neighbour did not show before (hidden then, or not detected): typically a still unit
    whose faces were all covered during the run by a unit that came to rest in front of it,
    its fiducial grabbing the neighbour's 20-45 mm away. Where a neighbour within ``span_mm``
    is seen in place (every one of its matches still, across the line of sight) and the
    template fits its current fiducials together with the taken one (:func:`template_pose`:
    positions within 5 mm RMS, normals within 30 deg), the fiducial is that neighbour's newly
    seen face and the pair is ruled out. A mover that landed beside a neighbour keeps its
    claim unless its face sits exactly where one of the neighbour's would
    (:func:`fits_template`). ``still``: :func:`_whole_in_place` of ``units``; ``match_of``:
    the result's pairs, baseline -> current index.
    """
    base, cur = result.baseline, result.current

    def moved(i: int) -> bool:
        return not seen_in_place(cur[match_of[i]].position_mm, base[i].position_mm)

    out: set[tuple[int, int]] = set()
    for u in units:
        if u.n_matched != 1:
            continue
        claims = [i for i in u.baseline_indices if i in match_of]
        if len(claims) != 1 or not moved(claims[0]):
            continue
        i = claims[0]
        j = match_of[i]
        taken = cur[j]
        pos = np.asarray(taken.position_mm, dtype=np.float64)
        for v in still:
            if v.unit == u.unit or j in v.current_indices:
                continue
            shown = [cur[k] for k in v.current_indices]
            if _lacks_code_near(shown, int(taken.code), pos, span_mm) and fits_template(
                [*shown, taken], template
            ):
                out.add((i, j))
                break
    return out


def _still_neighbours_faces(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    still: Sequence[UnitMotion],
    template: UnitSpec,
    span_mm: float,
    lone: dict[int, int],
) -> set[int]:
    """Lone pairs' baseline fiducials that are a still neighbour's own face, depth aside.

    A fiducial partly covered by a nearer one's paper can be posed tens of millimetres off in
    depth: no unit takes it in, and alone it matches any same-code face that appears nearby
    (a mover's newly seen one). Where a neighbour within ``span_mm`` is seen in place (every
    one of its matches still, across the line of sight) and the template fitted to its own
    baseline faces (:func:`template_pose`) puts its face of that code, missing from them,
    where the fiducial is seen (within :data:`STILL_SHOWN_MM` across the line of sight), the
    fiducial is that face. ``still``: the units seen in place (:func:`_whole_in_place`).
    Returns the baseline indices of such pairs."""
    out: set[int] = set()
    if not lone:
        return out
    # Each still unit's baseline faces and where its template puts the unit (fitted once).
    fitted = []
    for v in still:
        faces = [baseline[k] for k in v.baseline_indices]
        fit = template_pose(faces, template)
        if fit is not None:
            fitted.append((v, faces, fit))
    for i, j in lone.items():
        p = baseline[i]
        pos = np.asarray(p.position_mm, dtype=np.float64)
        if seen_in_place(current[j].position_mm, pos) or int(p.code) not in template.positions_mm:
            continue
        local = np.asarray(template.positions_mm[int(p.code)], dtype=np.float64)
        for v, faces, (R, t) in fitted:
            if i in v.baseline_indices:
                continue
            if _lacks_code_near(faces, int(p.code), pos, span_mm) and seen_in_place(
                R @ local + t, pos
            ):
                out.add(i)
                break
    return out


def _pair_into_unit_at_rest(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    units: Sequence[UnitMotion],
    lone: dict[int, int],
    cur_groups: Sequence[list[int]],
    template: UnitSpec,
) -> set[int]:
    """Lone pairs that moved into a current unit which holds another of their unit's faces
    where it was.

    A unit is one rigid body: where its one pair moved into a current unit of two or more faces
    that fit the template, that unit's pose says where the pair's unit's other faces are now. If
    one of them (a code the current unit does not show) is then where it was before (within
    :data:`STILL_SHOWN_MM` across the line of sight) while the pair moved, the two cannot be
    one body's: the baseline unit joined two neighbours' faces (a grouping that fits the
    template by chance), and the pair's face is the stranger's, come to rest in the still
    unit's place or gone. Returns the baseline indices of such pairs."""
    out: set[int] = set()
    if not lone:
        return out
    group_of = {j: c for c, g in enumerate(cur_groups) for j in g}
    unit_of = {i: u for u in units for i in u.baseline_indices}
    fits: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]] | None] = {}
    for i, j in lone.items():
        c, unit = group_of.get(j), unit_of.get(i)
        if c is None or unit is None or len(cur_groups[c]) < 2:
            continue
        if seen_in_place(current[j].position_mm, baseline[i].position_mm):
            continue
        group = cur_groups[c]
        if c not in fits:
            fits[c] = close_template_pose([current[k] for k in group], template)
        fit = fits[c]
        if fit is None:
            continue
        R, t = fit
        shown_codes = {int(current[k].code) for k in group}
        for k in unit.baseline_indices:
            code = int(baseline[k].code)
            if k == i or code in shown_codes or code not in template.positions_mm:
                continue
            at = R @ np.asarray(template.positions_mm[code], dtype=np.float64) + t
            if seen_in_place(at, baseline[k].position_mm):
                out.add(i)
                break
    return out


def _hidden_face_shown(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    units: Sequence[UnitMotion],
    lone: dict[int, int],
    template: UnitSpec,
    span_mm: float,
    match_of: dict[int, int],
) -> set[tuple[int, int]]:
    """Lone pairs whose unit shows now, where it was, a face it hid before.

    A still unit whose one seen face is covered during the run (a mover came to rest in front
    of it) often shows another face instead, uncovered as a neighbour moved away; its hidden
    face meanwhile takes a same-code stranger 30-50 mm off, and the unit is counted displaced.
    Where a current fiducial of a code the unit did not show fits the template together with
    the unit's baseline faces (:func:`fits_template`: where that face would be had the unit
    not moved), the unit is seen in place: the pair is ruled out and its fiducial is looked for
    where it was. That fiducial must not also fit the template with the pair's current face (a
    unit moved mostly along the line of sight, which one image barely measures, still fits its
    old place: its own face fits both, and tells nothing). Current fiducials held by a pair seen
    in place are another unit's. The shown fiducial is the unit's own, so a pair another
    baseline fiducial made into it (a same-code stranger's) is ruled out too, and so is a
    stranger's lone pair into such a face of a unit none of whose faces matched. Returns such
    pairs (30 dolos-field seeds, template map: still units counted displaced 19 -> 14, false
    displaced 37 -> 31, missed 60 -> 59; with the stranger's pair and lone pairs of units
    called overturned, a pair across codes most often, 3 -> 2 and 22 / 32 -> 20 / 32; with a
    stranger's pair into a face shown by a unit that matched nothing, through a physical blur,
    2 -> 1 and 20 / 17 -> 19 / 17)."""
    out: set[tuple[int, int]] = set()
    if not lone or not current:
        return out
    still_faces = {
        j
        for i, j in match_of.items()
        if int(baseline[i].code) == int(current[j].code)
        and seen_in_place(current[j].position_mm, baseline[i].position_mm)
    }
    unit_of = {i: u for u in units for i in u.baseline_indices}
    held_by = {j: i for i, j in match_of.items()}
    cur_pos = np.array([p.position_mm for p in current], dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(cur_pos), axis=1)
    tree = cKDTree(np.where(ok[:, None], cur_pos, 1e12))
    for i, j in lone.items():
        pos = np.asarray(baseline[i].position_mm, dtype=np.float64)
        u = unit_of.get(i)
        if u is None or seen_in_place(current[j].position_mm, pos):
            continue
        faces = [baseline[k] for k in u.baseline_indices]
        # Depth, a single image's weak axis, gets the fit's slack beyond the unit's span.
        near = [
            c
            for c in sorted(tree.query_ball_point(pos, span_mm + 10.0))
            if c != j and c not in still_faces
        ]
        for c in faces_shown_in_place(faces, current, near, template):
            if not fits_template([current[j], current[c]], template):
                out.add((i, j))
                k = held_by.get(c)
                if k is not None:
                    out.add((k, c))
                break
    # A unit none of whose faces matched (its one face hidden now, most often) may show such a
    # face too, held by the lone pair of a stranger come from elsewhere (ELSEWHERE_MM across
    # the line of sight: nearer, the face is as likely the stranger's own after a small move):
    # that pair is ruled out alike.
    for u in units:
        if u.n_matched or not u.baseline_indices:
            continue
        faces = [baseline[k] for k in u.baseline_indices]
        centre = np.mean([f.position_mm for f in faces], axis=0)
        held = [
            c
            for c in sorted(tree.query_ball_point(centre, span_mm + 10.0))
            if held_by.get(c) in lone
            and c not in still_faces
            and not seen_in_place(
                current[c].position_mm, baseline[held_by[c]].position_mm, ELSEWHERE_MM
            )
        ]
        shown = next(faces_shown_in_place(faces, current, held, template), None)
        if shown is not None:
            out.add((held_by[shown], shown))
    return out


def _lacks_code_near(
    faces: Sequence[FiducialPose], code: int, point: NDArray[np.float64], span_mm: float
) -> bool:
    """Whether a unit showing ``faces`` has none of ``code`` and one within ``span_mm`` of
    ``point``: a unit that could own a face of that code seen there."""
    if code in {int(f.code) for f in faces}:
        return False
    near = np.linalg.norm(np.array([f.position_mm for f in faces]) - point, axis=1)
    return bool(np.min(near) <= span_mm)


def _whole_in_place(
    units: Sequence[UnitMotion],
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    match_of: dict[int, int],
) -> list[UnitMotion]:
    """Units seen in place: not overturned, with one match or more, every one of them still
    across the line of sight (``match_of``: baseline -> current index)."""
    out = []
    for v in units:
        matched = [i for i in v.baseline_indices if i in match_of]
        if (
            not v.overturned
            and matched
            and all(
                seen_in_place(current[match_of[i]].position_mm, baseline[i].position_mm)
                for i in matched
            )
        ):
            out.append(v)
    return out


def _turned_too_far(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    lone: dict[int, int],
) -> set[tuple[int, int]]:
    """Lone same-code pairs whose fiducial turned more than :data:`.units.MAX_FACE_TURN_DEG`
    between the states.

    One pair is the whole evidence of where its unit went, and a same-code stranger offers it
    as readily as the unit's own face, most often where that face is hidden now. The code's
    sectors fix each pose's spin, so the pair says how the face turned (:func:`.units.least_turn`,
    the least of its four branch combinations, so a pose on its wrong branch does not condemn
    it); a neighbour's face lies as the neighbour does. (Poses without printed axes, and pairs
    across codes, are left to the other rules.)
    """
    out: set[tuple[int, int]] = set()
    for i, j in lone.items():
        if int(baseline[i].code) != int(current[j].code):
            continue
        turn = least_turn(baseline[i], current[j])
        if turn is not None and turn > MAX_FACE_TURN_DEG:
            out.add((i, j))
    return out


def _strangers_in_units(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    units: Sequence[UnitMotion],
    pair_of: dict[int, int],
) -> set[tuple[int, int]]:
    """Same-code pairs of a unit whose faces' turns do not agree with the rest of its pairs'.

    A unit is one rigid body, so each of its faces turned as it did, spin included, and the
    printed frames say so (:func:`.units.frames_apart`). Every dolos carries the same codes in
    the same places, so a neighbour's faces fit a unit's template and its positions as well as
    its own (a mover's faces taken by a neighbour turned over beside it, seed 18); but each
    fiducial is glued at its own spin, and a stranger's face turns by the two glue spins'
    difference. The pairs outside the largest set that agree (:func:`.units.one_body`) are ruled
    out; where no two agree, all but the one that turned least (:func:`.units.least_turn`: a
    unit's own face turns as the unit did, 32 deg at most on the dolos fields, a stranger's
    anyhow), which the lone-pair rules then judge in the next pass.
    """
    out: set[tuple[int, int]] = set()
    for u in units:
        pairs = [
            (i, pair_of[i])
            for i in u.baseline_indices
            if i in pair_of and int(baseline[i].code) == int(current[pair_of[i]].code)
        ]
        if len(pairs) < 2:
            continue
        apart = _pairs_apart(baseline, current, pairs)
        body = one_body(apart)
        if len(body) < 2:
            turns = [least_turn(baseline[i], current[j]) for i, j in pairs]
            body = (int(np.argmin([np.inf if t is None else t for t in turns])),)
        keep = set(body)
        out.update(p for k, p in enumerate(pairs) if k not in keep)
    return out


def _contested_lone_pairs(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    units: Sequence[UnitMotion],
    pred: NDArray[np.float64],
    lone: dict[int, int],
    span_mm: float = DEFAULT_SPAN_MM,
) -> set[tuple[int, int]]:
    """Lone pairs whose current fiducial another unit's own evidence places there.

    A unit measured through one pair predicts that pair's fiducial exactly (its motion is the
    pair's offset), which confirms the pair whatever it is. Where another unit's fiducial of
    the same code is predicted from independent evidence (its unit's other matches) within
    :data:`STILL_SHOWN_MM` of that current fiducial across the line of sight, the fiducial is
    that one's: typically a mover that came to rest in front of a still unit, whose face the
    covered unit's same-code fiducial had taken. A pair seen in place is never contested.

    Another unit measured through one pair itself knows its rotation only in part, and its
    translation-only prediction misses its other faces by up to ``2 sin(turn / 2)`` times their
    distance from the pair (6 mm on a dolos turned 20 deg). Such a unit contests the fiducial
    when the rotation its pair's normals and the fiducial's own normal fix carries its
    same-code face there (:func:`_turned_onto`): two faces moving as one body outweigh one face
    that moved alone. (Its pair's fiducial must lie within ``span_mm`` of that fiducial, across
    the line of sight: faces of one unit.)
    """
    if not lone:
        return set()
    unit_of = {i: n for n, u in enumerate(units) for i in u.baseline_indices}
    rows = [
        k for k in range(len(pred)) if k not in lone and k in unit_of and np.isfinite(pred[k]).all()
    ]
    # The one pair of each unit measured through one pair: unit -> (baseline, current).
    pair_of_unit = {
        unit_of[i]: (i, j)
        for i, j in lone.items()
        if i in unit_of and units[unit_of[i]].n_matched == 1
    }
    out: set[tuple[int, int]] = set()
    for i, j in lone.items():
        pos = np.asarray(current[j].position_mm, dtype=np.float64)
        if seen_in_place(pos, baseline[i].position_mm):
            continue  # a face seen in place is its own evidence
        code = int(current[j].code)
        for k in rows:
            if unit_of[k] == unit_of.get(i) or int(baseline[k].code) != code:
                continue
            if seen_in_place(pred[k], pos):
                out.add((i, j))
                break
            own = pair_of_unit.get(unit_of[k])
            if (
                own is not None
                and seen_in_place(current[own[1]].position_mm, pos, span_mm)
                and _turned_onto(baseline, current, own, k, j)
            ):
                out.add((i, j))
                break
    return out


def _turned_onto(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    pair: tuple[int, int],
    k: int,
    j: int,
) -> bool:
    """Whether the rotation the normals fix carries baseline fiducial ``k`` onto current
    fiducial ``j`` along with the unit's one pair ``pair``.

    One pair's normals fix two of the unit's three rotation angles; ``j``'s normal, taken as
    ``k``'s, fixes the spin about the pair's normal (Wahba's problem over the two normal pairs,
    :func:`.rigid.rigid_fit` without point pairs). Each of the four normals may lie on the
    wrong branch of the circle pose's two-fold ambiguity (:func:`.units.mirror_normals`), and
    choosing per pair the smallest turn can pick branches no one rotation explains: the
    combination with which the rotation carries its worst normal best is taken (as
    :func:`.units.branch_fit` chooses), and must carry both within 15 deg. Then the pair's
    offset with that rotation must put ``k`` within :data:`STILL_SHOWN_MM` of ``j`` across the
    line of sight (where one image measures precisely; the pair's depth does not move a
    prediction across it): the positions, which chose nothing, are the test.
    """
    i, m = pair
    geometry = _paired_geometry([baseline[i], baseline[k]], [current[m], current[j]])
    if geometry is None:
        return False
    pb, pa, nb, na = geometry
    alt_b, alt_a = mirror_normals(pb, nb), mirror_normals(pa, na)
    best: tuple[float, NDArray[np.float64], NDArray[np.float64]] | None = None
    for flip in itertools.product((False, True), repeat=4):
        xb = np.where(np.asarray(flip[:2])[:, None], alt_b, nb)
        xa = np.where(np.asarray(flip[2:])[:, None], alt_a, na)
        R, t = rigid_fit(pb[:1], pa[:1], np.ones(1), xb, xa)
        worst = float(np.min(np.einsum("ki,ki->k", xb @ R.T, xa)))
        if best is None or worst > best[0]:
            best = (worst, R, t)
    assert best is not None
    worst, R, t = best
    if worst < np.cos(np.radians(15.0)):
        return False
    return seen_in_place(R @ pb[1] + t, pa[1])


def _mostly_in_place(
    members: Sequence[int],
    in_place: dict[int, int],
    pair_of: dict[int, int],
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
) -> bool:
    """Whether a unit's baseline fiducials that have a face of their code still seen where they
    were (across the line of sight, :func:`.units.still_in_place`), their own pair's or no
    pair's, outnumber those whose pairs moved, two or more of them; or, one against one, the
    face in place is also at its depth (within :data:`TIE_DEPTH_MM`): most units do not move,
    and a face seen again where it was, depth included, is as strong as a pair that moved (a
    neighbour's face taken: 30 dolos-field seeds, still units counted displaced 7 -> 6). Depth
    only breaks the tie: a partly covered face's depth may be centimetres off, while a unit
    moving along the line of sight keeps its faces in place across it."""
    claimed = set(pair_of.values())
    stayed = moved = deep = 0
    for i in members:
        j = in_place.get(i)
        if j is not None and (pair_of.get(i) == j or j not in claimed):
            stayed += 1
            gap = np.asarray(current[j].position_mm) - np.asarray(baseline[i].position_mm)
            deep += bool(np.linalg.norm(gap) <= TIE_DEPTH_MM)
        elif i in pair_of:
            moved += 1
    return (stayed >= 2 and stayed > moved) or (stayed == moved == deep == 1)
