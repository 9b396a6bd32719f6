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

Rule 5 rejects correct reads of tracks so small that blur mixes neighbouring sectors (a 25 px
fiducial slanted 60 deg); :func:`model_read` fits the blurred image of every code instead, and
the detector uses it to confirm (or not) such reads.

The code's orientation (the image direction of the boundary between its sectors 15 and 0) is
read finer than the phase search's step (1/8 of a sector, 2.8 deg): once the code is known, the
boundaries where the track changes colour are located to a fraction of a step from the samples
around them (:func:`_phase_offset`). Under the affine approximation ``t`` differs from the printed
polar angle by a constant, so one offset common to all boundaries is what is estimated. On
renders (blur 0.5 px, noise 1 %, slants 0-60 deg) the detector's ``rotation`` is then within an
RMS 0.02-0.06 deg of the truth at 60 px and 0.08-0.3 deg at 33 px (was 0.75-1.2 deg). At 33 px
and 60 deg the fitted ellipse's own error, which the parameter ``t`` inherits, counts as much as
the reading: ``ring`` 0.29 deg (0.18 through the true ellipse); ``dot``, whose 5 px dot carries
the pose, 0.62 deg (0.14). Reads that :func:`model_read` confirms keep this reader's rotation
(its ``phase`` is only the best of 8 per sector).

Pixel convention: ``(u, v)`` = (column, row), pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from . import _profile_kernel
from .codebook import BITS, rotation_table
from .design import FiducialDesign
from .profile_fit import KERNEL_KINDS

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
        between the code's sectors 15 and 0: the phase found to a step, refined to a fraction
        of one by :func:`_phase_offset` where the bits decode.
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
def _distance_table() -> NDArray[np.int8]:
    """Hamming distance of every 16-bit word to the nearest rotation of any code.

    A distance transform on the 16-cube: start at 0 on the code rotations and relax across every
    single-bit edge until nothing changes (a few passes, once per process, ~20 ms); a lookup then
    replaces comparing each word read with all code rotations on every frame.
    """
    dist = np.full(1 << BITS, BITS + 1, dtype=np.int8)
    dist[_decode_table()[2] == 0] = 0
    words = np.arange(1 << BITS)
    changed = True
    while changed:
        changed = False
        for bit in range(BITS):
            step = dist[words ^ (1 << bit)] + 1
            better = step < dist
            if better.any():
                dist[better] = step[better]
                changed = True
    return dist


