"""ROS 2 node ``pose_estimator``: per-frame detections + camera -> per-frame 3-D fiducial poses.

A thin shell around the pose estimator's core (paper section 4): decode the detector's
``FiducialDetectionRecord`` cloud, estimate each fiducial's position, normal and covariance in
the camera frame, publish them as ``FiducialPoseRecord`` rows and, for viewers, as a PoseArray.
Output headers are the input's (the image's stamp and frame_id). Records go to the vectorised
core as columns and back (:func:`armourcam.records.estimate_pose_records`), without
per-fiducial objects: the same numbers as :func:`pose_estimator.estimate` on the decoded
detections, a few milliseconds sooner on the frame's critical path.

Topics
------
Default names are relative: they resolve in the node's namespace (``-r __ns:=/cell2``:
``/cell2/armourcam/poses``; without one ``/armourcam/poses``). ``/diagnostics`` is absolute.

Subscribed
    ``detections_topic`` (default ``armourcam/detections``), ``sensor_msgs/PointCloud2``
    (FiducialDetectionRecord rows), QoS per ``qos`` (``reliable`` / ``sensor_data``),
    KEEP_LAST ``queue_depth``.
    ``camera_info_topic`` (default ``camera/camera_info``), ``sensor_msgs/CameraInfo``, same
    QoS; not subscribed when ``calibration_file`` is set (camera_calibration YAML).
Published
    ``poses_topic`` (default ``armourcam/poses``), ``sensor_msgs/PointCloud2`` of
    ``FiducialPoseRecord`` rows (mm, camera optical frame), QoS as the input.
    ``pose_array_topic`` (default ``armourcam/pose_array``), ``geometry_msgs/PoseArray``:
    the same poses for RViz/Foxglove in **metres** (REP 103), orientation = the printed
    target's frame (x its +x axis, where the code's sector 0 starts; z the normal), or, for a
    pose without an axis, the rotation taking +z to the normal; QoS as the input.
    ``/diagnostics``, ``diagnostic_msgs/DiagnosticArray``: frames, drops, repeats, camera
    state, age of the last detections (``last_input_age_s``); WARN while waiting for camera
    info or after a dropped frame, ERROR after a rejected camera info (each problem for 30 s,
    :class:`armourcam.graph.RecentProblems`), WARN while no detections came for more than
    ``stale_after_s`` after earlier ones (a stalled camera, :class:`armourcam.graph.InputAge`).

Detections that arrive before any camera info are held (at most ``pending_limit`` frames, oldest
dropped with a warning) and processed as soon as the camera is known. A frame whose records are
malformed, lies outside the camera's image (a camera info that is not this camera's), or whose
pose estimation fails, is logged and dropped; the node lives on. A frame this process has
already taken (same header stamp and frame_id, among the last 256: the detector's
transient-local history delivered again, a second publisher of the same frames) is not
processed again (``frames_duplicate``).

Parameters: see :data:`PARAMS`. ``diameter_mm`` alone may change at runtime (``ros2 param set
/pose_estimator diameter_mm 7``; an integer is taken as its float, as at start-up; the start-up
rules apply, :func:`armourcam.graph.parameter_problem`). Positions scale with it, so poses
published after a change are not comparable with those before: a displacement baseline the
matcher captured with the old diameter no longer fits, and must be re-captured. The node logs a
WARN saying so, is WARN for 30 s, and its /diagnostics carry ``diameter_mm``,
``diameter_mm_before`` and ``diameter_changed_at`` (node clock, ROS time in seconds, as the
frames' stamps; empty before any change) from then on.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, Pose, PoseArray, Quaternion
from numpy.typing import NDArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, PointCloud2, PointField

from armourcam import records
from armourcam.graph import (
    FrameTimes,
    GraphError,
    InputAge,
    Param,
    RecentProblems,
    RecentStamps,
    declare_parameters,
    merge_status,
    parameter_problem,
    publish_diagnostics,
    record_qos,
    run_node,
    stream_qos,
    worst_level,
)

from .camera import CameraModel
from .errors import CalibrationError
from .orientation import target_frames

PARAMS = (
    Param("detections_topic", "armourcam/detections", "Input: detections (PointCloud2)."),
    Param("camera_info_topic", "camera/camera_info", "Input: sensor_msgs/CameraInfo."),
    Param(
        "calibration_file",
        "",
        "camera_calibration YAML; when set, camera_info_topic is not used.",
    ),
    Param("poses_topic", "armourcam/poses", "Output: FiducialPoseRecord rows (PointCloud2)."),
    Param("pose_array_topic", "armourcam/pose_array", "Output: geometry_msgs/PoseArray (m)."),
    Param(
        "qos",
        "reliable",
        "QoS of inputs and outputs: reliable for replay, sensor_data for a live camera.",
        choices=("reliable", "sensor_data"),
    ),
    Param("queue_depth", 10, "KEEP_LAST depth of input and output queues.", minimum=1),
    Param(
        "diameter_mm",
        7.1,
        "Printed diameter of the fiducials' outer circle, mm. Changeable at runtime, but a change "
        "rescales every position: re-capture the displacement baseline after it.",
        read_only=False,
        minimum=0.1,
    ),
    Param("pending_limit", 100, "Frames held while waiting for camera info.", minimum=1),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics, s.", minimum=0.1),
    Param(
        "stale_after_s",
        5.0,
        "/diagnostics WARN when no detections came for this long after earlier ones, s (0: never).",
        minimum=0.0,
    ),
)

#: The parameters a set_parameters call may change (checked by the start-up rules).
_WRITABLE = {p.name: p for p in PARAMS if not p.read_only}


@dataclass(frozen=True, slots=True)
class PoseNodeConfig:
    """Validated parameters of the node (see :data:`PARAMS`)."""

    detections_topic: str
    camera_info_topic: str
    calibration_file: str
    poses_topic: str
    pose_array_topic: str
    qos: str
    queue_depth: int
    diameter_mm: float
    pending_limit: int
    diagnostics_period_s: float
    stale_after_s: float


def normal_quaternions(normals: np.ndarray) -> np.ndarray:
    """Quaternions ``(x, y, z, w)``, one row per unit vector of ``(n, 3)`` ``normals``: the
    shortest rotation taking +z to it (a half turn about x for -z)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.where(norm > 0, norm, 1.0)
    # q = (z x n, 1 + z.n), normalised; z x n = (-n_y, n_x, 0).
    q = np.column_stack([-n[:, 1], n[:, 0], np.zeros(len(n)), 1.0 + n[:, 2]])
    flip = q[:, 3] < 1e-9
    q[flip] = (1.0, 0.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def frame_quaternions(normals: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Quaternions ``(x, y, z, w)`` of the printed target frames (columns: axis, normal x axis,
    normal; :attr:`pose_estimator.types.FiducialPose.frame`), one row per ``(n, 3)`` normal and
    axis; where an axis is not finite, :func:`normal_quaternions`' instead."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    q = normal_quaternions(n)
    has = np.isfinite(a).all(axis=1)
    if has.any():
        nn = n[has] / np.linalg.norm(n[has], axis=1, keepdims=True)
        q[has] = Rotation.from_matrix(target_frames(nn, a[has])).as_quat()
    return q


def pose_array(header: Any, rows: NDArray[Any]) -> PoseArray:
    """PoseArray (metres) of ``FiducialPoseRecord`` rows (mm); orientation: the printed target's
    frame, or +z turned onto the normal where no axis was measured (:func:`frame_quaternions`)."""
    out = PoseArray(header=header)
    if len(rows) == 0:
        return out
    # Whole columns: per-pose numpy calls would cost more than the messages themselves.
    xyz = (np.column_stack([rows["x"], rows["y"], rows["z"]]) / 1000.0).tolist()
    quat = frame_quaternions(
        np.column_stack([rows["nx"], rows["ny"], rows["nz"]]),
        np.column_stack([rows["ax"], rows["ay"], rows["az"]]),
    ).tolist()
    out.poses = [
        Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
        for (x, y, z), (qx, qy, qz, qw) in zip(xyz, quat, strict=True)
    ]
    return out


class PoseEstimatorNode(Node):
    """Detections + camera in, poses out."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("pose_estimator", **kwargs)
        self.config = PoseNodeConfig(**declare_parameters(self, PARAMS))
        cfg = self.config
        self.camera: CameraModel | None = None
        if cfg.calibration_file:
            try:
                self.camera = CameraModel.from_yaml(cfg.calibration_file)
            except CalibrationError as err:
                raise GraphError(f"pose_estimator: calibration_file: {err}") from err
        qos = stream_qos(cfg.qos, cfg.queue_depth)
        records = record_qos(cfg.qos, cfg.queue_depth)
        self._pub = self.create_publisher(PointCloud2, cfg.poses_topic, records)
        self._pub_array = self.create_publisher(PoseArray, cfg.pose_array_topic, qos)
        self._diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        sub = self.create_subscription(
            PointCloud2, cfg.detections_topic, self._on_detections, records
        )
        if self.camera is None:
            self.create_subscription(CameraInfo, cfg.camera_info_topic, self._on_camera_info, qos)
        self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics)
        self._diameter_mm = cfg.diameter_mm
        self._diameter_before = self._diameter_changed_at = ""
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._parameters_set)
        self._pending: deque[PointCloud2] = deque()
        self.received = self.published = self.dropped = 0
        self.problems = RecentProblems()
        self.frame_times = FrameTimes()
        self.input_age = InputAge("detections", cfg.stale_after_s)
        self.seen = RecentStamps()
        # The camera info topic as resolved (namespace, remaps), also the diagnostics' hardware_id.
        source = cfg.calibration_file or self.resolve_topic_name(cfg.camera_info_topic)
        self._camera_source = source
        self.get_logger().info(  # the names as remapped
            f"poses from {sub.topic_name} with camera from {source} -> {self._pub.topic_name}, "
            f"{self._pub_array.topic_name}"
        )

    def _check_parameters(self, params: list[Any]) -> SetParametersResult:
        """Runtime changes of the writable parameters (``diameter_mm``): the start-up rules."""
        for p in params:
            spec = _WRITABLE.get(p.name)
            problem = None if spec is None else parameter_problem(spec, p.value)
            if problem is not None:
                return SetParametersResult(successful=False, reason=f"{p.name} {problem}")
        return SetParametersResult(successful=True)

    def _parameters_set(self, params: list[Any]) -> None:
        """After a successful change: a new ``diameter_mm`` rescales every position from now on,
        so baselines measured before it are not comparable (WARN, and in /diagnostics)."""
        for p in params:
            if p.name != "diameter_mm" or float(p.value) == self._diameter_mm:
                continue
            old, new = self._diameter_mm, float(p.value)
            self._diameter_mm = new
            self._diameter_before = f"{old:g}"
            self._diameter_changed_at = f"{self.get_clock().now().nanoseconds * 1e-9:.3f}"
            text = (
                f"diameter_mm changed from {old:g} to {new:g} mm at {self._diameter_changed_at}: "
                f"positions from now on are {new / old:.4g} times those before; displacement "
                "baselines measured before the change are not comparable, re-capture the baseline"
            )
            self.problems.report("warn", text)
            self.get_logger().warning(text)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            camera = CameraModel.from_camera_info(
                msg.width, msg.height, msg.k, msg.distortion_model, msg.d
            )
        except CalibrationError as err:
            text = f"camera info rejected: {err}"
            self.problems.report("error", text)
            self.get_logger().error(text, throttle_duration_sec=5.0)
            return
        first = self.camera is None
        self.camera = camera
        if first:
            self.get_logger().info(f"camera {camera.width}x{camera.height} from camera info")
            while self._pending:
                self._process(self._pending.popleft())

    def _on_detections(self, msg: PointCloud2) -> None:
        self.received += 1
        if self.seen.skip_repeat(msg.header, self.get_logger(), "detection frames"):
            return
        self.input_age.received()
        if self.camera is None:
            self._pending.append(msg)
            if len(self._pending) > self.config.pending_limit:
                self._pending.popleft()
                self.dropped += 1
                self.get_logger().warning(
                    "no camera info yet: oldest held frame dropped", throttle_duration_sec=5.0
                )
            return
        self._process(msg)

    def _process(self, msg: PointCloud2) -> None:
        assert self.camera is not None
        t0 = time.perf_counter()
        try:
            recs = records.from_pointcloud2(msg, records.DETECTION)
            rows = records.estimate_pose_records(recs, self.camera, self._diameter_mm)
        except Exception as err:
            self.dropped += 1
            kind = "" if isinstance(err, ValueError) else f"{type(err).__name__}: "
            text = f"frame dropped: {kind}{err}"
            self.problems.report("warn", text)
            self.get_logger().error(text)
            return
        # The PoseArray first: it is what viewers (and the latency budget) wait for.
        self._pub_array.publish(pose_array(msg.header, rows))
        self._pub.publish(
            records.to_pointcloud2(PointCloud2, PointField, msg.header, records.POSE, rows)
        )
        self.published += 1
        self.frame_times.add(1e3 * (time.perf_counter() - t0))

    def _publish_diagnostics(self) -> None:
        cam = f"{self.camera.width}x{self.camera.height}" if self.camera else "waiting"
        # Waiting for the camera is a state (WARN while it lasts); drops and rejected camera
        # infos are events, shown while recent.
        level = self.problems.level()
        message = self.problems.message()
        if self.camera is None:
            level = worst_level(level, "warn")
            message = message or "waiting for camera info"
        level, message = merge_status(self.input_age.status(), (level, message))
        publish_diagnostics(
            self,
            self._diag,
            level=level,
            message=message or "ok",
            hardware_id=self._camera_source,
            values={
                "camera": cam,
                "frames_received": str(self.received),
                "frames_published": str(self.published),
                "frames_dropped": str(self.dropped),
                "frames_pending": str(len(self._pending)),
                "frames_duplicate": str(self.seen.repeats),
                "diameter_mm": f"{self._diameter_mm:g}",
                "diameter_mm_before": self._diameter_before,
                "diameter_changed_at": self._diameter_changed_at,
                **self.input_age.values(),
                **self.problems.values(),
                **self.frame_times.values(),
            },
        )


NODE_CLASS = PoseEstimatorNode


def main(args: list[str] | None = None) -> int:
    """Console script ``pose_estimator``."""
    return run_node(PoseEstimatorNode, args)


if __name__ == "__main__":
    sys.exit(main())
