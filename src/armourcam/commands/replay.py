"""``armourcam replay``: publish a bag's images, camera info and hall topics into the graph."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from . import add_ros_args

_SKIP_TYPES = ("sensor_msgs/msg/PointCloud2", "visualization_msgs/msg/MarkerArray")
_SKIP_PREFIXES = ("/diagnostics", "/rosout")
#: The matcher's report, also as recorded from a graph in a namespace (``/cell2/armourcam/report``).
_SKIP_SUFFIXES = ("/armourcam/report",)


def register(subparsers: Any) -> None:
    """Add the ``replay`` subcommand."""
    p = subparsers.add_parser(
        "replay",
        help="publish a bag (ROS 2 MCAP/SQLite or ROS 1) into the running graph",
        description=(
            "Publish a bag's images (sensor_msgs/Image or CompressedImage), camera info and hall "
            "topics (std_msgs Bool/String/Empty) with rclpy. Headers are restamped with the "
            "publication time unless --keep-stamps, so frames and hall events share one clock. "
            "Recorded graph outputs (PointCloud2, MarkerArray, String reports) are not replayed "
            "unless named with --topics. Topics are published relative to the replay's "
            "namespace: with --ros-args -r __ns:=/cell2 the bag's /camera/image_raw is "
            "published as /cell2/camera/image_raw, feeding a graph started in /cell2 (a "
            "--remap target is taken as given). --ros-args ends the command's own options: "
            "everything after it goes to rclpy."
        ),
    )
    p.add_argument("bag", type=Path, help="bag directory, .mcap file or ROS 1 .bag")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument(
        "--rate", type=float, default=1.0, help="playback speed, x recorded time (default 1)"
    )
    speed.add_argument(
        "--as-fast-as-consumed",
        action="store_true",
        help="publish each image after the detector answered the previous one (lossless)",
    )
    p.add_argument(
        "--remap",
        action="append",
        default=[],
        metavar="FROM:=TO",
        help="publish bag topic FROM as TO (repeatable); TO empty skips the topic",
    )
    p.add_argument(
        "--qos",
        choices=("reliable", "sensor_data"),
        default="reliable",
        help="QoS of images and camera info (default reliable; must match the nodes' qos)",
    )
    p.add_argument("--topics", nargs="*", help="replay only these bag topics")
    p.add_argument(
        "--confirm-topic",
        default="armourcam/detections",
        help="with --as-fast-as-consumed: the detector's output topic (relative names resolve "
        "in the replay's namespace)",
    )
    p.add_argument("--keep-stamps", action="store_true", help="keep the bag's header stamps")
    p.add_argument(
        "--wait-for",
        action="append",
        default=[],
        metavar="TOPIC",
        help="also wait until TOPIC has a subscriber in the graph (repeatable), e.g. "
        "/armourcam/poses so that the matcher sees the first frames",
    )
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=10.0,
        help="seconds to wait for the graph to subscribe before publishing (default 10)",
    )
    p.add_argument(
        "--linger", type=float, default=1.0, help="seconds to stay up after the last message"
    )
    add_ros_args(p, "the rest of the command line goes to rclpy (e.g. -r __ns:=/cell2)")
    p.set_defaults(func=run)


def parse_remaps(items: list[str]) -> dict[str, str]:
    """``["/a:=/b", ...]`` -> ``{"/a": "/b"}``."""
    out: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition(":=")
        if not sep or not src:
            raise ValueError(f"--remap expects FROM:=TO, got {item!r}")
        out[src] = dst
    return out


def default_remaps(bag: Path, topics: list[str] | None) -> dict[str, str]:
    """Skip the recorded graph outputs (unless asked for) so replay only feeds inputs."""
    from armourcam import bagio

    skip: dict[str, str] = {}
    with bagio.open_bag(bag) as b:
        for name, info in b.topics.items():
            if topics is not None:
                if name not in topics:
                    skip[name] = ""
            elif (
                info.msgtype in _SKIP_TYPES
                or name.startswith(_SKIP_PREFIXES)
                or name.endswith(_SKIP_SUFFIXES)
            ):
                skip[name] = ""
    return skip


def run(args: argparse.Namespace) -> int:
    """Replay the bag; prints what was published."""
    from armourcam import graph

    if not args.bag.exists():
        raise FileNotFoundError(f"bag {args.bag} does not exist")
    remap = default_remaps(args.bag, args.topics)
    remap.update(parse_remaps(args.remap))

    def progress(i: int, n: int) -> None:
        if sys.stderr.isatty():
            print(f"\rreplay {i}/{n}", end="" if i < n else "\n", file=sys.stderr)

    stats = graph.replay_bag(
        args.bag,
        remap=remap,
        qos=args.qos,
        rate=None if args.as_fast_as_consumed else args.rate,
        as_fast_as_consumed=args.as_fast_as_consumed,
        confirm_topic=args.confirm_topic,
        restamp=not args.keep_stamps,
        wait_subscribers=args.wait_subscribers,
        wait_for=args.wait_for,
        settle_s=args.linger,
        progress=progress,
        ros_args=args.ros_args,
    )
    for topic, n in sorted(stats.published.items()):
        print(f"{topic}: {n}")
    line = f"frames: {stats.frames} in {stats.seconds:.1f} s"
    if args.as_fast_as_consumed:
        line += f", confirmed by the detector: {stats.frames_confirmed}"
    print(line)
    if args.as_fast_as_consumed and stats.frames_confirmed < stats.frames:
        return 1
    return 0
