"""The hall-automation state machine of the displacement matcher (pure: no rclpy, no DDS).

A monitoring session between wave runs, as a lab runs it:

1. **Baseline.** Captured on command (:meth:`Session.capture_baseline`) or automatically before the
   first run: once ``baseline_frames`` consecutive frames agree (the scene is settled), their pose
   sets are fused (:func:`pose_estimator.fuse`, a covariance-weighted average) into the baseline.
2. **Run.** The hall announces a run id (``/hall/run_id``) and the run state (``/hall/run_active``).
   While a run is active the scene moves and frames are ignored. No two runs of a session share
   an id: the id of a completed run announced again is ignored with a warning and the run gets
   its automatic name (``run-NNN``, see :meth:`Session.set_run_id`).
3. **Settling.** When the run stops, frames are collected until ``settle_frames`` consecutive
   frames agree within ``settle_tolerance_mm`` (or ``settle_timeout_frames`` pass, or
   ``settle_timeout_s`` seconds: the report then says ``"settled": false``); those frames are
   fused into the after-run pose set. The time bound holds even when no frame comes at all (a
   camera stopped right after the run): the caller passes the time (``now_s``, monotonic
   seconds) with its inputs and calls :meth:`Session.tick` periodically, and the run is then
   measured on what it has, or reported as not measured for lack of frames, instead of waiting
   for ever.
4. **Report.** The after-run set is matched against the baseline (cumulative displacement, paper
   sections 2.2 and 3 steps 5-6) and against the previous run's set (incremental); the report is
   tagged with the run id.

Nothing is lost: the baseline, every run (its fused poses and its report) and the run in
progress (its id and stamps, at every start, stop and completion, and the frames' ``frame_id``
when it changes: ``session.json``) are written
atomically (temporary file + ``os.replace``) to ``data_dir``; a new :class:`Session` on the same
directory resumes with them, and a run that was active or still settling when the matcher died is
measured on the frames that come after the restart. A file that cannot be written (disk full)
is kept in memory, reported by an error notice and written at the next save
(:attr:`Session.unsaved_paths`).

Frames are pose sets in the camera frame (millimetres, OpenCV axes) as produced by
:func:`pose_estimator.estimate`; times are seconds (ROS header stamps).
"""

from __future__ import annotations

import enum
import functools
import json
import math
import os
import re
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Concatenate, ParamSpec

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pose_estimator.types import FiducialPose

from .atomic import write_atomic

FORMAT_VERSION = 1
#: The run in progress, beside ``baseline.json`` and ``runs/`` in the data directory.
SESSION_STATE_FILE = "session.json"
#: Completed runs held in memory (the last one is republished, the latest with poses is the
#: reference of the next incremental report); all of them are on disk.
RUNS_IN_MEMORY = 4

Fuser = Callable[[Sequence[Sequence[FiducialPose]]], list[FiducialPose]]
Comparer = Callable[[Sequence[FiducialPose], Sequence[FiducialPose]], "Comparison"]
_P = ParamSpec("_P")


class SessionError(ValueError):
    """A session input or the data directory is malformed."""


class Phase(enum.Enum):
    """Where the session is in the hall's cycle."""

    WAITING_BASELINE = "waiting_baseline"  # no baseline yet; watching for a settled scene
    CAPTURING_BASELINE = "capturing_baseline"  # baseline commanded; collecting settled frames
    MONITORING = "monitoring"  # baseline held, no run active
    RUN_ACTIVE = "run_active"  # waves running; frames ignored
    SETTLING = "settling"  # run stopped; waiting for the scene to settle


@dataclass(frozen=True, slots=True)
class SessionConfig:
    """Settings of the state machine.

    Attributes
    ----------
    baseline_frames : int
        Consecutive settled frames fused into the baseline.
    settle_frames : int
        Consecutive settled frames required after a run (and fused into its pose set).
    settle_tolerance_mm : float
        Largest frame-to-frame movement of a fiducial for the scene to count as settled, mm.
    settle_fraction : float
        Fraction of fiducials that must agree between consecutive frames (occlusions, glints).
    settle_timeout_frames : int
        After this many frames without settling, the last ``settle_frames`` are used anyway.
    settle_timeout_s : float
        After this many seconds of settling (by the ``now_s`` the caller passes: monotonic,
        not the frames' stamps) the run is measured on the frames it has, or reported as not
        measured when none came; 0 disables the bound.
    auto_baseline : bool
        Capture the baseline automatically before the first run.
    data_dir : Path or None
        Where the baseline and the runs are kept (None: memory only).
    """

    baseline_frames: int = 5
    settle_frames: int = 3
    settle_tolerance_mm: float = 0.5
    settle_fraction: float = 0.9
    settle_timeout_frames: int = 50
    settle_timeout_s: float = 120.0
    auto_baseline: bool = True
    data_dir: Path | None = None

    def __post_init__(self) -> None:
        if self.baseline_frames < 1 or self.settle_frames < 1:
            raise SessionError(
                f"baseline_frames and settle_frames must be >= 1, got "
                f"{self.baseline_frames} and {self.settle_frames}"
            )
        if not self.settle_tolerance_mm > 0:
            raise SessionError(f"settle_tolerance_mm must be > 0, got {self.settle_tolerance_mm}")
        if not 0.0 < self.settle_fraction <= 1.0:
            raise SessionError(f"settle_fraction must be in (0, 1], got {self.settle_fraction}")
        if self.settle_timeout_frames < self.settle_frames:
            raise SessionError(
                f"settle_timeout_frames ({self.settle_timeout_frames}) must be >= "
                f"settle_frames ({self.settle_frames})"
            )
        if not (self.settle_timeout_s >= 0 and math.isfinite(self.settle_timeout_s)):
            raise SessionError(
                f"settle_timeout_s must be >= 0 s (0: no time bound), got {self.settle_timeout_s}"
            )


