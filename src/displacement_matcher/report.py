"""Report files of a comparison: JSON, CSV per fiducial and per unit, overlay and plot PNGs.

The JSON has the keys of ``armourcam compare --json``: ``fiducials`` (label, unit, codes,
positions and displacement per entry), ``units`` (id, translation, rotation, status, reference
point), ``summary`` (damage counts with their thresholds), plus ``rejected`` poses, the
matching ``params`` and, when no unit map was given, the ``template`` learned from the baseline
(in the unit map's layout). The overlay draws the displacement vectors on the after image the way
the paper's Figure 8 does: green for same-code pairs, red for cross-code pairs; vanished fiducials
are marked with a yellow circle at their baseline position, appeared ones with a blue one.
Positions are camera frame, mm; pixels ``(u, v)`` with pixel centres at integer coordinates.

The CSVs are plain rectangular tables (one header row, no comment lines), so a spreadsheet,
``csv.DictReader`` or ``pandas.read_csv`` opens them without options, and rows of several runs
can be pasted or concatenated into one table and still say what they were measured against.
Columns are only ever appended, so scripts that index them by position keep working:

- ``fiducials.csv``, one row per fiducial: ``label, baseline_index, current_index, code_before,
  code_after, before_{x,y,z}_mm, after_{x,y,z}_mm, displacement_{x,y,z}_mm, distance_mm,
  sigma_{x,y,z}_mm, cost, unit``. ``unit`` is the unit the fiducial belonged to in the baseline;
  for an appeared fiducial the unit it was attached to, empty when none (or for a baseline
  fiducial whose code is in no unit of the unit map).
- ``units.csv``, one row per unit: ``unit, status, displaced, translation_{x,y,z}_mm,
  distance_mm, rotation_deg, method, overturned, n_matched, n_vanished, n_appeared,
  n_cross_code, codes, reference_before_{x,y,z}_mm`` (the point whose displacement
  ``translation`` is: the unit's origin when its template locates it, else the centroid of its
  baseline fiducials), then the thresholds the status was decided with, repeated on every row:
  ``dn_mm, displaced_threshold_mm, moved_threshold_mm, rotated_threshold_deg,
  overturn_threshold_deg`` (empty when the report has no damage summary). Repeating them costs a
  few bytes a row; as ``#`` comment lines above the header they would break the header row of
  every reader above, and be lost the moment rows are sorted, filtered or pasted elsewhere.

Every file is written atomically (a temporary file in the same directory, then ``os.replace``),
and the files of one report as a set (all on disk under temporary names before any replaces its
target), so a reader never sees half a report or one that mixes two comparisons, and a crash or a
full disk never leaves one behind. :func:`write_report_files`
writes the whole set from a report mapping; ``armourcam compare``, ``armourcam demo`` and
``armourcam analyze`` all write through it, so their report directories hold the same files.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from pose_estimator.camera import CameraModel

from .atomic import write_atomic_set
from .errors import MatcherError
from .types import MATCH_LABELS, DamageSummary, MatchResult, UnitMotion
from .units import UnitSpec

GREEN = (60, 200, 60)  # BGR
RED = (40, 40, 230)
YELLOW = (0, 220, 240)
BLUE = (230, 120, 30)


def _vec(x: NDArray[np.float64] | None) -> list[float] | None:
    if x is None:
        return None
    return [round(float(v), 4) if math.isfinite(float(v)) else None for v in x]  # type: ignore[misc]


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 4)


def report_dict(
    result: MatchResult,
    units: Sequence[UnitMotion] = (),
    summary: DamageSummary | None = None,
    *,
    unassigned: Sequence[int] = (),
    learned_template: UnitSpec | None = None,
) -> dict[str, Any]:
    """The report as a JSON-ready mapping (see the module docstring); ``learned_template``, the
    unit template learned from the baseline without a unit map, is reported under
    ``template``."""
    unit_of = _unit_of_fiducial(units)
    fids = []
    for d in result.displacements:
        fids.append(
            {
                "label": d.label,
                "unit": unit_of(d.baseline_index, d.current_index),
                "baseline_index": d.baseline_index,
                "current_index": d.current_index,
                "code_before": d.code_before,
                "code_after": d.code_after,
                "before_mm": _vec(d.before_mm),
                "after_mm": _vec(d.after_mm),
                "displacement_mm": _vec(d.displacement_mm),
                "distance_mm": _num(d.distance_mm),
                "sigma_mm": _vec(d.sigma_mm),
                "cost": _num(d.cost),
            }
        )
    unit_rows = []
    for u in units:
        unit_rows.append(
            {
                "unit": u.unit,
                "status": u.status,
                "displaced": u.status in _displaced_states(summary),
                "translation_mm": _vec(u.translation_mm),
                "distance_mm": _num(u.distance_mm),
                "rotation_deg": _num(u.rotation_deg),
                "method": u.method,
                "overturned": u.overturned,
                "n_matched": u.n_matched,
                "n_vanished": u.n_vanished,
                "n_appeared": u.n_appeared,
                "n_cross_code": u.n_cross_code,
                "codes": list(u.codes),
                "reference_mm": _vec(u.reference_before_mm),
                "residual_mm": _num(u.residual_mm),
            }
        )
    out: dict[str, Any] = {"fiducials": fids, "units": unit_rows}
    counts = result.counts()
    summ: dict[str, Any] = {f"{k}_fiducials": v for k, v in counts.items()}
    if summary is not None:
        t = summary.thresholds
        summ.update(
            {
                "units": summary.n_units,
                "displaced_units": summary.displaced_units,
                "moved_units": summary.moved_units,
                "overturned_units": summary.overturned_units,
                "lost_units": summary.lost_units,
                "still_units": summary.still_units,
                "percent_displaced": round(summary.percent_displaced, 3),
                "n_od": _num(summary.n_od),
                "section_width_mm": summary.section_width_mm,
                "displaced_ids": list(summary.displaced_ids),
                "thresholds": {
                    "dn_mm": t.dn_mm,
                    "displaced_mm": t.displaced_mm,
                    "displaced_dn": t.displaced_mm / t.dn_mm,
                    "moved_mm": t.moved_mm,
                    "rotated_deg": t.rotated_deg,
                    "overturn_deg": t.overturn_deg,
                    "overturned_count_as_displaced": t.overturned_displaced,
                    "lost_count_as_displaced": t.lost_displaced,
                    "lateral_confirm_mm": t.lateral_confirm_mm,
                },
                "text": summary.describe(),
            }
        )
    else:
        summ["displaced_units"] = None
    summ["unassigned_fiducials"] = list(unassigned)
    out["summary"] = summ
    if learned_template is not None:
        out["template"] = template_dict(learned_template)
    out["rejected"] = [
        {"side": r.side, "index": r.index, "code": r.code, "reason": r.reason}
        for r in result.rejected
    ]
    p = result.params
    out["params"] = {
        "gate_mm": p.gate_mm,
        "code_penalty_mm": p.code_penalty_mm if math.isfinite(p.code_penalty_mm) else "inf",
        "motion_scale_mm": p.motion_scale_mm,
        "normal_weight_mm": p.normal_weight_mm,
        "total_cost_mm": _num(result.total_cost),
    }
    return out


def template_dict(template: UnitSpec) -> dict[str, Any]:
    """A learned unit template as a JSON-ready mapping, in the unit map's YAML layout
    (:mod:`.units`): a lab can keep it as the ``template`` of a unit map."""
    return {
        "source": "learned from the baseline",
        "codes": [int(c) for c in template.codes],
        "positions_mm": {str(c): _vec(p) for c, p in sorted(template.positions_mm.items())},
        "normals": {str(c): _vec(n) for c, n in sorted(template.normals.items())},
        "hidden": sorted(int(c) for c in template.hidden),
    }


def _unit_of_fiducial(
    units: Sequence[UnitMotion],
) -> Callable[[int | None, int | None], str | None]:
    """``unit_of(baseline_index, current_index)``: the id of the unit a fiducial belongs to.

    A fiducial seen in the baseline belongs to the unit that holds it there, even when it was
    paired with another unit's fiducial (a cross-code pair): its unit is what moved. Only an
    appeared fiducial (no baseline index) is looked up on the current side, where the units list
    the fiducials they were attached to. None when no unit holds it.
    """
    base: dict[int, str] = {}
    cur: dict[int, str] = {}
    for u in units:
        for i in u.baseline_indices:
            base.setdefault(int(i), u.unit)
        for j in u.current_indices:
            cur.setdefault(int(j), u.unit)

    def unit_of(baseline_index: int | None, current_index: int | None) -> str | None:
        if baseline_index is not None:
            return base.get(int(baseline_index))
        if current_index is not None:
            return cur.get(int(current_index))
        return None

    return unit_of


def _displaced_states(summary: DamageSummary | None) -> set[str]:
    states = {"displaced"}
    if summary is None or summary.thresholds.overturned_displaced:
        states.add("overturned")
    if summary is None or summary.thresholds.lost_displaced:
        states.add("lost")
    return states


def _csv_bytes(header: list[str], rows: list[list[Any]]) -> bytes:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue().encode()


def fiducials_csv(report: dict[str, Any]) -> bytes:
    """Per-fiducial CSV of a :func:`report_dict` mapping (columns: the module docstring)."""
    header = ["label", "baseline_index", "current_index", "code_before", "code_after"]
    header += [f"{k}_{a}_mm" for k in ("before", "after", "displacement") for a in "xyz"]
    header += ["distance_mm", "sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "cost", "unit"]
    rows = []
    for f in report["fiducials"]:
        row = [
            f["label"],
            f["baseline_index"],
            f["current_index"],
            f["code_before"],
            f["code_after"],
        ]
        for k in ("before_mm", "after_mm", "displacement_mm"):
            row += f[k] if f[k] is not None else ["", "", ""]
        row += [f["distance_mm"]] + (f["sigma_mm"] or ["", "", ""]) + [f["cost"]]
        # Reports written before the unit was recorded per fiducial have no "unit" key.
        row.append(f.get("unit"))
        rows.append(["" if v is None else v for v in row])
    return _csv_bytes(header, rows)


#: ``units.csv`` threshold columns and their keys in ``summary["thresholds"]``.
_THRESHOLD_COLUMNS = (
    ("dn_mm", "dn_mm"),
    ("displaced_threshold_mm", "displaced_mm"),
    ("moved_threshold_mm", "moved_mm"),
    ("rotated_threshold_deg", "rotated_deg"),
    ("overturn_threshold_deg", "overturn_deg"),
)


def _thresholds(report: dict[str, Any]) -> dict[str, Any]:
    """The thresholds of a :func:`report_dict` mapping's summary (empty for a failed run's
    report, whose summary is empty)."""
    return (report.get("summary") or {}).get("thresholds") or {}


def units_csv(report: dict[str, Any]) -> bytes:
    """Per-unit CSV of a :func:`report_dict` mapping (columns: the module docstring)."""
    header = ["unit", "status", "displaced", "translation_x_mm", "translation_y_mm"]
    header += ["translation_z_mm", "distance_mm", "rotation_deg", "method", "overturned"]
    header += ["n_matched", "n_vanished", "n_appeared", "n_cross_code", "codes"]
    header += ["reference_before_x_mm", "reference_before_y_mm", "reference_before_z_mm"]
    header += [name for name, _ in _THRESHOLD_COLUMNS]
    limits = _thresholds(report)  # a failed run's threshold cells stay empty
    thresholds = [limits.get(key) for _, key in _THRESHOLD_COLUMNS]
    rows = []
    for u in report["units"]:
        tr = u["translation_mm"] or [None, None, None]
        row = [u["unit"], u["status"], u["displaced"], *tr, u["distance_mm"], u["rotation_deg"]]
        row += [u["method"], u["overturned"], u["n_matched"], u["n_vanished"], u["n_appeared"]]
        row += [u["n_cross_code"], " ".join(str(c) for c in u["codes"])]
        row += u.get("reference_mm") or [None, None, None]
        row += thresholds
        rows.append(["" if v is None else v for v in row])
    return _csv_bytes(header, rows)


#: One fiducial as the overlay draws it: label, before and after positions (camera frame, mm).
_Vector = tuple[str, NDArray[np.float64] | None, NDArray[np.float64] | None]


def overlay_image(
    result: MatchResult,
    camera: CameraModel,
    after_image: NDArray[np.generic] | None = None,
    *,
    thickness: int = 2,
) -> NDArray[np.uint8]:
    """The after image (grey or BGR; blank when None) with the displacement vectors drawn.

    Before and after 3-D positions are projected through ``camera``; an arrow goes from the
    before point to the after point, green for a same-code pair and red for a cross-code pair
    (paper, Figure 8). Vanished fiducials: yellow circle at the before point; appeared: blue.
    """
    vectors = [(d.label, d.before_mm, d.after_mm) for d in result.displacements]
    return _draw_overlay(vectors, camera, after_image, thickness)


def overlay_from_report(
    report: dict[str, Any],
    camera: CameraModel,
    after_image: NDArray[np.generic] | None = None,
    *,
    thickness: int = 2,
) -> NDArray[np.uint8]:
    """:func:`overlay_image` of a :func:`report_dict` mapping (a stored or published report).

    The positions are the report's, rounded to 0.1 um: the drawing is the result's to the pixel.
    """
    vectors = [
        (str(f["label"]), _position(f.get("before_mm")), _position(f.get("after_mm")))
        for f in report["fiducials"]
    ]
    return _draw_overlay(vectors, camera, after_image, thickness)


def _position(v: Sequence[float | None] | None) -> NDArray[np.float64] | None:
    # A report writes a non-finite coordinate as null; NaN keeps the point off the drawing.
    return None if v is None else np.array([np.nan if c is None else c for c in v], np.float64)


def _draw_overlay(
    vectors: Sequence[_Vector],
    camera: CameraModel,
    after_image: NDArray[np.generic] | None,
    thickness: int,
) -> NDArray[np.uint8]:
    if after_image is None:
        canvas = np.full((camera.height, camera.width, 3), 255, dtype=np.uint8)
    else:
        img = np.asarray(after_image)
        if img.dtype != np.uint8:
            # Stretched to its brightest pixel, for display: a 12-bit camera's frames in 16-bit
            # containers (or a [0, 1] float image) would be near black against the type's range.
            top = float(np.nanmax(img)) if img.size else 0.0
            scale = 255.0 / top if top > 0 else 1.0
            img = np.clip(np.nan_to_num(img.astype(np.float64)) * scale, 0, 255).astype(np.uint8)
        if img.ndim == 2:
            canvas = np.asarray(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
        elif img.shape[2] == 4:
            canvas = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGRA2BGR), dtype=np.uint8)
        else:
            canvas = np.array(img, dtype=np.uint8)
    radius = max(4, round(min(canvas.shape[:2]) / 150))

    def px(p: NDArray[np.float64] | None) -> tuple[int, int] | None:
        if p is None or not np.all(np.isfinite(p)) or p[2] <= 0:
            return None
        uv = camera.project(p.reshape(1, 3))[0]
        if not np.all(np.isfinite(uv)):
            return None
        return round(uv[0]), round(uv[1])

    for label, before, after in vectors:
        a, b = px(before), px(after)
        if label in MATCH_LABELS and a is not None and b is not None:
            color = GREEN if label == "same_code" else RED
            cv2.circle(canvas, a, max(2, thickness + 1), color, -1, cv2.LINE_AA)
            if a != b:
                cv2.arrowedLine(canvas, a, b, color, thickness, cv2.LINE_AA, tipLength=0.2)
        elif label == "vanished" and a is not None:
            cv2.circle(canvas, a, radius, YELLOW, thickness, cv2.LINE_AA)
        elif label == "appeared" and b is not None:
            cv2.circle(canvas, b, radius, BLUE, thickness, cv2.LINE_AA)
    return canvas


def magnitude_plot(
    result: MatchResult,
    summary: DamageSummary | None = None,
    *,
    size: tuple[int, int] = (960, 540),
) -> NDArray[np.uint8]:
    """Plot (drawn with OpenCV) of every matched fiducial's displacement, largest first.

    One bar per pair (green same-code, red cross-code) against a millimetre axis, with the
    displacement and movement thresholds as dashed lines when ``summary`` is given.
    """
    pairs = [d for d in result.displacements if d.is_match]
    mags = [np.nan if d.distance_mm is None else d.distance_mm for d in pairs]
    limits = None
    if summary is not None:
        limits = (summary.thresholds.displaced_mm, summary.thresholds.moved_mm)
    return _draw_magnitudes(mags, [d.label == "same_code" for d in pairs], limits, size)


def magnitude_plot_from_report(
    report: dict[str, Any], *, size: tuple[int, int] = (960, 540)
) -> NDArray[np.uint8]:
    """:func:`magnitude_plot` of a :func:`report_dict` mapping (thresholds from its summary)."""
    pairs = [f for f in report["fiducials"] if f["label"] in MATCH_LABELS]
    mags = [np.nan if f.get("distance_mm") is None else f["distance_mm"] for f in pairs]
    t = _thresholds(report)
    limits = (float(t["displaced_mm"]), float(t["moved_mm"])) if t else None
    return _draw_magnitudes(mags, [f["label"] == "same_code" for f in pairs], limits, size)


def _draw_magnitudes(
    magnitudes: Sequence[float],
    same_code: Sequence[bool],
    limits: tuple[float, float] | None,
    size: tuple[int, int],
) -> NDArray[np.uint8]:
    """Bars of ``magnitudes`` (mm), largest first; ``limits``: (displaced, moved) thresholds."""
    w, h = size
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    left, right, top, bottom = 70, 20, 40, 50
    mags = np.asarray(magnitudes, dtype=np.float64).reshape(-1)
    shown = mags[np.isfinite(mags)]
    order = np.argsort(-mags, kind="stable")
    limit = float(shown.max()) if len(shown) else 1.0
    if limits is not None:
        limit = max(limit, limits[0])
    limit = max(limit * 1.1, 1e-3)
    x0, x1, y0, y1 = left, w - right, h - bottom, top
    black = (0, 0, 0)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.line(img, (x0, y0), (x1, y0), black, 1)
    cv2.line(img, (x0, y0), (x0, y1), black, 1)
    step = _nice_step(limit)
    v = 0.0
    while v <= limit + 1e-9:
        y = round(y0 - (y0 - y1) * v / limit)
        cv2.line(img, (x0 - 5, y), (x0, y), black, 1)
        cv2.putText(img, f"{v:g}", (5, y + 5), font, 0.45, black, 1, cv2.LINE_AA)
        v += step
    n = len(mags)
    title = f"displacement of {n} matched fiducials (mm), largest first"
    cv2.putText(img, title, (x0, 25), font, 0.55, black, 1, cv2.LINE_AA)
    cv2.putText(img, "fiducials", (x1 - 80, h - 15), font, 0.45, black, 1, cv2.LINE_AA)
    if n:
        bw = (x1 - x0) / n
        for rank, k in enumerate(order.tolist()):
            if not math.isfinite(mags[k]):
                continue  # no length to draw (sorted last, so the ranks of the others hold)
            ya = round(y0 - (y0 - y1) * mags[k] / limit)
            xa = round(x0 + rank * bw)
            xb = max(xa, round(x0 + (rank + 1) * bw) - 1)
            color = GREEN if same_code[k] else RED
            cv2.rectangle(img, (xa, ya), (xb, y0 - 1), color, -1)
    if limits is not None:
        for val, name in ((limits[0], "displaced"), (limits[1], "moved")):
            y = round(y0 - (y0 - y1) * val / limit)
            for xs in range(x0, x1, 12):
                cv2.line(img, (xs, y), (min(xs + 6, x1), y), (90, 90, 90), 1)
            cv2.putText(img, f"{name} {val:.1f} mm", (x1 - 170, y - 4), font, 0.45, (60, 60, 60), 1)
    return img


def _nice_step(limit: float) -> float:
    raw = limit / 6.0
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if raw <= m * mag:
            return m * mag
    return 10.0 * mag


def _png(img: NDArray[np.uint8]) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise MatcherError("PNG encoding failed")
    return bytes(buf.tobytes())


def write_report(
    out_dir: str | Path,
    result: MatchResult,
    units: Sequence[UnitMotion] = (),
    summary: DamageSummary | None = None,
    *,
    camera: CameraModel | None = None,
    after_image: NDArray[np.generic] | None = None,
    unassigned: Sequence[int] = (),
    extra: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """:func:`write_report_files` of the :func:`report_dict` of a comparison (plus ``extra``).

    Returns
    -------
    dict of str to Path
        ``{"json", "fiducials_csv", "units_csv", "plot", "overlay"}`` (``overlay`` only with a
        camera).
    """
    rep = report_dict(result, units, summary, unassigned=unassigned)
    if extra:
        rep.update(extra)
    return write_report_files(out_dir, rep, camera=camera, after_image=after_image)


def write_report_files(
    out_dir: str | Path,
    report: dict[str, Any],
    *,
    camera: CameraModel | None = None,
    after_image: NDArray[np.generic] | None = None,
) -> dict[str, Path]:
    """Write ``report.json``, ``fiducials.csv``, ``units.csv``, ``plot.png`` and, with a camera,
    ``overlay.png`` of a :func:`report_dict` mapping into ``out_dir``, as one atomic set
    (:func:`.atomic.write_atomic_set`).

    The one writer of a report directory (``compare --out``, each run of ``demo`` and
    ``analyze``): files and figures are drawn from the mapping alone, so a report read back from
    disk or from the ``/armourcam/report`` topic gives the same files as the comparison did.

    Parameters
    ----------
    out_dir : str or Path
        Created when missing.
    report : dict
        A :func:`report_dict` mapping, possibly with more keys (all go to ``report.json``; it
        must be JSON-ready).
    camera : CameraModel, optional
        Projects the overlay; without one no overlay is written.
    after_image : ndarray, optional
        The after image under the overlay (grey, BGR or BGRA; blank when None).

    Returns
    -------
    dict of str to Path
        ``{"json", "fiducials_csv", "units_csv", "plot", "overlay"}`` (``overlay`` only with a
        camera).
    """
    out = Path(out_dir)
    # Everything is drawn first, then written as one set: a failure (a figure, a full disk)
    # leaves the directory's earlier report whole, never half old and half new.
    files = {
        "json": (out / "report.json", (json.dumps(report, indent=1) + "\n").encode()),
        "fiducials_csv": (out / "fiducials.csv", fiducials_csv(report)),
        "units_csv": (out / "units.csv", units_csv(report)),
        "plot": (out / "plot.png", _png(magnitude_plot_from_report(report))),
    }
    if camera is not None:
        files["overlay"] = (
            out / "overlay.png",
            _png(overlay_from_report(report, camera, after_image)),
        )
    write_atomic_set(dict(files.values()))
    return {name: path for name, (path, _) in files.items()}
