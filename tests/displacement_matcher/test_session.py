"""Tests of the hall-automation state machine (no rclpy)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

import displacement_matcher.session as session_module
from displacement_matcher.session import (
    RUNS_IN_MEMORY,
    BaselineCaptured,
    Event,
    Notice,
    Phase,
    RunCompleted,
    Session,
    SessionConfig,
    SessionError,
    frames_agree,
)
from pose_estimator.types import FiducialPose

SIGMA = np.array([0.02, 0.02, 0.1])  # mm, per-frame noise of x, y, z


def mean_fuse(frames: Sequence[Sequence[FiducialPose]]) -> list[FiducialPose]:
    """Reference fusion for the state-machine tests: same-code nearest partner, plain mean."""
    first = frames[-1]
    out = []
    for p in first:
        pts = [p.position_mm]
        for f in frames[:-1]:
            cand = [q for q in f if q.code == p.code]
            if cand:
                q = min(cand, key=lambda q: np.linalg.norm(q.position_mm - p.position_mm))
                if np.linalg.norm(q.position_mm - p.position_mm) < 1.0:
                    pts.append(q.position_mm)
        n = len(pts)
        out.append(
            FiducialPose(p.code, np.mean(pts, axis=0), p.normal, p.covariance_mm2 / n, None, n)
        )
    return out


OFFSETS = np.array([[0.0, 0.0, 0.0], [9.0, 0.0, 2.0], [0.0, 9.0, -2.0], [9.0, 9.0, 0.0]])


def scene(n: int = 40, seed: int = 1) -> np.ndarray:
    """True fiducial centres (mm, camera frame) of ``n // 4`` units about 800 mm away.

    Fiducial ``i`` is slot ``i % 4`` (code ``i % 4``, like a dolos' four codes) of unit
    ``i // 4``; units sit 45 mm apart, their fiducials 9 mm apart on the unit.
    """
    rng = np.random.default_rng(seed)
    n_units = n // 4
    side = int(np.ceil(np.sqrt(n_units)))
    centres = np.array([(u % side, u // side, 0.0) for u in range(n_units)]) * 45.0
    centres += [-100.0, -100.0, 800.0]
    centres[:, 2] += rng.uniform(-20, 20, n_units)
    return (centres[:, None, :] + OFFSETS[None]).reshape(-1, 3)


def frame(truth: np.ndarray, rng: np.random.Generator, drop: int = 0) -> list[FiducialPose]:
    """One noisy observation of ``truth`` (codes cycle 0..3 like a dolos' four codes)."""
    cov = np.diag(SIGMA**2)
    keep = np.arange(len(truth))
    if drop:
        keep = np.sort(rng.choice(len(truth), len(truth) - drop, replace=False))
    return [
        FiducialPose(
            int(i % 4),
            truth[i] + rng.normal(0.0, SIGMA),
            np.array([0.0, 0.0, -1.0]),
            cov,
        )
        for i in keep
    ]


def feed(session: Session, frames: list[list[FiducialPose]], t0: float) -> list[Event]:
    events: list[Event] = []
    for k, f in enumerate(frames):
        events += session.add_frame(f, t0 + 0.2 * k)
    return events


def of_type(events: list[Event], cls: type) -> list:
    return [e for e in events if isinstance(e, cls)]


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def make(tmp_path: Path | None = None, **kw: object) -> Session:
    cfg = SessionConfig(data_dir=tmp_path, **kw)  # type: ignore[arg-type]
    return Session(cfg, fuse=mean_fuse)


def moved(truth: np.ndarray, units: Sequence[int], delta: Sequence[float]) -> np.ndarray:
    """``truth`` with the fiducials of ``units`` translated by ``delta`` (mm)."""
    out = truth.copy()
    for u in units:
        out[4 * u : 4 * u + 4] += np.asarray(delta, dtype=float)
    return out


def disp_by_before(report: dict, truth_before: np.ndarray) -> dict[int, np.ndarray]:
    """Measured displacement of each baseline fiducial, keyed by its index in ``truth_before``."""
    out = {}
    for f in report["fiducials"]:
        if f["displacement_mm"] is None:
            continue
        i = int(np.argmin(np.linalg.norm(truth_before - np.array(f["before_mm"]), axis=1)))
        out[i] = np.array(f["displacement_mm"])
    return out


def test_auto_baseline_waits_for_a_settled_scene(rng: np.random.Generator) -> None:
    truth = scene()
    s = make(baseline_frames=5)
    # A camera still being set up: the scene jumps 3 mm between frames -> no baseline.
    shaky = [frame(truth + np.array([3.0 * k, 0, 0]), rng) for k in range(6)]
    assert not of_type(feed(s, shaky, 0.0), BaselineCaptured)
    assert s.phase == Phase.WAITING_BASELINE
    events = feed(s, [frame(truth, rng) for _ in range(5)], 10.0)
    (cap,) = of_type(events, BaselineCaptured)
    assert cap.baseline.n_frames == 5 and cap.baseline.reason == "auto"
    got = np.array([p.position_mm for p in cap.baseline.poses])
    err = np.linalg.norm(got - truth, axis=1)
    assert err.max() < 0.3  # fused over 5 frames of 0.1 mm z noise
    assert s.phase == Phase.MONITORING


def test_run_cycle_reports_cumulative_and_incremental(rng: np.random.Generator) -> None:
    truth0 = scene()
    s = make(baseline_frames=3, settle_frames=3)
    feed(s, [frame(truth0, rng) for _ in range(3)], 0.0)
    assert s.baseline is not None

    # Run 1: unit 0 moves 12 mm along x.
    truth1 = moved(truth0, [0], [12.0, 0.0, 0.0])
    s.set_run_id("storm-A")
    s.set_run_active(True, 1.0)
    assert s.phase == Phase.RUN_ACTIVE
    # During the run the scene moves: nothing is measured.
    assert not feed(s, [frame(truth0 + rng.normal(0, 5, truth0.shape), rng) for _ in range(4)], 1.1)
    s.set_run_active(False, 2.0)
    assert s.phase == Phase.SETTLING
    # Still wobbling for two frames, then settled.
    wobble = [frame(moved(truth1, [5], [3.0 * k, 0, 0]), rng) for k in range(1, 3)]
    assert not of_type(feed(s, wobble, 2.1), RunCompleted)
    (done,) = of_type(feed(s, [frame(truth1, rng) for _ in range(3)], 3.0), RunCompleted)
    run = done.run
    assert run.run_id == "storm-A" and run.sequence == 1
    assert run.report["settled"] is True and run.report["frames_fused"] == 3
    assert run.report["incremental"] is None
    d = disp_by_before(run.report, truth0)
    for i in range(len(truth0)):
        want = truth1[i] - truth0[i]
        assert np.linalg.norm(d[i] - want) < 0.5, (i, d[i], want)
    assert sum(m.kind == "arrow" for m in run.markers) == len(truth0)
    assert len(run.rows) == len(run.report["fiducials"])

    # Run 2 (no id announced): unit 2 moves 6 mm along y.
    truth2 = moved(truth1, [2], [0.0, 6.0, 0.0])
    s.set_run_active(True, 5.0)
    s.set_run_active(False, 6.0)
    (done2,) = of_type(feed(s, [frame(truth2, rng) for _ in range(3)], 6.1), RunCompleted)
    run2 = done2.run
    assert run2.run_id == "run-002"
    cum = disp_by_before(run2.report, truth0)
    assert np.linalg.norm(cum[0] - [12.0, 0, 0]) < 0.5  # cumulative keeps run 1's motion
    assert np.linalg.norm(cum[9] - [0, 6.0, 0]) < 0.5
    inc = disp_by_before(run2.report["incremental"], truth1)
    assert np.linalg.norm(inc[0]) < 0.5  # incremental: unit 0 did not move in run 2
    assert np.linalg.norm(inc[9] - [0, 6.0, 0]) < 0.5
    assert run2.report["incremental"]["summary"]["moved_units"] == 1


def test_frames_stamped_before_the_stop_are_not_used(rng: np.random.Generator) -> None:
    truth0 = scene()
    s = make(baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    truth1 = moved(truth0, [1], [0.0, 0.0, 9.0])
    s.set_run_active(True, 10.0)
    s.set_run_active(False, 20.0)
    # Frames still in the pipeline when the stop arrived: stamped before it, scene mid-run.
    late = [frame(truth0 + np.array([30.0, 0, 0]), rng) for _ in range(3)]
    assert not feed(s, late, 19.0)
    (done,) = of_type(feed(s, [frame(truth1, rng) for _ in range(2)], 20.5), RunCompleted)
    d = disp_by_before(done.run.report, truth0)
    assert np.linalg.norm(d[7] - [0, 0, 9.0]) < 0.5


def test_run_id_delivered_after_the_stop_names_the_run(rng: np.random.Generator) -> None:
    """Run id and run state travel on separate topics: an id announced before the start may be
    delivered after the stop; it still names the run being settled, and a named run keeps its
    name."""
    truth0 = scene()
    s = make(baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    s.set_run_id("wave-001")  # late
    (done,) = of_type(feed(s, [frame(truth0, rng) for _ in range(2)], 2.5), RunCompleted)
    assert done.run.run_id == "wave-001"

    s.set_run_id("wave-002")
    s.set_run_active(True, 3.0)
    s.set_run_active(False, 4.0)
    s.set_run_id("wave-003")  # the next run's id, announced while this one settles
    (done2,) = of_type(feed(s, [frame(truth0, rng) for _ in range(2)], 4.5), RunCompleted)
    assert done2.run.run_id == "wave-002"


def test_settle_timeout_reports_unsettled(rng: np.random.Generator) -> None:
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=3, settle_timeout_frames=6)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    creeping = [frame(truth0 + np.array([2.0 * k, 0, 0]), rng) for k in range(1, 7)]
    events = feed(s, creeping, 3.0)
    (done,) = of_type(events, RunCompleted)
    assert done.run.report["settled"] is False
    assert s.phase == Phase.MONITORING


def test_capture_command_replaces_the_baseline(rng: np.random.Generator) -> None:
    truth0 = scene(16)
    s = make(baseline_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    shifted = truth0 + np.array([0.0, 0.0, 40.0])  # the camera was moved back
    s.capture_baseline()
    assert s.phase == Phase.CAPTURING_BASELINE
    (cap,) = of_type(feed(s, [frame(shifted, rng) for _ in range(2)], 5.0), BaselineCaptured)
    assert cap.baseline.reason == "command"
    z = np.array([p.position_mm[2] for p in cap.baseline.poses])
    assert np.allclose(np.sort(z), np.sort(shifted[:, 2]), atol=0.3)


def test_run_before_any_baseline_uses_the_frames_seen(rng: np.random.Generator) -> None:
    truth0 = scene(16)
    s = make(baseline_frames=5)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)  # too few for the auto baseline
    assert s.baseline is None
    assert not of_type(s.set_run_active(True, 1.0), BaselineCaptured)
    # A pre-run frame still in the pipeline when the start arrived joins the baseline ...
    assert not s.add_frame(frame(truth0, rng), 0.9)
    # ... and the first frame of the run itself (the scene moving) fuses it without joining.
    events = s.add_frame(frame(truth0 + np.array([30.0, 0, 0]), rng), 1.5)
    (cap,) = of_type(events, BaselineCaptured)
    assert cap.baseline.n_frames == 3
    got = np.sort(np.array([p.position_mm[0] for p in cap.baseline.poses]))
    assert np.allclose(got, np.sort(truth0[:, 0]), atol=0.3)


def test_next_run_before_settling_measures_the_last_run(rng: np.random.Generator) -> None:
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=3)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    s.set_run_id("A")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    feed(s, [frame(truth1, rng)], 2.5)  # one frame only, then the next run starts
    s.set_run_id("B")
    # The start is ordered by stamps: run A is closed by the first frame stamped after it.
    assert not of_type(s.set_run_active(True, 3.0), RunCompleted)
    (done,) = of_type(feed(s, [frame(truth1, rng)], 3.1), RunCompleted)
    assert done.run.run_id == "A" and done.run.report["settled"] is False
    d = disp_by_before(done.run.report, truth0)
    assert np.linalg.norm(d[4] - [6.0, 0, 0]) < 0.5
    assert s.phase == Phase.RUN_ACTIVE
    s.set_run_active(False, 4.0)
    (done_b,) = of_type(s.end_of_input(), RunCompleted)  # the bag ended while settling
    assert done_b.run.run_id == "B" and done_b.run.report["frames_fused"] == 0
    assert "error" in done_b.run.report


def test_frames_queued_behind_the_next_start_still_settle_the_last_run(
    rng: np.random.Generator,
) -> None:
    """Hall events and frames travel on separate topics: the next run's start may be handled
    before frames stamped earlier. Those frames still settle the last run."""
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=3)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    s.set_run_id("A")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    s.set_run_id("B")
    s.set_run_active(True, 5.0)  # delivered before the settled frames stamped 2.5 .. 2.7
    (done,) = of_type(feed(s, [frame(truth1, rng) for _ in range(3)], 2.5), RunCompleted)
    assert done.run.run_id == "A" and done.run.report["settled"] is True
    assert s.phase == Phase.RUN_ACTIVE
    s.set_run_active(False, 6.0)
    (done_b,) = of_type(feed(s, [frame(truth1, rng) for _ in range(3)], 6.5), RunCompleted)
    assert done_b.run.run_id == "B" and done_b.run.report["settled"] is True


def test_baseline_frames_delivered_after_the_run_still_make_the_baseline(
    rng: np.random.Generator,
) -> None:
    """A matcher discovered late gets the pre-run frames (TRANSIENT_LOCAL history) after the
    hall's start and stop: stamped before the start, they are still the baseline."""
    truth0 = scene(16)
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    s = make(baseline_frames=3, settle_frames=2)
    s.set_run_id("A")
    s.set_run_active(True, 5.0)
    s.set_run_active(False, 6.0)
    assert s.baseline is None
    assert not feed(s, [frame(truth0, rng) for _ in range(3)], 1.0)  # late, pre-run
    assert not feed(s, [frame(truth1 + 20.0, rng)], 5.5)  # late, mid-run: ignored
    events = feed(s, [frame(truth1, rng) for _ in range(2)], 6.5)
    (cap,) = of_type(events, BaselineCaptured)
    assert cap.baseline.n_frames == 3
    (done,) = of_type(events, RunCompleted)
    d = disp_by_before(done.run.report, truth0)
    assert np.linalg.norm(d[4] - [6.0, 0, 0]) < 0.5
    assert np.linalg.norm(d[0]) < 0.5


def test_state_survives_a_restart(tmp_path: Path, rng: np.random.Generator) -> None:
    truth0 = scene()
    s = make(tmp_path, baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    truth1 = moved(truth0, [0], [5.0, 0, 0])
    s.set_run_id("R1")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    feed(s, [frame(truth1, rng) for _ in range(2)], 2.5)
    assert (tmp_path / "baseline.json").is_file()
    run_files = sorted((tmp_path / "runs").glob("*.json"))
    assert [p.name for p in run_files] == ["0001-R1.json"]
    assert not list(tmp_path.rglob("*.tmp"))  # atomic writes leave no temporaries
    assert json.loads(run_files[0].read_text())["report"]["run_id"] == "R1"

    # A new process on the same directory: same baseline, same runs, and the next run is
    # measured incrementally against the resumed run 1.
    r = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert r.phase == Phase.MONITORING
    assert r.baseline is not None and len(r.baseline.poses) == len(truth0)
    assert s.baseline is not None
    a = np.array([p.position_mm for p in s.baseline.poses])
    b = np.array([p.position_mm for p in r.baseline.poses])
    assert np.array_equal(a, b)
    assert [x.run_id for x in r.runs] == ["R1"]
    truth2 = moved(truth1, [0], [0.0, 4.0, 0])
    r.set_run_active(True, 3.0)
    r.set_run_active(False, 4.0)
    (done,) = of_type(feed(r, [frame(truth2, rng) for _ in range(2)], 4.5), RunCompleted)
    assert done.run.sequence == 2
    inc = disp_by_before(done.run.report["incremental"], truth1)
    assert np.linalg.norm(inc[3] - [0, 4.0, 0]) < 0.5
    cum = disp_by_before(done.run.report, truth0)
    assert np.linalg.norm(cum[3] - [5.0, 4.0, 0]) < 0.5


def test_a_run_in_progress_survives_a_restart(tmp_path: Path, rng: np.random.Generator) -> None:
    """The matcher dies after the hall stopped the run but before the scene settled: the new
    process still measures that run, under its id, once the scene settles."""
    truth0 = scene()
    s = make(tmp_path, baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("R7")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    truth1 = moved(truth0, [1], [0.0, 6.0, 0])
    feed(s, [frame(truth1, rng)], 2.5)  # one frame: not settled yet
    assert s.phase == Phase.SETTLING and not s.runs
    del s  # the crash

    r = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert r.phase == Phase.SETTLING
    # Frames stamped before the stop (still in flight) do not count; settled ones measure it.
    assert not of_type(feed(r, [frame(truth0, rng)], 1.5), RunCompleted)
    (done,) = of_type(feed(r, [frame(truth1, rng) for _ in range(2)], 3.0), RunCompleted)
    assert done.run.run_id == "R7" and done.run.sequence == 1
    cum = disp_by_before(done.run.report, truth0)
    assert np.linalg.norm(cum[4] - [0, 6.0, 0]) < 0.5
    # Measured: a further restart has nothing pending.
    again = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert again.phase == Phase.MONITORING and [x.run_id for x in again.runs] == ["R7"]

    # A restart while waves are running resumes the active run: its stop settles it.
    again.set_run_id("R8")
    again.set_run_active(True, 4.0)
    third = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert third.phase == Phase.RUN_ACTIVE
    third.set_run_active(True, 4.0)  # the hall's latched state, delivered again: harmless
    third.set_run_active(False, 5.0)
    (done,) = of_type(feed(third, [frame(truth1, rng) for _ in range(2)], 5.5), RunCompleted)
    assert done.run.run_id == "R8" and done.run.sequence == 2


def test_corrupt_session_state_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "session.json").write_text('{"phase": "flying"}')
    with pytest.raises(SessionError, match=r"session\.json"):
        make(tmp_path)


def test_corrupt_data_dir_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "baseline.json").write_text("{not json")
    with pytest.raises(SessionError, match=r"baseline\.json"):
        make(tmp_path)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"baseline_frames": 0}, "baseline_frames"),
        ({"settle_tolerance_mm": 0.0}, "settle_tolerance_mm"),
        ({"settle_fraction": 1.5}, "settle_fraction"),
        ({"settle_frames": 5, "settle_timeout_frames": 3}, "settle_timeout_frames"),
        ({"settle_timeout_s": -1.0}, "settle_timeout_s"),
        ({"settle_timeout_s": float("inf")}, "settle_timeout_s"),
    ],
)
def test_bad_config_is_rejected(kw: dict, match: str) -> None:
    with pytest.raises(SessionError, match=match):
        SessionConfig(**kw)


