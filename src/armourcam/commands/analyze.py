"""``armourcam analyze``: the graph's cores on a bag, without DDS."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from . import output_path


def register(subparsers: Any) -> None:
    """Add the ``analyze`` subcommand."""
    p = subparsers.add_parser(
        "analyze",
        help="measure every wave run of a bag offline (no ROS graph needed)",
        description=(
            "Run detection, pose estimation and the matcher's session (baseline, runs announced "
            "on the hall topics, settling, cumulative and incremental displacement) over a bag "
            "in log-time order. Writes DIR/report.json (every run), per run "
            "DIR/runs/<NNNN>-<run_id>/ with the files of 'compare --out' (report.json, "
            "fiducials.csv, units.csv, plot.png, overlay.png) and DIR/markers, an MCAP bag of "
            "the markers for Foxglove or RViz. Topics are found by type when not given."
        ),
    )
    p.add_argument("bag", type=Path, help="bag directory, .mcap file or ROS 1 .bag")
    p.add_argument("--out", type=output_path, required=True, help="output directory")
    p.add_argument("--image-topic", help="Image or CompressedImage topic")
    p.add_argument("--camera-info-topic", help="CameraInfo topic")
    p.add_argument("--camera", type=Path, help="camera_calibration YAML instead of CameraInfo")
    p.add_argument("--run-active-topic", help="std_msgs/Bool hall run state topic")
    p.add_argument("--run-id-topic", help="std_msgs/String hall run id topic")
    p.add_argument(
        "--diameter-mm", type=float, default=7.1, help="printed fiducial diameter (default 7.1)"
    )
    p.add_argument("--dn-mm", type=float, default=20.5, help="nominal unit size Dn, mm (20.5)")
    p.add_argument(
        "--displaced-dn", type=float, default=1.0, help="displaced from this many Dn (1.0)"
    )
    p.add_argument("--section-width-mm", type=float, help="section width, mm (for N_od)")
    p.add_argument(
        "--units",
        type=Path,
        help="unit map YAML (default: the template is learned from the baseline)",
    )
    p.add_argument("--baseline-frames", type=int, default=5, help="frames fused into the baseline")
    p.add_argument("--settle-frames", type=int, default=3, help="settled frames after a run")
    p.add_argument(
        "--settle-tolerance-mm", type=float, default=0.5, help="settled-scene tolerance, mm"
    )
    p.add_argument(
        "--subpixel",
        choices=("profile", "ml"),
        default="profile",
        help="sub-pixel ellipse method (ml: the edge model, about half the centre noise, slower)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Analyse; prints one line per run."""
    from armourcam.analyze import analyze_bag, text_progress
    from displacement_matcher.markers import Comparer
    from displacement_matcher.session import SessionConfig
    from displacement_matcher.units import load_unit_map
    from pose_estimator.camera import CameraModel

    if not args.bag.exists():
        raise FileNotFoundError(f"bag {args.bag} does not exist")
    calibration = CameraModel.from_yaml(args.camera) if args.camera else None
    cfg = SessionConfig(
        baseline_frames=args.baseline_frames,
        settle_frames=args.settle_frames,
        settle_tolerance_mm=args.settle_tolerance_mm,
    )
    comparer = Comparer(
        dn_mm=args.dn_mm,
        displaced_dn=args.displaced_dn,
        section_width_mm=args.section_width_mm,
        unit_map=load_unit_map(args.units) if args.units else None,
    )
    result = analyze_bag(
        args.bag,
        args.out,
        image_topic=args.image_topic,
        camera_info_topic=args.camera_info_topic,
        run_active_topic=args.run_active_topic,
        run_id_topic=args.run_id_topic,
        diameter_mm=args.diameter_mm,
        subpixel=args.subpixel,
        calibration=calibration,
        session_config=cfg,
        comparer=comparer,
        progress=text_progress("analyze"),
    )
    fids = result.fiducials_per_frame
    print(
        f"frames: {result.frames} ({result.frames_dropped} dropped), fiducials per frame: "
        f"{min(fids) if fids else 0}-{max(fids) if fids else 0}, baseline: "
        f"{result.baseline_fiducials if result.baseline_fiducials is not None else 'none'}"
    )
    for r in result.runs:
        summary = r.report.get("summary") or {}
        said = summary.get("text") or f"not measured: {r.report.get('error') or 'no summary'}"
        print(f"run {r.run_id}: settled={r.report.get('settled')}: {said}")
    for n in result.notices:
        if not n.startswith("info"):  # the info notices are in the report
            print(f"armourcam analyze: {n}", file=sys.stderr)
    print(
        f"report: {args.out / 'report.json'}; per run: {args.out / 'runs'}/<NNNN>-<run_id>/; "
        f"markers bag: {args.out / 'markers'}"
    )
    # Some input could not be used: the bag ends early, or no frame could be measured.
    every_frame_dropped = result.frames > 0 and result.frames_dropped == result.frames
    return 1 if result.truncation is not None or every_frame_dropped else 0
