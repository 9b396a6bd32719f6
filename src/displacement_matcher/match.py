"""Optimal before/after correspondence of fiducials (paper section 2.2; section 3, steps 5-6).

The paper matches the fiducials of a before and an after image with Maciel and Costeira's global
method: the best partial permutation between the two sets. With a cost that is linear in the
permutation matrix this is exactly a minimum-cost bipartite matching in which every fiducial may
also stay unmatched, which we solve exactly:

* Cost of a pair ``(a, b)``: the weighted distance ``sqrt(s^2 d^T (s^2 I + C_a + C_b)^-1 d)``
  (``d = p_b - p_a``, ``C`` the pose covariances, ``s`` the motion scale), so depth, which a single
  camera measures several times worse than x and y, counts less where it is uncertain (the paper's
  section 4.1 advice); plus ``code_penalty_mm`` when the codes differ (the paper's red vectors),
  plus an optional normal-disagreement term. The cost is a distance, not a squared distance: a
  squared cost would rather split one large move into two medium ones (40^2 > 2 * 20^2) and hand
  a still fiducial's partner to a moved neighbour. Leaving a fiducial unmatched costs
  ``gate_mm / 2``, so a pair is only ever matched when its cost is below ``gate_mm``: that is the
  gate, and the only pairs the solver sees; a k-d tree finds them.
* The gated pairs form a sparse bipartite graph; every connected component is an independent
  problem. One-to-one components are matched directly; the others are solved exactly as a
  rectangular assignment with a dummy "no match" row and column per fiducial
  (:func:`scipy.optimize.linear_sum_assignment` on small dense blocks, the sparse Jonker-Volgenant
  solver on large ones).

All positions are in the camera frame of :mod:`pose_estimator`, millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components, min_weight_full_bipartite_matching
from scipy.spatial import cKDTree

from pose_estimator.types import FiducialPose

from .errors import MatcherError
from .types import Displacement, Label, MatchParams, MatchResult, RejectedPose

DEFAULT_GATE_MM = 50.0
DEFAULT_CODE_PENALTY_MM = 25.0
DEFAULT_MOTION_SCALE_MM = 5.0
DEFAULT_NORMAL_WEIGHT_MM = 0.0
# Components with more fiducials than this go to the sparse solver instead of a dense block.
DENSE_LIMIT = 600


def make_params(
    *,
    gate_mm: float = DEFAULT_GATE_MM,
    code_penalty_mm: float = DEFAULT_CODE_PENALTY_MM,
    motion_scale_mm: float = DEFAULT_MOTION_SCALE_MM,
    normal_weight_mm: float = DEFAULT_NORMAL_WEIGHT_MM,
) -> MatchParams:
    """Validated :class:`MatchParams` (raises :class:`MatcherError` naming a bad value)."""
    if not (math.isfinite(gate_mm) and gate_mm > 0):
        raise MatcherError(f"gate_mm must be a positive finite length, got {gate_mm!r}")
    if math.isnan(code_penalty_mm) or code_penalty_mm < 0:
        raise MatcherError(f"code_penalty_mm must be >= 0 (inf forbids), got {code_penalty_mm!r}")
    if not (math.isfinite(motion_scale_mm) and motion_scale_mm > 0):
        raise MatcherError(f"motion_scale_mm must be positive and finite, got {motion_scale_mm!r}")
    if not (math.isfinite(normal_weight_mm) and normal_weight_mm >= 0):
        raise MatcherError(f"normal_weight_mm must be >= 0 and finite, got {normal_weight_mm!r}")
    return MatchParams(
        float(gate_mm), float(code_penalty_mm), float(motion_scale_mm), float(normal_weight_mm)
    )


class _PoseSet:
    """Usable poses of one side as arrays, with the rejected ones listed."""

    def __init__(self, poses: Sequence[FiducialPose], side: str) -> None:
        if isinstance(poses, FiducialPose) or not isinstance(poses, Sequence):
            raise MatcherError(f"{side} must be a sequence of FiducialPose, got {type(poses)}")
        for i, pose in enumerate(poses):
            if not isinstance(pose, FiducialPose):
                raise MatcherError(f"{side}[{i}] is a {type(pose).__name__}, not a FiducialPose")
        n = len(poses)
        self.rejected: list[RejectedPose] = []
        try:
            pos = np.array([p.position_mm for p in poses], dtype=np.float64).reshape(n, 3)
            cov = np.array([p.covariance_mm2 for p in poses], dtype=np.float64).reshape(n, 3, 3)
        except ValueError:
            # Some pose has a malformed array: sort them out one by one.
            pos, cov = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
            for i, p in enumerate(poses):
                pi = np.asarray(p.position_mm, dtype=np.float64)
                ci = np.asarray(p.covariance_mm2, dtype=np.float64)
                if pi.size == 3 and ci.size == 9:
                    pos[i], cov[i] = pi.reshape(3), ci.reshape(3, 3)
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        ok_pos = np.all(np.isfinite(pos), axis=1)
        ok_cov = np.all(np.isfinite(cov), axis=(1, 2))
        eig = np.zeros((n, 3))
        if ok_cov.any():
            eig[ok_cov] = np.linalg.eigvalsh(cov[ok_cov])
        ok_psd = eig[:, 0] >= -1e-9 * np.maximum(1.0, eig[:, 2])
        good = ok_pos & ok_cov & ok_psd
        for i in np.flatnonzero(~good).tolist():
            self.rejected.append(
                RejectedPose(side, i, int(poses[i].code), _reason(poses[i]))  # type: ignore[arg-type]
            )
        self.index = np.flatnonzero(good)
        # Along-the-line-of-sight discrepancy (mm) not counted in a pair's cost (see match()).
        self.slack = np.zeros(int(good.sum()))
        self.code = np.array([int(poses[i].code) for i in self.index.tolist()], dtype=np.int64)
        self.pos = pos[good]
        self.cov = cov[good]
        self.lam_max = eig[good, 2].clip(0.0)
        try:
            nrm = np.array([poses[i].normal for i in self.index.tolist()], dtype=np.float64)
            nrm = nrm.reshape(len(self.index), 3)
        except ValueError:
            nrm = np.zeros((len(self.index), 3))
        length = np.linalg.norm(nrm, axis=1)
        usable = np.isfinite(length) & (length > 0)
        self.normal = np.zeros_like(nrm)
        self.normal[usable] = nrm[usable] / length[usable, None]

    def __len__(self) -> int:
        return len(self.index)


def _reason(pose: FiducialPose) -> str:
    """Why a pose cannot take part in the matching."""
    p = np.asarray(pose.position_mm, dtype=np.float64)
    if p.size != 3:
        return f"position_mm has {p.size} elements, not 3"
    if not np.all(np.isfinite(p)):
        return f"position_mm is not finite: {p.reshape(3).tolist()}"
    c = np.asarray(pose.covariance_mm2, dtype=np.float64)
    if c.size != 9:
        return f"covariance_mm2 has {c.size} elements, not 9"
    if not np.all(np.isfinite(c)):
        return "covariance_mm2 is not finite"
    eig = np.linalg.eigvalsh(0.5 * (c.reshape(3, 3) + c.reshape(3, 3).T))
    return f"covariance_mm2 is not positive semi-definite (eigenvalues {eig.tolist()})"


def _candidates(a: _PoseSet, b: _PoseSet, params: MatchParams) -> tuple[NDArray, NDArray]:
    """All pairs ``(i, j)`` (indices into the usable arrays) that can pass the gate.

    The weighted distance satisfies ``s^2 d^T S^-1 d >= s^2 |d|^2 / lambda_max(S)`` with
    ``lambda_max(S) <= s^2 + l_a + l_b <= 2 max(s^2/2 + l_a, s^2/2 + l_b)``, so a pair within the
    gate lies within ``gate/s * sqrt(s^2 + 2 l)`` of one of its two members (``l`` that member's
    largest covariance eigenvalue).
    """
    s = params.motion_scale_mm
    g = params.gate_mm
    ra = g * np.sqrt(s * s + 2.0 * a.lam_max) / s
    rb = g * np.sqrt(s * s + 2.0 * b.lam_max) / s
    # Most poses share a modest covariance: one C-level fixed-radius search covers every pair of
    # such "narrow" poses; the few "wide" ones (radius above the 95th percentile) search alone.
    r_norm = float(np.percentile(np.concatenate([ra, rb]), 95.0))
    tree_a, tree_b = cKDTree(a.pos), cKDTree(b.pos)
    near = tree_a.sparse_distance_matrix(tree_b, r_norm, output_type="ndarray")
    keys = [near["i"].astype(np.int64) * len(b) + near["j"]]
    for tree, pts, radii, flip in ((tree_b, a.pos, ra, False), (tree_a, b.pos, rb, True)):
        wide = np.flatnonzero(radii > r_norm)
        if len(wide) == 0:
            continue
        hits = tree.query_ball_point(pts[wide], radii[wide], return_sorted=False)
        lens = np.fromiter((len(h) for h in hits), dtype=np.intp, count=len(hits))
        src = np.repeat(wide, lens)
        dst = np.fromiter((k for h in hits for k in h), dtype=np.intp, count=int(lens.sum()))
        i, j = (dst, src) if flip else (src, dst)
        keys.append(i.astype(np.int64) * len(b) + j)
    slack_rows = np.flatnonzero(a.slack > 0)
    if len(slack_rows):
        # Rows with depth slack: their lateral offset (across the line of sight) is still bounded
        # by the radius, their depth offset only by radius + slack. Search by direction from the
        # camera: a lateral offset L at range r is an angle of about L / r.
        rng_a = np.linalg.norm(a.pos[slack_rows], axis=1)
        reach = ra[slack_rows] + np.sqrt(s * s + 2.0 * float(b.lam_max.max())) * g / s
        lo = np.maximum(rng_a - reach - a.slack[slack_rows], 1e-3)
        chord = np.minimum(1.1 * reach / lo, 2.0)
        dir_b = b.pos / np.maximum(np.linalg.norm(b.pos, axis=1, keepdims=True), 1e-12)
        dir_a = a.pos[slack_rows] / np.maximum(rng_a, 1e-12)[:, None]
        hits = cKDTree(dir_b).query_ball_point(dir_a, chord, return_sorted=False)
        lens = np.fromiter((len(h) for h in hits), dtype=np.intp, count=len(hits))
        src = np.repeat(slack_rows, lens)
        dst = np.fromiter((k for h in hits for k in h), dtype=np.intp, count=int(lens.sum()))
        keys.append(src.astype(np.int64) * len(b) + dst)
    # The fixed-radius search returns each pair once; only the extra searches can repeat pairs.
    uniq = keys[0] if len(keys) == 1 else np.unique(np.concatenate(keys))
    i, j = (uniq // len(b)).astype(np.intp), (uniq % len(b)).astype(np.intp)
    # Exact per-pair bound before the 3x3 solves: |d|^2 <= g'^2 (s^2 + l_a + l_b) / s^2, where
    # a cross-code pair must fit its weighted distance under g' = gate - code penalty.
    dd = _slackened(a, b, i, j)
    d2 = np.einsum("ki,ki->k", dd, dd)
    cross = a.code[i] != b.code[j]
    g_eff = np.where(cross, max(g - params.code_penalty_mm, 0.0), g) if len(i) else np.zeros(0)
    ok = d2 * s * s <= g_eff * g_eff * (s * s + a.lam_max[i] + b.lam_max[j]) * (1.0 + 1e-9)
    if math.isinf(params.code_penalty_mm) or params.code_penalty_mm >= g:
        ok &= ~cross
    return i[ok], j[ok]


def _slackened(a: _PoseSet, b: _PoseSet, i: NDArray, j: NDArray) -> NDArray[np.float64]:
    """``p_b - p_a`` per pair, its component along the line of sight shrunk by row ``i``'s slack.

    The line of sight is the direction from the camera (the origin) to the pair's midpoint.
    """
    d = b.pos[j] - a.pos[i]
    sl = a.slack[i]
    if not np.any(sl > 0):
        return d
    r = a.pos[i] + b.pos[j]
    r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    along = np.einsum("ki,ki->k", d, r)
    kept = np.sign(along) * np.maximum(np.abs(along) - sl, 0.0)
    return np.asarray(d - (along - kept)[:, None] * r, dtype=np.float64)


def _pair_costs(
    a: _PoseSet, b: _PoseSet, i: NDArray, j: NDArray, params: MatchParams
) -> NDArray[np.float64]:
    """Cost (mm) of matching usable baseline ``i`` with usable current ``j``, elementwise."""
    if len(i) == 0:
        return np.zeros(0)
    s2 = params.motion_scale_mm**2
    d = _slackened(a, b, i, j)
    S = a.cov[i] + b.cov[j]
    # d^T S^-1 d for the symmetric positive-definite S = s^2 I + C_a + C_b, in closed form
    # (adjugate over determinant): much faster than batched LAPACK solves on 3x3 blocks.
    sa, sb, sc = S[:, 0, 0] + s2, S[:, 0, 1], S[:, 0, 2]
    sd, se, sf = S[:, 1, 1] + s2, S[:, 1, 2], S[:, 2, 2] + s2
    c00, c01, c02 = sd * sf - se * se, sc * se - sb * sf, sb * se - sc * sd
    c11, c12, c22 = sa * sf - sc * sc, sb * sc - sa * se, sa * sd - sb * sb
    det = sa * c00 + sb * c01 + sc * c02
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    quad = (
        c00 * x * x + c11 * y * y + c22 * z * z + 2.0 * (c01 * x * y + c02 * x * z + c12 * y * z)
    ) / det
    cost = np.sqrt(np.clip(s2 * quad, 0.0, None))
    cost += np.where(a.code[i] != b.code[j], params.code_penalty_mm, 0.0)
    if params.normal_weight_mm > 0:
        dot = np.einsum("ki,ki->k", a.normal[i], b.normal[j])
        cost += params.normal_weight_mm * (1.0 - dot)
    return np.asarray(cost, dtype=np.float64)


def _solve_block(
    costs: NDArray[np.float64], rows: NDArray, cols: NDArray, nr: int, nc: int, unmatched: float
) -> tuple[NDArray, NDArray]:
    """Optimal partial matching of one component; returns matched local ``(rows, cols)``.

    ``costs[k]`` is the cost of local edge ``(rows[k], cols[k])``; every node can instead stay
    unmatched at ``unmatched``. Augmented square problem of size ``nr + nc``: real block top-left,
    a diagonal "no match" block for rows (top-right) and for columns (bottom-left), and a
    dummy-dummy block bottom-right.
    """
    size = nr + nc
    if size <= DENSE_LIMIT:
        big = np.full((size, size), np.inf)
        big[rows, cols] = costs
        big[np.arange(nr), nc + np.arange(nr)] = unmatched
        big[nr + np.arange(nc), np.arange(nc)] = unmatched
        big[nr:, nc:] = 0.0
        r, c = linear_sum_assignment(big)
    else:
        # Sparse form: the dummy-dummy block only needs the mirror (j', i') of each real edge
        # (i, j), and a constant offset keeps every weight non-zero (LAPJVsp ignores zero
        # entries) without changing the optimum of a perfect matching.
        off = 1.0 + unmatched
        er = np.concatenate([rows, np.arange(nr), nr + np.arange(nc), nr + cols])
        ec = np.concatenate([cols, nc + np.arange(nr), np.arange(nc), nc + rows])
        ew = np.concatenate(
            [
                costs + off,
                np.full(nr, unmatched + off),
                np.full(nc, unmatched + off),
                np.full(len(rows), off),
            ]
        )
        graph = sparse.csr_array((ew, (er, ec)), shape=(size, size))
        r, c = min_weight_full_bipartite_matching(graph)
    real = (r < nr) & (c < nc)
    return r[real], c[real]


def match(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    *,
    gate_mm: float = DEFAULT_GATE_MM,
    code_penalty_mm: float = DEFAULT_CODE_PENALTY_MM,
    motion_scale_mm: float = DEFAULT_MOTION_SCALE_MM,
    normal_weight_mm: float = DEFAULT_NORMAL_WEIGHT_MM,
    prediction_mm: NDArray[np.float64] | None = None,
    row_gate_mm: NDArray[np.float64] | None = None,
    depth_slack_mm: float = 0.0,
    exclude_pairs: Sequence[tuple[int, int]] = (),
    identity_codes: Collection[int] = (),
) -> MatchResult:
    """Globally optimal partial matching of baseline and current fiducials.

    Parameters
    ----------
    baseline, current : sequence of FiducialPose
        Fiducial poses before and after (camera frame, mm). Either may be empty.
    gate_mm : float
        Largest cost (mm) at which a pair may be matched; leaving a fiducial unmatched costs
        ``gate_mm / 2``.
    code_penalty_mm : float
        Penalty (mm) added to the weighted distance of a cross-code pair; ``inf`` forbids them.
    motion_scale_mm : float
        Scale ``s`` of the covariance weighting ``s^2 (s^2 I + C_a + C_b)^-1``.
    normal_weight_mm : float
        Weight (mm) of ``(1 - n_a . n_b)`` (0: normals are not used).
    prediction_mm : (n, 3) array_like, optional
        Where each baseline fiducial is expected now (for example moved with its unit, see
        :func:`displacement_matcher.units.match_units`); costs are measured from there, while
        ``before_mm`` and the displacements stay the measured ones. Rows of NaN mean "no
        prediction" (the baseline position is used).
    row_gate_mm : (n,) array_like, optional
        A tighter gate per baseline fiducial (NaN or inf: the global gate): pairs costing more
        than ``row_gate_mm[i]`` are not considered for row ``i``.
    depth_slack_mm : float
        For rows with a prediction: the part of a pair's offset along the line of sight (from
        the camera through the pair) up to this length is not counted in its cost. Monocular
        depth has heavy tails - a 2 % error in a small ellipse's size is a 35 mm depth error at
        1.8 m - while the offset across the line of sight is measured to a fraction of a
        millimetre, so a fiducial found where its unit's motion predicts it, but at another
        depth, is still that fiducial. 0 (default) counts every offset.
    exclude_pairs : sequence of (int, int)
        ``(baseline_index, current_index)`` pairs that may not be matched (ruled out by
        unit-level reasoning).
    identity_codes : collection of int
        Codes printed on one fiducial only (an explicit unit map's codes): a fiducial of such a
        code seen once before and once now is that fiducial wherever it went, so the pair is
        matched whatever its cost, beyond the gate too (a unit thrown 4 Dn is displaced, not
        lost), unless ``exclude_pairs`` rules it out. The gate still governs every other pair.

    Returns
    -------
    MatchResult
        Every usable pose labelled ``same_code``/``cross_code`` (paired), ``vanished`` (baseline
        only) or ``appeared`` (current only); unusable poses (non-finite position, bad covariance)
        listed in ``rejected`` with the reason.

    Raises
    ------
    MatcherError
        If an input is not a sequence of ``FiducialPose`` or a parameter is invalid.
    """
    params = make_params(
        gate_mm=gate_mm,
        code_penalty_mm=code_penalty_mm,
        motion_scale_mm=motion_scale_mm,
        normal_weight_mm=normal_weight_mm,
    )
    a = _PoseSet(baseline, "baseline")
    b = _PoseSet(current, "current")
    n, m = len(a), len(b)
    gate = params.gate_mm
    unmatched = 0.5 * gate
    measured = a.pos.copy()
    row_gate = np.full(n, gate)
    if prediction_mm is not None:
        pred = np.asarray(prediction_mm, dtype=np.float64)
        if pred.shape != (len(baseline), 3):
            raise MatcherError(
                f"prediction_mm must have shape ({len(baseline)}, 3), got {pred.shape}"
            )
        rows = pred[a.index]
        ok = np.all(np.isfinite(rows), axis=1)
        a.pos[ok] = rows[ok]
        if not (math.isfinite(depth_slack_mm) and depth_slack_mm >= 0):
            raise MatcherError(f"depth_slack_mm must be >= 0 and finite, got {depth_slack_mm!r}")
        a.slack[ok] = depth_slack_mm
    if row_gate_mm is not None:
        rg = np.asarray(row_gate_mm, dtype=np.float64).reshape(-1)
        if rg.shape != (len(baseline),):
            raise MatcherError(f"row_gate_mm must have {len(baseline)} entries, got {rg.size}")
        rg = rg[a.index]
        ok = np.isfinite(rg)
        row_gate[ok] = np.minimum(gate, rg[ok])

    forced_i, forced_j = _identity_pairs(a, b, identity_codes, exclude_pairs)
    # The identified fiducials leave the optimisation: none of their other pairs is a choice.
    a_free = np.ones(n, dtype=bool)
    b_free = np.ones(m, dtype=bool)
    a_free[forced_i] = False
    b_free[forced_j] = False
    if n and m:
        ei, ej = _candidates(a, b, params)
        ec = _pair_costs(a, b, ei, ej, params)
        keep = (ec < row_gate[ei]) & a_free[ei] & b_free[ej]
        if len(exclude_pairs):
            # Usable-array positions of the excluded (input-index) pairs.
            pos_a = {int(x): k for k, x in enumerate(a.index.tolist())}
            pos_b = {int(x): k for k, x in enumerate(b.index.tolist())}
            bad = {pos_a[i] * m + pos_b[j] for i, j in exclude_pairs if i in pos_a and j in pos_b}
            if bad:
                keys = ei.astype(np.int64) * m + ej
                keep &= ~np.isin(keys, np.fromiter(bad, dtype=np.int64, count=len(bad)))
        ei, ej, ec = ei[keep], ej[keep], ec[keep]
    else:
        ei = ej = np.zeros(0, dtype=np.intp)
        ec = np.zeros(0)

    mi, mj, n_comp, largest = _solve(ei, ej, ec, n, m, unmatched)
    mi, mj = np.r_[mi, forced_i].astype(np.intp), np.r_[mj, forced_j].astype(np.intp)

    order = np.argsort(mi, kind="stable")
    mi, mj = mi[order], mj[order]
    mcost = _pair_costs(a, b, mi, mj, params)
    sig = np.sqrt(np.clip(np.diagonal(a.cov[mi] + b.cov[mj], axis1=1, axis2=2), 0.0, None))
    out: list[Displacement] = []
    matched_a = np.zeros(n, dtype=bool)
    matched_b = np.zeros(m, dtype=bool)
    matched_a[mi] = True
    matched_b[mj] = True
    pos_a, pos_b = measured, b.pos.copy()
    idx_a, idx_b = a.index.tolist(), b.index.tolist()
    code_a, code_b = a.code.tolist(), b.code.tolist()
    for k, (i, j) in enumerate(zip(mi.tolist(), mj.tolist(), strict=True)):
        label: Label = "same_code" if code_a[i] == code_b[j] else "cross_code"
        out.append(
            Displacement(
                label,
                idx_a[i],
                idx_b[j],
                code_a[i],
                code_b[j],
                pos_a[i],
                pos_b[j],
                float(mcost[k]),
                sig[k],
            )
        )
    for i in np.flatnonzero(~matched_a).tolist():
        out.append(
            Displacement("vanished", idx_a[i], None, code_a[i], None, pos_a[i], None, unmatched)
        )
    for j in np.flatnonzero(~matched_b).tolist():
        out.append(
            Displacement("appeared", None, idx_b[j], None, code_b[j], None, pos_b[j], unmatched)
        )
    total = float(sum(d.cost for d in out))
    return MatchResult(
        tuple(out),
        tuple(baseline),
        tuple(current),
        total,
        tuple(a.rejected + b.rejected),
        params,
        n_comp,
        largest,
    )


def _identity_pairs(
    a: _PoseSet,
    b: _PoseSet,
    identity_codes: Collection[int],
    exclude_pairs: Sequence[tuple[int, int]],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Usable-array rows ``(i, j)`` of the fiducials identified by their code (see
    :func:`match`): a code of ``identity_codes`` seen exactly once in each set."""
    codes = {int(c) for c in identity_codes}
    if not codes or len(a) == 0 or len(b) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    ca, cb = a.code.astype(np.int64), b.code.astype(np.int64)
    ua, na = np.unique(ca, return_counts=True)
    ub, nb = np.unique(cb, return_counts=True)
    once = np.intersect1d(ua[na == 1], ub[nb == 1])
    once = once[np.isin(once, np.fromiter(codes, dtype=np.int64, count=len(codes)))]
    ii = np.flatnonzero(np.isin(ca, once))
    jj = np.flatnonzero(np.isin(cb, once))
    ii, jj = ii[np.argsort(ca[ii])], jj[np.argsort(cb[jj])]  # both sorted by code: paired
    if len(exclude_pairs):
        excluded = {(int(i), int(j)) for i, j in exclude_pairs}
        ok = [
            (int(a.index[i]), int(b.index[j])) not in excluded
            for i, j in zip(ii.tolist(), jj.tolist(), strict=True)
        ]
        ii, jj = ii[ok], jj[ok]
    return ii.astype(np.intp), jj.astype(np.intp)


def _solve(
    ei: NDArray, ej: NDArray, ec: NDArray[np.float64], n: int, m: int, unmatched: float
) -> tuple[NDArray, NDArray, int, int]:
    """Solve every connected component of the gated graph; returns matched ``(i, j)`` arrays."""
    if len(ei) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty, 0, 0
    adj = sparse.coo_array((np.ones(len(ei)), (ei, n + ej)), shape=(n + m, n + m)).tocsr()
    _, label = connected_components(adj, directed=False)
    comp = label[ei]
    size = np.bincount(label, minlength=int(label.max()) + 1)
    edges_per = np.bincount(comp, minlength=len(size))
    # A component of one baseline and one current fiducial joined by a gated edge: matched.
    simple = (size[comp] == 2) & (edges_per[comp] == 1)
    out_i, out_j = [ei[simple]], [ej[simple]]
    hard = np.flatnonzero(~simple)
    n_comp, largest = int(simple.sum()), 2 if simple.any() else 0
    if len(hard):
        order = hard[np.argsort(comp[hard], kind="stable")]
        hc = comp[order]
        starts = np.flatnonzero(np.r_[True, hc[1:] != hc[:-1]])
        for lo, hi in zip(starts, np.r_[starts[1:], len(order)], strict=True):
            k = order[lo:hi]
            gi, gj = ei[k], ej[k]
            ur, lr = np.unique(gi, return_inverse=True)
            uc, lc = np.unique(gj, return_inverse=True)
            r, c = _solve_block(ec[k], lr, lc, len(ur), len(uc), unmatched)
            out_i.append(ur[r])
            out_j.append(uc[c])
            n_comp += 1
            largest = max(largest, len(ur) + len(uc))
    return np.concatenate(out_i), np.concatenate(out_j), n_comp, largest


def cost_matrix(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    **kwargs: float,
) -> NDArray[np.float64]:
    """Dense ``(n, m)`` pair-cost matrix (mm) of :func:`match`, ``inf`` outside the gate.

    For diagnostics and tests on small sets; rows and columns follow the inputs (all poses must
    be usable).
    """
    params = make_params(**kwargs)
    a = _PoseSet(baseline, "baseline")
    b = _PoseSet(current, "current")
    if a.rejected or b.rejected:
        raise MatcherError(f"cost_matrix needs usable poses; rejected: {a.rejected + b.rejected}")
    i, j = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
    c = _pair_costs(a, b, i.ravel(), j.ravel(), params).reshape(len(a), len(b))
    return np.where(c < params.gate_mm, c, np.inf)
