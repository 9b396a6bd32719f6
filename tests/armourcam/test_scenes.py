"""Whole scenes: no overlaps, all in frame, slants and codes as asked; the paper's cameras."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from armourcam.render import MARGIN, WHITE, render
from armourcam.scenes import (
    CLUTTER_KINDS,
    PAPER_FOCAL_PX,
    SceneError,
    SceneLayout,
    clutter_patch,
    distance_for_size,
    grid_layout,
    grid_scene,
    paper_camera,
    random_layout,
    random_scene,
    table3_camera,
)
from pose_estimator.camera import CameraModel


def _outline(
    camera: CameraModel, rotation: NDArray[np.float64], position: NDArray[np.float64], r: float
) -> NDArray[np.float64]:
    """Image of a disc's boundary (radius ``r`` mm in its plane), 360 points."""
    ang = np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)]) * r
    return camera.project(ring @ rotation.T + position)


def _coverage(camera: CameraModel, layout: SceneLayout) -> NDArray[np.int32]:
    """How many items (paper margin included) cover each pixel, rasterised independently."""
    count = np.zeros((camera.height, camera.width), np.int32)
    items = [(t.rotation, t.position_mm, MARGIN * t.diameter_mm / 2) for t in layout.targets]
    items += [(p.rotation, p.position_mm, p.extent_mm) for p in layout.clutter]
    for rotation, position, r in items:
        uv = _outline(camera, rotation, position, r)
        u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 1
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        assert u0 >= -1 and v0 >= -1 and u1 <= camera.width + 2 and v1 <= camera.height + 2
        u0, v0 = max(u0, 0), max(v0, 0)
        layer = np.zeros((v1 - v0, u1 - u0), dtype=np.uint8)
        poly = np.rint((uv - [u0, v0]) * 16).astype(np.int32)
        cv2.fillPoly(layer, [poly], 1, lineType=cv2.LINE_8, shift=4)
        count[v0:v1, u0:u1] += layer[: camera.height - v0, : camera.width - u0]
    return count


def _slant(rotation: NDArray[np.float64], position: NDArray[np.float64]) -> float:
    """Angle (degrees) between a patch's normal and the direction to the camera."""
    to_camera = -position / np.linalg.norm(position)
    return float(np.degrees(np.arccos(np.clip(rotation[:, 2] @ to_camera, -1.0, 1.0))))


def test_paper_cameras() -> None:
    """The benchmark camera (f = 6507 px) and the Table 3 camera (45 mm / 7.8 um)."""
    cam = paper_camera()
    assert (cam.width, cam.height) == (3008, 2000)
    assert cam.K[0, 0] == cam.K[1, 1] == PAPER_FOCAL_PX == 6507.0
    assert not cam.has_distortion
    assert distance_for_size(60.0) == pytest.approx(6507.0 * 7.1 / 60.0)
    assert distance_for_size(35.0) == pytest.approx(1320.0, abs=0.1)  # the paper's 35 px
    t3 = table3_camera()
    assert (t3.width, t3.height) == (3008, 2000)
    assert t3.K[0, 0] == pytest.approx(45.0 / 0.0078)
    with pytest.raises(SceneError, match="positive"):
        distance_for_size(0.0)


def test_size_px_is_the_imaged_outer_diameter() -> None:
    """A target laid out at ``size_px`` is imaged that many pixels across its outer circle."""
    cam = paper_camera(400, 300)
    rng = np.random.default_rng(5)
    layout = grid_layout(cam, 1, 1, 120.0, "ring", rng, clutter=False)
    scene = render(cam, layout.targets, dtype=np.uint16)
    truth = scene.truth[0]
    assert truth.outer_diameter_px == pytest.approx(120.0)
    # Measured: the outer edge along the row through the centre (ring design: black to 1.0).
    u, v = truth.center_px
    row = scene.image[round(v)].astype(np.float64) / 65535.0
    mid = 0.5 * (WHITE + 0.12)
    cols = np.arange(cam.width)
    dark = np.nonzero((row < mid) & (np.abs(cols - u) < 70.0))[0]  # on the paper disc
    left, right = dark.min(), dark.max()
    # Sub-pixel crossings by linear interpolation on both sides.
    xl = left - (mid - row[left]) / (row[left - 1] - row[left])
    xr = right + (mid - row[right]) / (row[right + 1] - row[right])
    assert xr - xl == pytest.approx(120.0, abs=0.1)
    assert 0.5 * (xl + xr) == pytest.approx(u, abs=0.05)


def test_400_targets_on_a_full_frame_without_overlap() -> None:
    """The benchmark layout: 400 targets of 60 px plus clutter, none overlapping, all in frame."""
    cam = paper_camera()
    layout = random_layout(cam, 400, 60.0, ("dot", "ring"), np.random.default_rng(1234), 70.0)
    assert len(layout.targets) == 400 and len(layout.clutter) == 200
    count = _coverage(cam, layout)
    assert count.max() == 1  # no pixel covered twice
    for t in layout.targets:
        uv = _outline(cam, t.rotation, t.position_mm, MARGIN * t.diameter_mm / 2)
        assert uv.min() >= 0 and uv[:, 0].max() <= cam.width - 1 and uv[:, 1].max() <= 1999
    codes = {t.code for t in layout.targets}
    assert len(codes) > 50 and min(codes) >= 0 and max(codes) <= 65
    assert {t.design for t in layout.targets} == {"dot", "ring"}
    slants = [_slant(t.rotation, t.position_mm) for t in layout.targets]
    assert max(slants) <= 70.0 + 1e-9 and max(slants) > 65.0 and min(slants) < 5.0
    assert set(layout.clutter_kinds) == set(CLUTTER_KINDS)


