"""The one image-message codec: ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` <-> numpy.

Duck-typed: the same functions read rclpy messages and messages deserialised by rosbags (anything
with the messages' attribute names; ``data`` may be ``bytes``, ``array.array`` or a uint8 array).
Pixel data are converted with ``frombuffer``/``tobytes`` and OpenCV only, never element-wise.

API summary
-----------
Reading (grey by default, what the detector takes; ``colour=True`` gives OpenCV's BGR order):

- :func:`decode` ``(msg, *, colour=False) -> ndarray``: either message type.
- :func:`decode_image` / :func:`decode_compressed` for one type;
  :func:`image_from_fields` / :func:`compressed_from_fields` for bare fields (no message object);
  :func:`raw_image` ``(msg) -> (H, W[, C]) ndarray`` in the message's own channel layout;
  :func:`jpeg_damage` ``(data) -> str | None``: why JPEG bytes are not a whole image (checked
  before every JPEG decode).
- Output dtype follows the bit depth: ``uint8`` for 8-bit encodings, ``uint16`` for 16-bit ones
  (mono16, rgb16/bgr16/rgba16/bgra16, bayer_*16, 16-bit PNG).

Writing (for publishers and bag writers):

- :func:`image_to_msg_fields` ``(image, encoding=None, *, data_as="bytes") -> dict`` with
  ``height, width, encoding, is_bigendian, step, data`` (pass ``data_as="numpy"`` for rosbags'
  classes, which want a uint8 array).
- :func:`compressed_to_msg_fields` ``(image, codec="jpeg", *, quality=95, data_as="bytes")``
  -> dict with ``format`` (``"bgr8; jpeg compressed bgr8"`` style) and ``data``.

Supported ``Image.encoding`` values: :data:`ENCODINGS` (mono8/16, 8UC1/16UC1, rgb8/bgr8/rgba8/bgra8,
8UC3/8UC4, their 16-bit versions, bayer_rggb8/bggr8/gbrg8/grbg8 and the 16-bit bayer ones, yuv422
(UYVY) and yuv422_yuy2). ``step`` (row padding) and ``is_bigendian`` are honoured.
``CompressedImage.format``: ``"ORIG; CODEC compressed [PIXFMT]"`` or a bare ``jpeg``/``jpg``/
``png``; an empty or unrecognised format is identified from the data's magic bytes.

Bayer: ROS names the 2x2 block by its first row (``bayer_rggb8``: R G / G B); OpenCV names it by
its second row, so ``bayer_rggb8`` is OpenCV's ``COLOR_BayerBG2*`` (its ``BayerRGGB`` alias).

Errors: :class:`ImageCodecError` (a ``ValueError``) names what is wrong: unknown encoding, zero
size, ``step`` smaller than a row, data shorter or longer than the header says, a corrupt or
truncated JPEG/PNG.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray


class ImageCodecError(ValueError):
    """An image message cannot be decoded (or an array cannot be encoded) as asked."""


@dataclass(frozen=True, slots=True)
class _Encoding:
    channels: int
    depth: str  # numpy dtype code without byte order: "u1" or "u2"
    to_grey: int | None  # OpenCV conversion code to grey (None: already grey)
    to_bgr: int | None  # OpenCV conversion code to BGR (None: already BGR)


def _enc(channels: int, depth: str, to_grey: int | None, to_bgr: int | None) -> _Encoding:
    return _Encoding(channels, depth, to_grey, to_bgr)


_BAYER = {
    # ROS name (first row) -> OpenCV code names (second row): see the module docstring.
    "rggb": (cv2.COLOR_BayerBG2GRAY, cv2.COLOR_BayerBG2BGR),
    "bggr": (cv2.COLOR_BayerRG2GRAY, cv2.COLOR_BayerRG2BGR),
    "gbrg": (cv2.COLOR_BayerGR2GRAY, cv2.COLOR_BayerGR2BGR),
    "grbg": (cv2.COLOR_BayerGB2GRAY, cv2.COLOR_BayerGB2BGR),
}

_ENCODINGS: dict[str, _Encoding] = {
    "mono8": _enc(1, "u1", None, cv2.COLOR_GRAY2BGR),
    "8UC1": _enc(1, "u1", None, cv2.COLOR_GRAY2BGR),
    "mono16": _enc(1, "u2", None, cv2.COLOR_GRAY2BGR),
    "16UC1": _enc(1, "u2", None, cv2.COLOR_GRAY2BGR),
    "bgr8": _enc(3, "u1", cv2.COLOR_BGR2GRAY, None),
    "8UC3": _enc(3, "u1", cv2.COLOR_BGR2GRAY, None),
    "rgb8": _enc(3, "u1", cv2.COLOR_RGB2GRAY, cv2.COLOR_RGB2BGR),
    "bgra8": _enc(4, "u1", cv2.COLOR_BGRA2GRAY, cv2.COLOR_BGRA2BGR),
    "8UC4": _enc(4, "u1", cv2.COLOR_BGRA2GRAY, cv2.COLOR_BGRA2BGR),
    "rgba8": _enc(4, "u1", cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2BGR),
    "bgr16": _enc(3, "u2", cv2.COLOR_BGR2GRAY, None),
    "16UC3": _enc(3, "u2", cv2.COLOR_BGR2GRAY, None),
    "rgb16": _enc(3, "u2", cv2.COLOR_RGB2GRAY, cv2.COLOR_RGB2BGR),
    "bgra16": _enc(4, "u2", cv2.COLOR_BGRA2GRAY, cv2.COLOR_BGRA2BGR),
    "rgba16": _enc(4, "u2", cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2BGR),
    "yuv422": _enc(2, "u1", cv2.COLOR_YUV2GRAY_UYVY, cv2.COLOR_YUV2BGR_UYVY),
    "uyvy": _enc(2, "u1", cv2.COLOR_YUV2GRAY_UYVY, cv2.COLOR_YUV2BGR_UYVY),
    "yuv422_yuy2": _enc(2, "u1", cv2.COLOR_YUV2GRAY_YUY2, cv2.COLOR_YUV2BGR_YUY2),
    "yuyv": _enc(2, "u1", cv2.COLOR_YUV2GRAY_YUY2, cv2.COLOR_YUV2BGR_YUY2),
}
for _pattern, (_grey, _bgr) in _BAYER.items():
    _ENCODINGS[f"bayer_{_pattern}8"] = _enc(1, "u1", _grey, _bgr)
    _ENCODINGS[f"bayer_{_pattern}16"] = _enc(1, "u2", _grey, _bgr)

ENCODINGS: frozenset[str] = frozenset(_ENCODINGS)
"""``sensor_msgs/Image.encoding`` values this codec decodes."""

_JPEG_MAGIC = b"\xff\xd8\xff"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _buffer(data: Any) -> NDArray[np.uint8]:
    """Zero-copy uint8 view of a message's ``data`` (bytes, array.array, memoryview, ndarray)."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        # A list of ints (some message implementations): one vectorised conversion, no loop.
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def _lookup(encoding: str) -> _Encoding:
    enc = _ENCODINGS.get(encoding.strip())
    if enc is None:
        enc = _ENCODINGS.get(encoding.strip().lower())
    if enc is None:
        raise ImageCodecError(
            f"unknown image encoding {encoding!r}; supported: {', '.join(sorted(ENCODINGS))}"
        )
    return enc


