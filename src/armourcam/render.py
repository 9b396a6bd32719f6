"""The synthetic scene renderer: planar printed patches seen by a calibrated pinhole camera.

This is armourcam's one renderer, used by tests, benchmarks, bag generation and the demo. Each
patch (a fiducial, or clutter such as a dark blob, a plain circle or a text-like mark) is a plane at
a known 3-D pose whose printed reflectance is a function of plane coordinates. For every pixel the
renderer traces rays through the pixel's area (pixel centres at integer coordinates, OpenCV's
convention), undistorting them through the lens model, intersects them with the patch plane and
averages the reflectance: area integration by supersampling, refined only where the pixel straddles
an edge. A fiducial's rays each stand for a sub-square of the pixel, covered exactly by the printed
edge nearest it (its distance and direction come from the design), so its image is accurate to
about 0.001 of the contrast with a few rays and changes continuously with the pose; clutter is
sampled plainly. Gaussian blur (defocus) and additive Gaussian noise as a fraction of the full
range follow, as in the paper's section 4.1. Ground truth comes with every image: projected
centres, the image conics of every printed circle, and the 3-D pose.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from fiducial_detector.design import (
    PAPER_RADIUS,
    FiducialDesign,
    get_design,
    reflectance,
    reflectance_near_edges,
)
from pose_estimator.camera import CameraModel

# Paper-white and toner-black levels as fractions of the sensor's full range.
WHITE = 0.85
BLACK = 0.12
BACKGROUND = 0.45
MARGIN = PAPER_RADIUS  # the white paper disc around a printed fiducial, in outer radii

ReflectanceFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]
_F64 = NDArray[np.float64]
EdgeReflectanceFn = Callable[[_F64, _F64], tuple[_F64, _F64, _F64, _F64]]


class RenderError(ValueError):
    """A scene cannot be rendered as asked (bad pose, size or parameter)."""


def rotation_from_slant_tilt(slant: float, tilt: float = 0.0, spin: float = 0.0) -> NDArray:
    """Rotation (target frame -> camera frame) of a target slanted away from the camera.

    Parameters
    ----------
    slant : float
        Angle between the target's normal and the direction towards the camera, radians.
    tilt : float
        Direction of the slant axis in the image plane, radians.
    spin : float
        In-plane rotation of the target about its own normal, radians.

    Returns
    -------
    (3, 3) ndarray
        At ``slant = tilt = spin = 0`` the target faces the camera upright:
        ``diag(1, -1, -1)`` (target y up appears as image up, the face looks at the camera).
    """
    face = np.diag([1.0, -1.0, -1.0])
    cs, ss = np.cos(spin), np.sin(spin)
    rz = np.array([[cs, -ss, 0.0], [ss, cs, 0.0], [0.0, 0.0, 1.0]])
    # Slant about an in-image axis at angle `tilt`: rotate about that axis in the camera frame.
    axis = np.array([np.cos(tilt), np.sin(tilt), 0.0])
    rs, _ = cv2.Rodrigues(axis * slant)
    return np.asarray(rs @ face @ rz, dtype=np.float64)


@dataclass(frozen=True, slots=True, eq=False)
class Patch:
    """A planar printed patch at a 3-D pose.

    Attributes
    ----------
    rotation : (3, 3) ndarray
        Patch frame -> camera frame; the patch lies in its frame's z = 0 plane, printed face +z.
    position_mm : (3,) ndarray
        Origin of the patch frame in the camera frame, mm.
    extent_mm : float
        Radius around the origin outside which the patch does not exist.
    reflectance : callable
        ``f(x_mm, y_mm) -> reflectance in [0, 1]`` over patch-frame millimetres (0 black, 1 white),
        or NaN where the patch is transparent (so patches need not be discs); points outside
        ``extent_mm`` are never asked for.
    edges : callable, optional
        ``f(x_mm, y_mm) -> (reflectance, distance_mm, normal_x, normal_y)``: the reflectance with
        the distance to (and unit normal of) the nearest edge across which it changes. Where
        given, each ray of a pixel straddling an edge stands for its sub-square of the pixel,
        split exactly by that edge (taken as straight across the sub-square), so the image
        changes continuously with the patch's pose instead of in steps of one ray: what a fit
        to rendered images needs.
    """

    rotation: NDArray[np.float64]
    position_mm: NDArray[np.float64]
    extent_mm: float
    reflectance: ReflectanceFn
    edges: EdgeReflectanceFn | None = None


@dataclass(frozen=True, slots=True, eq=False)
class TargetTruth:
    """Ground truth of one rendered fiducial.

    Attributes
    ----------
    code, design, diameter_mm
        What was printed.
    rotation, position_mm
        Pose (target frame -> camera frame; centre in mm).
    normal : (3,) ndarray
        Unit normal of the printed face in the camera frame.
    center_px : (2,) ndarray
        Projection (with distortion) of the fiducial's centre, pixels.
    conics : tuple of (3, 3) ndarray
        Ideal (undistorted) image conics of the design's printed circles, largest first.
    outer_diameter_px : float
        Imaged diameter of the outer printed circle, fronto-parallel equivalent
        (``f * diameter / z``).
    arc_conics : tuple of (3, 3) ndarray
        The same for the circles that carry the coding track's arcs (``FiducialDesign.arcs``).
    """

    code: int
    design: str
    diameter_mm: float
    rotation: NDArray[np.float64]
    position_mm: NDArray[np.float64]
    normal: NDArray[np.float64]
    center_px: NDArray[np.float64]
    conics: tuple[NDArray[np.float64], ...]
    outer_diameter_px: float
    arc_conics: tuple[NDArray[np.float64], ...] = ()


@dataclass(frozen=True, slots=True)
class Target:
    """A fiducial to render: what is printed and where it is."""

    code: int
    design: str
    diameter_mm: float
    rotation: NDArray[np.float64] = field(default_factory=lambda: np.diag([1.0, -1.0, -1.0]))
    position_mm: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 0.0, 800.0]))


@dataclass(frozen=True, slots=True, eq=False)
class RenderedScene:
    """A rendered image with its ground truth.

    Attributes
    ----------
    image : (H, W) ndarray of uint8 or uint16
    truth : tuple of TargetTruth
        One per fiducial, in the order given.
    camera : CameraModel
    """

    image: NDArray[np.generic]
    truth: tuple[TargetTruth, ...]
    camera: CameraModel


def fiducial_patch(target: Target) -> Patch:
    """The printed fiducial (with its white paper margin) as a renderable patch."""
    design = get_design(target.design)
    radius = target.diameter_mm / 2.0
    code = target.code

    def f(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return reflectance(design, code, x / radius, y / radius)

    def edges(x: _F64, y: _F64) -> tuple[_F64, _F64, _F64, _F64]:
        value, distance, nx, ny = reflectance_near_edges(design, code, x / radius, y / radius)
        return value, distance * radius, nx, ny

    return Patch(
        np.asarray(target.rotation, dtype=np.float64),
        np.asarray(target.position_mm, dtype=np.float64),
        MARGIN * radius,
        f,
        edges,
    )


def target_truth(camera: CameraModel, target: Target) -> TargetTruth:
    """Ground truth of a fiducial: projected centre, circle conics and pose."""
    design: FiducialDesign = get_design(target.design)
    R = np.asarray(target.rotation, dtype=np.float64)
    t = np.asarray(target.position_mm, dtype=np.float64)
    # Homography plane (x, y, 1) [mm] -> ideal pixels; a circle x^2 + y^2 = rho^2 maps to
    # C = H^-T diag(1, 1, -rho^2) H^-1.
    H = camera.K @ np.column_stack([R[:, 0], R[:, 1], t])
    Hinv = np.linalg.inv(H)

    def conic(radius: float) -> NDArray[np.float64]:
        rho = radius * target.diameter_mm / 2.0
        C = Hinv.T @ np.diag([1.0, 1.0, -rho * rho]) @ Hinv
        return np.asarray(C / np.sqrt(abs(np.linalg.det(C[:2, :2]))), dtype=np.float64)

    conics = [conic(c.radius) for c in design.circles]
    center = camera.project(t.reshape(1, 3))[0]
    return TargetTruth(
        code=target.code,
        design=target.design,
        diameter_mm=target.diameter_mm,
        rotation=R,
        position_mm=t,
        normal=R[:, 2].copy(),
        center_px=center,
        conics=tuple(conics),
        outer_diameter_px=float(camera.K[0, 0] * target.diameter_mm / t[2]),
        arc_conics=tuple(conic(c.radius) for c in design.arcs),
    )


def _patch_bbox(camera: CameraModel, patch: Patch) -> tuple[int, int, int, int] | None:
    """Pixel bounding box (u0, v0, u1, v1), inclusive-exclusive, or None when off-image."""
    ang = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)]) * patch.extent_mm
    pts = ring @ patch.rotation.T + patch.position_mm
    if np.any(pts[:, 2] <= 1e-6):
        raise RenderError("a patch reaches behind the camera")
    uv = camera.project(pts)
    u0 = max(int(np.floor(uv[:, 0].min())) - 2, 0)
    v0 = max(int(np.floor(uv[:, 1].min())) - 2, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + 3, camera.width)
    v1 = min(int(np.ceil(uv[:, 1].max())) + 3, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, v0, u1, v1


_Undistort = Callable[
    [NDArray[np.float64], NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]
]
# Spacing (pixels) of the lattice on which lens distortion is inverted exactly; in between it is
# interpolated bilinearly. The inverse mapping's curvature is ~1e-4 px per px^2 even for strong
# distortion, so the interpolation error (step^2 / 8 * curvature) stays below 1e-4 px, while the
# iterative inverse on every supersample would cost a hundred times more.
_UNDISTORT_STEP = 2.0


def supersample_offsets(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offsets ``(du, dv)`` from a pixel's centre of its ``n * n`` area samples.

    A multi-jittered pattern: one sample in each of the ``n x n`` sub-squares and, in addition,
    one in each of the ``n * n`` columns and rows of a ``n^2 x n^2`` grid, so an edge along a pixel
    row or column is resolved to ``1 / n^2`` of a pixel instead of ``1 / n`` (a regular grid's
    samples share only ``n`` distinct u values) with the same number of samples.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    du = (i * n + j + 0.5) / (n * n) - 0.5
    dv = (j * n + i + 0.5) / (n * n) - 0.5
    return du.ravel().astype(np.float64), dv.ravel().astype(np.float64)


def _undistorter(camera: CameraModel, box: tuple[int, int, int, int]) -> _Undistort:
    """Pixel -> ideal normalised coordinates over ``box`` (exact when there is no distortion)."""
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    if not camera.has_distortion:

        def ideal(
            u: NDArray[np.float64], v: NDArray[np.float64]
        ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
            return (u - cx) / fx, (v - cy) / fy

        return ideal
    u0, v0, u1, v1 = box
    step = _UNDISTORT_STEP
    gu = np.arange(u0 - 1.0, u1 + step, step)
    gv = np.arange(v0 - 1.0, v1 + step, step)
    mu, mv = np.meshgrid(gu, gv)
    grid = camera.undistort_normalized(np.column_stack([mu.ravel(), mv.ravel()]))
    gx = grid[:, 0].reshape(mu.shape)
    gy = grid[:, 1].reshape(mu.shape)

    def interpolated(
        u: NDArray[np.float64], v: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        fu = (u - gu[0]) / step
        fv = (v - gv[0]) / step
        i = np.clip(np.floor(fu).astype(np.int64), 0, len(gu) - 2)
        j = np.clip(np.floor(fv).astype(np.int64), 0, len(gv) - 2)
        a, b = fu - i, fv - j
        w00, w01, w10, w11 = (1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b
        x = w00 * gx[j, i] + w01 * gx[j, i + 1] + w10 * gx[j + 1, i] + w11 * gx[j + 1, i + 1]
        y = w00 * gy[j, i] + w01 * gy[j, i + 1] + w10 * gy[j + 1, i] + w11 * gy[j + 1, i + 1]
        return x, y

    return interpolated


def _plane_points(
    undistort: _Undistort, patch: Patch, u: _F64, v: _F64
) -> tuple[_F64, _F64, NDArray[np.bool_]]:
    """Patch-frame points ``(x, y)`` mm seen at pixel positions (u, v), flattened, and where the
    ray meets the patch (its plane in front of the camera, within its extent)."""
    x, y = undistort(u.ravel(), v.ravel())
    R, t = patch.rotation, patch.position_mm
    # Ray d = (x, y, 1) meets the plane n.(P - t) = 0 at P = s d, s = n.t / n.d; the plane point
    # is q = R^T (P - t), i.e. q_k = s (R^T d)_k - (R^T t)_k, written out per component.
    n = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = float(n @ t) / (n[0] * x + n[1] * y + n[2])
    hit = np.isfinite(s) & (s > 0)
    c = R.T @ t
    q0 = s * (R[0, 0] * x + R[1, 0] * y + R[2, 0]) - c[0]
    q1 = s * (R[0, 1] * x + R[1, 1] * y + R[2, 1]) - c[1]
    with np.errstate(invalid="ignore"):
        return q0, q1, hit & (q0 * q0 + q1 * q1 <= patch.extent_mm**2)


def _sample(
    undistort: _Undistort, patch: Patch, u: NDArray[np.float64], v: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Reflectance of ``patch`` seen at pixel positions (u, v), and where the patch is hit."""
    shape = u.shape
    q0, q1, inside = _plane_points(undistort, patch, u, v)
    value = np.zeros(q0.size)
    idx = np.flatnonzero(inside)
    if idx.size:
        refl = np.asarray(patch.reflectance(q0[idx], q1[idx]), dtype=np.float64)
        # NaN reflectance marks transparent parts of a patch (a blob's outside, a text mark).
        clear = np.isnan(refl)
        inside[idx[clear]] = False
        value[idx[~clear]] = refl[~clear]
    return value.reshape(shape), inside.reshape(shape)


