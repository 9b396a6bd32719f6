"""The renderer's images against its ground truth: areas, edges on the truth conics, lens
distortion, blur and noise statistics, transparency and reproducibility."""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.stats import norm

from armourcam.render import (
    BACKGROUND,
    BLACK,
    WHITE,
    Patch,
    RenderError,
    Target,
    fiducial_patch,
    reflectance_image,
    render,
    rotation_from_slant_tilt,
)
from fiducial_detector.codebook import code_bits
from fiducial_detector.design import get_design
from pose_estimator.camera import CameraModel

FULL16 = 65535.0
FACE = np.diag([1.0, -1.0, -1.0])  # fronto-parallel, upright


def _camera(distorted: bool, width: int = 400, height: int = 300) -> CameraModel:
    K = np.array([[900.0, 0.0, 203.4], [0.0, 900.0, 148.7], [0.0, 0.0, 1.0]])
    D = np.array([-0.35, 0.2, 0.002, -0.001, 0.0]) if distorted else np.zeros(5)
    return CameraModel(width, height, K, "plumb_bob", D)


def _disc_patch(position: NDArray[np.float64], radius_mm: float, extent_mm: float) -> Patch:
    """A black disc on white paper, fronto-parallel."""

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where(np.hypot(x, y) < radius_mm, 0.0, 1.0)

    return Patch(FACE, position, extent_mm, f)


def _at_pixel(camera: CameraModel, u: float, v: float, z: float) -> NDArray[np.float64]:
    """Camera-frame point at depth z that images at distorted pixel (u, v)."""
    xy = camera.undistort_normalized([[u, v]])[0]
    return np.array([xy[0] * z, xy[1] * z, z])


def _darkness(img: NDArray[np.generic]) -> NDArray[np.float64]:
    """Per-pixel black fraction of a noise-free uint16 render of black on white."""
    return (WHITE - img.astype(np.float64) / FULL16) / (WHITE - BLACK)


def test_fronto_parallel_disc_area_is_exact() -> None:
    """The summed darkness of a rendered disc equals its analytic area in pixels."""
    camera = _camera(False)
    z, rho = 200.0, 4.0  # 18 px radius
    position = np.array([0.37, -0.61, z])  # centre off the pixel grid
    scene = render(camera, clutter=[_disc_patch(position, rho, 3 * rho)], dtype=np.uint16)
    centre = camera.project(position.reshape(1, 3))[0]
    vv, uu = np.mgrid[: camera.height, : camera.width]
    window = np.hypot(uu - centre[0], vv - centre[1]) < 2.0 * rho * 900.0 / z
    area = _darkness(scene.image)[window].sum()
    r_px = rho * 900.0 / z
    assert area == pytest.approx(np.pi * r_px**2, rel=1e-3)


@pytest.mark.parametrize("name", ["dot", "ring"])
def test_fiducial_black_area_matches_design(name: str) -> None:
    """A fronto-parallel fiducial's rendered black area is the design's analytic black area."""
    camera = _camera(False)
    design = get_design(name)
    code = 23
    z = 900.0 * 7.1 / 120.0  # 120 px across
    target = Target(code, name, 7.1, FACE, np.array([0.2, 0.1, z]))
    scene = render(camera, [target], dtype=np.uint16)
    R = 60.0
    n_black = int(code_bits(code).sum())
    area = np.pi * design.dot_radius**2 + n_black / 16 * np.pi * (
        design.track_outer**2 - design.track_inner**2
    )
    if design.annulus_inner is not None:
        area += np.pi * (1.0 - design.annulus_inner**2)
    centre = scene.truth[0].center_px
    vv, uu = np.mgrid[: camera.height, : camera.width]
    window = np.hypot(uu - centre[0], vv - centre[1]) < 1.15 * R  # inside the white paper
    assert _darkness(scene.image)[window].sum() == pytest.approx(area * R**2, rel=2e-3)
    assert scene.truth[0].outer_diameter_px == pytest.approx(120.0)


