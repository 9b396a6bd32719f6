"""Offline analysis of bags (no DDS) and the session bags it is checked on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from armourcam import bagio, sessionbag
from armourcam.analyze import AnalysisResult, AnalyzeError, analyze_bag
from displacement_matcher.session import SessionConfig

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "session_small"
FIXTURE = REPO.parent / "shared" / "fixtures" / "real_camera_aruco_ros1.bag"


def test_session_bag_layout_and_truth(tmp_path: Path) -> None:
    spec = sessionbag.SessionSpec(
        width=376, height=250, n_units=4, baseline_frames=2, during_frames=1, after_frames=2
    )
    bag = tmp_path / "tiny"
    truth = sessionbag.write_session_bag(bag, spec)
    with bagio.open_bag(bag) as b:
        counts = {t: i.count for t, i in b.topics.items()}
        active = [m.message.data for m in b.messages(["/hall/run_active"])]
        ids = [m.message.data for m in b.messages(["/hall/run_id"])]
    frames = 2 + (1 + 1 + 2) + (1 + 2)  # baseline, run 1 (during, rocking, after), run 2
    assert counts[sessionbag.COMPRESSED_TOPIC] == frames
    assert counts[sessionbag.CAMERA_INFO_TOPIC] == frames
    assert active == [True, False, True, False]
    assert ids == ["wave-001", "wave-002"]
    run1 = truth["runs"][0]["cumulative"]
    # The truth is the field's rigid motion: still units have zero displacement.
    for u in run1["units"]:
        if not (u["moved"] or u["overturned"]):
            assert np.allclose(u["translation_mm"], 0.0)
    assert sessionbag.truth_paths(bag)[1].read_text().startswith("run_id,reference,")
    assert truth["runs"][1]["incremental"]["displaced_units"] == 0


def test_compare_to_truth_scores_a_pose_far_off_in_depth_and_flags_wrong_partners() -> None:
    """Measured fiducials are paired with the truth by code and across the line of sight: one
    10 mm off in depth is scored (its error counted, not dropped); one given a neighbour's
    motion is a wrong partner; one of a code no truth fiducial near it has is unpaired."""
    ray = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    truth = {
        "fiducials": [
            {"code": 3, "before_mm": (1000 * ray).tolist(), "displacement_mm": [0.0, 0.0, 0.0]},
            {"code": 17, "before_mm": [120.0, -30.0, 1000.0], "displacement_mm": [20, 5, -8]},
            {"code": 17, "before_mm": [140.0, -30.0, 1000.0], "displacement_mm": [0, 0, 0]},
        ],
        "displaced_units": 1,
    }
    report = {
        "fiducials": [
            # Still, its depth 10 mm off in both states: right partner, 0 displacement error.
            {"code_before": 3, "before_mm": (1010 * ray).tolist(), "displacement_mm": [0, 0, 0]},
            # The still code-17 fiducial reported with its neighbour's motion: a wrong partner.
            {
                "code_before": 17,
                "before_mm": [140.2, -30.1, 1001.0],
                "displacement_mm": [20, 5, -8],
            },
            # A code-29 fiducial where the truth has none.
            {"code_before": 29, "before_mm": [120.0, -30.0, 1000.0], "displacement_mm": [0, 0, 0]},
            {"code_before": 17, "before_mm": [120.0, -30.0, 1000.0], "displacement_mm": None},
        ]
    }
    acc = sessionbag.compare_to_truth(report, truth)
    assert acc["paired"] == 2 and acc["unpaired"] == 1 and acc["wrong"] == 1
    assert acc["err_median_mm"] == pytest.approx(0.5 * np.linalg.norm([20, 5, -8]))


@pytest.fixture(scope="module")
def analyzed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, AnalysisResult]:
    """The bundled session bag analysed once (the output directory and the result)."""
    truth = sessionbag.read_truth(BAG)
    assert truth is not None
    cfg = SessionConfig(baseline_frames=truth["spec"]["baseline_frames"], settle_frames=3)
    out = tmp_path_factory.mktemp("analyzed")
    return out, analyze_bag(BAG, out, session_config=cfg)


def test_analyze_groups_the_session_bags_units_as_the_truth_does(
    analyzed: tuple[Path, AnalysisResult],
) -> None:
    """No unit map: every one of the bag's 24 units carries codes 3, 17 and 29, 28.7-30.4 mm
    apart, while another unit's fiducial is often 9-15 mm away. Grouping by the code distances
    learned from the baseline keeps every reported unit to one true unit and finds about as many
    units as there are (proximity alone reported 32, and most of them mixed two units)."""
    truth = sessionbag.read_truth(BAG)
    assert truth is not None
    tmp_path, _ = analyzed
    doc = json.loads((tmp_path / "report.json").read_text())
    part = truth["runs"][0]["cumulative"]
    tb = np.array([f["before_mm"] for f in part["fiducials"]])
    owner = [f["unit"] for f in part["fiducials"]]
    run = doc["runs"][0]
    members: dict[str, set[int]] = {}
    for f in run["fiducials"]:
        if f.get("before_mm") is None or f.get("unit") is None:
            continue
        gap = np.linalg.norm(tb - np.asarray(f["before_mm"]), axis=1)
        k = int(np.argmin(gap))
        if gap[k] < 3.0:  # a fiducial measured where the truth has one
            members.setdefault(f["unit"], set()).add(owner[k])
    mixed = {u: m for u, m in members.items() if len(m) > 1}
    assert not mixed, mixed
    assert len(truth["runs"][0]["cumulative"]["units"]) == 24
    assert 22 <= run["summary"]["units"] <= 26, run["summary"]["units"]
    # A third of the units moved or rocked, the camera did not: no camera-motion warning (a
    # registration that left 48 of 48 fiducials out once passed for one).
    assert all(r["warnings"] == [] for r in doc["runs"]), [r["warnings"] for r in doc["runs"]]


def test_analyze_session_bag_reports_every_run(analyzed: tuple[Path, AnalysisResult]) -> None:
    truth = sessionbag.read_truth(BAG)
    assert truth is not None
    tmp_path, result = analyzed
    assert result.frames == 17 and result.frames_dropped == 0
    assert [r.run_id for r in result.runs] == ["wave-001", "wave-002"]
    doc = json.loads((tmp_path / "report.json").read_text())
    assert [r["run_id"] for r in doc["runs"]] == ["wave-001", "wave-002"]
    for run, part in zip(doc["runs"], truth["runs"], strict=True):
        assert {"fiducials", "units", "summary"} <= set(run)  # compare --json keys
        acc = sessionbag.compare_to_truth(run, part["cumulative"])
        assert acc["err_median_mm"] < 1.0
        assert acc["wrong"] <= 2
    assert doc["runs"][1]["incremental"]["summary"]["displaced_units"] == 0
    run_files = sorted((tmp_path / "runs").glob("*/report.json"))
    assert len(run_files) == 2
    for path in run_files:  # each stands alone: it names what it was measured from
        inputs = json.loads(path.read_text())["inputs"]
        assert inputs == {"bag": str(BAG), "topics": doc["topics"]}
        assert inputs["topics"]["image"] == sessionbag.COMPRESSED_TOPIC
    # The markers bag opens with the plain MCAP reader Foxglove uses.
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (mcap,) = (tmp_path / "markers").glob("*.mcap")
    seen: dict[str, int] = {}
    with mcap.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "/armourcam/markers":
                arrows = [k for k in msg.markers if k.type == 0 and k.action == 0]
                assert arrows and all(0.0 < k.color.a <= 1.0 for k in arrows)
    assert seen["/armourcam/markers"] == 2 and seen["/armourcam/poses"] == 17


def test_analyze_writes_each_runs_report_files(analyzed: tuple[Path, AnalysisResult]) -> None:
    """Per run, runs/<NNNN>-<run_id>/ holds the files of ``compare --out``: the run's report,
    both CSVs (agreeing with it), the plot and the overlay on the run's last fused frame."""
    import csv

    import cv2

    out, result = analyzed
    doc = json.loads((out / "report.json").read_text())
    dirs = sorted(p for p in (out / "runs").iterdir() if p.is_dir())
    named = [f"{r.sequence:04d}-{r.run_id}" for r in result.runs]
    assert [p.name for p in dirs] == named == ["0001-wave-001", "0002-wave-002"]
    with bagio.open_bag(BAG) as bag:
        camera = bag.camera_model()
    assert camera is not None
    for run_dir, run in zip(dirs, doc["runs"], strict=True):
        names = {"report.json", "fiducials.csv", "units.csv", "plot.png", "overlay.png"}
        assert {p.name for p in run_dir.iterdir()} == names  # and no temporary file left
        rep = json.loads((run_dir / "report.json").read_text())
        assert rep["run_id"] == run["run_id"] and rep["fiducials"] == run["fiducials"]
        fids = list(csv.DictReader((run_dir / "fiducials.csv").read_text().splitlines()))
        assert [f["label"] for f in fids] == [f["label"] for f in run["fiducials"]]
        assert [f["unit"] for f in fids] == [f["unit"] or "" for f in run["fiducials"]]
        units = list(csv.DictReader((run_dir / "units.csv").read_text().splitlines()))
        assert [u["unit"] for u in units] == [u["unit"] for u in run["units"]]
        assert all(float(u["dn_mm"]) == run["summary"]["thresholds"]["dn_mm"] for u in units)
        assert cv2.imread(str(run_dir / "plot.png")) is not None
        overlay = cv2.imread(str(run_dir / "overlay.png"))
        assert overlay is not None and overlay.shape == (camera.height, camera.width, 3)
        # The bag's frame under the vectors, not a blank canvas; same-code vectors in green.
        assert np.mean(overlay) < 200
        b, g, r = (overlay[..., k].astype(int) for k in range(3))
        assert np.any((g > 150) & (r < 120) & (b < 120))


