"""``armourcam graph``: start the three nodes (separate processes, or one process)."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

from . import add_ros_args


def register(subparsers: Any) -> None:
    """Add the ``graph`` subcommand."""
    p = subparsers.add_parser(
        "graph",
        help="run the ROS 2 graph (fiducial_detector, pose_estimator, displacement_matcher)",
        description=(
            "Start fiducial_detector, pose_estimator and displacement_matcher, each as its own "
            "process (default) or all in one process, until Ctrl-C. Parameters come from a ROS "
            "params YAML (see config/armourcam.params.yaml) and from --ros-args, which ends "
            "the command's own options: everything after it goes to every node (e.g. "
            "--ros-args -r __ns:=/cell2 -p diameter_mm:=10.0 moves the whole graph into /cell2, "
            "its topics included, and sets a parameter)."
        ),
    )
    p.add_argument("--params", type=Path, help="ROS 2 parameters YAML (--ros-args --params-file)")
    p.add_argument(
        "--one-process",
        action="store_true",
        help="run the three nodes in this process on one executor",
    )
    p.add_argument(
        "--single-threaded",
        action="store_true",
        help="with --one-process: a SingleThreadedExecutor instead of a MultiThreadedExecutor",
    )
    p.add_argument(
        "--log-dir",
        type=Path,
        help="separate processes: write each node's output to DIR/<node>.log",
    )
    add_ros_args(
        p, "the rest of the command line goes to every node's rclpy (remaps, -p, --log-level)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the graph until interrupted; returns the exit status."""
    from armourcam import graph

    if args.params is not None and not args.params.is_file():
        raise FileNotFoundError(f"params file {args.params} does not exist")
    params = str(args.params) if args.params else None
    if args.one_process:
        return graph.run_one_process(
            params, multithreaded=not args.single_threaded, ros_args=args.ros_args
        )
    procs = graph.launch_processes(params, log_dir=args.log_dir, ros_args=args.ros_args)
    stopping = False

    def _stop(_sig: int, _frame: Any) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGHUP, _stop)  # a closed terminal stops the graph like Ctrl-C
    status = 0
    try:
        while not stopping:
            for name, proc in procs.items():
                if proc.poll() is not None:
                    print(f"armourcam graph: {name} exited with {proc.returncode}", file=sys.stderr)
                    stopping = True
                    status = 1
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        graph.stop_processes(procs.values())
    return status
