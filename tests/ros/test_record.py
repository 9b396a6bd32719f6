"""``armourcam record`` over DDS: subscriptions that match each publisher's QoS (a live camera is
best effort), the publishers' QoS in the bag's metadata, topics without publishers left out; the
graph's topics subscribed before their publishers appear (a replay started once the recorder is
ready is recorded whole), messages logged at their publication time (latched history too), the
hall events recorded by default."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rosutil import REPO, Probe, Recorder, armourcam, ignore_sigint, start_armourcam

from armourcam import bagio, graph
from armourcam.commands.record import TOPIC_TYPES
from armourcam.graph import Replayer, event_qos, latched_qos, stream_qos

SESSION = REPO / "bags" / "session_small"


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
    proc = start_armourcam(
        "record",
        "--out",
        str(bag),
        "--inputs",
        "--duration",
        "6",
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
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


def test_up_front_subscriptions_mirror_what_a_replay_offers(probe: Probe) -> None:
    """For each of the graph's topic types, one of the recorder's up-front subscriptions has the
    reliability and durability a replay publishes with: matched at once, history included."""

    def key(q: Any) -> tuple[Any, Any]:
        return q.reliability, q.durability

    replayer = Replayer(probe.node)
    for msgtype in set(TOPIC_TYPES.values()):
        ours = {key(graph._recording_qos([q])) for q in graph._expected_offers(msgtype)}
        # The matcher's markers are latched, and so recorded and republished.
        offered = replayer.qos(msgtype, latched=msgtype.endswith("/MarkerArray"))
        assert key(offered) in ours, msgtype


def test_a_replay_waiting_for_the_recorder_is_recorded_whole(
    probe: Probe, tmp_path: Path, recorder: Callable[..., Recorder]
) -> None:
    """The session bag replayed into a recorder started just before it: with ``--wait-for
    armourcam/recorder_ready`` every topic's count and the order of all messages are the bag's.
    A viewer of the camera (standing in for a running graph) satisfies the replay's own wait for
    subscribers, so only the handshake waits for the recorder."""
    from sensor_msgs.msg import CameraInfo, CompressedImage

    for cls, topic in (
        (CompressedImage, "/camera/image_raw/compressed"),
        (CameraInfo, "/camera/camera_info"),
    ):
        probe.node.create_subscription(cls, topic, lambda _: None, stream_qos("reliable", 100))
    rec = recorder(tmp_path / "rec", "--inputs")
    wait = ("--wait-for", graph.RECORDER_READY_TOPIC, "--wait-subscribers", "30")
    out = armourcam("replay", str(SESSION), "--rate", "10", "--linger", "1", *wait)
    assert out.returncode == 0, out.stderr
    assert "no subscriber yet" not in out.stderr  # it did wait for the recorder
    assert rec.wait_ready(0.0), rec.lines
    counts = rec.stop()

    def contents(bag: Path) -> tuple[dict[str, int], list[str]]:
        with bagio.open_bag(bag) as b:
            return {t: i.count for t, i in b.topics.items()}, [
                m.topic for m in b.messages(deserialize=False)
            ]

    want_counts, want_order = contents(SESSION)
    got_counts, got_order = contents(tmp_path / "rec")
    assert got_counts == want_counts, counts
    assert got_order == want_order  # logged at publication: hall events between their frames


def test_a_publisher_appearing_after_ready_loses_no_frame(
    probe: Probe, tmp_path: Path, recorder: Callable[..., Recorder]
) -> None:
    """A camera started after the recorder publishes at once (no wait for subscribers): once it
    has discovered the recorder's subscription, already in the graph, every frame is recorded.
    (A recorder subscribing only after discovering the publisher lost the first frames.)"""
    from sensor_msgs.msg import Image

    rec = recorder(tmp_path / "rec", "--inputs")
    assert rec.wait_ready(), rec.lines
    # Subscribed before any publisher exists: a publisher created now matches it at once.
    assert probe.spin_until(lambda: probe.node.count_subscribers("/camera/image_raw") > 0, 10.0)
    camera = probe.node.create_publisher(Image, "/camera/image_raw", stream_qos("reliable", 100))
    n_frames = 30
    for k in range(n_frames):
        camera.publish(Image(height=4, width=6, encoding="mono8", step=6, data=bytes([k]) * 24))
        probe.spin_for(0.02)
    probe.spin_for(1.0)
    counts = rec.stop()
    assert f"/camera/image_raw: {n_frames}" in counts, counts
    with bagio.open_bag(tmp_path / "rec") as b:
        firsts = [bytes(m.message.data)[0] for m in b.messages(["/camera/image_raw"])]
    assert firsts == list(range(n_frames))


def test_latched_history_is_logged_when_it_was_published(
    probe: Probe, tmp_path: Path, recorder: Callable[..., Recorder]
) -> None:
    """Hall events published (latched) a second before the recorder started are logged at their
    publication time, not when the recorder received them, and in their order, before a live
    event; each is written once although two subscriptions (transient-local and volatile)
    deliver the live one."""
    from std_msgs.msg import Bool, String

    node = probe.node
    run_id = node.create_publisher(String, "/hall/run_id", event_qos())
    run_active = node.create_publisher(Bool, "/hall/run_active", event_qos())
    published: list[tuple[int, int]] = []  # wall clock just before and after each publication

    def publish(pub: Any, msg: Any) -> None:
        before = time.time_ns()
        pub.publish(msg)
        published.append((before, time.time_ns()))

    publish(run_id, String(data="wave-001"))
    publish(run_active, Bool(data=True))
    probe.spin_for(1.0)  # received at least a second later
    t_start = time.time_ns()
    rec = recorder(tmp_path / "rec", "hall/run_id", "hall/run_active")
    assert rec.wait_ready(), rec.lines

    def matched() -> bool:  # by both of the recorder's readers of each topic
        return min(run_id.get_subscription_count(), run_active.get_subscription_count()) >= 2

    assert probe.spin_until(matched, 10.0)  # slow discovery of a busy machine is not the point
    publish(run_active, Bool(data=False))
    probe.spin_for(1.0)
    counts = rec.stop()
    with bagio.open_bag(tmp_path / "rec") as b:
        got = [(m.topic, m.message.data, m.timestamp_ns) for m in b.messages()]
    assert [(topic, data) for topic, data, _ in got] == [
        ("/hall/run_id", "wave-001"),
        ("/hall/run_active", True),
        ("/hall/run_active", False),
    ], (counts, rec.lines)
    for (_, _, t_ns), (before, after) in zip(got, published, strict=True):
        assert before <= t_ns <= after
    assert got[1][2] < t_start


def test_a_recorder_started_with_sigint_ignored_stops_cleanly_on_sigint(
    probe: Probe, tmp_path: Path, recorder: Callable[..., Recorder]
) -> None:
    """Started with SIGINT ignored (``armourcam record &`` from a script), the recorder still
    stops on SIGINT, as rclpy's handler takes it: it used to end with a traceback (its context
    shut down under it, no KeyboardInterrupt); now with status 0, its counts and a whole bag."""
    from std_msgs.msg import String

    run_id = probe.node.create_publisher(String, "/hall/run_id", event_qos())
    run_id.publish(String(data="wave-007"))
    rec = recorder(tmp_path / "rec", "hall/run_id", preexec_fn=ignore_sigint)
    assert rec.wait_ready(), rec.lines
    assert probe.spin_until(lambda: run_id.get_subscription_count() >= 1, 10.0)
    probe.spin_for(1.0)
    counts = rec.stop()  # SIGINT; asserts status 0
    assert "/hall/run_id: 1" in counts, (counts, rec.lines)
    with bagio.open_bag(tmp_path / "rec") as b:
        assert [m.message.data for m in b.messages()] == ["wave-007"]


def test_default_topics_include_the_events_in_the_recorders_namespace(
    probe: Probe, tmp_path: Path, recorder: Callable[..., Recorder]
) -> None:
    """Without topics the recording has the hall's run state and id and the baseline command
    (what ``armourcam analyze`` needs), named as the matcher's relative defaults resolve in the
    namespace (``/cell2/hall/run_id``), not another feed's ``/hall/run_id``."""
    from std_msgs.msg import Bool, Empty, String

    node = probe.node
    run_id = node.create_publisher(String, "/cell2/hall/run_id", event_qos())
    run_active = node.create_publisher(Bool, "/cell2/hall/run_active", event_qos())
    other = node.create_publisher(String, "/hall/run_id", event_qos())
    capture = node.create_publisher(
        Empty, "/cell2/armourcam/capture_baseline", stream_qos("reliable", 10)
    )
    run_id.publish(String(data="wave-007"))
    run_active.publish(Bool(data=True))
    other.publish(String(data="not this cell"))
    rec = recorder(tmp_path / "rec", "--ros-args", "-r", "__ns:=/cell2")
    assert rec.wait_ready(), rec.lines
    pubs = (run_id, run_active, capture)
    assert probe.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs), 10.0)
    capture.publish(Empty())
    run_active.publish(Bool(data=False))
    probe.spin_for(1.0)
    counts = rec.stop()
    with bagio.open_bag(tmp_path / "rec") as b:
        topics = {t: i.count for t, i in b.topics.items()}
    assert topics == {
        "/cell2/hall/run_id": 1,
        "/cell2/hall/run_active": 2,
        "/cell2/armourcam/capture_baseline": 1,
    }, counts
