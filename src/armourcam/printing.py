"""Printable fiducial targets: a vector PDF sheet for a laser printer, or one target as a PNG.

Both outputs come from the geometry of :mod:`fiducial_detector.design`. The PDF draws the design's
black regions (:func:`black_regions`: the central dot, the outer annulus of the ``ring`` design and
each run of black code sectors) as filled paths of cubic Bezier arcs, so they are exact at any
printer resolution; the PNG is rasterised through the design's one :func:`reflectance` function
with area-averaging supersampling, so it cannot drift from what the renderer and the detector use.

Coordinates: the PDF uses points (1/72 in) with y up, like the target frame (x right, y up on the
sheet, angles counter-clockwise as seen on the printed face). The PNG uses pixel centres at integer
coordinates with v down; the target's centre is at the image centre ``((n - 1) / 2, (n - 1) / 2)``.

The PDF writer is a small PDF 1.4 writer (no PDF library is a dependency): a catalog, a page tree,
one Helvetica font resource, one uncompressed content stream per page and a byte-exact xref table.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from displacement_matcher.atomic import write_atomic
from fiducial_detector.codebook import BITS, code_bits, code_count
from fiducial_detector.design import FiducialDesign, get_design, reflectance

from .render import supersample_offsets

MM_PER_INCH = 25.4
PT_PER_MM = 72.0 / MM_PER_INCH
A4_MM = (210.0, 297.0)
PAGE_MARGIN_MM = 12.0
# White paper left around the target inside the cut square, as a fraction of the diameter (the
# renderer models a white margin of 0.3 outer radii; 0.15 diameters is the same).
CUT_MARGIN = 0.15
MIN_CUT_MARGIN_MM = 1.0
CROP_OFFSET_MM = 0.6  # crop marks stop short of the cut corner so no ink lands on the target
CROP_LENGTH_MM = 2.5
LABEL_GAP_MM = 3.0
CODE_FONT_PT = 7.0
DETAIL_FONT_PT = 5.0
MIN_FEATURE_DOTS = 2.0  # thinnest printed feature must span at least this many printer dots
SCALE_BAR_MM = 50.0
PNG_MARGIN = 0.5  # white margin on each side of the PNG target, in target diameters
#: Largest side of a single-target PNG (its supersampling lattice holds about 24 bytes per pixel
#: of twice that side squared: 1.5 GB here; a 7.1 mm target at 4800 dpi is 2,700 px).
MAX_PNG_SIDE_PX = 4000
#: Most targets on one PDF sheet (about 1.8 kB and 0.15 ms each: 90 MB, 600 pages of 7.1 mm ones),
#: a guard against a mistyped ``copies``.
MAX_SHEET_TARGETS = 50_000
TITLE_FONT_PT = 9.0
PAGE_LINE_FONT_PT = 7.0
FOOTER_FONT_PT = 6.0
#: Advance widths of Helvetica (the PDF's font; Arial and Liberation Sans share them) for the
#: printable ASCII characters 32..126 in WinAnsiEncoding, in 1/1000 em (Adobe's Helvetica AFM).
HELVETICA_WIDTHS = (
    # space ! " # $ % & ' ( ) * + , - . /
    (278, 278, 355, 556, 556, 889, 667, 191, 333, 333, 389, 584, 278, 333, 278, 278)
    # 0-9 : ; < = > ? @
    + (556,) * 10
    + (278, 278, 584, 584, 584, 556, 1015)
    # A-Z
    + (667, 667, 722, 722, 667, 611, 778, 722, 278, 500, 667, 556, 833)
    + (722, 778, 667, 778, 722, 667, 611, 722, 667, 944, 667, 667, 611)
    # [ \ ] ^ _ `
    + (278, 278, 278, 469, 556, 333)
    # a-z
    + (556, 556, 500, 556, 556, 278, 556, 556, 222, 222, 500, 222, 833)
    + (556, 556, 556, 556, 333, 500, 278, 556, 500, 722, 500, 500, 500)
    # { | } ~
    + (334, 260, 334, 584)
)


class PrintError(ValueError):
    """Targets cannot be printed as asked (bad code range, size, resolution or output path)."""


@dataclass(frozen=True, slots=True)
class Region:
    """One black region of a printed target, in units of the outer printed radius.

    An annular sector between radii ``r_inner`` and ``r_outer`` (``r_inner = 0`` for a disc or a
    pie slice) over polar angles ``[start, stop)`` in radians, counter-clockwise from +x in the
    target frame; ``stop - start = 2*pi`` for a full disc or annulus.
    """

    r_inner: float
    r_outer: float
    start: float
    stop: float

    @property
    def full(self) -> bool:
        """True for a full disc or annulus."""
        return self.stop - self.start >= 2.0 * math.pi - 1e-12


def black_regions(design: FiducialDesign, code: int) -> tuple[Region, ...]:
    """The black regions of ``design`` printed with ``code``, as the design module defines them.

    Adjacent black code sectors are merged into one region so that no seam can print between them.

    Raises
    ------
    ValueError
        If ``code`` is not in the codebook.
    """
    bits = code_bits(code)
    regions = [Region(0.0, design.dot_radius, 0.0, 2.0 * math.pi)]
    if design.annulus_inner is not None:
        regions.append(Region(design.annulus_inner, 1.0, 0.0, 2.0 * math.pi))
    # Runs of black sectors, cyclically: start each run at a black sector after a white one.
    if bits.all():
        regions.append(Region(design.track_inner, design.track_outer, 0.0, 2.0 * math.pi))
    elif bits.any():
        step = 2.0 * math.pi / BITS
        for k in range(BITS):
            if bits[k] and not bits[k - 1]:
                n = 1
                while bits[(k + n) % BITS]:
                    n += 1
                regions.append(
                    Region(design.track_inner, design.track_outer, k * step, (k + n) * step)
                )
    return tuple(regions)


def min_feature(design: FiducialDesign) -> float:
    """Thinnest printed feature of ``design`` (black or white), in units of the outer radius.

    The smallest of the radial widths between successive printed radii and the arc width of one
    code sector at the inner edge of the track.
    """
    radii = {design.dot_radius, design.track_inner, design.track_outer, 1.0}
    if design.annulus_inner is not None:
        radii.add(design.annulus_inner)
    ordered = sorted(radii)
    widths = [b - a for a, b in zip([0.0, *ordered], ordered, strict=False)]
    sector = 2.0 * math.pi * design.track_inner / BITS
    return min([*widths, sector])


def parse_codes(spec: str, *, unique: bool = True) -> tuple[int, ...]:
    """Parse a code list such as ``"0-63"`` or ``"3,5,10-12"`` into sorted codes.

    Parameters
    ----------
    spec : str
        Comma-separated codes and inclusive ranges ``lo-hi``.
    unique : bool
        True (default): each code once. False: a code appears as many times as the list names
        it, also through overlapping ranges (``"1,1,2"`` and ``"0-2,1"`` both give code 1 twice),
        for printing several targets of one code.

    Raises
    ------
    PrintError
        If the list is malformed, a range is reversed, or a code is not in the codebook.
    """
    n = code_count()
    codes: list[int] = []
    items = [s.strip() for s in spec.split(",")]
    if not spec.strip() or any(not s for s in items):
        raise PrintError(f"empty item in code list {spec!r}; expected e.g. '0-63' or '3,5,10-12'")
    for item in items:
        lo_s, sep, hi_s = item.partition("-")
        try:
            lo = int(lo_s)
            hi = int(hi_s) if sep else lo
        except ValueError:
            raise PrintError(
                f"bad code range {item!r} in {spec!r}; expected e.g. '0-63' or '3,5,10-12'"
            ) from None
        if lo > hi:
            raise PrintError(f"reversed code range {item!r} in {spec!r}")
        if lo < 0 or hi >= n:
            raise PrintError(f"code range {item!r} is outside the codebook (codes 0..{n - 1})")
        codes.extend(range(lo, hi + 1))
    return tuple(sorted(set(codes) if unique else codes))


def format_codes(codes: Sequence[int]) -> str:
    """Inverse of :func:`parse_codes`: ``[0, 1, 2, 5]`` -> ``"0-2,5"``."""
    out: list[str] = []
    ordered = sorted(set(codes))
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        out.append(str(ordered[i]) if i == j else f"{ordered[i]}-{ordered[j]}")
        i = j + 1
    return ",".join(out)


def describe_codes(codes: Sequence[int], *, total: bool = True) -> str:
    """Short description of the targets of a sheet, codes summarised as ranges.

    ``[0, 1, 2, 5]`` -> ``"codes 0-2,5"``; every code twice -> ``"codes 0-2,5 x2 (8 targets)"``;
    codes with different counts are grouped by count in order of their first code:
    ``[1, 1, 2]`` -> ``"codes 1 x2; 2 x1 (3 targets)"``. ``total=False`` leaves out the
    ``(N targets)``.
    """
    counts = Counter(codes)
    if not counts:
        return "no codes"
    by_count: dict[int, list[int]] = {}
    for code in sorted(counts):
        by_count.setdefault(counts[code], []).append(code)
    if len(by_count) == 1 and 1 in by_count:
        return f"codes {format_codes(by_count[1])}"
    text = "codes " + "; ".join(f"{format_codes(group)} x{m}" for m, group in by_count.items())
    return text + (f" ({len(codes)} targets)" if total else "")


def parse_copies(text: str) -> int:
    """Parse a number of copies (a positive integer such as ``"150"``).

    Raises
    ------
    PrintError
        If ``text`` is not a positive integer.
    """
    try:
        copies = int(text.strip())
    except ValueError:
        copies = 0
    if copies < 1:
        raise PrintError(f"copies must be a positive integer, got {text!r}")
    return copies


def repeat_codes(codes: Sequence[int], copies: int) -> tuple[int, ...]:
    """Each code of ``codes`` ``copies`` times, copies of one entry next to each other.

    ``repeat_codes([1, 1, 2], 3)`` gives code 1 six times, then code 2 three times.

    Raises
    ------
    PrintError
        If ``copies`` is not a positive integer, or the total is above
        :data:`MAX_SHEET_TARGETS`.
    """
    if isinstance(copies, bool) or not isinstance(copies, int) or copies < 1:
        raise PrintError(f"copies must be a positive integer, got {copies!r}")
    total = len(codes) * copies
    if total > MAX_SHEET_TARGETS:
        raise PrintError(
            f"{len(codes)} codes x {copies} copies = {total} targets; a sheet holds at most "
            f"{MAX_SHEET_TARGETS}"
        )
    return tuple(code for code in codes for _ in range(copies))


def _check_common(diameter_mm: float, dpi: float, design: FiducialDesign) -> None:
    if not math.isfinite(dpi) or dpi <= 0:
        raise PrintError(f"dpi must be a positive number, got {dpi}")
    if not math.isfinite(diameter_mm) or diameter_mm <= 0:
        raise PrintError(f"diameter must be a positive number of mm, got {diameter_mm}")
    thinnest_dots = min_feature(design) * diameter_mm / 2.0 / MM_PER_INCH * dpi
    if thinnest_dots < MIN_FEATURE_DOTS:
        raise PrintError(
            f"a {diameter_mm} mm {design.name} target at {dpi} dpi has features of only "
            f"{thinnest_dots:.2f} printer dots (need >= {MIN_FEATURE_DOTS}); "
            f"use a larger diameter or a higher dpi"
        )


# --- PNG -------------------------------------------------------------------------------------


def target_image(
    design_name: str, code: int, diameter_mm: float, dpi: float, *, supersample: int = 16
) -> NDArray[np.uint8]:
    """One target as an 8-bit grayscale image at ``dpi`` (0 black, 255 white).

    The outermost printed circle is ``diameter_mm`` across (``diameter_mm / 25.4 * dpi`` pixels),
    centred at ``((n - 1) / 2, (n - 1) / 2)`` in an ``n x n`` image with a white margin of half a
    diameter on each side. Each pixel is the mean of the design's :func:`reflectance` over a
    ``supersample x supersample`` grid of its area; pixels whose neighbourhood is uniform on a
    half-pixel probe lattice skip the supersampling (the design's thinnest feature spans at least
    two pixels, see :data:`MIN_FEATURE_DOTS`, so the probes cannot step over an edge pair).

    Raises
    ------
    PrintError
        On an unknown design or code, a non-positive size or dpi, or features thinner than two
        pixels.
    """
    try:
        design = get_design(design_name)
        code_bits(code)
    except ValueError as err:
        raise PrintError(str(err)) from None
    _check_common(diameter_mm, dpi, design)
    if supersample < 1:
        raise PrintError(f"supersample must be >= 1, got {supersample}")
    radius_px = diameter_mm / MM_PER_INCH * dpi / 2.0
    side = 2.0 * radius_px * (1.0 + 2.0 * PNG_MARGIN)
    if side > MAX_PNG_SIDE_PX:
        raise PrintError(
            f"a {diameter_mm} mm target at {_num(dpi)} dpi would be {side:.0f} px across; "
            f"single-target PNGs are at most {MAX_PNG_SIDE_PX} px (lower the dpi)"
        )
    n = math.ceil(side)
    c = (n - 1) / 2.0

    def refl(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        # Pixel (u, v) -> target frame in outer radii; v grows down, target y grows up.
        return reflectance(design, code, (u - c) / radius_px, (c - v) / radius_px)

    # Half-pixel probe lattice: a pixel whose 3x3 probes (corners, edge midpoints, centre) agree
    # lies inside one region and takes the probe value.
    probe = -0.5 + 0.5 * np.arange(2 * n + 1)
    pu, pv = np.meshgrid(probe, probe)
    val = refl(pu, pv)
    blocks = np.lib.stride_tricks.sliding_window_view(val, (3, 3))[::2, ::2]
    mixed = blocks.min(axis=(2, 3)) != blocks.max(axis=(2, 3))
    out = val[1::2, 1::2].copy()
    rows, cols = np.nonzero(mixed)
    ou, ov = supersample_offsets(supersample)
    chunk = max(1, 2_000_000 // (supersample * supersample))
    for i in range(0, rows.size, chunk):
        r, k = rows[i : i + chunk], cols[i : i + chunk]
        su = k[:, None] + ou[None, :]
        sv = r[:, None] + ov[None, :]
        out[r, k] = refl(su.astype(np.float64), sv.astype(np.float64)).mean(axis=1)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    body = kind + data
    return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)


def encode_png(image: NDArray[np.uint8], dpi: float) -> bytes:
    """Encode an 8-bit grayscale image as PNG with its physical resolution (``pHYs``) set."""
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise PrintError(f"PNG needs a 2-D uint8 image, got {img.dtype} {img.shape}")
    h, w = img.shape
    ppm = round(dpi / MM_PER_INCH * 1000.0)  # pixels per metre
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(h))  # filter type 0 per row
    return b"".join(
        [
            b"\x89PNG\r\n\x1a\n",
            _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)),
            _png_chunk(b"pHYs", struct.pack(">IIB", ppm, ppm, 1)),
            _png_chunk(b"IDAT", zlib.compress(raw, 9)),
            _png_chunk(b"IEND", b""),
        ]
    )


# --- PDF -------------------------------------------------------------------------------------


def _num(x: float) -> str:
    s = f"{x:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _pdf_text(s: str) -> str:
    if not s.isascii():
        raise PrintError(f"label text must be ASCII, got {s!r}")
    return "(" + s.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)") + ")"


def _arc(cx: float, cy: float, r: float, a0: float, a1: float) -> list[str]:
    """Cubic Bezier segments (``c`` operators) along a circle from angle ``a0`` to ``a1``.

    Each segment spans at most 90 degrees with control points at distance
    ``4/3 tan(delta/4) r`` along the end tangents, the standard approximation whose radial error is
    below 2.8e-4 r at 90 degrees (far below a printer dot at target sizes).
    """
    n = max(1, math.ceil(abs(a1 - a0) / (math.pi / 2.0) - 1e-9))
    delta = (a1 - a0) / n
    k = 4.0 / 3.0 * math.tan(delta / 4.0)
    ops = []
    for i in range(n):
        t0 = a0 + i * delta
        t1 = t0 + delta
        c0, s0, c1, s1 = math.cos(t0), math.sin(t0), math.cos(t1), math.sin(t1)
        p1 = (cx + r * (c0 - k * s0), cy + r * (s0 + k * c0))
        p2 = (cx + r * (c1 + k * s1), cy + r * (s1 - k * c1))
        p3 = (cx + r * c1, cy + r * s1)
        ops.append(" ".join(_num(v) for v in (*p1, *p2, *p3)) + " c")
    return ops


def _region_path(region: Region, cx: float, cy: float, radius: float) -> list[str]:
    """PDF path operators filling ``region`` of a target centred at (cx, cy), radius in points.

    Outer boundaries run counter-clockwise and inner ones clockwise, so the nonzero fill rule
    leaves holes open.
    """
    ro, ri = region.r_outer * radius, region.r_inner * radius
    a0, a1 = region.start, region.stop
    ops = [f"{_num(cx + ro * math.cos(a0))} {_num(cy + ro * math.sin(a0))} m"]
    ops += _arc(cx, cy, ro, a0, a1)
    if region.full:
        ops.append("h")
        if ri > 0:
            ops.append(f"{_num(cx + ri * math.cos(a1))} {_num(cy + ri * math.sin(a1))} m")
            ops += _arc(cx, cy, ri, a1, a0)
            ops.append("h")
    else:
        ops.append(f"{_num(cx + ri * math.cos(a1))} {_num(cy + ri * math.sin(a1))} l")
        if ri > 0:
            ops += _arc(cx, cy, ri, a1, a0)
        ops.append("h")
    ops.append("f")
    return ops


def _crop_marks(cx: float, cy: float, half: float) -> list[str]:
    """Crop marks outside the four corners of the cut square of half-side ``half`` (points)."""
    off, length = CROP_OFFSET_MM * PT_PER_MM, CROP_LENGTH_MM * PT_PER_MM
    ops = []
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            x, y = cx + sx * half, cy + sy * half
            ops.append(
                f"{_num(x + sx * off)} {_num(y)} m {_num(x + sx * (off + length))} {_num(y)} l"
            )
            ops.append(
                f"{_num(x)} {_num(y + sy * off)} m {_num(x)} {_num(y + sy * (off + length))} l"
            )
    ops.append("S")
    return ops


def _text(x: float, y: float, size: float, s: str) -> str:
    return f"BT /F1 {_num(size)} Tf {_num(x)} {_num(y)} Td {_pdf_text(s)} Tj ET"


def text_width(s: str, size: float) -> float:
    """Width in points of ``s`` set in Helvetica at ``size`` points (:data:`HELVETICA_WIDTHS`).

    Raises
    ------
    PrintError
        If ``s`` holds a character outside printable ASCII.
    """
    total = 0
    for ch in s:
        k = ord(ch) - 32
        if not 0 <= k < len(HELVETICA_WIDTHS):
            raise PrintError(f"label text must be printable ASCII, got {s!r}")
        total += HELVETICA_WIDTHS[k]
    return total * size / 1000.0


def _fitted_text(x: float, y: float, size: float, s: str, max_width: float) -> str:
    """:func:`_text`, the font shrunk if need be so that the line is at most ``max_width`` wide."""
    width = text_width(s, size)
    if width > max_width:
        size = math.floor(size * max_width / width * 1e4) / 1e4  # _num keeps 4 decimals
    return _text(x, y, size, s)


def _title_prefix(design_name: str, diameter_mm: float) -> str:
    """What a sheet's title says before its codes."""
    diameter = _num(diameter_mm)
    return f"armourcam fiducial targets - design {design_name} - outer diameter {diameter} mm - "


