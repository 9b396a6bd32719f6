"""armourcam's benchmarks: printed tables beside the paper's and peers' figures (see run_all).

Speed is measured on one thread: numpy's BLAS (the edge fit's batched products) reads these
variables when numpy loads, which is after this package is imported by ``python -m
benchmarks.<name>``; an explicit setting in the environment wins.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
