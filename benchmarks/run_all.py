"""Run the benchmarks and print their tables (``make bench``, ``armourcam bench``).

By default each benchmark runs in a quick form that finishes in minutes on 2 cores; ``--full``
runs the full protocols (the paper's 30 noise images per case, the 5-minute graph replay).
Benchmarks are measurements printed as tables beside the paper's and peers' figures, never
pass/fail tests.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from collections.abc import Sequence

# name -> (arguments of the quick run, arguments of the full run)
BENCHMARKS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "detector_speed": (("--quick",), ()),
    "detector_precision": (("--quick",), ()),
    "detector_recall": (("--quick",), ()),
    "pose_tables": (("--quick",), ("--jobs", "2")),
    "pose_bound_odds": (("--sizes", "35"), ("--jobs", "2")),
    "pose_table3": (("--images", "3"), ()),
    "pose_speed": ((), ()),
    "matcher_scale": (("--repeat", "1"), ()),
    "matcher_field": (("--seeds", "1"), ("--seeds", "4")),
    "matcher_count_odds": (("--seeds", "10", "--draws", "2000"), ()),
    "graph_latency": (("--duration", "30"), ()),
    "render_speed": (("--repeat", "1"), ()),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the chosen benchmarks, each in its own process; non-zero if any failed to run."""
    parser = argparse.ArgumentParser(prog="benchmarks.run_all", description=__doc__)
    parser.add_argument(
        "names", nargs="*", help=f"benchmarks to run (default all): {', '.join(BENCHMARKS)}"
    )
    parser.add_argument("--full", action="store_true", help="full protocols instead of quick runs")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; known: {', '.join(BENCHMARKS)}")
    failed = []
    for name in args.names or list(BENCHMARKS):
        quick, full = BENCHMARKS[name]
        extra = full if args.full else quick
        print(f"\n=== benchmarks.{name} {' '.join(extra)}", flush=True)
        start = time.monotonic()
        status = subprocess.call([sys.executable, "-m", f"benchmarks.{name}", *extra])
        print(f"--- {name}: exit {status}, {time.monotonic() - start:.0f} s", flush=True)
        if status != 0:
            failed.append(name)
    if failed:
        print(f"\nbenchmarks that failed to run: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
