"""Type stub of the compiled entropy-objective loop (``_objective.pyx``, visual-servoing paper eq. 7-9)."""

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

F64: TypeAlias = NDArray[np.float64]

def max_threads() -> int: ...

class Scorer:
    def __init__(self, dirs: F64, crop_in: F64, crop_out: F64, roi_lo: F64, roi_hi: F64, res: float,
                 k_lo: NDArray[np.int64], shape: NDArray[np.int64], voxels: F64) -> None: ...
    def score(self, poses: F64, out: F64, n_threads: int) -> None: ...