def _convert(image: NDArray[Any], enc: _Encoding, colour: bool) -> NDArray[Any]:
    code = enc.to_bgr if colour else enc.to_grey
    if code is None:
        return image
    return np.asarray(cv2.cvtColor(image, code))


def _raw_from_fields(
    encoding: str, width: int, height: int, step: int, data: Any, is_bigendian: bool
) -> tuple[NDArray[Any], _Encoding]:
    enc = _lookup(encoding)
    width, height, step = int(width), int(height), int(step)
    if width <= 0 or height <= 0:
        raise ImageCodecError(f"image has zero size ({width}x{height}, encoding {encoding})")
    itemsize = np.dtype(enc.depth).itemsize
    row_bytes = width * enc.channels * itemsize
    if step < row_bytes:
        raise ImageCodecError(
            f"step {step} is smaller than one row of {width} {encoding} pixels ({row_bytes} bytes)"
        )
    if enc.channels == 2 and width % 2:
        raise ImageCodecError(f"{encoding} needs an even width, got {width}")
    buf = _buffer(data)
    # The last row's padding may be missing (some drivers); anything less is a broken message.
    needed = step * (height - 1) + row_bytes
    if buf.size < needed:
        raise ImageCodecError(
            f"data has {buf.size} bytes, but {height} rows of step {step} need {step * height} "
            f"({encoding} {width}x{height})"
        )
    if buf.size > step * height:
        raise ImageCodecError(
            f"data has {buf.size} bytes, more than {height} rows of step {step} ({step * height}); "
            f"height or step is wrong ({encoding} {width}x{height})"
        )
    if step == row_bytes:
        rows = buf[: row_bytes * height].reshape(height, row_bytes)
    else:
        # Skip each row's padding with a strided view; the copy below makes it contiguous.
        rows = np.lib.stride_tricks.as_strided(buf, shape=(height, row_bytes), strides=(step, 1))
    order = ">" if is_bigendian else "<"
    pixels = np.ascontiguousarray(rows).view(order + enc.depth)
    if pixels.dtype != np.dtype(enc.depth):  # to native byte order (for 16-bit data only)
        pixels = pixels.astype(enc.depth)
    shape = (height, width) if enc.channels == 1 else (height, width, enc.channels)
    return pixels.reshape(shape), enc


