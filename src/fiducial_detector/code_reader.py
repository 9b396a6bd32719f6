"""Reading the coding track (paper section 3, step 4), vectorised over all candidates.

For each candidate the pose ellipse (and, when known, a second concentric ellipse) maps the printed
target plane into the image. A point at printed radius ``r`` and parameter ``t`` is taken at

    p(r, t) = c(r) + (r / r0) * R(angle) diag(a, b) [cos t, -sin t]^T,
    c(r)    = c0 + k (r^2 - r0^2),

where ``(c0, a, b, angle)`` is the ellipse of the pose circle of radius ``r0`` and ``k`` the drift
of ellipse centres: under perspective the image of a concentric circle of radius ``r`` is centred
at ``c_true + k r^2`` (first order in the target's angular size), so two fitted circles fix
``k`` and the image of the true centre. The minus sign makes ``t`` run counter-clockwise on the
printed face (the camera sees the face, so the image is mirrored relative to +u right, +v down);
then ``t`` differs from the printed polar angle by a constant: the code's unknown rotation.

The track is sampled (bilinear) at 8 angles per sector on 3 radii; since ``t = 0`` falls anywhere
within a sector, each of the 8 sector phases is tried and the one whose sectors lie farthest from
the mid level is kept; a sector's value is the mean of its 4 middle angles. Black and white
reference levels are medians over printed regions of known colour (``ring``: annulus and centre
black, the white ring around the dot and the paper outside white; ``dot``: the dot black, the
white ring and the paper outside white). Explicit rejection rules, in order:

1. every sample inside the image;
2. contrast (white - black level) at least ``min_contrast`` of full scale;
3. consistency of the design's concentric regions: at most ``max_ref_outliers`` of the samples on
   each known-black ring are lighter than the mid level and likewise for the known-white rings;
4. Hamming distance to the nearest rotation of a code at most ``max_hamming`` (0 or 1);
5. bit-contrast margin: a corrected sector must be a weak one (margin below ``weak_margin``), and at
   most ``max_weak_bits`` sectors may be weak (``max_weak_bits_exact`` for an exact match: reaching
   a wrong code exactly takes at least four wrong sectors, since the codebook's distance is 4).

Pixel convention: ``(u, v)`` = (column, row), pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .codebook import BITS, rotation_table
from .design import FiducialDesign

#: Samples per sector: angular offsets (fraction of a sector, about its middle) x radial offsets
#: (fraction of the track width).
_PER_SECTOR = 8  # angular samples per sector; the sector phase is searched in these steps
_CORE = 4  # the middle samples of a sector that give its value
_RAD = np.array([0.25, 0.5, 0.75])
_REF_ANGLES = 24
_MAX_REMAP_ROWS = 30000
#: Default smallest accepted contrast (white - black level), fraction of full scale.
DEFAULT_MIN_CONTRAST = 0.06


@dataclass(frozen=True, slots=True)
class ReaderConfig:
    """Rejection thresholds of the code reader (see the module docstring)."""

    min_contrast: float = DEFAULT_MIN_CONTRAST
    max_ref_outliers: float = 0.2
    max_hamming: int = 1
    weak_margin: float = 0.35
    max_weak_bits: int = 2
    max_weak_bits_exact: int = 2


@dataclass(frozen=True, slots=True, eq=False)
class TrackReading:
    """Codes read for N candidates.

    Attributes
    ----------
    accepted : (N,) bool
        Passed every rejection rule.
    consistent : (N,) bool
        Passed rules 1-3 (inside the image, contrast, concentric regions): looks like a fiducial of
        the design whatever the code read.
    nearest : (N,) int64
        Hamming distance of the bits read to the nearest rotation of any code (for consistent
        candidates; ``BITS + 1`` for the others).
    code, rotation_sector, hamming : (N,) int64
        Nearest code, the code's sector read first, Hamming distance (``BITS + 1`` when more than
        one sector is wrong or the candidate was rejected before decoding).
    bits : (N, 16) uint8
        Sector values read (1 = black), from parameter ``t = 0`` onwards.
    margin : (N, 16) float64
        ``|sector mean - mid level| / (contrast / 2)``: 1 at a reference level, 0 at the mid level.
    black, white : (N,) float64
        Reference levels, fraction of full scale.
    rotation : (N,) float64
        Image angle (radians from +u towards +v, seen from the ellipse centre) of the boundary
        between the code's sectors 15 and 0.
    """

    accepted: NDArray[np.bool_]
    consistent: NDArray[np.bool_]
    nearest: NDArray[np.int64]
    code: NDArray[np.int64]
    rotation_sector: NDArray[np.int64]
    hamming: NDArray[np.int64]
    bits: NDArray[np.uint8]
    margin: NDArray[np.float64]
    black: NDArray[np.float64]
    white: NDArray[np.float64]
    rotation: NDArray[np.float64]

    @property
    def contrast(self) -> NDArray[np.float64]:
        """White minus black reference level."""
        return self.white - self.black


@lru_cache(maxsize=1)
def _decode_table() -> tuple[NDArray[np.int16], NDArray[np.int8], NDArray[np.int8]]:
    """Code, rotation and distance of every 16-bit word within distance 1 of a code rotation.

    The codebook's minimum distance is 4, so these radius-1 balls are disjoint and a lookup gives
    the same answer as :func:`fiducial_detector.codebook.decode` for every word it accepts.
    Words farther away get distance ``BITS + 1``.
    """
    table = rotation_table()
    weights = (1 << np.arange(BITS)).astype(np.int64)
    words = (table.astype(np.int64) * weights).sum(axis=2)  # (codes, BITS)
    code = np.full(1 << BITS, -1, dtype=np.int16)
    rot = np.zeros(1 << BITS, dtype=np.int8)
    dist = np.full(1 << BITS, BITS + 1, dtype=np.int8)
    c_idx, r_idx = np.meshgrid(np.arange(words.shape[0]), np.arange(BITS), indexing="ij")
    flat_w, flat_c, flat_r = words.ravel(), c_idx.ravel(), r_idx.ravel()
    for flip in [0, *(1 << np.arange(BITS)).tolist()]:
        w = flat_w ^ flip
        code[w] = flat_c
        rot[w] = flat_r
        dist[w] = 0 if flip == 0 else 1
    return code, rot, dist


@lru_cache(maxsize=1)
def _all_words() -> NDArray[np.int64]:
    """Every rotation of every code word as a 16-bit integer, shape (codes * BITS,)."""
    weights = (1 << np.arange(BITS)).astype(np.int64)
    return (rotation_table().astype(np.int64) * weights).sum(axis=2).ravel()


@lru_cache(maxsize=1)
def _popcount16() -> NDArray[np.uint8]:
    return np.array([bin(i).count("1") for i in range(1 << BITS)], dtype=np.uint8)


def _nearest_distance(words: NDArray[np.int64], known: NDArray[np.int64]) -> NDArray[np.int64]:
    """Distance to the nearest code rotation; computed only where the table says it is > 1."""
    out = known.copy()
    far = np.nonzero(known > 1)[0]
    if far.size:
        xor = words[far, None] ^ _all_words()[None, :]
        out[far] = _popcount16()[xor].min(axis=1)
    return out


def _rot2(angle: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (N, 2, 2)


def track_points(
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    r0: float,
    drift: NDArray[np.float64],
    radii: NDArray[np.float64],
    params: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Image points ``p(r, t)`` for N candidates and K (radius, parameter) pairs: shape (N, K, 2).

    Parameters
    ----------
    centre : (N, 2)
        Pose-ellipse centres ``(u, v)``.
    axes : (N, 2)
        Semi-axes ``(a, b)``.
    angle : (N,)
        Major-axis angles.
    r0 : float
        Printed radius of the pose circle (fraction of the outer radius).
    drift : (N, 2)
        Centre drift ``k`` per unit ``r^2`` (zeros for the affine approximation).
    radii, params : (K,)
        Printed radii and parameters ``t`` of the points.
    """
    scale = radii / r0
    ux = np.cos(params) * scale  # (K,)
    uy = -np.sin(params) * scale
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    a, b = axes[:, 0:1], axes[:, 1:2]
    # R diag(a, b) [ux, uy]^T written out: einsum over (N, K) is several times slower.
    ax_u, ax_v = a * ux, b * uy
    dr2 = radii**2 - r0**2
    out = np.empty((len(centre), len(radii), 2))
    out[..., 0] = centre[:, 0:1] + drift[:, 0:1] * dr2 + c * ax_u - s * ax_v
    out[..., 1] = centre[:, 1:2] + drift[:, 1:2] * dr2 + s * ax_u + c * ax_v
    return out