def test_frames_agree(rng: np.random.Generator) -> None:
    truth = scene()
    a, b = frame(truth, rng), frame(truth, rng)
    assert frames_agree(a, b, 0.5, 0.9)
    assert not frames_agree(a, frame(truth + np.array([1.5, 0, 0]), rng), 0.5, 0.9)
    # A few fiducials hidden in one frame (a passing glint) still agree ...
    assert frames_agree(a, frame(truth, rng, drop=2), 0.5, 0.9)
    # ... but half the scene hidden does not.
    assert not frames_agree(a, frame(truth, rng, drop=20), 0.5, 0.9)
    assert frames_agree([], [], 0.5, 0.9)
    assert not frames_agree(a, [], 0.5, 0.9)


def test_memory_holds_the_latest_runs_and_the_disk_all_of_them(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    """Twice RUNS_IN_MEMORY runs: the session holds only the latest, numbers them on, keeps the
    incremental report against the run before, and a restart resumes the count from disk."""
    truth = scene(12)
    s = make(tmp_path, baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth, rng) for _ in range(2)], 0.0)
    n = 2 * RUNS_IN_MEMORY
    for k in range(n):
        t = 10.0 * (k + 1)
        s.set_run_id(f"W{k}")
        s.set_run_active(True, t)
        s.set_run_active(False, t + 1.0)
        truth = moved(truth, [k % 3], [0.5, 0.0, 0.0])
        (done,) = of_type(feed(s, [frame(truth, rng) for _ in range(2)], t + 2.0), RunCompleted)
        assert done.run.sequence == k + 1
        if k:
            assert done.run.report["incremental"] is not None
    assert s.runs_completed == n
    assert [r.run_id for r in s.runs] == [f"W{k}" for k in range(n - RUNS_IN_MEMORY, n)]
    assert len(list((tmp_path / "runs").glob("*.json"))) == n
    again = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert again.runs_completed == n and len(again.runs) == RUNS_IN_MEMORY
    assert again.status()["runs_completed"] == str(n)


