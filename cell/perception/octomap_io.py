"""OctoMap binary ``.bt`` export and import of an ``OccupancyMap`` (the job folder's ``map.bt`` opens in
octovis and pyoctomap).

Format (OctoMap ``OcTree::writeBinary``): ASCII header lines

    # Octomap OcTree binary file
    id OcTree
    size <number of tree nodes>
    res <voxel edge [m]>
    data

then the tree in depth-first pre-order, children in index order 0..7. Each inner node writes two bytes
holding 2 bits per child (children 0-3 in the first byte, 4-7 in the second, child i of a byte in bits
2i and 2i+1): 00 child absent (unknown), bit 2i+1 alone occupied leaf, bit 2i alone free leaf, both
bits an inner node whose own two bytes follow later in the pre-order. Only the maximum-likelihood state is
stored: on reading, occupied leaves get the clamping maximum and free leaves the clamping minimum, as
OctoMap's reader does.

Keys: tree depth 16, key = floor(x / res) + 32768 per axis (voxel centre (key - 32768 + 0.5) res, the same
grid as ``OccupancyMap``). The child index of a node at depth d (root d = 0) is bit (15 - d) of the x key
+ 2 * that bit of y + 4 * that bit of z. A leaf above depth 16 covers all voxels below it (OctoMap prunes
8 identical leaves into their parent); the writer prunes in the same way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.perception.occupancy import OccupancyMap, OccupancyParams, logit
from drivers.atomic_file import atomic_open

TREE_DEPTH = 16
KEY_OFFSET = 1 << (TREE_DEPTH - 1)  # 32768
HEADER = "# Octomap OcTree binary file"
_FREE, _OCC, _INNER = 1, 2, 3  # 2-bit child codes


def _morton(keys: NDArray[np.int64], bits: int) -> NDArray[np.int64]:
    """Interleave the low ``bits`` bits of (x, y, z) keys, x least significant in each 3-bit group."""
    m = np.zeros(keys.shape[0], dtype=np.int64)
    for i in range(bits):
        for axis in range(3):
            m |= ((keys[:, axis] >> i) & 1) << (3 * i + axis)
    return m


def write_bt(occ_map: OccupancyMap, path: str | Path) -> int:
    """Write the maximum-likelihood occupancy of ``occ_map`` to an OctoMap ``.bt`` file; returns the
    number of tree nodes. Raises ValueError if a voxel lies outside OctoMap's key range (+-32768 voxels)."""
    keys, lo = occ_map.known_keys()
    keys = keys + KEY_OFFSET
    if keys.size and (keys.min() < 0 or keys.max() >= (1 << TREE_DEPTH)):
        raise ValueError(f"map extends beyond OctoMap's key range (+-{KEY_OFFSET} voxels of "
                         f"{occ_map.resolution_m} m)")
    state = np.where(occ_map.classify_logodds(lo), _OCC, _FREE).astype(np.int64)
    # Bottom-up: at each level the nodes (keys at that depth) and their state (leaf code or inner).
    inner_levels: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []  # (parent keys, child codes)
    n_nodes = 0
    for depth in range(TREE_DEPTH, 0, -1):
        n_nodes += keys.shape[0]
        if keys.shape[0] == 0:
            break
        parent = keys >> 1
        child = (keys[:, 0] & 1) | ((keys[:, 1] & 1) << 1) | ((keys[:, 2] & 1) << 2)
        pid = _morton(parent, depth - 1)
        uniq, inv = np.unique(pid, return_inverse=True)
        code = np.zeros(uniq.size, dtype=np.int64)
        np.bitwise_or.at(code, inv, state << (2 * child))
        first = np.zeros(uniq.size, dtype=np.int64)
        first[inv[::-1]] = np.arange(inv.size)[::-1]
        pkeys = parent[first]
        # prune: 8 leaves of the same state become one leaf (never at the root)
        all_free = code == 0x5555
        all_occ = code == 0xAAAA
        pstate = np.where(all_free, _FREE, np.where(all_occ, _OCC, _INNER))
        if depth - 1 == 0:
            pstate[:] = _INNER
        is_inner = pstate == _INNER
        inner_levels.append((pkeys[is_inner], code[is_inner]))
        # pruned children are no longer nodes
        n_nodes -= int(np.count_nonzero(~is_inner)) * 8
        keys, state = pkeys, pstate
    # Pre-order: sort inner nodes by the Morton code of their first voxel, parents before children.
    mort, dep, codes = [], [], []
    for level, (pkeys, code) in enumerate(inner_levels):
        depth = TREE_DEPTH - 1 - level
        mort.append(_morton(pkeys, depth) << (3 * (TREE_DEPTH - depth)))
        dep.append(np.full(pkeys.shape[0], depth, dtype=np.int64))
        codes.append(code)
    path = Path(path)
    n_total = n_nodes + (1 if inner_levels else 0)  # + root
    with atomic_open(path) as f:  # whole or not at all (drivers.atomic_file)
        f.write(f"{HEADER}\n# (written by cell.perception.octomap_io)\n#\nid OcTree\nsize {n_total}\n"
                f"res {occ_map.resolution_m!r}\ndata\n".encode("ascii"))
        if inner_levels:
            m = np.concatenate(mort)
            d = np.concatenate(dep)
            c = np.concatenate(codes)
            order = np.lexsort((d, m))
            f.write(c[order].astype("<u2").tobytes())
    return n_total


