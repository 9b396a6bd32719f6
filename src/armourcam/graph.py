"""The ROS 2 graph: node plumbing shared by the three nodes, launching, replay and recording.

With the three ``*/node.py`` modules this is the only module importing rclpy. It holds

- the QoS profiles (:func:`stream_qos`, :func:`latched_qos`) and the parameter declaration helper
  every node uses (:class:`Param`, :func:`declare_parameters`), and :func:`run_node`, the shared
  ``main()`` body (rclpy init, spin, clean shutdown on Ctrl-C or external shutdown);
- launching: :func:`launch_processes` (each node its own process, own process group), watched
  by :func:`supervise_processes` (a node's exit stops the graph, or it is respawned), and
  :func:`run_one_process` (all three nodes in one process on one executor);
- :class:`Replayer` (``armourcam replay``): publishes a bag's images, camera info and hall topics;
- :func:`record_topics` (``armourcam record``): writes the graph's topics to an MCAP bag.

Namespaces: the nodes' default topic names are relative (``camera/image_raw``), so
``--ros-args -r __ns:=/cell2`` moves a whole graph (``/cell2/camera/image_raw``); only
:data:`GLOBAL_TOPICS` such as ``/diagnostics`` stay absolute. A replay publishes a bag's names
relative to its own namespace (:func:`replay_name`) and a recording resolves relative names in
its own, so the same ``--ros-args`` move them along with the graph.

QoS names used throughout: ``reliable`` (RELIABLE, VOLATILE, KEEP_LAST depth; replay, nothing
lost while queues keep up) and ``sensor_data`` (BEST_EFFORT, VOLATILE, KEEP_LAST depth; a live
camera, late frames are dropped rather than queued). Latched outputs are RELIABLE +
TRANSIENT_LOCAL, depth 1.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .blas import one_blas_thread
from .heap import keep_freed_memory

QOS_NAMES = ("reliable", "sensor_data")
NODE_NAMES = ("fiducial_detector", "pose_estimator", "displacement_matcher")


class GraphError(ValueError):
    """A node's parameters, a launch or a replay request is invalid."""


# ---------------------------------------------------------------------- QoS


def stream_qos(name: str, depth: int) -> QoSProfile:
    """QoS of a per-frame stream: ``reliable`` (replay) or ``sensor_data`` (live camera)."""
    if name not in QOS_NAMES:
        raise GraphError(f"qos must be one of {QOS_NAMES}, got {name!r}")
    if depth < 1:
        raise GraphError(f"queue depth must be >= 1, got {depth}")
    reliability = (
        ReliabilityPolicy.RELIABLE if name == "reliable" else ReliabilityPolicy.BEST_EFFORT
    )
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=reliability,
        durability=DurabilityPolicy.VOLATILE,
    )


def record_qos(name: str, depth: int) -> QoSProfile:
    """QoS of the graph's own per-frame record streams (detections, poses).

    As :func:`stream_qos`, but in ``reliable`` mode also TRANSIENT_LOCAL: a node that joins (or
    is discovered) late still receives the last ``depth`` frames instead of losing those
    published before the match. Publisher and subscriber of these streams both use it; a
    VOLATILE subscriber (a viewer, ``armourcam record``) still matches.
    """
    profile = stream_qos(name, depth)
    if name == "reliable":
        profile.durability = DurabilityPolicy.TRANSIENT_LOCAL
    return profile


def publish_diagnostics(
    node: Node,
    publisher: Any,
    *,
    level: str,
    message: str,
    hardware_id: str,
    values: dict[str, str],
) -> None:
    """Publish one ``diagnostic_msgs/DiagnosticArray`` with the node's status.

    ``level`` is ``"ok"``, ``"warn"`` or ``"error"``; the status is named ``<fully qualified
    node name>: armourcam`` (diagnostic_updater's ``node: task``, e.g.
    ``/cell2/fiducial_detector: armourcam``, so nodes of several cells stay apart) and stamped
    now.
    """
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    levels = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN}
    status = DiagnosticStatus(
        level=levels.get(level, DiagnosticStatus.ERROR),
        name=f"{node.get_fully_qualified_name()}: armourcam",
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value=v) for k, v in values.items()],
    )
    arr = DiagnosticArray(status=[status])
    arr.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(arr)


_LEVEL_RANK = {"ok": 0, "warn": 1, "error": 2}


class RecentProblems:
    """A node's problems for its diagnostics: each shows in the level while it is recent.

    A dropped frame or a failed save is a passing event, not a state: once ``hold_s`` seconds
    pass without another, the node's level returns to OK (a rig's monitoring sees it recover),
    while the counters in the diagnostics values stay cumulative and the last problem stays
    named there (``last_problem``, ``last_problem_age_s``).

    Parameters
    ----------
    hold_s : float
        Seconds a problem keeps the level raised.
    clock : callable, optional
        Monotonic seconds (tests pass their own).
    """

    def __init__(self, hold_s: float = 30.0, clock: Callable[[], float] = time.monotonic) -> None:
        if not (hold_s > 0 and math.isfinite(hold_s)):
            raise GraphError(f"problem hold time must be > 0 s, got {hold_s}")
        self.hold_s = float(hold_s)
        self._clock = clock
        self._last: dict[str, tuple[str, float]] = {}  # level -> (text, when)
        self.last_text = ""
        self._last_t: float | None = None

    def report(self, level: str, text: str) -> None:
        """Note a problem of ``level`` ``"warn"`` or ``"error"``."""
        if level not in ("warn", "error"):
            raise GraphError(f"problem level must be warn or error, got {level!r}")
        now = self._clock()
        self._last[level] = (text, now)
        self.last_text, self._last_t = text, now

    def level(self) -> str:
        """``"error"``, ``"warn"`` or ``"ok"``: the worst problem within ``hold_s``."""
        return self._recent()[0]

    def message(self) -> str:
        """The worst recent problem's text, ``""`` when there is none."""
        return self._recent()[1]

    def values(self) -> dict[str, str]:
        """``last_problem`` and its age in seconds (empty strings before the first)."""
        age = "" if self._last_t is None else f"{self._clock() - self._last_t:.1f}"
        return {"last_problem": self.last_text, "last_problem_age_s": age}

    def _recent(self) -> tuple[str, str]:
        now = self._clock()
        for level in ("error", "warn"):
            hit = self._last.get(level)
            if hit is not None and now - hit[1] <= self.hold_s:
                return level, hit[0]
        return "ok", ""


def worst_level(*levels: str) -> str:
    """The most severe of ``"ok"``, ``"warn"`` and ``"error"`` levels."""
    return max(levels, key=_LEVEL_RANK.__getitem__, default="ok")


class FrameTimes:
    """Processing times of a node's recent frames, for its diagnostics: a rig's monitoring sees
    a node falling behind the camera (``p95`` near the frame period) before frames queue up or
    are dropped.

    Parameters
    ----------
    window : int
        Frames the statistics cover (the most recent).
    """

    def __init__(self, window: int = 100) -> None:
        if window < 1:
            raise GraphError(f"frame time window must be >= 1 frame, got {window}")
        self._ms: deque[float] = deque(maxlen=window)

    def add(self, ms: float) -> None:
        """Record one frame's processing time, milliseconds."""
        self._ms.append(float(ms))

    def values(self) -> dict[str, str]:
        """Diagnostic key/values: ``frame_ms_last``, ``frame_ms_p50``, ``frame_ms_p95``,
        ``frame_ms_max`` over the window and ``frame_ms_frames``, the frames it holds (the
        statistics are empty strings before the first frame)."""
        if not self._ms:
            stats = dict.fromkeys(("last", "p50", "p95", "max"), "")
        else:
            ordered = sorted(self._ms)
            n = len(ordered)
            # Nearest-rank percentiles: values that occurred, no interpolation.
            stats = {
                "last": f"{self._ms[-1]:.1f}",
                "p50": f"{ordered[max(0, -(-50 * n // 100) - 1)]:.1f}",
                "p95": f"{ordered[max(0, -(-95 * n // 100) - 1)]:.1f}",
                "max": f"{ordered[-1]:.1f}",
            }
        out = {f"frame_ms_{k}": v for k, v in stats.items()}
        out["frame_ms_frames"] = str(len(self._ms))
        return out


