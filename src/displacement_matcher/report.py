"""Report files of a comparison: JSON, CSV per fiducial and per unit, overlay and plot PNGs.

The JSON has the keys of ``armourcam compare --json``: ``fiducials`` (label, codes, positions and
displacement per entry), ``units`` (id, translation, rotation, status), ``summary`` (damage counts
with their thresholds), plus ``rejected`` poses and the matching ``params``. The overlay draws the
displacement vectors on the after image the way the paper's Figure 8 does: green for same-code
pairs, red for cross-code pairs; vanished fiducials are marked with a yellow circle at their
baseline position, appeared ones with a blue one. Positions are camera frame, mm; pixels ``(u, v)``
with pixel centres at integer coordinates.

Every file is written atomically (a temporary file in the same directory, then ``os.replace``), so
a reader never sees half a report and a crash never leaves one behind.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from pose_estimator.camera import CameraModel

from .atomic import write_atomic
from .errors import MatcherError
from .types import DamageSummary, MatchResult, UnitMotion

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
) -> dict[str, Any]:
    """The report as a JSON-ready mapping (see the module docstring)."""
    fids = []
    for d in result.displacements:
        fids.append(
            {
                "label": d.label,
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
    """Per-fiducial CSV of a :func:`report_dict` mapping."""
    header = ["label", "baseline_index", "current_index", "code_before", "code_after"]
    header += [f"{k}_{a}_mm" for k in ("before", "after", "displacement") for a in "xyz"]
    header += ["distance_mm", "sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "cost"]
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
        rows.append(["" if v is None else v for v in row])
    return _csv_bytes(header, rows)


def units_csv(report: dict[str, Any]) -> bytes:
    """Per-unit CSV of a :func:`report_dict` mapping."""
    header = ["unit", "status", "displaced", "translation_x_mm", "translation_y_mm"]
    header += ["translation_z_mm", "distance_mm", "rotation_deg", "method", "overturned"]
    header += ["n_matched", "n_vanished", "n_appeared", "n_cross_code", "codes"]
    rows = []
    for u in report["units"]:
        tr = u["translation_mm"] or [None, None, None]
        row = [u["unit"], u["status"], u["displaced"], *tr, u["distance_mm"], u["rotation_deg"]]
        row += [u["method"], u["overturned"], u["n_matched"], u["n_vanished"], u["n_appeared"]]
        row += [u["n_cross_code"], " ".join(str(c) for c in u["codes"])]
        rows.append(["" if v is None else v for v in row])
    return _csv_bytes(header, rows)


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

    for d in result.displacements:
        a, b = px(d.before_mm), px(d.after_mm)
        if d.is_match and a is not None and b is not None:
            color = GREEN if d.label == "same_code" else RED
            cv2.circle(canvas, a, max(2, thickness + 1), color, -1, cv2.LINE_AA)
            if a != b:
                cv2.arrowedLine(canvas, a, b, color, thickness, cv2.LINE_AA, tipLength=0.2)
        elif d.label == "vanished" and a is not None:
            cv2.circle(canvas, a, radius, YELLOW, thickness, cv2.LINE_AA)
        elif d.label == "appeared" and b is not None:
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
    w, h = size
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    left, right, top, bottom = 70, 20, 40, 50
    pairs = [d for d in result.displacements if d.is_match]
    mags = np.array([d.distance_mm for d in pairs], dtype=np.float64)
    order = np.argsort(-mags, kind="stable")
    limit = float(mags.max()) if len(mags) else 1.0
    if summary is not None:
        limit = max(limit, summary.thresholds.displaced_mm)
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
    title = f"displacement of {len(pairs)} matched fiducials (mm), largest first"
    cv2.putText(img, title, (x0, 25), font, 0.55, black, 1, cv2.LINE_AA)
    cv2.putText(img, "fiducials", (x1 - 80, h - 15), font, 0.45, black, 1, cv2.LINE_AA)
    n = len(pairs)
    if n:
        bw = (x1 - x0) / n
        for rank, k in enumerate(order.tolist()):
            ya = round(y0 - (y0 - y1) * mags[k] / limit)
            xa = round(x0 + rank * bw)
            xb = max(xa, round(x0 + (rank + 1) * bw) - 1)
            color = GREEN if pairs[k].label == "same_code" else RED
            cv2.rectangle(img, (xa, ya), (xb, y0 - 1), color, -1)
    if summary is not None:
        t = summary.thresholds
        for val, name in ((t.displaced_mm, "displaced"), (t.moved_mm, "moved")):
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
    """Write ``report.json``, ``fiducials.csv``, ``units.csv``, ``plot.png`` and, with a camera,
    ``overlay.png`` into ``out_dir``, each atomically.

    Returns
    -------
    dict of str to Path
        ``{"json", "fiducials_csv", "units_csv", "plot", "overlay"}`` (``overlay`` only with a
        camera).
    """
    out = Path(out_dir)
    rep = report_dict(result, units, summary, unassigned=unassigned)
    if extra:
        rep.update(extra)
    paths = {
        "json": write_atomic(out / "report.json", (json.dumps(rep, indent=1) + "\n").encode()),
        "fiducials_csv": write_atomic(out / "fiducials.csv", fiducials_csv(rep)),
        "units_csv": write_atomic(out / "units.csv", units_csv(rep)),
        "plot": write_atomic(out / "plot.png", _png(magnitude_plot(result, summary))),
    }
    if camera is not None:
        paths["overlay"] = write_atomic(
            out / "overlay.png", _png(overlay_image(result, camera, after_image))
        )
    return paths
