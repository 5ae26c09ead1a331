"""OctoMap .bt export/import: own round trip (with pruning) and, when pyoctomap is installed, files that
OctoMap reads and writes."""

from __future__ import annotations

import numpy as np
import pytest

from cell.perception.occupancy import OccupancyMap, OccupancyParams, logit
from cell.perception.octomap_io import HEADER, read_bt, write_bt

RES = 0.01


def scanned_map(res: float = RES) -> OccupancyMap:
    m = OccupancyMap(OccupancyParams(resolution_m=res))
    rng = np.random.default_rng(3)
    origin = np.array([0.013, -0.021, 0.4])
    ends = np.column_stack([rng.uniform(-0.1, 0.1, 400), rng.uniform(-0.1, 0.1, 400),
                            rng.uniform(0.0, 0.05, 400)])
    m.integrate(origin, ends)
    m.integrate(origin + np.array([0.1, 0.0, 0.0]), ends[:200])
    return m


def key_set(keys: np.ndarray) -> set[tuple[int, int, int]]:
    return {tuple(int(v) for v in k) for k in keys}


def test_round_trip_keeps_occupied_and_free(tmp_path):
    m = scanned_map()
    path = tmp_path / "map.bt"
    n_nodes = write_bt(m, path)
    assert n_nodes > 0
    text = path.read_bytes()
    assert text.startswith(HEADER.encode() + b"\n")
    assert b"\nid OcTree\n" in text and b"\nres 0.01\n" in text and b"\ndata\n" in text
    r = read_bt(path)
    assert r.resolution_m == RES
    assert key_set(r.occupied_keys()) == key_set(m.occupied_keys())
    assert key_set(r.free_keys()) == key_set(m.free_keys())
    assert np.allclose(r.probability(r.occupied_centers()), 0.97)
    assert np.allclose(r.probability(r.free_centers()), 0.12)


def test_pruned_block_and_negative_keys(tmp_path):
    m = OccupancyMap(OccupancyParams(resolution_m=RES))
    cube = np.stack(np.meshgrid(*[np.arange(-2, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)  # 4^3
    m.set_logodds(cube, np.full(cube.shape[0], logit(0.9)))
    m.set_logodds(np.array([[5, 0, 0], [-7, 3, 1]]), np.array([logit(0.2), logit(0.3)]))
    path = tmp_path / "cube.bt"
    n_nodes = write_bt(m, path)
    r = read_bt(path)
    assert key_set(r.occupied_keys()) == key_set(cube)
    assert key_set(r.free_keys()) == {(5, 0, 0), (-7, 3, 1)}
    # the 4^3 cube spans 8 octants around the origin, each a pruned 2^3 leaf: far fewer nodes than voxels
    assert n_nodes < 16 * 8 + 66


def test_empty_map_and_bad_files(tmp_path):
    m = OccupancyMap(OccupancyParams(resolution_m=0.005))
    path = tmp_path / "empty.bt"
    assert write_bt(m, path) == 0
    r = read_bt(path)
    assert r.n_known == 0 and r.resolution_m == 0.005
    bad = tmp_path / "bad.bt"
    bad.write_bytes(b"# not octomap\n")
    with pytest.raises(ValueError, match="not an OctoMap"):
        read_bt(bad)
    far = OccupancyMap(OccupancyParams(resolution_m=0.001))
    far.set_logodds(np.array([[40000, 0, 0]]), np.array([1.0]))
    with pytest.raises(ValueError, match="key range"):
        write_bt(far, tmp_path / "far.bt")


def _octomap_leaves(tree, res: float) -> tuple[set, set]:
    occ, free = set(), set()
    for leaf in tree.begin_leafs():
        c = np.array(leaf.getCoordinate())
        size = leaf.getSize()
        n = round(size / res)
        k0 = np.floor((c - size / 2) / res + 0.5).astype(int)
        g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) + k0
        (occ if tree.isNodeOccupied(leaf.current_node) else free).update(key_set(g))
    return occ, free


def test_pyoctomap_reads_our_file(tmp_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    m = scanned_map()
    path = tmp_path / "ours.bt"
    write_bt(m, path)
    tree = pyoctomap.OcTree(RES)
    assert tree.readBinary(str(path))
    occ, free = _octomap_leaves(tree, RES)
    assert occ == key_set(m.occupied_keys())
    assert free == key_set(m.free_keys())


def test_we_read_a_file_pyoctomap_wrote(tmp_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    rng = np.random.default_rng(5)
    tree = pyoctomap.OcTree(RES)
    ends = np.column_stack([rng.uniform(-0.1, 0.1, 300), rng.uniform(-0.1, 0.1, 300),
                            rng.uniform(0.0, 0.04, 300)])
    tree.insertPointCloud(ends, np.array([0.02, 0.01, 0.3]), -1.0)
    path = tmp_path / "octomap.bt"
    assert tree.writeBinary(str(path))
    occ, free = _octomap_leaves(tree, RES)
    r = read_bt(path)
    assert key_set(r.occupied_keys()) == occ
    assert key_set(r.free_keys()) == free


def test_same_voxels_and_states_as_octomap_over_several_scans():
    """Independent reference: OctoMap itself (pyoctomap insertPointCloud, discretize=false, maxrange),
    three overlapping scans from different origins with rays beyond the max range."""
    pyoctomap = pytest.importorskip("pyoctomap")
    rng = np.random.default_rng(7)
    ours = OccupancyMap(OccupancyParams(resolution_m=RES, max_range_m=0.45))
    tree = pyoctomap.OcTree(RES)
    tree.setProbHit(0.7)
    tree.setProbMiss(0.4)
    for origin in ([0.013, -0.021, 0.4], [0.21, 0.05, 0.33], [-0.12, 0.17, 0.52]):
        ends = np.column_stack([rng.uniform(-0.1, 0.1, 500), rng.uniform(-0.1, 0.1, 500),
                                rng.uniform(-0.05, 0.05, 500)])
        ours.integrate(np.array(origin), ends)
        tree.insertPointCloud(ends, np.array(origin), 0.45)
    occ, free = _octomap_leaves(tree, RES)
    ours_occ, ours_free = key_set(ours.occupied_keys()), key_set(ours.free_keys())
    both = (occ | free) & (ours_occ | ours_free)
    assert len(both) >= 0.99 * len(occ | free) and len(both) >= 0.99 * len(ours_occ | ours_free)
    agree = sum((k in occ) == (k in ours_occ) for k in both)
    assert agree >= 0.99 * len(both)
