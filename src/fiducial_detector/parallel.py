"""Detection with step 4 shared out over worker processes, for a live rig's latency.

The front of the pipeline (threshold, boundaries, candidates: about 30 ms on a 6 MP frame) runs
in the calling process; the candidates' reads and sub-pixel fits, each candidate's independent
of the others' (:func:`.detect.finish_candidates`), are split over the caller and ``workers - 1``
worker processes. The image reaches the workers through one shared-memory block (a memcpy per
frame); only candidate arrays and detections travel through the pipes. Threads would not help:
the fits are many small NumPy calls that hold the GIL.

The detections are those of :func:`.detect.detect` on the same image, in the same order. A
worker that fails or dies costs nothing but time: its share is computed in the calling process
and the worker is started again for the next frame (:attr:`ParallelDetector.failures` counts).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .code_reader import ReaderConfig
from .design import get_design
from .detect import (
    Candidates,
    SubpixelMethod,
    detect_grey,
    detector_config,
    finish_candidates,
    to_grey,
)
from .errors import DetectorError
from .types import FiducialDetection

#: Fewest candidates per share: below it the pipes cost more than the split saves.
MIN_SHARE = 6
#: Where POSIX shared memory blocks appear as files (Linux).
_SHM_DIR = Path("/dev/shm")
#: BLAS thread-count variables, defaulted to 1 for the workers (as ``armourcam.blas`` does for
#: the nodes).
_BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
#: Seconds a worker may take for its share before it is given up and the share done here.
WORKER_TIMEOUT_S = 30.0


@dataclass(frozen=True, slots=True)
class _Share:
    """One worker's part of step 4 for one design's candidates (what crosses the pipe)."""

    frame: int
    shm_name: str
    shape: tuple[int, ...]
    dtype: str
    full_scale: float
    design: str
    centre: NDArray[np.float64]
    axes: NDArray[np.float64]
    angle: NDArray[np.float64]
    drift: NDArray[np.float64]
    reader: ReaderConfig
    subpixel: SubpixelMethod
    noise: float


class ParallelDetector:
    """:func:`.detect.detect` with step 4 split over ``workers`` processes (this one included).

    Parameters
    ----------
    workers : int
        Processes taking part, at least 1; 1 detects in this process alone.

    Notes
    -----
    Workers are started lazily, as fresh interpreters (``python -m fiducial_detector.parallel``:
    no fork beside rclpy's and DDS's threads), and stop when :meth:`close` is called, when this
    object is garbage-collected, or when this process dies (their pipe closes). Use as a
    context manager where possible. Linux: the image is shared through ``/dev/shm``.
    """

    def __init__(self, workers: int = 2) -> None:
        if int(workers) != workers or workers < 1:
            raise DetectorError(f"workers must be an integer >= 1, got {workers!r}")
        self.workers = int(workers)
        self.failures = 0
        self.last_failure = ""
        if self.workers > 1 and not _SHM_DIR.is_dir():
            raise DetectorError(f"workers > 1 needs POSIX shared memory at {_SHM_DIR}")
        self._procs: list[tuple[subprocess.Popen[bytes], Connection] | None] = [None] * (
            self.workers - 1
        )
        self._shm: SharedMemory | None = None
        self._frame = 0

    # ------------------------------------------------------------------ public

    def detect(self, image: NDArray[np.generic], **kwargs: Any) -> list[FiducialDetection]:
        """Fiducials in ``image``: the same arguments, result and errors as
        :func:`.detect.detect`."""
        config = detector_config(**kwargs)
        grey, full_scale = to_grey(image)
        if self.workers == 1:
            return detect_grey(grey, full_scale, config)
        self._frame += 1
        self._publish_image(grey)
        return detect_grey(grey, full_scale, config, finish=self._finish)

    def close(self) -> None:
        """Stop the workers and free the shared memory (idempotent)."""
        for k, slot in enumerate(self._procs):
            if slot is not None:
                _stop(*slot)
                self._procs[k] = None
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    def __enter__(self) -> ParallelDetector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown: nothing left to free
            self.close()

    # ------------------------------------------------------------------ internals

    def _publish_image(self, grey: NDArray[np.generic]) -> None:
        if self._shm is None or self._shm.size < grey.nbytes:
            if self._shm is not None:
                self._shm.close()
                self._shm.unlink()
            self._shm = SharedMemory(create=True, size=max(grey.nbytes, 1))
        view = np.ndarray(grey.shape, dtype=grey.dtype, buffer=self._shm.buf)
        view[...] = grey

    def _worker(self, k: int) -> tuple[subprocess.Popen[bytes], Connection]:
        slot = self._procs[k]
        if slot is not None and slot[0].poll() is None:
            return slot
        if slot is not None:
            _stop(*slot)
        # A plain subprocess, not multiprocessing's spawn: that would re-run the caller's
        # __main__ module in the worker. The pipe is one end of a socket pair.
        here, there = socket.socketpair()
        env = dict(os.environ)
        for name in _BLAS_THREAD_VARIABLES:  # tiny batched solves: extra BLAS threads only spin
            env.setdefault(name, "1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "fiducial_detector.parallel", str(there.fileno())],
            pass_fds=(there.fileno(),),
            stdin=subprocess.DEVNULL,
            env=env,
        )
        there.close()
        conn = Connection(here.detach())
        self._procs[k] = (proc, conn)
        return proc, conn

    def _finish(
        self,
        grey: NDArray[np.generic],
        full_scale: float,
        cands: Candidates,
        reader: ReaderConfig,
        subpixel: SubpixelMethod,
        noise: float,
    ) -> list[FiducialDetection]:
        n = len(cands.centre)
        parts = min(self.workers, n // MIN_SHARE)
        if parts < 2:
            return finish_candidates(grey, full_scale, cands, reader, subpixel, noise)
        # Interleaved shares: neighbouring candidates (similar size and cost) go to different
        # processes.
        shares = [_subset(cands, np.arange(k, n, parts)) for k in range(parts)]
        sent: list[tuple[int, Connection, Candidates]] = []
        assert self._shm is not None
        for k, share in enumerate(shares[1:]):
            try:
                _, conn = self._worker(k)
                conn.send(
                    _Share(
                        self._frame,
                        self._shm.name,
                        grey.shape,
                        grey.dtype.str,
                        full_scale,
                        cands.design.name,
                        share.centre,
                        share.axes,
                        share.angle,
                        share.drift,
                        reader,
                        subpixel,
                        noise,
                    )
                )
                sent.append((k, conn, share))
            except (OSError, ValueError) as err:
                self._failed(k, f"could not start or reach worker {k + 1}: {err}")
                sent.append((k, _NO_CONN, share))
        found = finish_candidates(grey, full_scale, shares[0], reader, subpixel, noise)
        for k, conn, share in sent:
            got = None if conn is _NO_CONN else self._receive(k, conn)
            if got is None:  # the worker failed: its share is done here
                got = finish_candidates(grey, full_scale, share, reader, subpixel, noise)
            found += got
        return found

    def _receive(self, k: int, conn: Connection) -> list[FiducialDetection] | None:
        try:
            if not conn.poll(WORKER_TIMEOUT_S):
                self._failed(k, f"worker {k + 1} took over {WORKER_TIMEOUT_S:g} s")
                return None
            status, payload = conn.recv()
        except (EOFError, OSError) as err:
            self._failed(k, f"worker {k + 1} died: {err or type(err).__name__}")
            return None
        if status != "ok":
            self._failed(k, f"worker {k + 1} failed: {payload}")
            return None
        return list(payload)

    def _failed(self, k: int, reason: str) -> None:
        self.failures += 1
        self.last_failure = reason
        slot = self._procs[k]
        if slot is not None:
            _stop(*slot)
            self._procs[k] = None


class _NoConnection:
    """Marks a share that never reached its worker."""


_NO_CONN: Any = _NoConnection()


def _subset(cands: Candidates, rows: NDArray[np.intp]) -> Candidates:
    return Candidates(
        cands.design, cands.centre[rows], cands.axes[rows], cands.angle[rows], cands.drift[rows]
    )


def _stop(proc: subprocess.Popen[bytes], conn: Connection) -> None:
    with contextlib.suppress(OSError, ValueError):
        conn.send(None)
    conn.close()  # the worker's recv ends: it exits even if the message was lost
    try:
        proc.wait(timeout=2.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=2.0)


def serve(conn: Connection) -> None:
    """A worker's loop: shares in, detections out, until told to stop or the parent is gone."""
    import cv2

    cv2.setNumThreads(1)  # the parallelism is the processes'
    # The parent decides when this worker stops (it closes the pipe); a Ctrl-C or a launcher's
    # SIGINT to the process group is the parent's to handle.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    image: tuple[str, NDArray[np.uint8]] | None = None
    while True:
        try:
            share = conn.recv()
        except (EOFError, OSError):
            return  # the parent closed the pipe or died
        if share is None:
            return
        try:
            if image is None or image[0] != share.shm_name:
                # The parent's block, mapped read-only as a file: attaching a SharedMemory here
                # would start a resource tracker that unlinks the block when this worker exits.
                image = (share.shm_name, np.memmap(_SHM_DIR / share.shm_name, mode="r"))
            count = int(np.prod(share.shape))
            grey = image[1].view(np.dtype(share.dtype))[:count].reshape(share.shape)
            cands = Candidates(
                get_design(share.design), share.centre, share.axes, share.angle, share.drift
            )
            found = finish_candidates(
                grey, share.full_scale, cands, share.reader, share.subpixel, share.noise
            )
            conn.send(("ok", found))
        except Exception as err:  # reported to the parent, which does the share itself
            conn.send(("error", f"{type(err).__name__}: {err}"))


if __name__ == "__main__":
    from fiducial_detector.parallel import serve as _serve_here

    _serve_here(Connection(int(sys.argv[1])))