def _sample_covering(
    undistort: _Undistort,
    patch: Patch,
    edges: EdgeReflectanceFn,
    u: _F64,
    v: _F64,
    supersample: int,
) -> tuple[_F64, NDArray[np.bool_]]:
    """As :func:`_sample` for ``(k, n)`` samples, row ``i`` the sub-square centres of one pixel
    (symmetric about its centre), each sample's value its sub-square's coverage by the printing
    on either side of the nearest edge (:attr:`Patch.edges`)."""
    shape = u.shape
    q0, q1, inside = _plane_points(undistort, patch, u, v)
    value = np.zeros(q0.size)
    idx = np.flatnonzero(inside)
    if idx.size:
        # Plane millimetres per pixel at each pixel (central differences over a pixel).
        cu = u.mean(axis=1, keepdims=True)
        cv = v.mean(axis=1, keepdims=True)
        du = np.array([[-0.5, 0.5, 0.0, 0.0]])
        dv = np.array([[0.0, 0.0, -0.5, 0.5]])
        p0, p1, _ = _plane_points(undistort, patch, cu + du, cv + dv)
        p0, p1 = p0.reshape(-1, 4), p1.reshape(-1, 4)
        per = shape[1]
        pix = idx // per
        j = np.stack(
            [p0[:, 1] - p0[:, 0], p1[:, 1] - p1[:, 0], p0[:, 3] - p0[:, 2], p1[:, 3] - p1[:, 2]],
            axis=1,
        )[pix]
        refl, dist, nx, ny = edges(q0[idx], q1[idx])
        # The edge in pixels: its normal (gu, gv) = d(plane distance)/d(u, v); the sample's
        # sub-square (side 1 / supersample, axis-aligned) is cut by it exactly (straight within
        # the sub-square): the covered share is the CDF at the edge's distance of the sum of two
        # uniforms, the square's extents along the edge's normal.
        gu = nx * j[:, 0] + ny * j[:, 1]
        gv = nx * j[:, 2] + ny * j[:, 3]
        rate = np.hypot(gu, gv)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = supersample * dist / rate
            w1 = np.maximum(np.abs(gu), np.abs(gv)) / rate
            w2 = np.minimum(np.abs(gu), np.abs(gv)) / rate
            own = np.where(
                t >= 0.5 * (w1 - w2),
                1.0 - np.square(np.maximum(0.5 * (w1 + w2) - t, 0.0)) / (2.0 * w1 * w2),
                0.5 + t / w1,
            )
        own = np.where(np.isfinite(own), np.clip(own, 0.5, 1.0), 1.0)
        value[idx] = refl * own + (1.0 - refl) * (1.0 - own)
    return value.reshape(shape), inside.reshape(shape)