def merge_status(*parts: tuple[str, str]) -> tuple[str, str]:
    """One ``(level, message)`` of several: the worst level, and the non-empty messages joined
    by ``"; "``, the most severe first (in the given order among equals)."""
    level = worst_level(*(lv for lv, _ in parts))
    ranked = sorted(
        (p for p in parts if p[1]), key=lambda p: _LEVEL_RANK[p[0]], reverse=True
    )  # sorted() is stable: equals keep their order
    return level, "; ".join(text for _, text in ranked)


class InputAge:
    """Age of a node's last input frame, for its diagnostics: a stalled camera shows.

    Before the first frame there is no age and no warning: the node reports what it did before
    (OK, or what it waits for), since a rig idle between wave runs, or whose camera is not
    started yet, is not a fault. Once frames have come, none for longer than ``stale_after_s``
    makes the status WARN, with a message saying so; WARN, not ERROR, because between wave runs
    the camera may be stopped on purpose. The age itself is always in the values
    (``last_input_age_s``, seconds on the node's monotonic clock, not the frames' stamps).

    Parameters
    ----------
    what : str
        The input, for the message (``"image"``, ``"detections"``, ``"pose frame"``).
    stale_after_s : float
        Seconds without input after which the status is WARN; 0 disables the warning.
    clock : callable, optional
        Monotonic seconds (tests pass their own).
    """

    def __init__(
        self, what: str, stale_after_s: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if not (stale_after_s >= 0 and math.isfinite(stale_after_s)):
            raise GraphError(f"stale_after_s must be >= 0 s (0: off), got {stale_after_s}")
        self.what = what
        self.stale_after_s = float(stale_after_s)
        self._clock = clock
        self._last: float | None = None

    def received(self) -> None:
        """Note that an input frame arrived now."""
        self._last = self._clock()

    def age_s(self) -> float | None:
        """Seconds since the last input frame (None before the first)."""
        return None if self._last is None else self._clock() - self._last

    def status(self) -> tuple[str, str]:
        """``("warn", "no <what> for <age> s ...")`` while the input is stale, else
        ``("ok", "")`` (also before the first frame)."""
        age = self.age_s()
        if age is None or self.stale_after_s <= 0 or age <= self.stale_after_s:
            return "ok", ""
        return (
            "warn",
            f"no {self.what} for {age:.1f} s (stale_after_s {self.stale_after_s:g}): input "
            "stalled or stopped",
        )

    def values(self) -> dict[str, str]:
        """``last_input_age_s``: seconds, one decimal (an empty string before the first)."""
        age = self.age_s()
        return {"last_input_age_s": "" if age is None else f"{age:.1f}"}


class KeyMemory:
    """The last ``size`` distinct keys seen (a bounded memory of what came already)."""

    def __init__(self, size: int) -> None:
        self._order: deque[Hashable] = deque()
        self._keys: set[Hashable] = set()
        self.size = size

    def seen(self, key: Hashable) -> bool:
        """Whether ``key`` is remembered; if not, remember it (forgetting the oldest beyond
        ``size``)."""
        if key in self._keys:
            return True
        self._keys.add(key)
        self._order.append(key)
        while len(self._order) > self.size:
            self._keys.discard(self._order.popleft())
        return False


class RecentStamps:
    """The header stamps (with frame_id) of a node's last ``size`` input frames, to recognise a
    frame delivered again: the transient-local history a restarted upstream node (or a second
    publisher of the same frames) sends.

    A zero stamp is never taken for a repeat (a source that does not stamp its frames).
    """

    def __init__(self, size: int = 256) -> None:
        if size < 1:
            raise GraphError(f"stamp memory must hold >= 1 frame, got {size}")
        self._keys = KeyMemory(size)
        #: Frames recognised as repeats so far.
        self.repeats = 0

    def repeated(self, header: Any) -> bool:
        """Whether the frame of ``header`` (a ``std_msgs/Header``) was seen; if not, note it
        (forgetting the oldest beyond ``size``)."""
        key = (int(header.stamp.sec), int(header.stamp.nanosec), str(header.frame_id))
        if key[0] == 0 and key[1] == 0:
            return False
        if self._keys.seen(key):
            self.repeats += 1
            return True
        return False

    def skip_repeat(self, header: Any, logger: Any, what: str) -> bool:
        """:meth:`repeated`, saying so in ``logger`` (throttled) when it is: a node's intake of
        ``what`` (e.g. ``"pose frames"``) calls it first and returns on True."""
        if not self.repeated(header):
            return False
        logger.info(
            f"{what} already taken, ignored ({self.repeats} so far)", throttle_duration_sec=5.0
        )
        return True


def latched_qos(depth: int = 1) -> QoSProfile:
    """RELIABLE + TRANSIENT_LOCAL: a late subscriber gets the last ``depth`` messages."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def event_qos() -> QoSProfile:
    """Hall automation inputs: reliable, latched so a late-starting node sees the current state."""
    return latched_qos(depth=10)


# ---------------------------------------------------------------------- parameters


@dataclass(frozen=True, slots=True)
class Param:
    """A node parameter: name, default (its type fixes the parameter's type), description.

    ``read_only`` parameters are structural (topics, QoS, queue depths): fixed at start-up.
    ``choices`` restricts a string or integer parameter; ``minimum`` a numeric one.
    """

    name: str
    default: Any
    description: str
    read_only: bool = True
    choices: tuple[str, ...] | tuple[int, ...] = ()
    minimum: float | None = None


_PTYPE = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
}


def declare_parameters(node: Node, params: Sequence[Param]) -> dict[str, Any]:
    """Declare ``params`` on ``node`` and return their validated values by name.

    Raises
    ------
    GraphError
        A value has the wrong type, is not finite, is not among the choices or is below the
        minimum; the message names the node, the parameter and the value.
    """
    values: dict[str, Any] = {}
    for p in params:
        extra = ""
        if p.choices:
            extra = f" One of: {', '.join(map(str, p.choices))}."
        elif p.minimum is not None:
            extra = f" Minimum: {p.minimum}."
        desc = ParameterDescriptor(
            name=p.name,
            type=_PTYPE[type(p.default)],
            description=p.description + extra,
            read_only=p.read_only,
        )
        _float_override(node, p)
        try:
            value = node.declare_parameter(p.name, p.default, desc).value
        except Exception as err:  # rclpy raises several types for a mistyped YAML value
            raise GraphError(f"{node.get_name()}: parameter {p.name}: {err}") from err
        if isinstance(p.default, float) and isinstance(value, int):
            value = float(value)
        problem = parameter_problem(p, value)
        if problem is not None:
            raise GraphError(f"{node.get_name()}: parameter {p.name} {problem}")
        values[p.name] = value
    _accept_int_for_float(node, params)
    return values


def parameter_problem(p: Param, value: Any) -> str | None:
    """What is wrong with ``value`` for parameter ``p``, or None: the same rules at start-up
    (:func:`declare_parameters`) and for runtime changes (a node's on-set-parameters callback).

    An int is a float parameter's number (:func:`_float_override`, :func:`_accept_int_for_float`
    convert it before). Returns the message's tail: ``"must be >= 0.1, got 0.0"``.
    """
    if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, type(p.default)):
        return f"must be {type(p.default).__name__}, got {value!r}"
    if isinstance(value, float) and not math.isfinite(value):
        # NaN slips past every comparison below, infinity past the minimum.
        return f"must be a finite number, got {value!r}"
    if p.choices and value not in p.choices:
        return f"must be one of {p.choices}, got {value!r}"
    if p.minimum is not None and value < p.minimum:
        return f"must be >= {p.minimum}, got {value!r}"
    return None


def _accept_int_for_float(node: Node, params: Sequence[Param]) -> None:
    """At runtime too, an integer set for a writable float parameter (a ``set_parameters``
    service call with an INTEGER value: ``ros2 param set /pose_estimator diameter_mm 7``) is
    taken as that float, as at start-up (:func:`_float_override`). rclpy checks the type
    against the descriptor before any on-set callback runs, so the conversion is a pre-set
    callback, rclpy's hook for rewriting the list first. rclpy concatenates the lists every
    pre-set callback returns: a node must not add another one."""
    names = frozenset(p.name for p in params if not p.read_only and isinstance(p.default, float))
    if not names:
        return
    from rclpy.parameter import Parameter

    def as_float(parameters: list[Parameter[Any]]) -> list[Parameter[Any]]:
        return [
            Parameter(q.name, Parameter.Type.DOUBLE, float(q.value))
            if q.name in names and q.type_ == Parameter.Type.INTEGER
            else q
            for q in parameters
        ]

    node.add_pre_set_parameters_callback(as_float)


def _float_override(node: Node, p: Param) -> None:
    """An integer given for a float parameter (``diameter_mm: 7`` in a params file, ``-p
    dn_mm:=20``) is taken as that float: rclpy would refuse it as the wrong type, while YAML
    and a person both mean the number. rclpy keeps the overrides in a private mapping; without
    it the value reaches rclpy unchanged (and is refused, naming the parameter)."""
    overrides = getattr(node, "_parameter_overrides", None)
    if not isinstance(p.default, float) or not isinstance(overrides, dict):
        return
    given = overrides.get(p.name)
    value = getattr(given, "value", None)
    if isinstance(value, int) and not isinstance(value, bool):
        from rclpy.parameter import Parameter

        overrides[p.name] = Parameter(p.name, value=float(value))


def param_table(params: Sequence[Param]) -> str:
    """Markdown table of parameters (for the README)."""
    rows = [
        "| parameter | type | default | read-only | description |",
        "| --- | --- | --- | --- | --- |",
    ]
    for p in params:
        rows.append(
            f"| `{p.name}` | {type(p.default).__name__} | `{p.default!r}` | "
            f"{'yes' if p.read_only else 'no'} | {p.description} |"
        )
    return "\n".join(rows)


# ---------------------------------------------------------------------- running nodes


def stamp_seconds(stamp: Any) -> float:
    """A ``builtin_interfaces/Time`` as float seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


#: Fast DDS participant profile shipped with the package (a shared-memory segment that holds whole
#: 6 MP frames; see the file's comment).
DDS_PROFILE = Path(__file__).with_name("fastdds.xml")
#: Free ``/dev/shm`` the profile needs: a 64 MB segment for each of a handful of processes.
_DDS_SHM_NEEDED = 1 << 30


def use_dds_profile() -> None:
    """Point Fast DDS at :data:`DDS_PROFILE` for participants this process creates from now on,
    unless ``FASTDDS_DEFAULT_PROFILES_FILE`` is already set (a rig's own DDS configuration
    wins) or ``/dev/shm`` has too little room for the segments (a container's 64 MB default:
    Fast DDS' own small segments are used then). Child processes inherit it."""
    if "FASTDDS_DEFAULT_PROFILES_FILE" in os.environ:
        return
    try:
        st = os.statvfs("/dev/shm")
    except OSError:
        return
    if st.f_bavail * st.f_frsize >= _DDS_SHM_NEEDED:
        os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(DDS_PROFILE)


#: Exit status of a node whose parameters are invalid (:func:`_run_nodes`): not respawned.
_STATUS_BAD_PARAMETERS = 2


@contextlib.contextmanager
def _shutdown_is_a_stop() -> Iterator[None]:
    """Take an error raised once the context has been shut down (RCLError, an invalid
    handle...: a call made as a signal stopped the process, without a KeyboardInterrupt) as the
    clean stop it is; any other error propagates."""
    try:
        yield
    except Exception:
        if rclpy.ok():
            raise


def _run_nodes(
    argv: Sequence[str],
    factories: Sequence[Callable[[], Node]],
    make_executor: Callable[[], SingleThreadedExecutor | MultiThreadedExecutor],
) -> int:
    """Init, build the nodes, spin them on one executor until Ctrl-C or shutdown, clean up.

    A node whose parameters are invalid raises :class:`GraphError` in its constructor; that ends
    the process with status 2 and a one-line error, before any topic is touched.
    """
    if not end_with_launcher():
        print("error: the launcher that started this node has already exited", file=sys.stderr)
        return 1
    use_dds_profile()
    keep_freed_memory()  # per-frame temporaries stay in the process (armourcam.heap)
    # rclpy's own handler takes SIGINT and SIGTERM: it shuts the context down, so that spin()
    # returns between callbacks. It then calls the Python handler it found at init; Python's
    # default one would raise KeyboardInterrupt at whatever line runs, inside a callback or
    # rclpy's own executor and entity code (the suspected cause of a stopping node's rare
    # SIGSEGV). This one only notes the signal.
    stop_signals: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: stop_signals.append(signum))
    rclpy.init(args=list(argv))
    if stop_signals:  # came before rclpy's handler was in place: stopped before starting
        rclpy.try_shutdown()
        signal.signal(signal.SIGINT, previous)
        return 0
    executor = make_executor()
    nodes: list[Node] = []
    status = 0
    try:
        with _shutdown_is_a_stop():  # e.g. under a node being built or a callback publishing
            for factory in factories:
                nodes.append(factory())
                executor.add_node(nodes[-1])
            if rclpy.ok():
                executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except GraphError as err:
        print(f"error: {err}", file=sys.stderr)
        status = _STATUS_BAD_PARAMETERS
    finally:
        executor.shutdown()
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
        signal.signal(signal.SIGINT, previous)
    return status


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """The ``main()`` of every node (see :func:`_run_nodes` for errors and shutdown)."""
    return _run_nodes(
        list(args) if args is not None else sys.argv, [factory], SingleThreadedExecutor
    )


def node_factories() -> dict[str, Callable[[], Node]]:
    """The three node classes by node name (imported here so the CLI stays light)."""
    out: dict[str, Callable[[], Node]] = {}
    for name in NODE_NAMES:
        module = importlib.import_module(f"{name}.node")
        out[name] = module.NODE_CLASS
    return out


def run_one_process(
    params_file: str | None = None, *, multithreaded: bool = True, ros_args: Sequence[str] = ()
) -> int:
    """Run all three nodes in this process on one executor until Ctrl-C.

    ``ros_args`` (remaps such as ``__ns``, ``-p`` parameters) apply to every node; they come
    after the params file, so a ``-p`` given there wins over the file, as in a node process
    (:func:`node_command`).
    """
    argv = ["armourcam-graph", "--ros-args"]
    if params_file:
        argv += ["--params-file", str(params_file)]
    argv += list(ros_args)

    def make_executor() -> SingleThreadedExecutor | MultiThreadedExecutor:
        return MultiThreadedExecutor(num_threads=3) if multithreaded else SingleThreadedExecutor()

    return _run_nodes(argv, list(node_factories().values()), make_executor)


def node_command(
    name: str, params_file: str | None = None, ros_args: Sequence[str] = ()
) -> list[str]:
    """Command line that starts node ``name`` as its own process with this interpreter."""
    if name not in NODE_NAMES:
        raise GraphError(f"unknown node {name!r}; nodes: {NODE_NAMES}")
    cmd = [sys.executable, "-m", f"{name}.node", "--ros-args"]
    if params_file:
        cmd += ["--params-file", str(params_file)]
    return cmd + list(ros_args)


#: Set by :func:`launch_processes` in each node's environment: the launcher's process id.
LAUNCHER_PID_ENV = "ARMOURCAM_LAUNCHER_PID"
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def end_with_launcher() -> bool:
    """In a node started by :func:`launch_processes`, ask the kernel for SIGTERM when the
    launcher dies, however it dies (SIGKILL, a closed terminal's SIGHUP, a crash): the nodes
    run in their own sessions (so a Ctrl-C reaches them through the launcher, in order), and
    would otherwise live on unseen. SIGTERM then stops the node cleanly (rclpy's handler).

    Returns False when the launcher is already gone (it died before the request), True
    otherwise, and also for a process not started by the launcher or off Linux.
    """
    launcher = os.environ.pop(LAUNCHER_PID_ENV, "")
    if not launcher.isdigit() or not sys.platform.startswith("linux"):
        return True
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    # Reparented already: the launcher died before the request could cover it.
    return os.getppid() == int(launcher)


#: CPU niceness of nodes started by :func:`launch_processes`. The matcher's work at the end of a
#: run (fusing, matching, unit motions, the report: about half a second of one core) is not
#: urgent, while every frame's detection and pose are: on a two-core rig the matcher yields.
NICENESS: dict[str, int] = {"displacement_matcher": 10}


def launch_processes(
    params_file: str | None = None,
    *,
    nodes: Sequence[str] = NODE_NAMES,
    env: dict[str, str] | None = None,
    log_dir: Path | None = None,
    ros_args: Sequence[str] = (),
    niceness: Mapping[str, int] | None = None,
) -> dict[str, subprocess.Popen[bytes]]:
    """Start each node as its own process, each in its own process group.

    The nodes end when this process does, however it ends (:func:`end_with_launcher`). The
    nodes get one BLAS thread each (:mod:`armourcam.blas`) unless ``env`` says otherwise.
    Output goes to ``log_dir/<node>.log`` when given (else inherited). ``niceness`` (default
    :data:`NICENESS`) lowers the CPU priority of the named nodes by that much. Stop them with
    :func:`stop_processes`.
    """
    niceness = NICENESS if niceness is None else niceness
    child_env = one_blas_thread(dict(env if env is not None else os.environ))
    child_env[LAUNCHER_PID_ENV] = str(os.getpid())  # the nodes end with us (end_with_launcher)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for name in nodes:
            out: Any = None
            if log_dir is not None:
                log_dir.mkdir(parents=True, exist_ok=True)
                out = open(log_dir / f"{name}.log", "ab")  # noqa: SIM115 - owned by the child
            procs[name] = subprocess.Popen(
                node_command(name, params_file, ros_args),
                env=child_env,
                stdout=out,
                stderr=subprocess.STDOUT if out is not None else None,
                start_new_session=True,
            )
            if out is not None:
                out.close()
            if niceness.get(name, 0) > 0:
                # Raised right after the start, before the node has done any work.
                with contextlib.suppress(OSError):
                    nice = min(19, os.getpriority(os.PRIO_PROCESS, 0) + niceness[name])
                    os.setpriority(os.PRIO_PROCESS, procs[name].pid, nice)
    except BaseException:
        stop_processes(procs.values())
        raise
    return procs


def stop_processes(procs: Any, timeout: float = 5.0) -> dict[int, int | None]:
    """SIGINT each process group, then SIGKILL whatever is left after ``timeout`` seconds."""
    procs = list(procs)
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGINT)
    deadline = time.monotonic() + timeout
    for p in procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(max(0.0, deadline - time.monotonic()))
    for p in procs:
        # The group may hold children even after the leader exited.
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(p.pid, signal.SIGKILL)
        if p.poll() is None:
            p.wait(5.0)
    return {p.pid: p.returncode for p in procs}


