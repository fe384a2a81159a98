"""Precomputed cell-to-cell visibility (mrbsp-lod-visibility.txt section 4): conservative against the
rasterizer from sampled ground viewpoints, toggling equals recomputing, storage of changes only."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import digest

import terrainwarp as tw
from terrainwarp.lod.bintree import Bintree, select_bintree
from terrainwarp.lod.visibility import VisibilityState, encode, expand, precompute_visibility
from terrainwarp.rendering import rasterize as tw_rasterize

# six 90-degree views: everything around the observer
_CUBE = [((1, 0, 0), (0, 1, 0)), ((-1, 0, 0), (0, 1, 0)), ((0, 0, 1), (0, 1, 0)), ((0, 0, -1), (0, 1, 0)),
         ((0, 1, 0), (0, 0, 1)), ((0, -1, 0), (0, 0, 1))]
_PX = 96


@pytest.fixture(scope="module")
def fbm_tree() -> Bintree:
    return Bintree.build(tw.Heightmap.fbm(129, seed=3, dx=10.0, max_height=400.0), 14)


@pytest.fixture(scope="module")
def dem_tree() -> Bintree:
    return Bintree.build(tw.Heightmap.example(), 16)


def _seen_nodes(tree: Bintree, full, eye: np.ndarray) -> np.ndarray:
    """Heap nodes of the full-depth mesh that the rasterizer shows from ``eye`` in any direction."""
    rel = (full.mesh.world_positions() - eye).astype(np.float32)
    seen = []
    for d, up in _CUBE:
        cam = tw.Camera(position=eye, target=eye + np.asarray(d, float), up=up, fov_y_deg=90.0, width=_PX,
                        height=_PX, near=0.05, far=1e6)
        fr = tw_rasterize(rel, full.mesh.triangles, cam.view_matrix(relative=True), cam.proj_matrix(), _PX, _PX)
        seen.append(full.node[np.unique(fr.triangle_id[fr.triangle_id >= 0])])
    return np.unique(np.concatenate(seen))


def _check_conservative(tree: Bintree, table, per_cell: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    full = select_bintree(tree, tw.Camera(position=(0, 0, 0), target=(1, 0, 0)), lod=False, frustum=False)
    rows, cols = table.cells
    state = table.state()
    missed = kept_hidden = kept = seen_total = 0
    for i in range(rows):
        for j in range(cols):
            for _ in range(per_cell):
                x = tree.origin[0] + (j + rng.random()) * tree.side / cols
                z = tree.origin[1] + (i + rng.random()) * tree.side / rows
                eye = np.array([x, float(tree.surface_height(x, z)) + 1.8, z])
                state.move_to(x, z)
                assert state.cell == (i, j)
                cam = tw.Camera(position=eye, target=eye + np.array([1.0, 0.0, 0.0]), near=0.05, far=1e6)
                drawn = select_bintree(tree, cam, lod=False, frustum=False, visibility=state).node
                seen = _seen_nodes(tree, full, eye)
                missed += int(np.count_nonzero(~np.isin(seen, drawn)))
                kept_hidden += int(np.count_nonzero(~np.isin(drawn, seen)))
                kept += len(drawn)
                seen_total += len(seen)
    return {"missed": missed, "kept_hidden": kept_hidden, "kept": kept, "seen": seen_total,
            "all": per_cell * rows * cols * 2 ** tree.depth}


def test_conservative_on_fbm(fbm_tree):
    table = precompute_visibility(fbm_tree, 6, 9)
    r = _check_conservative(fbm_tree, table, 2, seed=1)
    assert r["missed"] == 0, r
    assert r["kept"] < 0.95 * r["all"]  # it does hide something: the check could fail
    assert r["kept_hidden"] > 0  # and it overestimates, as the paper says


def test_conservative_on_fbm_paper_sampling(fbm_tree):
    """The paper's vertex-to-vertex sampling at the surface (no raised end points): tighter, and still no
    miss on these sampled viewpoints (measured, not argued)."""
    raised = precompute_visibility(fbm_tree, 6, 9)
    table = precompute_visibility(fbm_tree, 6, 9, raised=False, samples=4)
    r = _check_conservative(fbm_tree, table, 2, seed=2)
    assert r["missed"] == 0, r
    full_r = raised.compute_cells([(i, j) for i in range(6) for j in range(6)])
    full_p = table.compute_cells([(i, j) for i in range(6) for j in range(6)])
    assert full_p.sum() < full_r.sum()


def test_conservative_on_dem(dem_tree):
    table = precompute_visibility(dem_tree, 5, 10)
    r = _check_conservative(dem_tree, table, 1, seed=3)
    assert r["missed"] == 0, r
    assert r["kept"] < r["all"]


def test_paper_sampling_can_miss_raised_does_not(dem_tree):
    """Why the raised end points are the default: with the paper's vertex-to-vertex sampling at the
    surface, finer blockees (level 12) and blockers (128 squares), this DEM viewpoint in cell (3, 3) of
    8 x 8 sees a triangle that its cell's set lacks; raising the eye to the cell's top and the targets
    to the node's top keeps it."""
    from terrainwarp.lod.visibility import _compute

    t = dem_tree
    x, z = 13478.260332756405, 15607.459147278838
    eye = np.array([x, float(t.surface_height(x, z)) + 1.8, z])
    full = select_bintree(t, tw.Camera(position=(0, 0, 0), target=(1, 0, 0)), lod=False, frustum=False)
    node = 87812
    assert node in _seen_nodes(t, full, eye)
    lc = 12
    anc = ((node + 1) >> (t.depth - lc)) - 1 - ((1 << lc) - 1)
    kw = dict(samples=3, eye_height=1.8, blocker_cells=128)
    paper = _compute(t, (8, 8), lc, np.array([[3, 3]]), raised=False, **kw)[0]
    raised = _compute(t, (8, 8), lc, np.array([[3, 3]]), raised=True, **kw)[0]
    assert paper[anc] == 0 and raised[anc] == 1
    assert raised.sum() > paper.sum()