def _edge_points(
    img: NDArray[np.float64],
    camera: CameraModel,
    conic: NDArray[np.float64],
    centre_ideal: NDArray[np.float64],
    dark_inside: bool,
    n: int = 48,
) -> NDArray[np.float64]:
    """Mid-level crossings of the image along rays from the centre, near where the rays meet the
    (ideal) conic; returned in ideal (undistorted) pixel coordinates."""
    pts = []
    mid = 0.5 * (WHITE + BLACK) * FULL16
    for phi in np.linspace(0.0, 2 * np.pi, n, endpoint=False):
        d = np.array([np.cos(phi), np.sin(phi)])
        # Ray-conic intersection in ideal pixels: p = c + s d, p^T C p = 0 (quadratic in s).
        c3, d3 = np.append(centre_ideal, 1.0), np.append(d, 0.0)
        a, b, cc = d3 @ conic @ d3, 2 * c3 @ conic @ d3, c3 @ conic @ c3
        s0 = (-b + np.sqrt(b * b - 4 * a * cc)) / (2 * a)
        s = s0 + np.arange(-2.0, 2.0, 0.01)
        ideal = centre_ideal + s[:, None] * d
        dist = camera.distort_normalized((ideal - camera.K[:2, 2]) / np.diag(camera.K)[:2])
        prof = cv2.remap(
            img.astype(np.float32),
            dist[:, 0].astype(np.float32)[None, :],
            dist[:, 1].astype(np.float32)[None, :],
            cv2.INTER_CUBIC,
        )[0].astype(np.float64)
        sign = 1.0 if dark_inside else -1.0
        cross = np.nonzero(sign * (prof[:-1] - mid) < 0)[0]
        cross = cross[sign * (prof[cross + 1] - mid) >= 0]
        assert cross.size == 1, "expected exactly one edge crossing near the truth conic"
        i = cross[0]
        t = (mid - prof[i]) / (prof[i + 1] - prof[i])
        pts.append(ideal[i] + t * (ideal[i + 1] - ideal[i]))
    return np.array(pts)


def _slanted_ring(z_mm: float = 520.0) -> tuple[CameraModel, Target]:
    """A 35 px ``ring`` fiducial slanted 50 deg, tilted and spun, off the pixel grid."""
    camera = CameraModel.ideal(70, 70, 2565.0, center=(34.6, 35.3))
    R = rotation_from_slant_tilt(np.radians(50.0), 0.3, 0.2)
    return camera, Target(23, "ring", 7.1, R, np.array([0.3, -0.2, z_mm]))


def test_edge_coverage_matches_dense_sampling() -> None:
    """Each ray's sub-square covered exactly by the edge through it: against 128 x 128 plainly
    sampled rays per pixel, 8 x 8 rays are within 0.006 of the contrast at every pixel and 4 x 4
    rays within a quarter of the summed error of 16 x 16 plain ones (which reach 0.01 at some
    pixel). The paper's own edge, plainly sampled, is hidden on a paper-white background."""
    camera, target = _slanted_ring()
    plain = dataclasses.replace(fiducial_patch(target), edges=None)

    def darkness(**kwargs: Any) -> NDArray[np.float64]:
        return _darkness(render(camera, dtype=np.uint16, background=WHITE, **kwargs).image)

    dense = darkness(clutter=[plain], supersample=128)

    def error(**kwargs: Any) -> NDArray[np.float64]:
        return np.abs(darkness(**kwargs) - dense)

    sampled = error(clutter=[plain], supersample=16)
    assert sampled.max() > 0.01
    assert error(targets=[target], supersample=8).max() < 0.006
    assert error(targets=[target], supersample=4).sum() < 0.25 * sampled.sum()


def test_image_is_continuous_in_the_pose() -> None:
    """The image changes in proportion to a small change of depth (what a fit to rendered images
    needs): steps of 1e-4 and 2e-4 mm give the same derivative image within 2 %, summed over
    the pixels."""
    camera, target = _slanted_ring()

    def at(dz: float) -> NDArray[np.float64]:
        t = target.position_mm + np.array([0.0, 0.0, dz])
        return reflectance_image(camera, dataclasses.replace(target, position_mm=t), supersample=4)

    base = at(0.0)
    small, large = ((at(h) - base) / h for h in (1e-4, 2e-4))
    assert np.abs(small).sum() > 0
    assert np.abs(small - large).sum() < 0.02 * np.abs(small).sum()


@pytest.mark.parametrize("distorted", [False, True])
@pytest.mark.parametrize("name", ["dot", "ring"])
def test_rendered_edges_lie_on_truth_conics(name: str, distorted: bool) -> None:
    """Every printed circle's rendered edge lies on its ground-truth conic (slanted target)."""
    camera = _camera(distorted, 640, 480)
    z = 900.0 * 7.1 / 200.0
    rotation = rotation_from_slant_tilt(np.radians(50.0), np.radians(30.0), 0.4)
    target = Target(5, name, 7.1, rotation, _at_pixel(camera, 420.0, 170.0, z))
    scene = render(camera, [target], blur_sigma=0.6, dtype=np.uint16)
    truth = scene.truth[0]
    img = scene.image.astype(np.float64)
    assert np.allclose(truth.center_px, camera.project(truth.position_mm.reshape(1, 3))[0])
    centre_ideal = camera.undistort_pixels(truth.center_px.reshape(1, 2))[0]
    for circle, conic in zip(get_design(name).circles, truth.conics, strict=True):
        pts = _edge_points(img, camera, conic, centre_ideal, circle.dark_inside)
        h = np.column_stack([pts, np.ones(len(pts))])
        grad = 2.0 * (h @ conic)[:, :2]
        geometric = np.einsum("ij,jk,ik->i", h, conic, h) / np.linalg.norm(grad, axis=1)
        # Sub-pixel agreement: no bias (a half-pixel convention slip would show as 0.5 px) and
        # a small scatter from interpolating the integrated, blurred pixels.
        assert abs(geometric.mean()) < 0.02, (circle, geometric.mean())
        assert np.abs(geometric).max() < 0.08, (circle, np.abs(geometric).max())


