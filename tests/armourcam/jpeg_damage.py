"""Damaged JPEGs for the codec and ``armourcam detect`` tests, built from a whole one."""

from __future__ import annotations


def with_comment(jpeg: bytes, text: bytes) -> bytes:
    """``jpeg`` with a COM segment holding ``text`` right after SOI (APPn/COM bytes are free:
    an EXIF thumbnail's own end-of-image marker is the common case)."""
    return jpeg[:2] + b"\xff\xfe" + (2 + len(text)).to_bytes(2, "big") + text + jpeg[2:]


def scan_start(jpeg: bytes) -> int:
    """Offset of the first byte of entropy-coded data (after the SOS segment)."""
    sos = jpeg.index(b"\xff\xda")
    return sos + 2 + int.from_bytes(jpeg[sos + 2 : sos + 4], "big")


def without_scan(jpeg: bytes) -> bytes:
    """``jpeg``'s headers and an end-of-image marker, no scan data (libjpeg decodes it grey)."""
    return jpeg[: scan_start(jpeg)] + b"\xff\xd9"
