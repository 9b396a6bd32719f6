"""Printable targets: the PDF sheet's structure and geometry, the PNG's size, and the CLI."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from armourcam.cli import main
from armourcam.printing import (
    A4_MM,
    MAX_SHEET_TARGETS,
    PAGE_MARGIN_MM,
    PT_PER_MM,
    PrintError,
    black_regions,
    describe_codes,
    encode_png,
    parse_codes,
    repeat_codes,
    sheet_layout,
    sheet_title,
    target_image,
    target_sheet_pdf,
    text_width,
    write_targets,
)
from fiducial_detector.codebook import BITS, code_bits
from fiducial_detector.design import get_design, reflectance

# --- a minimal PDF reader for the tests -------------------------------------------------------


def _objects(pdf: bytes) -> dict[int, bytes]:
    """Objects by number, located through the xref table (which must be byte-exact)."""
    assert pdf.startswith(b"%PDF-1.4\n")
    assert pdf.rstrip().endswith(b"%%EOF")
    startxref = int(re.findall(rb"startxref\s+(\d+)\s+%%EOF", pdf)[-1])
    assert pdf[startxref:].startswith(b"xref\n")
    head = re.match(rb"xref\n0 (\d+)\n", pdf[startxref:])
    assert head is not None
    size = int(head.group(1))
    table = pdf[startxref + head.end() :]
    trailer = re.search(rb"trailer\s*<<(.*?)>>", pdf[startxref:], re.S)
    assert trailer is not None and f"/Size {size}".encode() in trailer.group(1)
    objs = {}
    for i in range(size):
        entry = table[20 * i : 20 * (i + 1)]
        assert len(entry) == 20 and entry.endswith(b" \n")
        off, gen, kind = entry[:10], entry[11:16], entry[17:18]
        if i == 0:
            assert kind == b"f"
            continue
        assert kind == b"n" and gen == b"00000"
        start = int(off)
        assert pdf[start:].startswith(f"{i} 0 obj".encode()), f"xref offset of object {i}"
        end = pdf.index(b"endobj", start)
        objs[i] = pdf[start:end]
    return objs


def _stream(obj: bytes) -> bytes:
    """The data of a stream object, checked against its /Length."""
    m = re.search(rb"/Length (\d+)\s*>>\s*stream\n", obj)
    assert m is not None
    data = obj[m.end() : m.end() + int(m.group(1))]
    assert obj[m.end() + int(m.group(1)) :].startswith(b"endstream")
    return data


def _pages(pdf: bytes) -> list[bytes]:
    """Content streams of the pages, in page-tree order."""
    objs = _objects(pdf)
    root = int(re.search(rb"/Root (\d+) 0 R", pdf).group(1))  # type: ignore[union-attr]
    pages_ref = int(re.search(rb"/Pages (\d+) 0 R", objs[root]).group(1))  # type: ignore[union-attr]
    tree = objs[pages_ref]
    count = int(re.search(rb"/Count (\d+)", tree).group(1))  # type: ignore[union-attr]
    kids = [int(k) for k in re.findall(rb"(\d+) 0 R", tree.split(b"/Kids")[1].split(b"]")[0])]
    assert len(kids) == count
    out = []
    for kid in kids:
        assert b"/Type /Page " in objs[kid] and b"/MediaBox [0 0 595.2756 841.8898]" in objs[kid]
        content = int(re.search(rb"/Contents (\d+) 0 R", objs[kid]).group(1))  # type: ignore[union-attr]
        out.append(_stream(objs[content]))
    return out


Point = tuple[float, float]


def _filled_paths(content: bytes) -> list[list[list[tuple[str, list[Point]]]]]:
    """Filled paths as lists of subpaths; each subpath is a list of (operator, points)."""
    text = re.sub(rb"BT.*?ET", b"", content, flags=re.S).decode()
    paths: list[list[list[tuple[str, list[Point]]]]] = []
    current: list[list[tuple[str, list[Point]]]] = []
    nums: list[float] = []
    for tok in text.split():
        try:
            nums.append(float(tok))
            continue
        except ValueError:
            pass
        pts = [(nums[i], nums[i + 1]) for i in range(0, len(nums) - 1, 2)]
        if tok == "m":
            current.append([("m", pts)])
        elif tok in ("l", "c"):
            current[-1].append((tok, pts))
        elif tok == "f":
            paths.append(current)
            current = []
        elif tok == "S":
            current = []
        nums = []
    return paths


def _flatten(subpath: list[tuple[str, list[Point]]], scale: float) -> NDArray[np.float64]:
    """Polygon of a subpath with Bezier segments evaluated densely."""
    poly = [subpath[0][1][0]]
    t = np.linspace(0.0, 1.0, 64)[1:, None]
    for op, pts in subpath[1:]:
        p0 = np.array(poly[-1])
        if op == "l":
            poly.append(pts[0])
        else:
            p1, p2, p3 = (np.array(p) for p in pts)
            curve = (
                (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t**2 * p2 + t**3 * p3
            )
            poly += [tuple(q) for q in curve]
    return np.array(poly) * scale


# --- PDF --------------------------------------------------------------------------------------


def test_pdf_structure_and_contents() -> None:
    """Byte-exact xref, one page for 64 small targets, every region drawn, labels and title."""
    pdf = target_sheet_pdf("dot", list(range(64)), 7.1, 600)
    pages = _pages(pdf)
    assert len(pages) == 1
    paths = _filled_paths(pages[0])
    n_regions = sum(len(black_regions(get_design("dot"), c)) for c in range(64))
    assert len(paths) == n_regions
    assert b"/BaseFont /Helvetica" in pdf
    assert b"design dot - outer diameter 7.1 mm - codes 0-63" in pages[0]
    for code in (0, 9, 63):
        assert f"({code}) Tj".encode() in pages[0]
    assert pages[0].count(b"(dot 7.1 mm) Tj") == 64
    # Crop marks: 8 strokes per target (two at each corner of the cut square).
    marks = re.findall(rb"[\d.]+ [\d.]+ m [\d.]+ [\d.]+ l\n", pages[0])
    assert len(marks) == 8 * 64


def test_pdf_multiple_pages() -> None:
    """Large targets spill over several pages, each a valid page with its share of targets."""
    layout = sheet_layout(30.0, 10.0)
    pdf = target_sheet_pdf("ring", list(range(66)), 30.0, 600)
    pages = _pages(pdf)
    assert len(pages) == math.ceil(66 / layout.per_page) > 1
    per_page = [c.count(b"(ring 30 mm) Tj") for c in pages]
    assert sum(per_page) == 66
    assert per_page[0] == layout.per_page


@pytest.mark.parametrize("name", ["dot", "ring"])
def test_pdf_arcs_lie_on_the_design_radii(name: str) -> None:
    """Every path vertex lies on a printed radius, and every Bezier arc stays on its circle."""
    design = get_design(name)
    radius_pt = 7.1 / 2.0 * PT_PER_MM
    paths = _filled_paths(_pages(target_sheet_pdf(name, [12], 7.1, 600))[0])
    first = paths[0][0]
    centre = np.mean([pts[-1] for _, pts in first[1:]], axis=0)  # the central dot's quadrants
    radii = {design.dot_radius, design.track_inner, design.track_outer}
    if design.annulus_inner is not None:
        radii |= {design.annulus_inner, 1.0}
    allowed = np.array(sorted(radii)) * radius_pt
    for path in paths:
        for sub in path:
            p_prev = np.array(sub[0][1][0])
            for op, pts in sub:
                end = np.array(pts[-1])
                r = np.hypot(*(end - centre))
                assert np.min(np.abs(allowed - r)) < 2e-3
                if op == "c":
                    p1, p2 = np.array(pts[0]), np.array(pts[1])
                    mid = (p_prev + 3 * p1 + 3 * p2 + end) / 8.0
                    assert abs(np.hypot(*(mid - centre)) - r) < 3e-4 * r + 2e-3
                p_prev = end


@pytest.mark.parametrize("name", ["dot", "ring"])
@pytest.mark.parametrize("code", [0, 40])
def test_pdf_paths_fill_exactly_the_reflectance(name: str, code: int) -> None:
    """Rasterised PDF paths agree with ``reflectance`` everywhere away from the edges."""
    design = get_design(name)
    diameter = 7.1
    radius_pt = diameter / 2.0 * PT_PER_MM
    paths = _filled_paths(_pages(target_sheet_pdf(name, [code], diameter, 600))[0])
    centre = np.mean([pts[-1] for _, pts in paths[0][0][1:]], axis=0)
    scale = 20.0  # raster pixels per point
    n = int(2.4 * radius_pt * scale)
    origin = centre - 1.2 * radius_pt
    canvas = np.zeros((n, n), np.uint8)
    for path in paths:
        # Each region on its own layer with even-odd filling (cv2.fillPoly), then OR-ed: the
        # PDF's opposite-direction inner subpaths make the nonzero rule fill the same set.
        layer = np.zeros_like(canvas)
        polys = [np.rint(_flatten(sub, scale) - origin * scale).astype(np.int32) for sub in path]
        cv2.fillPoly(layer, polys, 1)
        canvas |= layer
    # Raster row r covers PDF y = origin_y + r / scale (y up); compare in target units.
    idx = np.arange(n) / scale
    x = (origin[0] + idx[None, :] - centre[0]) / radius_pt
    y = (origin[1] + idx[:, None] - centre[1]) / radius_pt
    expected_black = reflectance(design, code, x, y) == 0.0
    # Away from edges: the reflectance is constant over a 1.5-raster-pixel neighbourhood.
    h = 1.5 / scale / radius_pt
    stable = np.ones_like(expected_black)
    for dx, dy in [(-h, -h), (-h, h), (h, -h), (h, h), (0, h), (h, 0), (0, -h), (-h, 0)]:
        stable &= (reflectance(design, code, x + dx, y + dy) == 0.0) == expected_black
    assert stable.mean() > 0.9
    np.testing.assert_array_equal(canvas.astype(bool)[stable], expected_black[stable])


def test_black_regions_cover_the_code_sectors() -> None:
    """Merged sector runs cover exactly the black bits (checked at every sector's middle)."""
    design = get_design("ring")
    for code in range(66):
        bits = code_bits(code)
        track = [r for r in black_regions(design, code) if r.r_inner == design.track_inner]
        assert sum(r.stop - r.start for r in track) == pytest.approx(bits.sum() * 2 * np.pi / BITS)
        for k in range(BITS):
            theta = 2 * np.pi * (k + 0.5) / BITS
            hit = any(
                r.start <= theta < r.stop or r.start <= theta + 2 * np.pi < r.stop for r in track
            )
            assert hit == bool(bits[k])


_TEXT = re.compile(rb"BT /F1 (\S+) Tf (\S+) (\S+) Td \(((?:[^()\\]|\\.)*)\) Tj ET")


def _texts(content: bytes) -> list[tuple[float, float, float, str]]:
    """Text lines of a page as (font size, x, y, string), PDF escapes undone."""
    return [
        (float(m[1]), float(m[2]), float(m[3]), re.sub(r"\\(.)", r"\1", m[4].decode("ascii")))
        for m in _TEXT.finditer(content)
    ]


def _labels(content: bytes) -> list[int]:
    """The code labels beside the targets of a page, in drawing order."""
    return [int(s) for size, _, _, s in _texts(content) if size == 7.0 and s.isdigit()]


def test_text_width_uses_helvetica_metrics() -> None:
    """Widths add Helvetica's advance widths: 'm' is 0.833 em, digits 0.556 em, 'i' 0.222 em."""
    assert text_width("m", 1000.0) == pytest.approx(833.0)
    assert text_width("0123456789", 10.0) == pytest.approx(55.6)
    assert text_width("mi i", 9.0) == pytest.approx(9.0 * (0.833 + 0.222 + 0.278 + 0.222))
    with pytest.raises(PrintError, match="printable ASCII"):
        text_width("\u00b5m", 9.0)


@pytest.mark.parametrize(
    ("codes", "copies", "diameter"),
    [
        (list(range(0, 66, 2)), 1, 7.1),  # 33 isolated codes: no range shortens the list
        ([*range(0, 66, 2), 1, 1], 7, 12.3456),  # mixed counts and a long diameter
        (list(range(66)), 150, 7.1),
    ],
)
def test_every_text_line_fits_the_printable_width(
    codes: list[int], copies: int, diameter: float
) -> None:
    """Title, page line, labels and footer end inside the right margin for worst-case lists.

    The old title listed every code: 33 isolated codes made it 676 pt wide on a 527 pt line.
    """
    targets = repeat_codes(codes, copies)
    pdf = target_sheet_pdf("ring", targets, diameter, 600)
    right_pt = (A4_MM[0] - PAGE_MARGIN_MM) * PT_PER_MM
    pages = _pages(pdf)
    for content in (pages[0], pages[-1]):
        texts = _texts(content)
        assert texts[0][3].startswith("armourcam fiducial targets - design ring")
        for size, x, _, s in texts:
            assert x + text_width(s, size) <= right_pt + 1e-6, s
    # The title is shortened, not shrunk, and starts the list with as many codes as fit.
    size, _, _, title = _texts(pages[0])[0]
    assert size == 9.0
    assert f"outer diameter {diameter:g} mm - codes 0" in title


def test_sparse_title_is_cut_with_a_count_and_metadata_keeps_the_list() -> None:
    """A list too long for the line ends '..., (33 codes from 0 to 64)'; /Title has all codes."""
    codes = list(range(0, 66, 2))
    pdf = target_sheet_pdf("dot", codes, 7.1, 600)
    title = _texts(_pages(pdf)[0])[0][3]
    assert title.startswith("armourcam fiducial targets - design dot - outer diameter 7.1 mm - ")
    assert title.endswith(", ... (33 codes from 0 to 64)") and "codes 0,2,4,6," in title
    full = ",".join(str(c) for c in codes)
    assert f"- codes {full}) /Producer".encode() in pdf
    # Lists that fit are left whole, as ranges.
    short = [0, 3, 7, 12, 19, 25, 31, 40, 47, 55, 63]
    assert sheet_title("ring", 7.1, short, 527.0).endswith("codes 0,3,7,12,19,25,31,40,47,55,63")
    assert sheet_title("ring", 7.1, list(range(64)), 527.0).endswith("codes 0-63")
    # A width too small for any list still names the count.
    tiny = sheet_title("ring", 7.1, [5, 5], 50.0)
    assert tiny.endswith("codes ... (1 code from 5 to 5, 2 targets)")


@pytest.mark.parametrize(
    ("codes", "text"),
    [
        ([0, 1, 2, 5], "codes 0-2,5"),
        ([0, 0, 1, 1], "codes 0-1 x2 (4 targets)"),
        ([1, 1, 2], "codes 1 x2; 2 x1 (3 targets)"),
        ([7, 3, 3, 7, 9], "codes 3,7 x2; 9 x1 (5 targets)"),
    ],
)
def test_describe_codes(codes: list[int], text: str) -> None:
    """Codes as ranges, grouped by how many targets each has."""
    assert describe_codes(codes) == text


# --- copies -----------------------------------------------------------------------------------


def test_parse_codes_can_keep_repeats() -> None:
    """With ``unique=False`` a code counts once per listing, overlapping ranges included."""
    assert parse_codes("1,1,2", unique=False) == (1, 1, 2)
    assert parse_codes("2-3,0-2", unique=False) == (0, 1, 2, 2, 3)
    assert parse_codes("1,1,2") == (1, 2)


def test_repeat_codes() -> None:
    """Each entry ``copies`` times, copies side by side; bad counts name the problem."""
    assert repeat_codes([1, 1, 2], 3) == (1,) * 6 + (2,) * 3
    assert repeat_codes([4, 9], 1) == (4, 9)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(PrintError, match="copies must be a positive integer"):
            repeat_codes([1], bad)  # type: ignore[arg-type]
    with pytest.raises(PrintError, match=f"at most {MAX_SHEET_TARGETS}"):
        repeat_codes(list(range(64)), 10**9)


def test_copies_spill_over_pages_with_every_label_naming_its_code(tmp_path: Path) -> None:
    """Four codes x 150 copies: 600 targets on ceil(600 / per page) full pages, 150 of each."""
    path = tmp_path / "sheet.pdf"
    summary = write_targets(path, "ring", [0, 1, 2, 3], 7.1, 600, copies=150)
    pages = _pages(path.read_bytes())
    per_page = [len(_labels(c)) for c in pages]
    assert len(pages) == math.ceil(600 / per_page[0]) > 1
    assert all(n == per_page[0] for n in per_page[:-1]) and sum(per_page) == 600
    labels = [code for c in pages for code in _labels(c)]
    assert labels == [0] * 150 + [1] * 150 + [2] * 150 + [3] * 150
    n_regions = {c: len(black_regions(get_design("ring"), c)) for c in range(4)}
    for k, content in enumerate(pages, start=1):
        assert f"(page {k} of {len(pages)}; cut on the crop marks) Tj".encode() in content
        assert rb"codes 0-3 x150 \(600 targets\)) Tj" in content
        assert len(_filled_paths(content)) == sum(n_regions[c] for c in _labels(content))
    assert summary.startswith(f"wrote {path}: 600 ring targets of 7.1 mm on {len(pages)} pages")
    assert summary.endswith("(codes 0-3 x150)")


# --- PNG --------------------------------------------------------------------------------------


def _edge_radius(img: NDArray[np.float64], centre: float, theta: float, r_guess: float) -> float:
    """Radius where the profile along direction ``theta`` (y up) crosses mid-grey going outwards."""
    r = np.arange(0.8 * r_guess, 1.2 * r_guess, 0.01)
    u = centre + r * np.cos(theta)
    v = centre - r * np.sin(theta)
    prof = cv2.remap(
        img.astype(np.float32),
        u.astype(np.float32)[None, :],
        v.astype(np.float32)[None, :],
        cv2.INTER_LINEAR,
    )[0]
    above = np.nonzero((prof[:-1] < 127.5) & (prof[1:] >= 127.5))[0]
    assert above.size, "no dark-to-light crossing"
    i = above[-1]
    t = (127.5 - prof[i]) / (prof[i + 1] - prof[i])
    return float(r[i] + t * (r[i + 1] - r[i]))


@pytest.mark.parametrize(
    ("name", "code", "diameter", "dpi"),
    [
        ("ring", 7, 7.1, 600),
        ("dot", 21, 7.1, 600),
        ("ring", 50, 5.0, 300),
        ("dot", 3, 12.0, 150),
    ],
)
def test_png_outer_circle_has_the_asked_diameter(
    name: str, code: int, diameter: float, dpi: float
) -> None:
    """The outermost printed circle measures ``diameter_mm / 25.4 * dpi`` pixels across."""
    img = target_image(name, code, diameter, dpi)
    n = img.shape[0]
    assert img.shape == (n, n) and img.dtype == np.uint8
    centre = (n - 1) / 2.0
    want = diameter / 25.4 * dpi
    design = get_design(name)
    bits = code_bits(code)
    # Directions where the outer circle is printed: all round for ring, black sectors for dot.
    ks = [k for k in range(BITS) if design.annulus_inner is not None or bits[k]]
    radii = {
        k: _edge_radius(img.astype(np.float64), centre, 2 * np.pi * (k + 0.5) / BITS, want / 2)
        for k in ks
    }
    for k, r in radii.items():
        assert abs(2 * r - want) <= 1.0, (k, 2 * r, want)
        assert abs(2 * r - want) <= 0.25  # in fact far tighter than the +-1 px asked
        if (k + BITS // 2) % BITS in radii:
            assert abs(r + radii[(k + BITS // 2) % BITS] - want) <= 0.25
    # White margin all round, and the central dot is centred.
    for edge in (img[0], img[-1], img[:, 0], img[:, -1]):
        assert edge.min() == 255
    dot = [
        _edge_radius(img.astype(np.float64), centre, a, design.dot_radius * want / 2)
        for a in (0.0, np.pi / 2, np.pi, 3 * np.pi / 2)
    ]
    assert max(dot) - min(dot) < 0.2


def test_png_file_round_trip(tmp_path: Path) -> None:
    """The PNG decodes to the same pixels and carries its dpi in a pHYs chunk."""
    path = tmp_path / "target.png"
    summary = write_targets(path, "ring", [4], 7.1, 600)
    assert "167.7 px" in summary
    data = path.read_bytes()
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, target_image("ring", 4, 7.1, 600))
    phys = data.index(b"pHYs")
    ppm = int.from_bytes(data[phys + 4 : phys + 8], "big")
    assert ppm == round(600 / 0.0254)


def test_png_reads_back_through_the_detector() -> None:
    """The fiducial detector reads the printed code back from the PNG at its centre."""
    from fiducial_detector import detect

    for name, code in (("dot", 11), ("ring", 37)):
        img = target_image(name, code, 7.1, 300)  # about 84 px across
        dets = detect(img)
        assert [d.code for d in dets] == [code]
        centre = (img.shape[0] - 1) / 2.0
        assert np.hypot(dets[0].center_px[0] - centre, dets[0].center_px[1] - centre) < 0.2


# --- arguments and CLI ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "codes"),
    [
        ("0-3", (0, 1, 2, 3)),
        ("3,5,10-12", (3, 5, 10, 11, 12)),
        (" 7 , 2-3,3", (2, 3, 7)),
        ("65", (65,)),
    ],
)
def test_parse_codes(spec: str, codes: tuple[int, ...]) -> None:
    """Ranges and lists, sorted and de-duplicated."""
    assert parse_codes(spec) == codes


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("", "empty"),
        ("1,,2", "empty"),
        ("5-3", "reversed"),
        ("0-66", "outside the codebook"),
        ("-1", "bad code range|outside"),
        ("a-b", "bad code range"),
        ("1-2-3", "bad code range"),
    ],
)
def test_parse_codes_rejects_bad_lists(spec: str, match: str) -> None:
    """Bad code lists name what is wrong."""
    with pytest.raises(PrintError, match=match):
        parse_codes(spec)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dpi": 0}, "dpi must be a positive"),
        ({"dpi": -600}, "dpi must be a positive"),
        ({"diameter_mm": 0.0}, "diameter"),
        ({"diameter_mm": 0.5}, "printer dots"),
        ({"diameter_mm": 400.0}, "does not fit"),
        ({"codes": [66]}, "not in the codebook"),
        ({"codes": []}, "no codes"),
        ({"design_name": "star"}, "unknown fiducial design"),
    ],
)
def test_sheet_rejects_bad_arguments(kwargs: dict[str, object], match: str) -> None:
    """Bad sizes, resolutions, codes and designs raise PrintError naming the problem."""
    args: dict[str, object] = {"design_name": "dot", "codes": [1], "diameter_mm": 7.1, "dpi": 600}
    args.update(kwargs)
    with pytest.raises(PrintError, match=match):
        target_sheet_pdf(**args)  # type: ignore[arg-type]


