"""``armourcam compare`` end to end: render -> detect -> estimate -> match -> report."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from armourcam.cli import main
from armourcam.field import Field, make_field
from armourcam.render import render
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
