"""The papers' experiments and the held-out set as grids (``cell eval vs-table|packing|heldout``).

- ``vs-table``: the visual-servoing paper's Table I, its eight objects x VS-Local, VS-Global, VS-Hybrid
  at the station's centre on the shipped ``sim-franka-rgbd`` cell; the paper ran each three times and
  measured the clouds re-processed offline at 1 mm (section III-B), so each job is re-processed; its
  report is Table I's, without the packing paper's section (results.csv keeps its scans' packing figures).
- ``packing``: the LR-NBV paper's section 4, its four objects x LR-NBV, NBV, HEU, five runs each, on the
  shipped ``sim-ur5e-tof`` cell.
- ``heldout``: fifteen shapes and placements that are not Table I's (nine of the shapes built here: a can,
  a ring lying flat, a cone, a thin upright slab, and the hard cases of issue 24: an open cup (thin
  walls), a ring standing up and a washer (holes; the washer also flat), a mushroom (an overhang) and a
  tall square post; the two packing boxes turned; four of Table I's objects moved and turned), VS-Local on
  ``sim-franka-rgbd``: the figures away from the objects the planners were tuned on. Each object has its
  own placement.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from cell.evaluation import paper
from cell.evaluation.spec import Placement, ScanSpec, check_specs, cross
from cell.templates import template_path
from drivers.errors import CellError
from drivers.sim.objects import ObjectMesh, recentre, write_mesh

CENTRE: Placement = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Preset:
    """A grid's defaults: cell file, objects with their placements, planners, seeds and whether each job
    is re-processed as the visual-servoing paper measures Table I (``ScanSpec.reprocess``); and whether
    its report has the packing section (``cell.evaluation.report.write_report``)."""

    config: Path
    cases: tuple[tuple[str, Placement], ...]
    planners: tuple[str, ...]
    seeds: tuple[int, ...]
    reprocess: bool = False
    packing_report: bool = True

    def specs(self, config: Path | None = None, objects: Sequence[str] | None = None,
              placements: Sequence[Placement] | None = None, planners: Sequence[str] | None = None,
              seeds: Sequence[int] | None = None, max_time_s: float | None = None,
              reprocess: bool | None = None, object_scale: float = 1.0) -> list[ScanSpec]:
        """The grid of this preset with whatever is given in place of its own (``object_scale``: of every
        object's mesh, into metres), checked (``check_specs``).
        Given objects alone: those of the preset's own (by name: a shape file's stem) at the preset's
        placements of them, any other at each of the preset's distinct placements (or the station's
        centre); given placements: crossed with the given objects, or the preset's."""
        cases = self.cases
        if placements:
            cases = crossed([self._named(o) for o in objects] if objects
                            else list(dict.fromkeys(o for o, _ in self.cases)), placements)
        elif objects:
            everywhere = list(dict.fromkeys(p for _, p in self.cases)) or [CENTRE]
            cases = tuple(case for o in objects for case in
                          ([c for c in self.cases if c[0] == self._named(o)] or crossed([o], everywhere)))
        specs = cross(str((config or self.config).resolve()), cases, planners or self.planners,
                      seeds or self.seeds, max_time_s, self.reprocess if reprocess is None else reprocess,
                      object_scale)
        check_specs(specs)
        return specs

    def _named(self, obj: str) -> str:
        """The preset's own object ``obj`` names (itself, or a shape file of that stem), else ``obj``."""
        return next((o for o, _ in self.cases if o == obj or Path(o).stem == obj), obj)


VS_TABLE = Preset(template_path("sim-franka-rgbd"), tuple((o, CENTRE) for o in paper.TABLE_I_OBJECTS),
                  paper.VS_PLANNERS, (0, 1, 2), reprocess=True, packing_report=False)
PACKING = Preset(template_path("sim-ur5e-tof"), tuple((o, CENTRE) for o in paper.PACKING_OBJECTS),
                 paper.PACKING_PLANNERS, (0, 1, 2, 3, 4))
# (object: a shape of ``heldout_shapes`` or a shipped name, placement)
HELDOUT_CASES: tuple[tuple[str, Placement], ...] = (
    ("cylinder", CENTRE), ("torus", CENTRE), ("cone", CENTRE), ("slab", (0.0, 0.0, 30.0)),
    ("horizontal_box", (0.0, 0.0, 20.0)), ("vertical_box", (0.0, 0.0, -15.0)),
    ("bunny", (0.05, -0.04, 60.0)), ("mustard", (-0.04, 0.05, -40.0)), ("cube", (0.0, 0.0, 30.0)),
    ("teapot", (0.03, 0.03, 120.0)), ("cup", CENTRE), ("standing_ring", (0.0, 0.0, 45.0)),
    ("washer", (0.02, 0.0, 0.0)), ("mushroom", CENTRE), ("post", (-0.02, 0.02, 10.0)),
)


