"""3-D position, normal and position covariance of detected fiducials (paper section 4, improved).

The paper takes each fiducial's 3-D position from the ellipse of its central dot alone (its step 4,
the TRIP method). Here every fitted concentric circle of the design contributes:

1. **Undistort the boundaries, not the image.** Each fitted ellipse (in distorted pixels) is
   sampled at 16 points, the points are undistorted through the lens model and a conic is refitted:
   the ideal-camera image of that circle. Its covariance is carried through the local affine part of
   the undistortion.
2. **Closed form, both solutions.** The pose circle's cone gives the two candidate poses
   (:func:`pose_estimator.conic_pose.circle_pose`), each fitting the pose circle exactly.
3. **Ambiguity from the concentric circles.** Each candidate predicts the images of the other
   printed circles; the chi-square of the fitted ellipses against those predictions (weighted by
   the fits' covariances) gives the candidates' likelihood weights. The false candidate's
   concentric circles are inconsistent (its pole of the vanishing line differs between circles).
4. **Joint refinement over all circles.** Gauss-Newton adjusts the better candidate's centre (3-D)
   and normal (2 angles) to all circles at once. Because the model predicts whole conics, the image
   of the true centre (not the ellipse centre, under perspective) is used implicitly: no
   eccentricity bias. Depth comes from the pose circle, the largest full circle: the inner
   circles' radii are nuisance parameters and their fits carry a systematic floor
   (:data:`INNER_FLOOR_PX`), so that their edge biases (coding track nearby, toner spread)
   cannot pull z while they still fix the centre's image and the normal. Circles larger than
   the pose circle - the ``dot`` design's coding-track arcs, fitted only where its sectors are
   black - keep their printed radius and their fits' own covariance (large along what the arcs
   leave unmeasured): with 3.3 times the dot's radius they carry the depth.
5. **Honest covariance.** The position covariance is the estimator's own (sandwich) covariance
   under the fits' covariances. When the two candidates fit (almost) equally well - a design with a
   single circle, or a nearly fronto-parallel view - the result is their likelihood-weighted
   mixture, whose covariance includes the spread between them. That covariance is the scatter
   from image to image; a pose circle whose fit is known to be biased (``Ellipse.systematic_px``:
   the dual conic standing in) also gives the error that bias makes, the same in every image, as
   a systematic covariance beside it (``systematic_mm2``), which neither weighs the fits nor
   shrinks when frames are fused.
6. **Spin from the code.** The circles leave the rotation about the normal free; the image angle
   at which the code's sector 0 starts (``FiducialDetection.rotation``), back-projected onto the
   fiducial's plane, gives the printed +x axis (:mod:`pose_estimator.orientation`), so each pose
   carries its full orientation (``FiducialPose.axis``, ``frame``).

Conventions: pixels ``(u, v)`` with pixel centres at integer coordinates; camera frame OpenCV
(x right, y down, z forward), millimetres; normals point out of the printed face, towards the
camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import chain
from operator import attrgetter

import numpy as np
from numpy.typing import NDArray

from fiducial_detector.types import Ellipse, FiducialDetection

from .batched import spd_inverse
from .camera import CameraModel
from .conic_pose import (
    CircleImage,
    axes_from_params,
    circle_image_t,
    circle_params_jacobian_t,
    circle_pose_t,
    ellipse_offsets_t,
    fit_ellipse_params_t,
    image_params_t,
    map_image,
    plane_basis,
    sqrtm_diff,
)
from .errors import PoseError
from .orientation import printed_axes
from .types import FiducialPose

F64 = NDArray[np.float64]

#: Standard deviation (pixels) assumed for each ellipse parameter when a fit reports no usable
#: covariance; the pose covariance is then only nominal.
DEFAULT_SIGMA_PX = 0.05
#: Systematic floor (pixels, per ellipse parameter) added to the inner circles' fit covariances:
#: the coding track next to them and toner spread bias inner edges by several hundredths of a
#: pixel at small sizes, which a noise-only covariance does not cover. They still resolve the
#: ambiguity and refine the normal, without pulling the depth.
INNER_FLOOR_PX = 0.05
#: Boundary samples per ellipse for the lens correction. The undistorted samples of a fitted
#: ellipse lie on a conic to far below the fits' noise, so evenly spaced samples beyond the
#: five a conic needs change nothing: 12, 16, 32 and 64 give the same ideal ellipse to 1e-12 px
#: (k1 up to -0.25 over a 3008x2000 frame), 8 to 1e-10 px. 16 keeps a margin.
_UNDISTORT_SAMPLES = 16
_GN_ITERATIONS = 1
#: Rows of the ellipse columns: ``(u, v, semi_major, semi_minor, angle, radius, systematic_px)``.
_COLUMNS = 7


def estimate(
    detections: Sequence[FiducialDetection],
    camera: CameraModel,
    diameter_mm: float,
) -> list[FiducialPose]:
    """Pose of each detected fiducial.

    Parameters
    ----------
    detections : sequence of FiducialDetection
        Detections in one image of ``camera`` (ellipses in distorted pixels, ``(u, v)``, pixel
        centres at integer coordinates).
    camera : CameraModel
        Intrinsics and lens distortion of the image.
    diameter_mm : float
        Printed diameter of the outermost circle (the design's radius 1.0), millimetres.

    Returns
    -------
    list of FiducialPose
        One per detection whose pose circle gives a real pose, in the order given; degenerate
        detections (pose ellipse not an ellipse) are left out.

    Raises
    ------
    PoseError
        If ``diameter_mm`` is not a positive finite number, an item is not a detection or a
        detection has no (or malformed) ellipses.
    """
    if not np.isfinite(diameter_mm) or diameter_mm <= 0:
        raise PoseError(f"diameter_mm must be a positive finite number, got {diameter_mm!r}")
    dets = list(detections)
    # Checked per type, not per detection (an empty detection is caught while gathering).
    for kind in {type(d) for d in dets}:
        if not issubclass(kind, FiducialDetection):
            raise PoseError(f"expected FiducialDetection, got {kind.__name__}")
    if not dets:
        return []
    values, covs = detection_columns(dets)
    rotation = np.array([d.rotation for d in dets], dtype=np.float64)
    result = estimate_ellipses(values, covs, 0.5 * float(diameter_mm), camera, rotation)
    pos, nrm, cvm = result.position_mm, result.normal, result.covariance_mm2
    biased, axis = result.systematic_mm2, result.axis
    assert axis is not None  # the angles were given
    if not result.valid.all():
        keep = np.flatnonzero(result.valid)
        dets = [dets[i] for i in keep]
        pos, nrm, cvm, axis = pos[keep], nrm[keep], cvm[keep], axis[keep]
        biased = None if biased is None else biased[keep]
    sysm = None
    if biased is not None:
        # A pose without a known bias keeps None (most of them).
        sysm = [b if b.any() else None for b in biased]
    finite = np.all(np.isfinite(axis), axis=1).tolist()
    axes = [a if ok else None for a, ok in zip(axis, finite, strict=True)]
    return FiducialPose.from_rows([d.code for d in dets], pos, nrm, cvm, dets, sysm, axes)


@dataclass(frozen=True, slots=True, eq=False)
class PoseArrays:
    """Vectorised pose results for ``N`` fiducials (camera frame, mm).

    Attributes
    ----------
    position_mm : (N, 3) ndarray
    normal : (N, 3) ndarray
    covariance_mm2 : (N, 3, 3) ndarray
    valid : (N,) bool ndarray
    ambiguity : (N,) ndarray
        Likelihood weight of the rejected candidate (0 when the concentric circles resolved the
        ambiguity decisively, 0.5 when the two candidates fit equally well).
    center_px : (N, 2) ndarray
        Ideal (undistorted) image of the true circle centre.
    chi2 : (N,) ndarray
        Weighted squared residual of the chosen candidate's fit.
    systematic_mm2 : (N, 3, 3) ndarray or None
        Covariance of the position's systematic error, beside ``covariance_mm2`` (its scatter):
        the error a pose circle's known fit bias (``Ellipse.systematic_px``) makes, the same in
        every image of the scene; None where no fit has one.
    axis : (N, 3) ndarray or None
        The printed +x axis of each fiducial (``FiducialPose.axis``; NaN rows where not
        measured), when the image angles were given (:func:`estimate_ellipses`).
    """

    position_mm: F64
    normal: F64
    covariance_mm2: F64
    valid: NDArray[np.bool_]
    ambiguity: F64
    center_px: F64
    chi2: F64
    systematic_mm2: F64 | None = None
    axis: F64 | None = None


def detections_to_arrays(
    dets: Sequence[FiducialDetection], outer_radius_mm: float
) -> tuple[F64, F64, F64]:
    """Observation arrays ``(N, K, 5)``, covariances ``(N, K, 5, 5)`` and radii ``(N, K)`` (mm)
    of :func:`estimate_arrays`; missing circles (fewer ellipses than ``K``) get NaN observations.

    The arrays returned are views of memory laid out as :func:`estimate_arrays` works, ``(5, K,
    N)`` and ``(5, 5, K, N)``, which it then uses without a copy.

    Raises
    ------
    PoseError
        If a detection has no ellipses, an ellipse's centre is not a pair of numbers or a
        parameter is not a number.
    """
    return ellipse_arrays(*detection_columns(dets), outer_radius_mm)


def detection_columns(dets: Sequence[FiducialDetection]) -> tuple[F64, F64]:
    """The detections' ellipses as columns: ``(u, v, semi_major, semi_minor, angle, radius,
    systematic_px)`` ``(7, K, N)`` and covariances ``(5, 5, K, N)`` (circle ``k`` of detection
    ``n`` at ``[..., k, n]``; NaN where a detection has fewer than ``K`` ellipses).

    Raises
    ------
    PoseError
        If a detection has no ellipses, an ellipse's centre is not a pair of numbers or a
        parameter is not a number.
    """
    per_det = [d.ellipses for d in dets]
    counts = list(map(len, per_det))
    n, kc = len(per_det), max(counts)
    if min(counts) == 0:
        raise PoseError(f"detection of code {dets[counts.index(0)].code} has no ellipses")
    if min(counts) == kc:
        # Circle-major order (circle 0 of every detection, then circle 1, ...): the gathered
        # columns are already (K, N) and need no transposing copy.
        values, covs = _ellipse_columns(list(chain.from_iterable(zip(*per_det, strict=True))))
        return values.reshape(_COLUMNS, kc, n), covs.reshape(5, 5, kc, n)
    flat_values, flat_covs = _ellipse_columns(list(chain.from_iterable(per_det)))
    det_index = np.repeat(np.arange(n), counts)
    circle_index = np.concatenate([np.arange(c) for c in counts])
    values = np.full((_COLUMNS, kc, n), np.nan)
    values[:, circle_index, det_index] = flat_values
    covs = np.full((5, 5, kc, n), np.nan)
    covs[:, :, circle_index, det_index] = flat_covs.reshape(5, 5, -1)
    return values, covs


def ellipse_arrays(values: F64, covs: F64, outer_radius_mm: float) -> tuple[F64, F64, F64]:
    """:func:`estimate_arrays`' inputs from ellipse columns (see :func:`detection_columns`):
    ``(N, K, 5)`` observations, ``(N, K, 5, 5)`` covariances and ``(N, K)`` radii in mm (views
    of ``(..., K, N)`` memory); the fits' systematic errors (row 6) are
    :func:`estimate_arrays`' ``systematic_px``, ``values[6].T``."""
    obs, cov = _axes_to_params(values[:5], covs)
    return obs.transpose(2, 1, 0), cov.transpose(3, 2, 0, 1), values[5].T * outer_radius_mm


