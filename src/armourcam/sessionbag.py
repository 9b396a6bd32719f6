"""Monitoring-session bags made with the project's renderer: the camera for tests and the demo.

A session is what the capture rig sees between and around wave runs: a dolos field
(:mod:`armourcam.field`) photographed repeatedly, the hall's automation announcing runs, and the
scene moving during a run and settling after it. :func:`write_session_bag` renders it with
:func:`armourcam.render.render` and writes a ROS 2 MCAP bag with :class:`armourcam.bagio.BagWriter`:

================================  =================================  ============================
topic                             type                               when
================================  =================================  ============================
``/camera/image_raw/compressed``  ``sensor_msgs/CompressedImage``    every frame (JPEG, mono8)
  or ``/camera/image_raw``        ``sensor_msgs/Image`` (mono8)      (``compressed=False``)
``/camera/camera_info``           ``sensor_msgs/CameraInfo``         with every frame
``/hall/run_id``                  ``std_msgs/String``                before each run starts
``/hall/run_active``              ``std_msgs/Bool``                  run start (true) and stop
================================  =================================  ============================

Timeline (``fps`` frames per second of bag time): ``baseline_frames`` frames of the still field;
for each run, its id and start, ``during_frames`` frames of the scene in motion (every fiducial
jittered by several mm: water and moving units), the stop, one frame of the units still rocking,
then ``after_frames`` frames of the settled field. Run 1 is the field's wave run
(``Field.before -> Field.after``); run 2 is a calm run in which nothing moves (its incremental
displacement is zero, its cumulative equals run 1's).

Ground truth goes beside the bag as ``<bag>.truth.json`` (every fiducial's true positions in
each state, every unit's motion and whether it is displaced) and ``<bag>.truth.csv`` (one row per
fiducial and run). Camera frame: OpenCV (x right, y down, z forward), mm.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from armourcam.field import Field, FieldState, make_field
from armourcam.render import Target, render
from displacement_matcher.atomic import make_directory
from displacement_matcher.rigid import across_line_of_sight
from pose_estimator.camera import CameraModel

from . import bagio

IMAGE_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
RUN_ID_TOPIC = "/hall/run_id"
RUN_ACTIVE_TOPIC = "/hall/run_active"
FRAME_ID = "armourcam_camera"
T0_NS = 1_800_000_000 * 10**9  # bag time of the first message (2027-01-15)

PAPER_FOCAL_PX = 45.0 / 0.0078  # the paper's 45 mm lens on 7.8 um pixels


@dataclass(frozen=True, slots=True)
class SessionSpec:
    """What to render.

    Attributes
    ----------
    width, height : int
        Image size; the focal length scales with the width so the scene is the same at any size
        (the paper's camera at 3008 px).
    n_units : int
        Dolosse in the field.
    seed : int
    diameter_mm : float
        Printed fiducial diameter.
    design : str
    compressed : bool
        JPEG ``CompressedImage`` (small) or raw mono8 ``Image``.
    jpeg_quality : int
    fps : float
        Frames per second of bag time.
    baseline_frames, during_frames, after_frames : int
    blur_sigma, noise : float
        Renderer degradation (pixels; fraction of full range).
    moved_fraction, overturned_fraction, hidden_fraction : float
        Passed to :func:`armourcam.field.make_field`.
    """

    width: int = 1504
    height: int = 1000
    n_units: int = 24
    seed: int = 9
    diameter_mm: float = 7.1
    design: str = "ring"
    compressed: bool = True
    jpeg_quality: int = 92
    fps: float = 2.0
    baseline_frames: int = 4
    during_frames: int = 2
    after_frames: int = 4
    blur_sigma: float = 0.6
    noise: float = 0.01
    moved_fraction: float = 0.2
    overturned_fraction: float = 0.05
    hidden_fraction: float = 0.0

    def camera(self) -> CameraModel:
        """The session's camera (plumb_bob, no distortion)."""
        return CameraModel.ideal(self.width, self.height, PAPER_FOCAL_PX * self.width / 3008.0)


def _jittered(targets: list[Target], rng: np.random.Generator, sigma_mm: float) -> list[Target]:
    return [
        Target(
            t.code, t.design, t.diameter_mm, t.rotation, t.position_mm + rng.normal(0, sigma_mm, 3)
        )
        for t in targets
    ]


def _rocking(field: Field, spec: SessionSpec, rng: np.random.Generator) -> list[Target]:
    """The after state with the moved units still rocking (2 mm off their rest)."""
    targets = field.after.targets(spec.design, spec.diameter_mm)
    ids = field.after.visible_ids.tolist()
    moving = field.moved | field.overturned
    out = []
    for t, i in zip(targets, ids, strict=True):
        if moving[field.after.unit[i]]:
            t = Target(
                t.code, t.design, t.diameter_mm, t.rotation, t.position_mm + rng.normal(0, 2.0, 3)
            )
        out.append(t)
    return out


def session_truth(field: Field, spec: SessionSpec, dn_threshold: float = 1.0) -> dict[str, Any]:
    """Ground truth of the session's runs (JSON-ready).

    Per fiducial (every one visible in the baseline): code, unit, ``before_mm``, ``after_mm`` and
    ``displacement_mm`` (true rigid motion of its unit applied to it). Per unit: moved,
    overturned, the displacement of the centroid of its baseline-visible fiducials, in mm and
    Dn, and ``displaced`` (centroid moved >= ``dn_threshold`` Dn, or overturned).
    """
    before: FieldState = field.before
    dn = field.geometry.dn_mm
    fids = []
    for i in before.visible_ids.tolist():
        u = int(before.unit[i])
        p = before.position_mm[i]
        d = field.displacement_at(u, p)
        fids.append(
            {
                "fiducial": i,
                "unit": u,
                "code": int(before.code[i]),
                "before_mm": p.tolist(),
                "after_mm": (p + d).tolist(),
                "displacement_mm": d.tolist(),
                "visible_after": bool(field.after.visible[i]),
            }
        )
    units = []
    for u in range(field.n_units):
        mine = [f for f in fids if f["unit"] == u]
        if mine:
            c = np.mean([f["before_mm"] for f in mine], axis=0)
            d = field.displacement_at(u, c)
        else:
            d = field.after.centres_mm[u] - field.before.centres_mm[u]
        dist = float(np.linalg.norm(d))
        units.append(
            {
                "unit": u,
                "moved": bool(field.moved[u]),
                "overturned": bool(field.overturned[u]),
                "translation_mm": d.tolist(),
                "distance_mm": dist,
                "distance_dn": dist / dn,
                "displaced": bool(field.overturned[u] or dist >= dn_threshold * dn),
                "visible_fiducials_before": len(mine),
            }
        )
    displaced = sum(u["displaced"] for u in units)
    calm_fids = [
        {**f, "before_mm": f["after_mm"], "displacement_mm": [0.0, 0.0, 0.0]} for f in fids
    ]
    return {
        "camera": spec.camera().to_dict(),
        "dn_mm": dn,
        "displaced_threshold_dn": dn_threshold,
        "section_width_mm": field.section_width_mm,
        "spec": {k: getattr(spec, k) for k in spec.__dataclass_fields__},
        "runs": [
            {
                "run_id": "wave-001",
                "cumulative": {"fiducials": fids, "units": units, "displaced_units": displaced},
                "incremental": None,
            },
            {
                "run_id": "wave-002",
                "cumulative": {"fiducials": fids, "units": units, "displaced_units": displaced},
                "incremental": {
                    "fiducials": calm_fids,
                    "units": [
                        {
                            **u,
                            "translation_mm": [0.0, 0.0, 0.0],
                            "distance_mm": 0.0,
                            "distance_dn": 0.0,
                            "displaced": False,
                        }
                        for u in units
                    ],
                    "displaced_units": 0,
                },
            },
        ],
    }


def replace_session_bag(path: Path, spec: SessionSpec | None = None) -> dict[str, Any]:
    """:func:`write_session_bag`, replacing a bag already at ``path`` only once the new one and
    its ground truth are complete: they are rendered in a hidden directory beside it and moved
    into place, so a failure or an interrupt (a full disk, Ctrl-C) leaves the old bag whole."""
    make_directory(path.parent)
    work = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    old = work / "replaced"
    try:
        fresh = work / path.name
        truth = write_session_bag(fresh, spec)
        if path.exists():
            os.replace(path, old)
        os.replace(fresh, path)
        for new_file, target in zip(truth_paths(fresh), truth_paths(path), strict=True):
            os.replace(new_file, target)
    except BaseException:
        if old.exists() and not path.exists():
            os.replace(old, path)
        raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return truth


def write_session_bag(path: Path, spec: SessionSpec | None = None) -> dict[str, Any]:
    """Render a monitoring session into an MCAP bag at ``path`` with its ground truth beside it.

    Returns the ground truth (also written to ``<path>.truth.json`` and ``<path>.truth.csv``).
    """
    spec = spec or SessionSpec()
    cam = spec.camera()
    field = make_field(
        spec.n_units,
        seed=spec.seed,
        camera=cam,
        moved_fraction=spec.moved_fraction,
        overturned_fraction=spec.overturned_fraction,
        hidden_fraction=spec.hidden_fraction,
        diameter_mm=spec.diameter_mm,
        # Unsettled (moved units may interpenetrate still ones): keeps the committed bags and
        # their truth reproducible.
        settle=False,
    )
    rng = np.random.default_rng(spec.seed + 1000)
    still_before = field.before.targets(spec.design, spec.diameter_mm)
    still_after = field.after.targets(spec.design, spec.diameter_mm)
    dt = int(1e9 / spec.fps)
    t = [T0_NS]

    def tick() -> int:
        t[0] += dt
        return t[0]

    def shoot(w: bagio.BagWriter, targets: list[Target]) -> None:
        img = render(cam, targets, blur_sigma=spec.blur_sigma, noise=spec.noise, rng=rng).image
        now = tick()
        w.write_camera_info(CAMERA_INFO_TOPIC, cam, now, frame_id=FRAME_ID)
        if spec.compressed:
            w.write_compressed_image(
                COMPRESSED_TOPIC,
                img,
                now + 1,
                frame_id=FRAME_ID,
                quality=spec.jpeg_quality,
                stamp_ns=now,
            )
        else:
            w.write_image(IMAGE_TOPIC, img, now + 1, frame_id=FRAME_ID, stamp_ns=now)

    def run(
        w: bagio.BagWriter,
        run_id: str,
        during: list[Target],
        rocking: list[Target] | None,
        after: list[Target],
    ) -> None:
        w.write_string(RUN_ID_TOPIC, run_id, tick())
        w.write_bool(RUN_ACTIVE_TOPIC, True, tick())
        for _ in range(spec.during_frames):
            shoot(w, _jittered(during, rng, 4.0))
        w.write_bool(RUN_ACTIVE_TOPIC, False, tick())
        if rocking is not None:
            shoot(w, rocking)
        for _ in range(spec.after_frames):
            shoot(w, after)

    path.parent.mkdir(parents=True, exist_ok=True)
    with bagio.BagWriter(path) as w:
        for _ in range(spec.baseline_frames):
            shoot(w, still_before)
        run(w, "wave-001", still_after, _rocking(field, spec, rng), still_after)
        run(w, "wave-002", still_after, None, still_after)
    truth = session_truth(field, spec)
    write_truth(path, truth)
    return truth


def truth_paths(bag: Path) -> tuple[Path, Path]:
    """``(<bag>.truth.json, <bag>.truth.csv)``."""
    return bag.with_name(bag.name + ".truth.json"), bag.with_name(bag.name + ".truth.csv")


def write_truth(bag: Path, truth: dict[str, Any]) -> None:
    """Write the ground truth JSON and CSV next to ``bag``."""
    jpath, cpath = truth_paths(bag)
    jpath.write_text(json.dumps(truth, indent=1))
    with cpath.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "run_id",
                "reference",
                "fiducial",
                "unit",
                "code",
                "before_x_mm",
                "before_y_mm",
                "before_z_mm",
                "dx_mm",
                "dy_mm",
                "dz_mm",
                "unit_displaced",
            ]
        )
        for run in truth["runs"]:
            for ref in ("cumulative", "incremental"):
                part = run[ref]
                if part is None:
                    continue
                disp = {u["unit"]: u["displaced"] for u in part["units"]}
                for fd in part["fiducials"]:
                    w.writerow(
                        [
                            run["run_id"],
                            ref,
                            fd["fiducial"],
                            fd["unit"],
                            fd["code"],
                            *(f"{x:.4f}" for x in fd["before_mm"]),
                            *(f"{x:.4f}" for x in fd["displacement_mm"]),
                            int(disp[fd["unit"]]),
                        ]
                    )


