# The compiled kernel of fiducial_detector.components (_border_kernel.c).
from typing import Any

from numpy.typing import NDArray

def outer_borders(binary: NDArray[Any], height: int, width: int) -> tuple[bytes, bytes, bytes]: ...