@dataclass(frozen=True, slots=True)
class MarkerSpec:
    """One displacement marker, independent of any message library.

    Attributes
    ----------
    kind : {"arrow", "label"}
    start_mm, end_mm : (float, float, float)
        Camera-frame points, mm (for a label both are its position).
    same_code : bool
        Arrow between fiducials of the same code (green) or of different codes (red).
    text : str
        Label text (unit id and its displacement), empty for arrows.
    """

    kind: str
    start_mm: tuple[float, float, float]
    end_mm: tuple[float, float, float]
    same_code: bool = True
    text: str = ""


@dataclass(frozen=True, slots=True)
class Comparison:
    """Outcome of comparing two pose sets: the report dict and its markers."""

    report: dict[str, Any]
    markers: tuple[MarkerSpec, ...]
    rows: tuple[dict[str, Any], ...] = ()


@dataclass(frozen=True, slots=True, eq=False)
class Baseline:
    """The fused reference pose set all runs are measured against.

    Attributes
    ----------
    poses : tuple of FiducialPose
        Fused poses (camera frame, mm).
    n_frames : int
        Frames fused.
    stamp_s : float
        Header time of the last frame fused, seconds.
    reason : str
        ``"command"`` or ``"auto"``.
    """

    poses: tuple[FiducialPose, ...]
    n_frames: int
    stamp_s: float
    reason: str


@dataclass(frozen=True, slots=True, eq=False)
class RunRecord:
    """One completed wave run.

    Attributes
    ----------
    run_id : str
        The hall's id for the run (or ``run-NNN`` when none was announced).
    sequence : int
        1-based position among the session's runs.
    poses : tuple of FiducialPose
        The fused settled after-run pose set.
    report : dict
        JSON-ready report: the keys of ``armourcam compare --json`` (cumulative, against the
        baseline) plus ``run_id``, ``sequence``, ``settled``, ``frames_fused``, ``stamp_s`` and
        ``incremental`` (the report against the previous run, or None for the first run).
    markers : tuple of MarkerSpec
        Markers of the cumulative displacement.
    rows : tuple of dict
        ``DisplacementRecord`` rows (``msg/DisplacementRecord.msg`` field names) of the
        cumulative displacement.
    """

    run_id: str
    sequence: int
    poses: tuple[FiducialPose, ...]
    report: dict[str, Any]
    markers: tuple[MarkerSpec, ...]
    rows: tuple[dict[str, Any], ...] = ()


@dataclass(frozen=True, slots=True)
class BaselineCaptured:
    """Event: a new baseline is held."""

    baseline: Baseline


@dataclass(frozen=True, slots=True)
class RunCompleted:
    """Event: a run was measured; its report and markers are ready to publish."""

    run: RunRecord


@dataclass(frozen=True, slots=True)
class Notice:
    """Event: something the operator should see in the log (``level`` "info"/"warn"/"error")."""

    level: str
    text: str


Event = BaselineCaptured | RunCompleted | Notice


@dataclass(slots=True)
class _Window:
    """The last frames, with the count of consecutive settled frame pairs at its end."""

    maxlen: int
    frames: deque[tuple[tuple[FiducialPose, ...], float]] = field(default_factory=deque)
    stable_run: int = 0

    def clear(self) -> None:
        self.frames.clear()
        self.stable_run = 0


DEPTH_TOLERANCE_FACTOR = 4.0
"""Along the viewing ray a settled fiducial may differ this many times ``tolerance_mm``."""


def frames_agree(
    a: Sequence[FiducialPose], b: Sequence[FiducialPose], tolerance_mm: float, fraction: float
) -> bool:
    """Whether two pose sets show the same, unmoved scene.

    Each fiducial of the larger set needs a partner of the same code in the other whose
    difference is within ``tolerance_mm`` across the viewing ray and
    ``DEPTH_TOLERANCE_FACTOR * tolerance_mm`` along it, each plus three standard deviations of
    the difference from both covariances: monocular depth is several times less certain than
    the lateral position (paper section 4), so its frame-to-frame noise is not movement, while a
    unit still rocking shows up across the ray. At least ``fraction`` of the fiducials must have
    a partner (a glint or a passing occlusion may hide a few). Two empty sets agree.
    """
    if len(a) < len(b):
        a, b = b, a
    if not a:
        return True
    if not b:
        return False
    pa = np.array([p.position_mm for p in a], dtype=np.float64)
    pb = np.array([p.position_mm for p in b], dtype=np.float64)
    ca = np.array([np.asarray(p.covariance_mm2, dtype=np.float64) for p in a])
    cb = np.array([np.asarray(p.covariance_mm2, dtype=np.float64) for p in b])
    codes_b = np.array([p.code for p in b])
    k = min(4, len(b))
    _, idx = cKDTree(pb).query(pa, k=k)
    idx = np.asarray(idx).reshape(len(a), k)
    ok = np.zeros(len(a), dtype=bool)
    ray = pa / np.linalg.norm(pa, axis=1, keepdims=True).clip(1e-9)
    codes_a = np.array([p.code for p in a])
    for j in range(k):
        nb = idx[:, j]
        d = pb[nb] - pa
        along = np.einsum("ij,ij->i", d, ray)
        lateral = np.linalg.norm(d - along[:, None] * ray, axis=1)
        cov = np.nan_to_num(ca + cb[nb], nan=0.0, posinf=0.0)
        var_along = np.einsum("ij,ijk,ik->i", ray, cov, ray).clip(0.0)
        var_lateral = (np.trace(cov, axis1=1, axis2=2) - var_along).clip(0.0)
        ok |= (
            (codes_b[nb] == codes_a)
            & (lateral <= tolerance_mm + 3.0 * np.sqrt(var_lateral))
            & (np.abs(along) <= DEPTH_TOLERANCE_FACTOR * tolerance_mm + 3.0 * np.sqrt(var_along))
        )
    return bool(ok.mean() >= fraction)


