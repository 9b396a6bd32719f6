"""Fusion of several frames of a static scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pose_synth import synthetic_detection

from armourcam.field import make_field
from armourcam.render import Target, rotation_from_slant_tilt
from pose_estimator import CameraModel, FiducialPose, PoseError, estimate, fuse, fuse_poses
from pose_estimator.fusion import fuse_frames

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


def test_fusion_keeps_a_bias_common_to_the_frames() -> None:
    """A pose's systematic covariance (a known bias of its fit, the same in every frame) is not
    averaged down by fusing frames, as the scatter is: the fused pose keeps the frames' mean."""
    from dataclasses import replace

    rng = np.random.default_rng(6)
    bias = np.diag([0.01, 0.01, 4.0])
    frames = [
        [replace(p, systematic_mm2=bias) if k == 0 else p for k, p in enumerate(frame)]
        for frame in _frames(8, rng)
    ]
    fused = sorted(fuse(frames), key=lambda p: p.position_mm[0])
    assert [p.systematic_mm2 is not None for p in fused] == [True, False, False]
    np.testing.assert_allclose(fused[0].systematic_mm2, bias)
    assert fused[0].covariance_mm2[2, 2] < frames[0][0].covariance_mm2[2, 2] / 4.0
    np.testing.assert_allclose(fused[0].systematic_sigma_mm, [0.1, 0.1, 2.0])


def test_fusion_averages_the_printed_axes() -> None:
    """The fused pose's axis is the frames' mean, in the fused normal's plane; frames that
    disagree (a code read a half turn apart in every other frame) leave it unknown rather than
    blended."""
    from dataclasses import replace

    rng = np.random.default_rng(9)
    truth = [t.rotation[:, 0] for t in TARGETS]
    frames = []
    for f, frame in enumerate(_frames(6, rng)):
        spun = []
        for k, p in enumerate(frame):
            # Each frame's reading a degree or so off the truth, about the normal.
            angle = np.radians(rng.normal(0.0, 1.0))
            a = np.cos(angle) * truth[k] + np.sin(angle) * np.cross(p.normal, truth[k])
            a -= (a @ p.normal) * p.normal
            if k == 2 and f % 2:
                a = -a
            spun.append(replace(p, axis=a / np.linalg.norm(a)))
        frames.append(spun)
    for pose in fuse(frames):
        k = min(range(3), key=lambda j: np.linalg.norm(TARGETS[j].position_mm - pose.position_mm))
        if k == 2:
            assert pose.axis is None
            continue
        assert pose.axis is not None
        assert abs(float(pose.axis @ pose.normal)) < 1e-12
        assert np.degrees(np.arccos(np.clip(pose.axis @ truth[k], -1.0, 1.0))) < 1.5


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


def _field_frames(n: int, rng: np.random.Generator, seed: int = 3) -> list[list[FiducialPose]]:
    """``n`` frames of a 40-dolos field (about 90 fiducials, codes repeated on every unit) with
    the pose estimator's anisotropic noise."""
    state = make_field(40, seed=seed, hidden_fraction=0.05).before
    return [state.poses(rng, sigma_xy_mm=0.05, sigma_z_mm=0.3) for _ in range(n)]


def _camera_moved(
    poses: list[FiducialPose], deg: float, shift_mm: list[float]
) -> list[FiducialPose]:
    """The poses seen by a camera turned by ``deg`` about its y axis and shifted: every fiducial
    moves by the same rigid motion of the camera frame."""
    R = np.asarray(cv2.Rodrigues(np.array([0.0, np.radians(deg), 0.0]))[0])
    t = np.asarray(shift_mm, dtype=np.float64)
    return [
        FiducialPose(p.code, R @ p.position_mm + t, R @ p.normal, R @ p.covariance_mm2 @ R.T)
        for p in poses
    ]


def test_frames_of_one_scene_from_one_place_agree() -> None:
    """No false alarm: frames that differ only by their noise all agree, on the estimator's own
    poses (3 fiducials) and on a field, and their fusion is :func:`fuse`'s."""
    rng = np.random.default_rng(11)
    for k in range(12):
        frames = _frames(3 + k % 3, rng) if k % 2 else _field_frames(2 + k % 3, rng)
        fusion = fuse_frames(frames)
        assert not fusion.disagreeing and not fusion.camera_moved, [
            a.describe() for a in fusion.disagreeing
        ]
        assert fusion.consensus == fusion.fused == tuple(range(len(frames)))
        plain = fuse(frames)
        assert len(fusion.poses) == len(plain)
        for a, b in zip(fusion.poses, plain, strict=True):
            np.testing.assert_array_equal(a.position_mm, b.position_mm)
    # One frame: returned as it is, nothing to compare.
    (only,) = _frames(1, rng)
    single = fuse_frames([only])
    assert single.poses == tuple(only) and single.frames[0].verdict == "agrees"