def test_an_unusable_data_dir_is_refused_at_start(tmp_path: Path) -> None:
    """A data_dir that is a file cannot hold the baseline: refused when the session starts,
    naming it, rather than at the first save in the middle of a run."""
    taken = tmp_path / "afile"
    taken.write_text("x")
    with pytest.raises(SessionError, match=f"data_dir {taken}"):
        Session(SessionConfig(data_dir=taken))
    fresh = tmp_path / "new" / "dir"
    Session(SessionConfig(data_dir=fresh))
    assert fresh.is_dir()


def test_frames_stamped_behind_the_hall_clock_still_settle_the_run(
    rng: np.random.Generator,
) -> None:
    """A camera clock 12.3 s behind the hall's: every frame after the stop is stamped before it.
    After ``settle_timeout_frames`` such frames in a row the run settles on arrival order, with
    one warning; the next stop is honoured again."""
    lag = 12.3
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=2, settle_timeout_frames=6)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0 - lag)
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    s.set_run_id("A")
    s.set_run_active(True, 10.0)
    s.set_run_active(False, 20.0)
    # Six settled frames count as still in flight: ignored, silently.
    assert not feed(s, [frame(truth1, rng) for _ in range(6)], 20.0 - lag)
    events = s.add_frame(frame(truth1, rng), 21.2 - lag)
    (warn,) = of_type(events, Notice)
    assert warn.level == "warn"
    assert "frames stamped 11.1 s before the hall's stop" in warn.text
    assert "(6 frames)" in warn.text and "settling on arrival order" in warn.text
    assert not of_type(events, RunCompleted)
    events = s.add_frame(frame(truth1, rng), 21.4 - lag)
    assert not of_type(events, Notice)  # warned once
    (done,) = of_type(events, RunCompleted)
    assert done.run.run_id == "A" and done.run.report["settled"] is True
    d = disp_by_before(done.run.report, truth0)
    assert np.linalg.norm(d[4] - [6.0, 0, 0]) < 0.5

    # The counter restarts at each stop: a few in-flight frames after the next stop (a settled
    # but wrong scene) are ignored again.
    s.set_run_active(True, 30.0)
    s.set_run_active(False, 40.0)
    assert not feed(s, [frame(truth0 + 30.0, rng) for _ in range(3)], 39.0)
    (done2,) = of_type(feed(s, [frame(truth1, rng) for _ in range(2)], 40.5), RunCompleted)
    d2 = disp_by_before(done2.run.report, truth0)
    assert np.linalg.norm(d2[4] - [6.0, 0, 0]) < 0.5


