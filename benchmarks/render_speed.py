"""Speed of the synthetic scene generator: 400 fiducials of 60 px plus clutter on 3008x2000.

Times :func:`armourcam.scenes.random_layout` (placement without overlap) and
:func:`armourcam.scenes.render_layout` (the one renderer: supersampled edges, blur 0.5 px, noise
1 %) for both designs, with an ideal lens and with plumb_bob distortion, on the paper's benchmark
camera (f = 6507 px). Not a product target; it keeps benchmark and test scenes cheap to make.

Run: ``.venv/bin/python -m benchmarks.render_speed [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from armourcam.scenes import paper_camera, random_layout, render_layout
from pose_estimator.camera import CameraModel


def main(argv: list[str] | None = None) -> int:
    """Print a table of layout and render times."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="frames per row (default 3)")
    parser.add_argument("--targets", type=int, default=400)
    parser.add_argument("--size", type=float, default=60.0, help="target size in px")
    args = parser.parse_args(argv)
    ideal = paper_camera()
    distorted = CameraModel(
        ideal.width, ideal.height, ideal.K, "plumb_bob", np.array([-0.15, 0.05, 1e-3, -5e-4, 0.0])
    )
    print(f"{args.targets} targets of {args.size:g} px + {args.targets // 2} clutter, 3008x2000")
    print(f"{'design':<7} {'lens':<10} {'layout s':>9} {'render s':>9}")
    for design in ("dot", "ring"):
        for lens, camera in (("ideal", ideal), ("plumb_bob", distorted)):
            t_layout, t_render = [], []
            for seed in range(args.repeat):
                rng = np.random.default_rng(seed)
                t0 = time.perf_counter()
                layout = random_layout(camera, args.targets, args.size, design, rng, 70.0)
                t1 = time.perf_counter()
                render_layout(camera, layout, rng, blur_sigma=0.5, noise=0.01)
                t2 = time.perf_counter()
                t_layout.append(t1 - t0)
                t_render.append(t2 - t1)
            print(f"{design:<7} {lens:<10} {np.median(t_layout):>9.2f} {np.median(t_render):>9.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
