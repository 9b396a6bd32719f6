"""ROS 2 node ``displacement_matcher``: holds the baseline, measures every wave run, reports.

A thin shell around :class:`displacement_matcher.session.Session` (the hall-automation state
machine: baseline on command or automatically, wait for the scene to settle after a run, fuse,
match against the baseline and the previous run; paper sections 2.2, 3 steps 5-6 and 5). State
is kept in ``data_dir`` (atomic writes) and a restarted node resumes from it and republishes the
last run's latched outputs, labelled with the frame_id of the frames it last took (kept in
``data_dir`` too). A run settling longer than ``settle_timeout_s`` (a camera stopped right after
the run) is measured on the frames it has, or reported as not measured, instead of waiting for
frames for ever. A pose frame already taken (same header stamp and frame_id, among the last 256:
the history a restarted pose estimator sends again) is ignored (``frames_duplicate``).

Topics
------
Default names are relative: they resolve in the node's namespace (``-r __ns:=/cell2``:
``/cell2/armourcam/report``; without one ``/armourcam/report``). ``/diagnostics`` is absolute.
The hall topics are relative too: each cell (flume, basin) under its own namespace gets its
own wave-run feed; a hall-wide feed is set with ``-p run_active_topic:=/hall/run_active -p
run_id_topic:=/hall/run_id``.

Subscribed
    ``poses_topic`` (default ``armourcam/poses``), ``sensor_msgs/PointCloud2`` of
    ``FiducialPoseRecord`` rows, QoS per ``qos`` (``reliable`` / ``sensor_data``), KEEP_LAST
    ``queue_depth``.
    ``run_active_topic`` (default ``hall/run_active``), ``std_msgs/Bool``;
    ``run_id_topic`` (default ``hall/run_id``), ``std_msgs/String``;
    ``capture_baseline_topic`` (default ``armourcam/capture_baseline``), ``std_msgs/Empty``.
    Run state and id: each subscribed twice, RELIABLE + TRANSIENT_LOCAL, depth 10 (a restarted
    node is told the hall's latched state; of the messages published before the node started
    only the latest state is applied, so finished runs are not measured twice) and RELIABLE +
    VOLATILE (a hall publishing volatile, which a transient-local reader never matches); a
    message both deliver is applied once. The capture command: RELIABLE, VOLATILE (a restart
    never re-captures).
Published (latched: RELIABLE + TRANSIENT_LOCAL, depth 1, so a late subscriber gets the last run)
    ``markers_topic`` (default ``armourcam/markers``), ``visualization_msgs/MarkerArray``:
    arrows baseline -> current in **metres** (REP 103), green for same-code, red for cross-code
    matches, and a text label per unit (id and displacement in mm); namespace ``armourcam``,
    frame the camera's.
    ``displacements_topic`` (default ``armourcam/displacements``), ``sensor_msgs/PointCloud2``
    of ``DisplacementRecord`` rows (cumulative, mm).
    ``report_topic`` (default ``armourcam/report``), ``std_msgs/String``: the run report as
    JSON (the keys of ``armourcam compare --json`` plus ``run_id``, ``sequence``, ``settled``,
    ``frames_fused``, ``incremental``).
    ``baseline_topic`` (default ``armourcam/baseline``), ``sensor_msgs/PointCloud2`` of the
    fused baseline's ``FiducialPoseRecord`` rows.
    ``/diagnostics``, ``diagnostic_msgs/DiagnosticArray`` (reliable, volatile) every
    ``diagnostics_period_s`` and on every state change: phase, run, baseline, counts. ERROR
    while files could not be saved to ``data_dir`` (kept in memory, retried at every save) and
    for 30 s after a run's error, WARN before the baseline and for 30 s after a warning or a
    dropped frame (:class:`armourcam.graph.RecentProblems`), and WARN while no pose frame came
    for more than ``stale_after_s`` after earlier ones (``last_input_age_s``,
    :class:`armourcam.graph.InputAge`).

Parameters: see :data:`PARAMS`.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Bool, Empty, Header, String
from visualization_msgs.msg import Marker, MarkerArray

from armourcam import records
from armourcam.graph import (
    GraphError,
    InputAge,
    Param,
    RecentProblems,
    RecentStamps,
    declare_parameters,
    event_qos,
    latched_qos,
    merge_status,
    publish_diagnostics,
    record_qos,
    run_node,
    stamp_seconds,
    stream_qos,
    worst_level,
)

from .errors import MatcherError
from .markers import Comparer, displacement_records
from .session import (
    BaselineCaptured,
    Event,
    MarkerSpec,
    Notice,
    Phase,
    RunCompleted,
    RunRecord,
    Session,
    SessionConfig,
    SessionError,
)
from .units import load_unit_map

PARAMS = (
    Param("poses_topic", "armourcam/poses", "Input: per-frame FiducialPoseRecord rows."),
    # Hall topics are relative like the rest: a cell in its own namespace (``__ns:=/cell2``)
    # follows its own flume's runs; a hall-wide feed is named absolute (``/hall/run_active``).
    Param("run_active_topic", "hall/run_active", "Input: hall run state (std_msgs/Bool)."),
    Param("run_id_topic", "hall/run_id", "Input: hall run id (std_msgs/String)."),
    Param(
        "capture_baseline_topic",
        "armourcam/capture_baseline",
        "Input: capture-baseline command (std_msgs/Empty).",
    ),
    Param("markers_topic", "armourcam/markers", "Output (latched): MarkerArray, metres."),
    Param(
        "displacements_topic",
        "armourcam/displacements",
        "Output (latched): DisplacementRecord rows (PointCloud2), mm.",
    ),
    Param("report_topic", "armourcam/report", "Output (latched): run report JSON (String)."),
    Param("baseline_topic", "armourcam/baseline", "Output (latched): baseline pose rows."),
    Param(
        "qos",
        "reliable",
        "QoS of the pose input: reliable for replay, sensor_data for a live camera.",
        choices=("reliable", "sensor_data"),
    ),
    Param("queue_depth", 10, "KEEP_LAST depth of the pose input.", minimum=1),
    Param(
        "data_dir",
        "armourcam_data",
        "Directory keeping the baseline and every run's report (resumed on restart).",
    ),
    Param("baseline_frames", 5, "Settled frames fused into the baseline.", minimum=1),
    Param("settle_frames", 3, "Consecutive settled frames required after a run.", minimum=1),
    Param(
        "settle_tolerance_mm",
        0.5,
        "Largest frame-to-frame fiducial movement of a settled scene, mm.",
        minimum=1e-6,
    ),
    Param(
        "settle_fraction",
        0.9,
        "Fraction of fiducials that must agree between consecutive frames.",
        minimum=1e-6,
    ),
    Param(
        "settle_timeout_frames",
        50,
        "Frames after a run after which the scene is taken as it is (report says settled=false).",
        minimum=1,
    ),
    Param(
        "settle_timeout_s",
        120.0,
        "Seconds after a run's stop after which it is measured on the frames it has, or reported "
        "as not measured when none came (0: no time bound).",
        minimum=0.0,
    ),
    Param("auto_baseline", True, "Capture the baseline automatically before the first run."),
    Param("dn_mm", 20.5, "Nominal armour-unit size Dn, mm.", minimum=1e-3),
    Param(
        "displaced_dn",
        1.0,
        "A unit that moved at least this many Dn counts as displaced.",
        minimum=1e-3,
    ),
    Param(
        "section_width_mm",
        0.0,
        "Width of the observed section across the slope, mm, for N_od (0: not reported).",
        minimum=0.0,
    ),
    Param(
        "unit_map_file",
        "",
        "Unit map YAML (unit id -> codes [, positions]); empty: template learned from baseline.",
    ),
    Param(
        "frame_id",
        "",
        "frame_id of the outputs when no pose frame was seen, now or by an earlier process on the "
        "same data_dir (default: none).",
    ),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics, s.", minimum=0.1),
    Param(
        "stale_after_s",
        5.0,
        "/diagnostics WARN when no pose frame came for this long after earlier ones, s (0: never).",
        minimum=0.0,
    ),
)


@dataclass(frozen=True, slots=True)
class MatcherNodeConfig:
    """Validated parameters of the node (see :data:`PARAMS`)."""

    poses_topic: str
    run_active_topic: str
    run_id_topic: str
    capture_baseline_topic: str
    markers_topic: str
    displacements_topic: str
    report_topic: str
    baseline_topic: str
    qos: str
    queue_depth: int
    data_dir: str
    baseline_frames: int
    settle_frames: int
    settle_tolerance_mm: float
    settle_fraction: float
    settle_timeout_frames: int
    settle_timeout_s: float
    auto_baseline: bool
    dn_mm: float
    displaced_dn: float
    section_width_mm: float
    unit_map_file: str
    frame_id: str
    diagnostics_period_s: float
    stale_after_s: float

    def session_config(self) -> SessionConfig:
        """The state machine's settings."""
        return SessionConfig(
            baseline_frames=self.baseline_frames,
            settle_frames=self.settle_frames,
            settle_tolerance_mm=self.settle_tolerance_mm,
            settle_fraction=self.settle_fraction,
            settle_timeout_frames=self.settle_timeout_frames,
            settle_timeout_s=self.settle_timeout_s,
            auto_baseline=self.auto_baseline,
            data_dir=Path(self.data_dir) if self.data_dir else None,
        )


