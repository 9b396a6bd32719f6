"""Sub-pixel ellipse estimation from image gradients (paper section 3, step 3).

Implements the dual-conic method of Ouellet & Hébert [1]: every pixel near an edge whose gradient is
strong defines a line ``l_i = (I_u, I_v, -(I_u u + I_v v))`` through the pixel, normal to the
gradient. Those lines are (nearly) tangent to the imaged circle, so they satisfy
``l_i^T C* l_i = 0`` for the *dual* conic ``C* = C^-1`` of the ellipse. ``C*`` is found by linear
least squares with ``C*_33 = 1`` after centring and scaling the coordinates; the ellipse is
``C = inv(C*)``. No contour points are extracted, so every pixel of the blurred edge contributes.

Refinements over [1] (measured in ``benchmarks/detector_precision.py``):

- pixels are restricted to a band of half-width ``band_px`` around the current ellipse (Sampson
  distance); a first pass uses a band one pixel wider for the seed's error, then the fit is
  repeated with the band re-centred on the previous estimate until it moves less than 0.01 px;
  the band has hard edges (no taper), so the final estimate does not depend on the previous
  pass's noise, which the covariance could not account for;
- pixels whose gradient direction disagrees with the ellipse normal, or whose polarity (dark to
  bright) is the opposite of the edge's, are excluded: they belong to neighbouring edges such as
  the code sectors; so are gradients not clearly above the noise;
- gradients are Scharr derivatives (normalised to intensity per pixel), computed only at the
  band's pixels for a few fits, or once with ``cv2.Scharr`` over the crop holding all the bands
  when many fits share an image (cheaper per pixel than gathering neighbourhoods in every pass);
  fits are batched: the distinct monomials of all normal equations are summed per fit with
  ``np.add.reduceat`` in one (15, N) array, no per-fit Python loop;
- gradients below a tenth of the band's strongest are ignored too (the blurred edge's far
  tails: ~17 % of the pixels, ~0.2 % of the weight);
- a fit that drifts far from its seed (it locked onto another edge) is rejected.

Uncertainty: the image noise ``sigma`` (estimated robustly from the image, or given) is propagated
to first order through the Scharr filter and the weighted normal equations, including the
correlation that the filter introduces between neighbouring gradients, then to the ellipse
parameters by a numerical Jacobian. This stays exact on the hot path: the per-pixel sensitivities
are computed in float32 and filtered for all fits at once on tiles packed into shared canvases.
The dual-conic fit's own residuals are *not* used to scale the covariance: they are dominated by
the deterministic spread of tangent lines across the blurred edge (the same in every noise
realisation), and would overstate the random error several times.

Pixel convention: ``(u, v)`` = (x, y) = (column, row), pixel centres at integer coordinates.

References
----------
.. [1] J.-N. Ouellet and P. Hébert, "Precise ellipse estimation without contour point extraction",
   Machine Vision and Applications 21 (2009) 59-67.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import DetectorError
from .types import Ellipse

__all__ = [
    "DEFAULT_BAND_PX",
    "ellipse_from_conic",
    "estimate_noise",
    "fit_ellipse",
    "fit_ellipses",
]

DEFAULT_BAND_PX = 2.5
"""Default half-width of the pixel band around the edge (final iteration), pixels."""

_MIN_BAND_PX = 1.5
_SEED_SLACK_PX = 1.0  # extra band half-width in the first iteration, for the seed's error
_MIN_COS = 0.85  # gradient direction vs ellipse normal: |angle| <= ~32 degrees
_MIN_REL_GRADIENT = 0.1  # gradients below this fraction of the band's strongest are ignored
_MIN_SNR = 3.0  # gradient magnitude over its noise std below which a pixel is ignored
_SCHARR_GAIN = float(np.sqrt(2 * (9 + 100 + 9)) / 32)  # noise std of a Scharr/32 derivative
_MIN_PIXELS = 12  # fewer band pixels than this cannot determine an ellipse reliably
_MAX_REFINEMENTS = 3  # passes after the first, while a fit still moves by > _CONVERGED_PX
_CONVERGED_PX = 0.01

# Scharr derivative along u, normalised to intensity per pixel: [[-3,0,3],[-10,0,10],[-3,0,3]]/32.
# (dv, du, weight) triples; the v derivative is the transpose.
_SCHARR_U = ((-1, -1, -3.0), (-1, 1, 3.0), (0, -1, -10.0), (0, 1, 10.0), (1, -1, -3.0), (1, 1, 3.0))
_SCHARR_KERNEL = np.array([[-3.0, 0.0, 3.0], [-10.0, 0.0, 10.0], [-3.0, 0.0, 3.0]]) / 32.0
# Scharr kernels rotated by 180 degrees (= negated), for the adjoint of the gradient filter.
_FLIPPED_U = np.ascontiguousarray(-_SCHARR_KERNEL, dtype=np.float32)
_FLIPPED_V = np.ascontiguousarray(-_SCHARR_KERNEL.T, dtype=np.float32)


SeedLike = Ellipse | ArrayLike


def ellipse_from_conic(C: ArrayLike) -> tuple[float, float, float, float, float]:
    """Centre, semi-axes and angle of the ellipse with conic matrix ``C``.

    Parameters
    ----------
    C : (3, 3) array_like
        Symmetric conic, ``[u v 1] C [u v 1]^T = 0`` on the ellipse (any scale, either sign).

    Returns
    -------
    (u, v, a, b, angle) : tuple of float
        Centre in pixels, semi-axes ``a >= b > 0`` and the major axis' angle from +u towards +v in
        ``[0, pi)`` (canonical form).

    Raises
    ------
    ValueError
        If ``C`` is not 3x3 or is not a real, non-degenerate ellipse.
    """
    arr = np.asarray(C, dtype=np.float64)
    if arr.shape != (3, 3):
        raise ValueError(f"conic must be a 3x3 matrix, got shape {arr.shape}")
    out = _ellipses_from_conics(arr[None])
    if not np.all(np.isfinite(out)):
        raise ValueError(f"conic is not a real ellipse: {arr.tolist()}")
    u, v, a, b, angle = (float(x) for x in out[0])
    return u, v, a, b, angle


def _ellipses_from_conics(C: NDArray[np.float64]) -> NDArray[np.float64]:
    """Vectorised :func:`ellipse_from_conic`: (n, 3, 3) -> (n, 5); NaN rows for non-ellipses."""
    C = 0.5 * (C + np.swapaxes(C, 1, 2))
    q11, q12, q22 = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    det = q11 * q22 - q12 * q12
    with np.errstate(divide="ignore", invalid="ignore"):
        # Centre: Q x0 = -c.
        x0 = (-q22 * C[:, 0, 2] + q12 * C[:, 1, 2]) / det
        y0 = (q12 * C[:, 0, 2] - q11 * C[:, 1, 2]) / det
        # (x - x0)^T Q (x - x0) = k on the ellipse.
        k = q11 * x0 * x0 + 2 * q12 * x0 * y0 + q22 * y0 * y0 - C[:, 2, 2]
        tr = q11 + q22
        disc = np.sqrt((q11 - q22) ** 2 + 4 * q12 * q12)
        lam_small = 0.5 * (tr / k - disc / np.abs(k))  # eigenvalues of Q / k: 1/a^2 <= 1/b^2
        lam_big = 0.5 * (tr / k + disc / np.abs(k))
        a = 1.0 / np.sqrt(lam_small)
        b = 1.0 / np.sqrt(lam_big)
        # Major axis: eigenvector of the smaller eigenvalue of Q.
        angle = 0.5 * np.arctan2(-2.0 * q12 * np.sign(k), -(q11 - q22) * np.sign(k))
    angle = np.mod(angle, np.pi)
    ok = (det > 0) & (lam_small > 0) & (lam_big > 0) & np.isfinite(a) & np.isfinite(b)
    out = np.column_stack([x0, y0, a, b, angle])
    out[~ok] = np.nan
    return out


def estimate_noise(image: ArrayLike) -> float:
    """Robust standard deviation of additive white noise in an image, in its intensity units.

    Immerkær's Laplacian-difference estimator, made robust to edges: its mean absolute response
    is taken only over pixels whose 3x3 neighbourhood has no gradient clearly above the noise
    (starting from a median-based estimate; two passes), so printed edges do not inflate it.
    Large images are subsampled by row blocks.

    Parameters
    ----------
    image : (H, W) array_like
        Grey image, at least 5x5.

    Returns
    -------
    float
        Noise standard deviation (NaN when no flat pixel is left); at least the quantisation
        noise ``1/sqrt(12)`` for integer images.
    """
    arr = np.asarray(image)
    if arr.ndim != 2 or min(arr.shape) < 5:
        raise DetectorError(f"noise estimation needs a 2-D image of at least 5x5, got {arr.shape}")
    blocks = [arr]
    if arr.size > 400_000:
        # On full frames, ~250k pixels in evenly spread blocks of 8 rows keep the estimate cheap.
        count = max(2, 250_000 // (8 * arr.shape[1]))
        rows = np.linspace(0, arr.shape[0] - 8, count).astype(int)
        blocks = [arr[r : r + 8] for r in rows]
    lap, grad = [], []
    for block in blocks:
        blk = np.asarray(block, dtype=np.float32)
        # Largest central difference in the 3x3 neighbourhood of each pixel (edge detector).
        g = np.maximum(
            np.abs(blk[1:-1, 2:] - blk[1:-1, :-2]), np.abs(blk[2:, 1:-1] - blk[:-2, 1:-1])
        )
        g = cv2.dilate(np.nan_to_num(g, nan=np.inf), np.ones((3, 3), np.uint8))
        lap.append(_laplacian_valid(blk).ravel())
        grad.append(g.ravel())
    response = np.abs(np.concatenate(lap))
    gmax = np.concatenate(grad)
    finite = np.isfinite(response)
    response, gmax = response[finite], gmax[finite]
    if response.size == 0:
        return float("nan")
    # The mask [[1,-2,1],[-2,4,-2],[1,-2,1]] has sum of squares 36; 0.6745 = median|N(0,1)|.
    sigma = _median(response, np.issubdtype(arr.dtype, np.integer)) / (0.6745 * 6.0)
    for _ in range(2):
        # A central difference of pure noise has std sigma * sqrt(2); 3.5 of those is an edge.
        flat = gmax <= 3.5 * np.sqrt(2.0) * max(sigma, 0.5)
        if np.count_nonzero(flat) < 0.1 * response.size:
            break
        # Mean absolute response over flat pixels (Immerkær's form; smoother than the median on
        # integer images): E|N(0, 36 sigma^2)| = 6 sigma sqrt(2 / pi).
        sigma = float(np.mean(response[flat])) * np.sqrt(0.5 * np.pi) / 6.0
    if np.issubdtype(arr.dtype, np.integer):
        # Quantisation floor: integer images carry at least 1/sqrt(12) of rounding noise.
        sigma = max(sigma, 1.0 / np.sqrt(12.0))
    return sigma


def _median(values: NDArray[np.float32], integral: bool) -> float:
    """``np.median`` of ``values``, by counting where they are whole numbers (``integral``: the
    responses of an integer image): the same number, without the selection's cost on the many
    equal values a flat image gives."""
    if not integral or values.size == 0:
        return float(np.median(values))
    n = values.size
    below = np.cumsum(np.bincount(values.astype(np.intp)))
    lower = np.float32(np.searchsorted(below, (n - 1) // 2, side="right"))
    upper = np.float32(np.searchsorted(below, n // 2, side="right"))
    return float((lower + upper) / np.float32(2.0))


def _laplacian_valid(img: NDArray[np.float32]) -> NDArray[np.float32]:
    """The valid part of the 3x3 noise-estimation mask's response."""
    a = img[:-2, :-2] - 2 * img[:-2, 1:-1] + img[:-2, 2:]
    b = img[1:-1, :-2] - 2 * img[1:-1, 1:-1] + img[1:-1, 2:]
    c = img[2:, :-2] - 2 * img[2:, 1:-1] + img[2:, 2:]
    return np.asarray(a - 2 * b + c, dtype=np.float32)


