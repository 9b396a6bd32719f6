"""Synthetic armour fields: dolosse on a breakwater slope, before and after a wave run.

Each unit carries the same set of coded fiducials (the paper's section 5 set-up: every dolos bears
the same four codes), glued at fixed positions and normals on the unit, each at its own spin about
its normal (by hand: a code does not sit the same way on two units). Units lie on a 1:1.5 slope
seen obliquely by the paper's camera (3008x2000, 7.8 um pixels, 45 mm lens). A wave run then moves
some units (up to 2 Dn, mostly down-slope, with a rotation), overturns a few, and fiducials are
hidden at random in each state. Everything comes with exact ground truth: which fiducial is which,
each unit's rigid motion, and which fiducials the camera can observe: a rendered fiducial whose
printed disc is even partly covered in the image by a nearer fiducial's patch (its white paper
disc, painted over it by the renderer) is *occluded*, so not observable in that state.

Frames: the camera frame of :mod:`pose_estimator` (x right, y down, z forward, mm). A unit's local
frame has its origin at the unit's centre; the unit rotation maps local to camera coordinates.
The field gives :class:`armourcam.render.Target` lists for the one renderer and
:class:`pose_estimator.FiducialPose` lists (exact, or with simulated estimation noise) for the
matcher.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from armourcam.render import MARGIN, Target
from displacement_matcher.units import UnitMap, UnitSpec
from pose_estimator.camera import CameraModel
from pose_estimator.types import FiducialPose

PIXEL_PITCH_MM = 0.0078
LENS_MM = 45.0


def field_camera() -> CameraModel:
    """The paper's camera: 3008x2000 pixels of 7.8 um behind a 45 mm lens (f = 5769 px)."""
    return CameraModel.ideal(3008, 2000, LENS_MM / PIXEL_PITCH_MM)


@dataclass(frozen=True, slots=True, eq=False)
class UnitGeometry:
    """Where the fiducials sit on one unit (unit-local frame, mm).

    Attributes
    ----------
    codes : tuple of int
        Code of each fiducial slot (the same on every unit).
    positions_mm : (K, 3) ndarray
        Fiducial centres on the unit.
    normals : (K, 3) ndarray
        Unit normals of the printed faces.
    dn_mm : float
        Nominal unit size Dn (cube root of the unit's volume), mm.
    """

    codes: tuple[int, ...]
    positions_mm: NDArray[np.float64]
    normals: NDArray[np.float64]
    dn_mm: float

    def unit_map(self, span_mm: float | None = None) -> UnitMap:
        """This layout as the matcher's template (every unit carries it; no named units).

        ``span_mm`` (the grouping span) defaults to the largest distance between two of the
        unit's fiducials plus 5 mm.
        """
        spec = UnitSpec(
            "template",
            self.codes,
            {c: self.positions_mm[k] for k, c in enumerate(self.codes)},
            {c: self.normals[k] for k, c in enumerate(self.codes)},
        )
        if span_mm is None:
            gaps = self.positions_mm[:, None] - self.positions_mm[None]
            span_mm = float(np.max(np.linalg.norm(gaps, axis=2))) + 5.0
        return UnitMap((), spec, span_mm)


