"""The detector: image -> fiducials (paper section 3, steps 1-4).

Pipeline, designed so that only cheap vectorised work touches every pixel or every boundary:

1. Bradley & Roth adaptive threshold of an 8-bit copy, plus a thin-dark-line test
   (:mod:`.threshold`), full resolution.
2. Outer boundaries of the black components (:mod:`.components`) with step 2's length limits,
   each summarised by its moment ellipse (a broken thin ring by its convex hull's). Conservative
   tests on size, ellipticity and eccentricity (vectorised) keep the boundaries that can be a
   design's pose circle: the ``ring`` design's outer annulus edge, the ``dot`` design's dot.
3. The coding track of every candidate is read at once through its coarse ellipse
   (:mod:`.code_reader`, step 4): clutter, code sectors and the other design's parts are rejected
   here, before any expensive step. Candidates that look like fiducials but read poorly get their
   pose circle fitted and are read again.
4. Only decoded candidates get sub-pixel ellipses for every printed circle of their design
   (Ouellet & Hébert dual conic from gradients, :mod:`.ellipse`, step 3), seeded by the coarse
   ellipse scaled to each circle; the track is read again through the fitted ellipses and the
   centre drift they give, and two accepted reads must agree.
5. A detection centred inside a bigger one (a ``ring`` fiducial's dot and track read as a ``dot``
   fiducial) is dropped.

Pixel convention: ``(u, v)`` = (x, y) = (column, row), pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .code_reader import DEFAULT_MIN_CONTRAST, ReaderConfig, TrackReading, read_codes
from .components import Boundaries, outer_boundaries
from .design import DESIGNS, DOT, RING, FiducialDesign
from .ellipse import estimate_noise, fit_ellipses
from .errors import DetectorError
from .threshold import DEFAULT_T, bradley_threshold
from .types import Ellipse, FiducialDetection

DesignChoice = Literal["ring", "dot", "any"]

#: Smallest imaged outer diameter (pixels) the detector looks for, for each design's pose circle.
MIN_OUTER_DIAMETER_PX = 18.0
#: Step 3's conservative shape tests on a boundary's moment ellipse: area over ellipse area, and
#: minor over major axis (0.15 is a circle slanted 81 deg).
MIN_ELLIPTICITY = 0.85
#: Candidates that look like fiducials but read at most this far from a code get their pose
#: ellipse fitted and are read again (small fiducials' coarse ellipses are poor).
RETRY_MAX_DISTANCE = 1
#: Fitted pose ellipses thinner than this (semi-minor axis, pixels; a 35 px ``dot`` fiducial
#: beyond about 70 deg slant) predict the coding track poorly: their reads must be exact with at
#: most one sector below 0.4 of the reference contrast (the benchmark saw exact reads of wrong
#: codes there, with several sectors at 0.1-0.5).
THIN_POSE_MINOR_PX = 2.0
THIN_MAX_WEAK_BITS = 1
THIN_WEAK_MARGIN = 0.4
MIN_ASPECT = 0.15


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    """Parameters of :func:`detect` (see its docstring)."""

    design: DesignChoice = "any"
    threshold_window: int | None = None
    threshold_t: float = DEFAULT_T
    min_diameter_px: float = MIN_OUTER_DIAMETER_PX
    max_diameter_px: float | None = None
    reader: ReaderConfig = field(default_factory=ReaderConfig)


@dataclass(frozen=True, slots=True, eq=False)
class _Candidates:
    """Coarse pose ellipses of N candidates of one design."""

    design: FiducialDesign
    centre: NDArray[np.float64]  # (N, 2)
    axes: NDArray[np.float64]  # (N, 2) semi-axes a >= b
    angle: NDArray[np.float64]  # (N,)
    drift: NDArray[np.float64]  # (N, 2)


def detect(
    image: NDArray[np.generic],
    *,
    design: DesignChoice = "any",
    threshold_window: int | None = None,
    threshold_t: float = DEFAULT_T,
    min_diameter_px: float = MIN_OUTER_DIAMETER_PX,
    max_diameter_px: float | None = None,
    max_hamming: int = 1,
    min_contrast: float = DEFAULT_MIN_CONTRAST,
) -> list[FiducialDetection]:
    """Find armourcam fiducials in an image.

    Parameters
    ----------
    image : (H, W) or (H, W, C) ndarray
        Grey, BGR or BGRA image (OpenCV channel order) of dtype uint8, uint16, float32 or float64
        (floats in ``[0, 1]``), indexed ``[v, u]``.
    design : {"any", "ring", "dot"}
        Which fiducial design to look for; ``"any"`` finds both in one image.
    threshold_window, threshold_t
        Bradley & Roth window side (pixels, default one eighth of the larger image side, at least
        101) and relative darkness.
    min_diameter_px, max_diameter_px : float
        Range of imaged outer diameters (fronto-parallel equivalent) to look for; the default
        maximum is the smaller image side.
    max_hamming : {0, 1}
        Largest accepted Hamming distance to a code.
    min_contrast : float
        Smallest accepted white-minus-black contrast, fraction of full scale.

    Returns
    -------
    list of FiducialDetection
        Sorted by ``(v, u)`` of the centre. Centres and ellipses in pixels ``(u, v)``, pixel
        centres at integer coordinates.

    Raises
    ------
    DetectorError
        If the image has an unsupported shape, dtype or value range, or a parameter is invalid.
    """
    if design not in ("any", "ring", "dot"):
        raise DetectorError(f"design must be 'any', 'ring' or 'dot', got {design!r}")
    if max_hamming not in (0, 1):
        raise DetectorError(f"max_hamming must be 0 or 1, got {max_hamming}")
    if not 0.0 < min_contrast < 1.0:
        raise DetectorError(f"min_contrast must be in (0, 1), got {min_contrast}")
    if not min_diameter_px > 0:
        raise DetectorError(f"min_diameter_px must be > 0, got {min_diameter_px}")
    config = DetectorConfig(
        design=design,
        threshold_window=threshold_window,
        threshold_t=threshold_t,
        min_diameter_px=float(min_diameter_px),
        max_diameter_px=max_diameter_px,
        reader=ReaderConfig(min_contrast=min_contrast, max_hamming=max_hamming),
    )
    grey, full_scale = to_grey(image)
    return detect_grey(grey, full_scale, config)


def to_grey(image: NDArray[np.generic]) -> tuple[NDArray[np.generic], float]:
    """Validate an image and convert it to one channel; returns it with its full-scale value.

    The full-scale value is 255 for uint8, 1.0 for floats and ``2**k - 1`` for uint16 with ``k``
    the apparent bit depth (the bit length of the image's maximum, at least 8).

    Raises
    ------
    DetectorError
        For anything but a non-empty 2-D or 3-D (1, 3 or 4 channel) uint8/uint16/float array, or a
        float image with values outside ``[0, 1]`` or non-finite values.
    """
    if not isinstance(image, np.ndarray):
        raise DetectorError(f"image must be a numpy array, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise DetectorError(
            f"image must be (H, W) grey or (H, W, 3|4) colour, got shape {image.shape}"
        )
    if min(image.shape[:2]) < 8:
        raise DetectorError(f"image is too small to hold a fiducial: {image.shape}")
    if image.dtype == np.uint8:
        full = 255.0
    elif image.dtype == np.uint16:
        # Full scale of the data's apparent bit depth: a 12-bit camera's frames in 16-bit
        # containers have full scale 4095, not 65535 (contrast is a fraction of it).
        bits = max(8, int(image.max()).bit_length())
        full = float((1 << bits) - 1)
    elif image.dtype in (np.float32, np.float64):
        full = 1.0
        if not np.all(np.isfinite(image)):
            raise DetectorError("float image contains NaN or infinite values")
        lo, hi = float(image.min()), float(image.max())
        if lo < 0.0 or hi > 1.0:
            raise DetectorError(f"float image values must lie in [0, 1], got [{lo:g}, {hi:g}]")
        image = image.astype(np.float32, copy=False)
    else:
        raise DetectorError(
            f"image dtype must be uint8, uint16, float32 or float64, got {image.dtype}"
        )
    if image.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(np.ascontiguousarray(image), code)
    return np.ascontiguousarray(image), full


def _to_uint8(grey: NDArray[Any], full_scale: float) -> NDArray[np.uint8]:
    """8-bit copy for thresholding: uint16 and float images are stretched to their maximum."""
    if grey.dtype == np.uint8:
        return grey
    top = float(grey.max())
    alpha = 255.0 / top if top > 0 else 1.0
    return np.asarray(cv2.convertScaleAbs(grey, alpha=alpha), dtype=np.uint8)


def detect_grey(
    grey: NDArray[np.generic], full_scale: float, config: DetectorConfig
) -> list[FiducialDetection]:
    """:func:`detect` on an already validated one-channel image (see :func:`to_grey`)."""
    h, w = grey.shape
    binary = bradley_threshold(
        _to_uint8(grey, full_scale), window=config.threshold_window, t=config.threshold_t
    )
    max_d = config.max_diameter_px if config.max_diameter_px is not None else float(min(h, w))
    bounds = outer_boundaries(
        binary, max_extent=max_d, min_hull_extent=0.9 * config.min_diameter_px
    )
    found: list[FiducialDetection] = []
    designs = (RING, DOT) if config.design == "any" else (DESIGNS[config.design],)
    for design in designs:
        cands = _candidates(bounds, design, config.min_diameter_px, max_d)
        found += _finish(grey, full_scale, _outside(cands, found), config.reader)
    found = _deduplicate(found)
    found.sort(key=lambda d: (d.center_px[1], d.center_px[0]))
    return found


def _candidates(
    bounds: Boundaries, design: FiducialDesign, min_d: float, max_d: float
) -> _Candidates:
    """Boundaries that could be the pose circle of ``design``: conservative tests on the size the
    fiducial would have, on ellipticity and on eccentricity (vectorised)."""
    r0 = design.pose_circle.radius
    a = bounds.axes[:, 0]
    b = bounds.axes[:, 1]
    outer_d = 2.0 * a / r0
    keep = (outer_d >= min_d) & (outer_d <= max_d)
    keep &= (bounds.ellipticity > MIN_ELLIPTICITY) & (b >= MIN_ASPECT * a) & (b >= 1.0)
    sel = bounds.select(keep)
    n = len(sel)
    return _Candidates(design, sel.centre, sel.axes, sel.angle, np.zeros((n, 2)))


def _outside(cands: _Candidates, found: list[FiducialDetection]) -> _Candidates:
    """Drop candidates that :func:`_deduplicate` would drop anyway, before reading them.

    ``found`` holds detections of a design ranked before ``cands``' (the ``ring`` design comes
    first), so any detection of ``cands`` centred inside one of them is dropped there. A
    candidate's final centre stays within two :func:`_plausible` tolerances of its coarse centre
    (retry fit, then the final fit; ``3 * tol`` bounds both), so a candidate that far inside is
    certain to be dropped: on a ``ring`` frame, the ``dot`` reading of every ring's own dot,
    track and sectors costs nothing.
    """
    if not found or len(cands.centre) == 0:
        return cands
    centre = np.array([d.center_px for d in found])
    outer = np.array([d.pose_ellipse.semi_major / d.pose_ellipse.radius for d in found])
    margin = 3.0 * (0.25 * cands.axes[:, 1] + 1.5)
    keep = np.ones(len(cands.centre), dtype=bool)
    # Chunks of candidates keep the distance matrix small.
    for lo in range(0, len(cands.centre), 1024):
        c = cands.centre[lo : lo + 1024]
        dist = np.hypot(c[:, None, 0] - centre[None, :, 0], c[:, None, 1] - centre[None, :, 1])
        inside = np.any(dist + margin[lo : lo + 1024, None] < outer[None, :], axis=1)
        keep[lo : lo + 1024] = ~inside
    if np.all(keep):
        return cands
    return _Candidates(
        cands.design, cands.centre[keep], cands.axes[keep], cands.angle[keep], cands.drift[keep]
    )


def _finish(
    grey: NDArray[np.generic],
    full_scale: float,
    cands: _Candidates,
    reader: ReaderConfig,
) -> list[FiducialDetection]:
    """Read codes, fit every circle of the accepted candidates, read again, build results."""
    if len(cands.centre) == 0:
        return []
    design = cands.design
    r0 = design.pose_circle.radius
    first = read_codes(
        grey, full_scale, design, cands.centre, cands.axes, cands.angle, cands.drift, reader
    )
    noise = _noise_std(grey)
    retry = np.nonzero(first.consistent & ~first.accepted & (first.nearest <= RETRY_MAX_DISTANCE))[
        0
    ]
    if retry.size:
        # Second chance for candidates that look like fiducials but whose code did not read:
        # small boundaries give poor coarse ellipses, so fit the pose circle and read again.
        seeds0 = [_scaled_seed(cands, i, 1.0, 0.0) for i in retry.tolist()]
        refits = fit_ellipses(
            grey, seeds0, r0, noise_std=noise, dark_inside=design.pose_circle.dark_inside
        )
        good = [
            (i, e)
            for i, e, s in zip(retry.tolist(), refits, seeds0, strict=True)
            if e is not None and _plausible(e, s)
        ]
        if good:
            gi = np.array([i for i, _ in good])
            cands.centre[gi] = [e.center_px for _, e in good]
            cands.axes[gi] = [(e.semi_major, e.semi_minor) for _, e in good]
            cands.angle[gi] = [e.angle for _, e in good]
            again = read_codes(
                grey,
                full_scale,
                design,
                cands.centre[gi],
                cands.axes[gi],
                cands.angle[gi],
                cands.drift[gi],
                reader,
            )
            for name in TrackReading.__slots__:
                getattr(first, name)[gi] = getattr(again, name)
    idx = np.nonzero(first.accepted)[0]
    if idx.size == 0:
        return []
    seeds: list[Ellipse] = []
    radii: list[float] = []
    polarity: list[bool | None] = []
    for i in idx.tolist():
        for circle in design.circles:
            seeds.append(_scaled_seed(cands, i, circle.radius / r0, circle.radius**2 - r0**2))
            radii.append(circle.radius)
            polarity.append(circle.dark_inside)
    # The design knows each edge's polarity: no vote needed, and thin annuli stay safe.
    fits = fit_ellipses(grey, seeds, radii, noise_std=noise, dark_inside=polarity)
    m = len(design.circles)
    keep: list[int] = []
    fitted: list[tuple[Ellipse, ...]] = []
    for j, i in enumerate(idx.tolist()):
        group = fits[j * m : (j + 1) * m]
        pose = group[0]
        if pose is None or not _plausible(pose, seeds[j * m]):
            continue
        # Inner circles whose fit failed are left out: the pose circle always comes first.
        others = [
            e
            for e, s in zip(group[1:], seeds[j * m + 1 : (j + 1) * m], strict=True)
            if e and _plausible(e, s)
        ]
        keep.append(i)
        fitted.append((pose, *others))
    if not keep:
        return []
    kidx = np.array(keep)
    centre = np.array([f[0].center_px for f in fitted])
    axes = np.array([(f[0].semi_major, f[0].semi_minor) for f in fitted])
    angle = np.array([f[0].angle for f in fitted])
    drift = np.array([_drift(f, r0) for f in fitted])
    second = read_codes(grey, full_scale, design, centre, axes, angle, drift, reader)
    out: list[FiducialDetection] = []
    for j, i in enumerate(kidx.tolist()):
        if second.accepted[j]:
            # Two accepted reads of different codes: something is wrong, report nothing.
            if second.code[j] != first.code[i]:
                continue
            reading, k = second, j
        else:
            # The fitted ellipses did not give a clean read (tiny, very slanted fiducials): the
            # first read passed every rule on its own.
            reading, k = first, i
        if fitted[j][0].semi_minor < THIN_POSE_MINOR_PX:
            weak = int((reading.margin[k] < THIN_WEAK_MARGIN).sum())
            if reading.hamming[k] != 0 or weak > THIN_MAX_WEAK_BITS:
                continue
        out.append(_detection(design, fitted[j], reading, k))
    return out


def _scaled_seed(cands: _Candidates, i: int, scale: float, dr2: float) -> Ellipse:
    """The candidate's coarse pose ellipse scaled to a concentric circle, with centre drift."""
    c = cands.centre[i] + cands.drift[i] * dr2
    return Ellipse(
        center_px=(float(c[0]), float(c[1])),
        semi_major=float(cands.axes[i, 0] * scale),
        semi_minor=float(cands.axes[i, 1] * scale),
        angle=float(cands.angle[i]),
        covariance=np.zeros((5, 5)),
        radius=0.0,
    )


