"""Detector speed on a full frame, in the same run as AprilTag 3 and OpenCV's ArUco detector.

Frames (3008 x 2000, 8 bit, Gaussian blur 0.5 px, noise 1 % of full range):

- ours: :func:`armourcam.scenes.random_scene`, 400 fiducials of 60 px (outer diameter at zero
  slant, paper camera f = 6507 px), slant up to 60 deg, with clutter; one frame per design;
- tags: 400 tag36h11 markers of 60 px (black border edge to edge) with a one-cell white quiet
  zone on a grey background, made with ``cv2.aruco.generateImageMarker``.

Ours also runs with ``decimate=2`` (candidates found on the frame reduced 2x, like AprilTag's
``quad_decimate 2``; codes and fits at full resolution).

Every detector runs single-threaded (``cv2.setNumThreads(1)``, ``nthreads=1``); the table gives the
median wall time and CPU time over ``--repeats`` runs and how many markers were found correctly.
Our detector's time is also split into its stages. Reference figures from
``../shared/reference/README.md`` (measured elsewhere on 2 cores) are printed beside.

Run: ``.venv/bin/python -m benchmarks.detector_speed [--repeats N] [--quick]``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from armourcam.render import TargetTruth
from armourcam.scenes import paper_camera, random_scene
from fiducial_detector import detect
from fiducial_detector.code_reader import ReaderConfig, read_codes
from fiducial_detector.components import outer_boundaries
from fiducial_detector.design import get_design
from fiducial_detector.detect import DesignChoice, SubpixelMethod
from fiducial_detector.threshold import bradley_threshold

FRAME = (3008, 2000)
N_TARGETS = 400
SIZE_PX = 60
BLUR, NOISE = 0.5, 0.01
REFERENCE_MS = {
    "AprilTag 3, quad_decimate 1": 538.0,
    "AprilTag 3, quad_decimate 2": 103.0,
    "OpenCV ArUco (tag36h11)": 308.0,
}
_detect_module = importlib.import_module("fiducial_detector.detect")


def timed(fn: Callable[[], Any], repeats: int) -> tuple[float, float, Any]:
    """Median wall and CPU milliseconds of ``fn`` over ``repeats`` runs (after one warm-up)."""
    result = fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        wall.append(1000.0 * (time.perf_counter() - w0))
        cpu.append(1000.0 * (time.process_time() - c0))
    return statistics.median(wall), statistics.median(cpu), result


def tag_frame(rng: np.random.Generator) -> tuple[NDArray[np.uint8], list[int]]:
    """400 tag36h11 markers of 60 px on a 20 x 20 grid, blurred and noisy like our frames."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    w, h = FRAME
    img = np.full((h, w), 115.0)
    cell = SIZE_PX / 8.0  # tag36h11: 6x6 data bits inside a one-cell black border
    quiet = round(cell)
    ids = []
    for k in range(N_TARGETS):
        r, c = divmod(k, 20)
        u0 = int(c * w / 20 + (w / 20 - SIZE_PX) / 2)
        v0 = int(r * h / 20 + (h / 20 - SIZE_PX) / 2)
        marker = cv2.aruco.generateImageMarker(dictionary, k, SIZE_PX, borderBits=1)
        img[v0 - quiet : v0 + SIZE_PX + quiet, u0 - quiet : u0 + SIZE_PX + quiet] = 217.0
        img[v0 : v0 + SIZE_PX, u0 : u0 + SIZE_PX] = np.where(marker > 0, 217.0, 31.0)
        ids.append(k)
    img = cv2.GaussianBlur(img / 255.0, (0, 0), BLUR) + rng.normal(0.0, NOISE, img.shape)
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8), ids


def count_correct(found: list[Any], truth: tuple[TargetTruth, ...]) -> tuple[int, int]:
    """(correct, wrong): a detection is correct with the right code and design within 2 px."""
    centres = np.array([t.center_px for t in truth])
    correct = 0
    for d in found:
        j = int(np.argmin(np.hypot(*(centres - np.asarray(d.center_px)).T)))
        t = truth[j]
        near = np.hypot(*(centres[j] - np.asarray(d.center_px))) < 2.0
        correct += bool(near and t.code == d.code and t.design == d.design)
    return correct, len(found) - correct


