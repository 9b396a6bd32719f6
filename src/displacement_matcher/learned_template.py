"""A unit template learned from the baseline, for fields without a unit map (or with a template
that names the codes alone).

In the paper's section 5 set-up every dolos carries the same codes at the same places, and a lab
rarely measures where on the unit each fiducial sits. The baseline shows it anyway: every unit
seen with three or more faces is the template in some pose. :func:`learn_template` groups the
baseline by the distances between codes (:func:`.units.learn_pair_distances`), aligns the groups
that show the commonest code set of three or more by generalised Procrustes (each group rotated
and shifted onto the running consensus, the consensus their per-coordinate median), and returns
the consensus as a :class:`.units.UnitSpec` with positions and, where the groups agree on one,
face normals (each pose's normal on either branch of its two-fold ambiguity: the true faces'
normals coincide in the unit's frame, the mirrored ones scatter with the viewing direction).
Codes seen beside three of those in other groups are placed the same way. A code the other
state shows (at least :data:`MIN_CODE_SEEN` times) but the baseline hardly does is a face the
units' resting pose hides (a dolos's fourth fluke, facing the slope): it is listed as ``hidden``,
so that a unit showing it has turned over. Other codes seen that often in either state are the
units' too, with neither position nor normal (the matcher weighs them as without a template);
codes read fewer times are misreads or strays, and belong to no unit.

The template's frame is the consensus's: its origin, where units' motions are reported, is the
centroid of the learned faces, its axes those of the first group aligned. Camera frame in,
millimetres.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Sequence

import numpy as np
from numpy.typing import NDArray

from pose_estimator.types import FiducialPose

from .rigid import kabsch
from .units import (
    DEFAULT_SPAN_MM,
    UnitSpec,
    group_fiducials,
    learn_pair_distances,
    mirror_normals,
)

#: Fewest baseline groups showing one code set (or placing one more code) for the template to be
#: learned from them: fewer are as likely neighbours joined by chance as units.
MIN_LEARN_GROUPS = 5
#: Groups whose RMS distance from the consensus exceeds this (mm) or three times the median one
#: are left out of it (two units' faces joined, a pose far off in depth).
MAX_GROUP_RMS_MM = 2.0
#: Procrustes rounds (the consensus settles in two; a third costs little).
PROCRUSTES_ROUNDS = 3
#: Normals within this angle of a face's consensus direction count for it, degrees; the face
#: gets a normal when at least half its groups agree so.
NORMAL_AGREE_DEG = 10.0
#: Fewest sightings in one state of a code the template does not place for it to be on the
#: units (a hidden face when the baseline shows it fewer times): the thirty dolos fields end to
#: end read 0-3 codes no unit carries (partly covered fiducials misread), each at most twice in
#: a state, and the hidden fourth face 4-6 times after the run. Such a stray in a unit's
#: template code set bridged two units' faces into one group (seed 23).
MIN_CODE_SEEN = 3


def learn_template(
    poses: Sequence[FiducialPose],
    span_mm: float = DEFAULT_SPAN_MM,
    *,
    other_state: Sequence[FiducialPose] = (),
    codes: Collection[int] | None = None,
    min_groups: int = MIN_LEARN_GROUPS,
) -> UnitSpec | None:
    """The unit template that the units seen in ``poses`` (one state, every unit carrying the
    same code set) share.

    Parameters
    ----------
    poses : sequence of FiducialPose
        One state's fiducials (camera frame, mm).
    span_mm : float
        Largest distance between two fiducials of one unit.
    other_state : sequence of FiducialPose
        The other state's fiducials (after the run): the template also lists the codes seen
        often there, and those the units of ``poses`` hardly show are its hidden faces.
    codes : collection of int, optional
        The units' codes, where known (a unit map's template without positions): only these
        are learned, and the template lists every one of them.
    min_groups : int
        Fewest groups that must show a code set (:data:`MIN_LEARN_GROUPS`).

    Returns
    -------
    UnitSpec or None
        ``"template"`` with positions (mm, the template's frame, origin at the learned faces'
        centroid) for the codes learned, normals for those whose groups agree on one and the
        hidden faces; None when no code set of three or more is shown by ``min_groups``
        consistent groups.
    """
    if codes is not None:
        wanted = {int(c) for c in codes}
        poses = [p for p in poses if int(p.code) in wanted]
        other_state = [p for p in other_state if int(p.code) in wanted]
    ok = [p for p in poses if np.all(np.isfinite(p.position_mm)) and np.all(np.isfinite(p.normal))]
    if len(ok) < 3 * min_groups:
        return None
    groups = group_fiducials(
        ok, span_mm=span_mm, pair_distances=learn_pair_distances(ok, span_mm, min_groups)
    )
    code = np.array([int(p.code) for p in ok], dtype=np.int64)
    pos = np.array([p.position_mm for p in ok], dtype=np.float64).reshape(-1, 3)
    nrm = np.array([p.normal for p in ok], dtype=np.float64).reshape(-1, 3)
    sets = Counter(tuple(sorted(code[g].tolist())) for g in groups if len(g) >= 3)
    if not sets:
        return None
    core, count = sets.most_common(1)[0]
    if count < min_groups:
        return None
    members = [g for g in groups if tuple(sorted(code[g].tolist())) == core]
    consensus, kept = _procrustes(members, core, code, pos)
    if len(kept) < min_groups:
        return None
    positions = {c: consensus[k] for k, c in enumerate(core)}
    aligned = [(g, *_aligned(g, core, code, pos, consensus)) for g in kept]
    _place_more_codes(groups, positions, code, pos, min_groups)
    normals: dict[int, NDArray[np.float64]] = {}
    for c in core:
        n = _consensus_normal(
            [(R, pos[_index_of(g, c, code)], nrm[_index_of(g, c, code)]) for g, R, _ in aligned]
        )
        if n is not None:
            normals[c] = n
    centre = np.mean(np.array(list(positions.values())), axis=0)
    before = Counter(int(p.code) for p in poses)
    later = Counter(int(p.code) for p in other_state)
    hidden = frozenset(
        c
        for c, k in later.items()
        if k >= MIN_CODE_SEEN and before[c] < MIN_CODE_SEEN and c not in positions
    )
    often = {c for counts in (before, later) for c, k in counts.items() if k >= MIN_CODE_SEEN}
    every = sorted({*positions, *often} if codes is None else {int(c) for c in codes})
    return UnitSpec(
        "template",
        tuple(every),
        {c: np.asarray(p - centre, dtype=np.float64) for c, p in positions.items()},
        normals,
        hidden,
    )


def _index_of(group: Sequence[int], c: int, code: NDArray[np.int64]) -> int:
    """The member of ``group`` of code ``c`` (a group holds each code once)."""
    return next(i for i in group if int(code[i]) == c)


def _points(
    group: Sequence[int], codes: Sequence[int], code: NDArray[np.int64], pos: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The group's positions in the order of ``codes``, ``(len(codes), 3)``."""
    return np.array([pos[_index_of(group, c, code)] for c in codes], dtype=np.float64)


