"""Bags as the camera: reliable replay through the detector and pose processes, real fixture bag."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosutil import REPO, Nodes, Probe, armourcam, ignore_sigint, start_armourcam

from armourcam import bagio, graph, records
from armourcam.graph import Replayer, latched_qos, record_qos, stream_qos
from pose_estimator.camera import CameraModel

FIXTURE = Path(__file__).resolve().parents[3] / "shared" / "fixtures" / "real_camera_aruco_ros1.bag"
N_FRAMES = 30
IMAGE = "sensor_msgs/msg/Image"
CLOUD = "sensor_msgs/msg/PointCloud2"
MARKERS = "visualization_msgs/msg/MarkerArray"


def plain_bag(path: Path, n: int) -> None:
    """``n`` small mono8 frames (no fiducials) with camera info, 10 fps of bag time."""
    cam = CameraModel.ideal(320, 240, 400.0)
    rng = np.random.default_rng(3)
    with bagio.BagWriter(path) as w:
        for k in range(n):
            t = 1_700_000_000 * 10**9 + k * 100_000_000
            img = np.clip(rng.normal(120, 3, (240, 320)), 0, 255).astype(np.uint8)
            w.write_camera_info("/camera/camera_info", cam, t)
            w.write_image("/camera/image_raw", img, t + 1)


class Counter:
    """Counts the pose-estimator's outputs and their distinct stamps."""

    def __init__(self, probe: Probe) -> None:
        from sensor_msgs.msg import PointCloud2

        self.probe = probe
        self.stamps: list[tuple[int, int]] = []
        self.widths: list[int] = []
        self.detections: list[int] = []
        self.subs = [
            probe.node.create_subscription(
                PointCloud2, "/armourcam/poses", self._on, stream_qos("reliable", 100)
            )
        ]
        self.subs += [
            probe.node.create_subscription(
                PointCloud2,
                "/armourcam/detections",
                lambda m: self.detections.append(m.width),
                stream_qos("reliable", 100),
            )
        ]

    def wait_ready(self) -> bool:
        """Wait until the nodes' publishers are matched (so no output is published unseen)."""
        ok = self.probe.spin_until(
            lambda: all(s.get_publisher_count() > 0 for s in self.subs), 20.0
        )
        self.probe.spin_for(1.0)  # let the match settle on both sides
        return ok

    def _on(self, msg: Any) -> None:
        self.stamps.append((msg.header.stamp.sec, msg.header.stamp.nanosec))
        self.widths.append(msg.width)


def start_pipeline(nodes: Nodes, **detector: Any) -> None:
    nodes.start("fiducial_detector", params={"queue_depth": 100, **detector})
    nodes.start("pose_estimator", params={"queue_depth": 100})


@pytest.mark.parametrize("mode", [["--as-fast-as-consumed"], ["--rate", "20"]])
def test_reliable_replay_loses_no_frame(
    nodes: Nodes, probe: Probe, tmp_path: Path, mode: list[str]
) -> None:
    bag = tmp_path / "plain"
    plain_bag(bag, N_FRAMES)
    start_pipeline(nodes)
    counter = Counter(probe)
    assert counter.wait_ready(), nodes.log("pose_estimator")
    out = armourcam("replay", str(bag), "--qos", "reliable", *mode, "--linger", "0.5")
    assert out.returncode == 0, out.stderr + nodes.log("fiducial_detector")
    assert f"frames: {N_FRAMES}" in out.stdout
    assert probe.spin_until(lambda: len(counter.stamps) >= N_FRAMES, 30.0), (
        len(counter.stamps),
        nodes.log("pose_estimator"),
    )
    probe.spin_for(0.5)
    assert len(counter.stamps) == N_FRAMES
    assert len(set(counter.stamps)) == N_FRAMES  # every frame once, none repeated
    assert counter.stamps == sorted(counter.stamps)  # in order
    assert nodes.alive("fiducial_detector") and nodes.alive("pose_estimator")


def test_real_fixture_bag_replays_and_yields_zero_fiducials(nodes: Nodes, probe: Probe) -> None:
    # With the candidate search on frames reduced 2x (the node's ``decimate`` parameter).
    start_pipeline(nodes, transport="compressed", decimate=2)
    counter = Counter(probe)
    assert counter.wait_ready(), nodes.log("pose_estimator")
    out = armourcam(
        "replay",
        str(FIXTURE),
        "--as-fast-as-consumed",
        "--remap",
        "/raspicam_node/image/compressed:=/camera/image_raw/compressed",
        "--remap",
        "/raspicam_node/camera_info:=/camera/camera_info",
    )
    assert out.returncode == 0, out.stderr + nodes.log("fiducial_detector")
    assert "/camera/camera_info: 15" in out.stdout
    assert "confirmed by the detector: 1" in out.stdout
    assert probe.spin_until(lambda: len(counter.stamps) >= 1, 20.0), nodes.log("pose_estimator")
    probe.spin_for(0.5)
    assert counter.detections == [0]  # a real JPEG of people and ArUco tags: none of ours
    assert counter.widths == [0]


