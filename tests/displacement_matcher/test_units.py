"""Unit maps, grouping and per-unit rigid motion against ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from matcher_synth import facing_poses, make_pose, rotation

from armourcam.field import dolos_geometry, make_field
from displacement_matcher import MatcherError, match
from displacement_matcher.refine import match_units
from displacement_matcher.rigid import kabsch, rigid_fit
from displacement_matcher.units import (
    APART_IN_DEPTH_MM,
    UnitSpec,
    group_fiducials,
    learn_pair_distances,
    load_unit_map,
    parse_unit_map,
    precise_depth,
    still_in_place,
    unit_motions,
)
from pose_estimator.fusion import moved_poses
from pose_estimator.types import FiducialPose


@pytest.mark.parametrize("deg", [0.0, 5.0, 25.0, 60.0])
def test_kabsch_and_rigid_fit_recover_motion(deg: float) -> None:
    """Weighted Kabsch (points) and the normal-aided fit recover a known rigid motion."""
    rng = np.random.default_rng(1234)
    R = rotation([1.0, 2.0, -0.5], deg)
    t = np.array([3.0, -7.0, 11.0])
    src = rng.normal(0, 15, (5, 3))
    dst = src @ R.T + t
    R1, t1 = kabsch(src, dst, np.ones(5))
    np.testing.assert_allclose(R1, R, atol=1e-9)
    np.testing.assert_allclose(t1, t, atol=1e-9)
    # Two points plus their normals fix the rotation too.
    n = rng.normal(size=(2, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    R2, t2 = rigid_fit(src[:2], dst[:2], np.ones(2), n, n @ R.T)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)


def test_unit_motion_matches_ground_truth_on_a_field() -> None:
    """Per-unit displacement (at the reported reference point) agrees with the truth.

    On an unsettled field seen without occlusion (every rendered fiducial posed): the matcher's
    accuracy where each unit's evidence is whole. Stacked units and occlusion are measured by
    ``benchmarks/matcher_field.py``.
    """
    field = make_field(
        60, seed=3, moved_fraction=0.2, overturned_fraction=0.0, hidden_fraction=0, settle=False
    )
    rng = np.random.default_rng(7)
    base = field.before.poses(rng, sigma_xy_mm=0.05, sigma_z_mm=0.3, include_occluded=True)
    cur = field.after.poses(rng, sigma_xy_mm=0.05, sigma_z_mm=0.3, include_occluded=True)
    bid = field.before.visible_ids
    an = match_units(base, cur, unit_map=dolos_geometry().unit_map(40.0), gate_mm=50.0)
    measured = 0
    for u in an.units:
        owners = field.before.unit[bid[list(u.baseline_indices)]]
        assert np.all(owners == owners[0]), f"{u.unit} mixes units {set(owners.tolist())}"
        if u.method == "none":
            continue
        truth = field.displacement_at(int(owners[0]), u.reference_before_mm)
        tol = 1.5 if u.method == "rigid" else 6.0  # translation-only ignores the rotation
        np.testing.assert_allclose(u.translation_mm, truth, atol=tol, err_msg=u.unit)
        if not field.moved[owners[0]]:
            assert u.distance_mm < 2.0  # noise only (sigma_z 0.3 mm per state)
        measured += 1
    assert measured >= 55


def test_overturned_unit_is_flagged() -> None:
    """Fiducials seen before face away after, the opposite face shows: overturned."""
    g = dolos_geometry()
    umap = dolos_geometry().unit_map(40.0)
    R0 = np.diag([1.0, -1.0, -1.0])  # local z towards the camera
    c0 = np.array([0.0, 0.0, 800.0])
    flip = R0 @ rotation([1.0, 0.0, 0.0], 180.0)  # about the shank (local x)
    c1 = c0 + np.array([8.0, 3.0, 0.0])

    before, after = facing_poses(g, R0, c0), facing_poses(g, flip, c1)
    assert {p.code for p in before} == {3, 17, 29} and {p.code for p in after} == {41}
    an = match_units(before, after, unit_map=umap, gate_mm=50.0)
    assert len(an.units) == 1 and an.units[0].overturned
    # A still unit is not.
    an2 = match_units(before, facing_poses(g, R0, c0), unit_map=umap, gate_mm=50.0)
    assert not an2.units[0].overturned and an2.units[0].distance_mm < 1e-6


def test_grouping_separates_interlocked_units() -> None:
    """With the template's positions and normals every group is one true unit."""
    field = make_field(120, seed=5)
    poses = field.before.poses(np.random.default_rng(2))
    groups = group_fiducials(poses, span_mm=40.0, template=dolos_geometry().unit_map(40.0).template)
    owners = field.before.unit[field.before.observable_ids]
    assert sum(len(g) for g in groups) == len(poses)
    pure = sum(len(set(owners[g].tolist())) == 1 for g in groups)
    assert pure == len(groups)
    assert len(groups) <= len(set(owners.tolist())) + 3


