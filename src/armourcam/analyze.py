"""Offline analysis of a bag with the graph's cores, without DDS (``armourcam analyze``).

The bag's messages are taken in log-time order and fed to the same code the nodes run:
:func:`armourcam.image_codec.decode` -> :func:`fiducial_detector.detect` ->
:func:`pose_estimator.estimate` -> :class:`displacement_matcher.session.Session` (hall topics
drive it exactly as on the rig; frames and hall events are ordered by bag log time). Outputs:

- ``DIR/report.json``: ``{"bag", "baseline", "runs": [report, ...], "frames": {...}}`` where each
  run report has the keys of ``armourcam compare --json`` (plus ``run_id``, ``incremental``...);
- ``DIR/runs/<NNNN>-<run_id>/`` per run (``NNNN`` its 1-based sequence, characters of the run id
  other than letters, digits and ``._-`` replaced by ``_``): the files of ``armourcam compare
  --out``, written by the same :func:`displacement_matcher.report.write_report_files` as soon as
  the run is measured: ``report.json`` (the run's report, with ``inputs``: the bag and topics it
  was measured from), ``fiducials.csv``, ``units.csv``, ``plot.png`` (all of the cumulative
  displacement, against the baseline; the incremental one is in ``report.json``) and
  ``overlay.png``, the vectors on the last frame fused into the run's after-set (a run with no
  frame after it has no overlay: no image shows its state);
- ``DIR/markers``: a ROS 2 MCAP bag (Foxglove / RViz) with, per run, the latched
  ``/armourcam/markers`` (``visualization_msgs/MarkerArray``, metres), ``/armourcam/report``
  (``std_msgs/String``) and ``/armourcam/displacements`` (PointCloud2 of DisplacementRecord), and
  per frame ``/armourcam/poses`` (PointCloud2 of FiducialPoseRecord, mm).

rclpy is not used here; message objects are the bag typestore's (rosbags).
"""

from __future__ import annotations

import json
import math
import sys
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from displacement_matcher.atomic import write_atomic
from displacement_matcher.markers import Comparer, displacement_records
from displacement_matcher.report import write_report_files
from displacement_matcher.session import (
    BaselineCaptured,
    Event,
    MarkerSpec,
    Notice,
    RunCompleted,
    RunRecord,
    Session,
    SessionConfig,
)
from pose_estimator.camera import CameraModel

from . import bagio, image_codec, records

BOOL = "std_msgs/msg/Bool"
STRING = "std_msgs/msg/String"
EMPTY = "std_msgs/msg/Empty"


class AnalyzeError(ValueError):
    """The bag lacks what the analysis needs, or a topic choice is ambiguous."""


@dataclass(slots=True)
class AnalysisResult:
    """What :func:`analyze_bag` produced."""

    runs: list[RunRecord] = field(default_factory=list)
    frames: int = 0
    frames_dropped: int = 0
    fiducials_per_frame: list[int] = field(default_factory=list)
    notices: list[str] = field(default_factory=list)
    baseline_fiducials: int | None = None
    topics: dict[str, str] = field(default_factory=dict)
    #: Where the bag stopped being readable (None: read to its end).
    truncation: str | None = None


def _pick_hall(bag: bagio.Bag, given: str | None, msgtype: str, default: str) -> str | None:
    if given:
        if given not in bag.topics:
            raise AnalyzeError(f"{bag.path}: topic {given} is not in the bag")
        if given not in bag.topics_of_type(msgtype):
            raise AnalyzeError(
                f"{bag.path}: topic {given} is {bag.topics[given].msgtype}, not {msgtype}"
            )
        return given
    if default in bag.topics:
        return default
    found = bag.topics_of_type(msgtype)
    return found[0] if len(found) == 1 else None


