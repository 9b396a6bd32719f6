"""The odds that an ideal estimator meets the paper's Table 1 targets in the exact protocol.

Table 1 (:mod:`benchmarks.pose_tables`) takes, per cell (design, size, blur, noise), the maximum
over the 70 slants 0-69 deg of the standard deviation of z over 30 noise images. Suppose an
estimator unbiased and exactly at the Cramér-Rao bound of the printed pattern alone
(:attr:`pose_estimator.crb.DepthBound.print_only`: pose, blur and levels unknown, the paper's
cut edge left out, as for a real print on an armour unit). Each slant's 30-image sd is then
``bound * sqrt(chi2(29) / 29)``, independent across slants and cells (each has its own noise), so
the probability that a cell's maximum stays within its target ``L`` (ring: 1/5 of the paper's
value; dot: the paper's value) is the product over its slants of ``P(chi2(29) <= 29 (L /
bound)^2)``, and that of every cell the product over cells. That is the best any estimator using
only the print can expect: a real one sits at or above the bound.

Run: ``.venv/bin/python -m benchmarks.pose_bound_odds [--designs ring] [--jobs 2]``
(about 10 min per design on 2 cores: 70 slants x 2 blurs x 4 sizes of Fisher information).
"""

from __future__ import annotations

import argparse
import multiprocessing

import numpy as np
from scipy.stats import chi2

from benchmarks.pose_tables import (
    DEGRADATIONS,
    SIZES,
    TABLE_SLANT_LIMIT,
    TILES,
    protocol_bound,
    read_paper,
)

#: Targets, as a fraction of the paper's Table 1 value.
LIMITS = {"ring": 0.2, "dot": 1.0}


def slant_bounds(task: tuple[str, int, float]) -> tuple[tuple[str, int, float], list[float]]:
    """The print-only depth bound (unit noise, mm) at every table slant of one (design, size,
    blur)."""
    design, size, blur = task
    bounds = [protocol_bound(design, size, s, blur) for s in range(TABLE_SLANT_LIMIT)]
    return task, [b.print_only for b in bounds]


def cell_met(sd: np.ndarray, limit: float, n_images: int) -> float:
    """Probability that the largest of the sample sds (``n_images`` each, true sds ``sd``, one
    per slant, independent) is at most ``limit``."""
    dof = n_images - 1
    return float(np.prod(chi2.cdf(dof * (limit / sd) ** 2, dof)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--designs", default="ring")
    parser.add_argument("--sizes", default=",".join(map(str, SIZES)))
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args(argv)
    designs = args.designs.split(",")
    sizes = [int(s) for s in args.sizes.split(",")]
    tasks = [(d, s, b) for d in designs for s in sizes for b in (0.5, 0.7)]
    if args.jobs > 1:
        with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
            bounds = dict(pool.map(slant_bounds, tasks, chunksize=1))
    else:
        bounds = dict(map(slant_bounds, tasks))
    paper = read_paper()
    n = TILES[0] * TILES[1]
    for design in designs:
        limit = LIMITS[design]
        print(
            f"\n## {design} design - Table 1 in the exact protocol ({TABLE_SLANT_LIMIT} slants x "
            f"{n} images), an unbiased estimator at the print-only bound; target ours/paper <= "
            f"{limit:g}"
        )
        print("size blur noise | bound/paper: worst slant | P(cell met)")
        odds = []
        for size in sizes:
            for blur, noise in DEGRADATIONS:
                sd = np.array(bounds[(design, size, blur)]) * noise
                ref = paper[("table1", blur, noise, size)]
                odds.append(cell_met(sd, limit * ref, n))
                print(
                    f"{size:4d} {blur:4.1f} {noise * 100:3.0f} %  | {sd.max() / ref:5.3f} at "
                    f"{int(np.argmax(sd)):2d} deg        | {odds[-1]:6.3f}"
                )
        print(
            f"P(all {len(odds)} cells met) = {np.prod(odds):.3f}; expected cells met = "
            f"{sum(odds):.1f} of {len(odds)}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
