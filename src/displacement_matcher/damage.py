"""Damage numbers of a run: displaced, moved, overturned and lost units, and N_od.

A unit is *displaced* when its reference point moved at least the displacement threshold
(default one nominal unit size Dn, the usual criterion for armour-unit damage counts), *moved* when
it moved at least the movement threshold but less than that. Overturned units count as displaced;
units seen before but not found after are counted apart as *lost* (optionally as displaced).
``N_od`` is the number of displaced units per strip of width Dn across the section
(``displaced * Dn / section width``). Every summary carries its thresholds in millimetres so the
numbers are never printed without them.

A unit whose motion rests on a single fiducial is judged on what that fiducial can confirm: a
monocular pose measures the offset across the line of sight to a fraction of a millimetre but
depth from the apparent size of a small ellipse, with heavy tails (end to end in
``benchmarks/matcher_field`` about 3 % of poses are 10-90 mm off in depth, against a claimed
sigma near 1 mm). A lone fiducial that did not move across the line of sight (within
``lateral_confirm_mm``) has no confirmed motion: its depth change counts for nothing. Units with
two or more consistent fiducials are confirmed by their agreement (:mod:`.rigid`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from .errors import MatcherError
from .rigid import across_line_of_sight
from .types import DamageSummary, DamageThresholds, UnitMotion

DEFAULT_MOVED_MM = 2.0
DEFAULT_ROTATED_DEG = 10.0  # still units' fitted rotations stay below ~5 deg (matcher_field)
DEFAULT_LATERAL_CONFIRM_MM = 2.0


def thresholds(
    dn_mm: float,
    *,
    displaced_mm: float | None = None,
    displaced_dn: float | None = None,
    moved_mm: float = DEFAULT_MOVED_MM,
    rotated_deg: float = DEFAULT_ROTATED_DEG,
    overturn_deg: float = 90.0,
    overturned_displaced: bool = True,
    lost_displaced: bool = False,
    lateral_confirm_mm: float = DEFAULT_LATERAL_CONFIRM_MM,
) -> DamageThresholds:
    """Damage thresholds; the displacement threshold in mm or in Dn (default 1 Dn).

    Raises
    ------
    MatcherError
        For a non-positive Dn or threshold, or both ``displaced_mm`` and ``displaced_dn``.
    """
    if not (math.isfinite(dn_mm) and dn_mm > 0):
        raise MatcherError(f"Dn must be a positive length in mm, got {dn_mm!r}")
    if displaced_mm is not None and displaced_dn is not None:
        raise MatcherError("give the displacement threshold in mm or in Dn, not both")
    limit = dn_mm * (1.0 if displaced_dn is None else displaced_dn)
    if displaced_mm is not None:
        limit = displaced_mm
    if not (math.isfinite(limit) and limit > 0):
        raise MatcherError(f"displacement threshold must be positive, got {limit!r} mm")
    if not (math.isfinite(moved_mm) and 0 < moved_mm <= limit):
        raise MatcherError(
            f"movement threshold must be in (0, {limit:g}] mm (the displacement threshold), "
            f"got {moved_mm!r}"
        )
    if not 0 < overturn_deg <= 180:
        raise MatcherError(f"overturn angle must be in (0, 180] deg, got {overturn_deg!r}")
    if not 0 < rotated_deg <= overturn_deg:
        raise MatcherError(
            f"rotation threshold must be in (0, {overturn_deg:g}] deg, got {rotated_deg!r}"
        )
    if not (math.isfinite(lateral_confirm_mm) and lateral_confirm_mm >= 0):
        raise MatcherError(
            f"lateral_confirm_mm must be >= 0 and finite, got {lateral_confirm_mm!r}"
        )
    return DamageThresholds(
        float(dn_mm),
        float(limit),
        float(moved_mm),
        float(rotated_deg),
        float(overturn_deg),
        overturned_displaced,
        lost_displaced,
        float(lateral_confirm_mm),
    )


def confirmed_distance_mm(unit: UnitMotion, t: DamageThresholds) -> float:
    """The unit's displacement length as far as its measurement confirms it, mm.

    The full length, except for a unit whose motion rests on one fiducial and whose displacement
    across the line of sight (camera at the origin, through the reference point) is below
    ``t.lateral_confirm_mm``: then only that lateral part (see the module docstring).
    """
    dist = unit.distance_mm
    if unit.n_matched != 1 or not math.isfinite(dist):
        return dist
    ref = np.asarray(unit.reference_before_mm, dtype=np.float64)
    rng = float(np.linalg.norm(ref))
    if not (math.isfinite(rng) and rng > 0):
        return dist
    d = np.asarray(unit.translation_mm, dtype=np.float64)
    lateral = float(np.linalg.norm(across_line_of_sight(d, ref)))
    return lateral if lateral < t.lateral_confirm_mm else dist


def classify(unit: UnitMotion, t: DamageThresholds) -> str:
    """Status of one unit: still, moved, displaced, overturned, lost or unseen."""
    if unit.status == "unseen" or (not unit.baseline_indices):
        return "unseen"
    overturned = unit.overturned or (
        unit.rotation_deg is not None and unit.rotation_deg >= t.overturn_deg
    )
    if overturned:
        return "overturned"
    dist = confirmed_distance_mm(unit, t)
    if unit.method == "none" or not math.isfinite(dist):
        return "lost"
    if dist >= t.displaced_mm:
        return "displaced"
    if dist >= t.moved_mm or (unit.rotation_deg is not None and unit.rotation_deg >= t.rotated_deg):
        return "moved"
    return "still"


def assess(
    units: Sequence[UnitMotion],
    t: DamageThresholds,
    *,
    section_width_mm: float | None = None,
) -> tuple[tuple[UnitMotion, ...], DamageSummary]:
    """Classify every unit and count the damage.

    Parameters
    ----------
    units : sequence of UnitMotion
        From :func:`displacement_matcher.units.unit_motions`.
    t : DamageThresholds
    section_width_mm : float, optional
        Width of the section along the crest; gives ``N_od``.

    Returns
    -------
    units : tuple of UnitMotion
        The same units with ``status`` filled in.
    summary : DamageSummary
    """
    if section_width_mm is not None and not (
        math.isfinite(section_width_mm) and section_width_mm > 0
    ):
        raise MatcherError(f"section width must be a positive length, got {section_width_mm!r}")
    out = tuple(dataclasses.replace(u, status=classify(u, t)) for u in units)
    seen = [u for u in out if u.status != "unseen"]
    ids = {
        s: tuple(u.unit for u in seen if u.status == s)
        for s in ("displaced", "moved", "overturned", "lost", "still")
    }
    displaced = list(ids["displaced"])
    if t.overturned_displaced:
        displaced += ids["overturned"]
    if t.lost_displaced:
        displaced += ids["lost"]
    n = len(seen)
    n_disp = len(displaced)
    summary = DamageSummary(
        n_units=n,
        displaced_units=n_disp,
        moved_units=len(ids["moved"]),
        overturned_units=len(ids["overturned"]),
        lost_units=len(ids["lost"]),
        still_units=len(ids["still"]),
        percent_displaced=100.0 * n_disp / n if n else 0.0,
        n_od=None if section_width_mm is None else n_disp * t.dn_mm / section_width_mm,
        section_width_mm=section_width_mm,
        thresholds=t,
        displaced_ids=tuple(sorted(displaced)),
        moved_ids=ids["moved"],
        overturned_ids=ids["overturned"],
        lost_ids=ids["lost"],
    )
    return out, summary


def cumulative(runs: Sequence[DamageSummary]) -> dict[str, object]:
    """Damage per run and accumulated over runs that are each measured against the baseline.

    Each run's summary is already cumulative when measured against the first baseline; this adds
    the per-run increments (units newly displaced in each run).
    """
    seen: set[str] = set()
    rows = []
    for k, s in enumerate(runs):
        new = sorted(set(s.displaced_ids) - seen)
        seen |= set(s.displaced_ids)
        rows.append(
            {
                "run": k,
                "displaced_units": s.displaced_units,
                "newly_displaced": len(new),
                "percent_displaced": s.percent_displaced,
                "n_od": s.n_od,
            }
        )
    return {"runs": rows, "ever_displaced": len(seen), "ever_displaced_ids": sorted(seen)}