def _with_save_notices(
    method: Callable[Concatenate[Session, _P], list[Event]],
) -> Callable[Concatenate[Session, _P], list[Event]]:
    """Append the notices of the saves ``method`` made (disk errors) to the events it returns.

    The saves happen deep inside the state machine; collecting their notices here gives every
    public input one place where they reach the caller.
    """

    @functools.wraps(method)
    def wrapper(self: Session, /, *args: _P.args, **kwargs: _P.kwargs) -> list[Event]:
        events = method(self, *args, **kwargs)
        notices, self._save_notices = self._save_notices, []
        return events + notices

    return wrapper


class Session:
    """The matcher's hall-automation state machine.

    Feed it with :meth:`add_frame`, :meth:`set_run_active`, :meth:`set_run_id` and
    :meth:`capture_baseline`, and call :meth:`tick` periodically (the ``settle_timeout_s`` bound
    when no frame comes); each returns the events it caused (new baseline, completed run,
    notices). ``now_s`` arguments are the caller's monotonic clock, seconds (not the frames'
    stamps, which may be a replay's or a lagging camera's); without them there is no time bound.
    With a ``data_dir`` it resumes from what an earlier session wrote there; a file that cannot
    be written is kept in memory (:attr:`unsaved_paths`) and retried at every save.

    Parameters
    ----------
    config : SessionConfig
    fuse : callable, optional
        ``fuse(frames) -> poses``: several frames of a static scene -> one pose set
        (default :func:`pose_estimator.fuse`).
    compare : callable, optional
        ``compare(before, after) -> Comparison`` (default :func:`compare_poses`, which runs
        :func:`displacement_matcher.match` and builds the report).
    """

    def __init__(
        self,
        config: SessionConfig,
        *,
        fuse: Fuser | None = None,
        compare: Comparer | None = None,
    ) -> None:
        self.config = config
        self._fuse: Fuser = fuse if fuse is not None else default_fuse
        self._compare: Comparer = compare if compare is not None else compare_poses
        self.baseline: Baseline | None = None
        # The most recent runs (every run is on disk in data_dir): a rig that measures runs for
        # weeks must not hold them all.
        self.runs: list[RunRecord] = []
        self.runs_completed = 0
        self.frames_seen = 0
        self.frames_dropped = 0
        self.last_frame_fiducials = 0
        self._run_active = False
        self._pending_run_id: str | None = None
        self._current_run_id: str | None = None
        self._current_run_id_auto = False
        self._deferred_start: float | None = None
        self._late_baseline: list[tuple[tuple[FiducialPose, ...], float]] = []
        self._capture_requested = False
        self._settle_count = 0
        self._stop_stamp: float | None = None
        # Consecutive frames stamped before the stop that arrived since it (in flight, or a
        # camera clock lagging the hall's).
        self._stale_frames = 0
        self._start_stamp: float | None = None
        # When the settling began, on the caller's monotonic clock (None: not settling, or no
        # time given yet; after a restart the bound starts at the first time given).
        self._settle_started_s: float | None = None
        #: frame_id of the frames (the camera's optical frame), kept in session.json so that a
        #: restarted node labels its republished outputs with it.
        self.frame_id = ""
        # Documents a disk error kept from data_dir, oldest first, and the notices of the saves
        # not yet returned to the caller (see _with_save_notices).
        self._unsaved: dict[Path, Any] = {}
        self._save_notices: list[Event] = []
        # The id of every completed run (all of data_dir's, not only the runs in memory) -> the
        # sequence of the run that has it: no two runs get one id.
        self._used_run_ids: dict[str, int] = {}
        # Ids of completed runs announced again since the last run completed, each warned once
        # (a hall republishing its id periodically must not flood the log).
        self._reused_id_warned: set[str] = set()
        self._baseline_due = False
        self._window = _Window(max(config.baseline_frames, config.settle_frames))
        self.phase = Phase.WAITING_BASELINE
        if config.data_dir is not None:
            _check_data_dir(Path(config.data_dir))
            self._load(Path(config.data_dir))
        if self.baseline is not None and self.phase == Phase.WAITING_BASELINE:
            self.phase = Phase.MONITORING

    # ------------------------------------------------------------------ inputs

    @_with_save_notices
    def capture_baseline(self) -> list[Event]:
        """Command: capture a new baseline from the next settled frames."""
        if self._run_active:
            return [Notice("warn", "capture_baseline ignored: a run is active")]
        self._capture_requested = True
        if self.phase == Phase.SETTLING:
            # The run is measured against the old baseline first: capturing now would throw the
            # run away and make its after-state the new reference.
            return [
                Notice(
                    "info",
                    f"capture_baseline: after run {self._current_run_id} is measured, from "
                    f"{self.config.baseline_frames} frames",
                )
            ]
        self._window.clear()
        self.phase = Phase.CAPTURING_BASELINE
        return [Notice("info", f"capturing baseline from {self.config.baseline_frames} frames")]

    @_with_save_notices
    def set_run_id(self, run_id: str) -> list[Event]:
        """The hall announced the id of the current run (while one is active) or of the next.

        The id of a run this session already completed (the last one republished, or an older
        one reused; also one on disk from before a restart) is ignored with a warning, once per
        run: no two runs, and no two run files, share an id. The run keeps or gets its
        automatic name ``run-NNN`` (``run-NNN-2``, ... when a completed run has that one).
        """
        run_id = run_id.strip()
        if not run_id:
            return [Notice("warn", "empty run id ignored")]
        settling_unnamed = self.phase == Phase.SETTLING and self._current_run_id_auto
        if self._deferred_start is None and (self._run_active or settling_unnamed):
            # Announced just before the start but delivered after it, even after the stop:
            # separate topics carry no common order. A named run keeps its name.
            if run_id in self._used_run_ids:
                return self._reused_run_id(run_id, f"run {self._current_run_id} keeps its name")
            self._current_run_id = run_id
            self._current_run_id_auto = False
            self._save_state()
        elif run_id in self._used_run_ids:
            return self._reused_run_id(
                run_id,
                f"the next run will be named {self._next_run_id()} unless the hall announces a "
                "new id",
            )
        else:
            self._pending_run_id = run_id
        return []

    def _auto_run_id(self) -> str:
        """``run-NNN`` for the next run (NNN its sequence), suffixed ``-2``, ``-3``, ... when a
        completed run already has that id (a hall may announce ids of that form)."""
        base = name = f"run-{self.runs_completed + 1:03d}"
        k = 1
        while name in self._used_run_ids:
            k += 1
            name = f"{base}-{k}"
        return name

    def _next_run_id(self) -> str:
        """The name the next run would get if it started now."""
        pending = self._pending_run_id
        if pending is not None and pending not in self._used_run_ids:
            return pending
        return self._auto_run_id()

    def _reused_run_id(self, run_id: str, outcome: str) -> list[Event]:
        """The warning, once per run, for ``run_id`` announced again after its run completed;
        ``outcome`` says what the run is named instead."""
        if run_id in self._reused_id_warned:
            return []  # a hall republishing its id periodically must not flood the log
        self._reused_id_warned.add(run_id)
        sequence = self._used_run_ids[run_id]
        return [
            Notice("warn", f"run id {run_id} already measured (run {sequence}); ignored: {outcome}")
        ]

    @_with_save_notices
    def set_run_active(
        self, active: bool, stamp_s: float | None = None, *, now_s: float | None = None
    ) -> list[Event]:
        """The hall's run state changed (repeated identical states are harmless).

        ``stamp_s`` is when the change happened, on the clock of the frames' stamps. Frames
        stamped before a start that arrive after it (still in flight through the pipeline) still
        count for a pending baseline; frames stamped before a stop (the scene still moving) are
        not used for settling, unless ``settle_timeout_frames`` of them arrive in a row (a camera
        clock lagging the hall's): the run then settles on the frames in arrival order.
        ``now_s`` (monotonic seconds) starts the ``settle_timeout_s`` bound at a stop.
        """
        events: list[Event] = self._check_settle_timeout(now_s)
        if active == self._run_active:
            return events
        self._run_active = active
        if active:
            if self.phase == Phase.SETTLING:
                if (
                    stamp_s is not None
                    and self._stop_stamp is not None
                    and stamp_s > self._stop_stamp
                ):
                    # Frames stamped before this start may still be queued behind it (separate
                    # topics): let them settle the last run; the first frame stamped after the
                    # start begins the new run (see add_frame).
                    self._deferred_start = stamp_s
                    return [Notice("info", "next run started; the last run settles first")]
                # The next run started before the last one settled: measure it as it is.
                events += self._finish_run(force=True)
            events += self._start_run(stamp_s)
        else:
            if self._deferred_start is not None:
                # This run stopped before any frame of it arrived: close the last run first.
                events += self._finish_run(force=True)
                events += self._begin_deferred_run()
            if self._baseline_due:
                events += self._baseline_from_window("auto", partial=True)
            self._stop_stamp = stamp_s
            self._stale_frames = 0
            self._window.clear()
            self._settle_count = 0
            self._settle_started_s = now_s
            self.phase = Phase.SETTLING
            self._save_state()
            events.append(Notice("info", f"run {self._current_run_id} stopped; settling"))
        return events

    def _start_run(self, stamp_s: float | None) -> list[Event]:
        self._start_stamp = stamp_s
        self._stop_stamp = None
        self._settle_started_s = None
        if self.baseline is None and (self._capture_requested or self.config.auto_baseline):
            # Take the baseline from the frames before the start, including any still
            # in flight; it is fused at the first frame stamped after the start.
            self._baseline_due = True
        else:
            self._window.clear()
        events: list[Event] = []
        run_id, self._pending_run_id = self._pending_run_id, None
        if run_id is not None and run_id in self._used_run_ids:
            # Announced while the run of that id settled (the hall republishing it): that run
            # has completed since.
            events += self._reused_run_id(run_id, f"this run is named {self._auto_run_id()}")
            run_id = None
        self._current_run_id_auto = run_id is None
        self._current_run_id = run_id or self._auto_run_id()
        self.phase = Phase.RUN_ACTIVE
        self._save_state()
        return [*events, Notice("info", f"run {self._current_run_id} started")]

    def _begin_deferred_run(self) -> list[Event]:
        stamp, self._deferred_start = self._deferred_start, None
        return self._start_run(stamp)

    @_with_save_notices
    def add_frame(
        self,
        poses: Sequence[FiducialPose],
        stamp_s: float = 0.0,
        *,
        frame_id: str | None = None,
        now_s: float | None = None,
    ) -> list[Event]:
        """One frame's pose set (possibly empty).

        ``frame_id`` is the frame's header frame_id (kept, and saved when it changes, so that a
        restarted node labels its outputs with it; empty or None: unchanged); ``now_s`` the
        caller's monotonic clock (a run settling longer than ``settle_timeout_s`` is measured
        before this frame is taken).
        """
        timed_out = self._check_settle_timeout(now_s)
        if frame_id and frame_id != self.frame_id:
            self.frame_id = frame_id
            self._save_state()
        return timed_out + self._add_frame(poses, stamp_s)

    @_with_save_notices
    def tick(self, now_s: float) -> list[Event]:
        """Time passed (``now_s``: the caller's monotonic clock, seconds).

        A run that has been settling for ``settle_timeout_s`` is measured now on the frames it
        has, or reported as not measured when none came (a camera stopped after the run): it
        must not wait for frames for ever. Call it periodically (a node's timer).
        """
        return self._check_settle_timeout(now_s)

    def _check_settle_timeout(self, now_s: float | None) -> list[Event]:
        if now_s is None or self.phase != Phase.SETTLING:
            return []
        if self._settle_started_s is None:
            # Settling since before the first time given (resumed after a restart): the
            # bound starts now.
            self._settle_started_s = now_s
            return []
        waited = now_s - self._settle_started_s
        limit = self.config.settle_timeout_s
        if limit <= 0 or waited < limit:
            return []
        events = self._finish_run(force=True, waited_s=waited)
        if self._deferred_start is not None:
            events += self._begin_deferred_run()  # the next run, started while this one settled
        return events

    def _add_frame(self, poses: Sequence[FiducialPose], stamp_s: float) -> list[Event]:
        nxt = self._deferred_start
        if nxt is not None and self.phase == Phase.SETTLING and stamp_s >= nxt:
            # The first frame of the next run: the last run is measured as it is.
            events = self._finish_run(force=True)
            events += self._begin_deferred_run()
            return events + self._add_frame(poses, stamp_s)
        self.frames_seen += 1
        self.last_frame_fiducials = len(poses)
        start, stop = self._start_stamp, self._stop_stamp
        if self.phase == Phase.RUN_ACTIVE:
            if not self._baseline_due:
                return []
            if start is not None and stamp_s < start:
                self._push(poses, stamp_s)  # a pre-run frame arriving late: still baseline
                if self._settled(self.config.baseline_frames):
                    return self._baseline_from_window("auto", partial=False)
                return []
            return self._baseline_from_window("auto", partial=True)
        lag: list[Event] = []
        if self.phase == Phase.SETTLING and stop is not None and stamp_s < stop:
            if self._stale_frames < self.config.settle_timeout_frames:
                self._stale_frames += 1
                if self.baseline is None and start is not None and stamp_s < start:
                    # Pre-run frames delayed past the whole run (a matcher discovered late, a
                    # slow pipeline): still the scene before the run, so still the baseline.
                    self._late_baseline.append((tuple(poses), float(stamp_s)))
                return []
            # More frames than a settle timeout cannot all have been in flight: the camera's
            # clock lags the hall's (or a bag replays old stamps), so the stop stamp would hold
            # the run forever. The frames count in arrival order from now on.
            lag.append(
                Notice(
                    "warn",
                    f"frames stamped {stop - stamp_s:.1f} s before the hall's stop keep arriving "
                    f"after it ({self._stale_frames} frames): the camera clock seems to lag the "
                    "hall clock; settling on arrival order",
                )
            )
            self._stop_stamp = None
            # Frames taken for "pre-run, delayed" were as likely after the run: with clocks
            # this far apart a baseline from them could hide the run's every movement.
            self._late_baseline.clear()
            self._save_state()  # a restarted matcher settles this run on arrival order too
        self._stale_frames = 0
        self._push(poses, stamp_s)
        if self.phase == Phase.SETTLING:
            self._settle_count += 1
            events = lag + self._finish_run(force=False)
            if nxt is not None and any(isinstance(e, RunCompleted) for e in events):
                events += self._begin_deferred_run()
            return events
        wants_baseline = self._capture_requested or (
            self.baseline is None and self.config.auto_baseline and self.runs_completed == 0
        )
        if wants_baseline and self._settled(self.config.baseline_frames):
            reason = "command" if self._capture_requested else "auto"
            return self._baseline_from_window(reason, partial=False)
        return []

    @_with_save_notices
    def end_of_input(self) -> list[Event]:
        """No more frames will come (end of a bag): finish a pending baseline or run.

        The files a disk error kept in memory are tried once more first (the last chance
        before the process ends).
        """
        events: list[Event] = []
        if self._unsaved:
            self._flush_unsaved(None, len(self._unsaved))
        if self.baseline is None and self._window.frames and self.phase != Phase.SETTLING:
            events += self._baseline_from_window("auto", partial=True, cause="input ended")
        if self.phase == Phase.SETTLING:
            events += self._finish_run(force=True)
            self._deferred_start = None
        return events

    # ------------------------------------------------------------------ state

    def status(self) -> dict[str, str]:
        """Key/value state for ``/diagnostics``."""
        last = self.runs[-1] if self.runs else None
        return {
            "phase": self.phase.value,
            "run_active": str(self._run_active).lower(),
            "current_run_id": self._current_run_id or "",
            "baseline_fiducials": str(len(self.baseline.poses)) if self.baseline else "none",
            "baseline_frames": str(self.baseline.n_frames) if self.baseline else "0",
            "runs_completed": str(self.runs_completed),
            "last_run_id": last.run_id if last else "",
            "frames_seen": str(self.frames_seen),
            "frames_dropped": str(self.frames_dropped),
            "last_frame_fiducials": str(self.last_frame_fiducials),
            "data_dir": str(self.config.data_dir or ""),
            "unsaved_files": str(len(self._unsaved)),
        }

    @property
    def unsaved_paths(self) -> tuple[Path, ...]:
        """Files of ``data_dir`` not written yet (a disk error), oldest first.

        Their documents are held in memory and written, in this order, at the next save.
        """
        return tuple(self._unsaved)

    # ------------------------------------------------------------------ internals

    def _push(self, poses: Sequence[FiducialPose], stamp_s: float) -> None:
        frame = (tuple(poses), float(stamp_s))
        win = self._window
        if win.frames:
            cfg = self.config
            agree = frames_agree(
                win.frames[-1][0], frame[0], cfg.settle_tolerance_mm, cfg.settle_fraction
            )
            win.stable_run = win.stable_run + 1 if agree else 0
        win.frames.append(frame)
        while len(win.frames) > win.maxlen:
            win.frames.popleft()

    def _settled(self, n: int) -> bool:
        win = self._window
        return len(win.frames) >= n and (n == 1 or win.stable_run >= n - 1)

    def _last_frames(self, n: int) -> list[tuple[tuple[FiducialPose, ...], float]]:
        return list(self._window.frames)[-n:]

    def _baseline_from_window(
        self, reason: str, *, partial: bool, cause: str = "run started"
    ) -> list[Event]:
        """The baseline from the frames seen so far, taken early (``partial``) because of
        ``cause`` (a run started, the input ended)."""
        frames = self._last_frames(self.config.baseline_frames)
        if not frames:
            return [Notice("warn", f"{cause} without a baseline and no frames to take one")]
        # Fewer frames than asked that all agree are a still scene seen briefly (a short wait
        # before the run), not an unsettled one.
        agreed = len(frames) > 1 and self._settled(len(frames))
        fused = tuple(self._fuse([f for f, _ in frames]))
        self.baseline = Baseline(fused, len(frames), frames[-1][1], reason)
        self._capture_requested = False
        self._baseline_due = False
        self._window.clear()
        if self.phase not in (Phase.RUN_ACTIVE, Phase.SETTLING):
            self.phase = Phase.MONITORING
        self._save_baseline()
        events: list[Event] = [BaselineCaptured(self.baseline)]
        if partial and agreed:
            events.append(
                Notice(
                    "info",
                    f"baseline from the {len(frames)} agreeing frames before the "
                    f"{'run' if cause == 'run started' else 'end'} "
                    f"(baseline_frames {self.config.baseline_frames})",
                )
            )
        elif partial:
            events.append(
                Notice("warn", f"{cause} before the baseline settled: fused {len(frames)}")
            )
        return events

    def _baseline_from_late_frames(self) -> list[Event]:
        frames = self._late_baseline[-self.config.baseline_frames :]
        self._late_baseline.clear()
        fused = tuple(self._fuse([f for f, _ in frames]))
        self.baseline = Baseline(fused, len(frames), frames[-1][1], "auto")
        self._capture_requested = False
        self._baseline_due = False
        self._save_baseline()
        note = f"baseline from {len(frames)} pre-run frames that arrived after the run started"
        return [BaselineCaptured(self.baseline), Notice("warn", note)]

    def _finish_run(self, *, force: bool, waited_s: float | None = None) -> list[Event]:
        """Measure the run once the scene settled (or now, with ``force``; ``waited_s``: the
        seconds it settled when ``settle_timeout_s`` ended it)."""
        cfg = self.config
        settled = self._settled(cfg.settle_frames)
        if not (settled or force or self._settle_count >= cfg.settle_timeout_frames):
            return []
        frames = self._last_frames(cfg.settle_frames)
        run_id = self._current_run_id or self._auto_run_id()
        events: list[Event] = []
        no_frame_error = "no frame after run"
        if not frames and waited_s is not None:
            stale = (
                f"; {self._stale_frames} frames came, all stamped before the hall's stop"
                if self._stale_frames
                else " (is the camera running?)"
            )
            no_frame_error += f" within settle_timeout_s ({cfg.settle_timeout_s:g} s)"
            events.append(
                Notice(
                    "error",
                    f"run {run_id}: not measured: no frame in the {waited_s:.0f} s after the "
                    f"run (settle_timeout_s {cfg.settle_timeout_s:g}){stale}",
                )
            )
        elif not frames:
            events.append(Notice("error", f"run {run_id}: no frame after the run to measure"))
        after = tuple(self._fuse([f for f, _ in frames])) if frames else ()
        if not settled and frames and waited_s is not None:
            events.append(
                Notice(
                    "warn",
                    f"run {run_id}: scene not settled within settle_timeout_s "
                    f"({cfg.settle_timeout_s:g} s, {self._settle_count} frames): measured on the "
                    f"last {len(frames)}",
                )
            )
        elif not settled:
            events.append(
                Notice("warn", f"run {run_id}: scene not settled after {self._settle_count} frames")
            )
        if self.baseline is None and self._late_baseline:
            events += self._baseline_from_late_frames()
        report: dict[str, Any]
        markers: tuple[MarkerSpec, ...] = ()
        rows: tuple[dict[str, Any], ...] = ()
        if not frames:
            # Never report "everything vanished" for a scene that was simply not seen.
            report = {"fiducials": [], "units": [], "summary": {}, "error": no_frame_error}
        elif self.baseline is None:
            report = {"fiducials": [], "units": [], "summary": {}, "error": "no baseline"}
            events.append(Notice("error", f"run {run_id}: no baseline to compare against"))
        else:
            cumulative = self._safe_compare(
                self.baseline.poses, after, events, run_id, "the baseline"
            )
            report = dict(cumulative.report)
            markers = cumulative.markers
            rows = cumulative.rows
        previous = next((r.poses for r in reversed(self.runs) if r.poses), None) if frames else None
        incremental = (
            self._safe_compare(previous, after, events, run_id, "the previous run").report
            if previous is not None
            else None
        )
        report.update(
            run_id=run_id,
            sequence=self.runs_completed + 1,
            settled=settled,
            frames_fused=len(frames),
            stamp_s=frames[-1][1] if frames else None,
            incremental=incremental,
        )
        run = RunRecord(run_id, self.runs_completed + 1, after, report, markers, rows)
        self.runs.append(run)
        self.runs_completed += 1
        self._used_run_ids[run_id] = run.sequence
        self._reused_id_warned.clear()  # the next run is warned afresh
        del self.runs[:-RUNS_IN_MEMORY]
        self._save_run(run)
        self._current_run_id = None
        self._settle_started_s = None
        self._window.clear()
        self.phase = Phase.MONITORING if self.baseline is not None else Phase.WAITING_BASELINE
        if self._capture_requested:
            self.phase = Phase.CAPTURING_BASELINE  # asked for while the run settled
        self._save_state()
        events.append(RunCompleted(run))
        return events

    def _safe_compare(
        self,
        before: Sequence[FiducialPose],
        after: Sequence[FiducialPose],
        events: list[Event],
        run_id: str,
        against: str,
    ) -> Comparison:
        """``self._compare(before, after)``; its failure and warnings become notices naming the
        run and what it was compared ``against`` (the cumulative and the incremental report
        may both warn)."""
        try:
            comparison = self._compare(before, after)
        except ValueError as err:
            events.append(
                Notice("error", f"run {run_id} against {against}: comparison failed: {err}")
            )
            return Comparison({"fiducials": [], "units": [], "summary": {}, "error": str(err)}, ())
        for message in comparison.report.get("warnings", ()):
            events.append(Notice("warn", f"run {run_id} against {against}: {message}"))
        return comparison

    # ------------------------------------------------------------------ persistence

    def _save(self, path: Path, doc: dict[str, Any]) -> None:
        """Write ``doc`` to ``path`` after the documents still unsaved; never raises OSError.

        A disk error (full, read-only, gone) must not stop the node nor lose a result: the
        document waits in memory (replacing an older unsaved version of the same file) and is
        written at the next save. Notices go to ``_save_notices``.
        """
        backlog = len(self._unsaved)
        self._unsaved.pop(path, None)  # superseded: only the latest version is written
        self._unsaved[path] = doc
        self._flush_unsaved(path, backlog)

    def _flush_unsaved(self, requested: Path | None, backlog: int) -> None:
        """Write the unsaved documents in order, stopping at the first that fails.

        Stopping keeps the order on disk: ``session.json`` never says a run is done before
        the run's own file exists. ``requested`` is the file this save is for (None: a retry),
        named in the error notice; ``backlog`` the documents that were waiting before it.
        """
        for path, doc in list(self._unsaved.items()):
            try:
                write_json_atomic(path, doc)
            except OSError as err:
                name = requested or path
                where = "" if path == name else f" (writing the older {path} first)"
                self._save_notices.append(
                    Notice(
                        "error",
                        f"could not save {name}: {err.strerror or err}{where}; kept in memory, "
                        "retried at the next save",
                    )
                )
                return
            except Exception:
                # Not the disk (a document that cannot be written at all): dropped rather than
                # failing every later save too.
                del self._unsaved[path]
                raise
            del self._unsaved[path]
        if backlog > 0:
            self._save_notices.append(
                Notice("info", f"wrote the {backlog} files kept in memory since a disk error")
            )

    def _save_baseline(self) -> None:
        if self.config.data_dir is None or self.baseline is None:
            return
        b = self.baseline
        doc = {
            "format": FORMAT_VERSION,
            "kind": "baseline",
            "n_frames": b.n_frames,
            "stamp_s": b.stamp_s,
            "reason": b.reason,
            "poses": [pose_to_dict(p) for p in b.poses],
        }
        self._save(Path(self.config.data_dir) / "baseline.json", doc)

    def _save_run(self, run: RunRecord) -> None:
        if self.config.data_dir is None:
            return
        doc = {
            "format": FORMAT_VERSION,
            "kind": "run",
            "run_id": run.run_id,
            "sequence": run.sequence,
            "poses": [pose_to_dict(p) for p in run.poses],
            "markers": [marker_to_dict(m) for m in run.markers],
            "rows": list(run.rows),
            "report": run.report,
        }
        name = f"{run.sequence:04d}-{_safe_name(run.run_id)}.json"
        self._save(Path(self.config.data_dir) / "runs" / name, doc)

    def _save_state(self) -> None:
        """The run in progress (active or settling), so that a restarted matcher measures it,
        and the frames' ``frame_id``, so that it labels its republished outputs with it.

        Written atomically at every start, stop and completion and when the frame_id changes;
        the settling frames themselves are not kept (after a restart the run settles on the
        frames that come next).
        """
        if self.config.data_dir is None:
            return
        in_run = self.phase in (Phase.RUN_ACTIVE, Phase.SETTLING)
        doc = {
            "format": FORMAT_VERSION,
            "kind": "session",
            "phase": self.phase.value if in_run else None,
            "run_active": self._run_active if in_run else False,
            "run_id": self._current_run_id if in_run else None,
            "run_id_auto": self._current_run_id_auto,
            "start_stamp_s": self._start_stamp if in_run else None,
            "stop_stamp_s": self._stop_stamp if in_run else None,
            "baseline_due": self._baseline_due if in_run else False,
            "frame_id": self.frame_id,
        }
        self._save(Path(self.config.data_dir) / SESSION_STATE_FILE, doc)

    def _load_state(self, path: Path) -> None:
        doc = _read_json(path)
        try:
            self.frame_id = str(doc.get("frame_id") or "")  # absent in files of older versions
            phase = doc["phase"]
            if phase is None:
                return
            self.phase = Phase(phase)
            if self.phase not in (Phase.RUN_ACTIVE, Phase.SETTLING):
                raise ValueError(f"phase {phase!r} is not a run in progress")
            self._run_active = bool(doc["run_active"])
            run_id = doc["run_id"]
            self._current_run_id = None if run_id is None else str(run_id)
            self._current_run_id_auto = bool(doc["run_id_auto"])
            start, stop = doc["start_stamp_s"], doc["stop_stamp_s"]
            self._start_stamp = None if start is None else float(start)
            self._stop_stamp = None if stop is None else float(stop)
            self._baseline_due = bool(doc["baseline_due"])
        except (KeyError, TypeError, ValueError) as err:
            raise SessionError(f"{path}: malformed session state: {err}") from err

    def _load(self, data_dir: Path) -> None:
        path = data_dir / "baseline.json"
        if path.exists():
            doc = _read_json(path)
            try:
                self.baseline = Baseline(
                    tuple(pose_from_dict(p) for p in doc["poses"]),
                    int(doc["n_frames"]),
                    float(doc["stamp_s"]),
                    str(doc["reason"]),
                )
            except (KeyError, TypeError, ValueError) as err:
                raise SessionError(f"{path}: malformed baseline: {err}") from err
        runs_dir = data_dir / "runs"
        if runs_dir.is_dir():
            for run_path in sorted(runs_dir.glob("*.json")):
                doc = _read_json(run_path)
                try:
                    self.runs.append(
                        RunRecord(
                            str(doc["run_id"]),
                            int(doc["sequence"]),
                            tuple(pose_from_dict(p) for p in doc["poses"]),
                            dict(doc["report"]),
                            tuple(marker_from_dict(m) for m in doc.get("markers", [])),
                            tuple(dict(r) for r in doc.get("rows", [])),
                        )
                    )
                except (KeyError, TypeError, ValueError) as err:
                    raise SessionError(f"{run_path}: malformed run record: {err}") from err
            self.runs.sort(key=lambda r: r.sequence)
            self.runs_completed = max((r.sequence for r in self.runs), default=0)
            self._used_run_ids = {r.run_id: r.sequence for r in self.runs}
            del self.runs[:-RUNS_IN_MEMORY]
        state = data_dir / SESSION_STATE_FILE
        if state.exists():
            self._load_state(state)


