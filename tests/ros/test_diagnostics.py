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