#: ``armourcam graph --respawn``: a node that had to be restarted this many times within
#: :data:`RESPAWN_WINDOW_S` seconds (failing again at once) is given up on, and the graph stops.
RESPAWN_LIMIT = 5
RESPAWN_WINDOW_S = 60.0


class RestartBudget:
    """The restarts of one node: at most ``limit`` within any ``window_s`` seconds.

    Times are the caller's monotonic clock, seconds.
    """

    def __init__(self, limit: int = RESPAWN_LIMIT, window_s: float = RESPAWN_WINDOW_S) -> None:
        if limit < 0 or not (window_s > 0 and math.isfinite(window_s)):
            raise GraphError(
                f"restart limit must be >= 0 and window > 0 s, got {limit}, {window_s}"
            )
        self.limit = limit
        self.window_s = window_s
        self._times: deque[float] = deque()

    def take(self, now_s: float) -> bool:
        """Count a restart at ``now_s``; False, counting nothing, when ``limit`` restarts were
        made in the ``window_s`` seconds before it."""
        while self._times and self._times[0] <= now_s - self.window_s:
            self._times.popleft()
        if len(self._times) >= self.limit:
            return False
        self._times.append(now_s)
        return True

    def __len__(self) -> int:
        """Restarts counted within the window, as of the last :meth:`take`."""
        return len(self._times)


