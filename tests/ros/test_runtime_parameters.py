"""Runtime parameter changes over the parameter services: the pose estimator's ``diameter_mm``."""

from __future__ import annotations

import math
import time
from pathlib import Path

from rosutil import Nodes, Probe, ideal_calibration


def test_diameter_change_takes_an_integer_and_warns_that_baselines_are_stale(
    nodes: Nodes, probe: Probe, tmp_path: Path
) -> None:
    """``ros2 param set /pose_estimator diameter_mm 7`` sends an INTEGER: taken as 7.0 (as at
    start-up), not refused as the wrong type. The change is logged as a WARN saying that
    baselines measured before it are not comparable, the status is WARN, and /diagnostics carry
    the diameter, the one before and when it changed. Values the start-up rules refuse are
    refused at runtime too, with the parameter named."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from rcl_interfaces.msg import ParameterType, ParameterValue

    calibration = ideal_calibration(tmp_path)
    statuses = probe.statuses("pose_estimator")
    values = statuses.values  # the latest status's
    nodes.start(
        "pose_estimator",
        params={"calibration_file": str(calibration), "diagnostics_period_s": 0.2},
    )

    assert probe.spin_until(lambda: values().get("diameter_mm") == "7.1", 20.0), nodes.log(
        "pose_estimator"
    )
    assert values()["diameter_changed_at"] == "" and values()["diameter_mm_before"] == ""
    assert statuses[-1].level == DiagnosticStatus.OK, statuses[-1]

    node = "/pose_estimator"
    before = time.time()
    seven = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=7)
    result = probe.set_parameter(node, "diameter_mm", seven)
    assert result.successful, result.reason
    value = probe.get_parameter(node, "diameter_mm")
    assert value.type == ParameterType.PARAMETER_DOUBLE and value.double_value == 7.0

    assert probe.spin_until(lambda: values().get("diameter_mm") == "7", 10.0), statuses[-1:]
    v = values()
    assert v["diameter_mm_before"] == "7.1"
    assert before - 1.0 <= float(v["diameter_changed_at"]) <= time.time() + 1.0
    assert statuses[-1].level == DiagnosticStatus.WARN
    assert "re-capture the baseline" in statuses[-1].message
    log = nodes.log("pose_estimator")
    (line,) = [s for s in log.splitlines() if "diameter_mm changed" in s]
    assert "[WARN]" in line and "from 7.1 to 7 mm" in line, log
    assert "baselines measured before the change are not comparable" in line

    # The same value again is no change: no second warning.
    assert probe.set_parameter(node, "diameter_mm", seven).successful
    probe.spin_for(0.5)
    assert nodes.log("pose_estimator").count("diameter_mm changed") == 1

    # Refused as at start-up (the minimum, finiteness), and a string by rclpy's type check.
    for bad, reason in (
        (ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=0), ">= 0.1"),
        (ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=math.nan), "finite"),
        (ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=math.inf), "finite"),
        (ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="7"), "type"),
    ):
        result = probe.set_parameter(node, "diameter_mm", bad)
        assert not result.successful and reason in result.reason, (bad, result.reason)
    assert probe.get_parameter(node, "diameter_mm").double_value == 7.0
    assert nodes.alive("pose_estimator")
