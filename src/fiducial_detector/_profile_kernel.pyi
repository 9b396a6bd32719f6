# The compiled kernel of fiducial_detector.profile_fit (_profile_kernel.c).
from typing import Any

from numpy.typing import NDArray

# Arrays of the dtypes and shapes sample_lines documents, C-contiguous.
Buffer = NDArray[Any]

def sample_lines(
    src: Buffer,
    kind: int,
    height: int,
    width: int,
    ellipses: Buffer,
    count: Buffer,
    lo: float,
    hi: float,
    cap: Buffer,
    polarity: Buffer,
    m: int,
    second_moment: bool,
    valid: Buffer,
    jac: Buffer,
    kappa: Buffer,
    lower: Buffer,
    upper: Buffer,
    step: Buffer,
    mean: Buffer,
    mass: Buffer,
    m2: Buffer,
    blur: Buffer = ...,
    z0: Buffer = ...,
    v0: Buffer = ...,
    good: Buffer = ...,
    t: Buffer = ...,
    typical: Buffer = ...,
    normal: Buffer = ...,
    rhs: Buffer = ...,
) -> None: ...
def normal_sums(
    jac: Buffer, t: Buffer, good: Buffer, m: int, normal: Buffer, rhs: Buffer
) -> None: ...
def solve_rounds(
    jac: Buffer,
    t: Buffer,
    use: Buffer,
    m: int,
    normal: Buffer,
    rhs: Buffer,
    q: Buffer,
    o: Buffer,
    tie_sd: float,
    min_lines: int,
    limit: float,
    delta: Buffer,
    inv: Buffer,
    sd: Buffer,
    used: Buffer,
) -> None: ...
def sample_tracks(
    src: Buffer,
    kind: int,
    height: int,
    width: int,
    centre: Buffer,
    axes: Buffer,
    angle: Buffer,
    drift: Buffer,
    weights: Buffer,
    out: Buffer,
    outside: Buffer,
) -> None: ...
