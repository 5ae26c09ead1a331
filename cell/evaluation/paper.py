"""The papers' own figures, to print beside ours.

Visual-servoing paper, Table I: coverage [%], Chamfer and Hausdorff [mm] per object and strategy (means of
three runs); section III-C: the mean scan time [s] and trajectory length [m] over the objects per strategy.
The LR-NBV packing paper gives its results (Fig. 3: dimensions, IoU, coverage, poses and useless poses per
object and planner) as plots only, without numbers in its text; section 4.2 states which differences are
significant (Mann-Whitney U, p < 0.05), quoted in ``PACKING_CLAIMS``.
"""

from __future__ import annotations

TABLE_I_OBJECTS = ("bunny", "banana", "baseball", "mustard", "cube", "pyramid", "dragon", "teapot")
VS_PLANNERS = ("vs-local", "vs-global", "vs-hybrid")
# in TABLE_I_OBJECTS' order
TABLE_I: dict[str, dict[str, tuple[float, ...]]] = {
    "vs-global": {"coverage_pct": (88.2, 69.4, 77.3, 80.2, 94.9, 97.4, 90.8, 67.4),
                  "chamfer_mm": (1.5, 2.3, 2.2, 1.9, 0.9, 0.7, 1.1, 4.2),
                  "hausdorff_mm": (23.2, 14.2, 19.8, 17.4, 15.2, 15.4, 17.3, 39.3)},
    "vs-hybrid": {"coverage_pct": (95.1, 75.4, 78.8, 90.6, 95.0, 99.7, 90.6, 67.5),
                  "chamfer_mm": (0.8, 2.2, 2.3, 1.3, 0.9, 0.5, 1.1, 4.0),
                  "hausdorff_mm": (12.9, 14.5, 22.9, 14.2, 14.1, 6.7, 19.0, 39.4)},
    "vs-local": {"coverage_pct": (90.1, 71.2, 72.0, 90.8, 92.2, 99.1, 89.6, 68.9),
                 "chamfer_mm": (1.2, 2.5, 3.0, 1.4, 1.1, 0.5, 1.2, 3.8),
                 "hausdorff_mm": (17.8, 15.9, 24.8, 14.9, 16.1, 8.4, 18.8, 40.1)},
}
MEAN_SCAN_TIME_S = {"vs-local": 42.0, "vs-global": 57.0, "vs-hybrid": 67.0}
MEAN_PATH_M = {"vs-local": 0.8, "vs-global": 0.8, "vs-hybrid": 1.2}

PACKING_OBJECTS = ("horizontal_box", "vertical_box", "gripper", "flange")
PACKING_PLANNERS = ("lr-nbv", "nbv", "heu")
PACKING_CLAIMS = (
    "LR-NBV's IoU significantly better (p < 0.05) on the horizontal box and the gripper",
    "on the vertical box and the flange, a significant difference (p < 0.05) in at least one dimension",
    "LR-NBV needs significantly fewer poses (p < 0.05), often less than half of NBV's, at a comparable "
    "reconstruction percentage",
)


def table_i(planner: str, metric: str, obj: str) -> float | None:
    """Table I's figure for this strategy, metric and object; None where Table I has none."""
    if obj not in TABLE_I_OBJECTS or planner not in TABLE_I:
        return None
    return TABLE_I[planner][metric][TABLE_I_OBJECTS.index(obj)]
