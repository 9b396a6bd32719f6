"""displacement_matcher over DDS: latched outputs for late subscribers, state across restarts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from matcherutil import Hall, Latched, field
from rosutil import Nodes, Probe, status_values

from displacement_matcher.session import SESSION_STATE_FILE


def matcher_params(data_dir: Path) -> dict[str, Any]:
    return {"data_dir": str(data_dir), "baseline_frames": 3, "settle_frames": 3}


def _matcher_with_baseline(nodes: Nodes, probe: Probe, data: Path) -> tuple[Hall, np.ndarray]:
    """A matcher keeping ``data``, fed baseline frames of :func:`field` (automatic baseline)."""
    nodes.start("displacement_matcher", params=matcher_params(data))
    hall = Hall(probe)
    assert hall.wait_matched(), nodes.log("displacement_matcher")
    probe.spin_for(0.5)
    truth0 = field()
    hall.frames(truth0, 3)  # -> automatic baseline
    return hall, truth0


def test_late_subscriber_gets_latched_report_and_markers_and_state_survives_restart(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    data = tmp_path / "data"
    hall, truth0 = _matcher_with_baseline(nodes, probe, data)
    truth1 = truth0.copy()
    truth1[:4] += [10.0, 0.0, 0.0]  # one unit moves 10 mm
    hall.run("wave-A", truth1)
    assert probe.spin_until(lambda: (data / "runs").is_dir() and any((data / "runs").iterdir()), 20)
    probe.spin_for(0.5)

    # A subscriber that starts after the report was published still gets it (latched).
    late = Latched(probe)
    assert probe.spin_until(lambda: late.reports and late.markers and late.baselines, 10.0)
    report = late.reports[-1]
    assert report["run_id"] == "wave-A" and report["sequence"] == 1
    moved = [
        f
        for f in report["fiducials"]
        if f["displacement_mm"] is not None and np.linalg.norm(f["displacement_mm"]) > 5.0
    ]
    assert len(moved) == 4
    for f in moved:
        assert np.allclose(f["displacement_mm"], [10.0, 0.0, 0.0], atol=0.5)
    arrows = [m for m in late.markers[-1].markers if m.type == 0 and m.action == 0]  # ARROW, ADD
    assert len(arrows) == len(truth0)
    green = [m for m in arrows if m.color.g > 0.5 and m.color.r < 0.5]
    assert len(green) == len(truth0)  # all same-code matches
    assert late.baselines[-1].width == len(truth0)

    # Restart the matcher: it resumes from data_dir (baseline + run 1) and republishes.
    assert nodes.stop("displacement_matcher") == 0, nodes.log("displacement_matcher")
    nodes.start("displacement_matcher", params=matcher_params(data), label="matcher2")
    late2 = Latched(probe)
    assert probe.spin_until(lambda: late2.reports and late2.baselines, 20.0), nodes.log("matcher2")
    assert late2.reports[-1]["run_id"] == "wave-A"
    assert "resumed" in nodes.log("matcher2")

    # The next run is measured against the resumed baseline (cumulative) and run 1 (incremental).
    hall2 = hall
    assert probe.spin_until(lambda: hall2.poses.get_subscription_count() > 0, 20.0)
    probe.spin_for(0.5)
    truth2 = truth1.copy()
    truth2[8:12] += [0.0, 7.0, 0.0]  # unit 2 moves 7 mm
    hall2.run("wave-B", truth2)
    assert probe.spin_until(lambda: any(r["run_id"] == "wave-B" for r in late2.reports), 20.0), (
        nodes.log("matcher2")
    )
    rep = next(r for r in late2.reports if r["run_id"] == "wave-B")
    assert rep["sequence"] == 2
    inc = rep["incremental"]
    big = [
        f
        for f in inc["fiducials"]
        if f["displacement_mm"] is not None and np.linalg.norm(f["displacement_mm"]) > 3.0
    ]
    assert len(big) == 4
    for f in big:
        assert np.allclose(f["displacement_mm"], [0, 7.0, 0], atol=0.5)
    cum = [
        f
        for f in rep["fiducials"]
        if f["displacement_mm"] is not None and np.linalg.norm(f["displacement_mm"]) > 3.0
    ]
    assert len(cum) == 8  # run 1's unit and run 2's, both against the same baseline
    assert nodes.alive("matcher2")


def test_a_stop_published_while_the_matcher_is_down_ends_the_resumed_run(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """The matcher dies during a run; the hall stops the run meanwhile (latched). Restarted, it
    resumes the run from data_dir, takes the historic stop, settles on the next frames and
    reports the run under its own id (it used to wait for a stop already given)."""
    from std_msgs.msg import Bool, String

    data = tmp_path / "data"
    hall, truth0 = _matcher_with_baseline(nodes, probe, data)
    assert probe.spin_until(lambda: (data / "baseline.json").exists(), 20.0)
    hall.run_id.publish(String(data="wave-K"))
    hall.active.publish(Bool(data=True))
    state = data / SESSION_STATE_FILE
    assert probe.spin_until(
        lambda: state.exists() and json.loads(state.read_text())["run_id"] == "wave-K", 20.0
    ), nodes.log("displacement_matcher")
    assert nodes.stop("displacement_matcher") == 0, nodes.log("displacement_matcher")
    hall.active.publish(Bool(data=False))  # while the matcher is down
    probe.spin_for(0.5)
    nodes.start("displacement_matcher", params=matcher_params(data), label="matcher2")
    late = Latched(probe)
    assert probe.spin_until(lambda: hall.poses.get_subscription_count() > 0, 20.0)
    probe.spin_for(1.5)  # the historic hall state is applied half a second after start
    truth1 = truth0.copy()
    truth1[:4] += [10.0, 0.0, 0.0]
    for _ in range(4):
        hall.frames(truth1, 3)
        if probe.spin_until(lambda: any(r["run_id"] == "wave-K" for r in late.reports), 2.0):
            break
    assert any(r["run_id"] == "wave-K" for r in late.reports), nodes.log("matcher2")
    rep = next(r for r in late.reports if r["run_id"] == "wave-K")
    assert (
        rep["sequence"] == 1
        and rep["summary"]["moved_units"] + rep["summary"]["displaced_units"] >= 1
    )


def test_a_data_dir_that_fails_mid_session_loses_nothing_and_the_node_lives_on(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """data_dir stops taking files in the middle of a session (a full disk; here a file where
    the directory was, so that writes fail even for root): the run is still measured and
    published, /diagnostics says ERROR naming the files not saved, and once the directory is
    back the next save writes them all."""
    import shutil

    from diagnostic_msgs.msg import DiagnosticStatus

    data = tmp_path / "data"
    hall, truth0 = _matcher_with_baseline(nodes, probe, data)
    assert probe.spin_until(lambda: (data / "baseline.json").exists(), 20.0)
    statuses = probe.statuses("/displacement_matcher: armourcam")
    late = Latched(probe)
    shutil.rmtree(data)
    data.write_text("not a directory")
    truth1 = truth0.copy()
    truth1[:4] += [10.0, 0.0, 0.0]
    hall.run("wave-D", truth1)
    assert probe.spin_until(lambda: any(r["run_id"] == "wave-D" for r in late.reports), 20.0), (
        nodes.log("displacement_matcher")
    )

    def unsaved(status: Any) -> int:
        return int(status_values(status).get("unsaved_files", 0))

    # The status published before the run completed (its start and stop could not save
    # session.json) may still be the latest when the report arrives: wait for the one after.
    assert probe.spin_until(
        lambda: (
            bool(statuses)
            and statuses[-1].level == DiagnosticStatus.ERROR
            and unsaved(statuses[-1]) >= 2
        ),  # the run and session.json
        5.0,
    ), [(s.level, s.message, unsaved(s)) for s in statuses[-3:]]
    assert "not saved" in statuses[-1].message
    assert nodes.alive("displacement_matcher")
    assert "could not save" in nodes.log("displacement_matcher")

    data.unlink()
    data.mkdir()
    hall.run("wave-E", truth1)  # its saves write the kept files first
    assert probe.spin_until(lambda: len(list(data.glob("runs/*.json"))) == 2, 20.0), nodes.log(
        "displacement_matcher"
    )
    names = sorted(p.name for p in data.glob("runs/*.json"))
    assert names == ["0001-wave-D.json", "0002-wave-E.json"]
    assert probe.spin_until(
        lambda: (
            statuses[-1].level != DiagnosticStatus.ERROR or "not saved" not in statuses[-1].message
        ),
        5.0,
    )
    assert nodes.alive("displacement_matcher")


def test_a_hall_publishing_volatile_drives_the_runs(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """rclpy's and rclcpp's default publisher is volatile, which a transient-local reader never
    matches: the matcher also listens volatile, and applies a message once however many of its
    subscriptions deliver it (the latched hall of the other tests drives both)."""
    from std_msgs.msg import Bool, String

    from armourcam.graph import stream_qos

    data = tmp_path / "data"
    hall, truth0 = _matcher_with_baseline(nodes, probe, data)
    assert probe.spin_until(lambda: (data / "baseline.json").exists(), 20.0)
    active = probe.node.create_publisher(Bool, "/hall/run_active", stream_qos("reliable", 10))
    run_id = probe.node.create_publisher(String, "/hall/run_id", stream_qos("reliable", 10))
    assert probe.spin_until(lambda: active.get_subscription_count() >= 1, 20.0)
    probe.spin_for(0.5)
    late = Latched(probe)
    truth1 = truth0.copy()
    truth1[:4] += [10.0, 0.0, 0.0]
    run_id.publish(String(data="wave-V"))
    active.publish(Bool(data=True))
    probe.spin_for(0.3)
    active.publish(Bool(data=False))
    probe.spin_for(0.3)
    hall.frames(truth1, 3)
    assert probe.spin_until(lambda: any(r["run_id"] == "wave-V" for r in late.reports), 20.0), (
        nodes.log("displacement_matcher")
    )
    # The latched hall's messages reach both subscriptions: still one run per start and stop.
    hall.run("wave-L", truth1)
    assert probe.spin_until(lambda: any(r["run_id"] == "wave-L" for r in late.reports), 20.0)
    probe.spin_for(1.0)
    names = sorted(p.name for p in data.glob("runs/*.json"))
    assert names == ["0001-wave-V.json", "0002-wave-L.json"], names