def test_grouping_joins_template_placed_pairs_before_unchecked_ones() -> None:
    """A learned template places no hidden-code face, and the baseline shows too few to learn a
    distance for it: a pair with such a face is checked by the span alone and scores as a
    perfect fit. It must not take a unit's face from the unit's own face the template places
    with it (noisy-pose field, seed 17: a mover's code-29 face joined a neighbour's code-41
    face, leaving its code-3 face alone, and the mover lost its group)."""
    spec = UnitSpec(
        "template",
        (3, 29, 41),
        {3: np.array([0.0, 0.0, 0.0]), 29: np.array([28.0, 0.0, 0.0])},
        {},
        frozenset({41}),
    )
    poses = [
        make_pose(3, [0.0, 0.0, 600.0]),
        make_pose(29, [28.8, 0.0, 600.0]),  # the template's 28 mm, 0.8 mm off
        # 25 mm from the code-29 face, beyond the span from the code-3 one.
        make_pose(41, [53.8, 0.0, 600.0]),
    ]
    assert group_fiducials(poses, span_mm=40.0, template=spec) == [[0, 1], [2]]


def test_automatic_grouping_learns_the_units_code_distances() -> None:
    """Without a unit map, every unit carrying the same codes: the distances between a unit's
    codes are the same on every unit, so they are learned from the state itself (to within a
    few tenths of a millimetre of the template's), and grouping by them keeps most groups to
    one true unit, where proximity alone joins neighbours' nearer fiducials (under half pure)."""
    field = make_field(120, seed=5)
    poses = field.before.poses(np.random.default_rng(2))
    owners = field.before.unit[field.before.observable_ids]
    template = dolos_geometry().unit_map(40.0).template
    assert template is not None
    learned = learn_pair_distances(poses, 40.0)
    assert {(3, 17), (3, 29), (17, 29)} <= set(learned)
    for (a, b), d in learned.items():
        true = float(np.linalg.norm(template.positions_mm[a] - template.positions_mm[b]))
        assert abs(d - true) < 0.5, (a, b, d, true)
        assert learned[(b, a)] == d

    def purity(groups: list[list[int]]) -> float:
        return sum(len(set(owners[g].tolist())) == 1 for g in groups) / len(groups)

    plain = group_fiducials(poses, span_mm=40.0)
    grouped = group_fiducials(poses, span_mm=40.0, pair_distances=learned)
    assert purity(plain) < 0.5
    assert purity(grouped) > 0.8, purity(grouped)
    # match_units learns them itself when no unit map is given.
    an = match_units(poses, poses, gate_mm=50.0)
    members = [list(u.baseline_indices) for u in an.units if u.baseline_indices]
    assert purity(members) > 0.8


def test_no_distance_is_learned_without_a_repeated_unit() -> None:
    """Scattered fiducials (no unit repeats) show no spike among their distances: nothing is
    learned, and grouping falls back to proximity."""
    rng = np.random.default_rng(3)
    poses = [
        FiducialPose(
            int(c),
            np.array([*rng.uniform(-150, 150, 2), 800.0]),
            np.array([0, 0, -1.0]),
            np.eye(3) * 0.01,
        )
        for c in rng.choice([3, 17, 29], 120)
    ]
    assert learn_pair_distances(poses, 40.0) == {}


