"""Batched small-matrix linear algebra with the matrix axes first.

Stacks of tiny matrices are stored as ``(m, m, ...)``: each matrix entry is one contiguous array
over the batch, so one numpy operation updates that entry of every matrix at once. For thousands
of 5x5 or 6x6 matrices this is several times faster than per-matrix LAPACK calls
(:func:`numpy.linalg.inv`, ``eigh``, ``svd``), whose cost is dominated by per-matrix overhead.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def spd_inverse(A: F64, *, overwrite: bool = False) -> F64:
    """Inverses of a stack of symmetric positive-definite matrices ``(m, m, ...)``.

    Gauss-Jordan elimination without pivoting, which is stable for symmetric positive-definite
    matrices (as Cholesky is). Singular or indefinite matrices give non-finite or meaningless
    entries: callers check. With ``overwrite`` a C-contiguous float64 ``A`` is inverted in place
    and returned (for callers done with it: a stack of thousands of matrices is worth not
    copying).
    """
    m = A.shape[0]
    if overwrite and A.dtype == np.float64 and A.flags.c_contiguous and A.flags.writeable:
        B = A
    else:
        B = np.array(A, dtype=np.float64, order="C")
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(m):
            p = 1.0 / B[k, k]
            B[k, k] = 1.0
            B[k] *= p
            # Eliminate column k from every other row at once: B[i] -= B[i, k] * B[k].
            col = B[:, k].copy()
            col[k] = 0.0
            B[:, k] = 0.0
            B[k, k] = p
            B -= col[:, None] * B[k][None]
    return B
