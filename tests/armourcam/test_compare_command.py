"""``armourcam compare`` end to end: render -> detect -> estimate -> match -> report."""

from __future__ import annotations

import json
import os
import stat
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from armourcam.cli import main
from armourcam.field import Field, make_field
from armourcam.render import Target, render
from pose_estimator.camera import CameraModel

DIAMETER_MM = 10.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Field, Path]:
    """A 16-dolos field rendered before and after, with its camera and unit-map files."""
    d = tmp_path_factory.mktemp("compare")
    cam = CameraModel.ideal(1200, 800, 2400.0)
    f = make_field(
        16,
        seed=3,
        camera=cam,
        moved_fraction=0.25,
        overturned_fraction=0.07,
        diameter_mm=DIAMETER_MM,
    )
    for k, (name, state) in enumerate((("before", f.before), ("after", f.after))):
        rng = np.random.default_rng(10 + k)
        img = render(cam, state.targets("ring"), blur_sigma=0.5, noise=0.01, rng=rng)
        cv2.imwrite(str(d / f"{name}.png"), img.image)
    (d / "camera.yaml").write_text(yaml.safe_dump(cam.to_dict()))
    g = f.geometry
    tmpl = {
        "codes": list(g.codes),
        "positions_mm": {c: g.positions_mm[k].tolist() for k, c in enumerate(g.codes)},
        "normals": {c: g.normals[k].tolist() for k, c in enumerate(g.codes)},
    }
    (d / "units.yaml").write_text(yaml.safe_dump({"template": tmpl}))
    return f, d