def test_replayer_qos_matches_each_kind_of_subscriber(probe: Probe) -> None:
    """Record streams and latched topics are republished TRANSIENT_LOCAL (a transient-local
    reader, as the pose estimator's and the matcher's, matches no volatile writer); images and
    camera info stay VOLATILE, even when a bag says latched (no history of big frames)."""

    def qos(rep: Replayer, topic: str, msgtype: str, latched: bool = False) -> tuple[Any, ...]:
        q = rep.publisher(topic, msgtype, latched=latched).qos_profile
        return q.reliability.name, q.durability.name, q.depth

    reliable = Replayer(probe.node, depth=50)
    assert qos(reliable, "/camera/image_raw", IMAGE, True) == ("RELIABLE", "VOLATILE", 50)
    assert qos(reliable, "/camera/camera_info", "sensor_msgs/CameraInfo", True)[1] == "VOLATILE"
    assert qos(reliable, "/armourcam/poses", CLOUD) == ("RELIABLE", "TRANSIENT_LOCAL", 50)
    assert qos(reliable, "/armourcam/markers", MARKERS, True) == ("RELIABLE", "TRANSIENT_LOCAL", 1)
    assert qos(reliable, "/armourcam/markers_live", MARKERS)[1] == "VOLATILE"
    live = Replayer(probe.node, qos="sensor_data", depth=5)
    assert qos(live, "/live/image", IMAGE) == ("BEST_EFFORT", "VOLATILE", 5)
    assert qos(live, "/live/poses", CLOUD) == ("BEST_EFFORT", "VOLATILE", 5)
    # Recorded latched: reliable and transient-local whatever the replay's qos.
    assert qos(live, "/live/baseline", CLOUD, True) == ("RELIABLE", "TRANSIENT_LOCAL", 5)


def test_replayed_records_and_latched_outputs_reach_their_subscribers(
    probe: Probe, tmp_path: Path
) -> None:
    """``armourcam replay --topics /armourcam/poses ...`` feeds a transient-local subscriber (as
    the matcher's) and republishes a topic recorded latched so that a latched reader gets it."""
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    n_frames = 5
    recs = records.layout("FiducialPoseRecord").empty(3)
    recs["code"] = [4, 9, 17]
    bag = tmp_path / "outputs"
    with bagio.BagWriter(bag) as w:
        for k in range(n_frames):
            w.write_records("/armourcam/poses", "FiducialPoseRecord", recs, (k + 1) * 10**8)
        w.add_topic("/armourcam/markers", MARKERS, latched=True)
        w.write("/armourcam/markers", MARKERS, w.new(MARKERS, markers=[]), 10**9)
    got: dict[str, list[Any]] = {"matcher": [], "viewer": [], "markers": []}
    node = probe.node
    node.create_subscription(
        PointCloud2, "/armourcam/poses", got["matcher"].append, record_qos("reliable", 100)
    )
    node.create_subscription(
        PointCloud2, "/armourcam/poses", got["viewer"].append, stream_qos("reliable", 100)
    )
    node.create_subscription(
        MarkerArray, "/armourcam/markers", got["markers"].append, latched_qos()
    )
    out = armourcam(
        "replay",
        str(bag),
        "--topics",
        "/armourcam/poses",
        "/armourcam/markers",
        "--rate",
        "10",
        "--wait-subscribers",
        "5",
        "--linger",
        "0.5",
    )
    assert out.returncode == 0, out.stderr
    assert f"/armourcam/poses: {n_frames}" in out.stdout and "/armourcam/markers: 1" in out.stdout
    assert "no subscriber yet" not in out.stderr
    want = {"matcher": n_frames, "viewer": n_frames, "markers": 1}
    assert probe.spin_until(lambda: {k: len(v) for k, v in got.items()} == want, 10.0), {
        k: len(v) for k, v in got.items()
    }
    assert [records.from_pointcloud2(m)["code"].tolist() for m in got["matcher"]] == [
        [4, 9, 17]
    ] * n_frames


def paired_bag(path: Path, n: int) -> None:
    """``n`` frames whose image and camera info carry one stamp, as a camera driver writes."""
    cam = CameraModel.ideal(320, 240, 400.0)
    with bagio.BagWriter(path) as w:
        for k in range(n):
            t = 1_700_000_000 * 10**9 + k * 100_000_000
            w.write_camera_info("/camera/camera_info", cam, t)
            w.write_image(
                "/camera/image_raw", np.full((240, 320), 120, np.uint8), t + 1, stamp_ns=t
            )