def describe_exit(returncode: int) -> str:
    """A process' exit for a log line: its status, or ``-9 (SIGKILL)`` when a signal ended it."""
    if returncode >= 0:
        return str(returncode)
    try:
        name = signal.Signals(-returncode).name
    except ValueError:
        name = f"signal {-returncode}"
    return f"{returncode} ({name})"


def log_launcher(text: str) -> None:
    """One line of the ``armourcam graph`` launcher on stderr."""
    print(f"armourcam graph: {text}", file=sys.stderr, flush=True)


def supervise_processes(
    procs: dict[str, subprocess.Popen[bytes]],
    stopping: Callable[[], bool],
    *,
    respawn: Callable[[str], subprocess.Popen[bytes]] | None = None,
    respawn_delay_s: float = 2.0,
    respawn_limit: int = RESPAWN_LIMIT,
    respawn_window_s: float = RESPAWN_WINDOW_S,
    poll_s: float = 0.2,
    log: Callable[[str], None] = log_launcher,
) -> int:
    """Watch the nodes :func:`launch_processes` started until ``stopping()`` is true or a node's
    exit ends the graph; returns 0 or, when a node ended it, 1.

    Without ``respawn`` (ROS launch's default) a node exiting ends the graph; ``log`` names the
    node and its exit status. With ``respawn`` (``respawn(name)`` starts node ``name`` again and
    returns its process) a node that fails while the graph runs, with a non-zero status or
    killed by a signal, is started again ``respawn_delay_s`` seconds later, and ``log`` says so
    with its exit status. Not respawned, ending the graph as without ``respawn``: a node that
    exited with status 0 (stopped on purpose: SIGINT and SIGTERM end a node cleanly), one whose
    parameters are invalid (status 2: it would fail again), and one that needed more than
    ``respawn_limit`` restarts within ``respawn_window_s`` seconds.

    ``procs`` is kept current in place (a respawned node's new process replaces the old one, a
    node waiting for its respawn is absent), so that the caller's :func:`stop_processes` after
    this returns (or raises, e.g. ``KeyboardInterrupt``) stops every node still running. A
    stopping graph (``stopping()`` true) respawns nothing.
    """
    budgets = {name: RestartBudget(respawn_limit, respawn_window_s) for name in procs}
    due: dict[str, float] = {}  # node waiting for its respawn -> when, monotonic seconds
    while not stopping():
        now = time.monotonic()
        ended = False
        for name, proc in list(procs.items()):
            code = proc.poll()
            if code is None:
                continue
            del procs[name]
            stop_processes([proc], timeout=0.0)  # whatever its process group still holds
            exited = f"{name} exited with {describe_exit(code)}"
            if respawn is None:
                log(f"{exited}; stopping the graph")
                ended = True
            elif code == 0:
                log(f"{exited} (stopped on purpose): not respawned; stopping the graph")
                ended = True
            elif code == _STATUS_BAD_PARAMETERS:
                log(f"{exited} (invalid parameters): not respawned; stopping the graph")
                ended = True
            elif not budgets[name].take(now):
                log(
                    f"{exited}; it was respawned {respawn_limit} times within "
                    f"{respawn_window_s:g} s: giving up, stopping the graph"
                )
                ended = True
            else:
                log(
                    f"{exited}; respawning in {respawn_delay_s:g} s (restart {len(budgets[name])} "
                    f"of at most {respawn_limit} within {respawn_window_s:g} s)"
                )
                due[name] = now + respawn_delay_s
        if ended:
            return 1
        for name, at in list(due.items()):
            if respawn is not None and now >= at and not stopping():
                del due[name]
                procs[name] = respawn(name)
                log(f"{name} respawned (pid {procs[name].pid})")
        time.sleep(poll_s)
    return 0


# ---------------------------------------------------------------------- message conversion