def _rot2(angle: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (N, 2, 2)


def _track_maps(
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    r0: float,
    drift: NDArray[np.float64],
    radii: NDArray[np.float64],
    params: NDArray[np.float64],
    dtype: type[np.floating[Any]] = np.float64,
) -> tuple[NDArray[Any], NDArray[Any]]:
    """Columns ``u`` and rows ``v`` of :func:`track_points`, each (N, K) of ``dtype``.

    Each coordinate is a fixed linear combination of four per-candidate terms (centre, drift,
    and the two columns of ``R diag(a, b)``) with four per-point weights, so both maps are one
    (N, 4) x (4, K) matrix product: far cheaper than broadcasting over (N, K) term by term, and
    cheaper still in float32 (the type ``cv2.remap`` wants). The product works relative to the
    whole pixel nearest each centre, added last, so float32 keeps its ~1e-5 px resolution on
    the small offsets and rounds only once at the frame's scale.
    """
    weights = _track_weights(r0, radii, params, dtype)
    c, s = np.cos(angle), np.sin(angle)
    a, b = axes[:, 0], axes[:, 1]
    whole = np.round(centre)
    frac = centre - whole
    u = np.column_stack([frac[:, 0], drift[:, 0], c * a, -s * b]).astype(dtype) @ weights
    v = np.column_stack([frac[:, 1], drift[:, 1], s * a, c * b]).astype(dtype) @ weights
    u += whole[:, 0:1].astype(dtype)
    v += whole[:, 1:2].astype(dtype)
    return u, v


def _track_weights(
    r0: float,
    radii: NDArray[np.float64],
    params: NDArray[np.float64],
    dtype: type[np.floating[Any]],
) -> NDArray[Any]:
    """``(4, K)`` per-point weights of :func:`_track_maps`' four per-candidate terms."""
    scale = radii / r0
    return np.stack(
        [np.ones_like(radii), radii**2 - r0**2, np.cos(params) * scale, -np.sin(params) * scale]
    ).astype(dtype)


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
    return np.stack(_track_maps(centre, axes, angle, r0, drift, radii, params), axis=-1)


def _sample_points(
    image: NDArray[Any],
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    r0: float,
    drift: NDArray[np.float64],
    radii: NDArray[np.float64],
    params: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """:func:`_sample` at the points of :func:`track_points` (arguments as there)."""
    kind = KERNEL_KINDS.get(image.dtype)
    if kind is not None and image.ndim == 2 and image.flags.c_contiguous and min(image.shape) > 1:
        # The kernel makes each candidate's points as :func:`_track_maps` does (float32,
        # relative to the whole pixel nearest the centre) while sampling the previous one's.
        n, k = len(centre), len(radii)
        out = np.empty((n, k), dtype=np.float32)
        outside = np.empty((n, k), dtype=np.uint8)
        _profile_kernel.sample_tracks(
            image,
            kind,
            image.shape[0],
            image.shape[1],
            np.ascontiguousarray(centre, dtype=np.float64),
            np.ascontiguousarray(axes, dtype=np.float64),
            np.ascontiguousarray(angle, dtype=np.float64),
            np.ascontiguousarray(drift, dtype=np.float64),
            np.ascontiguousarray(_track_weights(r0, radii, params, np.float32)),
            out,
            outside,
        )
        return out, outside.view(np.bool_)
    u, v = _track_maps(centre, axes, angle, r0, drift, radii, params, np.float32)
    return _sample(image, u, v, _near_border(centre, axes, angle, r0, drift, radii, image.shape))


#: Slack (pixels) of :func:`_near_border`'s bound over the float32 maps' rounding (~1e-4 px).
_NEAR_SLACK_PX = 0.01


def _near_border(
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    r0: float,
    drift: NDArray[np.float64],
    radii: NDArray[np.float64],
    shape: tuple[int, ...],
) -> NDArray[np.bool_]:
    """Candidates some of whose points at printed ``radii`` may lie outside the image: every
    one with a point outside, and a few near the border (a bound per candidate, instead of the
    extremes of all its points).

    A point lies ``drift (r^2 - r0^2) + (r / r0) R diag(a, b) [cos t, -sin t]^T`` from the
    centre: per axis at most ``|drift| max |r^2 - r0^2|`` plus ``max r / r0`` times the
    amplitude of that sinusoid in ``t``.
    """
    c, s = np.cos(angle), np.sin(angle)
    a, b = axes[:, 0], axes[:, 1]
    scale = float(np.max(np.abs(radii))) / r0
    shift = float(np.max(np.abs(radii**2 - r0**2)))
    reach_u = np.abs(drift[:, 0]) * shift + scale * np.hypot(c * a, s * b) + _NEAR_SLACK_PX
    reach_v = np.abs(drift[:, 1]) * shift + scale * np.hypot(s * a, c * b) + _NEAR_SLACK_PX
    h, w = shape[:2]
    u, v = centre[:, 0], centre[:, 1]
    return np.asarray(
        (u - reach_u < 0) | (u + reach_u > w - 1) | (v - reach_v < 0) | (v + reach_v > h - 1),
        dtype=bool,
    )


def _sample(
    image: NDArray[Any],
    u: NDArray[np.float32],
    v: NDArray[np.float32],
    near: NDArray[np.bool_],
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Bilinear samples of ``image`` at ``(u, v)`` (each (N, K)), and where they left the image;
    ``near``: the candidates (rows) whose points may have (:func:`_near_border`), the only ones
    tested point by point.

    OpenCV interpolates in the image's own type (an 8-bit image gives 8-bit samples, ample for
    telling black from white), so the full frame is never converted to float (8/16-bit and
    float32 images take the kernel's :func:`_sample_points` instead, which samples alike). The
    samples come back as float32: integer samples and the sums of up to 12 of them stay exact
    in float32, so the rest of the reader works on exact integers for integer images.

    Returns
    -------
    samples : (N, K) float32
        Samples in the image's units; 0 where the point left the image.
    outside : (N, K) bool
        Points outside the image (their samples are not to be used).
    """
    n, k = u.shape
    out = np.empty((n, k), dtype=np.float32)
    for start in range(0, n, _MAX_REMAP_ROWS):
        stop = start + _MAX_REMAP_ROWS
        got = cv2.remap(
            image,
            u[start:stop],
            v[start:stop],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        out[start:stop] = got
    h, w = image.shape
    outside = np.zeros((n, k), dtype=bool)
    if near.any():
        un, vn = u[near], v[near]
        outside[near] = (un < 0) | (un > w - 1) | (vn < 0) | (vn > h - 1)
    return out, outside


def _median_pair_sum(samples: NDArray[np.float32]) -> NDArray[np.float32]:
    """Twice the median along axis 1 (the sum of the two middle values; even count).

    A full sort of these short rows (vectorised) is several times faster than ``np.partition``.
    """
    m = samples.shape[1] // 2
    ordered = np.sort(samples, axis=1)
    return np.asarray(ordered[:, m - 1] + ordered[:, m], dtype=np.float32)


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
        The track is read only for candidates that pass rules 1-3 on their reference regions;
        for the others ``bits`` and ``margin`` are zeros (and ``code``, ``rotation_sector`` and
        ``rotation`` those of an all-white track), and levels are NaN where their samples left
        the image.
    """
    cfg = config or ReaderConfig()
    n = len(centre)
    r0 = design.pose_circle.radius
    k = np.zeros((n, 2)) if drift is None else drift
    sector = 2.0 * np.pi / BITS
    n_ang = BITS * _PER_SECTOR
    step = 2.0 * np.pi / n_ang

    # Rules 1-3 on the reference regions first: they reject most candidates (code sectors,
    # clutter) from a fifth of the samples, and only the survivors' tracks are sampled.
    black_r, white_r = _reference_rings(design)
    ref_t = (np.arange(_REF_ANGLES) + 0.25) * (2.0 * np.pi / _REF_ANGLES)
    ref_r = np.repeat(np.array([*black_r, *white_r]), _REF_ANGLES)
    ref_t_all = np.tile(ref_t, len(black_r) + len(white_r))
    refs, outside = _sample_points(image, centre, axes, angle, r0, k, ref_r, ref_t_all)
    n_black = len(black_r) * _REF_ANGLES
    black_s, white_s = refs[:, :n_black], refs[:, n_black:]
    # Everything below works on sums of samples, exact for integer images: ``ring`` is 3 samples
    # per angle, a sector value 4 angles (12 samples), the mid level ``q / 4`` with ``q`` the sum
    # of the two middle black and the two middle white reference samples (medians of an even
    # count). So "sector darker than mid" is ``sum12 < 3 q``, free of rounding ties.
    black2 = _median_pair_sum(black_s)
    white2 = _median_pair_sum(white_s)
    q = black2 + white2
    # Levels as fractions of full scale; NaN where a reference sample left the image.
    black = black2.astype(np.float64) / (2.0 * full_scale)
    white = white2.astype(np.float64) / (2.0 * full_scale)
    black[outside[:, :n_black].any(axis=1)] = np.nan
    white[outside[:, n_black:].any(axis=1)] = np.nan
    contrast = white - black
    black_bad = (4.0 * black_s > q[:, None]).mean(axis=1)
    white_bad = (4.0 * white_s < q[:, None]).mean(axis=1)
    with np.errstate(invalid="ignore"):
        ok = contrast >= cfg.min_contrast  # False for NaN levels: rule 1 on the references
    ok &= (black_bad <= cfg.max_ref_outliers) & (white_bad <= cfg.max_ref_outliers)

    # The track, radius-major (all angles of one radius together): the radial sum is then a sum
    # of contiguous blocks.
    read = np.nonzero(ok)[0]
    width = design.track_outer - design.track_inner
    n_rad = len(_RAD)
    t_all = np.tile((np.arange(n_ang) + 0.5) * step, n_rad)
    r_all = np.repeat(design.track_inner + _RAD * width, n_ang)
    vals, outside = _sample_points(
        image, centre[read], axes[read], angle[read], r0, k[read], r_all, t_all
    )
    ok[read] = ~outside.any(axis=1)  # rule 1 on the track
    ring = vals[:, 0:n_ang].copy()
    for j in range(1, n_rad):
        ring += vals[:, j * n_ang : (j + 1) * n_ang]
    phase = np.zeros(n, dtype=np.int64)
    diff = np.zeros((n, BITS), dtype=np.float32)
    phase[read], diff[read] = _sector_phase(ring, 3.0 * q[read])
    consistent = ok.copy()
    bits = ((diff < 0) & ok[:, None]).astype(np.uint8)
    phase[~ok] = 0
    # |sector mean - mid| / (contrast / 2) = |sum12 - 3 q| / (3 (sum white2 - sum black2)), one
    # correctly rounded division of exact integers (for integer images).
    den = np.maximum(3.0 * (white2 - black2).astype(np.float64), 12.0 * full_scale * 1e-9)
    margin = np.abs(diff).astype(np.float64) / den[:, None]
    margin[~ok] = 0.0

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
    nearest = np.where(consistent, _distance_table()[words], BITS + 1).astype(np.int64)
    dist = np.where(ok, dist, BITS + 1)

    # Boundary between the code's sectors 15 and 0 sits at read index (BITS - rot) % BITS, at the
    # phase found to a step plus its sub-step offset (kept at 0 where the code did not decode or
    # the track left the image).
    offset = np.zeros(n)
    refine = consistent[read] & (code[read] >= 0)
    rows = read[refine]
    if rows.size:
        offset[rows] = _phase_offset(ring[refine], phase[rows], expected[rows], diff[rows])
    t_b = ((BITS - rot) % BITS) * sector + (phase + offset) * step
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
        margin=margin,
        black=black,
        white=white,
        rotation=rotation,
    )


def _sector_phase(
    ring: NDArray[np.float32], mid3: NDArray[np.float32]
) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """The sector phase that best separates black from white, and the sectors' offsets there.

    The ellipse parameter ``t`` starts at an arbitrary printed angle, so sector boundaries can fall
    anywhere among the ``_PER_SECTOR`` samples of a sector; each phase is tried and the one whose
    sectors lie farthest from the mid level (in total) is kept (the first of equals).

    Parameters
    ----------
    ring : (N, BITS * _PER_SECTOR) float32
        Per-angle sums over the track's radii.
    mid3 : (N,) float32
        The mid level in units of a sector sum (``_CORE`` angles of ``ring``).

    Returns
    -------
    phase : (N,) int64
        Sector 0 starts at angle ``phase``.
    diff : (N, BITS) float32
        Sum of the ``_CORE`` middle angles of each sector minus ``mid3``.
    """
    n, n_ang = ring.shape
    skip = (_PER_SECTOR - _CORE) // 2
    # Window sums of _CORE consecutive angles starting at every angle + skip (circularly); the
    # window of sector i at phase p starts at angle i * _PER_SECTOR + p + skip.
    ext = np.concatenate([ring[:, skip:], ring[:, : skip + _CORE - 1]], axis=1)
    window = ext[:, 0:n_ang] - mid3[:, None]
    for j in range(1, _CORE):
        window += ext[:, j : j + n_ang]
    diff_all = window.reshape(n, BITS, _PER_SECTOR)  # [candidate, sector, phase]
    phase = np.abs(diff_all).sum(axis=1).argmax(axis=1)
    return phase.astype(np.int64), diff_all[np.arange(n), :, phase]


def _phase_offset(
    ring: NDArray[np.float32],
    phase: NDArray[np.int64],
    expected: NDArray[np.uint8],
    diff: NDArray[np.float32],
) -> NDArray[np.float64]:
    """Sub-step offset of the sector boundaries from the phase :func:`_sector_phase` found.

    Boundary ``i`` (between sectors ``i - 1`` and ``i`` as read) gets the window of samples from
    the middle of sector ``i - 1`` to the middle of sector ``i``, and their sum ``S_i``. An edge
    at the window's centre, symmetric about the mid level ``M``, gives ``S_i = 8 M``; shifting
    the whole pattern by ``x`` steps changes ``S_i`` by ``-x (v_i - v_{i-1})``, with ``v`` the
    levels at the sectors' middles (the means of their ``_CORE`` middle samples), the values
    the window's two ends take. With ``g_i`` the colour change the code's bits make there (+1
    black to white, -1 white to black, 0 none; a corrected sector counts as printed), one
    least-squares (Gauss-Newton) step on all edges at once gives::

        x = -sum_i g_i S_i / sum_i g_i (v_i - v_{i-1})

    ``M`` drops out exactly: round a closed track there are as many rises as falls, so
    ``sum_i g_i = 0``. So does any error in it, such as the ``ring`` annulus' blur greying the
    track's white sectors (it moves every rise's crossing one way and every fall's the other
    way by the same amount), and so does most of the pull the blur of a lone sector's two
    opposite edges puts on each other's windows. The estimate is linear in the samples, so
    noise does not bias it; a crossing interpolated between the two samples straddling the mid
    level is not linear (and had up to 3x the RMS error on the renders). A window's sum equals
    the integral of the blurred edge up to a ripple periodic in its position, ``exp(-2 pi^2
    s^2) / pi`` of a step for a Gaussian blur of ``s`` steps (0.002 at ``s = 0.5``, 0.05 at
    0.3); edges blurred over more than a step lose tails beyond their windows (up to 0.013 of
    a step at ``s = 1.2``, 0.04 at 2, on noise-free synthetic tracks). A step is 0.44 px on a
    33 px ``ring`` fiducial's track, 0.8 px at 60 px.

    Parameters
    ----------
    ring : (N, BITS * _PER_SECTOR) float32
        Per-angle sums over the track's radii, sample ``j`` at ``t = (j + 0.5) * step``.
    phase : (N,) int64
        Sector 0 as read starts at ``t = phase * step``.
    expected : (N, BITS) uint8
        The decoded code's bits in the order read (1 = black).
    diff : (N, BITS) float32
        Sector sums of :func:`_sector_phase` (their mid-level offset cancels in differences).

    Returns
    -------
    (N,) float64
        Offset in steps: the boundaries lie at ``t = (phase + offset + i * _PER_SECTOR) * step``.
        0 (the phase as found) where it cannot be estimated: no colour change, NaN, a
        non-positive sensitivity, or an offset beyond half a window, where the edges would
        have left their windows and the linear model no longer holds.
    """
    n, n_ang = ring.shape
    half = _PER_SECTOR // 2
    # Row r of ``ext`` holds samples -half .. n_ang + half - 2 (circularly), and element j of
    # ``sums`` the sum of ext's flat elements j .. j + _PER_SECTOR - 1 (pairwise sums over the
    # flat array: contiguous, so 1.5-2x faster than row by row; exact in float32 for integer
    # images, as in _sector_phase). Boundary i, between samples b - 1 and b with
    # b = phase + i * _PER_SECTOR, has its window at flat index r * row + b.
    ext = np.concatenate([ring[:, -half:], ring, ring[:, : half - 1]], axis=1)
    row = ext.shape[1]
    sums = ext.ravel()
    width = 1
    while width < _PER_SECTOR:
        sums = sums[:-width] + sums[width:]
        width *= 2
    start = (np.arange(n) * row + phase)[:, None] + np.arange(0, n_ang, _PER_SECTOR)
    window = sums[start].astype(np.float64)
    bits = expected.astype(np.float64)
    change = np.roll(bits, 1, axis=1) - bits  # +1 where the track turns from black to white
    level = diff.astype(np.float64)
    num = -(change * window).sum(axis=1)
    den = (change * (level - np.roll(level, 1, axis=1))).sum(axis=1) * (1.0 / _CORE)
    offset = np.divide(num, den, out=np.zeros(n), where=den > 0.0)
    offset[~(np.abs(offset) < half)] = 0.0  # NaN included
    return offset


#: Effective blur (Gaussian standard deviation, image pixels: optics, pixel footprint and
#: bilinear sampling together) tried by :func:`model_read`; the best-fitting one is kept.
MODEL_BLUR_PX = (0.65, 0.9, 1.2)
#: Sector phases tried by :func:`model_read`, per sector.
_MODEL_PHASES = 8
#: Angles per sector and printed radii (fractions of the outer radius, relative to the track:
#: ``track_inner + f * width``) sampled by :func:`model_read`; the samples beside the track fix
#: the black and white levels and see the sectors' bleeding.
_MODEL_PER_SECTOR = 4
_MODEL_RAD = np.array([-0.2, 0.1, 0.3, 0.5, 0.7, 0.9, 1.2])


@dataclass(frozen=True, slots=True, eq=False)
class ModelReading:
    """Codes read by :func:`model_read` for N candidates.

    Attributes
    ----------
    code, rotation_sector : (N,) int64
        Best code and the code's sector read first (from ``phase`` onwards).
    phase : (N,) float64
        Ellipse parameter ``t`` at which the first sector read starts, radians.
    rms : (N,) float64
        Root-mean-square residual of the best code's model, as a fraction of the samples'
        spread (95th minus 5th percentile); NaN where samples left the image.
    separation : (N,) float64
        Residual sum of squares of the best *other* code minus the best code's, in units of the
        image noise variance: the log-likelihood ratio (times two) of the two codes.
    """

    code: NDArray[np.int64]
    rotation_sector: NDArray[np.int64]
    phase: NDArray[np.float64]
    rms: NDArray[np.float64]
    separation: NDArray[np.float64]


def model_read(
    image: NDArray[Any],
    design: FiducialDesign,
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    drift: NDArray[np.float64] | None,
    noise_std: float,
) -> ModelReading:
    """Read coding tracks by fitting a blurred image model of every code (small, slanted tracks).

    Where a sector images to a pixel or two, blur mixes it with its neighbours and with the
    printed black regions beside the track: a lone sector loses much of its contrast and white
    sectors next to the ``ring`` design's annulus turn grey, so thresholding sector means (rule
    5 of :func:`read_codes`) finds weak sectors on a correct read. The mixing is linear and known
    from the ellipse: through the affine map of the pose ellipse, a Gaussian blur of ``s``
    pixels is a Gaussian on the printed face with covariance ``s^2 r0^2 diag(1/a^2, 1/b^2)``
    (in the frame of the ellipse parameter), so the expected grey level of every sample is
    ``white - contrast * m``, with ``m`` the probability mass of black within the blur: the known
    black regions plus each black sector's (separable in printed radius and angle). Every
    rotation of every code is fitted (levels by linear least squares) for each blur in
    :data:`MODEL_BLUR_PX` and each sector phase; the best code is returned with its residual
    and its margin over the best other code.

    Parameters
    ----------
    image : (H, W) ndarray
        Grey image indexed ``[v, u]``.
    design : FiducialDesign
    centre, axes, angle, drift
        Pose ellipses of the candidates (see :func:`track_points`); ``drift`` defaults to zero.
    noise_std : float
        Image noise standard deviation in ``image``'s units.

    Returns
    -------
    ModelReading
    """
    n = len(centre)
    r0 = design.pose_circle.radius
    k = np.zeros((n, 2)) if drift is None else drift
    n_ang = BITS * _MODEL_PER_SECTOR
    sector = 2.0 * np.pi / BITS
    t = (np.arange(n_ang) + 0.5) * (2.0 * np.pi / n_ang)
    width = design.track_outer - design.track_inner
    radii = design.track_inner + _MODEL_RAD * width
    r_all = np.repeat(radii, n_ang)
    t_all = np.tile(t, len(radii))
    vals, outside = _sample_points(image, centre, axes, angle, r0, k, r_all, t_all)
    black_bands = [(0.0, design.dot_radius)]
    if design.annulus_inner is not None:
        black_bands.append((design.annulus_inner, 1.0))
    words, pairs = _word_tables()
    n_codes = rotation_table().shape[0]
    # Sector starts for every phase (in steps of a sector / _MODEL_PHASES).
    phases = np.arange(_MODEL_PHASES) * (sector / _MODEL_PHASES)
    code = np.zeros(n, dtype=np.int64)
    rot = np.zeros(n, dtype=np.int64)
    phase_out = np.zeros(n)
    rms = np.full(n, np.nan)
    separation = np.full(n, -np.inf)
    noise2 = max(float(noise_std), 1e-6) ** 2
    ct, st = np.cos(t_all), np.sin(t_all)
    # Angle from every sample to the start of every sector at every phase, wrapped to
    # [-pi, pi): (K, phases, BITS). Sector i spans starts i .. i + 1.
    start = phases[:, None] + np.arange(BITS) * sector
    d = ((start[None, :, :] - t_all[:, None, None] + np.pi) % (2.0 * np.pi) - np.pi).astype(
        np.float32
    )
    wraps = np.roll(d, -1, axis=2) < d  # the sector opposite the sample: its end wrapped round
    iu = np.triu_indices(BITS)
    for j in range(n):
        if outside[j].any():
            continue
        s = vals[j].astype(np.float64)
        sc = s - s.mean()
        a, b = axes[j]
        # Blur per pixel of image blur, on the printed face: radial (fraction of the outer
        # radius) and along the angle (radians).
        rad_unit = r0 * np.sqrt((ct / a) ** 2 + (st / b) ** 2)
        ang_unit = r0 * np.sqrt((st / a) ** 2 + (ct / b) ** 2) / r_all
        # Per (blur, phase): the centred model m = kc + rc @ word (the level w drops out), whose
        # sums of m^2 and m * s are quadratic and linear forms in the word.
        quad, lin, const = [], [], []
        for blur in MODEL_BLUR_PX:
            sr = blur * rad_unit
            known = np.zeros_like(s)
            for lo, hi in black_bands:
                known += _normal_cdf((hi - r_all) / sr) - _normal_cdf((lo - r_all) / sr)
            track = _normal_cdf((design.track_outer - r_all) / sr) - _normal_cdf(
                (design.track_inner - r_all) / sr
            )
            cdf = _normal_cdf(d * (1.0 / (blur * ang_unit)).astype(np.float32)[:, None, None])
            resp = np.roll(cdf, -1, axis=2) - cdf + wraps
            resp *= track[:, None, None].astype(np.float32)
            rc = resp.transpose(1, 0, 2).astype(np.float64)  # (phases, K, BITS)
            rc -= rc.mean(axis=1, keepdims=True)
            kc = known - known.mean()
            gram = rc.transpose(0, 2, 1) @ rc  # (phases, BITS, BITS)
            quad.append(gram[:, iu[0], iu[1]])
            lin.append(np.stack([rc.transpose(0, 2, 1) @ kc, rc.transpose(0, 2, 1) @ sc], -1))
            const.append((kc @ kc, kc @ sc))
        q = np.concatenate(quad)  # (combos, pairs)
        ln = np.concatenate(lin)  # (combos, BITS, 2)
        kk = np.repeat([c[0] for c in const], _MODEL_PHASES)
        ks = np.repeat([c[1] for c in const], _MODEL_PHASES)
        smm = kk + 2.0 * (words @ ln[:, :, 0].T) + pairs @ q.T  # (words, combos)
        sms = ks + words @ ln[:, :, 1].T
        # Levels by least squares; the black-minus-white gain must be positive.
        res = float(sc @ sc) - np.where(sms < 0.0, sms**2 / np.maximum(smm, 1e-12), 0.0)
        per = res.reshape(n_codes, BITS * res.shape[1])  # (code, rotation x combo)
        pick = per.argmin(axis=1)
        best = per[np.arange(n_codes), pick]
        order = np.argsort(best)
        c1, c2 = int(order[0]), int(order[1])
        rot[j], combo = divmod(int(pick[c1]), res.shape[1])
        code[j] = c1
        phase_out[j] = phases[combo % _MODEL_PHASES]
        separation[j] = (best[c2] - best[c1]) / noise2
        rms[j] = np.sqrt(max(best[c1], 0.0) / len(s)) / max(_contrast_of(vals[j]), 1e-9)
    return ModelReading(code, rot, phase_out, rms, separation)


@lru_cache(maxsize=1)
def _word_tables() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Every rotation of every code as a (codes * BITS, BITS) 0/1 matrix, and the products
    ``b_i b_j`` (``i <= j``, doubled off the diagonal) that turn a Gram matrix's upper triangle
    into the quadratic form ``b^T G b`` by one matrix product."""
    words = rotation_table().reshape(-1, BITS).astype(np.float64)
    iu = np.triu_indices(BITS)
    pairs = words[:, iu[0]] * words[:, iu[1]] * np.where(iu[0] == iu[1], 1.0, 2.0)
    return words, pairs


def _normal_cdf(x: NDArray[Any]) -> NDArray[Any]:
    """Standard normal distribution function, within 1.5e-4 (Bowling et al. 2009's logistic
    approximation; five times cheaper than ``scipy.special.ndtr``, ample for blur weights)."""
    z = np.clip(x, -8.0, 8.0)
    y = z * z
    y *= 0.07056
    y += 1.5976
    y *= -z
    np.exp(y, out=y)
    y += 1.0
    return np.reciprocal(y, out=y)


def _contrast_of(samples: NDArray[Any]) -> float:
    """Robust spread of a candidate's samples: 95th minus 5th percentile."""
    lo, hi = np.percentile(samples, [5.0, 95.0])
    return float(hi - lo)