def test_layout_through_lens_distortion() -> None:
    """With barrel distortion too, targets land where asked, inside the frame, apart."""
    ideal = paper_camera(1200, 800)
    cam = CameraModel(1200, 800, ideal.K, "plumb_bob", np.array([-0.4, 0.2, 1e-3, -1e-3, 0.0]))
    layout = random_layout(cam, 40, 60.0, "ring", np.random.default_rng(8), 60.0, n_clutter=20)
    assert _coverage(cam, layout).max() == 1
    for t in layout.targets:
        uv = _outline(cam, t.rotation, t.position_mm, MARGIN * t.diameter_mm / 2)
        assert uv.min() >= 0 and uv[:, 0].max() <= 1199 and uv[:, 1].max() <= 799
    scene = render(cam, layout.targets, clutter=layout.clutter)
    for t in scene.truth:
        u, v = np.rint(t.center_px).astype(int)
        assert scene.image[v, u] < 60  # the central dot is where the truth says


def test_layout_is_reproducible() -> None:
    """Same seed, same layout; another seed, another."""
    cam = paper_camera(1200, 800)

    def positions(seed: int) -> NDArray[np.float64]:
        lay = random_layout(cam, 30, 60.0, "dot", np.random.default_rng(seed), 60.0)
        return np.array([t.position_mm for t in lay.targets])

    np.testing.assert_array_equal(positions(3), positions(3))
    assert not np.array_equal(positions(3), positions(4))


def test_random_scene_truth_matches_image() -> None:
    """Rendered scene: each fiducial's centre is dark (its central dot), clutter adds dark
    pixels outside the fiducials, and no clutter means white or background there."""
    cam = paper_camera(800, 600)
    with_clutter = random_scene(
        cam, 12, 60.0, "dot", np.random.default_rng(9), 50.0, True, n_clutter=12
    )
    without = random_scene(cam, 12, 60.0, "dot", np.random.default_rng(9), 50.0, False)
    for scene in (with_clutter, without):
        assert len(scene.truth) == 12
        for t in scene.truth:
            u, v = np.rint(t.center_px).astype(int)
            assert scene.image[v, u] < 60  # the black central dot
            assert 0 <= t.center_px[0] <= cam.width - 1 and 0 <= t.center_px[1] <= cam.height - 1
    lay = random_layout(cam, 12, 60.0, "dot", np.random.default_rng(9), 50.0, True, n_clutter=12)
    targets_only = SceneLayout(lay.targets, (), (), lay.footprints_px)
    outside = _coverage(cam, targets_only) == 0
    # (the same seed gives the same layout as the rendered scene's)
    assert np.count_nonzero(with_clutter.image[outside] < 90) > 200
    assert np.count_nonzero(without.image[outside] < 90) == 0


def test_grid_scene_with_a_slant_sweep() -> None:
    """A grid with explicit slants: each target's slant from its line of sight is as given."""
    cam = paper_camera(1000, 700)
    sweep = [0.0, 20.0, 45.0, 60.0, 75.0, 85.0]
    layout = grid_layout(cam, 2, 3, 90.0, "ring", np.random.default_rng(2), slants_deg=sweep)
    got = [_slant(t.rotation, t.position_mm) for t in layout.targets]
    np.testing.assert_allclose(got, sweep, atol=1e-5)
    assert _coverage(cam, layout).max() == 1
    scene = grid_scene(
        cam, 2, 3, 90.0, "ring", np.random.default_rng(2), slants_deg=sweep, noise=0.01
    )
    assert scene.image.shape == (700, 1000) and len(scene.truth) == 6


@pytest.mark.parametrize("kind", CLUTTER_KINDS)
def test_clutter_kinds_print_dark_marks(kind: str) -> None:
    """Each clutter kind draws something dark within its extent and nothing outside it."""
    rng = np.random.default_rng(11)
    patch = clutter_patch(kind, rng, 5.0, np.eye(3), np.zeros(3))
    x, y = np.meshgrid(np.linspace(-5, 5, 201), np.linspace(-5, 5, 201))
    inside = np.hypot(x, y) <= 5.0
    refl = patch.reflectance(x[inside], y[inside])
    assert np.nanmin(refl) < 0.4
    assert np.all(np.isnan(refl) | ((refl >= 0) & (refl <= 1)))


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (
            lambda: random_layout(
                paper_camera(300, 200), 50, 60.0, "dot", _rng(), 0.0, max_tries=300
            ),
            "placed only",
        ),
        (lambda: random_layout(paper_camera(), 5, 60.0, "dot", _rng(), 90.0), "slant"),
        (lambda: random_layout(paper_camera(), 5, -1.0, "dot", _rng()), "size_px"),
        (lambda: random_layout(paper_camera(), 5, 60.0, "star", _rng()), "unknown fiducial"),
        (lambda: random_layout(paper_camera(), 5, 60.0, "dot", _rng(), codes=[70]), "codes"),
        (lambda: grid_layout(paper_camera(), 40, 40, 60.0, "dot", _rng()), "does not fit"),
        (lambda: clutter_patch("tree", _rng(), 1.0, np.eye(3), np.zeros(3)), "clutter kind"),
    ],
)
def test_bad_requests_raise(call: object, match: str) -> None:
    """Impossible or malformed requests raise SceneError naming the problem."""
    with pytest.raises(SceneError, match=match):
        call()  # type: ignore[operator]


def _rng() -> np.random.Generator:
    return np.random.default_rng(0)
