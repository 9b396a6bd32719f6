"""Helpers of the DDS tests: an isolated domain, node processes, a probe node, the CLI (and its
recorder).

Importing this module sets ``ROS_DOMAIN_ID`` (unique to the test run, derived from the pid, in
1..101) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` for this process and every child.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

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
from pose_estimator.camera import CameraModel  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def ros_env() -> dict[str, str]:
    """Environment of every child process."""
    env = os.environ.copy()
    env["ROS_DOMAIN_ID"] = str(DOMAIN_ID)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONFAULTHANDLER"] = "1"  # a crash in a node leaves its Python stack in its log
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
        """Stop one node (SIGINT to its group, SIGKILL after 5 s); returns its exit status.
        Callers asserting 0 show :meth:`log`: a crash leaves its Python stack there."""
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


def status_values(status: Any) -> dict[str, str]:
    """The key/value pairs of one DiagnosticStatus."""
    return {kv.key: kv.value for kv in status.values}


class Statuses(list[Any]):
    """DiagnosticStatus messages of one node in arrival order (see :meth:`Probe.statuses`)."""

    def values(self) -> dict[str, str]:
        """The key/value pairs of the latest status (empty before the first)."""
        return status_values(self[-1]) if self else {}


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

    def call(self, srv_type: Any, service: str, request: Any) -> Any:
        """One call of ``service``; returns the response (20 s to appear, 10 s to answer)."""
        client = self.node.create_client(srv_type, service)
        try:
            assert self.spin_until(client.service_is_ready, 20.0), service
            future = client.call_async(request)
            assert self.spin_until(future.done, 10.0), service
            return future.result()
        finally:
            self.node.destroy_client(client)

    def get_parameter(self, node: str, name: str) -> Any:
        """The ParameterValue message of parameter ``name`` of fully qualified ``node``."""
        from rcl_interfaces.srv import GetParameters

        request = GetParameters.Request(names=[name])
        (value,) = self.call(GetParameters, f"{node}/get_parameters", request).values
        return value

    def set_parameter(self, node: str, name: str, value: Any) -> Any:
        """One SetParameters call (what ``ros2 param set`` does); returns its result."""
        from rcl_interfaces.msg import Parameter as ParameterMsg
        from rcl_interfaces.srv import SetParameters

        request = SetParameters.Request(parameters=[ParameterMsg(name=name, value=value)])
        (result,) = self.call(SetParameters, f"{node}/set_parameters", request).results
        return result

    def statuses(self, node: str) -> Statuses:
        """The /diagnostics statuses whose name contains ``node``, appended as they arrive."""
        from diagnostic_msgs.msg import DiagnosticArray

        out = Statuses()
        self.node.create_subscription(
            DiagnosticArray,
            "/diagnostics",
            lambda m: out.extend(s for s in m.status if node in s.name),
            50,
        )
        return out

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def ideal_calibration(tmp: Path) -> Path:
    """``tmp/camera.yaml``: an ideal 640x480 camera, 500 px focal length."""
    path = tmp / "camera.yaml"
    path.write_text(yaml.safe_dump(CameraModel.ideal(640, 480, 500.0).to_dict()))
    return path


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


def ignore_sigint() -> None:
    """A ``preexec_fn``: the child starts with SIGINT ignored, as a non-interactive shell starts
    a command it puts in the background (``armourcam record &`` in a rig's script)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


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


class Recorder:
    """``armourcam record --out BAG ARGS...`` in its own process group; stderr read as it comes
    (``popen``: more :class:`subprocess.Popen` arguments)."""

    def __init__(self, bag: Path, *args: str, **popen: Any) -> None:
        self.proc = start_armourcam(
            "record",
            "--out",
            str(bag),
            *args,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            **popen,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)

    def wait_ready(self, timeout: float = 30.0) -> bool:
        """Wait for the ``armourcam record: ready`` line (False on timeout or exit)."""
        deadline = time.monotonic() + timeout
        while True:
            if any(line.startswith("armourcam record: ready") for line in self.lines):
                return True
            if self.proc.poll() is not None or time.monotonic() >= deadline:
                return False
            time.sleep(0.05)

    def stop(self) -> str:
        """Stop it as Ctrl-C does (idempotent); returns its stdout (the counts) and checks that
        it ended cleanly."""
        graph.stop_processes([self.proc])
        out = ""
        if self.proc.stdout is not None and not self.proc.stdout.closed:
            out = self.proc.stdout.read()
            self.proc.stdout.close()
        self._reader.join(5.0)
        if self.proc.stderr is not None:
            self.proc.stderr.close()
        assert self.proc.returncode == 0, "".join(self.lines)
        return out

    def close(self) -> None:
        """Stop it whatever its state and close its pipes (the fixture's finaliser)."""
        graph.stop_processes([self.proc])
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                pipe.close()