def test_distorted_point_lands_at_project() -> None:
    """A small dot rendered through lens distortion is centred where ``camera.project`` says."""
    camera = _camera(True)
    z = 300.0
    position = np.array([-60.0, 45.0, z])  # near the top-left corner: strong distortion
    uv = camera.project(position.reshape(1, 3))[0]
    ideal = camera.K[:2, :2] @ (position[:2] / z) + camera.K[:2, 2]
    assert np.hypot(*(uv - ideal)) > 3.0  # the test can tell distortion from none
    rho = 3.0 * z / 900.0  # ~3 px radius
    scene = render(camera, clutter=[_disc_patch(position, rho, 3 * rho)], dtype=np.uint16)
    dark = _darkness(scene.image)
    u0, v0 = np.rint(uv).astype(int)
    win = dark[v0 - 5 : v0 + 6, u0 - 5 : u0 + 6]  # inside the white paper (9 px radius)
    vv, uu = np.mgrid[v0 - 5 : v0 + 6, u0 - 5 : u0 + 6]
    centroid = np.array([(win * uu).sum(), (win * vv).sum()]) / win.sum()
    assert np.hypot(*(centroid - uv)) < 0.02


def _half_plane(edge_u_mm: float) -> Patch:
    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where(x < edge_u_mm, 0.0, 1.0)

    return Patch(FACE, np.array([0.0, 0.0, 100.0]), 1000.0, f)


@pytest.mark.parametrize("sigma", [0.0, 0.8, 1.5])
def test_blur_width_and_edge_position(sigma: float) -> None:
    """A straight edge's pixel differences spread with variance sigma^2 + 2/12 (the blur, the
    pixel's box and the difference's box) centred on the edge."""
    camera = _camera(False)
    edge_u = 200.3
    edge_mm = (edge_u - camera.K[0, 2]) * 100.0 / 900.0
    scene = render(camera, clutter=[_half_plane(edge_mm)], blur_sigma=sigma, dtype=np.uint16)
    prof = scene.image[150, 150:250].astype(np.float64) / FULL16
    u = np.arange(150, 250, dtype=np.float64)
    deriv = np.diff(prof)
    mid_u = 0.5 * (u[:-1] + u[1:])
    mean = (deriv * mid_u).sum() / deriv.sum()
    var = (deriv * (mid_u - mean) ** 2).sum() / deriv.sum()
    assert mean == pytest.approx(edge_u, abs=0.02)
    if sigma > 0:
        assert var == pytest.approx(sigma**2 + 2.0 / 12.0, rel=0.03)
    else:
        # No blur: only the edge pixel is partly covered, by exactly its white fraction.
        cover = (prof - BLACK) / (WHITE - BLACK)
        assert cover[50] == pytest.approx(0.2, abs=0.01)
        assert np.count_nonzero((cover > 1e-3) & (cover < 1 - 1e-3)) == 1
    assert prof[0] == pytest.approx(BLACK, abs=1e-4) and prof[-1] == pytest.approx(WHITE, abs=1e-4)