def estimate_ellipses(
    values: F64,
    covs: F64,
    outer_radius_mm: float,
    camera: CameraModel,
    rotation: F64 | None = None,
) -> PoseArrays:
    """Poses straight from ellipse columns, without detection objects: the path of a node that
    receives them as records (:func:`armourcam.records.detection_columns`).

    Parameters
    ----------
    values : (7, K, N) ndarray
        ``(u, v, semi_major, semi_minor, angle, radius, systematic_px)`` of circle ``k`` of
        fiducial ``n`` (distorted pixels; ``radius`` as a fraction of the outer radius;
        ``systematic_px`` the fit's known systematic error, ``Ellipse.systematic_px``; NaN: not
        fitted).
    covs : (5, 5, K, N) ndarray
        Covariances of ``(u, v, semi_major, semi_minor, angle)``.
    outer_radius_mm : float
        Printed radius of the design's radius 1.0.
    camera : CameraModel
    rotation : (N,) ndarray, optional
        Image angle of each fiducial's printed +x axis (``FiducialDetection.rotation``): the
        poses then carry their axes (:func:`pose_estimator.orientation.printed_axes`, measured
        at the pose ellipse's centre).

    Returns
    -------
    PoseArrays
        As :func:`estimate_arrays`; :func:`estimate` keeps the ``valid`` rows.
    """
    if not np.isfinite(outer_radius_mm) or outer_radius_mm <= 0:
        raise PoseError(f"outer radius must be a positive finite number, got {outer_radius_mm!r}")
    values = np.asarray(values, dtype=np.float64)
    covs = np.asarray(covs, dtype=np.float64)
    if values.ndim != 3 or values.shape[0] != _COLUMNS or covs.shape != (5, 5, *values.shape[1:]):
        raise PoseError(
            f"ellipse columns must be ({_COLUMNS}, K, N) and covariances (5, 5, K, N); got "
            f"{values.shape}, {covs.shape}"
        )
    result = estimate_arrays(
        *ellipse_arrays(values, covs, outer_radius_mm), camera, systematic_px=values[6].T
    )
    if rotation is None:
        return result
    angles = np.asarray(rotation, dtype=np.float64).reshape(-1)
    if angles.shape != (values.shape[2],):
        raise PoseError(f"rotation must be ({values.shape[2]},), got {angles.shape}")
    centre = values[:2, 0].T
    axis = printed_axes(camera, result.position_mm, result.normal, centre, angles)
    return replace(result, axis=axis)


