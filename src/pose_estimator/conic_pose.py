"""Closed-form pose of a circle of known radius from its image conic, and conic utilities.

All functions are vectorised over a leading batch axis. Conventions: pixels ``(u, v)`` = (x, y) with
pixel centres at integer coordinates; *normalised* image coordinates are ``(x/z, y/z)`` of camera-
frame points (OpenCV frame: x right, y down, z forward, millimetres).

An ellipse is carried internally as ``(u, v, s11, s12, s22)``: its centre and the symmetric square
root ``S`` of its shape matrix (the ellipse is ``{c + S w : |w| = 1}``). Unlike
``(u, v, a, b, angle)`` this is smooth through the circle (``a = b``), so covariances stay finite
for fronto-parallel targets, and every component is in pixels.

The circle pose (paper section 4, "3D coordinates ... directly from the ellipse parameters") is
the eigen-decomposition method for the cone of a circle (Safaee-Rad et al. 1992; Kanatani,
*Geometric Computation for Machine Vision*, 1993): with the cone matrix ``Q = K^T C K`` scaled to
eigenvalues ``l1 >= l2 > 0 > l3`` and eigenvectors ``e1, e2, e3``, ``Q - l2 I`` factors into two
planes, so the planes ``sqrt(l1 - l2) e1.x +- sqrt(l2 - l3) e3.x = k`` cut the cone in circles; the
known radius fixes ``k``. The two signs are the two-fold ambiguity of a single circle.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .batched import spd_inverse

F64 = NDArray[np.float64]


def conic_from_params(params: ArrayLike) -> F64:
    """Conic matrices of ellipses given as ``(u, v, s11, s12, s22)``.

    Parameters
    ----------
    params : (..., 5) array_like
        Centre ``(u, v)`` and square-root shape matrix entries.

    Returns
    -------
    (..., 3, 3) ndarray
        Symmetric conics with ``[u v 1] C [u v 1]^T = 0`` on the ellipse and ``C[2, 2] < 0``
        inside-negative (the centre gives ``-1``).
    """
    p = np.asarray(params, dtype=np.float64)
    return _symmetric(*conic_entries(*np.moveaxis(p, -1, 0)))


def _symmetric(q11: F64, q12: F64, q22: F64, q13: F64, q23: F64, q33: F64) -> F64:
    """``(..., 3, 3)`` symmetric matrices from their six distinct entries."""
    out = np.empty((*np.shape(q11), 3, 3))
    out[..., 0, 0] = q11
    out[..., 0, 1] = out[..., 1, 0] = q12
    out[..., 1, 1] = q22
    out[..., 0, 2] = out[..., 2, 0] = q13
    out[..., 1, 2] = out[..., 2, 1] = q23
    out[..., 2, 2] = q33
    return out


def conic_entries(
    u: F64, v: F64, s11: F64, s12: F64, s22: F64
) -> tuple[F64, F64, F64, F64, F64, F64]:
    """Entries ``(c11, c12, c22, c13, c23, c33)`` of the conics of :func:`conic_from_params`.

    Elementwise over arrays of any (equal or broadcastable) shape, for callers that keep the
    parameters as separate components.
    """
    det = s11 * s22 - s12 * s12
    # Q = S^-2 = (S^-1)^2 with S^-1 = adj(S) / det.
    i11, i12, i22 = s22 / det, -s12 / det, s11 / det
    q11 = i11 * i11 + i12 * i12
    q12 = i11 * i12 + i12 * i22
    q22 = i12 * i12 + i22 * i22
    q13 = -(q11 * u + q12 * v)
    q23 = -(q12 * u + q22 * v)
    q33 = q11 * u * u + 2.0 * q12 * u * v + q22 * v * v - 1.0
    return q11, q12, q22, q13, q23, q33


def params_from_conic(conic: ArrayLike) -> F64:
    """``(u, v, s11, s12, s22)`` of ellipse conics (any scale or sign).

    Parameters
    ----------
    conic : (..., 3, 3) array_like
        Symmetric conic matrices of real ellipses.

    Returns
    -------
    (..., 5) ndarray
        NaN rows where a conic is not a real ellipse.
    """
    C = np.asarray(conic, dtype=np.float64)
    return params_from_entries(
        C[..., 0, 0], C[..., 0, 1], C[..., 1, 1], C[..., 0, 2], C[..., 1, 2], C[..., 2, 2]
    )


def params_from_entries(a: F64, b: F64, c: F64, d: F64, e: F64, f: F64) -> F64:
    """``(u, v, s11, s12, s22)`` of the conics ``[[a, b, d], [b, c, e], [d, e, f]]`` (elementwise).

    Returns NaN rows where a conic is not a real ellipse.
    """
    comps, bad = _ellipse_components(a, b, c, d, e, f)
    out = np.stack(comps, axis=-1)
    out[bad] = np.nan
    return out


def params_from_entries_t(a: F64, b: F64, c: F64, d: F64, e: F64, f: F64) -> F64:
    """:func:`params_from_entries` with the parameter axis first: ``(5, ...)``."""
    return _stacked_first(*_ellipse_components(a, b, c, d, e, f))


def _stacked_first(comps: tuple[F64, ...], bad: NDArray[np.bool_]) -> F64:
    """Components stacked on a new first axis, NaN where ``bad``."""
    out = np.empty((len(comps), *np.shape(comps[0])))
    for k, comp in enumerate(comps):
        out[k] = comp
    if bad.any():
        out[:, bad] = np.nan
    return out


def _ellipse_components(
    a: F64, b: F64, c: F64, d: F64, e: F64, f: F64
) -> tuple[tuple[F64, F64, F64, F64, F64], NDArray[np.bool_]]:
    """The five ellipse parameters of conic entries, and where the conic is no real ellipse."""
    det2 = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (b * e - c * d) / det2
        v = (b * d - a * e) / det2
        # Value of the conic at the centre; the ellipse is (x-c)^T Q (x-c) = -g.
        k = -(d * u + e * v + f) / det2
        # M = S^2 = k Q^-1 = k adj(Q) / det2.
        m11, m12, m22 = k * c, -k * b, k * a
        detm = m11 * m22 - m12 * m12
        root = np.sqrt(detm)
        t = np.sqrt(m11 + m22 + 2.0 * root)
        comps = (u, v, (m11 + root) / t, m12 / t, (m22 + root) / t)
    # Every component is finite iff u, v and t are (t > 0 where the others hold).
    finite = np.isfinite(u + v + t)
    bad = ~((det2 > 0) & (m11 > 0) & (detm > 0) & finite)
    return comps, bad


def circle_params(center: ArrayLike, normal: ArrayLike, radius: ArrayLike) -> F64:
    """Ellipse parameters ``(..., 5)`` of circles imaged by a camera with ``K = I``.

    Parameters
    ----------
    center, normal : (..., 3) array_like
        Circle centres and unit plane normals (camera frame).
    radius : (...) array_like
        Circle radii (same unit as ``center``).

    Returns
    -------
    (..., 5) ndarray
        ``(u, v, s11, s12, s22)`` in normalised image coordinates; NaN rows where the image is
        no real ellipse (the circle reaches the camera's plane ``z = 0``).

    Notes
    -----
    The circle is the conic ``diag(1, 1, -r^2)`` of its plane, mapped by ``H = [e1 e2 c]``
    (``e1, e2`` an orthonormal basis of the plane); its image's *dual* conic is
    ``H diag(r^2, r^2, -1) H^T = r^2 (I - n n^T) - c c^T``: basis-free and linear in ``r^2``.
    The dual conic of the ellipse ``{m + S w : |w| = 1}`` is ``[[S^2 - m m^T, -m], [-m^T, -1]]``
    up to scale, so with ``q = c_z^2 - r^2 (1 - n_z^2)`` the centre is
    ``m = (c_xy c_z + r^2 n_xy n_z) / q`` and
    ``S^2 = (r^2 (I - n_xy n_xy^T) - c_xy c_xy^T) / q + m m^T``, whose square root is closed
    form. No cone is inverted, so no digits are lost to the cone's condition (``(z / r)^2``).
    """
    c = np.moveaxis(np.asarray(center, dtype=np.float64), -1, 0)
    n = np.moveaxis(np.asarray(normal, dtype=np.float64), -1, 0)
    r = np.asarray(radius, dtype=np.float64)
    return np.moveaxis(circle_params_t(c, n, r), 0, -1)


#: Image ellipses of circles as :func:`circle_image_t` gives them: the components ``(u, v, s11,
#: s12, s22)``, the intermediates ``(1 / q, m11, m12, m22)`` (``M = S^2``) and where the image is
#: no real ellipse.
CircleImage = tuple[tuple[F64, F64, F64, F64, F64], tuple[F64, F64, F64, F64], NDArray[np.bool_]]


def circle_params_t(center: F64, normal: F64, radius: F64) -> F64:
    """:func:`circle_params` with the component axes first.

    ``center``, ``normal`` ``(3, ...)`` and ``radius`` ``(...)`` give ``(5, ...)``.
    """
    return image_params_t(circle_image_t(center, normal, radius))


def image_params_t(image: CircleImage) -> F64:
    """The parameters ``(5, ...)`` of circle images (:func:`circle_image_t`), NaN where the
    image is no real ellipse: :func:`circle_params_t` of the same circles."""
    comps, _, bad = image
    return _stacked_first(comps, bad)


def map_image(image: CircleImage, part: Callable[[NDArray[Any]], NDArray[Any]]) -> CircleImage:
    """``part`` (an indexing or a selection, the same for all) of each array of ``image``."""
    (u, v, s11, s12, s22), (inv_q, m11, m12, m22), bad = image
    return (
        (part(u), part(v), part(s11), part(s12), part(s22)),
        (part(inv_q), part(m11), part(m12), part(m22)),
        part(bad),
    )


def circle_image_t(center: F64, normal: F64, radius: F64) -> CircleImage:
    """Image ellipses of circles, components first (``center``, ``normal`` ``(3, ...)``,
    ``radius`` ``(...)``), with the intermediates :func:`circle_params_jacobian_t` reuses:
    for callers that need both the predictions and, later, the Jacobian of some of them."""
    return _circle_image(center, normal, radius * radius)


def _circle_image(c: F64, n: F64, r2: F64) -> CircleImage:
    """Image ellipses of circles (see :func:`circle_params`), elementwise over ``r2 = r^2``
    (see :data:`CircleImage`)."""
    cx, cy, cz = c[0], c[1], c[2]
    nx, ny, nz = n[0], n[1], n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        rz = r2 * nz
        inv_q = 1.0 / (cz * cz - r2 * (1.0 - nz * nz))
        u = (cx * cz + rz * nx) * inv_q
        v = (cy * cz + rz * ny) * inv_q
        m11 = (r2 * (1.0 - nx * nx) - cx * cx) * inv_q + u * u
        m12 = u * v - (r2 * (nx * ny) + cx * cy) * inv_q
        m22 = (r2 * (1.0 - ny * ny) - cy * cy) * inv_q + v * v
        detm = m11 * m22 - m12 * m12
        root = np.sqrt(detm)
        inv_t = 1.0 / np.sqrt(m11 + m22 + 2.0 * root)
        comps = (u, v, (m11 + root) * inv_t, m12 * inv_t, (m22 + root) * inv_t)
        bad = ~((inv_q > 0) & (m11 > 0) & (detm > 0) & np.isfinite(u + v + inv_t))
    return comps, (inv_q, m11, m12, m22), bad


def circle_params_jacobian_t(
    center: F64,
    normal: F64,
    radius: F64,
    e1: F64,
    e2: F64,
    *,
    scale: bool = False,
    image: CircleImage | None = None,
) -> tuple[F64, F64]:
    """:func:`circle_params_t` and its analytic Jacobian, components first.

    Parameters
    ----------
    center, normal : (3, N) ndarray
        Circle centres and unit normals (camera frame), one per fiducial.
    radius : (K, N) ndarray
        Radii of the fiducial's ``K`` concentric circles.
    e1, e2 : (3, N) ndarray
        Unit vectors orthogonal to ``normal`` (and to each other): the normal's two tilt
        directions.
    scale : bool
        Add a sixth column, the derivative with respect to ``log r`` of each circle.
    image : CircleImage, optional
        :func:`circle_image_t` of the same circles (``(K, N)`` arrays), when the caller has it:
        it is not computed again.

    Returns
    -------
    params : (5, K, N) ndarray
        ``(u, v, s11, s12, s22)`` of each circle's image, normalised coordinates; NaN where
        the image is no real ellipse.
    jacobian : (5, M, K, N) ndarray
        Derivatives with respect to the centre's ``x, y, z`` and to the rotation of the normal
        towards ``e1`` and ``e2`` (``d n = e1 d a``), then ``log r`` if ``scale`` (``M`` = 5 or
        6); NaN where ``params`` is.

    Notes
    -----
    Forward-mode differentiation of :func:`circle_params`. With ``a = c_xy c_z + r^2 n_xy n_z``,
    ``q = c_z^2 - r^2 (1 - n_z^2)`` and ``B = r^2 (I - n_xy n_xy^T) - c_xy c_xy^T`` the centre is
    ``m = a / q`` and ``M = S^2 = B / q + m m^T``, so along any direction
    ``dm = (da - m dq) / q`` and ``dM = (dB - dq (M - m m^T)) / q + dm m^T + m dm^T``; ``dS``
    follows from the closed-form square root (:func:`sqrtm_diff`). Per direction:

    - centre ``x`` (``y`` alike): ``da = (c_z, 0)``, ``dq = 0``, ``dB = -(e_x c^T + c e_x^T)``;
    - centre ``z``: ``da = c_xy``, ``dq = 2 c_z``, ``dB = 0``;
    - tilt ``dn = e``: ``da = r^2 (e_xy n_z + n_xy e_z)``, ``dq = 2 r^2 n_z e_z``,
      ``dB = -r^2 (e n^T + n e^T)``;
    - ``log r``: ``da = 2 r^2 n_xy n_z``, ``dq = -2 r^2 (1 - n_z^2)``,
      ``dB = 2 r^2 (I - n n^T)``.
    """
    c, n = center, normal
    r2 = radius * radius
    if image is None:
        image = _circle_image(c, n, r2)
    (u, v, s11, s12, s22), (inv_q, m11, m12, m22), bad = image
    cx, cy, cz = c[0], c[1], c[2]
    nx, ny, nz = n[0], n[1], n[2]
    m = 6 if scale else 5
    shape = (m, *r2.shape)
    # Changes of a (2 components), q and B (3 entries) along each direction, in one buffer and
    # written in place (every allocation and copy of these arrays is a numpy call of its own).
    dax, day, dq, db11, db12, db22 = np.zeros((6, *shape))
    dax[0], db11[0], db12[0] = cz, -2.0 * cx, -cy
    day[1], db12[1], db22[1] = cz, -cx, -2.0 * cy
    dax[2], day[2], dq[2] = cx, cy, 2.0 * cz
    # Both tilt directions at once: (2, 1, N) components broadcast against r2 (K, N).
    ex, ey, ez = np.stack((e1, e2), axis=1)[:, :, None]
    np.multiply(r2, ex * nz + nx * ez, out=dax[3:5])
    np.multiply(r2, ey * nz + ny * ez, out=day[3:5])
    np.multiply(r2, 2.0 * nz * ez, out=dq[3:5])
    np.multiply(r2, -2.0 * ex * nx, out=db11[3:5])
    np.multiply(r2, -(ex * ny + nx * ey), out=db12[3:5])
    np.multiply(r2, -2.0 * ey * ny, out=db22[3:5])
    if scale:
        r2x2 = 2.0 * r2
        np.multiply(r2x2, nx * nz, out=dax[5])
        np.multiply(r2x2, ny * nz, out=day[5])
        np.multiply(r2x2, nz * nz - 1.0, out=dq[5])
        np.multiply(r2x2, 1.0 - nx * nx, out=db11[5])
        np.multiply(r2x2, 1.0 - ny * ny, out=db22[5])
        np.multiply(r2x2, -(nx * ny), out=db12[5])
    jac = np.empty((5, *shape))
    with np.errstate(divide="ignore", invalid="ignore"):
        du = np.multiply(dax - u * dq, inv_q, out=jac[0])
        dv = np.multiply(day - v * dq, inv_q, out=jac[1])
        # B / q = M - m m^T. (2 u is exact, so du (2 u) = 2 du u with one full-size product.)
        dm11 = (db11 - dq * (m11 - u * u)) * inv_q + du * (2.0 * u)
        dm12 = (db12 - dq * (m12 - u * v)) * inv_q + du * v + u * dv
        dm22 = (db22 - dq * (m22 - v * v)) * inv_q + dv * (2.0 * v)
        # Straight into the Jacobian, without a (3, m, K, N) temporary and its copy.
        sqrtm_diff(m11, m12, m22, s11, s12, s22, dm11, dm12, dm22, out=jac[2:])
    params = np.empty((5, *r2.shape))
    params[0], params[1], params[2], params[3], params[4] = u, v, s11, s12, s22
    if bad.any():
        params[:, bad] = np.nan
        jac[:, :, bad] = np.nan
    return params, jac


def sqrtm_diff(
    m11: F64,
    m12: F64,
    m22: F64,
    s11: F64,
    s12: F64,
    s22: F64,
    dm11: F64,
    dm12: F64,
    dm22: F64,
    *,
    out: F64 | None = None,
) -> F64:
    """Change ``(3, ...)`` ``(ds11, ds12, ds22)`` of the symmetric square roots ``S`` of 2x2
    SPD matrices ``M`` along ``dM`` (entries elementwise), written to ``out`` if given.

    ``S = (M + sqrt(det M) I) / t`` with ``t = sqrt(tr M + 2 sqrt(det M))`` (``t = tr S``,
    ``sqrt(det M) = det S``), differentiated as written.
    """
    root = s11 * s22 - s12 * s12
    inv_t = 1.0 / (s11 + s22)
    droot = (dm11 * m22 + m11 * dm22 - 2.0 * m12 * dm12) * (0.5 / root)
    dt = (dm11 + dm22 + 2.0 * droot) * (0.5 * inv_t)
    ds11 = dm11 + droot - s11 * dt
    if out is None:
        out = np.empty((3, *np.shape(ds11)))
    np.multiply(ds11, inv_t, out=out[0])
    np.multiply(dm12 - s12 * dt, inv_t, out=out[1])
    np.multiply(dm22 + droot - s22 * dt, inv_t, out=out[2])
    return out


def params_from_axes(
    u: ArrayLike, v: ArrayLike, a: ArrayLike, b: ArrayLike, angle: ArrayLike
) -> F64:
    """``(u, v, s11, s12, s22)`` from centre, semi-axes and major-axis angle (radians)."""
    ua, va, aa, ba, th = (np.asarray(x, dtype=np.float64) for x in (u, v, a, b, angle))
    c, s = np.cos(th), np.sin(th)
    return np.stack(
        [ua, va, aa * c * c + ba * s * s, (aa - ba) * c * s, aa * s * s + ba * c * c], axis=-1
    )


def axes_from_params(params: ArrayLike) -> F64:
    """``(u, v, a, b, angle)`` (``a >= b``, angle in ``[0, pi)``) from ``(u, v, s11, s12, s22)``."""
    p = np.asarray(params, dtype=np.float64)
    s11, s12, s22 = p[..., 2], p[..., 3], p[..., 4]
    mean = 0.5 * (s11 + s22)
    half = np.hypot(0.5 * (s11 - s22), s12)
    angle = np.mod(0.5 * np.arctan2(2.0 * s12, s11 - s22), np.pi)
    return np.stack([p[..., 0], p[..., 1], mean + half, mean - half, angle], axis=-1)


def axes_to_params_jacobian(a: ArrayLike, b: ArrayLike, angle: ArrayLike) -> F64:
    """Jacobian ``d(u, v, s11, s12, s22) / d(u, v, a, b, angle)``, shape ``(..., 5, 5)``."""
    aa, ba, th = (np.asarray(x, dtype=np.float64) for x in (a, b, angle))
    c, s = np.cos(th), np.sin(th)
    d = aa - ba
    J = np.zeros((*aa.shape, 5, 5))
    J[..., 0, 0] = J[..., 1, 1] = 1.0
    J[..., 2, 2], J[..., 2, 3], J[..., 2, 4] = c * c, s * s, -2.0 * c * s * d
    J[..., 3, 2], J[..., 3, 3], J[..., 3, 4] = c * s, -c * s, d * (c * c - s * s)
    J[..., 4, 2], J[..., 4, 3], J[..., 4, 4] = s * s, c * c, 2.0 * c * s * d
    return J


def circle_pose(cone: ArrayLike, radius_mm: ArrayLike) -> tuple[F64, F64]:
    """Both poses of a circle of known radius from its cone (closed form).

    Parameters
    ----------
    cone : (..., 3, 3) array_like
        Conic of the circle's image in *normalised* coordinates, ``K^T C K`` (any sign, any
        scale with entries within ~1e+-100).
    radius_mm : (...) array_like
        Radius of the printed circle.

    Returns
    -------
    centers : (..., 2, 3) ndarray
        The two candidate circle centres (camera frame, mm, ``z > 0``).
    normals : (..., 2, 3) ndarray
        Matching unit plane normals, oriented towards the camera (``n . center < 0``).

    Notes
    -----
    With eigenvalues ``l1 >= l2 > 0 > l3`` (sign chosen so two are positive), the planes are
    ``(sqrt(l1-l2) e1 +- sqrt(l2-l3) e3) . x = k``; on such a plane the cone equation reduces to a
    sphere through the origin, whose section has radius ``|k| sqrt(-l1 l3) / (l2 s)`` with
    ``s = sqrt(l1 - l3)``, which gives ``k`` from the known radius. Degenerate cones give NaN.
    The eigen-decomposition is closed form (:func:`_circle_pose_core`).
    """
    Q = np.asarray(cone, dtype=np.float64)
    Q = 0.5 * (Q + np.swapaxes(Q, -1, -2))
    r = np.asarray(radius_mm, dtype=np.float64)
    q = (Q[..., 0, 0], Q[..., 0, 1], Q[..., 1, 1], Q[..., 0, 2], Q[..., 1, 2], Q[..., 2, 2])
    # Sign: two positive eigenvalues (negative determinant). -adj(Q) = |det Q| Q^-1 stands in
    # for the inverse (no division by a determinant that may be all rounding).
    adj = _adjugate_columns(q[0], q[2], q[5], q[1], q[3], q[4])
    det = q[0] * adj[0][0] + q[1] * adj[0][1] + q[3] * adj[0][2]
    f = np.where(det > 0, -1.0, 1.0)
    # adj(f Q) = f^2 adj(Q) = adj(Q).
    inv = (-adj[0][0], -adj[0][1], -adj[1][1], -adj[0][2], -adj[1][2], -adj[2][2])
    qf = (q[0] * f, q[1] * f, q[2] * f, q[3] * f, q[4] * f, q[5] * f)
    centers, normals = _circle_pose_core(qf, inv, r, exact_inverse=False)
    return np.moveaxis(centers, (0, 1), (-1, -2)), np.moveaxis(normals, (0, 1), (-1, -2))


def circle_pose_t(params: F64, radius_mm: F64) -> tuple[F64, F64]:
    """:func:`circle_pose` from the circle's image ellipse, components first.

    Parameters
    ----------
    params : (5, ...) ndarray
        Ellipses ``(u, v, s11, s12, s22)`` in *normalised* coordinates, parameters first.
    radius_mm : (...) ndarray

    Returns
    -------
    centers, normals : (3, 2, ...) ndarray
        Components first, then the two solutions.

    Notes
    -----
    The cone of :func:`conic_from_params` is ``Q = [[A, -A m], [-m^T A, m^T A m - 1]]`` with
    ``A = S^-2``; its inverse is exactly ``[[S^2 - m m^T, -m], [-m^T, -1]]``, free of the
    rounding an inversion would add, and used for the lone eigenvector (see
    :func:`_circle_pose_core`).
    """
    u, v, s11, s12, s22 = params[0], params[1], params[2], params[3], params[4]
    inv = (
        s11 * s11 + s12 * s12 - u * u,
        s12 * (s11 + s22) - u * v,
        s12 * s12 + s22 * s22 - v * v,
        -u,
        -v,
        np.full_like(u, -1.0),
    )
    return _circle_pose_core(conic_entries(u, v, s11, s12, s22), inv, radius_mm, exact_inverse=True)


def _circle_pose_core(
    q: tuple[F64, F64, F64, F64, F64, F64],
    inv: tuple[F64, F64, F64, F64, F64, F64],
    radius_mm: F64,
    *,
    exact_inverse: bool,
) -> tuple[F64, F64]:
    """Both circle poses from a cone ``q`` and its inverse ``inv``, entries
    ``(11, 12, 22, 13, 23, 33)``, signed so that two eigenvalues are positive.

    ``inv`` may be any positive multiple of the inverse when ``exact_inverse`` is False; ``l3`` is
    then the Rayleigh quotient of ``e3`` instead of the reciprocal of the inverse's eigenvalue.

    Closed-form eigen-decomposition, far cheaper than a batched LAPACK call on 3x3 matrices. The
    lone-sign eigenvalue ``l3`` of the cone of a small image is the smallest in magnitude, so
    ``1 / l3`` is the dominant, isolated eigenvalue of the inverse: the trigonometric solution of
    its characteristic cubic (Smith 1961) gives it to rounding, and its eigenvector ``e3`` is the
    largest column of ``adj(Q^-1 - I / l3)``. Then ``l1``, ``l2`` and ``e1`` come from the 2x2
    restriction of ``Q`` to the plane orthogonal to ``e3``, which gives ``l1 - l2`` without
    cancellation and a stable ``e1`` even when ``l1 ~ l2`` (fronto-parallel circles). Against
    ground truth this is at least as accurate as ``numpy.linalg.eigh`` of ``Q``, also for far,
    89 deg circles whose ``l2`` and ``l3`` are tiny against ``l1``.
    """
    r = np.asarray(radius_mm, dtype=np.float64)
    a11, a12, a22, a13, a23, a33 = q
    b11, b12, b22, b13, b23, b33 = inv
    with np.errstate(invalid="ignore", divide="ignore"):
        # Smallest (most negative) eigenvalue mu of the inverse, trigonometric form.
        m = (b11 + b22 + b33) / 3.0
        c11, c22, c33 = b11 - m, b22 - m, b33 - m
        p = np.sqrt(
            (c11 * c11 + c22 * c22 + c33 * c33 + 2.0 * (b12 * b12 + b13 * b13 + b23 * b23)) / 6.0
        )
        detc = c11 * (c22 * c33 - b23 * b23) - b12 * (b12 * c33 - b23 * b13)
        detc += b13 * (b12 * b23 - c22 * b13)
        phi = np.arccos(np.minimum(np.maximum(0.5 * detc / (p * p * p), -1.0), 1.0)) / 3.0
        mu = m + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
        # e3: the largest column of adj(B - mu I).
        x, y, z = _adjugate_columns(b11 - mu, b22 - mu, b33 - mu, b12, b13, b23)
        xx = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
        yy = y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
        zz = z[0] * z[0] + z[1] * z[1] + z[2] * z[2]
        use_y = yy > xx
        size = np.where(use_y, yy, xx)
        use_z = zz > size
        size = np.where(use_z, zz, size)
        inv_size = 1.0 / np.sqrt(size)
        e3 = (
            np.where(use_z, z[0], np.where(use_y, y[0], x[0])) * inv_size,
            np.where(use_z, z[1], np.where(use_y, y[1], x[1])) * inv_size,
            np.where(use_z, z[2], np.where(use_y, y[2], x[2])) * inv_size,
        )
        l3 = 1.0 / mu if exact_inverse else _quadratic_form(a11, a12, a22, a13, a23, a33, e3)
        # l1, l2, e1: symmetric 2x2 eigenproblem in the plane orthogonal to e3.
        u, v = plane_basis(e3)
        au = (a11 * u[0] + a12 * u[1] + a13 * u[2], a12 * u[0] + a22 * u[1] + a23 * u[2])
        au2 = a13 * u[0] + a23 * u[1] + a33 * u[2]
        muu = au[0] * u[0] + au[1] * u[1] + au2 * u[2]
        muv = au[0] * v[0] + au[1] * v[1] + au2 * v[2]
        mvv = _quadratic_form(a11, a12, a22, a13, a23, a33, v)
        half = np.hypot(0.5 * (muu - mvv), muv)
        l2 = 0.5 * (muu + mvv) - half
        l1 = l2 + 2.0 * half
        theta = 0.5 * np.arctan2(2.0 * muv, muu - mvv)
        cos, sin = np.cos(theta), np.sin(theta)
        a = np.sqrt(2.0 * half)
        b = np.sqrt(np.maximum(l2 - l3, 0.0))
        s = np.sqrt(l1 - l3)
        k = r * l2 * s / np.sqrt(-l1 * l3)
        # a e1 and b e3, then both signs along a second axis.
        ab = np.empty((2, 3, *np.shape(k)))
        for i in range(3):
            ab[0, i] = a * (cos * u[i] + sin * v[i])
            ab[1, i] = b * e3[i]
        ae1 = ab[0][:, None]
        be3 = ab[1][:, None] * np.array([1.0, -1.0]).reshape(2, *([1] * np.ndim(k)))
        n = (ae1 + be3) / s  # plane m . x = k with m = a e1 +- b e3, |m| = s
        # Sphere |x|^2 + (k/l2) (a x1 -+ b x3) = 0 has centre cs = -(k / 2 l2) (a e1 -+ b e3).
        cs = -(k / (2.0 * l2)) * (ae1 - be3)
        dist = (n[0] * cs[0] + n[1] * cs[1] + n[2] * cs[2]) - k / s
        c = cs - dist * n
        # Both (k, c) and (-k, -c) are solutions; keep the one in front of the camera.
        c *= np.where(c[2] < 0, -1.0, 1.0)
        n *= np.where(n[0] * c[0] + n[1] * c[1] + n[2] * c[2] > 0, -1.0, 1.0)
    return c, n


def _adjugate_columns(
    d1: F64, d2: F64, d3: F64, a12: F64, a13: F64, a23: F64
) -> tuple[tuple[F64, F64, F64], ...]:
    """Columns of the adjugate of ``[[d1, a12, a13], [a12, d2, a23], [a13, a23, d3]]``.

    They are the cross products of pairs of its rows; for a matrix ``A - l I`` with ``l`` near
    a simple eigenvalue each is parallel to that eigenvector. The adjugate of a symmetric
    matrix is symmetric: six distinct cofactors.
    """
    c12 = a13 * a23 - a12 * d3
    c13 = a12 * a23 - a13 * d2
    c23 = a12 * a13 - d1 * a23
    return (
        (d2 * d3 - a23 * a23, c12, c13),
        (c12, d1 * d3 - a13 * a13, c23),
        (c13, c23, d1 * d2 - a12 * a12),
    )


def _quadratic_form(
    a11: F64, a12: F64, a22: F64, a13: F64, a23: F64, a33: F64, x: tuple[F64, F64, F64]
) -> F64:
    """``x^T A x`` for symmetric ``A`` given by its entries and ``x`` by its components."""
    x0, x1, x2 = x
    return (
        a11 * x0 * x0
        + a22 * x1 * x1
        + a33 * x2 * x2
        + 2.0 * (a12 * x0 * x1 + a13 * x0 * x2 + a23 * x1 * x2)
    )


def plane_basis(n: tuple[F64, F64, F64]) -> tuple[tuple[F64, F64, F64], tuple[F64, F64, F64]]:
    """Two unit vectors orthogonal to each unit vector ``n`` and to each other.

    Vectors are given and returned by their components ``(x, y, z)`` (arrays of any shape).
    """
    n0, n1, n2 = n
    use_x = np.abs(n0) < 0.9
    # e1 = n x (1, 0, 0) = (0, n2, -n1), or n x (0, 1, 0) = (-n2, 0, n0).
    e0 = np.where(use_x, 0.0, -n2)
    e1 = np.where(use_x, n2, 0.0)
    e2 = np.where(use_x, -n1, n0)
    inv = 1.0 / np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 * inv, e1 * inv, e2 * inv
    return (e0, e1, e2), (n1 * e2 - n2 * e1, n2 * e0 - n0 * e2, n0 * e1 - n1 * e0)


def fit_conics(points: ArrayLike) -> F64:
    """Algebraic least-squares conics through batches of points (Hartley-normalised).

    Parameters
    ----------
    points : (..., M, 2) array_like
        ``M >= 5`` points per conic, ``(u, v)``.

    Returns
    -------
    (..., 3, 3) ndarray
        Symmetric conics (exact when the points lie on a conic).

    Notes
    -----
    See :func:`fit_conic_entries_t`, which this wraps for points given as ``(u, v)`` pairs.
    """
    P = np.asarray(points, dtype=np.float64)
    U = np.ascontiguousarray(np.moveaxis(P[..., 0], -1, 0))
    V = np.ascontiguousarray(np.moveaxis(P[..., 1], -1, 0))
    return _symmetric(*fit_conic_entries_t(U, V))


def fit_conic_entries_t(u: F64, v: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
    """:func:`fit_conics` with the points first: coordinates ``u``, ``v`` of shape ``(M, ...)``.

    Returns the conics' entries ``(c11, c12, c22, c13, c23, c33)``, each of shape ``(...)``
    (the order :func:`params_from_entries_t` takes).

    Notes
    -----
    The conic ``c`` minimising ``|A c|`` (``|c| = 1``) over the design matrix ``A`` with rows
    ``(x^2, xy, y^2, x, y, 1)`` is the eigenvector of the smallest eigenvalue of ``A^T A``. That
    6x6 matrix is assembled from the 15 moments ``sum x^a y^b`` (``a + b <= 4``) and the
    eigenvector found by inverse iteration, all batched with the matrix axes first: the same
    solution as a batched SVD of ``A`` at a fraction of its cost. Normalisation keeps ``A^T A``
    well conditioned apart from its (near-)null direction, which is the one sought.
    """
    c, mx, my, inv_scale = _fit_normalised(u, v)
    # Undo the normalisation x = s (p - m): the conic in p is T^T Cn T, entry by entry.
    A, B, C, D, E, F = c
    s, s2 = inv_scale, inv_scale * inv_scale
    q11, q12, q22 = A * s2, 0.5 * B * s2, C * s2
    q13 = -(q11 * mx + q12 * my) + 0.5 * D * s
    q23 = -(q12 * mx + q22 * my) + 0.5 * E * s
    q33 = q11 * mx * mx + 2.0 * q12 * mx * my + q22 * my * my - s * (D * mx + E * my) + F
    return q11, q12, q22, q13, q23, q33


def fit_ellipse_params_t(u: F64, v: F64) -> F64:
    """Ellipses ``(5, ...)`` ``(u, v, s11, s12, s22)`` fitted through points ``u``, ``v``
    ``(M, ...)`` (points first), as :func:`fit_conic_entries_t`.

    The parameters are taken from the conic in the normalised frame and mapped back (a shift
    and a scale), which keeps the shape to rounding of the ellipse's own size: going through
    the conic in absolute pixels loses digits to the centre's distance from the origin. NaN
    where a fit is not a real ellipse.
    """
    c, mx, my, inv_scale = _fit_normalised(u, v)
    out = params_from_entries_t(c[0], 0.5 * c[1], c[2], 0.5 * c[3], 0.5 * c[4], c[5])
    scale = 1.0 / inv_scale
    out *= scale
    out[0] += mx
    out[1] += my
    return out


def _fit_normalised(u: F64, v: F64) -> tuple[F64, F64, F64, F64]:
    """Unit conic coefficients ``(6, ...)`` of ``(x^2, xy, y^2, x, y, 1)`` in the normalised
    frame ``x = s (p - m)`` of points ``u``, ``v`` ``(M, ...)``, and ``m`` (two arrays) and
    ``s``. See :func:`fit_conic_entries_t`."""
    count = u.shape[0]
    mx, my = u.mean(axis=0), v.mean(axis=0)
    X, Y = u - mx, v - my
    scale = np.sqrt(np.mean(X * X + Y * Y, axis=0))
    inv_scale = 1.0 / scale
    X *= inv_scale
    Y *= inv_scale
    # The 14 non-constant monomials x^a y^b (a + b <= 4) in one buffer, summed in one call.
    mono = np.empty((14, *X.shape))
    x2, xy, y2 = np.multiply(X, X, out=mono[2]), np.multiply(X, Y, out=mono[3]), mono[4]
    np.multiply(Y, Y, out=y2)
    mono[0], mono[1] = X, Y
    np.multiply(x2, X, out=mono[5])
    np.multiply(x2, Y, out=mono[6])
    np.multiply(X, y2, out=mono[7])
    np.multiply(y2, Y, out=mono[8])
    np.multiply(x2, x2, out=mono[9])
    np.multiply(x2, xy, out=mono[10])
    np.multiply(x2, y2, out=mono[11])
    np.multiply(xy, y2, out=mono[12])
    np.multiply(y2, y2, out=mono[13])
    sums = mono.sum(axis=1)
    names = (
        *((1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3)),
        *((4, 0), (3, 1), (2, 2), (1, 3), (0, 4)),
    )
    moment = dict(zip(names, sums, strict=True))
    moment[(0, 0)] = np.full(X.shape[1:], float(count))
    mono_order = ((2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0))
    M = np.empty((6, 6, *X.shape[1:]))
    for i, (ai, bi) in enumerate(mono_order):
        for j, (aj, bj) in enumerate(mono_order[i:], start=i):
            M[i, j] = M[j, i] = moment[(ai + aj, bi + bj)]
    # Inverse iteration. The shift keeps an exact fit (a singular A^T A) invertible without
    # moving the eigenvectors; the convergence factor per step is (l6 + shift) / (l5 + shift).
    shift = 1e-13 * (M[0, 0] + M[1, 1] + M[2, 2] + M[3, 3] + M[4, 4] + M[5, 5])
    for i in range(6):
        M[i, i] += shift
    Minv = spd_inverse(M, overwrite=True)
    c = np.empty((6, *X.shape[1:]))
    c[:] = np.array([1.0, 0.0, 1.0, 0.0, 0.0, -1.0]).reshape(6, *([1] * (c.ndim - 1)))
    for _ in range(4):
        c = np.einsum("ij...,j...->i...", Minv, c)
        c /= np.sqrt(np.sum(c * c, axis=0))
    return c, mx, my, inv_scale


def ellipse_points(params: ArrayLike, count: int) -> F64:
    """``count`` points evenly spaced in angle on each ellipse ``(u, v, s11, s12, s22)``.

    Returns
    -------
    (..., count, 2) ndarray
    """
    p = np.asarray(params, dtype=np.float64)
    du, dv = ellipse_offsets_t(p[..., 2], p[..., 3], p[..., 4], count)
    out = np.empty((*p.shape[:-1], count, 2))
    out[..., 0] = p[..., 0, None] + np.moveaxis(du, 0, -1)
    out[..., 1] = p[..., 1, None] + np.moveaxis(dv, 0, -1)
    return out


def ellipse_offsets_t(s11: F64, s12: F64, s22: F64, count: int) -> tuple[F64, F64]:
    """Offsets ``S (cos t, sin t)`` from the centre of ``count`` points evenly spaced in angle
    on ellipses of square-root shape ``S = [[s11, s12], [s12, s22]]`` (any shape ``(...)``):
    ``(du, dv)``, each ``(count, ...)`` (the samples first)."""
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    cos = np.cos(t).reshape(-1, *([1] * np.ndim(s11)))
    sin = np.sin(t).reshape(cos.shape)
    return s11 * cos + s12 * sin, s12 * cos + s22 * sin