def message_class(msgtype: str) -> Any:
    """The rclpy message class of a ROS type name (``sensor_msgs/msg/Image`` or ``.../Image``)."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3:
        raise GraphError(f"not a message type name: {msgtype!r}")
    try:
        module = importlib.import_module(f"{parts[0]}.{parts[1]}")
        return getattr(module, parts[2])
    except (ImportError, AttributeError) as err:
        raise GraphError(f"message type {msgtype} is not available to rclpy: {err}") from err


# ---------------------------------------------------------------------- replay


@dataclass(frozen=True, slots=True)
class ReplayStats:
    """What a replay published."""

    published: dict[str, int]  # messages per topic, by full (resolved) name
    frames: int
    frames_confirmed: int
    seconds: float


class Replayer:
    """Publishers for a replay and the bookkeeping of ``--as-fast-as-consumed``.

    Parameters
    ----------
    node : Node
        The replay's node.
    qos : {"reliable", "sensor_data"}
        QoS of the per-frame streams (images, camera info, the graph's record streams); see
        :meth:`qos` for each kind of topic.
    depth : int
        KEEP_LAST depth of the per-frame publishers.
    confirm_topic : str or None
        As-fast-as-consumed: the detector's output; :meth:`wait_confirmed` waits for the
        message whose header stamp equals a frame's.
    downstream_topic : str or None
        The pose estimator's output (see :meth:`wait_downstream`).
    confirm_timeout : float
        Seconds to wait for each confirmation.
    """

    def __init__(
        self,
        node: Node,
        *,
        qos: str = "reliable",
        depth: int = 100,
        confirm_topic: str | None = None,
        downstream_topic: str | None = "armourcam/poses",
        confirm_timeout: float = 30.0,
    ) -> None:
        from std_msgs.msg import Header  # noqa: F401  (ensures std_msgs is importable early)

        self.node = node
        self.qos_name = qos
        self.depth = depth
        self.confirm_topic = confirm_topic
        self.confirm_timeout = confirm_timeout
        self._pubs: dict[str, Any] = {}
        self._confirmed: set[tuple[int, int]] = set()
        self._downstream: set[tuple[int, int]] = set()
        self._cond = threading.Condition()
        self.downstream_sub: Any = None
        if confirm_topic:
            from sensor_msgs.msg import PointCloud2

            # The graph's outputs have the replay's QoS: a reliable reader would not match the
            # best-effort writers of a sensor_data graph, and every frame would time out.
            watch = stream_qos(qos, 100)
            node.create_subscription(PointCloud2, confirm_topic, self._on_confirm, watch)
            if downstream_topic:
                self.downstream_sub = node.create_subscription(
                    PointCloud2, downstream_topic, self._on_downstream, watch
                )

    def _on_confirm(self, msg: Any) -> None:
        with self._cond:
            self._confirmed.add((msg.header.stamp.sec, msg.header.stamp.nanosec))
            self._cond.notify_all()

    def _on_downstream(self, msg: Any) -> None:
        with self._cond:
            self._downstream.add((msg.header.stamp.sec, msg.header.stamp.nanosec))
            self._cond.notify_all()

    def wait_downstream(self, stamp: Any, timeout: float) -> bool:
        """Wait for the pose estimator's output stamped ``stamp``; True when none is running."""
        if self.downstream_sub is None or self.downstream_sub.get_publisher_count() == 0:
            return True
        key = (stamp.sec, stamp.nanosec)
        deadline = time.monotonic() + timeout
        with self._cond:
            while key not in self._downstream:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            self._downstream.discard(key)
        return True

    def qos(self, msgtype: str, *, latched: bool = False) -> QoSProfile:
        """QoS a topic of type ``msgtype`` is republished with, matching every subscriber the
        graph has for it.

        - hall topics (``std_msgs``): :func:`event_qos` (reliable, transient-local);
        - images and camera info: :func:`stream_qos`, VOLATILE even if ``latched`` (a
          transient-local history of ``depth`` 6 MP frames would hold gigabytes);
        - the graph's record streams (``PointCloud2``): :func:`record_qos`, whose
          TRANSIENT_LOCAL (in ``reliable`` mode) matches volatile and transient-local readers
          alike (the pose estimator and the matcher subscribe transient-local); ``latched``:
          reliable and transient-local whatever ``qos``;
        - other ``latched`` topics (the bag recorded a TRANSIENT_LOCAL offered QoS, as for the
          matcher's markers): :func:`latched_qos`, as the matcher publishes them;
        - anything else: :func:`stream_qos`.
        """
        from armourcam.bagio import normal_type

        msgtype = normal_type(msgtype)  # a ROS 1 bag's pkg/Name
        if msgtype.startswith("std_msgs/"):
            return event_qos()
        if msgtype in (*IMAGE_TYPES, "sensor_msgs/msg/CameraInfo"):
            return stream_qos(self.qos_name, self.depth)
        if msgtype == "sensor_msgs/msg/PointCloud2":
            return record_qos("reliable" if latched else self.qos_name, self.depth)
        if latched:
            return latched_qos()
        return stream_qos(self.qos_name, self.depth)

    def publisher(self, topic: str, msgtype: str, *, latched: bool = False) -> Any:
        """The publisher for ``topic``, created on first use with :meth:`qos` (``latched``: the
        bag recorded the topic TRANSIENT_LOCAL, see ``bagio.TopicInfo.latched``)."""
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self.node.create_publisher(
                message_class(msgtype), topic, self.qos(msgtype, latched=latched)
            )
            self._pubs[topic] = pub
        return pub

    def drain(self, timeout: float) -> list[str]:
        """Wait until every matched reliable reader has acknowledged what was published (a
        latched hall event or the last frames would otherwise die with this process while still
        in flight); returns the topics not acknowledged within ``timeout`` seconds."""
        from rclpy.duration import Duration
        from rclpy.qos import ReliabilityPolicy

        deadline = time.monotonic() + timeout
        unacked = []
        for topic, pub in self._pubs.items():
            if pub.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
                continue
            left = max(deadline - time.monotonic(), 0.0)
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                unacked.append(topic)
        return unacked

    def wait_for_subscribers(self, topics: Sequence[str], timeout: float) -> list[str]:
        """Wait until each topic's publisher is matched; returns the topics still unmatched."""
        deadline = time.monotonic() + timeout
        missing = list(topics)
        while missing and time.monotonic() < deadline:
            missing = [t for t in missing if self._pubs[t].get_subscription_count() == 0]
            if missing:
                time.sleep(0.05)
        return missing

    def wait_for_graph(self, topics: Sequence[str], timeout: float) -> list[str]:
        """Wait until every topic has a subscriber in the graph other than this replayer's own
        (e.g. the matcher on the pose topic: its frames are published by another node, so they
        would be lost while it is still being discovered); returns the topics still waiting.
        Relative names resolve in the replay node's namespace."""
        full = {t: self.node.resolve_topic_name(t) for t in topics}
        own = dict.fromkeys(full.values(), 0)
        for sub in self.node.subscriptions:
            if sub.topic_name in own:
                own[sub.topic_name] += 1
        deadline = time.monotonic() + timeout
        missing = list(topics)
        while missing and time.monotonic() < deadline:
            missing = [t for t in missing if self.node.count_subscribers(full[t]) <= own[full[t]]]
            if missing:
                time.sleep(0.05)
        return missing

    def wait_confirmed(self, stamp: Any) -> bool:
        """Wait for the consumer's output stamped ``stamp``; False on timeout."""
        key = (stamp.sec, stamp.nanosec)
        deadline = time.monotonic() + self.confirm_timeout
        with self._cond:
            while key not in self._confirmed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            self._confirmed.discard(key)
        return True


def _stamp_now(node: Node, last: list[int]) -> Any:
    """Current time as a Time message, strictly increasing within this replay."""
    ns = node.get_clock().now().nanoseconds
    if ns <= last[0]:
        ns = last[0] + 1000
    last[0] = ns
    from builtin_interfaces.msg import Time

    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")

#: Names that stay absolute whatever the namespace (ROS conventions: the diagnostics
#: aggregator's input, the log, parameter events, the transform tree).
GLOBAL_TOPICS = frozenset({"/diagnostics", "/rosout", "/parameter_events", "/tf", "/tf_static"})


def replay_name(bag_topic: str, remap: Mapping[str, str]) -> str:
    """The name a replay publishes bag topic ``bag_topic`` under (``""``: skipped).

    A ``remap`` target is used as given (absolute, or relative to the replay node's namespace).
    Otherwise the bag's name is made relative (``/camera/image_raw`` -> ``camera/image_raw``),
    so it resolves in the replay node's namespace as the nodes' relative default names resolve
    in theirs: ``armourcam replay BAG --ros-args -r __ns:=/cell2`` feeds a graph started with
    ``__ns:=/cell2``, and without a namespace the bag's own names are published.
    :data:`GLOBAL_TOPICS` stay absolute.
    """
    if bag_topic in remap:
        return remap[bag_topic]
    if bag_topic in GLOBAL_TOPICS:
        return bag_topic
    return bag_topic.lstrip("/")


def replay_bag(
    bag: Path,
    *,
    remap: dict[str, str],
    qos: str = "reliable",
    rate: float | None = 1.0,
    as_fast_as_consumed: bool = False,
    confirm_topic: str = "armourcam/detections",
    restamp: bool = True,
    wait_subscribers: float = 10.0,
    wait_for: Sequence[str] = (),
    match_grace_s: float = 1.0,
    hall_gap_s: float = 0.3,
    settle_s: float = 0.0,
    drain_s: float = 5.0,
    progress: Callable[[int, int], None] | None = None,
    ros_args: Sequence[str] = (),
    messages: Callable[[], Iterator[tuple[str, str, int, Any]]] | None = None,
) -> ReplayStats:
    """Publish a bag into the graph (the body of ``armourcam replay``).

    Parameters
    ----------
    bag : Path
        The bag; read with :mod:`armourcam.bagio`.
    remap : dict
        Bag topic -> published topic. Topics not in it keep their name, relative to the replay
        node's namespace (:func:`replay_name`; ``ros_args`` may set it); a topic mapped to
        ``""`` is skipped.
    qos, rate, as_fast_as_consumed, confirm_topic
        See :class:`Replayer`. ``as_fast_as_consumed`` waits for the detector's output stamped like
        each image before the next message (reliable, lossless by construction).
    restamp : bool
        Stamp headers with publication time (see :class:`Replayer`).
    wait_subscribers : float
        Seconds to wait for every image/camera-info publisher to be matched before starting.
    wait_for : sequence of str
        Topics (e.g. ``/armourcam/poses``) that must have a subscriber in the graph before
        starting, within the same ``wait_subscribers`` seconds.
    settle_s : float
        Seconds to keep spinning after the last message.
    drain_s : float
        Seconds, at most, to wait at the end for every matched reliable subscriber to
        acknowledge what was published (:meth:`Replayer.drain`).
    messages : callable, optional
        Source of ``(topic, msgtype, time_ns, rosbags_message)`` (default: the bag's messages).
    """
    from armourcam import bagio

    if rate is not None and rate <= 0:
        raise GraphError(f"rate must be > 0, got {rate}")
    use_dds_profile()
    rclpy.init(args=["armourcam-replay", "--ros-args", *ros_args])
    node = rclpy.create_node("armourcam_replay")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=_spin_quietly, args=(executor,), daemon=True)
    spinner.start()
    replayer = Replayer(node, qos=qos, confirm_topic=confirm_topic if as_fast_as_consumed else None)
    published: dict[str, int] = {}
    frames = confirmed = 0
    t_start = time.monotonic()
    try:
        with _shutdown_is_a_stop():
            # Messages are streamed from the bag (a 6 MP session does not fit in memory); the
            # topics come from its metadata.
            if messages is not None:
                listed = list(_plan(messages(), remap))
                topics = {t: mt for t, mt, _, _ in listed}
                latched: set[str] = set()  # no metadata to tell
                total = len(listed)
                items: Iterator[tuple[str, str, int, Any]] = iter(listed)
            else:
                with bagio.open_bag(bag) as b:
                    if b.message_count == 0:
                        raise GraphError(f"{bag}: the bag holds no messages")
                    infos = [i for i in b.topics.values() if replay_name(i.topic, remap)]
                topics = {replay_name(i.topic, remap): i.msgtype for i in infos}
                # Recorded with a TRANSIENT_LOCAL offered QoS: republished latched (Replayer.qos).
                latched = {replay_name(i.topic, remap) for i in infos if i.latched}
                total = sum(i.count for i in infos)
                items = _plan(_bag_messages(bag), remap)
            # Create every publisher first and wait for the graph to match them, so that the first
            # frames are not published into the void.
            for topic, msgtype in topics.items():
                replayer.publisher(topic, msgtype, latched=topic in latched)
            waited = [t for t, mt in topics.items() if not mt.startswith("std_msgs/")]
            missing = replayer.wait_for_subscribers(sorted(set(waited)), wait_subscribers)
            missing += replayer.wait_for_graph(list(wait_for), wait_subscribers)
            if missing:
                node.get_logger().warning(f"no subscriber yet on {missing}; publishing anyway")
            # A publisher sees the match before the subscriber has matched it back; samples sent in
            # between are not delivered to a volatile reader. Give discovery a moment to finish.
            time.sleep(match_grace_s)
            last_ns = [0]
            restamped: dict[tuple[int, int], Any] = {}  # recorded stamp -> new (the latest few)
            last_info: list[tuple[str, str, Any]] = []
            t0_bag: int | None = None
            t0_wall = time.monotonic()
            for i, (topic, msgtype, t_ns, obj) in enumerate(items):
                if not rclpy.ok():  # SIGINT or SIGTERM without a KeyboardInterrupt (see record)
                    break
                if rate is not None and not as_fast_as_consumed:
                    t0_bag = t_ns if t0_bag is None else t0_bag
                    due = t0_wall + (t_ns - t0_bag) / 1e9 / rate
                    _sleep_while_ok(due - time.monotonic())
                msg = bagio.copy_message(obj, message_class(msgtype))
                if restamp and hasattr(msg, "header"):
                    # One new stamp per recorded stamp: an image and its camera info stay paired
                    # for exact-time synchronisers (image_proc, viewers).
                    old = (msg.header.stamp.sec, msg.header.stamp.nanosec)
                    new = restamped.get(old)
                    if new is None:
                        new = _stamp_now(node, last_ns)
                        restamped[old] = new
                        while len(restamped) > 16:
                            del restamped[next(iter(restamped))]
                    msg.header.stamp = new
                pub = replayer.publisher(topic, msgtype)
                pub.publish(msg)
                published[pub.topic_name] = published.get(pub.topic_name, 0) + 1  # resolved name
                if msgtype == "sensor_msgs/msg/CameraInfo":
                    last_info[:] = [(topic, msgtype, msg)]
                if msgtype.startswith("std_msgs/") and as_fast_as_consumed:
                    # Hall events travel on their own topics: without recorded gaps, give each a
                    # head start so the matcher orders it against the frames around it.
                    time.sleep(hall_gap_s)
                if msgtype in IMAGE_TYPES:
                    frames += 1
                    if as_fast_as_consumed:
                        if replayer.wait_confirmed(msg.header.stamp):
                            confirmed += 1
                            # The pose estimator holds frames until it has a camera; camera info
                            # sent while discovery was still settling may not have reached it.
                            if not replayer.wait_downstream(msg.header.stamp, 3.0) and last_info:
                                info_topic, info_type, info = last_info[-1]
                                info.header.stamp = _stamp_now(node, last_ns)
                                replayer.publisher(info_topic, info_type).publish(info)
                                replayer.wait_downstream(msg.header.stamp, replayer.confirm_timeout)
                        else:
                            node.get_logger().error(
                                f"no output on {confirm_topic} for frame {frames} within "
                                f"{replayer.confirm_timeout:.0f} s"
                            )
                if progress is not None:
                    progress(i + 1, total)
            _sleep_while_ok(settle_s)
            unacked = replayer.drain(drain_s) if rclpy.ok() else []
            if unacked:
                node.get_logger().warning(
                    f"not acknowledged by every subscriber within {drain_s:.0f} s: {unacked}"
                )
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        spinner.join(2.0)
    return ReplayStats(published, frames, confirmed, time.monotonic() - t_start)