def _aligned(
    group: Sequence[int],
    codes: Sequence[int],
    code: NDArray[np.int64],
    pos: NDArray[np.float64],
    target: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rotation of the group onto ``target`` (rows in the order of ``codes``) and its points
    there."""
    p = _points(group, codes, code, pos)
    R, t = kabsch(p, target)
    return R, p @ R.T + t


def _procrustes(
    groups: list[list[int]],
    codes: Sequence[int],
    code: NDArray[np.int64],
    pos: NDArray[np.float64],
) -> tuple[NDArray[np.float64], list[list[int]]]:
    """Generalised Procrustes of the groups (each showing ``codes``): the consensus, centred,
    and the groups kept in it."""
    consensus = _points(groups[0], codes, code, pos)
    consensus -= consensus.mean(axis=0)
    kept = groups
    for _ in range(PROCRUSTES_ROUNDS):
        placed = np.array([_aligned(g, codes, code, pos, consensus)[1] for g in groups])
        rms = np.sqrt(np.mean(np.sum((placed - consensus) ** 2, axis=2), axis=1))
        good = (rms <= MAX_GROUP_RMS_MM) & (rms <= 3.0 * max(float(np.median(rms)), 1e-3))
        if not np.any(good):
            return consensus, []
        kept = [g for g, k in zip(groups, good.tolist(), strict=True) if k]
        consensus = np.median(placed[good], axis=0)
        consensus -= consensus.mean(axis=0)
    return consensus, kept


def _place_more_codes(
    groups: list[list[int]],
    positions: dict[int, NDArray[np.float64]],
    code: NDArray[np.int64],
    pos: NDArray[np.float64],
    min_groups: int,
) -> None:
    """Codes shown in groups beside three of the learned ones, placed by those three (the
    median over at least ``min_groups`` groups whose three fit within
    :data:`MAX_GROUP_RMS_MM`); ``positions`` is extended in place."""
    found: dict[int, list[NDArray[np.float64]]] = {}
    for g in groups:
        known = [int(code[i]) for i in g if int(code[i]) in positions]
        new = [int(code[i]) for i in g if int(code[i]) not in positions]
        if len(known) < 3 or not new:
            continue
        target = np.array([positions[c] for c in known])
        R, placed = _aligned(g, known, code, pos, target)
        if np.sqrt(np.mean(np.sum((placed - target) ** 2, axis=1))) > MAX_GROUP_RMS_MM:
            continue
        t = placed[0] - R @ pos[_index_of(g, known[0], code)]
        for c in new:
            found.setdefault(c, []).append(R @ pos[_index_of(g, c, code)] + t)
    for c, where in found.items():
        if len(where) >= min_groups:
            positions[c] = np.median(np.array(where), axis=0)


def _consensus_normal(
    seen: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
) -> NDArray[np.float64] | None:
    """One face's normal in the template's frame from its groups' ``(R, position, normal)``:
    the direction most of both branches of every pose agree on, or None when under half the
    groups do."""
    dirs = []
    for R, p, n in seen:
        length = float(np.linalg.norm(n))
        if not length > 0:
            continue
        n = n / length
        dirs += [R @ n, R @ mirror_normals(p[None], n[None])[0]]
    if not dirs:
        return None
    d = np.array(dirs)
    agree = d @ d.T > np.cos(np.radians(NORMAL_AGREE_DEG))
    best = int(np.argmax(agree.sum(axis=1)))
    close = d[agree[best]]
    if len(close) < 0.5 * len(seen):
        return None
    mean = close.mean(axis=0)
    return np.asarray(mean / np.linalg.norm(mean), dtype=np.float64)
