"""Optimality, labels and bad input of :func:`displacement_matcher.match`."""

from __future__ import annotations

import importlib
import itertools
import math

import numpy as np
import pytest
from matcher_synth import make_pose
from scipy.optimize import linear_sum_assignment

from displacement_matcher import MatcherError, cost_matrix, match
from pose_estimator.types import FiducialPose


def brute_force(cost: np.ndarray, unmatched: float) -> float:
    """Minimum over every partial matching (partial permutation matrix) by enumeration."""
    n, m = cost.shape
    best = math.inf
    # For each baseline fiducial: one of the current ones, or None; all distinct.
    for choice in itertools.product([None, *range(m)], repeat=n):
        used = [c for c in choice if c is not None]
        if len(used) != len(set(used)):
            continue
        total = 0.0
        for i, c in enumerate(choice):
            total += unmatched if c is None else cost[i, c]
        total += unmatched * (m - len(used))
        best = min(best, total)
    return best


def dense_optimum(cost: np.ndarray, unmatched: float) -> float:
    """Optimum of the whole augmented problem solved as one dense assignment."""
    n, m = cost.shape
    big = np.full((n + m, m + n), np.inf)
    big[:n, :m] = cost
    big[np.arange(n), m + np.arange(n)] = unmatched
    big[n + np.arange(m), np.arange(m)] = unmatched
    big[n:, m:] = 0.0
    r, c = linear_sum_assignment(big)
    return float(big[r, c].sum())


def random_case(rng: np.random.Generator, n: int, m: int, n_codes: int) -> tuple[list, list]:
    """Clustered random poses so that gates overlap and the assignment is non-trivial."""
    base = [
        make_pose(
            int(rng.integers(n_codes)),
            rng.uniform([-30, -30, 780], [30, 30, 820]),
            sigma_xy=rng.uniform(0.05, 0.5),
            sigma_z=rng.uniform(0.5, 8.0),
        )
        for _ in range(n)
    ]
    cur = [
        make_pose(
            int(rng.integers(n_codes)),
            rng.uniform([-30, -30, 780], [30, 30, 820]),
            sigma_xy=rng.uniform(0.05, 0.5),
            sigma_z=rng.uniform(0.5, 8.0),
        )
        for _ in range(m)
    ]
    return base, cur


@pytest.mark.parametrize("seed", range(40))
def test_cost_equals_brute_force_and_dense_optimum(seed: int) -> None:
    """On small random sets the matching's cost is the optimum over all partial matchings."""
    rng = np.random.default_rng(1234 + seed)
    n, m = int(rng.integers(0, 6)), int(rng.integers(0, 6))
    base, cur = random_case(rng, n, m, n_codes=int(rng.integers(1, 4)))
    kw = {
        "gate_mm": float(rng.uniform(10, 50)),
        "code_penalty_mm": float(rng.choice([5.0, 20.0, math.inf])),
        "motion_scale_mm": float(rng.uniform(1, 10)),
        "normal_weight_mm": float(rng.choice([0.0, 5.0])),
    }
    for p in base + cur:  # random normals so that the normal term matters
        v = rng.normal(size=3)
        p.normal[:] = v / np.linalg.norm(v)
    result = match(base, cur, **kw)
    cost = cost_matrix(base, cur, **kw)
    unmatched = kw["gate_mm"] / 2
    expected = brute_force(cost, unmatched)
    assert result.total_cost == pytest.approx(expected, rel=1e-9, abs=1e-9)
    assert result.total_cost == pytest.approx(dense_optimum(cost, unmatched), rel=1e-9, abs=1e-9)
    # The reported entries are consistent with the cost matrix.
    for d in result.displacements:
        if d.is_match:
            assert d.cost == pytest.approx(cost[d.baseline_index, d.current_index])
    assert sorted(
        d.baseline_index for d in result.displacements if d.baseline_index is not None
    ) == list(range(n))
    assert sorted(
        d.current_index for d in result.displacements if d.current_index is not None
    ) == list(range(m))


