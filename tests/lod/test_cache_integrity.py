"""The pyramid cache beside a GeoTIFF checks itself and is safe to build from many workers (issue 31,
defects 1-3): a corrupt or truncated cache file gives the clean frame (the file rebuilt), or an error naming
it; threads and processes opening a new file at once build its cache once and all draw the serial frame."""

from __future__ import annotations

import errno
import json
import multiprocessing
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
import xxhash

import terrainwarp as tw
from terrainwarp.io.cache import CacheError, CacheFolder, file_digest
from terrainwarp.io.files import digest
from terrainwarp.io.geotiff import write_tiled
from terrainwarp.io.tiles import FbmSource
from terrainwarp.rendering.sources import StreamedSource

SIZE = 1025  # the tiled GeoTIFF: 1025^2, deflate, 256^2 blocks


def _tif(path: Path) -> Path:
    src = FbmSource(SIZE, seed=11, dx=10.0, max_height=800.0)
    return write_tiled(path, src.shape, lambda r0, c0, n, m: src.read(1, r0, c0, n, m), dx=10.0, overviews=())


def _scene(hm) -> tw.Scene:
    cam = tw.Camera(position=(900.0, 1400.0, -900.0), target=(5000.0, 200.0, 5000.0), width=160, height=120)
    return tw.Scene(hm, camera=cam, mesh="lod", outputs=("image", "depth"), lod=tw.LodConfig(roots=8, tess=16))


def _frame(path: Path) -> tuple[str, int]:
    f = tw.render(_scene(tw.Heightmap.open(path)))
    return digest(f.image, f.depth), f.mesh.n_triangles


