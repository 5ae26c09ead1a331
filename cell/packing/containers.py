"""Container choice: the smallest container of the catalogue that holds the object's box plus clearance."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.packing.config import ContainerConfig

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ContainerChoice:
    """The chosen container (None when none fits), whether the object goes in turned by 90 degrees about
    the vertical (its L along the container's W), and why, in words."""

    container: ContainerConfig | None
    rotated: bool
    reason: str


def required_inner_dims(dims: Array, margin_m: float) -> Array:
    """Inner (L, W, H) [m] a container needs for a box of ``dims`` (L, W, H) [m]: ``margin_m`` of clearance
    on both sides in the table plane and above the object, which stands on the container floor."""
    return np.asarray(dims, dtype=float) + np.array([2.0 * margin_m, 2.0 * margin_m, margin_m])


def choose_container(dims: Array, containers: list[ContainerConfig], margin_m: float) -> ContainerChoice:
    """The container with the smallest inner volume that holds a box of ``dims`` (L, W, H) [m] with
    ``margin_m`` [m] of clearance, the box either way round in the plane (the yaw swap of L and W); ties
    go to the first in the catalogue."""
    need = required_inner_dims(dims, margin_m)
    best: tuple[float, int, bool] | None = None
    for i, c in enumerate(containers):
        inner = np.asarray(c.inner_dims_m, dtype=float)
        if need[2] > inner[2]:
            continue
        straight = need[0] <= inner[0] and need[1] <= inner[1]
        turned = need[0] <= inner[1] and need[1] <= inner[0]
        if not (straight or turned):
            continue
        volume = float(np.prod(inner))
        if best is None or volume < best[0]:
            best = (volume, i, not straight)
    need_text = " x ".join(f"{v:.3f}" for v in need)
    if best is None:
        if not containers:
            return ContainerChoice(None, False, "none fits: the catalogue (packing.containers) is empty")
        return ContainerChoice(None, False, f"none fits: no container holds {need_text} m "
                                            f"(object plus {margin_m:g} m clearance on each side and on top)")
    chosen = containers[best[1]]
    turn = ", turned by 90 deg" if best[2] else ""
    dims_text = " x ".join(f"{v:.3f}" for v in dims)
    return ContainerChoice(chosen, best[2], f"smallest container holding {need_text} m ({dims_text} m plus "
                                            f"{margin_m:g} m clearance on each side and on top){turn}")
