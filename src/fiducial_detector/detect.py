"""The detector: image -> fiducials (paper section 3, steps 1-4).

Pipeline, designed so that only cheap vectorised work touches every pixel or every boundary:

1. Bradley & Roth adaptive threshold of an 8-bit copy, plus a thin-dark-line test
   (:mod:`.threshold`), at full resolution or, with ``decimate``, on the image reduced by
   block means (steps 1-2 only).
2. Outer boundaries of the black components (:mod:`.components`) with step 2's length limits,
   each summarised by its moment ellipse (a broken thin ring by its convex hull's; components
   joined only at pixel corners, such as a slanted dot and a code sector, also by their
   4-connected parts). Conservative
   tests on size, ellipticity and eccentricity (vectorised) keep the boundaries that can be a
   design's pose circle: the ``ring`` design's outer annulus edge, the ``dot`` design's dot.
3. The coding track of every candidate is read at once through its coarse ellipse
   (:mod:`.code_reader`, step 4): clutter, code sectors and the other design's parts are rejected
   here, before any expensive step. Candidates that look like fiducials but read poorly get their
   pose circle fitted and are read again.
4. Only decoded candidates get sub-pixel ellipses for every printed circle of their design
   (step 3, then better: edge profiles along the normals, :mod:`.profile_fit`, by default; the
   maximum-likelihood edge model, :mod:`.edge_fit`, for steep fiducials and with
   ``subpixel="ml"``, and for the ``ring`` design's annulus below 40 px; the paper's Ouellet &
   Hébert dual conic, :mod:`.ellipse`, for the other circles below 40 px and as the last
   resort), the pose circle seeded by the coarse ellipse, the others by the
   fitted pose circle scaled; the track is read again through the fitted ellipses and the
   centre drift they give, and two accepted reads must agree. Accepted ``dot`` fiducials then
   get their track's outer edge fitted on its black sectors (:func:`fit_arcs`): 3.3 times
   the dot, it carries the depth.
5. A detection centred inside a bigger one (a ``ring`` fiducial's dot and track read as a ``dot``
   fiducial) is dropped.

Pixel convention: ``(u, v)`` = (x, y) = (column, row), pixel centres at integer coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .code_reader import (
    DEFAULT_MIN_CONTRAST,
    ReaderConfig,
    TrackReading,
    model_read,
    read_codes,
)
from .components import Boundaries, outer_boundaries
from .design import DESIGNS, DOT, PAPER_RADIUS, RING, Circle, FiducialDesign
from .edge_fit import EdgeFits, refine_annuli, refine_ellipses
from .ellipse import estimate_noise, fit_ellipses
from .errors import DetectorError
from .profile_fit import (
    LINE_SPACING_PX,
    MAX_WINDOW_PX,
    SampledImage,
    line_counts,
    refine_by_profiles_sampled,
    sampled_image,
)
from .threshold import DEFAULT_T, block_means, bradley_threshold, default_window
from .types import Ellipse, FiducialDetection, ellipses_from_rows

DesignChoice = Literal["ring", "dot", "any"]

#: Smallest imaged outer diameter (pixels) the detector looks for, for each design's pose circle.
MIN_OUTER_DIAMETER_PX = 18.0
#: Step 3's conservative shape tests on a boundary's moment ellipse: area over ellipse area, and
#: minor over major axis (0.15 is a circle slanted 81 deg).
MIN_ELLIPTICITY = 0.85
#: Candidates that look like fiducials but read at most this far from a code get their pose
#: ellipse fitted and are read again (small fiducials' coarse ellipses are poor). Two, not one:
#: a 25-35 px ``ring`` fiducial slanted 60-70 deg often reads two sectors off through its
#: moment ellipse and exactly through the fitted one. On the 400-target speed frames this adds
#: no retries (the ``dot`` readings of ``ring`` parts are dropped by :func:`_outside` first).
RETRY_MAX_DISTANCE = 2
#: Coarse pose ellipses thinner than this (semi-minor axis, pixels) are retried up to
#: ``RETRY_THIN_DISTANCE`` sectors off: the moment ellipse of a dot a few pixels thin is off by
#: several degrees (a 35 px ``dot`` fiducial at 65 deg: 5 deg), which the track, 2.6 times
#: farther out, turns into three sectors misread; through the fitted ellipse it reads exactly.
#: On the ``dot`` speed frame this adds five retries (specks that still read nothing).
RETRY_THIN_MINOR_PX = 3.0
RETRY_THIN_DISTANCE = 3
#: Fitted pose ellipses thinner than this (semi-minor axis, pixels; a 35 px ``dot`` fiducial
#: beyond about 70 deg slant) predict the coding track poorly: their reads must be exact with at
#: most one sector below 0.4 of the reference contrast (the benchmark saw exact reads of wrong
#: codes there, with several sectors at 0.1-0.5), unless the model read through the fitted
#: ellipses confirms the code (:data:`MODEL_MAX_RMS`). A read one sector off is confirmed the
#: same way: at 35 px and 70 deg the track read through the fitted ellipse often has one sector
#: blurred past the mid level (margins 0.07-0.2) where the model read fits with RMS 0.15-0.16
#: and a separation over 19 000.
THIN_POSE_MINOR_PX = 2.0
THIN_MAX_WEAK_BITS = 1
THIN_WEAK_MARGIN = 0.4
MIN_ASPECT = 0.15
#: Model-read confirmation (:func:`.code_reader.model_read`) of reads that rule 5 (weak sectors)
#: rejected, per design: largest RMS residual (fraction of the samples' spread) and smallest margin
#: over the best other code (residual sums of squares, in image noise variances). On the recall
#: benchmark's renders, true ``ring`` tracks at 25-60 px and slant <= 70 deg fitted with RMS
#: 0.05-0.13 and margins over 3000; the other design's parts read as a ``ring`` did not come
#: near the RMS limit. The ``dot`` design's model fits worse (its pose circle, the small dot,
#: predicts the track less well) and is used only to confirm exact reads of thin pose ellipses.
MODEL_MAX_RMS = {"ring": 0.14, "dot": 0.2}
MODEL_MIN_SEPARATION = 1000.0
#: Half-width of the pixel band of the maximum-likelihood edge fits (further limited to half-way
#: to the design's neighbouring printed edges).
EDGE_BAND_PX = 2.0
#: Smallest imaged outer radius (pixels) fitted by the edge model, but for an annulus' pose circle.
#: Below it (under 40 px across) the bands that stay clear of the neighbouring printed edges hold
#: few pixels for a single edge. The ``ring`` design's annulus, both of its edges in the model,
#: is fitted at every size (the dual conic's pose circle was 0.02-0.19 px too large at 24-39 px);
#: on the bundled session bag (33-36 px, JPEG quality 92) that leaves wrong matches at 0 and the
#: displaced units as they were, and brings the displacement errors' median from 0.16 to 0.11 mm.
EDGE_MODEL_MIN_RADIUS_PX = 20.0
#: Systematic error (sd, pixels) of the gradient dual-conic fit wherever it gives the pose circle
#: (``Ellipse.systematic_px``): standing in for one that neither the profiles nor the edge model
#: could fit, and the ``dot`` design's dot below the edge model's size. It is biased there, not
#: just noisy (errors in variables and blur: a 120 px circle 0.06-0.08 px small at 2 % noise,
#: 24-39 px rings 0.02-0.19 px large, the dot design's 35 px dot 0.05-0.08 px large), by the same
#: amount in every image of a scene, which its covariance (the scatter) leaves out. On the thirty
#: e2e dolos fields (ring, 33 px, physical blur) the 487 such poses of fiducials in full view
#: were off in depth by a median 3.0 of the scatter's sd (50 % beyond 3); by 0.64 of the scatter
#: and the pose's systematic error from this term together (none beyond 3; a Gaussian's 0.67).
DUAL_CONIC_SYSTEMATIC_PX = 0.05
#: Gauss-Newton iterations of the annulus model below the edge model's smallest size (4 above
#: it; fits leave once converged). A small fiducial's seed is its boundary's moment ellipse, up
#: to 1.5 px off: at 34 px and 40 deg such a seed had not converged after 4 (scale 0.08-0.12 px
#: off), and was within 0.01 px after 8. Larger ones start from seeds good to a fraction of a
#: pixel (the profile fit's, or a boundary whose pixels are smaller relative to it); 8 there
#: cost the 6 MP graph 14 ms per frame, and the quick pose tables at 45-120 px agree within 3 %.
SMALL_ANNULUS_ITERATIONS = 8
#: Gauss-Newton iterations of the edge model (4 elsewhere) where the ``profile`` method hands
#: it only fiducials whose pose circle the profiles fitted, near its seed, but none of whose
#: concentric circles: from that start the fits end within 1e-3 px of 4 iterations' and take
#: 2 ms less on the 400-fiducial frame (its three such fits' evaluations are mostly per-call
#: overhead). Not where the profiles' own pose circle is doubtful: at a 60 px ``dot``
#: fiducial's 75 deg tips it was up to 0.15 px from where 4 iterations end.
PROFILE_START_ITERATIONS = 2
#: Below the edge model's smallest size, annulus fits whose RMS residual exceeds this many times
#: the median of the image's fits (at least the noise) are replaced by the dual conic.
ANNULUS_OUTLIER_CHI = 3.0
#: Sectors of image angle about an annulus in which its fit's residuals are examined for
#: something nearer covering part of it (:func:`_uncovered_annuli`).
COVER_SECTORS = 16
#: A sector is covered where its RMS residual exceeds this many times the image's typical fit
#: and :data:`COVER_RELATIVE` of the fiducial's worst sector (a fit pulled off by the covered
#: part misfits everywhere by less).
COVER_CHI = 3.0
COVER_RELATIVE = 0.5
#: A hidden sector is shown again once the refit fits it within this many times the typical.
COVER_SHOW_CHI = 2.0
#: Refits of a partly covered annulus, each hiding what still stands out.
COVER_ROUNDS = 4
#: Most sectors (of :data:`COVER_SECTORS`) a refit may hide and still stand: half the annulus.
COVER_MAX_HIDDEN = 8
#: Reduction factors :func:`detect` takes for its candidate search (``decimate``).
DECIMATE_FACTORS: tuple[int, ...] = (1, 2, 3, 4)
#: Images smaller than this (reduced pixels, either side) are searched at full resolution.
_MIN_DECIMATED_SIDE = 16
#: Sub-pixel ellipse methods of step 4: ``profile`` (edge profiles along the normals,
#: :mod:`.profile_fit`: fast) and ``ml`` (the maximum-likelihood blurred-edge model of
#: :mod:`.edge_fit`: slower, at the Cramer-Rao bound).
SubpixelMethod = Literal["profile", "ml"]
SUBPIXEL_METHODS: tuple[str, ...] = ("profile", "ml")
#: Arc length between the profile lines of the two largest circles (the pose circle and, in the
#: ``ring`` design, the annulus' inner edge), pixels. Lines a pixel apart share interpolated
#: pixels (their errors correlate by 1/4); 1.5 px apart they nearly do not (1/32), so a third
#: fewer lines lose only about 3 % of centre precision, and take a third off those circles'
#: passes. The small inner circle keeps a line per pixel: seen obliquely it keeps few usable
#: lines, and fewer would send its fiducial to the much slower edge model.
POSE_LINE_SPACING_PX = 1.5
#: Fraction of a pose circle's profile lines that must find its edge; below it the fiducial is
#: fitted by the ``ml`` method instead.
PROFILE_MIN_COVERAGE = 0.5
#: Largest curvature (1/px) at a pose ellipse's tips for the ``profile`` method: beyond it (a
#: 60 px ``dot`` fiducial past about 60 deg of slant) the fiducial gets the ``ml`` fit.
PROFILE_MAX_TIP_CURVATURE = 0.4
#: Fraction of a coding-track arc's profile lines that must find its edge for the arc to be
#: reported (a code has at least five black sectors of 16; the lines near each sector's ends
#: are not used).
ARC_MIN_COVERAGE = 0.1
#: Smallest semi-minor axis (pixels) of a coding-track arc's image for it to be fitted. Thinner,
#: its sectors' ends crowd its few lines and its edge nears the paper's along the minor axis:
#: on the pose benchmark's 45 px fiducials at 66-69 deg (arc semi-minor 8-9 px) the fits that
#: found enough lines were off by several of their sds (chi-square 20-30 on 5), and those that
#: did not were left out, so that depth jumped between the arcs' and the dot's.
ARC_MIN_MINOR_PX = 10.0
#: Arc length between a coding-track arc's profile lines, pixels (as the pose circle's).
ARC_LINE_SPACING_PX = POSE_LINE_SPACING_PX
#: Profile passes of an arc fit: a coarse one (wide windows, measuring the blur) from the scaled
#: pose circle, then full ones.
ARC_PASSES = 3


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    """Parameters of :func:`detect` (see its docstring)."""

    design: DesignChoice = "any"
    threshold_window: int | None = None
    threshold_t: float = DEFAULT_T
    min_diameter_px: float = MIN_OUTER_DIAMETER_PX
    max_diameter_px: float | None = None
    reader: ReaderConfig = field(default_factory=ReaderConfig)
    subpixel: SubpixelMethod = "profile"
    decimate: int = 1


@dataclass(frozen=True, slots=True, eq=False)
class _Candidates:
    """Coarse pose ellipses of N candidates of one design."""

    design: FiducialDesign
    centre: NDArray[np.float64]  # (N, 2)
    axes: NDArray[np.float64]  # (N, 2) semi-axes a >= b
    angle: NDArray[np.float64]  # (N,)
    drift: NDArray[np.float64]  # (N, 2)


class _SampledFrame:
    """A frame as the profile fits sample it (:func:`.profile_fit.sampled_image`: 8 and 16-bit
    and float32 frames as they are, others as one float32 copy), made on first use and then
    shared by every stage and design of the frame: a 6 Mpx copy costs 1-3 ms (more when its
    memory is fresh), and the ``dot`` design's arcs, ``design="any"``'s second design and the
    circles each made their own."""

    __slots__ = ("_grey", "_sampled")

    def __init__(self, grey: NDArray[np.generic]) -> None:
        self._grey = grey
        self._sampled: SampledImage | None = None

    def get(self) -> SampledImage:
        """The whole frame, as the profile fits sample it."""
        if self._sampled is None:
            self._sampled = sampled_image(np.asarray(self._grey))
        return self._sampled


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
    subpixel: SubpixelMethod = "profile",
    decimate: int = 1,
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
    subpixel : {"profile", "ml"}
        Sub-pixel ellipse method (see :func:`fit_design_circles`): ``profile`` is several times
        faster, ``ml`` reaches the Cramer-Rao bound (about half the centre std).
    decimate : {1, 2, 3, 4}
        Find the candidates (threshold and boundaries, steps 1-2) on the image reduced by this
        factor (block means), like AprilTag's ``quad_decimate``; codes are read and every circle
        fitted on the full image, seeded from the reduced boundaries, so the results are those
        of the full search (centres within 0.01 px). 2 takes about 9 ms off a 6 Mpx frame, but
        small fiducials' annuli and dots blur into their surround in the reduced image. On the
        recall benchmark (every degradation, slant up to 70 deg) nothing is lost at 2 from
        ``ring`` fiducials of 45 px across and ``dot`` ones of 60 px, nor at 3 from ``ring``
        ones of 70 px and ``dot`` ones of 120 px; keep 1 for smaller ones.

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
    if subpixel not in SUBPIXEL_METHODS:
        raise DetectorError(f"subpixel must be one of {SUBPIXEL_METHODS}, got {subpixel!r}")
    if isinstance(decimate, bool) or decimate not in DECIMATE_FACTORS:
        raise DetectorError(f"decimate must be one of {DECIMATE_FACTORS}, got {decimate!r}")
    config = DetectorConfig(
        design=design,
        threshold_window=threshold_window,
        threshold_t=threshold_t,
        min_diameter_px=float(min_diameter_px),
        max_diameter_px=max_diameter_px,
        reader=ReaderConfig(min_contrast=min_contrast, max_hamming=max_hamming),
        subpixel=subpixel,
        decimate=int(decimate),
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
    max_d = config.max_diameter_px if config.max_diameter_px is not None else float(min(h, w))
    bounds = _boundaries(_to_uint8(grey, full_scale), config, max_d)
    found: list[FiducialDetection] = []
    designs = (RING, DOT) if config.design == "any" else (DESIGNS[config.design],)
    noise: float | None = None  # estimated once, when the first candidates need it
    sampled = _SampledFrame(grey)
    for design in designs:
        cands = _candidates(bounds, design, config.min_diameter_px, max_d)
        cands = _outside(cands, found)
        if noise is None and len(cands.centre):
            noise = _noise_std(grey)
        found += _finish(
            grey, full_scale, cands, config.reader, config.subpixel, noise, sampled=sampled
        )
    found = _deduplicate(found)
    found.sort(key=lambda d: (d.center_px[1], d.center_px[0]))
    return found


def _boundaries(grey8: NDArray[np.uint8], config: DetectorConfig, max_d: float) -> Boundaries:
    """Steps 1-2: threshold and outer boundaries, on the image reduced by ``config.decimate``
    (see :func:`detect`), in full-image pixels."""
    f = config.decimate
    window = config.threshold_window
    h, w = grey8.shape
    if f > 1 and min(h, w) >= f * _MIN_DECIMATED_SIDE:
        # The same window, in reduced pixels.
        window = max(3, (window or default_window(grey8.shape)) // f) | 1
        grey8 = block_means(grey8, f)
    else:
        f = 1
    binary = bradley_threshold(grey8, window=window, t=config.threshold_t)
    bounds = outer_boundaries(
        binary, max_extent=max_d / f, min_hull_extent=0.9 * config.min_diameter_px / f
    )
    return bounds if f == 1 else bounds.enlarged(f)


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


#: Detections nearest each candidate that :func:`_outside` tests.
_OUTSIDE_NEIGHBOURS = 8


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
    # The few detections nearest each candidate: a candidate inside a detection is nearer its
    # centre than that detection's outer radius, and detections do not overlap, so eight
    # neighbours hold it (one missed here would only be read and dropped later).
    k = min(_OUTSIDE_NEIGHBOURS, len(found))
    dist, near = cKDTree(centre).query(
        cands.centre, k=[*range(1, k + 1)], distance_upper_bound=float(outer.max())
    )
    reach = np.append(outer, 0.0)[near]  # no neighbour: index len(found), distance inf
    keep = ~np.any(dist + margin[:, None] < reach, axis=1)
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
    subpixel: SubpixelMethod = "profile",
    noise: float | None = None,
    *,
    sampled: _SampledFrame | None = None,
) -> list[FiducialDetection]:
    """Read codes, fit every circle of the accepted candidates, read again, build results
    (``noise``: the image's noise sd, estimated here when not given; ``sampled``: the frame as
    the profile fits sample it, shared, made here when not given)."""
    if len(cands.centre) == 0:
        return []
    design = cands.design
    r0 = design.pose_circle.radius
    first = read_codes(
        grey, full_scale, design, cands.centre, cands.axes, cands.angle, cands.drift, reader
    )
    if noise is None:
        noise = _noise_std(grey)
    reach = np.where(
        cands.axes[:, 1] < RETRY_THIN_MINOR_PX, RETRY_THIN_DISTANCE, RETRY_MAX_DISTANCE
    )
    retry = np.nonzero(first.consistent & ~first.accepted & (first.nearest <= reach))[0]
    if retry.size:
        # Second chance for candidates that look like fiducials but whose code did not read:
        # small boundaries give poor coarse ellipses, so fit the pose circle and read again.
        seeds0 = [_scaled_seed(cands, i, 1.0, 0.0) for i in retry.tolist()]
        refits = fit_ellipses(
            grey,
            seeds0,
            r0,
            noise_std=noise,
            dark_inside=design.pose_circle.dark_inside,
            covariance=False,  # only read through
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
    if design.name == "ring":
        # Rule 5 rejects correct reads of small, slanted tracks, whose sectors blur into each
        # other and into the annulus: such reads within the Hamming limit are confirmed (or not)
        # by fitting the blurred image of every code.
        check = np.nonzero(
            first.consistent & ~first.accepted & (first.nearest <= reader.max_hamming)
        )[0]
        if check.size:
            ok = _model_confirms(
                grey,
                design,
                cands.centre[check],
                cands.axes[check],
                cands.angle[check],
                cands.drift[check],
                first.code[check],
                noise,
            )
            first.accepted[check[ok]] = True
            first.hamming[check[ok]] = first.nearest[check[ok]]
    idx = np.nonzero(first.accepted)[0]
    if idx.size == 0:
        return []
    if sampled is None:
        sampled = _SampledFrame(grey)
    fitted_all = _fit_circles(grey, noise, cands, idx, subpixel, sampled)
    keep: list[int] = []
    fitted: list[tuple[Ellipse, ...]] = []
    for i, group in zip(idx.tolist(), fitted_all, strict=True):
        if group:
            keep.append(i)
            fitted.append(group)
    if not keep:
        return []
    kidx = np.array(keep)
    centre = np.array([f[0].center_px for f in fitted])
    axes = np.array([(f[0].semi_major, f[0].semi_minor) for f in fitted])
    angle = np.array([f[0].angle for f in fitted])
    drift = _drift(fitted, r0)
    second = read_codes(grey, full_scale, design, centre, axes, angle, drift, reader)
    chosen: list[tuple[int, TrackReading, int]] = []
    for j, i in enumerate(kidx.tolist()):
        if second.accepted[j]:
            # Two accepted reads of different codes: something is wrong, report nothing.
            if second.code[j] != first.code[i]:
                continue
            chosen.append((j, second, j))
        else:
            # The fitted ellipses did not give a clean read (tiny, very slanted fiducials): the
            # first read passed every rule on its own (or its model read confirmed it).
            chosen.append((j, first, i))
    # Thin pose ellipses: exact reads with at most THIN_MAX_WEAK_BITS weak sectors, or reads the
    # model read through the fitted ellipses confirms.
    thin = [
        (j, reading, k)
        for j, reading, k in chosen
        if fitted[j][0].semi_minor < THIN_POSE_MINOR_PX
        and (
            reading.hamming[k] != 0
            or int((reading.margin[k] < THIN_WEAK_MARGIN).sum()) > THIN_MAX_WEAK_BITS
        )
    ]
    confirmed: set[int] = set()
    if thin:
        tj = np.array([j for j, _, _ in thin])
        codes = np.array([reading.code[k] for _, reading, k in thin])
        ok = _model_confirms(grey, design, centre[tj], axes[tj], angle[tj], drift[tj], codes, noise)
        confirmed = {int(j) for j in tj[ok]}
    checked = {j for j, _, _ in thin}
    final = [(j, reading, k) for j, reading, k in chosen if j not in checked or j in confirmed]
    arcs_src = sampled.get() if design.arcs and final else None
    groups = fit_arcs(grey, [fitted[j] for j, _, _ in final], design, noise, src=arcs_src)
    return _detections(design, groups, [(reading, k) for _, reading, k in final])


def _model_confirms(
    grey: NDArray[np.generic],
    design: FiducialDesign,
    centre: NDArray[np.float64],
    axes: NDArray[np.float64],
    angle: NDArray[np.float64],
    drift: NDArray[np.float64],
    codes: NDArray[np.int64],
    noise: float,
) -> NDArray[np.bool_]:
    """Whether the model read through these pose ellipses gives ``codes`` clearly and fits well."""
    m = model_read(grey, design, centre, axes, angle, drift, noise)
    with np.errstate(invalid="ignore"):
        return np.asarray(
            (m.code == codes)
            & (m.rms <= MODEL_MAX_RMS[design.name])
            & (m.separation >= MODEL_MIN_SEPARATION),
            dtype=bool,
        )


def _fit_circles(
    grey: NDArray[np.generic],
    noise: float,
    cands: _Candidates,
    idx: NDArray[np.intp],
    subpixel: SubpixelMethod,
    sampled: _SampledFrame,
) -> list[tuple[Ellipse, ...]]:
    """:func:`fit_design_circles` for candidates ``idx`` (``sampled``: the frame as the profile
    fits sample it, taken only by them)."""
    seeds = np.column_stack([cands.centre[idx], cands.axes[idx], cands.angle[idx]])
    src = sampled.get() if subpixel == "profile" else None
    return fit_design_circles(grey, seeds, cands.design, noise, method=subpixel, src=src)


def fit_design_circles(
    grey: NDArray[np.generic],
    seeds: NDArray[Any],
    design: FiducialDesign,
    noise_std: float,
    *,
    method: SubpixelMethod = "profile",
    src: SampledImage | None = None,
) -> list[tuple[Ellipse, ...]]:
    """Sub-pixel ellipses of every printed circle of fiducials of one design (step 3, then better).

    Parameters
    ----------
    grey : (H, W) ndarray
        Grey image indexed ``[v, u]``.
    seeds : (n, 5) ndarray
        Coarse pose ellipses ``(u, v, a, b, angle)`` (e.g. a component boundary's moment ellipse),
        within about a pixel.
    design : FiducialDesign
    noise_std : float
        Image noise standard deviation in ``grey``'s units.
    method : {"profile", "ml"}
        ``profile``: every circle from edge profiles along its normals (:mod:`.profile_fit`),
        the pose circle first, the others seeded from it scaled and given its measured blur.
        ``ml``: as below.
    src : (H, W) ndarray, optional
        ``grey`` as the profile fits sample it (:func:`.profile_fit.sampled_image`), where the
        caller has it already; otherwise prepared here.

    Returns
    -------
    list of tuple of Ellipse
        One tuple per seed, pose circle first then the other circles that could be fitted;
        empty where the pose circle could not be fitted.

    Notes
    -----
    With ``method="ml"``, fiducials of at least :data:`EDGE_MODEL_MIN_RADIUS_PX` outer radius
    have every edge fitted by the maximum-likelihood blurred-edge model (:mod:`.edge_fit`:
    unbiased, at its Cramér-Rao bound), with a band that stops half-way to the design's
    neighbouring printed edges. The ``ring`` design's annulus (circles 0 and 1) is fitted as one
    two-edge model; the remaining circles are seeded from the fitted pose circle, scaled. A pose
    circle the model cannot fit (a seed too far off) gets the gradient dual-conic fit
    (:func:`.ellipse.fit_ellipses`); an inner circle that fails is left out. Smaller fiducials
    get the dual-conic fit for every circle, except the ``ring`` design's pose circle, which
    the two-edge annulus model still fits (see :func:`_fit_small_annulus`).
    """
    seeds = np.asarray(seeds, dtype=np.float64).reshape(-1, 5)
    if method not in SUBPIXEL_METHODS:
        raise DetectorError(f"method must be one of {SUBPIXEL_METHODS}, got {method!r}")
    if method == "ml" or len(seeds) == 0:
        return _fit_ml(grey, seeds, design, noise_std)
    if src is None:
        src = sampled_image(np.asarray(grey))
    first = _profile_circle(src, design, 0, seeds, None, noise_std)
    # Where most of the pose circle's lines found no clean edge (a small oblique dot whose
    # windows the code track cuts short), the profiles say too little: the model fit instead.
    weak = ~first.ok | (
        first.pixels < PROFILE_MIN_COVERAGE * line_counts(seeds, _spacing(design, 0))
    )
    # Ellipses whose tips bend within the blur (curvature a / b^2) break the profiles'
    # first-order curvature correction there.
    weak |= seeds[:, 2] / np.maximum(seeds[:, 3], 1e-9) ** 2 > PROFILE_MAX_TIP_CURVATURE
    near = first.ok & _plausible_rows(first.params, seeds)
    out: list[tuple[Ellipse, ...]] = [()] * len(seeds)
    strong = np.flatnonzero(~weak)
    groups = _fit_profiles(grey, src, seeds[strong], design, noise_std, first, strong, near)
    doubtful = weak.copy()  # the profiles' pose circle itself
    for j, g in zip(strong, groups, strict=True):
        out[j] = g
        # Without a concentric circle the pose is ambiguous: the model fit, which fits the
        # ring design's annulus as one, finds more.
        weak[j] = len(g) == 1 and len(design.circles) > 1
    # Where the profiles' pose circle is trusted, the single-edge model first looks for the
    # circles outside the annulus alone; the annulus model is left to those it does not find.
    weak[_concentric_by_model(grey, design, noise_std, out, weak & ~doubtful & near)] = False
    slow = np.flatnonzero(weak)
    # The profile fit, where it converged near its seed, seeds the model fit better than the
    # boundary's moment ellipse (fewer Gauss-Newton steps); where the profiles' pose circle was
    # also trusted (only its concentric circles were missing), fewer still. One call for all
    # (the model's fits of an image judge their residuals against each other's).
    start = np.where(near[slow, None], first.params[slow], seeds[slow])
    trusted = ~doubtful[slow] & near[slow]
    iterations = PROFILE_START_ITERATIONS if np.all(trusted) else 4
    for j, g in zip(slow, _fit_ml(grey, start, design, noise_std, iterations), strict=True):
        out[j] = g
    return out


def _concentric_by_model(
    grey: NDArray[np.generic],
    design: FiducialDesign,
    noise_std: float,
    out: list[tuple[Ellipse, ...]],
    missing: NDArray[np.bool_],
) -> NDArray[np.intp]:
    """Circles of the fiducials ``missing`` (a trusted profile pose circle, none of its
    concentric circles) that lie outside an annulus, by the single-edge model seeded from that
    pose circle scaled; ``out`` gains them. Returns the fiducials that gained one.

    At 55-60 deg the ``ring`` design's annulus and the white gap inside it are too thin for
    the profiles' windows, and its dot has too few clean lines; the single-edge model finds the
    dot from the profiles' pose circle. The annulus model (:func:`_fit_edge_model`), which
    refits the pose circle and fits both of the annulus' edges, is left to the fiducials this
    does not serve: it cost 8 ms for the 400-fiducial frame's four such fiducials, mostly per
    call, where this costs 2 ms.
    """
    r0 = design.pose_circle.radius
    rows = [
        j
        for j in np.flatnonzero(missing).tolist()
        if out[j] and out[j][0].semi_major >= EDGE_MODEL_MIN_RADIUS_PX * r0
    ]
    poses = [out[j][0] for j in rows]
    gained = []
    for j, more in zip(rows, _circles_beyond_annulus(grey, noise_std, design, poses), strict=True):
        if more:
            out[j] = (*out[j], *more)
            gained.append(j)
    return np.array(gained, dtype=np.intp)


def fit_arcs(
    grey: NDArray[np.generic],
    groups: list[tuple[Ellipse, ...]],
    design: FiducialDesign,
    noise_std: float | None = None,
    *,
    src: SampledImage | None = None,
) -> list[tuple[Ellipse, ...]]:
    """Each fiducial's fitted circles followed by its design's coding-track arcs (the ``dot``
    design's track's outer edge), where they could be fitted.

    The ``dot`` design's only full circle, its dot, is small (0.3 of the outer radius) and
    carries the pose badly; the track's outer edge, 3.3 times larger, is printed only where a
    sector is black. It is fitted from edge profiles on those parts only (the ``partial`` mode
    of :func:`.profile_fit.refine_by_profiles_sampled`: lines across white sectors or near a
    sector's end are left out), seeded by the fitted pose circle scaled and tied to that seed
    along what the arcs leave unmeasured, with the covariance of what they measure. The pose
    estimator takes it as one more concentric circle of known radius.

    Parameters
    ----------
    grey : (H, W) ndarray
        Grey image indexed ``[v, u]``.
    groups : list of tuple of Ellipse
        Fitted circles of each fiducial, pose circle first (:func:`fit_design_circles`).
    design : FiducialDesign
    noise_std : float, optional
        Image noise sd in ``grey``'s units: the arcs' covariances are propagated from it
        (otherwise from their residuals).
    src : (H, W) ndarray, optional
        ``grey`` as the profile fits sample it (:func:`.profile_fit.sampled_image`), where the
        caller has it already; otherwise the region the arcs' windows can reach is prepared
        here.

    Returns
    -------
    list of tuple of Ellipse
        ``groups``, each with its fitted arcs appended.
    """
    r0 = design.pose_circle.radius
    if not design.arcs or not groups:
        return groups
    base = np.array([_parameters(g[0]) for g in groups])
    if src is None:
        # Only the region the arcs' windows can reach is prepared (the kernel samples positions
        # relative to each fit's centre, so the cut changes no sample).
        reach = base[:, 2] * PAPER_RADIUS / r0 + MAX_WINDOW_PX + 2.0
        h, w = grey.shape[:2]
        u0 = int(np.clip(np.floor(np.min(base[:, 0] - reach)), 0, w))
        v0 = int(np.clip(np.floor(np.min(base[:, 1] - reach)), 0, h))
        u1 = int(np.clip(np.ceil(np.max(base[:, 0] + reach)) + 1, u0, w))
        v1 = int(np.clip(np.ceil(np.max(base[:, 1] + reach)) + 1, v0, h))
        region = sampled_image(np.asarray(grey[v0:v1, u0:u1]))
    else:
        region, u0, v0 = src, 0, 0
    base[:, 0] -= u0
    base[:, 1] -= v0
    out = list(groups)
    for arc in design.arcs:
        seeds = base.copy()
        seeds[:, 2:4] *= arc.radius / r0
        r = arc.radius
        res = refine_by_profiles_sampled(
            region,
            seeds,
            np.full(len(seeds), 1.0 if arc.dark_inside else -1.0),
            design.half_way(r),
            passes=ARC_PASSES,
            partial=True,
            noise_std=_usable_noise(noise_std),
            spacing=ARC_LINE_SPACING_PX,
        )
        res.params[:, 0] += u0
        res.params[:, 1] += v0
        seeds[:, 0] += u0
        seeds[:, 1] += v0
        keep = res.ok & (res.pixels >= ARC_MIN_COVERAGE * line_counts(seeds, ARC_LINE_SPACING_PX))
        keep &= seeds[:, 3] >= ARC_MIN_MINOR_PX
        keep &= _plausible_rows(res.params, seeds)
        for j, e in enumerate(_ellipses(res, r, keep=keep)):
            if e is not None:
                out[j] = (*out[j], e)
    return out


def _fit_ml(
    grey: NDArray[np.generic],
    seeds: NDArray[Any],
    design: FiducialDesign,
    noise: float,
    iterations: int = 4,
) -> list[tuple[Ellipse, ...]]:
    """:func:`fit_design_circles` by the edge model (below its smallest size the dual conic,
    except for an annulus' pose circle); ``iterations``: the edge model's Gauss-Newton steps
    above that size."""
    r0 = design.pose_circle.radius
    small = seeds[:, 2] < EDGE_MODEL_MIN_RADIUS_PX * r0
    out: list[tuple[Ellipse, ...]] = [()] * len(seeds)
    big = np.flatnonzero(~small)
    fits = _fit_edge_model(grey, seeds[big], design, noise, iterations)
    for j, g in zip(big, fits, strict=True):
        out[j] = g
    tiny = np.flatnonzero(small)
    fit_small = _fit_small_annulus if _has_annulus(design) else _fit_dual_conic
    for j, g in zip(tiny, fit_small(grey, seeds[tiny], design, noise), strict=True):
        out[j] = g
    return out


def _has_annulus(design: FiducialDesign) -> bool:
    """True when the design's pose circle is the outer edge of an annulus (circles 0 and 1)."""
    return design.annulus_inner is not None and len(design.circles) > 1


def _fit_small_annulus(
    grey: NDArray[np.generic], seeds: NDArray[Any], design: FiducialDesign, noise: float
) -> list[tuple[Ellipse, ...]]:
    """Fiducials below the edge model's smallest size whose pose circle is an annulus' outer
    edge: the annulus by the two-edge model, the other circles by the dual conic.

    The dual conic's gradients there take in the annulus' other edge and the code track a pixel
    or two away: its pose circle came out 0.02-0.19 px too large at 24-39 px across (noise-free
    renders, slant 0-65 deg), so depth 1-2 mm too near at 1.7 m. The two-edge model has both
    annulus edges in its intensities and stays within about 0.01 px there. The inner circles
    only fix the centre's image and the normal (their radii are nuisance parameters of the pose),
    so the dual conic serves them; it also takes every circle where the annulus model fails. An
    annulus partly covered by something nearer is fitted again on what is seen of it
    (:func:`_uncovered_annuli`).
    """
    if len(seeds) == 0:
        return []
    # Not the model's inner edge, even where seen: its prior ties it to the outer edge's centre,
    # and the offset between concentric circles' centres that perspective makes is what tells
    # the pose's two solutions apart (with it, 48 % of the field's normals were over 10 deg off,
    # against 35 % with the dual conic's).
    pose, second, fits = _refine_annulus(
        grey, noise, design, seeds, SMALL_ANNULUS_ITERATIONS, sectors=COVER_SECTORS
    )
    typical = _typical_rms(pose)
    if typical is not None:
        pose, _ = _uncovered_annuli(grey, noise, design, seeds, pose, second, fits, typical)
        chi = np.array([e.rms_residual if e is not None else np.nan for e in pose])
        # A fit whose residuals still far exceed the other fiducials' in the image was not
        # fitting an annulus (RMS 23-49 noise sds against 1-1.3 on the synthetic field, 5-6 on
        # the JPEG session bag); the dual conic serves it better.
        for k in np.flatnonzero(chi > ANNULUS_OUTLIER_CHI * typical).tolist():
            pose[k] = None
    # One dual-conic call (its gradients cost per call): the inner circles of the fitted
    # annuli, seeded from them, and every circle of the others, seeded from their seeds.
    start = np.array(
        [_parameters(e) if e is not None else s for e, s in zip(pose, seeds, strict=True)]
    )
    first = [1 if e is not None else 0 for e in pose]
    out: list[tuple[Ellipse, ...]] = []
    circles = _dual_conic_circles(grey, start, design, noise, first)
    for e, group in zip(pose, circles, strict=True):
        if e is None:
            e = group.pop(0)
        out.append(() if e is None else (e, *(o for o in group if o is not None)))
    return out


def _fit_profiles(
    grey: NDArray[np.generic],
    src: SampledImage,
    seeds: NDArray[Any],
    design: FiducialDesign,
    noise: float,
    first: EdgeFits,
    rows: NDArray[np.intp],
    near: NDArray[np.bool_],
) -> list[tuple[Ellipse, ...]]:
    """:func:`fit_design_circles` by edge profiles, given the pose circles' fits ``first`` and
    which of them stayed near their seeds, ``near`` (rows ``rows`` of both belong to
    ``seeds``)."""
    if len(seeds) == 0:
        return []
    r0 = design.pose_circle.radius
    fitted = _ellipses(first, r0, rows, near[rows])
    pose = _with_fallback(grey, seeds, design, noise, fitted)
    groups: list[list[Ellipse]] = [[e] if e is not None else [] for e in pose]
    found = [j for j, e in enumerate(pose) if e is not None]
    if not found or len(design.circles) < 2:
        return [tuple(g) for g in groups]
    base = np.array([_parameters(pose[j]) for j in found])  # type: ignore[arg-type]
    blur = first.spread[rows[found]]
    for k in range(1, len(design.circles)):
        inner = base.copy()
        inner[:, 2:4] *= design.circles[k].radius / r0
        res = _profile_circle(src, design, k, inner, blur, noise)
        keep = res.ok & _plausible_rows(res.params, inner)
        fits = _ellipses(res, design.circles[k].radius, keep=keep)
        for j, e in zip(found, fits, strict=True):
            if e is not None:
                groups[j].append(e)
    return [tuple(g) for g in groups]


def _plausible_rows(fits: NDArray[Any], seeds: NDArray[Any]) -> NDArray[np.bool_]:
    """Fits that stayed near their seeds, ``(n, 5)`` rows each (conservative thresholds on
    ellipse properties, step 3; NaN: not plausible)."""
    tol = 0.25 * seeds[:, 3] + 1.5
    with np.errstate(invalid="ignore"):
        near = np.hypot(fits[:, 0] - seeds[:, 0], fits[:, 1] - seeds[:, 1]) < tol
        near &= np.abs(fits[:, 2] - seeds[:, 2]) < tol
        near &= np.abs(fits[:, 3] - seeds[:, 3]) < tol
    return near


def _profile_circle(
    src: SampledImage,
    design: FiducialDesign,
    k: int,
    seeds: NDArray[Any],
    blur: NDArray[np.float64] | None,
    noise: float,
) -> EdgeFits:
    """Edge-profile fits of circle ``k`` of ``design`` from ``(n, 5)`` seeds (covariance from
    the image noise ``noise``)."""
    circle = design.circles[k]
    polarity = np.full(len(seeds), 1.0 if circle.dark_inside else -1.0)
    rho = design.half_way(circle.radius)
    # Circles seeded from the fitted pose circle (blur known) are within a tenth of a pixel
    # (perspective): one pass, whose first-order window corrections hold that far.
    passes = 4 if blur is None else 1
    return refine_by_profiles_sampled(
        src,
        seeds,
        polarity,
        rho,
        passes=passes,
        spread=blur,
        noise_std=_usable_noise(noise),
        spacing=_spacing(design, k),
    )


def _spacing(design: FiducialDesign, k: int) -> float:
    """Arc length between the profile lines of circle ``k`` of ``design``, pixels
    (:data:`POSE_LINE_SPACING_PX` for the pose circle and an annulus' inner edge)."""
    inner = design.annulus_inner is not None and design.circles[k].radius == design.annulus_inner
    return POSE_LINE_SPACING_PX if k == 0 or inner else LINE_SPACING_PX


def _usable_noise(noise: float | None) -> float | None:
    """The image noise sd where it can scale a covariance (None: the fits' residuals must)."""
    return float(noise) if noise is not None and np.isfinite(noise) and noise > 0 else None


def _with_fallback(
    grey: NDArray[np.generic],
    seeds: NDArray[Any],
    design: FiducialDesign,
    noise: float,
    pose: list[Ellipse | None],
) -> list[Ellipse | None]:
    """Pose ellipses, with the gradient dual-conic fit where ``pose`` has None: where a fit
    failed or strayed from its seed (a seed too far off)."""
    pose = list(pose)
    failed = [j for j, e in enumerate(pose) if e is None]
    if failed:
        fallback = fit_ellipses(
            grey,
            [_as_ellipse(seeds[j]) for j in failed],
            design.pose_circle.radius,
            noise_std=noise,
            dark_inside=design.pose_circle.dark_inside,
        )
        for j, e in zip(failed, fallback, strict=True):
            pose[j] = _stand_in(e) if e is not None and _plausible(e, seeds[j]) else None
    return pose


def _stand_in(e: Ellipse) -> Ellipse:
    """A dual-conic fit as a pose circle, with its method's systematic error
    (:data:`DUAL_CONIC_SYSTEMATIC_PX`)."""
    return replace(e, systematic_px=DUAL_CONIC_SYSTEMATIC_PX)


def _fit_dual_conic(
    grey: NDArray[np.generic], seeds: NDArray[Any], design: FiducialDesign, noise: float
) -> list[tuple[Ellipse, ...]]:
    """Every circle by the gradient dual-conic fit, seeded by the scaled pose seed (fiducials
    too small for the edge model's bands)."""
    out: list[tuple[Ellipse, ...]] = []
    for group in _dual_conic_circles(grey, seeds, design, noise, [0] * len(seeds)):
        if group[0] is None:
            out.append(())
            continue
        out.append(tuple(e for e in group if e is not None))
    return out


def _dual_conic_circles(
    grey: NDArray[np.generic],
    seeds: NDArray[Any],
    design: FiducialDesign,
    noise: float,
    first: Sequence[int],
) -> list[list[Ellipse | None]]:
    """Circles ``first[j]`` onwards of the design by the gradient dual-conic fit, seeded by pose
    ellipse ``seeds[j]`` scaled; per seed one entry per circle, None where a fit failed or
    strayed."""
    if len(seeds) == 0:
        return []
    r0 = design.pose_circle.radius
    flat: list[Ellipse] = []
    circles: list[Circle] = []
    for p, k0 in zip(seeds, first, strict=True):
        for circle in design.circles[k0:]:
            q = p.copy()
            q[2:4] *= circle.radius / r0
            flat.append(_as_ellipse(q))
            circles.append(circle)
    fits = fit_ellipses(
        grey,
        flat,
        [c.radius for c in circles],
        noise_std=noise,
        dark_inside=[c.dark_inside for c in circles],
    )
    out: list[list[Ellipse | None]] = []
    at = 0
    for k0 in first:
        m = len(design.circles) - k0
        group = [
            e if e is not None and _plausible(e, s) else None
            for e, s in zip(fits[at : at + m], flat[at : at + m], strict=True)
        ]
        if k0 == 0 and group[0] is not None:
            group[0] = _stand_in(group[0])  # the pose circle's
        out.append(group)
        at += m
    return out


def _fit_edge_model(
    grey: NDArray[np.generic],
    seeds: NDArray[Any],
    design: FiducialDesign,
    noise: float,
    iterations: int = 4,
) -> list[tuple[Ellipse, ...]]:
    """:func:`fit_design_circles` by the maximum-likelihood edge model, by at most
    ``iterations`` Gauss-Newton steps per circle (the refits of partly covered annuli take
    :data:`SMALL_ANNULUS_ITERATIONS`)."""
    if len(seeds) == 0:
        return []
    annulus = _has_annulus(design)
    if annulus:
        # The ring design's pose circle is the outer edge of a black annulus whose inner edge is
        # the second circle: both edges are fitted together (thin when seen obliquely).
        pose, second, fits = _refine_annulus(
            grey, noise, design, seeds, iterations, sectors=COVER_SECTORS
        )
        typical = _typical_rms(pose)
        if typical is not None:
            # At 60 px a nearer fiducial's paper over part of the annulus pulled it 0.1-1.1 px.
            pose, second = _uncovered_annuli(
                grey, noise, design, seeds, pose, second, fits, typical
            )
    else:
        pose = _refine_circle(grey, noise, design, 0, seeds, iterations)
        second = [None] * len(pose)
    kept = pose
    pose = _with_fallback(grey, seeds, design, noise, pose)
    # An annulus' inner edge goes with the outer edge it was fitted with.
    second = [e if p is q else None for e, p, q in zip(second, pose, kept, strict=True)]
    groups: list[list[Ellipse]] = [[e] if e is not None else [] for e in pose]
    for j, e in enumerate(second):
        if e is not None and groups[j]:
            groups[j].append(e)
    found = [j for j, e in enumerate(pose) if e is not None]
    poses = [e for e in pose if e is not None]
    for j, more in zip(
        found, _circles_beyond_annulus(grey, noise, design, poses, iterations), strict=True
    ):
        groups[j].extend(more)
    return [tuple(g) for g in groups]


def _circles_beyond_annulus(
    grey: NDArray[np.generic],
    noise: float,
    design: FiducialDesign,
    poses: Sequence[Ellipse],
    iterations: int = 4,
) -> list[list[Ellipse]]:
    """Per fitted pose circle, the design's circles outside its annulus (every circle but the
    pose circle, without one) that the single-edge model fits from it scaled, by at most
    ``iterations`` Gauss-Newton steps, largest first."""
    out: list[list[Ellipse]] = [[] for _ in poses]
    rest = range(2 if _has_annulus(design) else 1, len(design.circles))
    if not poses or not rest:
        return out
    r0 = design.pose_circle.radius
    base = np.array([_parameters(e) for e in poses])
    for k in rest:
        seeds = base.copy()
        seeds[:, 2:4] *= design.circles[k].radius / r0
        for more, e in zip(
            out, _refine_circle(grey, noise, design, k, seeds, iterations), strict=True
        ):
            if e is not None:
                more.append(e)
    return out


def _refine_annulus(
    grey: NDArray[np.generic],
    noise: float,
    design: FiducialDesign,
    outer_seeds: NDArray[Any],
    iterations: int = 4,
    *,
    hidden: NDArray[np.bool_] | None = None,
    sectors: int = 0,
) -> tuple[list[Ellipse | None], list[Ellipse | None], EdgeFits]:
    """Both edges of the ring design's annulus (circles 0 and 1) from ``(n, 5)`` seeds of the
    outer one (the inner one's scaled from them), by at most ``iterations`` Gauss-Newton steps;
    also the outer edges' fits (``hidden`` and ``sectors`` as in
    :func:`.edge_fit.refine_annuli`)."""
    c_out, c_in = design.circles[0], design.circles[1]
    inner_seeds = np.array(outer_seeds, dtype=np.float64)
    inner_seeds[:, 2:4] *= c_in.radius / c_out.radius
    fo, fi = refine_annuli(
        grey,
        outer_seeds,
        inner_seeds,
        dark_annulus=c_out.dark_inside,
        noise_std=noise,
        band_px=EDGE_BAND_PX,
        rho_range=(design.half_way(c_in.radius)[0], design.half_way(c_out.radius)[1]),
        iterations=iterations,
        hidden=hidden,
        sectors=sectors,
    )
    pose = _ellipses(fo, c_out.radius, keep=_plausible_rows(fo.params, outer_seeds))
    second = _ellipses(fi, c_in.radius, keep=_plausible_rows(fi.params, inner_seeds))
    return pose, second, fo


def _typical_rms(fits: list[Ellipse | None]) -> float | None:
    """The median RMS residual of an image's fits, at least the noise (None: no fit)."""
    rms = [e.rms_residual for e in fits if e is not None and np.isfinite(e.rms_residual)]
    return max(float(np.median(rms)), 1.0) if rms else None


def _uncovered_annuli(
    grey: NDArray[np.generic],
    noise: float,
    design: FiducialDesign,
    seeds: NDArray[Any],
    pose: list[Ellipse | None],
    second: list[Ellipse | None],
    fits: EdgeFits,
    typical: float,
) -> tuple[list[Ellipse | None], list[Ellipse | None]]:
    """Annulus fits refitted without the sectors something nearer covers (a neighbour's paper, a
    unit's arm): ``pose`` and ``second`` (the annuli's outer and inner edges, and ``fits`` the
    outer edges' with their residuals by sector) with those replaced.

    The covered part of an annulus fits its model by tens of noise sds where the rest fits by
    one or two (in a crowded field at 33 px: the worst sector of a fiducial in full view at most
    2.1 times the image's typical RMS, of a partly covered one 2.4-35 times), and its pull moves
    the whole fit: the partly covered fiducials' pose circles were 0.14 px off centre and 0.06
    px off in size (median; 7.6 mm in depth), against 0.004 and 0.007 px in full view. Sectors
    far above the rest (:data:`COVER_CHI` times the typical fit and :data:`COVER_RELATIVE` of the
    worst, the first time with their neighbours) are left out and the fit repeated, each time
    hiding what still stands out and showing again what now fits, for :data:`COVER_ROUNDS`
    rounds. A refit that then fits like the image's others, with at most
    :data:`COVER_MAX_HIDDEN` sectors hidden, replaces the first; its covariance, from the arc
    left, says how much less it knows.
    """
    if fits.sector_chi is None:
        return pose, second
    limit = COVER_CHI * typical
    by_sector = np.nan_to_num(fits.sector_chi, nan=0.0)
    # Only fits that converged near their seeds: one the covered part sent astray gives no
    # sector pattern to trust (its residuals are its own geometry's), and refitted from its
    # seed with the wrong sectors hidden it can settle with its annulus over a dark occluder.
    found = np.array([e is not None for e in pose])
    rows = np.flatnonzero(found & (by_sector.max(axis=1) > limit))
    if rows.size == 0:
        return pose, second
    worst = by_sector[rows]
    hidden = worst > np.maximum(limit, COVER_RELATIVE * worst.max(axis=1))[:, None]
    # The sectors next to the worst share its boundary's blur.
    hidden |= np.roll(hidden, 1, axis=1) | np.roll(hidden, -1, axis=1)
    start = np.array([_parameters(pose[j]) for j in rows.tolist()])  # type: ignore[arg-type]
    out, out_second = list(pose), list(second)
    # Rows still changing which sectors they hide; each keeps the refit of its last round.
    active = np.arange(rows.size)
    for _ in range(COVER_ROUNDS):
        now_rows = rows[active]
        used = hidden[active]
        refit, refit_second, fo = _refine_annulus(
            grey,
            noise,
            design,
            start[active],
            SMALL_ANNULUS_ITERATIONS,
            hidden=used,
            sectors=COVER_SECTORS,
        )
        accept = (
            fo.ok
            & _plausible_rows(fo.params, seeds[now_rows])
            & (fo.chi <= ANNULUS_OUTLIER_CHI * typical)
            & (used.sum(axis=1) <= COVER_MAX_HIDDEN)
        )
        for n, j in enumerate(now_rows.tolist()):
            out[j], out_second[j] = (
                (refit[n], refit_second[n]) if accept[n] else (pose[j], second[j])
            )
        now = np.nan_to_num(fo.sector_chi, nan=0.0)  # type: ignore[arg-type]
        shown = np.where(used, 0.0, now)
        stands_out = ~used & (now > np.maximum(limit, COVER_RELATIVE * shown.max(axis=1))[:, None])
        update = (used & (now > COVER_SHOW_CHI * typical)) | stands_out
        hidden[active] = update
        # A refit that failed (too much hidden) ends its row with the first fit; the others
        # start their next round from their refit.
        more = np.any(update != used, axis=1) & fo.ok
        start[active[more]] = fo.params[more]
        active = active[more]
        if active.size == 0:
            break
    return out, out_second


def _refine_circle(
    grey: NDArray[np.generic],
    noise: float,
    design: FiducialDesign,
    k: int,
    seeds: NDArray[Any],
    iterations: int = 4,
) -> list[Ellipse | None]:
    """Maximum-likelihood fits of circle ``k`` of ``design`` from ``(n, 5)`` seeds, by at most
    ``iterations`` Gauss-Newton steps (None where a fit failed or strayed from its seed)."""
    circle = design.circles[k]
    r = circle.radius
    fits = refine_ellipses(
        grey,
        seeds,
        dark_inside=circle.dark_inside,
        noise_std=noise,
        band_px=EDGE_BAND_PX,
        rho_range=design.half_way(r),
        iterations=iterations,
    )
    return _ellipses(fits, r, keep=_plausible_rows(fits.params, seeds))


def _ellipses(
    fits: EdgeFits,
    radius: float,
    rows: NDArray[np.intp] | None = None,
    keep: NDArray[np.bool_] | None = None,
) -> list[Ellipse | None]:
    """Ellipse results of fits ``rows`` (all by default); None where a fit failed or ``keep``
    (aligned with ``rows``) is False."""
    idx = np.arange(len(fits)) if rows is None else rows
    good = fits.ok[idx] if keep is None else fits.ok[idx] & keep
    # Python scalars taken out of the arrays in one call each (per-element indexing of numpy
    # arrays costs more than building the Ellipse), the covariances as views by iteration.
    return ellipses_from_rows(
        good.tolist(),
        fits.params[idx].tolist(),
        list(fits.covariance[idx]),
        radius,
        fits.chi[idx].tolist(),
    )


def _parameters(e: Ellipse) -> tuple[float, float, float, float, float]:
    """``(u, v, a, b, angle)`` of an ellipse."""
    return (e.center_px[0], e.center_px[1], e.semi_major, e.semi_minor, e.angle)


def _as_ellipse(p: NDArray[Any]) -> Ellipse:
    """A seed ``(u, v, a, b, angle)`` as the Ellipse the dual-conic fit takes."""
    return Ellipse(
        center_px=(float(p[0]), float(p[1])),
        semi_major=float(p[2]),
        semi_minor=float(p[3]),
        angle=float(p[4]),
        covariance=np.zeros((5, 5)),
        radius=0.0,
    )


def _scaled_seed(cands: _Candidates, i: int, scale: float, dr2: float) -> Ellipse:
    """The candidate's coarse pose ellipse scaled to a concentric circle, with centre drift."""
    c = cands.centre[i] + cands.drift[i] * dr2
    return _as_ellipse(np.r_[c, cands.axes[i] * scale, cands.angle[i]])


def _plausible(fit: Ellipse, seed: Ellipse | NDArray[Any]) -> bool:
    """:func:`_plausible_rows` for one fitted Ellipse; ``seed`` is an :class:`Ellipse` or its
    ``(u, v, a, b, angle)`` row."""
    row = _parameters(seed) if isinstance(seed, Ellipse) else seed
    return bool(_plausible_rows(np.array([_parameters(fit)]), np.array([row], dtype=float))[0])


def _drift(fitted: list[tuple[Ellipse, ...]], r0: float) -> NDArray[np.float64]:
    """``(n, 2)``: each fiducial's centre drift per unit r^2 from its pose ellipse and its
    smallest other fitted circle (zero for a lone pose ellipse)."""
    pose = np.array([f[0].center_px for f in fitted]).reshape(-1, 2)
    other = np.array([f[-1].center_px for f in fitted]).reshape(-1, 2)
    r = np.array([f[-1].radius for f in fitted])
    lone = np.array([len(f) < 2 for f in fitted])
    # A lone pose ellipse is its own "other": zero drift, and a denominator kept clear of 0.
    return (pose - other) / np.where(lone, 1.0, r0**2 - r**2)[:, None]


def _noise_std(grey: NDArray[np.generic]) -> float:
    """Image noise for the ellipse covariances, estimated once per image.

    Large images are sampled in nine 64 x 64 tiles (the estimator is a robust median, and
    the noise is stationary): 1.5 ms on a full frame (5.2 ms with 128 x 128 tiles), and on the
    session frames the same estimate within 0.6 %.
    """
    h, w = grey.shape
    tile = 64
    if h * w <= 9 * tile * tile:
        return float(estimate_noise(grey))
    vs = np.linspace(0, h - tile, 3).astype(int)
    us = np.linspace(0, w - tile, 3).astype(int)
    tiles = [grey[v : v + tile, u : u + tile] for v in vs for u in us]
    return float(estimate_noise(np.vstack(tiles)))


def _detections(
    design: FiducialDesign,
    groups: list[tuple[Ellipse, ...]],
    readings: list[tuple[TrackReading, int]],
) -> list[FiducialDetection]:
    """Detections from each fiducial's ellipses and its reading (row ``k`` of a
    :class:`TrackReading`)."""
    # Each reading's columns as Python lists, once (indexing numpy arrays per element is slow).
    columns: dict[int, tuple[list[Any], ...]] = {}
    for reading, _ in readings:
        if id(reading) not in columns:
            columns[id(reading)] = tuple(
                getattr(reading, name).tolist()
                for name in ("code", "hamming", "contrast", "rotation")
            )
    out = []
    for group, (reading, k) in zip(groups, readings, strict=True):
        code, hamming, contrast, rotation = columns[id(reading)]
        out.append(
            FiducialDetection(
                code=int(code[k]),
                hamming=int(hamming[k]),
                center_px=group[0].center_px,
                ellipses=group,
                contrast=float(contrast[k]),
                design=design.name,
                rotation=float(rotation[k]),
            )
        )
    return out


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
    # Fiducials do not overlap: another centre within this one's outer radius, or whose own
    # outer radius reaches this centre, is a second reading of the same object. Only pairs
    # closer than the largest radius can be (a k-d tree finds them).
    pairs = cKDTree(centre).query_pairs(float(outer.max()), output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        dist = np.hypot(*(centre[i] - centre[j]).T)
        pairs = pairs[dist < np.maximum(outer[i], outer[j])]
    if len(pairs) == 0:
        return found
    same: dict[int, list[int]] = {}
    for a, b in pairs.tolist():
        same.setdefault(a, []).append(b)
        same.setdefault(b, []).append(a)
    dropped = np.zeros(len(found), dtype=bool)
    for k in rank:
        if not dropped[k]:
            dropped[same.get(k, [])] = True
    return [d for d, gone in zip(found, dropped.tolist(), strict=True) if not gone]