# ---------------------------------------------------------------------- helpers


def _safe_name(run_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", run_id)[:80] or "run"


def _read_json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise SessionError(f"cannot read {path}: {err}") from err
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_VERSION:
        raise SessionError(f"{path}: not an armourcam session record (format {FORMAT_VERSION})")
    return doc


def _check_data_dir(path: Path) -> None:
    """Create ``path`` if needed; a SessionError naming it where it cannot hold the session's
    files (a file of that name, no permission): found at start-up, not at the first save."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SessionError(f"data_dir {path}: {err.strerror or err}") from err
    if not os.access(path, os.W_OK | os.X_OK):
        raise SessionError(f"data_dir {path}: not writable")


def write_json_atomic(path: Path, doc: Any) -> None:
    """Write ``doc`` as JSON atomically (:func:`.atomic.write_atomic`)."""
    write_atomic(path, json.dumps(doc, indent=1, allow_nan=True).encode())


def pose_to_dict(pose: FiducialPose) -> dict[str, Any]:
    """JSON-ready form of a pose (the detection is not kept)."""
    return {
        "code": int(pose.code),
        "position_mm": np.asarray(pose.position_mm, dtype=float).tolist(),
        "normal": np.asarray(pose.normal, dtype=float).tolist(),
        "covariance_mm2": np.asarray(pose.covariance_mm2, dtype=float).tolist(),
        "n_frames": int(pose.n_frames),
        "systematic_mm2": (
            None
            if pose.systematic_mm2 is None
            else np.asarray(pose.systematic_mm2, dtype=float).tolist()
        ),
        "axis": None if pose.axis is None else np.asarray(pose.axis, dtype=float).tolist(),
    }


def pose_from_dict(doc: dict[str, Any]) -> FiducialPose:
    """Inverse of :func:`pose_to_dict`."""
    pos: NDArray[np.float64] = np.asarray(doc["position_mm"], dtype=np.float64).reshape(3)
    normal: NDArray[np.float64] = np.asarray(doc["normal"], dtype=np.float64).reshape(3)
    cov: NDArray[np.float64] = np.asarray(doc["covariance_mm2"], dtype=np.float64).reshape(3, 3)
    bias = doc.get("systematic_mm2")  # (absent from baselines saved before it existed)
    systematic = None if bias is None else np.asarray(bias, dtype=np.float64).reshape(3, 3)
    frames = int(doc.get("n_frames", 1))
    spin = doc.get("axis")  # (absent from baselines saved before it existed)
    axis = None if spin is None else np.asarray(spin, dtype=np.float64).reshape(3)
    return FiducialPose(int(doc["code"]), pos, normal, cov, None, frames, systematic, axis)


def marker_to_dict(m: MarkerSpec) -> dict[str, Any]:
    """JSON-ready form of a marker."""
    return {
        "kind": m.kind,
        "start_mm": list(m.start_mm),
        "end_mm": list(m.end_mm),
        "same_code": m.same_code,
        "text": m.text,
    }


def marker_from_dict(doc: dict[str, Any]) -> MarkerSpec:
    """Inverse of :func:`marker_to_dict`."""
    s = [float(x) for x in doc["start_mm"]]
    e = [float(x) for x in doc["end_mm"]]
    return MarkerSpec(
        str(doc["kind"]),
        (s[0], s[1], s[2]),
        (e[0], e[1], e[2]),
        bool(doc.get("same_code", True)),
        str(doc.get("text", "")),
    )


def default_fuse(frames: Sequence[Sequence[FiducialPose]]) -> list[FiducialPose]:
    """Fuse frames of a static scene with the pose estimator's fusion."""
    from pose_estimator import fuse  # the core; imported late so that tests may inject their own

    return list(fuse(frames))


def compare_poses(before: Sequence[FiducialPose], after: Sequence[FiducialPose]) -> Comparison:
    """Match ``after`` against ``before`` and build the report and markers (the cores' job)."""
    from . import markers as _markers

    return _markers.compare(before, after)
