"""Object meshes for the simulated cell: the twelve shipped evaluation objects and user mesh files.

Object frame: metres, z-up, the axis-aligned bounding box centred on x = y = 0 and the lowest point at
z = 0, so an object placed with the identity pose rests on a z = 0 table. The shipped meshes (package data
in ``drivers/sim/objects/``, origins and licences in ``CREDITS.md`` there) are already in that frame; a
user file given by path is translated into it on load (no rotation; no scaling unless asked: a file in
other units than metres needs the scale that converts them, e.g. 0.001 for millimetres) and its triangles
wound outward (:func:`oriented`: eq. 13's ground truth leaves out the faces pointing down, and an inverted
file would lose its top instead of its base). ``EMPTY_TABLE``
("none") names no object at all: a simulated cell's table with nothing on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from drivers.errors import JobError

Array = NDArray[np.float64]

OBJECTS_DIR: Path = Path(__file__).resolve().parent / "objects"
"""Folder of the shipped meshes (package data of ``drivers``)."""

_CC0 = "CC0 (generated here, no third-party content)"
_YCB = "CC BY 4.0 (YCB Object and Model Set, Calli et al. 2015; attribution required)"
_STANFORD = "Stanford 3D Scanning Repository terms (research use with acknowledgement; no commercial use)"

_LICENCES: dict[str, str] = {
    "banana": _YCB,
    "baseball": _YCB,
    "bunny": _STANFORD,
    "cube": _CC0,
    "dragon": _STANFORD + "; scanned by XYZ RGB Inc.",
    "flange": _CC0,
    "gripper": "Apache-2.0 (Franka Emika GmbH, franka_description meshes)",
    "horizontal_box": _CC0,
    "mustard": _YCB,
    "pyramid": _CC0,
    "teapot": "Utah teapot (Martin Newell, 1975), widely treated as public domain",
    "vertical_box": _CC0,
}

_MESH_SUFFIXES = (".ply", ".obj", ".stl")

DEFAULT_OBJECT = "bunny"
"""The shipped object a simulated scan takes when none is named (``cell scan``; the operator's page
preselects it, ``GET /api/v1/objects`` marking it ``default``): the visual-servoing paper's own example."""

EMPTY_TABLE = "none"
"""The object name of an empty table: a simulated scene with nothing on it (no mesh, no ground truth)."""


@dataclass(frozen=True)
class ObjectMesh:
    """A triangle mesh in the object frame.

    ``vertices`` (V, 3) float64 [m], object frame (z-up, bbox centred on x = y = 0, base at z = 0);
    ``triangles`` (F, 3) int32 vertex indices, counter-clockwise seen from outside (outward normals).
    """

    name: str
    vertices: Array
    triangles: NDArray[np.int32]

    @property
    def extents_m(self) -> Array:
        """Axis-aligned bounding-box size (x, y, z) [m]."""
        return np.ptp(self.vertices, axis=0)


@dataclass(frozen=True)
class ObjectInfo:
    """A shipped object: ``name``, ``path`` of its PLY file, ``extents_m`` (3,) bbox size x, y, z [m] and a
    short ``licence`` text (full record in ``drivers/sim/objects/CREDITS.md``)."""

    name: str
    path: Path
    extents_m: Array
    licence: str


def shipped_names() -> list[str]:
    """Names of the shipped objects, sorted."""
    return sorted(p.stem for p in OBJECTS_DIR.glob("*.ply"))


def mesh_file_scale(name_or_path: str | Path, scale: float) -> float:
    """The scale that applies to the object ``name_or_path`` given with ``scale`` (a ``--object-scale``):
    ``scale`` for a mesh file, 1 for a shipped object (shipped in metres), so that a grid mixing a
    millimetre mesh with shipped objects scales the mesh only."""
    return 1.0 if str(name_or_path) in shipped_names() else scale


def list_objects() -> list[ObjectInfo]:
    """The shipped objects, sorted by name."""
    return [_info(name) for name in shipped_names()]


@cache
def _info(name: str) -> ObjectInfo:
    mesh = _load_shipped(name)
    return ObjectInfo(name=name, path=OBJECTS_DIR / f"{name}.ply", extents_m=mesh.extents_m,
                      licence=_LICENCES.get(name, "see CREDITS.md"))


