"""Helpers of the DDS tests: an isolated domain, node processes, a probe node, the CLI.

Importing this module sets ``ROS_DOMAIN_ID`` (unique to the test run, derived from the pid, in
1..101) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` for this process and every child.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

DOMAIN_ID = 1 + os.getpid() % 101
os.environ["ROS_DOMAIN_ID"] = str(DOMAIN_ID)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

rclpy = pytest.importorskip("rclpy")

# rclpy's type-support import chain pulls in lark, which imports the deprecated ``sre_parse``;
# the suite runs with warnings as errors, so import it once here with that warning silenced.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import rosidl_generator_py  # noqa: F401

from armourcam import graph  # noqa: E402  (after the environment is set)

REPO = Path(__file__).resolve().parents[2]


def ros_env() -> dict[str, str]:
    """Environment of every child process."""
    env = os.environ.copy()
    env["ROS_DOMAIN_ID"] = str(DOMAIN_ID)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    return env


class Nodes:
    """Node processes of one test (started with :meth:`start`, stopped by the fixture)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(
        self,
        node: str,
        *ros_args: str,
        params: dict[str, Any] | None = None,
        label: str | None = None,
    ) -> subprocess.Popen[bytes]:
        """Start ``node`` (a package name) with ``-p name:=value`` parameters."""
        label = label or node
        args = list(ros_args)
        for k, v in (params or {}).items():
            val = str(v).lower() if isinstance(v, bool) else str(v)
            args += ["-p", f"{k}:={val}"]
        log = open(self.tmp / f"{label}.log", "wb")  # noqa: SIM115 - handed to the child
        proc = subprocess.Popen(
            graph.node_command(node, None, args),
            env=ros_env(),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        self.procs[label] = proc
        return proc

    def stop(self, label: str) -> int | None:
        """Stop one node (SIGINT to its group, SIGKILL after 5 s); returns its exit status."""
        proc = self.procs.pop(label)
        graph.stop_processes([proc])
        return proc.returncode

    def log(self, label: str) -> str:
        """Everything ``label`` printed so far."""
        return (self.tmp / f"{label}.log").read_text(errors="replace")

    def alive(self, label: str) -> bool:
        return self.procs[label].poll() is None

    def stop_all(self) -> None:
        graph.stop_processes(self.procs.values())
        self.procs.clear()


class Probe:
    """An rclpy node in the test process with its own context."""

    def __init__(self) -> None:
        from armourcam.graph import use_dds_profile

        use_dds_profile()  # the graph's own transport settings (shared memory for frames)
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"probe_{os.getpid()}", context=self.context)
        from rclpy.executors import SingleThreadedExecutor

        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, done: Callable[[], object], timeout: float) -> bool:
        """Spin until ``done()`` is truthy or ``timeout`` seconds pass; returns ``bool(done())``."""
        deadline = time.monotonic() + timeout
        while not done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
        return bool(done())

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def start_armourcam(*args: str, **popen: Any) -> subprocess.Popen[Any]:
    """Start the ``armourcam`` command line in its own process group in the test's domain, not
    waiting for it (``popen``: stdout, stderr, text... as :class:`subprocess.Popen` takes them;
    the caller stops it, e.g. with ``graph.stop_processes``)."""
    return subprocess.Popen(
        [sys.executable, "-m", "armourcam.cli", *args],
        env=ros_env(),
        start_new_session=True,
        **popen,
    )


def armourcam(*args: str, timeout: float = 90.0) -> subprocess.CompletedProcess[str]:
    """Run the ``armourcam`` command line as a separate process in the test's domain."""
    return subprocess.run(
        [sys.executable, "-m", "armourcam.cli", *args],
        env=ros_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        start_new_session=True,
    )