def stage_times(image: NDArray[Any], design: str, repeats: int) -> list[tuple[str, float]]:
    """CPU milliseconds of our pipeline's stages for one design."""
    spec = get_design(design)
    min_d = _detect_module.MIN_OUTER_DIAMETER_PX
    max_d = float(min(image.shape))
    _, t_thr, binary = timed(lambda: bradley_threshold(image), repeats)
    _, t_bnd, bounds = timed(
        lambda: outer_boundaries(binary, max_extent=max_d, min_hull_extent=0.9 * min_d), repeats
    )
    cands = _detect_module._candidates(bounds, spec, min_d, max_d)
    _, t_read, _ = timed(
        lambda: read_codes(image, 255.0, spec, cands.centre, cands.axes, cands.angle, cands.drift),
        repeats,
    )
    _, t_fin, _ = timed(
        lambda: _detect_module._finish(
            image, 255.0, _detect_module._candidates(bounds, spec, min_d, max_d), ReaderConfig()
        ),  # the default sub-pixel method
        1,
    )
    return [
        ("1 threshold (Bradley & Roth + thin lines)", t_thr),
        (f"2 outer boundaries ({len(bounds)} kept)", t_bnd),
        (f"4 coarse code read ({len(cands.centre)} candidates)", t_read),
        ("3+4 fits of every circle + second read", t_fin - t_read),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one repeat, ring frame only")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    repeats = 1 if args.quick else args.repeats
    rng = np.random.default_rng(20)
    camera = paper_camera(*FRAME)
    rows: list[tuple[str, float, float, str]] = []
    stages: dict[str, list[tuple[str, float]]] = {}
    t0 = time.perf_counter()
    for design in ("ring",) if args.quick else ("ring", "dot"):
        scene = random_scene(
            camera, N_TARGETS, SIZE_PX, design, rng, 60.0, True, blur_sigma=BLUR, noise=NOISE
        )
        for mode, subpixel, decimate in (
            (design, "profile", 1),
            (design, "profile", 2),
            ("any", "profile", 1),
            (design, "ml", 1),
        ):
            run = partial(
                detect,
                scene.image,
                design=cast(DesignChoice, mode),
                subpixel=cast(SubpixelMethod, subpixel),
                decimate=decimate,
            )
            wall, cpu, found = timed(run, repeats)
            good, wrong = count_correct(found, scene.truth)
            name = f"armourcam {design} frame, design={mode}"
            name += "" if subpixel == "profile" else f", {subpixel}"
            name += "" if decimate == 1 else f", decimate {decimate}"
            rows.append((name, wall, cpu, f"{good} ({wrong})"))
        stages[design] = stage_times(scene.image, design, repeats)
    tags, ids = tag_frame(rng)
    try:
        from pupil_apriltags import Detector
    except ImportError:  # pragma: no cover - dev extra not installed
        Detector = None
    if Detector is not None:
        for decimate in (1.0, 2.0):
            det = Detector(families="tag36h11", nthreads=1, quad_decimate=decimate)
            wall, cpu, found = timed(partial(det.detect, tags), repeats)
            good = len({f.tag_id for f in found} & set(ids))
            name = f"AprilTag 3, quad_decimate {decimate:.0f}"
            rows.append((name, wall, cpu, f"{good} ({len(found) - good})"))
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
        cv2.aruco.DetectorParameters(),
    )
    wall, cpu, (_, found_ids, _) = timed(lambda: aruco.detectMarkers(tags), repeats)
    got = set() if found_ids is None else {int(i) for i in found_ids.ravel()}
    n = 0 if found_ids is None else len(found_ids)
    rows.append(("OpenCV ArUco (tag36h11)", wall, cpu, f"{len(got & set(ids))} ({n - len(got)})"))

    print(
        f"detector speed: {FRAME[0]}x{FRAME[1]} frames, {N_TARGETS} markers of {SIZE_PX} px, "
        f"one thread, median of {repeats} run(s); setup {time.perf_counter() - t0:.0f} s"
    )
    print(f"{'detector':44s} {'wall ms':>9s} {'cpu ms':>9s}  {'found (wrong)':>13s}  reference ms")
    for name, wall, cpu, found_s in rows:
        ref = REFERENCE_MS.get(name)
        ref_s = f"{ref:.0f}" if ref is not None else "-"
        print(f"{name:44s} {wall:9.1f} {cpu:9.1f}  {found_s:>13s}  {ref_s}")
    for design, parts in stages.items():
        print(f"\narmourcam stages, {design} frame (cpu ms)")
        for label, ms in parts:
            print(f"  {label:52s} {ms:8.1f}")
    print("\ntarget: <= 50 ms per frame, at least twice as fast as AprilTag 3 at quad_decimate 2")
    return 0


if __name__ == "__main__":
    status = main()
    sys.stdout.flush()
    # pupil-apriltags may corrupt the heap when a second Detector is destroyed (tag families freed
    # before the detector; pupil-labs/apriltags PR #65, unmerged): skip the destructors at exit.
    os._exit(status)
