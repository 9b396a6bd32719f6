"""Whole synthetic scenes: hundreds of fiducials and clutter on a full frame, via :mod:`.render`.

Layouts (:func:`random_layout`, :func:`grid_layout`) place fiducials and clutter patches so that no
two overlap and every one lies wholly inside the frame; :func:`random_scene` and :func:`grid_scene`
render them with the one renderer, :func:`armourcam.render.render`, which supplies the ground truth.

Sizes are the paper's: ``size_px`` is the imaged outer diameter of a fiducial at zero slant, so a
fiducial of diameter ``D`` mm sits at depth ``z = f * D / size_px``. Slant is the angle between the
fiducial's normal and its line of sight (the paper's definition, section 4), not the optical axis.

Clutter (dark blobs, text-like marks, plain circles, rings, bull's-eyes without a code, checker
bits) is built from :class:`armourcam.render.Patch` objects whose reflectance is NaN where they are
transparent, so blobs and marks lie directly on the background.

Cameras: :func:`paper_camera` is the paper's synthetic benchmark camera (``f = 6507`` px, size
``s`` px at ``z = 6507 * 7.1 / s`` mm, section 4.1); :func:`table3_camera` is its Table 3 camera
(Nikon D40: 3008 x 2000 pixels of 7.8 um behind a 45 mm lens, ``f = 45 / 0.0078`` px).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fiducial_detector.codebook import code_count
from fiducial_detector.design import get_design
from pose_estimator.camera import CameraModel

from .render import (
    MARGIN,
    Patch,
    RenderedScene,
    Target,
    render,
    rotation_from_slant_tilt,
)

PAPER_FOCAL_PX = 6507.0
PAPER_DIAMETER_MM = 7.1
FRAME_SIZE = (3008, 2000)
TABLE3_PIXEL_MM = 0.0078
TABLE3_LENS_MM = 45.0
CLUTTER_KINDS = ("blob", "text", "circle", "ring", "bullseye", "checker")

ReflectanceFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


class SceneError(ValueError):
    """A scene cannot be laid out as asked (does not fit, bad size, slant or count)."""


def paper_camera(width: int = FRAME_SIZE[0], height: int = FRAME_SIZE[1]) -> CameraModel:
    """The paper's synthetic benchmark camera: ideal pinhole, ``f = 6507`` px, centred."""
    return CameraModel.ideal(width, height, PAPER_FOCAL_PX)


def table3_camera() -> CameraModel:
    """The paper's Table 3 camera: 3008 x 2000, 7.8 um pixels, 45 mm lens (``f`` = 5769.2 px)."""
    return CameraModel.ideal(FRAME_SIZE[0], FRAME_SIZE[1], TABLE3_LENS_MM / TABLE3_PIXEL_MM)


def distance_for_size(
    size_px: float, *, focal_px: float = PAPER_FOCAL_PX, diameter_mm: float = PAPER_DIAMETER_MM
) -> float:
    """Depth (mm) at which a fronto-parallel fiducial of ``diameter_mm`` images ``size_px`` across.

    ``z = focal_px * diameter_mm / size_px``; with the defaults, the paper's 60 px is 770.0 mm.
    """
    if not size_px > 0 or not focal_px > 0 or not diameter_mm > 0:
        raise SceneError(
            f"size, focal length and diameter must be positive "
            f"(got {size_px}, {focal_px}, {diameter_mm})"
        )
    return focal_px * diameter_mm / size_px


@dataclass(frozen=True, slots=True, eq=False)
class SceneLayout:
    """Fiducials and clutter placed in front of a camera, not yet rendered.

    Attributes
    ----------
    targets : tuple of Target
        Fiducials, each wholly in frame and overlapping nothing else.
    clutter : tuple of Patch
        Clutter patches, likewise.
    clutter_kinds : tuple of str
        The kind of each clutter patch (one of :data:`CLUTTER_KINDS`).
    footprints_px : (N, 3) ndarray
        ``(u, v, radius)`` of the circle enclosing each item's image (targets first, then
        clutter), with the fiducial's white paper margin included.
    """

    targets: tuple[Target, ...]
    clutter: tuple[Patch, ...]
    clutter_kinds: tuple[str, ...]
    footprints_px: NDArray[np.float64]