def test_a_full_disk_keeps_files_in_memory_until_it_frees_up(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Saves failing with ENOSPC neither raise nor lose anything: each failure is an error
    notice, the run is still measured and reported, and the next save once the disk has room
    writes every file kept in memory, in order, with its latest content."""
    truth0 = scene(16)
    s = make(tmp_path, baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    writes: list[Path] = []
    real_write = session_module.write_json_atomic

    def full_disk(path: Path, doc: object) -> None:
        raise OSError(28, "No space left on device")

    def counting_write(path: Path, doc: object) -> None:
        writes.append(path)
        real_write(path, doc)

    monkeypatch.setattr(session_module, "write_json_atomic", full_disk)
    state = tmp_path / "session.json"
    s.set_run_id("R1")
    (err,) = [e for e in of_type(s.set_run_active(True, 1.0), Notice) if e.level == "error"]
    assert err.text == (
        f"could not save {state}: No space left on device; kept in memory, retried at the next save"
    )
    assert s.unsaved_paths == (state,)
    assert s.status()["unsaved_files"] == "1"
    s.set_run_active(False, 2.0)
    assert s.unsaved_paths == (state,)  # the newer state replaced the older one
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    events = feed(s, [frame(truth1, rng) for _ in range(2)], 2.5)
    (done,) = of_type(events, RunCompleted)
    assert done.run.run_id == "R1" and done.run.report["settled"] is True
    assert any(e.level == "error" and "No space left" in e.text for e in of_type(events, Notice))
    run_file = tmp_path / "runs" / "0001-R1.json"
    assert s.unsaved_paths == (run_file, state)
    assert s.status()["unsaved_files"] == "2"
    assert not run_file.exists()
    assert not state.exists()  # none before the first run

    monkeypatch.setattr(session_module, "write_json_atomic", counting_write)
    events = s.set_run_active(True, 3.0)  # the next save
    assert writes == [run_file, state]
    assert not [e for e in of_type(events, Notice) if e.level == "error"]
    assert any("wrote the 2 files kept in memory" in e.text for e in of_type(events, Notice))
    assert s.unsaved_paths == () and s.status()["unsaved_files"] == "0"
    assert json.loads(run_file.read_text())["report"]["run_id"] == "R1"
    assert json.loads(state.read_text())["phase"] == "run_active"  # the latest, not a stale one
    assert not list(tmp_path.rglob("*.tmp"))
    again = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert [r.run_id for r in again.runs] == ["R1"] and again.phase == Phase.RUN_ACTIVE


def test_end_of_input_retries_unsaved_files(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The end of a bag is the last chance to write what a disk error kept in memory."""
    real_write = session_module.write_json_atomic

    def full_disk(path: Path, doc: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(session_module, "write_json_atomic", full_disk)
    s = make(tmp_path, baseline_frames=2)
    events = feed(s, [frame(scene(16), rng) for _ in range(2)], 0.0)
    assert of_type(events, BaselineCaptured)
    assert s.unsaved_paths == (tmp_path / "baseline.json",)
    monkeypatch.setattr(session_module, "write_json_atomic", real_write)
    s.end_of_input()
    assert s.unsaved_paths == ()
    assert json.loads((tmp_path / "baseline.json").read_text())["n_frames"] == 2


def test_a_reused_run_id_warns_once(rng: np.random.Generator) -> None:
    """The hall announcing the last run's id again means the next run gets an automatic name:
    a warning, once; a hall republishing the id periodically does not flood the log."""
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("A")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    feed(s, [frame(truth0, rng) for _ in range(2)], 2.5)
    (warn,) = s.set_run_id("A")
    assert isinstance(warn, Notice) and warn.level == "warn"
    assert "run id A already measured" in warn.text and "run-002" in warn.text
    assert s.set_run_id("A") == []
    assert s.set_run_id(" A ") == []
    s.set_run_active(True, 3.0)
    s.set_run_active(False, 4.0)
    (done,) = of_type(feed(s, [frame(truth0, rng) for _ in range(2)], 4.5), RunCompleted)
    assert done.run.run_id == "run-002"


def _measure(s: Session, rng: np.random.Generator, truth: np.ndarray, t: float) -> RunCompleted:
    """One run from ``t``: started, stopped, settled on two frames of ``truth``."""
    s.set_run_active(True, t)
    s.set_run_active(False, t + 1.0)
    (done,) = of_type(feed(s, [frame(truth, rng) for _ in range(2)], t + 1.5), RunCompleted)
    return done


def test_an_older_runs_id_is_not_given_to_a_second_run(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    """Not only the last run's id: the id of any completed run of the session, also one on disk
    from before a restart, is ignored with one warning per run, and the run gets a name of its
    own (and its own run file)."""
    truth0 = scene(16)
    s = make(tmp_path, baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    for k, run_id in enumerate(("A", "B")):
        s.set_run_id(run_id)
        assert _measure(s, rng, truth0, 10.0 * (k + 1)).run.run_id == run_id
    (warn,) = s.set_run_id("A")  # run 1's id, after run 2
    assert isinstance(warn, Notice) and warn.level == "warn"
    assert "run id A already measured (run 1)" in warn.text and "run-003" in warn.text
    assert s.set_run_id("A") == []  # once per run
    assert _measure(s, rng, truth0, 30.0).run.run_id == "run-003"

    # Delivered late, while the run is active: the run keeps its automatic name.
    s.set_run_active(True, 40.0)
    (warn,) = s.set_run_id("B")
    assert isinstance(warn, Notice) and warn.level == "warn"
    assert "run id B already measured (run 2)" in warn.text and "run-004 keeps" in warn.text
    s.set_run_active(False, 41.0)
    (done,) = of_type(feed(s, [frame(truth0, rng) for _ in range(2)], 41.5), RunCompleted)
    assert done.run.run_id == "run-004"

    # A restarted matcher knows every id on disk, beyond the runs it holds in memory.
    for k in range(RUNS_IN_MEMORY):
        s.set_run_id(f"C{k}")
        _measure(s, rng, truth0, 50.0 + 10.0 * k)
    r = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert "A" not in [run.run_id for run in r.runs]
    (warn,) = r.set_run_id("A")
    assert isinstance(warn, Notice) and "run id A already measured (run 1)" in warn.text
    n = r.runs_completed + 1
    assert _measure(r, rng, truth0, 200.0).run.run_id == f"run-{n:03d}"
    ids = [json.loads(f.read_text())["run_id"] for f in sorted((tmp_path / "runs").glob("*"))]
    assert len(ids) == len(set(ids)) == n


def test_a_run_id_republished_while_its_run_settles_does_not_name_the_next_run(
    rng: np.random.Generator,
) -> None:
    """A hall republishing the id of the run being settled: that id would have named the next
    run once the run completed; the next run is named automatically, with a warning."""
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("A")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    assert s.set_run_id("A") == []  # run A is not measured yet
    feed(s, [frame(truth0, rng) for _ in range(2)], 2.5)
    events = s.set_run_active(True, 3.0)
    (warn,) = [e for e in of_type(events, Notice) if e.level == "warn"]
    assert "run id A already measured (run 1); ignored: this run is named run-002" in warn.text
    assert s.status()["current_run_id"] == "run-002"


def test_an_automatic_run_name_taken_by_the_hall_gets_a_suffix(rng: np.random.Generator) -> None:
    """The hall may use ids of the automatic form: an unnamed run gets ``run-NNN-2`` then."""
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("run-002")
    assert _measure(s, rng, truth0, 1.0).run.run_id == "run-002"
    assert _measure(s, rng, truth0, 5.0).run.run_id == "run-002-2"


def test_a_short_still_wait_before_the_run_is_a_baseline_without_a_warning(
    rng: np.random.Generator,
) -> None:
    """Four agreeing frames when five were asked for (the bundled session bag): the baseline
    is their fusion, said at info level; frames that disagree still give the warning."""
    truth0 = scene(16)
    s = make(baseline_frames=5)
    feed(s, [frame(truth0, rng) for _ in range(4)], 0.0)
    assert s.baseline is None
    events = s.set_run_active(True, 1.0) + s.add_frame(frame(truth0 + 30.0, rng), 1.2)
    (cap,) = of_type(events, BaselineCaptured)
    assert cap.baseline.n_frames == 4
    (note,) = of_type(events, Notice)[-1:]
    assert note.level == "info" and "4 agreeing frames before the run" in note.text

    shaky = make(baseline_frames=5)
    feed(shaky, [frame(truth0 + 5.0 * k, rng) for k in range(4)], 0.0)  # the scene moving
    events = shaky.set_run_active(True, 1.0) + shaky.add_frame(frame(truth0, rng), 1.2)
    assert of_type(events, BaselineCaptured)
    assert any(
        e.level == "warn" and "before the baseline settled: fused 4" in e.text
        for e in of_type(events, Notice)
    )


def test_a_lagging_clock_does_not_make_a_baseline_of_frames_after_the_run(
    rng: np.random.Generator,
) -> None:
    """No baseline yet and a camera clock far behind the hall's: the frames after the run are
    stamped before its start, which looks like delayed pre-run frames. Once the lag shows, they
    are not fused into a baseline (which would report the run's moves as zero): the run is
    reported without a baseline instead."""
    lag = 100.0
    truth1 = moved(scene(16), [1], [6.0, 0, 0])
    s = make(baseline_frames=2, settle_frames=2, settle_timeout_frames=4)
    s.set_run_id("A")
    s.set_run_active(True, 10.0)
    s.set_run_active(False, 20.0)
    events = feed(s, [frame(truth1, rng) for _ in range(7)], 21.0 - lag)
    assert not of_type(events, BaselineCaptured) and s.baseline is None
    (done,) = of_type(events, RunCompleted)
    assert done.run.report["error"] == "no baseline"


def test_capture_baseline_while_a_run_settles_measures_the_run_first(
    rng: np.random.Generator,
) -> None:
    """The command arriving between the stop and the settled frames used to throw the run
    away (never measured, its after-state made the reference): the run is measured against the
    old baseline, then the new baseline is captured from the next frames."""
    truth0 = scene(16)
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    s = make(baseline_frames=2, settle_frames=2)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("A")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    (note,) = s.capture_baseline()
    assert note.level == "info" and "after run A is measured" in note.text
    assert s.phase == Phase.SETTLING
    (done,) = of_type(feed(s, [frame(truth1, rng) for _ in range(2)], 2.5), RunCompleted)
    assert done.run.run_id == "A"
    assert np.linalg.norm(disp_by_before(done.run.report, truth0)[4] - [6.0, 0, 0]) < 0.5
    assert s.phase == Phase.CAPTURING_BASELINE
    (cap,) = of_type(feed(s, [frame(truth1, rng) for _ in range(2)], 3.0), BaselineCaptured)
    assert cap.baseline.reason == "command" and s.phase == Phase.MONITORING


def test_a_run_whose_frames_stop_is_measured_after_settle_timeout_s(
    rng: np.random.Generator,
) -> None:
    """The camera stops one frame after the run (not settled, below settle_timeout_frames):
    the run used to wait for frames for ever. After ``settle_timeout_s`` (the caller's
    monotonic clock, no sleeping) it is measured on the frame it has, with a warning."""
    truth0 = scene(16)
    truth1 = moved(truth0, [1], [6.0, 0, 0])
    s = make(baseline_frames=2, settle_frames=3, settle_timeout_s=60.0)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("A")
    s.set_run_active(True, 1.0, now_s=1000.0)
    s.set_run_active(False, 2.0, now_s=1030.0)
    assert not s.add_frame(frame(truth1, rng), 2.5, now_s=1031.0)
    assert s.tick(1060.0) == [] and s.tick(1089.9) == []  # 59.9 s: still settling
    assert s.phase == Phase.SETTLING
    events = s.tick(1090.0)
    (done,) = of_type(events, RunCompleted)
    assert done.run.run_id == "A" and done.run.report["settled"] is False
    assert done.run.report["frames_fused"] == 1
    assert np.linalg.norm(disp_by_before(done.run.report, truth0)[4] - [6.0, 0, 0]) < 0.5
    (warn,) = [e for e in of_type(events, Notice) if e.level == "warn"]
    assert "not settled within settle_timeout_s (60 s, 1 frames): measured on the last 1" in (
        warn.text
    )
    assert s.phase == Phase.MONITORING
    assert s.tick(5000.0) == []  # nothing pending any more


def test_a_run_without_any_frame_after_it_is_reported_as_not_measured(
    rng: np.random.Generator,
) -> None:
    """No frame at all after the stop (the camera was switched off with the waves): after
    ``settle_timeout_s`` the run is reported as not measured (an error, no displacements), and
    a next run started meanwhile begins; a frame at the time of the timeout also ends it."""
    truth0 = scene(16)
    s = make(baseline_frames=2, settle_frames=2, settle_timeout_s=30.0)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("A")
    s.set_run_active(True, 1.0, now_s=0.0)
    s.set_run_active(False, 2.0, now_s=10.0)
    # Frames stamped before the stop keep coming (in flight): not after-run frames.
    assert not feed(s, [frame(truth0 + 30.0, rng) for _ in range(2)], 1.5)
    s.set_run_id("B")
    assert not of_type(s.set_run_active(True, 50.0, now_s=20.0), RunCompleted)  # deferred
    events = s.tick(40.0)
    (done,) = of_type(events, RunCompleted)
    assert done.run.run_id == "A" and done.run.report["frames_fused"] == 0
    assert done.run.report["settled"] is False
    assert done.run.report["error"] == "no frame after run within settle_timeout_s (30 s)"
    assert done.run.report["fiducials"] == [] and done.run.markers == ()
    (err,) = [e for e in of_type(events, Notice) if e.level == "error"]
    assert "run A: not measured: no frame in the 30 s after the run" in err.text
    assert "2 frames came, all stamped before the hall's stop" in err.text
    assert s.phase == Phase.RUN_ACTIVE and s.status()["current_run_id"] == "B"

    # The next run: the first frame after the bound ends the settling before it is taken.
    s.set_run_active(False, 60.0, now_s=100.0)
    events = s.add_frame(frame(truth0, rng), 61.0, now_s=130.0)
    (done_b,) = of_type(events, RunCompleted)
    assert done_b.run.run_id == "B" and done_b.run.report["frames_fused"] == 0
    assert s.phase == Phase.MONITORING


def test_settle_timeout_s_zero_or_no_clock_waits_for_frames(rng: np.random.Generator) -> None:
    """0 disables the bound; a caller that never passes the time (a bag analysed offline,
    ended by end_of_input) has none either."""
    truth0 = scene(16)
    for s, now in (
        (make(baseline_frames=2, settle_timeout_s=0.0), 0.0),
        (make(baseline_frames=2), None),
    ):
        feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
        s.set_run_active(True, 1.0, now_s=now)
        s.set_run_active(False, 2.0, now_s=now)
        if now is not None:
            assert s.tick(1e9) == []
        assert s.phase == Phase.SETTLING


def test_after_a_restart_the_settle_bound_starts_at_the_first_time_given(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    """The monotonic clock of a dead process means nothing to the next one: a run resumed
    while settling gets the whole ``settle_timeout_s`` from the restart."""
    truth0 = scene(16)
    s = make(tmp_path, baseline_frames=2, settle_frames=2, settle_timeout_s=30.0)
    feed(s, [frame(truth0, rng) for _ in range(2)], 0.0)
    s.set_run_id("R")
    s.set_run_active(True, 1.0, now_s=500.0)
    s.set_run_active(False, 2.0, now_s=510.0)
    del s
    r = make(tmp_path, baseline_frames=2, settle_frames=2, settle_timeout_s=30.0)
    assert r.phase == Phase.SETTLING
    assert r.tick(7.0) == []  # the new process' clock: the bound starts here
    assert r.tick(36.9) == []
    (done,) = of_type(r.tick(37.0), RunCompleted)
    assert done.run.run_id == "R" and done.run.report["frames_fused"] == 0


def test_the_frames_frame_id_is_kept_in_the_data_dir(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    """A restarted matcher republishes its latched outputs: it must know their frame_id before
    any new frame comes. It is saved (atomically, in session.json) when it changes, also
    between runs, and read back; an empty frame_id does not replace it."""
    truth0 = scene(16)
    s = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert s.frame_id == ""
    for k in range(2):
        s.add_frame(frame(truth0, rng), 0.2 * k, frame_id="cam_optical")
    s.add_frame(frame(truth0, rng), 0.5, frame_id="")
    assert s.frame_id == "cam_optical"
    state = tmp_path / "session.json"
    assert json.loads(state.read_text())["frame_id"] == "cam_optical"
    assert not list(tmp_path.rglob("*.tmp"))
    assert make(tmp_path).frame_id == "cam_optical"  # between runs (no run in progress)

    s.set_run_id("A")
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    s.add_frame(frame(truth0, rng), 2.5, frame_id="cam2_optical")
    resumed = make(tmp_path, baseline_frames=2, settle_frames=2)
    assert resumed.frame_id == "cam2_optical" and resumed.phase == Phase.SETTLING

    # A session.json of an earlier version (no frame_id) still loads.
    doc = json.loads(state.read_text())
    del doc["frame_id"]
    state.write_text(json.dumps(doc))
    assert make(tmp_path).frame_id == ""


def test_a_camera_moved_during_a_run_is_warned(rng: np.random.Generator) -> None:
    """The camera bumped during the wave run (every fiducial 1.5 mm along x after it): the run's
    report carries the warning and the session says so, naming the run; a run with units
    moving but the camera still does not."""
    truth0 = scene(80)
    s = make(baseline_frames=3, settle_frames=3)
    feed(s, [frame(truth0, rng) for _ in range(3)], 0.0)
    s.set_run_active(True, 1.0)
    s.set_run_active(False, 2.0)
    events = feed(s, [frame(moved(truth0, [3], [12.0, 0, 0]), rng) for _ in range(3)], 2.1)
    (done,) = of_type(events, RunCompleted)
    assert done.run.report["warnings"] == []
    assert not [e for e in of_type(events, Notice) if "camera" in e.text]
    s.set_run_active(True, 5.0)
    s.set_run_active(False, 6.0)
    bumped = moved(truth0, [3], [12.0, 0, 0]) + np.array([1.5, 0.0, 0.0])
    events = feed(s, [frame(bumped, rng) for _ in range(3)], 6.1)
    (done,) = of_type(events, RunCompleted)
    (warning,) = [w for w in done.run.report["warnings"] if w.startswith("camera moved")]
    assert "re-capture the baseline" in warning
    # The incremental report (against the previous run, taken with the camera where the
    # baseline had it) warns too; each notice says which comparison it is about.
    incremental = done.run.report["incremental"]["warnings"]
    assert [w for w in incremental if w.startswith("camera moved")]
    notices = [e.text for e in of_type(events, Notice) if e.level == "warn" and "camera" in e.text]
    run = done.run.run_id
    assert [t.split(": camera moved")[0] for t in notices] == [
        f"run {run} against the baseline",
        f"run {run} against the previous run",
    ], notices


def test_saved_poses_keep_their_systematic_covariance_and_axis() -> None:
    """A baseline written to disk and read back after a restart keeps each pose's systematic
    covariance (a known fit bias) and printed axis, and a pose without them stays without;
    baselines saved before the fields existed read as without."""
    bias = np.diag([0.01, 0.02, 3.0])
    axis = np.array([1.0, 0.0, 0.0])
    poses = [
        FiducialPose(3, np.array([1.0, 2.0, 900.0]), np.array([0.0, 0.0, -1.0]), np.eye(3), None),
        FiducialPose(
            17,
            np.array([5.0, 2.0, 910.0]),
            np.array([0.0, 0.6, -0.8]),
            np.eye(3),
            None,
            4,
            bias,
            axis,
        ),
    ]
    back = [
        session_module.pose_from_dict(json.loads(json.dumps(session_module.pose_to_dict(p))))
        for p in poses
    ]
    assert back[0].systematic_mm2 is None
    assert back[1].systematic_mm2 is not None and back[1].n_frames == 4
    np.testing.assert_array_equal(back[1].systematic_mm2, bias)
    assert back[0].axis is None
    assert back[1].axis is not None
    np.testing.assert_array_equal(back[1].axis, axis)
    old = session_module.pose_to_dict(poses[1])
    del old["systematic_mm2"], old["axis"]
    assert session_module.pose_from_dict(old).systematic_mm2 is None
    assert session_module.pose_from_dict(old).axis is None
