"""How often an ideal measurer gets the dolos fields' displaced-unit count exact.

Issue 4 asks for the displaced-unit count to be exact on the end-to-end dolos fields
(``matcher_field --source e2e``). A unit is displaced when its centre moved at least 1 Dn; the
fields' movers are drawn uniformly up to 2 Dn, so a field of 300 units holds on average about
0.6 movers within 0.02 Dn (0.4 mm) of the threshold, where any measurement's noise decides the
side. This benchmark takes the thirty fields' true centre displacements and asks: with every
unit matched right and its displacement measured with an unbiased Gaussian error of standard
deviation ``sd`` along it, how many fields come out with the count exact (reported displaced
equal to truly displaced, as ``matcher_field`` counts), and how likely is it that all of them
do? (The same question ``pose_bound_odds`` asks of the pose tables.)

The noise levels printed are round values and the unit displacement errors ``matcher_field``
measures end to end, per method of unit motion, beside the number of fields the matcher gets
exact: the part of the gap that matching errors, not the threshold, make.

Run: ``.venv/bin/python -m benchmarks.matcher_count_odds [--seeds 30] [--draws 20000]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from numpy.typing import NDArray

from armourcam.field import make_field

#: Unit displacement-distance error sd (mm) measured end to end on the thirty physical-blur
#: fields (matcher_field, session 42, units matched to their own faces): rigid motions (two or
#: more faces) and units measured through one pair (robust sd: 1.4826 x the median absolute
#: deviation of the reported minus the true centre distance), with and without the faces'
#: printed axes (``--without-axes``: the matcher before it used each face's spin).
MEASURED_SD_MM = {"rigid (2+ faces)": 0.33, "one pair": 0.71, "one pair, no spin": 1.17}


def mover_distances(seeds: range, units: int) -> tuple[list[NDArray[np.float64]], float]:
    """True centre displacements (mm) of each field's moved, not overturned units, and Dn."""
    out = []
    dn = 0.0
    for seed in seeds:
        field = make_field(units, seed=seed, diameter_mm=10.0)
        dn = field.geometry.dn_mm
        moved = np.flatnonzero(field.moved & ~field.overturned)
        out.append(
            np.array(
                [
                    np.linalg.norm(field.displacement_at(u, field.before.centres_mm[u]))
                    for u in moved
                ]
            )
        )
    return out, dn


def exact_odds(
    distances: list[NDArray[np.float64]],
    threshold_mm: float,
    sd_mm: float,
    draws: int,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Per field, the probability that the count of units measured at or beyond the threshold
    equals the true count, each distance measured with Gaussian error ``sd_mm``."""
    odds = []
    for d in distances:
        truth = int(np.sum(d >= threshold_mm))
        measured = d[None, :] + rng.normal(0.0, sd_mm, size=(draws, len(d)))
        odds.append(float(np.mean(np.sum(measured >= threshold_mm, axis=1) == truth)))
    return np.array(odds)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--units", type=int, default=300)
    ap.add_argument("--draws", type=int, default=20000)
    args = ap.parse_args(argv)
    distances, dn = mover_distances(range(args.seeds), args.units)
    rng = np.random.default_rng(0)
    near = [int(np.sum(np.abs(d - dn) <= 0.02 * dn)) for d in distances]
    print(
        f"{args.seeds} dolos fields ({args.units} units, Dn {dn:.2f} mm, threshold 1 Dn): "
        f"{sum(len(d) for d in distances)} movers, {sum(near)} within 0.02 Dn of the threshold "
        f"(fields with one or more: {sum(n > 0 for n in near)})"
    )
    print(
        f"{'error sd (mm)':>26} {'fields exact (expected)':>24} {'P(all exact)':>13} "
        f"{'worst field':>11}"
    )
    levels = [(f"{sd:g}", sd) for sd in (0.05, 0.1, 0.2)]
    levels += [(f"{sd:g} ({name})", sd) for name, sd in MEASURED_SD_MM.items()]
    for label, sd in levels:
        odds = exact_odds(distances, dn, sd, args.draws, rng)
        print(
            f"{label:>26} {odds.sum():>17.1f} of {args.seeds:<3} {np.prod(odds):>13.2e} "
            f"{odds.min():>11.2f}"
        )
    print(
        "paper: no damage count (it stops at the vectors); matcher_field measures the matcher's "
        "own exact fields on the same seeds"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
