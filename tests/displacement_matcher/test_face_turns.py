"""A fiducial's printed axis in the matcher: how a face turned, spin included, and what that
tells about its unit (:func:`displacement_matcher.units.face_turn` and the rules built on it).

Poses carry their printed +x axis (``FiducialPose.axis``, read from the code): one fiducial seen
in two states then gives the whole rotation of its unit. The axes here are glued at a different
spin on every unit, as a lab glues them by hand: nothing relies on the same code sitting the
same way on two units.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from matcher_synth import realistic_cov, rotation

from armourcam.field import dolos_geometry
from displacement_matcher.damage import assess, thresholds
from displacement_matcher.match import match
from displacement_matcher.refine import _merge_fragments, match_units
from displacement_matcher.units import (
    FRAMES_APART_DEG,
    MAX_FACE_TURN_DEG,
    face_turn,
    frames_apart,
    mirror_normals,
    one_body,
    still_in_place,
    turn_from_frames,
)
from pose_estimator.orientation import mirror_axes
from pose_estimator.types import FiducialPose

GEO = dolos_geometry()
UMAP = GEO.unit_map()
R0 = np.diag([1.0, -1.0, -1.0])  # local z towards the camera, which looks along +z


def _glued_axes(rng: np.random.Generator) -> np.ndarray:
    """Each slot's printed +x axis on one unit (unit frame): in the face's plane, at a random
    spin (glued by hand)."""
    out = []
    for n in GEO.normals:
        a = np.cross(n, rng.normal(size=3))
        out.append(a / np.linalg.norm(a))
    return np.array(out)


def _unit(
    centre: np.ndarray, R: np.ndarray, axes: np.ndarray, codes: tuple[int, ...] | None = None
) -> list[FiducialPose]:
    """Exact poses, axes included, of a dolos' camera-facing fiducials (of ``codes`` only, when
    given); depth sd 1 mm claimed."""
    out = []
    for k, code in enumerate(GEO.codes):
        p = centre + R @ GEO.positions_mm[k]
        n = R @ GEO.normals[k]
        if n @ (-p / np.linalg.norm(p)) > 0.3 and (codes is None or code in codes):
            out.append(FiducialPose(code, p, n, realistic_cov(p, 0.1, 1.0), axis=R @ axes[k]))
    return out


def _mirrored(pose: FiducialPose) -> FiducialPose:
    """The pose on the other branch of the circle's ambiguity: mirrored normal, its axis."""
    p = pose.position_mm[None]
    n = mirror_normals(p, pose.normal[None])
    assert pose.axis is not None
    return replace(pose, normal=n[0], axis=mirror_axes(p, pose.axis[None], n)[0])


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


@pytest.mark.parametrize("seed", range(5))
def test_a_faces_turn_is_its_units_rotation_on_its_true_branches(seed: int) -> None:
    """The four branch combinations hold the unit's rotation where each pose lies: [0][0] for
    poses on their true branches, [1][0] for a before pose on its mirror; a spin about the
    face's normal, which the normal alone does not see, included."""
    rng = np.random.default_rng(seed)
    axes = _glued_axes(rng)
    turn = rotation(list(rng.normal(size=3)), rng.uniform(5.0, 40.0))
    before = _unit(np.array([30.0, -20.0, 1500.0]), R0, axes)[0]
    after = _unit(np.array([45.0, -10.0, 1490.0]), turn @ R0, axes, (before.code,))[0]
    turned = face_turn(before, after)
    assert turned is not None
    rotations, angles = turned
    assert _angle_deg(rotations[0][0] @ turn.T) < 1e-4
    assert angles[0][0] == pytest.approx(_angle_deg(turn), abs=1e-4)
    flipped = face_turn(_mirrored(before), after)
    assert flipped is not None
    assert _angle_deg(flipped[0][1][0] @ turn.T) < 1e-4
    # A spin alone: the normal does not move, the frames do.
    n = before.normal
    spin = rotation(list(n), 30.0)
    spun = replace(before, normal=spin @ n, axis=spin @ before.axis)
    spun_turn = face_turn(before, spun)
    assert spun_turn is not None and spun_turn[1][0][0] == pytest.approx(30.0, abs=1e-4)
    assert face_turn(replace(before, axis=None), after) is None


