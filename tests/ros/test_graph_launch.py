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


def _children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid``."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _gone(pid: int) -> bool:
    """True once ``pid`` has exited (a zombie awaiting its new parent counts as exited)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return True
    return state == "Z"


def test_nodes_end_when_the_launcher_is_killed(tmp_path: Path) -> None:
    """``armourcam graph`` killed with SIGKILL (no chance to stop its nodes, which run in their
    own sessions) still leaves no node running: each asked the kernel to end it with its
    launcher."""
    import signal
    import subprocess
    import sys

    launcher = subprocess.Popen(
        [sys.executable, "-m", "armourcam.cli", "graph", "--log-dir", str(tmp_path)],
        env=ros_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    kids: list[int] = []
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            kids = _children(launcher.pid)
            logs = [tmp_path / f"{n}.log" for n in graph.NODE_NAMES]
            if len(kids) == 3 and all(f.exists() and f.stat().st_size for f in logs):
                break  # every node has started and logged its first line
            time.sleep(0.1)
        assert len(kids) == 3, kids
        launcher.kill()
        launcher.wait(5.0)
        deadline = time.monotonic() + 20.0
        while not all(_gone(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert all(_gone(k) for k in kids), [k for k in kids if not _gone(k)]
    finally:
        for k in kids:
            if not _gone(k):
                os.killpg(k, signal.SIGKILL)
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait(5.0)
