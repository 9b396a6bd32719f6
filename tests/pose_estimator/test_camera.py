"""Camera model: calibration files, errors for bad calibrations, lens distortion round trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from pose_estimator.camera import CameraModel
from pose_estimator.errors import CalibrationError

K = [[5769.0, 0.0, 1503.5], [0.0, 5771.0, 999.5], [0.0, 0.0, 1.0]]
MODELS = {
    "plumb_bob": [-0.12, 0.08, 0.0005, -0.0003, 0.01],
    "rational_polynomial": [-0.12, 0.08, 0.0005, -0.0003, 0.01, 0.02, -0.01, 0.005],
}


@pytest.mark.parametrize("model", sorted(MODELS))
def test_yaml_round_trip(tmp_path: Path, model: str) -> None:
    """A camera written as camera_calibration YAML reads back identically."""
    cam = CameraModel(3008, 2000, np.array(K), model, np.array(MODELS[model]))
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(cam.to_dict()))
    back = CameraModel.from_yaml(path)
    assert (back.width, back.height, back.distortion_model) == (3008, 2000, model)
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.D, cam.D)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_distortion_round_trip(model: str) -> None:
    """Projecting with distortion and undistorting returns the ideal normalised coordinates."""
    cam = CameraModel(3008, 2000, np.array(K), model, np.array(MODELS[model]))
    rng = np.random.default_rng(1234)
    xy = rng.uniform([-0.25, -0.17], [0.25, 0.17], size=(500, 2))
    uv = cam.distort_normalized(xy)
    # The distortion is real: over ten pixels at the corners.
    ideal = xy * np.diag(cam.K)[:2] + cam.K[:2, 2]
    assert np.max(np.linalg.norm(uv - ideal, axis=1)) > 10.0
    np.testing.assert_allclose(cam.undistort_normalized(uv), xy, atol=1e-10)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_undistort_guess_only_saves_iterations(model: str) -> None:
    """A starting guess near the answer converges to the same undistorted pixels."""
    cam = CameraModel(3008, 2000, np.array(K), model, np.array(MODELS[model]))
    rng = np.random.default_rng(1234)
    uv = rng.uniform([0.0, 0.0], [3007.0, 1999.0], size=(500, 2))
    plain = cam.undistort_pixels(uv)
    guess = plain + rng.normal(0.0, 0.05, plain.shape)
    np.testing.assert_allclose(cam.undistort_pixels(uv, guess), plain, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ({"image_width": 640}, "missing or malformed"),
        (
            {
                "image_width": 640,
                "image_height": 480,
                "camera_matrix": {"rows": 3, "cols": 3, "data": [1, 0, 0, 0, 1, 0]},
            },
            "9 elements",
        ),
        (
            {
                "image_width": 640,
                "image_height": 480,
                "camera_matrix": {
                    "rows": 3,
                    "cols": 3,
                    "data": [500, 0, 320, 0, 500, 240, 0, 0, 1],
                },
                "distortion_model": "fisheye_magic",
                "distortion_coefficients": {"data": [0, 0, 0, 0]},
            },
            "unsupported distortion model",
        ),
        (
            {
                "image_width": 640,
                "image_height": 480,
                "camera_matrix": {
                    "rows": 3,
                    "cols": 3,
                    "data": [500, 0, 320, 0, 500, 240, 0, 0, 1],
                },
                "distortion_model": "plumb_bob",
                "distortion_coefficients": {"data": [0.1, 0.0, 0.0]},
            },
            "needs 5",
        ),
        (
            {
                "image_width": 640,
                "image_height": 480,
                "camera_matrix": {"rows": 3, "cols": 3, "data": [-5, 0, 320, 0, 500, 240, 0, 0, 1]},
            },
            "not a pinhole",
        ),
        (
            {
                "image_width": 0,
                "image_height": 480,
                "camera_matrix": {
                    "rows": 3,
                    "cols": 3,
                    "data": [500, 0, 320, 0, 500, 240, 0, 0, 1],
                },
            },
            "must be positive",
        ),
    ],
)
def test_malformed_calibration_is_named(tmp_path: Path, doc: dict[str, object], match: str) -> None:
    """Each kind of malformed calibration raises CalibrationError naming the file and problem."""
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationError, match=match) as info:
        CameraModel.from_yaml(path)
    assert "bad.yaml" in str(info.value)


def test_unreadable_calibration(tmp_path: Path) -> None:
    """A missing file and a non-mapping document are reported, not crashed on."""
    with pytest.raises(CalibrationError, match="cannot read"):
        CameraModel.from_yaml(tmp_path / "absent.yaml")
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(CalibrationError, match="not a YAML mapping"):
        CameraModel.from_yaml(path)


def test_mismatched_image_size() -> None:
    """An image whose size differs from the calibration's is refused with both sizes named."""
    cam = CameraModel.ideal(3008, 2000, 5769.0)
    cam.check_image_size(3008, 2000)
    with pytest.raises(CalibrationError, match=r"1504x1000.*3008x2000"):
        cam.check_image_size(1504, 1000)


def test_camera_info_fields() -> None:
    """CameraInfo fields (row-major k, 8-element plumb_bob d padded with zeros) are accepted."""
    d = [0.1, -0.05, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0]
    cam = CameraModel.from_camera_info(640, 480, np.ravel(K), "plumb_bob", d)
    assert cam.D.shape == (5,)
    ideal = CameraModel.from_camera_info(640, 480, np.ravel(K), "", [])
    assert not ideal.has_distortion
