"""``armourcam compare``: measure unit displacement between before and after images.

Each state may be given as several images of the static scene; their poses are fused. Writes the
report (``report.json``, ``fiducials.csv``, ``units.csv``, ``overlay.png``, ``plot.png``) into
``--out`` and prints the damage summary, or with ``--json`` the report itself.

Images of one state that disagree are named on stderr (:func:`pose_estimator.fusion.fuse_frames`).
When one was taken from another camera position (all its fiducials shifted alike by 0.5 mm or
more) or shows another scene, nothing is compared and the exit status is 1: a moved camera would
add its motion to every displacement. ``--allow-camera-motion`` then aligns the moved images onto
the others (the largest set taken from one position), leaves out those of another scene and
compares, with a warning. A unit of ``--units`` whose baseline fiducials cannot be on one unit (a
code listed under the wrong unit) is named in a warning (:func:`displacement_matcher.compare.
check_unit_map`). Warnings also go into the report's ``warnings`` list, and how each image agreed
into its ``fusion`` entry.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import TYPE_CHECKING, Any

from ..imageio import ImageReadError
from . import output_path
from .detect import add_decimate_option, read_for_camera

if TYPE_CHECKING:
    from pose_estimator.fusion import Fusion

DEFAULT_DN_MM = 20.5  # a 38 mm dolos (Dn ~ 0.54 H)


def register(subparsers: Any) -> None:
    """Add the ``compare`` subcommand."""
    p = subparsers.add_parser(
        "compare",
        help="displacement of armour units between before and after images",
        description=(
            "Detect fiducials in the before and after images (several per state are fused), "
            "match them globally, measure per-unit motion and count the damage. Thresholds are "
            "printed with the numbers."
        ),
    )
    p.add_argument("before", nargs="+", metavar="BEFORE", help="baseline image(s)")
    p.add_argument("--after", nargs="+", required=True, metavar="AFTER", help="after image(s)")
    p.add_argument("--camera", required=True, help="camera_calibration YAML file")
    p.add_argument("--diameter-mm", type=float, default=7.1, help="printed diameter (7.1)")
    p.add_argument("--out", type=output_path, required=True, help="output directory of the report")
    p.add_argument(
        "--units",
        help="unit map YAML (explicit units or a repeated template; default: the template is "
        "learned from the baseline, reported under 'template')",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
    p.add_argument("--design", choices=("any", "ring", "dot"), default="any")
    p.add_argument(
        "--subpixel",
        choices=("profile", "ml"),
        default="profile",
        help="sub-pixel ellipse method (ml: the edge model, about half the centre noise, slower)",
    )
    add_decimate_option(p)
    p.add_argument(
        "--image-fit",
        action="store_true",
        help="refine each pose by fitting the rendered fiducial to the image (more precise in "
        "depth, about 0.1 s per fiducial at 35-45 px, 1 s at 120 px)",
    )
    p.add_argument("--dn-mm", type=float, default=DEFAULT_DN_MM, help="nominal unit size Dn, mm")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--displaced-dn", type=float, help="displacement threshold in Dn (default 1)")
    g.add_argument("--displaced-mm", type=float, help="displacement threshold in mm")
    p.add_argument("--moved-mm", type=float, default=2.0, help="movement threshold, mm (2)")
    p.add_argument("--rotated-deg", type=float, default=10.0, help="rotation counted as moved (10)")
    p.add_argument("--overturn-deg", type=float, default=90.0, help="overturned from (90 deg)")
    p.add_argument("--lost-displaced", action="store_true", help="count lost units as displaced")
    p.add_argument("--section-width-mm", type=float, help="section width along the crest (N_od)")
    p.add_argument(
        "--gate-mm",
        type=float,
        default=None,
        help="matching gate, mm: a fiducial moved further is not matched (default: 50 mm or "
        "2.4 Dn, whichever is longer; a unit map's codes are matched at any distance)",
    )
    p.add_argument("--code-penalty-mm", type=float, default=None, help="cross-code penalty, mm")
    p.add_argument("--no-cross-code", action="store_true", help="forbid cross-code matches")
    p.add_argument(
        "--allow-camera-motion",
        action="store_true",
        help="images of one state taken from different camera positions are refused (exit 1); "
        "with this flag the moved ones are aligned onto the others and images of another scene "
        "left out",
    )
    p.set_defaults(func=run)


def _readable(paths: list[str], camera: Any, failed: list[str]) -> tuple[list[str], list[Any]]:
    """The images of one state that can be read and fit the calibration (with their paths);
    one line naming the file and the problem per other file, appended to ``failed``."""
    used: list[str] = []
    images: list[Any] = []
    for path in paths:
        try:
            images.append(read_for_camera(path, camera))
        except ImageReadError as err:
            failed.append(str(err))
            continue
        used.append(path)
    return used, images


def run(args: argparse.Namespace) -> int:
    """Run the comparison, write the report, print the summary or the JSON."""
    from displacement_matcher.compare import compare_poses, state_from_images
    from displacement_matcher.damage import thresholds
    from displacement_matcher.report import write_report_files
    from displacement_matcher.units import load_unit_map
    from pose_estimator.camera import CameraModel

    camera = CameraModel.from_yaml(args.camera)
    unit_map = load_unit_map(args.units) if args.units else None
    limits = thresholds(
        args.dn_mm,
        displaced_mm=args.displaced_mm,
        displaced_dn=args.displaced_dn,
        moved_mm=args.moved_mm,
        rotated_deg=args.rotated_deg,
        overturn_deg=args.overturn_deg,
        lost_displaced=args.lost_displaced,
    )
    failed: list[str] = []
    before_paths, before_imgs = _readable(args.before, camera, failed)
    after_paths, after_imgs = _readable(args.after, camera, failed)
    for message in failed:
        print(f"armourcam compare: error: {message}", file=sys.stderr)
    missing = [name for name, imgs in (("BEFORE", before_imgs), ("AFTER", after_imgs)) if not imgs]
    if missing:
        print(
            f"armourcam compare: error: no usable {' or '.join(missing)} image; nothing compared",
            file=sys.stderr,
        )
        return 1
    states = [
        state_from_images(
            imgs,
            camera,
            args.diameter_mm,
            design=args.design,
            subpixel=args.subpixel,
            image_fit=args.image_fit,
            decimate=args.decimate,
            align=args.allow_camera_motion,
        )
        for imgs in (before_imgs, after_imgs)
    ]
    from pose_estimator.fusion import MOTION_VERDICTS

    refused = not args.allow_camera_motion and any(state.camera_moved for state in states)
    warnings: list[str] = []
    for name, paths, state in zip(
        ("BEFORE", "AFTER"), (before_paths, after_paths), states, strict=True
    ):
        for frame in state.disagreeing:
            message = f"{name} image {frame.describe(paths)}"
            level = "error" if refused and frame.verdict in MOTION_VERDICTS else "warning"
            print(f"armourcam compare: {level}: {message}", file=sys.stderr)
            warnings.append(message)
        consensus = ", ".join(paths[i] for i in state.consensus)
        done = []
        if state.aligned:
            done.append(f"aligned {', '.join(paths[i] for i in state.aligned)} onto {consensus}")
        left = [paths[i] for i in range(len(paths)) if i not in state.fused]
        if left:
            done.append(f"left out {', '.join(left)}")
        if done:
            message = (
                f"{name}: {' and '.join(done)} (--allow-camera-motion): its displacements are "
                f"measured from the camera position of {consensus}"
            )
            print(f"armourcam compare: warning: {message}", file=sys.stderr)
            warnings.append(message)
    if refused:
        print(
            "armourcam compare: error: the images of one state were not all taken from one "
            "camera position of one scene, and a moved camera adds its motion to every "
            "displacement: nothing compared. Pass only images taken from one position, or "
            "--allow-camera-motion to align them onto the largest such set",
            file=sys.stderr,
        )
        return 1
    before, after = (list(state.poses) for state in states)
    kw: dict[str, float] = {}
    if args.gate_mm is not None:
        kw["gate_mm"] = args.gate_mm
    if args.code_penalty_mm is not None:
        kw["code_penalty_mm"] = args.code_penalty_mm
    if args.no_cross_code:
        kw["code_penalty_mm"] = math.inf
    cmp = compare_poses(
        before, after, limits, unit_map=unit_map, section_width_mm=args.section_width_mm, **kw
    )
    extra = {
        "inputs": {
            "before": before_paths,
            "after": after_paths,
            "unusable": failed,
            "camera": args.camera,
            "diameter_mm": args.diameter_mm,
            "before_fiducials": len(before),
            "after_fiducials": len(after),
        },
        "fusion": {
            "before": _agreement_rows(states[0], before_paths),
            "after": _agreement_rows(states[1], after_paths),
        },
        "warnings": [*warnings, *cmp.warnings],
    }
    # One report mapping for the files and for --json.
    rep = cmp.report()
    rep.update(extra)
    write_report_files(args.out, rep, camera=camera, after_image=after_imgs[states[1].consensus[0]])
    if args.json:
        json.dump(rep, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        c = cmp.result.counts()
        print(
            f"fiducials: before {len(before)}, after {len(after)}; same-code {c['same_code']}, "
            f"cross-code {c['cross_code']}, vanished {c['vanished']}, appeared {c['appeared']}"
        )
        print(cmp.summary.describe())
        print(f"report written to {args.out}")
    problems = _measured_nothing(
        before, after, cmp.result.counts(), len(before_imgs), len(after_imgs)
    )
    for message in problems:
        print(f"armourcam compare: error: {message}", file=sys.stderr)
    for message in cmp.warnings:
        print(f"armourcam compare: warning: {message}", file=sys.stderr)
    if cmp.unassigned:
        codes = sorted({int(before[i].code) for i in cmp.unassigned})
        print(
            f"armourcam compare: warning: {len(cmp.unassigned)} BEFORE fiducials have codes not "
            f"in the unit map ({', '.join(map(str, codes))}); they are in no unit",
            file=sys.stderr,
        )
    return 1 if failed or problems else 0


def _agreement_rows(state: Fusion, paths: list[str]) -> list[dict[str, Any]]:
    """How each image of a state agreed with the others (``pose_estimator.fusion.Fusion``), as
    the report's ``fusion`` rows (camera frame, mm)."""
    rows = []
    for a in state.frames:
        rows.append(
            {
                "image": paths[a.frame],
                "verdict": a.verdict,
                "reference": [paths[i] for i in a.reference],
                "fiducials": a.n_poses,
                "shared": a.n_shared,
                "motion_mm": round(a.motion_mm, 4),
                "shift_mm": [round(float(x), 4) for x in a.shift_mm],
                "rotation_deg": round(a.rotation_deg, 4),
                "motion_chi2": round(a.motion_chi2, 2),
                "motion_dof": a.motion_dof,
                "chi2": round(a.chi2, 2),
                "outliers": a.n_outliers,
                "fused": a.frame in state.fused,
                "aligned": a.frame in state.aligned,
            }
        )
    return rows


def _measured_nothing(
    before: list[Any], after: list[Any], counts: dict[str, int], n_before: int, n_after: int
) -> list[str]:
    """Why a comparison measured nothing (a report of "nothing displaced" would be a lie)."""
    out = []
    for name, poses, n in (("BEFORE", before, n_before), ("AFTER", after, n_after)):
        if not poses:
            out.append(
                f"no fiducial found in the {n} {name} image{'s' if n > 1 else ''} (wrong "
                "--design or --diameter-mm, out of focus, another scene?): nothing was measured"
            )
    if before and after and counts["same_code"] + counts["cross_code"] == 0:
        out.append(
            f"none of the {len(before)} BEFORE fiducials was found again among the "
            f"{len(after)} AFTER ones (another scene, or the camera moved?): nothing was measured"
        )
    return out