def dolos_geometry(
    height_mm: float = 38.0, codes: tuple[int, ...] = (3, 17, 29, 41)
) -> UnitGeometry:
    """A dolos of overall height ``height_mm`` with a fiducial on each of its four fluke ends.

    The shank runs along local x; the flukes at +x point along +-y, those at -x along +-z. The
    fiducials on the +x flukes lean towards +z, so a unit resting with local +z towards the camera
    shows three fiducials (and one when overturned). Dn ~ 0.54 H (volume ~ 0.16 H^3 for a dolos of
    waist ratio about 0.33).
    """
    s, f = 0.25 * height_mm, 0.4 * height_mm
    pos = np.array([[s, f, 0.0], [s, -f, 0.0], [-s, 0.0, f], [-s, 0.0, -f]])
    nrm = np.array([[0.0, 1.0, 1.0], [0.0, -1.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return UnitGeometry(tuple(int(c) for c in codes), pos, nrm, 0.54 * height_mm)


@dataclass(frozen=True, slots=True, eq=False)
class FieldState:
    """All units and fiducials of a field at one moment.

    Attributes
    ----------
    rotations : (N, 3, 3) ndarray
        Unit-local -> camera rotation of each unit.
    centres_mm : (N, 3) ndarray
        Unit centres, camera frame.
    unit : (M,) ndarray of int
        Unit of each fiducial (``M = N * K``; fiducial ``u * K + k`` is slot ``k`` of unit ``u``).
    code : (M,) ndarray of int
    position_mm, normal : (M, 3) ndarray
        Fiducial centres and face normals, camera frame.
    visible : (M,) ndarray of bool
        Rendered: facing the camera (slant below the limit) and not randomly hidden.
    occluded_fraction : (M,) ndarray of float
        Fraction of the image area of the fiducial's printed disc covered by the paper discs of
        nearer rendered fiducials (the sum over them, capped at 1: an upper bound of the union);
        0 for fiducials that are not rendered.
    diameter_mm : float
        Printed (outer) diameter the occlusion was computed for; :meth:`targets` renders it.
    glue_spin : (M,) ndarray of float
        Angle (radians) each fiducial was glued at about its face's normal, the same in both
        states: a lab glues its targets by hand, so a code does not sit the same way on two
        units (:meth:`frame`).
    """

    rotations: NDArray[np.float64]
    centres_mm: NDArray[np.float64]
    unit: NDArray[np.intp]
    code: NDArray[np.int64]
    position_mm: NDArray[np.float64]
    normal: NDArray[np.float64]
    visible: NDArray[np.bool_]
    occluded_fraction: NDArray[np.float64]
    diameter_mm: float
    glue_spin: NDArray[np.float64]

    def frame(self, i: int) -> NDArray[np.float64]:
        """Printed target frame of fiducial ``i`` in the camera frame (columns: its +x axis,
        +y, and the face's normal), as it was glued (:attr:`glue_spin`)."""
        return _face_rotation(self.normal[i], self.rotations[self.unit[i]], self.glue_spin[i])

    @property
    def visible_ids(self) -> NDArray[np.intp]:
        """Fiducial ids (``u * K + k``) of the rendered fiducials, in order."""
        return np.flatnonzero(self.visible)

    @property
    def occluded(self) -> NDArray[np.bool_]:
        """Rendered fiducials whose printed disc is partly covered by a nearer one's patch."""
        return np.asarray(self.occluded_fraction > 0.0)

    @property
    def observable(self) -> NDArray[np.bool_]:
        """Rendered and not occluded: what a perfect detector would see whole."""
        return np.asarray(self.visible & ~self.occluded)

    @property
    def observable_ids(self) -> NDArray[np.intp]:
        """Fiducial ids of the observable fiducials, in order."""
        return np.flatnonzero(self.observable)

    def targets(self, design: str = "ring", diameter_mm: float | None = None) -> list[Target]:
        """Renderable targets of the visible fiducials (same order as :attr:`visible_ids`).

        ``diameter_mm`` defaults to the state's :attr:`diameter_mm`; another value is refused,
        since the occlusion truth holds only for the diameter it was computed for.
        """
        if diameter_mm is not None and not np.isclose(diameter_mm, self.diameter_mm):
            raise ValueError(
                f"the field's occlusion truth is for {self.diameter_mm} mm fiducials, "
                f"not {diameter_mm} mm: pass diameter_mm={diameter_mm} to make_field"
            )
        out = []
        for i in self.visible_ids.tolist():
            out.append(
                Target(
                    int(self.code[i]),
                    design,
                    self.diameter_mm,
                    self.frame(i),
                    self.position_mm[i].copy(),
                )
            )
        return out

    def poses(
        self,
        rng: np.random.Generator | None = None,
        *,
        sigma_xy_mm: float = 0.1,
        sigma_z_mm: float = 1.0,
        sigma_spin_deg: float = 0.7,
        include_occluded: bool = False,
    ) -> list[FiducialPose]:
        """Fiducial poses of the observable fiducials (order of :attr:`observable_ids`).

        ``include_occluded`` gives every rendered fiducial instead (order of
        :attr:`visible_ids`), as if occlusion did not exist.

        With ``rng`` the positions carry simulated monocular estimation noise: ``sigma_xy_mm``
        across the viewing ray and ``sigma_z_mm`` along it, the latter growing with the slant
        (``/ cos(slant)``, capped at 4x) as in the paper's Figure 4; the covariance says so,
        and each printed axis (``FiducialPose.axis``) is turned about its normal by a normal
        error of ``sigma_spin_deg`` (drawn from a generator spawned from ``rng``, so that the
        positions' draws are those of poses without axes). Without ``rng`` the poses are exact
        (covariance still the model's).
        """
        out = []
        ids = self.visible_ids if include_occluded else self.observable_ids
        spin = (
            np.zeros(len(ids))
            if rng is None
            else np.radians(rng.spawn(1)[0].normal(0.0, sigma_spin_deg, len(ids)))
        )
        for k, i in enumerate(ids.tolist()):
            p = self.position_mm[i]
            ray = p / np.linalg.norm(p)
            cos_slant = float(np.clip(-ray @ self.normal[i], 0.25, 1.0))
            sz = sigma_z_mm / cos_slant
            cov = sigma_xy_mm**2 * np.eye(3) + (sz**2 - sigma_xy_mm**2) * np.outer(ray, ray)
            q = p if rng is None else rng.multivariate_normal(p, cov)
            frame = self.frame(i)
            axis = np.cos(spin[k]) * frame[:, 0] + np.sin(spin[k]) * frame[:, 1]
            out.append(FiducialPose(int(self.code[i]), q, self.normal[i].copy(), cov, axis=axis))
        return out


@dataclass(frozen=True, slots=True, eq=False)
class Field:
    """A synthetic armour field before and after a wave run, with ground truth.

    Attributes
    ----------
    geometry : UnitGeometry
    camera : CameraModel
    before, after : FieldState
    moved, overturned : (N,) ndarray of bool
        Units the run moved (translated and turned) or overturned; the rest are exactly still.
    section_width_mm : float
        Width of the modelled section along the crest.
    """

    geometry: UnitGeometry
    camera: CameraModel
    before: FieldState
    after: FieldState
    moved: NDArray[np.bool_]
    overturned: NDArray[np.bool_]
    section_width_mm: float

    @property
    def n_units(self) -> int:
        """Number of units."""
        return len(self.before.centres_mm)

    def motion(self, unit: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """True rigid motion of a unit: ``(R, t)`` with ``x_after = R @ x_before + t``."""
        R = self.after.rotations[unit] @ self.before.rotations[unit].T
        t = self.after.centres_mm[unit] - R @ self.before.centres_mm[unit]
        return R, t

    def displacement_at(self, unit: int, point_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """True displacement (mm, camera frame) of a point rigidly attached to ``unit``."""
        R, t = self.motion(unit)
        p = np.asarray(point_mm, dtype=np.float64)
        return np.asarray(R @ p + t - p, dtype=np.float64)


def _face_rotation(
    normal: NDArray[np.float64], unit_rot: NDArray[np.float64], spin: float = 0.0
) -> NDArray:
    """A target rotation whose z axis is ``normal``, its in-plane angle tied to the unit and
    turned by ``spin`` (radians) about the normal: how that fiducial was glued."""
    z = normal / np.linalg.norm(normal)
    ref = unit_rot[:, 0] if abs(unit_rot[:, 0] @ z) < 0.9 else unit_rot[:, 1]
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(spin), np.sin(spin)
    return np.column_stack([c * x + s * y, c * y - s * x, z])


def _rot(axis: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    a = np.asarray(axis, dtype=np.float64)
    r, _ = cv2.Rodrigues(a / np.linalg.norm(a) * angle)
    return np.asarray(r, dtype=np.float64)


def _disc_outlines(
    camera: CameraModel,
    position: NDArray[np.float64],
    normal: NDArray[np.float64],
    radius_mm: float,
    n: int = 48,
) -> NDArray[np.float64]:
    """Image outlines (with distortion) of discs of ``radius_mm``: (M, n, 2) pixels, (u, v).

    The inscribed ``n``-gon of each disc's rim, projected point by point: under a pinhole a disc
    images as an ellipse, and the polygon falls short of it by ``1 - cos(pi / n)`` of its radius
    (0.2 % at n = 48, a few hundredths of a pixel here).
    """
    ref = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = np.cross(normal, ref)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(normal, a)
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rim = position[:, None, :] + radius_mm * (
        np.cos(ang)[None, :, None] * a[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :]
    )
    uv = camera.project(rim.reshape(-1, 3))
    return np.asarray(uv, dtype=np.float64).reshape(len(position), n, 2)


def _occlusion(
    camera: CameraModel,
    position: NDArray[np.float64],
    normal: NDArray[np.float64],
    visible: NDArray[np.bool_],
    diameter_mm: float,
) -> NDArray[np.float64]:
    """Fraction of each rendered fiducial's printed disc covered by nearer fiducials' paper.

    Follows the renderer's rule (:func:`armourcam.render.render`): patches are painted farthest
    centre first (a stable sort, so of equal depths the later in id order is on top), each one a
    paper disc of ``MARGIN`` outer radii. Fiducial ``i`` loses the part of its printed disc
    (outer radius) that lies under the paper of every fiducial painted after it; the fraction is
    the sum over those (capped at 1). Areas come from the exact intersection of the two convex
    image outlines.
    """
    out = np.zeros(len(position))
    ids = np.flatnonzero(visible)
    if len(ids) < 2:
        return out
    r = 0.5 * diameter_mm
    printed = _disc_outlines(camera, position[ids], normal[ids], r)
    paper = _disc_outlines(camera, position[ids], normal[ids], MARGIN * r)
    centre = paper.mean(axis=1)
    reach = np.max(np.linalg.norm(paper - centre[:, None, :], axis=2), axis=1)
    # Painting order of the renderer: farthest first, ties in list (id) order.
    order = np.argsort(-position[ids, 2], kind="stable")
    rank = np.empty(len(ids), dtype=np.intp)
    rank[order] = np.arange(len(ids))
    tree = cKDTree(centre)
    for a, b in sorted(tree.query_pairs(2.0 * float(reach.max()))):
        if np.linalg.norm(centre[a] - centre[b]) > reach[a] + reach[b]:
            continue
        under, over = (a, b) if rank[a] < rank[b] else (b, a)
        poly = printed[under].astype(np.float32)
        area, _ = cv2.intersectConvexConvex(poly, paper[over].astype(np.float32))
        if area > 0.0:
            out[ids[under]] += area / cv2.contourArea(poly)
    return np.minimum(out, 1.0)


def _state(
    geometry: UnitGeometry,
    camera: CameraModel,
    rotations: NDArray[np.float64],
    centres: NDArray[np.float64],
    hidden: NDArray[np.bool_],
    max_slant_deg: float,
    diameter_mm: float,
    glue_spin: NDArray[np.float64],
) -> FieldState:
    n, k = len(centres), len(geometry.codes)
    pos = np.einsum("uij,kj->uki", rotations, geometry.positions_mm) + centres[:, None, :]
    nrm = np.einsum("uij,kj->uki", rotations, geometry.normals)
    pos, nrm = pos.reshape(-1, 3), nrm.reshape(-1, 3)
    towards = -pos / np.linalg.norm(pos, axis=1, keepdims=True)
    facing = np.einsum("ki,ki->k", towards, nrm) > np.cos(np.radians(max_slant_deg))
    visible = facing & ~hidden
    return FieldState(
        rotations,
        centres,
        np.repeat(np.arange(n), k),
        np.tile(np.asarray(geometry.codes, dtype=np.int64), n),
        pos,
        nrm,
        visible,
        _occlusion(camera, pos, nrm, visible, diameter_mm),
        float(diameter_mm),
        glue_spin,
    )


def _settle(
    geometry: UnitGeometry,
    rotations: NDArray[np.float64],
    centres: NDArray[np.float64],
    movers: NDArray[np.intp],
    up: NDArray[np.float64],
    min_gap_mm: float,
) -> None:
    """Lift moved units that landed inside others out along the slope normal, in place.

    Two units cannot share space: a unit thrown onto another comes to rest on top of it. A
    moved unit is clear when its centre is at least Dn from every other unit's centre (their
    cores do not overlap) and its fiducials keep the baseline's ``min_gap_mm`` from other units'
    fiducials; until then it rises by 0.1 Dn steps along ``up`` (towards the camera side of the
    slope). Units are settled in id order, each against all others as they then lie, so every
    pair ends clear. Deterministic: the random draws of the field stay the same.
    """
    dn = geometry.dn_mm
    step = 0.1 * dn
    for u in movers.tolist():
        others = np.arange(len(centres)) != u
        for _ in range(60):
            near = others & (np.linalg.norm(centres - centres[u], axis=1) < 2.5 * dn)
            if not near.any():
                break
            fid = centres[u] + geometry.positions_mm @ rotations[u].T
            theirs = (
                np.einsum("uij,kj->uki", rotations[near], geometry.positions_mm)
                + centres[near][:, None, :]
            ).reshape(-1, 3)
            gap = float(np.min(np.linalg.norm(theirs[:, None] - fid[None], axis=2)))
            core = float(np.min(np.linalg.norm(centres[near] - centres[u], axis=1)))
            if gap >= min_gap_mm and core >= dn:
                break
            centres[u] = centres[u] + step * up


def make_field(
    n_units: int = 300,
    *,
    seed: int = 0,
    geometry: UnitGeometry | None = None,
    camera: CameraModel | None = None,
    moved_fraction: float = 0.10,
    max_move_dn: float = 2.0,
    overturned_fraction: float = 0.02,
    hidden_fraction: float = 0.05,
    pitch_dn: float = 1.75,
    slope: float = 1.5,
    view_deg: float = 35.0,
    max_slant_deg: float = 75.0,
    min_gap_mm: float = 9.0,
    diameter_mm: float = 7.1,
    settle: bool = True,
) -> Field:
    """A dolos field on a slope, before and after a simulated wave run.

    Parameters
    ----------
    n_units : int
        Number of units.
    seed : int
        Seed of everything random.
    geometry : UnitGeometry, optional
        Unit and fiducial layout (default :func:`dolos_geometry`).
    camera : CameraModel, optional
        Default :func:`field_camera`; the field is centred in its view and the distance chosen so
        that it fills about 90 % of the image width.
    moved_fraction : float
        Fraction of units moved: translated ``U(0.1, max_move_dn) * Dn`` within +-60 deg of
        down-slope, and turned up to 30 deg about a random axis. A unit that would land inside
        another rests on top of it instead (lifted along the slope normal until clear).
    overturned_fraction : float
        Fraction of units overturned (turned 180 deg about the shank) and shifted
        ``U(0.2, 1.5) Dn``.
    hidden_fraction : float
        Fraction of fiducials hidden (occluded) in each state, independently.
    pitch_dn : float
        Grid pitch of the unit centres, in Dn.
    slope : float
        Slope 1:``slope`` (only sets the drawing's plausibility; the camera sees the slope plane
        at ``view_deg`` from its normal).
    view_deg : float
        Angle between the camera's axis and the slope's normal.
    max_slant_deg : float
        A fiducial is visible when its normal is within this angle of the direction to the camera.
    min_gap_mm : float
        Smallest distance between fiducials of different units in the baseline.
    diameter_mm : float
        Printed outer diameter of the fiducials: with the camera it sets which fiducials occlude
        which in the image (:attr:`FieldState.occluded_fraction`), so render at this diameter.
    settle : bool
        Lift moved units that landed inside others until clear (see ``moved_fraction``); False
        keeps the raw draws, interpenetrating units included (older fields, recorded bags).

    Returns
    -------
    Field
    """
    if n_units < 1:
        raise ValueError(f"n_units must be >= 1, got {n_units}")
    for name, frac in (
        ("moved_fraction", moved_fraction),
        ("overturned_fraction", overturned_fraction),
        ("hidden_fraction", hidden_fraction),
    ):
        if not 0.0 <= frac <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {frac}")
    if not diameter_mm > 0.0:
        raise ValueError(f"diameter_mm must be > 0, got {diameter_mm}")
    if moved_fraction + overturned_fraction > 1.0:
        raise ValueError("moved_fraction + overturned_fraction exceeds 1")
    del slope  # the geometry below depends only on the viewing angle
    geo = geometry if geometry is not None else dolos_geometry()
    cam = camera if camera is not None else field_camera()
    rng = np.random.default_rng(seed)
    dn = geo.dn_mm
    pitch = pitch_dn * dn
    ncol = max(1, int(np.ceil(np.sqrt(n_units * 1.4))))
    nrow = int(np.ceil(n_units / ncol))
    width = ncol * pitch
    # Distance so the field spans ~90 % of the image width.
    z0 = cam.K[0, 0] * (width + 2 * pitch) / (0.9 * cam.width)
    th = np.radians(view_deg)
    n_s = np.array([0.0, -np.sin(th), -np.cos(th)])  # slope normal, towards the camera
    e1 = np.array([1.0, 0.0, 0.0])  # along the crest
    e2 = np.cross(n_s, e1)  # up-slope (towards image top)
    e2 /= np.linalg.norm(e2)
    if e2[1] > 0:
        e2 = -e2
    origin = np.array([0.0, 0.0, z0])
    # Base frame of a unit at rest: local z towards the camera side of the slope.
    base = np.column_stack([e1, np.cross(n_s, e1), n_s])

    rots = np.zeros((n_units, 3, 3))
    cents = np.zeros((n_units, 3))
    placed: list[NDArray[np.float64]] = []
    for u in range(n_units):
        r, c = divmod(u, ncol)
        stagger = 0.5 * pitch if r % 2 else 0.0
        x = (c - (ncol - 1) / 2) * pitch + stagger - 0.25 * pitch
        y = (r - (nrow - 1) / 2) * pitch * 0.9
        for _attempt in range(200):
            centre = origin + (x + rng.uniform(-0.15, 0.15) * pitch) * e1
            centre = centre + (y + rng.uniform(-0.15, 0.15) * pitch) * e2
            centre = centre + rng.uniform(-0.1, 0.1) * dn * n_s
            spin = _rot(n_s, rng.uniform(0, 2 * np.pi))
            tilt = _rot(rng.normal(size=3), np.radians(rng.uniform(0, 20)))
            R = tilt @ spin @ base
            fid = centre + geo.positions_mm @ R.T
            if (
                not placed
                or min(
                    float(np.min(np.linalg.norm(q[:, None] - fid[None], axis=2)))
                    for q in placed[-3 * ncol :]
                )
                >= min_gap_mm
            ):
                break
        rots[u], cents[u] = R, centre
        placed.append(fid)

    n_fid = n_units * len(geo.codes)
    hidden_b = rng.random(n_fid) < hidden_fraction
    # How each fiducial was glued, from a generator spawned from the field's (its draws leave
    # the rest of the field as it was).
    glue = rng.spawn(1)[0].uniform(0.0, 2.0 * np.pi, n_fid)
    before = _state(geo, cam, rots, cents, hidden_b, max_slant_deg, diameter_mm, glue)

    order = rng.permutation(n_units)
    n_over = round(overturned_fraction * n_units)
    n_move = round(moved_fraction * n_units)
    overturned = np.zeros(n_units, dtype=bool)
    moved = np.zeros(n_units, dtype=bool)
    overturned[order[:n_over]] = True
    moved[order[n_over : n_over + n_move]] = True
    rots_a, cents_a = rots.copy(), cents.copy()
    down = -e2
    for u in np.flatnonzero(moved | overturned).tolist():
        ang = np.radians(rng.uniform(-60, 60))
        direction = np.cos(ang) * down + np.sin(ang) * e1
        if overturned[u]:
            dist = rng.uniform(0.2, 1.5) * dn
            turn = _rot(rots[u][:, 0], np.pi)
        else:
            dist = rng.uniform(0.1, max_move_dn) * dn
            turn = _rot(rng.normal(size=3), np.radians(rng.uniform(0, 30)))
        rots_a[u] = turn @ rots[u]
        cents_a[u] = cents[u] + dist * direction + rng.uniform(-0.1, 0.1) * dn * n_s
    if settle:
        _settle(geo, rots_a, cents_a, np.flatnonzero(moved | overturned), n_s, min_gap_mm)
    hidden_a = rng.random(n_fid) < hidden_fraction
    after = _state(geo, cam, rots_a, cents_a, hidden_a, max_slant_deg, diameter_mm, glue)
    return Field(geo, cam, before, after, moved, overturned, float(width))