def _box_blurred_step(u: NDArray[np.float64], edge_u: float, sigma: float) -> NDArray[np.float64]:
    """White fraction of pixels ``u`` across a step at ``edge_u`` seen through a continuous
    Gaussian of sd ``sigma``, then each pixel's box: the integral of the normal cdf over the
    pixel (antiderivative ``t Phi(t) + phi(t)``)."""

    def anti(t: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(t * norm.cdf(t) + norm.pdf(t), dtype=np.float64)

    return sigma * (anti((u + 0.5 - edge_u) / sigma) - anti((u - 0.5 - edge_u) / sigma))


@pytest.mark.parametrize("subpixels", [6, 8])
def test_blur_on_subpixels_is_a_continuous_gaussian_then_the_pixel_box(subpixels: int) -> None:
    """With ``subpixels`` a straight edge's pixels are the step through a continuous Gaussian
    integrated over each pixel, to 1e-3 of the contrast at 0.5 px of blur from 6 sub-pixels per
    side; OpenCV's sampled kernel on the rendered pixels (the default) is off by 0.04 there."""
    camera = _camera(False)
    edge_u, sigma = 200.3, 0.5
    edge_mm = (edge_u - camera.K[0, 2]) * 100.0 / 900.0
    u = np.arange(190, 211, dtype=np.float64)
    exact = _box_blurred_step(u, edge_u, sigma)
    got = {}
    for s in (1, subpixels):
        scene = render(
            camera,
            clutter=[_half_plane(edge_mm)],
            blur_sigma=sigma,
            dtype=np.uint16,
            supersample=96,
            subpixels=s,
        )
        prof = scene.image[150, 190:211].astype(np.float64) / FULL16
        got[s] = (prof - BLACK) / (WHITE - BLACK)
    assert np.max(np.abs(got[subpixels] - exact)) < 1e-3
    assert np.max(np.abs(got[1] - exact)) > 0.02


def test_noise_statistics() -> None:
    """Additive noise has the asked standard deviation (fraction of full range) and zero mean."""
    camera = _camera(False)
    scene = render(
        camera,
        clutter=[_half_plane(-1e6)],  # all white paper
        noise=0.02,
        rng=np.random.default_rng(1234),
        dtype=np.uint16,
    )
    err = scene.image.astype(np.float64) / FULL16 - WHITE
    assert err.std() == pytest.approx(0.02, rel=0.03)
    assert abs(err.mean()) < 5e-4


def test_rng_reproducibility() -> None:
    """The same seed gives the same image; another seed gives another."""
    camera = _camera(False)
    target = Target(9, "ring", 7.1, FACE, np.array([0.0, 0.0, 60.0]))
    a = render(camera, [target], blur_sigma=0.5, noise=0.01, rng=np.random.default_rng(7)).image
    b = render(camera, [target], blur_sigma=0.5, noise=0.01, rng=np.random.default_rng(7)).image
    c = render(camera, [target], blur_sigma=0.5, noise=0.01, rng=np.random.default_rng(8)).image
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)


def test_transparent_parts_leave_the_background() -> None:
    """NaN reflectance is transparent: only the opaque square changes the image."""

    def square(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where((np.abs(x) < 2.0) & (np.abs(y) < 2.0), 0.0, np.nan)

    camera = _camera(False)
    patch = Patch(FACE, _at_pixel(camera, 100.0, 100.0, 90.0), 10.0, square)
    img = render(camera, clutter=[patch], dtype=np.uint16).image.astype(np.float64) / FULL16
    half = 2.0 * 900.0 / 90.0  # 20 px
    assert img[100, 100] == pytest.approx(BLACK, abs=1e-4)
    assert img[100, 100 + int(half) + 3] == pytest.approx(BACKGROUND, abs=1e-4)
    # Partial pixels along the square's border blend black with the background, not with white.
    row = img[100, 100 + int(half) - 2 : 100 + int(half) + 3]
    assert row.min() >= BLACK - 1e-4 and row.max() <= BACKGROUND + 1e-4


def test_occlusion_nearer_patch_wins() -> None:
    """Painter's order: the nearer patch covers the farther one whatever the order given."""
    camera = _camera(False)
    far = _disc_patch(np.array([0.0, 0.0, 200.0]), 100.0, 100.0)  # all black, big
    near = Patch(FACE, np.array([0.0, 0.0, 100.0]), 2.0, lambda x, y: np.ones_like(x))
    for order in ([far, near], [near, far]):
        img = render(camera, clutter=order, dtype=np.uint16).image.astype(np.float64) / FULL16
        assert img[148, 203] == pytest.approx(WHITE, abs=1e-4)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"blur_sigma": -1.0}, "blur_sigma"),
        ({"noise": -0.1}, "noise"),
        ({"supersample": 0}, "supersample"),
        ({"dtype": np.float32}, "dtype"),
        ({"white": 0.1, "black": 0.5}, "brighter"),
        ({"subpixels": 0}, "subpixels"),
    ],
)
def test_bad_parameters_raise(kwargs: dict[str, object], match: str) -> None:
    """Bad render parameters raise RenderError naming the parameter."""
    with pytest.raises(RenderError, match=match):
        render(_camera(False), **kwargs)  # type: ignore[arg-type]


def test_patch_behind_camera_raises() -> None:
    """A patch reaching behind the camera is refused."""
    rotation = rotation_from_slant_tilt(np.radians(80.0))
    target = Target(0, "dot", 7.1, rotation, np.array([0.0, 0.0, 2.0]))
    with pytest.raises(RenderError, match="behind the camera"):
        render(_camera(False), [target])
