"""Before/after comparison end to end: images -> fused poses -> matching -> units -> damage.

The pure pipeline behind ``armourcam compare`` and the offline tools: each state may be several
images of the static scene, whose per-image poses are fused into one pose per fiducial
(:func:`pose_estimator.fuse`) before the unit-aware matching
(:func:`displacement_matcher.units.match_units`) and the damage count
(:func:`displacement_matcher.damage.assess`). Camera frame, millimetres.

Two checks keep a wrong input from giving plausible numbers: :func:`state_from_images` says how
the images of one state agree (:func:`pose_estimator.fusion.fuse_frames`: a camera moved between
them shows as one motion of every fiducial), and :func:`check_unit_map` names a mapped unit whose
baseline fiducials cannot be on one unit (a code listed under the wrong unit in ``units.yaml``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pose_estimator.camera import CameraModel
from pose_estimator.fusion import FrameAgreement, Fusion, frame_agreement, fuse_frames
from pose_estimator.types import FiducialPose

from .damage import assess
from .match import DEFAULT_GATE_MM
from .refine import match_units
from .report import report_dict
from .types import DamageSummary, DamageThresholds, MatchResult, UnitMotion
from .units import DEFAULT_RIGID_TOL_MM, UnitMap, UnitSpec

#: Default matching gate in unit sizes Dn (when longer than ``DEFAULT_GATE_MM``): the issue's
#: fields move units up to 2 Dn; the gate leaves a margin for their depth noise.
GATE_DN = 2.4
#: Largest distance between two fiducials of one unit, in Dn (a dolos is about 1.85 Dn high),
#: when longer than the unit map's span: two codes of a mapped unit further apart in the baseline
#: are not on one unit.
UNIT_EXTENT_DN = 2.0
#: Largest fraction of the fiducials found in both states that a camera motion between them may
#: leave out (the units that moved: 7-8 % on the dolos fields).
CAMERA_MOTION_MAX_OUTLIERS = 0.5
#: Units with more fiducials seen than this are not checked (the check tries their subsets).
MAX_CHECKED_CODES = 12


@dataclass(frozen=True, slots=True)
class UnitMapProblem:
    """A mapped unit whose baseline fiducials do not fit on one unit (:func:`check_unit_map`).

    Attributes
    ----------
    unit : str
        The unit of the map.
    codes : tuple of int
        The code that does not fit with the unit's other codes; several when the baseline cannot
        tell which of them is on another unit (e.g. a unit with two codes seen, far apart).
    distance_mm : float
        Baseline distance from the code to the nearest of the unit's other codes (for several
        codes: the largest distance between two of them).
    limit_mm : float
        Largest distance between two fiducials of one unit used by the check.
    expected_mm : float or None
        The unit map's distance between the code and that nearest code (``positions_mm``), when
        the map gives one (the check then compares with it instead of ``limit_mm``).
    near_units : tuple of str
        Mapped units that the code fits with (nearest first): where it probably is.
    """

    unit: str
    codes: tuple[int, ...]
    distance_mm: float
    limit_mm: float
    expected_mm: float | None = None
    near_units: tuple[str, ...] = ()

    @property
    def message(self) -> str:
        """One line for the user, naming the unit, the code(s) and ``units.yaml``."""
        if len(self.codes) > 1:
            listed = ", ".join(map(str, self.codes))
            return (
                f"unit {self.unit}: codes {listed} are {self.distance_mm:.0f} mm apart in the "
                f"baseline (one unit spans at most {self.limit_mm:.0f} mm): is one of them on "
                "another unit? check units.yaml"
            )
        where = "another unit"
        if self.near_units:
            where = " or ".join(f"unit {u}" for u in self.near_units[:2])
        if self.expected_mm is not None:
            return (
                f"unit {self.unit}: code {self.codes[0]} is {self.distance_mm:.0f} mm from its "
                f"other codes in the baseline, {self.expected_mm:.0f} mm in the unit map: is it "
                f"on {where}? check units.yaml"
            )
        return (
            f"unit {self.unit}: code {self.codes[0]} is {self.distance_mm:.0f} mm from its other "
            f"codes in the baseline (one unit spans at most {self.limit_mm:.0f} mm): is it on "
            f"{where}? check units.yaml"
        )


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
    unit_map_problems : tuple of UnitMapProblem
        Mapped units whose baseline fiducials do not fit on one unit (:func:`check_unit_map`).
    camera_motion : FrameAgreement or None
        The camera's motion between the states, when the scene shows one (:func:`camera_motion`).
    learned_template : UnitSpec or None
        The unit template learned from the baseline when no unit map, or a template of codes
        alone, was given (:func:`.learned_template.learn_template`).
    """

    result: MatchResult
    units: tuple[UnitMotion, ...]
    summary: DamageSummary
    unassigned: tuple[int, ...]
    n_frames: tuple[int, int] = (1, 1)
    unit_map_problems: tuple[UnitMapProblem, ...] = ()
    camera_motion: FrameAgreement | None = None
    learned_template: UnitSpec | None = None

    def report(self) -> dict[str, Any]:
        """The report mapping of this assessment (:func:`.report.report_dict`)."""
        return report_dict(
            self.result,
            self.units,
            self.summary,
            unassigned=self.unassigned,
            learned_template=self.learned_template,
        )

    @property
    def warnings(self) -> tuple[str, ...]:
        """The messages of :attr:`camera_motion` and :attr:`unit_map_problems`."""
        moved = () if self.camera_motion is None else (camera_motion_message(self.camera_motion),)
        return moved + tuple(p.message for p in self.unit_map_problems)


