"""Pose of detected fiducials against ground truth: accuracy, ambiguity, distortion, covariance."""

from __future__ import annotations

import numpy as np
import pytest
from pose_synth import synthetic_detection

from armourcam.render import Target, rotation_from_slant_tilt
from pose_estimator import CameraModel, FiducialPose, PoseError, estimate, estimate_arrays
from pose_estimator.estimate import detections_to_arrays

F_PX = 6507.0  # the paper's benchmark camera
CAMERA = CameraModel.ideal(3008, 2000, F_PX)


def _target(
    design: str, slant_deg: float, position: tuple[float, float, float], tilt: float = 0.4
) -> Target:
    R = rotation_from_slant_tilt(np.radians(slant_deg), tilt=tilt, spin=1.0)
    return Target(7, design, 7.1, R, np.array(position))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


@pytest.mark.parametrize("design", ["ring", "dot"])
@pytest.mark.parametrize("slant_deg", [0.0, 30.0, 60.0, 80.0])
def test_exact_ellipses_give_exact_pose(design: str, slant_deg: float) -> None:
    """Noise-free ellipses give the true centre (not the ellipse centre's ray) to 1e-6 z."""
    target = _target(design, slant_deg, (60.0, -40.0, 770.0))
    det = synthetic_detection(CAMERA, target, 0.0, np.random.default_rng(0))
    (pose,) = estimate([det], CAMERA, 7.1)
    assert isinstance(pose, FiducialPose)
    assert pose.code == 7 and pose.detection is det
    np.testing.assert_allclose(pose.position_mm, target.position_mm, atol=1e-6 * 770.0)
    if design == "ring":
        assert _angle_deg(pose.normal, target.rotation[:, 2]) < 1e-3


@pytest.mark.parametrize(
    ("size_px", "slant_deg"), [(120, 20.0), (120, 65.0), (35, 20.0), (35, 65.0)]
)
def test_noisy_ellipses_error_bounds(size_px: int, slant_deg: float) -> None:
    """Errors stay within a few predicted sigmas and far inside the paper's Table 2 values."""
    z = F_PX * 7.1 / size_px
    rng = np.random.default_rng(1234)
    target = _target("ring", slant_deg, (20.0, 10.0, z))
    dets = [synthetic_detection(CAMERA, target, 0.05, rng) for _ in range(40)]
    poses = estimate(dets, CAMERA, 7.1)
    assert len(poses) == 40
    err = np.array([p.position_mm - target.position_mm for p in poses])
    sig = np.array([p.sigma_mm for p in poses])
    assert np.all(np.abs(err) < 5.0 * sig)
    paper_table2 = {120: 1.338, 35: 41.99}[size_px]  # blur 0.5, noise 1 %
    assert np.max(np.abs(err[:, 2])) < paper_table2 / 10.0
    # x and y are far better determined than z, as the paper observes.
    assert np.all(sig[:, :2] < sig[:, 2:3])


@pytest.mark.parametrize("slant_deg", [40.0, 60.0, 70.0, 75.0])
@pytest.mark.parametrize("tilt", [0.0, 1.3, 2.9])
def test_ambiguity_resolved_by_concentric_circles(slant_deg: float, tilt: float) -> None:
    """At high slant the ring design's inner circles pick the true normal out of the two."""
    rng = np.random.default_rng(7)
    target = _target("ring", slant_deg, (-80.0, 50.0, 770.0), tilt=tilt)
    dets = [synthetic_detection(CAMERA, target, 0.03, rng) for _ in range(10)]
    obs, cov, radius = detections_to_arrays(dets, 3.55)
    result = estimate_arrays(obs, cov, radius, CAMERA)
    for normal, amb in zip(result.normal, result.ambiguity, strict=True):
        assert _angle_deg(normal, target.rotation[:, 2]) < 1.0
        assert amb < 1e-3


def test_single_circle_ambiguity_is_honest() -> None:
    """With one circle (dot design) both solutions fit; the covariance covers their spread."""
    rng = np.random.default_rng(3)
    target = _target("dot", 50.0, (150.0, -90.0, 700.0))
    dets = [synthetic_detection(CAMERA, target, 0.02, rng) for _ in range(20)]
    obs, cov, radius = detections_to_arrays(dets, 3.55)
    result = estimate_arrays(obs, cov, radius, CAMERA)
    assert np.all(result.ambiguity > 0.3)
    err = result.position_mm - target.position_mm
    m2 = np.einsum("ni,nij,nj->n", err, np.linalg.inv(result.covariance_mm2), err)
    assert np.all(m2 < 16.3)  # chi-square(3) 99.9 %


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial"])
def test_lens_distortion_is_undone_on_the_boundaries(model: str) -> None:
    """Near a strongly distorted corner the pose is as accurate as with an ideal lens."""
    D = {
        "plumb_bob": [-0.25, 0.12, 0.001, -0.0008, 0.0],
        "rational_polynomial": [-0.25, 0.12, 0.001, -0.0008, 0.0, 0.05, -0.02, 0.01],
    }[model]
    cam = CameraModel(3008, 2000, CAMERA.K, model, np.array(D))
    target = _target("ring", 35.0, (-210.0, 140.0, 770.0))
    det = synthetic_detection(cam, target, 0.0, np.random.default_rng(0))
    (pose,) = estimate([det], cam, 7.1)
    assert np.linalg.norm(pose.position_mm - target.position_mm) < 0.01
    assert _angle_deg(pose.normal, target.rotation[:, 2]) < 0.05
    # Ignoring the distortion would be wrong by far more.
    (naive,) = estimate([det], CAMERA, 7.1)
    assert np.linalg.norm(naive.position_mm - target.position_mm) > 1.0