def _sleep_while_ok(seconds: float) -> None:
    """Sleep ``seconds`` (nothing if not positive), ending early once the context is shut
    down: a signal does not interrupt the sleep when it raises no KeyboardInterrupt."""
    end = time.monotonic() + seconds
    while rclpy.ok() and (left := end - time.monotonic()) > 0:
        time.sleep(min(left, 0.1))


def _bag_messages(bag: Path) -> Iterator[tuple[str, str, int, Any]]:
    from armourcam import bagio

    with bagio.open_bag(bag) as b:
        for m in b.messages(on_truncation="report"):
            yield m.topic, m.msgtype, m.timestamp_ns, m.message
        if b.truncation is not None:
            print(f"armourcam replay: {b.truncation.describe()}", file=sys.stderr)


def _spin_quietly(executor: Any) -> None:
    with contextlib.suppress(ExternalShutdownException, KeyboardInterrupt, Exception):
        executor.spin()


def _plan(
    messages: Iterator[tuple[str, str, int, Any]], remap: dict[str, str]
) -> Iterator[tuple[str, str, int, Any]]:
    for topic, msgtype, t_ns, obj in messages:
        target = replay_name(topic, remap)
        if target:
            yield target, msgtype, t_ns, obj


# ---------------------------------------------------------------------- record