def read_bt(path: str | Path, params: OccupancyParams | None = None) -> OccupancyMap:
    """Read an OctoMap ``.bt`` file into a new ``OccupancyMap`` (resolution from the file; other sensor
    parameters from ``params`` or ``OccupancyParams``' defaults). Occupied voxels get logit(clamp_max),
    free voxels logit(clamp_min); pruned leaves are expanded to all their voxels."""
    data = Path(path).read_bytes()
    pos = 0
    first = True
    header: dict[str, str] = {}
    while True:
        end = data.index(b"\n", pos)
        line = data[pos:end].decode("ascii").strip()
        pos = end + 1
        if first:
            if line != HEADER:
                raise ValueError(f"{path}: not an OctoMap binary file (first line {line!r})")
            first = False
            continue
        if not line or line.startswith("#"):
            continue
        if line == "data":
            break
        k, _, v = line.partition(" ")
        header[k] = v.strip()
    if header.get("id") != "OcTree":
        raise ValueError(f"{path}: tree type {header.get('id')!r}, expected 'OcTree'")
    res = float(header["res"])
    size = int(header.get("size", "0"))
    if params is None:
        params = OccupancyParams(resolution_m=res)
    else:
        params = params.model_copy(update={"resolution_m": res})
    occ_map = OccupancyMap(params)
    if size == 0:
        return occ_map
    buf = np.frombuffer(data, dtype=np.uint8, offset=pos)
    codes = buf[0::2].astype(np.int64) | (buf[1::2].astype(np.int64) << 8)
    # Depth-first walk with an explicit stack of (key at depth, depth); collect leaves per depth.
    leaves: list[tuple[int, int, int, int, int]] = []  # (x, y, z, depth, state)
    stack = [(0, 0, 0, 0)]
    i = 0
    while stack:
        x, y, z, depth = stack.pop()
        code = int(codes[i])
        i += 1
        children = []
        for ci in range(8):
            s = (code >> (2 * ci)) & 3
            if s == 0:
                continue
            cx, cy, cz = (x << 1) | (ci & 1), (y << 1) | ((ci >> 1) & 1), (z << 1) | ((ci >> 2) & 1)
            if s == _INNER:
                children.append((cx, cy, cz, depth + 1))
            else:
                leaves.append((cx, cy, cz, depth + 1, s))
        stack.extend(reversed(children))  # child 0 is read first
    if not leaves:
        return occ_map
    arr = np.array(leaves, dtype=np.int64)
    keys_all, states_all = [], []
    for depth in np.unique(arr[:, 3]):
        sel = arr[arr[:, 3] == depth]
        span = 1 << (TREE_DEPTH - int(depth))
        base = sel[:, :3] * span
        if span > 1:
            g = np.stack(np.meshgrid(*[np.arange(span)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
            base = (base[:, None, :] + g[None, :, :]).reshape(-1, 3)
            st = np.repeat(sel[:, 4], span**3)
        else:
            st = sel[:, 4]
        keys_all.append(base)
        states_all.append(st)
    keys = np.concatenate(keys_all) - KEY_OFFSET
    states = np.concatenate(states_all)
    occ_map.set_logodds(keys, np.where(states == _OCC, logit(params.clamp_max), logit(params.clamp_min)))
    return occ_map