def _full_resolution_frame(path: Path) -> str:
    hm = tw.Heightmap.open(path)
    sc = _scene(hm)
    f = tw.render(sc, source=StreamedSource(hm, sc.lod, full_resolution=True))
    return digest(f.image, f.depth)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A tiled GeoTIFF, its cache built by a first frame, and that frame (and the in-memory one)."""
    d = tmp_path_factory.mktemp("cache")
    p = _tif(d / "t.tif")
    first = _frame(p)
    mem = tw.render(_scene(tw.Heightmap.load(p)))
    return p, first, _full_resolution_frame(p), digest(mem.image, mem.depth)


def _copy(clean, tmp_path: Path) -> Path:
    """A copy of the GeoTIFF with its own cache built (the cache is keyed on the file's path and contents)."""
    q = Path(shutil.copy2(clean[0], tmp_path / clean[0].name))
    assert tw.lod.Terrain.prepare(tw.Heightmap.open(q), roots=8, tess=16).provider.counters["cache"] == "built"
    return q


def _flip_bits(f: Path) -> None:
    """Bit 0 of every byte past the first 128 (the .npy header stays valid; the size does not change)."""
    b = bytearray(f.read_bytes())
    b[128:] = bytes(x ^ 1 for x in b[128:])
    f.write_bytes(bytes(b))


@pytest.mark.parametrize("name", ["stats_*_L1.npy", "stats_*_L2.npy", "overview_8.npy", "overview_4.npy"])
@pytest.mark.parametrize("damage", ["flip", "truncate", "delete"])
def test_a_damaged_cache_file_is_rebuilt_and_the_frame_is_the_clean_one(clean, tmp_path, name, damage):
    p = _copy(clean, tmp_path)
    folder = p.with_name(p.name + ".twcache")
    (f,) = folder.glob(name)
    want_digest = file_digest(f)
    if damage == "flip":
        _flip_bits(f)
    elif damage == "truncate":  # truncate -s 50%
        with open(f, "r+b") as fh:
            fh.truncate(f.stat().st_size // 2)
    else:
        f.unlink()
    hm = tw.Heightmap.open(p)
    t = tw.lod.Terrain.prepare(hm, roots=8, tess=16)
    if damage == "flip" and name.startswith("overview"):
        # an overview is checked tile by tile as read, not whole on open: the frame reads the corrupt tiles'
        # samples from the file instead (the same values) and the overview goes, to be rebuilt by the next open
        assert t.provider.counters["cache"] == "reused"
        assert _frame(p) == clean[1] and not f.exists()
        t = tw.lod.Terrain.prepare(tw.Heightmap.open(p), roots=8, tess=16)
    assert t.provider.counters["cache"] == "repaired"
    assert file_digest(f) == want_digest  # rebuilt bit for bit
    assert _frame(p) == clean[1]
    assert _full_resolution_frame(p) == clean[2] == clean[3]  # and still the in-memory frame, bit for bit


def test_a_corrupt_manifest_rebuilds_the_cache(clean, tmp_path):
    p = _copy(clean, tmp_path)
    m = p.with_name(p.name + ".twcache") / "manifest.json"
    m.write_text(m.read_text().replace('"bytes": ', '"bytes": 1', 1))
    t = tw.lod.Terrain.prepare(tw.Heightmap.open(p), roots=8, tess=16)
    assert t.provider.counters["cache"] == "built"
    assert _frame(p) == clean[1]


def test_a_damaged_file_that_cannot_be_rebuilt_is_named(clean, tmp_path, monkeypatch):
    p = _copy(clean, tmp_path)
    (f,) = p.with_name(p.name + ".twcache").glob("stats_*_L1.npy")
    _flip_bits(f)

    def read_only(self):
        raise OSError(errno.EROFS, "Read-only file system", str(self.path))

    monkeypatch.setattr(CacheFolder, "building", read_only)
    with pytest.raises(CacheError, match=f"{f.name}: its checksum does not match the manifest's \\(corrupt\\), "
                                         r"and the pyramid cache cannot be \(re\)built there: Read-only file system"):
        tw.lod.Terrain.prepare(tw.Heightmap.open(p), roots=8, tess=16)


def _fresh(clean, tmp_path: Path, k: int) -> Path:
    d = tmp_path / f"round{k}"
    d.mkdir()
    return Path(shutil.copy2(clean[0], d / clean[0].name))  # no cache yet


def _thread_round(p: Path) -> tuple[list, list]:
    """Four threads render ``p`` at once (a barrier), two sharing one Heightmap.open and two with their own."""
    shared = tw.Heightmap.open(p)
    start = threading.Barrier(4)
    got, errors = [], []

    def work(hm):
        try:
            start.wait()
            f = tw.render(_scene(hm if hm is not None else tw.Heightmap.open(p)))
            got.append((digest(f.image, f.depth), f.mesh.n_triangles))
        except Exception as e:  # noqa: BLE001 - every failure is the test's finding
            errors.append(repr(e))

    threads = [threading.Thread(target=work, args=(h,)) for h in (shared, shared, None, None)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    return got, errors


def test_four_threads_on_a_new_cache_draw_the_serial_frame(clean, tmp_path):
    """Ten rounds on a new GeoTIFF each: every frame equals the serial one, and no error."""
    for k in range(10):
        got, errors = _thread_round(_fresh(clean, tmp_path, k))
        assert not errors, (k, errors)
        assert got == [clean[1]] * 4, k


def _process_worker(paths: list[str], start, out) -> None:
    import terrainwarp as tw_

    tw_.configure(quiet=True)
    for p in paths:
        start.wait()
        try:
            out.put((p, _frame(Path(p))))
        except Exception as e:  # noqa: BLE001 - reported to the test
            out.put((p, repr(e)))


def test_two_processes_on_a_new_cache_draw_the_serial_frame(clean, tmp_path):
    """Ten rounds: two processes open the same new GeoTIFF at once (a barrier before each round)."""
    paths = [str(_fresh(clean, tmp_path, k)) for k in range(10)]
    ctx = multiprocessing.get_context("spawn")
    start, out = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_process_worker, args=(paths, start, out)) for _ in range(2)]
    for pr in procs:
        pr.start()
    results = [out.get(timeout=600) for _ in range(2 * len(paths))]
    for pr in procs:
        pr.join(timeout=60)
        assert pr.exitcode == 0  # no SIGBUS (-7), no crash
    assert all(r == clean[1] for _, r in results), [r for r in results if r[1] != clean[1]]
    for p in paths:  # one cache, checked: every file in the manifest checks out
        folder = CacheFolder(Path(p).with_name(Path(p).name + ".twcache"), tw.Heightmap.open(p).source.fingerprint())
        body = folder.manifest()
        assert body is not None and not folder.check(sorted(body["files"]))


def test_the_cache_is_unchanged_by_reuse_and_its_digests_are_those_of_the_files(clean):
    folder = CacheFolder(clean[0].with_name(clean[0].name + ".twcache"),
                         tw.Heightmap.open(clean[0]).source.fingerprint())
    body = folder.manifest()
    assert body is not None and len(body["files"]) >= 6 and body["values"]["height_range"]
    tiled = 0
    for name, entry in body["files"].items():
        f = folder.path / name
        assert f.stat().st_size == entry["bytes"], name
        if "tiles" in entry:  # an overview: a digest per tile, in a digest file checked whole
            tiles = folder.tiled(name, body)
            assert all(xxhash.xxh3_64_intdigest(tiles.read_tile(i, j).tobytes()) == tiles.digests[i, j]
                       for i in range(tiles.grid[0]) for j in range(tiles.grid[1])), name
            tiled += 1
        else:
            assert file_digest(f) == entry["xxh3"], name
    assert tiled >= 2
    assert not np.isnan(body["values"]["height_range"]).any()


# -- issue 43 (finding 3): the cache sees every edit of its file ------------------------------------------------
def _plain_tif(path: Path, h: np.ndarray) -> Path:
    """An uncompressed, untiled GeoTIFF (an in-place edit of its middle keeps its size)."""
    import rasterio
    from affine import Affine

    with rasterio.open(path, "w", driver="GTiff", height=h.shape[0], width=h.shape[1], count=1, dtype="float32",
                       crs="EPSG:3857", transform=Affine(10.0, 0.0, 0.0, 0.0, -10.0, 0.0)) as ds:
        ds.write(h, 1)
    return path


def test_an_in_place_edit_that_keeps_size_and_mtime_is_seen(tmp_path):
    import os

    import rasterio

    h = FbmSource(257, seed=3, dx=10.0, max_height=500.0).read(1, 0, 0, 257, 257)
    p = _plain_tif(tmp_path / "dem.tif", h)
    cam = tw.Camera(position=(1200.0, 900.0, 2900.0), target=(1280.0, 200.0, 1280.0), width=96, height=64)
    scene = lambda hm: tw.Scene(hm, camera=cam, mesh="lod", outputs=("image", "depth"),  # noqa: E731
                                lod=tw.LodConfig(roots=4, tess=16))
    before = tw.render(scene(tw.Heightmap.open(p)))
    st = p.stat()
    with rasterio.open(p, "r+") as ds:  # the middle of the raster, in place: the same size
        ds.write(np.full((64, 64), 1200.0, np.float32), 1, window=rasterio.windows.Window(96, 96, 64, 64))
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))  # and the modification time set back
    assert (p.stat().st_size, p.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    hm = tw.Heightmap.open(p)
    assert hm.height_range == (float(h.min()), 1200.0)  # it stayed at the old range before
    after = tw.render(scene(hm))
    mem = tw.render(scene(tw.Heightmap.load(p)))
    assert digest(after.image, after.depth) != digest(before.image, before.depth)
    assert next(iter(hm.held.streamed_sources.values())).terrain.provider.counters["cache"] == "built"  # not stale
    assert after.mesh.n_triangles == mem.mesh.n_triangles


def test_the_content_digest_is_worked_out_once_and_again_when_the_file_changes(tmp_path, monkeypatch):
    import hashlib
    import os

    import terrainwarp.io.cache as cache

    p = _plain_tif(tmp_path / "dem.tif", FbmSource(65, seed=1).read(1, 0, 0, 65, 65))
    first = tw.Heightmap.open(p).source.fingerprint()
    record = p.with_name(p.name + ".twcache") / "source.json"
    assert json.loads(record.read_text())["sha256"] == hashlib.sha256(p.read_bytes()).hexdigest()
    cache._CONTENT.clear()  # a new process: the record beside the cache answers, the file is not read again

    def no_hashing(*a, **k):
        raise AssertionError("hashed the file again")

    monkeypatch.setattr(cache.hashlib, "sha256", no_hashing)
    assert tw.Heightmap.open(p).source.fingerprint() == first
    os.utime(p)  # a touch: the times differ, so the content is hashed again (and found the same)
    with pytest.raises(AssertionError, match="hashed the file again"):
        tw.Heightmap.open(p).source.fingerprint()
    monkeypatch.undo()
    assert tw.Heightmap.open(p).source.fingerprint() == first