def sheet_title(
    design_name: str, diameter_mm: float, codes: Sequence[int], max_width: float
) -> str:
    """The title line of a sheet, shortened to fit ``max_width`` points at :data:`TITLE_FONT_PT`.

    Parameters
    ----------
    design_name : str
    diameter_mm : float
    codes : sequence of int
        The sheet's targets, one entry each (repeats included).
    max_width : float
        Printable width in points.

    Returns
    -------
    str
        The codes summarised as ranges (:func:`describe_codes`); if that line is too wide, the
        list cut after as many items as fit, then ``", ... (N codes from LO to HI, M targets)"``
        (each target's label names its code). Should even that not fit, the caller shrinks the
        font (:func:`_fitted_text`).
    """
    prefix = _title_prefix(design_name, diameter_mm)
    desc = describe_codes(codes)
    full = prefix + desc
    if text_width(full, TITLE_FONT_PT) <= max_width:
        return full
    distinct = sorted(set(codes))
    plural = "s" if len(distinct) != 1 else ""
    summary = f"{len(distinct)} code{plural} from {distinct[0]} to {distinct[-1]}"
    if len(codes) != len(distinct):
        summary += f", {len(codes)} targets"
    tail = f", ... ({summary})"
    for cut in reversed([i for i, ch in enumerate(desc) if ch in ",;"]):
        line = prefix + desc[:cut] + tail
        if text_width(line, TITLE_FONT_PT) <= max_width:
            return line
    return prefix + f"codes ... ({summary})"