def _sample(
    image: NDArray[Any], full_scale: float, pts: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Bilinear samples of ``image`` at ``pts`` (N, K, 2) in fractions of full scale; NaN outside.

    OpenCV interpolates in the image's own type (an 8-bit image gives 8-bit samples, ample for
    telling black from white), so the full frame is never converted to float.
    """
    n, k, _ = pts.shape
    out = np.empty((n, k), dtype=np.float64)
    for start in range(0, n, _MAX_REMAP_ROWS):
        chunk = pts[start : start + _MAX_REMAP_ROWS].astype(np.float32)
        got = cv2.remap(
            image,
            np.ascontiguousarray(chunk[..., 0]),
            np.ascontiguousarray(chunk[..., 1]),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        out[start : start + len(chunk)] = got
    out /= full_scale
    h, w = image.shape
    outside = (pts[..., 0] < 0) | (pts[..., 0] > w - 1) | (pts[..., 1] < 0) | (pts[..., 1] > h - 1)
    out[outside] = np.nan
    return out


def _sector_values(
    ring: NDArray[np.float64], mid: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Sector means at the sector phase that best separates black from white.

    The ellipse parameter ``t`` starts at an arbitrary printed angle, so sector boundaries can fall
    anywhere among the ``_PER_SECTOR`` samples of a sector; each phase is tried and the one whose
    sectors lie farthest from the mid level (in total) is kept.

    Returns
    -------
    values : (N, BITS)
        Mean of the ``_CORE`` middle samples of each sector, sector 0 starting at sample ``phase``.
    phase : (N,) int64
    """
    n = ring.shape[0]
    skip = (_PER_SECTOR - _CORE) // 2
    best = np.full(n, -np.inf)
    values = np.zeros((n, BITS))
    phase = np.zeros(n, dtype=np.int64)
    for p in range(_PER_SECTOR):
        rolled = np.roll(ring, -(p + skip), axis=1).reshape(n, BITS, _PER_SECTOR)
        v = rolled[:, :, :_CORE].mean(axis=2)
        score = np.abs(v - mid[:, None]).sum(axis=1)
        better = score > best
        best = np.where(better, score, best)
        values[better] = v[better]
        phase[better] = p
    return values, phase


