"""Chunked LOD with skirts (terrainwarp.lod.chunked): skirts cover every chunk edge whose neighbour is at another
level, crack-free with the skirt triangles stated, exact at the finest setting, deterministic."""

import numpy as np
import pytest
from scheme_checks import (
    assert_crack_free,
    assert_fills_view,
    digest_over_threads,
    finest_error,
    ground_path,
    small_terrain,
    top_down,
)

from terrainwarp.kernels.lod import select_level
from terrainwarp.lod.chunked import ChunkedLod
from terrainwarp.lod.quadtree import tile_key
from terrainwarp.lod.scheme import root_nodes, view_of
from terrainwarp.rendering.sources import ChunkedSource

TILE = 8


@pytest.fixture(scope="module")
def hm():
    return small_terrain()


@pytest.fixture(scope="module")
def chunked(hm):
    return ChunkedLod(hm, 1.0, tile=TILE)


def _per_level_walk(ch: ChunkedLod, camera):
    """Leaves, neighbours and errors as numpy finds them, one select_level launch per tree level and a key search
    per probe and level (what the one-launch walk replaced)."""
    t, d = ch.terrain, ch.terrain.depth
    rel, planes = view_of(ch.heightmap, camera)
    x, y = root_nodes(t)
    parts, visited = [], 0
    for lvl in range(d + 1):
        keep = t.inside(lvl, x, y)
        x, y = x[keep], y[keep]
        if not len(x):
            break
        visited += len(x)
        sp, cu, _, _ = select_level(x, y, tile_key(np.full(len(x), lvl), x, y), t.stats_at(lvl, x, y), rel,
                                    t.node_size_world(lvl), planes, 1, float(ch.max_sse_px), camera.focal_px, 0.0,
                                    lvl < d, np.zeros(0, np.int64))
        leaf = sp == 0
        parts.append((np.full(int(leaf.sum()), lvl, np.int64), x[leaf], y[leaf], cu[leaf] != 0))
        split = ~leaf
        x = np.concatenate([2 * x[split] + q % 2 for q in range(4)])
        y = np.concatenate([2 * y[split] + q // 2 for q in range(4)])
    level, lx, ly, culled = (np.concatenate(a) for a in zip(*parts, strict=True))
    err_of = lambda lv, ax, ay: np.array([t.stats[int(a)][2][j, i] for a, i, j in zip(lv, ax, ay, strict=True)],  # noqa: E731
                                         np.float32).reshape(-1)
    keys = set(tile_key(level, lx, ly).tolist())
    nbr = np.full((len(level), 4), -1, np.int32)
    nerr = np.zeros((len(level), 4), np.float32)
    for j in range(len(level)):
        size = 1 << (d - level[j])
        fx0, fy0 = lx[j] * size, ly[j] * size
        for e, (fx, fy) in enumerate(((fx0 - 1, fy0), (fx0, fy0 - 1), (fx0 + size, fy0), (fx0, fy0 + size))):
            if not (0 <= fx < t.roots[0] << d and 0 <= fy < t.roots[1] << d):
                continue
            hit = [k for k in range(d + 1) if int(tile_key(np.array([k]), np.array([fx >> (d - k)]),
                                                           np.array([fy >> (d - k)]))[0]) in keys]
            nbr[j, e] = hit[0]
            at = min(hit[0], level[j])
            nerr[j, e] = err_of([at], [fx >> (d - at)], [fy >> (d - at)])[0]
    return level, lx, ly, culled, nbr, nerr, err_of(level, lx, ly), visited


@pytest.mark.parametrize("sse", [0.5, 4.0])
def test_one_launch_walk_equals_the_per_level_walk(hm, sse):
    """Every drawn chunk (key order), neighbour level and error of the one-launch walk, and its counts, equal
    numpy's per-level walk's."""
    ch = ChunkedLod(hm, sse, tile=TILE)
    tree_of = lambda: ch.terrain.cached(("chunk_tree", ch.device), lambda: None)  # noqa: E731 - made by select
    cams = ground_path(hm, 3) + [top_down(hm, 240.0)]
    culled = nbrs = 0
    for cam in cams:
        ch.select(cam)
        rel, planes = view_of(hm, cam)
        got = tree_of().select(rel, planes, float(sse), cam.focal_px)
        level, lx, ly, cu, nbr, nerr, err, visited = _per_level_walk(ch, cam)
        order = np.argsort(tile_key(level, lx, ly), kind="stable")
        order = order[~cu[order]]  # the drawn chunks in key order
        want = (*(a[order] for a in (level, lx, ly, nbr, nerr, err)), len(level), visited)
        for g, w in zip(got, want, strict=True):
            assert np.array_equal(g, w) and (not isinstance(g, np.ndarray) or g.dtype == w.dtype)
        culled += int(cu.sum())
        nbrs += int((nbr > level[:, None]).sum())
    assert culled > 0 and nbrs > 0  # culled leaves and finer neighbours were part of it


def _edge_heights(hm, origin, step, size, e, t):
    """Height of a chunk's edge e at offset t (cells, along the edge) : linear between its vertices (samples)."""
    cols, rows = hm.shape[1] - 1, hm.shape[0] - 1
    along = origin[1] if e in (0, 2) else origin[0]
    fixed = origin[0] + (size if e == 2 else 0) if e in (0, 2) else origin[1] + (size if e == 3 else 0)
    v0 = np.floor(t / step) * step
    f = (t - v0) / step

    def h(a):
        p = np.clip(along + a, 0, rows if e in (0, 2) else cols)
        q = min(max(fixed, 0), cols if e in (0, 2) else rows)
        return hm.heights[p.astype(int), int(q)] if e in (0, 2) else hm.heights[int(q), p.astype(int)]

    return (1 - f) * h(v0).astype(np.float64) + f * h(np.minimum(v0 + step, size)).astype(np.float64)


def _neighbour_pairs(sel):
    """(i, j, e, t) for every sample offset t along edge e of chunk i whose neighbour j across is drawn."""
    size = sel.step * TILE
    o = sel.origin.astype(np.float64)
    for i in range(len(sel.level)):
        s = float(size[i])
        for e in range(4):
            t = np.arange(0, int(s) + 1, dtype=np.float64)
            if e in (0, 2):
                x = np.full_like(t, o[i, 0] + (-0.5 if e == 0 else s + 0.5))
                z = o[i, 1] + np.clip(t, 0.25, s - 0.25)
            else:
                z = np.full_like(t, o[i, 1] + (-0.5 if e == 1 else s + 0.5))
                x = o[i, 0] + np.clip(t, 0.25, s - 0.25)
            inside = (x[:, None] > o[None, :, 0]) & (x[:, None] < o[None, :, 0] + size[None, :]) & \
                     (z[:, None] > o[None, :, 1]) & (z[:, None] < o[None, :, 1] + size[None, :])
            for k, j in zip(*np.nonzero(inside)):
                yield i, int(j), e, t[k]


def test_skirts_cover_every_edge_toward_another_level(hm, chunked):
    checked = 0
    for cam in ground_path(hm) + [top_down(hm, 120.0)]:
        sel = chunked.select(cam)
        assert len(set(sel.level.tolist())) >= 2
        size = sel.step * TILE
        for i, j, e, t in _neighbour_pairs(sel):
            if sel.level[i] == sel.level[j]:
                continue
            assert (sel.skirt_mask[i] >> e) & 1, f"chunk {i} edge {e}: neighbour at another level, no skirt"
            gx = sel.origin[i, 0] + (t if e in (1, 3) else (size[i] if e == 2 else 0))
            gz = sel.origin[i, 1] + (t if e in (0, 2) else (size[i] if e == 3 else 0))
            if not (0 <= gx <= hm.shape[1] - 1 and 0 <= gz <= hm.shape[0] - 1):
                continue
            f = _edge_heights(hm, sel.origin[i], sel.step[i], size[i], e, np.array([t]))[0]
            ej = (e + 2) % 4  # the same line is the neighbour's opposite edge
            tj = (gz - sel.origin[j, 1]) if e in (0, 2) else (gx - sel.origin[j, 0])
            c = _edge_heights(hm, sel.origin[j], sel.step[j], size[j], ej, np.array([tj]))[0]
            tol = 1e-4
            if f >= c:
                assert f - sel.skirt[i] <= c + tol, f"chunk {i} skirt ends above its neighbour's edge"
            else:
                assert c - sel.skirt[j] <= f + tol, f"chunk {j} skirt ends above its neighbour's edge"
            checked += 1
    assert checked > 100


def test_crack_free_with_skirts(hm, chunked):
    src = ChunkedSource(scheme=chunked)
    for cam in ground_path(hm) + [top_down(hm, 120.0)]:
        sel = chunked.select(cam)
        mesh = chunked.mesh(cam, sel)
        skirts = chunked.skirt_triangles(sel)
        # the frame's triangles: every chunk's grid plus its skirts (2 per segment of every skirted edge)
        assert skirts > 0
        assert mesh.n_triangles == 2 * TILE * TILE * len(sel.level) + skirts
        assert_crack_free(hm, cam, src, 3.0, f"chunked ({skirts} skirt triangles)")
    assert_fills_view(hm, top_down(hm, 120.0), src, "chunked")


def test_without_skirts_the_frame_would_crack(hm, device):
    """The control: depth-0 skirts leave the gaps the real ones cover (so the coverage check can see cracks)."""
    src = ChunkedSource(scheme=ChunkedLod(hm, 1.0, tile=TILE, skirt_depth=0.0, device=device))
    cracked = 0
    for cam in ground_path(hm, 5):
        try:
            assert_crack_free(hm, cam, src, 3.0, "chunked without skirts", device=device)
        except AssertionError:
            cracked += 1
    assert cracked > 0


def test_finest_setting_scores_zero(hm, device):
    src = ChunkedSource(scheme=ChunkedLod(hm, 0.0, tile=TILE, device=device))
    for cam in ground_path(hm, 2):
        assert finest_error(hm, cam, src, device=device) == 0.0


def test_no_skirts_on_the_terrain_border(hm, chunked):
    sel = chunked.select(top_down(hm, 2000.0))
    cols, rows = hm.shape[1] - 1, hm.shape[0] - 1
    size = sel.step * TILE
    west = sel.origin[:, 0] <= 0
    east = sel.origin[:, 0] + size >= cols
    north = sel.origin[:, 1] <= 0
    south = sel.origin[:, 1] + size >= rows
    for bit, edge in enumerate((west, north, east, south)):
        assert not ((sel.skirt_mask >> bit) & 1)[edge].any()
        assert ((sel.skirt_mask >> bit) & 1)[~edge].all()


def test_deterministic(hm, device):
    """Two runs, and any thread count, draw the same bytes."""

    def make():
        return ChunkedSource(scheme=ChunkedLod(hm, 1.0, tile=TILE, device=device))

    assert len(digest_over_threads(make, ground_path(hm), (1, 1, 3))) == 1


@pytest.mark.parametrize("kw, msg", [({"max_sse_px": -1.0}, "max_sse_px"), ({"skirt_depth": -1.0}, "skirt_depth"),
                                     ({"tile": 0}, "tess")])
def test_bad_parameters(hm, kw, msg):
    with pytest.raises(ValueError, match=msg):
        ChunkedLod(hm, **kw)
