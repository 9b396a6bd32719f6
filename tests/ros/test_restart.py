"""Restarting a node of a running graph: what it republishes and what it must not take twice."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from matcherutil import Hall, Latched, field, header
from rosutil import Nodes, Probe, ideal_calibration

from armourcam import records
from armourcam.graph import record_qos

FRAME_ID = "hall_cam_optical"


def test_a_restarted_matcher_republishes_its_outputs_in_the_frames_frame(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """The frame_id of the pose frames is kept in data_dir: the restarted matcher's latched
    baseline, markers and displacements carry it before any new frame comes (they used to
    carry an empty frame_id, which RViz cannot place)."""
    data = tmp_path / "data"
    params = {"data_dir": str(data), "baseline_frames": 2, "settle_frames": 2}
    nodes.start("displacement_matcher", params=params)
    hall = Hall(probe, rng=np.random.default_rng(3), frame_id=FRAME_ID)
    assert hall.wait_matched()
    probe.spin_for(0.5)
    truth = field(2, origin=(0.0, 0.0, 700.0))
    hall.frames(truth, 2)
    assert probe.spin_until(lambda: (data / "baseline.json").exists(), 20.0)
    moved = truth.copy()
    moved[:4] += [10.0, 0.0, 0.0]
    hall.run("wave-F", moved, settle=2)
    assert probe.spin_until(lambda: list(data.glob("runs/*.json")), 20.0), nodes.log(
        "displacement_matcher"
    )
    assert nodes.stop("displacement_matcher") == 0, nodes.log("displacement_matcher")
    # No frame reaches the restarted matcher: what it knows of the frame is what it kept.
    probe.node.destroy_publisher(hall.poses)
    assert json.loads((data / "session.json").read_text())["frame_id"] == FRAME_ID

    nodes.start("displacement_matcher", params=params, label="matcher2")
    late = Latched(probe)
    got = {"markers": late.markers, "disp": late.displacements, "baseline": late.baselines}
    assert probe.spin_until(lambda: all(got.values()), 20.0), nodes.log("matcher2")
    assert "resumed" in nodes.log("matcher2")
    assert got["baseline"][-1].header.frame_id == FRAME_ID
    assert got["disp"][-1].header.frame_id == FRAME_ID
    assert got["markers"][-1].markers
    assert {m.header.frame_id for m in got["markers"][-1].markers} == {FRAME_ID}


def test_a_restarted_pose_estimator_does_not_make_the_matcher_take_frames_twice(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """A restarted pose estimator receives the detector's transient-local history and
    publishes those frames' poses again: the matcher ignores frames whose stamp and frame_id it
    has already taken. Within one process the pose estimator itself processes a frame once."""
    from sensor_msgs.msg import PointCloud2, PointField

    calibration = ideal_calibration(tmp_path)
    pose_params = {"calibration_file": str(calibration), "diagnostics_period_s": 0.2}
    nodes.start("pose_estimator", params=pose_params)
    nodes.start(
        "displacement_matcher",
        params={"data_dir": str(tmp_path / "data"), "diagnostics_period_s": 0.2},
    )
    pose_status = probe.statuses("pose_estimator")
    matcher_status = probe.statuses("displacement_matcher")
    # The detector's output: reliable + transient-local, as record_qos makes it.
    dets = probe.node.create_publisher(
        PointCloud2, "/armourcam/detections", record_qos("reliable", 50)
    )
    poses_out: list[Any] = []
    probe.node.create_subscription(
        PointCloud2, "/armourcam/poses", poses_out.append, record_qos("reliable", 50)
    )
    assert probe.spin_until(lambda: dets.get_subscription_count() > 0, 20.0)

    def matcher_saw(seen: int, duplicate: int) -> bool:
        v = matcher_status.values()
        return v.get("frames_seen") == str(seen) and v.get("frames_duplicate") == str(duplicate)

    assert probe.spin_until(lambda: matcher_saw(0, 0), 20.0), (
        matcher_status[-1:],
        nodes.log("displacement_matcher"),
    )
    probe.spin_for(0.5)
    empty = records.detections_to_records([])
    sent = []
    for _ in range(4):
        msg = records.to_pointcloud2(
            PointCloud2, PointField, header(probe.node, FRAME_ID), records.DETECTION, empty
        )
        sent.append(msg)
        dets.publish(msg)
        probe.spin_for(0.1)
    dets.publish(sent[-1])  # the same frame again: processed once
    assert probe.spin_until(lambda: matcher_saw(4, 0), 10.0), (
        matcher_status[-1:],
        nodes.log("pose_estimator"),
    )
    assert probe.spin_until(lambda: pose_status.values().get("frames_received") == "5", 5.0)
    v = pose_status.values()
    assert (v["frames_published"], v["frames_duplicate"]) == ("4", "1"), v
    assert probe.spin_until(lambda: len(poses_out) >= 4, 5.0)
    probe.spin_for(0.3)
    assert len(poses_out) == 4

    assert nodes.stop("pose_estimator") == 0, nodes.log("pose_estimator")
    probe.spin_for(0.5)
    pose_status.clear()
    nodes.start("pose_estimator", params=pose_params, label="pose2")
    # The new process gets the 5 historic messages, processes 4 (it has not seen them) and
    # publishes them again; the matcher takes none of them.
    assert probe.spin_until(lambda: pose_status.values().get("frames_published") == "4", 20.0), (
        pose_status[-1:],
        nodes.log("pose2"),
    )
    assert probe.spin_until(lambda: matcher_saw(4, 4), 10.0), (
        matcher_status[-1:],
        nodes.log("displacement_matcher"),
    )
    # A new frame is taken as usual.
    dets.publish(
        records.to_pointcloud2(
            PointCloud2, PointField, header(probe.node, FRAME_ID), records.DETECTION, empty
        )
    )
    assert probe.spin_until(lambda: matcher_saw(5, 4), 10.0), matcher_status[-1:]
    assert nodes.alive("pose2") and nodes.alive("displacement_matcher")