def _reference_rings(design: FiducialDesign) -> tuple[list[float], list[float]]:
    """Printed radii known to be black and known to be white (white paper margin included)."""
    if design.annulus_inner is not None:
        black = [0.5 * (design.annulus_inner + 1.0), 0.0]
        white = [0.5 * (design.dot_radius + design.track_inner), 1.15]
    else:
        black = [0.0, 0.5 * design.dot_radius]
        white = [0.5 * (design.dot_radius + design.track_inner), 1.14]
    return black, white


def read_codes(
    image: NDArray[Any],
    full_scale: float,
    design: FiducialDesign,
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    drift: NDArray[np.float64] | None = None,
    config: ReaderConfig | None = None,
) -> TrackReading:
    """Read the coding track of N candidates of one design.

    Parameters
    ----------
    image : (H, W) ndarray of uint8, uint16 or float32
        Grey image indexed ``[v, u]``.
    full_scale : float
        Value of white at full scale (255, 65535 or 1.0); levels are returned as fractions of it.
    design : FiducialDesign
    centre, axes, angle, drift
        Pose ellipses of the candidates (see :func:`track_points`); ``drift`` defaults to zero.
    config : ReaderConfig, optional

    Returns
    -------
    TrackReading
    """
    cfg = config or ReaderConfig()
    n = len(centre)
    r0 = design.pose_circle.radius
    k = np.zeros((n, 2)) if drift is None else drift
    width = design.track_outer - design.track_inner
    sector = 2.0 * np.pi / BITS
    n_ang = BITS * _PER_SECTOR
    step = 2.0 * np.pi / n_ang
    t_all = np.repeat((np.arange(n_ang) + 0.5) * step, len(_RAD))
    r_all = np.tile(design.track_inner + _RAD * width, n_ang)
    black_r, white_r = _reference_rings(design)
    ref_t = (np.arange(_REF_ANGLES) + 0.25) * (2.0 * np.pi / _REF_ANGLES)
    ref_r = np.concatenate([np.full(_REF_ANGLES, r) for r in (*black_r, *white_r)])
    ref_t_all = np.tile(ref_t, len(black_r) + len(white_r))
    radii = np.concatenate([r_all, ref_r])
    params = np.concatenate([t_all, ref_t_all])
    pts = track_points(centre, axes, angle, r0, k, radii, params)
    vals = _sample(image, full_scale, pts)

    n_track = r_all.size
    ring = vals[:, :n_track].reshape(n, n_ang, len(_RAD)).mean(axis=2)  # (N, n_ang)
    refs = vals[:, n_track:].reshape(n, len(black_r) + len(white_r), _REF_ANGLES)
    black_s = refs[:, : len(black_r)].reshape(n, -1)
    white_s = refs[:, len(black_r) :].reshape(n, -1)
    valid = ~np.isnan(vals).any(axis=1)
    with np.errstate(invalid="ignore", all="ignore"):
        black = np.median(black_s, axis=1)
        white = np.median(white_s, axis=1)
        contrast = white - black
        mid = 0.5 * (black + white)
        track, phase = _sector_values(ring, mid)
        bits = (track < mid[:, None]).astype(np.uint8)
        margin = np.abs(track - mid[:, None]) / np.maximum(0.5 * contrast[:, None], 1e-9)
        black_bad = (black_s > mid[:, None]).mean(axis=1)
        white_bad = (white_s < mid[:, None]).mean(axis=1)
    ok = valid & (contrast >= cfg.min_contrast)
    ok &= (black_bad <= cfg.max_ref_outliers) & (white_bad <= cfg.max_ref_outliers)
    consistent = ok.copy()

    words = (bits.astype(np.int64) << np.arange(BITS)).sum(axis=1)
    t_code, t_rot, t_dist = _decode_table()
    code = t_code[words].astype(np.int64)
    rot = t_rot[words].astype(np.int64)
    dist = t_dist[words].astype(np.int64)
    ok &= dist <= cfg.max_hamming
    # Which sector was corrected (if any), and is it a weak one?
    expected = rotation_table()[np.maximum(code, 0), rot]  # (N, BITS)
    wrong = expected != bits
    weak = margin < cfg.weak_margin
    ok &= ~(wrong & ~weak).any(axis=1)
    ok &= weak.sum(axis=1) <= np.where(dist == 0, cfg.max_weak_bits_exact, cfg.max_weak_bits)
    nearest = np.where(consistent, _nearest_distance(words, dist), BITS + 1)
    dist = np.where(ok, dist, BITS + 1)

    # Boundary between the code's sectors 15 and 0 sits at read index (BITS - rot) % BITS.
    t_b = ((BITS - rot) % BITS) * sector + phase * step
    m = _rot2(angle) * axes[:, None, :]
    d = np.einsum("nij,nj->ni", m, np.stack([np.cos(t_b), -np.sin(t_b)], -1))
    rotation = np.arctan2(d[:, 1], d[:, 0])
    return TrackReading(
        accepted=ok,
        consistent=consistent,
        nearest=nearest,
        code=code,
        rotation_sector=rot,
        hamming=dist,
        bits=bits,
        margin=np.nan_to_num(margin),
        black=black,
        white=white,
        rotation=rotation,
    )
