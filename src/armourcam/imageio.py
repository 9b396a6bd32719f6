"""Reading image files for the command line: PNG, JPEG and TIFF, 8 or 16 bit, grey or colour.

Files are read as bytes and decoded with ``cv2.imdecode`` (so paths with any characters work and
the checks below see the bytes). The image comes back as stored: ``(H, W)`` grey or ``(H, W, 3|4)``
in OpenCV's BGR(A) order, ``uint8`` or ``uint16``; :func:`fiducial_detector.detect` takes it as is.

Every failure raises :class:`ImageReadError` with one line naming the file and the problem: a
missing or unreadable file, an empty file, data that is not a PNG, JPEG or TIFF image, a truncated
PNG (no ``IEND`` chunk) or JPEG (no end-of-image marker; libjpeg would fill the missing part with
grey and return a plausible image), or data the decoder rejects.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG = b"\xff\xd8\xff"
_TIFF = (b"II*\x00", b"MM\x00*")


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
    if kind == "jpeg" and b"\xff\xd9" not in data[-4096:]:
        raise ImageReadError(f"{name}: truncated JPEG ({len(data)} bytes, no end-of-image marker)")
    flags = cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if image is None or image.size == 0:
        raise ImageReadError(f"{name}: corrupt {kind.upper()} data, cannot be decoded")
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageReadError(
            f"{name}: unsupported sample type {image.dtype} (8- or 16-bit images only)"
        )
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return np.asarray(image)