def test_analyze_real_ros1_bag_finds_no_fiducials(tmp_path: Path) -> None:
    result = analyze_bag(FIXTURE, tmp_path, session_config=SessionConfig(baseline_frames=1))
    assert result.frames == 1
    assert result.fiducials_per_frame == [0]
    assert result.runs == []
    assert result.topics["image"] == "/raspicam_node/image/compressed"


def test_analyze_refuses_a_missing_image_topic_and_creates_nothing(tmp_path: Path) -> None:
    out = tmp_path / "never"
    with pytest.raises(ValueError, match="/no/such/topic"):
        analyze_bag(BAG, out, image_topic="/no/such/topic")
    assert not out.exists()


def test_analyze_refuses_an_existing_markers_bag(tmp_path: Path) -> None:
    (tmp_path / "markers").mkdir()
    with pytest.raises(AnalyzeError, match="markers"):
        analyze_bag(FIXTURE, tmp_path)


def test_analyze_command_says_where_a_truncated_bag_stopped(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """A bag cut short: what was readable is analysed and reported, the truncation is said on
    stderr (not only in the report) and the exit status is 1 (some input could not be used)."""
    from armourcam.cli import main

    (mcap,) = BAG.glob("*.mcap")
    data = mcap.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    assert main(["analyze", str(cut), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    (line,) = [s for s in err.splitlines() if "truncated" in s]
    assert line.startswith(f"armourcam analyze: warn: {cut}: bag is truncated or damaged at byte")
    doc = json.loads((tmp_path / "out" / "report.json").read_text())
    assert 0 < doc["frames"]["total"] < 17 and any("truncated" in n for n in doc["notices"])


def test_analyze_command_fails_when_every_frame_is_dropped(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """A calibration that fits none of the bag's frames: each dropped frame is named, each
    run says why it was not measured, and the exit status is 1."""
    import yaml

    from armourcam.cli import main
    from pose_estimator.camera import CameraModel

    camera = tmp_path / "camera.yaml"
    camera.write_text(yaml.safe_dump(CameraModel.ideal(1200, 800, 1400.0).to_dict()))
    assert main(["analyze", str(BAG), "--out", str(tmp_path / "o"), "--camera", str(camera)]) == 1
    captured = capsys.readouterr()
    assert "run wave-001: settled=False: not measured: " in captured.out
    dropped = [s for s in captured.err.splitlines() if "dropped" in s]
    assert len(dropped) == 17 and "calibration is for 1200x800" in dropped[0]


def test_demo_draws_each_run_on_the_scene_after_it() -> None:
    """The demo's overlays: run k is drawn on the last frame before run k + 1 starts (the
    bundled bag's frames between wave-001's stop and wave-002's start), not every run on the
    bag's last frame."""
    from armourcam.commands.demo import _after_images

    afters = _after_images(BAG)
    assert len(afters) == 2
    with bagio.open_bag(BAG) as b:
        start2 = [m.timestamp_ns for m in b.messages(["/hall/run_active"]) if m.message.data][1]
        frames = [(f.timestamp_ns, f.image) for f in b.frames() if f.image is not None]
    first = [img for t, img in frames if t < start2][-1]
    assert np.array_equal(afters[0], first)
    assert np.array_equal(afters[1], frames[-1][1])
    assert not np.array_equal(afters[0], afters[1])


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--dn-mm", "0"], "Dn must be a positive length"),
        (["--dn-mm", "nan"], "Dn must be a positive length"),
        (["--displaced-dn", "-1"], "displacement threshold must be positive"),
        (["--section-width-mm", "inf"], "section width must be a positive length"),
    ],
)
def test_analyze_refuses_bad_damage_settings_before_reading_the_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str], message: str
) -> None:
    """A threshold no run could be measured with is a usage error (exit 2) named up front, not
    a report of runs "not measured" with exit status 0; nothing is written."""
    from armourcam.cli import main

    out = tmp_path / "out"
    assert main(["analyze", str(BAG), "--out", str(out), *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_small_displacement_threshold_lowers_the_movement_threshold_with_it() -> None:
    """``--displaced-dn 0.05`` (about 1 mm) is a valid setting: the movement threshold, which
    may not exceed it and has no option of its own here, follows it down from 2 mm."""
    from displacement_matcher.markers import Comparer

    limits = Comparer(dn_mm=20.5, displaced_dn=0.05).thresholds()
    assert limits.displaced_mm == pytest.approx(1.025)
    assert limits.moved_mm == pytest.approx(1.025)
    assert Comparer().thresholds().moved_mm == 2.0


def test_make_bags_keeps_the_old_bag_until_the_new_one_is_complete(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Rendering fails half-way (a full disk, an interrupt): the bag and truth already there
    are untouched and no partial directory is left; once rendering succeeds, the new bag and
    its truth replace them."""
    spec = sessionbag.SessionSpec(
        width=376, height=250, n_units=4, baseline_frames=1, during_frames=1, after_frames=1
    )
    bag = tmp_path / "tiny"
    sessionbag.write_session_bag(bag, spec)
    files = sorted(p for p in tmp_path.rglob("*") if p.is_file())
    old = {p: p.read_bytes() for p in files}
    real = sessionbag.write_session_bag

    def fails_half_way(path: Path, spec: sessionbag.SessionSpec | None = None) -> object:
        real(path, spec)
        raise KeyboardInterrupt

    monkeypatch.setattr(sessionbag, "write_session_bag", fails_half_way)
    with pytest.raises(KeyboardInterrupt):
        sessionbag.replace_session_bag(bag, spec)
    assert sorted(p for p in tmp_path.rglob("*") if p.is_file()) == files
    assert all(p.read_bytes() == data for p, data in old.items())
    monkeypatch.setattr(sessionbag, "write_session_bag", real)
    other = sessionbag.SessionSpec(
        width=376, height=250, n_units=4, baseline_frames=2, during_frames=1, after_frames=1
    )
    sessionbag.replace_session_bag(bag, other)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file()) == sorted(
        p.relative_to(tmp_path) for p in files
    )
    with bagio.open_bag(bag) as b:
        assert b.topics[sessionbag.COMPRESSED_TOPIC].count == 2 + 3 + 2


def test_analyze_refuses_a_directory_holding_another_report(tmp_path: Path) -> None:
    """A compare --out directory (or any non-empty one) is refused before anything is read:
    a report tree written over it would overwrite its report.json and mix the two."""
    kept = tmp_path / "report.json"
    kept.write_text('{"kept": true}\n')
    with pytest.raises(AnalyzeError, match="is not empty"):
        analyze_bag(BAG, tmp_path)
    assert kept.read_text() == '{"kept": true}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


@pytest.mark.parametrize("command", ["analyze", "compare"])
def test_an_empty_output_path_is_a_usage_error(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    command: str,
) -> None:
    """``--out ""`` (an unset shell variable) is refused, not taken for the working directory,
    whose files the outputs would overwrite."""
    from armourcam.cli import main

    monkeypatch.chdir(tmp_path)
    args = {
        "analyze": ["analyze", str(BAG)],
        "compare": ["compare", "a.png", "--after", "b.png", "--camera", "c.yaml"],
    }[command]
    with pytest.raises(SystemExit) as info:
        main([*args, "--out", ""])
    assert info.value.code == 2
    assert "--out: an empty path" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_bag_without_the_hall_topics_says_why_no_run_was_measured(tmp_path: Path) -> None:
    """The real camera bag has no run-state topic: the analysis says so (and which option names
    one), and its baseline is not said to have been cut short by a run that never started."""
    result = analyze_bag(FIXTURE, tmp_path / "out", session_config=SessionConfig(baseline_frames=1))
    assert result.runs == []
    (warn,) = [n for n in result.notices if "run-state topic" in n]
    assert warn.startswith("warn: no run-state topic (std_msgs/msg/Bool; none) in the bag")
    assert "--run-active-topic" in warn
    assert not any("run started" in n for n in result.notices)
