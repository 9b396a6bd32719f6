"""Fusion of several frames of a static scene into one pose per fiducial.

Between wave runs the camera sees the same scene for many frames. Each fiducial's per-frame
positions are combined by inverse-covariance weighting, which is the minimum-variance unbiased
combination when the per-frame covariances are honest. Robustness to a bad frame (a wrong
ambiguity branch, a fiducial half-occluded by a passing hand) comes from iterated Mahalanobis
rejection around a median start; the fused covariance is inflated by the reduced chi-square of the
inliers when their scatter exceeds what their covariances predict, so it stays honest.

Frames: camera frame (OpenCV: x right, y down, z forward), millimetres.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import PoseError
from .types import FiducialPose

F64 = NDArray[np.float64]

#: 99.9 % quantile of the chi-square distribution with 3 degrees of freedom.
CHI2_3_999 = 16.266


def fuse_poses(poses: Sequence[FiducialPose], *, gate: float = CHI2_3_999) -> FiducialPose:
    """Fuse poses of one fiducial from several frames of a static scene.

    Parameters
    ----------
    poses : sequence of FiducialPose
        The same fiducial seen in different frames (same code).
    gate : float
        Squared Mahalanobis distance beyond which a frame is rejected as an outlier.

    Returns
    -------
    FiducialPose
        Inverse-covariance-weighted position of the inlier frames, their mean normal, the fused
        covariance (inflated by the reduced chi-square when that exceeds 1) and ``n_frames`` = the
        number of inlier frames; ``detection`` is None.

    Raises
    ------
    PoseError
        If ``poses`` is empty or mixes codes.
    """
    if not poses:
        raise PoseError("no poses to fuse")
    codes = {p.code for p in poses}
    if len(codes) != 1:
        raise PoseError(f"cannot fuse poses of different codes {sorted(codes)}")
    X = np.array([p.position_mm for p in poses], dtype=np.float64)
    C = np.array([p.covariance_mm2 for p in poses], dtype=np.float64)
    N = np.array([p.normal for p in poses], dtype=np.float64)
    info = np.linalg.inv(C + np.eye(3) * 1e-12 * np.trace(C, axis1=1, axis2=2)[:, None, None])
    inlier = np.ones(len(poses), dtype=bool)
    # Start from the coordinate-wise median (breakdown point 1/2), then iterate weighted means.
    centre = np.median(X, axis=0)
    for _ in range(10):
        d = X - centre
        m2 = np.einsum("ni,nij,nj->n", d, info, d)
        new = m2 <= gate
        if not np.any(new):
            new = m2 <= np.min(m2)
        centre, _ = _weighted_mean(X[new], info[new])
        if np.array_equal(new, inlier):
            break
        inlier = new
    centre, cov = _weighted_mean(X[inlier], info[inlier])
    k = int(inlier.sum())
    if k > 1:
        d = X[inlier] - centre
        chi2 = float(np.einsum("ni,nij,nj->", d, info[inlier], d))
        cov = cov * max(1.0, chi2 / (3.0 * (k - 1)))
    normal = np.sum(N[inlier], axis=0)
    normal /= np.linalg.norm(normal)
    return FiducialPose(
        code=poses[0].code,
        position_mm=centre,
        normal=normal,
        covariance_mm2=cov,
        detection=None,
        n_frames=k,
    )


def _weighted_mean(X: F64, info: F64) -> tuple[F64, F64]:
    """Inverse-covariance weighted mean of ``X`` (``(n, 3)``) and its covariance."""
    total = np.sum(info, axis=0)
    cov = np.linalg.inv(total)
    mean = cov @ np.einsum("nij,nj->i", info, X)
    return mean, 0.5 * (cov + cov.T)


def fuse(
    frames: Sequence[Sequence[FiducialPose]],
    *,
    gate_mm: float = 3.0,
    min_fraction: float = 0.5,
    gate: float = CHI2_3_999,
) -> list[FiducialPose]:
    """Fuse per-frame pose lists of a static scene into one pose per fiducial.

    Poses are associated across frames by code and 3-D proximity (codes repeat in a scene of
    hundreds of targets); each track is then fused by :func:`fuse_poses`.

    Parameters
    ----------
    frames : sequence of sequences of FiducialPose
        The poses estimated in each frame.
    gate_mm : float
        Largest distance (mm) between a pose and a track's first position for them to be the
        same fiducial; well below the spacing of equal codes, well above per-frame errors.
    min_fraction : float
        Tracks seen in fewer than this fraction of the frames are dropped (spurious detections).
    gate : float
        Outlier gate of :func:`fuse_poses`.

    Returns
    -------
    list of FiducialPose
        Fused poses, ordered by code then by first appearance.

    Raises
    ------
    PoseError
        If there are no frames or a parameter is out of range.
    """
    if not frames:
        raise PoseError("no frames to fuse")
    if gate_mm <= 0 or not 0.0 <= min_fraction <= 1.0:
        raise PoseError(
            f"need gate_mm > 0 and 0 <= min_fraction <= 1, got {gate_mm}, {min_fraction}"
        )
    tracks: list[list[FiducialPose]] = []
    anchors: list[tuple[int, F64]] = []
    for frame in frames:
        claimed: set[int] = set()
        for pose in frame:
            best, best_d = -1, gate_mm
            for t, (code, anchor) in enumerate(anchors):
                if code != pose.code or t in claimed:
                    continue
                dist = float(np.linalg.norm(pose.position_mm - anchor))
                if dist <= best_d:
                    best, best_d = t, dist
            if best < 0:
                tracks.append([pose])
                anchors.append((pose.code, np.median([pose.position_mm], axis=0)))
                claimed.add(len(tracks) - 1)
            else:
                tracks[best].append(pose)
                claimed.add(best)
                anchors[best] = (
                    pose.code,
                    np.median([p.position_mm for p in tracks[best]], axis=0),
                )
    need = min_fraction * len(frames)
    fused = [fuse_poses(t, gate=gate) for t in tracks if len(t) >= need]
    order = sorted(range(len(fused)), key=lambda i: fused[i].code)
    return [fused[i] for i in order]
