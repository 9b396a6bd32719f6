"""The graph launcher: one process per node, one BLAS thread each, the matcher at a lower CPU
priority, all stopped."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from rosutil import Probe, ignore_sigint, ros_env, start_armourcam

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
    launcher = _start_launcher(tmp_path)
    kids: list[int] = []
    try:
        kids += _wait_for_nodes(launcher).values()
        _wait_for_logs(tmp_path)
        assert len(kids) == 3, kids
        launcher.kill()
        launcher.wait(5.0)
        deadline = time.monotonic() + 20.0
        while not all(_gone(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert all(_gone(k) for k in kids), [_state(k) for k in kids if not _gone(k)]
    finally:
        _end(launcher, kids)


def _state(pid: int) -> str:
    """What a process left running is doing: its command line, state and kernel wait channel,
    for the assertion message."""
    proc = Path(f"/proc/{pid}")
    try:
        cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        status = [
            line
            for line in (proc / "status").read_text().splitlines()
            if line.startswith(("State:", "Threads:", "SigPnd:", "ShdPnd:", "SigCgt:"))
        ]
        wchan = (proc / "wchan").read_text()
    except OSError as err:
        return f"{pid}: {err}"
    return f"{pid} {cmd.strip()}: {'; '.join(status)}; wchan {wchan}"


# ---------------------------------------------------------------------- respawn


def _sleeper() -> subprocess.Popen[bytes]:
    """A stand-in for a node: runs until stopped."""
    return subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True
    )


def _failing() -> subprocess.Popen[bytes]:
    """A stand-in for a node that fails at once."""
    return subprocess.Popen([sys.executable, "-c", "raise SystemExit(1)"], start_new_session=True)


def test_restart_budget_counts_restarts_within_the_window() -> None:
    budget = graph.RestartBudget(limit=2, window_s=10.0)
    assert budget.take(0.0) and budget.take(1.0)
    assert not budget.take(5.0) and len(budget) == 2  # a third within 10 s: refused, not counted
    assert budget.take(10.5) and len(budget) == 2  # the restart at 0 s has left the window
    assert graph.describe_exit(-signal.SIGKILL) == "-9 (SIGKILL)"
    assert graph.describe_exit(1) == "1"


def test_supervise_respawns_a_failed_node_until_it_fails_too_often() -> None:
    """A node killed is respawned (logged with its exit status) while the other keeps running;
    one failing at once again and again is given up on after ``respawn_limit`` restarts."""
    procs = {"a": _sleeper(), "b": _sleeper()}
    b = procs["b"]
    log: list[str] = []
    respawned: list[subprocess.Popen[bytes]] = []

    def respawn(name: str) -> subprocess.Popen[bytes]:
        respawned.append(_failing())
        return respawned[-1]

    deadline = time.monotonic() + 30.0
    try:
        os.kill(procs["a"].pid, signal.SIGKILL)
        status = graph.supervise_processes(
            procs,
            lambda: time.monotonic() > deadline,
            respawn=respawn,
            respawn_delay_s=0.0,
            respawn_limit=2,
            poll_s=0.02,
            log=log.append,
        )
        assert status == 1
        assert len(respawned) == 2
        assert log == [
            "a exited with -9 (SIGKILL); respawning in 0 s (restart 1 of at most 2 within 60 s)",
            f"a respawned (pid {respawned[0].pid})",
            "a exited with 1; respawning in 0 s (restart 2 of at most 2 within 60 s)",
            f"a respawned (pid {respawned[1].pid})",
            "a exited with 1; it was respawned 2 times within 60 s: giving up, stopping the graph",
        ]
        assert procs == {"b": b} and b.poll() is None  # the caller stops what is left
    finally:
        graph.stop_processes([*procs.values(), *respawned])


@pytest.mark.parametrize("case", ["no_respawn", "clean_exit", "stopping"])
def test_supervise_stops_the_graph_or_respawns_nothing(case: str) -> None:
    """Without respawn a node's exit ends the graph, naming it and its status; a node that
    exited with status 0 (stopped on purpose) is not respawned; nor is a node of a graph that
    is stopping while it waits for its respawn."""
    # A node ends with status 0 on SIGINT or SIGTERM (rclpy's handlers).
    a = (
        subprocess.Popen([sys.executable, "-c", "pass"], start_new_session=True)
        if case == "clean_exit"
        else _sleeper()
    )
    procs = {"a": a, "b": _sleeper()}
    log: list[str] = []
    calls: list[str] = []

    def respawn(name: str) -> subprocess.Popen[bytes]:
        calls.append(name)
        return _sleeper()

    deadline = time.monotonic() + 30.0
    try:
        if case != "clean_exit":
            os.kill(procs["a"].pid, signal.SIGKILL)
        status = graph.supervise_processes(
            procs,
            lambda: time.monotonic() > deadline or any("respawning" in line for line in log),
            respawn=None if case == "no_respawn" else respawn,
            respawn_delay_s=100.0,
            poll_s=0.02,
            log=log.append,
        )
        assert calls == [] and "a" not in procs and procs["b"].poll() is None
        want = {
            "no_respawn": (1, "a exited with -9 (SIGKILL); stopping the graph"),
            "clean_exit": (
                1,
                "a exited with 0 (stopped on purpose): not respawned; stopping the graph",
            ),
            "stopping": (
                0,
                "a exited with -9 (SIGKILL); respawning in 100 s "
                "(restart 1 of at most 5 within 60 s)",
            ),
        }[case]
        assert (status, log) == (want[0], [want[1]])
    finally:
        graph.stop_processes([a, *procs.values()])


def _node_pids(launcher: int) -> dict[str, int]:
    """The launcher's node processes by node name (those that have exec'd their node)."""
    out = {}
    for pid in _children(launcher):
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        for name in graph.NODE_NAMES:
            if f"{name}.node".encode() in cmdline.split(b"\0"):
                out[name] = pid
    return out


def _start_launcher(tmp_path: Path, *options: str, **popen: Any) -> subprocess.Popen[bytes]:
    """``armourcam graph`` with node logs in ``tmp_path`` and its own stderr in
    ``tmp_path/launcher.err`` (``popen``: more :class:`subprocess.Popen` arguments)."""
    with open(tmp_path / "launcher.err", "wb") as err:
        return start_armourcam(
            "graph",
            "--log-dir",
            str(tmp_path),
            *options,
            stdout=subprocess.DEVNULL,
            stderr=err,
            **popen,
        )


def test_a_launcher_started_with_sigint_ignored_still_stops_on_sigint(tmp_path: Path) -> None:
    """A non-interactive shell starts a background command (`armourcam graph &` in a rig's
    script) with SIGINT ignored, and Python then leaves it ignored: the launcher used to sit
    through SIGINT until it was killed. It takes SIGINT itself, stops its nodes, each with
    status 0, and ends with 0."""
    launcher = _start_launcher(tmp_path, preexec_fn=ignore_sigint)
    kids: list[int] = []
    try:
        kids += _wait_for_nodes(launcher).values()
        _wait_for_logs(tmp_path)  # the nodes are up, their signal handlers in place
        os.killpg(launcher.pid, signal.SIGINT)
        assert launcher.wait(15.0) == 0
        assert all(_gone(k) for k in kids), [_state(k) for k in kids if not _gone(k)]
        err = (tmp_path / "launcher.err").read_text()
        assert "stopped with" not in err, err  # every node ended cleanly, none killed
    finally:
        _end(launcher, kids)


def _wait_for_nodes(launcher: subprocess.Popen[bytes], timeout: float = 30.0) -> dict[str, int]:
    deadline = time.monotonic() + timeout
    pids = _node_pids(launcher.pid)
    while len(pids) < 3 and time.monotonic() < deadline:
        assert launcher.poll() is None, "the launcher exited"
        time.sleep(0.1)
        pids = _node_pids(launcher.pid)
    assert len(pids) == 3, pids
    return pids


def _wait_for_logs(log_dir: Path, timeout: float = 30.0) -> None:
    """Until every node has started and logged its first line (or ``timeout`` seconds)."""
    logs = [log_dir / f"{n}.log" for n in graph.NODE_NAMES]
    deadline = time.monotonic() + timeout
    while not all(f.exists() and f.stat().st_size for f in logs):
        if time.monotonic() > deadline:
            break
        time.sleep(0.1)


def _end(launcher: subprocess.Popen[bytes], pids: list[int]) -> None:
    """Leave nothing running, whatever the test's outcome."""
    if launcher.poll() is None:
        launcher.kill()
        launcher.wait(5.0)
    for pid in pids:
        if not _gone(pid):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGKILL)