def image_from_fields(
    encoding: str,
    width: int,
    height: int,
    step: int,
    data: Any,
    *,
    is_bigendian: bool = False,
    colour: bool = False,
) -> NDArray[Any]:
    """Decode the fields of a ``sensor_msgs/Image``.

    Parameters
    ----------
    encoding, width, height, step, data, is_bigendian
        As in ``sensor_msgs/Image`` (``step`` is the row length in bytes, padding included).
    colour : bool
        False (default): a grey ``(height, width)`` image. True: ``(height, width, 3)`` BGR.

    Returns
    -------
    ndarray
        uint8 for 8-bit encodings, uint16 for 16-bit ones (two-channel YUV gives uint8). For an
        unpadded little-endian image already in the asked layout (e.g. mono8 read as grey) this is
        a zero-copy view of ``data``, read-only when ``data`` is ``bytes``: copy before writing.

    Raises
    ------
    ImageCodecError
        Unknown encoding, zero size, ``step`` shorter than a row, data shorter or longer than
        ``step * height``.
    """
    raw, enc = _raw_from_fields(encoding, width, height, step, data, is_bigendian)
    try:
        return _convert(raw, enc, colour)
    except cv2.error as err:
        raise ImageCodecError(f"cannot convert {encoding} {width}x{height}: {err}") from err


def raw_image(msg: Any) -> NDArray[Any]:
    """Pixels of a ``sensor_msgs/Image`` in its own layout: ``(H, W)`` or ``(H, W, C)``, native
    byte order, row padding removed (a Bayer mosaic stays a mosaic)."""
    raw, _ = _raw_from_fields(
        msg.encoding, msg.width, msg.height, msg.step, msg.data, bool(msg.is_bigendian)
    )
    return raw


def decode_image(msg: Any, *, colour: bool = False) -> NDArray[Any]:
    """Decode a ``sensor_msgs/Image`` message object (see :func:`image_from_fields`)."""
    return image_from_fields(
        msg.encoding,
        msg.width,
        msg.height,
        msg.step,
        msg.data,
        is_bigendian=bool(msg.is_bigendian),
        colour=colour,
    )