def _render_patch(
    camera: CameraModel,
    patch: Patch,
    canvas: NDArray[np.float64],
    supersample: int,
) -> None:
    """Composite one patch onto ``canvas`` (reflectance units), area-integrating each pixel."""
    box = _patch_bbox(camera, patch)
    if box is None:
        return
    u0, v0, u1, v1 = box
    undistort = _undistorter(camera, box)
    # Probe a half-pixel lattice covering the box; pixels whose 3x3 probes disagree straddle an
    # edge (or the patch border) and get the full supersampling, the rest take the probe value.
    h, w = v1 - v0, u1 - u0
    pu = u0 - 0.5 + 0.5 * np.arange(2 * w + 1)
    pv = v0 - 0.5 + 0.5 * np.arange(2 * h + 1)
    gu, gv = np.meshgrid(pu, pv)
    val, hit = _sample(undistort, patch, gu, gv)
    code = np.where(hit, val, -1.0)
    centre = code[1::2, 1::2]
    uniform = np.ones((h, w), dtype=bool)
    for dy in range(3):
        for dx in range(3):
            if dy != 1 or dx != 1:
                uniform &= code[dy : dy + 2 * h : 2, dx : dx + 2 * w : 2] == centre
    region = canvas[v0:v1, u0:u1]
    take = uniform & (centre >= 0)
    region[take] = centre[take]
    rows, cols = np.nonzero(~uniform)
    if rows.size == 0:
        return
    if patch.edges is None:
        ou, ov = supersample_offsets(supersample)
    else:
        # Sub-squares' centres: their exact coverages add up to the pixel's.
        ou, ov = (
            a.ravel()
            for a in np.meshgrid(*2 * [(np.arange(supersample) + 0.5) / supersample - 0.5])
        )
    su = (cols + u0)[:, None] + ou[None, :]
    sv = (rows + v0)[:, None] + ov[None, :]
    if patch.edges is None:
        sval, shit = _sample(undistort, patch, su, sv)
    else:
        sval, shit = _sample_covering(undistort, patch, patch.edges, su, sv, supersample)
    n_hit = shit.sum(axis=1)
    cover = n_hit / shit.shape[1]
    inside_mean = np.where(shit, sval, 0.0).sum(axis=1) / np.maximum(n_hit, 1)
    # Partial coverage at the patch border blends with what is already on the canvas.
    region[rows, cols] = cover * inside_mean + (1.0 - cover) * region[rows, cols]