#: Subscribed (``std_msgs/msg/Empty``, never published) by a recording once it is ready, after its
#: own subscriptions: ``armourcam replay BAG --wait-for armourcam/recorder_ready`` publishes only
#: once it has discovered it, and so the recorder's subscriptions (see :func:`record_topics`).
#: Relative: in the recorder's namespace, as the replay's ``--wait-for`` names are in its own.
RECORDER_READY_TOPIC = "armourcam/recorder_ready"


@dataclass(frozen=True, slots=True)
class RecordReady:
    """What :func:`record_topics` reports when it is ready (full topic names)."""

    #: Topics subscribed: of known type (at once) or with a publisher discovered.
    subscribed: tuple[str, ...]
    #: Topics of unknown type without a publisher yet: subscribed once one is discovered.
    awaiting: tuple[str, ...]
    #: Subscribed topics with a discovered publisher still unmatched when the wait ended.
    unmatched: tuple[str, ...]


def record_topics(
    out: Path,
    topics: Sequence[str],
    *,
    types: Mapping[str, str] | None = None,
    duration: float | None = None,
    stop: threading.Event | None = None,
    ready: Callable[[RecordReady], None] | None = None,
    discovery_s: float = 1.0,
    ready_timeout_s: float = 10.0,
    ros_args: Sequence[str] = (),
) -> dict[str, int]:
    """Record ``topics`` into an MCAP bag until stopped (the body of ``armourcam record``).

    Parameters
    ----------
    out : Path
        The bag directory to create.
    topics : sequence of str
        Topics to record. Relative names resolve in the recorder's namespace (``ros_args``
        such as ``-r __ns:=/cell2``); the bag stores full names.
    types : mapping, optional
        Known message types (``sensor_msgs/msg/Image``) by topic name, resolved as ``topics``
        are: those topics are subscribed at once, before any publisher exists. The others are
        subscribed once a publisher is discovered, with its type.
    duration : float, optional
        Seconds to record (default: until ``stop``, Ctrl-C or an external shutdown).
    stop : threading.Event, optional
        Set to end the recording.
    ready : callable, optional
        Called once with a :class:`RecordReady` when the recorder is ready (see Notes).
    discovery_s, ready_timeout_s : float
        Readiness comes no sooner than ``discovery_s`` seconds after the start (the graph's
        publishers are discovered meanwhile) and no later than ``ready_timeout_s``.
    ros_args : sequence of str
        Arguments for rclpy (remaps, ``__ns``, ``--log-level``).

    Returns
    -------
    dict
        Messages recorded per topic, by full name.

    Notes
    -----
    Subscriptions: a topic of known type is subscribed up front with the QoS the graph's and a
    replay's publishers of that type offer (:func:`_expected_offers`: transient-local for the
    record streams, the matcher's outputs and the hall topics, reliable and volatile
    otherwise). Each publisher discovered later gets a subscription mirroring its offered QoS
    unless one has it (:func:`_recording_qos` of its profile: best effort for a live camera at
    ``sensor_data``, transient-local for a latched publisher), so it is recorded as reliably as
    it publishes, with its history if it keeps one. A message delivered by several of a
    topic's subscriptions is written once (publisher GID and sequence number tell them apart).
    Publishers of another type than the topic's (the known one, else the first discovered)
    are ignored with a warning.

    Readiness: the recorder is ready once every subscription exists and every publisher
    discovered in the first ``discovery_s`` seconds is matched (or ``ready_timeout_s`` passed:
    ``RecordReady.unmatched`` names the topics still waiting). It then subscribes to
    :data:`RECORDER_READY_TOPIC` (after its other subscriptions, so a node that discovered
    that one has discovered them) and calls ``ready``. What it guarantees:

    - a publisher of a known topic that appears later finds the recorder's subscription in
      the graph: once the publisher's node has discovered it, a publisher created then is
      matched at once and everything it publishes is recorded (completely for a reliable
      publisher whose history keeps up with the recorder);
    - ``armourcam replay BAG --wait-for armourcam/recorder_ready`` (same namespace) starts
      publishing only after that, plus a second (``match_grace_s``): the replay is recorded
      whole even when started together with the recorder, or while other nodes (a running
      graph) already satisfy its own wait for subscribers. Without ``--wait-for`` a replay
      started after ``ready`` is recorded whole when the recorder is the only subscriber of
      its images and camera info (the replay waits for it; latched topics keep their
      history anyway), else only if it discovers the recorder within that second. With
      several recorders ``--wait-for`` waits for one;
    - latched (transient-local) topics are recorded with the history their publishers keep
      (up to 100 messages), whenever the recorder joins;
    - a topic of unknown type is subscribed only when its first publisher is discovered: what
      that publisher sent before the match is lost, unless it is latched.

    Log time: a message's source timestamp (when its publisher published it, on that
    publisher's clock; the receipt time when the middleware gives none), so latched history
    delivered late is logged when it was published and the bag orders messages as they were
    published (``armourcam analyze`` orders hall events against frames by it). Across hosts
    the clocks must agree (NTP, PTP). A bag may start before its recording did, by the age of
    the oldest latched message. Messages are written as they arrive; bag readers sort by log
    time (a recovered, truncated MCAP is read in file order).

    Storage: messages are stored as received (CDR bytes, not decoded). A topic enters the bag
    when its first publisher is discovered (a topic without publishers is left out), with the
    offered QoS profiles of the publishers discovered by then, so a replay republishes latched
    topics latched.
    """
    from armourcam import bagio

    use_dds_profile()
    rclpy.init(args=["armourcam-record", "--ros-args", *ros_args])
    node = rclpy.create_node("armourcam_record")
    names = [node.resolve_topic_name(t) for t in topics]
    stop = stop or threading.Event()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    t_start = time.monotonic()
    t_end = None if duration is None else t_start + duration
    announced = False
    written: dict[str, int] = {}  # full name -> messages written (the writer's own count)
    try:
        with _shutdown_is_a_stop(), bagio.BagWriter(out) as writer:
            written = writer.counts
            recorder = _Recorder(node, writer, names, types or {})
            # rclpy's handler shuts the context down on SIGINT or SIGTERM, also when the
            # process started with SIGINT ignored (no KeyboardInterrupt then).
            while not stop.is_set() and rclpy.ok():
                recorder.follow_publishers()
                executor.spin_once(timeout_sec=0.1)
                now = time.monotonic()
                if not announced and now - t_start >= discovery_s:
                    unmatched = recorder.unmatched()
                    if not unmatched or now - t_start >= ready_timeout_s:
                        recorder.announce_ready()
                        if ready is not None:
                            ready(recorder.readiness(unmatched))
                        announced = True
                if t_end is not None and now > t_end:
                    break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return {t: written.get(t, 0) for t in names}


