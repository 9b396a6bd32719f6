"""The edge-profile fit (:mod:`fiducial_detector.profile_fit`) against exact image conics."""

from __future__ import annotations

import numpy as np
import pytest
from fit_scenes import (
    abs_errors,
    coarse_seed,
    dual_conic_radius_error,
    render_one,
    true_ellipse,
)

from fiducial_detector.design import get_design
from fiducial_detector.detect import POSE_LINE_SPACING_PX, fit_design_circles
from fiducial_detector.errors import DetectorError
from fiducial_detector.profile_fit import refine_by_profiles

#: The ring design's pose circle: half-way to the annulus' inner edge and to the paper's edge.
RING_RHO = (0.9, 1.15)


@pytest.mark.parametrize(("size", "slant", "blur"), [(60, 0, 0.5), (60, 50, 0.7), (120, 30, 1.0)])
def test_recovers_the_exact_ellipse_without_noise(size: float, slant: float, blur: float) -> None:
    """Within 0.02 px of the exact conic from a seed ~0.4 px off, blur measured on the way (at
    60 px, 50 deg, blur 0.7 the semi-minor axis is 0.018 px long against renders exact to about
    0.001 px; the sampled renders before edge coverage hid 0.004 px of it)."""
    scene = render_one("ring", size, slant, blur, 0.0, 0)
    truth = true_ellipse(scene, 0)
    seed = coarse_seed(truth, np.random.default_rng(2))
    fit = refine_by_profiles(scene.image, seed[None], dark_inside=True, rho_range=RING_RHO)
    assert fit.ok[0]
    assert np.all(abs_errors(fit.params[0], truth) < 0.02), fit.params[0] - truth
    # The measured blur includes pixel integration and interpolation (~0.45 px together).
    assert blur < fit.spread[0] < np.hypot(blur, 0.6)


def test_mean_radius_is_unbiased_at_high_noise() -> None:
    """The area locator is linear in the intensities: at 2 % noise the mean radius of a 120 px
    ring stays within 0.01 px of the truth where the dual-conic fit shrinks by > 0.03 px."""
    prof, dual = [], []
    for rep in range(10):
        scene = render_one("ring", 120, 0, 0.5, 0.02, 100 + rep)
        truth = true_ellipse(scene, 0)
        seed = coarse_seed(truth, np.random.default_rng(rep))
        fit = refine_by_profiles(scene.image, seed[None], dark_inside=True, rho_range=RING_RHO)
        assert fit.ok[0]
        prof.append(0.5 * (fit.params[0, 2] + fit.params[0, 3] - truth[2] - truth[3]))
        dual.append(dual_conic_radius_error(scene, seed, 0.02 * 255))
    assert abs(np.mean(prof)) < 0.01
    assert np.mean(dual) < -0.03


def test_covariance_predicts_the_scatter_without_a_noise_estimate() -> None:
    """The covariance comes from the edge positions' own residuals: predicted sds of
    (u, v, a, b) between 0.55 and 1.6 times the empirical ones, at 1 % and 3 % noise alike (the
    residuals also hold the corrections' small systematic errors, which do not scatter: at low
    noise the semi-axes' sds are over-predicted)."""
    for noise, seed0 in ((0.01, 300), (0.03, 400)):
        errs, preds = [], []
        for rep in range(24):
            scene = render_one("ring", 60, 35, 0.7, noise, seed0 + rep)
            truth = true_ellipse(scene, 0)
            seed = coarse_seed(truth, np.random.default_rng(seed0 + 50 + rep))
            fit = refine_by_profiles(scene.image, seed[None], dark_inside=True, rho_range=RING_RHO)
            assert fit.ok[0]
            errs.append(fit.params[0, :4] - truth[:4])
            preds.append(np.sqrt(np.diag(fit.covariance[0])[:4]))
        ratio = np.std(errs, axis=0, ddof=1) / np.mean(preds, axis=0)
        assert np.all((ratio > 1 / 1.8) & (ratio < 1.6)), (noise, ratio)


@pytest.mark.parametrize(
    ("size", "slant", "spacing"), [(60, 35, 1.0), (90, 60, 1.0), (60, 35, POSE_LINE_SPACING_PX)]
)
def test_covariance_from_the_image_noise_predicts_the_scatter(
    size: float, slant: float, spacing: float
) -> None:
    """Given the image noise, the covariance is the noise's propagated through the lines:
    predicted sds of (u, v, a, b) within 0.65-1.45 times the empirical ones at 0.5 % and 3 %
    noise alike (blur 0.5 px, where aliasing leaves ~0.02 px of misfit per line), with lines a
    pixel apart (sharing interpolated pixels) or the detector's pose circle's sparser ones. From
    the residuals alone the same fits at 0.5 % noise over-predict the semi-axes' sds (that
    misfit does not scatter from image to image)."""
    for noise, seed0 in ((0.005, 300), (0.03, 400)):
        errs, preds, resid = [], [], []
        for rep in range(30):
            scene = render_one("ring", size, slant, 0.5, noise, seed0 + rep)
            truth = true_ellipse(scene, 0)
            seed = coarse_seed(truth, np.random.default_rng(seed0 + 50 + rep))
            args = {"dark_inside": True, "rho_range": RING_RHO, "spacing": spacing}
            fit = refine_by_profiles(scene.image, seed[None], noise_std=noise * 255, **args)
            assert fit.ok[0]
            errs.append(fit.params[0, :4] - truth[:4])
            preds.append(np.sqrt(np.diag(fit.covariance[0])[:4]))
            alone = refine_by_profiles(scene.image, seed[None], **args)
            resid.append(np.sqrt(np.diag(alone.covariance[0])[:4]))
        emp = np.std(errs, axis=0, ddof=1)
        ratio = emp / np.mean(preds, axis=0)
        assert np.all((ratio > 0.65) & (ratio < 1.45)), (noise, ratio)
        if noise < 0.01:
            assert np.all(emp[2:] / np.mean(resid, axis=0)[2:] < 0.8)


