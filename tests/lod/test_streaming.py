"""Pyramids of a streamed heightmap (terrainwarp.lod.streaming): exact root by root and cached beside a file,
or bounded on demand; and the hash-table tree map that deep trees select with."""

from __future__ import annotations

import numpy as np
import pytest

import terrainwarp.kernels.lod as klod
from terrainwarp import Camera, Heightmap
from terrainwarp.heightmap import StreamedHeightmap
from terrainwarp.io.geotiff import write_tiled
from terrainwarp.io.tiles import FbmSource
from terrainwarp.kernels.pyramid import node_stats
from terrainwarp.lod import Terrain, make_policy, select
from terrainwarp.scene import LodConfig


def _ground_camera(hm, width=960, height=540):
    (x0, z0), (x1, z1) = hm.bounds_xz
    cx, cz = 0.5 * (x0 + x1), 0.5 * (z0 + z1)
    g = float(hm.sample([cx], [cz])[0])
    return Camera(position=(cx, g + 40.0, cz), target=(cx + 1000.0, g + 20.0, cz + 300.0), fov_y_deg=60.0,
                  width=width, height=height, near=1.0, far=x1 - x0)


def test_exact_pyramid_root_by_root_equals_the_in_memory_one():
    hm = Heightmap.fbm(1025, 769, seed=2)
    t = Terrain.prepare(hm, roots=12, tess=16)
    ts = Terrain.prepare(StreamedHeightmap.of(hm), roots=12, tess=16)
    assert ts.provider.exact and ts.depth == t.depth and ts.roots == t.roots
    for lv in range(t.depth + 1):
        for a, b in zip(t.stats[lv], ts.provider.levels[lv], strict=True):
            assert np.array_equal(a, b), lv


@pytest.mark.parametrize("ridged", [False, True])
def test_on_demand_bounds_contain_every_nodes_own_stats(ridged):
    kw = dict(seed=5, max_height=1200.0, ridged=ridged)
    hm = Heightmap.fbm(2049, **kw)
    t = Terrain.prepare(StreamedHeightmap.fbm(2049, **kw), roots=16, tess=16)
    p = t.provider
    assert not p.exact
    for lv in range(t.depth + 1):
        (mn, mx, er), = node_stats(hm.heights, (4 << lv, 4 << lv), t.root_cells / 2**lv, 0, 16)  # own stats
        yy, xx = (a.ravel() for a in np.meshgrid(np.arange(4 << lv), np.arange(4 << lv), indexing="ij"))
        for step in p.steps(lv):
            a, b, e, pad = p.measured(lv, xx, yy, step)
            assert (a - pad <= mn.ravel()).all() and (b + pad >= mx.ravel()).all()
            assert (e + pad >= er.ravel() - 1e-3).all()
            assert (a >= mn.ravel()).all() and (e <= er.ravel() + 1e-3).all()  # measured: bounds from below
            if step == 1:
                assert pad == 0 and np.array_equal(e, er.ravel())


@pytest.mark.slow
def test_on_demand_selection_matches_the_in_memory_one():
    """Decisions are taken where the measured and the widened stats agree, so they are the exact pyramid's
    but where a node's own error is below a descendant's (the in-memory pyramid's monotone rule) or a
    node stays undecided at its finest step (1/8 of its vertex spacing; then it splits)."""
    hm = Heightmap.fbm(4097, seed=1, max_height=2000.0, dx=10.0)
    cam = _ground_camera(hm)
    prepared = {}  # the in-memory pyramids by (roots, tess): the first two configurations share theirs
    for lod in (LodConfig(), LodConfig(policy="distance"), LodConfig(tolerance_px=4.0, tess=32)):
        key = (lod.roots, lod.tess)
        if key not in prepared:
            prepared[key] = Terrain.prepare(hm, roots=lod.roots, tess=lod.tess)
        a = select(prepared[key], cam, make_policy(lod))
        st = StreamedHeightmap.fbm(4097, seed=1, max_height=2000.0, dx=10.0)
        b = select(Terrain.prepare(st, roots=lod.roots, tess=lod.tess), cam, make_policy(lod))
        differ = len(np.setxor1d(a.key, b.key))  # one split decided otherwise: 1 key against 4
        assert differ <= 8 + 0.01 * len(a.key), (lod, differ, len(a.key))
        if lod.policy == "distance":  # decided by the boxes alone
            assert np.array_equal(a.key, b.key) and np.array_equal(a.outer, b.outer)
        assert st.counters()["tiles_read"] < 0.5 * (4097 / 256) ** 2  # far from every tile of the grid


