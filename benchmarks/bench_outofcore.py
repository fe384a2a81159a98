"""Terrains larger than memory: peak RSS, tiles and bytes read, and time per frame of a ground-level camera
path over streamed heightmaps (``terrainwarp.StreamedHeightmap``), each case in its own process so that its
peak RSS is its own.

Cases:

* virtual fBm (``StreamedHeightmap.fbm``, never held) of 16,385^2, 65,537^2 (4.3 G samples: 17 GB as
  float32) and 1,048,577^2 (1.1 T samples) at 1920x1080, and 65,537^2 at 960x540: how memory grows with
  the heightmap and with the viewport;
* a 16,385^2 fBm written by this benchmark as a tiled GeoTIFF (256^2 deflate tiles, GDAL overviews),
  streamed (``Heightmap.open``; its pyramid cache built on the first open, then reused) against the
  in-memory path (``Heightmap.load``) on the same path.

Path: 8 cameras 40 m above the ground (sampled through the tiles), 150 m apart, looking 1 km ahead,
60 degree vertical field of view, far plane the terrain's extent; default LOD (sse 1 px, tess 16, 16
roots); tile cache 512 MiB (``TERRAINWARP_TILE_CACHE_MB``). The first frame includes the pyramid and every
tile generated or read for it. Time ratios are against an in-memory 4,097^2 fBm frame of the same camera
recipe, rendered in the same process after the case (its memory is not in the case's peak RSS).

    .venv/bin/python benchmarks/bench_outofcore.py           # ~12 min on 2 cores
    .venv/bin/python benchmarks/bench_outofcore.py --quick   # 16385^2 and 65537^2 at 960x540, ~3 min
    .venv/bin/python benchmarks/bench_outofcore.py --cache   # the cache study alone (below), ~4 min

The cache study (``--cache``, results/outofcore_cache.md): an 8193^2 float32 fBm GeoTIFF (256^2 deflate tiles,
GDAL overviews; written to a temporary folder), its content fingerprint's cost (the SHA-256 of the whole file
on the first open, then the stat check against the record kept beside the cache; as ratios to one plain read
of the file in the same process) and the peak RSS of three processes on the same two-camera path: the first
streamed render (it builds the cache), a later one (the cache reused) and the in-memory render
(``Heightmap.load``), each as a ratio to the in-memory one.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import md_table, write_result
from tqdm import tqdm

import terrainwarp as tw
from terrainwarp.io.geotiff import write_tiled
from terrainwarp.io.tiles import FbmSource
from terrainwarp.kernels.device import start as start_warp

N_FRAMES = 8
FBM = dict(seed=1, max_height=2000.0, dx=10.0)


def path(hm, width: int, height: int) -> list[tw.Camera]:
    """Ground-level cameras from the centre of ``hm`` (Heightmap or StreamedHeightmap)."""
    (x0, z0), (x1, z1) = hm.bounds_xz
    out = []
    for k in range(N_FRAMES):
        x, z = 0.5 * (x0 + x1) + 143.7 * k, 0.5 * (z0 + z1) + 43.1 * k
        g = float(hm.sample([x], [z])[0])
        out.append(tw.Camera(position=(x, g + 40.0, z), target=(x + 957.9, g + 20.0, z + 287.4), fov_y_deg=60.0,
                             width=width, height=height, near=1.0, far=max(x1 - x0, z1 - z0)))
    return out


def rss_mib() -> float:
    """This process's peak RSS in MiB: Linux's VmHWM (the peak of this process's own memory since it started;
    ``ru_maxrss`` would carry over the spawning process's peak across fork and exec), else ``ru_maxrss``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_now_mib() -> float:
    """This process's resident memory now (VmRSS), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def run_path(hm, width: int, height: int) -> dict:
    """The path's frames; an in-memory heightmap's Terrain (pyramids) is prepared once, in the first frame's
    time, and held across frames as a streamed heightmap holds its own. Each frame is dropped once its numbers
    are read (a caller that holds frame t while t+1 renders holds two frames: on this VM the second frame's
    first touch of memory the process never had costs ~1 s once, in frame 1)."""
    frames = []
    terrain = None
    for cam in path(hm, width, height):
        t0 = time.perf_counter()
        if isinstance(hm, tw.Heightmap) and terrain is None:
            lod = tw.LodConfig()
            terrain = tw.lod.Terrain.prepare(hm, roots=lod.roots, tess=lod.tess)
        f = tw.render(tw.Scene(hm, camera=cam, mesh="lod", outputs=("image", "depth")), terrain=terrain)
        s = time.perf_counter() - t0
        tiles = f.report.info.get("tiles", {})
        st = {r.name: r.time_ms for r in f.report.stages}
        frames.append({"s": s, "tris": f.mesh.n_triangles, "frame_ms": f.report.frame_ms, **tiles,
                       "select_ms": st.get("select", 0.0), "mesh_ms": st.get("mesh", 0.0),
                       "draw_ms": st.get("raster", 0.0) + st.get("shade", 0.0)})
        del f  # one frame at a time, as a flythrough that writes each frame out: the next reuses its memory
    return {"frames": frames, "rss_mib": rss_mib()}


def baseline(width: int, height: int) -> float:
    """Median wall seconds of the in-memory 4097^2 fBm path frames 2..8 (same camera recipe)."""
    hm = tw.Heightmap.fbm(4097, **FBM)
    return statistics.median(fr["s"] for fr in run_path(hm, width, height)["frames"][1:])


def case(name: str) -> dict:
    """One case, in this process: ``fbm:<n>:<w>x<h>``, ``tif-stream:<path>`` or ``tif-memory:<path>``."""
    kind, arg, *rest = name.split(":")
    width, height = (int(v) for v in (rest[0] if rest else "1920x1080").split("x"))
    t0 = time.perf_counter()
    if kind == "fbm":
        hm = tw.heightmap.StreamedHeightmap.fbm(int(arg), **FBM)
    elif kind == "tif-stream":
        hm = tw.Heightmap.open(arg)
    else:
        hm = tw.Heightmap.load(arg)
    open_s = time.perf_counter() - t0
    out = run_path(hm, width, height)
    out.update(open_s=open_s, width=width, height=height, samples=hm.shape[0] * hm.shape[1])
    if isinstance(hm, tw.heightmap.StreamedHeightmap):
        out["cache"] = hm.counters()
        src = next(iter(hm.held.streamed_sources.values()))
        out["pyramid"] = dict(src.terrain.provider.counters, build_s=src.build_ms / 1e3)
        out["last"] = src.last
    out["baseline_s"] = baseline(width, height)
    return out


def spawn(name: str) -> dict:
    r = subprocess.run([sys.executable, __file__, "--case", name], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"case {name} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def row(label: str, r: dict) -> list[object]:
    fr = r["frames"]
    later = [f["s"] for f in fr[1:]]
    later_read = [f.get("bytes_read", 0) for f in fr[1:]]
    return [label, f"{r['width']}x{r['height']}", f"{r['samples']:.3g}", f"{r['samples'] * 4 / 2**30:.3g}",
            round(r["rss_mib"]), round(r["open_s"] + fr[0]["s"], 1), round(statistics.median(later), 2),
            round(max(later), 2), f"{statistics.median(later) / r['baseline_s']:.2f}x",
            fr[0].get("tiles_read", "-"), round(fr[0].get("bytes_read", 0) / 2**20),
            round(statistics.mean(later_read) / 2**20, 1), round(statistics.mean(f.get("hits", 0) for f in fr[1:])),
            f"{statistics.median(f['tris'] for f in fr) / 1e6:.2f}",
            " / ".join(str(round(statistics.median(f[k] for f in fr[1:])))
                       for k in ("select_ms", "mesh_ms", "draw_ms"))]


HEADER = ["heightmap", "viewport", "samples", "GiB as float32", "peak RSS MiB", "first frame s", "later frames s",
          "later max s", "later / in-memory 4097^2", "tiles read (first)", "MiB read (first)",
          "MiB read / later frame", "cache hits / later frame", "M triangles",
          "later select / mesh / raster+shade ms"]


def error_rows() -> list[list[object]]:
    """Where overviews are read: the frame's primary error against the full-resolution reference, streamed
    (overviews) beside in-memory, on heightmaps that fit (the DEM and a 2049^2 fBm GeoTIFF), 640x360 path."""
    out = []
    with tempfile.TemporaryDirectory() as d:
        src = FbmSource(2049, seed=3, dx=10.0)
        p = write_tiled(Path(d) / "fbm2049.tif", src.shape, lambda r0, c0, a, b: src.read(1, r0, c0, a, b),
                        dx=10.0)
        for label, hm, st in (("jacksboro DEM 344x403", tw.Heightmap.example(), None),
                              ("fBm 2049^2 GeoTIFF", tw.Heightmap.load(p), tw.Heightmap.open(p))):
            st = st if st is not None else tw.heightmap.StreamedHeightmap.of(hm)
            for cam in tw.Scene(hm).camera_path(3):
                cam = cam.with_(width=640, height=360)
                fr = [tw.render(tw.Scene(h, camera=cam, mesh="lod", outputs=("error",))) for h in (hm, st)]
                e = [f.error.row() for f in fr]
                out.append([label, round(e[0]["p99_px"], 3), round(e[1]["p99_px"], 3), round(e[0]["max_px"], 3),
                            round(e[1]["max_px"], 3), fr[1].report.info["tiles"]["tiles_read"]])
    return out


def write_tif(folder: Path, n: int) -> tuple[Path, float]:
    src = FbmSource(n, **FBM)
    t0 = time.perf_counter()
    with tqdm(total=n, desc=f"writing {n}^2 tiled GeoTIFF", unit="rows", leave=False) as bar:
        p = write_tiled(folder / f"fbm{n}.tif", src.shape, lambda r0, c0, a, b: src.read(1, r0, c0, a, b),
                        dx=FBM["dx"], progress=bar.update)
    return p, time.perf_counter() - t0


def cache_case(name: str) -> dict:
    """``cache-stream:<path>:<w>x<h>`` or ``cache-memory:<path>:<w>x<h>``: the path's first two frames in this
    process, the peak RSS after each (the first streamed frame builds the cache when there is none)."""
    kind, arg, view = name.split(":")
    width, height = (int(v) for v in view.split("x"))
    t0 = time.perf_counter()
    hm = tw.Heightmap.open(arg) if kind == "cache-stream" else tw.Heightmap.load(arg)
    out = {"open_s": time.perf_counter() - t0, "open_rss_mib": rss_mib(), "open_now_mib": rss_now_mib()}
    start_warp()  # Warp's runtime (warp.so, LLVM), which the first frame would start: measured apart
    out["warp_now_mib"] = rss_now_mib()
    terrain = None
    for k, cam in enumerate(path(hm, width, height)[:2]):
        t1 = time.perf_counter()
        if isinstance(hm, tw.Heightmap) and terrain is None:
            terrain = tw.lod.Terrain.prepare(hm, roots=16, tess=16)
        f = tw.render(tw.Scene(hm, camera=cam, mesh="lod", outputs=("image", "depth")), terrain=terrain)
        out[f"frame{k}_s"], out[f"frame{k}_rss_mib"] = time.perf_counter() - t1, rss_mib()
        out["parts_mib"] = frame_parts(f, hm)
        del f
    if isinstance(hm, tw.heightmap.StreamedHeightmap):
        src = next(iter(hm.held.streamed_sources.values()))
        out["cache"] = src.terrain.provider.counters["cache"]
    return out


def frame_parts(f, hm) -> dict:
    """MiB of what a frame holds: its mesh's arrays (vertices and triangles), its images (the visibility pass's
    ids, depth and barycentrics, the shaded image), and a streamed heightmap's tile cache."""
    mib = lambda *a: sum(x.nbytes for x in a if x is not None) / 2**20  # noqa: E731
    m = f.mesh
    out = {"vertices": m.n_vertices, "triangles": m.n_triangles,
           "mesh": mib(m.positions, m.triangles, m.uv, m.normals, m.level, m.patch_id),
           "images": mib(f.triangle_id, f.depth, f.barycentrics, f.image)}
    if isinstance(hm, tw.heightmap.StreamedHeightmap):
        out["tiles"] = hm.counters()["resident_bytes"] / 2**20
    return out


