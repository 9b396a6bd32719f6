"""``armourcam record`` over DDS: subscriptions that match each publisher's QoS (a live camera is
best effort), the publishers' QoS in the bag's metadata, topics without publishers left out."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from rosutil import Probe, ros_env

from armourcam import bagio, graph
from armourcam.graph import latched_qos, stream_qos


def test_recording_qos_matches_every_publisher() -> None:
    """Best effort if any publisher is, transient-local only if all are."""
    from rclpy.qos import DurabilityPolicy as D
    from rclpy.qos import QoSProfile, qos_profile_sensor_data
    from rclpy.qos import ReliabilityPolicy as R

    def choose(*offered: QoSProfile) -> tuple[R, D]:
        q = graph._recording_qos(offered)
        return q.reliability, q.durability

    reliable = stream_qos("reliable", 10)
    assert choose(qos_profile_sensor_data) == (R.BEST_EFFORT, D.VOLATILE)
    assert choose(reliable) == (R.RELIABLE, D.VOLATILE)
    assert choose(latched_qos()) == (R.RELIABLE, D.TRANSIENT_LOCAL)
    assert choose(latched_qos(), reliable) == (R.RELIABLE, D.VOLATILE)
    assert choose(latched_qos(), qos_profile_sensor_data) == (R.BEST_EFFORT, D.VOLATILE)


def test_record_matches_each_publisher_and_stores_its_qos(probe: Probe, tmp_path: Path) -> None:
    """A best-effort camera (raw and compressed) and a camera info topic with a reliable and a
    best-effort publisher are all recorded; a latched report published before the recorder
    started is recorded once; a topic with only a subscriber is not in the bag; the metadata
    holds the publishers' offered QoS."""
    from rclpy.qos import qos_profile_sensor_data
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosReliability, QosTime
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image
    from std_msgs.msg import String

    node = probe.node
    raw = node.create_publisher(Image, "/camera/image_raw", qos_profile_sensor_data)
    jpeg = node.create_publisher(
        CompressedImage, "/camera/image_raw/compressed", qos_profile_sensor_data
    )
    infos = {
        "reliable": node.create_publisher(
            CameraInfo, "/camera/camera_info", stream_qos("reliable", 10)
        ),
        "best_effort": node.create_publisher(
            CameraInfo, "/camera/camera_info", qos_profile_sensor_data
        ),
    }
    report = node.create_publisher(String, "/armourcam/report", latched_qos())
    report.publish(String(data='{"run": 1}'))  # before the recorder starts
    # Subscribed to but never published (as the matcher's hall inputs without a hall).
    node.create_subscription(String, "/hall/run_id", lambda _: None, latched_qos(10))

    bag = tmp_path / "bag"
    cmd = [sys.executable, "-m", "armourcam.cli", "record", "--out", str(bag), "--inputs"]
    proc = subprocess.Popen(
        [*cmd, "--duration", "6"],
        env=ros_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 60.0
        while proc.poll() is None and time.monotonic() < deadline:
            raw.publish(Image(height=4, width=6, encoding="mono8", step=6, data=bytes(24)))
            jpeg.publish(CompressedImage(format="jpeg", data=b"\xff\xd8\xff\xd9"))
            for frame_id, pub in infos.items():
                info = CameraInfo(width=6, height=4)
                info.header.frame_id = frame_id
                pub.publish(info)
            probe.spin_for(0.1)
        stdout, stderr = proc.communicate(timeout=10.0)
    finally:
        graph.stop_processes([proc])
    assert proc.returncode == 0, stderr
    assert "/hall/run_id: 0" in stdout and "/armourcam/report: 1" in stdout

    with bagio.open_bag(bag) as b:
        topics = b.topics
        frame_ids = {m.message.header.frame_id for m in b.messages(["/camera/camera_info"])}
        image = next(iter(b.messages(["/camera/image_raw"]))).message
        report_text = next(iter(b.messages(["/armourcam/report"]))).message.data
    # Stored as received (CDR bytes), read back as published.
    assert (image.height, image.width, image.encoding) == (4, 6, "mono8")
    assert bytes(image.data) == bytes(24) and report_text == '{"run": 1}'
    assert set(topics) == {
        "/camera/image_raw",
        "/camera/image_raw/compressed",
        "/camera/camera_info",
        "/armourcam/report",
    }, stdout
    assert topics["/camera/image_raw"].count >= 10, stdout
    assert topics["/camera/image_raw/compressed"].count >= 10, stdout
    assert frame_ids == {"reliable", "best_effort"}
    assert topics["/armourcam/report"].count == 1 and topics["/armourcam/report"].latched
    assert not topics["/camera/image_raw"].latched

    with AnyReader([bag]) as reader:
        offered = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    (camera,) = offered["/camera/image_raw"]
    assert (camera.reliability, camera.durability) == (
        QosReliability.BEST_EFFORT,
        QosDurability.VOLATILE,
    )
    assert camera.deadline == QosTime(9_223_372_036, 854_775_807)  # infinite, as rosbag2 writes
    assert sorted(q.reliability.name for q in offered["/camera/camera_info"]) == [
        "BEST_EFFORT",
        "RELIABLE",
    ]
    (latched,) = offered["/armourcam/report"]
    assert (latched.reliability, latched.durability) == (
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
    )
