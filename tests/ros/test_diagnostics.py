"""``armourcam.graph.publish_diagnostics``: the one /diagnostics builder of the three nodes."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matcherutil import header
from rosutil import ideal_calibration

pytestmark = pytest.mark.ros


class _Node:
    """The methods of ``rclpy.node.Node`` the builder uses (a node in namespace ``/cell2``)."""

    def __init__(self) -> None:
        from rclpy.clock import Clock

        self._clock = Clock()

    def get_name(self) -> str:
        return "pose_estimator"

    def get_fully_qualified_name(self) -> str:
        return "/cell2/pose_estimator"

    def get_clock(self) -> Any:
        return self._clock


class _Publisher:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def publish(self, msg: Any) -> None:
        self.sent.append(msg)


@pytest.mark.parametrize(("level", "code"), [("ok", 0), ("warn", 1), ("error", 2)])
def test_status_carries_level_name_and_values(level: str, code: int) -> None:
    from diagnostic_msgs.msg import DiagnosticStatus

    from armourcam.graph import publish_diagnostics

    pub = _Publisher()
    values = {"frames_received": "12", "frames_dropped": "1"}
    publish_diagnostics(
        _Node(), pub, level=level, message="m", hardware_id="/camera/camera_info", values=values
    )
    (arr,) = pub.sent
    (status,) = arr.status
    assert status.level == {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN}.get(
        code, DiagnosticStatus.ERROR
    )
    assert status.name == "/cell2/pose_estimator: armourcam"  # diagnostic_updater's node: task
    assert status.hardware_id == "/camera/camera_info" and status.message == "m"
    assert {kv.key: kv.value for kv in status.values} == values
    assert arr.header.stamp.sec > 0


def test_frame_times_are_nearest_rank_percentiles_of_the_recent_window() -> None:
    from armourcam.graph import FrameTimes, GraphError

    times = FrameTimes(window=20)
    assert times.values() == {
        "frame_ms_last": "",
        "frame_ms_p50": "",
        "frame_ms_p95": "",
        "frame_ms_max": "",
        "frame_ms_frames": "0",
    }
    # 1..30 ms: the window keeps the last 20 (11..30), whose nearest-rank p50 is the 10th
    # (20) and p95 the 19th (29).
    for ms in range(1, 31):
        times.add(float(ms))
    values = times.values()
    assert values["frame_ms_last"] == "30.0" and values["frame_ms_max"] == "30.0"
    assert values["frame_ms_p50"] == "20.0" and values["frame_ms_p95"] == "29.0"
    assert values["frame_ms_frames"] == "20"
    with pytest.raises(GraphError, match="window"):
        FrameTimes(window=0)


def test_a_problem_raises_the_level_while_recent_then_the_node_recovers() -> None:
    from armourcam.graph import GraphError, RecentProblems, worst_level

    now = [100.0]
    problems = RecentProblems(hold_s=30.0, clock=lambda: now[0])
    assert (problems.level(), problems.message()) == ("ok", "")
    assert problems.values() == {"last_problem": "", "last_problem_age_s": ""}
    problems.report("warn", "frame 3 dropped: corrupt JPEG")
    now[0] += 10.0
    problems.report("error", "camera info rejected: K is singular")
    now[0] += 25.0  # the warning is 35 s old, the error 25 s
    assert (problems.level(), problems.message()) == (
        "error",
        "camera info rejected: K is singular",
    )
    now[0] += 10.0  # both older than the hold: recovered, the last one still named
    assert (problems.level(), problems.message()) == ("ok", "")
    assert problems.values() == {
        "last_problem": "camera info rejected: K is singular",
        "last_problem_age_s": "35.0",
    }
    problems.report("warn", "frame 9 dropped")
    assert problems.level() == "warn"
    assert worst_level("ok", "warn") == "warn" and worst_level("error", "ok") == "error"
    with pytest.raises(GraphError, match="level"):
        problems.report("ok", "fine")
    with pytest.raises(GraphError, match="hold"):
        RecentProblems(hold_s=0.0)


def test_an_integer_for_a_float_parameter_is_taken_as_that_number(nodes: Any) -> None:
    """``diameter_mm: 7`` (YAML's int) is the number a person means; rclpy alone refuses a
    static double parameter given an integer."""
    nodes.start(
        "pose_estimator", params={"diameter_mm": 7, "diagnostics_period_s": 1}, label="ints"
    )
    deadline = time.monotonic() + 20.0
    while "poses from" not in nodes.log("ints") and time.monotonic() < deadline:
        assert nodes.alive("ints"), nodes.log("ints")
        time.sleep(0.1)
    assert "poses from" in nodes.log("ints") and nodes.alive("ints"), nodes.log("ints")


def test_input_age_warns_only_after_input_came_and_stopped() -> None:
    """Before the first frame: no age, no warning (an idle rig is not a fault). After it: the
    age, and WARN with a message once none came for longer than ``stale_after_s``; 0 never
    warns."""
    from armourcam.graph import GraphError, InputAge, merge_status

    now = [50.0]
    age = InputAge("image", 5.0, clock=lambda: now[0])
    assert age.status() == ("ok", "") and age.values() == {"last_input_age_s": ""}
    now[0] += 100.0  # a rig idle for minutes before the first frame: still no warning
    assert age.status() == ("ok", "")
    age.received()
    now[0] += 5.0
    assert age.status() == ("ok", "") and age.values() == {"last_input_age_s": "5.0"}
    now[0] += 7.5
    level, text = age.status()
    assert level == "warn"
    assert text == "no image for 12.5 s (stale_after_s 5): input stalled or stopped"
    assert age.values() == {"last_input_age_s": "12.5"}
    age.received()  # the camera is back
    assert age.status() == ("ok", "")
    off = InputAge("image", 0.0, clock=lambda: now[0])
    off.received()
    now[0] += 1e6
    assert off.status() == ("ok", "") and off.values()["last_input_age_s"] == "1000000.0"
    with pytest.raises(GraphError, match="stale_after_s"):
        InputAge("image", -1.0)
    # Merged with a node's other state: the worst level, messages most severe first.
    assert merge_status(("warn", "stale"), ("ok", "")) == ("warn", "stale")
    assert merge_status(("warn", "stale"), ("error", "bad K")) == ("error", "bad K; stale")
    assert merge_status(("warn", "a"), ("warn", "b")) == ("warn", "a; b")
    assert merge_status(("ok", ""), ("ok", "")) == ("ok", "")


def test_recent_stamps_recognise_a_frame_seen_again_within_their_memory() -> None:
    from std_msgs.msg import Header

    from armourcam.graph import GraphError, RecentStamps

    def stamped(sec: int, nanosec: int = 0, frame_id: str = "cam") -> Header:
        h = Header(frame_id=frame_id)
        h.stamp.sec, h.stamp.nanosec = sec, nanosec
        return h

    seen = RecentStamps(size=3)
    assert not any(seen.repeated(stamped(s)) for s in (1, 2, 3))
    assert seen.repeated(stamped(2)) and seen.repeats == 1
    assert not seen.repeated(stamped(2, 1))  # one nanosecond apart: another frame
    assert not seen.repeated(stamped(2, frame_id="cam2"))  # another camera, same instant
    # Memory of 3: the oldest frames are forgotten (bounded).
    assert not seen.repeated(stamped(1))
    # An unstamped source (zero stamps) is never taken for repeats.
    assert not seen.repeated(stamped(0)) and not seen.repeated(stamped(0))
    assert seen.repeats == 1
    with pytest.raises(GraphError, match="stamp memory"):
        RecentStamps(size=0)


def _input_publisher(probe: Any, node: str) -> tuple[Any, Any]:
    """A publisher of ``node``'s input in the probe and a function making one frame (now)."""
    from sensor_msgs.msg import Image, PointCloud2, PointField

    from armourcam import image_codec, records
    from armourcam.graph import record_qos, stream_qos

    if node == "fiducial_detector":
        pub = probe.node.create_publisher(Image, "/camera/image_raw", stream_qos("reliable", 10))

        def image() -> Any:
            msg = Image(**image_codec.image_to_msg_fields(np.full((120, 160), 128, np.uint8)))
            msg.header = header(probe.node)
            return msg

        return pub, image
    topic, name, rows = {
        "pose_estimator": (
            "/armourcam/detections",
            records.DETECTION,
            records.detections_to_records([]),
        ),
        "displacement_matcher": ("/armourcam/poses", records.POSE, records.poses_to_records([])),
    }[node]
    pub = probe.node.create_publisher(PointCloud2, topic, record_qos("reliable", 10))
    return pub, lambda: records.to_pointcloud2(
        PointCloud2, PointField, header(probe.node), name, rows
    )


@pytest.mark.parametrize(
    ("node", "what"),
    [
        ("fiducial_detector", "image"),
        ("pose_estimator", "detections"),
        ("displacement_matcher", "pose frame"),
    ],
)
def test_a_stalled_input_turns_the_status_warn_until_frames_come_again(
    nodes: Any, probe: Any, tmp_path: Path, node: str, what: str
) -> None:
    """A camera that stops used to leave every node OK. Each node reports the age of its last
    input frame and is WARN, saying so, once none came for ``stale_after_s``; before the first
    frame it reports what it did before (an idle rig is not a fault)."""
    from diagnostic_msgs.msg import DiagnosticStatus

    params: dict[str, Any] = {"stale_after_s": 1.5, "diagnostics_period_s": 0.2}
    if node == "pose_estimator":
        params["calibration_file"] = str(ideal_calibration(tmp_path))
    if node == "displacement_matcher":
        params |= {"data_dir": str(tmp_path / "data"), "baseline_frames": 2}
    statuses = probe.statuses(node)
    values = statuses.values  # the latest status's
    pub, make_frame = _input_publisher(probe, node)
    nodes.start(node, params=params)

    def latest(pred: Any, timeout: float) -> bool:
        return probe.spin_until(lambda: statuses and pred(statuses[-1], values()), timeout)

    assert probe.spin_until(lambda: pub.get_subscription_count() > 0, 20.0), nodes.log(node)
    probe.spin_for(2.0)  # longer than stale_after_s, but no frame yet: as before
    assert latest(lambda s, v: "last_input_age_s" in v, 5.0), statuses[-1:]
    assert values()["last_input_age_s"] == ""
    assert "stalled" not in statuses[-1].message
    if node != "displacement_matcher":  # the matcher is WARN before its baseline, as before
        assert statuses[-1].level == DiagnosticStatus.OK, statuses[-1]

    for _ in range(3):
        pub.publish(make_frame())
        probe.spin_for(0.1)
    assert latest(
        lambda s, v: (
            v.get("last_input_age_s") not in ("", None)
            and float(v["last_input_age_s"]) < 1.0
            and s.level == DiagnosticStatus.OK
        ),
        10.0,
    ), (statuses[-1:], nodes.log(node))

    # The camera stops.
    assert latest(lambda s, v: s.level == DiagnosticStatus.WARN, 5.0), statuses[-1:]
    assert f"no {what} for " in statuses[-1].message
    assert "stale_after_s 1.5" in statuses[-1].message
    assert float(values()["last_input_age_s"]) >= 1.5  # one decimal: 1.54 s reads 1.5

    pub.publish(make_frame())  # and starts again
    assert latest(lambda s, v: s.level == DiagnosticStatus.OK, 5.0), statuses[-1:]
    assert nodes.alive(node)