_GREEN = (0.1, 0.85, 0.2)
_RED = (0.95, 0.1, 0.1)


def marker_array(header: Header, specs: tuple[MarkerSpec, ...]) -> MarkerArray:
    """MarkerArray (metres) of marker specs (mm); starts with a DELETEALL so old arrows vanish."""
    out = MarkerArray()
    clear = Marker(header=header, ns="armourcam", id=0, action=Marker.DELETEALL)
    out.markers.append(clear)
    for i, spec in enumerate(specs, start=1):
        m = Marker(header=header, ns="armourcam", id=i, action=Marker.ADD)
        m.pose.orientation.w = 1.0
        if spec.kind == "arrow":
            from geometry_msgs.msg import Point

            m.type = Marker.ARROW
            m.points = [
                Point(x=spec.start_mm[0] / 1e3, y=spec.start_mm[1] / 1e3, z=spec.start_mm[2] / 1e3),
                Point(x=spec.end_mm[0] / 1e3, y=spec.end_mm[1] / 1e3, z=spec.end_mm[2] / 1e3),
            ]
            m.scale.x, m.scale.y, m.scale.z = 0.0006, 0.0012, 0.0015  # shaft, head dia, head len
            r, g, b = _GREEN if spec.same_code else _RED
        else:
            m.type = Marker.TEXT_VIEW_FACING
            m.pose.position.x = spec.start_mm[0] / 1e3
            m.pose.position.y = spec.start_mm[1] / 1e3
            m.pose.position.z = spec.start_mm[2] / 1e3
            m.scale.z = 0.006
            m.text = spec.text
            r, g, b = (1.0, 1.0, 1.0)
        m.color.r, m.color.g, m.color.b, m.color.a = r, g, b, 1.0
        out.markers.append(m)
    return out