def test_encode_png_rejects_colour() -> None:
    """Only 8-bit grey images are encoded."""
    with pytest.raises(PrintError, match="2-D uint8"):
        encode_png(np.zeros((4, 4, 3), np.uint8), 600)


def test_cli_copies_and_repeated_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--codes 2,1,1 --copies 3`` prints code 1 six times, then code 2 three times."""
    pdf = tmp_path / "sheet.pdf"
    assert main(["targets", "--codes", "2,1,1", "--copies", "3", "-o", str(pdf)]) == 0
    (page,) = _pages(pdf.read_bytes())
    assert _labels(page) == [1] * 6 + [2] * 3
    assert "9 ring targets" in capsys.readouterr().out


def test_cli_writes_pdf_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``armourcam targets`` writes both outputs and reports them."""
    pdf = tmp_path / "sheet.pdf"
    assert main(["targets", "--design", "ring", "--codes", "0-63", "-o", str(pdf)]) == 0
    assert len(_pages(pdf.read_bytes())) == 1
    png = tmp_path / "t.png"
    args = ["targets", "--codes", "9", "--diameter-mm", "7.1", "--dpi", "600", "-o", str(png)]
    assert main(args) == 0
    back = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert back is not None and back.shape == (336, 336)
    out = capsys.readouterr().out
    assert "64 ring targets" in out and "ring target 9" in out  # ring: the default


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--codes", "0-3", "-o", "t.png"], "exactly one target"),
        (
            ["--codes", "9", "--copies", "2", "-o", "t.png"],
            r"exactly one target; got 2 \(codes 9 x2",
        ),
        (["--codes", "9,9", "-o", "t.png"], "exactly one target; got 2"),
        (["--copies", "0", "-o", "t.pdf"], "copies must be a positive integer, got '0'"),
        (["--copies", "-2", "-o", "t.pdf"], "copies must be a positive integer"),
        (["--copies", "1.5", "-o", "t.pdf"], "copies must be a positive integer"),
        (["--copies", "many", "-o", "t.pdf"], "copies must be a positive integer"),
        (["--copies", "1000", "-o", "t.pdf"], "64000 targets; a sheet holds at most"),
        (["-o", "t.jpg"], "unsupported output"),
        (["--codes", "99", "-o", "t.pdf"], "outside the codebook"),
        (["--dpi", "0", "-o", "t.pdf"], "dpi must be a positive"),
    ],
)
def test_cli_errors_are_one_line_and_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], match: str
) -> None:
    """Bad arguments exit with status 2, a one-line message and no output file."""
    args = [a if not a.startswith("t.") else str(tmp_path / a) for a in args]
    assert main(["targets", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and re.search(match, err)
    assert not list(tmp_path.iterdir())


def test_a_failed_write_leaves_the_earlier_sheet_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A sheet is written atomically: where the disk fills mid-write (here: the flush to disk
    fails), the sheet printed before under that name is still there, byte for byte, and no
    partial file is left beside it."""
    import errno
    import os

    from displacement_matcher import atomic

    path = tmp_path / "sheet.pdf"
    write_targets(path, "ring", [0, 1], 7.1, 600)
    before = path.read_bytes()

    def full_disk(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space left"):
        write_targets(path, "ring", list(range(40)), 7.1, 600, copies=20)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["sheet.pdf"]
