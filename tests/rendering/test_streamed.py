"""Frames of a streamed heightmap: read at full resolution they are the in-memory frames bit for bit; read
from overviews their geometry and error are the in-memory ones on these terrains (the DEM's 344 x 403 samples
included, where patches reach past the grid's last sample and the overviews end on its clamped last row and
column); a terrain far larger than memory renders with only the tiles its frame needs."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import digest

from terrainwarp import Camera, Heightmap, Scene, render
from terrainwarp.heightmap import StreamedHeightmap
from terrainwarp.io.geotiff import write_tiled
from terrainwarp.io.tiles import FbmSource
from terrainwarp.rendering.sources import StreamedSource
from terrainwarp.scene import LodConfig

OUTS = ("image", "depth", "error")


@pytest.fixture(scope="module")
def fbm_tif(tmp_path_factory):
    """A 2049^2 fBm written as a tiled (256^2, deflate) GeoTIFF with overviews, and its in-memory read."""
    src = FbmSource(2049, seed=3, dx=10.0)
    p = write_tiled(tmp_path_factory.mktemp("tif") / "fbm2049.tif", src.shape,
                    lambda r0, c0, n, m: src.read(1, r0, c0, n, m), dx=10.0)
    return p, Heightmap.load(p)


def _same(a, b) -> bool:
    return (np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth, equal_nan=True)
            and np.array_equal(a.triangle_id, b.triangle_id) and a.error.row() == b.error.row())


def _frames(hm, st, cams, src_full):
    for cam in cams:
        a = render(Scene(hm, camera=cam, mesh="lod", outputs=OUTS))
        b = render(Scene(st, camera=cam, mesh="lod", outputs=OUTS), source=src_full)
        c = render(Scene(st, camera=cam, mesh="lod", outputs=(*OUTS, "patches")))
        yield a, b, c


def _overhangs(f, shape) -> bool:
    """Whether a patch of ``f`` reaches past the grid's last sample (H - 1, W - 1)."""
    pl = f.patches
    return bool((pl.origin_cells + pl.size_cells[:, None] > np.array([shape[1] - 1, shape[0] - 1])).any())


def test_dem_streamed_at_full_resolution_is_the_in_memory_frame():
    """Also from overviews: the DEM's 343 and 402 cells are multiples of no step above 1, and the path's end
    camera draws patches past its south edge (the overview of step s ends on the grid's last row, not on its
    last multiple of s: 53 m apart there)."""
    hm = Heightmap.example()
    st = StreamedHeightmap.of(hm)
    cams = Scene(hm).camera_path(2)
    assert cams == Scene(st).camera_path(2)  # the path samples the ground through the tiles, bit for bit
    over = []
    for a, b, c in _frames(hm, st, cams, StreamedSource(st, LodConfig(), full_resolution=True)):
        assert _same(a, b)
        assert np.array_equal(a.depth, c.depth, equal_nan=True) and a.error.row() == c.error.row()
        over.append(_overhangs(c, hm.shape))
    assert any(over)  # the grid's edge was drawn from an overview