def _ellipse_columns(ells: list[Ellipse]) -> tuple[F64, F64]:
    """``(u, v, semi_major, semi_minor, angle, radius, systematic_px)`` ``(7, M)`` and the
    covariances ``(25, M)`` of ``M`` ellipses, in their order (NaNs for covariances not of
    shape (5, 5)).

    One list comprehension per attribute and ``np.fromiter`` over the lists: the cheapest way
    from hundreds of small objects to arrays (a comprehension reads a slot faster than
    ``map(attrgetter)``, and ``fromiter`` converts a list of floats without the shape discovery
    ``np.array`` does).
    """
    m = len(ells)
    values = np.empty((_COLUMNS, m))
    centers = [e.center_px for e in ells]
    try:
        # Unpacking also checks that each centre is a pair.
        values[0] = np.fromiter([u for u, _ in centers], np.float64, count=m)
        values[1] = np.fromiter([v for _, v in centers], np.float64, count=m)
    except (TypeError, ValueError) as err:
        raise PoseError(f"every ellipse centre must be a (u, v) pair of numbers: {err}") from err
    try:
        values[2] = np.fromiter([e.semi_major for e in ells], np.float64, count=m)
        values[3] = np.fromiter([e.semi_minor for e in ells], np.float64, count=m)
        values[4] = np.fromiter([e.angle for e in ells], np.float64, count=m)
        values[5] = np.fromiter([e.radius for e in ells], np.float64, count=m)
        values[6] = np.fromiter([e.systematic_px for e in ells], np.float64, count=m)
    except (TypeError, ValueError) as err:
        raise PoseError(
            f"ellipse axes, angle, radius and systematic error must be numbers: {err}"
        ) from err
    covs = _gather_covariances([e.covariance for e in ells]).reshape(m, 25)
    # A 2-D transposing copy (entries first) is several times cheaper than the 4-D one it
    # spares later.
    return values, np.ascontiguousarray(covs.T)


def _gather_covariances(covs: list[NDArray[np.float64]]) -> F64:
    """``(M, 5, 5)`` float64 covariances; NaNs for those without the shape ``(5, 5)``."""
    m = len(covs)
    try:
        # Native float64 blocks are joined through the buffer protocol: one copy, without the
        # per-array conversion numpy.concatenate does. Non-arrays have no dtype, non-contiguous
        # arrays export no buffer, and any size other than 25 values each shows in the total.
        if set(map(attrgetter("dtype"), covs)) == {_F64}:
            # (ndarrays export the buffer protocol; numpy does not declare it to the checker)
            flat = np.frombuffer(b"".join(covs), dtype=np.float64)  # type: ignore[arg-type]
            if flat.size == 25 * m:
                return flat.reshape(m, 5, 5)
    except (AttributeError, TypeError, BufferError):
        pass
    try:
        # One concatenation of (5, 5) blocks; any other shape mixes fail here or in the size.
        out = np.concatenate(covs, dtype=np.float64)
        if out.shape in ((5 * m, 5), (25 * m,)):
            return out.reshape(m, 5, 5)
    except ValueError:
        pass
    return np.stack([_cov_or_nan(c) for c in covs])


_F64 = np.dtype(np.float64)


def _cov_or_nan(cov: object) -> F64:
    """A 5x5 covariance as float64, or NaNs when it has the wrong shape."""
    c = np.asarray(cov, dtype=np.float64)
    return c if c.shape == (5, 5) else np.full((5, 5), np.nan)


