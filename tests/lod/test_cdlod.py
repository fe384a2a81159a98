"""CDLOD (terrainwarp.lod.cdlod): crack-free, continuous across range borders while the camera moves, exact at
its finest setting, deterministic; and the DX11 sample's edge factor against the continuous policy's."""

import math
from concurrent.futures import ThreadPoolExecutor

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

from terrainwarp import Heightmap
from terrainwarp.camera import Camera
from terrainwarp.kernels.lod import select_level
from terrainwarp.lod.cdlod import Cdlod, cdlod_ranges
from terrainwarp.lod.policies import dx11_edge_pixels, edge_pixels
from terrainwarp.lod.quadtree import tile_key
from terrainwarp.lod.scheme import root_nodes, view_of
from terrainwarp.measure.sample_error import surface_heights
from terrainwarp.rendering.sources import CdlodSource


@pytest.fixture(scope="module")
def hm():
    return small_terrain()


@pytest.fixture(scope="module")
def cdlod(hm):
    c = Cdlod(hm, 1.0, grid=8)
    c.first_range = math.ceil(c.min_first_range)
    return c


def test_ranges_follow_the_reference():
    rng, start, end = cdlod_ranges(100.0, 2.0, 0.7, 4)
    assert rng[:3].tolist() == [100.0, 300.0, 700.0] and math.isinf(rng[3])
    assert start[0] == pytest.approx(70.0) and start[1] == pytest.approx(70.0 + 230.0 * 0.7)
    assert end[0] == pytest.approx(100.0 - 0.01 * 30.0)  # morph end pulled 1% toward its start
    assert math.isinf(start[3])


def test_crack_free_on_a_ground_path_and_from_above(hm, cdlod):
    src = CdlodSource(scheme=cdlod)
    lods = set()
    for cam in ground_path(hm):
        sel = cdlod.select(cam)
        lods |= set(sel.lod.tolist())
        assert sel.stats["too_small"] == 0
        assert_crack_free(hm, cam, src, 3.0, "cdlod")
    assert len(lods) >= 3
    cam = top_down(hm, 240.0)
    assert len(set(cdlod.select(cam).lod.tolist())) >= 2
    assert_fills_view(hm, cam, src, "cdlod")


