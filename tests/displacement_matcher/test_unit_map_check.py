"""A unit map with a code under the wrong unit is named after matching (compare_poses)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from armourcam.field import Field, make_field
from displacement_matcher.compare import check_unit_map, compare_poses
from displacement_matcher.damage import thresholds
from displacement_matcher.units import parse_unit_map
from pose_estimator.fusion import moved_poses
from pose_estimator.types import FiducialPose


@pytest.fixture(scope="module")
def field() -> Field:
    """16 dolos, every fiducial of a unit seen (no occlusion), a quarter of them moved."""
    return make_field(16, seed=3, hidden_fraction=0.0, moved_fraction=0.25)


def _unique_codes(field: Field, before: bool, rng: np.random.Generator) -> list[FiducialPose]:
    """The state's poses, each unit's fiducials relabelled ``4 * unit + slot`` (every code on one
    fiducial: what an explicit unit map describes)."""
    state = field.before if before else field.after
    out = []
    poses = state.poses(rng, sigma_xy_mm=0.05, sigma_z_mm=0.3)
    for p, i in zip(poses, state.observable_ids, strict=True):
        slot = field.geometry.codes.index(int(state.code[i]))
        code = 4 * int(state.unit[i]) + slot
        out.append(FiducialPose(code, p.position_mm, p.normal, p.covariance_mm2))
    return out


def _units(n: int) -> dict[str, Any]:
    return {f"D{u:02d}": {"codes": [4 * u + k for k in range(4)]} for u in range(n)}


def test_codes_swapped_between_two_units_are_named_and_a_correct_map_is_silent(
    field: Field,
) -> None:
    """Code 8 of D02 listed under D09 and code 36 of D09 under D02: a warning for each unit,
    naming the code, its distance from the unit's other codes and the unit where it fits; the
    right map gives none."""
    rng = np.random.default_rng(1)
    base, cur = _unique_codes(field, True, rng), _unique_codes(field, False, rng)
    limits = thresholds(field.geometry.dn_mm)
    good = compare_poses(base, cur, limits, unit_map=parse_unit_map({"units": _units(16)}))
    assert good.unit_map_problems == () and good.warnings == ()
    units = _units(16)
    units["D02"]["codes"][0], units["D09"]["codes"][0] = 36, 8
    a = compare_poses(base, cur, limits, unit_map=parse_unit_map({"units": units}))
    assert [(p.unit, p.codes) for p in a.unit_map_problems] == [("D02", (36,)), ("D09", (8,))]
    at = {p.code: p.position_mm for p in base}
    for p, home in zip(a.unit_map_problems, ("D09", "D02"), strict=True):
        others = [c for c in units[p.unit]["codes"] if c != p.codes[0] and c in at]
        nearest = min(np.linalg.norm(at[p.codes[0]] - at[c]) for c in others)
        assert p.distance_mm == pytest.approx(nearest)
        assert p.distance_mm > p.limit_mm == pytest.approx(2.0 * field.geometry.dn_mm)
        assert p.near_units[0] == home
        assert p.message == (
            f"unit {p.unit}: code {p.codes[0]} is {p.distance_mm:.0f} mm from its other codes "
            f"in the baseline (one unit spans at most {p.limit_mm:.0f} mm): is it on unit {home}"
            + "".join(f" or unit {u}" for u in p.near_units[1:2])
            + "? check units.yaml"
        )
    assert a.warnings == tuple(p.message for p in a.unit_map_problems)


def test_the_unit_maps_positions_catch_a_code_within_the_span() -> None:
    """With positions in the map, a code where the map says it is not (though within a unit's
    span) is named with both distances; two codes alone too far apart are one problem, since the
    baseline cannot say which is wrong; templates are not checked."""
    cov = np.diag([0.01, 0.01, 0.25])
    n = np.array([0.0, 0.0, -1.0])

    def pose(code: int, x: float, y: float) -> FiducialPose:
        return FiducialPose(code, np.array([x, y, 800.0]), n, cov)

    base = [pose(1, 0, 0), pose(2, 20, 0), pose(3, 0, 30), pose(4, 200, 0), pose(5, 290, 0)]
    umap = parse_unit_map(
        {
            "units": {
                "A": {"codes": [1, 2, 3], "positions_mm": {1: [0, 0, 0], 2: [20, 0, 0],
                                                           3: [0, 12, 0]}},
                "B": {"codes": [4, 5]},
            }
        }
    )  # fmt: skip
    a, b = check_unit_map(base, umap, limit_mm=41.0)
    assert (a.unit, a.codes, a.expected_mm) == ("A", (3,), pytest.approx(12.0))
    assert a.distance_mm == pytest.approx(30.0)
    assert a.message == (
        "unit A: code 3 is 30 mm from its other codes in the baseline, 12 mm in the unit map: "
        "is it on another unit? check units.yaml"
    )
    assert (b.unit, b.codes, b.distance_mm) == ("B", (4, 5), pytest.approx(90.0))
    assert b.message == (
        "unit B: codes 4, 5 are 90 mm apart in the baseline (one unit spans at most 41 mm): "
        "is one of them on another unit? check units.yaml"
    )
    assert check_unit_map(base[:3], umap, limit_mm=41.0, skip={2}) == ()
    template = parse_unit_map({"template": {"codes": [1, 2, 3]}})
    assert check_unit_map(base, template, limit_mm=41.0) == ()


def test_a_camera_moved_between_the_states_is_named() -> None:
    """A camera bumped during the wave run moves every fiducial alike: the comparison says so
    (with the shift), while a field whose units moved with the camera still gives no warning.
    Without the check a 1 mm shift passed silently into every displacement."""
    import cv2

    field = make_field(120, seed=4)
    rng = np.random.default_rng(4)
    before, after = field.before.poses(rng), field.after.poses(rng)
    limits = thresholds(field.geometry.dn_mm)
    assert compare_poses(before, after, limits).camera_motion is None
    turn, _ = cv2.Rodrigues(np.array([0.0, np.radians(0.05), 0.0]))
    shift = np.array([1.0, -0.5, 0.0])
    cmp = compare_poses(before, moved_poses(after, np.asarray(turn), shift), limits)
    assert cmp.camera_motion is not None
    assert cmp.warnings
    assert cmp.warnings[0].startswith("camera moved between the before and after states?")
    assert "re-capture the baseline" in cmp.warnings[0]
