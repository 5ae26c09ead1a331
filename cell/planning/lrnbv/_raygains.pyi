"""Type stub of the compiled LR-NBV ray-gain loop (``_raygains.pyx``)."""

import numpy as np
from numpy.typing import NDArray

def ray_gains(origins: NDArray[np.float64], rotations: NDArray[np.float64], rays_sensor: NDArray[np.float64],
              weight: NDArray[np.float64], density: NDArray[np.float64], occluder: NDArray[np.uint8],
              lo: NDArray[np.float64], hi: NDArray[np.float64], resolution: float, step: float, n_max: int,
              span: int, g_e: NDArray[np.float64], g_d: NDArray[np.float64]) -> None: ...
