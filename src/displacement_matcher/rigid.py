"""Rigid motion of a unit from its matched fiducials (points, and normals when known).

:func:`rigid_fit` solves Wahba's problem over the normals and the vectors between points, then
the translation; :func:`kabsch` is the weighted Kabsch/Umeyama fit (no scale) of points alone;
:func:`consistent_subset` keeps the largest set of matches one rigid motion explains. Camera
frame, millimetres.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
from numpy.typing import NDArray


def kabsch(
    src: NDArray[np.float64], dst: NDArray[np.float64], weights: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Weighted least-squares rotation and translation ``dst ~ R @ src + t`` (Umeyama, no scale).

    Parameters
    ----------
    src, dst : (N, 3) ndarray
        Corresponding points, N >= 3 (not all collinear for a unique rotation).
    weights : (N,) ndarray, optional
        Non-negative weights (default equal).

    Returns
    -------
    R : (3, 3) ndarray
        Proper rotation (det +1).
    t : (3,) ndarray
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T))) or 1.0])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def consistent_subset(
    before: NDArray[np.float64],
    after: NDArray[np.float64],
    sigma: NDArray[np.float64],
    turn: NDArray[np.float64],
    tol_mm: float,
    normals_before: NDArray[np.float64] | None = None,
    normals_after: NDArray[np.float64] | None = None,
) -> list[int]:
    """Largest subset of a unit's matches that one rigid motion can explain.

    Two matches ``i, j`` agree when the distance between them is preserved and their displacements
    differ by no more than a rotation can make them: ``|d_i - d_j| <= 2 sin(theta / 2) |p_i - p_j|``
    where ``theta`` bounds the unit's rotation from the turn of the two fiducials' normals (plus
    15 deg for normal noise), each within ``tol_mm`` plus three standard deviations along the line.
    Among subsets of equal size the one with the smallest total displacement wins (most units do
    not move: a still unit's hidden fiducial that grabbed a stranger loses to its matched ones),
    then the one with the smallest distance change.

    Parameters
    ----------
    before, after : (k, 3) ndarray
        Matched positions, mm.
    sigma : (k, 3) ndarray
        Standard deviations of the displacements, mm.
    turn : (k,) ndarray
        Angle between each fiducial's normal before and after, radians (NaN: unknown).
    normals_before, normals_after : (k, 3) ndarray, optional
        Unit normals; with them a subset must also fit one rigid motion (points within
        tolerance, normals within 15 deg).
    """
    k = len(before)
    if k <= 1:
        return list(range(k))
    vb = before[:, None] - before[None]
    db = np.linalg.norm(vb, axis=2)
    da = np.linalg.norm(after[:, None] - after[None], axis=2)
    disp = after - before
    move = np.linalg.norm(disp, axis=1)
    ddiff = np.linalg.norm(disp[:, None] - disp[None], axis=2)
    u = vb / np.maximum(db, 1e-9)[..., None]
    var = np.einsum("ijk,ik->ij", u**2, sigma**2) + np.einsum("ijk,jk->ij", u**2, sigma**2)
    tol = tol_mm + 3.0 * np.sqrt(var)
    err = np.abs(db - da)
    t = np.where(np.isfinite(turn), turn, np.pi)
    theta = np.minimum(np.maximum(t[:, None], t[None, :]) + np.radians(15.0), np.pi)
    if normals_before is not None:
        # Two faces that point alike (fiducials on one flat face of a cube) do not see a spin
        # about their normal: their normals' turn bounds only the tilt, so such a pair's
        # displacements may differ by any spin (its distance must still be kept).
        nb = normals_before / np.maximum(
            np.linalg.norm(normals_before, axis=1, keepdims=True), 1e-12
        )
        parallel = nb @ nb.T >= np.cos(np.radians(15.0))
        theta = np.where(parallel, np.pi, theta)
    ok = (err <= tol) & (ddiff <= 2.0 * np.sin(theta / 2.0) * db + tol)
    w = 1.0 / np.maximum(np.sum(sigma**2, axis=1), 1e-6)

    def fits(sub: tuple[int, ...]) -> bool:
        # With normals on both sides one rigid motion must carry every point and normal of the
        # subset to its partner: a wrong partner that only turned its normal is caught here.
        if not all(ok[i, j] for i, j in itertools.combinations(sub, 2)):
            return False
        if normals_before is None or normals_after is None or len(sub) < 2:
            return True
        ix = list(sub)
        R, tr = rigid_fit(before[ix], after[ix], w[ix], normals_before[ix], normals_after[ix])
        res = np.linalg.norm(before[ix] @ R.T + tr - after[ix], axis=1)
        lim = tol_mm + 3.0 * np.sqrt(np.sum(sigma[ix] ** 2, axis=1))
        cosang = np.einsum("ki,ki->k", normals_before[ix] @ R.T, normals_after[ix])
        return bool(np.all(res <= lim) and np.all(cosang >= np.cos(np.radians(15.0))))

    for size in range(k, 0, -1):
        best: tuple[float, float, list[int]] | None = None
        for sub in itertools.combinations(range(k), size):
            if fits(sub):
                key = (
                    float(sum(move[i] for i in sub)),
                    float(sum(err[i, j] for i, j in itertools.combinations(sub, 2))),
                )
                if best is None or key < best[:2]:
                    best = (key[0], key[1], list(sub))
        if best is not None:
            return best[2]
    return []


NORMAL_SIGMA_RAD = 0.05


@functools.lru_cache(maxsize=64)
def _point_pairs(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Every pair ``i < j`` of ``n`` points (read-only; a matching fits thousands of units of a
    handful of fiducials)."""
    i, j = np.triu_indices(n, k=1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def rigid_fit(
    src: NDArray[np.float64],
    dst: NDArray[np.float64],
    weights: NDArray[np.float64],
    src_normals: NDArray[np.float64] | None = None,
    dst_normals: NDArray[np.float64] | None = None,
    normal_sigma_rad: float = NORMAL_SIGMA_RAD,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rigid motion ``dst ~ R @ src + t`` from points and, optionally, their normals.

    The rotation solves Wahba's problem over direction pairs: the normals (weight
    ``1 / normal_sigma_rad**2``) and the vectors between the points (weight ``|v|^2`` over the
    summed variances of their two ends, so a 4 mm depth error over a 28 mm baseline counts as the
    8 deg it is); the translation then follows from the weighted centroids. Without normals and
    with >= 3 points this is the weighted Kabsch/Umeyama fit.
    """
    w = np.asarray(weights, dtype=np.float64)
    var = 1.0 / np.maximum(w, 1e-12)  # mm^2 per point
    i, j = _point_pairs(len(src))
    vs, vd = src[j] - src[i], dst[j] - dst[i]
    length2 = np.einsum("ki,ki->k", vs, vs)
    good = length2 > 1e-12
    vs, vd, length2 = vs[good], vd[good], length2[good]
    S = vs / np.sqrt(length2)[:, None]
    D = vd / np.maximum(np.linalg.norm(vd, axis=1), 1e-12)[:, None]
    # Angular variance of a vector between two points: (var_i + var_j) / |v|^2 (rad^2).
    W = length2 / (var[i[good]] + var[j[good]])
    if src_normals is not None and dst_normals is not None:
        S = np.vstack([S, src_normals])
        D = np.vstack([D, dst_normals])
        W = np.concatenate([W, np.full(len(src_normals), 1.0 / normal_sigma_rad**2)])
    if len(S) == 0:
        return np.eye(3), np.average(dst - src, axis=0, weights=w)
    H = (S * W[:, None]).T @ D
    U, _, Vt = np.linalg.svd(H)
    sign = float(np.sign(np.linalg.det(Vt.T @ U.T))) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, sign]) @ U.T
    t = np.average(dst - src @ R.T, axis=0, weights=w)
    return np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)


def rms_misfit(
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    before: NDArray[np.float64],
    after: NDArray[np.float64],
) -> float:
    """RMS distance (mm) between ``R @ before + t`` and ``after``, row by row."""
    return float(np.sqrt(np.mean(np.sum((before @ R.T + t - after) ** 2, axis=1))))


def across_line_of_sight(
    vectors: NDArray[np.float64], through: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The components of ``vectors`` (``(..., 3)``) across the line of sight from the camera
    (the origin) through the point ``through`` (``(3,)``): what one image measures precisely."""
    ray = np.asarray(through, dtype=np.float64)
    ray = ray / max(float(np.linalg.norm(ray)), 1e-12)
    v = np.asarray(vectors, dtype=np.float64)
    return np.asarray(v - (v @ ray)[..., None] * ray, dtype=np.float64)