def fingerprint_costs(tif: Path) -> dict:
    """The content fingerprint's cost in this process: the SHA-256 of the whole file (first open: no record),
    the stat check against the record (a later open, in a new process: an empty memo), and one plain read of the
    file (the baseline of the ratios)."""
    import terrainwarp.io.cache as cache
    from terrainwarp.io.tiles import cache_dir_for

    folder = cache_dir_for(tif)
    (folder / cache.SOURCE_RECORD).unlink(missing_ok=True)
    buf = bytearray(1 << 20)
    t0 = time.perf_counter()
    with open(tif, "rb", buffering=0) as f:
        while f.readinto(buf):
            pass
    read_s = time.perf_counter() - t0
    cache._CONTENT.clear()
    t0 = time.perf_counter()
    cache.content_digest(tif, folder)
    hash_s = time.perf_counter() - t0
    cache._CONTENT.clear()
    t0 = time.perf_counter()
    for _ in range(100):
        cache._CONTENT.clear()
        cache.content_digest(tif, folder)
    stat_s = (time.perf_counter() - t0) / 100
    return {"read_s": read_s, "hash_s": hash_s, "stat_s": stat_s, "bytes": tif.stat().st_size}


def cache_study(views: tuple[str, ...] = ("960x540", "1920x1080")) -> None:
    folder = Path(tempfile.mkdtemp(prefix="tw-cache-"))
    rows, parts = [], {}
    try:
        tif, write_s = write_tif(folder, 8193)
        with open(tif, "rb") as f:  # the file in the page cache for every case alike (not held here)
            while f.read(1 << 20):
                pass
        first_s = None
        for view in views:
            shutil.rmtree(tif.with_name(tif.name + ".twcache"), ignore_errors=True)  # each first open builds
            first = spawn_cache(f"cache-stream:{tif}:{view}")
            later = spawn_cache(f"cache-stream:{tif}:{view}")
            mem = spawn_cache(f"cache-memory:{tif}:{view}")
            first_s = first["open_s"] + first["frame0_s"] if first_s is None else first_s
            peak = lambda r: max(r["frame0_rss_mib"], r["frame1_rss_mib"])  # noqa: E731
            rows += [[view, label, r.get("cache", "-"), round(r["open_s"] + r["frame0_s"], 1), round(r["frame1_s"], 2),
                      round(r["open_now_mib"]), round(r["warp_now_mib"] - r["open_now_mib"]),
                      "-" if r["open_rss_mib"] >= peak(r) else round(peak(r) - r["warp_now_mib"]), round(peak(r)),
                      f"{peak(r) / peak(mem):.3f}x"]
                     for label, r in (("streamed, first open (builds the cache)", first),
                                      ("streamed, cache reused", later), ("in memory (Heightmap.load)", mem))]
            parts[view] = later["parts_mib"]
        fp = fingerprint_costs(tif)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    mb = fp["bytes"] / 2**20
    body = (f"An 8193^2 float32 fBm GeoTIFF ({mb:.0f} MiB on disk: 256^2 deflate tiles, GDAL overviews 2-16, "
            f"written in {write_s:.0f} s), the first two cameras of the benchmark's path; each case in its own "
            "process (the file in the page cache for all of them). Memory columns: the process's resident MiB once "
            "the heightmap is open (Python, numpy, rasterio; for the in-memory case the grid too, after the load's "
            "own peak), what starting Warp's runtime adds (warp.so and LLVM, which every process that renders "
            "maps), the rest of the peak above that (the frames, and the cache's build on a first open; '-' where "
            "the peak was the load's), and the peak (VmHWM). The target: every streamed render's peak RSS below "
            "0.25x the in-memory one's.\n\n"
            + md_table(["viewport", "render", "pyramid cache", "open + first frame s", "second frame s",
                        "after open MiB", "+ Warp MiB", "+ frames MiB", "peak RSS MiB", "peak RSS / in memory"],
                       rows) + "\n\n"
            "What a streamed frame holds (the second frame, cache reused): "
            + "; ".join(f"at {v}, {p['vertices'] / 1e6:.2f} M vertices and {p['triangles'] / 1e6:.2f} M triangles in "
                        f"a {p['mesh']:.0f} MiB mesh, {p['images']:.0f} MiB of images (ids, depth, barycentrics, "
                        f"colour), {p['tiles']:.1f} MiB of tiles" for v, p in parts.items())
            + "; the rest of the frames' part is the rasterizer's own (clip coordinates, the binned triangle "
            "lists) and the overview windows.\n\n"
            f"Content fingerprint (SHA-256 of the whole file, kept beside the cache in source.json with the file's "
            f"size, mtime, ctime, inode and device): first open {fp['hash_s']:.2f} s "
            f"({fp['hash_s'] / fp['read_s']:.2f}x one plain read of the file, {fp['read_s']:.2f} s; "
            f"{mb / fp['hash_s']:.0f} MiB/s); a later open checks the stat against the record in "
            f"{fp['stat_s'] * 1e3:.2f} ms ({fp['stat_s'] / fp['read_s']:.1e}x the read). The fingerprint's first "
            f"open is {fp['hash_s'] / first_s:.1%} of the first streamed frame at {views[0]} (which builds the "
            "pyramid and the overviews). Overview tiles are checked as read (xxHash3 of each 257^2 tile, every "
            "read); the node arrays (12 bytes a node) whole when opened.\n")
    write_result("outofcore_cache", "The cache of a streamed GeoTIFF: fingerprint and memory (bench_outofcore.py "
                 "--cache)", body)


