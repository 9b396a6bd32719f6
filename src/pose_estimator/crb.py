"""Cramér-Rao bound of a fiducial's depth from the rendered image itself.

For an image ``I(theta)`` observed with additive white Gaussian noise of standard deviation
``sigma`` (fraction of full range, the paper's noise model), the Fisher information is
``F = J^T J / sigma^2`` with ``J = dI/dtheta`` over all pixels. ``J`` is obtained by central
finite differences of noise-free renders (the one renderer, :mod:`armourcam.render`, with heavy
supersampling so that edge motion is resolved smoothly). Two bounds on ``std(z)``:

``z only``
    ``sigma / sqrt(sum((dI/dz)^2))``: every other pose parameter known (the loosest bound).
``pose``
    ``sqrt((F^-1)_zz)`` with x, y, z and the two out-of-plane rotations unknown (what any pose
    estimator faces).

No estimator using the image can have a smaller variance if it is unbiased. Camera frame OpenCV,
millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from armourcam.render import Target, defocus, render

from .camera import CameraModel


@dataclass(frozen=True, slots=True)
class DepthBound:
    """Cramér-Rao bounds of ``std(z)`` in mm for unit noise (multiply by the noise fraction).

    Attributes
    ----------
    z_only : float
        Bound with every other pose parameter known.
    pose : float
        Bound with position and out-of-plane orientation unknown.
    """

    z_only: float
    pose: float


def _image(
    camera: CameraModel, target: Target, blur_sigma: float, supersample: int
) -> NDArray[np.float64]:
    """Noise-free image (fraction of full range) of one target, blurred."""
    scene = render(camera, [target], dtype=np.uint16, supersample=supersample)
    img = scene.image.astype(np.float64) / 65535.0
    return defocus(img, blur_sigma) if blur_sigma > 0 else img


def depth_bound(
    camera: CameraModel,
    target: Target,
    *,
    blur_sigma: float,
    supersample: int = 24,
    step_px: float = 0.15,
) -> DepthBound:
    """Cramér-Rao bounds of the depth of ``target`` for unit noise.

    Parameters
    ----------
    camera : CameraModel
        The camera rendering the image (ideally a small region around the target).
    target : Target
        The fiducial and its true pose.
    blur_sigma : float
        Gaussian defocus blur applied to the noise-free image, pixels.
    supersample : int
        Supersampling of edge pixels (``supersample**2`` rays).
    step_px : float
        Finite-difference step, chosen so that the outer edge moves about this many pixels.

    Returns
    -------
    DepthBound
    """
    f = float(camera.K[0, 0])
    z = float(target.position_mm[2])
    radius = 0.5 * target.diameter_mm
    # Steps: translations moving the image by ~step_px; rotations moving the rim by ~step_px.
    dxy = step_px * z / f
    dz = step_px * z / (f * radius / z)
    drot = step_px * z / (f * radius)
    cols = []
    for axis, h in ((0, dxy), (1, dxy), (2, dz)):
        d = np.zeros(3)
        d[axis] = h
        plus = replace(target, position_mm=target.position_mm + d)
        minus = replace(target, position_mm=target.position_mm - d)
        diff = _image(camera, plus, blur_sigma, supersample) - _image(
            camera, minus, blur_sigma, supersample
        )
        cols.append(diff.ravel() / (2.0 * h))
    for axis in (0, 1):
        w = np.zeros(3)
        w[axis] = drot
        rp, _ = cv2.Rodrigues(w)
        rm, _ = cv2.Rodrigues(-w)
        plus = replace(target, rotation=rp @ target.rotation)
        minus = replace(target, rotation=rm @ target.rotation)
        diff = _image(camera, plus, blur_sigma, supersample) - _image(
            camera, minus, blur_sigma, supersample
        )
        cols.append(diff.ravel() / (2.0 * drot))
    J = np.stack(cols, axis=1)
    F = J.T @ J
    z_only = 1.0 / np.sqrt(F[2, 2])
    pose = np.sqrt(np.linalg.inv(F)[2, 2])
    return DepthBound(float(z_only), float(pose))
