"""``armourcam detect``: find fiducials in image files and print them as a table or JSON.

``armourcam detect IMAGE... [--design ring|dot|any] [--json]``. Each file is processed on its
own: a file that cannot be read (missing, empty, not an image, truncated) gets a one-line error
and the others are still processed; the exit status is 1 when any file failed.

Table output: one row per detection; its semi-axes are those of the outermost fitted circle,
named in the ``circle`` column (``outer``, the printed outer circle, for both designs: the
``ring`` design's pose circle, the ``dot`` design's coding-track arc, not its small pose dot;
see :func:`outer_ellipse`). The JSON lists every fitted ellipse with its ``radius``.

JSON output: ``{"images": [{"path", "error", "detections": [...]}]}`` with one record per
detection built by :func:`detection_record` (extend that function to add fields, e.g. a pose).
Pixel coordinates ``(u, v)``: pixel centres at integer coordinates (OpenCV's convention).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

from fiducial_detector import DESIGNS, DetectorError, detect
from fiducial_detector.detect import DECIMATE_FACTORS, SUBPIXEL_METHODS
from fiducial_detector.types import Ellipse, FiducialDetection
from pose_estimator import CalibrationError, CameraModel, FiducialPose, estimate
from pose_estimator.image_fit import refine_from_image

from ..imageio import ImageReadError, read_image


def register(subparsers: Any) -> None:
    """Add the ``detect`` subcommand."""
    parser = subparsers.add_parser(
        "detect",
        help="find fiducials in image files",
        description=(
            "Detect armourcam fiducials in PNG, JPEG or TIFF images (8 or 16 bit, grey or colour) "
            "and print code, centre and fitted ellipses of each. Pixel centres are at integer "
            "coordinates."
        ),
    )
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="image files")
    parser.add_argument(
        "--design",
        choices=("any", "ring", "dot"),
        default="any",
        help="fiducial design to look for (default: any, both designs in one image)",
    )
    parser.add_argument(
        "--subpixel",
        choices=SUBPIXEL_METHODS,
        default="profile",
        help="sub-pixel ellipse method: profile (default, fast) or ml (the edge model, about "
        "half the centre noise)",
    )
    add_decimate_option(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--camera",
        metavar="CAMERA.yaml",
        type=_camera,
        help=(
            "camera_calibration YAML of the camera (plumb_bob or rational_polynomial): adds "
            "position_mm, normal and sigma_mm (camera frame, millimetres) to each detection"
        ),
    )
    parser.add_argument(
        "--diameter-mm",
        type=_diameter,
        default=7.1,
        help="printed diameter of the fiducials' outer circle, mm (default: 7.1)",
    )
    parser.add_argument(
        "--image-fit",
        action="store_true",
        help=(
            "with --camera: refine each pose by fitting the rendered fiducial to the image "
            "(pose_estimator.image_fit: several times more precise in depth for small or "
            "oblique fiducials, about 0.1 s per fiducial at 35-45 px, 1 s at 120 px)"
        ),
    )
    parser.set_defaults(func=run)


def _camera(path: str) -> CameraModel:
    """argparse type: a calibration file, with a clear error when it is malformed."""
    try:
        return CameraModel.from_yaml(path)
    except CalibrationError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _diameter(text: str) -> float:
    """argparse type: a positive printed diameter in millimetres."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"--diameter-mm must be a positive number, got {text!r}")
    return value


def ellipse_record(ellipse: Ellipse) -> dict[str, Any]:
    """JSON record of one fitted ellipse (pixels, radians; ``radius`` = nominal printed radius as
    a fraction of the outer radius; ``sigma_center_px`` = standard deviations of u and v;
    ``systematic_px`` = the fit method's known systematic error, ``Ellipse.systematic_px``)."""
    cov = np.asarray(ellipse.covariance, dtype=np.float64)
    sigma = np.sqrt(np.maximum(np.diag(cov)[:2], 0.0)) if cov.shape == (5, 5) else np.zeros(2)
    return {
        "center_px": [float(ellipse.center_px[0]), float(ellipse.center_px[1])],
        "semi_major": float(ellipse.semi_major),
        "semi_minor": float(ellipse.semi_minor),
        "angle": float(ellipse.angle),
        "radius": float(ellipse.radius),
        "sigma_center_px": [float(sigma[0]), float(sigma[1])],
        "systematic_px": float(ellipse.systematic_px),
    }