def spawn_cache(name: str) -> dict:
    r = subprocess.run([sys.executable, __file__, "--cache-case", name], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"case {name} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--cache-case", help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--cache", action="store_true", help="the cache study alone")
    a = ap.parse_args()
    if a.case:
        print(json.dumps(case(a.case)))
        return
    if a.cache_case:
        print(json.dumps(cache_case(a.cache_case)))
        return
    if a.cache:
        cache_study()
        return
    view = "960x540" if a.quick else "1920x1080"
    fbm_cases = [16385, 65537] if a.quick else [16385, 65537, 1048577]
    rows, notes = [], []
    for n in tqdm(fbm_cases, desc="virtual fBm"):
        r = spawn(f"fbm:{n}:{view}")
        rows.append(row(f"virtual fBm {n}^2", r))
        notes.append(f"fBm {n}^2: pyramid blocks built {r['pyramid']['blocks_built']}, cache peak "
                     f"{r['cache']['peak_bytes'] / 2**20:.0f} MiB, evicted {r['cache']['evicted']} tiles, "
                     f"last frame {r['last']['windows']} windows of {r['last']['window_samples'] / 1e6:.1f} M "
                     f"samples (steps {r['last']['finest_step']}..{r['last']['coarsest_step']}), "
                     f"{r['last']['patches']} patches")
    if not a.quick:
        r = spawn("fbm:65537:960x540")
        rows.append(row("virtual fBm 65537^2", r))
    folder = Path(tempfile.mkdtemp(prefix="tw-outofcore-"))
    try:
        n = 4097 if a.quick else 16385
        tif, write_s = write_tif(folder, n)
        size = tif.stat().st_size
        first = spawn(f"tif-stream:{tif}:{view}")
        again = spawn(f"tif-stream:{tif}:{view}")
        mem = spawn(f"tif-memory:{tif}:{view}")
        rows.append(row(f"GeoTIFF {n}^2 streamed, first open", first))
        rows.append(row(f"GeoTIFF {n}^2 streamed, cache reused", again))
        rows.append(row(f"GeoTIFF {n}^2 in memory (load)", mem))
        notes.append(f"GeoTIFF {n}^2: written in {write_s:.0f} s ({size / 2**20:.0f} MiB, 256^2 deflate tiles, "
                     f"overviews 2-16); pyramid cache {first['pyramid']['cache']} in "
                     f"{first['pyramid']['build_s']:.1f} s on the first open, {again['pyramid']['cache']} in "
                     f"{again['pyramid']['build_s']:.2f} s on the second; peak RSS streamed "
                     f"{again['rss_mib']:.0f} MiB against {mem['rss_mib']:.0f} MiB in memory "
                     f"({again['rss_mib'] / mem['rss_mib']:.2f}x)")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    errs = error_rows()
    body = (f"{N_FRAMES} cameras 40 m above the ground, 150 m apart, 60 degree fov, far plane = the extent; "
            "default LOD (sse 1 px, tess 16, 16 roots); tile cache 512 MiB. First frame: opening the heightmap, "
            "its pyramid (built or read) and every tile its frame needed. Later frames: frames 2..8 (render "
            "wall time: select, mesh, raster, shade). Each case ran in its own process; the ratio column "
            "divides by the median later frame of an in-memory 4097^2 fBm on the same camera recipe in that "
            "process.\n\n" + md_table(HEADER, rows) + "\n\n" + "\n".join(f"* {t}" for t in notes) + "\n\n"
            "Error where coarse patches read overviews (heightmaps that fit in memory; the default 8-camera path "
            "of each, first 3 cameras; sse 1 px): the primary error at the heightmap's samples against the "
            "full-resolution grid, streamed from overviews beside the in-memory frame.\n\n"
            + md_table(["heightmap", "p99 px in memory", "p99 px streamed", "max px in memory", "max px streamed",
                        "tiles read"], errs) + "\n")
    write_result("outofcore", "Terrains larger than memory (bench_outofcore.py)", body)
    if not a.quick:
        cache_study()


if __name__ == "__main__":
    main()
