"""Maximum-likelihood ellipse refinement from pixel intensities (beyond the paper's step 3).

The dual-conic fit (:mod:`.ellipse`) uses image *gradients* as tangent lines. Its least squares put
noise into the design matrix (errors in variables), which biases the ellipse in proportion to the
noise variance: at 2 % noise a 120 px circle shrinks by 0.06-0.08 px, and a fit of the dot design's
small dot grows by 0.04 px. Depth is inversely proportional to the semi-axes, so that bias is what
limits monocular depth (the paper's Table 2).

This module fits instead a model of the *intensities* themselves. Near one printed circle's edge
the image is a blurred step across the imaged ellipse:

    I(p) = m + h * erf(t / sqrt(2)),    t = (d(p) + kappa(p) * s^2 / 2) / s

with ``d`` the signed distance of pixel ``p`` from the ellipse (positive outside), ``s`` the edge
spread (the camera's blur and the pixel's area together, ``s^2 ~ blur^2 + 1/12``), ``m`` and ``h``
the mid level and half contrast (``h > 0`` when the inside is dark), and ``kappa * s^2 / 2`` the
known inward shift of a blurred convex edge's half-level contour (``kappa`` the ellipse's curvature
at the nearest point). Gauss-Newton over the 8 parameters ``(u, v, a, b, angle, m, h, s)`` on the
pixels of a band around the edge is the maximum-likelihood estimate under white Gaussian noise:
unbiased to first order, and its covariance ``sigma^2 (J^T J)^-1`` is the Cramér-Rao bound of the
model, so the reported uncertainty is the right one by construction.

The signed distance is the first-order one, ``d = (rho - 1) / |grad rho|`` with
``rho = sqrt((x/a)^2 + (y/b)^2)`` in the ellipse's axes: exact for circles, and on an ellipse of
axis ratio 1/3 within 0.01 px over a 2.5 px band.

Fits are batched: every fit's band pixels are gathered once into a padded ``(fits, pixels)``
layout (fits of similar size share a block), so each Gauss-Newton step is a few dozen whole-array
operations and one batched 8x8 product, with no per-fit Python.

Pixel convention: ``(u, v)`` = (x, y) = (column, row), pixel centres at integer coordinates.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from .ellipse import _band_pixels
from .errors import DetectorError

__all__ = ["EdgeFits", "refine_annuli", "refine_ellipses"]

#: Default half-width of the band of pixels around the edge, pixels.
DEFAULT_BAND_PX = 2.0
#: Extra half-width of the gathered pixels beyond the band, for the seed's error (pixels).
_GATHER_SLACK_PX = 1.0
#: Starting edge spread, pixels (a sharp camera: blur 0.5 px and the pixel's area).
_START_SPREAD_PX = 0.7
_MIN_SPREAD_PX, _MAX_SPREAD_PX = 0.25, 4.0
#: Largest geometric step of one iteration, pixels (a Gauss-Newton step can overshoot far from
#: the optimum; the seed is within about a pixel).
_MAX_STEP_PX = 1.0
#: A fit whose last step moved its edges less than this (pixels) has converged.
_CONVERGED_PX = 1e-3
#: RMS model misfit, as a fraction of the edge's contrast, that does not widen the covariance:
#: the blurred-step model's typical gap to an area-sampled printed edge (0.007-0.016 on renders
#: at 35-60 px, slant 0-69 deg, blur 0.5-0.7 px), which noise of 1 % or less would otherwise
#: turn into a depth sd predicted 1.2-2 times too large. Typical, not the largest: JPEG's
#: artefacts at edges are of the same size (0.023 on the demo bag's quality-92 frames, whose
#: flat areas understate the noise threefold) and do scatter from frame to frame, so a larger
#: allowance would take them for misfit.
MISFIT_TOLERANCE = 0.012
#: Iterations on every other pixel before the full band is used.
_COARSE_ITERATIONS = 3
_MIN_PIXELS = 16
#: Largest curvature times spread where the shifted-step model is used (first order in it). The
#: tips of a small, steep ellipse carry its position along the major axis: at 0.35 a 60 px
#: ``dot`` fiducial at 70 deg lost them (centre sd 0.027 px along the axis, semi-major axis biased
#: by -0.075 px); at 0.7 its centre sd is 0.018 px and the axis bias -0.009 px (first-order
#: model error there is below the masking's own bias). Unchanged below 0.35.
_MAX_CURVATURE_SPREAD = 0.7
#: Smallest distance, in edge spreads, from a neighbouring printed edge for a pixel to be used
#: (its blur is then below 1.3 % of its step there).
_MIN_GAP_SPREADS = 2.25
#: Prior sd of an annulus' inner edge about its scaled outer edge, pixels (see refine_annuli).
ANNULUS_TIE_PX = 0.1
#: An inner edge whose fitted sd exceeds this fraction of the prior's was not seen by the data.
_SEEN_FRACTION = 0.5
#: Fewest band pixels of a sector for its residual to be reported (see EdgeFits.sector_chi).
_MIN_SECTOR_PIXELS = 4
#: Fits per padded block: blocks of similar size keep the padding small.
_BLOCK = 256
_SQRT_2_PI = float(np.sqrt(2.0 / np.pi))


@dataclass(frozen=True, slots=True, eq=False)
class EdgeFits:
    """Results of :func:`refine_ellipses` for ``n`` seeds.

    Attributes
    ----------
    params : (n, 5) ndarray
        ``(u, v, a, b, angle)`` in full-image pixels, ``a >= b``, angle in ``[0, pi)``.
    covariance : (n, 5, 5) ndarray
        Covariance of ``params`` (``sigma^2 (J^T J)^-1`` of the intensity model).
    contrast : (n,) ndarray
        Step height ``2 h`` across the edge in image units, positive when the inside is dark.
    spread : (n,) ndarray
        Edge spread ``s``, pixels.
    chi : (n,) ndarray
        RMS residual over the noise standard deviation (about 1 when the model holds).
    pixels : (n,) ndarray of int
        Band pixels used in the final iteration.
    ok : (n,) ndarray of bool
        False where the fit failed (too few pixels, singular, diverged, wrong polarity).
    sector_chi : (n, S) ndarray or None
        Where asked for (``sectors=S``), the RMS residual over the noise of each of ``S`` equal
        sectors of image angle about the seed's centre, at the fit's last evaluation (within
        1e-3 px of its result; failed or not) and over every band pixel of the sector, hidden
        ones too (NaN: too few pixels).
    """

    params: NDArray[np.float64]
    covariance: NDArray[np.float64]
    contrast: NDArray[np.float64]
    spread: NDArray[np.float64]
    chi: NDArray[np.float64]
    pixels: NDArray[np.intp]
    ok: NDArray[np.bool_]
    sector_chi: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return int(self.ok.shape[0])

    @classmethod
    def blank(cls, n: int) -> EdgeFits:
        """``n`` fits not done (yet): NaN, not ok."""
        return cls(
            params=np.full((n, 5), np.nan),
            covariance=np.full((n, 5, 5), np.nan),
            contrast=np.full(n, np.nan),
            spread=np.full(n, np.nan),
            chi=np.full(n, np.nan),
            pixels=np.zeros(n, dtype=np.intp),
            ok=np.zeros(n, dtype=bool),
        )


def refine_ellipses(
    image: NDArray[Any],
    seeds: NDArray[np.float64],
    *,
    dark_inside: NDArray[np.bool_] | bool,
    noise_std: float,
    band_px: float = DEFAULT_BAND_PX,
    rho_range: tuple[float, float] = (0.0, np.inf),
    iterations: int = 4,
) -> EdgeFits:
    """Refine ellipses by fitting the blurred-edge intensity model (see the module docstring).

    Parameters
    ----------
    image : (H, W) ndarray
        Grey image (uint8, uint16 or float), indexed ``[v, u]``.
    seeds : (n, 5) ndarray
        Starting ``(u, v, a, b, angle)`` of each ellipse, full-image pixels; within about a pixel.
    dark_inside : bool or (n,) ndarray of bool
        Polarity of each edge (True: the ellipse's inside is darker than its outside). A fit that
        ends with the other polarity locked onto another edge and is rejected.
    noise_std : float
        Standard deviation of the image noise in ``image``'s units (scales the covariance).
    band_px : float
        Half-width of the band of pixels used around each edge, pixels.
    rho_range : (float, float)
        Half-way to the nearest other printed edges inside and outside, in units of the ellipse's
        own scale (``rho = 1`` on it): pixels beyond are not used, nor pixels that such an edge
        comes within a few edge spreads of (its blur would reach them; a thin annulus seen
        obliquely). A printed design knows these at every slant, where a band in pixels does not.
    iterations : int
        Gauss-Newton iterations (4 reach 1e-3 px from a seed within a pixel).

    Returns
    -------
    EdgeFits

    Raises
    ------
    DetectorError
        If the image is not 2-D, the seeds are not ``(n, 5)``, or a parameter is out of range.
    """
    seeds = checked_seeds(seeds)
    polarity = polarity_signs(dark_inside, seeds.shape[0])
    return _refine(
        image, seeds[:, None, :], (1.0,), polarity, noise_std, band_px, rho_range, iterations
    )[0]


def refine_annuli(
    image: NDArray[Any],
    outer: NDArray[np.float64],
    inner: NDArray[np.float64],
    *,
    dark_annulus: bool,
    noise_std: float,
    band_px: float = DEFAULT_BAND_PX,
    rho_range: tuple[float, float] = (0.0, np.inf),
    iterations: int = 4,
    tie_px: float = ANNULUS_TIE_PX,
    hidden: NDArray[np.bool_] | None = None,
    sectors: int = 0,
) -> tuple[EdgeFits, EdgeFits]:
    """Refine both edges of printed annuli together (the ``ring`` design's pose annulus).

    Seen obliquely, an annulus becomes thin along the ellipse's minor axis and the blur of each
    edge reaches the other: fitted one by one, each edge is biased by its neighbour. Here the
    model is both blurred edges at once, ``I = m + h (erf_outer - erf_inner)`` with one level,
    contrast and spread and two independent ellipses (perspective makes the images of concentric
    circles non-concentric), so every pixel across the annulus is used and nothing is biased.

    Parameters
    ----------
    image : (H, W) ndarray
        Grey image, indexed ``[v, u]``.
    outer, inner : (n, 5) ndarray
        Starting ``(u, v, a, b, angle)`` of the outer and the inner edge of each annulus.
    dark_annulus : bool
        True for a dark annulus on a light ground.
    noise_std, band_px, iterations
        As in :func:`refine_ellipses`.
    rho_range : (float, float)
        Half-way to the nearest other printed edges inside the inner edge (in units of the inner
        ellipse) and outside the outer edge (in units of the outer ellipse).
    tie_px : float
        Prior standard deviation (pixels, centre and axes) of the inner edge about the outer
        edge scaled by the seeds' ratio of sizes. Perspective moves the two apart by far less
        than this at fiducial sizes; it keeps the fit well posed where the inner edge itself is
        masked out (too close to the printed code, small or oblique fiducials) and is negligible
        wherever the inner edge is seen.
    hidden : (n, S) ndarray of bool, optional
        Sectors of image angle about each outer seed's centre (``S`` equal ones, the first
        starting at +u and turning towards +v) whose pixels the fit leaves out: where something
        nearer covers the annulus.
    sectors : int
        With ``S > 0``, the fits' ``sector_chi`` over ``S`` such sectors (``S`` must match
        ``hidden``'s).

    Returns
    -------
    (EdgeFits, EdgeFits)
        The outer and the inner edges.
    """
    outer = np.asarray(outer, dtype=np.float64)
    inner = np.asarray(inner, dtype=np.float64)
    if outer.ndim != 2 or outer.shape[1] != 5 or inner.shape != outer.shape:
        raise DetectorError(
            f"outer and inner seeds must be (n, 5) arrays alike, got {outer.shape}, {inner.shape}"
        )
    polarity = np.full(outer.shape[0], 1.0 if dark_annulus else -1.0)
    if not tie_px > 0:
        raise DetectorError(f"tie_px must be positive, got {tie_px}")
    if hidden is not None:
        hidden = np.asarray(hidden, dtype=bool)
        sectors = sectors or (hidden.shape[1] if hidden.ndim == 2 else 0)
        if hidden.shape != (outer.shape[0], sectors) or sectors < 1:
            raise DetectorError(
                f"hidden must be an (n, sectors) boolean array for {outer.shape[0]} seeds and "
                f"{sectors} sectors, got shape {hidden.shape}"
            )
    if sectors < 0:
        raise DetectorError(f"sectors must be non-negative, got {sectors}")
    fits = _refine(
        image,
        np.stack([outer, inner], axis=1),
        (1.0, -1.0),
        polarity,
        noise_std,
        band_px,
        rho_range,
        iterations,
        tie_px,
        hidden,
        sectors,
    )
    return fits[0], fits[1]


def checked_image(image: NDArray[Any]) -> NDArray[Any]:
    """``image`` as an array, which must be 2-D (grey)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise DetectorError(f"image must be 2-D (grey), got shape {img.shape}")
    return img


def checked_seeds(seeds: NDArray[Any]) -> NDArray[np.float64]:
    """``seeds`` as an ``(n, 5)`` float array of ``(u, v, a, b, angle)`` rows."""
    out = np.asarray(seeds, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 5:
        raise DetectorError(
            f"seeds must be an (n, 5) array of (u, v, a, b, angle), got {out.shape}"
        )
    return out


def checked_rho_range(rho_range: tuple[float, float]) -> tuple[float, float]:
    """``rho_range`` as ``(lo, hi)`` with ``0 <= lo < 1 < hi``."""
    lo, hi = (float(x) for x in rho_range)
    if not (0.0 <= lo < 1.0 < hi):
        raise DetectorError(f"rho_range must satisfy 0 <= lo < 1 < hi, got {rho_range}")
    return lo, hi


def polarity_signs(dark_inside: NDArray[np.bool_] | bool, n: int) -> NDArray[np.float64]:
    """+1 where an edge's inside is dark, -1 where it is light, for ``n`` edges."""
    return np.where(np.broadcast_to(np.asarray(dark_inside, dtype=bool), (n,)), 1.0, -1.0)


def _refine(
    image: NDArray[Any],
    seeds: NDArray[np.float64],
    signs: tuple[float, ...],
    polarity: NDArray[np.float64],
    noise_std: float,
    band_px: float,
    rho_range: tuple[float, float],
    iterations: int,
    tie_px: float = 0.0,
    hidden: NDArray[np.bool_] | None = None,
    sectors: int = 0,
) -> list[EdgeFits]:
    """Common core: ``seeds`` is ``(n, E, 5)``, outermost edge first; ``signs`` the sign of each
    edge's step in the model (+1 the outermost); ``hidden`` and ``sectors`` as in
    :func:`refine_annuli`."""
    img = checked_image(image)
    if not (np.isfinite(noise_std) and noise_std > 0):
        raise DetectorError(f"noise_std must be a positive number, got {noise_std}")
    if iterations < 1:
        raise DetectorError(f"iterations must be at least 1, got {iterations}")
    if not band_px >= 1.0:
        raise DetectorError(f"band_px must be at least 1 pixel, got {band_px}")
    lo, hi = checked_rho_range(rho_range)
    n, n_edges = seeds.shape[0], seeds.shape[1]
    outs = [EdgeFits.blank(n) for _ in range(n_edges)]
    sector_chi = np.full((n, sectors), np.nan) if sectors > 0 else None
    if sector_chi is not None:
        outs = [dataclasses.replace(o, sector_chi=sector_chi) for o in outs]
    usable = np.all(np.isfinite(seeds), axis=(1, 2))
    usable &= np.all(seeds[:, :, 3] > 0.5, axis=1) & np.all(
        seeds[:, :, 2] >= seeds[:, :, 3], axis=1
    )
    idx = np.flatnonzero(usable)
    if idx.size == 0 or min(img.shape) < 5:
        return outs
    # Pixels within the band of any edge: between the innermost edge minus the band and the
    # outermost plus the band (around the mean of the two, with the half-width covering both).
    out_e, in_e = seeds[idx, 0], seeds[idx, -1]
    mid = out_e.copy()
    mid[:, 2:4] = 0.5 * (out_e[:, 2:4] + in_e[:, 2:4])
    half = 0.5 * (out_e[:, 2] - in_e[:, 2]) + band_px + _GATHER_SLACK_PX
    fit, pu, pv = _band_pixels(mid, half, img.shape)
    counts = np.bincount(fit, minlength=idx.size)
    starts = np.cumsum(counts) - counts
    intensity = img[pv, pu].astype(np.float32)
    sector = shown = None
    if sectors > 0:
        # Single precision: a sector is 22 degrees wide, the pixels' angles are exact to 1e-6.
        dv = (pv - out_e[fit, 1]).astype(np.float32)
        du = (pu - out_e[fit, 0]).astype(np.float32)
        turns = np.arctan2(dv, du) * np.float32(sectors / (2.0 * np.pi))
        sector = np.floor(turns).astype(np.intp) % sectors
        if hidden is not None:
            shown = ~hidden[idx[fit], sector]
    # Blocks of fits with similar pixel counts, each padded to its largest.
    order = np.argsort(counts, kind="stable")
    for first in range(0, idx.size, _BLOCK):
        blk = order[first : first + _BLOCK]
        length = int(counts[blk].max())
        if length == 0:
            continue
        pos = np.arange(length)
        gathered = pos[None, :] < counts[blk, None]
        take = np.where(gathered, starts[blk, None] + pos[None, :], 0)
        valid = gathered if shown is None else gathered & shown[take]
        res = _gauss_newton(
            seeds[idx[blk]],
            signs,
            pu[take].astype(np.float32),
            pv[take].astype(np.float32),
            intensity[take],
            valid,
            band_px,
            (lo, hi),
            polarity[idx[blk]],
            float(noise_std),
            iterations,
            tie_px,
            None if sector is None else (np.where(gathered, sector[take], -1), sectors),
        )
        j = idx[blk]
        if sector_chi is not None and res.sector_chi is not None:
            sector_chi[j] = res.sector_chi
        for e, out in enumerate(outs):
            out.params[j], out.covariance[j] = res.params[:, e], res.covariance[:, e]
            out.contrast[j], out.spread[j], out.chi[j] = res.contrast, res.spread, res.chi
            out.pixels[j], out.ok[j] = res.pixels, res.ok
            if e > 0 and tie_px > 0:
                # An inner edge known mostly through its prior (hidden by the code's blur) is
                # not reported: the prior ignores perspective, the data did not correct it.
                sd = np.sqrt(np.abs(np.diagonal(res.covariance[:, e], axis1=1, axis2=2)[:, :4]))
                out.ok[j] &= np.all(sd < _SEEN_FRACTION * tie_px, axis=1)
    return outs


@dataclass(frozen=True, slots=True, eq=False)
class _BlockFit:
    params: NDArray[np.float64]  # (k, E, 5)
    covariance: NDArray[np.float64]  # (k, E, 5, 5)
    contrast: NDArray[np.float64]
    spread: NDArray[np.float64]
    chi: NDArray[np.float64]
    pixels: NDArray[np.intp]
    ok: NDArray[np.bool_]
    sector_chi: NDArray[np.float64] | None = None


def _gauss_newton(
    seeds: NDArray[np.float64],
    signs: tuple[float, ...],
    pu: NDArray[np.float32],
    pv: NDArray[np.float32],
    intensity: NDArray[np.float32],
    valid: NDArray[np.bool_],
    band: float,
    rho_range: tuple[float, float],
    polarity: NDArray[np.float64],
    sigma: float,
    iterations: int,
    tie_px: float,
    sectors: tuple[NDArray[np.intp], int] | None = None,
) -> _BlockFit:
    """Fit one padded block: ``pu, pv, intensity, valid`` are ``(k, L)``; seeds ``(k, E, 5)``;
    ``sectors``, where given, each gathered pixel's sector (-1: padding) and their number, for
    the residuals by sector at the end (over every gathered pixel, ``valid`` or not).

    Each edge's geometry is parametrised as its centre and the quadratic form
    ``Q = [[A, B], [B, C]]`` of ``(p - c)^T Q (p - c) = 1``: smooth at circles, where the axis
    angle is undefined. Parameters: 5 per edge, then ``m, h, s``.
    """
    k, n_edges = seeds.shape[0], seeds.shape[1]
    npar = 5 * n_edges + 3
    ih, isp = npar - 2, npar - 1
    f32 = np.float32
    # Coordinates relative to the outer seed's centre keep float32 exact to 1e-5 px.
    ref = seeds[:, 0, :2].copy()
    du0 = pu - ref[:, 0:1].astype(np.float32)
    dv0 = pv - ref[:, 1:2].astype(np.float32)
    theta = np.zeros((k, npar))
    for e in range(n_edges):
        theta[:, 5 * e : 5 * e + 2] = seeds[:, e, :2] - ref
        theta[:, 5 * e + 2 : 5 * e + 5] = quadratic_form(seeds[:, e, 2:5])
    theta[:, isp] = _START_SPREAD_PX
    ok = np.ones(k, dtype=bool)
    lo, hi = rho_range
    # Unmodelled neighbouring edges: inside the innermost edge at rho 2 lo - 1, outside the
    # outermost at 2 hi - 1 (rho_range holds the half-way points).
    gap_in, gap_out = f32(2.0 * (1.0 - lo)), f32(2.0 * (hi - 1.0))
    band32 = f32(band)
    scale = 0.5 * seeds[:, 0, 2]  # edge shift per unit relative change of Q, pixels (about)
    tie = _Tie.build(seeds, npar, tie_px, sigma) if n_edges == 2 and tie_px > 0 else None
    normal = np.zeros((k, npar, npar))
    count = np.zeros(k, dtype=np.intp)
    chi = np.full(k, np.nan)
    model = _EdgeModel(signs, band32, (f32(lo), f32(hi)), (gap_in, gap_out))
    by_sector = None
    in_loop = False
    if sectors is not None:
        label, n_sectors = sectors
        by_sector = np.full((k, n_sectors), np.nan)
        # Nothing hidden: each fit's last evaluation (its step after it under 1e-3 px) gives its
        # residuals by sector at no extra cost.
        in_loop = bool(np.array_equal(valid, label >= 0))
    # Fits that have converged leave the batch: later iterations cost only what still moves.
    rows = np.arange(k)
    for it in range(iterations + 1):
        # The first steps, from a seed a pixel off, need only every other pixel; the last ones
        # (and the covariance) use them all.
        coarse = it < iterations - 1 and it < _COARSE_ITERATIONS
        px = slice(None, None, 2) if coarse else slice(None)
        theta_rows = theta[rows]
        nrm, rhs, cnt, rms_rows, resid, mask = model.normal_equations(
            theta_rows,
            du0[rows, px],
            dv0[rows, px],
            intensity[rows, px],
            valid[rows, px],
            None if tie is None else tie.rows(rows),
            levels_polarity=polarity[rows] if it == 0 else None,
        )
        if it == 0:
            theta[rows] = theta_rows  # with the levels the first evaluation started from
        normal[rows], count[rows], chi[rows] = nrm, cnt, rms_rows / sigma
        if it == iterations:
            if in_loop and by_sector is not None:
                by_sector[rows] = _rms_by_sector(resid, mask, label[rows, px], n_sectors)
            break
        # Marquardt damping of the diagonal keeps early steps short where the model is poor.
        diag = np.einsum("kii->ki", nrm)
        damp = nrm + 1e-3 * diag[:, :, None] * np.eye(npar)
        enough = cnt >= _MIN_PIXELS * n_edges
        step = np.zeros((rows.size, npar))
        good = enough & ok[rows] & np.all(np.isfinite(damp), axis=(1, 2))
        good &= np.all(diag > 0, axis=1)
        if np.any(good):
            step[good] = _safe_solve(damp[good], rhs[good])
        ok[rows] &= enough & np.all(np.isfinite(step), axis=1)
        step[~ok[rows]] = 0.0
        # Largest implied edge shift: a centre's step, or a form's relative change.
        shift = np.zeros(rows.size)
        for e in range(n_edges):
            q = theta[rows, 5 * e + 2 : 5 * e + 5]
            dq = step[:, 5 * e + 2 : 5 * e + 5]
            form = (np.abs(dq[:, 0]) + 2 * np.abs(dq[:, 1]) + np.abs(dq[:, 2])) / (
                q[:, 0] + q[:, 2]
            )
            centre = np.max(np.abs(step[:, 5 * e : 5 * e + 2]), axis=1)
            shift = np.maximum(shift, np.maximum(centre, form * scale[rows]))
        step *= np.minimum(1.0, _MAX_STEP_PX / np.maximum(shift, 1e-12))[:, None]
        # The spread is poorly determined while the edge is misplaced: bounded relative steps.
        sp = theta[rows, isp]
        step[:, isp] = np.clip(step[:, isp], -0.5 * sp, 0.5 * sp)
        theta[rows] += step
        theta[rows, isp] = np.clip(theta[rows, isp], _MIN_SPREAD_PX, _MAX_SPREAD_PX)
        moving = ok[rows] & ((shift > _CONVERGED_PX) | coarse)
        if in_loop and by_sector is not None and not np.all(moving):
            done = ~moving
            by_sector[rows[done]] = _rms_by_sector(
                resid[done], mask[done], label[rows[done], px], n_sectors
            )
        rows = rows[moving]
        if rows.size == 0:
            break
    cov_all = np.full((k, npar, npar), np.nan)
    good = ok & (count >= _MIN_PIXELS * n_edges)
    if np.any(good):
        # A posteriori variance factor: residuals beyond the image noise (compression
        # artefacts, a partly covered edge) widen the covariance; it is never narrowed below
        # the noise. The model's own misfit to a clean printed edge (MISFIT_TOLERANCE of the
        # contrast) is the same in every image of a scene, a bias rather than scatter: only
        # what exceeds it widens.
        tol = (MISFIT_TOLERANCE * 2.0 * np.abs(theta[good, ih]) / sigma) ** 2
        factor = np.maximum(np.nan_to_num(chi[good], nan=1.0) ** 2 - tol, 1.0)
        cov_all[good] = _safe_inverse(normal[good]) * (sigma * sigma * factor)[:, None, None]
    params = np.empty((k, n_edges, 5))
    cov = np.empty((k, n_edges, 5, 5))
    for e in range(n_edges):
        sl = slice(5 * e, 5 * e + 5)
        p, jac5 = from_quadratic_form(theta[:, sl])
        p[:, :2] += ref
        params[:, e] = p
        cov[:, e] = jac5 @ cov_all[:, sl, sl] @ np.swapaxes(jac5, 1, 2)
    finite = np.all(np.isfinite(params), axis=(1, 2)) & np.all(np.isfinite(cov), axis=(1, 2, 3))
    drift = np.max(np.abs(params[:, :, :4] - seeds[:, :, :4]), axis=(1, 2))
    # The edge must be there: its contrast clearly above its own uncertainty (a flat patch or
    # an edge of the other polarity fits nothing).
    h_sd = np.sqrt(np.abs(np.nan_to_num(cov_all[:, ih, ih], nan=np.inf)))
    ok &= good & finite & (theta[:, ih] * polarity > 5.0 * h_sd)
    ok &= np.nan_to_num(drift, nan=np.inf) <= 2.0 * (band + _GATHER_SLACK_PX)
    ok &= np.all(np.nan_to_num(params[:, :, 3], nan=0.0) > 0.5, axis=1)
    if by_sector is not None and sectors is not None:
        if not in_loop:
            by_sector = model.sector_chi(theta, du0, dv0, intensity, *sectors)
        by_sector = by_sector / sigma
    return _BlockFit(params, cov, 2.0 * theta[:, ih], theta[:, isp], chi, count, ok, by_sector)


class _EdgeModel:
    """The blurred-edge intensity model of one block: masks, residuals and normal equations."""

    def __init__(
        self,
        signs: tuple[float, ...],
        band: np.float32,
        rho_limits: tuple[np.float32, np.float32],
        gaps: tuple[np.float32, np.float32],
    ) -> None:
        self.signs = signs
        self.band = band
        self.rho_limits = rho_limits
        self.gaps = gaps
        self.n_edges = len(signs)
        self.npar = 5 * self.n_edges + 3

    def _terms(
        self,
        theta: NDArray[np.float64],
        du0: NDArray[np.float32],
        dv0: NDArray[np.float32],
        valid: NDArray[np.bool_],
    ) -> tuple[
        list[_Geometry],
        NDArray[np.bool_],
        NDArray[np.float32],
        list[NDArray[np.float32]],
        NDArray[np.float32],
    ]:
        """Geometry of every edge, the pixel mask, the summed steps, each edge's Gaussian, s."""
        f32 = np.float32
        n_edges, band = self.n_edges, self.band
        lo, hi = self.rho_limits
        gap_in, gap_out = self.gaps
        isp = self.npar - 1
        geos = [_geometry(theta[:, 5 * e : 5 * e + 5], du0, dv0) for e in range(n_edges)]
        s = theta[:, isp : isp + 1].astype(np.float32)
        outer_g, inner_g = geos[0], geos[-1]
        mask = valid & (outer_g.d <= band) & (inner_g.d >= -band)
        mask &= (outer_g.rho <= hi) & (inner_g.rho >= lo)
        if n_edges == 1:
            mask &= np.abs(outer_g.d) <= band
        # Where an unmodelled neighbouring edge comes within a few spreads of a pixel (a thin
        # annulus seen obliquely, the paper's edge) its blur reaches the pixel: it is left out.
        # Pixel by pixel, so that the pixels next to the fitted edge, which carry its position,
        # stay when the band's far end goes: at 35 px a whole side went, the minor axis' ends of
        # oblique views lost their outside (paper edge) or annulus pixels (code track), and the
        # depth sd at 55-69 deg grew by half.
        least = f32(_MIN_GAP_SPREADS) * s
        beyond = outer_g.rho > f32(1.0)
        # Distances to the neighbours, at rho 1 + gap_out of the outermost edge and 1 - gap_in
        # of the innermost (level curves of rho: to first order).
        far_out = (f32(1.0) + gap_out - outer_g.rho) * outer_g.rho >= least * outer_g.gn
        far_in = (inner_g.rho - f32(1.0) + gap_in) * inner_g.rho >= least * inner_g.gn
        mask &= np.where(beyond, far_out, far_in)
        step_sum = np.zeros_like(du0)
        gauss_l: list[NDArray[np.float32]] = []
        for sign, geo in zip(self.signs, geos, strict=True):
            # Where the edge bends within the blur (the tips of a thin ellipse) the blurred
            # profile is no longer a shifted step: those pixels would bias the fit.
            near = np.abs(geo.d) <= band + f32(1.0)
            mask &= ~near | (geo.kappa * s <= f32(_MAX_CURVATURE_SPREAD))
            t = np.asarray((geo.d + f32(0.5) * geo.kappa * s * s) / s, dtype=np.float32)
            gauss = np.exp(f32(-0.5) * t * t)
            step_sum += f32(sign) * erf_scaled(t, gauss)
            gauss_l.append(gauss)
        return geos, mask, step_sum, gauss_l, s

    def normal_equations(
        self,
        theta: NDArray[np.float64],
        du0: NDArray[np.float32],
        dv0: NDArray[np.float32],
        intensity: NDArray[np.float32],
        valid: NDArray[np.bool_],
        tie: _Tie | None,
        *,
        levels_polarity: NDArray[np.float64] | None = None,
    ) -> tuple[
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.intp],
        NDArray[np.float64],
        NDArray[np.float32],
        NDArray[np.bool_],
    ]:
        """``J^T J``, ``J^T r``, the pixel count, the RMS residual, the residuals (zero outside
        the mask) and the mask at ``theta`` (rows of the block).

        With ``levels_polarity`` (the first evaluation, at the seeds) the mid level and half
        contrast are first set in ``theta``, in place, by linear least squares at its geometry.
        """
        f32 = np.float32
        npar = self.npar
        im, ih, isp = npar - 3, npar - 2, npar - 1
        geos, mask, step_sum, gauss_l, s = self._terms(theta, du0, dv0, valid)
        if levels_polarity is not None:
            theta[:, im], theta[:, ih] = _levels(intensity, step_sum, mask)
            keep = theta[:, ih] * levels_polarity > 0
            theta[:, ih] = np.where(keep, theta[:, ih], levels_polarity * 1e-3)
        k = theta.shape[0]
        h = theta[:, ih : ih + 1].astype(np.float32)
        resid = intensity - (theta[:, im : im + 1].astype(np.float32) + h * step_sum)
        # Rows of J^T, one per parameter, zero outside the band; float32 products keep the
        # batched sums in single-precision BLAS (relative error ~1e-6, far below the noise).
        jac = np.empty((k, npar, du0.shape[1]), dtype=np.float32)
        jac[:, isp] = 0.0
        for e, (sign, geo) in enumerate(zip(self.signs, geos, strict=True)):
            g = (h * f32(sign * _SQRT_2_PI)) * gauss_l[e]  # dI/dt of this edge
            gs = g / s
            for col, dd in enumerate(geo.dd):
                np.multiply(gs, dd, out=jac[:, 5 * e + col])
            jac[:, isp] += g * (geo.kappa * f32(0.5) - geo.d / (s * s))
        jac[:, im] = 1.0
        jac[:, ih] = step_sum
        jac *= mask[:, None, :]
        resid = np.where(mask, resid, f32(0.0))
        normal = (jac @ np.swapaxes(jac, 1, 2)).astype(np.float64)
        rhs = (jac @ resid[:, :, None])[:, :, 0].astype(np.float64)
        if tie is not None:
            normal += tie.normal
            rhs -= tie.gradient(theta)
        count = mask.sum(axis=1)
        rms = np.sqrt(np.einsum("kl,kl->k", resid, resid) / np.maximum(count - npar, 1))
        return normal, rhs, count.astype(np.intp), rms.astype(np.float64), resid, mask

    def sector_chi(
        self,
        theta: NDArray[np.float64],
        du0: NDArray[np.float32],
        dv0: NDArray[np.float32],
        intensity: NDArray[np.float32],
        label: NDArray[np.intp],
        n_sectors: int,
    ) -> NDArray[np.float64]:
        """RMS residual of each fit's pixels in each sector (``label``: a pixel's sector, -1
        none), over the pixels the model would use at ``theta``; NaN below a few pixels."""
        im, ih = self.npar - 3, self.npar - 2
        _, mask, step_sum, _, _ = self._terms(theta, du0, dv0, label >= 0)
        resid = intensity - (theta[:, im : im + 1] + theta[:, ih : ih + 1] * step_sum)
        return _rms_by_sector(resid, mask, label, n_sectors)


def _rms_by_sector(
    resid: NDArray[np.floating[Any]],
    mask: NDArray[np.bool_],
    label: NDArray[np.intp],
    n_sectors: int,
) -> NDArray[np.float64]:
    """RMS of each row's masked residuals in each sector (``label``; NaN below a few pixels)."""
    k = resid.shape[0]
    flat = np.where(mask & (label >= 0), label + n_sectors * np.arange(k)[:, None], k * n_sectors)
    size = k * n_sectors + 1
    sums = np.bincount(flat.ravel(), weights=(resid * resid).ravel(), minlength=size)
    counts = np.bincount(flat.ravel(), minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(sums[:-1] / counts[:-1]).reshape(k, n_sectors)
    rms[counts[:-1].reshape(k, n_sectors) < _MIN_SECTOR_PIXELS] = np.nan
    return rms


@dataclass(frozen=True, slots=True, eq=False)
class _Tie:
    """Prior tying an annulus' inner edge to its outer one scaled by ``ratio``: whitened residuals
    ``r = w (inner - T outer)`` (``w`` = noise sd / prior sd, so they add to the intensity normal
    equations), their ``J^T`` over all parameters ``(k, npar, 5)`` and the constant ``J^T J``."""

    jt: NDArray[np.float64]
    w: NDArray[np.float64]
    ratio: NDArray[np.float64]
    normal: NDArray[np.float64]

    @classmethod
    def build(cls, seeds: NDArray[np.float64], npar: int, tie_px: float, sigma: float) -> _Tie:
        k = seeds.shape[0]
        ratio = seeds[:, 1, 2] / seeds[:, 0, 2]
        q_in = quadratic_form(seeds[:, 1, 2:5])
        a_in = seeds[:, 1, 2]
        # Edge shift of a form entry's change: dA/A * a / 2 pixels, so sd(A) = 2 tie A / a.
        sd = np.empty((k, 5))
        sd[:, :2] = tie_px
        sd[:, 2:] = 2.0 * tie_px * (np.abs(q_in[:, [0, 0, 2]]) + 1e-12) / a_in[:, None]
        w = sigma / sd
        jt = np.zeros((k, npar, 5))
        for i in range(5):
            jt[:, 5 + i, i] = w[:, i]
            jt[:, i, i] = -w[:, i] * (1.0 if i < 2 else 1.0 / ratio**2)
        return cls(jt, w, ratio, jt @ np.swapaxes(jt, 1, 2))

    def rows(self, rows: NDArray[np.intp]) -> _Tie:
        """The prior of some fits of the block."""
        return _Tie(self.jt[rows], self.w[rows], self.ratio[rows], self.normal[rows])

    def gradient(self, theta: NDArray[np.float64]) -> NDArray[np.float64]:
        """``J^T r`` at ``theta``."""
        diff = theta[:, 5:10].copy()
        diff[:, :2] -= theta[:, :2]
        diff[:, 2:] -= theta[:, 2:5] / self.ratio[:, None] ** 2
        return np.asarray((self.jt @ (self.w * diff)[:, :, None])[:, :, 0], dtype=np.float64)


def quadratic_form(axes: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(A, B, C)`` of ``R diag(1/a^2, 1/b^2) R^T`` for rows ``(a, b, angle)``."""
    a, b, ang = axes.T
    c, s = np.cos(ang), np.sin(ang)
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    return np.column_stack([c * c * ia + s * s * ib, c * s * (ia - ib), s * s * ia + c * c * ib])


def from_quadratic_form(
    theta: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(u, v, a, b, angle)`` from ``(u, v, A, B, C)``, canonical (``a >= b``, angle in
    ``[0, pi)``), with the Jacobian of the conversion (central differences)."""

    def convert(t: NDArray[np.float64]) -> NDArray[np.float64]:
        A, B, C = t[:, 2], t[:, 3], t[:, 4]
        with np.errstate(invalid="ignore", divide="ignore"):
            mean, half = 0.5 * (A + C), np.sqrt(0.25 * (A - C) ** 2 + B * B)
            a = 1.0 / np.sqrt(mean - half)  # the smaller eigenvalue is 1/a^2
            b = 1.0 / np.sqrt(mean + half)
            ang = 0.5 * np.arctan2(-2.0 * B, C - A)
        return np.column_stack([t[:, 0], t[:, 1], a, b, ang])

    # The point and its six displaced copies converted as one batch (seven calls' overhead
    # cost more than the arithmetic on a few hundred rows).
    n = theta.shape[0]
    h = 1e-6 * (np.abs(theta[:, 2]) + np.abs(theta[:, 4]))
    stacked = np.repeat(theta[None], 7, axis=0)
    for k, i in enumerate((2, 3, 4)):
        stacked[1 + 2 * k, :, i] += h
        stacked[2 + 2 * k, :, i] -= h
    conv = convert(stacked.reshape(7 * n, 5)).reshape(7, n, 5)
    params = conv[0]
    jac = np.zeros((n, 5, 5))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0
    for k, i in enumerate((2, 3, 4)):
        diff = conv[1 + 2 * k] - conv[2 + 2 * k]
        # The angle wraps by pi across the branch cut of arctan2.
        diff[:, 4] = np.mod(diff[:, 4] + 0.5 * np.pi, np.pi) - 0.5 * np.pi
        jac[:, :, i] = diff / (2 * h[:, None])
    params[:, 4] = np.mod(params[:, 4], np.pi)
    return params, jac


class _Geometry:
    """Signed distance of pixels from the current ellipses, its derivatives and the curvature."""

    __slots__ = ("d", "dd", "gn", "kappa", "rho")

    def __init__(
        self,
        d: NDArray[np.float32],
        dd: tuple[NDArray[np.float32], ...],
        kappa: NDArray[np.float32],
        rho: NDArray[np.float32],
        gn: NDArray[np.float32],
    ) -> None:
        self.d, self.dd, self.kappa, self.rho, self.gn = d, dd, kappa, rho, gn


def _geometry(
    theta: NDArray[np.float64], du0: NDArray[np.float32], dv0: NDArray[np.float32]
) -> _Geometry:
    """``d`` and ``dd/d(u, v, A, B, C)`` at every pixel (``theta[:, :2]`` is the centre's offset
    from the reference that ``du0, dv0`` are relative to)."""
    f32 = np.float32
    u, v, A, B, C = (theta[:, i : i + 1].astype(np.float32) for i in range(5))
    du = du0 - u
    dv = dv0 - v
    gx = A * du + B * dv  # half the gradient of q = (p - c)^T Q (p - c)
    gy = B * du + C * dv
    q = np.maximum(du * gx + dv * gy, f32(0.0))
    rho = np.sqrt(q)
    gn = np.maximum(np.sqrt(gx * gx + gy * gy), f32(1e-12))
    inv = f32(1.0) / gn
    d = (rho - f32(1.0)) * rho * inv
    # Second order along the normal: the level curves of rho are scaled copies of the ellipse,
    # not parallel to it, and off the axes the first-order distance falls short by a term in
    # d^2 (a 34 x 14 px ellipse: 0.02-0.04 px at 1 px from it, either side), which pulled the
    # fitted edges outwards. Zero on circles and on the axes.
    gqg = A * gx * gx + f32(2.0) * B * gx * gy + C * gy * gy
    d += f32(0.5) * d * d * (gqg * inv * inv - gn * gn / np.maximum(q, f32(1e-12))) * inv
    # First-order derivatives of the distance: d(q)/d(param) / (2 |grad q| / 2).
    half = f32(0.5) * inv
    dd = (-gx * inv, -gy * inv, du * du * half, du * dv * inv, dv * dv * half)
    # Curvature of the level curve through the pixel, times rho: the ellipse's curvature at the
    # corresponding point.
    kappa = (A * gy * gy - f32(2.0) * B * gx * gy + C * gx * gx) * inv * inv * inv * rho
    return _Geometry(d, dd, kappa, rho, gn)


# Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7): erf(x) = 1 - poly(1 / (1 + p x)) exp(-x^2),
# which reuses the Gaussian the Jacobian needs anyway (scipy's erf costs twice as much).
_Float = TypeVar("_Float", np.float32, np.float64)
_AS_P = 0.3275911 / np.sqrt(2.0)
_AS_COEFFS = (1.061405429, -1.453152027, 1.421413741, -0.284496736, 0.254829592)


def erf_scaled(t: NDArray[_Float], gauss: NDArray[_Float]) -> NDArray[_Float]:
    """``erf(t / sqrt(2))`` given ``gauss = exp(-t^2 / 2)``, in the precision of ``t``."""
    one = t.dtype.type(1.0)
    z = one / (one + t.dtype.type(_AS_P) * np.abs(t))
    poly = np.full_like(t, _AS_COEFFS[0])
    for c in _AS_COEFFS[1:]:
        poly *= z
        poly += t.dtype.type(c)
    poly *= z
    poly *= gauss
    out: NDArray[_Float] = np.copysign(one - poly, t)
    return out


def _levels(
    intensity: NDArray[np.float32], e: NDArray[np.float32], mask: NDArray[np.bool_]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-fit least squares of ``intensity ~ m + h e`` over the masked pixels."""
    w = mask.astype(np.float64)
    e64 = e.astype(np.float64) * w
    i64 = intensity.astype(np.float64) * w
    n = w.sum(axis=1)
    se, si = e64.sum(axis=1), i64.sum(axis=1)
    see, sei = (e64 * e64).sum(axis=1), (e64 * i64).sum(axis=1)
    det = n * see - se * se
    with np.errstate(divide="ignore", invalid="ignore"):
        h = (n * sei - se * si) / det
        m = (si - h * se) / n
    return np.nan_to_num(m), np.nan_to_num(h)


def _safe_solve(A: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched ``solve(A, b)`` for ``(k, n, n)`` and ``(k, n)``; NaN rows where singular."""
    return per_matrix(lambda m, v: np.linalg.solve(m, v[..., None])[..., 0], b.shape, A, b)


def _safe_inverse(A: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched inverse; NaN matrices where singular."""
    return per_matrix(np.linalg.inv, A.shape, A)


def per_matrix(
    op: Callable[..., NDArray[Any]],
    shape: tuple[int, ...],
    *args: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``op`` on whole batches, or item by item (NaN where singular) when a batch is singular."""
    try:
        return np.asarray(op(*args), dtype=np.float64)
    except np.linalg.LinAlgError:
        pass
    out = np.full(shape, np.nan)
    for i in range(shape[0]):
        with contextlib.suppress(np.linalg.LinAlgError):
            out[i] = op(*(x[i] for x in args))
    return out