def detection_record(detection: FiducialDetection, **_context: Any) -> dict[str, Any]:
    """JSON record of one detection: the single place that decides the per-detection fields.

    Keyword arguments are context: ``pose`` (a FiducialPose, or None where the detection gave
    none) adds the pose fields (:func:`pose_record`); others are ignored.
    """
    record = {
        "code": int(detection.code),
        "center_px": [float(detection.center_px[0]), float(detection.center_px[1])],
        "hamming": int(detection.hamming),
        "design": detection.design,
        "contrast": float(detection.contrast),
        "rotation": float(detection.rotation),
        "ellipses": [ellipse_record(e) for e in detection.ellipses],
    }
    if "pose" in _context:
        record.update(pose_record(_context["pose"]))
    return record


def pose_record(pose: FiducialPose | None) -> dict[str, Any]:
    """Pose fields of one detection (camera frame: x right, y down, z forward; millimetres).

    ``position_mm`` [x, y, z] of the fiducial's centre, unit ``normal`` [nx, ny, nz] out of the
    printed face, ``sigma_mm`` [sx, sy, sz] standard deviations (the scatter from image to
    image), ``systematic_sigma_mm`` [sx, sy, sz] those of a known fit bias, the same in every
    image (zeros for most fiducials; see ``FiducialPose.systematic_mm2``), unit ``axis`` [ax, ay,
    az] the printed +x axis, where the code's sector 0 starts (None when not measured); all None
    when the pose circle gives no real pose.
    """
    if pose is None:
        return {
            "position_mm": None,
            "normal": None,
            "axis": None,
            "sigma_mm": None,
            "systematic_sigma_mm": None,
        }
    return {
        "position_mm": [float(x) for x in pose.position_mm],
        "normal": [float(x) for x in pose.normal],
        "axis": None if pose.axis is None else [float(x) for x in pose.axis],
        "sigma_mm": [float(x) for x in pose.sigma_mm],
        "systematic_sigma_mm": [float(x) for x in pose.systematic_sigma_mm],
    }


def add_decimate_option(parser: argparse.ArgumentParser) -> None:
    """``--decimate``: :func:`fiducial_detector.detect`'s candidate-search reduction (shared by
    the commands that detect)."""
    parser.add_argument(
        "--decimate",
        type=int,
        choices=DECIMATE_FACTORS,
        default=1,
        help="find candidates on the image reduced by this factor (1: full resolution; 2 saves "
        "about 9 ms on a 6 Mpx frame, for fiducials at least 45 px across (ring design) or 60 "
        "px (dot)); codes and fits use the full image",
    )


def read_for_camera(path: str, camera: CameraModel | None) -> Any:
    """:func:`armourcam.imageio.read_image`, then the calibration's image-size check: every
    failure an :class:`ImageReadError` whose one line names the file."""
    image = read_image(path)
    if camera is not None:
        try:
            camera.check_image_size(image.shape[1], image.shape[0])
        except CalibrationError as err:
            raise ImageReadError(f"{path}: {err}") from err
    return image