#: Types whose publishers in the graph latch (RELIABLE + TRANSIENT_LOCAL): the record streams in
#: reliable mode (:func:`record_qos`) and the matcher's outputs.
_LATCHED_TYPES = frozenset({"sensor_msgs/msg/PointCloud2", "visualization_msgs/msg/MarkerArray"})
#: Events and the report: a replay publishes events latched (:func:`event_qos`), the matcher its
#: report too, while a hall or an operator's tool may publish volatile, which a transient-local
#: reader never matches; so both readers (as the matcher's hall inputs).
_EVENT_TYPES = frozenset({"std_msgs/msg/String", "std_msgs/msg/Bool", "std_msgs/msg/Empty"})
#: Messages remembered to write a message delivered by two subscriptions once.
_SEEN_WINDOW = 4096


def _expected_offers(msgtype: str) -> list[QoSProfile]:
    """The QoS profiles the graph's (and a replay's) publishers of ``msgtype`` offer: a
    recording subscribes to match them before any publisher is discovered."""
    reliable = stream_qos("reliable", 10)
    if msgtype in _EVENT_TYPES:
        return [latched_qos(), reliable]
    if msgtype in _LATCHED_TYPES:
        return [latched_qos()]
    return [reliable]


def _serves(subscription: QoSProfile, offered: QoSProfile) -> bool:
    """Whether a subscription with QoS ``subscription`` matches a publisher offering
    ``offered`` (reliability and durability; the only policies a recording sets)."""
    reliable_ok = (
        subscription.reliability != ReliabilityPolicy.RELIABLE
        or offered.reliability == ReliabilityPolicy.RELIABLE
    )
    durable_ok = (
        subscription.durability != DurabilityPolicy.TRANSIENT_LOCAL
        or offered.durability == DurabilityPolicy.TRANSIENT_LOCAL
    )
    return reliable_ok and durable_ok


class _Recorder:
    """Subscriptions, de-duplication and bag writing of one :func:`record_topics` run.

    Runs on the recording's one executor thread (subscriptions and polling alike).
    """

    def __init__(
        self, node: Node, writer: Any, topics: Sequence[str], types: Mapping[str, str]
    ) -> None:
        from armourcam.bagio import normal_type

        self.node = node
        self.writer = writer
        known = {node.resolve_topic_name(t): normal_type(mt) for t, mt in types.items()}
        self.types = {t: known[t] for t in topics if t in known}
        # Per topic, its subscriptions by (reliability, durability).
        self.subs: dict[str, dict[tuple[Any, Any], Any]] = {t: {} for t in topics}
        self._warned: set[tuple[str, str]] = set()
        self._seen = KeyMemory(_SEEN_WINDOW)
        self._next_poll = 0.0
        self._ready_sub: Any = None
        for topic, msgtype in self.types.items():
            for offered in _expected_offers(msgtype):
                self._subscribe(topic, offered)

    def follow_publishers(self) -> None:
        """Subscribe to match publishers discovered since the last call (every 0.1 s at most)."""
        now = time.monotonic()
        if now < self._next_poll:
            return
        self._next_poll = now + 0.1
        for topic in list(self.subs):
            infos = self.node.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            msgtype = self.types.setdefault(topic, infos[0].topic_type)
            for other in {i.topic_type for i in infos} - {msgtype}:
                self._warn_once(topic, f"{topic}: ignoring publishers of {other}, not {msgtype}")
            offered = [i.qos_profile for i in infos if i.topic_type == msgtype]
            if not offered:
                continue
            try:
                for qos in offered:
                    self._subscribe(topic, qos)
            except GraphError as err:  # a type rclpy cannot import: record the other topics
                self._warn_once(topic, f"{topic}: not recorded: {err}")
                del self.subs[topic]
                continue
            self._enter_bag(topic)

    def unmatched(self) -> list[str]:
        """Topics with a discovered publisher that no subscription of the topic matched yet."""
        out = []
        for topic, subs in self.subs.items():
            msgtype = self.types.get(topic)
            if msgtype is None:
                continue
            offered = [
                i.qos_profile
                for i in self.node.get_publishers_info_by_topic(topic)
                if i.topic_type == msgtype
            ]
            if any(self._key(_recording_qos([q])) not in subs for q in offered) or any(
                sub.get_publisher_count() < sum(_serves(sub.qos_profile, q) for q in offered)
                for sub in subs.values()
            ):
                out.append(topic)
        return out

    def announce_ready(self) -> None:
        """Subscribe to :data:`RECORDER_READY_TOPIC` (once): the graph's sign of readiness."""
        if self._ready_sub is None:
            from std_msgs.msg import Empty

            self._ready_sub = self.node.create_subscription(
                Empty, RECORDER_READY_TOPIC, lambda _msg: None, stream_qos("reliable", 1)
            )

    def readiness(self, unmatched: Sequence[str]) -> RecordReady:
        """The :class:`RecordReady` of now, with ``unmatched`` from :meth:`unmatched`."""
        return RecordReady(
            subscribed=tuple(t for t, subs in self.subs.items() if subs),
            awaiting=tuple(t for t, subs in self.subs.items() if not subs),
            unmatched=tuple(unmatched),
        )

    @staticmethod
    def _key(qos: QoSProfile) -> tuple[Any, Any]:
        return qos.reliability, qos.durability

    def _subscribe(self, topic: str, offered: QoSProfile) -> None:
        """Add a subscription of ``topic`` mirroring ``offered``, unless one has that QoS."""
        qos = _recording_qos([offered])
        key = self._key(qos)
        if key in self.subs[topic]:
            return

        def on_message(raw: bytes, info: Any, topic: str = topic) -> None:
            # Two arguments: rclpy passes the MessageInfo (source timestamp, publisher GID).
            self._on_message(topic, raw, info)

        self.subs[topic][key] = self.node.create_subscription(
            message_class(self.types[topic]), topic, on_message, qos, raw=True
        )

    def _enter_bag(self, topic: str) -> None:
        """Add ``topic`` to the bag, with its discovered publishers' offered QoS."""
        if topic in self.writer.counts:  # in the bag already
            return
        offered = [
            i.qos_profile
            for i in self.node.get_publishers_info_by_topic(topic)
            if i.topic_type == self.types[topic]
        ]
        self.writer.add_topic(topic, self.types[topic], offered_qos=offered)

    def _on_message(self, topic: str, raw: bytes, info: Mapping[str, Any]) -> None:
        if len(self.subs[topic]) > 1 and self._repeated(topic, raw, info):
            return
        # A message can come before the poll has seen its publisher (the graph cache lags).
        self._enter_bag(topic)
        source_ns = int(info.get("source_timestamp") or 0)
        t_ns = source_ns if source_ns > 0 else time.time_ns()
        # Stored as received: the CDR bytes rosbag2 would store (a 6 MP frame is not decoded
        # and encoded again).
        self.writer.write_raw(topic, self.types[topic], raw, t_ns)

    def _repeated(self, topic: str, raw: bytes, info: Mapping[str, Any]) -> bool:
        """Whether this message came already through another subscription of ``topic``."""
        gid = info.get("publisher_gid")
        seq = info.get("publication_sequence_number")
        key: tuple[Any, ...]
        if gid is not None and seq is not None:
            key = (topic, bytes(gid.get("data", b"")), int(seq))
        elif info.get("source_timestamp"):
            # Without GIDs (another middleware): one publisher's stamp and size.
            key = (topic, int(info["source_timestamp"]), len(raw))
        else:
            return False
        return self._seen.seen(key)

    def _warn_once(self, topic: str, text: str) -> None:
        if (topic, text) not in self._warned:
            self._warned.add((topic, text))
            self.node.get_logger().warning(text)


def _recording_qos(offered: Sequence[QoSProfile], depth: int = 100) -> QoSProfile:
    """A subscription QoS that matches every publisher offering one of ``offered``.

    RELIABLE only if every publisher is reliable (a reliable reader does not match a
    best-effort writer), TRANSIENT_LOCAL only if every publisher is (a transient-local reader
    does not match a volatile writer); KEEP_LAST ``depth``.
    """
    reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )
