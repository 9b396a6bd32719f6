"""The dual-conic ellipse fit against the renderer's exact image conics.

Every image comes from :mod:`armourcam.render` (the one renderer) with seeded noise; the truth is
``TargetTruth.conics`` (ideal camera, so image conics are exact).
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from armourcam.render import (
    RenderedScene,
    Target,
    render,
    rotation_from_slant_tilt,
)
from fiducial_detector.design import get_design
from fiducial_detector.ellipse import (
    _median,
    ellipse_from_conic,
    estimate_noise,
    fit_ellipse,
    fit_ellipses,
)
from fiducial_detector.errors import DetectorError
from fiducial_detector.types import Ellipse, conic_from_parameters
from pose_estimator.camera import CameraModel

FOCAL = 2000.0
DIAMETER = 7.1


def _scene(
    design: str,
    size: float,
    slant_deg: float,
    blur: float,
    noise: float,
    seed: int,
    *,
    tilt: float = 0.4,
    spin: float = 0.3,
) -> RenderedScene:
    """One fiducial whose outer diameter is ``size`` pixels at zero slant."""
    z = FOCAL * DIAMETER / size
    n = int(1.5 * size) + 24
    cam = CameraModel.ideal(n, n, FOCAL, center=(n / 2 - 0.31, n / 2 + 0.17))
    R = rotation_from_slant_tilt(np.radians(slant_deg), tilt, spin)
    target = Target(7, design, DIAMETER, R, np.array([0.0, 0.0, z]))
    return render(
        cam,
        [target],
        blur_sigma=blur,
        noise=noise,
        rng=np.random.default_rng(seed),
    )


def _truth(conic: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array(ellipse_from_conic(conic))


def _perturbed_seed(truth: NDArray[np.float64], rng: np.random.Generator) -> Ellipse:
    """A coarse seed: centre off by ~0.5 px, axes by ~3 %, angle by ~3 degrees."""
    u, v, a, b, ang = truth
    return Ellipse(
        (u + rng.normal(0, 0.5), v + rng.normal(0, 0.5)),
        a * (1 + rng.normal(0, 0.03)),
        min(b * (1 + rng.normal(0, 0.03)), a),
        ang + rng.normal(0, 0.05),
        np.zeros((5, 5)),
        1.0,
    )


@pytest.mark.parametrize("angle", np.linspace(0.0, np.pi, 9)[:-1])
@pytest.mark.parametrize("scale", [1.0, -3.5])
def test_ellipse_from_conic_round_trip(angle: float, scale: float) -> None:
    """Any scale or sign of the conic gives the canonical parameters back."""
    C = scale * conic_from_parameters(12.5, -3.0, 9.0, 4.0, angle)
    u, v, a, b, ang = ellipse_from_conic(C)
    assert (u, v, a, b) == pytest.approx((12.5, -3.0, 9.0, 4.0), abs=1e-9)
    assert 0.0 <= ang < np.pi
    assert ang == pytest.approx(angle, abs=1e-9)


def test_ellipse_from_conic_canonical_for_swapped_axes() -> None:
    """Semi-axes given minor-first come back major-first with the angle turned by 90 degrees."""
    _, _, a, b, ang = ellipse_from_conic(conic_from_parameters(0, 0, 3.0, 7.0, 0.2))
    assert (a, b) == pytest.approx((7.0, 3.0))
    assert ang == pytest.approx(0.2 + np.pi / 2)


@pytest.mark.parametrize(
    "conic",
    [np.diag([1.0, -1.0, -1.0]), np.diag([1.0, 1.0, 1.0]), np.diag([1.0, 0.0, -1.0])],
    ids=["hyperbola", "imaginary", "parabola-like"],
)
def test_ellipse_from_conic_rejects_non_ellipses(conic: NDArray[np.float64]) -> None:
    with pytest.raises(ValueError, match="not a real ellipse"):
        ellipse_from_conic(conic)


@pytest.mark.parametrize(
    ("design", "size", "slant", "blur", "noise", "centre_tol", "axis_tol"),
    [
        ("dot", 120, 0, 0.5, 0.01, 0.03, 0.05),
        ("dot", 120, 60, 0.7, 0.02, 0.03, 0.06),
        ("dot", 60, 30, 0.5, 0.02, 0.04, 0.06),
        ("dot", 35, 45, 0.7, 0.01, 0.12, 0.12),
        ("ring", 120, 75, 0.5, 0.01, 0.03, 0.2),
        ("ring", 60, 0, 0.7, 0.02, 0.03, 0.08),
        ("ring", 60, 60, 0.5, 0.02, 0.05, 0.10),
        ("ring", 35, 30, 0.7, 0.02, 0.04, 0.12),
    ],
)
def test_fit_matches_truth(
    design: str,
    size: int,
    slant: float,
    blur: float,
    noise: float,
    centre_tol: float,
    axis_tol: float,
) -> None:
    """The pose circle is recovered to a few hundredths of a pixel in centre and axes from a
    coarse seed; the other printed circles (at least 3 px semi-minor axis) to within 0.25 px:
    on small targets, code sectors close to them bias them slightly."""
    scene = _scene(design, size, slant, blur, noise, seed=11)
    rng = np.random.default_rng(5)
    checked = 0
    for k, (circle, conic) in enumerate(
        zip(get_design(design).circles, scene.truth[0].conics, strict=True)
    ):
        truth = _truth(conic)
        if truth[3] < 3.0:
            continue
        if k > 0:
            centre_tol, axis_tol = max(centre_tol, 0.25), max(axis_tol, 0.25)
        e = fit_ellipse(
            scene.image,
            _perturbed_seed(truth, rng),
            radius=circle.radius,
            dark_inside=circle.dark_inside,
        )
        assert e is not None
        assert e.radius == circle.radius
        assert np.hypot(e.center_px[0] - truth[0], e.center_px[1] - truth[1]) < centre_tol
        assert abs(e.semi_major - truth[2]) < axis_tol
        assert abs(e.semi_minor - truth[3]) < axis_tol
        if truth[2] - truth[3] > 1.0:
            # A nearly round ellipse's angle is loosely measured: its own sd says how loosely.
            d_ang = (e.angle - truth[4] + np.pi / 2) % np.pi - np.pi / 2
            assert abs(d_ang) < max(0.01, 4.0 * np.sqrt(e.covariance[4, 4]))
        assert e.semi_major >= e.semi_minor > 0 and 0 <= e.angle < np.pi
        checked += 1
    assert checked >= 1


@pytest.mark.parametrize(
    ("design", "size", "slant", "blur", "noise"),
    [("ring", 60, 40, 0.7, 0.02), ("dot", 60, 0, 0.5, 0.01)],
)
def test_covariance_predicts_the_scatter(
    design: str, size: int, slant: float, blur: float, noise: float
) -> None:
    """Predicted centre std agrees with the std over 30 noise realisations within 30 %.

    The pose estimator weights fiducials by these covariances, so they must be honest.
    """
    circle = get_design(design).pose_circle
    truth = _truth(_scene(design, size, slant, blur, 0.0, seed=0).truth[0].conics[0])
    seed = _perturbed_seed(truth, np.random.default_rng(3))
    centres, predicted, covs = [], [], []
    for rep in range(30):
        scene = _scene(design, size, slant, blur, noise, seed=100 + rep)
        e = fit_ellipse(scene.image, seed, radius=circle.radius, dark_inside=circle.dark_inside)
        assert e is not None
        centres.append(e.center_px)
        covs.append(e.covariance)
        predicted.append(np.sqrt(np.diag(e.covariance)[:2]))
    empirical = np.std(np.array(centres), axis=0, ddof=1)
    ratio = empirical / np.mean(predicted, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio
    # The covariance is a proper one: symmetric, positive definite.
    cov = covs[-1]
    assert np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_batched_fit_equals_single_fits_and_roi_origin() -> None:
    """``fit_ellipses`` gives the single fits' answers; an ROI crop with ``origin`` gives the same
    full-image coordinates."""
    design = get_design("ring")
    scene = _scene("ring", 60, 35, 0.5, 0.01, seed=2)
    truths = [_truth(c) for c in scene.truth[0].conics]
    rng = np.random.default_rng(8)
    seeds = [_perturbed_seed(t, rng) for t in truths]
    radii = [c.radius for c in design.circles]
    polarity = [c.dark_inside for c in design.circles]
    batch = fit_ellipses(scene.image, seeds, radii, dark_inside=polarity)
    u0, v0 = 9, 7
    crop = scene.image[v0:-5, u0:-4]
    for seed, r, pol, b in zip(seeds, radii, polarity, batch, strict=True):
        one = fit_ellipse(scene.image, seed, radius=r, dark_inside=pol)
        roi = fit_ellipse(crop, seed, radius=r, dark_inside=pol, origin=(u0, v0))
        assert one is not None and b is not None and roi is not None
        assert np.allclose(b.center_px, one.center_px, atol=1e-9)
        assert np.allclose(b.covariance, one.covariance, rtol=1e-6)
        assert np.allclose(roi.center_px, one.center_px, atol=1e-3)
        assert roi.semi_major == pytest.approx(one.semi_major, abs=1e-3)
    # Without covariances: the same ellipses, covariance left NaN.
    bare = fit_ellipses(scene.image, seeds, radii, dark_inside=polarity, covariance=False)
    for b, g in zip(batch, bare, strict=True):
        assert b is not None and g is not None
        assert g.center_px == b.center_px and g.semi_minor == b.semi_minor
        assert np.all(np.isnan(g.covariance))


def test_seed_from_boundary_points() -> None:
    """Boundary points (e.g. a thresholded component's contour) seed the fit as well."""
    scene = _scene("dot", 60, 20, 0.5, 0.01, seed=4)
    truth = _truth(scene.truth[0].conics[0])
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    u, v, a, b, ang = truth
    # Points on a shrunk, shifted ellipse, as a pixel contour would be.
    x, y = (a - 0.5) * np.cos(t), (b - 0.5) * np.sin(t)
    pts = np.column_stack(
        [u + 0.3 + x * np.cos(ang) - y * np.sin(ang), v - 0.2 + x * np.sin(ang) + y * np.cos(ang)]
    )
    e = fit_ellipse(scene.image, np.round(pts), radius=0.3)
    assert e is not None
    assert np.hypot(e.center_px[0] - u, e.center_px[1] - v) < 0.03


def test_gradients_argument_gives_the_same_fit() -> None:
    """Precomputed Scharr gradients (intensity per pixel) are used as given."""
    import cv2

    scene = _scene("dot", 60, 20, 0.5, 0.01, seed=4)
    truth = _truth(scene.truth[0].conics[0])
    seed = _perturbed_seed(truth, np.random.default_rng(1))
    img = scene.image.astype(np.float32)
    grads = (cv2.Scharr(img, cv2.CV_32F, 1, 0) / 32, cv2.Scharr(img, cv2.CV_32F, 0, 1) / 32)
    a = fit_ellipse(scene.image, seed, radius=0.3)
    b = fit_ellipse(scene.image, seed, radius=0.3, gradients=grads)
    assert a is not None and b is not None
    assert np.allclose(a.center_px, b.center_px, atol=1e-5)


def test_degenerate_inputs_give_none() -> None:
    """No edge, too small an image, a seed off the image or NaN pixels: None, not a guess."""
    seed = Ellipse((30.0, 30.0), 10.0, 8.0, 0.3, np.zeros((5, 5)), 1.0)
    flat = np.full((64, 64), 100, np.uint8)
    assert fit_ellipse(flat, seed, radius=1.0) is None
    assert fit_ellipse(np.zeros((4, 4)), seed, radius=1.0) is None
    far = Ellipse((500.0, 500.0), 10.0, 8.0, 0.3, np.zeros((5, 5)), 1.0)
    scene = _scene("dot", 60, 0, 0.5, 0.01, seed=1)
    assert fit_ellipse(scene.image, far, radius=1.0) is None
    truth = _truth(scene.truth[0].conics[0])
    good = Ellipse((truth[0], truth[1]), truth[2], truth[3], truth[4], np.zeros((5, 5)), 0.3)
    nan_img = scene.image.astype(np.float64)
    nan_img[int(truth[1]), :] = np.nan
    assert fit_ellipse(nan_img, good, radius=0.3) is None
    assert fit_ellipse(scene.image, np.zeros((3, 2)), radius=0.3) is None
    assert fit_ellipses(scene.image, [], []) == []


def test_caller_mistakes_raise() -> None:
    seed = Ellipse((30.0, 30.0), 10.0, 8.0, 0.3, np.zeros((5, 5)), 1.0)
    with pytest.raises(DetectorError, match="2-D"):
        fit_ellipse(np.zeros((8, 8, 3)), seed, radius=1.0)
    with pytest.raises(DetectorError, match="N, 2"):
        fit_ellipse(np.zeros((64, 64)), np.zeros((10, 3)), radius=1.0)
    with pytest.raises(DetectorError, match="band_px"):
        fit_ellipse(np.zeros((64, 64)), seed, radius=1.0, band_px=0.1)
    with pytest.raises(DetectorError, match="radii"):
        fit_ellipses(np.zeros((64, 64)), [seed, seed], [1.0, 0.5, 0.3])
    with pytest.raises(DetectorError, match="gradients"):
        fit_ellipse(np.zeros((64, 64)), seed, radius=1.0, gradients=(np.zeros((3, 3)),) * 2)


@pytest.mark.parametrize("noise", [0.01, 0.02])
def test_noise_estimate(noise: float) -> None:
    """The image-noise estimate that scales the covariance is within 10 % of the truth."""
    scene = _scene("ring", 60, 30, 0.5, noise, seed=6)
    assert estimate_noise(scene.image) == pytest.approx(noise * 255, rel=0.1)


def test_median_by_counting_is_numpys() -> None:
    """The noise estimate's median of an integer image's responses, by counting, is
    ``np.median``'s to the bit: odd and even counts, heavy ties, one value, a long tail."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 10, 11, 999, 1000, 36_000):
        for spread in (0, 2, 40, 4080):
            values = np.abs(rng.integers(-spread, spread + 1, n)).astype(np.float32)
            values[: n // 7] = 4080.0
            assert _median(values, integral=True) == float(np.median(values))
    fractional = rng.random(101).astype(np.float32)
    assert _median(fractional, integral=False) == float(np.median(fractional))


def test_polarity_vote_picks_the_seeded_edge_of_a_thin_annulus() -> None:
    """Without ``dark_inside`` the nearest edge's polarity wins: the ring's two annulus edges
    (opposite polarities, 0.2 R apart) are each found from their own seed."""
    design = get_design("ring")
    scene = _scene("ring", 45, 30, 0.7, 0.01, seed=3)
    rng = np.random.default_rng(4)
    for circle, conic in zip(design.circles[:2], scene.truth[0].conics[:2], strict=True):
        truth = _truth(conic)
        seed = _perturbed_seed(truth, rng)
        voted = fit_ellipse(scene.image, seed, radius=circle.radius)
        given = fit_ellipse(scene.image, seed, radius=circle.radius, dark_inside=circle.dark_inside)
        assert voted is not None and given is not None
        assert np.allclose(voted.center_px, given.center_px, atol=1e-9)
        assert abs(voted.semi_major - truth[2]) < 0.1
