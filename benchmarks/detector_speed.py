"""Detector speed on a full frame, in the same run as AprilTag 3 and OpenCV's ArUco detector.

Frames (3008 x 2000, 8 bit, Gaussian blur 0.5 px, noise 1 % of full range):

- ours: :func:`armourcam.scenes.random_scene`, 400 fiducials of 60 px (outer diameter at zero
  slant, paper camera f = 6507 px), slant up to 60 deg, with clutter; one frame per design;
- tags: 400 tag36h11 markers of 60 px (black border edge to edge) with a one-cell white quiet
  zone on a grey background, made with ``cv2.aruco.generateImageMarker``.

Ours also runs with ``decimate=2`` (candidates found on the frame reduced 2x, like AprilTag's
``quad_decimate 2``; codes and fits at full resolution).

Every detector runs single-threaded (``cv2.setNumThreads(1)``, ``nthreads=1``), all of them in
turn in each of ``--repeats`` rounds (the order rotated round by round: the VM's speed drifts
over seconds, so timing one detector's runs back to back and then the next's compared phases,
not detectors); the table gives the median wall time and CPU time and how many markers were
found correctly, then each of our runs over AprilTag's at quad_decimate 2 in the same round.
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
from dataclasses import dataclass, field
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


@dataclass
class Contender:
    """One detector on its frame: ``run`` detects, ``score`` says how many it found right and
    wrong; ``wall`` and ``cpu`` collect the milliseconds of each timed run."""

    name: str
    run: Callable[[], Any]
    score: Callable[[Any], tuple[int, int]]
    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    found: str = ""


def interleaved(contenders: list[Contender], repeats: int) -> None:
    """Each contender once as a warm-up (scored), then ``repeats`` rounds in which each runs once,
    the order rotated round by round: the VM's speed drifts over seconds, and a detector timed
    over consecutive runs of its own meets a different phase from the next one's."""
    for c in contenders:
        good, wrong = c.score(c.run())
        c.found = f"{good} ({wrong})"
    for r in range(repeats):
        k = r % len(contenders)
        for c in contenders[k:] + contenders[:k]:
            w0, c0 = time.perf_counter(), time.process_time()
            c.run()
            c.wall.append(1000.0 * (time.perf_counter() - w0))
            c.cpu.append(1000.0 * (time.process_time() - c0))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one repeat, ring frame only")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    repeats = 1 if args.quick else args.repeats
    rng = np.random.default_rng(20)
    camera = paper_camera(*FRAME)
    contenders: list[Contender] = []
    stages: dict[str, list[tuple[str, float]]] = {}
    t0 = time.perf_counter()
    scenes = {}
    for design in ("ring",) if args.quick else ("ring", "dot"):
        scene = random_scene(
            camera, N_TARGETS, SIZE_PX, design, rng, 60.0, True, blur_sigma=BLUR, noise=NOISE
        )
        scenes[design] = scene
        for mode, subpixel, decimate in (
            (design, "profile", 1),
            (design, "profile", 2),
            ("any", "profile", 1),
            (design, "ml", 1),
        ):
            name = f"armourcam {design} frame, design={mode}"
            name += "" if subpixel == "profile" else f", {subpixel}"
            name += "" if decimate == 1 else f", decimate {decimate}"
            run = partial(
                detect,
                scene.image,
                design=cast(DesignChoice, mode),
                subpixel=cast(SubpixelMethod, subpixel),
                decimate=decimate,
            )
            contenders.append(Contender(name, run, partial(count_correct, truth=scene.truth)))
    tags, ids = tag_frame(rng)

    def tag_score(found_ids: set[int], n_found: int) -> tuple[int, int]:
        good = len(found_ids & set(ids))
        return good, n_found - good

    try:
        from pupil_apriltags import Detector
    except ImportError:  # pragma: no cover - dev extra not installed
        Detector = None
    apriltags: list[Any] = []
    if Detector is not None:
        for decimate in (1.0, 2.0):
            det = Detector(families="tag36h11", nthreads=1, quad_decimate=decimate)
            apriltags.append(det)
            contenders.append(
                Contender(
                    f"AprilTag 3, quad_decimate {decimate:.0f}",
                    partial(det.detect, tags),
                    lambda found: tag_score({f.tag_id for f in found}, len(found)),
                )
            )
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
        cv2.aruco.DetectorParameters(),
    )

    def aruco_score(result: Any) -> tuple[int, int]:
        found_ids = result[1]
        if found_ids is None:
            return 0, 0
        return tag_score({int(i) for i in found_ids.ravel()}, len(found_ids))

    contenders.append(
        Contender("OpenCV ArUco (tag36h11)", lambda: aruco.detectMarkers(tags), aruco_score)
    )
    interleaved(contenders, repeats)
    for design, scene in scenes.items():
        stages[design] = stage_times(scene.image, design, repeats)

    print(
        f"detector speed: {FRAME[0]}x{FRAME[1]} frames, {N_TARGETS} markers of {SIZE_PX} px, "
        f"one thread, median of {repeats} interleaved run(s); setup and runs "
        f"{time.perf_counter() - t0:.0f} s"
    )
    print(f"{'detector':44s} {'wall ms':>9s} {'cpu ms':>9s}  {'found (wrong)':>13s}  reference ms")
    for c in contenders:
        ref = REFERENCE_MS.get(c.name)
        ref_s = f"{ref:.0f}" if ref is not None else "-"
        print(
            f"{c.name:44s} {statistics.median(c.wall):9.1f} {statistics.median(c.cpu):9.1f}  "
            f"{c.found:>13s}  {ref_s}"
        )
    by_name = {c.name: c for c in contenders}
    qd2 = by_name.get("AprilTag 3, quad_decimate 2")
    if qd2 is not None:
        # Run by run, each against the AprilTag run of the same round: the ratio the drift
        # leaves least room to move.
        print("\nours / AprilTag 3 at quad_decimate 2, round by round: median (lowest-highest)")
        for c in contenders:
            if not c.name.startswith("armourcam") or ", ml" in c.name:
                continue
            ratio = np.array(c.wall) / np.array(qd2.wall)
            print(f"  {c.name:44s} {np.median(ratio):6.2f}x ({ratio.min():.2f}-{ratio.max():.2f})")
    for design, parts in stages.items():
        print(f"\narmourcam stages, {design} frame (cpu ms)")
        for label, ms in parts:
            print(f"  {label:52s} {ms:8.1f}")
    print("\ntarget: <= 50 ms per frame, at least twice as fast as AprilTag 3 at quad_decimate 2")
    for det in apriltags:
        release_apriltag(det)
    return 0


def release_apriltag(det: Any) -> None:
    """Free a ``pupil_apriltags.Detector`` in the order its C library needs: the detector, then
    its tag families. The binding's own ``__del__`` frees the families first, and the detector's
    destructor then reads them (pupil-labs/apriltags#46, fixed so in duckietown's fork): a
    segmentation fault at exit whenever the freed memory has been reused or returned (4 runs in
    6 here, depending on the heap's layout)."""
    if getattr(det, "tag_detector_ptr", None) is None:
        return
    det.libc.apriltag_detector_destroy.restype = None
    det.libc.apriltag_detector_destroy(det.tag_detector_ptr)
    for family, tf in det.tag_families.items():
        destroy = getattr(det.libc, f"{family}_destroy")
        destroy.restype = None
        destroy(tf)
    det.tag_detector_ptr = None  # its __del__ then frees nothing


if __name__ == "__main__":
    status = main()
    sys.stdout.flush()
    # pupil-apriltags may corrupt the heap when a second Detector is destroyed (tag families freed
    # before the detector; pupil-labs/apriltags PR #65, unmerged): skip the destructors at exit.
    os._exit(status)