def test_toggling_along_a_path_equals_recomputing(fbm_tree):
    table = precompute_visibility(fbm_tree, (5, 7), 8, samples=2)
    rows, cols = table.cells
    full = table.compute_cells([(i, j) for i in range(rows) for j in range(cols)]).reshape(rows, cols, -1)
    assert np.array_equal(expand(table.base, table.coarse_level), full[0, 0])
    rng = np.random.default_rng(7)
    state = table.state()
    cell = (0, 0)
    for step in range(40):
        if step % 5 == 4:  # a jump across several cells
            cell = (int(rng.integers(rows)), int(rng.integers(cols)))
        else:
            di, dj = [(0, 1), (0, -1), (1, 0), (-1, 0)][int(rng.integers(4))]
            cell = (min(max(cell[0] + di, 0), rows - 1), min(max(cell[1] + dj, 0), cols - 1))
        state.move_to_cell(cell)
        assert state.cell == cell
        assert np.array_equal(state.coarse, full[cell])
        assert np.array_equal(state.coarse, table.compute_cells([cell])[0])
    # per-node flags: a node at/below Lc takes its ancestor's flag, above it the OR of its descendants
    nf = state.node_flags()
    lc = table.coarse_level
    t = fbm_tree
    deep = np.arange(*t.level_slice(t.depth).indices(t.n_nodes)[:2])
    anc = ((deep + 1) >> (t.depth - lc)) - 1 - ((1 << lc) - 1)
    assert np.array_equal(nf[deep], state.coarse[anc])
    lv3 = nf[t.level_slice(3)]
    assert np.array_equal(lv3, state.coarse.reshape(8, -1).max(axis=1))
    assert state.toggles > 0


def test_encoding_round_trips():
    rng = np.random.default_rng(0)
    for level in (1, 3, 8):
        for p in (0.0, 0.3, 0.9, 1.0):
            m = (rng.random(2 ** level) < p).astype(np.uint8)
            ids = encode(m, level)
            assert np.array_equal(expand(ids, level), m)
    # the paper's Table 1: "11" toggles 1100, 1101, 1110, 1111 -> one id for the subtree
    m = np.zeros(16, np.uint8)
    m[12:16] = 1
    assert encode(m, 4).tolist() == [2 ** 2 - 1 + 3]
    assert encode(np.ones(8, np.uint8), 3).tolist() == [0]


def test_storage_is_the_changes(fbm_tree):
    table = precompute_visibility(fbm_tree, 8, 9)
    rows, cols = table.cells
    full = table.compute_cells([(i, j) for i in range(rows) for j in range(cols)]).reshape(rows, cols, -1)
    right = full[:, 1:] ^ full[:, :-1]
    for p, ch in enumerate(right.reshape(-1, full.shape[-1])):
        assert np.array_equal(expand(table.right_ids[table.right_ptr[p]:table.right_ptr[p + 1]], 9), ch)
    n_changes = int(right.sum() + (full[1:] ^ full[:-1]).sum())
    assert table.right_ids.size + table.down_ids.size < n_changes  # the encoding pays
    assert table.right_ids.dtype == np.uint16
    assert table.storage_bytes == (2 * (len(table.base) + table.right_ids.size + table.down_ids.size)
                                   + 4 * (table.right_ptr.size + table.down_ptr.size))
    assert table.full_bytes == rows * cols * (2 ** 9 // 8)
    assert table.preprocess_s > 0


def test_deterministic(fbm_tree):
    def run() -> str:
        t = precompute_visibility(fbm_tree, 4, 8)
        return digest(t.base, t.right_ptr, t.right_ids, t.down_ptr, t.down_ids)

    assert run() == run()


def test_bad_input(fbm_tree):
    with pytest.raises(TypeError, match="tree"):
        precompute_visibility(None)
    with pytest.raises(ValueError, match="cells"):
        precompute_visibility(fbm_tree, 0)
    with pytest.raises(ValueError, match="coarse_level"):
        precompute_visibility(fbm_tree, 4, 15)
    with pytest.raises(ValueError, match="blocker_cells"):
        precompute_visibility(fbm_tree, 4, 8, blocker_cells=3)
    with pytest.raises(ValueError, match="eye_height"):
        precompute_visibility(fbm_tree, 4, 8, eye_height=-1.0)
    s = VisibilityState(precompute_visibility(fbm_tree, 2, 4))
    with pytest.raises(ValueError, match="cell"):
        s.move_to_cell((2, 0))
