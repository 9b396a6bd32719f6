"""Armour units: which fiducials belong together, and how each unit moved.

A unit map (YAML) names the units and their fiducial codes, or gives a *template*: the code set
that repeats on every unit (the paper's section 5 case, where every dolos carries the same four
codes), optionally with the fiducials' positions and face normals on the unit. Without a map, or
with a template, units are found automatically in the baseline (and in the current state):
fiducials of different codes are grouped by proximity, never two of one code in a unit, and when
the template gives positions (and normals) only pairs whose distance (and the rigid invariants of
the two oriented fiducials) agree with the unit's own geometry are grouped; without positions, the
distances between codes are learned from the baseline (:func:`learn_pair_distances`), and so,
by :func:`displacement_matcher.refine.match_units`, is the template itself
(:mod:`.learned_template`: where the codes sit on the unit, their normals, and the faces the
units' resting pose hides). Every
normal check allows for the circle pose's two-fold ambiguity (:func:`mirror_normals`): the pose
estimator puts a sizeable share of normals on the wrong branch.

Unit map YAML (lengths in mm, positions in the unit's own frame)::

    units:                  # explicit units: every code on one unit only
      D01: {codes: [3, 17]}
      D02: {codes: [29, 41], positions_mm: {29: [0, 0, 15], 41: [0, 0, -15]}}
    # or
    template:               # the same code set on every unit
      codes: [3, 17, 29, 41]
      positions_mm: {3: [9.5, 15.2, 0], 17: [9.5, -15.2, 0],
                     29: [-9.5, 0, 15.2], 41: [-9.5, 0, -15.2]}
      normals: {3: [0, 1, 1], 17: [0, -1, 1], 29: [0, 0, 1], 41: [0, 0, -1]}  # optional
      hidden: [41]          # optional: faces the units' resting pose hides (seen: overturned)
      span_mm: 35           # optional: largest distance between two fiducials of a unit

Per unit the motion is a weighted rigid fit (:mod:`.rigid`: Kabsch/Umeyama without scale, or
Wahba's problem over normals and inter-fiducial vectors) when at least three of its fiducials, or
two with normals, are matched consistently; a translation otherwise. Matches are screened first:
same-code matches are preferred to cross-code ones, and only the largest subset that one rigid
motion explains is used (among equal sizes the smallest motion: most units do not move). With a
template, or an explicit unit's own positions, the displacement is reported at the unit's origin,
located by fitting those positions to the unit's baseline fiducials.
:func:`displacement_matcher.refine.match_units` re-matches knowing how each unit moved.
Camera frame, millimetres.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from fiducial_detector.codebook import code_count
from pose_estimator.orientation import mirror_axes, target_frames
from pose_estimator.types import FiducialPose
from pose_estimator.yaml_file import YamlFileError, load_yaml

from .errors import MatcherError
from .rigid import across_line_of_sight, consistent_subset, rigid_fit, rms_misfit
from .types import MatchResult, UnitMotion

DEFAULT_SPAN_MM = 40.0
DEFAULT_RIGID_TOL_MM = 3.0
DEFAULT_OVERTURN_DEG = 90.0
# Template faces whose normals' dot product is below this point away from each other: a unit
# showing one of them cannot show the other too (a dolos's 4th fluke face against the other three).
OPPOSED_DOT = -0.3
# A baseline fiducial with a same-code fiducial now within this distance across the line of sight
# (where one image measures precisely) is still seen in place.
STILL_SHOWN_MM = 3.0
# ... unless both poses claim a precise depth and their depths differ by more than this: another
# unit's face that came to rest in front of the place (:func:`still_in_place`).
APART_IN_DEPTH_MM = 12.0
# A pose's depth counts as precise when its claimed sd along the line of sight is at most this
# many times the median of both states' poses: on the thirty end-to-end fields, 3 of the 32,576
# poses within 1.6 times the median (about 0.46 mm) were over 12 mm off in depth, against 113 of
# the 7,418 beyond it (mostly partly covered fiducials).
PRECISE_DEPTH_RATIO = 1.6


@dataclass(frozen=True, slots=True, eq=False)
class UnitSpec:
    """One unit (or the repeated template) of a unit map.

    Attributes
    ----------
    unit : str
        Unit id (``"template"`` for the template).
    codes : tuple of int
        Codes of its fiducials.
    positions_mm : dict of int to (3,) ndarray
        Fiducial centres on the unit (unit frame, mm), for the codes that have one.
    normals : dict of int to (3,) ndarray
        Unit normals of the printed faces on the unit (unit frame), for the codes that have one.
    hidden : frozenset of int
        Codes whose faces the units' resting pose hides (a learned template's faces that no
        baseline unit showed, :mod:`.learned_template`): such a face now seen points away from
        every face with a normal, so showing it means the unit turned over.
    """

    unit: str
    codes: tuple[int, ...]
    positions_mm: dict[int, NDArray[np.float64]]
    normals: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    hidden: frozenset[int] = frozenset()


@dataclass(frozen=True, slots=True, eq=False)
class UnitMap:
    """Explicit units, or the template repeated on every unit (exactly one of the two).

    Attributes
    ----------
    units : tuple of UnitSpec
    template : UnitSpec or None
    span_mm : float
        Largest distance between two fiducials of one unit (for automatic grouping).
    """

    units: tuple[UnitSpec, ...] = ()
    template: UnitSpec | None = None
    span_mm: float = DEFAULT_SPAN_MM


def _codes(value: Any, where: str) -> tuple[int, ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or not value:
        raise MatcherError(f"{where}: codes must be a non-empty list of integers, got {value!r}")
    out = []
    for c in value:
        if isinstance(c, bool) or not isinstance(c, int):
            raise MatcherError(f"{where}: code {c!r} is not an integer")
        if not 0 <= c < code_count():
            raise MatcherError(
                f"{where}: unknown code {c} (the codebook has codes 0..{code_count() - 1})"
            )
        out.append(int(c))
    if len(set(out)) != len(out):
        raise MatcherError(f"{where}: a code is listed twice in {out}")
    return tuple(out)


def _spec(name: str, doc: Any) -> UnitSpec:
    if not isinstance(doc, Mapping):
        raise MatcherError(f"unit {name!r}: expected a mapping with 'codes', got {doc!r}")
    unknown = set(doc) - {"codes", "positions_mm", "normals", "hidden", "span_mm"}
    if unknown:
        raise MatcherError(f"unit {name!r}: unknown keys {sorted(map(str, unknown))}")
    codes = _codes(doc.get("codes"), f"unit {name!r}")
    positions: dict[int, NDArray[np.float64]] = {}
    raw = doc.get("positions_mm") or {}
    if not isinstance(raw, Mapping):
        raise MatcherError(f"unit {name!r}: positions_mm must map codes to [x, y, z]")
    for key, value in raw.items():
        try:
            code = int(key)
            p = np.asarray(value, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as err:
            raise MatcherError(f"unit {name!r}: bad position for code {key!r}: {value!r}") from err
        if code not in codes:
            raise MatcherError(f"unit {name!r}: position given for code {code} not in {codes}")
        if not np.all(np.isfinite(p)):
            raise MatcherError(f"unit {name!r}: position of code {code} is not finite")
        positions[code] = p
    normals: dict[int, NDArray[np.float64]] = {}
    raw = doc.get("normals") or {}
    if not isinstance(raw, Mapping):
        raise MatcherError(f"unit {name!r}: normals must map codes to [nx, ny, nz]")
    for key, value in raw.items():
        try:
            code = int(key)
            v = np.asarray(value, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as err:
            raise MatcherError(f"unit {name!r}: bad normal for code {key!r}: {value!r}") from err
        if code not in codes:
            raise MatcherError(f"unit {name!r}: normal given for code {code} not in {codes}")
        length = float(np.linalg.norm(v))
        if not (np.isfinite(length) and length > 0):
            raise MatcherError(f"unit {name!r}: normal of code {code} is zero or not finite")
        normals[code] = v / length
    hidden: tuple[int, ...] = ()
    if doc.get("hidden"):
        hidden = _codes(doc["hidden"], f"unit {name!r} hidden")
        stray = sorted(set(hidden) - set(codes))
        if stray:
            raise MatcherError(f"unit {name!r}: hidden codes {stray} not in {codes}")
    return UnitSpec(str(name), codes, positions, normals, frozenset(hidden))


def template_span(spec: UnitSpec) -> float:
    """A template's grouping span where none is given: its own extent (the largest distance
    between two of its positions) plus 5 mm, or :data:`DEFAULT_SPAN_MM` without two positions."""
    if len(spec.positions_mm) < 2:
        return DEFAULT_SPAN_MM
    pts = np.array(list(spec.positions_mm.values()))
    return float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=2))) + 5.0


def parse_unit_map(doc: Any) -> UnitMap:
    """Validate a parsed unit-map mapping (see the module docstring for the format).

    Raises
    ------
    MatcherError
        Naming the unit and value that is wrong: unknown codes, a code on two units, malformed
        positions, neither or both of ``units`` and ``template``.
    """
    if not isinstance(doc, Mapping):
        raise MatcherError("unit map must be a mapping with 'units' or 'template'")
    extra = set(doc) - {"units", "template"}
    if extra:
        raise MatcherError(f"unit map: unknown keys {sorted(map(str, extra))}")
    if ("units" in doc) == ("template" in doc):
        raise MatcherError("unit map needs exactly one of 'units' and 'template'")
    if "template" in doc:
        tdoc = doc["template"]
        spec = _spec("template", tdoc)
        raw_span = tdoc.get("span_mm")
        span = 0.0
        if raw_span is not None:
            try:
                span = float(raw_span)
            except (TypeError, ValueError) as err:
                raise MatcherError(
                    f"template span_mm must be a length in mm, got {raw_span!r}"
                ) from err
            if not (np.isfinite(span) and span > 0):
                raise MatcherError(
                    f"template span_mm must be a positive length in mm, got {raw_span!r}"
                )
        if span <= 0:
            span = template_span(spec)
        return UnitMap((), spec, span)
    udoc = doc["units"]
    if not isinstance(udoc, Mapping) or not udoc:
        raise MatcherError("unit map: 'units' must be a non-empty mapping of unit id -> unit")
    specs = tuple(_spec(str(k), v) for k, v in udoc.items())
    names = [s.unit for s in specs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        # YAML keeps 1 and "1" apart; the report, the CSVs and the markers do not.
        raise MatcherError(f"unit id {twice[0]!r} is given twice (e.g. as 1 and '1')")
    owner: dict[int, str] = {}
    for s in specs:
        for c in s.codes:
            if c in owner:
                raise MatcherError(
                    f"unit map: code {c} is on units {owner[c]!r} and {s.unit!r}; a code set "
                    "repeated on every unit is given as 'template'"
                )
            owner[c] = s.unit
    return UnitMap(specs, None, DEFAULT_SPAN_MM)


def load_unit_map(path: str | Path) -> UnitMap:
    """Read and validate a unit-map YAML file (raises :class:`MatcherError`)."""
    try:
        doc = load_yaml(path)
    except YamlFileError as err:
        raise MatcherError(f"cannot read unit map {err}") from err
    try:
        return parse_unit_map(doc)
    except MatcherError as err:
        raise MatcherError(f"unit map {path}: {err}") from err


def places_every_code(template: UnitSpec | None) -> bool:
    """Whether a template gives every one of its codes a position on the unit (else the
    distances between the codes it leaves unplaced are learned: :func:`learn_pair_distances`)."""
    return template is not None and all(c in template.positions_mm for c in template.codes)


#: Widths (mm) of the distance windows :func:`learn_pair_distances` tries, narrowest first: pose
#: noise spreads an exact template distance over about a millimetre; fiducials glued by hand, a
#: few more.
LEARN_WINDOWS_MM = (2.0, 4.0, 6.0)
#: How far (in Poisson sds of the local background) a window must stand above the distances on
#: either side of it (three windows' width each) to count as a unit's distance. Over random
#: scatter (200 sets of 30-300 fiducials, 3 codes) the busiest window reached 5.8 at most (99th
#: percentile 5.2); units' distances stood 9.7-13.8 above on dolos fields of 120 units and
#: 8.9-11.0 on the bundled session's 24.
LEARN_MIN_Z = 7.0


def learn_pair_distances(
    poses: Sequence[FiducialPose], span_mm: float = DEFAULT_SPAN_MM, min_units: int = 3
) -> dict[tuple[int, int], float]:
    """Distances between the codes of one unit, learned from a state where every unit carries
    the same code set.

    Units of one kind carry their fiducials at the same places, so between two codes the
    distance within a unit is the same on every unit, while fiducials of neighbouring units lie
    at any distance, and often nearer (the bundled session: 28.7-30.4 mm within a unit, 9-15
    mm to the nearest fiducial of another). Proximity alone then joins neighbours' fiducials;
    the within-unit distance shows as a spike among all distances of the two codes up to
    ``span_mm``. A code pair gets its distance (the median in the spike's window) when the
    busiest window of a width in :data:`LEARN_WINDOWS_MM` holds at least ``min_units``
    distances and stands :data:`LEARN_MIN_Z` Poisson sds above the distances around it.

    Returns
    -------
    dict
        ``(code_a, code_b) -> mm``, both orders; pairs with no clear spike are left out.
    """
    pos: dict[int, list[NDArray[np.float64]]] = {}
    for p in poses:
        x = np.asarray(p.position_mm, dtype=np.float64).reshape(-1)
        if x.size == 3 and np.all(np.isfinite(x)):
            pos.setdefault(int(p.code), []).append(x)
    out: dict[tuple[int, int], float] = {}
    for a, b in itertools.combinations(sorted(pos), 2):
        pa, pb = np.array(pos[a]), np.array(pos[b])
        d = np.linalg.norm(pa[:, None] - pb[None], axis=2).ravel()
        d = np.sort(d[d <= span_mm])
        if len(d) < min_units:
            continue
        for width in LEARN_WINDOWS_MM:
            # Distances in [d_i, d_i + width] for every i: the busiest such window.
            counts = np.searchsorted(d, d + width, side="right") - np.arange(len(d))
            k = int(np.argmax(counts))
            lo, hi = float(d[k]), float(d[k] + width)
            # The background: distances within three widths on either side (clipped to
            # [0, span_mm]). Fiducials scattered over a surface have pairs at distance d in
            # proportion to d, so the sides' density per unit of d, not their count, predicts
            # the window's.
            left, right = max(lo - 3.0 * width, 0.0), min(hi + 3.0 * width, span_mm)
            side = ((d >= left) & (d < lo)) | ((d > hi) & (d <= right))
            covered = (lo - left) + (right - hi)
            density = float(np.sum(1.0 / np.maximum(d[side], 1e-6))) / covered if covered else 0.0
            background = density * width * 0.5 * (lo + hi)
            z = (counts[k] - background) / np.sqrt(background + 1.0)
            if counts[k] >= min_units and z >= LEARN_MIN_Z:
                dist = float(np.median(d[k : k + counts[k]]))
                out[(a, b)] = out[(b, a)] = dist
                break
    return out


def group_fiducials(
    poses: Sequence[FiducialPose],
    *,
    span_mm: float = DEFAULT_SPAN_MM,
    template: UnitSpec | None = None,
    tol_mm: float = DEFAULT_RIGID_TOL_MM,
    normal_tol: float = 0.3,
    pair_distances: Mapping[tuple[int, int], float] | None = None,
) -> list[list[int]]:
    """Group the fiducials of one state into units by proximity and code set.

    Pairs closer than ``span_mm`` with different codes are joined in order of increasing distance
    (complete linkage) as long as a group never holds one code twice, every pair in it is within
    ``span_mm`` and, when ``template`` gives positions for both codes, their distance agrees with
    the template's within ``tol_mm`` plus three standard deviations, and when it gives normals
    too, the rigid invariants of the two oriented fiducials (``n_i . n_j`` and each normal against
    the line between them) agree within ``normal_tol``. Fiducials whose code is not in
    ``template.codes`` (when given) are left out; non-finite poses are left out.
    ``pair_distances`` (:func:`learn_pair_distances`) stand in for the template's distances
    between codes where it gives no positions for both; with a template, pairs it does not place
    are joined after every pair it does (a learned template's hidden codes, for which the
    baseline shows too few faces to learn a distance: checked by the span alone, they would
    score as a perfect fit and be joined first).

    Returns
    -------
    list of list of int
        Indices into ``poses``, one list per unit, ordered by their first index.
    """
    allowed = set(template.codes) if template is not None else None
    idx = [
        i
        for i, p in enumerate(poses)
        if np.all(np.isfinite(p.position_mm)) and (allowed is None or int(p.code) in allowed)
    ]
    if not idx:
        return []
    pos = np.array([poses[i].position_mm for i in idx], dtype=np.float64).reshape(-1, 3)
    code = np.array([int(poses[i].code) for i in idx])
    cov = np.array([poses[i].covariance_mm2 for i in idx], dtype=np.float64).reshape(-1, 3, 3)
    cov = np.where(np.isfinite(cov), cov, 0.0)
    from scipy.spatial import cKDTree

    pairs = cKDTree(pos).query_pairs(span_mm, output_type="ndarray")
    # Learned distances serve the code pairs the template does not place (all of them without
    # template positions; with a learned template, another kind of unit's codes).
    tdist = {(int(a), int(b)): float(d) for (a, b), d in (pair_distances or {}).items()}
    if template is not None:
        for ca, cb in itertools.permutations(template.positions_mm, 2):
            tdist[(ca, cb)] = float(
                np.linalg.norm(template.positions_mm[ca] - template.positions_mm[cb])
            )

    nrm = np.array([poses[i].normal for i in idx], dtype=np.float64).reshape(-1, 3)
    nlen = np.linalg.norm(nrm, axis=1)
    has_n = np.isfinite(nlen) & (nlen > 0.5)
    nrm = np.where(has_n[:, None], nrm / np.where(has_n, nlen, 1.0)[:, None], 0.0)
    # Either branch of each pose's two-fold normal ambiguity may be the true one.
    branches = (nrm, mirror_normals(pos, nrm))
    tinv: dict[tuple[int, int], tuple[float, float, float]] = {}
    if template is not None:
        tp, tn = template.positions_mm, template.normals
        for ca, cb in itertools.permutations(tp, 2):
            if ca in tn and cb in tn:
                u = (tp[cb] - tp[ca]) / max(float(np.linalg.norm(tp[cb] - tp[ca])), 1e-9)
                tinv[(ca, cb)] = (float(tn[ca] @ tn[cb]), float(tn[ca] @ u), float(tn[cb] @ u))

    if tinv:
        # Pairs whose depths may be far off (see depth_free) are found by direction from the
        # camera: a lateral offset L at range r is an angle of about L / r.
        rng = np.linalg.norm(pos, axis=1)
        if np.all(rng > 0):
            chord = span_mm / float(rng.min())
            lateral = cKDTree(pos / rng[:, None]).query_pairs(chord, output_type="ndarray")
            if len(lateral):
                both = np.vstack([pairs.reshape(-1, 2), lateral])
                pairs = np.unique(np.sort(both, axis=1), axis=0)

    def depth_free(i: int, j: int, dt: float) -> list[NDArray[np.float64]]:
        """Directions from ``i`` to ``j`` with their depths re-set to the template distance.

        A monocular pose's offset across its line of sight is precise, its depth is not: end to
        end a few percent of poses are 5-90 mm off in depth, far beyond their claimed sigma,
        which fails a 3-D distance check or tilts the direction between two fiducials enough
        to fail the normal invariants, splitting their unit. When the offset across the line of
        sight (``L``, through the pair's midpoint) alone fits the template distance ``dt``, the
        depths can be moved along the line of sight to make the distance exactly ``dt``: the
        depth offset is then ``+-sqrt(dt^2 - L^2)``, the measured sign first. Empty when ``L``
        does not fit.
        """
        v = pos[j] - pos[i]
        ray = pos[i] + pos[j]
        ray = ray / max(float(np.linalg.norm(ray)), 1e-12)
        along = float(v @ ray)
        lat = v - along * ray
        length = float(np.linalg.norm(lat))
        if length < 1e-9:
            return []
        u_lat = lat / length
        sd = float(np.sqrt(max(u_lat @ (cov[i] + cov[j]) @ u_lat, 0.0)))
        if length > dt + tol_mm + 3.0 * sd:
            return []
        depth = float(np.sqrt(max(dt * dt - length * length, 0.0)))
        out = []
        for sign in (1.0, -1.0) if along >= 0 else (-1.0, 1.0):
            w = lat + sign * depth * ray
            out.append(np.asarray(w / max(float(np.linalg.norm(w)), 1e-12), dtype=np.float64))
        return out

    def normal_error(i: int, j: int, key: tuple[int, int], w: NDArray[np.float64]) -> float:
        """Worst disagreement of the pair's rigid invariants with the template's.

        Rigid invariants of two oriented points: ``n_i . n_j`` and each normal against the
        direction ``w`` from i to j. A pose on the wrong branch must not split its unit, so
        mirrored normals may stand in; but four combinations make chance agreement likelier, so
        each mirror halves the tolerance.
        """
        err = np.inf
        for (fi, ni), (fj, nj) in itertools.product(
            enumerate(b[i] for b in branches), enumerate(b[j] for b in branches)
        ):
            seen = (float(ni @ nj), float(ni @ w), float(nj @ w))
            e = max(abs(a - b) for a, b in zip(seen, tinv[key], strict=True))
            err = min(err, e * 2.0 ** (fi + fj))
        return float(err)

    def mismatch(i: int, j: int) -> float:
        """Template distance error over its tolerance (<= 1 compatible); inf if incompatible.

        With template normals, the larger of that and the normal invariants' error over
        ``normal_tol``. A pair that fails with its measured depths is tried with its depths
        re-set (:func:`depth_free`): then it scores at least 1 (joined after every pair that
        fits in 3-D) and its normals must bear all the weight (the reversed depth offset, a
        second guess, at half the tolerance).
        """
        if code[i] == code[j]:
            return np.inf
        v = pos[j] - pos[i]
        d = float(np.linalg.norm(v))
        key = (int(code[i]), int(code[j]))
        if key not in tdist:
            return 0.0 if d <= span_mm else np.inf
        w = v / max(d, 1e-9)
        sd = float(np.sqrt(max(w @ (cov[i] + cov[j]) @ w, 0.0)))
        score = abs(d - tdist[key]) / (tol_mm + 3.0 * sd) if d <= span_mm else np.inf
        if not (key in tinv and has_n[i] and has_n[j]):
            return score
        best = max(score, normal_error(i, j, key, w) / normal_tol)
        if best <= 1.0:
            return best
        for k, w_free in enumerate(depth_free(i, j, tdist[key])):
            best = min(best, max(1.0, normal_error(i, j, key, w_free) * 2.0**k / normal_tol))
        return best

    def compatible(i: int, j: int) -> bool:
        return mismatch(i, j) <= 1.0

    if len(pairs):
        # Best-fitting pairs first: by template error when there is a template, else by distance.
        dist = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
        if tdist:
            key = np.array([mismatch(i, j) for i, j in pairs.tolist()])
            # Pairs the template places (distance and normals) before those it does not (a
            # learned template's hidden codes: with no distance known, a pair within the span
            # scores 0, as if it fitted perfectly).
            placed = np.isin(code, list(template.positions_mm) if template is not None else [])
            unplaced = ~(placed[pairs[:, 0]] & placed[pairs[:, 1]])
            order = np.lexsort((dist, key, unplaced))
            pairs = pairs[order][key[order] <= 1.0]
        else:
            pairs = pairs[np.argsort(dist, kind="stable")]
    group = list(range(len(idx)))
    members: dict[int, list[int]] = {k: [k] for k in range(len(idx))}
    for i, j in pairs.tolist():
        gi, gj = group[i], group[j]
        if gi == gj:
            continue
        a, b = members[gi], members[gj]
        if set(code[a].tolist()) & set(code[b].tolist()):
            continue
        if not all(compatible(x, y) for x in a for y in b):
            continue
        for k in b:
            group[k] = gi
        members[gi] = a + b
        del members[gj]
    out = [sorted(idx[k] for k in m) for m in members.values()]
    return sorted(out, key=lambda g: g[0])


def unit_normals(poses: Sequence[FiducialPose]) -> NDArray[np.float64] | None:
    """Unit normals of the poses as ``(k, 3)``, or None when any is unusable."""
    if not poses:
        return None
    n = np.array([np.asarray(p.normal, dtype=np.float64).reshape(-1) for p in poses])
    if n.shape[1] != 3:
        return None
    length = np.linalg.norm(n, axis=1)
    if not np.all(np.isfinite(length)) or np.any(length < 0.5):
        return None
    return np.asarray(n / length[:, None], dtype=np.float64)


def mirror_normals(
    positions_mm: NDArray[np.float64], normals: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The other branch of each circle pose's two-fold normal ambiguity.

    A single circle seen in perspective has two poses (:mod:`pose_estimator.conic_pose`) whose
    normals share the slant to the viewing ray and differ in the sign of the tilt: to first order
    (weak perspective) the second normal is the first mirrored about the line of sight,
    ``2 (n . v) v - n`` with ``v`` the unit vector from the fiducial to the camera. The pose
    estimator picks one branch, and on small or nearly fronto-parallel images it picks the wrong
    one for a sizeable fraction of fiducials (about 30 % end to end in ``matcher_field``, where
    this mirror lands within 1.5 deg of the truth for 95 % of them), so geometric checks on
    normals must accept either branch.

    Parameters
    ----------
    positions_mm : (k, 3) ndarray
        Fiducial centres, camera frame (the camera at the origin).
    normals : (k, 3) ndarray
        Unit normals as estimated.

    Returns
    -------
    (k, 3) ndarray
        The mirrored unit normals.
    """
    p = np.asarray(positions_mm, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    v = -p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
    return np.asarray(2.0 * np.einsum("ki,ki->k", n, v)[:, None] * v - n, dtype=np.float64)


def branch_fit(
    local: NDArray[np.float64],
    seen: NDArray[np.float64],
    w: NDArray[np.float64],
    n_local: NDArray[np.float64],
    n_seen: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Rigid fit ``seen ~ R local + t`` choosing each fiducial's normal branch.

    The measured normals are kept when every one of them fits within 30 deg; otherwise every
    combination of measured and mirrored normals (:func:`mirror_normals`) is fitted and the one
    whose worst normal then agrees best with the rotated model wins (a mirror is a second
    chance, not a free choice: with a stranger in the group it could make a wrong fit look
    right). Returns ``R``, ``t`` and the chosen normals.
    """
    R, t, worst = _fit_with_normals(local, seen, w, n_local, n_seen)
    if worst >= np.cos(np.radians(30.0)):
        return R, t, n_seen
    alt = mirror_normals(seen, n_seen)
    best: tuple[float, NDArray, NDArray, NDArray] | None = None
    k = len(seen)
    # Units carry a handful of fiducials: 2^k fits stay cheap (capped for safety).
    flips = itertools.product((False, True), repeat=k) if k <= 6 else iter([(False,) * k])
    for flip in flips:
        n = np.where(np.asarray(flip)[:, None], alt, n_seen)
        R, t, worst = _fit_with_normals(local, seen, w, n_local, n)
        if best is None or worst > best[0]:
            best = (worst, R, t, n)
    assert best is not None
    return best[1], best[2], best[3]


def _fit_with_normals(
    local: NDArray[np.float64],
    seen: NDArray[np.float64],
    w: NDArray[np.float64],
    n_local: NDArray[np.float64],
    n_seen: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Rigid fit ``seen ~ R local + t`` with the normals ``n_seen`` (:func:`.rigid.rigid_fit`):
    ``R``, ``t`` and the worst face's cosine between its normal and the rotated model's."""
    R, t = rigid_fit(local, seen, w, n_local, n_seen)
    return R, t, float(np.min(np.einsum("ki,ki->k", n_local @ R.T, n_seen)))


def _fit_weights(poses: Sequence[FiducialPose]) -> NDArray[np.float64]:
    """Each pose's weight in a template fit: the inverse of its mean position variance."""
    return np.array([1.0 / max(float(np.trace(p.covariance_mm2)) / 3.0, 1e-6) for p in poses])


def _placed_faces(
    poses: Sequence[FiducialPose], template: UnitSpec
) -> tuple[NDArray[np.float64], ...] | None:
    """``(local, n_local, seen, w)``: the template's positions and normals of the poses' codes,
    the poses' positions and their fit weights (:func:`_fit_weights`); None where the template
    does not place every code with its normal."""
    codes = [int(p.code) for p in poses]
    if not all(c in template.positions_mm and c in template.normals for c in codes):
        return None
    local = np.array([template.positions_mm[c] for c in codes], dtype=np.float64)
    n_local = np.array([template.normals[c] for c in codes], dtype=np.float64)
    seen = np.array([p.position_mm for p in poses], dtype=np.float64)
    return local, n_local, seen, _fit_weights(poses)


def _template_branches(
    poses: Sequence[FiducialPose], normals: NDArray[np.float64], template: UnitSpec | None
) -> NDArray[np.float64] | None:
    """The poses' normals on the branches that fit the template, or None when it cannot tell.

    Needs >= 3 poses whose codes have template positions and normals (with two, four branch
    combinations can make a stranger fit), and a fit whose every normal then lies within 30 deg
    of the rotated template's and whose points lie within 5 mm RMS.
    """
    if template is None or len(poses) < 3:
        return None
    placed = _placed_faces(poses, template)
    if placed is None:
        return None
    local, n_local, seen, w = placed
    R, t, n_used = branch_fit(local, seen, w, n_local, normals)
    if np.any(np.einsum("ki,ki->k", n_local @ R.T, n_used) < np.cos(np.radians(30.0))):
        return None
    # The points must fit too (as in template_pose): a stranger among them makes any branch
    # choice meaningless.
    if rms_misfit(R, t, local, seen) > 5.0:
        return None
    return n_used


def _pair_normals(
    before: Sequence[FiducialPose], after: Sequence[FiducialPose], template: UnitSpec | None
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None]:
    """Normals of a unit's matched fiducials before and after, each on its likely branch.

    Each side's branches are chosen by the template when it can tell
    (:func:`_template_branches`); otherwise, per pair, the branches with the smallest turn
    between before and after (a wrong branch shows as a spurious turn of about twice the slant).
    ``(None, None)`` when a normal is unusable.
    """
    nb, na = unit_normals(before), unit_normals(after)
    if nb is None or na is None:
        return None, None
    rb = _template_branches(before, nb, template)
    ra = _template_branches(after, na, template)
    if rb is not None and ra is not None:
        return rb, ra
    pb = np.array([p.position_mm for p in before], dtype=np.float64)
    pa = np.array([p.position_mm for p in after], dtype=np.float64)
    cand_b = (rb,) if rb is not None else (nb, mirror_normals(pb, nb))
    cand_a = (ra,) if ra is not None else (na, mirror_normals(pa, na))
    return _closest_branches(cand_b, cand_a, np.eye(3))


def _closest_branches(
    cand_b: Sequence[NDArray[np.float64]],
    cand_a: Sequence[NDArray[np.float64]],
    rotation: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per pair, the candidate normals before and after that ``rotation`` carries nearest into
    each other (the first such combination on a tie)."""
    best = np.full(len(cand_b[0]), -np.inf)
    out_b, out_a = cand_b[0].copy(), cand_a[0].copy()
    for xb, xa in itertools.product(cand_b, cand_a):
        dot = np.einsum("ki,ki->k", xb @ rotation.T, xa)
        better = dot > best
        best = np.where(better, dot, best)
        out_b[better], out_a[better] = xb[better], xa[better]
    return out_b, out_a


def _joint_branches(
    before: NDArray[np.float64],
    after: NDArray[np.float64],
    w: NDArray[np.float64],
    nb: NDArray[np.float64],
    na: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pairs' branches chosen together where too few points fix the rotation.

    Per pair the smallest turn is as likely on both mirrors as on both true normals (a pair
    whose two normals are both mirrored turns about as little). Two pairs chosen apart can then
    fit no one rotation, and the unit's second pair is dropped, its motion resting on one; or
    both sit on their mirrors, which fit one rotation as well as the truth does (mirroring is a
    half turn about the line of sight) but the wrong one, off by about the unit's turn, which
    two points do not fix about the line joining them: the translation at the unit's origin is
    then off by millimetres. So each pair's two normals are flipped to their mirrors together,
    in every combination, and of those whose normals fit one rigid motion (within 15 deg) the
    one whose motion carries the points best is kept (the choice apart on a tie, as for a unit
    that did not turn; it stands where none fits).
    """
    k = len(before)
    if k < 2 or k > 6:
        return nb, na
    lim = np.cos(np.radians(15.0))
    alt_b, alt_a = mirror_normals(before, nb), mirror_normals(after, na)
    best: tuple[float, NDArray[np.float64], NDArray[np.float64]] | None = None
    for flip in itertools.product((False, True), repeat=k):
        f = np.asarray(flip)[:, None]
        xb, xa = np.where(f, alt_b, nb), np.where(f, alt_a, na)
        R, t = rigid_fit(before, after, w, xb, xa)
        if np.min(np.einsum("ki,ki->k", xb @ R.T, xa)) < lim:
            continue
        misfit = rms_misfit(R, t, before, after)
        if best is None or misfit < best[0]:
            best = (misfit, xb, xa)
    return (best[1], best[2]) if best is not None else (nb, na)


def _branches_by_points(
    before: NDArray[np.float64],
    after: NDArray[np.float64],
    sigma: NDArray[np.float64],
    nb: NDArray[np.float64],
    na: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each pair's normal branches re-chosen by the rotation its points alone fix.

    Three or more matched points not on a line fix the unit's rotation without normals. The
    smallest-turn choice of :func:`_pair_normals` picks the wrong branches of a unit that turned
    far (a 30 deg rock: each mirror lies a couple of degrees nearer than the truth), and the
    wrong normals then reverse the fitted turn. Where the points fit one rigid motion (RMS
    within 1 mm), each pair takes the branches that motion carries into each other; otherwise
    (a stranger among them) the choice stands; with too few or collinear points they are
    chosen together by :func:`_joint_branches`.
    """
    k = len(before)
    w = 1.0 / np.maximum(np.sum(sigma**2, axis=1), 1e-6)
    if k < 3 or np.linalg.matrix_rank(before - before.mean(axis=0), 1e-6) < 2:
        return _joint_branches(before, after, w, nb, na)
    R, t = rigid_fit(before, after, w)
    if rms_misfit(R, t, before, after) > 1.0:
        return nb, na
    return _closest_branches((nb, mirror_normals(before, nb)), (na, mirror_normals(after, na)), R)


def template_pose(
    poses: Sequence[FiducialPose], template: UnitSpec
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Where the unit is: ``(R, t)`` with ``position = R @ template position + t`` (camera frame),
    from the template fitted to its fiducials.

    Needs template positions for >= 3 of them, or >= 2 with normals on both sides; None when
    the fit is impossible or poor (RMS above 5 mm, or a normal more than 30 deg off: a grouping
    mistake or a pose on the wrong ambiguity branch).
    """
    sel = [p for p in poses if int(p.code) in template.positions_mm]
    if len(sel) < 2:
        return None
    local = np.array([template.positions_mm[int(p.code)] for p in sel])
    seen = np.array([p.position_mm for p in sel], dtype=np.float64)
    n_seen = unit_normals(sel)
    has_tn = all(int(p.code) in template.normals for p in sel)
    w = _fit_weights(sel)
    if n_seen is not None and has_tn:
        n_local = np.array([template.normals[int(p.code)] for p in sel])
        # Each pose's normal may be on the wrong branch of the circle's two-fold ambiguity: the
        # branches that fit the template best are used; a normal still far off means a grouping
        # mistake, and then the template cannot be trusted to locate the unit.
        R, t, n_used = branch_fit(local, seen, w, n_local, n_seen)
        if np.any(np.einsum("ki,ki->k", n_local @ R.T, n_used) < np.cos(np.radians(30.0))):
            return None
    elif len(sel) >= 3:
        R, t = rigid_fit(local, seen, w)
    else:
        return None
    if rms_misfit(R, t, local, seen) > 5.0:
        return None
    return np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)


def _centre_of(
    name: str,
    ix: list[int],
    base: tuple[FiducialPose, ...],
    unit_map: UnitMap | None,
    cache: dict[str, NDArray[np.float64] | None] | None,
) -> NDArray[np.float64] | None:
    """The unit's origin located by its template, or by its own positions in an explicit map
    (cached by unit id when a cache is given): its motion is reported there."""
    if unit_map is None or not ix:
        return None
    spec = unit_map.template
    if spec is None:
        spec = next((u for u in unit_map.units if u.unit == name and u.positions_mm), None)
    if spec is None:
        return None
    if cache is not None and name in cache:
        return cache[name]
    fit = template_pose([base[i] for i in ix], spec)
    centre = None if fit is None else fit[1]
    if cache is not None:
        cache[name] = centre
    return centre


def _turn(a: FiducialPose, b: FiducialPose) -> float:
    """Angle between two poses' normals, radians (NaN when either is unusable)."""
    na = np.asarray(a.normal, dtype=np.float64).reshape(-1)
    nb = np.asarray(b.normal, dtype=np.float64).reshape(-1)
    la, lb = float(np.linalg.norm(na)), float(np.linalg.norm(nb))
    if na.size != 3 or nb.size != 3 or not (la > 0 and lb > 0) or not np.isfinite(la * lb):
        return float("nan")
    return float(np.arccos(np.clip(na @ nb / (la * lb), -1.0, 1.0)))


def _rotation_deg(R: NDArray[np.float64]) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def units_of(
    poses: Sequence[FiducialPose],
    span_mm: float,
    template: UnitSpec | None,
    tol_mm: float,
    pair_distances: Mapping[tuple[int, int], float] | None = None,
) -> list[list[int]]:
    """Units of one state (:func:`group_fiducials` on its finite poses), as indices of ``poses``."""
    ok = [j for j, p in enumerate(poses) if np.all(np.isfinite(p.position_mm))]
    found = group_fiducials(
        [poses[j] for j in ok],
        span_mm=span_mm,
        template=template,
        tol_mm=tol_mm,
        pair_distances=pair_distances,
    )
    return [[ok[k] for k in g] for g in found]


def assign_units(
    result: MatchResult,
    *,
    unit_map: UnitMap | None = None,
    span_mm: float | None = None,
    rigid_tol_mm: float = DEFAULT_RIGID_TOL_MM,
    pair_distances: Mapping[tuple[int, int], float] | None = None,
) -> tuple[list[tuple[str, list[int]]], list[int]]:
    """Units over the baseline: ``[(unit id, baseline indices)]`` and the unassigned indices.

    From ``unit_map.units`` (a baseline fiducial belongs to the unit listing its code; mapped units
    with no fiducial seen get an empty list), or grouped automatically (:func:`group_fiducials`,
    with the template when given; without template positions, with ``pair_distances``, learned
    from the baseline by :func:`learn_pair_distances` when not given).
    """
    base = result.baseline
    span = span_mm if span_mm is not None else (unit_map.span_mm if unit_map else DEFAULT_SPAN_MM)
    if not span > 0:
        raise MatcherError(f"span_mm must be positive, got {span}")
    rejected_b = {r.index for r in result.rejected if r.side == "baseline"}
    usable_b = [i for i in range(len(base)) if i not in rejected_b]
    unassigned: list[int] = []
    if unit_map is not None and unit_map.units:
        owner = {c: s.unit for s in unit_map.units for c in s.codes}
        by_unit: dict[str, list[int]] = {s.unit: [] for s in unit_map.units}
        for i in usable_b:
            u = owner.get(int(base[i].code))
            if u is None:
                unassigned.append(i)
            else:
                by_unit[u].append(i)
        return list(by_unit.items()), unassigned
    template = unit_map.template if unit_map is not None else None
    sub = [base[i] for i in usable_b]
    if pair_distances is None and not places_every_code(template):
        pair_distances = learn_pair_distances(sub, span)
    found = group_fiducials(
        sub, span_mm=span, template=template, tol_mm=rigid_tol_mm, pair_distances=pair_distances
    )
    grouped = {usable_b[k] for g in found for k in g}
    unassigned = [i for i in usable_b if i not in grouped]
    return [(f"U{n + 1:04d}", [usable_b[k] for k in g]) for n, g in enumerate(found)], unassigned


def unit_motions(
    result: MatchResult,
    *,
    unit_map: UnitMap | None = None,
    span_mm: float | None = None,
    rigid_tol_mm: float = DEFAULT_RIGID_TOL_MM,
    overturn_deg: float = DEFAULT_OVERTURN_DEG,
    groups: tuple[list[tuple[str, list[int]]], list[int]] | None = None,
    centres: dict[str, NDArray[np.float64] | None] | None = None,
    in_place: dict[int, int] | None = None,
    cur_groups: Sequence[list[int]] | None = None,
) -> tuple[tuple[UnitMotion, ...], tuple[int, ...]]:
    """Per-unit rigid motion from a fiducial matching.

    Units come from :func:`assign_units` (or ``groups``, its earlier result). ``centres`` caches
    each unit's template-located origin across calls on the same baseline (filled in here).
    Appeared current fiducials are attached to the nearest unit that already has current fiducials
    (or lost all of them) when their code is free on it and its face does not point away from one
    the unit shows, within the unit span. A face pointing away from faces a unit showed before (with
    template normals) is evidence that the unit turned over: such faces go one to one, within the
    matching gate, to units that lost all their old faces (:func:`_overturn_evidence`; a unit that
    matched nothing is not held by a face seen in place that the matching gave another baseline face
    of its code). With template positions, a unit that matched nothing is found again where a
    current unit none of whose faces matched, or matched only on weak evidence, fits it
    (:func:`_relocated`; method ``template``); a face so taken leaves the unit whose pair held it. A
    unit measured through one pair that moved, whose faces fit the template before and now, is
    measured by the template's two poses (:func:`_located_motion`); one whose faces fit it only
    before, at the origin the template places, turned as its face's normal turned
    (:func:`_centred_motion`). ``in_place``: :func:`still_in_place` of the result's baseline and
    current poses, and ``cur_groups``: the current state's units (:func:`group_fiducials` on the
    current poses, current indices), where the caller has them (computed here otherwise).

    Returns
    -------
    units : tuple of UnitMotion
        One per unit seen in the baseline, plus, for an explicit map, ``unseen`` entries for mapped
        units none of whose codes was seen.
    unassigned : tuple of int
        Baseline indices of usable fiducials that belong to no unit (code not in the map).
    """
    base, cur = result.baseline, result.current
    span = span_mm if span_mm is not None else (unit_map.span_mm if unit_map else DEFAULT_SPAN_MM)
    if groups is None:
        groups = assign_units(result, unit_map=unit_map, span_mm=span, rigid_tol_mm=rigid_tol_mm)
    unit_list, unassigned = groups

    unit_of_b = {i: n for n, (_, ix) in enumerate(unit_list) for i in ix}
    pairs_of: dict[int, list[int]] = {n: [] for n in range(len(unit_list))}  # entry indices
    cur_of: dict[int, list[int]] = {n: [] for n in range(len(unit_list))}
    vanished_of = dict.fromkeys(range(len(unit_list)), 0)
    for k, d in enumerate(result.displacements):
        if d.baseline_index is None or d.baseline_index not in unit_of_b:
            continue
        n = unit_of_b[d.baseline_index]
        if d.is_match:
            pairs_of[n].append(k)
            assert d.current_index is not None
            cur_of[n].append(d.current_index)
        else:
            vanished_of[n] += 1

    # Appeared fiducials: attach to a unit whose current fiducials (or, failing that, baseline
    # position) are within the span and which does not already show that code.
    template = unit_map.template if unit_map is not None else None
    normals = template.normals if template is not None else {}
    appeared_of = dict.fromkeys(range(len(unit_list)), 0)
    owner_codes = None
    if unit_map is not None and unit_map.units:
        owner_codes = {c: n for n, s in enumerate(unit_map.units) for c in s.codes}
    has_same = {
        n
        for n, ks in pairs_of.items()
        if any(result.displacements[k].label == "same_code" for k in ks)
    }
    appeared = result.by_label("appeared")
    taken: set[int] = set()
    if owner_codes is None and template is not None and normals:
        # A lone pair reading as a turn-over that another unit which lost every face would read
        # the same way, nearly as near, measures neither: its face is left to no one.
        for n in _ambiguous_overturns(result, unit_list, pairs_of, has_same, template):
            (k,) = pairs_of[n]
            j = result.displacements[k].current_index
            assert j is not None
            pairs_of[n].remove(k)
            cur_of[n].remove(j)
            vanished_of[n] += 1
            taken.add(j)
    # Faces still seen in place, for both unit-level rules below (found once).
    shown: dict[int, int] = {}
    if owner_codes is None and template is not None and (normals or template.positions_mm):
        shown = still_in_place(base, cur) if in_place is None else in_place
    if owner_codes is None and template is not None and (normals or template.hidden):
        # Faces opposite to those a unit showed first: they can only be an overturned unit's.
        # A face seen in place holds a unit that matched nothing only if it is not another
        # face's same-code partner: a neighbour's face come to rest where the unit's was is
        # the neighbour's (30 dolos-field seeds: a unit turned over in place held so, 1 of 1).
        partner = {
            d.current_index: d.baseline_index
            for d in result.displacements
            if d.label == "same_code"
        }
        held = {
            i: j
            for i, j in shown.items()
            if i not in unit_of_b or partner.get(j, i) == i or pairs_of[unit_of_b[i]]
        }
        for d, n in _overturn_evidence(
            appeared,
            unit_list,
            base,
            cur,
            cur_of,
            has_same,
            template,
            result.params.gate_mm,
            held,
        ):
            cur_of[n].append(d.current_index)
            appeared_of[n] += 1
            taken.add(d.current_index)
    relocated: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    if owner_codes is None and template is not None and template.positions_mm:
        if cur_groups is None:
            cur_groups = units_of(cur, span, template, rigid_tol_mm)
        evidence = {n for n in cur_of if appeared_of[n]}
        loose = _loosely_held(result, unit_list, pairs_of, has_same, shown, taken)
        for n, faces, R, t in _relocated(
            [d for d in appeared if d.current_index not in taken],
            loose,
            unit_list,
            base,
            cur,
            pairs_of,
            has_same,
            cur_groups,
            template,
            # The old face's motion: the unit's (at most the matching gate) and its turn about
            # its origin (a face is about half a span from it).
            result.params.gate_mm + 0.5 * span,
            evidence,
            shown,
        ):
            for j in faces:
                if j in loose:
                    # Taken from the unit its pair gave it to: that unit's fiducial is unmatched.
                    m, k = loose[j]
                    pairs_of[m].remove(k)
                    cur_of[m].remove(j)
                    vanished_of[m] += 1
            cur_of[n].extend(faces)
            appeared_of[n] += len(faces)
            taken.update(faces)
            relocated[n] = (R, t)
    for d in appeared:
        assert d.current_index is not None and d.after_mm is not None
        if d.current_index in taken:
            continue
        code = int(d.code_after or 0)
        if owner_codes is not None:
            n_own = owner_codes.get(code)
            if n_own is not None:
                cur_of[n_own].append(d.current_index)
                appeared_of[n_own] += 1
            continue
        if template is not None and code not in template.codes:
            continue
        best, best_d = None, span
        for n, (_, ix) in enumerate(unit_list):
            codes_now = {int(cur[j].code) for j in cur_of[n]}
            if code in codes_now or opposed_faces(template, code, codes_now):
                # A rigid unit cannot show a face and the one opposite it at once.
                continue
            if not cur_of[n] and opposed_faces(template, code, {int(base[i].code) for i in ix}):
                # Turned over: only as the evidence above weighed it.
                continue
            ref = [cur[j].position_mm for j in cur_of[n]] or [base[i].position_mm for i in ix]
            if not ref:
                continue
            dist = float(np.min(np.linalg.norm(np.asarray(ref) - d.after_mm, axis=1)))
            if dist < best_d:
                best, best_d = n, dist
        if best is not None:
            cur_of[best].append(d.current_index)
            appeared_of[best] += 1

    out: list[UnitMotion] = []
    for n, (name, ix) in enumerate(unit_list):
        if n in relocated:
            assert template is not None
            n_cross = sum(result.displacements[k].label == "cross_code" for k in pairs_of[n])
            out.append(
                _relocated_motion(
                    name,
                    ix,
                    tuple(cur_of[n]),
                    vanished_of[n],
                    appeared_of[n],
                    n_cross,
                    base,
                    relocated[n],
                    template,
                )
            )
            continue
        before_codes = {int(base[i].code) for i in ix}
        new_codes = tuple(sorted({int(cur[j].code) for j in cur_of[n]} - before_codes))
        out.append(
            _motion_of_unit(
                name,
                ix,
                [result.displacements[k] for k in pairs_of[n]],
                tuple(cur_of[n]),
                vanished_of[n],
                appeared_of[n],
                base,
                cur,
                rigid_tol_mm,
                overturn_deg,
                new_codes,
                _centre_of(name, ix, base, unit_map, centres),
                template,
            )
        )
    return tuple(out), tuple(unassigned)


def seen_in_place(
    point: NDArray[np.float64] | Any,
    where: NDArray[np.float64] | Any,
    within_mm: float = STILL_SHOWN_MM,
) -> bool:
    """Whether ``point`` lies within ``within_mm`` of ``where`` across the line of sight
    through ``where`` (what one image measures precisely; depth aside)."""
    w = np.asarray(where, dtype=np.float64)
    off = across_line_of_sight(np.asarray(point, dtype=np.float64) - w, w)
    return bool(np.linalg.norm(off) <= within_mm)


def fits_template(poses: Sequence[FiducialPose], template: UnitSpec) -> bool:
    """Whether the poses are one unit's faces: the template fitted to them
    (:func:`template_pose`) places every one within :data:`STILL_SHOWN_MM` of its measured
    position across the line of sight, where one image measures precisely (the fit's own
    5 mm RMS bound would let two faces misfit by 10 mm: too loose to call a fiducial a
    neighbour's face)."""
    return close_template_pose(poses, template) is not None


def close_template_pose(
    poses: Sequence[FiducialPose], template: UnitSpec
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """:func:`template_pose` where it places every pose as :func:`fits_template` asks, else
    None."""
    fit = template_pose(poses, template)
    if fit is None:
        return None
    R, t = fit
    for p in poses:
        if int(p.code) not in template.positions_mm:
            return None
        at = R @ np.asarray(template.positions_mm[int(p.code)], dtype=np.float64) + t
        if not seen_in_place(at, p.position_mm):
            return None
    return fit


def still_in_place(
    baseline: Sequence[FiducialPose], current: Sequence[FiducialPose]
) -> dict[int, int]:
    """Baseline fiducials whose face is still seen where it was: baseline index -> the current
    fiducial of the same code within :data:`STILL_SHOWN_MM` of it across the line of sight
    (where one image measures precisely; the nearest such), whatever the matching paired.

    Depth is left aside (a partly covered fiducial's may be centimetres off) except where both
    poses claim it precisely (:func:`precise_depth`): a face more than
    :data:`APART_IN_DEPTH_MM` nearer or farther is then another unit's, come to rest in front of
    the place or uncovered behind it. Nor is a face that turned more than
    :data:`MAX_FACE_TURN_DEG` (its printed frames, :func:`least_turn`): a face seen again in
    place turns by its reading's error (a tenth of a degree; 29 deg at most, partly covered, on
    the 30 dolos fields), a neighbour's face there by its own glue spin (57-156 deg)."""
    bpos = np.array([p.position_mm for p in baseline], dtype=np.float64).reshape(-1, 3)
    cpos = np.array([p.position_mm for p in current], dtype=np.float64).reshape(-1, 3)
    sure = precise_depth([*baseline, *current])
    bsure, csure = sure[: len(baseline)], sure[len(baseline) :]
    bcode = np.array([int(p.code) for p in baseline], dtype=np.int64)
    ccode = np.array([int(p.code) for p in current], dtype=np.int64)
    out: dict[int, int] = {}
    for code in np.intersect1d(bcode, ccode).tolist():
        bi, cj = np.flatnonzero(bcode == code), np.flatnonzero(ccode == code)
        ray = bpos[bi] / np.maximum(np.linalg.norm(bpos[bi], axis=1), 1e-12)[:, None]
        v = cpos[cj][None, :, :] - bpos[bi][:, None, :]
        along = np.einsum("bcd,bd->bc", v, ray)
        with np.errstate(invalid="ignore"):
            lateral = np.linalg.norm(v - along[..., None] * ray[:, None, :], axis=2)
            apart = bsure[bi][:, None] & csure[cj][None, :] & (np.abs(along) > APART_IN_DEPTH_MM)
            lateral = np.where(np.isfinite(lateral) & ~apart, lateral, np.inf)
        for k in np.flatnonzero(np.min(lateral, axis=1) <= STILL_SHOWN_MM).tolist():
            near = np.flatnonzero(lateral[k] <= STILL_SHOWN_MM)
            for c in near[np.argsort(lateral[k, near], kind="stable")].tolist():
                turn = least_turn(baseline[int(bi[k])], current[int(cj[c])])
                if turn is None or turn <= MAX_FACE_TURN_DEG:
                    out[int(bi[k])] = int(cj[c])
                    break
    return out


def precise_depth(poses: Sequence[FiducialPose]) -> NDArray[np.bool_]:
    """Per pose, whether its claimed sd along its line of sight is at most
    :data:`PRECISE_DEPTH_RATIO` times the median of ``poses`` (NaN: not precise)."""
    if not poses:
        return np.zeros(0, dtype=bool)
    pos = np.array([p.position_mm for p in poses], dtype=np.float64)
    cov = np.array([p.covariance_mm2 for p in poses], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = pos / np.linalg.norm(pos, axis=1)[:, None]
        sd = np.sqrt(np.einsum("ni,nij,nj->n", ray, cov, ray))
    finite = np.isfinite(sd)
    if not finite.any():
        return finite
    return finite & (sd <= PRECISE_DEPTH_RATIO * float(np.median(sd[finite])))


def opposed_faces(template: UnitSpec | None, code: int, others: Any) -> bool:
    """Whether the template face of ``code`` points away from that of any code in ``others``:
    by their normals, or a face the template lists as hidden against one with a normal."""
    if template is None:
        return False
    normals, hidden = template.normals, template.hidden
    if code in hidden:
        return any(b in normals and b not in hidden for b in others)
    if code not in normals:
        return False
    return any(
        b in hidden or (b in normals and float(normals[code] @ normals[b]) < OPPOSED_DOT)
        for b in others
    )


#: A rival lost unit at most this many times the nearer unit's distance from a face opposite
#: to both reads that turn-over as well (:func:`_ambiguous_overturns`).
AMBIGUOUS_OVERTURN_RATIO = 1.2


def _ambiguous_overturns(
    result: MatchResult,
    unit_list: Sequence[tuple[str, list[int]]],
    pairs_of: Mapping[int, list[int]],
    has_same: set[int],
    template: UnitSpec,
) -> list[int]:
    """Units whose only evidence is one cross-code pair reading as a turn-over (its current
    face's template normal opposite the unit's old faces) that another unit which lost every
    face, at least as many as this one showed, would read the same way from at most
    :data:`AMBIGUOUS_OVERTURN_RATIO` times the pair's distance.

    Two neighbours each seen through one face before, neither of them after, and one face
    opposite to both now shown between them: one of them turned over, the other is hidden
    behind it, and the matching's cost cannot tell which (30 dolos-field seeds: a still unit
    counted overturned at 21.6 mm, the unit that turned over 22.7 mm away). A damage count
    should not rest on that: neither unit is measured by the face.
    """
    base, cur = result.baseline, result.current
    # Where a face it hid may show now (as _relocated looks: the gate and half a unit).
    reach_mm = result.params.gate_mm + 0.5 * template_span(template)
    lost = [m for m, ks in pairs_of.items() if not ks and unit_list[m][1]]
    alone = np.array(
        [e.current_index for e in result.by_label("appeared") if e.current_index is not None]
    )
    out: list[int] = []
    for n, ks in pairs_of.items():
        if len(ks) != 1 or n in has_same:
            continue
        d = result.displacements[ks[0]]
        if d.label != "cross_code" or d.code_after is None or d.after_mm is None:
            continue
        code = int(d.code_after)
        if not opposed_faces(template, code, {int(base[i].code) for i in unit_list[n][1]}):
            continue
        reach = AMBIGUOUS_OVERTURN_RATIO * float(d.distance_mm or 0.0)
        for m in lost:
            ix = unit_list[m][1]
            if len(ix) < len(unit_list[n][1]):
                continue  # it lost fewer faces: weaker evidence of a turn
            if not opposed_faces(template, code, {int(base[i].code) for i in ix}):
                continue
            pos = np.array([base[i].position_mm for i in ix], dtype=np.float64)
            if float(np.min(np.linalg.norm(pos - d.after_mm, axis=1))) > reach:
                continue
            # A unit showing now, where it was, a face it hid then (one matched to nothing) did
            # not turn over.
            if not _shown_in_place([base[i] for i in ix], cur, alone, template, reach_mm):
                out.append(n)
                break
    return out


def _shown_in_place(
    faces: Sequence[FiducialPose],
    cur: tuple[FiducialPose, ...],
    alone: NDArray[np.intp],
    template: UnitSpec,
    reach_mm: float,
) -> set[int]:
    """The appeared fiducials among ``alone`` (current indices) within ``reach_mm`` of
    ``faces`` that a unit which lost every face it showed (``faces``) hid before and shows now,
    where it was (:func:`faces_shown_in_place`). A still unit whose one seen face is hidden
    after the run (covered, or a neighbour moved in front) often shows another then; it is not
    a unit that moved far (:func:`_relocated`) nor one that turned over
    (:func:`_ambiguous_overturns`)."""
    if alone.size == 0:
        return set()
    old = np.array([f.position_mm for f in faces], dtype=np.float64)
    now = np.array([cur[j].position_mm for j in alone.tolist()], dtype=np.float64)
    near = np.min(np.linalg.norm(now[:, None, :] - old[None, :, :], axis=2), axis=1)
    return set(faces_shown_in_place(faces, cur, alone[near <= reach_mm].tolist(), template))


def _overturn_evidence(
    appeared: Sequence[Any],
    unit_list: Sequence[tuple[str, list[int]]],
    base: tuple[FiducialPose, ...],
    cur: tuple[FiducialPose, ...],
    cur_of: Mapping[int, list[int]],
    has_same: set[int],
    template: UnitSpec,
    gate_mm: float,
    shown: Mapping[int, int],
) -> list[tuple[Any, int]]:
    """Appeared faces opposite to those a unit showed, given one to one to the units they fit.

    A face now seen whose template normal points away from the faces a unit showed before can only
    be that unit's if it turned over, and the unit must then show none of its old faces (no
    same-code match), nor a face that contradicts it, nor one of that code already. A unit that
    turned over also moved, often beyond the grouping span, so the candidates are all such units
    within the matching gate, and each face and each unit is used once: a minimum-cost assignment on
    the distance from the unit's baseline fiducials (several nearby units may have lost their faces,
    an overturned one among them; the nearest fit wins as a whole, not greedily).

    Returns
    -------
    list of (Displacement, int)
        Appeared entries with the index (into ``unit_list``) of the unit each joins.
    """
    faces = set(template.normals) | template.hidden
    rows = [d for d in appeared if d.code_after is not None and int(d.code_after) in faces]
    if not rows:
        return []
    lone_cross = {j for n, js in cur_of.items() if n not in has_same and len(js) == 1 for j in js}
    # A unit still showing an old face where it was (``shown``, :func:`still_in_place`) did not
    # turn over, whatever that face was matched to.
    cols = [
        n
        for n, (_, ix) in enumerate(unit_list)
        if ix and n not in has_same and not any(i in shown for i in ix)
    ]
    if not cols:
        return []
    big = 10.0 * gate_mm
    cost = np.full((len(rows), len(cols)), big)
    for r, d in enumerate(rows):
        code = int(d.code_after)
        for c, n in enumerate(cols):
            ix = unit_list[n][1]
            # A lone cross-code partner is no evidence of what the unit shows (mostly a
            # stranger, see _motion_of_unit): it does not rule the face out.
            now = {int(cur[j].code) for j in cur_of[n] if j not in lone_cross}
            if opposed_faces(template, code, now):
                continue
            if any(int(cur[j].code) == code for j in cur_of[n]):
                # One face per code: a unit whose pair (even a lone cross-code one) shows this
                # code already holds no second face of it.
                continue
            if not opposed_faces(template, code, {int(base[i].code) for i in ix}):
                continue
            pos = np.array([base[i].position_mm for i in ix], dtype=np.float64)
            dist = float(np.min(np.linalg.norm(pos - d.after_mm, axis=1)))
            if dist < gate_mm:
                cost[r, c] = dist
    # A face two units could have turned to, nearly as near each, goes to neither (see
    # _ambiguous_overturns): a unit showing now, where it was, another face it hid then did
    # not turn over, and is no rival.
    alone = np.array([d.current_index for d in appeared if d.current_index is not None])
    reach_mm = gate_mm + 0.5 * template_span(template)
    shows: dict[int, set[int]] = {}
    for r, d in enumerate(rows):
        finite = np.flatnonzero(cost[r] < big)
        if finite.size < 2:
            continue
        rivals = []
        for c in finite.tolist():
            if c not in shows:
                shows[c] = _shown_in_place(
                    [base[i] for i in unit_list[cols[c]][1]], cur, alone, template, reach_mm
                )
            if shows[c] <= {d.current_index}:
                rivals.append((float(cost[r, c]), len(unit_list[cols[c]][1])))
        if len(rivals) > 1:
            (nearest, its_faces), *others = sorted(rivals)
            # A rival as near that lost at least as many faces reads the turn-over as well.
            if any(
                dist <= AMBIGUOUS_OVERTURN_RATIO * nearest and n_faces >= its_faces
                for dist, n_faces in others
            ):
                cost[r] = big
    ri, ci = linear_sum_assignment(cost)
    return [(rows[r], cols[c]) for r, c in zip(ri, ci, strict=True) if cost[r, c] < big]


def _loosely_held(
    result: MatchResult,
    unit_list: Sequence[tuple[str, list[int]]],
    pairs_of: Mapping[int, list[int]],
    has_same: set[int],
    shown: Mapping[int, int],
    taken: set[int],
) -> dict[int, tuple[int, int]]:
    """Matched current fiducials that their pair's unit holds on weak evidence, for
    :func:`_relocated`: current index -> (unit, entry index of the pair).

    A pair that moved while another face of its unit is still seen where it was contradicts
    that face: a still unit's face hidden now has taken a mover's face of its code come to rest
    in front of it (30 dolos-field seeds: 6 of 15 movers reported lost). A unit's one
    cross-code pair does not measure it either (the rule for the lost units themselves).
    """
    loose: dict[int, tuple[int, int]] = {}
    for n, ks in pairs_of.items():
        ix = unit_list[n][1]
        lone_cross = len(ks) == 1 and n not in has_same
        for k in ks:
            d = result.displacements[k]
            i, j = d.baseline_index, d.current_index
            if i is None or j is None or j in taken or shown.get(i) == j:
                continue
            if lone_cross or any(p in shown for p in ix if p != i):
                loose[j] = (n, k)
    return loose


def _relocated(
    appeared: Sequence[Any],
    loose: Mapping[int, tuple[int, int]],
    unit_list: Sequence[tuple[str, list[int]]],
    base: tuple[FiducialPose, ...],
    cur: tuple[FiducialPose, ...],
    pairs_of: Mapping[int, list[int]],
    has_same: set[int],
    cur_groups: Sequence[list[int]],
    template: UnitSpec,
    limit_mm: float,
    skip_units: set[int],
    shown: Mapping[int, int],
) -> list[tuple[int, list[int], NDArray[np.float64], NDArray[np.float64]]]:
    """Lost units found again as a whole: current units none of whose faces was matched, or
    matched only ``loose``-ly (:func:`_loosely_held`).

    A unit that moved far often shows none of the faces it showed before (one or two, the rest
    hidden by its neighbours or turned away) and so matches nothing, while faces it did not show
    before now appear together where it went. Fiducial by fiducial there is no evidence; as a
    unit there is: the template fitted to those faces (:func:`template_pose`) says where each of
    the lost unit's old faces now is. Candidates are current units (``cur_groups``) of two or
    more faces, each appeared or only loosely held (:func:`_loosely_held`), that the template
    fits, and baseline units with no
    same-code match, at most one cross-code one (which alone does not measure a unit) and no
    face still seen in place; the cost of a pair is the mean distance from the unit's old faces
    to where the fitted template puts them now, below ``limit_mm``, and the assignment is one to
    one at minimum total cost (several lost units may share a neighbourhood). A unit that shows
    now, where it was, a face it hid before (:func:`_shown_in_place`) is not a candidate.

    Returns
    -------
    list of (int, list of int, (3, 3) ndarray, (3,) ndarray)
        The unit (index into ``unit_list``), the current faces it now shows, and the template's
        pose there (``R``, ``t``: camera frame position of a template point ``R @ p + t``).
    """
    free = {int(d.current_index) for d in appeared if d.current_index is not None}
    found: list[tuple[list[int], NDArray[np.float64], NDArray[np.float64]]] = []
    for g in cur_groups:
        if len(g) < 2 or not all(j in free or j in loose for j in g):
            continue
        fit = template_pose([cur[j] for j in g], template)
        if fit is not None:
            found.append((list(g), fit[0], fit[1]))
    if not found:
        return []
    # Appeared fiducials seen with no other face of their unit now (a face of a group may be a
    # mover's come nearer along the line of sight, which one image barely measures).
    alone = np.array(
        sorted(free - {j for g in cur_groups if len(g) >= 2 for j in g}), dtype=np.intp
    )
    rows = []
    for n, (_, ix) in enumerate(unit_list):
        if not ix or n in skip_units or n in has_same or len(pairs_of[n]) > 1:
            continue
        if any(i in shown for i in ix):
            continue
        if not all(int(base[i].code) in template.positions_mm for i in ix):
            continue
        if _shown_in_place([base[i] for i in ix], cur, alone, template, limit_mm):
            continue
        rows.append(n)
    if not rows:
        return []
    big = 10.0 * limit_mm
    cost = np.full((len(rows), len(found)), big)
    for r, n in enumerate(rows):
        ix = unit_list[n][1]
        old = np.array([base[i].position_mm for i in ix], dtype=np.float64)
        local = np.array([template.positions_mm[int(base[i].code)] for i in ix])
        placed = template_pose([base[i] for i in ix], template)
        for c, (g, R, t) in enumerate(found):
            d = float(np.mean(np.linalg.norm(local @ R.T + t - old, axis=1)))
            turn = None if placed is None else R @ placed[0].T
            if d < limit_mm and _faces_turned_alike(ix, g, base, cur, turn):
                cost[r, c] = d
    ri, ci = linear_sum_assignment(cost)
    return [
        (rows[r], found[c][0], found[c][1], found[c][2])
        for r, c in zip(ri.tolist(), ci.tolist(), strict=True)
        if cost[r, c] < big
    ]


def _faces_turned_alike(
    ix: Sequence[int],
    group: Sequence[int],
    base: tuple[FiducialPose, ...],
    cur: tuple[FiducialPose, ...],
    turn: NDArray[np.float64] | None,
) -> bool:
    """Whether a lost unit's baseline faces ``ix`` and a current group's faces of the same codes
    (the same fiducials, if the group is the unit) turned as the unit would have: each such
    face's own turn (:func:`face_turn`, its printed frames on some branch of each pose) no more
    than :data:`MAX_FACE_TURN_DEG` (a face seen in both states, as for a lone pair) and, where
    the template fitted in both states says how the unit turned (``turn``), within
    :data:`FACE_TURN_AGREEMENT_DEG` of that. Faces without printed axes say nothing."""
    for i in ix:
        for j in group:
            if int(cur[j].code) != int(base[i].code):
                continue
            turned = face_turn(base[i], cur[j])
            if turned is None:
                continue
            if float(np.min(turned[1])) > MAX_FACE_TURN_DEG:
                return False
            # Some branch combination's turn must be the unit's.
            if (
                turn is not None
                and min(_rotation_deg(T @ turn.T) for T in turned[0].reshape(-1, 3, 3))
                > FACE_TURN_AGREEMENT_DEG
            ):
                return False
    return True


def faces_shown_in_place(
    faces: Sequence[FiducialPose],
    cur: Sequence[FiducialPose],
    candidates: Iterable[int],
    template: UnitSpec,
) -> Iterator[int]:
    """The current fiducials among ``candidates``, in their order, that a unit showing
    ``faces`` before hid then and shows now where it was: of a template code the unit did not
    show, fitting the template together with its faces (:func:`fits_template`)."""
    codes = {int(f.code) for f in faces}
    for j in candidates:
        p = cur[j]
        code = int(p.code)
        if code in codes or code not in template.positions_mm:
            continue
        if fits_template([*faces, p], template):
            yield j


def _relocated_motion(
    name: str,
    ix: list[int],
    current_indices: tuple[int, ...],
    n_vanished: int,
    n_appeared: int,
    n_cross: int,
    base: tuple[FiducialPose, ...],
    pose_now: tuple[NDArray[np.float64], NDArray[np.float64]],
    template: UnitSpec,
) -> UnitMotion:
    """Motion of a unit found again by :func:`_relocated` (method ``template``).

    With the template also fitted to its baseline faces the motion is the rigid one between the
    two template poses, at the unit's origin; otherwise (one old face) it is the displacement of
    that face's point, with the rotation unknown.
    """
    codes = tuple(int(base[i].code) for i in ix)
    R_now, t_now = pose_now
    before = np.array([base[i].position_mm for i in ix], dtype=np.float64)
    fit = template_pose([base[i] for i in ix], template)
    if fit is not None:
        R_b, t_b = fit
        rotation = R_now @ R_b.T
        ref = np.asarray(t_b, dtype=np.float64)
        trans = np.asarray(t_now - t_b, dtype=np.float64)
        rot_deg: float | None = _rotation_deg(rotation)
    else:
        rotation = np.eye(3)
        ref = before.mean(axis=0)
        local = np.array([template.positions_mm[c] for c in codes])
        trans = np.mean(local @ R_now.T + t_now - before, axis=0)
        rot_deg = None
    return UnitMotion(
        name,
        codes,
        tuple(ix),
        current_indices,
        0,
        "template",
        rotation,
        trans,
        rot_deg,
        ref,
        0.0,
        False,
        n_vanished,
        n_appeared,
        n_cross,
    )


def _motion_of_unit(
    name: str,
    ix: list[int],
    pairs: list[Any],
    current_indices: tuple[int, ...],
    n_vanished: int,
    n_appeared: int,
    base: tuple[FiducialPose, ...],
    cur: tuple[FiducialPose, ...],
    rigid_tol_mm: float,
    overturn_deg: float,
    new_codes: tuple[int, ...] = (),
    centre: NDArray[np.float64] | None = None,
    template: UnitSpec | None = None,
) -> UnitMotion:
    """Motion of one unit from its matched fiducials (see :func:`unit_motions`).

    ``new_codes`` are the codes it shows now that it did not show before (appeared or cross-code
    partners); ``template`` gives the face normals and hidden faces.
    """
    codes = tuple(int(base[i].code) for i in ix)
    nan3 = np.full(3, np.nan)
    ref_all = np.mean([base[i].position_mm for i in ix], axis=0).astype(np.float64) if ix else nan3
    n_cross = sum(d.label == "cross_code" for d in pairs)
    same = [d for d in pairs if d.label == "same_code"]
    use = same if same else [d for d in pairs if d.label == "cross_code"]
    # Fiducials seen before now face away and other faces show instead: turned over. (A unit
    # with any same-code match still shows a face it showed before.) With the template's normals
    # a face now shown must point against one that vanished; without them one vanished face is
    # too little evidence.
    turned_over = bool(ix) and not same and bool(new_codes)
    normals = template.normals if template is not None else {}
    if turned_over and template is not None and normals:
        old_codes = [c for c in codes if c in normals]
        # A face the template knows nothing of (neither normal nor hidden: a learned template
        # knows only the faces the baseline showed) is weighed as without normals. A code that
        # is not the template's at all is no face of the unit: a misread, or a stranger's tag
        # (30 dolos fields: a still unit's hidden face read as code 6 turned it over).
        known = set(normals) | template.hidden
        turned_over = any(opposed_faces(template, a, old_codes) for a in new_codes) or (
            len(ix) >= 2 and any(a not in known and a in template.codes for a in new_codes)
        )
    elif turned_over:
        turned_over = len(ix) >= 2
    if len(use) == 1 and not same and not turned_over:
        # One cross-code match and nothing else: the only evidence of where the unit went is a
        # pairing of two different codes, which end to end is mostly a stranger picked up where
        # the unit's own fiducial is hidden (the paper's red vectors are the unreliable ones).
        # Its motion is not measured: the unit is lost, not displaced.
        use = []
    if not ix:
        status = "unseen"
        return UnitMotion(
            name,
            codes,
            (),
            current_indices,
            0,
            "none",
            np.eye(3),
            nan3,
            None,
            nan3,
            0.0,
            False,
            0,
            n_appeared,
            0,
            status,
        )
    if not use:
        return UnitMotion(
            name,
            codes,
            tuple(ix),
            current_indices,
            0,
            "none",
            np.eye(3),
            nan3,
            None,
            ref_all,
            0.0,
            turned_over,
            n_vanished,
            n_appeared,
            n_cross,
            "lost",
        )
    before = np.array([d.before_mm for d in use], dtype=np.float64)
    after = np.array([d.after_mm for d in use], dtype=np.float64)
    sig = np.array([d.sigma_mm for d in use], dtype=np.float64).reshape(-1, 3)
    var = np.sum(sig**2, axis=1) / 3.0
    # Normals on their likely branches of the two-fold ambiguity (a wrong branch would fake a
    # turn of twice the slant, and pull the rotation with it).
    nb_all, na_all = _pair_normals(
        [base[d.baseline_index] for d in use], [cur[d.current_index] for d in use], template
    )
    if nb_all is not None and na_all is not None:
        nb_all, na_all = _branches_by_points(before, after, sig, nb_all, na_all)
    if nb_all is not None and na_all is not None:
        turn = np.arccos(np.clip(np.einsum("ki,ki->k", nb_all, na_all), -1.0, 1.0))
    else:
        turn = np.array([_turn(base[d.baseline_index], cur[d.current_index]) for d in use])
    keep = (
        consistent_subset(before, after, sig, turn, rigid_tol_mm, nb_all, na_all)
        if same
        else list(range(len(use)))
    )
    before, after, var = before[keep], after[keep], var[keep]
    w = 1.0 / np.maximum(var, 1e-6)
    nb = nb_all[keep] if nb_all is not None else None
    na = na_all[keep] if na_all is not None else None
    with_normals = bool(same) and nb is not None and na is not None
    rigid_ok = len(keep) >= 3 and np.linalg.matrix_rank(before - before.mean(axis=0), 1e-6) >= 2
    # The faces' own turns, where every kept same-code pair's poses carry printed axes: a
    # tenth of a degree each, where two or three faces' positions and normals fix the turn to a
    # few degrees (30 e2e fields: a 0.93 Dn mover seen through two faces fitted 24.3 deg, its
    # faces' frames 21.2, the truth 21.1; its distance then 1.4 mm long).
    frames_turn = None
    if same and nb is not None and na is not None:
        frames_turn = turn_from_frames(
            [base[use[k].baseline_index] for k in keep],
            [cur[use[k].current_index] for k in keep],
            nb,
            na,
            template,
        )
    if (len(keep) >= 2 and with_normals) or rigid_ok:
        if frames_turn is not None:
            R = frames_turn
            t = np.average(after - before @ R.T, axis=0, weights=w)
        elif with_normals:
            R, t = rigid_fit(before, after, w, nb, na)
        else:
            R, t = rigid_fit(before, after, w)
        resid = rms_misfit(R, t, before, after)
        ref = centre if centre is not None else ref_all
        trans = R @ ref + t - ref
        rot_deg: float | None = _rotation_deg(R)
        method = "rigid"
    else:
        R = np.eye(3)
        ref = np.average(before, axis=0, weights=w)
        trans = np.average(after - before, axis=0, weights=w)
        resid, rot_deg, method = 0.0, None, "translation"
        located = (
            _located_motion(ix, current_indices, before, after, base, cur, template, overturn_deg)
            if len(same) == 1
            else None
        )
        if located is not None:
            # One pair measures the motion of its face, which a unit's turn carries several
            # millimetres away from the unit's own: the template fitted in both states measures
            # the unit's (30 end-to-end fields: 24 such units, the median error of their
            # displacement 3.3 -> 0.6 mm).
            R, t = located
            ref = centre if centre is not None else ref_all
            trans = R @ ref + t - ref
            resid = rms_misfit(R, t, before, after)
            rot_deg = _rotation_deg(R)
            method = "rigid"
        elif len(same) == 1:
            centred = _centred_motion(ix, current_indices, same[0], base, cur, template)
            if centred is not None:
                # One pair measures its face's motion; the unit's origin, 18 mm behind the face
                # of a dolos, turns with the unit: where the template places the origin in one
                # state and the face's normal turns it, the unit's own motion is measured there
                # (30 end-to-end fields: moved one-pair units' distance error, median absolute
                # deviation 1.1-1.9 -> 0.75-1.0 mm).
                R, ref, trans = centred
                rot_deg = _rotation_deg(R)
    overturned = turned_over or (rot_deg is not None and rot_deg >= overturn_deg)
    return UnitMotion(
        name,
        codes,
        tuple(ix),
        current_indices,
        len(keep),
        method,  # type: ignore[arg-type]
        R,
        np.asarray(trans, dtype=np.float64),
        rot_deg,
        np.asarray(ref, dtype=np.float64),
        resid,
        bool(overturned),
        n_vanished,
        n_appeared,
        n_cross,
    )


#: A fiducial seen in both states turned at most this far (deg; the least turn over the two
#: poses' branches of the circle's ambiguity, from their printed frames, :func:`face_turn`)
#: where its own face is all the evidence of its unit's motion: a lone same-code pair
#: (:func:`displacement_matcher.refine.match_units`) or a lost unit found again through a face of
#: its code (:func:`_relocated`). The dolos fields' movers turn up to 30 deg (their true pairs
#: 31.6 deg at most, end to end); of the same-code strangers within the gate 70 % turn further
#: than 45 deg: a neighbour's face lies as the neighbour does, not as the unit.
MAX_FACE_TURN_DEG = 45.0
#: Where the template says how a lost unit found again turned, its shared faces' own turns must
#: agree with it within this angle (deg; :func:`_relocated`): the poses' reading (a few tenths
#: of a degree) and the template fits' rotations (a few degrees from two or three faces'
#: normals).
FACE_TURN_AGREEMENT_DEG = 20.0
#: Pairs whose faces' own turns differ by more than this (deg) do not give their unit's rotation
#: from their frames (:func:`turn_from_frames`): readings agree to a degree or so.
FRAME_TURN_TOL_DEG = 5.0
#: Two pairs whose faces' own turns (:func:`face_turn`, on the branches that bring them closest)
#: differ by more than this (deg) are not faces of one body (:func:`one_body`): a fiducial is
#: glued at its own spin, so a stranger's face turns by the two glue spins' difference. On the
#: 30 dolos fields the 6,810 units matched right agree within 2.7 deg in 99 % (16 deg at most, a
#: partly covered face); units made of strangers' pairs lie 49-152 deg apart.
FRAMES_APART_DEG = 30.0
#: :func:`turn_from_frames` chooses among the branch combinations of up to this many pairs
#: (4 ** n) by the template.
JOINT_BRANCHES_MAX = 5
#: Poses whose branches (:func:`branch_normals`, :func:`branch_frames`) are kept: a dolos
#: field's two states (about 1,400 poses) with room to spare. The cache holds the poses
#: themselves (about 1.5 kB each with their detections), so a long-running matcher keeps at
#: most about 6 MB of old ones.
BRANCH_CACHE_SIZE = 4096
#: :func:`one_body` searches every subset of up to this many pairs.
ONE_BODY_EXHAUSTIVE = 10
#: A unit's one pair must have moved this far (mm) before the template located in both states
#: measures the unit's motion (:func:`_located_motion`): a still unit's pair measures it better
#: than two template fits, each through two faces' normals.
LOCATED_MIN_MOVE_MM = STILL_SHOWN_MM
#: ... and the template's motion must carry the pair's face onto its partner within this
#: distance (mm) across the line of sight ...
LOCATED_PAIR_TOL_MM = 0.5
#: ... and turn the unit less than this (deg): a unit showing a face it showed before, turned
#: further, is more likely a still unit whose hidden face took a mover's (the dolos fields' movers
#: turn up to 30 deg; one still unit, seed 9, came out turned 74 deg and displaced).
LOCATED_MAX_TURN_DEG = 45.0


#: The two branches of a face's normal now must turn it by angles this far apart (deg) for the
#: nearer to say how it turned (:func:`_centred_motion`).
CENTRED_BRANCH_MARGIN_DEG = 10.0


def _centred_motion(
    ix: Sequence[int],
    current_indices: Sequence[int],
    pair: Any,
    base: tuple[FiducialPose, ...],
    cur: tuple[FiducialPose, ...],
    template: UnitSpec | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None:
    """``(R, origin, translation)`` of a unit measured through one same-code pair, at the unit's
    origin: the template fitted to its faces in one state (two or more, :func:`fits_template`;
    the baseline's first) places the origin there, and the turn of the pair's face carries it to
    the other state: the face's full turn where both poses carry their printed axes
    (:func:`face_turn`; each pose on the branch whose normal is nearer the template's normal
    there, where the face lies), else the smallest rotation between the template's normal of
    the face and the face's measured normal in the other state, on the nearer branch, the spin
    about the normal, not seen, taken as none. None where the face
    moved less than :data:`LOCATED_MIN_MOVE_MM` across the line of sight (a still unit's depth
    outlier stays measured at its face, where only its lateral motion is confirmed), the faces
    fit in neither state, the two branches of the measured normal turn it within
    :data:`CENTRED_BRANCH_MARGIN_DEG` of each other (which way it turned is not told; with
    printed axes only where the two branches' turns also differ by more than
    :data:`FRAME_TURN_TOL_DEG`: a face seen square on has both branches alike), or the normal
    turned :data:`LOCATED_MAX_TURN_DEG` or more.
    """
    if template is None:
        return None
    code = int(base[pair.baseline_index].code)
    if code not in template.positions_mm or code not in template.normals:
        return None
    before = np.asarray(pair.before_mm, dtype=np.float64)
    after = np.asarray(pair.after_mm, dtype=np.float64)
    lateral = across_line_of_sight(after - before, before)
    if float(np.linalg.norm(lateral)) < LOCATED_MIN_MOVE_MM:
        return None
    local = np.asarray(template.normals[code], dtype=np.float64)
    fit = close_template_pose([base[i] for i in ix], template) if len(ix) >= 2 else None
    placed_before = fit is not None
    if fit is None and len(current_indices) >= 2:
        fit = close_template_pose([cur[j] for j in current_indices], template)
    if fit is None:
        return None
    placed = fit[0] @ local
    # Placed before, the measured normal now is where the face turned to; placed now, the
    # measured normal before is where it turned from.
    seen = cur[pair.current_index] if placed_before else base[pair.baseline_index]
    if unit_normals([seen]) is None:
        return None
    branches = branch_normals(seen)
    turns = np.degrees(np.arccos(np.clip(branches @ placed, -1.0, 1.0)))
    if float(np.min(turns)) >= LOCATED_MAX_TURN_DEG:
        return None
    ks = int(np.argmin(turns))
    nearer = branches[ks]
    # The face's own frames, where both poses carry axes: in the placed state on the branch
    # the template's normal picks, in the other on the nearer one (as chosen above).
    at_fit = base[pair.baseline_index] if placed_before else cur[pair.current_index]
    turned = face_turn(at_fit, seen) if placed_before else face_turn(seen, at_fit)
    if turned is not None:
        kp = int(np.argmax(branch_normals(at_fit) @ placed))
        # turned[0][k_before][k_after]: the rotation taking the frame before to the frame now.
        options = [turned[0][kp][k] if placed_before else turned[0][k][kp] for k in (0, 1)]
        R = options[ks]
        tied = abs(float(turns[0] - turns[1])) < CENTRED_BRANCH_MARGIN_DEG
        if tied and _rotation_deg(options[0] @ options[1].T) > FRAME_TURN_TOL_DEG:
            return None  # which way the face turned is not told: each branch as near
    elif abs(float(turns[0] - turns[1])) < CENTRED_BRANCH_MARGIN_DEG:
        return None  # which way the face turned is not told: each branch as near
    elif placed_before:
        R = _smallest_rotation(placed, nearer)
    else:
        R = _smallest_rotation(nearer, placed)
    # Placed now, the origin before is where the turn back from the face puts the origin now.
    origin = fit[1] if placed_before else before + R.T @ (fit[1] - after)
    return R, origin, after + R @ (origin - before) - origin


# A matching asks for the same poses' branches thousands of times (every pass, every rule):
# they are kept per pose (poses are immutable and hash by identity), read-only.
@functools.lru_cache(maxsize=BRANCH_CACHE_SIZE)
def branch_normals(pose: FiducialPose) -> NDArray[np.float64]:
    """``(2, 3)``: the pose's unit normal and its mirror about the line of sight
    (:func:`mirror_normals`), the two branches of the circle's ambiguity (read-only)."""
    n = np.asarray(pose.normal, dtype=np.float64).reshape(1, 3)
    n = n / np.linalg.norm(n)
    p = np.asarray(pose.position_mm, dtype=np.float64).reshape(1, 3)
    out = np.vstack([n, mirror_normals(p, n)])
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=BRANCH_CACHE_SIZE)
def branch_frames(pose: FiducialPose) -> NDArray[np.float64] | None:
    """``(2, 3, 3)``: the pose's printed frame (:attr:`FiducialPose.frame`) on each branch of
    the circle's ambiguity (the mirrored normal with its axis, :func:`mirror_axes`), or None
    without an axis (read-only)."""
    if pose.axis is None:
        return None
    normals = branch_normals(pose)
    a = np.asarray(pose.axis, dtype=np.float64).reshape(1, 3)
    p = np.asarray(pose.position_mm, dtype=np.float64).reshape(1, 3)
    axes = np.vstack([a / np.linalg.norm(a), mirror_axes(p, a, normals[1:])])
    if not np.isfinite(axes).all():
        return None
    out = target_frames(normals, axes)
    out.flags.writeable = False
    return out


def face_turn(
    before: FiducialPose, after: FiducialPose
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """How one fiducial turned between two states, from its printed frames (normal and axis):
    the rotations ``R[kb][ka] = F_after @ F_before.T`` for each branch ``kb`` of the pose before
    and ``ka`` of the pose after (``(2, 2, 3, 3)``), and their angles in degrees (``(2, 2)``);
    None where a pose has no axis. The true turn is one of the four: on a fiducial's true
    branches the frames give the body's whole rotation, spin about the face included."""
    fb, fa = branch_frames(before), branch_frames(after)
    if fb is None or fa is None:
        return None
    R = np.einsum("aij,bkj->baik", fa, fb)
    cos = (np.trace(R, axis1=2, axis2=3) - 1.0) / 2.0
    return R, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def least_turn(before: FiducialPose, after: FiducialPose) -> float | None:
    """The least of a fiducial's four branch-combination turns (:func:`face_turn`), degrees:
    how little it can have turned, whichever branch each pose lies on; None without axes."""
    turned = face_turn(before, after)
    return None if turned is None else float(np.min(turned[1]))


def _four_turns(
    before: Sequence[FiducialPose], after: Sequence[FiducialPose]
) -> list[NDArray[np.float64] | None]:
    """Each pair's four branch-combination turns (:func:`face_turn`) as ``(4, 3, 3)``, index
    ``2 * (branch before) + (branch after)``; None for a pair without axes."""
    out: list[NDArray[np.float64] | None] = []
    for pb, pa in zip(before, after, strict=True):
        turned = face_turn(pb, pa)
        out.append(None if turned is None else turned[0].reshape(4, 3, 3))
    return out


def _turn_cosines(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(4, 4)``: the cosines of the angles between two pairs' branch-combination turns
    (``trace(A @ B.T) = 1 + 2 cos``)."""
    return np.asarray((np.einsum("kij,lij->kl", a, b) - 1.0) / 2.0, dtype=np.float64)


def frames_apart(
    before: Sequence[FiducialPose], after: Sequence[FiducialPose]
) -> NDArray[np.float64]:
    """How far apart pairs' turns are: ``(n, n)`` angles (deg) between the turns of pairs ``a``
    and ``b`` (``before[a] -> after[a]`` and ``before[b] -> after[b]``, :func:`face_turn`), on
    the branches of their poses that bring them closest. Faces of one body turned as the body
    did and lie a reading's error apart; a pose without an axis is apart from none (0)."""
    turns = _four_turns(before, after)
    n = len(turns)
    apart = np.zeros((n, n))
    for a, b in itertools.combinations(range(n), 2):
        ta, tb = turns[a], turns[b]
        if ta is None or tb is None:
            continue
        # The closest of the two pairs' branch combinations.
        cos = float(np.max(_turn_cosines(ta, tb)))
        apart[a, b] = apart[b, a] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return apart


def one_body(apart: NDArray[np.float64], tol_deg: float = FRAMES_APART_DEG) -> tuple[int, ...]:
    """The largest set of pairs whose turns lie within ``tol_deg`` of each other's
    (``apart`` from :func:`frames_apart`): the faces that can be one body's. Of equal sets the
    one with the least total disagreement; a single pair where none agree. Exhaustive (a unit
    shows a handful of faces)."""
    n = len(apart)
    if n == 0:
        return ()
    fits = apart <= tol_deg
    if n > ONE_BODY_EXHAUSTIVE:
        # Many faces (a unit map's large unit): grown greedily from the best-connected pair.
        order = sorted(range(n), key=lambda a: (-int(fits[a].sum()), float(apart[a].sum())))
        body: list[int] = []
        for a in order:
            if all(fits[a, b] for b in body):
                body.append(a)
        return tuple(sorted(body))
    for size in range(n, 1, -1):
        sets = [
            s
            for s in itertools.combinations(range(n), size)
            if all(fits[a, b] for a, b in itertools.combinations(s, 2))
        ]
        if sets:
            return min(sets, key=lambda s: float(sum(apart[a, b] for a in s for b in s)))
    return (0,)


def turn_from_frames(
    before: Sequence[FiducialPose],
    after: Sequence[FiducialPose],
    normals_before: NDArray[np.float64],
    normals_after: NDArray[np.float64],
    template: UnitSpec | None = None,
) -> NDArray[np.float64] | None:
    """A unit's rotation from its matched fiducials' printed frames: each pair's turn
    (:func:`face_turn`) on the branches whose normals are ``normals_before`` and
    ``normals_after`` (as chosen for the pairs, :func:`_pair_normals`), averaged (the rotation
    nearest their sum, by SVD). None where a pose has no axis, or where the pairs' turns
    disagree by more than :data:`FRAME_TURN_TOL_DEG` (faces of different bodies, or a pose's
    branch chosen wrong: the fit on positions and normals then decides).

    With a ``template`` placing every pair's code, the branches are chosen by it instead: of
    two or more pairs, the faces' frames agree on their true branches and also, always, with
    every pose mirrored (a mirrored unit turns alike too). The positions and normals chosen
    for each state must then fit the template: of the combinations whose turns agree, the one
    whose normals the template fits best in the two states (the worst face's angle, summed) is
    taken. (30 e2e fields, physical blur, 6,782 units matched through two to four pairs: the
    branches chosen from the normals' turns left 21 units more than 5 deg off, 57 at worst and
    a 0.89 Dn mover measured 5.8 mm off; by the template none, the true combination fitting
    within 15 deg and the mirrored ones 27-270 deg off.)
    """
    turns = _four_turns(before, after)
    four = [t for t in turns if t is not None]
    if not turns or len(four) < len(turns):
        return None
    # Branch combination index per pair: 2 * (branch before) + (branch after).
    chosen = tuple(
        2 * int(np.argmax(branch_normals(pb) @ nb)) + int(np.argmax(branch_normals(pa) @ na))
        for pb, pa, nb, na in zip(before, after, normals_before, normals_after, strict=True)
    )
    placed_before = placed_after = None
    if template is not None and 2 <= len(four) <= JOINT_BRANCHES_MAX:
        placed_before, placed_after = (
            _placed_faces(before, template),
            _placed_faces(after, template),
        )
    if placed_before is None or placed_after is None:
        return _agreed_turn([four[k][c] for k, c in enumerate(chosen)])
    placed = (placed_before, placed_after)
    # Turns that agree with the mean within the tolerance lie within twice it of each other:
    # combinations are built pair by pair from those alone.
    cos_limit = np.cos(np.radians(2.0 * FRAME_TURN_TOL_DEG))
    near = {
        (a, b): _turn_cosines(four[a], four[b]) >= cos_limit
        for a, b in itertools.combinations(range(len(four)), 2)
    }
    combos: list[tuple[int, ...]] = [(c,) for c in range(4)]
    for b in range(1, len(four)):
        combos = [
            (*combo, c)
            for combo in combos
            for c in range(4)
            if all(near[(a, b)][combo[a], c] for a in range(b))
        ]
    misfit_of: dict[tuple[int, tuple[int, ...]], float] = {}

    def misfit(state: int, branches: tuple[int, ...]) -> float:
        # Each state's fit depends on its own branches only.
        if (state, branches) not in misfit_of:
            poses = before if state == 0 else after
            normals = np.array([branch_normals(p)[k] for p, k in zip(poses, branches, strict=True)])
            local, n_local, seen, w = placed[state]
            _, _, worst = _fit_with_normals(local, seen, w, n_local, normals)
            misfit_of[(state, branches)] = float(np.degrees(np.arccos(np.clip(worst, -1.0, 1.0))))
        return misfit_of[(state, branches)]

    agreed = [
        (combo, R)
        for combo in combos
        if (R := _agreed_turn([four[k][c] for k, c in enumerate(combo)])) is not None
    ]
    if not agreed:
        return None
    first = next((R for combo, R in agreed if combo == chosen), agreed[0][1])
    if all(_rotation_deg(R @ first.T) <= FRAME_TURN_TOL_DEG for _, R in agreed):
        # The branches barely differ (faces nearly square to the camera): any will do.
        return first
    best, best_misfit = first, np.inf
    for combo, R in agreed:
        total = misfit(0, tuple(c // 2 for c in combo)) + misfit(1, tuple(c % 2 for c in combo))
        if total < best_misfit:
            best, best_misfit = R, total
    return best


def _agreed_turn(turns: Sequence[NDArray[np.float64]]) -> NDArray[np.float64] | None:
    """The rotation nearest the sum of ``turns`` (by SVD), or None where one of them is more
    than :data:`FRAME_TURN_TOL_DEG` from it."""
    U, _, Vt = np.linalg.svd(np.sum(turns, axis=0))
    R = U @ np.diag([1.0, 1.0, float(np.linalg.det(U @ Vt))]) @ Vt
    if max(_rotation_deg(T @ R.T) for T in turns) > FRAME_TURN_TOL_DEG:
        return None
    return np.asarray(R, dtype=np.float64)


def _smallest_rotation(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation turning unit vector ``a`` onto unit vector ``b`` about their common normal
    (Rodrigues' formula; ``b`` not opposite to ``a``)."""
    v = np.cross(a, b)
    c = float(a @ b)
    if float(np.linalg.norm(v)) < 1e-12:
        return np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.asarray(np.eye(3) + vx + vx @ vx / (1.0 + c), dtype=np.float64)


def _located_motion(
    ix: Sequence[int],
    current_indices: Sequence[int],
    before: NDArray[np.float64],
    after: NDArray[np.float64],
    base: tuple[FiducialPose, ...],
    cur: tuple[FiducialPose, ...],
    template: UnitSpec | None,
    overturn_deg: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The rigid motion ``(R, t)`` (``after = R @ before + t``) of a unit measured through one
    same-code pair (``before``, ``after``: (1, 3)) whose faces, two or more in each state, fit
    the template (:func:`fits_template`) both before and now: the template's pose now composed
    with the inverse of its pose before. None where the pair barely moved
    (:data:`LOCATED_MIN_MOVE_MM`), the template's motion misses the pair
    (:data:`LOCATED_PAIR_TOL_MM`) or turns it by :data:`LOCATED_MAX_TURN_DEG` or more (or
    ``overturn_deg``: a unit that still shows a face it showed is not turned over)."""
    if template is None or not template.positions_mm or len(ix) < 2 or len(current_indices) < 2:
        return None
    if float(np.linalg.norm(after[0] - before[0])) < LOCATED_MIN_MOVE_MM:
        return None
    fit_before = close_template_pose([base[i] for i in ix], template)
    fit_now = close_template_pose([cur[j] for j in current_indices], template)
    if fit_before is None or fit_now is None:
        return None
    R = fit_now[0] @ fit_before[0].T
    t = fit_now[1] - R @ fit_before[1]
    miss = across_line_of_sight(R @ before[0] + t - after[0], after[0])
    if float(np.linalg.norm(miss)) > LOCATED_PAIR_TOL_MM:
        return None
    if _rotation_deg(R) >= min(LOCATED_MAX_TURN_DEG, overturn_deg):
        return None
    return R, t
