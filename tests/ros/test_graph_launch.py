"""The graph launcher: one process per node, one BLAS thread each, the matcher at a lower CPU
priority, all stopped."""

from __future__ import annotations

import os
import time
from pathlib import Path

from rosutil import ros_env

from armourcam import graph


def _environ(pid: int, name: str) -> dict[str, str]:
    """The environment of node ``name``'s process, once it has exec'd (until then /proc shows
    the forking parent's)."""
    deadline = time.monotonic() + 20.0
    while f"{name}.node".encode() not in Path(f"/proc/{pid}/cmdline").read_bytes():
        assert time.monotonic() < deadline, f"{name} did not start"
        time.sleep(0.02)
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode().split("=", 1) for item in raw if b"=" in item)


def test_launched_matcher_runs_niced_and_every_process_stops(tmp_path: Path) -> None:
    env = ros_env()
    env.pop("OPENBLAS_NUM_THREADS", None)
    env["MKL_NUM_THREADS"] = "3"  # an explicit setting wins
    procs = graph.launch_processes(
        nodes=("pose_estimator", "displacement_matcher"), env=env, log_dir=tmp_path
    )
    try:
        for name, p in procs.items():
            child = _environ(p.pid, name)
            assert child["OPENBLAS_NUM_THREADS"] == "1" and child["MKL_NUM_THREADS"] == "3"
        base = os.getpriority(os.PRIO_PROCESS, 0)
        want = min(19, base + graph.NICENESS["displacement_matcher"])
        assert os.getpriority(os.PRIO_PROCESS, procs["displacement_matcher"].pid) == want
        assert os.getpriority(os.PRIO_PROCESS, procs["pose_estimator"].pid) == base
    finally:
        graph.stop_processes(procs.values())
    assert all(p.poll() is not None for p in procs.values())