def reflectance_image(
    camera: CameraModel, target: Target, *, supersample: int = 8, fill: float = 1.0
) -> NDArray[np.float64]:
    """Area-integrated printed reflectance of one fiducial over the camera's image (0 black,
    1 white; ``fill`` where the fiducial's paper is not seen): what :func:`render` draws before
    the levels, blur and noise. The model that :mod:`pose_estimator.image_fit` fits."""
    canvas = np.full((camera.height, camera.width), fill, dtype=np.float64)
    _render_patch(camera, fiducial_patch(target), canvas, supersample)
    return canvas


def defocus(image: NDArray[np.floating[Any]], sigma: float) -> NDArray[np.float64]:
    """The camera's blur as every synthetic image gets it by default: a Gaussian of sd ``sigma``
    pixels (OpenCV's sampled kernel, edges reflected), the paper's protocol.

    On an image whose pixels are already integrated this is not what optics then pixels make:
    the kernel's taps sit at whole pixels, so below about one pixel of blur it is far from a
    Gaussian (at 0.5 px its variance is 0.215 px^2, not 0.25, and its tails are light). A thin
    oblique annulus then renders darker than any Gaussian blur makes it, and a fit of both its
    edges widens it by up to 0.013 px at 35 px across (0.002 px after :func:`defocus_subpixels`
    on 3 sub-pixels).
    """
    return np.asarray(
        cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REFLECT), dtype=np.float64
    )


