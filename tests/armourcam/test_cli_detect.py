"""``armourcam detect``: JSON and table output, every image format, and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from jpeg_damage import scan_start, with_comment, without_scan

from armourcam.cli import main
from armourcam.imageio import ImageReadError, read_image
from armourcam.render import Target, render
from pose_estimator.camera import CameraModel

FOCAL_PX = 6507.0


@pytest.fixture(scope="module")
def scene_image() -> np.ndarray:
    """A ring fiducial (code 5) and a dot fiducial (code 9), 60 px, side by side."""
    z = FOCAL_PX * 7.1 / 60
    dx = 60 * z / FOCAL_PX
    targets = [
        Target(5, "ring", 7.1, position_mm=np.array([-dx, 0.0, z])),
        Target(9, "dot", 7.1, position_mm=np.array([dx, 0.0, z])),
    ]
    scene = render(
        CameraModel.ideal(300, 200, FOCAL_PX),
        targets,
        blur_sigma=0.5,
        noise=0.01,
        rng=np.random.default_rng(0),
    )
    return scene.image


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    status = main(["detect", *args])
    out, err = capsys.readouterr()
    return status, out, err


def test_json_output(tmp_path: Path, scene_image: np.ndarray, capsys) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "scene.png"
    cv2.imwrite(str(path), scene_image)
    status, out, _ = _run(capsys, str(path), "--json")
    assert status == 0
    doc = json.loads(out)
    (image,) = doc["images"]
    assert image["path"] == str(path) and image["error"] is None
    dets = sorted(image["detections"], key=lambda d: d["center_px"][0])
    assert [(d["code"], d["design"]) for d in dets] == [(5, "ring"), (9, "dot")]
    assert np.allclose(dets[0]["center_px"], [89.5, 99.5], atol=0.05)
    assert np.allclose(dets[1]["center_px"], [209.5, 99.5], atol=0.05)
    ring = dets[0]
    assert [e["radius"] for e in ring["ellipses"]] == [1.0, 0.8, 0.24]
    for key in (
        "center_px",
        "semi_major",
        "semi_minor",
        "angle",
        "radius",
        "sigma_center_px",
        "systematic_px",
    ):
        assert key in ring["ellipses"][0]
    assert ring["hamming"] == 0 and 0.5 < ring["contrast"] < 0.9
    _, out, _ = _run(capsys, str(path), "--json", "--design", "dot")
    assert [d["code"] for d in json.loads(out)["images"][0]["detections"]] == [9]
    # The 60 px fiducials are found on the frame reduced 2x as on the full one.
    _, out, _ = _run(capsys, str(path), "--json", "--decimate", "2")
    reduced = sorted(json.loads(out)["images"][0]["detections"], key=lambda d: d["center_px"][0])
    assert [d["code"] for d in reduced] == [5, 9]
    for a, b in zip(dets, reduced, strict=True):
        assert np.allclose(a["center_px"], b["center_px"], atol=0.01)
    with pytest.raises(SystemExit) as exit_info:
        _run(capsys, str(path), "--decimate", "5")
    assert exit_info.value.code == 2
    assert "--decimate" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("name", "convert"),
    [
        ("grey.jpg", lambda im: im),
        ("colour.jpg", lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)),
        ("grey16.png", lambda im: im.astype(np.uint16) * 257),
        ("colour16.png", lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR).astype(np.uint16) * 257),
        ("rgba.png", lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGRA)),
        ("grey.tif", lambda im: im),
        ("grey16.tiff", lambda im: im.astype(np.uint16) * 257),
    ],
)
def test_formats(tmp_path: Path, scene_image: np.ndarray, name: str, convert, capsys) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / name
    assert cv2.imwrite(str(path), convert(scene_image))
    status, out, _ = _run(capsys, str(path), "--json")
    assert status == 0
    dets = json.loads(out)["images"][0]["detections"]
    assert sorted(d["code"] for d in dets) == [5, 9]


def test_bad_files_get_one_line_errors(tmp_path: Path, scene_image: np.ndarray, capsys) -> None:  # type: ignore[no-untyped-def]
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), scene_image)
    png = good.read_bytes()
    ok, jpg = cv2.imencode(".jpg", scene_image)
    assert ok
    files = {
        "text.png": b"this is not an image\n",
        "empty.jpg": b"",
        "cut.png": png[: len(png) // 2],
        "cut.jpg": jpg.tobytes()[: jpg.size // 2],
        "garbage.png": png[:8] + bytes(200) + b"IEND\xaeB`\x82",
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    paths = [str(tmp_path / n) for n in files] + [str(tmp_path / "missing.tif"), str(good)]
    status, out, err = _run(capsys, *paths, "--json")
    assert status == 1
    images = json.loads(out)["images"]
    assert [im["path"] for im in images] == paths
    expected = {
        "text.png": "not a PNG, JPEG or TIFF",
        "empty.jpg": "empty file",
        "cut.png": "truncated PNG",
        "cut.jpg": "truncated JPEG",
        "garbage.png": "corrupt PNG",
        "missing.tif": "no such file",
    }
    for im in images[:-1]:
        name = Path(im["path"]).name
        assert expected[name] in im["error"] and im["path"] in im["error"]
        assert "\n" not in im["error"] and im["detections"] == []
    assert images[-1]["error"] is None and len(images[-1]["detections"]) == 2
    assert len(err.strip().splitlines()) == len(expected)
    # The table output processes the good file too and reports the others on stderr.
    status, out, err = _run(capsys, str(tmp_path / "text.png"), str(good))
    assert status == 1 and "good.png: 2 fiducials" in out and "text.png" in err


def test_read_image_keeps_depth_and_channels(tmp_path: Path, scene_image: np.ndarray) -> None:
    path = tmp_path / "x16.png"
    cv2.imwrite(str(path), scene_image.astype(np.uint16) * 257)
    im = read_image(path)
    assert im.dtype == np.uint16 and im.shape == scene_image.shape
    with pytest.raises(ImageReadError, match="is a directory"):
        read_image(tmp_path)
    # A device is refused before it is read (/dev/zero has no end).
    with pytest.raises(ImageReadError, match=r"/dev/zero: not a regular file"):
        read_image("/dev/zero")


def test_damaged_data_inside_a_file_is_an_error_naming_it(  # type: ignore[no-untyped-def]
    tmp_path: Path, scene_image: np.ndarray, capfd
) -> None:
    """A JPEG whose entropy-coded data stops half-way yet ends with the end-of-image marker
    (libjpeg fills the rest with grey and says so on the process' stderr) and a PNG with a
    damaged compressed stream: one error line each naming the file with the decoder's own
    reason, nothing else on stderr."""
    ok, jpg = cv2.imencode(".jpg", scene_image)
    assert ok
    bad_jpg = tmp_path / "halved.jpg"
    bad_jpg.write_bytes(jpg.tobytes()[: jpg.size // 2] + b"\xff\xd9")
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), scene_image)
    png = bytearray(good.read_bytes())
    idat = png.index(b"IDAT") + 8
    png[idat : idat + 64] = bytes(range(64))
    bad_png = tmp_path / "idat.png"
    bad_png.write_bytes(bytes(png))
    capfd.readouterr()
    for path, reason in (
        (bad_jpg, "corrupt JPEG data (Corrupt JPEG data"),
        (bad_png, "corrupt PNG"),
    ):
        with pytest.raises(ImageReadError) as info:
            read_image(path)
        assert str(info.value).startswith(f"{path}: {reason}") and "\n" not in str(info.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert read_image(good).shape == scene_image.shape


def test_table_gives_the_outer_circle_of_both_designs(
    tmp_path: Path, scene_image: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """The table's semi-axes are the outermost fitted circle's, named: for both 60 px fiducials
    the printed outer circle (30 px), not the ``dot`` design's 9 px pose dot."""
    path = tmp_path / "scene.png"
    cv2.imwrite(str(path), scene_image)
    status, out, _ = _run(capsys, str(path))
    assert status == 0
    head, *rows = out.splitlines()[1:]
    assert head.endswith("semi-axes (px)    circle")
    by_design = {row.split()[1]: row.split() for row in rows}
    assert set(by_design) == {"ring", "dot"}
    for words in by_design.values():
        major, x, minor, circle = words[-4:]
        assert x == "x" and circle == "outer"
        assert float(major) == pytest.approx(30.0, abs=0.3)
        assert float(minor) == pytest.approx(30.0, abs=0.3)
    # Columns line up: the circle names start under the header's "circle".
    assert {row.index("outer") for row in rows} == {head.index("circle")}


def test_outer_ellipse_names_the_circle_it_gives() -> None:
    """Where the outer circle was not fitted the largest fitted one is given and named."""
    from armourcam.commands.detect import outer_ellipse

    def record(design: str, *radii: float) -> dict[str, object]:
        ellipses = [{"radius": r, "semi_major": 30.0 * r, "semi_minor": 29.0 * r} for r in radii]
        return {"design": design, "ellipses": ellipses}

    assert outer_ellipse(record("dot", 0.3, 1.0)) == ({"radius": 1.0, **_axes(1.0)}, "outer")
    assert outer_ellipse(record("dot", 0.3)) == ({"radius": 0.3, **_axes(0.3)}, "dot")
    assert outer_ellipse(record("ring", 0.8, 0.24)) == ({"radius": 0.8, **_axes(0.8)}, "r=0.80")
    assert outer_ellipse(record("ring", 0.24))[1] == "dot"


def _axes(radius: float) -> dict[str, float]:
    return {"semi_major": 30.0 * radius, "semi_minor": 29.0 * radius}


def test_truncated_jpeg_files_get_one_line_errors(
    tmp_path: Path, scene_image: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """The damaged JPEGs the image codec now refuses (cut short with an ``FF D9`` left in a
    comment segment; headers and end-of-image marker but no scan data) are one-line errors of
    ``armourcam detect`` too, naming the file; the good file is still processed."""
    ok, buf = cv2.imencode(".jpg", scene_image)
    assert ok
    jpeg = with_comment(buf.tobytes(), b"ab\xff\xd9cd")
    files = {"cut.jpg": jpeg[: scan_start(jpeg) + 200], "noscan.jpg": without_scan(jpeg)}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    good = tmp_path / "good.jpg"
    good.write_bytes(jpeg)
    paths = [str(tmp_path / n) for n in files]
    status, out, err = _run(capsys, *paths, str(good))
    assert status == 1 and f"{good}: 2 fiducials" in out
    lines = err.strip().splitlines()
    assert len(lines) == 2
    # Named by the codec's structure check (the same rule as the node's frames).
    cut, noscan = lines
    assert cut.startswith(f"armourcam detect: error: {paths[0]}: truncated JPEG"), cut
    assert noscan.startswith(f"armourcam detect: error: {paths[1]}: damaged JPEG"), noscan
    assert "no entropy-coded" in noscan or "scan" in noscan, noscan


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def test_a_png_claiming_an_absurd_size_is_a_one_line_error(
    tmp_path: Path, scene_image: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 70-byte PNG whose header claims 100000 x 100000 pixels (OpenCV refuses such a header
    with an exception, not a None) is a one-line error naming the file; the good file after it
    is still processed."""
    import struct
    import zlib

    header = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 0, 0, 0, 0)
    bomb = (
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", header)
        + _png_chunk(b"IDAT", zlib.compress(b"\x00" * 9))
        + _png_chunk(b"IEND", b"")
    )
    path = tmp_path / "bomb.png"
    path.write_bytes(bomb)
    with pytest.raises(ImageReadError, match=r"bomb\.png: PNG data OpenCV will not decode"):
        read_image(path)
    good = tmp_path / "good.png"
    assert cv2.imwrite(str(good), scene_image)
    status, out, err = _run(capsys, str(path), str(good))
    assert status == 1 and f"{good}: 2 fiducials" in out
    (line,) = err.strip().splitlines()
    assert line.startswith(f"armourcam detect: error: {path}: PNG data OpenCV will not decode")
