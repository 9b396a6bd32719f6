"""One BLAS thread per armourcam process, unless the environment says otherwise.

armourcam's cores solve many tiny systems in batches (5x5 ellipse fits, 3x3 covariances), where
OpenBLAS' extra threads do not make a frame faster but spin on the other cores: on the 400-target
speed frame the detector took 187 ms of wall time and 373 ms of CPU with them, 195 ms and
195 ms without. On a two-core rig that spinning is taken from the other nodes. BLAS reads these
variables once, when numpy is first imported, so they are set before that: by the command line
for its own process and by the graph launcher for the nodes it starts.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(env: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """Default every BLAS thread-count variable of ``env`` (``os.environ``) to 1; an explicit
    setting wins. Returns ``env``."""
    target: MutableMapping[str, str] = os.environ if env is None else env
    for name in BLAS_THREAD_VARIABLES:
        target.setdefault(name, "1")
    return target
