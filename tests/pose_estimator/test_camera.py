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


@pytest.mark.parametrize("model", sorted(MODELS))
def test_undistort_components_match_opencv(model: str) -> None:
    """The component-wise undistortion (any array shape, one vectorised Newton call) equals
    OpenCV's iterative inverse run to convergence, and the ``(N, 2)`` methods built on it."""
    import cv2

    cam = CameraModel(3008, 2000, np.array(K), model, np.array(MODELS[model]))
    rng = np.random.default_rng(1234)
    u = rng.uniform(0.0, 3007.0, size=(7, 40))
    v = rng.uniform(0.0, 1999.0, size=(7, 40))
    got_u, got_v = cam.undistort_components(u, v)
    assert got_u.shape == got_v.shape == (7, 40)
    src = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    # OpenCV 4 names the variant with termination criteria undistortPointsIter; OpenCV 5 folds
    # the criteria into undistortPoints. Normalised coordinates either way.
    iterate = getattr(cv2, "undistortPointsIter", None)
    if iterate is not None:
        ref = iterate(src, cam.K, cam.D, None, None, criteria)
    else:
        ref = cv2.undistortPoints(src, cam.K, cam.D, None, np.eye(3), np.eye(3), criteria)
    ref = ref.reshape(-1, 2) * np.diag(cam.K)[:2] + cam.K[:2, 2]
    np.testing.assert_allclose(got_u.ravel(), ref[:, 0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(got_v.ravel(), ref[:, 1], rtol=0, atol=1e-7)
    pairs = cam.undistort_pixels(np.stack([u.ravel(), v.ravel()], axis=-1))
    np.testing.assert_array_equal(pairs, np.stack([got_u.ravel(), got_v.ravel()], axis=-1))
    # Normalised output, and a guess in the output's unit, give the same points.
    x, y = cam.undistort_components(u, v, (got_u + 0.03, got_v - 0.02))
    np.testing.assert_allclose(x, got_u, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, got_v, rtol=0, atol=1e-9)
    nx, ny = cam.undistort_components(u, v, pixels=False)
    np.testing.assert_allclose(nx * cam.K[0, 0] + cam.K[0, 2], got_u, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ny * cam.K[1, 1] + cam.K[1, 2], got_v, rtol=0, atol=1e-9)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_undistortion_jacobian_matches_finite_differences(model: str) -> None:
    """The analytic Jacobian of the undistortion (pixels to ideal pixels) equals central
    differences of the undistortion itself, over the whole frame."""
    cam = CameraModel(3008, 2000, np.array(K), model, np.array(MODELS[model]))
    rng = np.random.default_rng(1234)
    u = rng.uniform(0.0, 3007.0, size=(3, 50))
    v = rng.uniform(0.0, 1999.0, size=(3, 50))
    iu, iv, A = cam.undistortion_jacobian(u, v)
    np.testing.assert_array_equal(np.stack([iu, iv]), np.stack(cam.undistort_components(u, v)))
    h = 1e-3
    pu, pv = cam.undistort_components(u + h, v)
    mu, mv = cam.undistort_components(u - h, v)
    qu, qv = cam.undistort_components(u, v + h)
    nu, nv = cam.undistort_components(u, v - h)
    num = np.stack([pu - mu, qu - nu, pv - mv, qv - nv]) / (2 * h)
    np.testing.assert_allclose(A, num, rtol=0, atol=1e-8)
    assert np.max(np.abs(A[1])) > 1e-3  # a real shear near the corners


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


def test_invalid_yaml_is_one_line_naming_file_and_place(tmp_path: Path) -> None:
    """PyYAML's several-line message becomes one line with the file, line and column."""
    path = tmp_path / "broken.yaml"
    path.write_text("image_width: 1200\nimage_height: [800\n")
    with pytest.raises(CalibrationError) as info:
        CameraModel.from_yaml(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"cannot read calibration {path}: not valid YAML at line 3, column 1")


@pytest.mark.parametrize("n_coefficients", [4, 5, 8])
def test_opencv_calibration_files_are_read(tmp_path: Path, n_coefficients: int) -> None:
    """The YAML OpenCV's calibration writes (cv2.FileStorage, !!opencv-matrix) gives the same
    camera as the camera_calibration file of the same numbers."""
    import cv2

    coeffs = {4: MODELS["plumb_bob"][:4], 5: MODELS["plumb_bob"]}
    d = coeffs.get(n_coefficients, MODELS["rational_polynomial"])
    path = tmp_path / "opencv.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 3008)
    fs.write("image_height", 2000)
    fs.write("camera_matrix", np.array(K))
    fs.write("distortion_coefficients", np.array([d]))
    fs.release()
    cam = CameraModel.from_yaml(path)
    model = "rational_polynomial" if n_coefficients == 8 else "plumb_bob"
    want = CameraModel.from_camera_info(
        3008, 2000, np.ravel(K), model, (d + [0.0] * 5)[: max(5, len(d))]
    )
    assert (cam.width, cam.height, cam.distortion_model) == (3008, 2000, model)
    np.testing.assert_array_equal(cam.K, want.K)
    np.testing.assert_array_equal(cam.D, want.D)

    (tmp_path / "short.yaml").write_text("%YAML:1.0\n---\nimage_width: 3008\n")
    with pytest.raises(CalibrationError, match=r"short\.yaml: missing field image_height"):
        CameraModel.from_yaml(tmp_path / "short.yaml")


def test_opencv_matrix_whose_shape_disagrees_with_its_data_is_named(tmp_path: Path) -> None:
    """An !!opencv-matrix of rows x cols other than its data's length (OpenCV itself asserts)
    is a CalibrationError naming the file, not OpenCV's traceback."""
    path = tmp_path / "short_matrix.yaml"
    path.write_text(
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 500., 0., 320., 0., 500., 240. ]\n"
    )
    with pytest.raises(CalibrationError, match=r"short_matrix\.yaml: malformed OpenCV matrix"):
        CameraModel.from_yaml(path)


def test_a_key_given_twice_is_an_error_naming_both_lines(tmp_path: Path) -> None:
    """PyYAML lets the last of two equal keys win silently: a pasted second
    distortion_coefficients would change every depth without a word."""
    good = CameraModel.from_camera_info(3008, 2000, np.ravel(K), "plumb_bob", MODELS["plumb_bob"])
    text = yaml.safe_dump(good.to_dict(), sort_keys=False)
    path = tmp_path / "twice.yaml"
    path.write_text(text + "distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n")
    first = 1 + text.splitlines().index(
        next(s for s in text.splitlines() if s.startswith("distortion_coefficients"))
    )
    last = len(text.splitlines()) + 1
    with pytest.raises(CalibrationError) as info:
        CameraModel.from_yaml(path)
    assert str(info.value) == (
        f"cannot read calibration {path}: not valid YAML at line {last}, column 1: key "
        f"'distortion_coefficients' given twice (first at line {first})"
    )