@dataclass(frozen=True, slots=True)
class SheetLayout:
    """Where targets go on A4 pages (millimetres, origin at the bottom-left of the page).

    Attributes
    ----------
    cut_side_mm : float
        Side of the square to cut around each target (the target plus its white margin).
    cell_w_mm, cell_h_mm : float
        Pitch of the grid of cells (cut square, crop marks, label).
    columns, rows : int
        Cells per row and rows per page.
    """

    cut_side_mm: float
    cell_w_mm: float
    cell_h_mm: float
    columns: int
    rows: int

    @property
    def per_page(self) -> int:
        """Targets per page."""
        return self.columns * self.rows


def sheet_layout(diameter_mm: float, label_width_mm: float) -> SheetLayout:
    """Grid of cells for targets of ``diameter_mm`` with labels ``label_width_mm`` wide.

    Raises
    ------
    PrintError
        If not even one target fits on an A4 page.
    """
    cut = diameter_mm + 2.0 * max(CUT_MARGIN * diameter_mm, MIN_CUT_MARGIN_MM)
    marks = CROP_OFFSET_MM + CROP_LENGTH_MM
    cell_w = cut + LABEL_GAP_MM + label_width_mm + 2.0 * marks
    cell_h = cut + 2.0 * marks + 1.0
    avail_w = A4_MM[0] - 2.0 * PAGE_MARGIN_MM
    avail_h = A4_MM[1] - 2.0 * PAGE_MARGIN_MM - 22.0  # title at the top, scale bar at the bottom
    cols, rows = int(avail_w // cell_w), int(avail_h // cell_h)
    if cols < 1 or rows < 1:
        raise PrintError(f"a {diameter_mm} mm target with its label does not fit on an A4 page")
    return SheetLayout(cut, cell_w, cell_h, cols, rows)


def target_sheet_pdf(
    design_name: str, codes: Sequence[int], diameter_mm: float, dpi: float
) -> bytes:
    """An A4 PDF sheet of vector targets, labels, crop marks, a title and a scale bar.

    Parameters
    ----------
    design_name : {"dot", "ring"}
    codes : sequence of int
        Codes to print, one target each, in the given order; a code given ``n`` times is printed
        ``n`` times (see :func:`repeat_codes`). Each target's label names its code.
    diameter_mm : float
        Diameter of the outermost printed circle.
    dpi : float
        Resolution of the laser printer; used to refuse targets whose thinnest feature is under
        two printer dots and stated on the sheet (the artwork itself is vector).

    Returns
    -------
    bytes
        A PDF 1.4 file with as many pages as needed.

    Raises
    ------
    PrintError
        On an unknown design or code, no codes or more than :data:`MAX_SHEET_TARGETS`, a
        non-positive size or dpi, features thinner than two printer dots, or targets too large for
        A4.
    """
    try:
        design = get_design(design_name)
        for code in codes:
            code_bits(code)
    except ValueError as err:
        raise PrintError(str(err)) from None
    if not codes:
        raise PrintError("no codes to print")
    if len(codes) > MAX_SHEET_TARGETS:
        raise PrintError(
            f"{len(codes)} targets asked for; a sheet holds at most {MAX_SHEET_TARGETS}"
        )
    _check_common(diameter_mm, dpi, design)
    detail = f"{design.name} {_num(diameter_mm)} mm"
    label_w_pt = max(
        max(text_width(str(c), CODE_FONT_PT) for c in set(codes)),
        text_width(detail, DETAIL_FONT_PT),
    )
    layout = sheet_layout(diameter_mm, label_w_pt / PT_PER_MM)
    pages = [codes[i : i + layout.per_page] for i in range(0, len(codes), layout.per_page)]
    thinnest = min_feature(design) * diameter_mm / 2.0
    line_w_pt = (A4_MM[0] - 2.0 * PAGE_MARGIN_MM) * PT_PER_MM
    title = sheet_title(design.name, diameter_mm, codes, line_w_pt)
    full_title = _title_prefix(design.name, diameter_mm) + describe_codes(codes)
    footer = (
        f"Print at 100 % (actual size, no fit to page). The bar is {_num(SCALE_BAR_MM)} mm long. "
        f"Vector artwork; thinnest feature {thinnest:.2f} mm = "
        f"{thinnest / MM_PER_INCH * dpi:.1f} dots at {_num(dpi)} dpi."
    )
    w_pt, h_pt = A4_MM[0] * PT_PER_MM, A4_MM[1] * PT_PER_MM
    radius_pt = diameter_mm / 2.0 * PT_PER_MM
    half_cut = layout.cut_side_mm / 2.0 * PT_PER_MM
    marks = CROP_OFFSET_MM + CROP_LENGTH_MM
    contents: list[bytes] = []
    for page_no, page_codes in enumerate(pages, start=1):
        ops = ["0 g 0 G"]
        top = A4_MM[1] - PAGE_MARGIN_MM
        x_pt = PAGE_MARGIN_MM * PT_PER_MM
        ops.append(_fitted_text(x_pt, (top - 4.0) * PT_PER_MM, TITLE_FONT_PT, title, line_w_pt))
        ops.append(
            _fitted_text(
                x_pt,
                (top - 8.5) * PT_PER_MM,
                PAGE_LINE_FONT_PT,
                f"page {page_no} of {len(pages)}; cut on the crop marks",
                line_w_pt,
            )
        )
        grid_top = top - 12.0
        for i, code in enumerate(page_codes):
            row, col = divmod(i, layout.columns)
            x0 = PAGE_MARGIN_MM + col * layout.cell_w_mm + marks
            cy_mm = grid_top - row * layout.cell_h_mm - marks - layout.cut_side_mm / 2.0
            cx_mm = x0 + layout.cut_side_mm / 2.0
            cx, cy = cx_mm * PT_PER_MM, cy_mm * PT_PER_MM
            for region in black_regions(design, code):
                ops += _region_path(region, cx, cy, radius_pt)
            ops.append("0.25 w")
            ops += _crop_marks(cx, cy, half_cut)
            lx = (x0 + layout.cut_side_mm + LABEL_GAP_MM) * PT_PER_MM
            ops.append(_text(lx, cy + 0.5, CODE_FONT_PT, str(code)))
            ops.append(_text(lx, cy - DETAIL_FONT_PT - 0.5, DETAIL_FONT_PT, detail))
        bar_y = (PAGE_MARGIN_MM + 4.0) * PT_PER_MM
        x0_pt = PAGE_MARGIN_MM * PT_PER_MM
        x1_pt = x0_pt + SCALE_BAR_MM * PT_PER_MM
        tick = 1.5 * PT_PER_MM
        ops.append("0.5 w")
        ops.append(
            f"{_num(x0_pt)} {_num(bar_y)} m {_num(x1_pt)} {_num(bar_y)} l "
            f"{_num(x0_pt)} {_num(bar_y - tick)} m {_num(x0_pt)} {_num(bar_y + tick)} l "
            f"{_num(x1_pt)} {_num(bar_y - tick)} m {_num(x1_pt)} {_num(bar_y + tick)} l S"
        )
        ops.append(
            _fitted_text(x0_pt, PAGE_MARGIN_MM * PT_PER_MM - 3.0, FOOTER_FONT_PT, footer, line_w_pt)
        )
        contents.append(("\n".join(ops) + "\n").encode("ascii"))
    return _pdf_document(contents, w_pt, h_pt, full_title)


def _pdf_document(contents: Sequence[bytes], w_pt: float, h_pt: float, title: str) -> bytes:
    """Assemble a PDF 1.4 file: catalog 1, page tree 2, font 3, info 4, then page/content pairs."""
    n_pages = len(contents)
    page_ids = [5 + 2 * i for i in range(n_pages)]
    objects: list[bytes] = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        (
            "<< /Type /Pages /Kids ["
            + " ".join(f"{p} 0 R" for p in page_ids)
            + f"] /Count {n_pages} >>"
        ).encode("ascii"),
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        f"<< /Title {_pdf_text(title)} /Producer (armourcam) >>".encode("ascii"),
    ]
    for pid, content in zip(page_ids, contents, strict=True):
        objects.append(
            (
                f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_num(w_pt)} {_num(h_pt)}] "
                f"/Resources << /Font << /F1 3 0 R >> >> /Contents {pid + 1} 0 R >>"
            ).encode("ascii")
        )
        objects.append(
            f"<< /Length {len(content)} >>\nstream\n".encode("ascii") + content + b"endstream"
        )
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for num, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f"{num} 0 obj\n".encode("ascii") + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode("ascii")
    for off in offsets:
        out += f"{off:010d} 00000 n \n".encode("ascii")
    out += (
        f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R /Info 4 0 R >>\n"
        f"startxref\n{xref}\n%%EOF\n"
    ).encode("ascii")
    return bytes(out)


