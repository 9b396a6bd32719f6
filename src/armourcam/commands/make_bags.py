"""``armourcam make-bags``: regenerate the committed session bags (and 6 MP ones on demand)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from . import output_path

SMALL_NAME = "session_small"
LARGE_NAME = "session_6mp"


def register(subparsers: Any) -> None:
    """Add the ``make-bags`` subcommand."""
    p = subparsers.add_parser(
        "make-bags",
        help="render the monitoring-session bags with ground truth",
        description=(
            "Render a monitoring session (camera info, baseline frames, wave runs announced on "
            "/hall/run_id and /hall/run_active, after frames) with armourcam's renderer into a "
            "ROS 2 MCAP bag, the ground-truth displacements beside it (.truth.json/.truth.csv). "
            f"Writes OUT/{SMALL_NAME} (1504x1000 JPEG, committed); --large also writes "
            f"OUT/large/{LARGE_NAME} (3008x2000 mono8, git-ignored)."
        ),
    )
    p.add_argument("--out", type=output_path, default=Path("bags"), help="directory (default bags)")
    p.add_argument("--large", action="store_true", help="also write the 6 MP version")
    p.add_argument("--seed", type=_seed, default=9, help="field seed (default 9)")
    p.set_defaults(func=run)


def _seed(text: str) -> int:
    """argparse type: a non-negative integer seed."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {text!r}")
    return value


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def run(args: argparse.Namespace) -> int:
    """Write the bags; prints their sizes."""
    from armourcam.sessionbag import SessionSpec, replace_session_bag, truth_paths

    jobs = [(args.out / SMALL_NAME, SessionSpec(seed=args.seed))]
    if args.large:
        spec = SessionSpec(width=3008, height=2000, compressed=False, seed=args.seed)
        jobs.append((args.out / "large" / LARGE_NAME, spec))
    for path, spec in jobs:
        truth = replace_session_bag(path, spec)
        n = len(truth["runs"][0]["cumulative"]["fiducials"])
        size = _size(path) + sum(p.stat().st_size for p in truth_paths(path))
        print(
            f"{path}: {spec.width}x{spec.height}, {n} fiducials, "
            f"{truth['runs'][0]['cumulative']['displaced_units']} displaced units, "
            f"{size / 1e6:.1f} MB"
        )
    return 0
