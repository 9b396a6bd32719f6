"""Run every benchmark in its quick form and print their tables (``make bench``).

The full protocols (the paper's 30 noise images per case, the 5-minute graph replay) are run one at
a time with each module's own arguments; see ``benchmarks/README.md``.
"""

from __future__ import annotations

import subprocess
import sys
import time

# (module, arguments for a run that finishes in minutes on 2 cores)
QUICK: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("benchmarks.detector_speed", ("--quick",)),
    ("benchmarks.detector_precision", ("--quick",)),
    ("benchmarks.detector_recall", ("--quick",)),
    ("benchmarks.pose_tables", ("--quick",)),
    ("benchmarks.pose_table3", ("--images", "3")),
    ("benchmarks.pose_speed", ()),
    ("benchmarks.matcher_scale", ("--repeat", "1")),
    ("benchmarks.matcher_field", ("--seeds", "1")),
    ("benchmarks.graph_latency", ("--duration", "30")),
)


def main() -> int:
    """Run each quick benchmark in its own process; returns non-zero if any failed to run."""
    failed = []
    for module, args in QUICK:
        print(f"\n=== {module} {' '.join(args)}", flush=True)
        start = time.monotonic()
        status = subprocess.call([sys.executable, "-m", module, *args])
        print(f"--- {module}: exit {status}, {time.monotonic() - start:.0f} s", flush=True)
        if status != 0:
            failed.append(module)
    if failed:
        print(f"\nbenchmarks that failed to run: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
