"""``armourcam demo``: the three-process graph fed by the bundled session bag, report in OUT."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from . import output_path

REPO = Path(__file__).resolve().parents[3]
BUNDLED = REPO / "bags" / "session_small"


def register(subparsers: Any) -> None:
    """Add the ``demo`` subcommand."""
    p = subparsers.add_parser(
        "demo",
        help="run the ROS 2 graph on the bundled session bag and write the report",
        description=(
            "Start fiducial_detector, pose_estimator and displacement_matcher as three processes, "
            "replay the bundled monitoring-session bag through them over DDS (reliable, as fast "
            "as consumed), and leave each run's report (JSON, CSV, overlay PNG, plot) in OUT; "
            "prints the per-run summary with the ground truth beside it."
        ),
    )
    p.add_argument(
        "--out", type=output_path, default=Path("out"), help="output directory (default out)"
    )
    p.add_argument("--bag", type=Path, default=BUNDLED, help="session bag (default: bundled)")
    p.add_argument(
        "--timeout", type=float, default=300.0, help="give up after this many seconds (300)"
    )
    p.set_defaults(func=run)


def _params(out: Path, data_dir: Path, truth: dict[str, Any] | None, compressed: bool) -> Path:
    spec = (truth or {}).get("spec", {})
    dn = float((truth or {}).get("dn_mm", 20.5))
    det = {"transport": "compressed" if compressed else "raw", "queue_depth": 50}
    pose = {"queue_depth": 50, "diameter_mm": float(spec.get("diameter_mm", 7.1))}
    match = {
        "queue_depth": 50,
        "data_dir": str(data_dir.resolve()),
        "baseline_frames": int(spec.get("baseline_frames", 4)),
        "settle_frames": 3,
        "dn_mm": dn,
        "section_width_mm": float((truth or {}).get("section_width_mm", 0.0)),
    }
    doc = {
        "fiducial_detector": {"ros__parameters": det},
        "pose_estimator": {"ros__parameters": pose},
        "displacement_matcher": {"ros__parameters": match},
    }
    path = out / "graph.params.yaml"
    import yaml

    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _after_images(bag: Path) -> list[Any]:
    """The scene after each wave run: the last frame before the next run starts (the bag's
    last frame for the last run), one per run in order, for the runs' overlays."""
    from armourcam import bagio, sessionbag

    out: list[Any] = []
    last = None
    with bagio.open_bag(bag) as b:
        topic = sessionbag.RUN_ACTIVE_TOPIC
        starts = [m.timestamp_ns for m in b.messages([topic]) if m.message.data]
        # One pass, keeping the last image: each run's ends where the next run starts.
        for frame in b.frames():
            if frame.image is None:
                continue
            while len(out) < len(starts) - 1 and frame.timestamp_ns >= starts[len(out) + 1]:
                out.append(last)
            last = frame.image
    return out + [last] * (max(len(starts), 1) - len(out))


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns 0 when every run of the bag was reported."""
    from armourcam import bagio, graph, sessionbag
    from armourcam.commands.replay import default_remaps

    # The demo's graph talks to itself only (children inherit the environment).
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    out: Path = args.out
    bag: Path = args.bag
    if not bag.exists():
        if bag != BUNDLED:
            raise FileNotFoundError(f"bag {bag} does not exist")
        print(f"{bag} missing: rendering it (armourcam make-bags)", file=sys.stderr)
        sessionbag.write_session_bag(bag)
    truth = sessionbag.read_truth(bag)
    out.mkdir(parents=True, exist_ok=True)
    data_dir = out / "data"
    if data_dir.exists():
        shutil.rmtree(data_dir)  # a demo starts from scratch; a rig would resume from it
    with bagio.open_bag(bag) as b:
        compressed = bool(b.topics_of_type(bagio.COMPRESSED_IMAGE))
        n_runs = sum(1 for m in b.messages(["/hall/run_active"]) if not m.message.data)
        camera = b.camera_model()
    params = _params(out, data_dir, truth, compressed)
    logs = out / "logs"
    print(f"starting the graph (3 processes, logs in {logs}) ...", file=sys.stderr)
    procs = graph.launch_processes(str(params), log_dir=logs)
    t0 = time.monotonic()
    try:
        stats = graph.replay_bag(
            bag,
            remap=default_remaps(bag, None),
            qos="reliable",
            rate=None,
            as_fast_as_consumed=True,
            wait_subscribers=30.0,
            wait_for=("/armourcam/poses",),
            settle_s=0.5,
            progress=_progress,
        )
        print(
            f"replayed {stats.frames} frames over DDS in {stats.seconds:.1f} s "
            f"({stats.frames_confirmed} confirmed by the detector)",
            file=sys.stderr,
        )
        runs = _wait_runs(data_dir, n_runs, args.timeout - (time.monotonic() - t0), procs)
    finally:
        graph.stop_processes(procs.values())
    afters = _after_images(bag)
    written = [
        _write_run_files(out, r, camera, afters[k] if k < len(afters) else None)
        for k, r in enumerate(runs)
    ]
    _print_table(runs, truth)
    print(f"\nreports: {', '.join(str(w) for w in written)}")
    if len(runs) < n_runs:
        print(f"only {len(runs)} of {n_runs} runs reported; see {logs}", file=sys.stderr)
        return 1
    return 0


def _progress(i: int, n: int) -> None:
    if sys.stderr.isatty():
        print(f"\rreplay {i}/{n}", end="" if i < n else "\n", file=sys.stderr)


def _wait_runs(data_dir: Path, n_runs: int, timeout: float, procs: dict[str, Any]) -> list[Any]:
    """Run records the matcher wrote (atomically) to its data directory."""
    deadline = time.monotonic() + max(timeout, 5.0)
    files: list[Path] = []
    while time.monotonic() < deadline:
        files = sorted((data_dir / "runs").glob("*.json")) if (data_dir / "runs").is_dir() else []
        if len(files) >= n_runs:
            break
        dead = [name for name, p in procs.items() if p.poll() is not None]
        if dead:
            print(f"node(s) {dead} exited early", file=sys.stderr)
            break
        time.sleep(0.2)
    return [json.loads(f.read_text()) for f in files]


def _write_run_files(out: Path, run: dict[str, Any], camera: Any, after: Any) -> Path:
    """JSON, CSVs, plot and overlay of one run in OUT/<run_id>/ (the files of ``compare --out``,
    by the same writer)."""
    from displacement_matcher.report import write_report_files

    run_dir = out / run["run_id"]
    write_report_files(run_dir, run["report"], camera=camera, after_image=after)
    return run_dir


def _print_table(runs: list[dict[str, Any]], truth: dict[str, Any] | None) -> None:
    from armourcam.sessionbag import compare_to_truth

    truth_runs = {r["run_id"]: r for r in (truth or {}).get("runs", [])}
    head = (
        f"{'run':<10} {'ref':<11} {'settled':<7} {'matched':>7} {'wrong':>5} "
        f"{'displaced':>9} {'truth':>5} {'lost':>4} {'moved':>5} {'err med':>8} {'err p95':>8}"
    )
    print(head)
    print("-" * len(head))
    for run in runs:
        rep = run["report"]
        tr = truth_runs.get(run["run_id"])
        for ref, part in (("cumulative", rep), ("incremental", rep.get("incremental"))):
            if part is None:
                continue
            summ = part.get("summary", {})
            matched = sum(1 for f in part["fiducials"] if f.get("displacement_mm") is not None)
            tpart = tr.get(ref) if tr else None
            if tpart:
                acc = compare_to_truth(part, tpart)
                truth_n = f"{int(acc['truth_displaced_units'])}"
                wrong = f"{int(acc['wrong'])}"
                errs = f"{acc['err_median_mm']:8.3f} {acc['err_p95_mm']:8.3f}"
            else:
                truth_n, wrong, errs = "-", "-", f"{'-':>8} {'-':>8}"
            print(
                f"{run['run_id']:<10} {ref:<11} {rep.get('settled')!s:<7} {matched:>7} "
                f"{wrong:>5} {summ.get('displaced_units', '-')!s:>9} {truth_n:>5} "
                f"{summ.get('lost_units', '-')!s:>4} {summ.get('moved_units', '-')!s:>5} {errs}"
            )
    print(
        "matched: fiducial pairs; wrong: pairs whose displacement is > 2 mm off the truth; "
        "err: |measured - true displacement| per pair, mm; displaced/truth: units >= 1 Dn; "
        "lost: units none of whose fiducials could be found again (not counted as displaced)"
    )