# --- poses and footprints ---------------------------------------------------------------------


def _look_rotation(direction: NDArray[np.float64]) -> NDArray[np.float64]:
    """Smallest rotation taking the optical axis (0, 0, 1) to the unit vector ``direction``."""
    z = np.array([0.0, 0.0, 1.0])
    d = direction / np.linalg.norm(direction)
    axis = np.cross(z, d)
    s, c = np.linalg.norm(axis), float(d @ z)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * kx + (1.0 - c) * (kx @ kx)


def pose_at_pixel(
    camera: CameraModel,
    uv: tuple[float, float],
    depth_mm: float,
    slant: float,
    tilt: float,
    spin: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pose of a planar patch whose centre images at pixel ``uv`` (distorted) at ``depth_mm``.

    ``slant`` (radians) is measured from the line of sight, ``tilt`` is the direction of the
    slant axis and ``spin`` the in-plane rotation, as in
    :func:`armourcam.render.rotation_from_slant_tilt`.

    Returns
    -------
    rotation : (3, 3) ndarray
        Patch frame -> camera frame.
    position_mm : (3,) ndarray
        Patch centre in the camera frame.
    """
    xy = camera.undistort_normalized(np.array([uv], dtype=np.float64))[0]
    position = np.array([xy[0] * depth_mm, xy[1] * depth_mm, depth_mm])
    rotation = _look_rotation(position) @ rotation_from_slant_tilt(slant, tilt, spin)
    return rotation, position


def _footprint(
    camera: CameraModel,
    rotation: NDArray[np.float64],
    position: NDArray[np.float64],
    radius_mm: float,
) -> tuple[float, float, float] | None:
    """Circle ``(u, v, r)`` enclosing the image of a disc of ``radius_mm``; None if it leaves the
    frame or reaches behind the camera."""
    ang = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)]) * radius_mm
    pts = ring @ rotation.T + position
    if np.any(pts[:, 2] <= 1e-6):
        return None
    uv = camera.project(pts)
    centre = camera.project(position.reshape(1, 3))[0]
    r = float(np.max(np.hypot(uv[:, 0] - centre[0], uv[:, 1] - centre[1])))
    return float(centre[0]), float(centre[1]), r


class _Placer:
    """Random sequential placement of non-overlapping circles inside the frame."""

    def __init__(self, camera: CameraModel, gap_px: float, border_px: float) -> None:
        self.camera = camera
        self.gap = gap_px
        self.border = border_px
        self.circles = np.zeros((0, 3))

    def fits(self, fp: tuple[float, float, float] | None) -> bool:
        if fp is None:
            return False
        u, v, r = fp
        b = self.border + r
        if not (b - 0.5 <= u <= self.camera.width - 0.5 - b):
            return False
        if not (b - 0.5 <= v <= self.camera.height - 0.5 - b):
            return False
        if len(self.circles) == 0:
            return True
        d = np.hypot(self.circles[:, 0] - u, self.circles[:, 1] - v)
        return bool(np.all(d >= self.circles[:, 2] + r + self.gap))

    def blocked(self, u: float, v: float, r_min: float) -> bool:
        """Cheap early rejection: True if a circle of at least ``r_min`` at (u, v) cannot fit."""
        b = self.border + r_min
        if not (b - 0.5 <= u <= self.camera.width - 0.5 - b):
            return True
        if not (b - 0.5 <= v <= self.camera.height - 0.5 - b):
            return True
        if len(self.circles) == 0:
            return False
        d = np.hypot(self.circles[:, 0] - u, self.circles[:, 1] - v)
        return bool(np.any(d < self.circles[:, 2] + r_min + self.gap))

    def add(self, fp: tuple[float, float, float]) -> None:
        self.circles = np.vstack([self.circles, np.array(fp)])


def _check_common(size_px: float, slant_max_deg: float, camera: CameraModel) -> None:
    if not size_px > 0:
        raise SceneError(f"size_px must be positive, got {size_px}")
    if not 0.0 <= slant_max_deg < 90.0:
        raise SceneError(f"slant must be in [0, 90) degrees, got {slant_max_deg}")
    if size_px * MARGIN > min(camera.width, camera.height):
        raise SceneError(
            f"targets of {size_px} px do not fit a {camera.width}x{camera.height} frame"
        )


def _designs(design: str | Sequence[str]) -> list[str]:
    names = [design] if isinstance(design, str) else list(design)
    if not names:
        raise SceneError("no fiducial design given")
    for name in names:
        try:
            get_design(name)
        except ValueError as err:
            raise SceneError(str(err)) from None
    return names


def _codes(codes: Sequence[int] | None) -> NDArray[np.int64]:
    n = code_count()
    pool = np.arange(n) if codes is None else np.asarray(list(codes), dtype=np.int64)
    if pool.size == 0 or pool.min() < 0 or pool.max() >= n:
        raise SceneError(f"codes must be a non-empty subset of 0..{n - 1}")
    return pool


# --- clutter ----------------------------------------------------------------------------------


def _polar(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    return np.hypot(x, y), np.arctan2(y, x)


def _blob(rng: np.random.Generator, r: float) -> tuple[ReflectanceFn, float]:
    """A dark irregular blob (a stain, a shadow, a hole) on no paper."""
    k = np.arange(2, 6)
    amp = rng.uniform(0.0, 0.12, k.size)
    phase = rng.uniform(0.0, 2.0 * np.pi, k.size)
    level = rng.uniform(0.0, 0.35)
    r0 = r / (1.0 + amp.sum())

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        rho, th = _polar(x, y)
        edge = r0 * (1.0 + (amp[:, None] * np.cos(k[:, None] * th.ravel() + phase[:, None])).sum(0))
        return np.where(rho.ravel() <= edge, level, np.nan).reshape(np.shape(x))

    return f, r


# Seven-segment glyph strokes as (x0, y0, x1, y1) in a unit cell 0.6 wide, 1 tall (y up).
_SEGMENTS = (
    (0.0, 0.9, 0.6, 1.0),
    (0.5, 0.5, 0.6, 1.0),
    (0.5, 0.0, 0.6, 0.5),
    (0.0, 0.0, 0.6, 0.1),
    (0.0, 0.0, 0.1, 0.5),
    (0.0, 0.5, 0.1, 1.0),
    (0.0, 0.45, 0.6, 0.55),
    (0.25, 0.0, 0.35, 1.0),  # a vertical bar (I, 1, l)
)


def _text(rng: np.random.Generator, r: float) -> tuple[ReflectanceFn, float]:
    """A line of letter-like glyphs (bars as rectangles), on a white label or bare."""
    n = int(rng.integers(2, 6))
    glyphs = []
    for _ in range(n):
        m = int(rng.integers(2, 6))
        glyphs.append(rng.choice(len(_SEGMENTS), size=m, replace=False))
    width = 0.8 * n  # cell pitch 0.8, glyph 0.6 wide, height 1
    scale = 2.0 * r / np.hypot(width + 0.4, 1.4)  # the label's diagonal is the patch diameter
    rects = np.array(
        [
            [
                (x0 + 0.8 * i - width / 2.0 + 0.1) * scale,
                (y0 - 0.5) * scale,
                (x1 + 0.8 * i - width / 2.0 + 0.1) * scale,
                (y1 - 0.5) * scale,
            ]
            for i, glyph in enumerate(glyphs)
            for x0, y0, x1, y1 in (_SEGMENTS[g] for g in glyph)
        ]
    )
    label = bool(rng.integers(2))
    half_w, half_h = (width + 0.4) / 2.0 * scale, 0.7 * scale
    ink = rng.uniform(0.0, 0.15)

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        xs, ys = x.ravel()[:, None], y.ravel()[:, None]
        on = np.any(
            (xs >= rects[:, 0]) & (xs < rects[:, 2]) & (ys >= rects[:, 1]) & (ys < rects[:, 3]),
            axis=1,
        )
        paper = (np.abs(x.ravel()) <= half_w) & (np.abs(y.ravel()) <= half_h)
        back = np.where(paper, 1.0, np.nan) if label else np.full(on.shape, np.nan)
        return np.where(on, ink, back).reshape(np.shape(x))

    return f, r


def _circle(rng: np.random.Generator, r: float) -> tuple[ReflectanceFn, float]:
    """A plain black disc, on a white paper disc or bare."""
    inner = r * rng.uniform(0.55, 1.0)
    paper = 1.0 if inner < r * 0.95 else np.nan

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where(np.hypot(x, y) < inner, 0.0, paper)

    return f, r


def _ring(rng: np.random.Generator, r: float) -> tuple[ReflectanceFn, float]:
    """A black annulus on white paper (a washer, a printed circle outline)."""
    outer = r / MARGIN
    inner = outer * rng.uniform(0.4, 0.9)

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        rho = np.hypot(x, y)
        return np.where((rho >= inner) & (rho < outer), 0.0, 1.0)

    return f, r


def _bullseye(rng: np.random.Generator, r: float) -> tuple[ReflectanceFn, float]:
    """Concentric black dot and rings with no code track: fiducial-like but not a fiducial."""
    outer = r / MARGIN
    n = int(rng.integers(1, 4))
    edges = np.sort(rng.uniform(0.15, 1.0, 2 * n - 1)) * outer
    edges = np.append(edges, outer)  # black from 0..e0, e1..e2, ... e_{2n-2}..outer

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        band = np.searchsorted(edges, np.hypot(x, y), side="right")
        return np.where(band % 2 == 0, 0.0, 1.0)

    return f, r


def _checker(rng: np.random.Generator, r: float) -> tuple[ReflectanceFn, float]:
    """A bit of a checkerboard (a calibration target's corner, a chequered label)."""
    k = int(rng.integers(2, 6))
    half = r / np.sqrt(2.0)
    cell = 2.0 * half / k

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        inside = (np.abs(x) < half) & (np.abs(y) < half)
        parity = (np.floor((x + half) / cell) + np.floor((y + half) / cell)) % 2
        return np.where(inside, np.where(parity == 0, 0.05, 0.95), np.nan)

    return f, r


_CLUTTER: dict[str, Callable[[np.random.Generator, float], tuple[ReflectanceFn, float]]] = {
    "blob": _blob,
    "text": _text,
    "circle": _circle,
    "ring": _ring,
    "bullseye": _bullseye,
    "checker": _checker,
}


def clutter_patch(
    kind: str,
    rng: np.random.Generator,
    radius_mm: float,
    rotation: NDArray[np.float64],
    position_mm: NDArray[np.float64],
) -> Patch:
    """One clutter patch of ``kind`` (see :data:`CLUTTER_KINDS`) within ``radius_mm`` of its centre.

    Raises
    ------
    SceneError
        If ``kind`` is unknown or the radius is not positive.
    """
    if kind not in _CLUTTER:
        raise SceneError(f"unknown clutter kind {kind!r}; known: {list(CLUTTER_KINDS)}")
    if not radius_mm > 0:
        raise SceneError(f"clutter radius must be positive, got {radius_mm}")
    fn, extent = _CLUTTER[kind](rng, radius_mm)
    return Patch(
        np.asarray(rotation, dtype=np.float64),
        np.asarray(position_mm, dtype=np.float64),
        extent,
        fn,
    )


# --- layouts ----------------------------------------------------------------------------------


def _place_clutter(
    camera: CameraModel,
    placer: _Placer,
    n_clutter: int,
    size_px: float,
    depth_mm: float,
    rng: np.random.Generator,
    slant_max: float,
    kinds: Sequence[str],
    max_tries: int,
) -> tuple[list[Patch], list[str]]:
    patches: list[Patch] = []
    names: list[str] = []
    mm_per_px = depth_mm / camera.K[0, 0]
    tries = 0
    while len(patches) < n_clutter:
        tries += 1
        if tries > max_tries:
            raise SceneError(
                f"placed only {len(patches)} of {n_clutter} clutter patches without overlap; "
                f"ask for fewer or smaller items"
            )
        kind = str(kinds[int(rng.integers(len(kinds)))])
        radius_mm = rng.uniform(0.3, 0.9) * size_px * mm_per_px
        uv = (rng.uniform(0, camera.width - 1), rng.uniform(0, camera.height - 1))
        slant = rng.uniform(0.0, slant_max)
        # A slanted disc's image is never much narrower than its fronto-parallel width.
        if placer.blocked(uv[0], uv[1], 0.9 * radius_mm / mm_per_px):
            continue
        rot, pos = pose_at_pixel(
            camera, uv, depth_mm, slant, rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
        )
        fp = _footprint(camera, rot, pos, radius_mm)
        if not placer.fits(fp):
            continue
        assert fp is not None
        placer.add(fp)
        patches.append(clutter_patch(kind, rng, radius_mm, rot, pos))
        names.append(kind)
    return patches, names


def random_layout(
    camera: CameraModel,
    n_targets: int,
    size_px: float,
    design: str | Sequence[str],
    rng: np.random.Generator,
    slant_max_deg: float = 60.0,
    clutter: bool = True,
    *,
    n_clutter: int | None = None,
    clutter_kinds: Sequence[str] = CLUTTER_KINDS,
    diameter_mm: float = PAPER_DIAMETER_MM,
    codes: Sequence[int] | None = None,
    gap_px: float = 4.0,
    border_px: float = 4.0,
    max_tries: int | None = None,
) -> SceneLayout:
    """Fiducials at random places, codes, slants, tilts and spins; clutter in the gaps.

    Parameters
    ----------
    camera : CameraModel
    n_targets : int
        Number of fiducials.
    size_px : float
        Imaged outer diameter of each fiducial at zero slant (all at depth ``f * D / size_px``).
    design : str or sequence of str
        Fiducial design, or designs to draw from at random.
    rng : numpy.random.Generator
        The only source of randomness: the same seed gives the same layout.
    slant_max_deg : float
        Slants are uniform in ``[0, slant_max_deg]``, measured from each line of sight.
    clutter : bool
        Whether to add clutter patches.
    n_clutter : int, optional
        Number of clutter patches (default ``n_targets // 2``).
    clutter_kinds : sequence of str
        Kinds to draw clutter from (see :data:`CLUTTER_KINDS`).
    diameter_mm : float
        Printed outer diameter of the fiducials.
    codes : sequence of int, optional
        Codes to draw from (default: the whole codebook), with repetition.
    gap_px, border_px : float
        Minimum gap between items' footprints (paper margin included), and to the frame edge.
    max_tries : int, optional
        Placement attempts before giving up (default ``200 * (n_targets + n_clutter) + 1000``).

    Raises
    ------
    SceneError
        If the items cannot be placed without overlap, or a parameter is out of range.
    """
    _check_common(size_px, slant_max_deg, camera)
    if n_targets < 0:
        raise SceneError(f"n_targets must be >= 0, got {n_targets}")
    names = _designs(design)
    pool = _codes(codes)
    nc = (n_targets // 2 if n_clutter is None else n_clutter) if clutter else 0
    if nc < 0:
        raise SceneError(f"n_clutter must be >= 0, got {n_clutter}")
    tries_left = max_tries if max_tries is not None else 200 * (n_targets + nc) + 1000
    depth = distance_for_size(size_px, focal_px=float(camera.K[0, 0]), diameter_mm=diameter_mm)
    slant_max = np.radians(slant_max_deg)
    placer = _Placer(camera, gap_px, border_px)
    targets: list[Target] = []
    tries = 0
    while len(targets) < n_targets:
        tries += 1
        if tries > tries_left:
            raise SceneError(
                f"placed only {len(targets)} of {n_targets} targets of {size_px} px without "
                f"overlap in {camera.width}x{camera.height}; ask for fewer or smaller targets"
            )
        uv = (rng.uniform(0, camera.width - 1), rng.uniform(0, camera.height - 1))
        slant, tilt, spin = rng.uniform(0.0, slant_max), *rng.uniform(0.0, 2 * np.pi, 2)
        if placer.blocked(uv[0], uv[1], 0.9 * MARGIN * size_px / 2.0):
            continue
        rot, pos = pose_at_pixel(camera, uv, depth, slant, tilt, spin)
        fp = _footprint(camera, rot, pos, MARGIN * diameter_mm / 2.0)
        if not placer.fits(fp):
            continue
        assert fp is not None
        placer.add(fp)
        targets.append(
            Target(
                int(pool[rng.integers(pool.size)]),
                names[int(rng.integers(len(names)))],
                diameter_mm,
                rot,
                pos,
            )
        )
    patches, kinds = _place_clutter(
        camera, placer, nc, size_px, depth, rng, slant_max, clutter_kinds, tries_left
    )
    return SceneLayout(tuple(targets), tuple(patches), tuple(kinds), placer.circles.copy())


def grid_layout(
    camera: CameraModel,
    rows: int,
    cols: int,
    size_px: float,
    design: str | Sequence[str],
    rng: np.random.Generator,
    slant_max_deg: float = 0.0,
    clutter: bool = False,
    *,
    slants_deg: Sequence[float] | None = None,
    n_clutter: int | None = None,
    clutter_kinds: Sequence[str] = CLUTTER_KINDS,
    diameter_mm: float = PAPER_DIAMETER_MM,
    codes: Sequence[int] | None = None,
    gap_px: float = 4.0,
    border_px: float = 4.0,
) -> SceneLayout:
    """Fiducials on a regular ``rows x cols`` grid spanning the frame; random codes and spins.

    Parameters are those of :func:`random_layout`, plus ``slants_deg``: explicit slants for the
    grid cells in row-major order (repeated cyclically), e.g. a sweep of 0..85 degrees for a
    benchmark; otherwise slants are uniform in ``[0, slant_max_deg]``. Clutter, if asked for, is
    placed at random in the gaps (default ``rows * cols // 4`` patches).

    Raises
    ------
    SceneError
        If the grid's pitch is too small for the targets, or a parameter is out of range.
    """
    _check_common(size_px, max([slant_max_deg, *(slants_deg or [])]), camera)
    if rows < 1 or cols < 1:
        raise SceneError(f"grid must have at least one row and column, got {rows}x{cols}")
    if slants_deg is not None and len(slants_deg) == 0:
        raise SceneError("slants_deg is empty")
    names = _designs(design)
    pool = _codes(codes)
    depth = distance_for_size(size_px, focal_px=float(camera.K[0, 0]), diameter_mm=diameter_mm)
    pitch_u = (camera.width - 2 * border_px) / cols
    pitch_v = (camera.height - 2 * border_px) / rows
    placer = _Placer(camera, gap_px, border_px)
    targets: list[Target] = []
    for i in range(rows * cols):
        r, c = divmod(i, cols)
        uv = (
            border_px - 0.5 + (c + 0.5) * pitch_u,
            border_px - 0.5 + (r + 0.5) * pitch_v,
        )
        if slants_deg is not None:
            slant = np.radians(slants_deg[i % len(slants_deg)])
        else:
            slant = rng.uniform(0.0, np.radians(slant_max_deg))
        tilt, spin = rng.uniform(0.0, 2 * np.pi, 2)
        rot, pos = pose_at_pixel(camera, uv, depth, slant, tilt, spin)
        fp = _footprint(camera, rot, pos, MARGIN * diameter_mm / 2.0)
        if not placer.fits(fp):
            raise SceneError(
                f"a {rows}x{cols} grid of {size_px} px targets does not fit "
                f"{camera.width}x{camera.height} without overlap"
            )
        assert fp is not None
        placer.add(fp)
        targets.append(
            Target(
                int(pool[rng.integers(pool.size)]),
                names[int(rng.integers(len(names)))],
                diameter_mm,
                rot,
                pos,
            )
        )
    nc = (rows * cols // 4 if n_clutter is None else n_clutter) if clutter else 0
    slant_max = np.radians(slant_max_deg)
    patches, kinds = _place_clutter(
        camera, placer, nc, size_px, depth, rng, slant_max, clutter_kinds, 200 * nc + 1000
    )
    return SceneLayout(tuple(targets), tuple(patches), tuple(kinds), placer.circles.copy())


def render_layout(
    camera: CameraModel,
    layout: SceneLayout,
    rng: np.random.Generator,
    *,
    blur_sigma: float = 0.0,
    noise: float = 0.0,
    supersample: int = 8,
    dtype: type[np.unsignedinteger] = np.uint8,
) -> RenderedScene:
    """Render a layout with :func:`armourcam.render.render` (noise drawn from ``rng``)."""
    return render(
        camera,
        layout.targets,
        clutter=layout.clutter,
        blur_sigma=blur_sigma,
        noise=noise,
        rng=rng,
        supersample=supersample,
        dtype=dtype,
    )


def random_scene(
    camera: CameraModel,
    n_targets: int,
    size_px: float,
    design: str | Sequence[str],
    rng: np.random.Generator,
    slant_max_deg: float = 60.0,
    clutter: bool = True,
    *,
    blur_sigma: float = 0.0,
    noise: float = 0.0,
    supersample: int = 8,
    dtype: type[np.unsignedinteger] = np.uint8,
    **layout_options: Any,
) -> RenderedScene:
    """A rendered :func:`random_layout` (e.g. 400 fiducials of 60 px on a 3008 x 2000 frame).

    ``layout_options`` are the keyword-only options of :func:`random_layout`; ``blur_sigma``,
    ``noise``, ``supersample`` and ``dtype`` are the renderer's. The ground truth (one
    :class:`armourcam.render.TargetTruth` per fiducial) comes with the image.
    """
    layout = random_layout(
        camera, n_targets, size_px, design, rng, slant_max_deg, clutter, **layout_options
    )
    return render_layout(
        camera,
        layout,
        rng,
        blur_sigma=blur_sigma,
        noise=noise,
        supersample=supersample,
        dtype=dtype,
    )


def grid_scene(
    camera: CameraModel,
    rows: int,
    cols: int,
    size_px: float,
    design: str | Sequence[str],
    rng: np.random.Generator,
    slant_max_deg: float = 0.0,
    clutter: bool = False,
    *,
    blur_sigma: float = 0.0,
    noise: float = 0.0,
    supersample: int = 8,
    dtype: type[np.unsignedinteger] = np.uint8,
    **layout_options: Any,
) -> RenderedScene:
    """A rendered :func:`grid_layout`; options as in :func:`random_scene`."""
    layout = grid_layout(
        camera, rows, cols, size_px, design, rng, slant_max_deg, clutter, **layout_options
    )
    return render_layout(
        camera,
        layout,
        rng,
        blur_sigma=blur_sigma,
        noise=noise,
        supersample=supersample,
        dtype=dtype,
    )