def test_graph_respawn_restarts_a_killed_node_and_the_others_keep_running(
    tmp_path: Path, probe: Probe
) -> None:
    """``armourcam graph --respawn``: the pose estimator killed with SIGKILL comes back as a
    new process that publishes its diagnostics again; the detector and the matcher run on in
    the same processes; the launcher says what happened. SIGTERM then stops everything."""
    from diagnostic_msgs.msg import DiagnosticArray

    pose_diags: list[float] = []  # header stamps, seconds

    def on_diagnostics(msg: DiagnosticArray) -> None:
        if any(s.name == "/pose_estimator: armourcam" for s in msg.status):
            pose_diags.append(graph.stamp_seconds(msg.header.stamp))

    probe.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)
    launcher = _start_launcher(tmp_path, "--respawn", "--respawn-delay", "0.5")
    seen: list[int] = []
    try:
        before = _wait_for_nodes(launcher)
        seen += before.values()
        assert probe.spin_until(lambda: pose_diags, 30.0), "no diagnostics of pose_estimator"
        os.kill(before["pose_estimator"], signal.SIGKILL)

        def respawned() -> int | None:
            pid = _node_pids(launcher.pid).get("pose_estimator")
            return pid if pid not in (None, before["pose_estimator"]) else None

        assert probe.spin_until(respawned, 30.0), "pose_estimator was not respawned"
        new_pid = respawned()
        assert new_pid is not None
        seen.append(new_pid)
        t_respawn = time.time()  # the killed process published nothing stamped after this
        assert probe.spin_until(lambda: pose_diags[-1] > t_respawn, 30.0), (
            "no diagnostics from the respawned pose_estimator"
        )
        after = _node_pids(launcher.pid)
        for name in ("fiducial_detector", "displacement_matcher"):
            assert after[name] == before[name] and not _gone(before[name])
        assert launcher.poll() is None
        err = (tmp_path / "launcher.err").read_text()
        assert "pose_estimator exited with -9 (SIGKILL); respawning in 0.5 s" in err
        assert f"pose_estimator respawned (pid {new_pid})" in err

        launcher.send_signal(signal.SIGTERM)
        assert launcher.wait(30.0) == 0
        assert all(_gone(pid) for pid in after.values())
    finally:
        _end(launcher, seen)


def test_graph_without_respawn_stops_naming_the_node_that_exited(tmp_path: Path) -> None:
    """Without ``--respawn`` one node killed stops the graph: the launcher exits with status 1,
    names the node and its exit, and stops the other nodes."""
    launcher = _start_launcher(tmp_path)
    pids: list[int] = []
    try:
        before = _wait_for_nodes(launcher)
        pids += before.values()
        os.kill(before["displacement_matcher"], signal.SIGKILL)
        assert launcher.wait(30.0) == 1
        err = (tmp_path / "launcher.err").read_text()
        assert "displacement_matcher exited with -9 (SIGKILL); stopping the graph" in err
        assert all(_gone(pid) for pid in pids)
    finally:
        _end(launcher, pids)