@pytest.mark.parametrize("seed", range(3))
def test_large_components_sparse_solver_matches_dense(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The sparse solver used for large components gives the dense optimum."""
    mod = importlib.import_module("displacement_matcher.match")

    rng = np.random.default_rng(99 + seed)
    base, cur = random_case(rng, 60, 55, n_codes=3)
    kw = {"gate_mm": 25.0, "code_penalty_mm": 10.0, "motion_scale_mm": 4.0}
    dense = match(base, cur, **kw)
    monkeypatch.setattr(mod, "DENSE_LIMIT", 4)
    sparse_res = match(base, cur, **kw)
    cost = cost_matrix(base, cur, **kw)
    opt = dense_optimum(cost, kw["gate_mm"] / 2)
    assert dense.total_cost == pytest.approx(opt, rel=1e-9)
    assert sparse_res.total_cost == pytest.approx(opt, rel=1e-9)


def test_labels_same_cross_vanished_appeared() -> None:
    """Each kind of entry gets its label (paper section 5: red cross-code vectors)."""
    base = [
        make_pose(1, [0, 0, 800]),  # stays
        make_pose(2, [100, 0, 800]),  # overturned: code 2 faces away, code 3 appears nearby
        make_pose(4, [-200, 0, 800]),  # vanishes
    ]
    cur = [
        make_pose(1, [0.5, 0.2, 800.3]),
        make_pose(3, [104, 2, 801]),
        make_pose(5, [300, 0, 800]),  # appears far from everything
    ]
    r = match(base, cur, gate_mm=30.0, code_penalty_mm=10.0)
    got = {(d.baseline_index, d.current_index): d.label for d in r.displacements}
    assert got == {
        (0, 0): "same_code",
        (1, 1): "cross_code",
        (2, None): "vanished",
        (None, 2): "appeared",
    }
    assert r.counts() == {"same_code": 1, "cross_code": 1, "vanished": 1, "appeared": 1}
    d0 = r.displacements[0]
    np.testing.assert_allclose(d0.displacement_mm, [0.5, 0.2, 0.3])
    # Forbidding cross-code pairs leaves the overturned fiducials unmatched.
    r2 = match(base, cur, gate_mm=30.0, code_penalty_mm=math.inf)
    assert r2.counts()["cross_code"] == 0 and r2.counts()["vanished"] == 2


def test_depth_counts_less_where_uncertain() -> None:
    """Between two same-code candidates, the one off in depth (uncertain) wins over one off in x."""
    a = make_pose(7, [0, 0, 1000], sigma_xy=0.05, sigma_z=5.0)
    off_depth = make_pose(7, [0, 0, 1008], sigma_xy=0.05, sigma_z=5.0)
    off_x = make_pose(7, [6, 0, 1000], sigma_xy=0.05, sigma_z=5.0)
    r = match([a], [off_x, off_depth], gate_mm=20.0)
    assert r.pairs().tolist() == [[0, 1]]
    # With an isotropic, tight covariance the plain nearer one wins.
    a2 = make_pose(7, [0, 0, 1000], sigma_xy=0.05, sigma_z=0.05)
    r2 = match(
        [a2],
        [make_pose(7, [6, 0, 1000], 0.05, 0.05), make_pose(7, [0, 0, 1008], 0.05, 0.05)],
        gate_mm=20.0,
    )
    assert r2.pairs().tolist() == [[0, 0]]


def test_global_beats_greedy() -> None:
    """A chain where greedy nearest-neighbour fails and the global optimum does not."""
    base = [make_pose(1, [0, 0, 800]), make_pose(1, [10, 0, 800])]
    cur = [make_pose(1, [6, 0, 800]), make_pose(1, [17, 0, 800])]
    r = match(base, cur, gate_mm=20.0)
    # Greedy would pair (1, 0) at 4 mm and leave 0 with 17 mm; optimum is the two 6-7 mm shifts.
    assert sorted(r.pairs().tolist()) == [[0, 0], [1, 1]]


def test_empty_and_one_side_empty() -> None:
    """Empty inputs give empty or all-vanished/appeared results, never an error."""
    assert match([], []).displacements == ()
    one = [make_pose(3, [0, 0, 800])]
    r = match(one, [])
    assert [d.label for d in r.displacements] == ["vanished"]
    r = match([], one)
    assert [d.label for d in r.displacements] == ["appeared"]
    assert r.total_cost == pytest.approx(r.params.gate_mm / 2)


def test_nan_and_bad_covariance_poses_are_reported_not_lost() -> None:
    """Unusable poses are listed with their reason; the rest are matched."""
    good = make_pose(1, [0, 0, 800])
    nan_pose = FiducialPose(2, np.array([np.nan, 0, 800]), np.array([0, 0, -1.0]), np.eye(3))
    bad_cov = FiducialPose(3, np.array([5.0, 0, 800]), np.array([0, 0, -1.0]), -np.eye(3))
    inf_cov = FiducialPose(
        4, np.array([9.0, 0, 800]), np.array([0, 0, -1.0]), np.full((3, 3), np.inf)
    )
    nan_normal = FiducialPose(1, np.array([0.2, 0, 800]), np.full(3, np.nan), np.eye(3) * 0.01)
    r = match([good, nan_pose, bad_cov], [nan_normal, inf_cov])
    assert r.pairs().tolist() == [[0, 0]]
    reasons = {(x.side, x.index): x.reason for x in r.rejected}
    assert set(reasons) == {("baseline", 1), ("baseline", 2), ("current", 1)}
    assert "not finite" in reasons[("baseline", 1)]
    assert "positive semi-definite" in reasons[("baseline", 2)]
    assert "covariance_mm2 is not finite" in reasons[("current", 1)]


def test_wrong_types_and_parameters_raise() -> None:
    """Caller mistakes raise MatcherError naming the problem."""
    p = make_pose(1, [0, 0, 800])
    with pytest.raises(MatcherError, match=r"baseline\[1\] is a str"):
        match([p, "x"], [p])  # type: ignore[list-item]
    with pytest.raises(MatcherError, match="current must be a sequence"):
        match([p], p)  # type: ignore[arg-type]
    with pytest.raises(MatcherError, match="gate_mm"):
        match([p], [p], gate_mm=0.0)
    with pytest.raises(MatcherError, match="code_penalty_mm"):
        match([p], [p], code_penalty_mm=float("nan"))
    with pytest.raises(MatcherError, match="motion_scale_mm"):
        match([p], [p], motion_scale_mm=-1.0)


def test_malformed_arrays_are_rejected() -> None:
    """A position with the wrong number of elements is reported, not a crash."""
    odd = FiducialPose(1, np.array([0.0, 1.0]), np.array([0, 0, -1.0]), np.eye(3))
    r = match([odd, make_pose(1, [0, 0, 800])], [make_pose(1, [0, 0, 800])])
    assert [x.index for x in r.rejected] == [0]
    assert "2 elements" in r.rejected[0].reason
    assert r.pairs().tolist() == [[1, 0]]


def test_prediction_row_gate_and_excluded_pairs() -> None:
    """Unit-aware options: costs from predicted positions, tighter row gates, excluded pairs."""
    base = [make_pose(1, [0, 0, 800]), make_pose(1, [40, 0, 800])]
    cur = [make_pose(1, [20, 0, 800]), make_pose(1, [41, 0, 800])]
    assert sorted(match(base, cur, gate_mm=50.0).pairs().tolist()) == [[0, 0], [1, 1]]
    # Excluding (0, 0) leaves baseline 0 unmatched (current 1 is taken more cheaply).
    r = match(base, cur, gate_mm=50.0, exclude_pairs=[(0, 0)])
    assert r.pairs().tolist() == [[1, 1]]
    # A prediction that baseline 0 stayed, with a tight gate, rejects the 20 mm partner ...
    pred = np.array([[0.0, 0, 800], [np.nan, np.nan, np.nan]])
    r = match(base, cur, gate_mm=50.0, prediction_mm=pred, row_gate_mm=np.array([5.0, np.nan]))
    assert r.pairs().tolist() == [[1, 1]]
    # ... while one that it moved by 20 mm makes the pair nearly free; before_mm stays measured.
    pred[0] = [20.0, 0, 800]
    r = match(base, cur, gate_mm=50.0, prediction_mm=pred, row_gate_mm=np.array([5.0, np.nan]))
    d = r.displacements[0]
    assert (d.baseline_index, d.current_index) == (0, 0) and d.cost < 1.0
    np.testing.assert_allclose(d.displacement_mm, [20.0, 0, 0])
    with pytest.raises(MatcherError, match="prediction_mm must have shape"):
        match(base, cur, prediction_mm=np.zeros((3, 3)))
    with pytest.raises(MatcherError, match="row_gate_mm must have"):
        match(base, cur, row_gate_mm=np.zeros(5))


def test_identity_codes_are_matched_beyond_the_gate_and_only_when_seen_once() -> None:
    """A code printed once (an explicit unit map's) seen once in each set is that fiducial,
    however far it went; a code seen twice on a side, an excluded pair and every other code
    still follow the gate."""
    far = np.array([0.0, 80.0, 0.0])
    base = [
        make_pose(3, [0.0, 0.0, 800.0]),
        make_pose(4, [150.0, 0, 800]),
        make_pose(5, [300.0, 0, 800]),
    ]
    cur = [make_pose(3, base[0].position_mm + far), make_pose(4, base[1].position_mm + far)]
    cur += [make_pose(5, base[2].position_mm + far), make_pose(5, [-300.0, 0, 800])]
    plain = match(base, cur)
    assert not [d for d in plain.displacements if d.is_match]  # all beyond the 50 mm gate
    got = match(base, cur, identity_codes={3, 4, 5})
    pairs = {(d.baseline_index, d.current_index) for d in got.displacements if d.is_match}
    assert pairs == {(0, 0), (1, 1)}  # code 5 is seen twice now: left to the gate
    (d0,) = [d for d in got.displacements if d.baseline_index == 0]
    assert d0.label == "same_code"
    np.testing.assert_allclose(d0.displacement_mm, far)
    assert got.total_cost == pytest.approx(sum(d.cost for d in got.displacements))
    excluded = match(base, cur, identity_codes={3, 4}, exclude_pairs=[(0, 0)])
    assert {(d.baseline_index, d.current_index) for d in excluded.displacements if d.is_match} == {
        (1, 1)
    }
