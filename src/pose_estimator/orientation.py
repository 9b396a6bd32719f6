"""The printed in-plane axis of each fiducial: its full orientation from one image.

A circle's image fixes its centre and normal (paper section 4) but not its spin about the
normal. The coding track does: the detector reads the image angle of the printed line on which
the code's sector 0 starts (``FiducialDetection.rotation``, the target frame's +x axis). A
straight line through the centre of the printed plane images to a straight line through the
image of the centre, so that image direction, back-projected onto the fiducial's plane, is the
axis: exact under perspective (no affine approximation), up to the reading's own error.

With the axis a single fiducial gives the rotation of the body it is glued to between two
states (``F_after @ F_before.T`` of the two frames), which the normal alone leaves free about
itself. The circle pose's two-fold ambiguity (the normal mirrored about the line of sight,
:func:`displacement_matcher.units.mirror_normals`) carries over: :func:`mirror_axes` gives the
axis on the other branch, the same image direction back-projected onto the mirrored plane.

Camera frame (x right, y down, z forward), millimetres; image angles from +u towards +v.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .camera import CameraModel
from .errors import PoseError

F64 = NDArray[np.float64]

#: Below this |cos| between a plane's normal and the ray to its centre (or to the point of the
#: axis) the plane is seen edge on and the back-projection is undefined (NaN).
_EDGE_ON_COS = 1e-6


def printed_axes(
    camera: CameraModel,
    position_mm: ArrayLike,
    normal: ArrayLike,
    center_px: ArrayLike,
    rotation: ArrayLike,
) -> F64:
    """The printed +x axis of each fiducial in the camera frame.

    Parameters
    ----------
    camera : CameraModel
        The image's camera (lens distortion honoured at the fiducial's centre).
    position_mm, normal : (N, 3) array_like
        The fiducials' centres and unit normals (camera frame).
    center_px : (N, 2) array_like
        Distorted pixels where the image angles were measured (the pose ellipses' centres):
        the lens's local Jacobian there turns each direction into an ideal one.
    rotation : (N,) array_like
        Image angle of each printed +x axis, radians from +u towards +v
        (``FiducialDetection.rotation``).

    Returns
    -------
    (N, 3) ndarray
        Unit axes orthogonal to the normals; NaN rows where an input is not finite or the plane
        is seen edge on.

    Raises
    ------
    PoseError
        If the arrays' shapes disagree.
    """
    C = np.asarray(position_mm, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    uv = np.asarray(center_px, dtype=np.float64)
    theta = np.asarray(rotation, dtype=np.float64)
    k = len(theta.reshape(-1))
    if C.shape != (k, 3) or n.shape != (k, 3) or uv.shape != (k, 2) or theta.shape != (k,):
        raise PoseError(
            "printed_axes needs (N, 3) positions and normals, (N, 2) centres and (N,) angles; "
            f"got {C.shape}, {n.shape}, {uv.shape}, {theta.shape}"
        )
    d_px = np.stack([np.cos(theta), np.sin(theta)])  # (2, N) distorted pixel direction
    if camera.has_distortion:
        with np.errstate(invalid="ignore"):
            _, _, A = camera.undistortion_jacobian(uv[:, 0], uv[:, 1])
        d_px = np.stack([A[0] * d_px[0] + A[1] * d_px[1], A[2] * d_px[0] + A[3] * d_px[1]])
    # Ideal pixels to normalised coordinates: divide by the focal lengths.
    d_norm = d_px / np.array([camera.K[0, 0], camera.K[1, 1]])[:, None]
    return _back_projected(C, n, d_norm.T)


def mirror_axes(position_mm: ArrayLike, axis: ArrayLike, mirrored_normal: ArrayLike) -> F64:
    """The axes on the other branch of the circle pose's ambiguity.

    The image shows one direction; each branch's plane turns it into its own axis. Here the
    image direction of ``axis`` (the derivative of the projection of ``position + s axis``) is
    back-projected onto the plane through ``position`` with ``mirrored_normal``.

    Parameters
    ----------
    position_mm, axis, mirrored_normal : (N, 3) array_like
        Centres, axes on the estimated branch and the other branch's normals
        (:func:`displacement_matcher.units.mirror_normals`).

    Returns
    -------
    (N, 3) ndarray
        Unit axes orthogonal to ``mirrored_normal`` (NaN where undefined).
    """
    C = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(axis, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(mirrored_normal, dtype=np.float64).reshape(-1, 3)
    # d/ds of (C + s a)_xy / (C + s a)_z at s = 0, up to the positive factor 1 / C_z^2.
    d_norm = a[:, :2] * C[:, 2:3] - C[:, :2] * a[:, 2:3]
    return _back_projected(C, m, d_norm)


def target_frames(normal: ArrayLike, axis: ArrayLike) -> F64:
    """Printed target frames ``(N, 3, 3)``: columns axis, normal x axis, normal."""
    n = np.asarray(normal, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(axis, dtype=np.float64).reshape(-1, 3)
    return np.stack([a, np.cross(n, a), n], axis=2)


def _back_projected(C: F64, n: F64, d_norm: F64) -> F64:
    """Unit direction, in the plane through ``C`` with normal ``n``, of the line through ``C``
    whose image has direction ``d_norm`` (normalised coordinates, ``(N, 2)``) at the image of
    ``C``: a point of that image line, back-projected onto the plane, minus ``C``.

    The image line is straight and so is its back-projection, so the point's distance along it
    only sets the rounding: 1e-3 in normalised coordinates (a few pixels).
    """
    z = C[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        q0 = C[:, :2] / z[:, None]
        step = 1e-3 / np.linalg.norm(d_norm, axis=1)
        ray = np.column_stack([q0 + step[:, None] * d_norm, np.ones(len(C))])
        along = np.einsum("ki,ki->k", n, ray)
        height = np.einsum("ki,ki->k", n, C)
        t = height / along
        a = ray * t[:, None] - C
        a -= np.einsum("ki,ki->k", a, n)[:, None] * n
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        # Edge on: the plane passes through the camera, or the ray runs along it.
        edge_on = np.abs(height) < _EDGE_ON_COS * np.linalg.norm(C, axis=1)
        edge_on |= np.abs(along) < _EDGE_ON_COS * np.linalg.norm(ray, axis=1)
    bad = edge_on | ~np.isfinite(a).all(axis=1) | ~(z > 0)
    a[bad] = np.nan
    return np.asarray(a, dtype=np.float64)