def _axes_to_params(values: F64, cov: F64) -> tuple[F64, F64]:
    """Ellipses ``(u, v, a, b, angle)`` ``(5, K, N)`` with covariances ``(5, 5, K, N)`` as
    ``(u, v, s11, s12, s22)`` (:func:`pose_estimator.conic_pose.params_from_axes`) with the
    covariances carried over: ``J C J^T``.

    ``J`` (:func:`pose_estimator.conic_pose.axes_to_params_jacobian`) is the identity on the
    centre, so only its 3x3 shape block ``G`` is applied, blockwise.
    """
    u, v, a, b, angle = values
    c, s = np.cos(angle), np.sin(angle)
    d = a - b
    obs = np.empty(values.shape)
    obs[0], obs[1] = u, v
    obs[2], obs[3], obs[4] = a * c * c + b * s * s, d * c * s, a * s * s + b * c * c
    G = np.empty((3, 3, *a.shape))
    G[0, 0], G[0, 1], G[0, 2] = c * c, s * s, -2.0 * c * s * d
    G[1, 0], G[1, 1], G[1, 2] = c * s, -c * s, d * (c * c - s * s)
    G[2, 0], G[2, 1], G[2, 2] = s * s, c * c, 2.0 * c * s * d
    out = np.empty(cov.shape)
    out[:2, :2] = cov[:2, :2]
    out[2:, :2] = np.einsum("ij...,jk...->ik...", G, cov[2:, :2])
    out[:2, 2:] = np.einsum("ij...,kj...->ik...", cov[:2, 2:], G)
    GC = np.einsum("ij...,jk...->ik...", G, cov[2:, 2:])
    out[2:, 2:] = np.einsum("ij...,kj...->ik...", GC, G)
    return obs, out


