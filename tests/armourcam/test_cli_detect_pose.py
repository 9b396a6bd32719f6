"""``armourcam detect --camera``: pose fields of each detection, and calibration errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from armourcam.cli import main
from armourcam.render import Target, render, rotation_from_slant_tilt
from pose_estimator.camera import CameraModel

FOCAL_PX = 6507.0
Z_MM = FOCAL_PX * 7.1 / 60.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Target]:
    """A 60 px ring fiducial slanted 35 deg, its image file and its calibration file."""
    cam = CameraModel.ideal(160, 140, FOCAL_PX)
    rot = rotation_from_slant_tilt(np.radians(35.0), tilt=0.6)
    target = Target(5, "ring", 7.1, rot, np.array([0.4, -0.3, Z_MM]))
    image = render(cam, [target], blur_sigma=0.5, noise=0.01, rng=np.random.default_rng(3)).image
    folder = tmp_path_factory.mktemp("pose_cli")
    path = folder / "scene.png"
    cv2.imwrite(str(path), image)
    calib = folder / "camera.yaml"
    calib.write_text(yaml.safe_dump(cam.to_dict()))
    return path, calib, target


def test_pose_fields_match_ground_truth(
    scene: tuple[Path, Path, Target], capsys: pytest.CaptureFixture[str]
) -> None:
    """position_mm, normal, axis and sigma_mm come with each detection and agree with the
    truth."""
    path, calib, target = scene
    status = main(["detect", str(path), "--camera", str(calib), "--diameter-mm", "7.1", "--json"])
    out, _ = capsys.readouterr()
    assert status == 0
    (det,) = json.loads(out)["images"][0]["detections"]
    pos = np.array(det["position_mm"])
    sigma = np.array(det["sigma_mm"])
    assert np.all(sigma > 0) and sigma[2] < 1.0
    assert np.all(np.abs(pos - target.position_mm) < np.maximum(5 * sigma, [0.02, 0.02, 0.5]))
    assert float(np.array(det["normal"]) @ target.rotation[:, 2]) > np.cos(np.radians(2.0))
    assert float(np.array(det["axis"]) @ target.rotation[:, 0]) > np.cos(np.radians(2.5))


def test_without_camera_no_pose_fields(
    scene: tuple[Path, Path, Target], capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --camera the records are the detector's alone."""
    path, _, _ = scene
    assert main(["detect", str(path), "--json"]) == 0
    (det,) = json.loads(capsys.readouterr()[0])["images"][0]["detections"]
    assert "position_mm" not in det


def test_wrong_diameter_scales_depth(
    scene: tuple[Path, Path, Target], capsys: pytest.CaptureFixture[str]
) -> None:
    """Depth scales with the printed diameter given."""
    path, calib, target = scene
    main(["detect", str(path), "--camera", str(calib), "--diameter-mm", "14.2", "--json"])
    (det,) = json.loads(capsys.readouterr()[0])["images"][0]["detections"]
    assert abs(det["position_mm"][2] / target.position_mm[2] - 2.0) < 0.01


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--camera", "{missing}"], "cannot read calibration"),
        (["--camera", "{bad}"], "missing or malformed"),
        (["--camera", "{calib}", "--diameter-mm", "-3"], "positive"),
    ],
)
def test_bad_calibration_arguments(
    scene: tuple[Path, Path, Target],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    match: str,
) -> None:
    """A missing or malformed calibration or a bad diameter is a one-line usage error."""
    path, calib, _ = scene
    bad = tmp_path / "bad.yaml"
    bad.write_text("image_width: 160\n")
    names = {"missing": str(tmp_path / "none.yaml"), "bad": str(bad), "calib": str(calib)}
    with pytest.raises(SystemExit) as info:
        main(["detect", str(path), *[a.format(**names) for a in args]])
    assert info.value.code == 2
    assert match in capsys.readouterr()[1]


def test_calibration_for_another_image_size_is_a_per_file_error(
    scene: tuple[Path, Path, Target], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An image whose size differs from the calibration's gets a one-line error naming both
    sizes; the other images are still processed."""
    path, _, _ = scene
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(CameraModel.ideal(320, 240, FOCAL_PX).to_dict()))
    status = main(["detect", str(path), str(path), "--camera", str(other), "--json"])
    images = json.loads(capsys.readouterr()[0])["images"]
    assert status == 1
    assert len(images) == 2
    for res in images:
        assert res["detections"] == []
        assert str(path) in res["error"]
        assert "160x140" in res["error"] and "320x240" in res["error"]


def test_image_fit_refines_pose(
    scene: tuple[Path, Path, Target], capsys: pytest.CaptureFixture[str]
) -> None:
    """--image-fit gives every pose field, within its sigma of the truth; it needs --camera."""
    path, calib, target = scene
    status = main(["detect", str(path), "--camera", str(calib), "--image-fit", "--json"])
    (det,) = json.loads(capsys.readouterr()[0])["images"][0]["detections"]
    assert status == 0
    pos, sigma = np.array(det["position_mm"]), np.array(det["sigma_mm"])
    assert np.all(sigma > 0) and sigma[2] < 1.0
    assert np.all(np.abs(pos - target.position_mm) < np.maximum(5 * sigma, [0.02, 0.02, 0.5]))
    assert float(np.array(det["normal"]) @ target.rotation[:, 2]) > np.cos(np.radians(2.0))
    assert main(["detect", str(path), "--image-fit"]) == 2
    assert "--image-fit needs --camera" in capsys.readouterr()[1]