def defocus_subpixels(
    image: NDArray[np.floating[Any]], sigma: float, factor: int
) -> NDArray[np.float64]:
    """Blur as optics, then pixels, make it: ``image`` rendered on ``factor`` x ``factor``
    sub-pixels per pixel is blurred there (sd ``factor * sigma`` sub-pixels) and each block
    averaged. The sub-pixels' own squares and the block mean together integrate each pixel's
    square, so the result is the scene through a Gaussian, then the pixel's box, but for the
    kernel's steps of ``1 / factor`` px: errors of order ``factor^-2`` (a step's pixels at 0.5 px
    of blur within 0.003 of the contrast with 3 sub-pixels, 0.0005 with 8; OpenCV's sampled
    kernel on the pixels is 0.04 off).

    Parameters
    ----------
    image : (factor * H, factor * W) ndarray
        Intensities on the sub-pixel grid (sub-pixel ``i`` of pixel ``p`` centred at
        ``p + (i + 1/2) / factor - 1/2``).
    sigma : float
        Blur sd, pixels (0: only the block mean).
    factor : int
        Sub-pixels per pixel side; 1: ``image`` is on the pixels, blurred by :func:`defocus`.
    """
    if factor < 1:
        raise RenderError(f"factor must be >= 1, got {factor}")
    img = np.asarray(image, dtype=np.float64)
    if sigma > 0:
        img = defocus(img, sigma * factor)
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    out = img[: h * factor, : w * factor].reshape(h, factor, w, factor).mean(axis=(1, 3))
    return np.asarray(out, dtype=np.float64)