def test_turn_from_frames_averages_pairs_and_refuses_disagreement() -> None:
    """Two faces of one unit give its rotation; a stranger's face among them, turned otherwise,
    leaves the turn to the fit on positions and normals (None)."""
    rng = np.random.default_rng(3)
    axes = _glued_axes(rng)
    turn = rotation([0.3, -0.2, 1.0], 25.0)
    before = _unit(np.array([0.0, 0.0, 1600.0]), R0, axes)
    after = _unit(np.array([12.0, 8.0, 1590.0]), turn @ R0, axes)
    assert [p.code for p in before] == [p.code for p in after]
    nb = np.array([p.normal for p in before])
    na = np.array([p.normal for p in after])
    R = turn_from_frames(before, after, nb, na)
    assert R is not None and _angle_deg(R @ turn.T) < 1e-4
    stranger = replace(after[1], axis=rotation(list(after[1].normal), 40.0) @ after[1].axis)
    assert turn_from_frames(before, [after[0], stranger, *after[2:]], nb, na) is None


def test_one_face_measures_its_unit_at_the_origin_with_the_spin_it_turned() -> None:
    """A unit seen through three faces before and one after, which turned 25 deg about that
    face's own normal and moved 14 mm: its origin's displacement, measured through the one
    pair, is the truth to a fraction of a millimetre, and so is its turn. Without the axes the
    spin is not seen and the origin lands millimetres off."""
    rng = np.random.default_rng(11)
    axes = _glued_axes(rng)
    centre = np.array([20.0, 10.0, 1700.0])
    before = _unit(centre, R0, axes)
    code = 29
    k = GEO.codes.index(code)
    spin = rotation(list(R0 @ GEO.normals[k]), 25.0)
    R1 = spin @ R0
    # The face's own point stays on the spin's axis; the unit also moves across the view.
    shift = np.array([14.0, 0.0, 0.0])
    face = centre + R0 @ GEO.positions_mm[k]
    centre1 = spin @ (centre - face) + face + shift
    after = _unit(centre1, R1, axes, (code,))
    assert len(before) == 3 and len(after) == 1
    truth = centre1 - centre
    an = match_units(before, after, unit_map=UMAP, gate_mm=50.0)
    (unit,) = an.units
    assert unit.n_matched == 1
    np.testing.assert_allclose(unit.translation_mm, truth, atol=0.2)
    assert unit.rotation_deg == pytest.approx(25.0, abs=0.5)
    blind = match_units(
        [replace(p, axis=None) for p in before],
        [replace(p, axis=None) for p in after],
        unit_map=UMAP,
        gate_mm=50.0,
    )
    assert float(np.linalg.norm(blind.units[0].translation_mm - truth)) > 2.0


def test_a_still_units_hidden_face_takes_no_strangers_face_turned_away() -> None:
    """A still unit seen through one face, hidden after the run; a neighbour, glued and lying
    otherwise, shows a face of the same code 12 mm from the still unit's old face (it showed it
    before too, 32 mm further on: it moved). That pair would measure the still unit 12 mm off
    and is the cheaper: but the face turned 70 deg, so it is ruled out and the still unit is
    lost, not moved. (The neighbour's own lone face 32 mm on is not looked for that far: a lone
    face is weak evidence, and the count is left without either.)"""
    rng = np.random.default_rng(5)
    still_axes, other_axes = _glued_axes(rng), _glued_axes(rng)
    centre = np.array([0.0, 0.0, 1700.0])
    still = _unit(centre, R0, still_axes, (29,))
    k = GEO.codes.index(29)
    old_face = centre + R0 @ GEO.positions_mm[k]
    R_other = rotation([0.0, 0.0, 1.0], 70.0) @ R0
    # The neighbour's code-29 face lies 12 mm across from the still one's after the run.
    centre_after = old_face + np.array([12.0, 0.0, 0.0]) - R_other @ GEO.positions_mm[k]
    centre_before = centre_after + np.array([0.0, -32.0, 0.0])
    other_before = _unit(centre_before, R_other, other_axes, (29,))
    other_after = _unit(centre_after, R_other, other_axes, (29,))
    assert len(still) == len(other_before) == len(other_after) == 1
    an = match_units(still + other_before, other_after, unit_map=UMAP, gate_mm=50.0)
    units, summary = assess(an.units, thresholds(GEO.dn_mm))
    assert (0, 0) not in an.result.pairs().tolist()
    assert next(u for u in units if 0 in u.baseline_indices).status == "lost"
    assert summary.displaced_units == 0 and summary.moved_units == 0
    # Without the axes the stranger's pair stands (the test's premise).
    blind = match_units(
        [replace(p, axis=None) for p in still + other_before],
        [replace(p, axis=None) for p in other_after],
        unit_map=UMAP,
        gate_mm=50.0,
    )
    assert dict(blind.result.pairs().tolist()) == {0: 0}
    blind_units, _ = assess(blind.units, thresholds(GEO.dn_mm))
    assert next(u for u in blind_units if 0 in u.baseline_indices).status == "moved"


