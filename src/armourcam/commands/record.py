"""``armourcam record``: write the graph's outputs and hall events (and inputs if asked) to an
MCAP bag."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import Any

from . import add_ros_args, output_path

#: The graph's default names: relative (resolved in the recorder's namespace, as the nodes'
#: are in theirs, so ``--ros-args -r __ns:=/cell2`` records ``/cell2/armourcam/poses``) but
#: ``/diagnostics``, which every namespace shares.
OUTPUT_TOPICS = (
    "armourcam/detections",
    "armourcam/poses",
    "armourcam/pose_array",
    "armourcam/markers",
    "armourcam/displacements",
    "armourcam/report",
    "armourcam/baseline",
    "/diagnostics",
)
#: The matcher's event inputs, recorded by default: the hall's wave-run state and run id (relative
#: like the matcher's defaults, so each cell's own feed) and the operator's baseline command.
#: With them a bag of the camera is analysed as the graph measured it (``armourcam analyze``).
EVENT_TOPICS = (
    "hall/run_active",
    "hall/run_id",
    "armourcam/capture_baseline",
)
DEFAULT_TOPICS = OUTPUT_TOPICS + EVENT_TOPICS
#: Recorded with ``--inputs``: the camera and the events; those no publisher offers (say the raw
#: or the compressed image) are left out of the bag.
INPUT_TOPICS = (
    "camera/image_raw",
    "camera/image_raw/compressed",
    "camera/camera_info",
    *EVENT_TOPICS,
)
#: Types of the graph's topics: the recorder subscribes to them at once, before a publisher
#: appears, so it is ready for a replay or a graph started after it (``graph.record_topics``).
TOPIC_TYPES = {
    "armourcam/detections": "sensor_msgs/msg/PointCloud2",
    "armourcam/poses": "sensor_msgs/msg/PointCloud2",
    "armourcam/pose_array": "geometry_msgs/msg/PoseArray",
    "armourcam/markers": "visualization_msgs/msg/MarkerArray",
    "armourcam/displacements": "sensor_msgs/msg/PointCloud2",
    "armourcam/report": "std_msgs/msg/String",
    "armourcam/baseline": "sensor_msgs/msg/PointCloud2",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "hall/run_active": "std_msgs/msg/Bool",
    "hall/run_id": "std_msgs/msg/String",
    "armourcam/capture_baseline": "std_msgs/msg/Empty",
    "camera/image_raw": "sensor_msgs/msg/Image",
    "camera/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
    "camera/camera_info": "sensor_msgs/msg/CameraInfo",
}


def register(subparsers: Any) -> None:
    """Add the ``record`` subcommand."""
    p = subparsers.add_parser(
        "record",
        help="record the graph's output topics to an MCAP bag",
        description=(
            "Record topics (default: the graph's outputs and the hall and baseline events "
            "hall/run_active, hall/run_id, armourcam/capture_baseline) into a ROS 2 MCAP bag "
            "until Ctrl-C, SIGTERM or --duration. The graph's topics are subscribed at once; "
            "others once a publisher appears, with its type. Each publisher is matched with its "
            "own QoS (best effort for a live camera, transient-local for a latched one: its "
            "history is recorded whenever it was published); the publishers' QoS profiles are "
            "stored in the bag. When subscribed and matched with the publishers already there, "
            "the recorder subscribes to armourcam/recorder_ready and prints 'armourcam record: "
            "ready' on stderr: 'armourcam replay BAG --wait-for armourcam/recorder_ready' waits "
            "for it, and is then recorded whole. Messages are logged at their source timestamp "
            "(when published). Topics without a publisher are not recorded. Relative names (the "
            "defaults) resolve in the recorder's namespace, set with --ros-args -r __ns:=/cell2; "
            "the bag stores full names. --ros-args ends the command's own options: everything "
            "after it goes to rclpy."
        ),
    )
    p.add_argument("--out", type=output_path, required=True, help="bag directory to create")
    p.add_argument(
        "topics", nargs="*", help="topics to record (default: the graph's outputs and events)"
    )
    p.add_argument(
        "--inputs",
        action="store_true",
        help="also record the camera (raw and compressed images, camera info) and the events",
    )
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    add_ros_args(p, "the rest of the command line goes to rclpy (e.g. -r __ns:=/cell2)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Record until interrupted; prints message counts."""
    from armourcam import graph

    if args.out.exists():
        raise FileExistsError(f"{args.out} exists; choose a new bag path")
    topics = list(args.topics) or list(DEFAULT_TOPICS)
    if args.inputs:
        topics += [t for t in INPUT_TOPICS if t not in topics]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def ready(state: graph.RecordReady) -> None:
        # On stderr, flushed: a script (or test) starts its replay once it reads the line.
        line = f"armourcam record: ready: {len(state.subscribed)} topics subscribed"
        if state.awaiting:
            line += f"; waiting for a publisher of {', '.join(state.awaiting)}"
        if state.unmatched:
            line += f"; publishers not matched yet on {', '.join(state.unmatched)}"
        print(line, file=sys.stderr, flush=True)

    counts = graph.record_topics(
        args.out,
        topics,
        types=TOPIC_TYPES,
        duration=args.duration,
        stop=stop,
        ready=ready,
        ros_args=args.ros_args,
    )
    for topic, n in sorted(counts.items()):
        print(f"{topic}: {n}")
    return 0