def estimate_arrays(
    obs: F64,
    cov: F64,
    radius_mm: F64,
    camera: CameraModel,
    *,
    iterations: int = _GN_ITERATIONS,
    free_scale: bool = True,
    inner_floor_px: float = INNER_FLOOR_PX,
    systematic_px: F64 | None = None,
) -> PoseArrays:
    """Vectorised core of :func:`estimate`.

    Parameters
    ----------
    obs : (N, K, 5) ndarray
        Fitted ellipses ``(u, v, s11, s12, s22)`` in distorted pixels; circle 0 is the pose circle.
        NaN rows mark circles that were not fitted. Circles larger than the pose circle (coding-
        track arcs) keep their printed radius and get no floor (see the module notes).
    cov : (N, K, 5, 5) ndarray
        Their covariances (NaN or non-positive-definite: :data:`DEFAULT_SIGMA_PX` is assumed).
    radius_mm : (N, K) ndarray
        Printed radius of each circle.
    camera : CameraModel
    iterations : int
        Gauss-Newton steps from the closed-form solution (the problem is nearly linear there).
    free_scale : bool
        Estimate the inner circles' radii instead of trusting their printed values: depth then
        comes from the pose circle (and any larger arcs) alone, immune to size biases of inner
        edges (see :func:`_gauss_newton`); False uses every circle's printed radius.
    inner_floor_px : float
        Systematic standard deviation added to each inner circle's parameters, pixels.
    systematic_px : (N, K) ndarray, optional
        Each fit's known systematic error, pixels (``Ellipse.systematic_px``; NaN or 0: none).
        The pose circle's gives the position's systematic covariance (``systematic_mm2``), as
        the pose moves with a size and a centre error of that sd (:func:`_systematic_covariance`);
        ``covariance_mm2``, the fits' weights and the poses stay those of the fits' scatter.

    Returns
    -------
    PoseArrays
    """
    obs = np.asarray(obs, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    radius_mm = np.asarray(radius_mm, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[2] != 5 or cov.shape != (*obs.shape, 5):
        raise PoseError(f"obs must be (N, K, 5) and cov (N, K, 5, 5); got {obs.shape}, {cov.shape}")
    if radius_mm.shape != obs.shape[:2]:
        raise PoseError(f"radius_mm must be {obs.shape[:2]}, got {radius_mm.shape}")
    pose_sys = None
    if systematic_px is not None:
        sys_px = np.asarray(systematic_px, dtype=np.float64)
        if sys_px.shape != obs.shape[:2]:
            raise PoseError(f"systematic_px must be {obs.shape[:2]}, got {sys_px.shape}")
        s0 = sys_px[:, 0]
        if np.any(s0 > 0):  # (NaN compares False)
            pose_sys = np.where(s0 > 0, s0, 0.0)
    n, kc = obs.shape[:2]
    K = camera.K
    # Internally every stack of small vectors and matrices keeps its component axes first, then
    # circles (or candidates), and the fiducials last: (5, K, N), (5, 5, K, N). Each matrix entry
    # is then one contiguous array, every elementwise operation runs over long inner loops, and
    # products of the tiny matrices are arithmetic or einsum over whole batches instead of
    # per-matrix LAPACK or matmul calls.
    obs_t = np.ascontiguousarray(obs.transpose(2, 1, 0))
    r_t = radius_mm.T
    present = np.isfinite(obs_t).all(axis=0) & np.isfinite(r_t) & (r_t > 0)
    present &= (obs_t[2] * obs_t[4] - obs_t[3] ** 2) > 0
    cov_t = _sanitise_covariance(cov.transpose(2, 3, 1, 0), present)
    if camera.has_distortion:
        obs_t, cov_t = _undistort(obs_t, cov_t, present, camera)
        present &= np.isfinite(obs_t).all(axis=0)
    everything = bool(present.all())
    safe_obs = obs_t if everything else np.where(present, obs_t, _NOMINAL_ELLIPSE)
    safe_r = r_t if everything else np.where(present, r_t, 1.0)
    if pose_sys is not None:
        # The pose circle's semi-major axis (ideal pixels), before the observations are
        # normalised.
        pose_a_px = axes_from_params(safe_obs[:, 0].T)[:, 2]
    # The ambiguity test uses the fits' own covariances (the inner circles' geometry relative to
    # the pose circle is what tells the candidates apart); the refinement adds the systematic
    # floor to the inner circles, as a scalar deflation (sigma^2 / (sigma^2 + floor^2)).
    lam = np.ones((kc, n))
    # Circles larger than the pose circle (a ``dot`` fiducial's coding-track arcs) keep their
    # printed radius and their fits' own covariance: they carry depth (see ``_gauss_newton``).
    sized = np.where(present, r_t, 0.0)
    arcs = sized > sized[:1] * (1.0 + 1e-9)
    if kc > 1 and inner_floor_px > 0:
        c = cov_t[:, :, 1:]
        var = (c[0, 0] + c[1, 1] + c[2, 2] + c[3, 3] + c[4, 4]) / 5.0
        lam[1:] = np.where(arcs[1:], 1.0, var / (var + inner_floor_px**2))
    # Work in normalised coordinates (K = I): an affine change of the observations. (The
    # covariances are inverted in place: cov_t is not used after this.)
    obs_n, W = _to_normalised(safe_obs, _information(cov_t), K)
    del cov_t
    if not everything:
        W = np.where(present, W, 0.0)
    # Closed form from the pose circle (index 0), both candidates: (3, 2, N).
    centers, normals = circle_pose_t(obs_n[:, 0], safe_r[0])
    valid = present[0] & np.isfinite(centers).all(axis=(0, 1))
    centers = np.where(valid, centers, np.array([0.0, 0.0, 1000.0])[:, None, None])
    normals = np.where(valid, normals, np.array([0.0, 0.0, -1.0])[:, None, None])
    # Both fit the pose circle exactly (to rounding), so only the other circles, which tell
    # them apart, enter their chi-square. Likelihood weights: a decisive chi2 gap gives (1, 0),
    # a single circle or a fronto-parallel view ~ 0.5.
    # The images of every circle of both candidates, (2, K, N): the inner circles' for the test,
    # and the chosen candidate's are the refinement's first prediction (not computed twice).
    image = circle_image_t(centers[:, :, None], normals[:, :, None], safe_r)
    chi2_cf = _chi2(obs_n[:, 1:], W[:, :, 1:], image) if kc > 1 else np.zeros((2, n))  # (2, N)
    dchi = chi2_cf[1] - chi2_cf[0]
    w0 = likelihood_weight(dchi)
    best = np.where(w0 >= 0.5, 0, 1)
    idx = np.arange(n)
    # Joint refinement of the better candidate over all circles.
    # Circles whose floored weight is below 1 % of their own fit's add nothing measurable to
    # the refinement (they already did their job in the ambiguity test): leave them out, per
    # fiducial (weight 0), so that a pose never depends on the other fiducials in the batch,
    # and from the arrays where that holds for every fiducial.
    small = lam < 0.01
    keep = np.array(~small.all(axis=1), dtype=bool)
    keep[0] = True
    if small.any():
        lam = np.where(small, 0.0, lam)
    chosen = best == 0
    first = map_image(image, lambda a: np.where(chosen, a[0], a[1]))  # (K, N) arrays
    if not keep.all():
        obs_n, W, lam, safe_r = obs_n[:, keep], W[:, :, keep], lam[keep], safe_r[keep]
        arcs = arcs[keep]
        first = map_image(first, lambda a: a[keep])
    c_best, normal, cov_c, chi2 = _gauss_newton(
        obs_n,
        W,
        lam,
        safe_r,
        centers[:, best, idx],
        normals[:, best, idx],
        iterations,
        free_scale,
        first_image=first,
        fixed=arcs if arcs.any() else None,
    )
    cov_best = 0.5 * (cov_c + np.swapaxes(cov_c, 0, 1))  # (3, 3, N)
    systematic = None
    if pose_sys is not None:
        focal = 0.5 * (K[0, 0] + K[1, 1])
        bias = _systematic_covariance(c_best, pose_sys, pose_a_px, focal)
        systematic = np.ascontiguousarray(bias.transpose(2, 0, 1))
    c = centers.copy()
    # The other candidate moves as the refinement moved the better one: the closed form rests
    # on the pose circle alone, and where larger circles carry the depth (a ``dot`` fiducial's
    # arcs, 3.3 times its dot) its depth error would otherwise enter the mixture as spread
    # between the candidates, which only their branch should make.
    c[:, 1 - best, idx] += c_best - centers[:, best, idx]
    c[:, best, idx] = c_best
    # The refined candidate's covariance stands for both.
    mean, mix = candidate_mixture(w0, c[:, 0], c[:, 1], cov_best)  # (3, N), (3, 3, N)
    w1 = 1.0 - w0
    p = K @ mean
    center_px = (p[:2] / p[2]).T
    ok = valid & np.isfinite(mean).all(axis=0) & np.isfinite(mix).all(axis=(0, 1))
    ok &= mean[2] > 0
    return PoseArrays(
        np.ascontiguousarray(mean.T),
        np.ascontiguousarray(normal.T),
        np.ascontiguousarray(mix.transpose(2, 0, 1)),
        ok,
        np.minimum(w0, w1),
        np.ascontiguousarray(center_px),
        chi2,
        systematic,
    )


def _systematic_covariance(center: F64, sd_px: F64, semi_major_px: F64, focal_px: float) -> F64:
    """Position covariance ``(3, 3, N)`` that a systematic error of sd ``sd_px`` in a pose
    circle's size and centre makes: a circle ``a`` pixels across at distance ``d`` is ``d delta /
    a`` nearer or farther when its image is ``delta`` larger or smaller (depth is inversely
    proportional to the image's size), and ``d delta / f`` aside when its centre is ``delta``
    off. (First order; the slant's share in the semi-minor axis is left out, as the size error
    of a biased fit is nearly the same along both axes.)"""
    d = np.sqrt(np.einsum("i...,i...->...", center, center))
    ray = center / d  # (the refined centres are finite and in front of the camera)
    along = (d * sd_px / semi_major_px) ** 2
    across = (d * sd_px / focal_px) ** 2
    outer = ray[:, None] * ray[None, :]
    eye = np.eye(3).reshape(3, 3, *([1] * (center.ndim - 1)))
    return np.asarray(along * outer + across * (eye - outer))


def likelihood_weight(dchi: F64 | float) -> F64:
    """Likelihood weight of the first of two candidates whose chi-squares differ by ``dchi``
    (second minus first)."""
    return np.asarray(1.0 / (1.0 + np.exp(np.clip(-0.5 * np.asarray(dchi), -700.0, 700.0))))


def candidate_mixture(w0: F64 | float, first: F64, second: F64, covariance: F64) -> tuple[F64, F64]:
    """The two circle-pose candidates as one estimate: their likelihood-weighted mean position
    and the mixture covariance (``covariance``, standing for both, plus their spread about the
    mean).

    Parameters
    ----------
    w0 : float or (N,) ndarray
        The first candidate's likelihood weight (:func:`likelihood_weight`).
    first, second : (3,) or (3, N) ndarray
        The candidates' positions.
    covariance : (3, 3) or (3, 3, N) ndarray

    Returns
    -------
    mean : (3,) or (3, N) ndarray
    covariance : (3, 3) or (3, 3, N) ndarray
    """
    w1 = 1.0 - w0
    mean = w0 * first + w1 * second
    d0, d1 = first - mean, second - mean
    mix = covariance + w0 * d0[:, None] * d0[None, :] + w1 * d1[:, None] * d1[None, :]
    return mean, mix


#: Stand-in ellipse ``(u, v, s11, s12, s22)`` (matrix axes first) for circles not observed.
_NOMINAL_ELLIPSE = np.array([0.0, 0.0, 1.0, 0.0, 1.0])[:, None, None]


def _to_normalised(obs: F64, W: F64, K: F64) -> tuple[F64, F64]:
    """Ellipse parameters ``(5, ...)`` and information matrices ``(5, 5, ...)`` in normalised
    coordinates ``K^-1 (u, v, 1)``. ``W`` (the caller's own) may be scaled in place."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    shifted = obs - np.array([cx, cy, 0.0, 0.0, 0.0]).reshape(5, *([1] * (obs.ndim - 1)))
    if fx == fy:
        W *= fx * fx
        return shifted / fx, W
    A = np.diag([1.0 / fx, 1.0 / fy]).reshape(2, 2, *([1] * (obs.ndim - 1)))
    Jinv = _inverse_affine_jacobian(_affine_params_jacobian(shifted, A))
    W_n = np.einsum("ji...,jk...->ik...", Jinv, np.einsum("ij...,jk...->ik...", W, Jinv))
    return _affine_params(shifted, A), W_n


def _inverse_affine_jacobian(J: F64) -> F64:
    """Inverses of Jacobians ``(5, 5, ...)`` of :func:`_affine_params`.

    The centre depends only on the centre and the shape only on the shape, so ``J`` is block
    diagonal (2x2 and 3x3 blocks, the other entries exactly zero): each block is inverted in
    closed form.
    """
    out = np.zeros_like(J)
    det2 = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    out[0, 0], out[0, 1] = J[1, 1] / det2, -J[0, 1] / det2
    out[1, 0], out[1, 1] = -J[1, 0] / det2, J[0, 0] / det2
    g = J[2:, 2:]
    cof = np.empty_like(g)
    for i in range(3):
        for j in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            cof[i, j] = g[i1, j1] * g[i2, j2] - g[i1, j2] * g[i2, j1]
    det3 = g[0, 0] * cof[0, 0] + g[0, 1] * cof[0, 1] + g[0, 2] * cof[0, 2]
    out[2:, 2:] = np.swapaxes(cof, 0, 1) / det3
    return out


def _sanitise_covariance(cov: F64, present: NDArray[np.bool_]) -> F64:
    """Replace unusable covariances (non-finite, non-positive variances) by the nominal one.

    ``cov`` is ``(5, 5, ...)`` (matrix axes first); returns a new contiguous array.
    """
    out = np.add(cov, np.swapaxes(cov, 0, 1), out=np.empty(cov.shape))
    out *= 0.5
    diag = out.reshape(25, *out.shape[2:])[::6]
    # The usual case (every covariance usable) is settled by two whole-array tests, without
    # the per-matrix masks.
    if present.all() and np.isfinite(out).all() and (diag > 0).all():
        floor = 1e-9 * np.sum(diag, axis=0)
        for i in range(5):
            out[i, i] += floor
        return out
    good = np.isfinite(out).all(axis=(0, 1)) & (diag > 0).all(axis=0) & present
    floor = 1e-9 * np.sum(diag, axis=0, where=good)
    if not good.all():
        nominal = np.eye(5).reshape(5, 5, *([1] * (out.ndim - 2))) * DEFAULT_SIGMA_PX**2
        out = np.where(good, out, nominal)
    # A tiny floor keeps the inverse well conditioned without changing honest covariances.
    for i in range(5):
        out[i, i] += floor
    return out


def _information(cov: F64) -> F64:
    """Inverse covariances ``(5, 5, ...)``; the nominal one where one is not positive definite.

    ``cov`` (the caller's own) is inverted in place when it is C-contiguous float64.
    """
    W = spd_inverse(cov, overwrite=True)
    diag = W.reshape(25, *W.shape[2:])[::6]
    if np.isfinite(W).all() and (diag > 0).all():  # the usual case, without per-matrix masks
        return W
    good = np.isfinite(W).all(axis=(0, 1)) & (diag > 0).all(axis=0)
    nominal = np.eye(5).reshape(5, 5, *([1] * (W.ndim - 2))) / DEFAULT_SIGMA_PX**2
    out: F64 = np.where(good, W, nominal)
    return out


def _undistort(
    obs: F64, cov: F64, present: NDArray[np.bool_], camera: CameraModel
) -> tuple[F64, F64]:
    """Ideal-camera ellipses ``(5, ...)`` of fitted (distorted) ones, with propagated
    covariances ``(5, 5, ...)``.

    All boundary samples of all ellipses are undistorted in one vectorised Newton call, in the
    layout ``(samples, ...)`` with the coordinates as separate arrays, and the conics refitted
    from the same layout (no per-fiducial work, no ``(N, 2)`` interleaving).
    """
    safe = np.where(present, obs, _NOMINAL_ELLIPSE)
    u, v, s11, s12, s22 = safe
    # The undistorted centre and the local affine part of the undistortion there (the lens
    # model's own Jacobian, inverted).
    mu, mv, (a00, a01, a10, a11) = camera.undistortion_jacobian(u, v)
    # The boundary samples c + S (cos t, sin t), undistorted from the affine prediction (fewer
    # Newton steps, same converged points), and a conic refitted through them.
    du, dv = ellipse_offsets_t(s11, s12, s22, _UNDISTORT_SAMPLES)  # (S, K, N)
    guess = (mu + a00 * du + a01 * dv, mv + a10 * du + a11 * dv)
    uu, vv = camera.undistort_components(u + du, v + dv, guess)
    new = fit_ellipse_params_t(uu, vv)
    A = np.empty((2, 2, *u.shape))
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = a00, a01, a10, a11
    J = _affine_params_jacobian(safe, A)
    newcov = np.einsum("ij...,kj...->ik...", np.einsum("ij...,jk...->ik...", J, cov), J)
    new = np.where(present, new, np.nan)
    return new, newcov


def _affine_params(p: F64, A: F64) -> F64:
    """Parameters ``(5, ...)`` of the ellipses ``p`` mapped by the linear maps ``A`` (2, 2, ...)."""
    c0 = A[0, 0] * p[0] + A[0, 1] * p[1]
    c1 = A[1, 0] * p[0] + A[1, 1] * p[1]
    s11, s12, s22 = _affine_shape(p[2], p[3], p[4], A)
    shape = np.broadcast_shapes(c0.shape, s11.shape)
    out = np.empty((5, *shape))
    out[0], out[1], out[2], out[3], out[4] = c0, c1, s11, s12, s22
    return out


def _affine_shape(s11: F64, s12: F64, s22: F64, A: F64) -> tuple[F64, F64, F64]:
    """Square-root shape ``(s11, s12, s22)`` of ellipses of shape ``S`` mapped by ``A``."""
    return _shape_root(*_affine_moments(s11, s12, s22, A)[1])


def _affine_moments(
    s11: F64, s12: F64, s22: F64, A: F64
) -> tuple[tuple[F64, F64, F64, F64], tuple[F64, F64, F64]]:
    """``X = A S`` (entries 11, 12, 21, 22) and ``M = X X^T`` (11, 12, 22) for the square-root
    shapes ``S = [[s11, s12], [s12, s22]]``."""
    x11 = A[0, 0] * s11 + A[0, 1] * s12
    x12 = A[0, 0] * s12 + A[0, 1] * s22
    x21 = A[1, 0] * s11 + A[1, 1] * s12
    x22 = A[1, 0] * s12 + A[1, 1] * s22
    m11 = x11 * x11 + x12 * x12
    m12 = x11 * x21 + x12 * x22
    m22 = x21 * x21 + x22 * x22
    return (x11, x12, x21, x22), (m11, m12, m22)


def _shape_root(m11: F64, m12: F64, m22: F64) -> tuple[F64, F64, F64]:
    """Symmetric square root of the 2x2 SPD matrices ``M`` (see :func:`sqrtm_diff`)."""
    root = np.sqrt(m11 * m22 - m12 * m12)
    t = np.sqrt(m11 + m22 + 2.0 * root)
    return (m11 + root) / t, m12 / t, (m22 + root) / t


def _affine_params_jacobian(p: F64, A: F64) -> F64:
    """Jacobian of :func:`_affine_params` w.r.t. ``p``, shape ``(5, 5, ...)``.

    Block diagonal: the centre maps linearly (its block is ``A`` itself) and the shape does not
    depend on the centre. The shape block is analytic: ``M = (A S)(A S)^T`` changes along
    ``dS`` by ``dX X^T + X dX^T`` with ``X = A S``, ``dX = A dS``, and the new square root
    follows through :func:`pose_estimator.conic_pose.sqrtm_diff`.
    """
    J = np.zeros((5, 5, *np.broadcast_shapes(p.shape[1:], A.shape[2:])))
    J[:2, :2] = A
    s11, s12, s22 = p[2], p[3], p[4]
    a00, a01, a10, a11 = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
    (x11, x12, x21, x22), (m11, m12, m22) = _affine_moments(s11, s12, s22, A)
    new = _shape_root(m11, m12, m22)
    zero = np.zeros_like(a00)
    # dX = A dS for dS = [[1, 0], [0, 0]], [[0, 1], [1, 0]] and [[0, 0], [0, 1]].
    for j, (d11, d12, d21, d22) in enumerate(
        ((a00, zero, a10, zero), (a01, a00, a11, a10), (zero, a01, zero, a11))
    ):
        dm11 = 2.0 * (d11 * x11 + d12 * x12)
        dm12 = d11 * x21 + d12 * x22 + x11 * d21 + x12 * d22
        dm22 = 2.0 * (d21 * x21 + d22 * x22)
        J[2:, 2 + j] = sqrtm_diff(m11, m12, m22, *new, dm11, dm12, dm22)
    return J


def _chi2(obs: F64, W: F64, image: CircleImage) -> F64:
    """Weighted squared residual over circles ``1..K-1`` of both candidate poses.

    ``obs`` ``(5, K-1, N)`` and ``W`` ``(5, 5, K-1, N)`` of those circles; ``image`` of all
    ``K`` circles of both candidates (``(2, K, N)`` arrays, :func:`circle_image_t`); returns
    ``(2, N)``.
    """
    pred = image_params_t(map_image(image, lambda a: a[:, 1:]))  # (5, 2, K-1, N)
    res = obs[:, None] - pred
    if not np.isfinite(res.sum()):  # degenerate predictions contribute nothing
        res = np.where(np.isfinite(res), res, 0.0)
    return _quadratic(res, W[:, :, None])


def _quadratic(res: F64, W: F64) -> F64:
    """Sum over circles of ``res^T W res``.

    ``res`` ``(5, ..., K, N)`` and ``W`` ``(5, 5, ..., K, N)`` give ``(..., N)``.
    """
    out: F64 = np.einsum("i...,ij...,j...->...", res, W, res).sum(axis=-2)
    return out


def _gauss_newton(
    obs: F64,
    W: F64,
    lam: F64,
    radius: F64,
    center: F64,
    normal: F64,
    iterations: int,
    free_scale: bool = True,
    first_image: CircleImage | None = None,
    fixed: NDArray[np.bool_] | None = None,
) -> tuple[F64, F64, F64, F64]:
    """Refine circle centres and normals (``(3, N)``) against all circles of each fiducial.

    ``obs`` ``(5, K, N)`` and ``W`` ``(5, 5, K, N)`` (inverse covariances of the fits) are in
    normalised coordinates, ``radius`` ``(K, N)``. Circle ``k`` is weighted by ``lam[k] * W``
    (``lam < 1`` deflates circles with a systematic floor); the covariance returned is then the
    sandwich ``A^-1 B A^-1`` with ``A = sum lam J^T W J`` and ``B = sum lam^2 J^T W J``, which is
    the estimator's actual covariance under the fits' own covariances.

    With ``free_scale`` the radii of circles ``1..K-1`` are nuisance parameters (their scale
    relative to the printed value is estimated): they still fix the centre's image and the normal,
    but depth comes from the pose circle alone, so a size bias of the inner edges (toner spread,
    blur of a nearby track) cannot leak into z. ``fixed`` ``(K, N)`` marks further circles whose
    printed radius is kept (coding-track arcs larger than the pose circle). ``iterations >= 1``.

    Each scale belongs to one circle only, so it is profiled out in closed form (a Schur
    complement): circle ``k``'s weight becomes ``P = W - W d d^T W / (d^T W d)`` with ``d`` its
    scale column, which leaves a 5-parameter problem in centre and normal whose step, inverse
    (the position block of the full inverse) and sandwich covariance are exactly those of the
    full problem with the scales (``P W^-1 P = P``), at the cost of 5x5 instead of
    ``(4 + K)``-square systems.

    ``first_image`` is the circles' image at the start (:func:`circle_image_t` of ``center``,
    ``normal`` and ``radius``, ``(K, N)`` arrays) when the caller has it.

    Returns centres ``(3, N)``, normals ``(3, N)``, the covariances of the centres ``(3, 3, N)``
    and the final weighted chi-square ``(N,)``.
    """
    c = center.copy()
    n = normal.copy()
    rad = radius.copy()
    kc = radius.shape[0]
    extra = free_scale and kc > 1
    cov = np.zeros((3, 3, *c.shape[1:]))
    chi2 = np.zeros(c.shape[1:])
    # Where every weight is 0 or 1, B = A and the covariance is A^-1 itself (the sandwich
    # product would only add rounding, amplified by A's condition), fiducial by fiducial.
    plain = ((lam == 0.0) | (lam == 1.0)).all(axis=0)
    all_plain = bool(plain.all())
    image = first_image
    for _ in range(iterations):
        e1, e2 = (np.stack(e) for e in plane_basis((n[0], n[1], n[2])))
        # Predicted ellipses and their analytic Jacobian (exact to rounding; the forward
        # differences used before were good to ~1e-3 in the covariance at worst).
        base, jac = circle_params_jacobian_t(c, n, rad, e1, e2, scale=extra, image=image)
        image = None  # later iterations start from new centres, normals and radii
        J = jac[:, :5]  # centre and normal columns
        res = obs - base
        # Each circle's own scale column (none for the pose circle, whose radius is known).
        ds = None
        if extra:
            ds = jac[:, 5]  # (5, K, N)
            ds[:, 0] = 0.0
            if fixed is not None:
                ds[:, fixed] = 0.0
        check = res.sum() + jac.sum()  # (one pass over the contiguous whole, ds included)
        if not np.isfinite(check):  # degenerate predictions contribute nothing
            J = np.where(np.isfinite(J), J, 0.0)
            res = np.where(np.isfinite(res), res, 0.0)
            ds = None if ds is None else np.where(np.isfinite(ds), ds, 0.0)
        if ds is not None:
            Wd = np.einsum("ij...,j...->i...", W, ds)  # (5, K, N)
            alpha = np.einsum("i...,i...->...", ds, Wd)  # (K, N)
            with np.errstate(divide="ignore"):
                inv_alpha = np.where(alpha > 0, 1.0 / alpha, 0.0)
            # P and lam P in one (5, 5, K, N) buffer, in place: for 400 fiducials each such
            # array is 240 KB, whose allocation and fresh pages cost as much as the arithmetic.
            P = np.multiply(Wd[:, None], (Wd * inv_alpha)[None])
            np.subtract(W, P, out=P)
            lam_p = np.multiply(P, lam, out=P)
        else:
            lam_p = W * lam
        PJ = np.einsum("ijkn,jqkn->iqkn", lam_p, J)  # lam_k P J
        info = np.einsum("ipkn,iqkn->pqn", J, PJ)  # (5, 5, N), sum over circles
        Pr = np.einsum("ijkn,jkn->ikn", lam_p, res)  # lam_k P res
        grad = np.einsum("ipkn,ikn->pn", J, Pr)  # (5, N)
        chi2_lin = np.einsum("ikn,ikn->n", res, Pr)
        # A tiny damping only guards against singular steps (e.g. a missing inner circle).
        damp = 1e-12 * info.trace() + 1e-300
        for i in range(5):
            info[i, i] += damp
        inv_info = spd_inverse(info, overwrite=True)
        delta = np.einsum("pq...,q...->p...", inv_info, grad)
        if all_plain:
            cov = inv_info[:3, :3]
        else:
            # Sandwich covariance of the position block only (what is reported).
            B = np.einsum("ipkn,iqkn,kn->pqn", J, PJ, lam)  # sum lam_k^2 J^T P J
            cov = np.einsum(
                "ip...,pj...->ij...",
                inv_info[:3],
                np.einsum("pq...,qj...->pj...", B, inv_info[:, :3]),
            )
            if plain.any():
                cov = np.where(plain, inv_info[:3, :3], cov)
        if not np.isfinite(delta.sum()):
            delta = np.where(np.isfinite(delta), delta, 0.0)
        chi2 = np.maximum(chi2_lin - (grad * delta).sum(axis=0), 0.0)
        if ds is not None:
            # The profiled scales at the new centre and normal: d^T W (r - J delta) / (d^T W d).
            r_new = res - np.einsum("ipkn,pn->ikn", J, delta)
            scale = np.einsum("ikn,ikn->kn", Wd, r_new) * inv_alpha
            rad[1:] *= 1.0 + scale[1:]
        c = c + delta[:3]
        n = n + delta[3] * e1 + delta[4] * e2
        n /= np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    # The covariance of the last linearisation serves the final point, and its chi-square is the
    # linearised one (res^T W res - grad^T delta): the step is far below the scale on which the
    # Jacobian changes.
    return c, n, cov, chi2
