"""``armourcam bench``: run the repository's benchmarks (``benchmarks/run_all.py``)."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

# src/armourcam/commands/bench.py -> the checkout's top level (benchmarks/ is not installed).
_CHECKOUT = Path(__file__).resolve().parents[3]


def register(sub: Any) -> None:
    """Add the ``bench`` subcommand."""
    p = sub.add_parser(
        "bench",
        help="run the benchmarks and print their tables (from a checkout of the repository)",
        description="Runs benchmarks/run_all.py: quick forms by default, --full for the full "
        "protocols. Tables are printed beside the paper's and peers' figures.",
    )
    p.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    p.add_argument("--full", action="store_true", help="full protocols (slow)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the benchmarks in a child process from the checkout's top level."""
    if not (_CHECKOUT / "benchmarks" / "run_all.py").is_file():
        raise FileNotFoundError(
            f"no benchmarks/ beside the installed package ({_CHECKOUT}): run from a checkout"
        )
    cmd = [sys.executable, "-m", "benchmarks.run_all", *args.names]
    if args.full:
        cmd.append("--full")
    return subprocess.call(cmd, cwd=_CHECKOUT)