def test_the_dem_as_a_geotiff_draws_its_edge_from_the_cached_overviews_as_in_memory(tmp_path):
    """The pyramid cache's overviews of a 344 x 403 file end on the grid's clamped last row and column, and the
    frames drawn from them (patches past the south edge included) are the in-memory ones."""
    dem = Heightmap.example()
    p = write_tiled(tmp_path / "dem.tif", dem.shape, lambda r0, c0, n, m: dem.heights[r0:r0 + n, c0:c0 + m],
                    dx=dem.dx, dz=dem.dz, overviews=())
    hm, st = Heightmap.load(p), Heightmap.open(p)
    over = []
    for cam in Scene(hm).camera_path(2):
        a = render(Scene(hm, camera=cam, mesh="lod", outputs=OUTS))
        c = render(Scene(st, camera=cam, mesh="lod", outputs=(*OUTS, "patches")))
        assert np.array_equal(a.depth, c.depth, equal_nan=True) and a.error.row() == c.error.row()
        over.append(_overhangs(c, hm.shape))
    assert any(over) and st.source.levels  # drawn from the cache's overviews, over the edge
    for step, ov in st.source.levels.items():
        rows = np.minimum(np.arange(-(-343 // step) + 1) * step, 343)
        cols = np.minimum(np.arange(-(-402 // step) + 1) * step, 402)
        assert np.array_equal(np.asarray(ov), hm.heights[np.ix_(rows, cols)]), step


def test_geotiff_streamed_equals_in_memory_and_overviews_keep_the_error(fbm_tif):
    p, hm = fbm_tif
    st = Heightmap.open(p)
    assert st.shape == hm.shape and (st.dx, st.dz) == (hm.dx, hm.dz) and st.height_range == hm.height_range
    cams = Scene(hm).camera_path(2)
    full = StreamedSource(st, LodConfig(), full_resolution=True)
    for a, b, c in _frames(hm, st, cams, full):
        assert _same(a, b)
        # from overviews: every vertex of an integer tessellation lies on a sample of the window it reads
        assert np.array_equal(a.depth, c.depth, equal_nan=True)
        assert c.error.row()["p99_px"] == a.error.row()["p99_px"] <= 1.0
        tiles = c.report.info["tiles"]
        assert set(tiles) == {"tiles_read", "bytes_read", "hits"} and tiles["tiles_read"] + tiles["hits"] > 0
        sel = next(r for r in c.report.stages if r.name == "select")
        assert sel.counters["windows"] >= 1 and sel.counters["window_samples"] < hm.heights.size


def test_streamed_frames_are_deterministic_and_report_their_reads(fbm_tif):
    p, hm = fbm_tif
    cam = Scene(hm).camera_path(3)[1]
    runs = []
    for _ in range(2):
        st = Heightmap.open(p, cache_mb=4)  # a small cache: tiles are evicted and read again
        f = render(Scene(st, camera=cam, mesh="lod", outputs=("image", "depth")))
        runs.append(digest(f.image, f.depth, f.triangle_id))
        assert st.counters()["resident_bytes"] <= 4 * 2**20 + 300_000  # the cap (one tile may overhang)
    assert runs[0] == runs[1]


def _ground(st, k, width=480, height=270):
    (x0, z0), (x1, z1) = st.bounds_xz
    x, z = 0.5 * (x0 + x1) + 150.0 * k, 0.5 * (z0 + z1) + 50.0 * k
    g = float(st.sample([x], [z])[0])
    return Camera(position=(x, g + 40.0, z), target=(x + 1000.0, g + 20.0, z + 300.0), fov_y_deg=60.0,
                  width=width, height=height, near=1.0, far=x1 - x0)


def test_a_terrain_larger_than_memory_renders_from_the_tiles_it_needs():
    st = StreamedHeightmap.fbm(65537, seed=1, max_height=2000.0, dx=10.0, cache_mb=128)  # 17 GB as float32
    f0 = render(Scene(st, camera=_ground(st, 0), mesh="lod", outputs=("image", "depth")))
    f1 = render(Scene(st, camera=_ground(st, 1), mesh="lod", outputs=("image", "depth")))
    c = st.counters()
    assert c["bytes_read"] < 2e9 and c["peak_bytes"] <= 128 * 2**20 + 300_000
    assert f1.report.info["tiles"]["tiles_read"] < f0.report.info["tiles"]["tiles_read"] / 4  # the cache serves
    for f in (f0, f1):
        assert np.isfinite(f.depth).mean() > 0.5 and len(np.unique(f.image.reshape(-1, 3), axis=0)) > 100
    sel = next(r for r in f1.report.stages if r.name == "select")
    assert sel.counters["coarsest_step"] >= 64 and sel.counters["finest_step"] == 1


def test_hysteresis_state_changes_a_streamed_selection_as_it_does_in_memory(fbm_tif):
    """A frame at tolerance 1 px, then one at 1.25 px (hysteresis 0.3): with the state held, the nodes split at
    1 px stay split (merge threshold 1.25 * 0.7 px), as in memory; without it, the second frame is coarser. A
    render without a state after one with it is stateless (the heightmap's held source keeps no state)."""
    from terrainwarp.lod import LodState

    p, hm = fbm_tif
    st = Heightmap.open(p)
    cam = Scene(hm).camera_path(8)[2]
    first, second = LodConfig(hysteresis=0.3, tolerance_px=1.0), LodConfig(hysteresis=0.3, tolerance_px=1.25)
    keys = {}
    for name, h in (("streamed", st), ("memory", hm)):
        state = LodState()
        for lod in (first, second):
            f = render(Scene(h, camera=cam, mesh="lod", lod=lod, outputs=("patches",)), state=state)
        keys[name] = sorted(f.patches.key.tolist())
        assert state.frames == 2 and len(state.split_keys) > 0
        keys[name + " stateless"] = sorted(render(Scene(h, camera=cam, mesh="lod", lod=second,
                                                        outputs=("patches",))).patches.key.tolist())
    assert keys["streamed"] == keys["memory"] and keys["streamed stateless"] == keys["memory stateless"]
    assert len(keys["streamed"]) > len(keys["streamed stateless"])  # hysteresis kept the finer selection


def test_streamed_scenes_refuse_what_they_cannot_draw(fbm_tif):
    p, _ = fbm_tif
    st = Heightmap.open(p)
    with pytest.raises(ValueError, match="mesh: a streamed heightmap is drawn with mesh='lod'"):
        render(Scene(st, outputs=("depth",)))
    with pytest.raises(ValueError, match="lod.filter"):
        render(Scene(st, mesh="lod", lod=LodConfig(filter="bicubic"), outputs=("depth",)))
    with pytest.raises(ValueError, match="method"):
        st.sample([0.0], [0.0], method="bicubic")
    with pytest.raises(TypeError, match="source"):
        StreamedHeightmap(np.zeros((4, 4), np.float32))


def test_a_streamed_mesh_carries_level_and_patch_id_only_for_what_reads_them():
    """A hillshaded image reads neither (the tessellator writes neither: 8 bytes a vertex less); the mesh output
    and the level shading do, and the image is the same either way."""
    st = StreamedHeightmap.of(Heightmap.example())
    cam = Scene(st).camera_path(2)[0].with_(width=160, height=120)
    plain = render(Scene(st, camera=cam, mesh="lod", outputs=("image",)))
    full = render(Scene(st, camera=cam, mesh="lod", outputs=("image", "mesh")))
    level = render(Scene(st, camera=cam, mesh="lod", outputs=("image",), shading="level"))
    assert plain.mesh.level is None and plain.mesh.patch_id is None
    assert full.mesh.level is not None and len(full.mesh.patch_id) == full.mesh.n_vertices
    assert level.mesh.level is not None
    assert np.array_equal(plain.image, full.image) and not np.array_equal(plain.image, level.image)
