"""Bradley & Roth adaptive threshold with the thin-line test."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fiducial_detector import DetectorError
from fiducial_detector.threshold import _apply_scale_table, bradley_threshold, default_window


def test_dark_on_gradient_background() -> None:
    """A dark disc is found on a strong illumination gradient that defeats a global threshold."""
    ramp = np.tile(np.linspace(40, 250, 400), (200, 1))
    img = ramp.copy()
    cv2.circle(img, (300, 100), 20, 0, -1)
    img[80:120, 300 - 20 : 300 + 20] *= 1.0
    img = np.where(np.hypot(*np.mgrid[-100:100, -300:100]) < 20, ramp * 0.4, ramp)
    grey = np.clip(img, 0, 255).astype(np.uint8)
    black = bradley_threshold(grey)
    yy, xx = np.mgrid[:200, :400]
    disc = np.hypot(xx - 300, yy - 100) < 18
    assert black[disc].mean() > 0.99 * 255
    # The dark end of the ramp is not black (a global threshold at the disc level would be).
    assert black[:, :150].mean() < 0.01 * 255


def test_big_black_disc_stays_filled() -> None:
    """A black disc much bigger than the small window is not hollowed out."""
    img = np.full((300, 300), 200, np.uint8)
    cv2.circle(img, (150, 150), 45, 30, -1)
    black = bradley_threshold(img) > 0
    yy, xx = np.mgrid[:300, :300]
    assert black[np.hypot(xx - 150, yy - 150) < 43].all()
    assert not black[np.hypot(xx - 150, yy - 150) > 48].any()


def test_thin_faint_ring_on_small_paper_is_found() -> None:
    """A faint one-pixel ring on a small white ellipse on a dark background: darker than its
    surround but not than the window mean; only the thin-line test finds it."""
    grey = np.full((200, 200), 60, np.uint8)
    cv2.ellipse(grey, (100, 100), (30, 12), 0, 0, 360, 220, -1)
    line = np.zeros_like(grey)
    cv2.ellipse(line, (100, 100), (24, 9), 0, 0, 360, 255, 1)
    grey[line > 0] = 150
    assert (bradley_threshold(grey) > 0)[line > 0].all()
    assert not (bradley_threshold(grey, thin_px=0) > 0)[line > 0].any()
    assert not (bradley_threshold(grey) > 0)[grey == 220].any()


def test_noise_on_flat_paper_stays_white() -> None:
    rng = np.random.default_rng(1234)
    grey = np.clip(rng.normal(200, 5, (200, 200)), 0, 255).astype(np.uint8)
    assert (bradley_threshold(grey) > 0).mean() < 0.001


def test_validation() -> None:
    with pytest.raises(DetectorError, match="uint8"):
        bradley_threshold(np.zeros((10, 10), np.float32))  # type: ignore[arg-type]
    with pytest.raises(DetectorError, match="t must"):
        bradley_threshold(np.zeros((10, 10), np.uint8), t=1.5)
    with pytest.raises(DetectorError, match="window"):
        bradley_threshold(np.zeros((10, 10), np.uint8), window=1)
    assert default_window((2000, 3008)) == 377
    assert default_window((100, 100)) == 101


def _full_resolution_threshold(grey: np.ndarray, side: int, t: float, thin_t: float) -> tuple:
    """Bradley & Roth and the thin-line test written out at full resolution: the black image
    and the window-mean limit it compares against."""
    mean = cv2.boxFilter(grey, -1, (side, side), borderType=cv2.BORDER_REPLICATE)
    limit = np.ceil(mean * (1.0 - t))
    closed = cv2.morphologyEx(grey, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)).astype(float)
    thin = (closed - grey) > np.ceil(thin_t * closed)
    return (grey < limit) | thin, limit


def test_reduced_window_mean_decides_like_full_resolution() -> None:
    """On a frame big enough for the reduced-resolution window mean, the result differs from the
    full-resolution filter only at a few pixels, each within a grey level of the limit."""
    rng = np.random.default_rng(5)
    h, w = 1200, 1800
    grey = np.tile(np.linspace(60.0, 230.0, w), (h, 1))  # strong illumination gradient
    for _ in range(300):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        r = int(rng.integers(4, 40))
        cv2.circle(grey, c, r + 6, 235, -1)
        cv2.circle(grey, c, r, float(rng.uniform(10, 120)), int(rng.choice([-1, 2])))
    grey = np.clip(grey + rng.normal(0, 3, grey.shape), 0, 255).astype(np.uint8)
    side = default_window(grey.shape)
    ref, limit = _full_resolution_threshold(grey, side, 0.2, 0.25)
    got = bradley_threshold(grey) > 0
    differ = got != ref
    assert differ.mean() < 2e-3
    assert np.all(np.abs(grey[differ] - limit[differ]) <= 1)


def test_small_image_is_exactly_bradley_roth_with_thin_lines() -> None:
    """Below the reduced-mean size the threshold is the full-resolution one, pixel for pixel."""
    rng = np.random.default_rng(6)
    grey = np.clip(rng.normal(150, 40, (180, 240)), 0, 255).astype(np.uint8)
    grey = cv2.GaussianBlur(grey, (0, 0), 1.5)
    for t, thin_t in ((0.2, 0.25), (0.15, 0.1), (0.3, 0.37)):
        ref, _ = _full_resolution_threshold(grey, default_window(grey.shape), t, thin_t)
        assert np.array_equal(bradley_threshold(grey, t=t, thin_t=thin_t) > 0, ref)


def test_scale_table_is_applied_exactly_or_falls_back_to_the_lookup() -> None:
    values = np.arange(256, dtype=np.uint8)[None, :]
    for scale in (0.75, 0.9, 0.63, 0.5):
        floor = np.floor(np.arange(256) * scale).astype(np.uint8)
        assert np.array_equal(_apply_scale_table(values.copy(), floor, scale)[0], floor)
    # Rounding up cannot be had from round-to-nearest with one offset: the table is used.
    ceil = np.ceil(np.arange(256) * 0.75).astype(np.uint8)
    assert np.array_equal(_apply_scale_table(values.copy(), ceil, 0.75)[0], ceil)
