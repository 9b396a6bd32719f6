"""Before/after comparison end to end: images -> fused poses -> matching -> units -> damage.

The pure pipeline behind ``armourcam compare`` and the offline tools: each state may be several
images of the static scene, whose per-image poses are fused into one pose per fiducial
(:func:`pose_estimator.fuse`) before the unit-aware matching
(:func:`displacement_matcher.units.match_units`) and the damage count
(:func:`displacement_matcher.damage.assess`). Camera frame, millimetres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pose_estimator.camera import CameraModel
from pose_estimator.types import FiducialPose

from .damage import assess
from .match import DEFAULT_GATE_MM
from .refine import match_units
from .types import DamageSummary, DamageThresholds, MatchResult, UnitMotion
from .units import UnitMap

#: Default matching gate in unit sizes Dn (when longer than ``DEFAULT_GATE_MM``): the issue's
#: fields move units up to 2 Dn; the gate leaves a margin for their depth noise.
GATE_DN = 2.4


@dataclass(frozen=True, slots=True, eq=False)
class Assessment:
    """Everything measured between a baseline and a current state.

    Attributes
    ----------
    result : MatchResult
    units : tuple of UnitMotion
        With ``status`` filled in.
    summary : DamageSummary
    unassigned : tuple of int
        Baseline fiducials that belong to no unit.
    n_frames : (int, int)
        Images fused for the baseline and the current state.
    """

    result: MatchResult
    units: tuple[UnitMotion, ...]
    summary: DamageSummary
    unassigned: tuple[int, ...]
    n_frames: tuple[int, int] = (1, 1)


def poses_from_images(
    images: Sequence[NDArray[np.generic]],
    camera: CameraModel,
    diameter_mm: float,
    *,
    design: str = "any",
    subpixel: str = "profile",
    image_fit: bool = False,
    decimate: int = 1,
) -> list[FiducialPose]:
    """Detect, estimate (refined by :func:`pose_estimator.image_fit.refine_from_image` when
    ``image_fit``) and, for several images of one static state, fuse fiducial poses
    (``design``, ``subpixel``, ``decimate``: :func:`fiducial_detector.detect`'s).

    Raises
    ------
    ValueError
        (``DetectorError``, ``PoseError``, ``CalibrationError``) for an image that does not fit
        the camera or cannot be read as an image.
    """
    from fiducial_detector.detect import detect
    from pose_estimator.estimate import estimate
    from pose_estimator.fusion import fuse
    from pose_estimator.image_fit import refine_from_image

    frames = []
    for image in images:
        h, w = image.shape[:2]
        camera.check_image_size(w, h)
        found = detect(
            image,
            design=design,  # type: ignore[arg-type]
            subpixel=subpixel,  # type: ignore[arg-type]
            decimate=decimate,
        )
        poses = estimate(found, camera, diameter_mm)
        if image_fit:
            poses = refine_from_image(image, poses, camera, diameter_mm)
        frames.append(poses)
    if len(frames) == 1:
        return list(frames[0])
    return list(fuse(frames))


def compare_poses(
    baseline: Sequence[FiducialPose],
    current: Sequence[FiducialPose],
    thresholds: DamageThresholds,
    *,
    unit_map: UnitMap | None = None,
    section_width_mm: float | None = None,
    **match_kw: Any,
) -> Assessment:
    """Unit-aware matching and damage count of two pose sets (see :func:`match_units`).

    Without a ``gate_mm`` the gate is :data:`.match.DEFAULT_GATE_MM` or :data:`GATE_DN` unit
    sizes, whichever is longer: a unit that moved beyond the gate can only be found lost, and
    the units of a model at a larger scale move further.
    """
    match_kw.setdefault("gate_mm", max(DEFAULT_GATE_MM, GATE_DN * thresholds.dn_mm))
    analysis = match_units(baseline, current, unit_map=unit_map, **match_kw)
    units, summary = assess(analysis.units, thresholds, section_width_mm=section_width_mm)
    return Assessment(analysis.result, units, summary, analysis.unassigned)
