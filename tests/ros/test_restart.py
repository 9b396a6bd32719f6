"""Restarting a node of a running graph: what it republishes and what it must not take twice."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosutil import Nodes, Probe

from armourcam import records
from armourcam.graph import event_qos, latched_qos, record_qos
from pose_estimator.camera import CameraModel
from pose_estimator.types import FiducialPose

FRAME_ID = "hall_cam_optical"


def _header(probe: Probe) -> Any:
    from std_msgs.msg import Header

    h = Header(frame_id=FRAME_ID)
    h.stamp = probe.node.get_clock().now().to_msg()
    return h


def _pose_cloud(probe: Probe, truth: np.ndarray, rng: np.random.Generator) -> Any:
    """One noisy FiducialPoseRecord frame of ``truth`` (mm), stamped now, frame FRAME_ID."""
    from sensor_msgs.msg import PointCloud2, PointField

    cov = np.diag([0.02, 0.02, 0.1]) ** 2
    poses = [
        FiducialPose(i % 4, p + rng.normal(0, [0.02, 0.02, 0.1]), np.array([0, 0, -1.0]), cov)
        for i, p in enumerate(truth)
    ]
    rows = records.poses_to_records(poses)
    return records.to_pointcloud2(PointCloud2, PointField, _header(probe), records.POSE, rows)


def _statuses(probe: Probe, node: str) -> list[Any]:
    """The /diagnostics statuses of ``node``, as they arrive."""
    from diagnostic_msgs.msg import DiagnosticArray

    out: list[Any] = []
    probe.node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: out.extend(s for s in m.status if node in s.name),
        50,
    )
    return out


def _values(statuses: list[Any]) -> dict[str, str]:
    return {kv.key: kv.value for kv in statuses[-1].values} if statuses else {}


def test_a_restarted_matcher_republishes_its_outputs_in_the_frames_frame(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """The frame_id of the pose frames is kept in data_dir: the restarted matcher's latched
    baseline, markers and displacements carry it before any new frame comes (they used to
    carry an empty frame_id, which RViz cannot place)."""
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Bool, String
    from visualization_msgs.msg import MarkerArray

    data = tmp_path / "data"
    params = {"data_dir": str(data), "baseline_frames": 2, "settle_frames": 2}
    nodes.start("displacement_matcher", params=params)
    n = probe.node
    poses = n.create_publisher(PointCloud2, "/armourcam/poses", record_qos("reliable", 50))
    active = n.create_publisher(Bool, "/hall/run_active", event_qos())
    run_id = n.create_publisher(String, "/hall/run_id", event_qos())
    assert probe.spin_until(lambda: poses.get_subscription_count() > 0, 20.0)
    probe.spin_for(0.5)
    rng = np.random.default_rng(3)
    offsets = np.array([[0.0, 0, 0], [9.0, 0, 2], [0, 9.0, -2], [9.0, 9.0, 0]])
    truth = (np.array([[0.0, 0, 700], [45.0, 0, 700]])[:, None] + offsets).reshape(-1, 3)
    for _ in range(2):
        poses.publish(_pose_cloud(probe, truth, rng))
        probe.spin_for(0.05)
    assert probe.spin_until(lambda: (data / "baseline.json").exists(), 20.0)
    run_id.publish(String(data="wave-F"))
    active.publish(Bool(data=True))
    probe.spin_for(0.3)
    active.publish(Bool(data=False))
    probe.spin_for(0.3)
    moved = truth.copy()
    moved[:4] += [10.0, 0.0, 0.0]
    for _ in range(2):
        poses.publish(_pose_cloud(probe, moved, rng))
        probe.spin_for(0.05)
    assert probe.spin_until(lambda: list(data.glob("runs/*.json")), 20.0), nodes.log(
        "displacement_matcher"
    )
    assert nodes.stop("displacement_matcher") == 0
    # No frame reaches the restarted matcher: what it knows of the frame is what it kept.
    n.destroy_publisher(poses)
    assert json.loads((data / "session.json").read_text())["frame_id"] == FRAME_ID

    nodes.start("displacement_matcher", params=params, label="matcher2")
    got: dict[str, list[Any]] = {"markers": [], "disp": [], "baseline": []}
    n.create_subscription(MarkerArray, "/armourcam/markers", got["markers"].append, latched_qos())
    n.create_subscription(
        PointCloud2, "/armourcam/displacements", got["disp"].append, latched_qos()
    )
    n.create_subscription(PointCloud2, "/armourcam/baseline", got["baseline"].append, latched_qos())
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

    calibration = tmp_path / "camera.yaml"
    calibration.write_text(yaml.safe_dump(CameraModel.ideal(640, 480, 500.0).to_dict()))
    pose_params = {"calibration_file": str(calibration), "diagnostics_period_s": 0.2}
    nodes.start("pose_estimator", params=pose_params)
    nodes.start(
        "displacement_matcher",
        params={"data_dir": str(tmp_path / "data"), "diagnostics_period_s": 0.2},
    )
    pose_status = _statuses(probe, "pose_estimator")
    matcher_status = _statuses(probe, "displacement_matcher")
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
        v = _values(matcher_status)
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
            PointCloud2, PointField, _header(probe), records.DETECTION, empty
        )
        sent.append(msg)
        dets.publish(msg)
        probe.spin_for(0.1)
    dets.publish(sent[-1])  # the same frame again: processed once
    assert probe.spin_until(lambda: matcher_saw(4, 0), 10.0), (
        matcher_status[-1:],
        nodes.log("pose_estimator"),
    )
    assert probe.spin_until(lambda: _values(pose_status).get("frames_received") == "5", 5.0)
    v = _values(pose_status)
    assert (v["frames_published"], v["frames_duplicate"]) == ("4", "1"), v
    assert probe.spin_until(lambda: len(poses_out) >= 4, 5.0)
    probe.spin_for(0.3)
    assert len(poses_out) == 4

    assert nodes.stop("pose_estimator") == 0
    probe.spin_for(0.5)
    pose_status.clear()
    nodes.start("pose_estimator", params=pose_params, label="pose2")
    # The new process gets the 5 historic messages, processes 4 (it has not seen them) and
    # publishes them again; the matcher takes none of them.
    assert probe.spin_until(lambda: _values(pose_status).get("frames_published") == "4", 20.0), (
        pose_status[-1:],
        nodes.log("pose2"),
    )
    assert probe.spin_until(lambda: matcher_saw(4, 4), 10.0), (
        matcher_status[-1:],
        nodes.log("displacement_matcher"),
    )
    # A new frame is taken as usual.
    dets.publish(
        records.to_pointcloud2(PointCloud2, PointField, _header(probe), records.DETECTION, empty)
    )
    assert probe.spin_until(lambda: matcher_saw(5, 4), 10.0), matcher_status[-1:]
    assert nodes.alive("pose2") and nodes.alive("displacement_matcher")
