"""The coding-track reader: decoding table, phase independence, orientation and rejection rules."""

from __future__ import annotations

import numpy as np
import pytest

from armourcam.render import Target, render, rotation_from_slant_tilt
from fiducial_detector.code_reader import ReaderConfig, _decode_table, read_codes
from fiducial_detector.codebook import BITS, code_count, decode, rotation_table
from fiducial_detector.design import get_design
from fiducial_detector.ellipse import ellipse_from_conic
from pose_estimator.camera import CameraModel


def test_decode_table_agrees_with_codebook_decode() -> None:
    """The lookup gives codebook.decode's answer for every word within distance 1 of a code."""
    t_code, t_rot, t_dist = _decode_table()
    rng = np.random.default_rng(1234)
    table = rotation_table()
    for _ in range(300):
        c, k = int(rng.integers(code_count())), int(rng.integers(BITS))
        bits = table[c, k].copy()
        if rng.random() < 0.5:
            bits[rng.integers(BITS)] ^= 1
        word = int((bits.astype(np.int64) << np.arange(BITS)).sum())
        assert (t_code[word], t_rot[word], t_dist[word]) == decode(bits)
    # Words two flips away are not in the table.
    bits = table[0, 0].copy()
    bits[[0, 5]] ^= 1
    word = int((bits.astype(np.int64) << np.arange(BITS)).sum())
    assert t_dist[word] > 1 and decode(bits)[2] >= 2


def _truth_ellipse(design: str, spin: float, slant: float, code: int) -> tuple:
    camera = CameraModel.ideal(140, 140, 6507.0)
    rot = rotation_from_slant_tilt(np.radians(slant), 0.7, spin)
    scene = render(
        camera,
        [Target(code, design, 7.1, rot, np.array([0.0, 0.0, 6507 * 7.1 / 80]))],
        blur_sigma=0.6,
        noise=0.01,
        rng=np.random.default_rng(int(spin * 100)),
    )
    u, v, a, b, ang = ellipse_from_conic(scene.truth[0].conics[0])
    return scene, np.array([[u, v]]), np.array([[a, b]]), np.array([ang])


@pytest.mark.parametrize("design", ["ring", "dot"])
def test_reads_every_spin_through_the_true_ellipse(design: str) -> None:
    """Whatever the in-plane rotation (sector boundaries anywhere), the code reads correctly."""
    for k, spin in enumerate(np.linspace(0.0, 2 * np.pi, 23, endpoint=False)):
        code = (7 * k) % code_count()
        scene, c, ax, ang = _truth_ellipse(design, float(spin), 50.0, code)
        r = read_codes(scene.image, 255.0, get_design(design), c, ax, ang)
        assert r.accepted[0] and r.code[0] == code and r.hamming[0] == 0
        assert r.consistent[0]
        assert np.all(r.margin[0] > 0.5)
        assert 0.65 < r.contrast[0] < 0.8


def test_rejects_uniform_and_uncoded_regions() -> None:
    design = get_design("ring")
    flat = np.full((100, 100), 128, np.uint8)
    c, ax, ang = np.array([[50.0, 50.0]]), np.array([[30.0, 20.0]]), np.array([0.3])
    r = read_codes(flat, 255.0, design, c, ax, ang)
    assert not r.accepted[0] and not r.consistent[0]
    # A candidate whose track would leave the image is rejected, never read from the border.
    r = read_codes(flat, 255.0, design, np.array([[5.0, 50.0]]), ax, ang)
    assert not r.accepted[0]


def test_wrong_design_is_inconsistent() -> None:
    """A ring fiducial read as a dot fiducial (its central dot as the pose circle) is rejected
    by the concentric-region rule, though its track would decode."""
    scene, c, ax, ang = _truth_ellipse("ring", 0.4, 20.0, 12)
    dot = get_design("dot")
    scale = 0.24 / 1.0  # the ring's central dot, taken as a dot design's pose circle
    r = read_codes(scene.image, 255.0, dot, c, ax * scale, ang)
    assert not r.accepted[0]


def test_strict_config_rejects_weak_reads() -> None:
    scene, c, ax, ang = _truth_ellipse("dot", 1.0, 40.0, 5)
    # Misplaced by a quarter of the track width: bits still read, but not with margin to spare.
    strict = ReaderConfig(max_hamming=0, weak_margin=0.99, max_weak_bits=0)
    r = read_codes(
        scene.image, 255.0, get_design("dot"), c + np.array([[0.0, 3.0]]), ax, ang, None, strict
    )
    assert not r.accepted[0]
    ok = read_codes(scene.image, 255.0, get_design("dot"), c, ax, ang)
    assert ok.accepted[0]