@pytest.mark.parametrize(
    ("deg", "shift"),
    [(0.0, [0.6, 0.0, 0.0]), (0.0, [3.0, -2.0, 1.0]), (0.3, [0.0, 0.0, 0.0])],
    ids=["0.6mm", "3.7mm", "0.3deg"],
)
def test_a_frame_from_a_moved_camera_is_named_with_its_motion(
    deg: float, shift: list[float]
) -> None:
    """A bumped camera between the frames (a shift below and beyond the association gate, a
    small turn): the frame is ``moved`` by about the motion's size, the others agree; with
    ``align`` its motion is removed before fusing, so the fusion is that of the good frames."""
    rng = np.random.default_rng(4)
    frames = _field_frames(4, rng)
    original = frames[2]
    frames[2] = _camera_moved(original, deg, shift)
    fusion = fuse_frames(frames)
    assert [a.verdict for a in fusion.frames] == ["agrees", "agrees", "moved", "agrees"]
    assert fusion.camera_moved and fusion.consensus == (0, 1, 3)
    moved = fusion.frames[2]
    assert moved.reference == (0, 1, 3) and moved.n_shared >= 0.9 * moved.n_poses
    expect = max(
        float(np.linalg.norm(p.position_mm - q.position_mm))
        for p, q in zip(frames[2], original, strict=True)
    )
    assert moved.motion_mm == pytest.approx(expect, rel=0.05, abs=0.02)
    assert moved.motion_chi2 > 1000
    text = moved.describe(["b1.png", "b2.png", "b3.png", "b4.png"])
    assert text.startswith(f"b3.png is moved {moved.motion_mm:.2f} mm against b1.png, b2.png, b4")
    assert "as when the camera moves" in text
    aligned = fuse_frames(frames, align=True)
    assert aligned.aligned == (2,) and aligned.fused == (0, 1, 2, 3)
    good = fuse([frames[i] for i in (0, 1, 3)])
    assert len(aligned.poses) == len(good)
    for a, b in zip(aligned.poses, good, strict=True):
        assert a.code == b.code and a.n_frames == 4
        assert np.linalg.norm(a.position_mm - b.position_mm) < 4 * np.sqrt(
            np.trace(b.covariance_mm2)
        )


def test_a_frame_of_another_scene_is_unmatched() -> None:
    """A frame of another scene (another field, another seed) among frames of one: ``unmatched``,
    naming how few of its fiducials are found; with two frames the first is the reference. With
    ``align`` it is left out of the fusion (plain fusion keeps its fiducials, seen once in two
    frames)."""
    rng = np.random.default_rng(6)
    a, b = _field_frames(2, rng)
    (other,) = _field_frames(1, rng, seed=9)
    three = fuse_frames([a, other, b])
    assert [f.verdict for f in three.frames] == ["agrees", "unmatched", "agrees"]
    assert three.camera_moved and three.consensus == (0, 2)
    text = three.frames[1].describe(["b1.png", "b2.png", "b3.png"])
    assert text.startswith(f"only {three.frames[1].n_shared} of the {len(other)} fiducials of ")
    assert "b2.png are found among" in text and "another scene" in text
    two = fuse_frames([a, other])
    assert [f.verdict for f in two.frames] == ["agrees", "unmatched"]
    assert len(two.poses) > 1.5 * len(a)  # the two scenes mixed, as fuse() does
    kept = fuse_frames([a, other], align=True)
    assert kept.fused == (0,) and len(kept.poses) == len(fuse([a]))


def test_a_frame_with_many_stray_fiducials_disagrees_without_a_camera_motion() -> None:
    """A quarter of a frame's fiducials 2 mm off in depth (not a motion of the camera): the
    frame ``disagrees`` with its count of fiducials beyond the gate; not ``moved``. A frame with
    no fiducial among frames with some also disagrees."""
    rng = np.random.default_rng(8)
    frames = _field_frames(3, rng)
    frames[1] = [
        FiducialPose(p.code, p.position_mm + (k % 4 == 0) * np.array([0.0, 0.0, 2.0]), p.normal,
                     p.covariance_mm2)
        for k, p in enumerate(frames[1])
    ]  # fmt: skip
    fusion = fuse_frames(frames)
    assert [f.verdict for f in fusion.frames] == ["agrees", "disagrees", "agrees"]
    assert not fusion.camera_moved
    bad = fusion.frames[1]
    assert bad.n_outliers > 0.1 * bad.n_shared and bad.motion_mm < 0.2
    assert f"{bad.n_outliers} of its {bad.n_shared} shared fiducials beyond" in bad.describe()
    blank = fuse_frames([frames[0], [], frames[2]])
    assert [f.verdict for f in blank.frames] == ["agrees", "disagrees", "agrees"]
    assert blank.frames[1].describe().startswith("no fiducial found in frame 1")
    with pytest.raises(PoseError, match="no frames"):
        fuse_frames([])
    with pytest.raises(PoseError, match=r"warn_mm=1\.0, moved_mm=0\.5"):
        fuse_frames(frames, warn_mm=1.0)


def test_a_fiducial_whose_depth_wanders_between_frames_is_fused_once() -> None:
    """A partly covered fiducial's depth can differ by several millimetres from frame to frame
    while its direction from the camera holds to hundredths: the frames are still paired into
    one track (depth counts DEPTH_SCALE times less than the offset across the line of sight),
    not split into two poses of one fiducial; a neighbour of the same code 10 mm away across
    the line of sight stays apart."""
    cov = np.diag([0.01, 0.01, 0.36])
    here, there = np.array([0.0, 0.0, 600.0]), np.array([10.0, 0.0, 600.0])
    frames = []
    for k in range(4):
        depth = 600.0 + (6.0 if k % 2 else 0.0)  # two frames 6 mm deeper than the others
        frames.append(
            [
                FiducialPose(3, here * depth / 600.0, np.array([0.0, 0.0, -1.0]), cov),
                FiducialPose(3, there, np.array([0.0, 0.0, -1.0]), cov),
            ]
        )
    fused = fuse(frames)
    assert len(fused) == 2, [p.position_mm for p in fused]
    near = min(fused, key=lambda p: abs(p.position_mm[0]))
    assert abs(near.position_mm[0]) < 1e-9 and 600.0 <= near.position_mm[2] <= 606.0
    # Their disagreement widens the fused depth sd well past the 0.3 mm their own sds give.
    assert np.sqrt(near.covariance_mm2[2, 2]) > 0.9
