"""``armourcam record``: write the graph's outputs (and inputs if asked) to an MCAP bag."""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path
from typing import Any

from . import add_ros_args

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
#: Recorded with ``--inputs``; those no publisher offers (say the raw or the compressed image) are
#: left out of the bag.
INPUT_TOPICS = (
    "camera/image_raw",
    "camera/image_raw/compressed",
    "camera/camera_info",
    "hall/run_active",
    "hall/run_id",
    "armourcam/capture_baseline",
)


def register(subparsers: Any) -> None:
    """Add the ``record`` subcommand."""
    p = subparsers.add_parser(
        "record",
        help="record the graph's output topics to an MCAP bag",
        description=(
            "Record topics (default: the graph's outputs) into a ROS 2 MCAP bag until Ctrl-C or "
            "--duration. Types and QoS are discovered from the graph: each topic is subscribed "
            "to match its publishers (best effort for a live camera), whose QoS profiles are "
            "stored in the bag; latched topics are recorded with their last message even when "
            "published before the recorder started. Topics without a publisher are not recorded. "
            "Relative names (the defaults) resolve in the recorder's namespace, set with "
            "--ros-args -r __ns:=/cell2; the bag stores full names. --ros-args ends the "
            "command's own options: everything after it goes to rclpy."
        ),
    )
    p.add_argument("--out", type=Path, required=True, help="bag directory to create")
    p.add_argument("topics", nargs="*", help="topics to record (default: the graph's outputs)")
    p.add_argument(
        "--inputs",
        action="store_true",
        help="also record the camera (raw and compressed images, camera info) and hall inputs",
    )
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    add_ros_args(p, "the rest of the command line goes to rclpy (e.g. -r __ns:=/cell2)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Record until interrupted; prints message counts."""
    from armourcam import graph

    if args.out.exists():
        raise FileExistsError(f"{args.out} exists; choose a new bag path")
    topics = list(args.topics) or list(OUTPUT_TOPICS)
    if args.inputs:
        topics += [t for t in INPUT_TOPICS if t not in topics]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    counts = graph.record_topics(
        args.out, topics, duration=args.duration, stop=stop, ros_args=args.ros_args
    )
    for topic, n in sorted(counts.items()):
        print(f"{topic}: {n}")
    return 0
