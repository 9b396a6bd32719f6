"""Scale of :func:`displacement_matcher.match`: 10,000 against 10,000 fiducials (target <= 1 s).

Scenes: ``N`` fiducials on a plane 1-1.1 m from the camera at a spacing of 15 mm (a dense lab
field), codes drawn from 4 (the paper's dolos set-up) or 66 (the whole codebook); the current set
moves 10 % of them by N(0, 15 mm) per axis and adds estimation noise (0.1 mm across the ray,
1 mm along it, the covariance saying so). The gate sets how large the components of the gated
graph become; the table gives the time of one full :func:`match` call (input checks, gating,
components, exact solves, result objects), the best of ``--repeat`` runs, with component sizes.

Run: ``.venv/bin/python -m benchmarks.matcher_scale [--n 10000] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from displacement_matcher import match
from pose_estimator.types import FiducialPose


def scene(n: int, n_codes: int, seed: int) -> tuple[list[FiducialPose], list[FiducialPose]]:
    """Baseline and current pose sets of ``n`` fiducials each."""
    rng = np.random.default_rng(seed)
    side = np.sqrt(n) * 15.0
    p = np.column_stack([rng.uniform(-side / 2, side / 2, (n, 2)), rng.uniform(1000, 1100, n)])
    codes = rng.integers(0, n_codes, n)
    q = p.copy()
    moved = rng.random(n) < 0.1
    q[moved] += rng.normal(0.0, 15.0, (int(moved.sum()), 3))

    def cov(x: np.ndarray) -> np.ndarray:
        r = x / np.linalg.norm(x)
        return 0.01 * np.eye(3) + (1.0 - 0.01) * np.outer(r, r)

    nrm = np.array([0.0, 0.0, -1.0])
    base = [FiducialPose(int(codes[k]), p[k], nrm, cov(p[k])) for k in range(n)]
    cur = []
    for k in range(n):
        c = cov(q[k])
        cur.append(FiducialPose(int(codes[k]), rng.multivariate_normal(q[k], c), nrm, c))
    return base, cur


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"match(): {args.n} vs {args.n} fiducials, best of {args.repeat} (target <= 1 s)")
    print(
        f"{'codes':>5} {'gate mm':>7} {'time s':>7} {'pairs':>6} {'cross':>6} "
        f"{'right %':>7} {'components':>10} {'largest':>7}"
    )
    for n_codes in (4, 66):
        base, cur = scene(args.n, n_codes, seed=7)
        for gate in (20.0, 40.0, 50.0, 60.0):
            best = np.inf
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                r = match(base, cur, gate_mm=gate)
                best = min(best, time.perf_counter() - t0)
            pairs = r.pairs()
            right = 100.0 * float(np.mean(pairs[:, 0] == pairs[:, 1])) if len(pairs) else 0.0
            print(
                f"{n_codes:>5} {gate:>7.0f} {best:>7.3f} {len(pairs):>6} "
                f"{r.counts()['cross_code']:>6} {right:>7.2f} {r.n_components:>10} "
                f"{r.largest_component:>7}"
            )


if __name__ == "__main__":
    main()
