"""A hall and a camera feeding the matcher from the probe, and a late reader of its outputs."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np
from rosutil import Probe

from armourcam import records
from armourcam.graph import event_qos, latched_qos, record_qos
from pose_estimator.types import FiducialPose

POSES = "/armourcam/poses"


def field(n_units: int = 6, origin: Sequence[float] = (-45.0, -20.0, 700.0)) -> np.ndarray:
    """True fiducial centres (mm) of a small field: units of 4 fiducials (codes 0-3, 9 mm apart
    on the unit), units 45 mm apart from ``origin``; fiducial ``i`` is on unit ``i // 4``."""
    offsets = np.array([[0.0, 0.0, 0.0], [9.0, 0.0, 2.0], [0.0, 9.0, -2.0], [9.0, 9.0, 0.0]])
    centres = np.array([(u % 3, u // 3, 0.0) for u in range(n_units)]) * 45.0
    centres += origin
    return (centres[:, None, :] + offsets[None]).reshape(-1, 3)


def header(node: Any, frame_id: str = "cam") -> Any:
    """A Header in ``frame_id`` stamped now by ``node``'s clock."""
    from std_msgs.msg import Header

    h = Header(frame_id=frame_id)
    h.stamp = node.get_clock().now().to_msg()
    return h


def cloud(node: Any, truth: np.ndarray, rng: np.random.Generator, *, frame_id: str = "cam") -> Any:
    """A FiducialPoseRecord cloud of one noisy frame of ``truth`` (mm), stamped now."""
    from sensor_msgs.msg import PointCloud2, PointField

    cov = np.diag([0.02, 0.02, 0.1]) ** 2
    poses = [
        FiducialPose(i % 4, p + rng.normal(0, [0.02, 0.02, 0.1]), np.array([0, 0, -1.0]), cov)
        for i, p in enumerate(truth)
    ]
    rows = records.poses_to_records(poses)
    return records.to_pointcloud2(
        PointCloud2, PointField, header(node, frame_id), records.POSE, rows
    )


class Hall:
    """The hall's automation and a camera feeding pose frames, published from the probe."""

    def __init__(
        self, probe: Probe, *, rng: np.random.Generator | None = None, frame_id: str = "cam"
    ) -> None:
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import Bool, String

        self.probe = probe
        n = probe.node
        self.poses = n.create_publisher(PointCloud2, POSES, record_qos("reliable", 50))
        self.active = n.create_publisher(Bool, "/hall/run_active", event_qos())
        self.run_id = n.create_publisher(String, "/hall/run_id", event_qos())
        self.rng = np.random.default_rng(5) if rng is None else rng
        self.frame_id = frame_id

    def wait_matched(self) -> bool:
        return self.probe.spin_until(lambda: self.poses.get_subscription_count() > 0, 20.0)

    def frames(self, truth: np.ndarray, k: int) -> None:
        for _ in range(k):
            self.poses.publish(cloud(self.probe.node, truth, self.rng, frame_id=self.frame_id))
            self.probe.spin_for(0.05)

    def run(self, run_id: str, after: np.ndarray, settle: int = 3) -> None:
        """A run (its id, then run_active true and false), then ``settle`` frames of ``after``."""
        from std_msgs.msg import Bool, String

        self.run_id.publish(String(data=run_id))
        self.active.publish(Bool(data=True))
        self.probe.spin_for(0.3)
        self.active.publish(Bool(data=False))
        self.probe.spin_for(0.3)
        self.frames(after, settle)


class Latched:
    """A late subscriber to the matcher's latched outputs."""

    def __init__(self, probe: Probe) -> None:
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String
        from visualization_msgs.msg import MarkerArray

        self.reports: list[dict[str, Any]] = []
        self.markers: list[Any] = []
        self.baselines: list[Any] = []
        self.displacements: list[Any] = []
        n = probe.node
        n.create_subscription(
            String,
            "/armourcam/report",
            lambda m: self.reports.append(json.loads(m.data)),
            latched_qos(),
        )
        n.create_subscription(MarkerArray, "/armourcam/markers", self.markers.append, latched_qos())
        n.create_subscription(
            PointCloud2, "/armourcam/baseline", self.baselines.append, latched_qos()
        )
        n.create_subscription(
            PointCloud2, "/armourcam/displacements", self.displacements.append, latched_qos()
        )