@pytest.mark.parametrize(
    ("design", "size_px", "slant_deg"),
    [
        ("ring", 120, 15.0),
        ("ring", 120, 60.0),
        ("ring", 45, 15.0),
        ("ring", 45, 60.0),
        ("dot", 60, 40.0),
    ],
)
def test_covariance_is_calibrated(design: str, size_px: int, slant_deg: float) -> None:
    """Predicted standard deviations agree with the empirical ones within +-30 %."""
    z = F_PX * 7.1 / size_px
    rng = np.random.default_rng(99)
    target = _target(design, slant_deg, (0.0, 0.0, z))
    dets = [synthetic_detection(CAMERA, target, 0.04, rng) for _ in range(200)]
    poses = estimate(dets, CAMERA, 7.1)
    emp = np.std([p.position_mm for p in poses], axis=0)
    pred = np.sqrt(np.mean([p.sigma_mm**2 for p in poses], axis=0))
    np.testing.assert_array_less(np.abs(pred / emp - 1.0), 0.3)


def test_bad_inputs_are_named() -> None:
    """A bad diameter, a non-detection, a detection without ellipses or a malformed ellipse
    raises PoseError naming the problem."""
    from dataclasses import replace

    det = synthetic_detection(
        CAMERA, _target("ring", 10.0, (0, 0, 700.0)), 0.0, np.random.default_rng(0)
    )
    with pytest.raises(PoseError, match="diameter_mm"):
        estimate([det], CAMERA, -7.1)
    with pytest.raises(PoseError, match="FiducialDetection"):
        estimate([det, "not a detection"], CAMERA, 7.1)  # type: ignore[list-item]
    with pytest.raises(PoseError, match=f"code {det.code + 1} has no ellipses"):
        estimate([det, replace(det, code=det.code + 1, ellipses=())], CAMERA, 7.1)
    first = det.ellipses[0]
    for bad in (replace(first, center_px=(1.0, 2.0, 3.0)), replace(first, semi_major="wide")):
        with pytest.raises(PoseError, match=r"centre|axes"):
            estimate([det, replace(det, ellipses=(bad, *det.ellipses[1:]))], CAMERA, 7.1)
    assert estimate([], CAMERA, 7.1) == []


def test_covariance_fallback_when_fit_reports_none() -> None:
    """Ellipses without a usable covariance still give a pose with a nominal covariance."""
    from dataclasses import replace

    target = _target("ring", 30.0, (0.0, 0.0, 700.0))
    det = synthetic_detection(CAMERA, target, 0.0, np.random.default_rng(0))
    blank = tuple(replace(e, covariance=np.zeros((5, 5))) for e in det.ellipses)
    (pose,) = estimate([replace(det, ellipses=blank)], CAMERA, 7.1)
    np.testing.assert_allclose(pose.position_mm, target.position_mm, atol=1e-3)
    assert np.all(np.isfinite(pose.sigma_mm)) and np.all(pose.sigma_mm > 0)


