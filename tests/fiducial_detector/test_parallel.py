"""Step 4 shared over worker processes: the same detections as in one process, and no worker
left behind, even when one dies."""

from __future__ import annotations

import numpy as np
import pytest

from armourcam.render import RenderedScene
from armourcam.scenes import paper_camera, random_scene
from fiducial_detector import DetectorError, FiducialDetection, detect
from fiducial_detector.parallel import ParallelDetector


@pytest.fixture(scope="module")
def scene() -> RenderedScene:
    # Both designs, slanted, with clutter: every path of step 4 (retries, model reads, the
    # profile and model fits) has candidates to share.
    return random_scene(
        paper_camera(1200, 800),
        30,
        60.0,
        ("ring", "dot"),
        np.random.default_rng(11),
        70.0,
        True,
        blur_sigma=0.7,
        noise=0.01,
    )


def _assert_same(a: list[FiducialDetection], b: list[FiducialDetection]) -> None:
    assert [(d.code, d.design, len(d.ellipses)) for d in a] == [
        (d.code, d.design, len(d.ellipses)) for d in b
    ]
    # Batches of other sizes sum in another order: agreement to rounding, not bits.
    assert np.allclose([d.center_px for d in a], [d.center_px for d in b], atol=1e-6, rtol=0)


def test_workers_find_what_one_process_finds(scene: RenderedScene) -> None:
    serial = detect(scene.image)
    assert len(serial) >= 25  # most of the 30 targets: the comparison means something
    with ParallelDetector(2) as pool:
        shared = pool.detect(scene.image)
        assert pool.failures == 0
        workers = [slot[0] for slot in pool._procs if slot is not None]
        assert len(workers) == 1 and workers[0].poll() is None
    _assert_same(serial, shared)
    assert all(p.poll() is not None for p in workers)  # close() stopped it


def test_a_dead_worker_costs_no_detection(scene: RenderedScene) -> None:
    serial = detect(scene.image, design="ring")
    with ParallelDetector(2) as pool:
        _assert_same(serial, pool.detect(scene.image, design="ring"))
        slot = pool._procs[0]
        assert slot is not None
        slot[0].kill()
        slot[0].wait()
        _assert_same(serial, pool.detect(scene.image, design="ring"))  # replaced
        slot = pool._procs[0]
        assert slot is not None
        slot[1].send("not a share")  # a bad request: the worker answers with an error, lives on
        assert slot[1].recv()[0] == "error"
        # A worker that dies after the liveness check, holding its share: the share is done
        # here and counted as a failure.
        slot[0].kill()
        slot[0].wait()
        pool._worker = lambda k: slot  # type: ignore[method-assign]
        _assert_same(serial, pool.detect(scene.image, design="ring"))
        del pool._worker
        assert pool.failures >= 1 and "worker 1" in pool.last_failure


def test_one_worker_starts_no_process_and_bad_counts_raise(scene: RenderedScene) -> None:
    with ParallelDetector(1) as pool:
        _assert_same(detect(scene.image), pool.detect(scene.image))
        assert pool._procs == []
    for bad in (0, -1, 1.5):
        with pytest.raises(DetectorError, match="workers"):
            ParallelDetector(bad)  # type: ignore[arg-type]
    with ParallelDetector(2) as pool, pytest.raises(DetectorError, match="design"):
        pool.detect(scene.image, design="square")  # type: ignore[arg-type]