def camera_motion(
    baseline: Sequence[FiducialPose], current: Sequence[FiducialPose]
) -> FrameAgreement | None:
    """The camera's motion between the baseline and the current state, when the scene says so.

    Most units do not move in a wave run, so a camera bumped between the two states shows as one
    rigid motion shared by most fiducials (:func:`pose_estimator.fusion.frame_agreement`, the check
    of one state's images, applied to the two states: its registration leaves the moved units
    out as outliers, and a motion that leaves more than :data:`CAMERA_MOTION_MAX_OUTLIERS` of
    the shared fiducials out is none). On the dolos fields, a 1 mm shift or a 0.1 deg turn of
    the camera is found with 10 % of the units moved; without one, 30 end-to-end seeds gave
    0.002 mm at most.

    Returns
    -------
    FrameAgreement or None
        The current state's registration onto the baseline when it is ``moved`` (None
        otherwise, and when either state is empty).
    """

    if not baseline or not current:
        return None
    agreement = frame_agreement(current, baseline)
    # A camera motion carries most fiducials (the still units); a "motion" that leaves most of
    # them outliers is no rigid motion of the scene (the bundled session: 48 of 48 outliers,
    # chi-square 1e6, after a run that moved or rocked a third of its 24 units).
    shared_by_most = agreement.n_outliers <= CAMERA_MOTION_MAX_OUTLIERS * agreement.n_shared
    return agreement if agreement.verdict == "moved" and shared_by_most else None