def test_hash_table_tree_map_selects_as_the_dense_one(monkeypatch):
    hm = Heightmap.fbm(2049, seed=1, max_height=2000.0, dx=10.0)
    t = Terrain.prepare(hm, roots=16, tess=16)
    cam = _ground_camera(hm)
    a = select(t, cam, make_policy(LodConfig()))
    monkeypatch.setattr(klod, "DENSE_MAX_CELLS", 16)
    b = select(t, cam, make_policy(LodConfig()))
    for f in a._fields[:-1]:
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    m = klod.tree_map((4, 4), t.depth)
    assert m.sparse
    keys = np.arange(10000, dtype=np.int64) * 7919
    m.put(keys, np.arange(10000, dtype=np.int32))
    m.put(keys[:10], np.full(10, -1, np.int32))  # overwrite
    assert m.n == 10000 and len(m.k) >= 20000
    got = {int(k): int(v) for k, v in zip(m.k, m.v, strict=True) if k >= 0}
    assert got[keys[3]] == -1 and got[keys[500]] == 500


def test_file_pyramid_is_cached_beside_the_file_and_rebuilt_when_it_changes(tmp_path):
    src = FbmSource(513, seed=4, dx=10.0)
    p = write_tiled(tmp_path / "t.tif", src.shape, lambda r0, c0, n, m: src.read(1, r0, c0, n, m), dx=10.0,
                    overviews=())
    t1 = Terrain.prepare(Heightmap.open(p), roots=4, tess=16)
    assert t1.provider.counters["cache"] == "built"
    folder = tmp_path / "t.tif.twcache"
    assert (folder / "manifest.json").exists() and sorted(f.name for f in folder.glob("overview_*.npy"))
    st = Heightmap.open(p)
    t2 = Terrain.prepare(st, roots=4, tess=16)
    assert t2.provider.counters["cache"] == "reused"
    assert all(np.array_equal(a, b) for lv in range(t1.depth + 1)
               for a, b in zip(t1.provider.levels[lv], t2.provider.levels[lv], strict=True))
    ov = st.source.levels[4]  # point-sampled: sample (i, j) of the step-4 overview is sample (4i, 4j)
    assert np.array_equal(np.asarray(ov), src.read(1, 0, 0, 513, 513)[::4, ::4])
    other = FbmSource(513, seed=5, dx=10.0)  # the file changes: nothing cached is valid
    write_tiled(p, other.shape, lambda r0, c0, n, m: other.read(1, r0, c0, n, m), dx=10.0, overviews=())
    t3 = Terrain.prepare(Heightmap.open(p), roots=4, tess=16)
    assert t3.provider.counters["cache"] == "built"
    ref = Terrain.prepare(Heightmap.load(p), roots=4, tess=16)
    assert all(np.array_equal(a, b) for lv in range(ref.depth + 1)
               for a, b in zip(ref.stats[lv], t3.provider.levels[lv], strict=True))
    assert Heightmap.open(p).height_range == Heightmap.load(p).height_range


def test_file_pyramid_built_on_the_dask_runner_equals_one_process(tmp_path):
    from terrainwarp.experiments.runner import Runner

    src = FbmSource(1025, seed=6, dx=10.0)
    p = write_tiled(tmp_path / "d.tif", src.shape, lambda r0, c0, n, m: src.read(1, r0, c0, n, m), dx=10.0,
                    overviews=())
    with Runner(workers=2) as runner:
        st = Heightmap.open(p)
        t = Terrain.prepare_streamed(st, roots=16, tess=16, map=runner.map)
    assert t.provider.counters["cache"] == "built"
    ref = Terrain.prepare(Heightmap.load(p), roots=16, tess=16)
    for lv in range(ref.depth + 1):
        for a, b in zip(ref.stats[lv], t.provider.levels[lv], strict=True):
            assert np.array_equal(a, b), lv
    assert np.array_equal(np.asarray(st.source.levels[8]), src.read(8, 0, 0, *src.level_shape(8)))
