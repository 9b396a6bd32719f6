"""Keep freed memory in armourcam processes instead of handing it back to the system every frame.

The per-frame cores allocate a few MB of temporaries (the pose stage's ``(5, 5, K, N)``
covariances and Jacobians, the lens correction's boundary samples). With glibc's defaults memory
freed at the top of the heap beyond 128 KB (or twice the largest mmapped block freed so far) is
returned to the system at once, so the next frame faults every page back in: on the 400-target
pose speed frame some 150-400 page faults per call, 0.4-0.8 ms of a 5 ms
``pose_estimator.estimate`` and about 2 ms of 11 with a lens model (``benchmarks.pose_speed``).
Raising glibc's mmap and trim thresholds keeps those pages in the process; its resident size
grows once, by the frame's peak.

Applied to the running process with ``mallopt`` by every node process (:mod:`armourcam.graph`),
the command line and the pose speed benchmark. An explicit ``MALLOC_MMAP_THRESHOLD_`` or
``MALLOC_TRIM_THRESHOLD_`` in the environment wins; off glibc this does nothing.
"""

from __future__ import annotations

import ctypes
import os

#: Blocks up to this size come from the heap, not from their own mapping (bytes).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory at the top of the heap up to this size stays in the process (bytes).
TRIM_THRESHOLD = 64 * 1024 * 1024
#: glibc's environment variables for the same settings (an explicit one wins).
ALLOCATOR_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
# mallopt parameter numbers (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Raise this process's glibc mmap and trim thresholds (see the module docstring).

    Returns
    -------
    bool
        True if applied; False when the environment sets either threshold itself or the C
        library has no ``mallopt`` (not glibc).
    """
    if any(name in os.environ for name in ALLOCATOR_VARIABLES):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # Setting either disables glibc's dynamic thresholds, so both are set.
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