def read_truth(bag: Path) -> dict[str, Any] | None:
    """The ground truth next to ``bag``, or None."""
    jpath, _ = truth_paths(bag)
    if not jpath.is_file():
        return None
    doc: dict[str, Any] = json.loads(jpath.read_text())
    return doc


#: Largest distance across the line of sight (mm) of a measured fiducial from the truth one it
#: is scored against (:func:`compare_to_truth`): the session bag's fiducials are 7 mm across.
TRUTH_PAIR_MM = 3.0


def compare_to_truth(report: dict[str, Any], truth_part: dict[str, Any]) -> dict[str, float]:
    """Accuracy of one measured report against one truth part (cumulative or incremental).

    Each measured fiducial entry with a displacement is paired with the truth fiducial of its
    code whose ``before_mm`` is nearest across the line of sight (within
    :data:`TRUTH_PAIR_MM`), where one image places a fiducial to a fraction of a millimetre
    whatever its depth error: a measured pose far off in depth is scored, not dropped. Returns
    counts (``unpaired``: entries no truth fiducial is near) and the error statistics of the
    displacement vectors (mm); ``wrong`` counts pairs whose displacement is off by more than
    2 mm across the line of sight (a wrong partner; depth errors of a right one aside).
    """
    truth = truth_part["fiducials"]
    tb = np.array([f["before_mm"] for f in truth], dtype=float).reshape(-1, 3)
    td = np.array([f["displacement_mm"] for f in truth], dtype=float).reshape(-1, 3)
    codes = np.array([int(f["code"]) for f in truth], dtype=np.int64)
    errs: list[NDArray[np.float64]] = []
    across: list[float] = []
    unpaired = 0
    for f in report.get("fiducials", []):
        if f.get("displacement_mm") is None or f.get("before_mm") is None:
            continue
        b = np.asarray(f["before_mm"], dtype=float)
        code = f.get("code_before")
        lateral = np.linalg.norm(across_line_of_sight(tb - b, b), axis=1)
        if code is not None:
            lateral = np.where(codes == int(code), lateral, np.inf)
        k = int(np.argmin(lateral)) if len(lateral) else -1
        if k < 0 or lateral[k] > TRUTH_PAIR_MM:
            unpaired += 1
            continue
        err = np.asarray(f["displacement_mm"], dtype=float) - td[k]
        errs.append(err)
        across.append(float(np.linalg.norm(across_line_of_sight(err, b))))
    e = np.array(errs).reshape(-1, 3)
    norm = np.linalg.norm(e, axis=1) if len(e) else np.zeros(0)
    return {
        "truth_fiducials": float(len(tb)),
        "paired": float(len(e)),
        "unpaired": float(unpaired),
        "err_median_mm": float(np.median(norm)) if len(norm) else float("nan"),
        "err_p95_mm": float(np.percentile(norm, 95)) if len(norm) else float("nan"),
        "err_max_mm": float(np.max(norm)) if len(norm) else float("nan"),
        "err_rms_x_mm": float(np.sqrt(np.mean(e[:, 0] ** 2))) if len(e) else float("nan"),
        "err_rms_y_mm": float(np.sqrt(np.mean(e[:, 1] ** 2))) if len(e) else float("nan"),
        "err_rms_z_mm": float(np.sqrt(np.mean(e[:, 2] ** 2))) if len(e) else float("nan"),
        "wrong": float(np.sum(np.array(across) > 2.0)),
        "truth_displaced_units": float(truth_part["displaced_units"]),
    }
