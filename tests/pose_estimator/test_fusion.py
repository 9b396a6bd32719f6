"""Fusion of several frames of a static scene."""

from __future__ import annotations

import numpy as np
import pytest
from pose_synth import synthetic_detection

from armourcam.render import Target, rotation_from_slant_tilt
from pose_estimator import CameraModel, FiducialPose, PoseError, estimate, fuse, fuse_poses

CAMERA = CameraModel.ideal(3008, 2000, 6507.0)
TARGETS = [
    Target(4, "ring", 7.1, rotation_from_slant_tilt(np.radians(s), 0.5), np.array(p))
    for s, p in [
        (20.0, (-60.0, 10.0, 800.0)),
        (55.0, (40.0, -30.0, 820.0)),
        (35.0, (40.0, 50.0, 790.0)),
    ]
]


def _frames(n: int, rng: np.random.Generator) -> list[list[FiducialPose]]:
    return [
        estimate([synthetic_detection(CAMERA, t, 0.05, rng) for t in TARGETS], CAMERA, 7.1)
        for _ in range(n)
    ]


def test_fusion_averages_frames_with_honest_covariance() -> None:
    """Fusing 16 frames shrinks the error by about 4 and the covariance stays consistent."""
    rng = np.random.default_rng(5)
    m2 = []
    for _ in range(6):
        fused = fuse(_frames(16, rng))
        # Two targets share code 4: they are told apart by position.
        assert len(fused) == 3
        for pose in fused:
            truth = min(TARGETS, key=lambda t: np.linalg.norm(t.position_mm - pose.position_mm))
            d = pose.position_mm - truth.position_mm
            m2.append(d @ np.linalg.solve(pose.covariance_mm2, d))
            assert pose.n_frames >= 15  # the 99.9 % gate may drop one good frame
            assert abs(np.linalg.norm(pose.normal) - 1.0) < 1e-12
    # Mean squared Mahalanobis distance of a consistent 3-D estimate is 3.
    assert 1.8 < np.mean(m2) < 4.5


def test_fusion_rejects_an_outlier_frame() -> None:
    """A frame with a grossly wrong pose (e.g. the wrong ambiguity branch) is left out."""
    rng = np.random.default_rng(8)
    frames = _frames(9, rng)
    good = fuse(frames)
    bad = frames[4][0]
    frames[4][0] = FiducialPose(
        bad.code, bad.position_mm + np.array([0.0, 0.0, 1.5]), bad.normal, bad.covariance_mm2
    )
    fused = fuse(frames)
    assert sorted(p.n_frames for p in fused) == [8, 9, 9]
    for a, b in zip(good, fused, strict=True):
        assert np.linalg.norm(a.position_mm - b.position_mm) < 3 * np.sqrt(
            np.trace(a.covariance_mm2)
        )


def test_fusion_drops_spurious_tracks_and_names_bad_input() -> None:
    """A detection seen in one frame of ten does not become a fused fiducial; bad calls raise."""
    rng = np.random.default_rng(2)
    frames = _frames(10, rng)
    frames[3].append(
        FiducialPose(9, np.array([0.0, 0.0, 500.0]), np.array([0, 0, -1.0]), np.eye(3))
    )
    assert all(p.code == 4 for p in fuse(frames))
    with pytest.raises(PoseError, match="no frames"):
        fuse([])
    with pytest.raises(PoseError, match="different codes"):
        fuse_poses([frames[0][0], frames[3][-1]])