def _codec_of(fmt: str, buf: NDArray[np.uint8]) -> str:
    """``"jpeg"`` or ``"png"`` from a CompressedImage format string, else from magic bytes."""
    text = fmt.strip().lower()
    if ";" in text:
        words = text.split(";", 1)[1].split()
        if words and words[0] == "compresseddepth":
            raise ImageCodecError(f"compressedDepth images are not supported (format {fmt!r})")
        text = words[0] if words else ""
    if text in ("jpeg", "jpg"):
        return "jpeg"
    if text == "png":
        return "png"
    head = buf[:8].tobytes()
    if head.startswith(_JPEG_MAGIC):
        return "jpeg"
    if head.startswith(_PNG_MAGIC):
        return "png"
    raise ImageCodecError(
        f"unknown compressed image format {fmt!r} and data is neither JPEG nor PNG"
    )


#: Marker codes without a length field: TEM, SOI and the restart markers RST0-RST7.
_JPEG_STANDALONE = frozenset({0x01, 0xD8, *range(0xD0, 0xD8)})
_JPEG_EOI, _JPEG_SOS = 0xD9, 0xDA


def jpeg_damage(data: Any) -> str | None:
    """Why JPEG ``data`` is not a whole image, or None when its marker structure is complete.

    Walks the marker segments from SOI by their lengths (so bytes inside APPn/COM segments, an
    EXIF thumbnail's own end-of-image marker included, are never taken for markers) and each
    scan's entropy-coded data to its first marker (``FF 00`` stuffing, fill bytes and RST0-7 are
    part of the data), until the end-of-image marker (EOI, ``FF D9``). Bytes after the EOI are
    ignored, as decoders do (some cameras pad frames). No pixel is decoded: thread-safe and a
    few milliseconds for a 6 Mpx frame, unlike catching libjpeg's warnings on descriptor 2.

    Parameters
    ----------
    data
        The compressed bytes (``bytes``, ``array.array``, uint8 array ...), starting with SOI.

    Returns
    -------
    str or None
        The damage, worded for an error message: the data ends before the EOI (a truncated
        frame, which libjpeg would fill with grey), a marker segment length that cannot be, or
        no entropy-coded scan data before the EOI (libjpeg's "premature end": a grey image).
        Not found: damage inside the entropy-coded data that keeps the structure (a hole cut
        out of the middle of a scan); only a decoder's warnings tell that.
    """
    buf = _buffer(data)
    n = int(buf.size)
    truncated = "no end-of-image marker, data is truncated"
    if n < 4 or buf[0] != 0xFF or buf[1] != 0xD8:
        return "no start-of-image marker"
    # Every place a marker can start: 0xFF followed by neither a stuffed zero, another 0xFF (fill)
    # nor a restart marker (JPEG standard, B.1.1.5 and F.1.2.3). One vectorised pass.
    ff = np.flatnonzero(buf[:-1] == 0xFF)
    code = buf[ff + 1]
    candidates = ff[(code != 0x00) & (code != 0xFF) & ((code < 0xD0) | (code > 0xD7))]
    pos, scans, scan_bytes = 2, 0, 0
    while True:
        # The next marker at or after pos (libjpeg, too, skips stray bytes before a marker).
        k = int(np.searchsorted(candidates, pos))
        if k == candidates.size:
            return truncated
        at = int(candidates[k])
        marker = int(buf[at + 1])
        if marker == _JPEG_EOI:
            break
        if marker in _JPEG_STANDALONE:
            pos = at + 2
            continue
        if at + 4 > n:
            return truncated
        length = (int(buf[at + 2]) << 8) | int(buf[at + 3])
        if length < 2:
            return f"marker 0x{marker:02X} at byte {at} has length {length}, cannot be decoded"
        pos = at + 2 + length
        if pos > n:
            return truncated
        if marker == _JPEG_SOS:
            # The scan's entropy-coded data runs from here to the next marker.
            k = int(np.searchsorted(candidates, pos))
            if k == candidates.size:
                return truncated
            scans += 1
            scan_bytes += int(candidates[k]) - pos
            pos = int(candidates[k])
    if scans == 0 or scan_bytes == 0:
        return "no image data before the end-of-image marker (no scan), cannot be decoded"
    return None


