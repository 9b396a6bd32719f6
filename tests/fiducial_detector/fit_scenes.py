"""Single rendered fiducials with their exact image conics, for the sub-pixel fit tests.

Images come from :mod:`armourcam.render` (the one renderer) with seeded noise; the truth is
``TargetTruth.conics`` (ideal camera, so the image conics are exact).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from armourcam.render import RenderedScene, Target, render, rotation_from_slant_tilt
from fiducial_detector.ellipse import ellipse_from_conic, fit_ellipse
from fiducial_detector.types import Ellipse
from pose_estimator.camera import CameraModel

FOCAL = 2000.0
DIAMETER = 7.1


def render_one(
    design: str, size: float, slant_deg: float, blur: float, noise: float, seed: int
) -> RenderedScene:
    """One fiducial of outer diameter ``size`` px (at zero slant), off the pixel grid."""
    z = FOCAL * DIAMETER / size
    n = int(1.5 * size) + 24
    cam = CameraModel.ideal(n, n, FOCAL, center=(n / 2 - 0.31, n / 2 + 0.17))
    R = rotation_from_slant_tilt(np.radians(slant_deg), 0.4, 0.3)
    target = Target(7, design, DIAMETER, R, np.array([0.0, 0.0, z]))
    return render(cam, [target], blur_sigma=blur, noise=noise, rng=np.random.default_rng(seed))


def true_ellipse(scene: RenderedScene, k: int) -> NDArray[np.float64]:
    """``(u, v, a, b, angle)`` of circle ``k``'s exact image."""
    return np.array(ellipse_from_conic(scene.truth[0].conics[k]))


def coarse_seed(truth: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """A coarse seed like a component boundary's ellipse: ~0.4 px, ~0.3 px, ~1 degree off."""
    seed = truth + np.r_[rng.normal(0, 0.4, 2), rng.normal(0, 0.3, 2), rng.normal(0, 0.02)]
    seed[2:4] = np.sort(seed[2:4])[::-1]
    return seed


def dual_conic_radius_error(
    scene: RenderedScene, seed: NDArray[np.float64], noise_std: float
) -> float:
    """Mean semi-axis error of the paper's dual-conic fit of the pose circle from ``seed``."""
    e = fit_ellipse(
        scene.image,
        Ellipse((seed[0], seed[1]), seed[2], seed[3], seed[4], np.zeros((5, 5)), 1.0),
        radius=1.0,
        dark_inside=True,
        noise_std=noise_std,
    )
    assert e is not None
    truth = true_ellipse(scene, 0)
    return 0.5 * (e.semi_major + e.semi_minor - truth[2] - truth[3])


def abs_errors(params: NDArray[np.float64], truth: NDArray[np.float64]) -> NDArray[np.float64]:
    """|error| of centre and semi-axes."""
    return np.abs(params[:4] - truth[:4])
