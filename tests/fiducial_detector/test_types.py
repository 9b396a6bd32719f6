"""The detector's result types."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fiducial_detector.types import Ellipse, ellipses_from_rows


def test_ellipses_from_rows_are_the_constructors() -> None:
    """The fast builder gives the objects ``Ellipse(...)`` gives, field for field, None where a
    row is not good, and they stay frozen."""
    rng = np.random.default_rng(1)
    params = rng.random((6, 5)).tolist()
    cov = list(rng.random((6, 5, 5)))
    rms = rng.random(6).tolist()
    good = [True, False, True, True, False, True]
    got = ellipses_from_rows(good, params, cov, 0.8, rms)
    for g, e, (u, v, a, b, angle), c, r in zip(good, got, params, cov, rms, strict=True):
        if not g:
            assert e is None
            continue
        assert e is not None
        want = Ellipse((u, v), a, b, angle, c, 0.8, r)
        for f in dataclasses.fields(Ellipse):
            assert getattr(e, f.name) is getattr(want, f.name) or (
                getattr(e, f.name) == getattr(want, f.name)
            ), f.name
        with pytest.raises(dataclasses.FrozenInstanceError):
            e.semi_major = 1.0  # type: ignore[misc]
