"""Cramér-Rao bound of a fiducial's depth from the rendered image itself.

For an image ``I(theta)`` observed with additive white Gaussian noise of standard deviation
``sigma`` (fraction of full range, the paper's noise model), the Fisher information is
``F = J^T J / sigma^2`` with ``J = dI/dtheta`` over all pixels. ``J`` is obtained by central
finite differences of noise-free renders (the one renderer, :mod:`armourcam.render`, with heavy
supersampling so that edge motion is resolved smoothly). Three bounds on ``std(z)``:

``z only``
    ``sigma / sqrt(sum((dI/dz)^2))``: every other pose parameter known (the loosest bound).
``pose``
    ``sqrt((F^-1)_zz)`` with x, y, z and the two out-of-plane rotations unknown, blur and levels
    known, every pixel of the synthetic image counted.
``print_only``
    As ``pose``, but from the printed pattern alone, and with the blur and the black and white
    levels unknown too: the paper around the print is rendered white to the image's edge. In
    a real scene the paper is cut by hand and what lies beyond it (the armour unit) is unknown,
    so its edge tells an estimator nothing it can rely on; in a synthetic image on a uniform
    background it carries depth (at 60 px and 65 deg slant ``pose`` is 15 % below
    ``print_only``), which no estimator of a real print can use.

No estimator using the image can have a smaller variance if it is unbiased. Camera frame OpenCV,
millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from armourcam.render import BACKGROUND, WHITE, Target, defocus, render

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
    print_only : float
        Bound from the printed pattern alone, with position, out-of-plane orientation, blur and
        the black and white levels unknown.
    """

    z_only: float
    pose: float
    print_only: float


def _image(
    camera: CameraModel,
    target: Target,
    blur_sigma: float,
    supersample: int,
    background: float = BACKGROUND,
) -> NDArray[np.float64]:
    """Noise-free image (fraction of full range) of one target, blurred."""
    scene = render(
        camera, [target], dtype=np.uint16, supersample=supersample, background=background
    )
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
    steps = (step_px * z / f, step_px * z / (f * radius / z), step_px * z / (f * radius))
    F = _information(camera, target, blur_sigma, supersample, steps, BACKGROUND, nuisance=False)
    z_only = 1.0 / np.sqrt(F[2, 2])
    pose = np.sqrt(np.linalg.inv(F)[2, 2])
    F = _information(camera, target, blur_sigma, supersample, steps, WHITE, nuisance=True)
    print_only = np.sqrt(np.linalg.inv(F)[2, 2])
    return DepthBound(float(z_only), float(pose), float(print_only))


def _information(
    camera: CameraModel,
    target: Target,
    blur_sigma: float,
    supersample: int,
    steps: tuple[float, float, float],
    background: float,
    *,
    nuisance: bool,
) -> NDArray[np.float64]:
    """Fisher information for unit noise of x, y, z, the two out-of-plane rotations and, with
    ``nuisance``, the blur (when there is any) and the two levels, in that order."""
    dxy, dz, drot = steps

    def image(t: Target, blur: float = blur_sigma) -> NDArray[np.float64]:
        return _image(camera, t, blur, supersample, background)

    cols = []
    for axis, h in ((0, dxy), (1, dxy), (2, dz)):
        d = np.zeros(3)
        d[axis] = h
        plus = replace(target, position_mm=target.position_mm + d)
        minus = replace(target, position_mm=target.position_mm - d)
        cols.append((image(plus) - image(minus)).ravel() / (2.0 * h))
    for axis in (0, 1):
        w = np.zeros(3)
        w[axis] = drot
        rp, _ = cv2.Rodrigues(w)
        rm, _ = cv2.Rodrigues(-w)
        plus = replace(target, rotation=rp @ target.rotation)
        minus = replace(target, rotation=rm @ target.rotation)
        cols.append((image(plus) - image(minus)).ravel() / (2.0 * drot))
    if nuisance:
        # One render of the print serves the blur's column and the levels'.
        sharp = image(target, 0.0)
        if blur_sigma > 0:
            h = min(0.05, 0.5 * blur_sigma)
            diff = defocus(sharp, blur_sigma + h) - defocus(sharp, blur_sigma - h)
            cols.append(diff.ravel() / (2.0 * h))
        # The levels enter linearly: a constant and the image itself span them.
        cols.append(np.ones(cols[0].size))
        cols.append((defocus(sharp, blur_sigma) if blur_sigma > 0 else sharp).ravel())
    J = np.stack(cols, axis=1)
    return J.T @ J