def test_explicit_unit_map_and_unknown_codes(tmp_path: pytest.TempPathFactory) -> None:
    """Explicit units by code; unmapped codes reported as unassigned; unseen units reported."""
    path = tmp_path / "units.yaml"  # type: ignore[operator]
    path.write_text("units:\n  A: {codes: [1, 2]}\n  B: {codes: [5]}\n  C: {codes: [9]}\n")
    umap = load_unit_map(path)
    base = [
        FiducialPose(1, np.array([0.0, 0, 800]), np.array([0, 0, -1.0]), np.eye(3) * 0.01),
        FiducialPose(2, np.array([20.0, 0, 800]), np.array([0, 0, -1.0]), np.eye(3) * 0.01),
        FiducialPose(5, np.array([90.0, 0, 800]), np.array([0, 0, -1.0]), np.eye(3) * 0.01),
        FiducialPose(7, np.array([150.0, 0, 800]), np.array([0, 0, -1.0]), np.eye(3) * 0.01),
    ]
    cur = [
        FiducialPose(p.code, p.position_mm + np.array([2.0, 0, 0]), p.normal, p.covariance_mm2)
        for p in base[:2]
    ] + [base[2]]
    units, unassigned = unit_motions(match(base, cur), unit_map=umap)
    by = {u.unit: u for u in units}
    np.testing.assert_allclose(by["A"].translation_mm, [2.0, 0, 0], atol=1e-9)
    assert by["B"].distance_mm == pytest.approx(0.0)
    assert by["C"].status == "unseen" and not by["C"].baseline_indices
    assert unassigned == (3,)


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"units": {"A": {"codes": [999]}}}, "unknown code 999"),
        ({"units": {"A": {"codes": [1]}, "B": {"codes": [1]}}}, "code 1 is on units"),
        ({"units": {"A": {"codes": "x"}}}, "codes must be a non-empty list"),
        ({"units": {"A": {"codes": [1], "positions_mm": {2: [0, 0, 0]}}}}, "not in"),
        ({"template": {"codes": [1, 2], "normals": {1: [0, 0, 0]}}}, "zero or not finite"),
        ({"units": {}, "template": {"codes": [1]}}, "exactly one of"),
        ([1, 2], "must be a mapping"),
        ({"units": {"A": {"codes": [1], "colour": "red"}}}, "unknown keys"),
        # YAML keeps the keys 1 and "1" apart; every output names units by their string.
        ({"units": {1: {"codes": [1]}, "1": {"codes": [2]}}}, "unit id '1' is given twice"),
        ({"template": {"codes": [1, 2], "span_mm": [1, 2]}}, "span_mm must be a length"),
        ({"template": {"codes": [1, 2], "span_mm": "abc"}}, "span_mm must be a length"),
        ({"template": {"codes": [1, 2], "span_mm": float("nan")}}, "positive length"),
        ({"template": {"codes": [1, 2], "span_mm": -5}}, "positive length"),
        ({"template": {"codes": [1, 2], "hidden": [3]}}, r"hidden codes \[3\] not in"),
        ({"template": {"codes": [1, 2], "hidden": "2"}}, "codes must be a non-empty list"),
    ],
)
def test_bad_unit_maps_raise_clear_errors(doc: object, message: str) -> None:
    """Malformed unit maps name what is wrong."""
    with pytest.raises(MatcherError, match=message):
        parse_unit_map(doc)


def test_template_hidden_faces_are_read() -> None:
    """A template's ``hidden`` faces (what a learned template's report lists) are read back."""
    umap = parse_unit_map({"template": {"codes": [3, 17, 29, 41], "hidden": [41]}})
    assert umap.template is not None and umap.template.hidden == {41}


