"""Report files: atomic, readable, with the compare --json keys."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from matcher_synth import make_pose

from displacement_matcher import match
from displacement_matcher.damage import assess, thresholds
from displacement_matcher.report import report_dict, write_atomic, write_report
from displacement_matcher.units import unit_motions
from pose_estimator.camera import CameraModel


def _scene() -> tuple:
    base = [make_pose(1, [0, 0, 800]), make_pose(2, [30, 0, 800]), make_pose(4, [-60, 0, 800])]
    cur = [make_pose(1, [5, 1, 800]), make_pose(3, [33, 2, 801]), make_pose(9, [90, 0, 800])]
    r = match(base, cur, gate_mm=40.0, code_penalty_mm=10.0)
    units, unassigned = unit_motions(r, span_mm=35.0)
    units, summary = assess(units, thresholds(20.0), section_width_mm=500.0)
    return r, units, summary, unassigned


def test_report_files_are_written_and_readable(tmp_path: Path) -> None:
    """JSON, both CSVs, the overlay and the plot exist, parse, and agree with the result."""
    r, units, summary, _ = _scene()
    cam = CameraModel.ideal(640, 480, 600.0)
    after = np.full((480, 640), 90, dtype=np.uint8)
    paths = write_report(tmp_path, r, units, summary, camera=cam, after_image=after)
    assert set(paths) == {"json", "fiducials_csv", "units_csv", "plot", "overlay"}
    doc = json.loads(paths["json"].read_text())
    assert {"fiducials", "units", "summary"} <= set(doc)
    labels = [f["label"] for f in doc["fiducials"]]
    assert labels.count("same_code") == 1 and labels.count("cross_code") == 1
    f0 = doc["fiducials"][0]
    assert set(f0) >= {"label", "code_before", "code_after", "before_mm", "after_mm"}
    np.testing.assert_allclose(f0["displacement_mm"], [5, 1, 0], atol=1e-3)
    assert doc["summary"]["displaced_units"] == summary.displaced_units
    assert doc["summary"]["thresholds"]["displaced_mm"] == 20.0
    for u in doc["units"]:
        assert set(u) >= {"unit", "translation_mm", "rotation_deg", "displaced"}
    rows = list(csv.DictReader(paths["fiducials_csv"].read_text().splitlines()))
    assert len(rows) == len(r.displacements) and rows[0]["label"] == "same_code"
    assert float(rows[0]["displacement_x_mm"]) == pytest.approx(5.0, abs=1e-3)
    urows = list(csv.DictReader(paths["units_csv"].read_text().splitlines()))
    assert [row["unit"] for row in urows] == [u.unit for u in units]
    overlay = cv2.imread(str(paths["overlay"]))
    assert overlay.shape == (480, 640, 3)
    # Green (same-code) and red (cross-code) vectors were drawn (BGR).
    b, g, rr = overlay[..., 0].astype(int), overlay[..., 1].astype(int), overlay[..., 2].astype(int)
    assert np.any((g > 150) & (rr < 120) & (b < 120))
    assert np.any((rr > 150) & (g < 100) & (b < 100))
    plot = cv2.imread(str(paths["plot"]))
    assert plot is not None and plot.shape[2] == 3
    # No temporary files left behind.
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_write_atomic_replaces_and_cleans_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A failed write leaves the old file intact and no temporary file."""
    target = tmp_path / "report.json"
    write_atomic(target, b"old")

    def boom(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_atomic(target, b"new")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["report.json"]


def test_report_of_empty_and_rejected_inputs(tmp_path: Path) -> None:
    """Empty sets and NaN poses still give a complete, readable report."""
    from pose_estimator.types import FiducialPose

    nan = FiducialPose(5, np.full(3, np.nan), np.array([0, 0, -1.0]), np.eye(3))
    r = match([nan], [])
    paths = write_report(tmp_path, r)
    doc = json.loads(paths["json"].read_text())
    assert doc["fiducials"] == [] and doc["rejected"][0]["reason"].startswith("position_mm")
    assert doc["summary"]["displaced_units"] is None
    assert report_dict(match([], []))["params"]["gate_mm"] > 0


@pytest.mark.parametrize(
    "after", [np.full((40, 60), 2000, np.uint16), np.full((40, 60, 3), 0.5, np.float32)]
)
def test_overlay_shows_12_bit_and_float_frames(after: np.ndarray) -> None:
    """A 12-bit camera's frame in a 16-bit container, or a float frame, is shown stretched to
    its brightest pixel, not near black against the type's range."""
    from displacement_matcher.report import overlay_image

    canvas = overlay_image(match([], []), CameraModel.ideal(60, 40, 100.0), after)
    assert canvas.shape == (40, 60, 3) and canvas.dtype == np.uint8
    assert np.all(canvas == 255)
