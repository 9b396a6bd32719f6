"""``armourcam graph``: start the three nodes (separate processes, or one process)."""

from __future__ import annotations

import argparse
import math
import signal
import subprocess
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
    p.add_argument(
        "--respawn",
        action="store_true",
        help=(
            "separate processes: restart a node that fails (non-zero status or killed by a "
            "signal) instead of stopping the graph; a node that needs more than "
            "5 restarts within 60 s is given up on and the graph stops. Without it (as in ROS "
            "launch) any node's exit stops the graph"
        ),
    )
    p.add_argument(
        "--respawn-delay",
        type=float,
        metavar="SECONDS",
        help="with --respawn: wait this long before restarting a node (default 2)",
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
    delay = _respawn_delay(args)
    if args.one_process:
        if args.respawn:
            raise ValueError("--respawn restarts node processes: not with --one-process")
        return graph.run_one_process(
            params, multithreaded=not args.single_threaded, ros_args=args.ros_args
        )
    stopping = False

    def _stop(_sig: int, _frame: Any) -> None:
        nonlocal stopping
        stopping = True

    # Python leaves SIGINT ignored when it started ignored, as it does for a command that a
    # non-interactive shell put in the background (`armourcam graph &` in a rig's script), and
    # the nodes would inherit that: Ctrl-C and `kill -INT` must stop the graph all the same.
    # Installed before the nodes start, so that they start with the default dispositions.
    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGHUP, _stop)  # a closed terminal stops the graph like Ctrl-C
    procs = graph.launch_processes(params, log_dir=args.log_dir, ros_args=args.ros_args)

    def _respawn(name: str) -> subprocess.Popen[bytes]:
        new = graph.launch_processes(
            params, nodes=(name,), log_dir=args.log_dir, ros_args=args.ros_args
        )
        return new[name]

    status = 0
    try:
        status = graph.supervise_processes(
            procs,
            lambda: stopping,
            respawn=_respawn if args.respawn else None,
            respawn_delay_s=delay,
        )
    finally:
        # ``procs`` is kept current: respawned processes included.
        names = {proc.pid: name for name, proc in procs.items()}
        ended = graph.stop_processes(procs.values())
        for pid, code in ended.items():
            # Status 0, or the SIGINT itself for a node still starting up: a clean stop. Any
            # other end (a crash, the SIGKILL of a node that did not stop) is named.
            if code not in (0, -signal.SIGINT, None):
                graph.log_launcher(f"{names[pid]} stopped with {graph.describe_exit(code)}")
    return status


def _respawn_delay(args: argparse.Namespace) -> float:
    """``--respawn-delay`` checked (seconds, default 2)."""
    if args.respawn_delay is None:
        return 2.0
    if not args.respawn:
        raise ValueError("--respawn-delay needs --respawn")
    delay = float(args.respawn_delay)
    if not (delay >= 0 and math.isfinite(delay)):
        raise ValueError(f"--respawn-delay must be >= 0 s, got {args.respawn_delay}")
    return delay