def test_unreadable_unit_map_file(tmp_path: pytest.TempPathFactory) -> None:
    """A missing or non-YAML file raises MatcherError naming the file."""
    with pytest.raises(MatcherError, match="cannot read unit map"):
        load_unit_map(tmp_path / "missing.yaml")  # type: ignore[operator]
    bad = tmp_path / "bad.yaml"  # type: ignore[operator]
    bad.write_text("units: [\n")
    with pytest.raises(MatcherError, match="cannot read unit map"):
        load_unit_map(bad)


def test_units_with_empty_and_nan_inputs() -> None:
    """Empty sets and NaN poses give empty or lost units, never a crash."""
    assert match_units([], []).units == ()
    nan = FiducialPose(3, np.full(3, np.nan), np.array([0, 0, -1.0]), np.eye(3))
    ok = FiducialPose(3, np.array([0.0, 0, 800]), np.array([0, 0, -1.0]), np.eye(3) * 0.01)
    an = match_units([nan, ok], [])
    assert [u.status for u in an.units] == ["lost"]
    assert an.units[0].baseline_indices == (1,)
    assert [r.index for r in an.result.rejected] == [0]


def test_a_unit_given_twice_in_a_map_is_an_error(tmp_path: pytest.TempPathFactory) -> None:
    """A copied block with the id left unchanged would silently drop the first unit."""
    path = tmp_path / "units.yaml"  # type: ignore[operator]
    path.write_text("units:\n  U00: {codes: [0, 1, 2]}\n  U00: {codes: [3, 4, 5]}\n")
    with pytest.raises(
        MatcherError, match=r"line 3, column 3: key 'U00' given twice \(first at line 2\)"
    ):
        load_unit_map(path)


def test_a_mapped_unit_thrown_far_is_displaced_and_the_gate_follows_dn() -> None:
    """With a unit map (codes printed once) a unit thrown 4 Dn is measured, not lost; without
    one, the gate grows with Dn (a 45 mm unit moved 1.5 Dn is matched)."""
    from displacement_matcher.compare import compare_poses
    from displacement_matcher.damage import thresholds
    from displacement_matcher.units import parse_unit_map

    nrm = np.array([0.0, 0.0, -1.0])
    cov = np.eye(3) * 0.01
    base = [FiducialPose(c, np.array([40.0 * c, 0.0, 800.0]), nrm, cov) for c in range(6)]
    throw = np.array([0.0, 82.0, 0.0])  # 4 Dn of 20.5 mm
    cur = [
        FiducialPose(p.code, p.position_mm + (throw if p.code < 2 else 0.0), nrm, cov) for p in base
    ]
    umap = parse_unit_map({"units": {f"U{k}": {"codes": [2 * k, 2 * k + 1]} for k in range(3)}})
    a = compare_poses(base, cur, thresholds(20.5), unit_map=umap)
    by = {u.unit: u for u in a.units}
    assert by["U0"].status == "displaced"
    np.testing.assert_allclose(by["U0"].translation_mm, throw, atol=1e-6)
    assert a.summary.displaced_units == 1

    move = np.array([0.0, 67.5, 0.0])  # 1.5 Dn of 45 mm: beyond 50 mm, within 2.4 Dn
    cur = [
        FiducialPose(p.code, p.position_mm + (move if p.code < 2 else 0.0), nrm, cov) for p in base
    ]
    small = compare_poses(base, cur, thresholds(20.5))
    large = compare_poses(base, cur, thresholds(45.0))
    assert small.result.params.gate_mm == 50.0 and large.result.params.gate_mm == 108.0
    assert large.summary.displaced_units == 1
    assert small.summary.displaced_units == 0


