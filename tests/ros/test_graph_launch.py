"""The graph launcher: one process per node, the matcher at a lower CPU priority, all stopped."""

from __future__ import annotations

import os
from pathlib import Path

from rosutil import ros_env

from armourcam import graph


def test_launched_matcher_runs_niced_and_every_process_stops(tmp_path: Path) -> None:
    procs = graph.launch_processes(
        nodes=("pose_estimator", "displacement_matcher"), env=ros_env(), log_dir=tmp_path
    )
    try:
        base = os.getpriority(os.PRIO_PROCESS, 0)
        want = min(19, base + graph.NICENESS["displacement_matcher"])
        assert os.getpriority(os.PRIO_PROCESS, procs["displacement_matcher"].pid) == want
        assert os.getpriority(os.PRIO_PROCESS, procs["pose_estimator"].pid) == base
    finally:
        graph.stop_processes(procs.values())
    assert all(p.poll() is not None for p in procs.values())
