"""Damage counts, thresholds in mm or Dn, N_od, cumulative runs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from displacement_matcher import MatcherError
from displacement_matcher.damage import assess, classify, cumulative, thresholds
from displacement_matcher.types import UnitMotion


def unit(
    name: str, dist: float | None, *, overturned: bool = False, rot: float = 0.0
) -> UnitMotion:
    """A unit moved ``dist`` mm along x (None: lost)."""
    tr = np.full(3, np.nan) if dist is None else np.array([dist, 0.0, 0.0])
    return UnitMotion(
        name,
        (1,),
        (0,),
        (),
        0 if dist is None else 3,
        "none" if dist is None else "rigid",
        np.eye(3),
        tr,
        None if dist is None else rot,
        np.zeros(3),
        0.0,
        overturned,
        0,
        0,
        0,
    )


def test_counts_and_n_od() -> None:
    """Displaced/moved/still/overturned/lost counts, percentage and N_od with Dn = 20 mm."""
    t = thresholds(20.0)
    units = [
        unit("a", 0.3),
        unit("b", 5.0),
        unit("c", 19.99),
        unit("d", 20.0),
        unit("e", 45.0),
        unit("f", 3.0, overturned=True),
        unit("g", None),
        unit("h", 4.0, rot=120.0),
        unit("i", 0.5, rot=12.0),
    ]
    classified, s = assess(units, t, section_width_mm=400.0)
    assert [u.status for u in classified] == [
        "still",
        "moved",
        "moved",
        "displaced",
        "displaced",
        "overturned",
        "lost",
        "overturned",
        "moved",
    ]
    assert s.n_units == 9
    assert s.displaced_units == 4  # d, e and the two overturned; lost counted apart
    assert s.moved_units == 3 and s.still_units == 1 and s.lost_units == 1
    assert s.overturned_units == 2
    assert s.percent_displaced == pytest.approx(400.0 / 9)
    assert s.n_od == pytest.approx(4 * 20.0 / 400.0)
    assert set(s.displaced_ids) == {"d", "e", "f", "h"}
    text = s.describe()
    assert "20.00 mm (1.00 Dn, Dn = 20.00 mm)" in text and "moved >= 2.00 mm or >= 10 deg" in text


def test_thresholds_in_dn_and_mm() -> None:
    """The displacement threshold can be given in Dn or mm; lost units optionally displaced."""
    assert thresholds(20.0, displaced_dn=0.5).displaced_mm == pytest.approx(10.0)
    assert thresholds(20.0, displaced_mm=7.0).displaced_mm == pytest.approx(7.0)
    t = thresholds(20.0, displaced_mm=7.0, lost_displaced=True)
    _, s = assess([unit("a", 8.0), unit("b", None)], t)
    assert s.displaced_units == 2 and s.n_od is None
    assert classify(unit("x", 6.9), t) == "moved"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"dn_mm": 0.0}, "Dn must be a positive"),
        ({"dn_mm": math.nan}, "Dn must be a positive"),
        ({"dn_mm": 20.0, "displaced_mm": 5.0, "displaced_dn": 1.0}, "not both"),
        ({"dn_mm": 20.0, "displaced_dn": -1.0}, "must be positive"),
        ({"dn_mm": 20.0, "moved_mm": 30.0}, "movement threshold"),
        ({"dn_mm": 20.0, "overturn_deg": 0.0}, "overturn angle"),
        ({"dn_mm": 20.0, "rotated_deg": 100.0}, "rotation threshold"),
    ],
)
def test_bad_thresholds(kwargs: dict, message: str) -> None:
    """Bad thresholds raise MatcherError with the value."""
    with pytest.raises(MatcherError, match=message):
        thresholds(**kwargs)


def test_bad_section_width_and_empty() -> None:
    """A bad section width is an error; no units is an empty, valid summary."""
    t = thresholds(20.0)
    with pytest.raises(MatcherError, match="section width"):
        assess([], t, section_width_mm=-1.0)
    _, s = assess([], t, section_width_mm=100.0)
    assert s.n_units == 0 and s.percent_displaced == 0.0 and s.n_od == 0.0


def test_cumulative_over_runs() -> None:
    """Per-run increments of the displaced units measured against one baseline."""
    t = thresholds(20.0)
    _, r1 = assess([unit("a", 25.0), unit("b", 1.0)], t)
    _, r2 = assess([unit("a", 26.0), unit("b", 30.0)], t)
    c = cumulative([r1, r2])
    assert [r["newly_displaced"] for r in c["runs"]] == [1, 1]
    assert c["ever_displaced"] == 2 and c["ever_displaced_ids"] == ["a", "b"]
