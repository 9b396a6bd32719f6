"""Random binary images holding every kind of boundary the border follower meets, for the
boundary tests (:mod:`test_components`, :mod:`test_border_kernel`)."""

from __future__ import annotations

import cv2
import numpy as np


def random_binary(rng: np.random.Generator, shape: tuple[int, int] = (90, 120)) -> np.ndarray:
    """Speckle, lines, filled and hollow ellipses: every kind of boundary the tracer meets."""
    img = (rng.random(shape) < 0.03).astype(np.uint8) * 255
    for _ in range(6):
        c = (int(rng.integers(10, shape[1] - 10)), int(rng.integers(10, shape[0] - 10)))
        ax = (int(rng.integers(2, 25)), int(rng.integers(1, 15)))
        cv2.ellipse(
            img, c, ax, float(rng.uniform(0, 180)), 0, 360, 255, int(rng.choice([-1, 1, 2]))
        )
    p, q = rng.integers(0, min(shape), (2, 2))
    cv2.line(img, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 255, 1)
    return img
