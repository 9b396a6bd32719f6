"""armourcam's benchmarks: printed tables beside the paper's and peers' figures (see run_all).

Speed is measured on one thread: numpy's BLAS (the edge fit's batched products) reads its
thread-count variables when numpy loads, which is after this package is imported by ``python -m
benchmarks.<name>``; :mod:`armourcam.blas` (numpy-free) sets them, an explicit setting wins.
"""

from armourcam.blas import one_blas_thread

one_blas_thread()
