"""Result types of the displacement matcher (camera frame, millimetres).

Positions and vectors are in the camera frame of :mod:`pose_estimator` (x right, y down, z forward,
millimetres). Indices refer to the baseline and current pose sequences given to
:func:`displacement_matcher.match`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from pose_estimator.types import FiducialPose

Label = Literal["same_code", "cross_code", "vanished", "appeared"]
LABELS: tuple[Label, ...] = ("same_code", "cross_code", "vanished", "appeared")
#: The labels of a pair (a fiducial matched before and after).
MATCH_LABELS: tuple[Label, ...] = ("same_code", "cross_code")


@dataclass(frozen=True, slots=True)
class MatchParams:
    """Parameters of one matching (all lengths in millimetres).

    Attributes
    ----------
    gate_mm : float
        Largest cost at which two fiducials may still be matched; leaving both unmatched costs
        ``gate_mm``, so a pair is matched only when its cost is below that.
    code_penalty_mm : float
        Added to the weighted distance when the codes differ; ``inf`` forbids cross-code
        matches.
    motion_scale_mm : float
        Displacement scale ``s`` of the weighting ``W = s^2 (s^2 I + C_a + C_b)^-1``: directions in
        which the two poses are uncertain compared with ``s`` (depth, mostly) count less.
    normal_weight_mm : float
        Added per unit of ``(1 - n_a . n_b)`` (0 disables normals in the cost).
    """

    gate_mm: float
    code_penalty_mm: float
    motion_scale_mm: float
    normal_weight_mm: float


@dataclass(frozen=True, slots=True, eq=False)
class Displacement:
    """One entry of the correspondence: a matched pair, a vanished or an appeared fiducial.

    Attributes
    ----------
    label : {"same_code", "cross_code", "vanished", "appeared"}
        ``cross_code`` pairs are allowed but less reliable (the paper's red vectors, section 5).
    baseline_index, current_index : int or None
        Indices into the baseline and current pose sequences (None on the missing side).
    code_before, code_after : int or None
        Codes of the two fiducials.
    before_mm, after_mm : (3,) ndarray or None
        Positions, camera frame, mm.
    cost : float
        This entry's share of the optimal total cost, mm (the weighted distance plus the code
        penalty for a pair; ``gate_mm / 2`` for an unmatched fiducial).
    sigma_mm : (3,) ndarray or None
        Standard deviation of the displacement's x, y, z (from both covariances), mm.
    """

    label: Label
    baseline_index: int | None
    current_index: int | None
    code_before: int | None
    code_after: int | None
    before_mm: NDArray[np.float64] | None
    after_mm: NDArray[np.float64] | None
    cost: float
    sigma_mm: NDArray[np.float64] | None = None

    @property
    def is_match(self) -> bool:
        """True for a same-code or cross-code pair."""
        return self.label in MATCH_LABELS

    @property
    def displacement_mm(self) -> NDArray[np.float64] | None:
        """``after_mm - before_mm`` for a pair, else None."""
        if self.before_mm is None or self.after_mm is None:
            return None
        return np.asarray(self.after_mm - self.before_mm, dtype=np.float64)

    @property
    def distance_mm(self) -> float | None:
        """Length of the displacement vector, mm (None unless matched)."""
        d = self.displacement_mm
        return None if d is None else float(np.linalg.norm(d))


# The name for the same record.
FiducialMatch = Displacement


@dataclass(frozen=True, slots=True)
class RejectedPose:
    """A pose left out of the matching because it is unusable, with the reason.

    Attributes
    ----------
    side : {"baseline", "current"}
    index : int
        Index into that side's pose sequence.
    code : int
    reason : str
    """

    side: Literal["baseline", "current"]
    index: int
    code: int
    reason: str


@dataclass(frozen=True, slots=True, eq=False)
class MatchResult:
    """The optimal partial matching of a baseline and a current fiducial set.

    Attributes
    ----------
    displacements : tuple of Displacement
        Pairs first (in baseline order), then vanished (baseline order), then appeared (current
        order). Every usable pose appears exactly once.
    baseline, current : tuple of FiducialPose
        The inputs.
    total_cost : float
        Sum of the entries' costs, mm: the minimum over all partial matchings (rejected poses
        excluded).
    rejected : tuple of RejectedPose
        Poses that could not be used (non-finite position, bad covariance), never silently lost.
    params : MatchParams
    n_components : int
        Connected components of the gated graph that needed an assignment solve.
    largest_component : int
        Fiducials (both sides) in the largest such component.
    """

    displacements: tuple[Displacement, ...]
    baseline: tuple[FiducialPose, ...]
    current: tuple[FiducialPose, ...]
    total_cost: float
    rejected: tuple[RejectedPose, ...]
    params: MatchParams
    n_components: int = 0
    largest_component: int = 0

    def by_label(self, label: Label) -> tuple[Displacement, ...]:
        """The entries carrying ``label``."""
        return tuple(d for d in self.displacements if d.label == label)

    def pairs(self) -> NDArray[np.intp]:
        """``(K, 2)`` array of matched ``(baseline_index, current_index)``."""
        rows = [(d.baseline_index, d.current_index) for d in self.displacements if d.is_match]
        return np.asarray(rows, dtype=np.intp).reshape(-1, 2)

    def counts(self) -> dict[str, int]:
        """Number of entries per label."""
        return {label: sum(d.label == label for d in self.displacements) for label in LABELS}


@dataclass(frozen=True, slots=True, eq=False)
class UnitMotion:
    """Rigid motion of one armour unit between baseline and current.

    Attributes
    ----------
    unit : str
        Unit id (from the unit map, or ``"U0001"``... for automatic grouping, in baseline order).
    codes : tuple of int
        Codes of the unit's fiducials seen in the baseline.
    baseline_indices, current_indices : tuple of int
        The unit's fiducials in each set.
    n_matched : int
        Fiducials of the unit matched between the two sets.
    method : {"rigid", "translation", "template", "none"}
        ``rigid``: weighted Kabsch/Umeyama over >= 3 consistently matched fiducials, or over >= 2
        whose normals (before and after) fix the rotation, or, for one pair that moved, the
        template fitted to two or more faces in each state; ``translation``: otherwise, rotation
        unknown (identity), except for one same-code pair that moved across the line of sight
        of a unit whose baseline faces fit the template: measured at the unit's origin, turned
        as the face's normal turned (the spin about it unseen); ``template``: none of its faces
        matched, but the faces it shows now were found together and the unit's template fitted
        to them (its motion is between the template's poses before and now; translation only
        when one face located it before);
        ``none``: nothing to measure (``status`` says why).
    rotation : (3, 3) ndarray
        Rotation, camera frame (identity when unknown).
    translation_mm : (3,) ndarray
        Displacement of the unit's reference point, mm (NaN when nothing was measured).
    rotation_deg : float or None
        Rotation angle, degrees (None when unknown).
    reference_before_mm : (3,) ndarray
        The reference point in the baseline: the unit's own origin when the unit map's template
        locates it (template fitted to the unit's baseline fiducials), else the centroid of its
        baseline fiducials for a rigid fit, of its matched ones for a translation (the mean of
        their displacements is then exactly the centroid's, whatever the rotation; the unit's
        origin where the template places it).
    residual_mm : float
        RMS residual of the rigid fit, mm (0 for fewer than 3 fiducials).
    status : {"still", "moved", "displaced", "overturned", "lost", "unseen"}
        Filled by :func:`displacement_matcher.damage.assess` (``"still"`` before that). ``lost``:
        seen in the baseline, none of its fiducials matched; ``unseen``: a mapped unit none of
        whose codes was seen.
    overturned : bool
        Fiducials seen before now face away and others appeared (or rotation above the overturn
        angle).
    n_vanished, n_appeared, n_cross_code : int
        The unit's vanished, appeared and cross-code fiducials.
    """

    unit: str
    codes: tuple[int, ...]
    baseline_indices: tuple[int, ...]
    current_indices: tuple[int, ...]
    n_matched: int
    method: Literal["rigid", "translation", "template", "none"]
    rotation: NDArray[np.float64]
    translation_mm: NDArray[np.float64]
    rotation_deg: float | None
    reference_before_mm: NDArray[np.float64]
    residual_mm: float
    overturned: bool
    n_vanished: int
    n_appeared: int
    n_cross_code: int
    status: str = "still"

    @property
    def distance_mm(self) -> float:
        """Length of ``translation_mm`` (NaN when nothing was measured)."""
        return float(np.linalg.norm(self.translation_mm))


@dataclass(frozen=True, slots=True)
class DamageThresholds:
    """Thresholds of a damage count, with their numbers in millimetres.

    Attributes
    ----------
    dn_mm : float
        Nominal unit size Dn, mm.
    displaced_mm : float
        A unit whose reference point moved at least this far is displaced.
    moved_mm : float
        A unit that moved at least this far (but less than ``displaced_mm``) moved-not-displaced.
    rotated_deg : float
        A unit that turned at least this much (but less than ``overturn_deg``) and was not
        displaced counts as moved too (rocking, rotation in place).
    overturn_deg : float
        Rotation at or above which a unit counts as overturned.
    overturned_displaced : bool
        Whether overturned units count as displaced.
    lost_displaced : bool
        Whether units seen before and not found after count as displaced.
    lateral_confirm_mm : float
        A unit measured by one fiducial that moved less than this across the line of sight has
        no confirmed motion (its depth change alone is not trusted).
    """

    dn_mm: float
    displaced_mm: float
    moved_mm: float
    rotated_deg: float
    overturn_deg: float
    overturned_displaced: bool
    lost_displaced: bool
    lateral_confirm_mm: float = 2.0


@dataclass(frozen=True, slots=True)
class DamageSummary:
    """Damage numbers of one comparison (a run, or cumulative since the baseline).

    Attributes
    ----------
    n_units : int
        Units seen in the baseline.
    displaced_units, moved_units, overturned_units, lost_units, still_units : int
        Counts (``displaced_units`` includes overturned/lost ones when the thresholds say so).
    percent_displaced : float
        ``100 * displaced_units / n_units`` (0 with no units).
    n_od : float or None
        Displaced units per strip of width Dn across the section: ``displaced * Dn / width``; None
        unless the section width is given.
    section_width_mm : float or None
    thresholds : DamageThresholds
    displaced_ids, moved_ids, overturned_ids, lost_ids : tuple of str
    """

    n_units: int
    displaced_units: int
    moved_units: int
    overturned_units: int
    lost_units: int
    still_units: int
    percent_displaced: float
    n_od: float | None
    section_width_mm: float | None
    thresholds: DamageThresholds
    displaced_ids: tuple[str, ...] = ()
    moved_ids: tuple[str, ...] = ()
    overturned_ids: tuple[str, ...] = ()
    lost_ids: tuple[str, ...] = ()

    def describe(self) -> str:
        """One-paragraph human summary with the thresholds' numbers."""
        t = self.thresholds
        nod = "n/a (no section width)" if self.n_od is None else f"{self.n_od:.3f}"
        return (
            f"units {self.n_units}: displaced {self.displaced_units} "
            f"({self.percent_displaced:.1f} %), moved-not-displaced {self.moved_units}, "
            f"overturned {self.overturned_units}, lost {self.lost_units}, N_od {nod}; "
            f"thresholds: displaced >= {t.displaced_mm:.2f} mm "
            f"({t.displaced_mm / t.dn_mm:.2f} Dn, Dn = {t.dn_mm:.2f} mm), "
            f"moved >= {t.moved_mm:.2f} mm or >= {t.rotated_deg:.0f} deg, "
            f"overturned >= {t.overturn_deg:.0f} deg; a unit seen through one fiducial must "
            f"move >= {t.lateral_confirm_mm:.2f} mm across the line of sight"
        )
