"""The unit template learned from the baseline, against the field's true template."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from matcher_synth import facing_poses, make_pose, rotation

from armourcam.field import dolos_geometry, make_field
from displacement_matcher.damage import assess, thresholds
from displacement_matcher.learned_template import MIN_CODE_SEEN, learn_template
from displacement_matcher.refine import match_units
from displacement_matcher.rigid import kabsch
from displacement_matcher.units import UnitMap, UnitSpec, mirror_normals, parse_unit_map
from pose_estimator.types import FiducialPose


def _mirror_some(poses: list[FiducialPose], share: float, seed: int) -> list[FiducialPose]:
    """``share`` of the poses with the normal on the other branch of the circle pose's two-fold
    ambiguity, as the pose estimator gives a third of them end to end."""
    rng = np.random.default_rng(seed)
    out = []
    for p in poses:
        if rng.random() < share:
            n = mirror_normals(p.position_mm[None], p.normal[None])[0]
            p = dataclasses.replace(p, normal=n)
        out.append(p)
    return out


def _in_true_frame(spec: UnitSpec, truth: UnitSpec) -> tuple[np.ndarray, list[int]]:
    """Rotation taking the learned frame onto the true one (by the learned codes' positions),
    and the learned codes."""
    codes = sorted(spec.positions_mm)
    R, _ = kabsch(
        np.array([spec.positions_mm[c] for c in codes]),
        np.array([truth.positions_mm[c] for c in codes]),
    )
    return R, codes


def test_learned_template_is_the_true_one_up_to_a_rigid_motion() -> None:
    """Every unit carries the dolos's codes; the baseline's units, 30 % of their normals on the
    wrong branch, give the faces' positions within 0.3 mm and their normals within 3 deg of the
    truth (in the learned frame, whose origin is the learned faces' centroid). The fourth
    fluke's face, which no unit shows before the run and the overturned ones show after it, is
    a hidden face."""
    field = make_field(300, seed=5)
    rng = np.random.default_rng(2)
    poses = _mirror_some(field.before.poses(rng), 0.3, 3)
    after = field.after.poses(rng)
    assert 41 not in {p.code for p in poses}
    assert sum(p.code == 41 for p in after) >= MIN_CODE_SEEN
    truth = dolos_geometry().unit_map(40.0).template
    assert truth is not None
    spec = learn_template(poses, 40.0, other_state=after)
    assert spec is not None
    assert set(spec.codes) == {3, 17, 29, 41} and spec.hidden == {41}
    assert set(spec.positions_mm) == {3, 17, 29} and set(spec.normals) == {3, 17, 29}
    learned = np.array([spec.positions_mm[c] for c in (3, 17, 29)])
    np.testing.assert_allclose(learned.mean(axis=0), 0.0, atol=1e-9)
    R, codes = _in_true_frame(spec, truth)
    true_pos = np.array([truth.positions_mm[c] for c in codes])
    placed = learned @ R.T
    placed += true_pos.mean(axis=0) - placed.mean(axis=0)
    assert np.max(np.linalg.norm(placed - true_pos, axis=1)) < 0.3
    for c in codes:
        n_true = truth.normals[c] / np.linalg.norm(truth.normals[c])
        angle = np.degrees(np.arccos(np.clip((R @ spec.normals[c]) @ n_true, -1.0, 1.0)))
        assert angle < 3.0, (c, angle)


def test_a_code_seen_beside_three_learned_ones_is_placed() -> None:
    """Units of a four-faced kind, most seen with three faces and some with all four: the
    fourth is placed by the three it is seen with."""
    rng = np.random.default_rng(1234)
    local = {1: [12.0, 0.0, 0.0], 2: [0.0, 14.0, 0.0], 3: [0.0, 0.0, 10.0], 4: [-9.0, -8.0, 3.0]}
    poses = []
    for k in range(30):
        R = rotation(rng.normal(size=3).tolist(), float(rng.uniform(0.0, 40.0)))
        centre = np.array([100.0 * (k % 6), 100.0 * (k // 6), 900.0])
        shown = (1, 2, 3, 4) if k % 3 == 0 else (1, 2, 3)
        for c in shown:
            p = centre + R @ np.asarray(local[c])
            poses.append(make_pose(c, p + rng.normal(0.0, 0.05, 3), sigma_z=0.1))
    spec = learn_template(poses, 30.0)
    assert spec is not None and set(spec.positions_mm) == {1, 2, 3, 4}
    codes = [1, 2, 3, 4]
    R, t = kabsch(
        np.array([spec.positions_mm[c] for c in codes]), np.array([local[c] for c in codes])
    )
    for c in codes:
        assert np.linalg.norm(R @ spec.positions_mm[c] + t - local[c]) < 0.2, c


@pytest.mark.parametrize("n_units", [0, 3])
def test_no_template_from_too_few_units(n_units: int) -> None:
    """Fewer units than :data:`MIN_LEARN_GROUPS`, or fiducials scattered at random, teach no
    template: None, and the matcher groups by code distances alone."""
    rng = np.random.default_rng(7)
    poses = [
        make_pose(int(c), rng.uniform([-200, -200, 800], [200, 200, 900]))
        for c in rng.choice([3, 17, 29], 60)
    ]
    truth = dolos_geometry()
    for k in range(n_units):
        centre = np.array([400.0 + 100.0 * k, 0.0, 850.0])
        poses += [make_pose(c, centre + truth.positions_mm[i]) for i, c in enumerate((3, 17, 29))]
    assert learn_template(poses, 40.0) is None


@pytest.mark.parametrize("hidden", [frozenset(), frozenset({41})])
def test_unknown_face_of_a_partial_template_still_tells_a_turn(hidden: frozenset[int]) -> None:
    """A learned template knows only the faces the baseline showed: a unit showing none of
    its old faces and one the template has no normal for is overturned, as without a
    template, and so it is when the template lists that face as hidden."""
    g = dolos_geometry()
    full = g.unit_map(40.0).template
    assert full is not None
    known = {c: full.positions_mm[c] for c in (3, 17, 29)}
    partial = UnitSpec("template", full.codes, known, {c: full.normals[c] for c in known}, hidden)
    R0 = np.diag([1.0, -1.0, -1.0])
    c0 = np.array([0.0, 0.0, 800.0])
    flip = R0 @ rotation([1.0, 0.0, 0.0], 180.0)
    c1 = c0 + np.array([8.0, 3.0, 0.0])

    before, after = facing_poses(g, R0, c0), facing_poses(g, flip, c1)
    assert {p.code for p in after} == {41}
    an = match_units(before, after, unit_map=UnitMap((), partial, 40.0), gate_mm=50.0)
    assert len(an.units) == 1 and an.units[0].overturned


def test_matching_without_a_map_learns_the_template_and_counts_better() -> None:
    """The paper's case, no unit map, on a 300-unit dolos field (simulated monocular pose
    noise, a third of the normals mirrored): the template is learned from the baseline, and
    against the truth it reports fewer still units displaced and fewer false and missed
    displaced units than grouping by the code distances alone (``learn=False``)."""
    from benchmarks.matcher_field import GATE_MM, poses_noisy

    field = make_field(300, seed=1, diameter_mm=10.0)
    base, cur, bid, _ = poses_noisy(field, 1)
    base, cur = _mirror_some(base, 0.3, 4), _mirror_some(cur, 0.3, 5)
    bid = np.asarray(bid)
    limits = thresholds(field.geometry.dn_mm)
    true_disp = {
        u
        for u in range(field.n_units)
        if field.overturned[u]
        or (
            field.moved[u]
            and np.linalg.norm(field.displacement_at(u, field.before.centres_mm[u]))
            >= limits.displaced_mm
        )
    }

    def score(learn: bool) -> tuple[int, int]:
        an = match_units(base, cur, gate_mm=GATE_MM, learn=learn)
        assert (an.learned_template is not None) == learn
        units, summary = assess(an.units, limits)
        still = wrong = 0
        reported = set()
        for u in units:
            if u.unit not in summary.displaced_ids:
                continue
            owners = field.before.unit[bid[list(u.baseline_indices)]]
            tu = int(np.bincount(owners).argmax())
            reported.add(tu)
            still += not (field.moved[tu] or field.overturned[tu])
        wrong = len(reported - true_disp) + len(true_disp - reported)
        return still, wrong

    learned, pairs = score(True), score(False)
    assert learned[0] <= pairs[0] and learned[1] <= pairs[1], (learned, pairs)
    assert learned[0] == 0, learned


def test_a_hidden_face_turns_a_one_faced_unit_over() -> None:
    """A unit seen through one face before, showing after only a face the template lists as
    hidden, turned over (without ``hidden`` one vanished face is too little evidence: lost)."""
    g = dolos_geometry()
    full = g.unit_map(40.0).template
    assert full is not None
    known = {c: full.positions_mm[c] for c in (3, 17, 29)}
    normals = {c: full.normals[c] for c in known}
    before = [make_pose(29, [0.0, 0.0, 800.0], normal=[0.0, 0.0, -1.0])]
    after = [make_pose(41, [9.0, 4.0, 806.0], normal=[0.0, 0.0, -1.0])]
    for hidden, turned in ((frozenset({41}), True), (frozenset(), False)):
        spec = UnitSpec("template", full.codes, known, normals, hidden)
        an = match_units(before, after, unit_map=UnitMap((), spec, 40.0), gate_mm=50.0)
        (unit,) = an.units
        assert unit.overturned is turned, hidden


def test_a_second_kind_of_unit_is_grouped_by_its_learned_distances() -> None:
    """Two kinds of units without a map: the commoner kind's template is learned, and the other
    kind, packed tighter than its own faces are apart, is still grouped by the distances
    between its codes learned from the baseline (by proximity alone its groups mix
    neighbours)."""
    from displacement_matcher.units import assign_units, group_fiducials

    rng = np.random.default_rng(1234)
    kind_a = {1: [12.0, 0.0, 0.0], 2: [0.0, 14.0, 0.0], 3: [0.0, 0.0, 10.0]}
    kind_b = {5: [0.0, 0.0, 0.0], 6: [26.0, 0.0, 0.0]}
    poses: list[FiducialPose] = []
    owner: list[int] = []
    for k in range(12):
        R = rotation(rng.normal(size=3).tolist(), float(rng.uniform(0.0, 40.0)))
        centre = np.array([100.0 * (k % 4), 100.0 * (k // 4), 900.0])
        for c, q in kind_a.items():
            poses.append(make_pose(c, centre + R @ np.asarray(q), sigma_z=0.1))
            owner.append(k)
    for k in range(30):
        # Kind B units strewn over a small patch, often nearer a neighbour's face than their own.
        centre = np.array([-300.0, 400.0, 900.0]) + rng.uniform(0.0, 160.0, 3) * [1, 1, 0.1]
        turn = rotation([0.0, 0.0, 1.0], float(rng.uniform(0.0, 360.0)))
        for c, q in kind_b.items():
            p = centre + turn @ (np.asarray(q) - [13.0, 0.0, 0.0])
            poses.append(make_pose(c, p + rng.normal(0.0, 0.05, 3)))
            owner.append(100 + k)
    spec = learn_template(poses, 40.0)
    assert spec is not None and set(spec.positions_mm) == {1, 2, 3}
    an = match_units(poses, poses, gate_mm=50.0, refine_passes=0)
    assert an.learned_template is not None
    groups = assign_units(an.result, unit_map=UnitMap((), an.learned_template, 40.0))[0]
    owners = np.array(owner)
    b_groups = [ix for _, ix in groups if owners[ix[0]] >= 100]
    pure = sum(len(set(owners[ix].tolist())) == 1 and len(ix) == 2 for ix in b_groups)
    assert pure >= 24, pure
    # By proximity alone (no distances) far fewer are.
    near = group_fiducials(poses, span_mm=40.0, template=an.learned_template)
    alone = sum(
        len(set(owners[g].tolist())) == 1 and len(g) == 2 for g in near if owners[g[0]] >= 100
    )
    assert alone < pure - 5, (alone, pure)


def test_a_code_read_twice_is_no_face_of_the_units() -> None:
    """A code the baseline reads only twice (partly covered fiducials misread) is left out of
    the learned template, so its fiducials belong to no unit rather than bridge two units'
    faces into one group."""
    field = make_field(120, seed=5)
    poses = field.before.poses(np.random.default_rng(2))
    shift = np.array([6.0, 0.0, 0.0])
    strays = [make_pose(0, poses[k].position_mm + shift) for k in (10, 40)]
    spec = learn_template([*poses, *strays], 40.0)
    assert spec is not None and 0 not in spec.codes
    an = match_units([*poses, *strays], poses, gate_mm=50.0, refine_passes=0)
    assert set(an.unassigned) == {len(poses), len(poses) + 1}


def test_a_template_of_codes_alone_is_learned_too() -> None:
    """A unit map whose template names the codes but not where they sit gets them learned from
    the baseline, restricted to its codes (a code outside them is no face of the units)."""
    field = make_field(120, seed=5)
    poses = field.before.poses(np.random.default_rng(2))
    codes_only = parse_unit_map({"template": {"codes": [3, 17, 29, 41]}})
    an = match_units(poses, poses, unit_map=codes_only, gate_mm=50.0, refine_passes=0)
    learned = an.learned_template
    assert learned is not None and learned.codes == (3, 17, 29, 41)
    assert set(learned.positions_mm) == {3, 17, 29}
    narrow = parse_unit_map({"template": {"codes": [3, 17]}})
    an2 = match_units(poses, poses, unit_map=narrow, gate_mm=50.0, refine_passes=0)
    assert an2.learned_template is None  # no code set of three to learn from
    placed = parse_unit_map({"template": {"codes": [3, 17], "positions_mm": {3: [0, 0, 0]}}})
    an3 = match_units(poses, poses, unit_map=placed, gate_mm=50.0, refine_passes=0)
    assert an3.learned_template is None  # positions given: the lab's template is used