def _names_hint() -> str:
    return "shipped objects: " + ", ".join(shipped_names())


def _read_mesh(path: Path) -> tuple[Array, NDArray[np.int32]]:
    """Read a PLY / OBJ / STL with Open3D; raises ``JobError`` when unreadable or empty."""
    import open3d as o3d

    if path.is_dir():
        raise JobError(f"object file {path} is a folder, not a mesh file: give the .ply/.obj/.stl file in it "
                       f"({_names_hint()})")
    if not path.is_file():
        raise JobError(f"object file not found: {path} ({_names_hint()})")
    if path.suffix.lower() not in _MESH_SUFFIXES:
        raise JobError(f"object file {path} is not a .ply/.obj/.stl mesh ({_names_hint()})")
    _check_declared_size(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(path)
    if path.suffix.lower() == ".stl":
        # an STL repeats each corner in every facet that has it (Open3D's reader keeps them apart): one
        # vertex each, six times fewer, for the same triangles
        mesh.remove_duplicated_vertices()
    vertices = np.asarray(mesh.vertices, dtype=np.float64).copy()
    triangles = np.asarray(mesh.triangles, dtype=np.int32).copy()
    if len(vertices) == 0 or len(triangles) == 0:
        raise JobError(f"object file {path} is unreadable or has no triangles ({_names_hint()})")
    if not np.all(np.isfinite(vertices)):
        raise JobError(f"object file {path} has non-finite vertices ({_names_hint()})")
    return vertices, oriented(vertices, triangles, str(path))


# Bytes per value of a binary PLY property type; an ASCII value takes at least 2 (a digit, a separator).
_PLY_BYTES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
              "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
              "double": 8, "float64": 8}
_PLY_HEADER_MAX_BYTES = 65536
_STL_HEADER_BYTES, _STL_FACET_BYTES = 84, 50


_FLAT_RELATIVE_VOLUME = 1e-9
"""Below this share of (surface area x bounding-box diagonal), a patch's signed volume is rounding noise:
the patch is flat (or a symmetric sheet) and encloses no side to point away from."""


def _edge_adjacency(tri: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                     NDArray[np.bool_], NDArray[np.int64]]:
    """The triangle pairs (a, b) that share a manifold edge (one used by exactly two triangles), whether
    each pair runs that edge the same way (inconsistent winding), and per triangle its number of edges
    used by one triangle only (boundary) or by more than two (non-manifold)."""
    f = tri.shape[0]
    heads = tri.reshape(-1)
    tails = tri[:, [1, 2, 0]].reshape(-1)
    owner = np.repeat(np.arange(f), 3)
    keys = np.sort(np.stack([heads, tails], axis=1), axis=1)
    _, edge, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    edge = edge.reshape(-1)
    order = np.argsort(edge, kind="stable")
    paired = counts[edge[order]] == 2
    first = order[paired][0::2]
    second = order[paired][1::2]
    same_way = heads[first] == heads[second]
    open_edges = np.bincount(owner, weights=(counts[edge] != 2), minlength=f).astype(np.int64)
    return owner[first], owner[second], same_way, open_edges