def write_targets(
    path: str | Path,
    design_name: str,
    codes: Sequence[int],
    diameter_mm: float,
    dpi: float,
    *,
    copies: int = 1,
) -> str:
    """Write a PDF sheet (``.pdf``) or a single-target PNG (``.png``); returns a summary line.

    Each entry of ``codes`` is printed ``copies`` times (:func:`repeat_codes`), so a code listed
    twice prints ``2 * copies`` targets. A PNG holds exactly one target: one code, one copy.

    Raises
    ------
    PrintError
        On an unsupported extension, a bad ``copies``, a PNG asked for other than exactly one
        target, or any error of :func:`target_sheet_pdf` / :func:`target_image`. Nothing is
        written on error.
    """
    out = Path(path)
    ext = out.suffix.lower()
    targets = repeat_codes(codes, copies)
    if ext == ".pdf":
        data = target_sheet_pdf(design_name, targets, diameter_mm, dpi)
        n_pages = data.count(b"/Type /Page ")
        summary = (
            f"wrote {out}: {len(targets)} {design_name} targets of {_num(diameter_mm)} mm "
            f"on {n_pages} page{'s' if n_pages != 1 else ''}"
        )
        if len(set(targets)) != len(targets):
            summary += f" ({describe_codes(targets, total=False)})"
    elif ext == ".png":
        if len(targets) != 1:
            raise PrintError(
                f"a PNG holds exactly one target; got {len(targets)} "
                f"({describe_codes(targets, total=False)}); write a .pdf sheet for several"
            )
        img = target_image(design_name, targets[0], diameter_mm, dpi)
        data = encode_png(img, dpi)
        summary = (
            f"wrote {out}: {design_name} target {targets[0]}, {_num(diameter_mm)} mm = "
            f"{diameter_mm / MM_PER_INCH * dpi:.1f} px at {_num(dpi)} dpi, "
            f"{img.shape[1]}x{img.shape[0]} px"
        )
    else:
        raise PrintError(
            f"unsupported output {str(out)!r}: use a .pdf (sheet) or .png (one target)"
        )
    # Atomic: a failed write (a full disk) leaves an earlier sheet of that name whole.
    write_atomic(out, data)
    return summary