def _seed_parameters(seed: SeedLike, origin: tuple[int, int]) -> NDArray[np.float64]:
    """(u, v, a, b, angle) of a seed in ROI coordinates, or NaNs when it is unusable."""
    if isinstance(seed, Ellipse):
        p = np.array(
            [seed.center_px[0], seed.center_px[1], seed.semi_major, seed.semi_minor, seed.angle],
            dtype=np.float64,
        )
    else:
        pts = np.asarray(seed, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise DetectorError(
                f"a seed must be an Ellipse or (N, 2) boundary points, got shape {pts.shape}"
            )
        if pts.shape[0] < 5 or not np.all(np.isfinite(pts)):
            return np.full(5, np.nan)
        (cu, cv), (w, h), deg = cv2.fitEllipse(pts.astype(np.float32))
        a, b, ang = 0.5 * w, 0.5 * h, np.radians(deg)
        if b > a:
            a, b, ang = b, a, ang + 0.5 * np.pi
        p = np.array([cu, cv, a, b, np.mod(ang, np.pi)])
    p[0] -= origin[0]
    p[1] -= origin[1]
    if p[3] > p[2]:
        p[2], p[3], p[4] = p[3], p[2], np.mod(p[4] + 0.5 * np.pi, np.pi)
    if not np.all(np.isfinite(p)) or p[3] <= 0:
        return np.full(5, np.nan)
    return p


def _ellipse_seed_parameters(
    seeds: Sequence[Ellipse], origin: tuple[int, int]
) -> NDArray[np.float64]:
    """Vectorised :func:`_seed_parameters` for Ellipse seeds: (n, 5), NaN rows when unusable."""
    p = np.array(
        [(e.center_px[0], e.center_px[1], e.semi_major, e.semi_minor, e.angle) for e in seeds],
        dtype=np.float64,
    ).reshape(-1, 5)
    p[:, 0] -= origin[0]
    p[:, 1] -= origin[1]
    swap = p[:, 3] > p[:, 2]
    p[swap, 2], p[swap, 3] = p[swap, 3], p[swap, 2].copy()
    p[swap, 4] = np.mod(p[swap, 4] + 0.5 * np.pi, np.pi)
    bad = ~np.all(np.isfinite(p), axis=1) | ~(p[:, 3] > 0)
    p[bad] = np.nan
    return p


def _band_pixels(
    params: NDArray[np.float64], half_width: NDArray[np.float64], shape: tuple[int, int]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Pixels between the ellipses with semi-axes ``(a - m, b - m)`` and ``(a + m, b + m)``.

    Returns the fit index, u and v of every such pixel (one row-run or two per image row), kept
    one pixel away from the image border so that 3x3 derivatives are defined.
    """
    height, width = shape
    u0, v0, a, b, ang = params.T
    c, s = np.cos(ang), np.sin(ang)
    ao, bo = a + half_width, b + half_width
    half_h = np.sqrt((ao * s) ** 2 + (bo * c) ** 2)
    vlo = np.clip(np.ceil(v0 - half_h), 1, height).astype(np.intp)
    vhi = np.clip(np.floor(v0 + half_h), -1, height - 2).astype(np.intp)
    nrows = np.where(half_width > 0, np.maximum(vhi - vlo + 1, 0), 0)
    fit = np.repeat(np.arange(len(params)), nrows)
    first = np.cumsum(nrows) - nrows
    v = vlo[fit] + (np.arange(fit.size) - first[fit])
    dv = v - v0[fit]

    def row_span(
        A: NDArray[np.float64], B: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        # Solve q11 du^2 + 2 q12 du dv + q22 dv^2 = 1 for du on each row.
        cf, sf = c[fit], s[fit]
        ia, ib = 1.0 / (A[fit] ** 2), 1.0 / (B[fit] ** 2)
        q11 = cf * cf * ia + sf * sf * ib
        q12 = cf * sf * (ia - ib)
        q22 = sf * sf * ia + cf * cf * ib
        disc = q12 * q12 * dv * dv - q11 * (q22 * dv * dv - 1.0)
        root = np.sqrt(np.where(disc > 0, disc, np.nan))
        mid = u0[fit] - q12 * dv / q11
        return mid - root / q11, mid + root / q11

    with np.errstate(invalid="ignore"):
        olo, ohi = row_span(ao, bo)
        inner_a = np.maximum(a - half_width, 0.0)
        inner_b = b - half_width
        has_inner = inner_b > 0.5
        ilo, ihi = row_span(np.where(has_inner, inner_a, 1.0), np.where(has_inner, inner_b, 1.0))
        ilo = np.where(has_inner[fit], ilo, np.nan)
        ihi = np.where(has_inner[fit], ihi, np.nan)
    hole = np.isfinite(ilo)
    l1 = np.ceil(olo)
    r1 = np.where(hole, np.floor(ilo), np.floor(ohi))
    l2 = np.where(hole, np.ceil(ihi), 0.0)
    r2 = np.where(hole, np.floor(ohi), -1.0)
    # Runs ordered by (fit, row, left/right), so the pixels come out grouped by fit.
    starts = np.column_stack([l1, l2]).ravel()
    ends = np.column_stack([r1, r2]).ravel()
    starts = np.maximum(np.nan_to_num(starts, nan=1.0), 1.0)
    ends = np.minimum(np.nan_to_num(ends, nan=-1.0), width - 2.0)
    lengths = np.maximum(ends - starts + 1, 0).astype(np.intp)
    run_fit = np.repeat(fit, 2)
    run_v = np.repeat(v, 2)
    total = int(lengths.sum())
    run_of = np.repeat(np.arange(lengths.size), lengths)
    run_first = np.cumsum(lengths) - lengths
    pu = starts.astype(np.intp)[run_of] + (np.arange(total) - run_first[run_of])
    return run_fit[run_of], pu, run_v[run_of]


def _gradients_at(
    img: NDArray[Any], u: NDArray[np.intp], v: NDArray[np.intp]
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Scharr derivatives (intensity per pixel) at pixels ``(u, v)`` (not on the border)."""
    flat = img.ravel()
    stride = img.shape[1]
    base = v * stride + u
    gu = np.zeros(u.shape, dtype=np.float32)
    gv = np.zeros(u.shape, dtype=np.float32)
    # Differences of opposite neighbours, then the [3, 10, 3] smoothing across.
    for dv, du, w in _SCHARR_U:
        if du < 0:
            continue
        row = base + dv * stride
        col = base + dv
        gu += np.float32(w / 32.0) * (
            flat[row + 1].astype(np.float32) - flat[row - 1].astype(np.float32)
        )
        gv += np.float32(w / 32.0) * (
            flat[col + stride].astype(np.float32) - flat[col - stride].astype(np.float32)
        )
    return gu.astype(np.float64), gv.astype(np.float64)


class _GradientField:
    """Scharr derivatives (intensity per pixel = ``scale`` x stored values) of an image crop whose
    top-left pixel is ``origin`` = (u0, v0) of the fitted image."""

    __slots__ = ("gu", "gv", "origin", "scale")

    def __init__(
        self, gu: NDArray[Any], gv: NDArray[Any], scale: float, origin: tuple[int, int]
    ) -> None:
        self.gu, self.gv, self.scale, self.origin = gu, gv, scale, origin

    def at(
        self, u: NDArray[np.intp], v: NDArray[np.intp]
    ) -> tuple[NDArray[Any], NDArray[Any], NDArray[np.intp] | None]:
        """Stored derivatives (times ``scale``: intensity per pixel) at pixels ``(u, v)``, and
        the indices of pixels outside the crop (or None; their derivatives are set to zero)."""
        cu, cv = u - self.origin[0], v - self.origin[1]
        h, w = self.gu.shape
        outside = None
        if cu.size and (cu.min() < 0 or cv.min() < 0 or cu.max() >= w or cv.max() >= h):
            out = (cu < 0) | (cv < 0) | (cu >= w) | (cv >= h)
            outside = np.flatnonzero(out)
            cu, cv = np.where(out, 0, cu), np.where(out, 0, cv)
        gu = self.gu[cv, cu]
        gv = self.gv[cv, cu]
        if outside is not None:
            gu[outside] = 0
            gv[outside] = 0
        return gu, gv, outside


# Gathering the 3x3 neighbourhood at a band pixel costs about ten times as much as filtering one
# pixel with cv2.Scharr; with this many expected band-pixel visits per crop pixel (all passes),
# the whole crop is filtered once instead.
_CROP_FILTER_RATIO = 0.1


def _crop_gradients(
    img: NDArray[Any], params: NDArray[np.float64], ok: NDArray[np.bool_], band: NDArray[np.float64]
) -> _GradientField | None:
    """Scharr derivatives of the image crop holding every fit's reachable band, when filtering it
    once is cheaper than gathering neighbourhoods at the band's pixels in every pass."""
    if not np.any(ok):
        return None
    u0, v0, a, b = (params[ok, k] for k in range(4))
    reach = a + 3.0 * (band[ok] + _SEED_SLACK_PX) + 3.0
    h, w = img.shape
    ulo = int(np.clip(np.floor(np.min(u0 - reach)), 0, w - 1))
    uhi = int(np.clip(np.ceil(np.max(u0 + reach)), 0, w - 1))
    vlo = int(np.clip(np.floor(np.min(v0 - reach)), 0, h - 1))
    vhi = int(np.clip(np.ceil(np.max(v0 + reach)), 0, h - 1))
    area = (uhi - ulo + 1) * (vhi - vlo + 1)
    # Expected band pixels over about two and a half passes.
    visits = 2.5 * float(np.sum(np.pi * (a + b) * 2.0 * (band[ok] + _SEED_SLACK_PX)))
    if visits < _CROP_FILTER_RATIO * area:
        return None
    # One pixel more on every side, so the crop's own border never enters a derivative.
    cu0, cv0 = max(ulo - 1, 0), max(vlo - 1, 0)
    crop = img[cv0 : min(vhi + 2, h), cu0 : min(uhi + 2, w)]
    if crop.dtype == np.uint8:
        # Exact in int16 (|sum| <= 16 * 255); scaled to intensity per pixel when gathered.
        gu = cv2.Scharr(crop, cv2.CV_16S, 1, 0)
        gv = cv2.Scharr(crop, cv2.CV_16S, 0, 1)
    else:
        crop32 = np.asarray(crop, dtype=np.float32)
        gu = cv2.Scharr(crop32, cv2.CV_32F, 1, 0)
        gv = cv2.Scharr(crop32, cv2.CV_32F, 0, 1)
    return _GradientField(gu, gv, 1.0 / 32.0, (cu0, cv0))


def _segments(fit: NDArray[np.intp], n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Start offset and count of each fit's pixels in the fit-sorted pixel arrays."""
    counts = np.bincount(fit, minlength=n)
    return np.cumsum(counts) - counts, counts


def _segment_sum(values: NDArray[np.float64], fit: NDArray[np.intp], n: int) -> NDArray[np.float64]:
    """Per-fit sums of ``values`` (pixels along axis 0, sorted by fit)."""
    out = np.zeros((n, *values.shape[1:]))
    if values.shape[0] == 0:
        return out
    starts, counts = _segments(fit, n)
    present = counts > 0
    out[present] = np.add.reduceat(values, starts[present], axis=0)
    return out


def _per_fit(value: float | Sequence[float], n: int, name: str) -> NDArray[np.float64]:
    """A scalar or one value per seed, as a float array of length ``n``."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.size != n):
        raise DetectorError(f"{name} must be a number or one per seed ({n}), got shape {arr.shape}")
    return np.broadcast_to(arr, (n,)).copy()


def fit_ellipses(
    image: ArrayLike,
    seeds: Sequence[SeedLike],
    radii: Sequence[float] | float,
    *,
    band_px: float | Sequence[float] | None = None,
    gradients: tuple[ArrayLike, ArrayLike] | None = None,
    origin: tuple[int, int] = (0, 0),
    noise_std: float | None = None,
    dark_inside: bool | Sequence[bool | None] | None = None,
    covariance: bool = True,
) -> list[Ellipse | None]:
    """Fit many ellipses in one image at once (batched :func:`fit_ellipse`).

    Parameters
    ----------
    image : (H, W) array_like
        Grey image (any real dtype), or an ROI crop of one whose top-left pixel is ``origin``.
    seeds : sequence of Ellipse or (N, 2) array_like
        Coarse estimates in full-image pixel coordinates: an :class:`Ellipse` (e.g. from
        ``cv2.fitEllipse`` of a component boundary) or the boundary points ``(u, v)`` themselves.
    radii : sequence of float, or float
        Nominal radius of each printed circle (fraction of the outer radius), stored in the result.
    band_px : float or sequence of float, optional
        Half-width of the pixel band around the edge in the final iterations. Default: half the
        seed's semi-minor axis, clipped to ``[1.5, DEFAULT_BAND_PX]`` pixels (right for blur
        sigma up to ~1 px; narrower on small ellipses, whose neighbouring printed edges are
        close). The first iteration adds one pixel for the seed's error. A caller that knows
        the printed geometry should keep it below half the distance to the nearest other
        printed edge (e.g. code sectors next to a thin ring), whose blurred gradients otherwise
        bias the fit even though their polarity excludes them.
    gradients : (gu, gv) of (H, W) array_like, optional
        Precomputed derivatives of ``image`` along u and v, which must be Scharr derivatives in
        intensity per pixel (``cv2.Scharr(img, cv2.CV_32F, 1, 0) / 32``) for the covariance to
        hold. By default they are computed at the band's pixels (few fits) or once over the crop
        holding every band (many fits), whichever is cheaper.
    origin : (int, int)
        Full-image ``(u0, v0)`` of ``image[0, 0]``; results are in full-image pixels.
    noise_std : float, optional
        Standard deviation of the image noise in ``image``'s intensity units; estimated with
        :func:`estimate_noise` when omitted. Scales the returned covariances.
    dark_inside : bool or sequence of (bool or None), optional
        Polarity of each edge (True: dark inside the ellipse, as ``design.Circle.dark_inside``).
        Pixels of the other polarity are ignored. When omitted it is voted by the gradients
        nearest the seed; giving it makes thin annuli (two close edges) safe.
    covariance : bool
        Whether to compute the covariances (a third of the cost of a few fits); without, each
        ellipse's covariance is NaN (for callers that need only the geometry, e.g. to read a
        code again through it).

    Returns
    -------
    list of Ellipse or None
        One per seed; None where the fit is degenerate (too few edge pixels, not an ellipse,
        non-finite values, or the seed is unusable).

    Raises
    ------
    DetectorError
        If ``image`` is not 2-D, a seed has the wrong shape, or ``radii`` does not match.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise DetectorError(f"image must be 2-D (grey), got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise DetectorError(f"image must have a real dtype, got {img.dtype}")
    n = len(seeds)
    radius_arr = _per_fit(radii, n, "radii")
    if gradients is not None:
        gshape = tuple(np.shape(g) for g in gradients)
        if len(gshape) != 2 or any(s != img.shape for s in gshape):
            raise DetectorError(f"gradients must be two arrays of shape {img.shape}, got {gshape}")
    if band_px is not None:
        band_arr = _per_fit(band_px, n, "band_px")
        if not np.all(band_arr > 0.5):
            raise DetectorError(f"band_px must be > 0.5 pixel, got {band_px}")
    if n == 0:
        return []
    if min(img.shape) < 5:
        return [None] * n
    # Keep the caller's dtype (no full-frame conversion); samples are cast where gathered.
    imgf = (
        img
        if img.dtype in (np.uint8, np.uint16, np.float32, np.float64)
        else img.astype(np.float64)
    )
    imgf = np.ascontiguousarray(imgf)
    sigma = estimate_noise(imgf) if noise_std is None else float(noise_std)
    if np.issubdtype(img.dtype, np.integer) and noise_std is None:
        sigma = max(sigma, 1.0 / np.sqrt(12.0))
    if all(isinstance(s, Ellipse) for s in seeds):
        params = _ellipse_seed_parameters(seeds, origin)  # type: ignore[arg-type]
    else:
        params = np.array([_seed_parameters(s, origin) for s in seeds]).reshape(n, 5)
    ok = np.all(np.isfinite(params), axis=1)
    params[~ok] = np.array([0.0, 0.0, 1.0, 1.0, 0.0])
    grads: _GradientField | None = None
    if gradients is not None:
        grads = _GradientField(np.asarray(gradients[0]), np.asarray(gradients[1]), 1.0, (0, 0))
    seed_params = params.copy()
    if dark_inside is None:
        sign = np.full(n, np.nan)
    else:
        flags = np.broadcast_to(np.asarray(dark_inside, dtype=object), (n,))
        sign = np.array([np.nan if f is None else (1.0 if f else -1.0) for f in flags])
    if band_px is None:
        # Narrow the band on small ellipses, whose neighbouring printed edges are close.
        band = np.clip(0.5 * params[:, 3], _MIN_BAND_PX, DEFAULT_BAND_PX)
    else:
        band = band_arr.copy()
    if grads is None:
        grads = _crop_gradients(imgf, params, ok, band)
    # First pass with a wider band for the seed's error, then passes with the band re-centred on
    # the previous estimate, repeated only for fits that still moved (elongated ellipses).
    state = _fit_once(
        imgf, params, np.where(ok, band + _SEED_SLACK_PX, 0.0), ok, grads, sign, sigma
    )
    ok &= state.ok
    params = np.where(ok[:, None], state.params, params)
    rms = state.rms.copy()
    passes = [state]
    owner = np.zeros(n, dtype=np.intp)  # the pass each fit's final estimate comes from
    active = ok.copy()
    for _ in range(_MAX_REFINEMENTS):
        new = _fit_once(imgf, params, np.where(active, band, 0.0), active, grads, sign, sigma)
        moved = np.max(np.abs(new.params[:, :4] - params[:, :4]), axis=1, initial=0.0)
        ok &= ~active | new.ok
        done = active & ok
        params = np.where(done[:, None], new.params, params)
        rms = np.where(done, new.rms, rms)
        owner[active] = len(passes)
        passes.append(new)
        active &= ok & (moved > _CONVERGED_PX)
        if not np.any(active):
            break
    # A fit that wandered far from its seed locked onto some other edge: not this ellipse.
    limit = 2.0 * (band + _SEED_SLACK_PX)
    drift = np.max(np.abs(params[:, :4] - seed_params[:, :4]), axis=1)
    ok &= np.nan_to_num(drift, nan=np.inf) <= limit
    cov = np.full((n, 5, 5), np.nan)
    for k, st in enumerate(passes):
        mine = ok & (owner == k)
        if covariance and np.any(mine):
            cov[mine] = _covariances(st, sigma, mine)[mine]
    results: list[Ellipse | None] = []
    for j in range(n):
        if not ok[j] or (covariance and not np.all(np.isfinite(cov[j]))):
            results.append(None)
            continue
        u, v, a, b, ang = params[j]
        results.append(
            Ellipse(
                center_px=(float(u + origin[0]), float(v + origin[1])),
                semi_major=float(a),
                semi_minor=float(b),
                angle=float(ang),
                covariance=cov[j],
                radius=float(radius_arr[j]),
                rms_residual=float(rms[j]),
            )
        )
    return results


def fit_ellipse(
    image: ArrayLike,
    seed: SeedLike,
    *,
    radius: float,
    band_px: float | None = None,
    gradients: tuple[ArrayLike, ArrayLike] | None = None,
    origin: tuple[int, int] = (0, 0),
    noise_std: float | None = None,
    dark_inside: bool | None = None,
) -> Ellipse | None:
    """Fit one ellipse to the image gradients around a seed (Ouellet & Hébert dual conic).

    Parameters
    ----------
    image : (H, W) array_like
        Grey image, or an ROI crop of one whose top-left pixel is ``origin`` (full-image
        ``(u0, v0)``). Pixel centres at integer coordinates.
    seed : Ellipse or (N, 2) array_like
        Coarse ellipse, or boundary points ``(u, v)``, in full-image pixels.
    radius : float
        Nominal radius of the printed circle (fraction of the outer radius), stored in the result.
    band_px, gradients, origin, noise_std, dark_inside
        See :func:`fit_ellipses`.

    Returns
    -------
    Ellipse or None
        The fitted ellipse in full-image pixels with the covariance of
        ``(u, v, semi_major, semi_minor, angle)``; None for a degenerate fit.
    """
    return fit_ellipses(
        image,
        [seed],
        [radius],
        band_px=band_px,
        gradients=gradients,
        origin=origin,
        noise_std=noise_std,
        dark_inside=dark_inside,
    )[0]


class _FitState:
    """Per-pixel and per-fit quantities of one dual-conic solve, kept for the covariance."""

    __slots__ = (
        "M",
        "W",
        "fit",
        "gmag",
        "nu",
        "nv",
        "ok",
        "params",
        "pu",
        "pv",
        "rms",
        "scale",
        "theta",
        "x",
        "y",
    )

    def __init__(self, **kw: NDArray[Any]) -> None:
        for k, val in kw.items():
            setattr(self, k, val)

    M: NDArray[np.float64]
    W: NDArray[np.float64]
    fit: NDArray[np.intp]
    gmag: NDArray[np.float64]
    nu: NDArray[np.float64]
    nv: NDArray[np.float64]
    ok: NDArray[np.bool_]
    params: NDArray[np.float64]
    pu: NDArray[np.intp]
    pv: NDArray[np.intp]
    rms: NDArray[np.float64]
    scale: NDArray[np.float64]
    theta: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]


# Rows of one packed canvas chunk in the covariance's filtering (about 8 MB per 5-channel buffer).
_CHUNK_ROWS = 192

# Index pairs of the 15 distinct entries of a symmetric 5x5 matrix.
_IU = np.triu_indices(5)


def _dual_to_conics(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Conic matrices ``inv(C*)`` of dual conics ``theta = (A, B, C, D, E)`` with ``C*_33 = 1``."""
    A, B, Cc, D, E = theta.T
    dual = np.empty((len(theta), 3, 3))
    dual[:, 0, 0], dual[:, 1, 1], dual[:, 2, 2] = A, Cc, 1.0
    dual[:, 0, 1] = dual[:, 1, 0] = 0.5 * B
    dual[:, 0, 2] = dual[:, 2, 0] = 0.5 * D
    dual[:, 1, 2] = dual[:, 2, 1] = 0.5 * E
    det = np.linalg.det(dual)
    good = np.isfinite(det) & (np.abs(det) > 1e-300)
    out = np.full_like(dual, np.nan)
    if np.any(good):
        out[good] = np.linalg.inv(dual[good])
    return out


# The 15 distinct entries of W p p^T (p = (nu^2, nu nv, nv^2, nu c, nv c)) hold 12 distinct
# monomials: p1 p1 = p0 p2, p1 p3 = p0 p4, p2 p3 = p1 p4. Rows of the sums below, per entry.
_PAIRS = (
    (0, 0),
    (0, 1),
    (0, 2),
    (0, 3),
    (0, 4),
    (1, 2),
    (1, 4),
    (2, 2),
    (2, 4),
    (3, 3),
    (3, 4),
    (4, 4),
)
_SAME = {(1, 1): (0, 2), (1, 3): (0, 4), (2, 3): (1, 4)}
_ENTRY_ROW = np.array(
    [_PAIRS.index(_SAME.get((int(i), int(j)), (int(i), int(j)))) for i, j in zip(*_IU, strict=True)]
)


def _normal_equations(
    nu: NDArray[np.float64],
    nv: NDArray[np.float64],
    c: NDArray[np.float64],
    W: NDArray[np.float64],
    fit: NDArray[np.intp],
    n: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per-fit ``M = sum W p p^T``, ``rhs = -sum W c^2 p`` and ``sum W`` (pixels sorted by fit).

    One (15, N) array of the distinct weighted monomials (``W c^2 (nu^2, nu nv, nv^2)`` are
    entries of M already), summed per fit along contiguous rows.
    """
    p = (nu * nu, nu * nv, nv * nv, nu * c, nv * c)
    rows = np.empty((15, nu.size))
    wp = [W * pk for pk in p]
    for k, (i, j) in enumerate(_PAIRS):
        np.multiply(wp[i], p[j], out=rows[k])
    cc = c * c
    np.multiply(wp[3], cc, out=rows[12])
    np.multiply(wp[4], cc, out=rows[13])
    rows[14] = W
    sums = np.zeros((n, 15))
    starts, counts = _segments(fit, n)
    present = counts > 0
    if nu.size:
        sums[present] = np.add.reduceat(rows, starts[present], axis=1).T
    M = np.empty((n, 5, 5))
    M[:, _IU[0], _IU[1]] = sums[:, _ENTRY_ROW]
    M[:, _IU[1], _IU[0]] = sums[:, _ENTRY_ROW]
    rhs = -np.column_stack([sums[:, 9], sums[:, 10], sums[:, 11], sums[:, 12], sums[:, 13]])
    return M, rhs, sums[:, 14]


def _fit_once(
    img: NDArray[Any],
    params: NDArray[np.float64],
    half: NDArray[np.float64],
    ok: NDArray[np.bool_],
    gradients: _GradientField | None,
    sign: NDArray[np.float64],
    sigma: float,
) -> _FitState:
    """One weighted dual-conic solve for every fit, with the band around ``params``."""
    n = len(params)
    fit, pu, pv = _band_pixels(params, half, img.shape)
    bad = np.zeros(n, dtype=bool)
    gscale = 1.0
    ru: NDArray[Any]
    rv: NDArray[Any]
    if gradients is None:
        ru, rv = _gradients_at(img, pu, pv)
    else:
        ru, rv, outside = gradients.at(pu, pv)
        gscale = gradients.scale
        if outside is not None:
            # Bands that wandered off the precomputed crop: those fits moved far, not this edge.
            bad = np.bincount(fit[outside], minlength=n) > 0
    if ru.dtype.kind == "f" and not np.isfinite(np.sum(ru) + np.sum(rv)):
        # NaN or inf pixels near the edge: those fits are degenerate.
        finite = np.isfinite(ru) & np.isfinite(rv)
        bad |= np.bincount(fit[~finite], minlength=n) > 0
        ru, rv = np.where(finite, ru, 0), np.where(finite, rv, 0)
    # Gradients not clearly above the noise carry no edge and point anywhere; they would also
    # make the first-order covariance overstate the scatter. Drop them first (cheapest: squared
    # magnitudes in float32, before anything else is computed for the pixel). Also the blurred
    # edge's far tails (below a tenth of the band's strongest gradient): with weights |g|^2 they
    # carry ~0.2 % of the information on 17 % of the pixels (measured).
    fu, fv = ru.astype(np.float32, copy=False), rv.astype(np.float32, copy=False)
    g2 = fu * fu
    g2 += fv * fv
    floor2 = np.zeros(n)
    starts, counts = _segments(fit, n)
    present = counts > 0
    if g2.size:
        floor2[present] = _MIN_REL_GRADIENT**2 * np.maximum.reduceat(g2, starts[present])
    floor2 = np.maximum(floor2, (_MIN_SNR * _SCHARR_GAIN * sigma / gscale) ** 2)
    strong = np.flatnonzero(g2 > floor2[fit])
    fit, pu, pv = fit[strong], pu[strong], pv[strong]
    gu = ru[strong].astype(np.float64)
    gv = rv[strong].astype(np.float64)
    if gscale != 1.0:
        gu *= gscale
        gv *= gscale
    gmag = np.sqrt(gu * gu + gv * gv)
    # Centre and scale coordinates on the current estimate for conditioning ([1], section 3).
    u0, v0, a, b, ang = params.T
    scale = a.copy()
    inv_scale = (1.0 / scale)[fit]
    x = (pu - u0[fit]) * inv_scale
    y = (pv - v0[fit]) * inv_scale
    cs, sn = np.cos(ang), np.sin(ang)
    ia, ib = (scale / a) ** 2, (scale / b) ** 2
    q11 = cs * cs * ia + sn * sn * ib
    q12 = cs * sn * (ia - ib)
    q22 = sn * sn * ia + cs * cs * ib
    # Sampson distance to the current ellipse (pixels), and the ellipse's normal direction.
    fx = q11[fit] * x + q12[fit] * y
    fy = q12[fit] * x + q22[fit] * y
    glen = np.maximum(2.0 * np.hypot(fx, fy), 1e-12)
    dist = (x * fx + y * fy - 1.0) / glen * scale[fit]
    nu, nv = gu / gmag, gv / gmag
    cosang = (nu * fx + nv * fy) * (2.0 / glen)
    inband = np.abs(dist) < half[fit]
    # Polarity of the edge (+1: dark inside, gradients point outwards): given, or voted by the
    # gradients nearest the current ellipse (a neighbouring edge of the other polarity, such as
    # the other side of a thin annulus, must not win the vote).
    polarity = sign
    if np.any(np.isnan(sign)):
        near = np.where(inband, gmag * cosang * np.exp(-0.5 * dist * dist), 0.0)
        vote = _segment_sum(near, fit, n)
        polarity = np.where(np.isnan(sign), np.where(vote >= 0, 1.0, -1.0), sign)
    # Pixels in the band whose gradient agrees with the ellipse normal, with the edge's polarity.
    sel = np.flatnonzero(inband & (polarity[fit] * cosang > _MIN_COS))
    fit, pu, pv = fit[sel], pu[sel], pv[sel]
    x, y, nu, nv, gmag = x[sel], y[sel], nu[sel], nv[sel], gmag[sel]
    # Weights: squared gradient magnitude ([1]). No taper at the band's edge: it would make the
    # result depend on the previous iteration's noise and the covariance would miss that.
    W = gmag * gmag
    counts = np.bincount(fit, minlength=n)
    c = -(nu * x + nv * y)
    M, rhs, wsum = _normal_equations(nu, nv, c, W, fit, n)
    good = ok & ~bad & (counts >= _MIN_PIXELS)
    theta = np.full((n, 5), np.nan)
    if np.any(good):
        Mg = M[good]
        # Condition check before solving: a near-singular system is a degenerate fit.
        # M is symmetric: its singular values are its eigenvalues' magnitudes (eigvalsh is
        # several times cheaper than the SVD behind np.linalg.cond).
        lam = np.abs(np.linalg.eigvalsh(Mg))
        with np.errstate(divide="ignore", invalid="ignore"):
            cond = lam.max(axis=1) / lam.min(axis=1)
        solvable = np.isfinite(cond) & (cond < 1e12)
        idx = np.flatnonzero(good)[solvable]
        if idx.size:
            theta[idx] = np.linalg.solve(M[idx], rhs[idx][:, :, None])[:, :, 0]
    ell = _ellipses_from_conics(_dual_to_conics(np.nan_to_num(theta, nan=0.0)))
    ell[~np.all(np.isfinite(theta), axis=1)] = np.nan
    new = np.column_stack(
        [u0 + scale * ell[:, 0], v0 + scale * ell[:, 1], scale * ell[:, 2], scale * ell[:, 3]]
    )
    new = np.column_stack([new, ell[:, 4]])
    tp = np.nan_to_num(theta)
    r = c * c + tp[fit, 0] * (nu * nu)
    r += tp[fit, 1] * (nu * nv)
    r += tp[fit, 2] * (nv * nv)
    r += tp[fit, 3] * (nu * c)
    r += tp[fit, 4] * (nv * c)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(_segment_sum(W * r * r, fit, n) / wsum)
    fine = good & np.all(np.isfinite(new), axis=1) & (new[:, 3] > 0.25)
    return _FitState(
        M=M,
        W=W,
        fit=fit,
        gmag=gmag,
        nu=nu,
        nv=nv,
        ok=fine,
        params=new,
        pu=pu,
        pv=pv,
        rms=rms,
        scale=scale,
        theta=theta,
        x=x,
        y=y,
    )


def _sensitivities(st: _FitState, sigma: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Per-pixel ``d(W p r)/d g`` (two (N, 5) arrays, for g_u and g_v): how a perturbation of the
    pixel's gradient moves the normal equations (first order, at the solution).

    The derivatives belong at the noise-free gradients, which are not known. Terms that vanish for
    an ideal edge (a tangent line turned about its point of contact does not move to first order)
    are driven by the angle ``phi`` between the gradient and the fitted ellipse's normal, which
    has a deterministic part ``phi0`` (filter anisotropy, pixel effects) and noise of variance
    ``s^2 = (sigma_g / |g|)^2``. The exact variance contains ``4 phi0^2 s^2 + 2 s^4``; plugging
    in the measured angle would give ``4 (phi0^2 + s^2) s^2``, overstating the scatter (by up to
    ~50 % at 2 % noise). So each pixel's angle is shrunk to ``phi^2 - s^2 / 2`` in expectation.
    """
    # float32 throughout: these feed a covariance (relative precision ~1e-6 is ample), and the
    # per-pixel work is memory bound.
    f32 = np.float32
    fit = st.fit
    th = np.nan_to_num(st.theta).astype(f32)
    t0, t1, t2, t3, t4 = (th[:, k][fit] for k in range(5))
    x, y, W = st.x.astype(f32), st.y.astype(f32), st.W.astype(f32)
    gnu, gnv, gmag = st.nu.astype(f32), st.nv.astype(f32), st.gmag.astype(f32)
    conic = np.nan_to_num(_dual_to_conics(np.nan_to_num(st.theta))).astype(f32)
    c00, c01, c02 = conic[:, 0, 0][fit], conic[:, 0, 1][fit], conic[:, 0, 2][fit]
    c11, c12 = conic[:, 1, 1][fit], conic[:, 1, 2][fit]
    mu = c00 * x + c01 * y + c02
    mv = c01 * x + c11 * y + c12
    flip = np.where(mu * gnu + mv * gnv < 0, f32(-1.0), f32(1.0)) / np.maximum(
        np.hypot(mu, mv), f32(1e-30)
    )
    mu *= flip
    mv *= flip
    phi = np.arctan2(mu * gnv - mv * gnu, mu * gnu + mv * gnv)
    s2 = np.square(f32(_SCHARR_GAIN * sigma) / gmag)
    with np.errstate(divide="ignore", invalid="ignore"):
        shrink = np.sqrt(np.clip(1.0 - 0.5 * s2 / (phi * phi), 0.0, 1.0, dtype=f32))
    psi = np.nan_to_num(shrink) * phi
    cs, sn = np.cos(psi), np.sin(psi)
    nu, nv = mu * cs - mv * sn, mv * cs + mu * sn
    c = -(nu * x + nv * y)
    # p = (nu^2, nu nv, nv^2, nu c, nv c) and the residual r = p . theta + c^2.
    p = (nu * nu, nu * nv, nv * nv, nu * c, nv * c)
    r = p[0] * t0 + p[1] * t1 + p[2] * t2 + p[3] * t3 + p[4] * t4 + c * c
    # dp/dn for c = -(nu x + nv y): d/dnu = (2 nu, nv, 0, c - nu x, -nv x),
    # d/dnv = (0, nu, 2 nv, -nu y, c - nv y).
    dp_du = (2 * nu, nv, None, c - nu * x, -nv * x)
    dp_dv = (None, nu, 2 * nv, -nu * y, c - nv * y)
    dr_du = 2 * nu * t0 + nv * t1 + dp_du[3] * t3 + dp_du[4] * t4 - 2 * c * x
    dr_dv = nu * t1 + 2 * nv * t2 + dp_dv[3] * t3 + dp_dv[4] * t4 - 2 * c * y
    # Chain through n = g/|g|: dn/dg = (I - n n^T)/|g|; and W = |g|^2: dW/dg = 2 W n / |g|.
    inv = 1 / gmag
    a11, a12, a22 = (1 - nu * nu) * inv, -nu * nv * inv, (1 - nv * nv) * inv
    wr = W * r
    fu = r * (2 * W * nu * inv) + W * (dr_du * a11 + dr_dv * a12)
    fv = r * (2 * W * nv * inv) + W * (dr_du * a12 + dr_dv * a22)
    Vu = np.empty((fit.size, 5), f32)
    Vv = np.empty((fit.size, 5), f32)
    for k in range(5):
        du, dv = dp_du[k], dp_dv[k]
        if du is None:
            assert dv is not None
            gu_k, gv_k = dv * a12, dv * a22
        elif dv is None:
            gu_k, gv_k = du * a11, du * a12
        else:
            gu_k, gv_k = du * a11 + dv * a12, du * a12 + dv * a22
        Vu[:, k] = p[k] * fu + gu_k * wr
        Vv[:, k] = p[k] * fv + gv_k * wr
    return Vu, Vv


def _covariances(st: _FitState, sigma: float, wanted: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(n, 5, 5) covariances of (u, v, a, b, angle) from image noise ``sigma`` (first order),
    for the ``wanted`` fits (NaN for the others)."""
    n = len(st.params)
    out = np.full((n, 5, 5), np.nan)
    if st.fit.size == 0 or not np.isfinite(sigma):
        return out
    Vu, Vv = _sensitivities(st, sigma)
    starts, counts = _segments(st.fit, n)
    present = st.ok & wanted & (counts > 0)
    S = _filtered_gram(st, Vu, Vv, starts, counts, present)
    good = st.ok & present
    if not np.any(good):
        return out
    Minv = np.linalg.inv(st.M[good])
    cov_theta = sigma * sigma * Minv @ S[good] @ Minv
    J = _jacobian(st.theta[good], st.scale[good])
    out[good] = J @ cov_theta @ np.swapaxes(J, 1, 2)
    return out


def _records(a: NDArray[np.float32]) -> NDArray[np.void]:
    """A contiguous float32 array of 5-vectors (last axis) as a flat array of 20-byte records:
    fancy indexing then moves one record per index (several times faster than rows)."""
    return a.reshape(-1, 5).view(np.dtype((np.void, 20))).reshape(-1)


def _filtered_gram(
    st: _FitState,
    Vu: NDArray[Any],
    Vv: NDArray[Any],
    starts: NDArray[np.intp],
    counts: NDArray[np.intp],
    present: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """(n, 5, 5) ``sum_k G_k G_k^T`` for the ``present`` fits, ``G = Vu (x) K_u + Vv (x) K_v``.

    The gradients are Scharr filters of the image (g = K (x) I, correlation), so the normal
    equations move by ``G_k = sum_i V_i K(k - i)`` per unit change of pixel k: the convolution of
    V with K, i.e. the correlation with the flipped (negated) Scharr kernels. Exact, including the
    correlation the filter puts between neighbouring gradients.

    Every fit's pixels are laid out in its own tile (its bounding box plus a one-pixel zero
    border, which the 3x3 kernels cannot cross), the tiles packed side by side on shelves of one
    canvas, so that two filter calls serve all fits at once; ``G`` is non-zero only on the band
    dilated by one pixel, where it is gathered and summed per fit.
    """
    n = len(starts)
    S = np.zeros((n, 5, 5))
    idx = np.flatnonzero(present)
    if idx.size == 0:
        return S
    # Per-fit bounding boxes (pixels are grouped by fit; reduceat over the present fits' runs).
    order = np.flatnonzero(present[st.fit])
    pu, pv = st.pu[order], st.pv[order]
    seg = np.cumsum(counts[idx]) - counts[idx]
    umin = np.minimum.reduceat(pu, seg) - 1
    vmin = np.minimum.reduceat(pv, seg) - 1
    tw = np.maximum.reduceat(pu, seg) - umin + 2
    th = np.maximum.reduceat(pv, seg) - vmin + 2
    # Shelf packing, tallest tiles first; shelves grouped into chunks of about _CHUNK_ROWS rows,
    # each filtered in the same few reused buffers (fresh canvases for all fits at once cost
    # more in page faults than in filtering).
    width = int(max(2048, int(tw.max())))
    ox = np.zeros(idx.size, dtype=np.intp)
    oy = np.zeros(idx.size, dtype=np.intp)
    chunk = np.zeros(idx.size, dtype=np.intp)
    heights: list[int] = []
    x = y = shelf = 0
    for t in np.argsort(-th, kind="stable").tolist():
        w_t = int(tw[t])
        if x + w_t > width:
            x, y, shelf = 0, y + shelf, 0
            if y >= _CHUNK_ROWS:
                heights.append(y)
                y = 0
        ox[t], oy[t], chunk[t] = x, y, len(heights)
        x += w_t
        shelf = max(shelf, int(th[t]))
    heights.append(y + shelf)
    tile = np.repeat(np.arange(idx.size), counts[idx])
    flat = (oy[tile] + (pv - vmin[tile])) * width + ox[tile] + (pu - umin[tile])
    # Pixels grouped by chunk (stable: still by tile within a chunk).
    by_chunk = np.argsort(chunk[tile].astype(np.uint16), kind="stable")
    chunk_first = np.searchsorted(chunk[tile][by_chunk], np.arange(len(heights) + 1))
    rows = max(heights)
    cu_buf = np.empty((rows, width, 5), np.float32)
    cv_buf = np.empty((rows, width, 5), np.float32)
    g_buf = np.empty((rows, width, 5), np.float32)
    g2_buf = np.empty((rows, width, 5), np.float32)
    marks_buf = np.empty((rows, width), np.float32)
    ids_buf = np.empty((rows, width), np.float32)
    kernel = np.ones((3, 3), np.uint8)
    iu, ju = _IU
    sums = np.zeros((idx.size, 15))
    vu_rec = _records(np.ascontiguousarray(Vu, dtype=np.float32))
    vv_rec = _records(np.ascontiguousarray(Vv, dtype=np.float32))
    for c, h in enumerate(heights):
        pix = by_chunk[chunk_first[c] : chunk_first[c + 1]]
        if pix.size == 0:
            continue
        f = flat[pix]
        cu, cv, G, G2 = cu_buf[:h], cv_buf[:h], g_buf[:h], g2_buf[:h]
        marks, ids2d = marks_buf[:h], ids_buf[:h]
        cu.fill(0.0)
        cv.fill(0.0)
        marks.fill(0.0)
        src = order[pix]
        _records(cu)[f] = vu_rec[src]
        _records(cv)[f] = vv_rec[src]
        cv2.filter2D(cu, -1, _FLIPPED_U, dst=G, borderType=cv2.BORDER_CONSTANT)
        cv2.filter2D(cv, -1, _FLIPPED_V, dst=G2, borderType=cv2.BORDER_CONSTANT)
        G += G2
        # Support of G: the band pixels and their 8 neighbours, all inside their own tile; tile
        # ids (1-based, exact in float32) spread there by a 3x3 dilation, as tiles never touch.
        marks.reshape(-1)[f] = tile[pix] + 1
        cv2.dilate(marks, kernel, dst=ids2d)
        ids = ids2d.reshape(-1)
        sup = np.flatnonzero(ids)
        who = ids[sup].astype(np.uint16 if idx.size < 65535 else np.intp) - 1
        # Group the support by tile (radix sort of small ints), then per-tile product sums.
        sup = sup[np.argsort(who, kind="stable")]
        seg_counts = np.bincount(who, minlength=idx.size)
        here = np.flatnonzero(seg_counts)
        Gt = np.ascontiguousarray(_records(G)[sup].view(np.float32).reshape(-1, 5).T)
        prods = np.empty((15, sup.size), np.float32)
        for k in range(15):
            np.multiply(Gt[iu[k]], Gt[ju[k]], out=prods[k])
        first = np.cumsum(seg_counts[here]) - seg_counts[here]
        # float32 sums of a few thousand positive terms: ~1e-6 relative, ample for a variance.
        sums[here] = np.add.reduceat(prods, first, axis=1).T
    Sp = np.empty((idx.size, 5, 5))
    Sp[:, iu, ju] = sums
    Sp[:, ju, iu] = sums
    S[idx] = Sp
    return S


def _jacobian(theta: NDArray[np.float64], scale: NDArray[np.float64]) -> NDArray[np.float64]:
    """(m, 5, 5) Jacobian of pixel-unit (u, v, a, b, angle) w.r.t. the dual conic parameters."""
    m = len(theta)
    h = 1e-6 * np.maximum(np.abs(theta), 1e-3)
    steps = np.zeros((m, 10, 5))
    for k in range(5):
        steps[:, 2 * k, k] = h[:, k]
        steps[:, 2 * k + 1, k] = -h[:, k]
    pert = (theta[:, None, :] + steps).reshape(-1, 5)
    ell = _ellipses_from_conics(_dual_to_conics(pert)).reshape(m, 5, 2, 5)
    diff = ell[:, :, 0, :] - ell[:, :, 1, :]  # (m, param k, output)
    # The angle wraps at 0 / pi: take the difference modulo pi.
    diff[:, :, 4] = (diff[:, :, 4] + 0.5 * np.pi) % np.pi - 0.5 * np.pi
    J = np.swapaxes(diff / (2.0 * h[:, :, None]), 1, 2)  # (m, output, param)
    J[:, :4, :] *= scale[:, None, None]
    return J
