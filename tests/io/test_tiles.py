"""Tiled sources and the tile cache (terrainwarp.io.tiles): windows equal the whole grid bit for bit, the cache
keeps to its cap and counts what it read, bad tiles and bad settings give one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from terrainwarp import Heightmap
from terrainwarp.io.geotiff import read_geotiff, read_header, write_tiled
from terrainwarp.io.tiles import TILE, ArraySource, FbmSource, GeoTiffSource, TileCache, cache_mb_from_env
from terrainwarp.kernels.sampling import sample_grid


def test_fbm_windows_at_any_step_are_the_whole_grids_samples():
    """Sample (i, j) of the step-s overview is the grid's (min(i s, H - 1), min(j s, W - 1)): 599 and 699 are
    multiples of no step above 1, so each overview ends on the grid's last row and column (clamped)."""
    whole = Heightmap.fbm(600, 700, seed=7).heights
    src, arr = FbmSource(600, 700, seed=7), ArraySource(whole)
    for step in (1, 2, 4, 16):
        lr, lc = src.level_shape(step)
        assert (lr, lc) == (-(-599 // step) + 1, -(-699 // step) + 1) == arr.level_shape(step)
        rows, cols = np.minimum(np.arange(3, lr) * step, 599), np.minimum(np.arange(5, lc) * step, 699)
        want = whole[np.ix_(rows, cols)]
        assert np.array_equal(src.read(step, 3, 5, lr - 3, lc - 5), want)
        assert np.array_equal(arr.read(step, 3, 5, lr - 3, lc - 5), want)
        assert np.array_equal(src.read(step, lr - 1, lc - 1, 1, 1), whole[-1:, -1:])  # the corner alone


def test_cache_window_assembles_tiles_and_keeps_to_its_cap():
    h = np.random.default_rng(0).standard_normal((3 * TILE + 7, 2 * TILE + 3)).astype(np.float32)
    tiles = TileCache(ArraySource(h), cache_mb=(TILE + 1) ** 2 * 4 * 2.5 / 2**20)  # room for two tiles
    got = tiles.window(1, TILE - 5, 10, 2 * TILE, TILE + 20)
    assert np.array_equal(got, h[TILE - 5:3 * TILE - 5, 10:TILE + 30])
    c = tiles.snapshot()
    assert c["tiles_read"] == 6 and c["bytes_read"] > 0 and c["evicted"] >= 4
    assert c["resident_bytes"] <= tiles.cap
    # a window ending on a tile boundary needs no tile past it (tiles share their last row and column)
    fresh = TileCache(ArraySource(h))
    assert np.array_equal(fresh.window(1, 0, 0, TILE + 1, TILE + 1), h[:TILE + 1, :TILE + 1])
    assert fresh.snapshot()["tiles_read"] == 1
    fresh.window(1, 0, 0, 5, 5)
    assert fresh.snapshot()["hits"] == 1
    with pytest.raises(ValueError, match="window: rows"):
        fresh.window(1, 0, 0, h.shape[0] + 1, 3)
    buf = np.zeros(40, np.float32)  # a window assembled into a caller's buffer (a frame's one flat stack)
    assert fresh.window(2, 3, 4, 5, 8, out=buf[:40].reshape(5, 8)).base is buf
    assert np.array_equal(buf.reshape(5, 8), h[6:15:2, 8:23:2])
    with pytest.raises(ValueError, match="out"):
        fresh.window(1, 0, 0, 5, 8, out=np.zeros((5, 8), np.float64))


def test_cache_cap_from_the_environment(monkeypatch):
    monkeypatch.setenv("TERRAINWARP_TILE_CACHE_MB", "64")
    assert cache_mb_from_env(None) == 64.0
    assert cache_mb_from_env(8) == 8.0
    monkeypatch.setenv("TERRAINWARP_TILE_CACHE_MB", "lots")
    with pytest.raises(ValueError, match="TERRAINWARP_TILE_CACHE_MB"):
        cache_mb_from_env(None)
    for bad in (0, -1, float("nan"), True):
        with pytest.raises(ValueError, match="cache_mb"):
            cache_mb_from_env(bad)


@pytest.mark.parametrize("ridged", [False, True])
def test_fbm_detail_bound_holds(ridged):
    """Everywhere between the samples of an overview, the grid is within detail_bound(step) of the overview's
    bilinear interpolation (the bound the on-demand pyramids add)."""
    n = 1025
    src = FbmSource(n, seed=3, max_height=1500.0, ridged=ridged)
    whole = src.read(1, 0, 0, n, n)
    rows, cols = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    for step in (2, 4, 8, 32):
        ov = src.read(step, 0, 0, *src.level_shape(step))
        interp = sample_grid(ov, (cols / step).astype(np.float32), (rows / step).astype(np.float32))
        worst = float(np.abs(whole - interp).max())
        assert 0 < worst <= src.detail_bound(step), (step, worst, src.detail_bound(step))
    assert src.detail_bound(1) == 0.0


def test_fbm_source_rejects_bad_sizes():
    with pytest.raises(ValueError, match="rows"):
        FbmSource(0)
    with pytest.raises(ValueError, match="2\\^24"):
        FbmSource(2**24 + 1)
    with pytest.raises(ValueError, match="feature_size"):
        FbmSource(64, feature_size=-1.0)


def _geotiff(path, a, *, nodata=None, south_up=False):
    transform = rasterio.Affine(30.0, 0.0, 500000.0, 0.0, -30.0, 4000000.0 + a.shape[0] * 30.0)
    if south_up:
        a = a[::-1]
        transform = rasterio.Affine(30.0, 0.0, 500000.0, 0.0, 30.0, 4000000.0)
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=str(a.dtype),
                       crs="EPSG:32633", transform=transform, nodata=nodata, tiled=True, blockxsize=256,
                       blockysize=256, compress="deflate") as d:
        d.write(a, 1)
    return path


@pytest.mark.parametrize("south_up", [False, True])
def test_geotiff_windows_equal_the_in_memory_read(tmp_path, south_up):
    a = (np.random.default_rng(1).random((700, 530)) * 900).astype(np.int16)
    a[100:140, 200:260] = -9999
    p = _geotiff(tmp_path / "dem.tif", a, nodata=-9999, south_up=south_up)
    whole = read_geotiff(p)
    src = GeoTiffSource(p)
    assert src.shape == whole.heights.shape and (src.dx, src.dz) == (whole.dx, whole.dz)
    for k in ("crs", "transform", "nodata", "flipped_rows", "spacing_note", "sample00_crs", "source_dtype"):
        assert src.meta[k] == whole.meta[k], k
    got = TileCache(src).window(1, 90, 190, 300, 300)
    assert np.array_equal(got, whole.heights[90:390, 190:490], equal_nan=True)
    assert np.isnan(got).sum() == 40 * 60
    assert read_header(p).shape == whole.heights.shape


def test_corrupt_tile_names_the_tile_and_the_file(tmp_path):
    a = (np.random.default_rng(2).random((1024, 1024)) * 100).astype(np.float32)
    p = _geotiff(tmp_path / "bad.tif", a)
    raw = bytearray(p.read_bytes())
    mid = len(raw) // 2
    raw[mid:mid + 4096] = b"\xff" * 4096  # inside the compressed tiles
    p.write_bytes(bytes(raw))
    tiles = TileCache(GeoTiffSource(p))
    with pytest.raises(ValueError, match=r"tile \(step 1, row \d+, col \d+.*bad\.tif: band 1, block \(row \d+, col "
                                         r"\d+\) of 256 x 256 pixels: rows \d+\.\.\d+, columns \d+\.\.\d+: cannot be "
                                         r"read: ZIPDecode") as e:
        tiles.window(1, 0, 0, 1024, 1024)
    # GDAL's cause, not rasterio's "Read failed. See previous exception for details.", and the file once
    assert "previous exception" not in str(e.value) and str(e.value).count("bad.tif") == 1


def test_write_tiled_round_trips(tmp_path):
    src = FbmSource(300, 400, seed=2, dx=5.0)
    p = write_tiled(tmp_path / "t.tif", src.shape, lambda r0, c0, n, m: src.read(1, r0, c0, n, m), dx=5.0,
                    overviews=(2, 4))
    hm = Heightmap.load(p)
    assert np.array_equal(hm.heights, src.read(1, 0, 0, 300, 400)) and hm.dx == 5.0 and hm.dz == 5.0
    with rasterio.open(p) as d:
        assert d.block_shapes[0] == (256, 256) and d.overviews(1) == [2, 4]