def _detected_poses(
    camera: CameraModel,
    target: Target,
    n: int,
    seed: int,
    noise: float = 0.01,
    jpeg_quality: int | None = None,
    blur: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Positions and sigmas of ``n`` rendered (optionally JPEG-compressed), detected and posed
    images."""
    import cv2

    from armourcam.render import render
    from fiducial_detector import detect

    rng = np.random.default_rng(seed)
    pos, sig = [], []
    for _ in range(n):
        scene = render(camera, [target], blur_sigma=blur, noise=noise, rng=rng)
        image = scene.image
        if jpeg_quality is not None:
            _, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
            image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        found = detect(image, design="ring" if target.design == "ring" else "dot")
        dets = [d for d in found if d.code == target.code]
        assert len(dets) == 1
        (pose,) = estimate(dets, camera, target.diameter_mm)
        pos.append(pose.position_mm)
        sig.append(pose.sigma_mm)
    return np.array(pos), np.array(sig)


@pytest.mark.parametrize(("design", "slant_deg"), [("ring", 30.0), ("ring", 60.0), ("dot", 30.0)])
def test_end_to_end_through_the_detector(design: str, slant_deg: float) -> None:
    """Rendered 60 px fiducials, the real detector, then pose: z well inside the paper's error."""
    z = F_PX * 7.1 / 60.0
    cam = CameraModel.ideal(110, 110, F_PX)
    target = _target(design, slant_deg, (0.3, -0.2, z))
    pos, sig = _detected_poses(cam, target, 6, seed=21)
    err = pos - target.position_mm
    # Paper Table 2, 60 px, blur 0.5, noise 1 %: 3.986 mm (its dot design).
    assert np.max(np.abs(err[:, 2])) < 3.986 / (4.0 if design == "ring" else 2.0)
    assert np.max(np.abs(err[:, :2])) < 0.05
    assert np.all(sig[:, 2] < 1.0)


@pytest.mark.parametrize(("size_px", "slant_deg"), [(60, 30.0), (35, 30.0)])
def test_sigma_is_honest_end_to_end_at_low_noise(size_px: int, slant_deg: float) -> None:
    """Rendered ``ring`` fiducials at 0.5 % noise, detected (edge profiles at 60 px, the edge
    model at 35 px) and posed: predicted sds of x, y and z within +-30 % of the empirical ones
    over 40 images. The fits' own typical misfit to a clean printed edge, the same in every
    image of a scene, no longer widens them (it made them 1.45-2.1 times too large here)."""
    z = F_PX * 7.1 / size_px
    n = int(1.5 * size_px) + 24
    cam = CameraModel.ideal(n, n, F_PX)
    target = _target("ring", slant_deg, (0.3, -0.2, z))
    pos, sig = _detected_poses(cam, target, 40, seed=7, noise=0.005)
    pred = np.sqrt(np.mean(sig**2, axis=0))
    emp = np.std(pos, axis=0, ddof=1)
    np.testing.assert_array_less(np.abs(pred / emp - 1.0), 0.3)


def test_dual_conic_pose_circle_carries_its_bias_to_the_pose() -> None:
    """A ``dot`` fiducial of 35 px at 44 deg under 0.7 px of blur: the profiles keep too few of
    its dot's lines, and the dual conic it falls back to fits the dot 0.05-0.08 px large, the
    same in every image. The depth is then off by many times the sd of the fit's scatter alone;
    with the fit's systematic error (``DUAL_CONIC_SYSTEMATIC_PX``), which the pose reports beside
    its scatter, within three sds of both together, at the same positions."""
    from dataclasses import replace

    from fiducial_detector.detect import DUAL_CONIC_SYSTEMATIC_PX

    z = F_PX * 7.1 / 35
    cam = CameraModel.ideal(76, 76, F_PX)
    target = _target("dot", 44.0, (0.3, -0.2, z), tilt=0.0)
    rng = np.random.default_rng(9)
    from armourcam.render import render
    from fiducial_detector import detect

    for _ in range(6):
        scene = render(cam, [target], blur_sigma=0.7, noise=0.01, rng=rng)
        (det,) = [d for d in detect(scene.image, design="dot") if d.code == target.code]
        assert det.ellipses[0].systematic_px == DUAL_CONIC_SYSTEMATIC_PX
        assert all(e.systematic_px == 0.0 for e in det.ellipses[1:])
        plain_fit = replace(det.ellipses[0], systematic_px=0.0)
        scatter_only = replace(det, ellipses=(plain_fit, *det.ellipses[1:]))
        (pose,) = estimate([det], cam, 7.1)
        (plain,) = estimate([scatter_only], cam, 7.1)
        np.testing.assert_array_equal(pose.position_mm, plain.position_mm)
        np.testing.assert_array_equal(pose.covariance_mm2, plain.covariance_mm2)
        assert plain.systematic_mm2 is None and pose.systematic_mm2 is not None
        dz = abs(pose.position_mm[2] - target.position_mm[2])
        assert dz > 3.0 * pose.sigma_mm[2]
        assert dz < 3.0 * np.hypot(pose.sigma_mm[2], pose.systematic_sigma_mm[2])


def test_pose_circle_systematic_error_gives_the_pose_its_systematic_covariance() -> None:
    """A pose circle's systematic error of sd ``delta`` (``Ellipse.systematic_px``) leaves the
    pose and its covariance (the scatter) where the fits put them; its systematic covariance is
    what a size error of that sd does to depth, ``d delta / a`` along the line of sight, and a
    centre error across it, ``d delta / f``. An inner circle's is not the pose circle's (it
    carries no depth)."""
    from dataclasses import replace

    rng = np.random.default_rng(11)
    delta = 0.05
    for slant in (10.0, 50.0, 70.0):
        det = synthetic_detection(CAMERA, _target("ring", slant, (30.0, -20.0, 900.0)), 0.02, rng)
        pose_circle, *inner = det.ellipses
        biased = replace(det, ellipses=(replace(pose_circle, systematic_px=delta), *inner))
        inner_sys = (pose_circle, replace(inner[0], systematic_px=delta), *inner[1:])
        (plain,) = estimate([det], CAMERA, 7.1)
        (wide,) = estimate([biased], CAMERA, 7.1)
        (same,) = estimate([replace(det, ellipses=inner_sys)], CAMERA, 7.1)
        np.testing.assert_array_equal(wide.position_mm, plain.position_mm)
        np.testing.assert_array_equal(wide.covariance_mm2, plain.covariance_mm2)
        assert plain.systematic_mm2 is None and same.systematic_mm2 is None
        assert wide.systematic_mm2 is not None
        d = float(np.linalg.norm(plain.position_mm))
        ray = plain.position_mm / d
        across = np.cross(ray, [1.0, 0.0, 0.0])
        across /= np.linalg.norm(across)
        extra = wide.systematic_mm2
        np.testing.assert_allclose(ray @ extra @ ray, (d * delta / pose_circle.semi_major) ** 2)
        np.testing.assert_allclose(across @ extra @ across, (d * delta / F_PX) ** 2)
        np.testing.assert_allclose(across @ extra @ ray, 0.0, atol=1e-12)


def test_depth_sigma_stays_honest_on_jpeg_frames() -> None:
    """JPEG (quality 92, as the recorded bags) smooths the noise of flat areas, which the noise
    estimate then understates about threefold, and adds artefacts at edges that do scatter from
    frame to frame: the depth sd of 35 px rings at 1 % noise is still predicted within +-30 %
    over 40 frames (the residuals beyond a clean edge's typical misfit widen it)."""
    z = F_PX * 7.1 / 35
    cam = CameraModel.ideal(76, 76, F_PX)
    target = _target("ring", 30.0, (0.3, -0.2, z))
    pos, sig = _detected_poses(cam, target, 40, seed=8, jpeg_quality=92)
    ratio = np.sqrt(np.mean(sig[:, 2] ** 2)) / np.std(pos[:, 2], ddof=1)
    assert abs(ratio - 1.0) < 0.3, ratio


def test_dot_track_arcs_carry_the_depth() -> None:
    """``dot`` design: the coding track's outer edge (3.3 times the dot, fitted on its black
    sectors) enters as a concentric circle of known radius and carries the depth: z scatter and
    predicted sd well below the dot's alone, the predicted sd honest, no bias."""
    from dataclasses import replace

    from armourcam.render import render
    from fiducial_detector import detect

    z = F_PX * 7.1 / 120.0
    cam = CameraModel.ideal(180, 180, F_PX)
    target = _target("dot", 40.0, (0.2, -0.1, z))
    rng = np.random.default_rng(5)
    both, alone = [], []
    for _ in range(8):
        scene = render(cam, [target], blur_sigma=0.5, noise=0.01, rng=rng)
        (det,) = detect(scene.image, design="dot")
        assert [e.radius for e in det.ellipses] == [0.30, 1.0]
        (with_arc,) = estimate([det], cam, 7.1)
        (dot_only,) = estimate([replace(det, ellipses=det.ellipses[:1])], cam, 7.1)
        both.append((with_arc.position_mm[2] - z, with_arc.sigma_mm[2]))
        alone.append((dot_only.position_mm[2] - z, dot_only.sigma_mm[2]))
    err, sig = np.array(both).T
    err_dot, sig_dot = np.array(alone).T
    assert np.median(sig) < 0.5 * np.median(sig_dot)
    assert np.sqrt(np.mean(err**2)) < 0.5 * np.sqrt(np.mean(err_dot**2))
    assert np.all(np.abs(err) < 4.0 * sig)
    assert abs(np.mean(err)) < 2.0 * np.median(sig)


def test_end_to_end_with_lens_distortion() -> None:
    """A fiducial in a strongly distorted corner, rendered through the lens, detected and posed."""
    K = np.array([[1500.0, 0.0, 319.5], [0.0, 1500.0, 239.5], [0.0, 0.0, 1.0]])
    cam = CameraModel(640, 480, K, "plumb_bob", np.array([-0.45, 0.3, 0.0, 0.0, 0.0]))
    target = _target("ring", 25.0, (-27.0, -19.8, 180.0))
    pos, _ = _detected_poses(cam, target, 3, seed=4)
    assert np.max(np.linalg.norm(pos - target.position_mm, axis=1)) < 0.1
    # The same detections read through an ideal lens are off by far more.
    from armourcam.render import render
    from fiducial_detector import detect

    scene = render(cam, [target], blur_sigma=0.5, noise=0.01, rng=np.random.default_rng(4))
    (naive,) = estimate(
        detect(scene.image, design="ring"), CameraModel(640, 480, K, "plumb_bob", np.zeros(5)), 7.1
    )
    assert np.linalg.norm(naive.position_mm - target.position_mm) > 0.5


def test_missing_inner_circles_mixed_in_one_batch() -> None:
    """Detections with 3, 2 and 1 fitted circles are posed together; fewer circles, less sure."""
    from dataclasses import replace

    target = _target("ring", 50.0, (10.0, 5.0, 770.0))
    det = synthetic_detection(CAMERA, target, 0.02, np.random.default_rng(0))
    dets = [det, replace(det, ellipses=det.ellipses[:2]), replace(det, ellipses=det.ellipses[:1])]
    poses = estimate(dets, CAMERA, 7.1)
    assert [len(p.detection.ellipses) for p in poses if p.detection] == [3, 2, 1]
    for pose in poses:
        assert np.all(np.abs(pose.position_mm - target.position_mm) < 4.0 * pose.sigma_mm)
    # One circle cannot tell the two poses apart: its x, y uncertainty includes their spread.
    assert poses[2].sigma_mm[0] > poses[0].sigma_mm[0]


def test_poses_from_rows_equal_constructed_poses() -> None:
    """The batch constructor fills every field as the dataclass constructor does."""
    import dataclasses

    rng = np.random.default_rng(1234)
    pos, nrm, cov = rng.normal(size=(3, 3)), rng.normal(size=(3, 3)), rng.normal(size=(3, 3, 3))
    codes = [4, 8, 15]
    batch = FiducialPose.from_rows(codes, pos, nrm, cov, [None, None, None])
    for i, pose in enumerate(batch):
        ref = FiducialPose(codes[i], pos[i], nrm[i], cov[i], None)
        for field in dataclasses.fields(FiducialPose):
            a, b = getattr(pose, field.name), getattr(ref, field.name)
            assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b, field.name
    with pytest.raises(ValueError, match="one length"):
        FiducialPose.from_rows(codes, pos[:2], nrm, cov, [None, None, None])


def test_detection_covariances_carried_to_shape_parameters() -> None:
    """detections_to_arrays applies J C J^T of the axes -> parameters Jacobian to each fit's
    covariance (also to a non-symmetric one), with NaN rows for missing circles."""
    from fiducial_detector.types import Ellipse, FiducialDetection
    from pose_estimator.conic_pose import axes_to_params_jacobian

    rng = np.random.default_rng(1234)
    dets = []
    for i, count in enumerate((3, 1, 2)):
        ells = []
        for k in range(count):
            a, b, angle = 30.0 - 5 * k, 20.0 - 4 * k, rng.uniform(0, np.pi)
            cov = rng.normal(size=(5, 5)) * 1e-3
            ells.append(Ellipse((100.0 * i, 50.0), a, b, angle, cov, 1.0 - 0.2 * k))
        dets.append(FiducialDetection(i, 0, (100.0 * i, 50.0), tuple(ells), 0.7, "ring"))
    obs, cov, radius = detections_to_arrays(dets, 3.55)
    assert obs.shape == (3, 3, 5) and cov.shape == (3, 3, 5, 5)
    for i, d in enumerate(dets):
        for k, e in enumerate(d.ellipses):
            J = axes_to_params_jacobian(e.semi_major, e.semi_minor, e.angle)
            np.testing.assert_allclose(cov[i, k], J @ e.covariance @ J.T, rtol=1e-12, atol=1e-18)
            assert radius[i, k] == pytest.approx(3.55 * e.radius)
        assert np.all(np.isnan(obs[i, len(d.ellipses) :]))
        assert np.all(np.isnan(cov[i, len(d.ellipses) :]))


def _scattered_detections(camera: CameraModel, count: int, seed: int) -> list:
    """Ring detections over the whole frame (600-900 mm, slant 0-70 deg) with honest noise."""
    rng = np.random.default_rng(seed)
    dets = []
    for i in range(count):
        z = rng.uniform(600.0, 900.0)
        x = rng.uniform(-0.4, 0.4) * camera.width * z / camera.K[0, 0]
        y = rng.uniform(-0.4, 0.4) * camera.height * z / camera.K[1, 1]
        R = rotation_from_slant_tilt(np.radians(rng.uniform(0.0, 70.0)), rng.uniform(0, 6.28))
        target = Target(i % 66, "ring", 7.1, R, np.array([x, y, z]))
        dets.append(synthetic_detection(camera, target, 0.02, rng))
    return dets


@pytest.mark.parametrize("lens", [False, True])
def test_batch_equals_per_fiducial_reference(lens: bool) -> None:
    """Posing a whole frame at once gives each fiducial the pose, normal and covariance it gets
    alone (the batched arithmetic shares nothing between fiducials), also through the lens."""
    cam = CAMERA
    if lens:
        cam = CameraModel(3008, 2000, CAMERA.K, "plumb_bob", np.array([-0.2, 0.1, 1e-3, -8e-4, 0]))
    dets = _scattered_detections(cam, 24, 5)
    batch = estimate(dets, cam, 7.1)
    assert len(batch) == len(dets)
    for det, pose in zip(dets, batch, strict=True):
        (alone,) = estimate([det], cam, 7.1)
        assert pose.detection is det and pose.code == alone.code
        # To rounding: the lens correction iterates until every point of the batch converged,
        # and the inverse of the refinement's information amplifies a last-bit change of its input
        # into ~1e-10 of itself, which the inverse amplifies by its condition (~1e5).
        np.testing.assert_allclose(pose.position_mm, alone.position_mm, rtol=0, atol=1e-7)
        np.testing.assert_allclose(pose.normal, alone.normal, rtol=0, atol=1e-9)
        scale = np.max(np.abs(alone.covariance_mm2))
        np.testing.assert_allclose(pose.covariance_mm2, alone.covariance_mm2, atol=2e-4 * scale)


@pytest.mark.parametrize("free_scale", [True, False])
def test_profiled_scales_equal_the_full_gauss_newton(free_scale: bool) -> None:
    """The refinement with the inner circles' scales profiled out in closed form takes the step,
    covariance (sandwich) and chi-square of the full problem solved densely per fiducial."""
    from pose_estimator.conic_pose import circle_params, plane_basis
    from pose_estimator.estimate import _gauss_newton

    rng = np.random.default_rng(1234)
    n_fid, radii = 12, np.array([3.55, 2.84, 0.85])
    centers = np.column_stack(
        [rng.uniform(-60, 60, n_fid), rng.uniform(-40, 40, n_fid), rng.uniform(600, 900, n_fid)]
    )
    normals = []
    for _ in range(n_fid):
        R = rotation_from_slant_tilt(np.radians(rng.uniform(5, 70)), rng.uniform(0, 6.28))
        normals.append(-R[:, 2] * np.sign(R[2, 2]))
    normals = np.array(normals)
    obs = np.stack(
        [circle_params(centers, normals, r * rng.uniform(0.98, 1.02, n_fid)) for r in radii]
    )  # (K, N, 5), normalised coordinates
    obs += rng.normal(0.0, 2e-6, obs.shape)
    G = rng.normal(size=(3, n_fid, 5, 5))
    W = (G @ np.swapaxes(G, -1, -2) + 0.5 * np.eye(5)) * 1e10  # information, (K, N, 5, 5)
    lam = np.stack([np.ones(n_fid), rng.uniform(0.1, 1, n_fid), rng.uniform(0.1, 1, n_fid)])
    start_c = centers + rng.normal(0.0, 0.05, centers.shape)
    start_n = normals + rng.normal(0.0, 1e-3, normals.shape)
    start_n /= np.linalg.norm(start_n, axis=1, keepdims=True)
    r_kn = np.repeat(radii[:, None], n_fid, axis=1)
    c, nrm, cov, chi2 = _gauss_newton(
        np.ascontiguousarray(obs.transpose(2, 0, 1)),
        np.ascontiguousarray(W.transpose(2, 3, 0, 1)),
        lam,
        r_kn,
        start_c.T.copy(),
        start_n.T.copy(),
        1,
        free_scale,
    )
    for i in range(n_fid):
        c0, n0 = start_c[i], start_n[i]
        e1, e2 = (np.array(e) for e in plane_basis(tuple(n0)))
        # Central differences (the refinement's Jacobian is analytic): rotations of the normal
        # by +-da towards e1 and e2, radii scaled by exp(+-da).
        h, da = 1e-4 * c0[2], 1e-4
        npar = 5 + (2 if free_scale else 0)
        A, B, g, chi2_lin = np.zeros((npar, npar)), np.zeros((npar, npar)), np.zeros(npar), 0.0
        for k in range(3):
            base = circle_params(c0, n0, radii[k])
            J = np.zeros((5, npar))
            for j in range(3):
                dc = np.zeros(3)
                dc[j] = h
                J[:, j] = (
                    circle_params(c0 + dc, n0, radii[k]) - circle_params(c0 - dc, n0, radii[k])
                ) / (2 * h)
            for j, e in enumerate((e1, e2)):
                plus = circle_params(c0, n0 * np.cos(da) + e * np.sin(da), radii[k])
                minus = circle_params(c0, n0 * np.cos(da) - e * np.sin(da), radii[k])
                J[:, 3 + j] = (plus - minus) / (2 * da)
            if free_scale and k > 0:
                plus = circle_params(c0, n0, radii[k] * np.exp(da))
                minus = circle_params(c0, n0, radii[k] * np.exp(-da))
                J[:, 4 + k] = (plus - minus) / (2 * da)
            res = obs[k, i] - base
            A += lam[k, i] * J.T @ W[k, i] @ J
            B += lam[k, i] ** 2 * J.T @ W[k, i] @ J
            g += lam[k, i] * J.T @ W[k, i] @ res
            chi2_lin += lam[k, i] * res @ W[k, i] @ res
        delta = np.linalg.solve(A, g)
        Ainv = np.linalg.inv(A)
        want_cov = (Ainv @ B @ Ainv)[:3, :3]
        # Equal but for the refinement's guard damping (1e-12 of the trace) and rounding, both
        # amplified by the condition number of A (~1e6: depth against size).
        tol = 1e-5 * np.max(np.abs(delta[:3]))
        np.testing.assert_allclose(c[:, i], c0 + delta[:3], rtol=0, atol=tol)
        new_n = n0 + delta[3] * e1 + delta[4] * e2
        np.testing.assert_allclose(nrm[:, i], new_n / np.linalg.norm(new_n), rtol=0, atol=1e-7)
        np.testing.assert_allclose(cov[:, :, i], want_cov, rtol=0, atol=1e-5 * want_cov.max())
        # res^T W res - g^T delta cancels: compare on the scale of its terms.
        assert chi2[i] == pytest.approx(max(chi2_lin - g @ delta, 0.0), abs=1e-6 * chi2_lin)


def test_vectorised_lens_correction_equals_per_ellipse_reference() -> None:
    """All fitted boundaries undistorted in one call give, ellipse by ellipse, the conic refitted
    through the same boundary samples undistorted by OpenCV one ellipse at a time."""
    import cv2

    from pose_estimator.conic_pose import ellipse_points, fit_conics, params_from_conic
    from pose_estimator.estimate import _UNDISTORT_SAMPLES, _undistort

    cam = CameraModel(3008, 2000, CAMERA.K, "plumb_bob", np.array([-0.2, 0.1, 1e-3, -8e-4, 0.0]))
    dets = _scattered_detections(cam, 10, 7)
    obs, cov, _ = detections_to_arrays(dets, 3.55)
    obs_t = np.ascontiguousarray(obs.transpose(2, 1, 0))
    cov_t = np.ascontiguousarray(cov.transpose(2, 3, 1, 0))
    got, _ = _undistort(obs_t, cov_t, np.ones(obs_t.shape[1:], dtype=bool), cam)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    iterate = getattr(cv2, "undistortPointsIter", None)
    for i in range(obs.shape[0]):
        for k in range(obs.shape[1]):
            pts = ellipse_points(obs[i, k], _UNDISTORT_SAMPLES).reshape(-1, 1, 2)
            if iterate is not None:
                und = iterate(pts, cam.K, cam.D, None, cam.K, criteria)
            else:
                und = cv2.undistortPoints(pts, cam.K, cam.D, None, np.eye(3), cam.K, criteria)
            want = params_from_conic(fit_conics(und.reshape(-1, 2)))
            np.testing.assert_allclose(got[:, k, i], want, rtol=0, atol=2e-6)


def _central_difference_jacobian(
    center: np.ndarray,
    normal: np.ndarray,
    radius: np.ndarray,
    e1: np.ndarray,
    e2: np.ndarray,
    *,
    scale: bool = False,
    image: object = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The refinement's Jacobian by central differences (stand-in for the analytic one; the
    circles' image the estimator already has is not used)."""
    from pose_estimator.conic_pose import circle_params_t

    def pred(c: np.ndarray, n: np.ndarray, r: np.ndarray) -> np.ndarray:
        return circle_params_t(c[:, None], n[:, None], r)

    h, da = 1e-4 * center[2], 1e-4
    cols = []
    for k in range(3):
        dc = np.zeros_like(center)
        dc[k] = h
        cols.append(
            (pred(center + dc, normal, radius) - pred(center - dc, normal, radius)) / (2 * h)
        )
    for e in (e1, e2):
        plus = pred(center, normal * np.cos(da) + e * np.sin(da), radius)
        minus = pred(center, normal * np.cos(da) - e * np.sin(da), radius)
        cols.append((plus - minus) / (2 * da))
    if scale:
        plus, minus = (
            pred(center, normal, radius * np.exp(da)),
            pred(center, normal, radius * np.exp(-da)),
        )
        cols.append((plus - minus) / (2 * da))
    return pred(center, normal, radius), np.stack(cols, axis=1)


@pytest.mark.parametrize("case", ["ideal", "plumb_bob", "missing_inner"])
def test_analytic_refinement_equals_central_differences(
    case: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Poses, normals and covariances with the refinement's analytic Jacobian equal those with a
    central-difference one, with the inner circles weighing in (fits of 0.3 px edge noise)."""
    import importlib
    from dataclasses import replace

    module = importlib.import_module("pose_estimator.estimate")
    cam = CAMERA
    if case == "plumb_bob":
        cam = CameraModel(3008, 2000, CAMERA.K, "plumb_bob", np.array([-0.2, 0.1, 1e-3, -8e-4, 0]))
    rng = np.random.default_rng(21)
    dets = []
    for i in range(24):
        z = rng.uniform(600.0, 900.0)
        R = rotation_from_slant_tilt(np.radians(rng.uniform(0.0, 70.0)), rng.uniform(0, 6.28))
        xy = rng.uniform(-0.4, 0.4, 2) * np.array([cam.width, cam.height]) * z / cam.K[0, 0]
        target = Target(i % 66, "ring", 7.1, R, np.array([*xy, z]))
        det = synthetic_detection(cam, target, 0.3, rng)
        if case == "missing_inner":
            det = replace(det, ellipses=det.ellipses[: 1 + i % 3])
        dets.append(det)
    obs, cov, radius = detections_to_arrays(dets, 3.55)
    got = estimate_arrays(obs, cov, radius, cam)
    monkeypatch.setattr(module, "circle_params_jacobian_t", _central_difference_jacobian)
    want = estimate_arrays(obs, cov, radius, cam)
    assert got.valid.all() and want.valid.all()
    # The inner circles took part: without them (a huge floor) the poses differ.
    pose_circle_only = estimate_arrays(obs, cov, radius, cam, inner_floor_px=1e3)
    assert np.abs(pose_circle_only.position_mm - want.position_mm).max() > 1e-3
    np.testing.assert_allclose(got.position_mm, want.position_mm, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.normal, want.normal, rtol=0, atol=1e-8)
    scale = np.abs(want.covariance_mm2).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(got.covariance_mm2 - want.covariance_mm2) <= 1e-5 * scale)


def test_affine_params_jacobian_equals_central_differences() -> None:
    """The analytic Jacobian of ellipses mapped by a linear map (lens correction, unequal focal
    lengths) equals central differences of the map."""
    from pose_estimator.estimate import _affine_params, _affine_params_jacobian

    rng = np.random.default_rng(1234)
    n = 50
    a, b, ang = rng.uniform(5, 80, n), rng.uniform(1, 5, n), rng.uniform(0, np.pi, n)
    p = np.stack([*rng.normal(0, 500, (2, n)), *params_from_axes_t(a, b, ang)])
    A = np.eye(2)[:, :, None] + rng.normal(0.0, 0.05, (2, 2, n))
    J = _affine_params_jacobian(p, A)
    for j in range(5):
        dp = np.zeros_like(p)
        dp[j] = 1e-5
        num = (_affine_params(p + dp, A) - _affine_params(p - dp, A)) / 2e-5
        np.testing.assert_allclose(J[:, j], num, rtol=0, atol=1e-8)


def params_from_axes_t(a: np.ndarray, b: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Square-root shapes ``(3, N)`` of ellipses with semi-axes ``a``, ``b`` at ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([a * c * c + b * s * s, (a - b) * c * s, a * s * s + b * c * c])


def test_records_path_equals_estimate_on_objects() -> None:
    """The pose node's path (detection records -> ellipse columns -> estimate_ellipses -> pose
    records, no objects) gives exactly the records of estimate() on the decoded detections,
    with mixed circle counts, a dot and a degenerate row left out alike."""
    from dataclasses import replace

    from armourcam import records
    from pose_estimator import estimate_ellipses

    rng = np.random.default_rng(3)
    dets = []
    for k, (design, slant) in enumerate([("ring", 10.0), ("ring", 55.0), ("dot", 35.0)] * 3):
        target = _target(design, slant, (20.0 * k - 80.0, 15.0 - 4.0 * k, 700.0 + 9.0 * k))
        dets.append(synthetic_detection(CAMERA, target, 0.02, rng))
    dets[4] = replace(dets[4], ellipses=dets[4].ellipses[:2])
    # A dual-conic pose circle's systematic error travels with the records too.
    stand_in = replace(dets[2].ellipses[0], systematic_px=0.05)
    dets[2] = replace(dets[2], ellipses=(stand_in, *dets[2].ellipses[1:]))
    flat = replace(dets[7].ellipses[0], semi_minor=0.0)  # not an ellipse: no pose
    dets[7] = replace(dets[7], ellipses=(flat,))
    recs = records.detections_to_records(dets)
    decoded = records.records_to_detections(recs)
    assert [e.systematic_px for e in decoded[2].ellipses] == [0.05] + [0.0] * (
        len(dets[2].ellipses) - 1
    )
    expected = records.poses_to_records(estimate(decoded, CAMERA, 7.1), decoded)

    got = records.estimate_pose_records(recs, CAMERA, 7.1)
    keep = got["detection_index"]
    assert 7 not in keep.tolist() and len(got) == len(dets) - 1
    for name in expected.dtype.names:
        np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
    none = estimate_ellipses(*records.detection_ellipse_columns(recs[:0]), 3.55, CAMERA)
    assert none.position_mm.shape == (0, 3) and none.valid.shape == (0,)
    recs["n_ellipses"][0] = 4
    with pytest.raises(records.RecordError, match="n_ellipses 4"):
        records.detection_ellipse_columns(recs)
    with pytest.raises(PoseError, match="outer radius"):
        estimate_ellipses(*records.detection_ellipse_columns(recs[1:]), 0.0, CAMERA)


def test_detections_outside_the_cameras_image_are_refused() -> None:
    """Detections from an image larger than the calibration's (a camera info that belongs to
    another camera) would be posed with the wrong principal point and focal length: the node's
    records path refuses the frame, naming the pixel and the calibration's size."""
    from armourcam import records
    from pose_estimator.camera import CameraModel
    from pose_estimator.errors import CalibrationError

    rng = np.random.default_rng(5)
    target = _target("ring", 20.0, (30.0, -10.0, 700.0))
    recs = records.detections_to_records([synthetic_detection(CAMERA, target, 0.02, rng)])
    assert len(records.estimate_pose_records(recs, CAMERA, 7.1)) == 1
    u, v = float(recs["u"][0]), float(recs["v"][0])
    small = CameraModel.ideal(int(u), 4000, 6507.0)  # the detection lies right of its image
    with pytest.raises(
        CalibrationError, match=rf"\({u:.1f}, {v:.1f}\) px lies outside .*{int(u)}x4000"
    ):
        records.estimate_pose_records(recs, small, 7.1)
    CameraModel.ideal(int(u) + 2, 4000, 6507.0).check_pixels([u, -0.5], [v, 3999.5])  # edges in
    recs["v"][0] = np.nan
    with pytest.raises(CalibrationError, match="not a pixel"):
        CAMERA.check_pixels(recs["u"], recs["v"])