def camera_motion_message(motion: FrameAgreement) -> str:
    """The warning for a camera that moved between the two states compared (the baseline and
    a run's state, or two runs' states for an incremental report)."""
    what = motion.describe(["the before state", "the after state"])
    return (
        f"camera moved between the before and after states? {what}; every displacement "
        "includes that motion: check the camera mount and re-capture the baseline"
    )


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
    (``design``, ``subpixel``, ``decimate``: :func:`fiducial_detector.detect`'s): the poses of
    :func:`state_from_images`, which also says how the images agree.

    Raises
    ------
    ValueError
        (``DetectorError``, ``PoseError``, ``CalibrationError``) for an image that does not fit
        the camera or cannot be read as an image.
    """
    state = state_from_images(
        images,
        camera,
        diameter_mm,
        design=design,
        subpixel=subpixel,
        image_fit=image_fit,
        decimate=decimate,
    )
    return list(state.poses)


def state_from_images(
    images: Sequence[NDArray[np.generic]],
    camera: CameraModel,
    diameter_mm: float,
    *,
    design: str = "any",
    subpixel: str = "profile",
    image_fit: bool = False,
    decimate: int = 1,
    align: bool = False,
) -> Fusion:
    """:func:`poses_from_images` with the images' agreement: the poses of each image, fused by
    :func:`pose_estimator.fusion.fuse_frames` (one image: its poses as they are).

    ``align`` removes the motion of images taken from another camera position (``moved``)
    before fusing and leaves out those that show another scene (``unmatched``); by default all
    images are fused as they are and ``Fusion.frames`` says which disagree.

    Raises
    ------
    ValueError
        As :func:`poses_from_images`.
    """
    from fiducial_detector.detect import detect
    from pose_estimator.estimate import estimate
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
        frames.append(list(poses))
    return fuse_frames(frames, align=align)


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
    the units of a model at a larger scale move further. An explicit unit map is checked against
    the baseline (:func:`check_unit_map`, the span being the map's or :data:`UNIT_EXTENT_DN`
    unit sizes, whichever is longer), and a camera that moved between the states is named
    (:func:`camera_motion`).
    """
    match_kw.setdefault("gate_mm", max(DEFAULT_GATE_MM, GATE_DN * thresholds.dn_mm))
    analysis = match_units(baseline, current, unit_map=unit_map, **match_kw)
    units, summary = assess(analysis.units, thresholds, section_width_mm=section_width_mm)
    problems: tuple[UnitMapProblem, ...] = ()
    if unit_map is not None and unit_map.units:
        span = match_kw.get("span_mm") or unit_map.span_mm
        rejected = {r.index for r in analysis.result.rejected if r.side == "baseline"}
        problems = check_unit_map(
            analysis.result.baseline,
            unit_map,
            limit_mm=max(float(span), UNIT_EXTENT_DN * thresholds.dn_mm),
            tol_mm=float(match_kw.get("rigid_tol_mm", DEFAULT_RIGID_TOL_MM)),
            skip=rejected,
        )
    return Assessment(
        analysis.result,
        units,
        summary,
        analysis.unassigned,
        unit_map_problems=problems,
        camera_motion=camera_motion(baseline, current),
        learned_template=analysis.learned_template,
    )


def check_unit_map(
    baseline: Sequence[FiducialPose],
    unit_map: UnitMap,
    *,
    limit_mm: float,
    tol_mm: float = DEFAULT_RIGID_TOL_MM,
    skip: Collection[int] = (),
) -> tuple[UnitMapProblem, ...]:
    """Mapped units whose baseline fiducials cannot all be on one unit.

    Two codes of a unit fit together when their baseline distance is within ``limit_mm`` (plus
    three standard deviations along the line between them) or, when the unit map gives both
    positions, within ``tol_mm`` (plus three standard deviations) of the map's distance. The
    largest set of the unit's codes that all fit together is its body; each code outside it is
    a problem, with the other mapped units it fits with. When two or more such sets are largest,
    the codes outside their intersection are one problem (the baseline cannot tell which is
    wrong). Only explicit units are checked (``unit_map.units``), on codes seen exactly once;
    units with more than :data:`MAX_CHECKED_CODES` such codes are skipped.

    Parameters
    ----------
    baseline : sequence of FiducialPose
        Camera frame, mm.
    unit_map : UnitMap
    limit_mm : float
        Largest distance between two fiducials of one unit, mm.
    tol_mm : float
        Tolerance on the map's distances, mm.
    skip : collection of int
        Baseline indices to leave out (rejected poses).

    Returns
    -------
    tuple of UnitMapProblem
        In the unit map's order.
    """
    seen: dict[int, list[int]] = {}
    for i, p in enumerate(baseline):
        if i not in skip and np.all(np.isfinite(p.position_mm)):
            seen.setdefault(int(p.code), []).append(i)
    once = {c: baseline[ix[0]] for c, ix in seen.items() if len(ix) == 1}
    bodies: dict[str, list[int]] = {}
    misfits: list[tuple[UnitSpec, list[int], list[int], bool]] = []
    for spec in unit_map.units:
        codes = [c for c in spec.codes if c in once]
        if not 2 <= len(codes) <= MAX_CHECKED_CODES:
            bodies[spec.unit] = codes
            continue

        def fits(a: int, b: int, spec: UnitSpec = spec) -> bool:
            return _excess(once[a], once[b], spec, limit_mm, tol_mm)[0] <= 0

        cliques = _largest_cliques(codes, fits)
        body = sorted(set.intersection(*map(set, cliques)))
        bodies[spec.unit] = body
        odd = [c for c in codes if c not in body]
        if odd:
            # Several largest cliques (two singletons at least where no pair fits): no body.
            ambiguous = len(cliques) > 1
            misfits.append((spec, body, odd, ambiguous))
    out: list[UnitMapProblem] = []
    for spec, body, odd, ambiguous in misfits:
        if ambiguous:
            d = max(_distance(once[a], once[b])[0] for a, b in itertools.combinations(odd, 2))
            out.append(UnitMapProblem(spec.unit, tuple(odd), d, limit_mm))
            continue
        for c in odd:
            # The nearest of the body's codes that it does not fit with.
            misfit = [(_excess(once[c], once[b], spec, limit_mm, tol_mm), b) for b in body]
            (_, d, expected), _ = min(
                ((e, b) for e, b in misfit if e[0] > 0), key=lambda eb: eb[0][1]
            )
            homes = []
            for other, other_codes in bodies.items():
                dists = [_distance(once[c], once[b]) for b in other_codes]
                if other != spec.unit and dists and all(x <= limit_mm + 3 * sd for x, sd in dists):
                    homes.append((max(x for x, _ in dists), other))
            near = tuple(u for _, u in sorted(homes))
            out.append(UnitMapProblem(spec.unit, (c,), d, limit_mm, expected, near))
    return tuple(out)


def _excess(
    a: FiducialPose, b: FiducialPose, spec: UnitSpec, limit_mm: float, tol_mm: float
) -> tuple[float, float, float | None]:
    """How far (mm) the distance between two fiducials of ``spec``'s codes is beyond what one
    unit allows (negative: within), the distance, and the map's distance when it gives one."""
    d, sd = _distance(a, b)
    pos = spec.positions_mm
    if int(a.code) in pos and int(b.code) in pos:
        expected = float(np.linalg.norm(pos[int(a.code)] - pos[int(b.code)]))
        return abs(d - expected) - (tol_mm + 3.0 * sd), d, expected
    return d - (limit_mm + 3.0 * sd), d, None


def _distance(a: FiducialPose, b: FiducialPose) -> tuple[float, float]:
    """Distance between two poses (mm) and its standard deviation."""
    v = np.asarray(a.position_mm - b.position_mm, dtype=np.float64)
    d = float(np.linalg.norm(v))
    u = v / d if d > 0 else v
    var = float(u @ (np.asarray(a.covariance_mm2) + np.asarray(b.covariance_mm2)) @ u)
    return d, float(np.sqrt(max(var, 0.0)))


def _largest_cliques(
    codes: Sequence[int], fits: Callable[[int, int], bool]
) -> list[tuple[int, ...]]:
    """The largest subsets of ``codes`` whose pairs all ``fits``."""
    ok = {(a, b) for a, b in itertools.combinations(codes, 2) if fits(a, b)}
    for size in range(len(codes), 0, -1):
        found = [
            sub
            for sub in itertools.combinations(codes, size)
            if all(pair in ok for pair in itertools.combinations(sub, 2))
        ]
        if found:
            return found
    return [()]
