"""``armourcam.graph.publish_diagnostics``: the one /diagnostics builder of the three nodes."""

from __future__ import annotations

import time
from typing import Any

import pytest

pytestmark = pytest.mark.ros


class _Node:
    """The two methods of ``rclpy.node.Node`` the builder uses."""

    def __init__(self) -> None:
        from rclpy.clock import Clock

        self._clock = Clock()

    def get_name(self) -> str:
        return "pose_estimator"

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
    assert status.name == "armourcam: pose_estimator"
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
