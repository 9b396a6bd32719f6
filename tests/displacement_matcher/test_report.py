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
from displacement_matcher.atomic import write_atomic
from displacement_matcher.damage import assess, thresholds
from displacement_matcher.report import (
    fiducials_csv,
    report_dict,
    units_csv,
    write_report,
)
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


def test_a_report_that_fails_half_written_leaves_the_earlier_one_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills while the fourth of a report's five files goes to disk: the directory
    still holds the earlier report, every file of it (not a new report.json beside an old
    overlay), and no temporary file."""
    r, units, summary, _ = _scene()
    cam = CameraModel.ideal(640, 480, 600.0)
    write_report(tmp_path, r, units, summary, camera=cam, after_image=None)
    before = {p: p.read_bytes() for p in tmp_path.iterdir()}
    assert len(before) == 5
    flushed = []

    def fills_up(fd: int) -> None:
        flushed.append(fd)
        if len(flushed) == 4:
            raise OSError("No space left on device")

    monkeypatch.setattr(os, "fsync", fills_up)
    r2, units2, summary2, _ = _scene()
    units2, summary2 = assess(units2, thresholds(2.0), section_width_mm=100.0)
    with pytest.raises(OSError, match="No space left"):
        write_report(tmp_path, r2, units2, summary2, camera=cam, after_image=None)
    assert {p: p.read_bytes() for p in tmp_path.iterdir()} == before


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


def _rows(data: bytes) -> list[dict[str, str]]:
    return list(csv.DictReader(data.decode().splitlines()))


def test_fiducials_csv_names_the_unit_of_every_fiducial() -> None:
    """Each fiducial row names its unit: the baseline side's (also for a cross-code pair and a
    vanished fiducial), the attached unit for an appeared one, empty when no unit took it."""
    base = [make_pose(1, [0, 0, 800]), make_pose(2, [30, 0, 800]), make_pose(4, [-60, 0, 800])]
    # Code 9 appears 17 mm from the first unit's fiducials (within its span): attached to it;
    # code 7 appears far from every unit: attached to none.
    cur = [
        make_pose(1, [5, 1, 800]),
        make_pose(3, [33, 2, 801]),
        make_pose(9, [50, 0, 800]),
        make_pose(7, [300, 0, 800]),
    ]
    r = match(base, cur, gate_mm=40.0, code_penalty_mm=10.0)
    units, _ = unit_motions(r, span_mm=35.0)
    units, summary = assess(units, thresholds(20.0))
    (first,) = [u.unit for u in units if 0 in u.baseline_indices]
    (second,) = [u.unit for u in units if 2 in u.baseline_indices]
    assert first != second and 2 in next(u for u in units if u.unit == first).current_indices
    rep = report_dict(r, units, summary)
    rows = _rows(fiducials_csv(rep))
    assert list(rows[0])[-1] == "unit"  # appended: earlier columns keep their positions
    got = {(row["label"], row["code_before"] or row["code_after"]): row["unit"] for row in rows}
    assert got == {
        ("same_code", "1"): first,
        ("cross_code", "2"): first,
        ("vanished", "4"): second,
        ("appeared", "9"): first,
        ("appeared", "7"): "",
    }
    assert [f["unit"] for f in rep["fiducials"]] == [row["unit"] or None for row in rows]


def test_units_csv_has_reference_point_and_thresholds() -> None:
    """units.csv keeps its columns in order and appends the reference point and, on every row,
    Dn and the thresholds the statuses were decided with (empty without a damage summary)."""
    r, units, summary, _ = _scene()
    rep = report_dict(r, units, summary)
    data = units_csv(rep)
    assert not data.startswith(b"#")  # a header row a spreadsheet and DictReader take as such
    rows = _rows(data)
    old = ["unit", "status", "displaced", "translation_x_mm", "translation_y_mm"]
    old += ["translation_z_mm", "distance_mm", "rotation_deg", "method", "overturned"]
    old += ["n_matched", "n_vanished", "n_appeared", "n_cross_code", "codes"]
    new = ["reference_before_x_mm", "reference_before_y_mm", "reference_before_z_mm", "dn_mm"]
    new += ["displaced_threshold_mm", "moved_threshold_mm", "rotated_threshold_deg"]
    new += ["overturn_threshold_deg"]
    assert list(rows[0]) == old + new
    t = summary.thresholds
    for row, u in zip(rows, units, strict=True):
        ref = [float(row[f"reference_before_{a}_mm"]) for a in "xyz"]
        np.testing.assert_allclose(ref, u.reference_before_mm, atol=1e-3)
        assert float(row["dn_mm"]) == t.dn_mm == 20.0
        assert float(row["displaced_threshold_mm"]) == t.displaced_mm
        assert float(row["moved_threshold_mm"]) == t.moved_mm
        assert float(row["rotated_threshold_deg"]) == t.rotated_deg
        assert float(row["overturn_threshold_deg"]) == t.overturn_deg
    # A report without a damage summary (a failed run's) leaves the threshold cells empty.
    (bare,) = _rows(units_csv({**rep, "units": rep["units"][:1], "summary": {}}))
    assert [bare[k] for k in new[3:]] == [""] * 5 and bare["reference_before_z_mm"] != ""


def test_report_files_from_a_stored_report_match_the_comparisons(tmp_path: Path) -> None:
    """The one writer works from the report mapping alone: a report read back from its JSON
    gives the same CSVs, plot and overlay as the comparison wrote."""
    from displacement_matcher.report import write_report_files

    r, units, summary, _ = _scene()
    cam = CameraModel.ideal(640, 480, 600.0)
    after = np.full((480, 640), 90, dtype=np.uint8)
    first = write_report(tmp_path / "a", r, units, summary, camera=cam, after_image=after)
    stored = json.loads(first["json"].read_text())
    again = write_report_files(tmp_path / "b", stored, camera=cam, after_image=after)
    assert set(again) == set(first)
    for key, path in first.items():
        assert again[key].name == path.name
        assert again[key].read_bytes() == path.read_bytes(), key
    # Drawn from the report, the figures are the comparison's own to the pixel.
    from displacement_matcher.report import magnitude_plot, overlay_image

    overlay = cv2.imread(str(again["overlay"]))
    np.testing.assert_array_equal(overlay, overlay_image(r, cam, after))
    np.testing.assert_array_equal(cv2.imread(str(again["plot"])), magnitude_plot(r, summary))
    assert write_report_files(tmp_path / "c", stored).keys() == first.keys() - {"overlay"}


def test_a_report_directory_that_is_a_file_is_named(tmp_path: Path) -> None:
    """``--out`` naming a file: the error says it is a file, not only "File exists"."""
    r, units, summary, _ = _scene()
    (tmp_path / "notes.txt").write_text("kept\n")
    with pytest.raises(NotADirectoryError, match=r"notes\.txt is a file, not a directory"):
        write_report(tmp_path / "notes.txt" / "run1", r, units, summary)
    assert (tmp_path / "notes.txt").read_text() == "kept\n"


def test_a_learned_template_is_reported_as_a_unit_map_template() -> None:
    """Without a unit map the report gives the learned template under ``template``, in the unit
    map's layout: read back as a map's template (through JSON, as a lab would keep it) it is
    the same template, and a report with a map given has no ``template``."""
    from armourcam.field import make_field
    from displacement_matcher.refine import match_units
    from displacement_matcher.units import parse_unit_map

    field = make_field(300, seed=5)
    rng = np.random.default_rng(2)
    before, after = field.before.poses(rng), field.after.poses(rng)
    an = match_units(before, after, gate_mm=50.0, refine_passes=0)
    learned = an.learned_template
    assert learned is not None and learned.hidden
    rep = json.loads(json.dumps(report_dict(an.result, an.units, learned_template=learned)))
    doc = {k: rep["template"][k] for k in ("codes", "positions_mm", "normals", "hidden")}
    back = parse_unit_map({"template": doc}).template
    assert back is not None
    assert back.codes == learned.codes and back.hidden == learned.hidden
    for c, p in learned.positions_mm.items():
        np.testing.assert_allclose(back.positions_mm[c], p, atol=1e-4)
    for c, n in learned.normals.items():
        np.testing.assert_allclose(back.normals[c], n, atol=1e-4)
    assert "template" not in report_dict(an.result, an.units)