def test_an_explicit_unit_with_positions_moves_at_its_own_origin() -> None:
    """An explicit unit map that gives a unit's fiducial positions: its motion is reported at
    the unit's origin (where the positions are measured from), as a template's is, not at its
    fiducials' centroid, which a turn of the unit moves differently. The unit rocks 30 deg:
    its three points fix the turn, and each normal's branch is the one that turn carries it to
    (the smallest-turn choice took every mirror, a couple of degrees nearer, and reversed the
    fitted turn)."""
    local = {
        1: np.array([20.0, 0.0, 0.0]),
        2: np.array([0.0, 20.0, 0.0]),
        3: np.array([20.0, 20.0, 5.0]),
    }
    umap = parse_unit_map(
        {
            "units": {
                "A": {"codes": [1, 2, 3], "positions_mm": {c: p.tolist() for c, p in local.items()}}
            }
        }
    )
    origin = np.array([10.0, -5.0, 600.0])
    turn = rotation([1.0, 0.2, 0.0], 30.0)  # rocking: the faces turn with it
    shift = np.array([6.0, -2.0, 1.0])

    def poses(R: np.ndarray, t: np.ndarray) -> list[FiducialPose]:
        cov = np.diag([0.01, 0.01, 0.04])
        return [
            FiducialPose(c, R @ p + t, R @ np.array([0.0, 0.0, -1.0]), cov)
            for c, p in local.items()
        ]

    an = match_units(
        poses(np.eye(3), origin), poses(turn, origin + shift), unit_map=umap, gate_mm=50.0
    )
    (unit,) = an.units
    assert unit.method == "rigid" and unit.n_matched == 3
    assert unit.rotation_deg is not None and abs(unit.rotation_deg - 30.0) < 1e-6
    np.testing.assert_allclose(unit.rotation, turn, atol=1e-9)
    np.testing.assert_allclose(unit.reference_before_mm, origin, atol=1e-6)
    np.testing.assert_allclose(unit.translation_mm, shift, atol=1e-6)


def test_a_cube_spinning_about_its_face_normal_is_fitted_rigidly() -> None:
    """Three fiducials on one flat face (a cube's): their normals do not turn when the unit
    spins about them, so the turn of the normals cannot bound that spin. A 40 deg spin in place
    is fitted as one rigid motion of all three, not left to a translation of one."""
    local = {
        1: np.array([-8.0, -6.0, 10.0]),
        2: np.array([8.0, -6.0, 10.0]),
        3: np.array([0.0, 8.0, 10.0]),
    }
    spec = {c: p.tolist() for c, p in local.items()}
    umap = parse_unit_map({"units": {"C": {"codes": [1, 2, 3], "positions_mm": spec}}})
    origin = np.array([-20.0, 10.0, 700.0])
    spin = rotation([0.0, 0.0, 1.0], 40.0)
    shift = np.array([2.0, 1.0, 0.0])
    face = np.array([0.0, 0.0, -1.0])  # the face looks at the camera
    cov = np.diag([0.01, 0.01, 0.09])  # the spin about z leaves it as it is
    faces = [FiducialPose(c, p, face, cov) for c, p in local.items()]

    an = match_units(
        moved_poses(faces, np.eye(3), origin),
        moved_poses(faces, spin, origin + shift),
        unit_map=umap,
        gate_mm=50.0,
    )
    (unit,) = an.units
    assert unit.method == "rigid" and unit.n_matched == 3, (unit.method, unit.n_matched)
    assert unit.rotation_deg is not None and abs(unit.rotation_deg - 40.0) < 1e-6
    np.testing.assert_allclose(unit.translation_mm, shift, atol=1e-6)


def test_without_a_map_still_faces_keep_their_partners_in_mixed_groups() -> None:
    """Learned distances leave some groups joining two neighbours' faces; the unit-aware rules,
    judging pairs by the units they join, then left still faces of such groups vanished (4 on
    this field, where the plain global matching got them all). A face still seen where it was
    keeps its partner."""
    from benchmarks.matcher_field import poses_noisy

    field = make_field(300, seed=1, diameter_mm=10.0)
    base, cur, bid, cid = poses_noisy(field, 1)
    partner = {int(f): k for k, f in enumerate(np.asarray(cid).tolist())}
    an = match_units(base, cur, gate_mm=50.0)
    still = ~(field.moved | field.overturned)
    wrong = []
    for d in an.result.displacements:
        if d.baseline_index is None:
            continue
        f = int(np.asarray(bid)[d.baseline_index])
        seen = field.before.observable[f] and field.after.observable[f]
        if still[field.before.unit[f]] and seen and partner.get(f) != d.current_index:
            wrong.append((f, d.label))
    assert not wrong, wrong