def compressed_from_fields(fmt: str, data: Any, *, colour: bool = False) -> NDArray[Any]:
    """Decode the fields of a ``sensor_msgs/CompressedImage``.

    Parameters
    ----------
    fmt : str
        The message's ``format`` (``"bgr8; jpeg compressed bgr8"``, ``"jpg"``, ``"png"``, ...).
    data
        The compressed bytes.
    colour : bool
        False: grey ``(H, W)``; True: BGR ``(H, W, 3)``.

    Returns
    -------
    ndarray
        uint8, or uint16 for a 16-bit PNG.

    Raises
    ------
    ImageCodecError
        Empty data, data that does not match the format, a JPEG whose marker structure is
        incomplete (:func:`jpeg_damage`: truncated before its end-of-image marker, or without
        scan data; libjpeg would return it with the missing part filled grey, saying so only on
        descriptor 2) or any undecodable data.
    """
    buf = _buffer(data)
    if buf.size == 0:
        raise ImageCodecError(f"compressed image ({fmt!r}) has no data")
    codec = _codec_of(fmt, buf)
    head = buf[:8].tobytes()
    magic = _JPEG_MAGIC if codec == "jpeg" else _PNG_MAGIC
    if not head.startswith(magic):
        raise ImageCodecError(f"format says {codec} ({fmt!r}) but the data is not {codec}")
    if codec == "jpeg":
        damage = jpeg_damage(buf)
        if damage is not None:
            raise ImageCodecError(f"corrupt JPEG ({buf.size} bytes): {damage}")
    # Grey straight from the decoder (a JPEG's luma plane, no colour round trip); ANYDEPTH keeps
    # 16-bit PNGs; camera frames are raw pixels, so EXIF orientation is ignored.
    flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION
    flags |= cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE
    image = cv2.imdecode(buf, flags)
    if image is None or image.size == 0:
        raise ImageCodecError(f"corrupt {codec.upper()} ({buf.size} bytes): cannot be decoded")
    return np.asarray(image)


def decode_compressed(msg: Any, *, colour: bool = False) -> NDArray[Any]:
    """Decode a ``sensor_msgs/CompressedImage`` object (see :func:`compressed_from_fields`)."""
    return compressed_from_fields(msg.format, msg.data, colour=colour)


def decode(msg: Any, *, colour: bool = False) -> NDArray[Any]:
    """Decode a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` message object.

    The type is told by duck typing: ``encoding`` -> Image, ``format`` -> CompressedImage.

    Returns
    -------
    ndarray
        Grey ``(H, W)`` (default) or BGR ``(H, W, 3)`` with ``colour=True``; uint8 or uint16.

    Raises
    ------
    ImageCodecError
        For anything that is not a decodable image message.
    """
    if hasattr(msg, "encoding") and hasattr(msg, "step"):
        return decode_image(msg, colour=colour)
    if hasattr(msg, "format") and hasattr(msg, "data"):
        return decode_compressed(msg, colour=colour)
    raise ImageCodecError(f"{type(msg).__name__} is neither sensor_msgs/Image nor CompressedImage")


_DEFAULT_ENCODING = {
    (2, "u1", 1): "mono8",
    (2, "u2", 1): "mono16",
    (3, "u1", 3): "bgr8",
    (3, "u1", 4): "bgra8",
    (3, "u2", 3): "bgr16",
    (3, "u2", 4): "bgra16",
}


def _data_out(raw: bytes, data_as: str) -> Any:
    if data_as == "bytes":
        return raw
    if data_as == "numpy":
        return np.frombuffer(raw, dtype=np.uint8)
    raise ValueError(f"data_as must be 'bytes' or 'numpy', got {data_as!r}")


