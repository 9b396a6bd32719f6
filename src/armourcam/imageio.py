"""Reading image files for the command line: PNG, JPEG and TIFF, 8 or 16 bit, grey or colour.

Files are read as bytes and decoded with ``cv2.imdecode`` (so paths with any characters work and
the checks below see the bytes). The image comes back as stored: ``(H, W)`` grey or ``(H, W, 3|4)``
in OpenCV's BGR(A) order, ``uint8`` or ``uint16``; :func:`fiducial_detector.detect` takes it as is.

Every failure raises :class:`ImageReadError` with one line naming the file and the problem: a
missing or unreadable file, an empty file, data that is not a PNG, JPEG or TIFF image, a truncated
PNG (no ``IEND`` chunk) or JPEG (no end-of-image marker; libjpeg would fill the missing part with
grey and return a plausible image), data the decoder rejects, or JPEG data libjpeg reports as
corrupt while decoding (entropy-coded data damaged in the middle: it too fills the rest with grey).
What the decoders print themselves (libpng, libjpeg, OpenCV's log) is caught rather than left on
the terminal without a file name; it names the problem in the error, and is dropped where the
image decoded whole (a libpng colour-profile warning, extraneous bytes after a JPEG's data).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from .image_codec import jpeg_damage

_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG = b"\xff\xd8\xff"
_TIFF = (b"II*\x00", b"MM\x00*")
#: OpenCV's log prefix: ``[ WARN:0@0.221] global grfmt_png.cpp:793 readFromStreamOrBuffer``.
_OPENCV_LOG = re.compile(r"^\[\s*[A-Z]+:[^\]]*\]\s*(global\s+\S+:\d+\s+\S+\s+)?")


class ImageReadError(ValueError):
    """An image file cannot be read; the message names the file and the problem."""


def image_format(data: bytes) -> str | None:
    """``"png"``, ``"jpeg"`` or ``"tiff"`` from a file's magic bytes, else None."""
    if data.startswith(_PNG):
        return "png"
    if data.startswith(_JPEG):
        return "jpeg"
    if data.startswith(_TIFF):
        return "tiff"
    return None


def read_image(path: str | Path) -> NDArray[np.generic]:
    """Read a PNG, JPEG or TIFF file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    ndarray
        ``(H, W)`` or ``(H, W, C)`` (BGR / BGRA), ``uint8`` or ``uint16``, indexed ``[v, u]``.

    Raises
    ------
    ImageReadError
        If the file is missing, unreadable, empty, not a PNG/JPEG/TIFF image, truncated or corrupt.
    """
    name = str(path)
    try:
        if Path(path).exists() and not Path(path).is_file() and not Path(path).is_dir():
            # A device or a pipe (/dev/zero) would be read without end.
            raise ImageReadError(f"{name}: not a regular file (a device or a pipe)")
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise ImageReadError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise ImageReadError(f"{name}: is a directory, not an image file") from None
    except OSError as err:
        raise ImageReadError(f"{name}: cannot read file ({err.strerror or err})") from err
    if not data:
        raise ImageReadError(f"{name}: empty file (0 bytes)")
    kind = image_format(data)
    if kind is None:
        raise ImageReadError(f"{name}: not a PNG, JPEG or TIFF image ({len(data)} bytes)")
    if kind == "png" and b"IEND" not in data[-64:]:
        raise ImageReadError(f"{name}: truncated PNG ({len(data)} bytes, no IEND chunk)")
    if kind == "jpeg" and (damage := jpeg_damage(data)) is not None:
        # The one structure check of the image codec (the node's frames get the same).
        kind_of = "truncated" if "truncated" in damage else "damaged"
        raise ImageReadError(f"{name}: {kind_of} JPEG ({len(data)} bytes): {damage}")
    flags = cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION
    with _decoder_messages() as messages:
        try:
            image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
        except cv2.error as err:
            # OpenCV refuses, rather than decodes, a header claiming an absurd size.
            raise ImageReadError(
                f"{name}: {kind.upper()} data OpenCV will not decode ({_first_line(err)})"
            ) from err
    said = f" ({messages[0]})" if messages else ""
    if image is None or image.size == 0:
        raise ImageReadError(f"{name}: corrupt {kind.upper()} data, cannot be decoded{said}")
    if kind == "jpeg" and any(_damaged_jpeg(m) for m in messages):
        raise ImageReadError(f"{name}: corrupt JPEG data{said}")
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageReadError(
            f"{name}: unsupported sample type {image.dtype} (8- or 16-bit images only)"
        )
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return np.asarray(image)


def _damaged_jpeg(message: str) -> bool:
    """Whether a libjpeg message means image data was lost (not merely extra bytes)."""
    return "Corrupt JPEG data" in message and "extraneous bytes" not in message


@contextlib.contextmanager
def _decoder_messages() -> Iterator[list[str]]:
    """Collect what native code writes to the process' standard error meanwhile (file
    descriptor 2, where libpng, libjpeg and OpenCV's log write), one stripped line each."""
    lines: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield lines
            finally:
                os.dup2(saved, 2)
                sink.seek(0)
                text = sink.read().decode(errors="replace")
                lines.extend(
                    _OPENCV_LOG.sub("", line.strip()) for line in text.splitlines() if line.strip()
                )
    finally:
        os.close(saved)


def _first_line(err: Exception) -> str:
    """The gist of an OpenCV error: its message without the source location."""
    text = str(err).strip()
    found = re.search(r"error: \([^)]*\) (.*)", text)
    gist = found.group(1) if found else text
    return gist.splitlines()[0] if gist else type(err).__name__