def _per_level_walk(c: Cdlod, camera: Camera):
    """The selection as numpy walks it, one select_level launch per tree level: (origin, size, step, lod, draws,
    order, stats) with the quadrants in the order the one-launch walk emits them."""
    t = c.terrain
    rng, start, _ = c.ranges()
    rel, planes = view_of(c.heightmap, camera)
    x, y = root_nodes(t)
    items, calls = [], []  # items: (x0, y0, size, step, lod) per quadrant
    st = {"nodes_visited": 0, "culled": 0, "too_small": 0, "whole_nodes": 0, "quadrant_draws": 0}
    for lvl in range(t.depth + 1):
        keep = t.inside(lvl, x, y)
        x, y = x[keep], y[keep]
        if not len(x):
            break
        lod = t.depth - lvl
        st["nodes_visited"] += len(x)
        _, cu, dist, _ = select_level(x, y, tile_key(np.full(len(x), lvl), x, y), t.stats_at(lvl, x, y), rel,
                                      t.node_size_world(lvl), planes, 0, 0.0, camera.focal_px, 0.0, False,
                                      np.zeros(0, np.int64))
        vis = cu == 0
        st["culled"] += int((~vis).sum())
        near = dist < rng[lod]
        split = vis & near & (dist < rng[lod - 1]) if lod > 0 else np.zeros(len(x), bool)
        whole = vis & near & ~split
        s = t.root_cells / 2.0 ** lvl
        for i in np.flatnonzero(vis & ~near):  # the parent draws this quadrant with its grid
            calls.append([len(items)])
            items.append((x[i] * s, y[i] * s, s, t.root_cells / 2.0 ** (lvl - 1) / c.grid, lod + 1))
            st["quadrant_draws"] += 1
        w = np.flatnonzero(whole)
        base = len(items)
        items += [(x[i] * s + (q % 2) * s / 2, y[i] * s + (q // 2) * s / 2, s / 2, s / c.grid, lod)
                  for q in range(4) for i in w]
        calls += [[base + j + q * len(w) for q in range(4)] for j in range(len(w))]
        st["whole_nodes"] += len(w)
        if lod + 1 < c.levels and len(w):  # the reference's "visibility distance too small"
            sx, sz = t.node_size_world(lvl)
            mn, mx, _ = t.stats[lvl]
            x0, z0 = rel[0] + x[w] * sx, rel[2] + y[w] * sz
            fx, fz = np.maximum(np.abs(x0), np.abs(x0 + sx)), np.maximum(np.abs(z0), np.abs(z0 + sz))
            fy = np.maximum(np.abs(mn[y[w], x[w]] - rel[1]), np.abs(mx[y[w], x[w]] - rel[1]))
            st["too_small"] += int((np.sqrt(fx * fx + fy * fy + fz * fz) > start[lod + 1]).sum())
        x = np.concatenate([2 * x[split] + q % 2 for q in range(4)])
        y = np.concatenate([2 * y[split] + q // 2 for q in range(4)])
    it = np.array(items, np.float64).reshape(-1, 5)
    order = np.array([k for cl in calls for k in cl], np.int32)
    ends = np.cumsum([len(cl) for cl in calls]).astype(np.int32)
    draws = np.stack([ends - np.diff(ends, prepend=0), ends], 1).reshape(-1, 2).astype(np.int32)
    return (it[:, :2].astype(np.float32), it[:, 2].astype(np.float32), it[:, 3].astype(np.float32),
            it[:, 4].astype(np.int32), draws, order, st)


@pytest.mark.parametrize("scale", [0.3, 1.0, 4.0])
def test_one_launch_walk_equals_the_per_level_walk(hm, scale):
    """Every quadrant, draw and count of the one-launch selection equals numpy's walk with one launch per level,
    below the smallest safe first range (nodes too_small), at it and far above it (parent quadrants)."""
    c = Cdlod(hm, 1.0, grid=8)
    c.first_range = c.min_first_range * scale
    cams = ground_path(hm, 4) + [top_down(hm, 240.0), ground_path(hm, 2, width=300, height=40)[1]]
    seen = {"too_small": 0, "quadrant_draws": 0, "culled": 0}
    for cam in cams:
        sel = c.select(cam)
        origin, size, step, lod, draws, order, st = _per_level_walk(c, cam)
        for got, want in ((sel.origin, origin), (sel.size, size), (sel.step, step), (sel.lod, lod),
                          (sel.draws, draws), (sel.order, order)):
            assert got.dtype == want.dtype and np.array_equal(got, want)
        assert {k: sel.stats[k] for k in st} == st and sel.stats["quadrants"] == len(size)
        for k in seen:
            seen[k] += st[k]
    assert seen["culled"] > 0
    if scale < 1.0:
        assert seen["too_small"] > 0
    if scale > 1.0:
        assert seen["quadrant_draws"] > 0


def test_selection_from_many_threads_equals_the_serial_one(hm, cdlod):
    """One tree, selected from four threads at once (its buffers are shared under a lock): the serial results."""
    cams = ground_path(hm, 8)
    serial = [cdlod.select(cam) for cam in cams]
    with ThreadPoolExecutor(4) as pool:
        for _ in range(5):
            for want, got in zip(serial, pool.map(cdlod.select, cams), strict=True):
                assert np.array_equal(want.origin, got.origin) and np.array_equal(want.order, got.order)
                assert want.stats == got.stats


def _lod_map(sel, shape):
    """The CDLOD level drawn over each sample (-1 where nothing is)."""
    out = np.full(shape, -1)
    for (x, z), size, lod in zip(sel.origin.astype(int), sel.size.astype(int), sel.lod):
        out[z:z + size, x:x + size] = lod
    return out


def _switches(cdlod, cams):
    """Camera pairs a hair apart (1e-4 m) across which the selection changes."""
    out = []
    for a, b in zip(cams, cams[1:]):
        sa, sb = cdlod.select(a), cdlod.select(b)
        if np.array_equal(sa.lod, sb.lod) and np.array_equal(sa.origin, sb.origin):
            continue
        pa, pb = np.array(a.position), np.array(b.position)
        for _ in range(40):  # bisect the switch down to 1e-4 m
            mid = Camera(position=tuple(0.5 * (pa + pb)), target=a.target, width=a.width, height=a.height)
            sm = cdlod.select(mid)
            if np.array_equal(sm.lod, sa.lod) and np.array_equal(sm.origin, sa.origin):
                pa = np.array(mid.position)
            else:
                pb = np.array(mid.position)
            if np.linalg.norm(pb - pa) < 1e-4:
                break
        out.append((a.with_(position=tuple(pa)), a.with_(position=tuple(pb))))
    return out


def test_vertex_positions_are_continuous_across_range_borders(hm, cdlod):
    (x0, z0), (x1, z1) = hm.bounds_xz
    y = float(hm.heights.max()) + 60.0
    target = (x1 + 500.0, 0.0, z0 + 0.3 * (z1 - z0))
    cams = [Camera(position=(x0 + t * (x1 - x0), y, z0 + 0.5 * (z1 - z0)), target=target, width=96, height=64)
            for t in np.linspace(0.05, 0.6, 24)]
    pairs = _switches(cdlod, cams)
    assert len(pairs) >= 3, "the path must cross range borders"
    ulp = float(np.spacing(np.float32(np.abs(hm.heights).max() + 60.0)))
    switched = 0
    for a, b in pairs:
        sa, sb = cdlod.select(a), cdlod.select(b)
        la, lb = _lod_map(sa, hm.shape), _lod_map(sb, hm.shape)
        switched += bool(((la != lb) & (la >= 0) & (lb >= 0)).any())  # a range border, not the frustum
        ha = surface_heights(hm, cdlod.mesh(a, sa))
        hb = surface_heights(hm, cdlod.mesh(b, sb))
        both = np.isfinite(ha) & np.isfinite(hb)
        assert both.mean() > 0.2
        # the eye moved by < 1e-4 m: the morph moved by far less than a float32 ulp of the heights
        jump = np.abs(ha - hb)[both].max()
        assert jump <= 16 * ulp, f"surface jumped by {jump} m across a range border (float32 ulp {ulp})"
    assert switched >= 2, "the path must cross range borders"


def test_finest_setting_scores_zero(hm, device):
    src = CdlodSource(scheme=Cdlod(hm, 1e9, grid=8, device=device))
    for cam in ground_path(hm, 2):
        assert finest_error(hm, cam, src, device=device) == 0.0


def test_deterministic(hm, cdlod, device):
    """Two runs, and any thread count, draw the same bytes."""

    def make():
        return CdlodSource(scheme=Cdlod(hm, cdlod.first_range, grid=8, device=device))

    assert len(digest_over_threads(make, ground_path(hm), (1, 1, 3))) == 1


@pytest.mark.parametrize("kw, msg", [({"first_range": 0.0}, "first_range"), ({"ratio": 1.0}, "ratio"),
                                     ({"morph_start_ratio": 1.0}, "morph_start_ratio"), ({"grid": 7}, "grid"),
                                     ({"levels": 0}, "levels")])
def test_bad_parameters(hm, kw, msg):
    args = {"first_range": 100.0, **kw}
    with pytest.raises(ValueError, match=msg):
        Cdlod(hm, **args)


def test_dx11_edge_factor_maps_to_the_continuous_policy():
    """Item 4: on a level terrain, for a patch whose edge midpoint lies on the view axis, the DX11 sample's size
    is twice ours (its NDC-to-pixel scale skips the halving); off axis it grows by d / z_view."""
    hm = Heightmap.from_array(np.zeros((65, 65), np.float32), dx=10.0)
    cam = Camera(position=(320.0, 0.0, 900.0), target=(320.0, 0.0, 0.0), width=160, height=90)
    origin = np.array([[270.0, 100.0], [0.0, 100.0]])
    size = np.array([[100.0, 100.0], [100.0, 100.0]])
    ours = edge_pixels(hm, cam.position, cam.focal_px, origin, size)
    theirs = dx11_edge_pixels(hm, cam, origin, size)
    # edge v=0 of patch 0 is centred on the view axis (x = 320): exactly twice ours
    assert theirs[0, 1] == pytest.approx(2.0 * ours[0, 1], rel=1e-9)
    eye = np.array(cam.position)
    mid = np.array([50.0, 0.0, 100.0])  # edge v=0 of patch 1, off axis
    d = np.linalg.norm(mid - eye)
    z_view = float(np.dot(mid - eye, cam.forward))
    assert theirs[1, 1] == pytest.approx(2.0 * ours[1, 1] * d / z_view, rel=1e-9)
    assert theirs[1, 1] > 2.0 * ours[1, 1]