def detect_file(
    path: str,
    design: str,
    subpixel: str = "profile",
    *,
    camera: CameraModel | None = None,
    diameter_mm: float = 7.1,
    image_fit: bool = False,
    decimate: int = 1,
) -> dict[str, Any]:
    """Read and process one file; errors become the record's one-line ``error``. With a
    camera each detection gets its pose (:func:`pose_estimator.estimate`, refined by
    :func:`pose_estimator.image_fit.refine_from_image` when ``image_fit``)."""
    try:
        image = read_for_camera(path, camera)
        found = detect(
            image,
            design=design,  # type: ignore[arg-type]
            subpixel=subpixel,  # type: ignore[arg-type]
            decimate=decimate,
        )
        poses: dict[int, FiducialPose] = {}
        if camera is not None:
            estimated = estimate(found, camera, diameter_mm)
            if image_fit:
                estimated = refine_from_image(image, estimated, camera, diameter_mm)
            poses = {id(p.detection): p for p in estimated}
    except (ImageReadError, DetectorError, CalibrationError) as err:
        message = str(err)
        if not message.startswith(path):
            message = f"{path}: {message}"
        return {"path": path, "error": message, "detections": []}
    if camera is None:
        records = [detection_record(d) for d in found]
    else:
        records = [detection_record(d, pose=poses.get(id(d))) for d in found]
    return {"path": path, "error": None, "detections": records}


def outer_ellipse(record: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The outermost fitted ellipse of a detection record (:func:`detection_record`) and the name
    of its printed circle, for the table's semi-axes column.

    The same circle for both designs whenever it was fitted: the outer circle (radius 1.0, the
    printed diameter), the ``ring`` design's pose circle and the ``dot`` design's coding-track
    arc (its pose circle is the small central dot). Where only smaller circles were fitted the
    largest is given, named ``dot`` (the central dot) or ``r=0.80`` (radius as a fraction of the
    outer radius).
    """
    ellipse = max(record["ellipses"], key=lambda e: float(e["radius"]))
    radius = float(ellipse["radius"])
    design = DESIGNS.get(record["design"])
    if abs(radius - 1.0) < 1e-6:
        name = "outer"
    elif design is not None and abs(radius - design.dot_radius) < 1e-6:
        name = "dot"
    else:
        name = f"r={radius:.2f}"
    return ellipse, name


def _print_table(results: list[dict[str, Any]]) -> None:
    for res in results:
        if res["error"] is not None:
            continue
        dets = res["detections"]
        print(f"{res['path']}: {len(dets)} fiducial{'s' if len(dets) != 1 else ''}")
        if not dets:
            continue
        posed = "position_mm" in dets[0]
        head = "  code  design         u          v  ham  contrast  semi-axes (px)    circle"
        print(head + ("      x, y, z (mm)              sd x, y, z (mm)" if posed else ""))
        for d in dets:
            ellipse, circle = outer_ellipse(d)
            line = (
                f"  {d['code']:>4}  {d['design']:>6}  {d['center_px'][0]:9.3f}  "
                f"{d['center_px'][1]:9.3f}  {d['hamming']:>3}  {d['contrast']:8.3f}  "
                f"{ellipse['semi_major']:6.2f} x {ellipse['semi_minor']:6.2f}  {circle:<6}"
            )
            if posed:
                line += "  " + _triple(d["position_mm"], 8, 2) + "  " + _triple(d["sigma_mm"], 6, 3)
            print(line.rstrip())


def _triple(values: list[float] | None, width: int, decimals: int) -> str:
    """Three numbers for the table (``-`` where the pose could not be estimated)."""
    if values is None or any(v is None for v in values):
        return f"{'-':>{3 * width + 4}}"
    return ", ".join(f"{v:{width}.{decimals}f}" for v in values)


def run(args: argparse.Namespace) -> int:
    """Process every image; exit status 1 if any could not be processed."""
    if args.image_fit and args.camera is None:
        print("armourcam detect: error: --image-fit needs --camera", file=sys.stderr)
        return 2
    results = [
        detect_file(
            path,
            args.design,
            args.subpixel,
            camera=args.camera,
            diameter_mm=args.diameter_mm,
            image_fit=args.image_fit,
            decimate=args.decimate,
        )
        for path in args.images
    ]
    failed = [r for r in results if r["error"] is not None]
    if args.json:
        json.dump({"images": results}, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        _print_table(results)
    for res in failed:
        print(f"armourcam detect: error: {res['error']}", file=sys.stderr)
    return 1 if failed else 0