def lathe(profile: Sequence[tuple[float, float]], segments: int = 48) -> o3d.geometry.TriangleMesh:
    """The closed surface swept by revolving ``profile`` about the z axis: (r, z) [m] points of a closed
    polygon, counter-clockwise in the (r, z) half-plane (the solid on its left); points with r = 0 lie on
    the axis and become one vertex. Faces point out of the solid."""
    angles = 2.0 * np.pi * np.arange(segments) / segments
    rings: list[list[int]] = []
    vertices: list[list[float]] = []
    for r, z in profile:
        if r == 0.0:
            rings.append([len(vertices)] * segments)
            vertices.append([0.0, 0.0, z])
        else:
            rings.append(list(range(len(vertices), len(vertices) + segments)))
            vertices.extend([r * np.cos(a), r * np.sin(a), z] for a in angles)
    triangles = []
    for i in range(len(rings)):
        lower, upper = rings[i], rings[(i + 1) % len(rings)]
        for j in range(segments):
            k = (j + 1) % segments
            # (a, b, c) with b one step round the axis and c one step along the profile: the normal
            # (b - a) x (c - a) points to the right of the profile, out of the solid
            for tri in ((lower[j], lower[k], upper[k]), (lower[j], upper[k], upper[j])):
                if len(set(tri)) == 3:
                    triangles.append(tri)
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.array(vertices)),
                                     o3d.utility.Vector3iVector(np.array(triangles, dtype=np.int32)))


def _shapes() -> dict[str, o3d.geometry.TriangleMesh]:
    """The held-out shapes [m]: a can, a ring lying flat, a cone, a thin upright slab; an open cup with
    4 mm walls, a ring standing on its rim, a washer with a 4 cm hole, a mushroom whose cap overhangs its
    stem by 2 cm, and a 4 x 4 x 18 cm post; and parts thin or tapering at the 8 x 8 sensor's scale: a 6 cm
    spire 15 cm tall, a 12 cm dome, a bottle with a 2.4 cm neck to 18 cm and a lamp, a 12 cm disc with a
    16 mm rod to 15 cm."""
    standing_ring = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.04, tube_radius=0.012,
                                                           radial_resolution=48, tubular_resolution=24)
    standing_ring.rotate(o3d.geometry.get_rotation_matrix_from_xyz((np.pi / 2, 0.0, 0.0)), center=(0, 0, 0))
    return {"cup": lathe([(0.0, 0.0), (0.045, 0.0), (0.045, 0.07), (0.041, 0.07), (0.041, 0.004),
                          (0.0, 0.004)]),
            "standing_ring": standing_ring,
            "washer": lathe([(0.02, 0.0), (0.06, 0.0), (0.06, 0.012), (0.02, 0.012)]),
            "mushroom": lathe([(0.0, 0.0), (0.02, 0.0), (0.02, 0.06), (0.04, 0.06), (0.045, 0.07),
                               (0.035, 0.085), (0.0, 0.09)]),
            "post": o3d.geometry.TriangleMesh.create_box(width=0.04, height=0.04, depth=0.18),
            "cylinder": o3d.geometry.TriangleMesh.create_cylinder(radius=0.035, height=0.11, resolution=48),
            "torus": o3d.geometry.TriangleMesh.create_torus(torus_radius=0.045, tube_radius=0.018,
                                                              radial_resolution=48, tubular_resolution=24),
            "cone": o3d.geometry.TriangleMesh.create_cone(radius=0.05, height=0.09, resolution=48),
            "slab": o3d.geometry.TriangleMesh.create_box(width=0.14, height=0.03, depth=0.09),
            "spire": lathe([(0.0, 0.0), (0.03, 0.0), (0.0, 0.15)]),
            "dome": lathe([(0.0, 0.0), *((0.06 * np.cos(a), 0.06 * np.sin(a))
                                         for a in np.linspace(0.0, np.pi / 2, 10)[:-1]), (0.0, 0.06)]),
            "bottle": lathe([(0.0, 0.0), (0.035, 0.0), (0.035, 0.11), (0.012, 0.14), (0.012, 0.18),
                             (0.0, 0.18)]),
            "lamp": lathe([(0.0, 0.0), (0.06, 0.0), (0.06, 0.015), (0.008, 0.015), (0.008, 0.15),
                           (0.0, 0.15)])}


def write_heldout_shapes(folder: Path) -> dict[str, Path]:
    """Each held-out shape as a PLY mesh in ``folder`` (bbox centred on x = y = 0, base at z = 0); the
    files are the same bytes every time, so the scans' keys are too."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, mesh in _shapes().items():
        paths[name] = folder / f"{name}.ply"
        write_mesh(ObjectMesh(name, recentre(np.asarray(mesh.vertices)),
                              np.asarray(mesh.triangles, dtype=np.int32)), paths[name])
    return paths


def heldout(folder: Path) -> Preset:
    """The held-out preset, its shapes written into ``folder``."""
    try:
        shapes = write_heldout_shapes(folder)
    except OSError as exc:
        raise CellError(f"cannot write the held-out shapes into {folder}: {exc}") from None
    cases = tuple((str(shapes[o]) if o in shapes else o, p) for o, p in HELDOUT_CASES)
    return Preset(template_path("sim-franka-rgbd"), cases, ("vs-local",), (0,))


def crossed(objects: Sequence[str], placements: Sequence[Placement]) -> tuple[tuple[str, Placement], ...]:
    """Every object at every placement."""
    return tuple((o, p) for o in objects for p in placements)
