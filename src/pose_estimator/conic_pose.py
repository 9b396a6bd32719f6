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

import numpy as np
from numpy.typing import ArrayLike, NDArray

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
    s11, s12, s22 = p[..., 2], p[..., 3], p[..., 4]
    det = s11 * s22 - s12 * s12
    # Q = S^-2 = (S^-1)^2 with S^-1 = adj(S) / det.
    i11, i12, i22 = s22 / det, -s12 / det, s11 / det
    q11 = i11 * i11 + i12 * i12
    q12 = i11 * i12 + i12 * i22
    q22 = i12 * i12 + i22 * i22
    u, v = p[..., 0], p[..., 1]
    out = np.empty((*p.shape[:-1], 3, 3))
    out[..., 0, 0] = q11
    out[..., 0, 1] = out[..., 1, 0] = q12
    out[..., 1, 1] = q22
    out[..., 0, 2] = out[..., 2, 0] = -(q11 * u + q12 * v)
    out[..., 1, 2] = out[..., 2, 1] = -(q12 * u + q22 * v)
    out[..., 2, 2] = q11 * u * u + 2.0 * q12 * u * v + q22 * v * v - 1.0
    return out


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
        out = np.stack([u, v, (m11 + root) / t, m12 / t, (m22 + root) / t], axis=-1)
    bad = ~((det2 > 0) & (m11 > 0) & (detm > 0) & np.all(np.isfinite(out), axis=-1))
    out[bad] = np.nan
    return out


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
        ``(u, v, s11, s12, s22)`` in normalised image coordinates.

    Notes
    -----
    With ``g = n . c``, the cone through the circle is
    ``C = g^2 I - g (c n^T + n c^T) + (|c|^2 - r^2) n n^T``: for ``x = c + r m`` (``m`` a unit
    vector in the plane) ``x^T C x = 0``. Basis-free, so it is cheap and smooth in ``n``.
    """
    c = np.asarray(center, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    r = np.asarray(radius, dtype=np.float64)
    c0, c1, c2 = c[..., 0], c[..., 1], c[..., 2]
    n0, n1, n2 = n[..., 0], n[..., 1], n[..., 2]
    g = c0 * n0 + c1 * n1 + c2 * n2
    cc = c0 * c0 + c1 * c1 + c2 * c2
    g2 = g * g
    r2 = r * r
    # Entry (i, j) = P_ij - r^2 n_i n_j with P computed once per centre (radius-free part).
    return params_from_entries(
        (g2 - 2.0 * g * c0 * n0 + cc * n0 * n0) - r2 * (n0 * n0),
        (-g * (c0 * n1 + n0 * c1) + cc * n0 * n1) - r2 * (n0 * n1),
        (g2 - 2.0 * g * c1 * n1 + cc * n1 * n1) - r2 * (n1 * n1),
        (-g * (c0 * n2 + n0 * c2) + cc * n0 * n2) - r2 * (n0 * n2),
        (-g * (c1 * n2 + n1 * c2) + cc * n1 * n2) - r2 * (n1 * n2),
        (g2 - 2.0 * g * c2 * n2 + cc * n2 * n2) - r2 * (n2 * n2),
    )


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
        Conic of the circle's image in *normalised* coordinates, ``K^T C K`` (any scale or sign).
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
    """
    Q = np.asarray(cone, dtype=np.float64)
    Q = 0.5 * (Q + np.swapaxes(Q, -1, -2))
    r = np.asarray(radius_mm, dtype=np.float64)
    w, V = np.linalg.eigh(Q)  # ascending
    # Two eigenvalues of one sign: make them positive (the product of all three is then negative).
    flip = np.linalg.det(Q) > 0
    w = np.where(flip[..., None], -w[..., ::-1], w)
    V = np.where(flip[..., None, None], V[..., ::-1], V)
    l3, l2, l1 = w[..., 0], w[..., 1], w[..., 2]
    e3, e1 = V[..., :, 0], V[..., :, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.sqrt(np.clip(l1 - l2, 0.0, None))
        b = np.sqrt(np.clip(l2 - l3, 0.0, None))
        s = np.sqrt(l1 - l3)
        k = r * l2 * s / np.sqrt(-l1 * l3)
        centers = np.empty((*w.shape[:-1], 2, 3))
        normals = np.empty_like(centers)
        for i, sign in enumerate((1.0, -1.0)):
            m = a[..., None] * e1 + sign * b[..., None] * e3  # plane m . x = k, |m| = s
            n = m / s[..., None]
            # Sphere |x|^2 + (k/l2) (a x1 - b x3) = 0 has centre cs = -(k / 2 l2) p.
            p = a[..., None] * e1 - sign * b[..., None] * e3
            cs = -(k / (2.0 * l2))[..., None] * p
            dist = (np.einsum("...i,...i->...", n, cs) - k / s)[..., None]
            c = cs - dist * n
            # Both (k, c) and (-k, -c) are solutions; keep the one in front of the camera.
            c = np.where(c[..., 2:3] < 0, -c, c)
            n = np.where(np.einsum("...i,...i->...", n, c)[..., None] > 0, -n, n)
            centers[..., i, :] = c
            normals[..., i, :] = n
    return centers, normals


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
    """
    P = np.asarray(points, dtype=np.float64)
    mean = P.mean(axis=-2, keepdims=True)
    scale = np.sqrt(np.mean(np.sum((P - mean) ** 2, axis=-1), axis=-1))[..., None, None]
    x = (P - mean) / scale
    X, Y = x[..., 0], x[..., 1]
    A = np.stack([X * X, X * Y, Y * Y, X, Y, np.ones_like(X)], axis=-1)
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    c = vt[..., -1, :]
    Cn = np.empty((*P.shape[:-2], 3, 3))
    Cn[..., 0, 0] = c[..., 0]
    Cn[..., 0, 1] = Cn[..., 1, 0] = 0.5 * c[..., 1]
    Cn[..., 1, 1] = c[..., 2]
    Cn[..., 0, 2] = Cn[..., 2, 0] = 0.5 * c[..., 3]
    Cn[..., 1, 2] = Cn[..., 2, 1] = 0.5 * c[..., 4]
    Cn[..., 2, 2] = c[..., 5]
    # Undo the normalisation x = T p: C = T^T Cn T.
    T = np.zeros((*P.shape[:-2], 3, 3))
    s = 1.0 / scale[..., 0, 0]
    T[..., 0, 0] = T[..., 1, 1] = s
    T[..., 0, 2] = -mean[..., 0, 0] * s
    T[..., 1, 2] = -mean[..., 0, 1] * s
    T[..., 2, 2] = 1.0
    out: F64 = np.swapaxes(T, -1, -2) @ Cn @ T
    return out


def ellipse_points(params: ArrayLike, count: int) -> F64:
    """``count`` points evenly spaced in angle on each ellipse ``(u, v, s11, s12, s22)``.

    Returns
    -------
    (..., count, 2) ndarray
    """
    p = np.asarray(params, dtype=np.float64)
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    w = np.stack([np.cos(t), np.sin(t)], axis=-1)  # (count, 2)
    S = np.empty((*p.shape[:-1], 2, 2))
    S[..., 0, 0], S[..., 0, 1], S[..., 1, 0], S[..., 1, 1] = (
        p[..., 2],
        p[..., 3],
        p[..., 3],
        p[..., 4],
    )
    out: F64 = p[..., None, :2] + np.einsum("...ij,mj->...mi", S, w)
    return out