def oriented(vertices: Array, triangles: NDArray[np.int32], name: str) -> NDArray[np.int32]:
    """``triangles`` (F, 3) of the mesh ``vertices`` (V, 3) [m] wound counter-clockwise seen from outside
    (outward normals, as ``ObjectMesh`` and ``sample_surface`` take them); ``name`` for the error.

    Vertices at the same coordinates count as one (an STL repeats them per facet). Within each patch of
    triangles joined by edges that two triangles share, the winding is made consistent: a patch where that
    is impossible (a Moebius strip) raises ``JobError``. Then each patch is turned to enclose a positive
    signed volume, taken about the patch's own centroid: for a closed patch that is its volume, and the
    normals point out; for an open patch (a scan missing its base, an edge used by one triangle or by more
    than two) it is the same test on the surface it has, outward wherever the patch wraps around its
    centroid. A flat open patch (a sheet, no volume to tell a side by) faces up (+z), the side a camera
    above the table sees. A mesh already so wound is returned unchanged (every shipped one is)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, canonical = np.unique(vertices, axis=0, return_inverse=True)
    tri = canonical.reshape(-1)[triangles].astype(np.int64)
    f = tri.shape[0]
    a, b, same_way, open_edges = _edge_adjacency(tri)
    # two states per triangle (kept, flipped); a consistent pair keeps both in the same state
    rows = np.concatenate([a, a + f])
    cols = np.concatenate([np.where(same_way, b + f, b), np.where(same_way, b, b + f)])
    graph = coo_matrix((np.ones(rows.shape[0]), (rows, cols)), shape=(2 * f, 2 * f))
    _, state = connected_components(graph, directed=False)
    kept, flipped = state[:f], state[f:]
    if np.any(kept == flipped):
        raise JobError(f"object file {name} cannot be oriented: a part of its surface is one-sided (a "
                       "Moebius strip), so it has no outside; repair the mesh")
    flip = kept > flipped  # each patch keeps the winding of its state with the lower label
    patch = np.minimum(kept, flipped)
    consistent = np.where(flip[:, None], triangles[:, [0, 2, 1]], triangles)
    v = vertices[consistent]
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    _, patch = np.unique(patch, return_inverse=True)
    n = int(patch.max()) + 1
    total = np.maximum(np.bincount(patch, weights=area, minlength=n), np.finfo(float).tiny)
    centroid = np.stack([np.bincount(patch, weights=area * v[:, :, k].mean(axis=1), minlength=n)
                         for k in range(3)], axis=1) / total[:, None]
    rel = v - centroid[patch][:, None, :]
    cones = np.einsum("ij,ij->i", rel[:, 0], np.cross(rel[:, 1], rel[:, 2])) / 6.0
    volume = np.bincount(patch, weights=cones, minlength=n)
    up = np.bincount(patch, weights=cross[:, 2], minlength=n)
    size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    flat = np.abs(volume) <= _FLAT_RELATIVE_VOLUME * total * size
    closed = np.bincount(patch, weights=open_edges, minlength=n) == 0
    inward = np.where(flat & ~closed, up < 0.0, volume < 0.0)
    turn = inward[patch]
    return np.where(turn[:, None], consistent[:, [0, 2, 1]], consistent).astype(np.int32)


def _check_declared_size(path: Path) -> None:
    """Raise ``JobError`` when a PLY header's element counts, or a binary STL's facet count, promise more
    than the file holds: the reader allocates what the header declares before it reads, and a 180-byte
    file declaring 200 million vertices took 10 GB."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(_PLY_HEADER_MAX_BYTES)
    if path.suffix.lower() == ".stl" and not head.lstrip().startswith(b"solid") and len(head) >= 84:
        facets = int.from_bytes(head[80:84], "little")
        if _STL_HEADER_BYTES + _STL_FACET_BYTES * facets > size:
            raise JobError(f"object file {path} declares {facets} facets, more than its {size} bytes hold")
        return
    if path.suffix.lower() != ".ply" or b"end_header" not in head:
        return
    header = head[:head.index(b"end_header")].decode("ascii", errors="replace").split("\n")
    binary = any(line.startswith("format binary") for line in header)
    needed = 0
    count = per_element = 0
    for words in (line.split() for line in header):
        if words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            needed += count * per_element
            count, per_element = int(words[2]), 0
        elif words[:1] == ["property"] and len(words) >= 3:
            # a list property takes at least its count; a value at least its size (2 in ASCII)
            kind = words[2] if words[1] == "list" else words[1]
            per_element += _PLY_BYTES.get(kind, 1) if binary else 2
    needed += count * per_element
    if needed > size:
        raise JobError(f"object file {path}: its header declares elements of at least {needed} bytes, more "
                       f"than the file's {size}")


@cache
def _load_shipped(name: str) -> ObjectMesh:
    vertices, triangles = _read_mesh(OBJECTS_DIR / f"{name}.ply")
    vertices.setflags(write=False)
    triangles.setflags(write=False)
    return ObjectMesh(name=name, vertices=vertices, triangles=triangles)


def recentre(vertices: Array) -> Array:
    """Translate vertices [m] so that the bbox is centred on x = y = 0 and the lowest point is at z = 0."""
    lo = vertices.min(axis=0)
    hi = vertices.max(axis=0)
    shift = np.array([-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]])
    return vertices + shift