def image_to_msg_fields(
    image: NDArray[Any],
    encoding: str | None = None,
    *,
    data_as: Literal["bytes", "numpy"] = "bytes",
) -> dict[str, Any]:
    """Fields of a ``sensor_msgs/Image`` holding ``image`` (little-endian, unpadded rows).

    Parameters
    ----------
    image : (H, W) or (H, W, C) uint8 or uint16 ndarray
        Pixels in the layout of ``encoding``.
    encoding : str, optional
        Defaults to mono8/mono16 for 2-D arrays and bgr8/bgra8 (bgr16/bgra16) for 3-D ones
        (OpenCV's channel order). Bayer mosaics are 2-D arrays with e.g. ``"bayer_rggb8"``.
    data_as : {"bytes", "numpy"}
        ``bytes`` for rclpy messages, ``numpy`` (uint8 array) for rosbags' message classes.

    Returns
    -------
    dict
        ``height, width, encoding, is_bigendian, step, data`` - pass as keyword arguments to the
        message class, with ``header``.

    Raises
    ------
    ImageCodecError
        When the array's shape or dtype does not fit the encoding, or it is empty.
    """
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.size == 0:
        raise ImageCodecError(f"cannot encode an array of shape {arr.shape} as an image")
    channels = 1 if arr.ndim == 2 else arr.shape[2]
    depth = arr.dtype.str[1:]
    if encoding is None:
        encoding = _DEFAULT_ENCODING.get((arr.ndim, depth, channels))
        if encoding is None:
            raise ImageCodecError(
                f"no image encoding for a {arr.dtype} array of shape {arr.shape}; "
                "use uint8/uint16 with 1, 3 or 4 channels"
            )
    enc = _lookup(encoding)
    if (channels, depth) != (enc.channels, enc.depth) or (enc.channels == 1 and arr.ndim != 2):
        raise ImageCodecError(
            f"{encoding} needs {enc.channels} channel(s) of {np.dtype(enc.depth)}, got a "
            f"{arr.dtype} array of shape {arr.shape}"
        )
    height, width = arr.shape[:2]
    data = np.ascontiguousarray(arr, dtype=np.dtype("<" + enc.depth)).tobytes()
    return {
        "height": int(height),
        "width": int(width),
        "encoding": encoding,
        "is_bigendian": 0,
        "step": int(width * enc.channels * arr.dtype.itemsize),
        "data": _data_out(data, data_as),
    }


def compressed_to_msg_fields(
    image: NDArray[Any],
    codec: Literal["jpeg", "png"] = "jpeg",
    *,
    quality: int = 95,
    data_as: Literal["bytes", "numpy"] = "bytes",
) -> dict[str, Any]:
    """Fields of a ``sensor_msgs/CompressedImage`` holding ``image``.

    Parameters
    ----------
    image : (H, W) grey or (H, W, 3) BGR ndarray
        uint8 (JPEG or PNG) or uint16 (PNG only).
    codec : {"jpeg", "png"}
    quality : int
        JPEG quality 1-100.
    data_as : {"bytes", "numpy"}

    Returns
    -------
    dict
        ``format`` in image_transport's style (``"mono8; jpeg compressed mono8"``) and ``data``.

    Raises
    ------
    ImageCodecError
        For an array the codec cannot hold or a failed encode.
    """
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.size == 0 or (arr.ndim == 3 and arr.shape[2] != 3):
        raise ImageCodecError(f"cannot compress an array of shape {arr.shape}")
    if arr.dtype not in (np.uint8, np.uint16) or (codec == "jpeg" and arr.dtype != np.uint8):
        raise ImageCodecError(f"{codec} cannot hold a {arr.dtype} image")
    if codec == "jpeg":
        if not 1 <= quality <= 100:
            raise ImageCodecError(f"JPEG quality must be 1-100, got {quality}")
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    elif codec == "png":
        params = [cv2.IMWRITE_PNG_COMPRESSION, 3]
    else:
        raise ImageCodecError(f"unknown codec {codec!r}; use 'jpeg' or 'png'")
    ok, out = cv2.imencode(".jpg" if codec == "jpeg" else ".png", arr, params)
    if not ok:
        raise ImageCodecError(f"OpenCV could not encode a {arr.dtype} {arr.shape} image as {codec}")
    bits = "16" if arr.dtype == np.uint16 else "8"
    pixfmt = f"mono{bits}" if arr.ndim == 2 else f"bgr{bits}"
    return {
        "format": f"{pixfmt}; {codec} compressed {pixfmt}",
        "data": _data_out(out.tobytes(), data_as),
    }