def test_detector_default_is_the_profile_fit_and_steep_dots_get_the_model_fit() -> None:
    """The default method's pose circle is the profile fit's; a 60 px dot at 70 deg (tips bending
    within the blur) is fitted by the edge model instead, exactly as ``method="ml"`` does."""
    spec = get_design("ring")
    scene = render_one("ring", 60, 20, 0.6, 0.01, 5)
    truth = true_ellipse(scene, 0)
    seed = coarse_seed(truth, np.random.default_rng(5))
    default = fit_design_circles(scene.image, seed[None], spec, 2.5)[0]
    alone = refine_by_profiles(
        scene.image,
        seed[None],
        dark_inside=True,
        rho_range=RING_RHO,
        spacing=POSE_LINE_SPACING_PX,
    )
    assert len(default) >= 2  # the pose circle and at least one concentric circle
    np.testing.assert_allclose(default[0].center_px, alone.params[0, :2], atol=1e-9)
    dot = get_design("dot")
    scene = render_one("dot", 60, 70, 0.6, 0.01, 6)
    seed = coarse_seed(true_ellipse(scene, 0), np.random.default_rng(6))
    fast = fit_design_circles(scene.image, seed[None], dot, 2.5)[0]
    model = fit_design_circles(scene.image, seed[None], dot, 2.5, method="ml")[0]
    assert fast and model
    assert fast[0].center_px == model[0].center_px


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ring_at_60_deg_keeps_its_profile_pose_circle_and_gains_its_dot_by_the_model(
    seed: int,
) -> None:
    """At 60 deg and blur 0.7 the annulus' inner edge and the dot leave the profiles too few
    clean lines; the dot is then fitted by the single-edge model from the profiles' pose
    circle, which is kept as it is (not refitted with the annulus by the slower model)."""
    spec = get_design("ring")
    scene = render_one("ring", 60, 60, 0.7, 0.01, seed)
    seed_ellipse = coarse_seed(true_ellipse(scene, 0), np.random.default_rng(seed))
    default = fit_design_circles(scene.image, seed_ellipse[None], spec, 2.55)[0]
    alone = refine_by_profiles(
        scene.image,
        seed_ellipse[None],
        dark_inside=True,
        rho_range=RING_RHO,
        noise_std=2.55,
        spacing=POSE_LINE_SPACING_PX,
    )
    assert [e.radius for e in default] == [1.0, 0.24]
    np.testing.assert_allclose(default[0].center_px, alone.params[0, :2], atol=1e-9)
    dot, truth = default[1], true_ellipse(scene, 2)
    fitted = np.array([*dot.center_px, dot.semi_major, dot.semi_minor])
    assert np.all(abs_errors(fitted, truth) < 0.03), fitted - truth[:4]
    sd = np.sqrt(np.diag(dot.covariance))
    assert np.all(np.isfinite(sd)) and np.all(sd[:2] < 0.03)


def test_unfittable_seeds_fail_cleanly_and_bad_arguments_raise() -> None:
    flat = np.full((80, 80), 128, np.uint8)
    seed = np.array([[40.0, 40.0, 20.0, 15.0, 0.3]])
    assert not refine_by_profiles(flat, seed, dark_inside=True).ok[0]
    nan_seed = np.array([[np.nan, 40.0, 20.0, 15.0, 0.3]])
    assert not refine_by_profiles(flat, nan_seed, dark_inside=True).ok[0]
    assert len(refine_by_profiles(flat, np.zeros((0, 5)), dark_inside=True)) == 0
    with pytest.raises(DetectorError, match="seeds"):
        refine_by_profiles(flat, np.zeros((3, 4)), dark_inside=True)
    with pytest.raises(DetectorError, match="rho_range"):
        refine_by_profiles(flat, seed, dark_inside=True, rho_range=(1.2, 1.5))
    with pytest.raises(DetectorError, match="2-D"):
        refine_by_profiles(np.zeros((8, 8, 3)), seed, dark_inside=True)
    with pytest.raises(DetectorError, match="passes"):
        refine_by_profiles(flat, seed, dark_inside=True, passes=0)
    with pytest.raises(DetectorError, match="noise_std"):
        refine_by_profiles(flat, seed, dark_inside=True, noise_std=0.0)
    with pytest.raises(DetectorError, match="spacing"):
        refine_by_profiles(flat, seed, dark_inside=True, spacing=0.0)