@pytest.mark.parametrize("image_fit", [False, True])
def test_compare_json_and_files(
    scene: tuple[Field, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    image_fit: bool,
) -> None:
    """The JSON has the issue's keys; displaced units are the truly displaced ones (with the
    ellipse poses and with the image fit's)."""
    f, d = scene
    out = tmp_path / "report"
    args = [
        "compare", str(d / "before.png"), "--after", str(d / "after.png"),
        "--camera", str(d / "camera.yaml"), "--diameter-mm", str(DIAMETER_MM),
        "--out", str(out), "--units", str(d / "units.yaml"),
        "--dn-mm", f"{f.geometry.dn_mm}", "--section-width-mm", f"{f.section_width_mm}", "--json",
    ]  # fmt: skip
    if image_fit:
        args.append("--image-fit")
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {"fiducials", "units", "summary"} <= set(doc)
    for key in ("label", "code_before", "code_after", "before_mm", "after_mm", "displacement_mm"):
        assert key in doc["fiducials"][0]
    for key in ("unit", "translation_mm", "rotation_deg", "displaced"):
        assert key in doc["units"][0]
    s = doc["summary"]
    assert s["thresholds"]["displaced_mm"] == pytest.approx(f.geometry.dn_mm)
    # Truth: overturned units and units whose centre moved >= Dn.
    moved = np.linalg.norm(f.after.centres_mm - f.before.centres_mm, axis=1)
    truth = int(np.sum(f.overturned | (f.moved & (moved >= f.geometry.dn_mm))))
    assert s["displaced_units"] == truth
    assert s["n_od"] == pytest.approx(truth * f.geometry.dn_mm / f.section_width_mm, rel=1e-3)
    for name in ("report.json", "fiducials.csv", "units.csv", "overlay.png", "plot.png"):
        assert (out / name).is_file()
    assert cv2.imread(str(out / "overlay.png")).shape == (800, 1200, 3)


def test_compare_human_summary_and_bad_inputs(
    scene: tuple[Field, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --json a summary with thresholds; bad inputs exit 2 with a one-line error."""
    _, d = scene
    base = ["--camera", str(d / "camera.yaml"), "--out", str(tmp_path / "r")]
    assert main(["compare", str(d / "before.png"), "--after", str(d / "before.png"), *base]) == 0
    text = capsys.readouterr().out
    assert "displaced 0" in text and "thresholds: displaced >=" in text
    # Input files that cannot be used: each named with its problem, as `detect` does (exit 1);
    # nothing is compared without a usable image of each state.
    assert main(["compare", str(d / "nope.png"), "--after", str(d / "after.png"), *base]) == 1
    err = capsys.readouterr().err
    assert f"{d / 'nope.png'}: no such file" in err and "no usable BEFORE image" in err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((10, 10), np.uint8))
    assert main(["compare", str(small), "--after", str(d / "after.png"), *base]) == 1
    err = capsys.readouterr().err
    assert f"{small}: image is 10x10 but the calibration is for" in err
    # One unusable BEFORE image among good ones: the others are compared, the report written.
    out2 = tmp_path / "out2"
    args2 = [str(d / "before.png"), str(small), "--after", str(d / "after.png")]
    assert main(["compare", *args2, *base[:-2], "--out", str(out2)]) == 1
    assert f"{small}: image is 10x10" in capsys.readouterr().err
    rep = json.loads((out2 / "report.json").read_text())
    assert rep["inputs"]["before"] == [str(d / "before.png")]
    assert rep["inputs"]["unusable"] and str(small) in rep["inputs"]["unusable"][0]
    # Reports are ordinary files (readable as other outputs are), not the temporary's 0600.
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE((out2 / "units.csv").stat().st_mode) == 0o666 & ~mask
    bad_units = tmp_path / "u.yaml"
    bad_units.write_text("units: {A: {codes: [500]}}\n")
    args = ["compare", str(d / "before.png"), "--after", str(d / "after.png"), *base]
    assert main([*args, "--units", str(bad_units)]) == 2
    assert "unknown code 500" in capsys.readouterr().err


def test_a_comparison_that_measured_nothing_says_so_and_fails(
    scene: tuple[Field, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No fiducial found (the wrong design asked for, a blank frame) or none found again
    (another scene): an error naming why, exit 1, never a plain "displaced 0"."""
    _, d = scene
    base = ["--camera", str(d / "camera.yaml"), "--out", str(tmp_path / "r")]
    pair = [str(d / "before.png"), "--after", str(d / "after.png")]
    assert main(["compare", *pair, *base, "--design", "dot"]) == 1
    err = capsys.readouterr().err
    assert "no fiducial found in the 1 BEFORE image" in err
    assert "no fiducial found in the 1 AFTER image" in err
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((800, 1200), 200, np.uint8))
    assert main(["compare", str(d / "before.png"), "--after", str(blank), *base]) == 1
    err = capsys.readouterr().err
    assert "AFTER" in err and "BEFORE image" not in err
    # Fiducials on both sides, none paired (distinct codes of another scene): also nothing.
    from armourcam.commands.compare import _measured_nothing

    counts = {"same_code": 0, "cross_code": 0, "vanished": 39, "appeared": 12}
    (message,) = _measured_nothing([object()] * 39, [object()] * 12, counts, 1, 2)
    assert message.startswith("none of the 39 BEFORE fiducials was found again among the 12")


def test_fiducials_outside_the_unit_map_are_named(
    scene: tuple[Field, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A unit map that leaves codes out: the summary is not silent about the fiducials in no
    unit (they were only in the JSON, as indices)."""
    f, d = scene
    first, *rest = f.geometry.codes
    umap = tmp_path / "one.yaml"
    umap.write_text(yaml.safe_dump({"units": {"A": {"codes": [int(first)]}}}))
    args = ["compare", str(d / "before.png"), "--after", str(d / "before.png")]
    args += ["--camera", str(d / "camera.yaml"), "--out", str(tmp_path / "r"), "--units", str(umap)]
    assert main(args) == 0
    (line,) = [s for s in capsys.readouterr().err.splitlines() if "not in the unit map" in s]
    listed = line.split("(")[1].split(")")[0]
    assert line.endswith("they are in no unit") and listed
    assert {int(c) for c in listed.split(", ")} <= {int(c) for c in rest}


def _render(cam: CameraModel, targets: list[Target], path: Path, seed: int) -> None:
    img = render(cam, targets, blur_sigma=0.5, noise=0.01, rng=np.random.default_rng(seed))
    cv2.imwrite(str(path), img.image)


def test_before_images_from_a_moved_camera_are_refused_unless_allowed(
    scene: tuple[Field, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A second BEFORE image after the camera moved 3.7 mm (every fiducial shifted alike): an
    error naming it and how far it moved, nothing compared (exit 1, no report). Plain fusion
    would have doubled the fiducials (the shift is beyond its association gate). With
    --allow-camera-motion it is aligned onto the first, the warning is printed and carried in
    the report, and the damage is the truth. Two images from one place give no warning."""
    f, d = scene
    cam = CameraModel.ideal(1200, 800, 2400.0)
    shift = np.array([3.0, -2.0, 1.0])
    moved = [replace(t, position_mm=t.position_mm + shift) for t in f.before.targets("ring")]
    _render(cam, moved, tmp_path / "moved.png", 12)
    _render(cam, f.before.targets("ring"), tmp_path / "again.png", 13)
    before, moved_png = str(d / "before.png"), str(tmp_path / "moved.png")
    common = [
        "--after", str(d / "after.png"), "--camera", str(d / "camera.yaml"),
        "--diameter-mm", str(DIAMETER_MM), "--units", str(d / "units.yaml"),
        "--dn-mm", f"{f.geometry.dn_mm}", "--section-width-mm", f"{f.section_width_mm}",
    ]  # fmt: skip
    out = tmp_path / "refused"
    assert main(["compare", before, moved_png, *common, "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and not (out / "report.json").exists()
    lines = captured.err.splitlines()
    assert (
        lines[0].startswith(f"armourcam compare: error: BEFORE image {moved_png} is moved 3.7")
        and f"mm against {before}: all its fiducials shift alike" in lines[0]
    )
    assert "nothing compared" in lines[1] and "--allow-camera-motion" in lines[1]

    out = tmp_path / "allowed"
    args = ["compare", before, moved_png, *common, "--out", str(out), "--allow-camera-motion"]
    assert main([*args, "--json"]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert doc == json.loads((out / "report.json").read_text())
    moved_warning, aligned_warning = doc["warnings"]
    assert moved_warning.startswith(f"BEFORE image {moved_png} is moved 3.7")
    assert aligned_warning.startswith(f"BEFORE: aligned {moved_png} onto {before}")
    assert captured.err.splitlines() == [
        f"armourcam compare: warning: {moved_warning}",
        f"armourcam compare: warning: {aligned_warning}",
    ]
    first, second = doc["fusion"]["before"]
    assert (first["verdict"], second["verdict"], second["aligned"]) == ("agrees", "moved", True)
    np.testing.assert_allclose(second["shift_mm"], -shift, atol=0.1)
    assert doc["inputs"]["before_fiducials"] <= first["fiducials"] + 2
    moved_mm = np.linalg.norm(f.after.centres_mm - f.before.centres_mm, axis=1)
    truth = int(np.sum(f.overturned | (f.moved & (moved_mm >= f.geometry.dn_mm))))
    assert doc["summary"]["displaced_units"] == truth

    out = tmp_path / "still"
    assert main(["compare", before, str(tmp_path / "again.png"), *common, "--out", str(out)]) == 0
    assert capsys.readouterr().err == ""
    doc = json.loads((out / "report.json").read_text())
    assert doc["warnings"] == []
    assert [r["verdict"] for r in doc["fusion"]["before"]] == ["agrees", "agrees"]


def test_a_unit_map_with_codes_swapped_between_units_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every fiducial with its own code (``4 * unit + slot``) and an explicit unit map: a code
    swapped between two distant units gives a warning for each, naming the unit and the code
    and pointing at units.yaml, on stderr and in the report's ``warnings``; the right map gives
    none."""
    cam = CameraModel.ideal(1200, 800, 2400.0)
    f = make_field(16, seed=3, camera=cam, moved_fraction=0.25, diameter_mm=DIAMETER_MM)
    for k, state in enumerate((f.before, f.after)):
        ids = state.visible_ids
        targets = [
            replace(t, code=4 * int(state.unit[i]) + f.geometry.codes.index(int(state.code[i])))
            for t, i in zip(state.targets("ring"), ids, strict=True)
        ]
        _render(cam, targets, tmp_path / f"{k}.png", 20 + k)
    (tmp_path / "camera.yaml").write_text(yaml.safe_dump(cam.to_dict()))
    units = {f"D{u:02d}": [4 * u + k for k in range(4)] for u in range(16)}
    # Two units far apart, each with three fiducials seen before: swap a seen code of each.
    seen = {
        u: [4 * u + f.geometry.codes.index(int(f.before.code[i]))
            for i in f.before.observable_ids if f.before.unit[i] == u]
        for u in range(16)
    }  # fmt: skip
    full = [u for u in range(16) if len(seen[u]) >= 3]
    a, b = max(
        ((a, b) for a in full for b in full if a < b),
        key=lambda ab: float(
            np.linalg.norm(f.before.centres_mm[ab[0]] - f.before.centres_mm[ab[1]])
        ),
    )
    ca, cb = seen[a][0], seen[b][0]
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump({"units": {k: {"codes": v} for k, v in units.items()}}))
    units[f"D{a:02d}"][units[f"D{a:02d}"].index(ca)] = cb
    units[f"D{b:02d}"][units[f"D{b:02d}"].index(cb)] = ca
    swapped = tmp_path / "swapped.yaml"
    swapped.write_text(yaml.safe_dump({"units": {k: {"codes": v} for k, v in units.items()}}))
    args = ["compare", str(tmp_path / "0.png"), "--after", str(tmp_path / "1.png")]
    args += ["--camera", str(tmp_path / "camera.yaml"), "--diameter-mm", str(DIAMETER_MM)]
    args += ["--dn-mm", f"{f.geometry.dn_mm}"]
    assert main([*args, "--units", str(good), "--out", str(tmp_path / "g")]) == 0
    assert "units.yaml" not in capsys.readouterr().err
    assert json.loads((tmp_path / "g" / "report.json").read_text())["warnings"] == []
    assert main([*args, "--units", str(swapped), "--out", str(tmp_path / "s")]) == 0
    err = [s for s in capsys.readouterr().err.splitlines() if s.endswith("check units.yaml")]
    assert len(err) == 2
    assert err[0].startswith(f"armourcam compare: warning: unit D{a:02d}: code {cb} is ")
    assert err[1].startswith(f"armourcam compare: warning: unit D{b:02d}: code {ca} is ")
    assert f"is it on unit D{b:02d}" in err[0] and f"is it on unit D{a:02d}" in err[1]
    doc = json.loads((tmp_path / "s" / "report.json").read_text())
    assert doc["warnings"] == [s.removeprefix("armourcam compare: warning: ") for s in err]