def analyze_bag(
    bag_path: Path,
    out_dir: Path,
    *,
    image_topic: str | None = None,
    camera_info_topic: str | None = None,
    run_active_topic: str | None = None,
    run_id_topic: str | None = None,
    capture_topic: str | None = None,
    diameter_mm: float = 7.1,
    subpixel: str = "profile",
    calibration: CameraModel | None = None,
    session_config: SessionConfig | None = None,
    comparer: Comparer | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> AnalysisResult:
    """Analyse a bag; write the reports and the markers bag into ``out_dir``.

    Raises
    ------
    AnalyzeError
        No image topic, no camera (neither CameraInfo in the bag nor ``calibration``), or
        ``out_dir`` is a file or a directory that is not empty.
    """
    from fiducial_detector.detect import detect
    from pose_estimator.estimate import estimate

    if not (diameter_mm > 0 and math.isfinite(diameter_mm)):
        raise AnalyzeError(f"diameter must be a positive number of mm, got {diameter_mm}")
    markers_path = out_dir / "markers"
    if markers_path.exists():
        raise AnalyzeError(f"{markers_path} exists; choose an empty output directory")
    if out_dir.exists() and not out_dir.is_dir():
        raise AnalyzeError(f"output {out_dir} is a file, not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        # A report tree written over another report (a compare --out directory, an earlier
        # analysis) would mix the two and overwrite what the user kept.
        raise AnalyzeError(f"output directory {out_dir} is not empty; choose an empty one")
    session = Session(session_config or SessionConfig(), compare=comparer or Comparer())
    result = AnalysisResult()
    with bagio.open_bag(bag_path) as bag:
        img_topic = bag.image_topic(image_topic)
        cam_topic = bag.camera_info_topic(camera_info_topic)
        if cam_topic is None and calibration is None:
            raise AnalyzeError(
                f"{bag_path}: no sensor_msgs/CameraInfo topic; give a calibration file"
            )
        active_topic = _pick_hall(bag, run_active_topic, BOOL, "/hall/run_active")
        id_topic = _pick_hall(bag, run_id_topic, STRING, "/hall/run_id")
        cap_topic = _pick_hall(bag, capture_topic, EMPTY, "/armourcam/capture_baseline")
        if active_topic is None:
            # Without the hall's run state no run starts or ends: the baseline is taken and
            # nothing is compared, and a report of no runs must say why.
            found = bag.topics_of_type(BOOL)
            which = f"several: {', '.join(found)}" if found else "none"
            result.notices.append(
                f"warn: no run-state topic ({BOOL}; {which}) in the bag, so no wave run can be "
                "measured; name one with --run-active-topic"
            )
        result.topics = {
            "image": img_topic,
            "camera_info": cam_topic or "",
            "run_active": active_topic or "",
            "run_id": id_topic or "",
        }
        wanted = [t for t in (img_topic, cam_topic, active_topic, id_topic, cap_topic) if t]
        total = sum(bag.topics[t].count for t in wanted)
        camera = calibration
        # Only now, with the bag's topics checked: a refused request leaves no empty directory.
        out_dir.mkdir(parents=True, exist_ok=True)
        inputs = {"bag": str(bag_path), "topics": dict(result.topics)}
        # The frames last given to the session, by stamp: a run is measured on its last frame
        # or, when the next run's first frame ends its settling, on the one before. Two frames
        # are all the overlay needs to hold.
        recent: deque[tuple[float, Any]] = deque(maxlen=2)
        with bagio.BagWriter(markers_path) as out:
            frame_id = ""

            def handle(events: list[Event], t_ns: int) -> None:
                for ev in events:
                    if isinstance(ev, Notice):
                        result.notices.append(f"{ev.level}: {ev.text}")
                    elif isinstance(ev, BaselineCaptured):
                        result.baseline_fiducials = len(ev.baseline.poses)
                    elif isinstance(ev, RunCompleted):
                        result.runs.append(ev.run)
                        write_run_outputs(out, ev.run, t_ns, frame_id)
                        stamp = ev.run.report.get("stamp_s")
                        after = next((img for t, img in recent if t == stamp), None)
                        write_run_report(out_dir, ev.run, inputs, camera, after)

            for k, m in enumerate(bag.messages(wanted, on_truncation="report")):
                t_s = m.timestamp_ns * 1e-9
                if m.topic == cam_topic and calibration is None:
                    try:
                        camera = bagio.camera_model_from_info(m.message)
                    except ValueError as err:
                        result.notices.append(f"error: camera info {m.index}: {err}")
                elif m.topic == img_topic:
                    result.frames += 1
                    frame_id = str(getattr(m.message.header, "frame_id", "")) or frame_id
                    try:
                        if camera is None:
                            raise AnalyzeError("no camera info before this frame")
                        image = image_codec.decode(m.message)
                        camera.check_image_size(image.shape[1], image.shape[0])
                        dets = detect(image, subpixel=subpixel)  # type: ignore[arg-type]
                        poses = estimate(dets, camera, diameter_mm)
                    except ValueError as err:
                        result.frames_dropped += 1
                        result.notices.append(f"error: frame {result.frames} dropped: {err}")
                        continue
                    result.fiducials_per_frame.append(len(poses))
                    recent.append((t_s, image))
                    out.write_records(
                        "/armourcam/poses",
                        records.POSE,
                        records.poses_to_records(poses),
                        m.timestamp_ns,
                        frame_id=frame_id,
                    )
                    handle(session.add_frame(poses, t_s), m.timestamp_ns)
                elif m.topic == active_topic:
                    handle(session.set_run_active(bool(m.message.data), t_s), m.timestamp_ns)
                elif m.topic == id_topic:
                    handle(session.set_run_id(str(m.message.data)), m.timestamp_ns)
                elif m.topic == cap_topic:
                    handle(session.capture_baseline(), m.timestamp_ns)
                if progress is not None:
                    progress(k + 1, total)
            handle(session.end_of_input(), bag.end_ns if hasattr(bag, "end_ns") else 0)
            if bag.truncation is not None:
                result.truncation = bag.truncation.describe()
                result.notices.append(f"warn: {result.truncation}")
    if session.baseline is not None:
        result.baseline_fiducials = len(session.baseline.poses)
    write_summary_report(out_dir, bag_path, result)
    return result


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if hasattr(obj, "tolist"):
        return _json_safe(obj.tolist())
    return obj


def run_dir(out_dir: Path, run: RunRecord) -> Path:
    """``out_dir/runs/<NNNN>-<run_id>``, the directory of one run's report files."""
    safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in run.run_id)
    return out_dir / "runs" / f"{run.sequence:04d}-{safe}"


def write_run_report(
    out_dir: Path,
    run: RunRecord,
    inputs: dict[str, Any],
    camera: CameraModel | None,
    after_image: Any,
) -> Path:
    """One run's report files in :func:`run_dir` (the files of ``armourcam compare --out``).

    The overlay is drawn on ``after_image`` and written only with an image and a camera.
    """
    # Each run's report stands alone: it names the bag and topics it was measured from.
    doc = _json_safe({**run.report, "inputs": inputs})
    where = run_dir(out_dir, run)
    with_overlay = after_image is not None and camera is not None
    write_report_files(where, doc, camera=camera if with_overlay else None, after_image=after_image)
    return where


def write_summary_report(out_dir: Path, bag_path: Path, result: AnalysisResult) -> None:
    """``out_dir/report.json``: the bag, its topics, frame counts, the baseline and every run."""
    doc = {
        "bag": str(bag_path),
        "topics": result.topics,
        "frames": {
            "total": result.frames,
            "dropped": result.frames_dropped,
            "fiducials_per_frame": result.fiducials_per_frame,
        },
        "baseline": {"fiducials": result.baseline_fiducials},
        "runs": [_json_safe(r.report) for r in result.runs],
        "notices": result.notices,
    }
    write_atomic(out_dir / "report.json", json.dumps(doc, indent=1).encode())


# ---------------------------------------------------------------------- markers bag


def _default(store: Any, msgtype: str) -> Any:
    """A rosbags message of ``msgtype`` with every field zero / empty (rosbags needs them all)."""
    import numpy as np
    from rosbags.typesys.store import Nodetype

    cls = store.types[msgtype]
    _, fields = store.fielddefs[msgtype]
    values: dict[str, Any] = {}
    for name, (kind, detail) in fields:
        if kind == Nodetype.NAME:
            values[name] = _default(store, detail)
        elif kind == Nodetype.BASE:
            typ = detail[0]
            values[name] = "" if typ == "string" else (False if typ == "bool" else 0)
        elif kind == Nodetype.ARRAY:
            (sub_kind, sub), length = detail
            if sub_kind == Nodetype.BASE and sub[0] != "string":
                values[name] = np.zeros(length, dtype=_NP.get(sub[0], np.float64))
            elif sub_kind == Nodetype.NAME:
                values[name] = [_default(store, sub) for _ in range(length)]
            else:
                values[name] = [""] * length
        else:  # sequence
            (sub_kind, sub), _ = detail
            if sub_kind == Nodetype.BASE and sub[0] != "string":
                values[name] = np.zeros(0, dtype=_NP.get(sub[0], np.float64))
            else:
                values[name] = []
    return cls(**values)


_NP = {
    "bool": "bool",
    "int8": "int8",
    "uint8": "uint8",
    "byte": "uint8",
    "char": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}

_GREEN = (0.1, 0.85, 0.2)
_RED = (0.95, 0.1, 0.1)


def marker_array_rosbags(store: Any, header: Any, specs: tuple[MarkerSpec, ...]) -> Any:
    """The node's MarkerArray (``displacement_matcher.node.marker_array``) as rosbags objects."""
    MARKER = "visualization_msgs/msg/Marker"
    point = store.types["geometry_msgs/msg/Point"]
    clear = _default(store, MARKER)
    clear.header, clear.ns, clear.id, clear.action = header, "armourcam", 0, 3  # DELETEALL
    markers = [clear]
    for i, spec in enumerate(specs, start=1):
        m = _default(store, MARKER)
        m.header, m.ns, m.id, m.action = header, "armourcam", i, 0
        m.pose.orientation.w = 1.0
        if spec.kind == "arrow":
            m.type = 0
            m.points = [
                point(x=spec.start_mm[0] / 1e3, y=spec.start_mm[1] / 1e3, z=spec.start_mm[2] / 1e3),
                point(x=spec.end_mm[0] / 1e3, y=spec.end_mm[1] / 1e3, z=spec.end_mm[2] / 1e3),
            ]
            m.scale.x, m.scale.y, m.scale.z = 0.0006, 0.0012, 0.0015
            r, g, b = _GREEN if spec.same_code else _RED
        else:
            m.type = 9  # TEXT_VIEW_FACING
            m.pose.position.x = spec.start_mm[0] / 1e3
            m.pose.position.y = spec.start_mm[1] / 1e3
            m.pose.position.z = spec.start_mm[2] / 1e3
            m.scale.z = 0.006
            m.text = spec.text
            r, g, b = 1.0, 1.0, 1.0
        m.color.r, m.color.g, m.color.b, m.color.a = r, g, b, 1.0
        markers.append(m)
    return store.types["visualization_msgs/msg/MarkerArray"](markers=markers)


def write_run_outputs(out: bagio.BagWriter, run: RunRecord, t_ns: int, frame_id: str) -> None:
    """Write one run's markers, report and displacement records into the markers bag."""
    header = out.header(t_ns, frame_id)
    out.add_topic("/armourcam/markers", "visualization_msgs/msg/MarkerArray", latched=True)
    out.write(
        "/armourcam/markers",
        "visualization_msgs/msg/MarkerArray",
        marker_array_rosbags(out.typestore, header, run.markers),
        t_ns,
    )
    out.add_topic("/armourcam/report", STRING, latched=True)
    out.write_string("/armourcam/report", json.dumps(_json_safe(run.report)), t_ns)
    out.write_records(
        "/armourcam/displacements",
        records.DISPLACEMENT,
        displacement_records(run.rows),
        t_ns,
        frame_id=frame_id,
        latched=True,
    )


def text_progress(label: str) -> Callable[[int, int], None]:
    """A progress bar on stderr (redrawn at most 100 times; none where stderr is no terminal,
    whose log would keep every redraw)."""
    state = {"last": -1}

    def show(i: int, n: int) -> None:
        if not sys.stderr.isatty():
            return
        pct = int(100 * i / max(n, 1))
        if pct == state["last"] and i < n:
            return
        state["last"] = pct
        bar = "#" * (pct // 4)
        end = "\n" if i >= n else ""
        print(f"\r{label} [{bar:<25}] {pct:3d}% ({i}/{n})", end=end, file=sys.stderr, flush=True)

    return show