def _moved_unit(seed: int) -> tuple[np.random.Generator, list[FiducialPose], list[FiducialPose]]:
    """A dolos's three camera-facing faces before and after a move and a turn of up to 30 deg
    (axes glued at random spins), with the generator for what a test draws next."""
    rng = np.random.default_rng(seed)
    axes = _glued_axes(rng)
    turn = rotation(list(rng.normal(size=3)), rng.uniform(0.0, 30.0))
    before = _unit(np.array([10.0, 0.0, 1600.0]), R0, axes)
    after = _unit(np.array([40.0, 15.0, 1580.0]), turn @ R0, axes)
    assert [p.code for p in before] == [p.code for p in after] and len(before) == 3
    return rng, before, after


def _strangers_face(pose: FiducialPose, rng: np.random.Generator) -> FiducialPose:
    """A neighbour's face of ``pose``'s code come to rest in its place: glued at another spin,
    more than :data:`FRAMES_APART_DEG` off."""
    assert pose.axis is not None
    glue = rng.uniform(FRAMES_APART_DEG + 10.0, 360.0 - FRAMES_APART_DEG - 10.0)
    return replace(pose, axis=rotation(list(pose.normal), glue) @ pose.axis)


@pytest.mark.parametrize("seed", range(4))
def test_one_body_keeps_a_units_faces_and_drops_a_strangers(seed: int) -> None:
    """Three faces of one unit turned with it (poses on either branch of the circle's
    ambiguity) lie within a reading's error of each other's turn; a neighbour's face of one of
    their codes, glued at another spin, put in place of one of them, is apart by the spins'
    difference, and the largest agreeing set is the unit's other faces."""
    rng, before, after = _moved_unit(seed)
    after[0] = _mirrored(after[0])  # a pose on its mirrored branch still agrees
    apart = frames_apart(before, after)
    assert apart.shape == (3, 3) and np.max(apart) < 1e-4
    assert one_body(apart) == (0, 1, 2)
    # A neighbour's face of the second code come to rest there: glued at another spin.
    mixed = [after[0], _strangers_face(after[1], rng), after[2]]
    apart = frames_apart(before, mixed)
    assert apart[0, 1] > FRAMES_APART_DEG and apart[1, 2] > FRAMES_APART_DEG
    assert one_body(apart) == (0, 2)
    # Without axes no pair is apart from another.
    blind = frames_apart([replace(p, axis=None) for p in before], mixed)
    assert not blind.any() and one_body(blind) == (0, 1, 2)


@pytest.mark.parametrize("seed", range(4))
def test_fragments_merge_only_through_faces_turned_alike(seed: int) -> None:
    """A baseline unit split in two fragments (one face's depth far off) is merged again where
    one current unit holds partners of both (:func:`displacement_matcher.refine.
    _merge_fragments`), but not where one of those pairs is a stranger's: a neighbour's face of
    that code glued at another spin turned otherwise than the rest of the group's."""
    rng, before, after = _moved_unit(seed)
    fragments = [("U1", [0]), ("U2", [1, 2])]
    whole = _merge_fragments(match(before, after, gate_mm=50.0), fragments, [[0, 1, 2]], 45.0)
    assert whole == [("U1", [0, 1, 2])]
    mixed = match(before, [_strangers_face(after[0], rng), *after[1:]], gate_mm=50.0)
    assert _merge_fragments(mixed, fragments, [[0, 1, 2]], 45.0) is None