def load_object(name_or_path: str | Path, scale: float = 1.0) -> ObjectMesh:
    """Load a shipped object by name, or any PLY / OBJ / STL mesh file by path, its coordinates
    multiplied by ``scale`` (1: the file is in metres; 0.001: in millimetres).

    A shipped name at scale 1 returns the mesh as shipped (already in the object frame; cached, its
    arrays are read-only, copy them to modify). A user file is read with Open3D, scaled and translated
    into the object frame (bbox centred on x = y = 0, lowest point at z = 0); it is not rotated, so it
    must be z-up. Its ``name`` is the file stem.

    Raises ``JobError`` (one line, listing the shipped names) for an unknown name, an unreadable, empty
    or non-mesh file, or a scale that is not a positive finite number.
    """
    if not (np.isfinite(scale) and scale > 0.0):
        raise JobError(f"an object's scale must be a positive number, got {scale}")
    text = str(name_or_path)
    if text in shipped_names():
        shipped = _load_shipped(text)
        if scale == 1.0:
            return shipped
        # the object frame's origin is on the base, so scaling keeps the mesh in it
        return ObjectMesh(name=text, vertices=shipped.vertices * scale, triangles=shipped.triangles.copy())
    path = Path(text).expanduser()
    if path.suffix.lower() not in _MESH_SUFFIXES and not path.exists():
        raise JobError(f"unknown object {text!r} ({_names_hint()}; {EMPTY_TABLE!r} for an empty table; or "
                       "give a path to a .ply/.obj/.stl file)")
    vertices, triangles = _read_mesh(path)
    return ObjectMesh(name=path.stem, vertices=recentre(vertices * scale), triangles=triangles)


def write_mesh(mesh: ObjectMesh, path: Path) -> None:
    """Write ``mesh`` as a binary PLY file [m, object frame], which ``load_object`` reads back as it is."""
    import open3d as o3d

    # Open3D takes writable arrays only (a shipped mesh's are read-only)
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices.copy()),
                                    o3d.utility.Vector3iVector(mesh.triangles.copy()))
    if not o3d.io.write_triangle_mesh(path, out):
        raise JobError(f"cannot write the mesh {mesh.name} to {path}")


def face_normals(vertices: Array, triangles: NDArray[np.int32]) -> tuple[Array, Array]:
    """Unit outward normals (F, 3) and areas (F,) [m^2] of the triangles (zero normal for degenerate ones)."""
    v = vertices[triangles]
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0.0)
    return normals, 0.5 * norm


def sample_surface(mesh: ObjectMesh, n: int, rng: np.random.Generator, *,
                   exclude_down_deg: float = 45.0) -> Array:
    """Sample ``n`` points (n, 3) [m, object frame] uniformly (area-weighted) on the visible-ish surface.

    Faces whose outward normal makes an angle of ``exclude_down_deg`` [deg] or less with straight down
    (-z) are left out (scanning paper, eq. 13 and the paragraph after it: the ground truth keeps only
    surfaces that point mostly sideways or upwards). ``exclude_down_deg = 0`` keeps all but exactly
    downward faces; a negative value keeps every face. Within the kept faces a triangle is drawn with
    probability proportional to its area and a point uniformly inside it.
    """
    if n < 0:
        raise ValueError(f"sample_surface: n must be >= 0, got {n}")
    normals, areas = face_normals(mesh.vertices, mesh.triangles)
    # angle(normal, -z) > exclude  <=>  dot(normal, -z) < cos(exclude)  <=>  n_z > -cos(exclude)
    keep = normals[:, 2] > -np.cos(np.deg2rad(exclude_down_deg)) if exclude_down_deg >= 0.0 else areas >= 0
    weights = np.where(keep, areas, 0.0)
    total = weights.sum()
    if total <= 0.0:
        raise ValueError(f"sample_surface: mesh {mesh.name!r} has no face left after the exclusion")
    faces = rng.choice(len(weights), size=n, p=weights / total)
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    v = mesh.vertices[mesh.triangles[faces]]
    return ((1.0 - r1)[:, None] * v[:, 0] + (r1 * (1.0 - r2))[:, None] * v[:, 1]
            + (r1 * r2)[:, None] * v[:, 2])