class DisplacementMatcherNode(Node):
    """Poses and hall events in; latched report, markers and displacements out."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("displacement_matcher", **kwargs)
        self.config = MatcherNodeConfig(**declare_parameters(self, PARAMS))
        cfg = self.config
        try:
            unit_map = load_unit_map(cfg.unit_map_file) if cfg.unit_map_file else None
            comparer = Comparer(
                dn_mm=cfg.dn_mm,
                displaced_dn=cfg.displaced_dn,
                section_width_mm=cfg.section_width_mm or None,
                unit_map=unit_map,
            )
            self.session = Session(cfg.session_config(), compare=comparer)
        except (SessionError, MatcherError) as err:
            raise GraphError(f"displacement_matcher: {err}") from err
        self.input_age = InputAge("pose frame", cfg.stale_after_s)
        self.seen = RecentStamps()
        latched = latched_qos()
        self._pub_markers = self.create_publisher(MarkerArray, cfg.markers_topic, latched)
        self._pub_disp = self.create_publisher(PointCloud2, cfg.displacements_topic, latched)
        self._pub_report = self.create_publisher(String, cfg.report_topic, latched)
        self._pub_baseline = self.create_publisher(PointCloud2, cfg.baseline_topic, latched)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        qos = record_qos(cfg.qos, cfg.queue_depth)
        poses = self.create_subscription(PointCloud2, cfg.poses_topic, self._on_poses, qos)
        self.get_logger().info(  # the names as remapped, as the other nodes say theirs
            f"matching poses from {poses.topic_name} -> {self._pub_disp.topic_name}, "
            f"{self._pub_markers.topic_name}, {self._pub_report.topic_name}"
        )
        # Hall state is latched: a (re)started matcher is told the current state. Events older
        # than this process are history already covered by the resumed session, except the
        # latest state (a run may be in progress): see _apply_history.
        self._start_ns = self.get_clock().now().nanoseconds
        self._historic: dict[str, Any] = {}
        self._historic_timer: Any = None
        # Two subscriptions per hall topic: transient-local for the latched state of a hall that
        # latches, volatile for a hall that does not (a transient-local reader never matches a
        # volatile writer). A message both deliver is applied once (_first_delivery).
        self._delivered: deque[tuple[str, int]] = deque(maxlen=64)
        for qos in (event_qos(), stream_qos("reliable", 10)):
            self.create_subscription(Bool, cfg.run_active_topic, self._on_run_active, qos)
            self.create_subscription(String, cfg.run_id_topic, self._on_run_id, qos)
        # A command is not state: volatile, so a restart never re-captures the baseline.
        self.create_subscription(
            Empty, cfg.capture_baseline_topic, self._on_capture, stream_qos("reliable", 10)
        )
        self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics)
        # settle_timeout_s must end a settling run even when no frame comes.
        self.create_timer(1.0, self._tick)
        self.problems = RecentProblems()
        s = self.session
        if s.baseline is not None:
            self.get_logger().info(
                f"resumed from {cfg.data_dir}: baseline of {len(s.baseline.poses)} fiducials, "
                f"{s.runs_completed} runs"
            )
            self._publish_baseline()
        if s.runs:
            self._publish_run(s.runs[-1])
        self._publish_diagnostics()

    # ------------------------------------------------------------------ callbacks

    def _on_poses(self, msg: PointCloud2) -> None:
        if self.seen.skip_repeat(msg.header, self.get_logger(), "pose frames"):
            return
        self.input_age.received()
        try:
            poses = records.records_to_poses(records.from_pointcloud2(msg, records.POSE))
        except Exception as err:  # a malformed frame must not take the node down
            self.session.frames_dropped += 1
            text = f"pose frame dropped: {err}"
            self.problems.report("warn", text)
            self.get_logger().error(text)
            return
        self._handle(
            self.session.add_frame(
                poses,
                stamp_seconds(msg.header.stamp),
                frame_id=msg.header.frame_id,
                now_s=time.monotonic(),
            )
        )

    def _tick(self) -> None:
        events = self.session.tick(time.monotonic())
        if events:
            self._handle(events)

    def _is_history(self, info: Any, key: str, value: Any) -> bool:
        """Keep the latest pre-start hall message instead of replaying the whole history."""
        source_ns = int(info["source_timestamp"])
        if source_ns >= self._start_ns:
            return False
        self._historic[key] = (value, source_ns)
        if self._historic_timer is None:
            self._historic_timer = self.create_timer(0.5, self._apply_history)
        return True

    def _apply_history(self) -> None:
        if self._historic_timer is not None:
            self._historic_timer.cancel()
            self.destroy_timer(self._historic_timer)
            self._historic_timer = None
        events: list[Event] = []
        if "run_id" in self._historic:
            events += self.session.set_run_id(self._historic["run_id"][0])
        if "active" in self._historic:
            active, source_ns = self._historic["active"]
            # A run in progress: the coming stop must be measured. A stop published while this
            # node was down ends the run it resumed from data_dir (else that run would wait for
            # a stop already given, and the next run id would rename it).
            if active or self.session.phase == Phase.RUN_ACTIVE:
                events += self.session.set_run_active(
                    active, source_ns * 1e-9, now_s=time.monotonic()
                )
        self._historic.clear()
        if events:
            self._handle(events)

    def _first_delivery(self, topic: str, info: Any) -> bool:
        """False for a hall message already taken from the other subscription of its topic."""
        key = (topic, int(info["source_timestamp"]))
        if key in self._delivered:
            return False
        self._delivered.append(key)
        return True

    def _on_run_active(self, msg: Bool, info: Any) -> None:
        if not self._first_delivery("active", info):
            return
        if self._is_history(info, "active", bool(msg.data)):
            return
        self._apply_history()  # history first: it happened before this live event
        # The hall's own publication time orders the event against the frames' stamps.
        stamp = int(info["source_timestamp"]) * 1e-9
        self._handle(self.session.set_run_active(bool(msg.data), stamp, now_s=time.monotonic()))

    def _on_run_id(self, msg: String, info: Any) -> None:
        if not self._first_delivery("run_id", info):
            return
        if self._is_history(info, "run_id", msg.data):
            return
        self._apply_history()
        self._handle(self.session.set_run_id(msg.data))

    def _on_capture(self, _msg: Empty) -> None:
        self._handle(self.session.capture_baseline())

    # ------------------------------------------------------------------ outputs

    def _handle(self, events: list[Event]) -> None:
        log = self.get_logger()
        changed = False
        for ev in events:
            changed = True
            if isinstance(ev, Notice):
                # One call site per severity: rclpy's logger refuses a severity change per site.
                if ev.level == "error":
                    log.error(ev.text)
                    self.problems.report("error", ev.text)
                elif ev.level == "warn":
                    log.warning(ev.text)
                    self.problems.report("warn", ev.text)
                else:
                    log.info(ev.text)
            elif isinstance(ev, BaselineCaptured):
                b = ev.baseline
                log.info(
                    f"baseline ({b.reason}): {len(b.poses)} fiducials fused over "
                    f"{b.n_frames} frames"
                )
                self._publish_baseline()
            elif isinstance(ev, RunCompleted):
                summary = ev.run.report.get("summary", {})
                text = summary.get("text") or ev.run.report.get("error", "")
                log.info(f"run {ev.run.run_id} measured: {text}")
                try:
                    self._publish_run(ev.run)
                except Exception as err:  # the report is on disk; stay up
                    text = f"run {ev.run.run_id}: publishing failed: {err}"
                    self.problems.report("error", text)
                    log.error(text)
        if changed:
            self._publish_diagnostics()

    def _header(self) -> Header:
        h = Header(frame_id=self.session.frame_id or self.config.frame_id)
        h.stamp = self.get_clock().now().to_msg()
        return h

    def _publish_baseline(self) -> None:
        b = self.session.baseline
        if b is None:
            return
        rows = records.poses_to_records(list(b.poses))
        self._pub_baseline.publish(
            records.to_pointcloud2(PointCloud2, PointField, self._header(), records.POSE, rows)
        )

    def _publish_run(self, run: RunRecord) -> None:
        header = self._header()
        self._pub_markers.publish(marker_array(header, run.markers))
        cloud_rows = displacement_records(run.rows)
        self._pub_disp.publish(
            records.to_pointcloud2(
                PointCloud2, PointField, header, records.DISPLACEMENT, cloud_rows
            )
        )
        self._pub_report.publish(String(data=json.dumps(run.report, default=_json_default)))

    def _publish_diagnostics(self) -> None:
        phase = self.session.phase
        # States (no baseline yet, files not saved) last as long as they hold; problems
        # (errors of a run, dropped frames) show while recent.
        level, message = self.problems.level(), self.problems.message()
        unsaved = self.session.unsaved_paths
        if unsaved:
            level, message = "error", f"{len(unsaved)} files not saved to {self.config.data_dir}"
        elif phase in (Phase.WAITING_BASELINE, Phase.CAPTURING_BASELINE):
            level = worst_level(level, "warn")
        level, message = merge_status((level, message), self.input_age.status())
        publish_diagnostics(
            self,
            self._pub_diag,
            level=level,
            message=message or phase.value,
            hardware_id="armourcam",
            values={
                **self.session.status(),
                "frames_duplicate": str(self.seen.repeats),
                **self.input_age.values(),
                **self.problems.values(),
            },
        )


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, float) and math.isnan(obj):
        return None
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


NODE_CLASS = DisplacementMatcherNode


def main(args: list[str] | None = None) -> int:
    """Console script ``displacement_matcher``."""
    return run_node(DisplacementMatcherNode, args)


if __name__ == "__main__":
    sys.exit(main())
