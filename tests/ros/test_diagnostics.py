"""``armourcam.graph.publish_diagnostics``: the one /diagnostics builder of the three nodes."""

from __future__ import annotations

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
