"""The profile fit's compiled kernel (:mod:`fiducial_detector._profile_kernel`) against its numpy
reference (``profile_fit._lines`` then ``profile_fit._centroids``, with ``cv2.remap``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fit_scenes import render_one, true_ellipse

from fiducial_detector import _profile_kernel, profile_fit
from fiducial_detector.profile_fit import line_counts, sampled_image

RHO = (0.9, 1.15)


def _ellipses(rng: np.random.Generator, n: int, shape: tuple[int, int]) -> np.ndarray:
    """Random ellipses over an image, some reaching past its borders."""
    a = rng.uniform(6.0, 60.0, n)
    return np.column_stack(
        [
            rng.uniform(-10.0, shape[1] + 10.0, n),
            rng.uniform(-10.0, shape[0] + 10.0, n),
            a,
            a * rng.uniform(0.3, 1.0, n),
            rng.uniform(0.0, np.pi, n),
        ]
    )


def _reference(src: np.ndarray, ellipses: np.ndarray, second: bool) -> tuple:
    count = line_counts(ellipses)
    cap = np.full(len(ellipses), 2.5)
    pol = np.where(np.arange(len(ellipses)) % 2 == 0, 1.0, -1.0)
    lines = profile_fit._lines(ellipses, count, RHO, cap)
    mean, mass, m2 = profile_fit._centroids(
        src.astype(np.float32), lines, pol, second_moment=second
    )
    return (lines, mean, mass, m2), (count, cap, pol)


@pytest.mark.parametrize("second", [True, False])
def test_lines_and_moments_match_the_numpy_reference(second: bool) -> None:
    """Geometry to float32 rounding; moments (borders replicated, as ``cv2.BORDER_REPLICATE``:
    some ellipses reach past the image) to what ``cv2.remap``'s rounding of the sample
    positions to 1/32 px makes of a blurred edge (a few 1e-6 px typically)."""
    rng = np.random.default_rng(5)
    scene = render_one("ring", 120, 40, 0.7, 0.01, 3)
    image = scene.image
    ellipses = np.vstack([_ellipses(rng, 60, image.shape), true_ellipse(scene, 0)[None]])
    (ref, ref_mean, ref_mass, ref_m2), (count, cap, pol) = _reference(image, ellipses, second)
    lines, mean, mass, m2, _ = profile_fit._sampled_lines(
        sampled_image(image), ellipses, count, RHO, cap, pol, second
    )
    valid = ref.valid
    assert np.array_equal(lines.valid, valid)
    for name in ("kappa", "lower", "upper", "step"):
        got, want = getattr(lines, name)[valid], getattr(ref, name)[valid]
        np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5, err_msg=name)
    jv = np.repeat(valid[:, None, :], 5, axis=1)
    scale = np.max(np.abs(ref.jac), axis=2, keepdims=True)
    np.testing.assert_allclose((lines.jac / scale)[jv], (ref.jac / scale)[jv], atol=2e-5)
    # Padding: no jacobian, no centroid.
    assert np.all(lines.jac[~jv] == 0.0)
    assert np.all(np.isnan(mean[~valid]))
    # Lines with a clear step (a tenth of the full range or more).
    step = valid & (np.abs(ref_mass) > 25.0)
    assert step.sum() > 500
    np.testing.assert_allclose(mass[step], ref_mass[step], rtol=1e-3)
    off = np.abs(mean[step] - ref_mean[step])
    assert np.median(off) < 1e-4
    assert np.max(off) < 2e-3
    if second:
        assert m2 is not None and ref_m2 is not None
        assert np.median(np.abs(m2[step] - ref_m2[step])) < 1e-4
    else:
        assert m2 is None


def test_pixel_types_sample_alike() -> None:
    """uint8, uint16 and float32 frames of the same values give the same moments, to float32
    rounding (the integers are read as they are, no float copy of the frame; 8 and 16-bit
    pixels have their own SIMD loop), also where windows reach past the image."""
    rng = np.random.default_rng(9)
    image = rng.integers(0, 256, (120, 150)).astype(np.uint8)
    image = cv2.GaussianBlur(image, (0, 0), 3.0)  # edges with some mass on every line
    ellipses = _ellipses(rng, 40, image.shape)
    count = line_counts(ellipses)
    cap, pol = np.full(len(ellipses), 3.0), np.ones(len(ellipses))
    results = [
        profile_fit._sampled_lines(
            sampled_image(image.astype(t) * s), ellipses, count, RHO, cap, pol, True
        )
        for t, s in ((np.uint8, 1), (np.uint16, 1), (np.float32, 1), (np.uint16, 257))
    ]
    assert sampled_image(image).dtype == np.uint8
    assert sampled_image(image.astype(np.float64)).dtype == np.float32
    lines, mean, mass, m2, _ = results[0]
    valid = lines.valid
    usable = valid & (np.abs(mass) > 5.0)
    assert usable.sum() > 0.3 * valid.sum()
    for scale, (_, mean_b, mass_b, m2_b, _) in zip((1, 1, 257), results[1:], strict=True):
        np.testing.assert_allclose(mass_b[valid], scale * mass[valid], rtol=1e-5, atol=1e-3 * scale)
        np.testing.assert_allclose(mean_b[usable], mean[usable], atol=1e-4)
        np.testing.assert_allclose(m2_b[usable], m2[usable], atol=1e-3)


def test_bad_buffers_are_refused() -> None:
    """Sizes that disagree with the counts, or an unknown pixel kind, raise instead of reading
    past a buffer."""
    k, m = 2, 20
    f32 = np.float32
    out = [np.empty((k, m), np.uint8), np.empty((k, 5, m), f32)]
    out += [np.empty((k, m), f32) for _ in range(7)]
    src = np.zeros((10, 10), f32)
    ell = np.zeros((k, 5))
    count = np.full(k, m, dtype=np.int64)
    args = (ell, count, 0.9, 1.1, np.ones(k), np.ones(k), m, True)
    with pytest.raises(ValueError, match="src"):
        _profile_kernel.sample_lines(src, 2, 10, 11, *args, *out)
    with pytest.raises(ValueError, match="kind"):
        _profile_kernel.sample_lines(src, 3, 10, 10, *args, *out)
    short = [*out[:-1], np.empty((k, m - 1), f32)]
    with pytest.raises(ValueError, match="m2"):
        _profile_kernel.sample_lines(src, 2, 10, 10, *args, *short)


def test_full_edge_terms_match_the_numpy_reference() -> None:
    """With a known blur the kernel also gives a full edge's usable lines, edge positions,
    typical step heights and least-squares sums: the numpy reference's
    (``profile_fit._edge_terms``, then the sums over its usable lines), to float32 rounding;
    the lines themselves are those of the kernel's plain pass."""
    rng = np.random.default_rng(11)
    scene = render_one("ring", 120, 50, 0.7, 0.01, 4)
    truth = true_ellipse(scene, 0)
    # Fits near the edge (as in the final passes) and some nowhere near one.
    near = truth + rng.normal(0.0, 0.05, (40, 5)) * [1, 1, 1, 1, 0.01]
    ellipses = np.vstack([near, _ellipses(rng, 20, scene.image.shape)])
    ellipses[:, 2:4] = np.sort(ellipses[:, 2:4], axis=1)[:, ::-1]
    count = line_counts(ellipses)
    cap = np.full(len(ellipses), 1.8)
    pol = np.ones(len(ellipses))
    blur = rng.uniform(0.6, 0.9, len(ellipses))
    src = sampled_image(scene.image)
    lines, mean, mass, _, _ = profile_fit._sampled_lines(src, ellipses, count, RHO, cap, pol, False)
    fused, _, _, _, full = profile_fit._sampled_lines(
        src, ellipses, count, RHO, cap, pol, False, blur
    )
    for name in ("valid", "jac", "kappa", "lower", "upper", "step"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(lines, name), err_msg=name)
    ref_good, ref_t, ref_typical, _ = profile_fit._edge_terms(
        lines, mean, mass, None, blur, cap, False
    )
    assert ref_good[:40].mean() > 0.5  # the test sees usable lines
    # A line exactly at a limit may flip on rounding; none did on this scene.
    assert np.mean(full.good != ref_good) <= 1e-3
    both = full.good & ref_good
    np.testing.assert_allclose(full.t[both], ref_t[both], atol=2e-5)
    assert np.all(full.t[~full.good] == 0.0)
    fin = np.isfinite(ref_typical)
    assert np.array_equal(np.isfinite(full.typical), fin)
    np.testing.assert_allclose(full.typical[fin], ref_typical[fin], rtol=1e-5)
    j64, g = lines.jac.astype(np.float64), full.good[:, None, :]
    want = np.einsum("kpl,kql->kpq", j64 * g, j64)
    np.testing.assert_allclose(full.normal, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    want_rhs = -np.einsum("kpl,kl->kp", j64 * g, full.t.astype(np.float64))
    np.testing.assert_allclose(full.rhs, want_rhs, atol=1e-9 * np.abs(want_rhs).max())


def _brute_rounds(jac, t, good, q, o, tie_sd, min_lines, limit):  # type: ignore[no-untyped-def]
    """The two least-squares rounds of ``profile_fit._solve`` written out with numpy, fit by
    fit."""
    k = t.shape[0]
    j64, t64 = jac.astype(np.float64), t.astype(np.float64)
    delta, inv, sd = np.full((k, 5), np.nan), np.full((k, 5, 5), np.nan), np.empty(k)
    use = good.copy()

    def sums(f, mask):  # type: ignore[no-untyped-def]
        jm = j64[f][:, mask]
        return jm @ jm.T, -jm @ t64[f][mask]

    def solve(f, n, r, s):  # type: ignore[no-untyped-def]
        if q is None:
            return np.linalg.solve(n, r)
        return np.linalg.solve(n + s * s * q[f], r - s * s * q[f] @ o[f])

    for f in range(k):
        step = np.zeros(5)
        if use[f].sum() >= min_lines:
            step = solve(f, *sums(f, use[f]), max(tie_sd, 1e-3))
        resid = t64[f] + step @ j64[f]
        n = use[f].sum()
        sd0 = np.sqrt(np.sum(resid[use[f]] ** 2) / max(n - 5, 1))
        use[f] &= np.abs(resid) <= limit * sd0
        n = use[f].sum()
        normal, rhs = sums(f, use[f])
        final = np.zeros(5)
        if n >= min_lines:
            delta[f] = final = solve(f, normal, rhs, max(sd0, 1e-3))
            inv[f] = np.linalg.inv(normal)
        resid = t64[f] + final @ j64[f]
        sd[f] = np.sqrt(np.sum(resid[use[f]] ** 2) / max(n - 5, 1))
    return delta, inv, sd, use


@pytest.mark.parametrize("with_prior", [False, True])
def test_least_squares_rounds_match_brute_force(with_prior: bool) -> None:
    """``normal_sums`` then ``solve_rounds`` against the rounds written out with numpy, on
    random lines with outliers: the sums, the lines left in use, the step, the inverse of the
    final sums and the final RMS; a fit with too few lines gets NaN, one with no lines too."""
    rng = np.random.default_rng(12)
    k, m = 6, 60
    jac = rng.normal(size=(k, 5, m)).astype(np.float32)
    t = (rng.normal(size=(k, m)) * 0.1).astype(np.float32)
    t[:, 0] += 20.0  # an outlier per fit
    good = rng.random((k, m)) < 0.8
    good[0] = False  # no lines
    good[1, 10:] = False  # too few
    use = good.astype(np.uint8)
    normal, rhs = np.empty((k, 5, 5)), np.empty((k, 5))
    _profile_kernel.normal_sums(jac, t, use, m, normal, rhs)
    j64, g = jac.astype(np.float64), good[:, None, :]
    np.testing.assert_allclose(normal, np.einsum("kpl,kql->kpq", j64 * g, j64), atol=1e-9)
    np.testing.assert_allclose(rhs, -np.einsum("kpl,kl->kp", j64 * g, t.astype(float)), atol=1e-9)
    q = o = None
    args = (np.empty(0), np.empty(0))
    if with_prior:
        a = rng.normal(size=(k, 5, 5))
        q, o = a @ a.transpose(0, 2, 1) * 10.0, rng.normal(size=(k, 5)) * 0.01
        args = (q, o)
    delta, inv, sd = np.empty((k, 5)), np.empty((k, 5, 5)), np.empty(k)
    used = use.sum(axis=1, dtype=np.int64)
    _profile_kernel.solve_rounds(
        jac, t, use, m, normal, rhs, *args, 0.1, 12, 4.0, delta, inv, sd, used
    )
    want = _brute_rounds(jac, t, good, q, o, 0.1, 12, 4.0)
    assert np.array_equal(use.astype(bool), want[3])
    assert np.array_equal(used, want[3].sum(axis=1))
    assert not want[3][2:, 0].any()  # the outliers left
    assert np.all(np.isnan(delta[:2])) and np.all(np.isnan(inv[:2]))
    np.testing.assert_allclose(delta[2:], want[0][2:], rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(inv[2:], want[1][2:], rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(sd[2:], want[2][2:], rtol=1e-6)


def test_fits_the_samples_cannot_reach_get_no_lines() -> None:
    """Ellipses not finite, centred far off the image or too large to sample safely give
    padding only (no usable line), and the others in the same call are unaffected."""
    image = np.zeros((50, 50), dtype=np.float32)
    image[:, 25:] = 100.0
    ok = [25.0, 25.0, 10.0, 8.0, 0.2]
    ellipses = np.array(
        [
            ok,
            [np.nan, 25.0, 10.0, 8.0, 0.2],
            [3e7, 25.0, 10.0, 8.0, 0.2],
            [25.0, 25.0, 5000.0, 8.0, 0.2],
            ok,
        ]
    )
    count = np.full(len(ellipses), 64)
    cap, pol = np.full(len(ellipses), 3.0), np.ones(len(ellipses))
    lines, mean, mass, _, _ = profile_fit._sampled_lines(
        image, ellipses, count, RHO, cap, pol, False
    )
    assert np.all(lines.valid[[0, 4]]) and not np.any(lines.valid[1:4])
    assert np.all(np.isnan(mean[1:4])) and np.all(mass[1:4] == 0.0)
    np.testing.assert_array_equal(mean[0], mean[4])


def test_track_samples_are_the_code_readers_remaps() -> None:
    """``sample_tracks`` gives the code reader's samples and off-image marks as its maps and
    ``cv2.remap`` give them (all but 0.1 % equal, the rest a level apart: float rounding at a
    half), candidates near and past the border included; for 16-bit and float32 frames too."""
    from fiducial_detector import code_reader

    rng = np.random.default_rng(15)
    image = cv2.GaussianBlur(rng.integers(0, 256, (150, 200)).astype(np.uint8), (0, 0), 2.0)
    n = 300
    centre = np.column_stack([rng.uniform(-10, 210, n), rng.uniform(-10, 160, n)])
    a = rng.uniform(5, 40, n)
    axes = np.column_stack([a, a * rng.uniform(0.3, 1.0, n)])
    angle = rng.uniform(0, np.pi, n)
    drift = rng.normal(0, 0.002, (n, 2))
    radii = np.repeat([0.3, 0.55, 0.9, 1.1], 24)
    params = np.tile(np.linspace(0, 2 * np.pi, 24, endpoint=False), 4)
    r0 = 1.0
    got, outside = code_reader._sample_points(image, centre, axes, angle, r0, drift, radii, params)
    u, v = code_reader._track_maps(centre, axes, angle, r0, drift, radii, params, np.float32)
    near = code_reader._near_border(centre, axes, angle, r0, drift, radii, image.shape)
    want, want_outside = code_reader._sample(image, u, v, near)  # cv2.remap's samples
    assert outside.any() and not outside.all()
    assert np.array_equal(outside, want_outside)
    diff = np.abs(got - want)
    assert np.max(diff) <= 1.0 and np.count_nonzero(diff) <= 0.001 * diff.size
    for other in (image.astype(np.uint16) * 257, image.astype(np.float32) / 255):
        got, outside = code_reader._sample_points(
            other, centre, axes, angle, r0, drift, radii, params
        )
        want, want_outside = code_reader._sample(other, u, v, near)
        assert np.array_equal(outside, want_outside)
        diff = np.abs(got - want)[~outside]
        top = 1.0 if other.dtype == np.uint16 else 1e-5
        assert np.max(diff) <= top and np.count_nonzero(diff > 1e-6) <= 0.002 * diff.size