def test_one_body_of_pairs_that_all_disagree_is_one_pair() -> None:
    apart = np.array([[0.0, 80.0, 60.0], [80.0, 0.0, 100.0], [60.0, 100.0, 0.0]])
    assert len(one_body(apart)) == 1
    assert one_body(np.zeros((0, 0))) == ()


def test_one_body_of_many_faces_is_found_greedily_as_exhaustively() -> None:
    """Twelve pairs (beyond the exhaustive search): nine that agree and three strangers, each
    apart from every other pair."""
    n = 12
    apart = np.full((n, n), 90.0)
    body = [0, 1, 2, 4, 5, 7, 8, 10, 11]
    for a in body:
        for b in body:
            apart[a, b] = 1.0
    np.fill_diagonal(apart, 0.0)
    assert one_body(apart) == tuple(body)


def test_a_face_in_place_turned_away_is_not_the_same_face() -> None:
    """A face of the same code seen within a millimetre of where a face was is that face seen
    again only if it turned no more than a partly covered reading can be off
    (:data:`MAX_FACE_TURN_DEG`): a neighbour's face come to rest there sits at its own glue
    spin."""
    rng = np.random.default_rng(7)
    axes = _glued_axes(rng)
    before = _unit(np.array([0.0, 0.0, 1500.0]), R0, axes, (29,))
    again = [replace(before[0], position_mm=before[0].position_mm + np.array([0.3, 0.0, 0.5]))]
    assert still_in_place(before, again) == {0: 0}
    for spin in (MAX_FACE_TURN_DEG + 5.0, 120.0):
        spun = rotation(list(before[0].normal), spin)
        other = [replace(again[0], axis=spun @ before[0].axis)]
        assert still_in_place(before, other) == {}
        # Without axes nothing tells it apart.
        assert still_in_place([replace(before[0], axis=None)], [replace(other[0], axis=None)]) == {
            0: 0
        }
    spun = rotation(list(before[0].normal), 10.0)
    assert still_in_place(before, [replace(again[0], axis=spun @ before[0].axis)]) == {0: 0}


@pytest.mark.parametrize("seed", range(4))
def test_the_template_tells_a_unit_from_its_mirror(seed: int) -> None:
    """Two faces of a unit that turned 20-35 deg: every pose mirrored (the other branch of the
    circle's ambiguity, normal and axis) makes a mirrored unit whose frames turned alike too.
    With the branches chosen wrong, the frames alone give the mirrored unit's turn; the
    template, which fits the true normals and not the mirrored ones, gives the true turn."""
    rng = np.random.default_rng(100 + seed)
    axes = _glued_axes(rng)
    turn = rotation(list(rng.normal(size=3)), rng.uniform(20.0, 35.0))
    tilt = rotation([1.0, 0.3, 0.0], 25.0) @ R0  # faces well off square to the camera
    before = _unit(np.array([-40.0, 20.0, 1500.0]), tilt, axes)[:2]
    after = _unit(np.array([-20.0, 30.0, 1490.0]), turn @ tilt, axes, [p.code for p in before])
    assert [p.code for p in before] == [p.code for p in after] and len(before) == 2
    wrong_b = mirror_normals(
        np.array([p.position_mm for p in before]), np.array([p.normal for p in before])
    )
    wrong_a = mirror_normals(
        np.array([p.position_mm for p in after]), np.array([p.normal for p in after])
    )
    mirrored = turn_from_frames(before, after, wrong_b, wrong_a)
    assert mirrored is not None and _angle_deg(mirrored @ turn.T) > 10.0
    R = turn_from_frames(before, after, wrong_b, wrong_a, UMAP.template)
    assert R is not None and _angle_deg(R @ turn.T) < 1e-3
