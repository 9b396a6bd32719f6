"""Fusion of several frames of a static scene into one pose per fiducial.

Between wave runs the camera sees the same scene for many frames. Each fiducial's per-frame
positions are combined by inverse-covariance weighting, which is the minimum-variance unbiased
combination when the per-frame covariances are honest. Robustness to a bad frame (a wrong
ambiguity branch, a fiducial half-occluded by a passing hand) comes from iterated Mahalanobis
rejection around a median start; the fused covariance is inflated by the reduced chi-square of the
inliers when their scatter exceeds what their covariances predict, so it stays honest.

Frames that disagree are not fused silently: :func:`fuse_frames` registers every frame onto the
others (same-code fiducials; a rigid motion weighted by the poses' covariances) and tests what it
finds against those covariances. One rigid motion shared by all fiducials is what a camera moved
between the frames does (a bumped tripod); a frame most of whose fiducials are not found in the
others shows another scene. Each frame's :class:`FrameAgreement` says which, and by how much.

Frames: camera frame (OpenCV: x right, y down, z forward), millimetres.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import PoseError
from .types import FiducialPose

F64 = NDArray[np.float64]

#: 99.9 % quantile of the chi-square distribution with 3 degrees of freedom.
CHI2_3_999 = 16.266
#: 99.9 % quantile of the chi-square distribution with 6 degrees of freedom.
CHI2_6_999 = 22.458


def fuse_poses(poses: Sequence[FiducialPose], *, gate: float = CHI2_3_999) -> FiducialPose:
    """Fuse poses of one fiducial from several frames of a static scene.

    Parameters
    ----------
    poses : sequence of FiducialPose
        The same fiducial seen in different frames (same code).
    gate : float
        Squared Mahalanobis distance beyond which a frame is rejected as an outlier.

    Returns
    -------
    FiducialPose
        Inverse-covariance-weighted position of the inlier frames, their mean normal, the fused
        covariance (inflated by the reduced chi-square when that exceeds 1), ``n_frames`` = the
        number of inlier frames, the mean of their systematic covariances (a bias common to
        the frames does not average out; None when none has one) and the mean of their axes
        (:func:`mean_axis`); ``detection`` is None.

    Raises
    ------
    PoseError
        If ``poses`` is empty or mixes codes.
    """
    if not poses:
        raise PoseError("no poses to fuse")
    codes = {p.code for p in poses}
    if len(codes) != 1:
        raise PoseError(f"cannot fuse poses of different codes {sorted(codes)}")
    X = np.array([p.position_mm for p in poses], dtype=np.float64)
    C = np.array([p.covariance_mm2 for p in poses], dtype=np.float64)
    N = np.array([p.normal for p in poses], dtype=np.float64)
    info = _information(C)
    inlier = np.ones(len(poses), dtype=bool)
    # Start from the coordinate-wise median (breakdown point 1/2), then iterate weighted means.
    centre = np.median(X, axis=0)
    for _ in range(10):
        d = X - centre
        m2 = np.einsum("ni,nij,nj->n", d, info, d)
        new = m2 <= gate
        if not np.any(new):
            new = m2 <= np.min(m2)
        centre, _ = _weighted_mean(X[new], info[new])
        if np.array_equal(new, inlier):
            break
        inlier = new
    centre, cov = _weighted_mean(X[inlier], info[inlier])
    k = int(inlier.sum())
    if k > 1:
        d = X[inlier] - centre
        chi2 = float(np.einsum("ni,nij,nj->", d, info[inlier], d))
        cov = cov * max(1.0, chi2 / (3.0 * (k - 1)))
    normal = np.sum(N[inlier], axis=0)
    normal /= np.linalg.norm(normal)
    biased = [p.systematic_mm2 for p, kept in zip(poses, inlier, strict=True) if kept]
    systematic = None
    if any(b is not None for b in biased):
        systematic = np.mean([np.zeros((3, 3)) if b is None else b for b in biased], axis=0)
    return FiducialPose(
        code=poses[0].code,
        position_mm=centre,
        normal=normal,
        covariance_mm2=cov,
        detection=None,
        n_frames=k,
        systematic_mm2=systematic,
        axis=mean_axis([p.axis for p, kept in zip(poses, inlier, strict=True) if kept], normal),
    )


def mean_axis(
    axes: Sequence[NDArray[np.float64] | None], normal: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """The mean of the frames' printed axes, in the plane of ``normal``, or None.

    None when no frame has an axis, or when they disagree so that their mean is short (under
    half a unit: a code read a sector apart, or frames on different branches of the circle's
    ambiguity), rather than a blend that no frame saw.
    """
    given = [np.asarray(a, dtype=np.float64) for a in axes if a is not None]
    if not given:
        return None
    n = np.asarray(normal, dtype=np.float64)
    mean = np.mean(given, axis=0)
    mean -= (mean @ n) * n
    length = float(np.linalg.norm(mean))
    if not length >= 0.5:
        return None
    return np.asarray(mean / length, dtype=np.float64)


def _weighted_mean(X: F64, info: F64) -> tuple[F64, F64]:
    """Inverse-covariance weighted mean of ``X`` (``(n, 3)``) and its covariance."""
    total = np.sum(info, axis=0)
    cov = np.linalg.inv(total)
    mean = cov @ np.einsum("nij,nj->i", info, X)
    return mean, 0.5 * (cov + cov.T)


def fuse(
    frames: Sequence[Sequence[FiducialPose]],
    *,
    gate_mm: float = 3.0,
    min_fraction: float = 0.5,
    gate: float = CHI2_3_999,
) -> list[FiducialPose]:
    """Fuse per-frame pose lists of a static scene into one pose per fiducial.

    Poses are associated across frames by code and proximity (codes repeat in a scene of
    hundreds of targets); each track is then fused by :func:`fuse_poses`. Proximity counts
    depth :data:`DEPTH_SCALE` times less than the offset across the line of sight: one image
    measures a fiducial's direction far better than its depth, and a partly covered fiducial's
    depth can wander several millimetres from frame to frame (the bundled session: 3.7 and
    7 mm off in different frames), which a 3-D gate split into two tracks, two poses of one
    fiducial in the baseline. :func:`fuse_poses` then weighs the depths by their covariances.

    Parameters
    ----------
    frames : sequence of sequences of FiducialPose
        The poses estimated in each frame.
    gate_mm : float
        Largest distance (mm) between a pose and a track's median position for them to be the
        same fiducial, across the line of sight (along it, ``DEPTH_SCALE`` times that); well
        below the spacing of equal codes, well above per-frame errors.
    min_fraction : float
        Tracks seen in fewer than this fraction of the frames are dropped (spurious detections).
    gate : float
        Outlier gate of :func:`fuse_poses`.

    Returns
    -------
    list of FiducialPose
        Fused poses, ordered by code then by first appearance.

    Raises
    ------
    PoseError
        If there are no frames or a parameter is out of range.
    """
    if not frames:
        raise PoseError("no frames to fuse")
    if gate_mm <= 0 or not 0.0 <= min_fraction <= 1.0:
        raise PoseError(
            f"need gate_mm > 0 and 0 <= min_fraction <= 1, got {gate_mm}, {min_fraction}"
        )
    tracks: list[list[FiducialPose]] = []
    anchors: list[F64] = []
    by_code: dict[int, list[int]] = {}  # track indices of each code, in creation order
    for frame in frames:
        claimed: set[int] = set()
        for pose in frame:
            best, best_d = -1, gate_mm
            for t in by_code.get(pose.code, ()):
                if t in claimed:
                    continue
                dist = _association_distance(pose.position_mm, anchors[t])
                if dist <= best_d:
                    best, best_d = t, dist
            if best < 0:
                tracks.append([pose])
                anchors.append(np.median([pose.position_mm], axis=0))
                by_code.setdefault(pose.code, []).append(len(tracks) - 1)
                claimed.add(len(tracks) - 1)
            else:
                tracks[best].append(pose)
                claimed.add(best)
                anchors[best] = np.median([p.position_mm for p in tracks[best]], axis=0)
    need = min_fraction * len(frames)
    fused = [fuse_poses(t, gate=gate) for t in tracks if len(t) >= need]
    order = sorted(range(len(fused)), key=lambda i: fused[i].code)
    return [fused[i] for i in order]


#: How many times less a depth difference counts than one across the line of sight when
#: :func:`fuse` pairs poses of different frames (monocular depth sds are 5-10 times the lateral
#: ones at 30-60 px).
DEPTH_SCALE = 10.0


def _association_distance(position_mm: F64, anchor_mm: F64) -> float:
    """Distance of a pose from a track's anchor, depth (along the anchor's line of sight)
    divided by :data:`DEPTH_SCALE`."""
    d = np.asarray(position_mm, dtype=np.float64) - anchor_mm
    rng = float(np.linalg.norm(anchor_mm))
    if not rng > 0:
        return float(np.linalg.norm(d))
    ray = anchor_mm / rng
    along = float(d @ ray)
    lateral = d - along * ray
    return float(np.sqrt(lateral @ lateral + (along / DEPTH_SCALE) ** 2))


#: How one frame compares with the others of its state (see :class:`FrameAgreement`).
Verdict = Literal["agrees", "disagrees", "moved", "unmatched"]

#: Verdicts saying that the frames do not show one scene from one camera position.
MOTION_VERDICTS: frozenset[str] = frozenset({"moved", "unmatched"})


@dataclass(frozen=True, slots=True, eq=False)
class FrameAgreement:
    """How one frame of a static state agrees with the other frames (camera frame, mm).

    The frame is registered onto its reference (the fusion of the frames that agree with each
    other, itself left out) by a rigid motion ``x_ref ~ rotation @ x + translation_mm`` over
    same-code fiducials, weighted by the poses' covariances.

    Attributes
    ----------
    frame : int
        Index of the frame.
    verdict : {"agrees", "disagrees", "moved", "unmatched"}
        ``moved``: all its fiducials are shifted alike, significantly and by at least
        ``moved_mm`` (the camera moved); ``unmatched``: too few of its fiducials are found in the
        reference (another scene, or a camera moved too far to register); ``disagrees``: a
        smaller common motion (at least ``warn_mm``), too many fiducials beyond the gate of their
        covariances, or no fiducial at all; ``agrees`` otherwise.
    reference : tuple of int
        The frames it was compared with (empty for the one frame of a consensus of one).
    n_poses, n_reference : int
        Fiducials in the frame and in its reference.
    n_shared : int
        Its fiducials paired with a reference fiducial of their code once the motion is removed.
    motion_mm : float
        Largest displacement, over the shared fiducials, that the motion makes: what a moved
        camera adds to every measured displacement.
    motion_chi2 : float
        Wald statistic of the motion against its covariance (chi-square with ``motion_dof``
        degrees of freedom when the frame and its reference show one scene from one place).
    motion_dof : int
        6, or 3 when fewer than three fiducials are shared (a translation alone is fitted).
    chi2 : float
        Sum over the shared fiducials of their squared Mahalanobis distances to the reference
        once the motion is removed (``3 * n_shared`` degrees of freedom).
    n_outliers : int
        Shared fiducials beyond the 99.9 % gate (:data:`CHI2_3_999`).
    rotation : (3, 3) ndarray
    translation_mm : (3,) ndarray
        The motion onto the reference.
    centre_mm : (3,) ndarray
        Centroid of the shared fiducials (in the frame), where :attr:`shift_mm` is taken.
    """

    frame: int
    verdict: Verdict
    reference: tuple[int, ...]
    n_poses: int
    n_reference: int
    n_shared: int
    motion_mm: float
    motion_chi2: float
    motion_dof: int
    chi2: float
    n_outliers: int
    rotation: F64
    translation_mm: F64
    centre_mm: F64

    @property
    def shift_mm(self) -> F64:
        """Shift of the shared fiducials' centroid by the motion, mm."""
        c = self.centre_mm
        return np.asarray(self.rotation @ c + self.translation_mm - c, dtype=np.float64)

    @property
    def rotation_deg(self) -> float:
        """Angle of the motion's rotation, degrees."""
        cos = (float(np.trace(self.rotation)) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def describe(self, names: Sequence[str] | None = None) -> str:
        """One line saying how the frame compares with its reference.

        Parameters
        ----------
        names : sequence of str, optional
            A name per frame (e.g. the image paths); default ``frame <index>``.
        """

        def name(i: int) -> str:
            return names[i] if names is not None else f"frame {i}"

        me = name(self.frame)
        refs = ", ".join(name(i) for i in self.reference) or "the other frames"
        if self.verdict == "moved":
            s = self.shift_mm
            return (
                f"{me} is moved {self.motion_mm:.2f} mm against {refs}: all its fiducials "
                f"shift alike (by {s[0]:+.2f}, {s[1]:+.2f}, {s[2]:+.2f} mm, turned "
                f"{self.rotation_deg:.2f} deg; chi-square {self.motion_chi2:.0f} for "
                f"{self.motion_dof} dof), as when the camera moves"
            )
        if self.verdict == "unmatched":
            return (
                f"only {self.n_shared} of the {self.n_poses} fiducials of {me} are found among "
                f"the {self.n_reference} of {refs} (another scene, or the camera moved far?)"
            )
        if self.verdict == "disagrees" and self.n_poses == 0:
            return f"no fiducial found in {me}, {self.n_reference} in {refs}"
        return (
            f"{me} {self.verdict} with {refs}: {self.n_outliers} of its "
            f"{self.n_shared} shared fiducials beyond the 99.9 % gate of their covariances, "
            f"common motion {self.motion_mm:.2f} mm (chi-square {self.motion_chi2:.0f} for "
            f"{self.motion_dof} dof)"
        )


@dataclass(frozen=True, slots=True, eq=False)
class Fusion:
    """Fused poses of several frames of a static state and how the frames agree.

    Attributes
    ----------
    poses : tuple of FiducialPose
        The fused poses (see :func:`fuse`).
    frames : tuple of FrameAgreement
        One per frame, in order.
    consensus : tuple of int
        The largest set of frames seen from one camera position (the reference of the others).
    fused : tuple of int
        The frames fused into ``poses``.
    aligned : tuple of int
        Frames whose motion onto the consensus was removed before fusing (``align``).
    """

    poses: tuple[FiducialPose, ...]
    frames: tuple[FrameAgreement, ...]
    consensus: tuple[int, ...]
    fused: tuple[int, ...]
    aligned: tuple[int, ...] = ()

    @property
    def disagreeing(self) -> tuple[FrameAgreement, ...]:
        """The frames whose verdict is not ``agrees``."""
        return tuple(a for a in self.frames if a.verdict != "agrees")

    @property
    def camera_moved(self) -> bool:
        """Whether some frame is ``moved`` or ``unmatched``: not one scene from one place."""
        return any(a.verdict in MOTION_VERDICTS for a in self.frames)


def fuse_frames(
    frames: Sequence[Sequence[FiducialPose]],
    *,
    gate_mm: float = 3.0,
    min_fraction: float = 0.5,
    gate: float = CHI2_3_999,
    search_mm: float = 15.0,
    moved_mm: float = 0.5,
    warn_mm: float = 0.2,
    min_shared: float = 0.5,
    outlier_fraction: float = 0.1,
    align: bool = False,
) -> Fusion:
    """Fuse frames of a static state (:func:`fuse`), testing first that they agree.

    Every pair of frames is registered (a rigid motion over same-code fiducials, weighted by
    their covariances); frames whose motion is below ``moved_mm`` or not significant (99.9 %)
    are seen from one camera position. The largest such set (ties: the one holding the earliest
    frame) is the consensus; every frame is then registered onto the fusion of the consensus
    frames other than itself and given a :class:`FrameAgreement`.

    Parameters
    ----------
    frames : sequence of sequences of FiducialPose
        The poses estimated in each frame. One frame is returned as it is.
    gate_mm, min_fraction, gate
        As for :func:`fuse`; ``gate_mm`` also pairs fiducials once a frame's motion is removed.
    search_mm : float
        Largest camera-induced shift looked for (mm): the first guess of a motion pairs each
        fiducial with the nearest one of its code within it. Keep it below half the spacing of
        equal codes.
    moved_mm : float
        A significant common motion at least this large makes the verdict ``moved``.
    warn_mm : float
        A significant common motion at least this large (and below ``moved_mm``) makes the
        verdict ``disagrees``.
    min_shared : float
        A frame sharing fewer than this fraction of its fiducials (or of its reference's, if
        fewer) with its reference is ``unmatched``.
    outlier_fraction : float
        A frame with more than this fraction of its shared fiducials (and at least 3) beyond
        ``gate`` after its motion is removed ``disagrees``.
    align : bool
        Remove the motion of ``moved`` frames before fusing them and leave out ``unmatched``
        ones; by default all frames are fused as they are (:func:`fuse`).

    Returns
    -------
    Fusion

    Raises
    ------
    PoseError
        If there are no frames or a parameter is out of range.
    """
    if not frames:
        raise PoseError("no frames to fuse")
    if not (
        0 < gate_mm <= search_mm
        and 0 <= warn_mm <= moved_mm
        and 0.0 <= min_shared <= 1.0
        and 0.0 <= outlier_fraction <= 1.0
    ):
        raise PoseError(
            "need 0 < gate_mm <= search_mm, 0 <= warn_mm <= moved_mm and min_shared, "
            f"outlier_fraction in [0, 1], got gate_mm={gate_mm}, search_mm={search_mm}, "
            f"warn_mm={warn_mm}, moved_mm={moved_mm}, min_shared={min_shared}, "
            f"outlier_fraction={outlier_fraction}"
        )
    lists = [list(f) for f in frames]
    n = len(lists)
    if n == 1:
        return Fusion(tuple(lists[0]), (_agreement(0, "agrees", (), len(lists[0]), 0),), (0,), (0,))
    fuse_kw = {"gate_mm": gate_mm, "min_fraction": min_fraction, "gate": gate}
    judge = _Criteria(search_mm, gate_mm, gate, moved_mm, warn_mm, min_shared, outlier_fraction)
    sets = [_PoseArrays.of(f) for f in lists]

    # Which frames see the scene from one place.
    near = np.eye(n, dtype=bool)
    for f, g in itertools.combinations(range(n), 2):
        reg = judge.register(sets[f], sets[g])
        if judge.shares_enough(reg, len(lists[f]), len(lists[g])):
            assert reg is not None
            near[f, g] = near[g, f] = reg.motion_mm < moved_mm or not reg.significant
    seen = [f for f in range(n) if lists[f]] or list(range(n))
    best = max(seen, key=lambda g: (sum(near[g, f] for f in seen), -g))
    consensus = tuple(f for f in seen if near[best, f])

    agreements = []
    whole = fuse([lists[g] for g in consensus], **fuse_kw)
    # The reference of the frames outside the consensus (there are some only if it is not all).
    outside_ref = _PoseArrays.of(whole) if len(consensus) < n else None
    for f in range(n):
        others = tuple(g for g in consensus if g != f)
        if not others:
            agreements.append(_agreement(f, "agrees", (), len(lists[f]), 0))
            continue
        if f in consensus:
            ref = _PoseArrays.of(fuse([lists[g] for g in others], **fuse_kw))
        else:
            assert outside_ref is not None
            ref = outside_ref
        agreements.append(judge(f, sets[f], len(lists[f]), ref, others))

    used = list(range(n))
    aligned: tuple[int, ...] = ()
    inputs = lists
    if align:
        used = [f for f in range(n) if agreements[f].verdict != "unmatched"] or list(consensus)
        aligned = tuple(f for f in used if agreements[f].verdict == "moved")
        inputs = [
            moved_poses(lists[f], agreements[f].rotation, agreements[f].translation_mm)
            if f in aligned
            else lists[f]
            for f in used
        ]
    # The consensus fusion already made is the result when every frame used is in it, as is.
    poses = whole if used == list(consensus) and not aligned else fuse(inputs, **fuse_kw)
    return Fusion(tuple(poses), tuple(agreements), consensus, tuple(used), aligned)


def frame_agreement(
    frame: Sequence[FiducialPose], reference: Sequence[FiducialPose]
) -> FrameAgreement:
    """How one pose set compares with a reference set of the same scene, as :func:`fuse_frames`
    judges each frame with its default parameters: ``frame`` is frame 1, ``reference`` frame 0.

    Without fusing anything: the check of a camera that moved between two states of a scene
    most of which stayed still (:func:`displacement_matcher.compare.camera_motion`).
    """
    judge = _Criteria()
    poses = list(frame)
    return judge(1, _PoseArrays.of(poses), len(poses), _PoseArrays.of(reference), (0,))


@dataclass(frozen=True, slots=True)
class _Criteria:
    """The registration and the verdict rules of :func:`fuse_frames` (its parameters; by default
    its defaults)."""

    search_mm: float = 15.0
    gate_mm: float = 3.0
    gate: float = CHI2_3_999
    moved_mm: float = 0.5
    warn_mm: float = 0.2
    min_shared: float = 0.5
    outlier_fraction: float = 0.1

    def register(self, a: _PoseArrays, b: _PoseArrays) -> _Registration | None:
        return _register(a, b, search_mm=self.search_mm, gate_mm=self.gate_mm, gate=self.gate)

    def shares_enough(self, reg: _Registration | None, a: int, b: int) -> bool:
        return reg is not None and reg.n_shared >= max(3.0, self.min_shared * min(a, b))

    def __call__(
        self,
        f: int,
        frame: _PoseArrays,
        n_poses: int,
        ref: _PoseArrays,
        others: tuple[int, ...],
    ) -> FrameAgreement:
        """Frame ``f`` (``n_poses`` poses, ``frame`` their finite ones) against ``ref``, the
        fusion of frames ``others``."""
        reg = self.register(frame, ref)
        verdict: Verdict = "agrees"
        if not n_poses:
            verdict = "disagrees" if len(ref) else "agrees"
        elif reg is None or not self.shares_enough(reg, n_poses, len(ref)):
            verdict = "unmatched"
        elif reg.significant and reg.motion_mm >= self.moved_mm:
            verdict = "moved"
        elif (reg.significant and reg.motion_mm >= self.warn_mm) or reg.n_outliers > max(
            2.0, self.outlier_fraction * reg.n_shared
        ):
            verdict = "disagrees"
        return _agreement(f, verdict, others, n_poses, len(ref), reg)


@dataclass(frozen=True, slots=True, eq=False)
class _PoseArrays:
    """Codes ``(n,)``, positions ``(n, 3)`` and covariances ``(n, 3, 3)`` of a pose list."""

    codes: NDArray[np.int64]
    X: F64
    C: F64

    @classmethod
    def of(cls, poses: Sequence[FiducialPose]) -> _PoseArrays:
        ok = [p for p in poses if np.all(np.isfinite(p.position_mm))]
        return cls(
            np.array([int(p.code) for p in ok], dtype=np.int64),
            np.array([p.position_mm for p in ok], dtype=np.float64).reshape(-1, 3),
            np.array([p.covariance_mm2 for p in ok], dtype=np.float64).reshape(-1, 3, 3),
        )

    def __len__(self) -> int:
        return len(self.codes)


@dataclass(frozen=True, slots=True, eq=False)
class _Registration:
    """Rigid motion of one pose set onto another and the statistics of its fit."""

    rotation: F64
    translation: F64
    centre: F64
    n_shared: int
    motion_mm: float
    wald: float
    dof: int
    chi2: float
    n_outliers: int

    @property
    def significant(self) -> bool:
        """Whether the motion is significant at 99.9 %."""
        return self.wald > (CHI2_6_999 if self.dof == 6 else CHI2_3_999)


def _agreement(
    frame: int,
    verdict: Verdict,
    reference: tuple[int, ...],
    n_poses: int,
    n_reference: int,
    reg: _Registration | None = None,
) -> FrameAgreement:
    """The agreement of a frame with its registration (none: compared with nothing, or
    nothing paired)."""
    if reg is None:
        z = np.zeros(3)
        return FrameAgreement(
            frame, verdict, reference, n_poses, n_reference, 0, 0.0, 0.0, 6, 0.0, 0, np.eye(3), z, z
        )
    return FrameAgreement(
        frame,
        verdict,
        reference,
        n_poses,
        n_reference,
        reg.n_shared,
        reg.motion_mm,
        reg.wald,
        reg.dof,
        reg.chi2,
        reg.n_outliers,
        reg.rotation,
        reg.translation,
        reg.centre,
    )


def moved_poses(poses: Sequence[FiducialPose], R: F64, t: F64) -> list[FiducialPose]:
    """``poses`` moved by ``x -> R @ x + t`` (normals and covariances turned with them)."""
    return [
        FiducialPose(
            p.code,
            R @ p.position_mm + t,
            R @ p.normal,
            R @ p.covariance_mm2 @ R.T,
            p.detection,
            p.n_frames,
            None if p.systematic_mm2 is None else R @ p.systematic_mm2 @ R.T,
            None if p.axis is None else R @ p.axis,
        )
        for p in poses
    ]


def _pairs(
    a_codes: NDArray[np.int64],
    A: F64,
    b_codes: NDArray[np.int64],
    B: F64,
    radius: float,
    *,
    mutual: bool,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index pairs ``(i, j)``: ``B[j]`` is the nearest point of ``A[i]``'s code within
    ``radius`` (and, when ``mutual``, ``A[i]`` the nearest of ``B[j]``'s)."""
    out_i: list[NDArray[np.intp]] = []
    out_j: list[NDArray[np.intp]] = []
    for code in np.intersect1d(a_codes, b_codes):
        ia = np.flatnonzero(a_codes == code)
        ib = np.flatnonzero(b_codes == code)
        d = np.linalg.norm(A[ia][:, None] - B[ib][None], axis=2)
        j = np.argmin(d, axis=1)
        rows = np.arange(len(ia))
        ok = d[rows, j] <= radius
        if mutual:
            ok &= np.argmin(d, axis=0)[j] == rows
        out_i.append(ia[ok])
        out_j.append(ib[j[ok]])
    if not out_i:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    return np.concatenate(out_i), np.concatenate(out_j)


def _skew(v: F64) -> F64:
    """Cross-product matrices ``[v]x`` of the rows of ``v`` (``(n, 3)`` -> ``(n, 3, 3)``)."""
    z = np.zeros(len(v))
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.stack([z, -w, y], 1), np.stack([w, z, -x], 1), np.stack([-y, x, z], 1)], 1)


def _motion_system(D: F64, r: F64, W: F64) -> tuple[F64, F64]:
    """Normal equations of the small motion ``r ~ w x D + tau`` (unknowns ``(w, tau)``),
    weighted by ``W`` (``(k, 3, 3)``): ``N (6, 6)`` and ``g (6,)``."""
    J = np.concatenate([-_skew(D), np.broadcast_to(np.eye(3), (len(D), 3, 3))], axis=2)
    N = np.einsum("kji,kjl,klm->im", J, W, J)
    g = np.einsum("kji,kjl,kl->i", J, W, r)
    return N, g


def _information(C: F64) -> F64:
    """Inverses of covariances ``(k, 3, 3)``, regularised (a trace-relative ridge) so that
    degenerate ones still invert."""
    tr = np.trace(C, axis1=1, axis2=2)[:, None, None]
    return np.asarray(np.linalg.inv(C + np.eye(3) * 1e-12 * tr), dtype=np.float64)


def _register(
    a: _PoseArrays, b: _PoseArrays, *, search_mm: float, gate_mm: float, gate: float
) -> _Registration | None:
    """Rigid motion ``b ~ R @ a + t`` over same-code fiducials (Gauss-Newton on the
    covariance-weighted residuals, pairs re-made as the search radius shrinks to ``gate_mm``; a
    translation alone when fewer than three fiducials pair up); None when none does."""
    ia, ib = _pairs(a.codes, a.X, b.codes, b.X, search_mm, mutual=False)
    if not len(ia):
        return None
    R = np.eye(3)
    t = np.median(b.X[ib] - a.X[ia], axis=0)
    radius = max(gate_mm, 0.5 * search_mm)
    for it in range(30):
        Y, ia, ib, r, W, m2 = _paired(a, b, R, t, radius)
        if not len(ia):
            return None
        use = _within(m2, gate) if it else np.ones(len(ia), dtype=bool)
        c = Y[ia][use].mean(axis=0)
        p = _solve_motion(*_motion_system(Y[ia][use] - c, r[use], W[use]))
        dR = np.asarray(cv2.Rodrigues(p[:3])[0], dtype=np.float64)
        R, t = dR @ R, dR @ (t - c) + c + p[3:]
        if radius <= gate_mm and np.linalg.norm(p[:3]) < 1e-9 and np.linalg.norm(p[3:]) < 1e-7:
            break
        radius = max(gate_mm, 0.5 * radius)
    Y, ia, ib, r, W, m2 = _paired(a, b, R, t, gate_mm)
    if not len(ia):
        return None
    inlier = _within(m2, gate)
    X = a.X[ia][inlier]
    centre = X.mean(axis=0)
    # Wald test of the whole motion, linearised about no motion at the shared fiducials.
    N, _ = _motion_system(X - centre, r[inlier], W[inlier])
    p = np.concatenate([cv2.Rodrigues(R)[0].ravel(), R @ centre + t - centre])
    dof = 6 if len(X) >= 3 else 3
    if dof == 3:
        N[:3, :] = N[:, :3] = 0.0
    motion = np.linalg.norm(Y[ia][inlier] - X, axis=1)
    return _Registration(
        rotation=R,
        translation=t,
        centre=centre,
        n_shared=len(ia),
        motion_mm=float(np.max(motion)),
        wald=float(p @ N @ p),
        dof=dof,
        chi2=float(np.sum(m2)),
        n_outliers=int(np.sum(m2 > gate)),
    )


def _paired(
    a: _PoseArrays, b: _PoseArrays, R: F64, t: F64, radius: float
) -> tuple[F64, NDArray[np.intp], NDArray[np.intp], F64, F64, F64]:
    """``a`` moved by ``(R, t)`` (``Y``) paired with ``b`` (mutual nearest of each code within
    ``radius``: indices ``ia``, ``ib``), the pairs' residuals ``r``, information ``W`` and squared
    Mahalanobis distances ``m2``."""
    Y = a.X @ R.T + t
    ia, ib = _pairs(a.codes, Y, b.codes, b.X, radius, mutual=True)
    r = b.X[ib] - Y[ia]
    W = _information(R @ a.C[ia] @ R.T + b.C[ib])
    return Y, ia, ib, r, W, np.einsum("ki,kij,kj->k", r, W, r)


def _within(m2: F64, gate: float) -> NDArray[np.bool_]:
    """Pairs within ``gate``; all of them when fewer than three (or than all) are."""
    use = m2 <= gate
    if use.sum() < min(3, len(m2)):
        use[:] = True
    return use


def _solve_motion(N: F64, g: F64) -> F64:
    """Least-squares ``(w, tau)`` of :func:`_motion_system`; the translation alone (``w = 0``)
    from fewer than three fiducials (``N`` then has rank 3 at most)."""
    p = np.zeros(6)
    if np.linalg.matrix_rank(N[:3, :3], tol=1e-9 * max(float(np.trace(N)), 1e-300)) < 3:
        p[3:] = np.linalg.lstsq(N[3:, 3:], g[3:], rcond=None)[0]
        return p
    return np.asarray(np.linalg.lstsq(N, g, rcond=None)[0], dtype=np.float64)