def test_passes_that_cycle_end_the_same_whatever_the_pass_limit() -> None:
    """On this field two units take the same two faces in turn, pass after pass (one through
    two cross-code pairs, 40 mm off its true motion): with a fixed number of passes the result
    followed that number's parity. The pairs the cycle does not agree on are ruled out, the
    result no longer depends on the limit, and no unit is measured through them."""
    from benchmarks.matcher_field import poses_noisy

    field = make_field(300, seed=1, diameter_mm=10.0)
    base, cur, bid, cid = poses_noisy(field, 1)
    umap = field.geometry.unit_map()
    runs = [match_units(base, cur, unit_map=umap, gate_mm=50.0, refine_passes=n) for n in (7, 8)]
    made = [set(map(tuple, an.result.pairs().tolist())) for an in runs]
    assert made[0] == made[1]
    bid, cid = np.asarray(bid), np.asarray(cid)
    for u in runs[1].units:
        if u.method == "none" or not u.current_indices:
            continue
        owners = set(field.before.unit[bid[list(u.baseline_indices)]].tolist())
        now = set(field.after.unit[cid[list(u.current_indices)]].tolist())
        if len(owners) == 1 and not (now - owners):
            (tu,) = owners
            if not field.overturned[tu]:
                err = u.translation_mm - field.displacement_at(tu, u.reference_before_mm)
                assert np.linalg.norm(err) < 20.0, (u.unit, err)


def _on_ray(code: int, depth_mm: float, across_mm: float, sd_mm: float) -> FiducialPose:
    """A pose of ``code`` at ``depth_mm`` along a fixed line of sight, ``across_mm`` off it, with
    a depth sd ``sd_mm`` along its own line of sight (0.1 mm across)."""
    ray = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    side = np.cross(ray, [0.0, 1.0, 0.0])
    p = depth_mm * ray + across_mm * side / np.linalg.norm(side)
    return make_pose(code, p, 0.1, sd_mm, normal=-p / np.linalg.norm(p))


def test_precise_depth_is_relative_to_the_median_claim() -> None:
    """Poses claiming a depth sd within 1.6 times the set's median are precise; a NaN claim is
    not, and the empty set gives an empty answer."""
    sds = [0.4, 0.45, 0.5, 0.7, 0.8, 2.0]
    poses = [_on_ray(3, 1700.0 + 30.0 * k, 0.0, sd) for k, sd in enumerate(sds)]
    nan = FiducialPose(
        3, np.array([0.0, 0.0, 1700.0]), np.array([0.0, 0.0, -1.0]), np.full((3, 3), np.nan)
    )
    np.testing.assert_array_equal(precise_depth(poses), [True] * 5 + [False])
    assert precise_depth([*poses, nan]).tolist() == [True] * 5 + [False, False]
    assert precise_depth([]).shape == (0,)


@pytest.mark.parametrize("now_sd", [0.5, 1.5])
@pytest.mark.parametrize("nearer_mm", [5.0, 24.0])
def test_face_in_place_across_the_line_of_sight_but_far_nearer_is_another(
    nearer_mm: float, now_sd: float
) -> None:
    """A face of the same code 1 mm off across the line of sight is seen again in place, unless
    it lies more than 12 mm nearer and both poses claim a precise depth (another unit's face
    come to rest in front); a pose claiming three times the others' sd keeps the lateral rule
    (a partly covered fiducial's depth may be centimetres off)."""
    base = [_on_ray(17, 1700.0, 0.0, 0.5), _on_ray(3, 1720.0, 40.0, 0.5)]
    cur = [_on_ray(3, 1720.0, 40.0, 0.5), _on_ray(17, 1700.0 - nearer_mm, 1.0, now_sd)]
    shown = still_in_place(base, cur)
    assert shown[1] == 0
    apart = nearer_mm > APART_IN_DEPTH_MM and now_sd < 1.0
    assert (0 in shown) is not apart
    if not apart:
        assert shown[0] == 1
