"""Tests of the image-message codec (armourcam.image_codec) against OpenCV and exact references."""

from __future__ import annotations

import array
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from jpeg_damage import scan_start, with_comment, without_scan

from armourcam import image_codec as ic
from armourcam.image_codec import ImageCodecError

FIXTURES = Path(__file__).resolve().parents[2].parent / "shared" / "fixtures"
H, W = 37, 54  # odd height, even width (YUV needs pairs of pixels)


def _bgr(depth: type = np.uint8, seed: int = 1234) -> np.ndarray:
    rng = np.random.default_rng(seed)
    top = 256 if depth == np.uint8 else 65536
    return rng.integers(0, top, size=(H, W, 3)).astype(depth)


def _layout(encoding: str, bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(array in the encoding's layout, expected grey, expected BGR) computed with OpenCV."""
    alpha = np.full((H, W, 1), 77, dtype=bgr.dtype)
    grey_ref = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if encoding in ("mono8", "8UC1", "mono16", "16UC1"):
        return grey_ref, grey_ref, cv2.cvtColor(grey_ref, cv2.COLOR_GRAY2BGR)
    if encoding in ("bgr8", "8UC3", "bgr16", "16UC3"):
        return bgr, grey_ref, bgr
    if encoding in ("rgb8", "rgb16"):
        return bgr[..., ::-1].copy(), grey_ref, bgr
    if encoding in ("bgra8", "8UC4", "bgra16"):
        return np.concatenate([bgr, alpha], axis=2), grey_ref, bgr
    if encoding in ("rgba8", "rgba16"):
        return np.concatenate([bgr[..., ::-1], alpha], axis=2), grey_ref, bgr
    raise AssertionError(encoding)


COLOUR_ENCODINGS = [
    "mono8", "8UC1", "mono16", "16UC1", "bgr8", "8UC3", "rgb8", "bgra8", "8UC4", "rgba8",
    "bgr16", "16UC3", "rgb16", "bgra16", "rgba16",
]  # fmt: skip


def _msg(fields: dict[str, Any], **changes: Any) -> SimpleNamespace:
    return SimpleNamespace(**{**fields, **changes})


@pytest.mark.parametrize("encoding", COLOUR_ENCODINGS)
def test_every_encoding_matches_opencv(encoding: str) -> None:
    depth = np.uint16 if "16" in encoding else np.uint8
    src, grey_ref, bgr_ref = _layout(encoding, _bgr(depth))
    fields = ic.image_to_msg_fields(src, encoding)
    assert fields["step"] == src.strides[0] and fields["is_bigendian"] == 0
    assert isinstance(fields["data"], bytes)
    grey = ic.decode(_msg(fields))
    assert grey.dtype == depth and grey.shape == (H, W)
    np.testing.assert_array_equal(grey, grey_ref)
    np.testing.assert_array_equal(ic.decode(_msg(fields), colour=True), bgr_ref)
    np.testing.assert_array_equal(ic.raw_image(_msg(fields)), src)


@pytest.mark.parametrize("encoding", ["mono8", "rgb8", "bgra8", "mono16", "rgb16", "bayer_gbrg16"])
@pytest.mark.parametrize("pad", [1, 3, 64])
def test_padded_step_is_honoured(encoding: str, pad: int) -> None:
    depth = np.uint16 if "16" in encoding else np.uint8
    if encoding.startswith("bayer"):
        src = _bgr(depth)[..., 1].copy()
    else:
        src = _layout(encoding, _bgr(depth))[0]
    fields = ic.image_to_msg_fields(src, encoding)
    row = fields["step"]
    padded = np.full((H, row + pad), 0xAB, dtype=np.uint8)
    padded[:, :row] = np.frombuffer(fields["data"], np.uint8).reshape(H, row)
    want = ic.decode(_msg(fields))
    got = ic.decode(_msg(fields, step=row + pad, data=padded.tobytes()))
    np.testing.assert_array_equal(got, want)
    # Some drivers leave the last row's padding out: still the same image.
    short = padded.tobytes()[:-pad]
    np.testing.assert_array_equal(ic.decode(_msg(fields, step=row + pad, data=short)), want)


@pytest.mark.parametrize("encoding", ["mono16", "bgr16", "rgba16", "bayer_rggb16"])
def test_big_endian_data(encoding: str) -> None:
    if encoding.startswith("bayer"):
        src = _bgr(np.uint16)[..., 0].copy()
    else:
        src = _layout(encoding, _bgr(np.uint16))[0]
    fields = ic.image_to_msg_fields(src, encoding)
    big = src.astype(">u2").tobytes()
    np.testing.assert_array_equal(
        ic.decode(_msg(fields, data=big, is_bigendian=1)), ic.decode(_msg(fields))
    )
    np.testing.assert_array_equal(ic.raw_image(_msg(fields, data=big, is_bigendian=True)), src)


# Colour of each site of the 2x2 block, by ROS's name (first row, then second row).
BAYER_SITES = {
    "rggb": ("R", "G", "G", "B"),
    "bggr": ("B", "G", "G", "R"),
    "gbrg": ("G", "B", "R", "G"),
    "grbg": ("G", "R", "B", "G"),
}


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("pattern", sorted(BAYER_SITES))
def test_bayer_patterns_give_the_true_colour(pattern: str, bits: int) -> None:
    """A flat scene of a known colour mosaicked in the ROS pattern demosaics to that colour."""
    scale = 1 if bits == 8 else 257
    value = {"R": 200 * scale, "G": 100 * scale, "B": 30 * scale}
    dtype = np.uint8 if bits == 8 else np.uint16
    mosaic = np.empty((16, 20), dtype=dtype)
    sites = BAYER_SITES[pattern]
    mosaic[0::2, 0::2] = value[sites[0]]
    mosaic[0::2, 1::2] = value[sites[1]]
    mosaic[1::2, 0::2] = value[sites[2]]
    mosaic[1::2, 1::2] = value[sites[3]]
    fields = ic.image_to_msg_fields(mosaic, f"bayer_{pattern}{bits}")
    bgr = ic.decode(_msg(fields), colour=True)
    assert bgr.dtype == dtype
    inner = bgr[2:-2, 2:-2].reshape(-1, 3)
    assert np.all(inner == [value["B"], value["G"], value["R"]])
    grey = ic.decode(_msg(fields))
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    assert np.abs(grey[2:-2, 2:-2].astype(int) - want[2:-2, 2:-2].astype(int)).max() <= scale


@pytest.mark.parametrize(("encoding", "y_offset"), [("yuv422", 1), ("yuv422_yuy2", 0)])
def test_yuv422_grey_is_the_luma_bytes(encoding: str, y_offset: int) -> None:
    rng = np.random.default_rng(4)
    raw = rng.integers(0, 256, size=(H, W * 2), dtype=np.uint8)
    msg = SimpleNamespace(
        encoding=encoding, width=W, height=H, step=2 * W, is_bigendian=0, data=raw.tobytes()
    )
    np.testing.assert_array_equal(ic.decode(msg), raw[:, y_offset::2])
    assert ic.decode(msg, colour=True).shape == (H, W, 3)


def test_data_types_of_message_implementations() -> None:
    """bytes, array.array (rclpy), numpy (rosbags) and memoryview data decode alike."""
    src = _bgr()[..., 2].copy()
    fields = ic.image_to_msg_fields(src, "mono8")
    as_numpy = ic.image_to_msg_fields(src, "mono8", data_as="numpy")["data"]
    assert isinstance(as_numpy, np.ndarray) and as_numpy.dtype == np.uint8
    for data in (fields["data"], array.array("B", fields["data"]), as_numpy, memoryview(as_numpy)):
        np.testing.assert_array_equal(ic.decode(_msg(fields, data=data)), src)


@pytest.mark.filterwarnings("ignore::DeprecationWarning:lark")
def test_rclpy_and_rosbags_messages() -> None:
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    from rosbags.typesys import Stores, get_typestore

    src = _bgr()
    msg = sensor_msgs.Image(**ic.image_to_msg_fields(src, "bgr8"))
    np.testing.assert_array_equal(ic.decode(msg, colour=True), src)
    cmsg = sensor_msgs.CompressedImage(**ic.compressed_to_msg_fields(src, "png"))
    np.testing.assert_array_equal(ic.decode(cmsg, colour=True), src)

    store = get_typestore(Stores.ROS2_KILTED)
    hdr = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=""
    )
    fields = ic.image_to_msg_fields(src, "bgr8", data_as="numpy")
    rmsg = store.types["sensor_msgs/msg/Image"](header=hdr, **fields)
    raw = store.serialize_cdr(rmsg, "sensor_msgs/msg/Image")
    back = store.deserialize_cdr(raw, "sensor_msgs/msg/Image")
    np.testing.assert_array_equal(ic.decode(back), cv2.cvtColor(src, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize(
    "fmt", ["jpeg", "jpg", "JPEG", "bgr8; jpeg compressed bgr8", "rgb8; jpeg compressed bgr8", ""]
)
def test_jpeg_formats(fmt: str) -> None:
    src = cv2.GaussianBlur(_bgr(), (0, 0), 3)
    data = ic.compressed_to_msg_fields(src, "jpeg", quality=90)["data"]
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    got = ic.decode(SimpleNamespace(format=fmt, data=data), colour=True)
    np.testing.assert_array_equal(got, ref)
    grey = ic.decode(SimpleNamespace(format=fmt, data=data))
    np.testing.assert_array_equal(grey, cv2.cvtColor(ref, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize("image", ["grey8", "grey16", "bgr8", "bgr16"])
def test_png_is_lossless(image: str) -> None:
    depth = np.uint16 if "16" in image else np.uint8
    src = _bgr(depth) if image.startswith("bgr") else _bgr(depth)[..., 0].copy()
    fields = ic.compressed_to_msg_fields(src, "png")
    bits = "16" if depth == np.uint16 else "8"
    kind = "bgr" if src.ndim == 3 else "mono"
    assert fields["format"] == f"{kind}{bits}; png compressed {kind}{bits}"
    np.testing.assert_array_equal(ic.decode(SimpleNamespace(**fields), colour=src.ndim == 3), src)


def test_real_photo_through_jpeg() -> None:
    photo = cv2.imread(str(FIXTURES / "real_photo_aruco_tag.png"), cv2.IMREAD_COLOR)
    assert photo is not None
    fields = ic.compressed_to_msg_fields(photo, "jpeg", quality=95)
    grey = ic.decode(SimpleNamespace(**fields))
    assert grey.shape == (960, 1280) and grey.dtype == np.uint8
    ref = cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY).astype(int)
    assert np.mean(np.abs(grey.astype(int) - ref)) < 3.0


def _mono(**changes: Any) -> SimpleNamespace:
    fields = ic.image_to_msg_fields(_bgr()[..., 0].copy(), "mono8")
    return _msg(fields, **changes)


@pytest.mark.parametrize(
    ("msg", "match"),
    [
        (_mono(encoding="32FC5"), "unknown image encoding '32FC5'"),
        (_mono(width=0), "zero size"),
        (_mono(height=0, data=b""), "zero size"),
        (_mono(step=W - 1), f"step {W - 1} is smaller than one row of {W} mono8 pixels"),
        (_mono(step=W + 4), "data has .* bytes, but 37 rows of step 58 need"),
        (_mono(height=H + 1), "data has .* bytes, but 38 rows"),
        (_mono(height=H - 1), "more than 36 rows"),
        (_mono(encoding="rgb8"), "step 54 is smaller than one row of 54 rgb8 pixels"),
        (_mono(encoding="rgb8", step=3 * W), f"data has {H * W} bytes, but"),
        (
            _msg(ic.image_to_msg_fields(_bgr(), "bgr8"), encoding="yuv422", width=W - 1),
            "even width",
        ),
    ],
)
def test_bad_raw_images_are_refused(msg: SimpleNamespace, match: str) -> None:
    with pytest.raises(ImageCodecError, match=match):
        ic.decode(msg)


def test_bad_compressed_images_are_refused() -> None:
    src = _bgr()
    jpeg = ic.compressed_to_msg_fields(src, "jpeg")["data"]
    png = ic.compressed_to_msg_fields(src, "png")["data"]
    cases = [
        (SimpleNamespace(format="jpeg", data=b""), "has no data"),
        (SimpleNamespace(format="jpeg", data=jpeg[: len(jpeg) // 2]), "corrupt JPEG.*truncated"),
        (SimpleNamespace(format="jpeg", data=jpeg[:2] + b"\x00" * 200), "not jpeg"),
        (SimpleNamespace(format="png", data=jpeg), "format says png"),
        (SimpleNamespace(format="png", data=png[: len(png) // 2]), "corrupt PNG"),
        (SimpleNamespace(format="tiff", data=b"II*\x00" + b"\x00" * 50), "unknown compressed"),
        (SimpleNamespace(format="16UC1; compressedDepth png", data=png), "compressedDepth"),
    ]
    for msg, match in cases:
        with pytest.raises(ImageCodecError, match=match):
            ic.decode(msg)
    # A JPEG whose entropy-coded body is zeroed, framed by valid markers, is refused too.
    garbled = jpeg[:200] + bytes(len(jpeg) - 202) + b"\xff\xd9"
    with pytest.raises(ImageCodecError, match=r"corrupt JPEG .* cannot be decoded"):
        ic.decode(SimpleNamespace(format="jpeg", data=garbled))


def test_damaged_jpegs_that_libjpeg_would_still_decode_are_refused() -> None:
    """Found from the marker structure (thread-safe, no capture of libjpeg's stderr): a frame
    cut short whose last 4 KB still hold an ``FF D9`` (inside a comment/EXIF segment: it used
    to pass for the end-of-image marker) is named truncated; a frame with headers and an
    end-of-image marker but no scan data, which libjpeg decodes to a flat grey image ("Corrupt
    JPEG data: premature end of data segment" on descriptor 2 only), is refused."""
    rng = np.random.default_rng(5)
    grey = rng.integers(0, 256, size=(40, 48)).astype(np.uint8)
    jpeg = with_comment(ic.compressed_to_msg_fields(grey, "jpeg")["data"], b"ab\xff\xd9cd")
    assert len(jpeg) < 4096 and ic.jpeg_damage(jpeg) is None
    scan = scan_start(jpeg)
    cut = jpeg[: (scan + len(jpeg)) // 2]
    with pytest.raises(
        ImageCodecError, match=r"corrupt JPEG \(\d+ bytes\): no end-of-image .*truncated"
    ):
        ic.decode(SimpleNamespace(format="jpeg", data=cut))
    no_scan = without_scan(jpeg)
    with pytest.raises(
        ImageCodecError, match=r"corrupt JPEG .* no image data .* cannot be decoded"
    ):
        ic.decode(SimpleNamespace(format="jpeg", data=no_scan))
    # Cut anywhere before its end-of-image marker (headers, segment lengths, scan data, the
    # marker's first byte): damaged.
    for end in range(2, len(jpeg) - 1):
        assert ic.jpeg_damage(jpeg[:end]) is not None, end
    bad_length = jpeg[:2] + b"\xff\xfe\x00\x01" + jpeg[2:]
    assert "has length 1" in (ic.jpeg_damage(bad_length) or "")


@pytest.mark.parametrize(
    "params",
    [
        [],
        [cv2.IMWRITE_JPEG_PROGRESSIVE, 1],  # several scans, tables between them
        [cv2.IMWRITE_JPEG_RST_INTERVAL, 2],  # restart markers inside the scan data
        [cv2.IMWRITE_JPEG_QUALITY, 100, cv2.IMWRITE_JPEG_OPTIMIZE, 1],
    ],
    ids=["baseline", "progressive", "restarts", "optimised"],
)
def test_whole_jpegs_pass_the_structure_check(params: list[int]) -> None:
    """No false alarm: any scan layout, ``FF D9`` inside a comment, bytes after the end-of-image
    marker (cameras padding frames) decode as the plain JPEG does."""
    ok, buf = cv2.imencode(".jpg", _bgr(), params)
    assert ok
    jpeg = buf.tobytes()
    expected = ic.decode(SimpleNamespace(format="jpeg", data=jpeg))
    for variant in (
        jpeg,
        with_comment(jpeg, b"\xff\xd9\xff\xda\x00\x08"),
        jpeg + bytes(100),
        jpeg + b"\xff\xd8 stale bytes",
    ):
        assert ic.jpeg_damage(variant) is None
        got = ic.decode(SimpleNamespace(format="jpeg", data=variant))
        assert np.array_equal(got, expected)


def test_not_an_image_message() -> None:
    with pytest.raises(ImageCodecError, match="neither sensor_msgs/Image nor CompressedImage"):
        ic.decode(SimpleNamespace(width=3))


@pytest.mark.parametrize(
    ("array", "encoding", "match"),
    [
        (np.zeros((4, 4), np.float32), None, "no image encoding for a float32"),
        (np.zeros((4, 4, 3), np.uint8), "mono8", "mono8 needs 1 channel"),
        (np.zeros((4, 4), np.uint16), "mono8", "mono8 needs 1 channel.* of uint8"),
        (np.zeros((4, 4, 3), np.uint8), "bayer_rggb8", "needs 1 channel"),
        (np.zeros((0, 4), np.uint8), None, "shape"),
        (np.zeros((4, 4), np.uint8), "weird", "unknown image encoding"),
    ],
)
def test_bad_arrays_are_refused(array: np.ndarray, encoding: str | None, match: str) -> None:
    with pytest.raises(ImageCodecError, match=match):
        ic.image_to_msg_fields(array, encoding)


def test_compress_errors() -> None:
    with pytest.raises(ImageCodecError, match="jpeg cannot hold a uint16"):
        ic.compressed_to_msg_fields(np.zeros((4, 4), np.uint16), "jpeg")
    with pytest.raises(ImageCodecError, match="quality"):
        ic.compressed_to_msg_fields(np.zeros((4, 4), np.uint8), "jpeg", quality=0)