def _plausible(fit: Ellipse, seed: Ellipse) -> bool:
    """A fit that stayed near its seed (conservative thresholds on ellipse properties, step 3)."""
    tol = 0.25 * seed.semi_minor + 1.5
    du = fit.center_px[0] - seed.center_px[0]
    dv = fit.center_px[1] - seed.center_px[1]
    return bool(
        np.hypot(du, dv) < tol
        and abs(fit.semi_major - seed.semi_major) < tol
        and abs(fit.semi_minor - seed.semi_minor) < tol
    )


def _drift(fits: tuple[Ellipse, ...], r0: float) -> NDArray[np.float64]:
    """Centre drift per unit r^2 from the pose ellipse and the smallest other fitted circle."""
    if len(fits) < 2:
        return np.zeros(2)
    other = fits[-1]
    d = np.subtract(fits[0].center_px, other.center_px)
    return np.asarray(d / (r0**2 - other.radius**2), dtype=np.float64)


def _noise_std(grey: NDArray[np.generic]) -> float:
    """Image noise for the ellipse covariances, estimated once per image.

    Large images are sampled in nine 128 x 128 tiles (the estimator is a robust median, and
    the noise is stationary), which keeps this to a millisecond on a full frame.
    """
    h, w = grey.shape
    tile = 128
    if h * w <= 9 * tile * tile:
        return float(estimate_noise(grey))
    vs = np.linspace(0, h - tile, 3).astype(int)
    us = np.linspace(0, w - tile, 3).astype(int)
    tiles = [grey[v : v + tile, u : u + tile] for v in vs for u in us]
    return float(estimate_noise(np.vstack(tiles)))