def test_restamped_images_and_camera_info_stay_paired(probe: Probe, tmp_path: Path) -> None:
    """An image and its camera info, one stamp in the bag, share their new stamp (exact-time
    synchronisers, image_proc and viewers pair them); each frame's stamp is its own."""
    from sensor_msgs.msg import CameraInfo, Image

    paired_bag(tmp_path / "paired", 6)
    seen: dict[str, list[tuple[int, int]]] = {"image": [], "info": []}
    for kind, cls, topic in (
        ("image", Image, "/camera/image_raw"),
        ("info", CameraInfo, "/camera/camera_info"),
    ):
        probe.node.create_subscription(
            cls,
            topic,
            lambda m, kind=kind: seen[kind].append((m.header.stamp.sec, m.header.stamp.nanosec)),
            stream_qos("reliable", 100),  # kept while the probe waits for the replay
        )
    out = armourcam("replay", str(tmp_path / "paired"), "--rate", "20", "--linger", "0.5")
    assert out.returncode == 0, out.stderr
    assert probe.spin_until(lambda: len(seen["image"]) >= 6 and len(seen["info"]) >= 6, 10.0)
    assert seen["image"] == seen["info"] and len(set(seen["image"])) == 6


def test_a_sensor_data_graph_confirms_an_as_fast_as_consumed_replay(
    nodes: Nodes, tmp_path: Path
) -> None:
    """The replay's watchers of the graph's outputs follow ``--qos``: reliable readers never
    matched a ``sensor_data`` graph's best-effort writers, and every frame waited out its 30 s.
    (Best effort may still lose a frame while discovery settles: at least two of three.)"""
    paired_bag(tmp_path / "paired", 3)
    nodes.start("fiducial_detector", params={"queue_depth": 100, "qos": "sensor_data"})
    nodes.start("pose_estimator", params={"queue_depth": 100, "qos": "sensor_data"})
    out = armourcam(
        "replay", str(tmp_path / "paired"), "--qos", "sensor_data", "--as-fast-as-consumed"
    )
    (line,) = [s for s in out.stdout.splitlines() if "confirmed by the detector" in s]
    assert int(line.rsplit(" ", 1)[1]) >= 2, out.stdout + out.stderr


def test_replay_drain_waits_for_every_subscriber_to_acknowledge(probe: Probe) -> None:
    """:meth:`Replayer.drain` (the replay's last step) names a topic whose matched subscriber has
    not acknowledged (a stopped process), and returns clean once it has: a latched hall event is
    not lost by exiting while it is in flight."""
    import os
    import signal
    import subprocess
    import sys

    from rosutil import ros_env
    from std_msgs.msg import String

    topic = f"/drain_probe_{os.getpid()}"
    script = (
        "import time, rclpy\n"
        "from std_msgs.msg import String\n"
        "from armourcam.graph import event_qos, use_dds_profile\n"
        "use_dds_profile(); rclpy.init(); n = rclpy.create_node('drain_sub')\n"
        f"n.create_subscription(String, {topic!r}, lambda m: None, event_qos())\n"
        "rclpy.spin(n)\n"
    )
    child = subprocess.Popen([sys.executable, "-c", script], env=ros_env(), start_new_session=True)
    try:
        replayer = Replayer(probe.node)
        pub = replayer.publisher(topic, "std_msgs/msg/String")
        assert replayer.wait_for_subscribers([topic], 20.0) == []
        probe.spin_for(1.0)  # the subscriber matches back
        os.kill(child.pid, signal.SIGSTOP)
        pub.publish(String(data="wave-7"))
        assert replayer.drain(1.0) == [topic]
        os.kill(child.pid, signal.SIGCONT)
        assert replayer.drain(10.0) == []
    finally:
        os.killpg(child.pid, signal.SIGKILL)
        child.wait(5.0)


def test_a_replay_started_with_sigint_ignored_stops_at_once_on_sigint() -> None:
    """Started with SIGINT ignored (``armourcam replay BAG &`` from a script), a slow replay
    stops on SIGINT, which rclpy's handler takes, within a second and with status 0; it used to
    publish on into a shut-down context and end with a traceback, and sleep out the time to
    its next message first."""
    import signal
    import subprocess
    import time

    proc = start_armourcam(
        "replay",
        str(REPO / "bags" / "session_small"),
        "--rate",
        "0.01",  # the bag's frames 0.5 s apart: 50 s between them
        "--wait-subscribers",
        "0",
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=ignore_sigint,
    )
    try:
        time.sleep(8.0)  # started, publishing, waiting for its next message
        assert proc.poll() is None, proc.communicate()
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=15.0)
        took = time.monotonic() - t0
    finally:
        graph.stop_processes([proc])
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err
    assert took < 10.0, took  # not the rest of the 50 s to the next frame
