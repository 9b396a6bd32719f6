"""Sub-pixel ellipses from edge profiles sampled along the normals (paper step 3, fast form).

Each edge is sampled along short lines normal to its current ellipse, one line per ``spacing``
pixels of arc (one by default), by bilinear interpolation (``cv2.remap``, one call for every edge
of every fiducial), with :data:`SAMPLES` samples spread over each line's window. Along each line
the edge's position is the centroid of the intensity derivative, which telescopes to the area
(zeroth-moment) edge locator: linear in the intensities (so no errors-in-variables shrinkage) and
independent of the sampling step once the step is below about twice the blur.

Windows stop half-way to the design's neighbouring printed edges (``rho_range``, as in
:mod:`.edge_fit`) and, in the final passes, at :data:`_WINDOW_SPREADS` spreads of the derivative
profile (every sample in a window adds noise). The centroid of a window-truncated Gaussian profile
is corrected to first order in the edge's offset (truncated-normal mean and variance); lines whose
window holds less than :data:`_MIN_WINDOW_SPREADS` spreads on either side (the thin side of an
oblique annulus) are not used. A blurred curved edge's centroid lies ``kappa s^2 / 2`` inside the
true edge (heat-equation argument: the blur takes ``s^2 / 2R`` of the step's area out of a radial
line), with ``s^2`` the image's total smoothing variance, measured from the lines' second moments
in a first, sparse pass with wide windows; the positions are corrected by it.

The five ellipse parameters follow by linear least squares on the positions (the signed
distance's derivatives in the quadratic-form parametrisation of :mod:`.edge_fit`), with one
re-solve without lines beyond :data:`_OUTLIER_SDS` sds, pass after pass until the ellipse moves
less than :data:`_CONVERGED_PX`. The covariance is the least-squares one (times
:func:`correlation_factor` for neighbouring lines sharing pixels) with the positions' variance
propagated from the image noise where it is known: each position is linear in its samples,
whose noise bilinear interpolation correlates (:func:`_line_noise_factor`). The residuals widen
it only by their misfit beyond :data:`MISFIT_TOLERANCE_PX`: the model's own small misfit to a
clean edge is the same in every image of a scene, so it biases a fit but does not scatter it
(at 0.5-1 % noise it made the predicted sds up to twice the empirical ones). Without a noise
estimate the residuals' variance stands for it, misfit included.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from . import _profile_kernel
from .edge_fit import (
    EdgeFits,
    checked_image,
    checked_rho_range,
    checked_seeds,
    erf_scaled,
    from_quadratic_form,
    polarity_signs,
    quadratic_form,
)
from .errors import DetectorError

#: Samples per line, spread evenly over its window (at most a pixel apart: the sums are then
#: exact to ~1e-5 for blur spreads from 0.5 px).
SAMPLES = 7
#: Largest half-window along a line, pixels (a first pass, from a seed about a pixel off).
MAX_WINDOW_PX = 3.0
#: Half-window of the final pass, in spreads of the derivative profile.
_WINDOW_SPREADS = 2.5
#: Arc length between neighbouring lines, pixels.
LINE_SPACING_PX = 1.0
#: Smallest distance, in spreads of the derivative profile, from the edge to either end of a
#: line's window (the truncated tails are corrected for, reliably only this far out).
_MIN_WINDOW_SPREADS = 2.0
#: Lines whose window reaches this many spreads on both sides measure the spread.
_WIDE_WINDOW_SPREADS = 2.0
#: Largest curvature times spread where the centroid's curvature correction holds.
_MAX_CURVATURE_SPREAD = 0.35
#: Lines whose residual exceeds this many robust sds are dropped before the second solve.
_OUTLIER_SDS = 4.0
_MIN_LINES = 12
#: Largest relative difference of a partial edge's line step from the fit's typical one (a line
#: crossing a sector boundary sees a fraction of the step).
_ARC_HEIGHT_TOLERANCE = 0.2
#: Largest relative difference of a partial edge's line step (mass over the window's share of
#: a centred step) from its fit's upper decile: a first cut of the lines across white sectors.
_ARC_STEP_TOLERANCE = 0.4
#: Lines left out next to a partial edge's ends.
_ARC_END_LINES = 1
#: Prior sd (pixels) of a partial edge's RMS displacement from its seed over the whole ellipse.
#: A few clustered arcs (a code with five black sectors side by side) leave some combinations
#: of centre, size and shape nearly unmeasured, along which a free fit wanders off by tens of
#: pixels; the tie holds those at the seed (the scaled pose circle, within a few tenths of a
#: pixel) and leaves what the arcs measure (within hundredths) to the data. The covariance
#: reported is the data's alone: large along what the arcs do not measure.
_ARC_TIE_PX = 0.3
#: Edge-position sd (pixels) of one line assumed before a partial fit's residuals measure it.
_TIE_LINE_SD = 0.1


def _interpolated_noise_correlation(d: NDArray[np.float64]) -> NDArray[np.float64]:
    """Covariance, in units of the pixel noise variance, of two samples ``d`` pixels apart of
    linearly interpolated white noise, averaged over the samples' sub-pixel phase (the tent
    kernel's autocorrelation: 2/3 at 0, 1/6 at 1 px, 0 beyond 2 px). Bilinear interpolation's
    is the product of both axes' (separable); along a line, this times the other axis' 2/3 at
    zero lag serves every direction to within 6 % (the 2-D form is nearly isotropic)."""
    d = np.abs(d)
    return np.where(
        d <= 1.0, 2.0 / 3.0 - d * d + 0.5 * d**3, np.clip(2.0 - d, 0.0, None) ** 3 / 6.0
    )


def correlation_factor(spacing: float) -> float:
    """Neighbouring lines ``spacing`` pixels apart along the arc share interpolated pixels:
    their positions' errors correlate by about R(spacing) / R(0) (1/4 at one pixel, 1/32 at
    1.5), which the least squares, taking them as independent, leave out. For parameters that
    move every line alike the fit's sd is then larger by sqrt(1 + 2 rho), returned here;
    renders agreed (1.2 measured at one pixel)."""
    rho = _interpolated_noise_correlation(np.array(spacing)) / _interpolated_noise_correlation(
        np.array(0.0)
    )
    return float(np.sqrt(1.0 + 2.0 * rho))


#: Model misfit tolerated before the residuals widen the covariance, RMS pixels per line: the
#: edge-profile model's typical gap to an area-sampled, Gaussian-blurred printed edge (aliasing
#: at 0.5 px of blur: 0.015-0.020 px on noise-free renders at 45-120 px, 0.007-0.015 at 0.7 px).
#: It is the same in every image of a scene (a bias, not scatter); misfit beyond it (a partly
#: covered edge, a reflection, compression artefacts, which do scatter) widens the covariance by
#: the excess. Typical rather than largest, as for :data:`.edge_fit.MISFIT_TOLERANCE`.
MISFIT_TOLERANCE_PX = 0.015
#: Image blur (optics, pixel integration, interpolation) assumed before it is measured, pixels.
_START_BLUR = 0.8
#: Arc length between the lines of a first pass from a coarse seed, pixels (whatever the final
#: passes' spacing: that pass also measures the blur, which the later passes and the other
#: circles of the fiducial keep). 4.5 px (3 before) took the 400-fiducial frame's first pass
#: from 10 to 6.5 ms; the final fits moved by 1e-3 px (median) and the precision benchmark's
#: rows by no more than their sampling error. At 6 px, eleven 60 deg seeds found too few lines
#: and went to the slower edge model.
_SPARSE_SPACING_PX = 4.5
#: A fit whose last pass moved it less than this (pixels) has converged.
_CONVERGED_PX = 0.05
#: Columns of the folded remap maps (remap takes maps of fewer than 32767 rows and columns).
_FOLD = 4096
#: Fits per padded block.
_BLOCK = 512
#: Pixel types the kernel samples as they are (its ``kind`` codes), for every caller of it.
KERNEL_KINDS = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1, np.dtype(np.float32): 2}
#: An image the kernel samples (:func:`sampled_image`).
SampledImage = NDArray[np.uint8] | NDArray[np.uint16] | NDArray[np.float32]
_INV_SQRT_2PI = float(1.0 / np.sqrt(2.0 * np.pi))


@dataclass(frozen=True, slots=True, eq=False)
class _Lines:
    """Sample lines of one pass for a block of ``k`` fits, padded to ``m`` lines each.

    Lines are in single precision (half the memory traffic of every per-line operation), but
    image coordinates in single precision are off by up to 1e-4 px, so each window's first
    sample point is rounded to it once, from double (fewer lines flip across a window or height
    test than with every term rounded); the least-squares sums too (a few hundred terms each),
    solved in double precision (:func:`_solve`). Against double precision throughout, full
    edges' fits on the 400-target frames moved by 3e-6 px (median) and under 5e-4 px (bar one
    dot in 1200, 2.5e-3 px, 0.2 of its sd). Partial edges (arcs) move more, though far less
    than their sds: many of their lines sit near the step tests' limits (lines across a
    sector's end see part of the step), so rounding flips a few of them; on the ``dot`` speed
    frame the 400 arcs moved by 0.001 sd (median), 0.02 sd (99th percentile), 0.25 sd at most.
    """

    valid: NDArray[np.bool_]  # (k, m) a line, not padding
    start_u: NDArray[np.float32]  # (k, m) first sample: the origin (a point on the current
    start_v: NDArray[np.float32]  # ellipse) plus the outward unit normal times ``lower``
    span_u: NDArray[np.floating[Any]]  # (k, m) the normal times ``width``: first to last sample
    span_v: NDArray[np.floating[Any]]
    jac: NDArray[np.floating[Any]]  # (k, 5, m) d(signed distance)/d(u, v, A, B, C)
    kappa: NDArray[np.floating[Any]]  # (k, m) curvature of the ellipse at the origin
    lower: NDArray[np.floating[Any]]  # (k, m) window along the normal, pixels from the origin
    upper: NDArray[np.floating[Any]]
    step: NDArray[np.floating[Any]]  # (k, m) spacing of the samples along each line


def refine_by_profiles(
    image: NDArray[Any],
    seeds: NDArray[np.float64],
    *,
    dark_inside: NDArray[np.bool_] | bool,
    rho_range: tuple[float, float] = (0.0, np.inf),
    passes: int = 4,
    noise_std: float | None = None,
    spacing: float = LINE_SPACING_PX,
) -> EdgeFits:
    """Refine ellipses from edge profiles along their normals (see the module docstring).

    Parameters
    ----------
    image : (H, W) ndarray
        Grey image (uint8, uint16 or float), indexed ``[v, u]``.
    seeds : (n, 5) ndarray
        Starting ``(u, v, a, b, angle)``, full-image pixels; within about a pixel.
    dark_inside : bool or (n,) ndarray of bool
        Polarity of each edge (True: the ellipse's inside is darker).
    rho_range : (float, float)
        Half-way to the nearest other printed edges inside and outside, in units of the ellipse's
        own scale: no line reaches beyond.
    passes : int
        Largest number of sampling passes (each re-centres the lines on the previous pass'
        ellipse; a fit stops when it has converged).
    noise_std : float, optional
        The image's noise sd in its intensity units: the covariance is then the noise's,
        propagated through the lines (:func:`_line_noise_factor`), widened only by misfit
        beyond :data:`MISFIT_TOLERANCE_PX`; without it, the residuals' own scatter.
    spacing : float
        Arc length between neighbouring lines, pixels (their shared pixels are accounted for
        in the covariance, :func:`correlation_factor`).

    Returns
    -------
    EdgeFits
        ``pixels`` counts the lines used, ``chi`` is the RMS position residual in pixels.

    Raises
    ------
    DetectorError
        If the image is not 2-D, the seeds are not ``(n, 5)``, or a parameter is out of range.
    """
    img = checked_image(image)
    seeds = checked_seeds(seeds)
    if passes < 1:
        raise DetectorError(f"passes must be at least 1, got {passes}")
    if not (np.isfinite(spacing) and 0.25 <= spacing <= 4.0):
        raise DetectorError(f"spacing must be in [0.25, 4] pixels, got {spacing!r}")
    if noise_std is not None and not (np.isfinite(noise_std) and noise_std > 0):
        raise DetectorError(f"noise_std must be positive and finite, got {noise_std!r}")
    rho = checked_rho_range(rho_range)
    polarity = polarity_signs(dark_inside, seeds.shape[0])
    return refine_by_profiles_sampled(
        sampled_image(img),
        seeds,
        polarity,
        rho,
        passes,
        noise_std=noise_std,
        spacing=float(spacing),
    )


def sampled_image(image: NDArray[Any]) -> SampledImage:
    """``image`` as the kernel samples it: C-contiguous uint8, uint16 or float32 pixels, the
    image itself where it is one (no copy of a frame), else one float32 copy."""
    if image.dtype in KERNEL_KINDS:
        return np.ascontiguousarray(image)
    return np.ascontiguousarray(image, dtype=np.float32)


def refine_by_profiles_sampled(
    src: SampledImage,
    seeds: NDArray[np.float64],
    polarity: NDArray[np.float64],
    rho_range: tuple[float, float],
    passes: int = 4,
    spread: NDArray[np.float64] | None = None,
    *,
    partial: bool = False,
    noise_std: float | None = None,
    spacing: float = LINE_SPACING_PX,
) -> EdgeFits:
    """:func:`refine_by_profiles` on an image :func:`sampled_image` has prepared (once for every
    circle of a frame); ``polarity`` is +1 where the inside is dark. ``spread``: the
    image blur of each fit where known (another edge of the same fiducial), used until the
    fit's own lines measure it. ``partial``: the edge is printed only along parts of the
    ellipse (a coding track's arcs): only lines whose step is near the largest ones' (within
    :data:`_ARC_HEIGHT_TOLERANCE`) count, so no line across a sector boundary is used, and the
    ellipse is tied to its seed (:data:`_ARC_TIE_PX`) along what those lines leave open.
    ``noise_std``: as in :func:`refine_by_profiles`. ``spacing``: arc length between lines,
    pixels (:func:`line_counts`)."""
    n = seeds.shape[0]
    out = EdgeFits.blank(n)
    usable = np.all(np.isfinite(seeds), axis=1) & (seeds[:, 3] > 1.0)
    usable &= seeds[:, 2] >= seeds[:, 3]
    idx = np.flatnonzero(usable)
    if idx.size == 0 or min(src.shape) < 5:
        return out
    count = line_counts(seeds[idx], spacing)
    # Blocks of fits with similar line counts, each padded to its largest.
    order = np.argsort(count, kind="stable")
    for first in range(0, idx.size, _BLOCK):
        blk = order[first : first + _BLOCK]
        j = idx[blk]
        blur = None if spread is None else spread[j]
        _fit_block(
            src,
            seeds[j],
            polarity[j],
            count[blk],
            rho_range,
            passes,
            blur,
            out,
            j,
            partial,
            noise_std,
            spacing,
        )
    drift = np.max(np.abs(out.params[:, :4] - seeds[:, :4]), axis=1)
    # A fit that wandered off its seed by more than its windows was not fitting this edge.
    out.ok[:] &= np.nan_to_num(drift, nan=np.inf) <= 2.0 * MAX_WINDOW_PX
    return out


def _fit_block(
    src: SampledImage,
    seeds: NDArray[np.float64],
    pol: NDArray[np.float64],
    count: NDArray[np.intp],
    rho_range: tuple[float, float],
    passes: int,
    known_blur: NDArray[np.float64] | None,
    out: EdgeFits,
    j: NDArray[np.intp],
    partial: bool = False,
    noise_std: float | None = None,
    spacing: float = LINE_SPACING_PX,
) -> None:
    """Fit one block of ellipses; results written into ``out`` at rows ``j``.

    Without a known blur the seed is taken as coarse: a first pass on lines 3 px apart with
    wide windows brings them onto the edge. Then full passes until the ellipse moves less than
    :data:`_CONVERGED_PX` (at most ``passes`` in all), each fit leaving when it has.
    """
    k = seeds.shape[0]
    cur = seeds.copy()
    blur = np.full(k, _START_BLUR)
    coarse_seed = known_blur is None
    if known_blur is not None:
        blur = np.where(np.isfinite(known_blur), known_blur, blur)
    alive = np.ones(k, dtype=bool)
    rows = np.arange(k)
    for p in range(passes):
        coarse = coarse_seed and p == 0 and passes > 1
        c, b = cur[rows], blur[rows]
        if coarse:
            # Every line of a partial edge: a third of them may hold too few of its arcs.
            sparse = (
                count[rows]
                if partial
                else np.maximum((count[rows] * (spacing / _SPARSE_SPACING_PX)).astype(np.intp), 16)
            )
            n_lines, cap = sparse, np.full(rows.size, MAX_WINDOW_PX)
        else:
            # Windows that hold the edge's tails and little more: every sample in a window adds
            # noise to the area locator.
            box = (2.0 * _WINDOW_SPREADS * b / (SAMPLES - 1)) ** 2 / 12.0
            n_lines, cap = (
                count[rows],
                np.minimum(_WINDOW_SPREADS * np.sqrt(b**2 + box), MAX_WINDOW_PX),
            )
        res = _pass(
            src,
            c,
            b,
            pol[rows],
            n_lines,
            rho_range,
            cap,
            measure_blur=coarse,
            tie=seeds[rows] if partial else None,
            noise_std=noise_std,
            spacing=spacing,
        )
        ok = res.ok & alive[rows]
        moved = np.max(np.abs(res.params[:, :4] - c[:, :4]), axis=1)
        cur[rows] = np.where(ok[:, None], res.params, c)
        blur[rows] = np.where(ok, res.spread, b)
        if coarse and partial:
            # A partial edge's coarse pass that found too little leaves the seed (the scaled
            # pose circle, close) to the full passes.
            continue
        alive[rows] = ok
        if coarse:
            continue
        jr = j[rows]
        out.params[jr] = res.params
        out.covariance[jr] = res.covariance
        out.contrast[jr] = res.contrast
        out.spread[jr] = res.spread
        out.chi[jr] = res.chi
        out.pixels[jr] = res.pixels
        out.ok[jr] = ok
        rows = rows[ok & (moved > _CONVERGED_PX)]
        if rows.size == 0:
            break


def _pass(
    src: SampledImage,
    cur: NDArray[np.float64],
    blur: NDArray[np.float64],
    pol: NDArray[np.float64],
    n_lines: NDArray[np.intp],
    rho_range: tuple[float, float],
    cap: NDArray[np.float64],
    *,
    measure_blur: bool,
    tie: NDArray[np.float64] | None = None,
    noise_std: float | None = None,
    spacing: float = LINE_SPACING_PX,
) -> EdgeFits:
    """One sampling pass: lines on the current ellipses, edge positions, a least-squares step.
    Returns the stepped ellipses; ``spread`` is the blur, measured when ``measure_blur`` (wide
    windows: the narrow ones of the final passes would feed back a truncated spread). ``tie``:
    the seeds of a partial edge (see :func:`refine_by_profiles_sampled`). ``noise_std``: the
    image noise the covariance is propagated from (None: the residuals')."""
    partial = tie is not None
    k = cur.shape[0]
    sums = None
    if partial or measure_blur:
        lines, mean, mass, m2, _ = _sampled_lines(
            src, cur, n_lines, rho_range, cap, pol, measure_blur
        )
        good, t, typical, blur = _edge_terms(lines, mean, mass, m2, blur, cap, partial)
        symmetric = _symmetric_window(cap, blur)
    else:
        # An edge printed all round at a known blur: its terms and sums from the kernel too.
        lines, _, _, _, full = _sampled_lines(src, cur, n_lines, rho_range, cap, pol, False, blur)
        assert full is not None
        good, t, typical, sums = full.good, full.t, full.typical, (full.normal, full.rhs)
        symmetric = full.symmetric
    prior = None if tie is None else _tie(lines, cur, tie)
    noise_var = None
    if noise_std is not None and not measure_blur:
        # Each line's edge is linear in its samples (the centroid, then the window's fixed
        # shift and gain): its variance from the image noise, per fit, at the symmetric window
        # most of its lines have (their spacing, gain and mass: the typical step height times
        # the window's share of it) with the centroid in the middle, where a converged fit's
        # edge lies. (The coarse pass's covariance is not used.)
        step0 = 2.0 * cap / (SAMPLES - 1)
        share, gain0 = symmetric
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = step0 / (typical * share * gain0)
        noise_var = noise_std * noise_std * _line_noise_factor(step0) * spread**2
    delta, cov_f, rms, used = _solve(
        lines.jac, t, good, prior, noise_var, correlation_factor(spacing), sums
    )
    ok = np.all(np.isfinite(delta), axis=1) & (used >= _MIN_LINES)
    theta = np.zeros((k, 5))
    theta[:, 2:] = quadratic_form(cur[:, 2:5])
    theta += np.where(ok[:, None], np.nan_to_num(delta), 0.0)
    new, jac5 = from_quadratic_form(theta)
    new[:, :2] += cur[:, :2]
    cov = jac5 @ cov_f @ np.swapaxes(jac5, 1, 2)
    ok &= np.all(np.isfinite(new), axis=1) & (new[:, 3] > 0.5)
    ok &= np.all(np.isfinite(cov), axis=(1, 2))
    return EdgeFits(new, cov, pol * typical, blur, rms, used, ok)


def _edge_terms(
    lines: _Lines,
    mean: NDArray[np.floating[Any]],
    mass: NDArray[np.floating[Any]],
    m2: NDArray[np.floating[Any]] | None,
    blur: NDArray[np.float64],
    cap: NDArray[np.float64],
    partial: bool,
) -> tuple[NDArray[np.bool_], NDArray[np.floating[Any]], NDArray[np.float64], NDArray[np.float64]]:
    """A pass' lines after their samples: the usable ones, each one's edge position as the
    right-hand side ``t`` of ``jac . delta = -t``, each fit's typical step height, and the blur
    (measured here where ``m2`` is given: the coarse pass). ``partial``: the lines of a partial
    edge (see :func:`refine_by_profiles_sampled`). In numpy: the reference of the kernel's
    :func:`_sampled_lines` with a blur, and what partial edges and the coarse pass use."""
    dtype = np.float32
    lower, upper = lines.lower, lines.upper
    box = lines.step**2 / 12.0  # the forward differences' box
    good = lines.valid & np.isfinite(mean) & (mass > 0)
    # Per-line arithmetic in the lines' precision.
    blur2 = (blur * blur).astype(dtype)[:, None]
    sg = np.sqrt(blur2 + box)
    window = None
    if partial:
        # Only lines across a printed part of the edge: steps (the mass over the fraction of
        # a step centred in the window that the window holds) near the largest ones'. (Lines
        # off the image or without a step give NaN, never near.)
        with np.errstate(invalid="ignore", divide="ignore"):
            window = _window_terms(lower, upper, sg, _symmetric_window(cap, blur), cap)
            step = mass / np.maximum(window[0], 1e-6)
        top = _upper_decile(step, good)
        good &= np.abs(step - top[:, None]) <= _ARC_STEP_TOLERANCE * top[:, None]
        # Lines across white sectors have no centroid (nor any use below).
        mean = np.where(good, mean, 0.0)
    if m2 is not None:
        # From lines whose window holds both tails (at the assumed blur), their slight
        # truncation undone.
        wide = good & (mean - lower >= _WIDE_WINDOW_SPREADS * sg)
        wide &= upper - mean >= _WIDE_WINDOW_SPREADS * sg
        _, _, ratio = _truncated_normal((lower - mean) / sg, (upper - mean) / sg)
        est = _mean(np.clip(m2 / ratio - box, 0.0, 9.0), wide)
        blur = np.where(np.isfinite(est), np.sqrt(np.maximum(est, 0.04)), blur)
        blur2 = (blur * blur).astype(dtype)[:, None]
        sg = np.sqrt(blur2 + box)
        window = None  # the step test's window terms were at the blur assumed before
    # The edge as the centre of the Gaussian whose window-truncated centroid was measured: to
    # first order in its offset c from the line's origin the centroid is sg T + c V, with T, V
    # the truncated standard normal's mean and variance (the origin lies within a few
    # hundredths of the edge once a fit has converged).
    symmetric = _symmetric_window(cap, blur)
    # (A partial edge's step test took them already, where the blur has not changed since.)
    z, shift, gain = _window_terms(lower, upper, sg, symmetric, cap) if window is None else window
    pos = (mean - sg * shift) / gain
    least = _MIN_WINDOW_SPREADS * sg
    good &= (pos - lower >= least) & (upper - pos >= least)
    # Where the ellipse bends within the blur the curvature correction below fails.
    good &= lines.kappa * blur.astype(dtype)[:, None] <= _MAX_CURVATURE_SPREAD
    # The step must be this fiducial's edge: its height near the fit's typical one.
    height = mass / np.maximum(z, 1e-6)
    typical = _mean(height, good)
    typ = typical.astype(dtype)[:, None]
    if not partial:
        good &= (height > 0.5 * typ) & (height < 1.5 * typ)
    else:
        good &= np.abs(height - typ) <= _ARC_HEIGHT_TOLERANCE * typ
        good = _inside_runs(good)
    # A blurred curved edge's centroid lies kappa s^2 / 2 inside it; then the linearised
    # distance d_new(origin) = jac . delta = -t.
    t = np.where(good, pos + 0.5 * lines.kappa * blur2, 0.0)
    return good, t, typical, blur


def _symmetric_window(
    cap: NDArray[np.float64], blur: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mass and variance of the truncated standard normal over each fit's symmetric window
    ``+-cap`` (its samples' spacing in the spread), the window most of its lines have."""
    box = (2.0 * cap / (SAMPLES - 1)) ** 2 / 12.0
    half = cap / np.sqrt(blur * blur + box)
    z0, _, v0 = _truncated_normal(-half, half)
    return z0, v0


def _window_terms(
    lower: NDArray[np.floating[Any]],
    upper: NDArray[np.floating[Any]],
    sg: NDArray[np.floating[Any]],
    symmetric: tuple[NDArray[np.float64], NDArray[np.float64]],
    cap: NDArray[np.float64],
) -> tuple[NDArray[np.floating[Any]], NDArray[np.floating[Any]], NDArray[np.floating[Any]]]:
    """:func:`_truncated_normal` of every line's window in spreads ``sg``. Most windows are their
    fit's symmetric cap (``symmetric``: :func:`_symmetric_window`, one evaluation per fit); the
    lines cut shorter are evaluated apiece."""
    z0, v0 = symmetric
    shape = lower.shape
    dtype = lower.dtype
    z = np.repeat(z0.astype(dtype)[:, None], shape[1], axis=1)
    gain = np.repeat(v0.astype(dtype)[:, None], shape[1], axis=1)
    shift = np.zeros(shape, dtype=dtype)
    # Windows not cut are the cap, in the lines' precision.
    cap_t = cap.astype(dtype)[:, None]
    cut = (lower > -cap_t) | (upper < cap_t)
    if np.any(cut):
        z[cut], shift[cut], gain[cut] = _truncated_normal(
            lower[cut] / sg[cut], upper[cut] / sg[cut]
        )
    return z, shift, gain


def _truncated_normal(
    alpha: NDArray[np.float64], beta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Mass, mean and variance of a standard normal truncated to ``[alpha, beta]`` (finite).

    The normal's CDF through :func:`.edge_fit.erf_scaled` (error < 1.5e-7), which reuses the
    densities needed anyway: a third of the cost of ``scipy.special.ndtr``."""
    ga = np.exp(-0.5 * alpha * alpha)
    gb = np.exp(-0.5 * beta * beta)
    z = np.maximum(0.5 * (erf_scaled(beta, gb) - erf_scaled(alpha, ga)), 1e-12)
    pa = ga * _INV_SQRT_2PI
    pb = gb * _INV_SQRT_2PI
    mean = (pa - pb) / z
    var = np.maximum(1.0 + (alpha * pa - beta * pb) / z - mean * mean, 1e-6)
    return z, mean, var


def line_counts(
    ellipses: NDArray[np.float64], spacing: float = LINE_SPACING_PX
) -> NDArray[np.intp]:
    """Lines a fit of each ``(u, v, a, b, angle)`` row samples: one per ``spacing`` pixels of
    arc (Ramanujan's perimeter), at least 16."""
    a, b = ellipses[:, 2], ellipses[:, 3]
    h = ((a - b) / (a + b)) ** 2
    perim = np.pi * (a + b) * (1.0 + 3.0 * h / (10.0 + np.sqrt(4.0 - 3.0 * h)))
    return np.clip(np.round(perim / spacing), 16, 4096).astype(np.intp)


@dataclass(frozen=True, slots=True)
class _FullEdge:
    """What the kernel gives of an edge printed all round, beside its lines (see
    :func:`_edge_terms`): usable lines, their edge positions ``t`` (right-hand side of
    ``jac . delta = -t``, 0 where not usable), each fit's typical step height and the
    least-squares sums over the usable lines (``normal`` (k, 5, 5), ``rhs`` (k, 5)), and the
    symmetric window's terms they were taken at."""

    good: NDArray[np.bool_]
    t: NDArray[np.float32]
    typical: NDArray[np.float64]
    normal: NDArray[np.float64]
    rhs: NDArray[np.float64]
    symmetric: tuple[NDArray[np.float64], NDArray[np.float64]]  # :func:`_symmetric_window`


def _sampled_lines(
    src: SampledImage,
    ellipses: NDArray[np.float64],
    count: NDArray[np.intp],
    rho_range: tuple[float, float],
    cap: NDArray[np.float64],
    polarity: NDArray[np.float64],
    second_moment: bool,
    blur: NDArray[np.float64] | None = None,
) -> tuple[
    _Lines,
    NDArray[np.floating[Any]],
    NDArray[np.floating[Any]],
    NDArray[np.floating[Any]] | None,
    _FullEdge | None,
]:
    """The lines of one pass on a block of ellipses and, along them, what :func:`_centroids`
    gives, from the compiled kernel (:mod:`._profile_kernel`): the arithmetic of :func:`_lines`
    then :func:`_centroids` (their numpy reference), fit by fit while its pixels are in cache,
    in SIMD, on the image's own pixels (:func:`sampled_image`), with exact bilinear samples
    (``cv2.remap`` rounds their positions to 1/32 px). Padding lines have no jacobian (zeros)
    and no centroid (NaN). With ``blur`` (an edge printed all round, at that blur) the kernel
    also takes :func:`_edge_terms` and the least-squares sums, each fit's while its lines are in
    cache: the :class:`_FullEdge`, None without."""
    k = ellipses.shape[0]
    m = int(count.max())
    f32 = np.float32
    valid = np.empty((k, m), dtype=np.uint8)
    jac = np.empty((k, 5, m), dtype=f32)
    kappa, lower, upper, step, mean, mass = (np.empty((k, m), dtype=f32) for _ in range(6))
    m2 = np.empty((k, m), dtype=f32) if second_moment else np.empty(0, dtype=f32)
    cap64 = np.ascontiguousarray(cap, dtype=np.float64)
    full = None
    edge_args: tuple[NDArray[Any], ...] = ()
    if blur is not None:
        blur64 = np.ascontiguousarray(blur, dtype=np.float64)
        z0, v0 = _symmetric_window(cap64, blur64)
        full = _FullEdge(
            np.empty((k, m), dtype=np.bool_),
            np.empty((k, m), dtype=f32),
            np.empty(k),
            np.empty((k, 5, 5)),
            np.empty((k, 5)),
            (z0, v0),
        )
        good = full.good.view(np.uint8)
        edge_args = (blur64, z0, v0, good, full.t, full.typical, full.normal, full.rhs)
    _profile_kernel.sample_lines(
        src,
        KERNEL_KINDS[src.dtype],
        src.shape[0],
        src.shape[1],
        np.ascontiguousarray(ellipses, dtype=np.float64),
        np.ascontiguousarray(count, dtype=np.int64),
        float(rho_range[0]),
        float(rho_range[1]),
        cap64,
        np.ascontiguousarray(polarity, dtype=np.float64),
        m,
        second_moment,
        valid,
        jac,
        kappa,
        lower,
        upper,
        step,
        mean,
        mass,
        m2,
        *edge_args,
    )
    # The sample positions are not kept: nothing after the moments needs them.
    none = np.empty((k, 0), dtype=f32)
    lines = _Lines(valid.view(np.bool_), none, none, none, none, jac, kappa, lower, upper, step)
    return lines, mean, mass, (m2 if second_moment else None), full


def _lines(
    ellipses: NDArray[np.float64],
    count: NDArray[np.intp],
    rho_range: tuple[float, float],
    cap: NDArray[np.float64],
) -> _Lines:
    """``count`` lines on every ellipse of a block, with their geometry and windows, in single
    precision (see :class:`_Lines`): the numpy reference of the kernel's lines (the tests hold
    :func:`_sampled_lines` to it)."""
    dtype = np.float32
    m = int(count.max())
    kk = np.arange(m)[None, :]
    valid = kk < count[:, None]
    a64, b64 = ellipses[:, 2:3], ellipses[:, 3:4]
    a, b, ang = (ellipses[:, i : i + 1].astype(dtype) for i in (2, 3, 4))
    # Spread evenly in arc length to first order: parametric angle phi = psi + e sin(2 psi) / 2,
    # e = (a - b) / (a + b), for uniform psi.
    # In single precision (SIMD trigonometry, several times faster): any angle serves, as long as
    # the point and its normal below come from the same (cp, sp); the spacing is a heuristic and
    # float32's 1e-7 is ~1e-5 px on a 100 px ellipse.
    psi = (kk + 0.5).astype(np.float32) * (2.0 * np.pi / count[:, None]).astype(np.float32)
    ecc = (0.5 * (a64 - b64) / (a64 + b64)).astype(np.float32)
    phi = psi + ecc * np.sin(np.float32(2.0) * psi)
    cp, sp = np.cos(phi), np.sin(phi)
    # Exactly on the unit circle in the lines' precision, so that the point lies on the ellipse.
    unit = np.sqrt(cp * cp + sp * sp)
    cp /= unit
    sp /= unit
    ca, sa = np.cos(ang), np.sin(ang)
    lx, ly = a * cp, b * sp  # point in the ellipse frame
    nx, ny = b * cp, a * sp  # outward normal direction in the ellipse frame
    nn = np.sqrt(nx * nx + ny * ny)
    nx /= nn
    ny /= nn
    du = ca * lx - sa * ly
    dv = sa * lx + ca * ly
    support = lx * nx + ly * ny  # distance of the tangent from the centre
    kappa = a * b / (nn * nn * nn)
    # Windows stop half-way to the neighbouring printed edges (concentric, so at rho times the
    # support along the normal).
    lo, hi = rho_range
    cap_t = cap.astype(dtype)[:, None]
    lower = -np.minimum((1.0 - lo) * support, cap_t)
    upper = np.minimum((hi - 1.0) * support, cap_t)
    width = upper - lower
    normal_u = ca * nx - sa * ny
    normal_v = sa * nx + ca * ny
    # d(signed distance)/d(u, v, A, B, C) at a point of the ellipse (rho = 1): the derivative of
    # q = (p - c)^T Q (p - c) over |grad q|, with grad q = 2 Q (p - c).
    q = quadratic_form(ellipses[:, 2:5]).astype(dtype)
    gx = q[:, 0:1] * du + q[:, 1:2] * dv
    gy = q[:, 1:2] * du + q[:, 2:3] * dv
    inv = 1.0 / np.sqrt(gx * gx + gy * gy)
    # Parameter-major (k, 5, m): each derivative is written and summed contiguously.
    jac = np.empty((du.shape[0], 5, m), dtype=dtype)
    minus = -inv
    np.multiply(gx, minus, out=jac[:, 0])
    np.multiply(gy, minus, out=jac[:, 1])
    half = 0.5 * inv
    np.multiply(du * du, half, out=jac[:, 2])
    np.multiply(du * dv, inv, out=jac[:, 3])
    np.multiply(dv * dv, half, out=jac[:, 4])
    return _Lines(
        valid,
        (ellipses[:, 0:1] + (du + normal_u * lower)).astype(dtype),
        (ellipses[:, 1:2] + (dv + normal_v * lower)).astype(dtype),
        normal_u * width,
        normal_v * width,
        jac,
        kappa,
        lower,
        upper,
        width / (SAMPLES - 1),
    )


def _centroids(
    src: NDArray[np.float32],
    lines: _Lines,
    polarity: NDArray[np.float64],
    *,
    second_moment: bool = True,
) -> tuple[NDArray[np.floating[Any]], NDArray[np.floating[Any]], NDArray[np.floating[Any]] | None]:
    """The numpy reference of the kernel's moments (the tests hold :func:`_sampled_lines` to
    it), on a float32 image. Per line, over its window: the derivative's centroid (outward,
    pixels from the origin),
    its mass (signed so that the expected polarity is positive) and, with ``second_moment``
    (None otherwise: only passes that measure the blur use it), its second central moment.

    Forward differences of the samples telescope: the mass is the last sample less the first,
    the centroid the area edge locator over the window (midpoint rule).
    """
    f32 = np.float32
    k, m = lines.valid.shape
    # Sample-major maps (k, SAMPLES, m): every broadcast runs along the lines, not along a
    # line's few samples (the short inner loops cost more than the arithmetic).
    frac = _FRACTIONS[None, :, None]
    # remap takes maps of fewer than 32767 rows and columns: the samples are written straight
    # into rows of a folded map.
    size = k * m * SAMPLES
    rows = -(-size // _FOLD)
    # Only the fold's tail needs zeros.
    fx = np.empty(rows * _FOLD, dtype=f32)
    fy = np.empty(rows * _FOLD, dtype=f32)
    for buf, start, span in ((fx, lines.start_u, lines.span_u), (fy, lines.start_v, lines.span_v)):
        buf[size:] = 0.0
        view = buf[:size].reshape(k, SAMPLES, m)
        np.multiply(span.astype(f32, copy=False)[:, None, :], frac, out=view)
        view += start[:, None, :]
    prof = cv2.remap(
        src,
        fx.reshape(rows, _FOLD),
        fy.reshape(rows, _FOLD),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    prof = prof.ravel()[:size].reshape(k, SAMPLES, m)
    # Sums over the forward differences at the midpoints (j + 1/2) steps from the window's
    # start, of 1, (j + 1/2) and (j + 1/2)^2, as weights on the samples (one product).
    weights = _MOMENT_WEIGHTS.T if second_moment else _MOMENT_WEIGHTS_01
    sums = (weights @ prof).astype(lines.lower.dtype, copy=False)
    pol = polarity.astype(lines.lower.dtype)[:, None]
    mass = sums[:, 0] * pol
    step = lines.step
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = pol / mass
        c1 = sums[:, 1] * inv
        mean = lines.lower + step * c1
        m2 = step * step * (sums[:, 2] * inv - c1 * c1) if second_moment else None
    return mean, mass, m2


def _moment_weights() -> NDArray[np.float32]:
    """``(SAMPLES, 3)``: sample weights giving sum(d), sum(d x), sum(d x^2) of the forward
    differences d_j = p_(j+1) - p_j at x_j = j + 1/2."""
    x = np.arange(SAMPLES - 1) + 0.5
    w = np.zeros((SAMPLES, 3))
    for power in range(3):
        w[1:, power] += x**power
        w[:-1, power] -= x**power
    return w.astype(np.float32)


_MOMENT_WEIGHTS = np.ascontiguousarray(_moment_weights())
#: The weights of sum(d) and sum(d x) alone (``(2, SAMPLES)``), for passes without the second
#: moment.
_MOMENT_WEIGHTS_01 = np.ascontiguousarray(_MOMENT_WEIGHTS.T[:2])
#: Each sample's place along its line's window, as a fraction of the window.
_FRACTIONS = np.linspace(0.0, 1.0, SAMPLES, dtype=np.float32)


def _lag_moments() -> NDArray[np.float64]:
    """``(SAMPLES, 3, 3)``: for each lag L, the sum over samples i of the moment weights' outer
    products ``w_i w_(i+L)^T``, plus its transpose for L > 0 (both orders of a pair)."""
    w = _MOMENT_WEIGHTS.astype(np.float64)
    out = np.zeros((SAMPLES, 3, 3))
    for lag in range(SAMPLES):
        m = w[: SAMPLES - lag].T @ w[lag:]
        out[lag] = m if lag == 0 else m + m.T
    return out


_LAG_MOMENTS = _lag_moments()


def _line_noise_factor(step: NDArray[np.float64]) -> NDArray[np.float64]:
    """Variance of a line's centroid, in sample steps, times its squared mass, per unit pixel
    noise variance: lines of sample spacing ``step`` whose centroid lies in the middle of the
    window (where a converged fit's edge lies), c1 = (SAMPLES - 1) / 2 steps in.

    The centroid c1 = S1 / S0 of the forward differences moves with the samples p_i by
    ``(w1_i - c1 w0_i) / S0`` (the moment weights of :func:`_moment_weights`); bilinear
    interpolation makes the samples' noise correlated, ``R(|i - i'| step)`` in units of the
    pixel variance (:func:`_interpolated_noise_correlation`, times 2/3 for the other axis).
    """
    lags = np.arange(SAMPLES, dtype=np.float64)
    rho = (2.0 / 3.0) * _interpolated_noise_correlation(lags[None, :] * step[:, None])
    m = np.einsum("kl,lij->kij", rho, _LAG_MOMENTS)
    c1 = 0.5 * (SAMPLES - 1)
    return np.asarray(m[:, 1, 1] - 2.0 * c1 * m[:, 0, 1] + c1 * c1 * m[:, 0, 0])


def _inside_runs(good: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The lines of a partial edge more than :data:`_ARC_END_LINES` from either end of their
    run of good lines: near a sector's end the blurred corner bends the edge."""
    m = good.shape[1]
    idx = np.arange(m)
    big = 4 * m
    last_bad = np.maximum.accumulate(np.where(good, -big, idx), axis=1)
    next_bad = np.minimum.accumulate(np.where(good, big, idx)[:, ::-1], axis=1)[:, ::-1]
    inside = (idx - last_bad > _ARC_END_LINES) & (next_bad - idx > _ARC_END_LINES)
    return np.asarray(good & inside, dtype=bool)


def _upper_decile(values: NDArray[np.float64], good: NDArray[np.bool_]) -> NDArray[np.float64]:
    """90th percentile (the lower of the two nearest ranks) of ``values`` over the good lines
    of each fit, NaN where none: one sort of all rows (NaN sorts last)."""
    v = np.sort(np.where(good, values, np.nan), axis=1)
    n = np.isfinite(v).sum(axis=1)
    rank = np.maximum((0.9 * (n - 1)).astype(np.intp), 0)
    top = np.take_along_axis(v, rank[:, None], axis=1)[:, 0]
    return np.asarray(np.where(n > 0, top, np.nan), dtype=np.float64)


def _mean(values: NDArray[np.float64], good: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Mean of ``values`` over the good lines of each fit (NaN where none)."""
    n = good.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(good, values, 0.0).sum(axis=1) / n


def _tie(
    lines: _Lines, cur: NDArray[np.float64], seeds: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The prior of a partial edge's step, in the units of ``jac . delta = -t``: information
    ``Q`` (k, 5, 5) of the mean squared edge displacement over all of each ellipse's lines
    (:data:`_ARC_TIE_PX`) and the current ellipses' offsets ``theta - theta_seed`` (k, 5)."""
    # Padding zeroed in single precision (cheaper than masking in double; the same values).
    jac = np.where(lines.valid[:, None, :], lines.jac, 0.0).astype(np.float64)
    n = np.maximum(lines.valid.sum(axis=1), 1)
    info = jac @ np.swapaxes(jac, 1, 2) / (n * _ARC_TIE_PX**2)[:, None, None]
    offset = np.empty((cur.shape[0], 5))
    offset[:, :2] = cur[:, :2] - seeds[:, :2]
    offset[:, 2:] = quadratic_form(cur[:, 2:5]) - quadratic_form(seeds[:, 2:5])
    return info, offset


def _solve(
    jac: NDArray[np.floating[Any]],
    t: NDArray[np.floating[Any]],
    good: NDArray[np.bool_],
    prior: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    noise_var: NDArray[np.float64] | None = None,
    correlation: float = 1.0,
    sums: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """Least squares ``jac . delta = -t`` per fit over the good lines, then once more without
    the lines beyond :data:`_OUTLIER_SDS` robust sds: the step, its covariance (the positions'
    variance from the residuals), the RMS residual and the lines used. ``prior``: information
    ``Q`` and current offsets ``o`` from the seeds (:func:`_tie`); the step then also pays
    ``(o + delta)^T Q (o + delta)``, and the covariance is still the lines' alone.
    ``noise_var``: each fit's line variance from the image noise; the covariance then takes it,
    or the residuals' variance less the tolerated misfit (:data:`MISFIT_TOLERANCE_PX`) where
    that is larger; ``correlation``: the lines' :func:`correlation_factor`, which widens the
    covariance; ``sums``: the first round's ``normal`` and ``rhs``, where the kernel took them
    with the lines (:func:`_sampled_lines` with a blur). The returned RMS residual is the residuals'
    either way."""
    k, _, m = jac.shape
    jac32 = np.ascontiguousarray(jac, dtype=np.float32)
    t32 = np.ascontiguousarray(t, dtype=np.float32)
    use = np.array(good, dtype=np.uint8)  # a copy: the outliers leave it
    if sums is None:
        normal = np.empty((k, 5, 5))
        rhs = np.empty((k, 5))
        _profile_kernel.normal_sums(jac32, t32, use, m, normal, rhs)
    else:
        normal, rhs = sums  # taken with the lines (changed in place below)
    # Both rounds in the kernel (a partial edge's lines are weighed against its prior by their
    # sd: assumed in the first round, the residuals' in the second).
    used = use.sum(axis=1, dtype=np.int64)
    empty = np.empty(0)
    q, o = (
        (empty, empty)
        if prior is None
        else (
            np.ascontiguousarray(prior[0], dtype=np.float64),
            np.ascontiguousarray(prior[1], dtype=np.float64),
        )
    )
    delta = np.empty((k, 5))
    inv = np.empty((k, 5, 5))
    sd = np.empty(k)
    _profile_kernel.solve_rounds(
        jac32,
        t32,
        use,
        m,
        normal,
        rhs,
        q,
        o,
        _TIE_LINE_SD,
        _MIN_LINES,
        _OUTLIER_SDS,
        delta,
        inv,
        sd,
        used,
    )
    var = sd**2
    if noise_var is not None:
        var = np.fmax(noise_var, var - MISFIT_TOLERANCE_PX**2)
    cov = inv * (correlation**2 * var)[:, None, None]
    cov[used < _MIN_LINES] = np.nan
    return delta, cov, sd, used.astype(np.intp)