def _detection(
    design: FiducialDesign, ellipses: tuple[Ellipse, ...], reading: TrackReading, j: int
) -> FiducialDetection:
    pose = ellipses[0]
    return FiducialDetection(
        code=int(reading.code[j]),
        hamming=int(reading.hamming[j]),
        center_px=pose.center_px,
        ellipses=ellipses,
        contrast=float(reading.contrast[j]),
        design=design.name,
        rotation=float(reading.rotation[j]),
    )


def _deduplicate(found: list[FiducialDetection]) -> list[FiducialDetection]:
    """Resolve detections of one object: keep the most trustworthy, drop those centred inside it.

    Order of trust: the ``ring`` design first (its pose circle is the fiducial's outer edge, so a
    ``dot`` reading inside it is its own central dot and track, or one of its code sectors), then
    the lower Hamming distance, then the bigger fiducial.
    """
    if len(found) < 2:
        return found
    # Outer printed radius in pixels (major axis).
    outer = np.array([d.pose_ellipse.semi_major / d.pose_ellipse.radius for d in found])
    centre = np.array([d.center_px for d in found])
    rank = sorted(
        range(len(found)),
        key=lambda i: (found[i].design != "ring", found[i].hamming, -outer[i]),
    )
    dist = np.hypot(*(centre[:, None, :] - centre[None, :, :]).transpose(2, 0, 1))
    dropped = np.zeros(len(found), dtype=bool)
    for i in rank:
        if dropped[i]:
            continue
        # Fiducials do not overlap: any other centre within this one's outer radius, or whose
        # own outer radius reaches this centre, is a second reading of the same object.
        same = (dist[i] < outer[i]) | (dist[i] < outer)
        same[i] = False
        dropped |= same
    return [d for d, gone in zip(found, dropped.tolist(), strict=True) if not gone]