def subpixel_rays(supersample: int, factor: int) -> int:
    """Rays per sub-pixel side at edges, for ``supersample`` per pixel side on ``factor`` x
    ``factor`` sub-pixels (at least one)."""
    return max(1, -(-supersample // factor))


def subpixel_camera(camera: CameraModel, factor: int) -> CameraModel:
    """``camera`` with ``factor`` x ``factor`` sub-pixels per pixel (the grid of
    :func:`defocus_subpixels`): focal lengths scaled, pixel ``p``'s sub-pixels centred at
    ``p + (i + 1/2) / factor - 1/2``, the same lens distortion."""
    K = camera.K.copy()
    K[0, 0] *= factor
    K[1, 1] *= factor
    K[0, 2] = factor * (K[0, 2] + 0.5) - 0.5
    K[1, 2] = factor * (K[1, 2] + 0.5) - 0.5
    return CameraModel(
        camera.width * factor, camera.height * factor, K, camera.distortion_model, camera.D
    )


def render(
    camera: CameraModel,
    targets: Sequence[Target] = (),
    *,
    clutter: Sequence[Patch] = (),
    blur_sigma: float = 0.0,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
    supersample: int = 8,
    background: float = BACKGROUND,
    white: float = WHITE,
    black: float = BLACK,
    dtype: type[np.unsignedinteger] = np.uint8,
    subpixels: int = 1,
) -> RenderedScene:
    """Render fiducials and clutter into one image with ground truth.

    Parameters
    ----------
    camera : CameraModel
        Image size, intrinsics and lens distortion.
    targets : sequence of Target
        Fiducials to draw.
    clutter : sequence of Patch
        Other printed things in the scene (drawn before the fiducials, farthest first).
    blur_sigma : float
        Standard deviation of the Gaussian defocus blur, pixels (0 for none).
    noise : float
        Standard deviation of the additive Gaussian noise as a fraction of the full range.
    rng : numpy.random.Generator, optional
        Noise source (required when ``noise > 0`` for reproducible tests; a fresh one otherwise).
    supersample : int
        Samples per pixel side where a pixel straddles an edge (``supersample**2`` rays).
    background, white, black : float
        Scene background, paper-white and toner-black levels as fractions of the full range.
    dtype : {numpy.uint8, numpy.uint16}
        Output sample type.
    subpixels : int
        1 (default): the blur is OpenCV's sampled kernel on the rendered pixels (:func:`defocus`,
        the paper's protocol). ``S > 1``: the scene is rendered on ``S`` x ``S`` sub-pixels per
        pixel and blurred there (:func:`defocus_subpixels`: a Gaussian, then each pixel's
        box, to order ``S^-2``), with ``supersample / S`` rays per sub-pixel side at edges.

    Returns
    -------
    RenderedScene
    """
    if blur_sigma < 0 or noise < 0 or supersample < 1:
        raise RenderError(
            f"blur_sigma, noise must be >= 0 and supersample >= 1 "
            f"(got {blur_sigma}, {noise}, {supersample})"
        )
    if dtype not in (np.uint8, np.uint16):
        raise RenderError(f"dtype must be uint8 or uint16, got {dtype}")
    if subpixels < 1:
        raise RenderError(f"subpixels must be >= 1, got {subpixels}")
    grid = camera if subpixels == 1 else subpixel_camera(camera, subpixels)
    if not white > black:
        raise RenderError(f"white ({white}) must be brighter than black ({black})")
    # The canvas holds reflectance; the background is the reflectance that maps to the
    # background level, so that a pixel partly covered by a patch blends with the background
    # (the mapping to intensity is affine, so blending before or after it is the same).
    canvas = np.full(
        (grid.height, grid.width), (background - black) / (white - black), dtype=np.float64
    )
    # Painter's algorithm, farthest first, so nearer patches occlude farther ones.
    patches = list(clutter) + [fiducial_patch(t) for t in targets]
    patches.sort(key=lambda p: -float(p.position_mm[2]))
    rays = subpixel_rays(supersample, subpixels)
    for patch in patches:
        _render_patch(grid, patch, canvas, rays)
    # Reflectance -> intensity: black..white (the background level where nothing is printed).
    img: NDArray[np.float64] = black + (white - black) * canvas
    img = defocus_subpixels(img, blur_sigma, subpixels)
    if noise > 0:
        gen = rng if rng is not None else np.random.default_rng()
        img = img + gen.normal(0.0, noise, img.shape)
    full = float(np.iinfo(dtype).max)
    out = np.clip(np.rint(img * full), 0, full).astype(dtype)
    truth = tuple(target_truth(camera, t) for t in targets)
    return RenderedScene(out, truth, camera)
