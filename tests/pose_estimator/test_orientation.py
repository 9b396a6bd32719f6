"""The printed axis of a fiducial against ground truth: exact back-projection, the other branch of
the circle's ambiguity, and end to end through the detector."""

from __future__ import annotations

import numpy as np
import pytest

from armourcam.render import Target, render, rotation_from_slant_tilt
from displacement_matcher.units import mirror_normals
from fiducial_detector import detect
from pose_estimator import CameraModel, PoseError, estimate
from pose_estimator.orientation import mirror_axes, printed_axes, target_frames

F_PX = 6507.0
IDEAL = CameraModel.ideal(3008, 2000, F_PX)
LENS = CameraModel(
    3008,
    2000,
    np.array([[F_PX, 0.0, 1504.0], [0.0, F_PX, 1000.0], [0.0, 0.0, 1.0]]),
    "plumb_bob",
    np.array([-0.25, 0.12, 0.001, -0.0015, 0.0]),
)


def _random_frames(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations of targets facing the camera within 70 deg, spread over a 3008x2000 view."""
    rot = np.array(
        [
            rotation_from_slant_tilt(
                np.radians(rng.uniform(0, 70)), rng.uniform(0, 2 * np.pi), rng.uniform(0, 7)
            )
            for _ in range(n)
        ]
    )
    z = rng.uniform(500.0, 1500.0, n)
    pos = np.column_stack([rng.uniform(-0.2, 0.2, n) * z, rng.uniform(-0.14, 0.14, n) * z, z])
    return rot, pos


def _image_angles(camera: CameraModel, rot: np.ndarray, pos: np.ndarray) -> tuple:
    """Where each centre images (distorted pixels) and the image angle there of its +x axis
    (the tangent of the axis's image at the centre)."""
    c = camera.project(pos)
    tip = camera.project(pos + 1e-4 * rot[:, :, 0])
    d = tip - c
    return c, np.arctan2(d[:, 1], d[:, 0])


@pytest.mark.parametrize("camera", [IDEAL, LENS], ids=["ideal", "plumb_bob"])
def test_exact_image_angles_give_the_true_axis(camera: CameraModel) -> None:
    """Back-projecting the axis's image direction onto the plane recovers it (perspective and
    lens included), orthogonal to the normal."""
    rot, pos = _random_frames(np.random.default_rng(4), 200)
    centre, angle = _image_angles(camera, rot, pos)
    axes = printed_axes(camera, pos, rot[:, :, 2], centre, angle)
    cos = np.einsum("ki,ki->k", axes, rot[:, :, 0])
    assert np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max() < 1e-4
    assert np.abs(np.einsum("ki,ki->k", axes, rot[:, :, 2])).max() < 1e-12
    np.testing.assert_allclose(target_frames(rot[:, :, 2], axes), rot, atol=1e-5)


def test_mirror_axes_are_the_same_image_direction_on_the_other_plane() -> None:
    """The other branch's axis is what the same image angle gives on the mirrored plane, and
    mirroring twice returns the axis."""
    rot, pos = _random_frames(np.random.default_rng(8), 200)
    normal, axis = rot[:, :, 2], rot[:, :, 0]
    centre, angle = _image_angles(IDEAL, rot, pos)
    other = mirror_normals(pos, normal)
    mirrored = mirror_axes(pos, axis, other)
    expected = printed_axes(IDEAL, pos, other, centre, angle)
    np.testing.assert_allclose(mirrored, expected, atol=1e-9)
    assert np.abs(np.einsum("ki,ki->k", mirrored, other)).max() < 1e-12
    np.testing.assert_allclose(mirror_axes(pos, mirrored, normal), axis, atol=1e-9)


def test_undefined_axes_are_nan_and_bad_shapes_are_refused() -> None:
    rot, pos = _random_frames(np.random.default_rng(2), 3)
    centre, angle = _image_angles(IDEAL, rot, pos)
    angle[1] = np.nan
    edge_on = rot[:, :, 2].copy()
    # Plane 2 seen edge on: its normal orthogonal to the ray to the centre and to the axis's.
    ray = pos[2] / np.linalg.norm(pos[2])
    edge_on[2] = np.cross(ray, [0.0, 0.0, 1.0])
    edge_on[2] /= np.linalg.norm(edge_on[2])
    axes = printed_axes(IDEAL, pos, edge_on, centre, np.where(np.arange(3) == 2, 0.0, angle))
    assert np.isfinite(axes[0]).all() and np.isnan(axes[1]).all() and np.isnan(axes[2]).all()
    with pytest.raises(PoseError, match=r"\(N, 3\) positions"):
        printed_axes(IDEAL, pos[:2], rot[:, :, 2], centre, angle)


@pytest.mark.parametrize("size_px", [40, 70])
def test_axis_end_to_end_through_the_detector(size_px: int) -> None:
    """Rendered fiducials at random spins and slants up to 60 deg: each pose's axis lies within
    the code reading's precision of the printed +x axis (where the normal is on its true
    branch, a tenth of a degree or so), and its frame is a rotation."""
    rng = np.random.default_rng(size_px)
    z = F_PX * 7.1 / size_px
    camera = CameraModel.ideal(900, 700, F_PX)
    errors = []
    for _ in range(24):
        R = rotation_from_slant_tilt(
            np.radians(rng.uniform(0, 60)), rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
        )
        target = Target(5, "ring", 7.1, R, np.array([rng.uniform(-10, 10), 0.0, z]))
        scene = render(camera, [target], blur_sigma=0.5, noise=0.01, rng=rng)
        (pose,) = estimate(detect(scene.image), camera, 7.1)
        assert pose.axis is not None and pose.frame is not None
        np.testing.assert_allclose(pose.frame.T @ pose.frame, np.eye(3), atol=1e-9)
        assert np.linalg.det(pose.frame) == pytest.approx(1.0)
        if pose.normal @ R[:, 2] > np.cos(np.radians(5.0)):
            errors.append(np.degrees(np.arccos(np.clip(pose.axis @ R[:, 0], -1.0, 1.0))))
    assert len(errors) >= 20
    # The code's boundaries are located to a fraction of the phase search's step (2.8 deg,
    # whose uniform error alone has a median of 0.7 deg); a sector off would be 22.5.
    assert max(errors) < 1.0
    assert np.median(errors) < 0.2
