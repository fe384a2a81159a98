"""Hashes of the rasterizer's outputs on the benchmarks' frames and the GL-oracle tests' frames: a change to the
rasterizer that must leave its results bit-identical is checked by running this before and after it.

For each frame: SHA-256 (``terrainwarp.io.files.digest``) of the triangle id image, the depth image, the barycentric
image, the pipeline statistics (``counters=True``; for a rendered frame the whole ``Report.counters``) and the
rasterizer's ``stats`` that describe the frame rather than the pass's own work (``triangles_in``,
``triangles_rasterized``, ``fragments_inside``, ``pixels_covered``); the others (``fragments_tested``,
``pixels_written``, ``triangles_binned``, ``tile_entries``) are kept in the file as values, not compared.

Frames: bench_terrain_frame.py's six (DEM at 1 and 0.25 px, fBm at ~50k, ~340k, ~1M triangles and the flyover;
1920x1080), bench_raster.py's (fBm grids of 1e4..1e7 triangles at 640x480 and 1920x1080), bench_counters.py's
whole-frame references against llvmpipe (three spacings, two cameras, 1920x1080), and the inputs of the tests that
compare with llvmpipe (tests/kernels/test_raster.py, tests/kernels/test_counters.py, tests/rendering/
test_gl_counters.py).

    .venv/bin/python benchmarks/raster_hashes.py --out before.json           # ~2-3 min on 2 cores
    .venv/bin/python benchmarks/raster_hashes.py --compare before.json       # exit 1 on any difference
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import configure_from_env  # noqa: E402

from terrainwarp import Camera, Heightmap, Scene, render  # noqa: E402
from terrainwarp.io.files import digest  # noqa: E402
from terrainwarp.kernels.displacement import grid_mesh  # noqa: E402
from terrainwarp.kernels.raster import rasterize, rasterize_clip  # noqa: E402
from terrainwarp.lod import Terrain  # noqa: E402
from terrainwarp.scene import LodConfig  # noqa: E402

configure_from_env()
COMPARED_STATS = ("triangles_in", "triangles_rasterized", "fragments_inside", "pixels_covered")


def _module(rel: str):
    """A test or benchmark module loaded from its path (tests/ is not a package)."""
    path = ROOT / rel
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _entry(f, counters: dict | None) -> dict:
    stats = dict(f.stats)
    return {"ids": digest(f.triangle_id), "depth": digest(f.depth), "bary": digest(f.barycentrics),
            "counters": None if counters is None else digest(np.frombuffer(json.dumps(counters, sort_keys=True)
                                                                          .encode(), np.uint8)),
            "stats": digest(np.array([stats[k] for k in COMPARED_STATS], np.int64)),
            "values": {"stats": stats, "counters": counters}}


def _clip_frame(clip, tri, w, h, cull_back=False) -> dict:
    f = rasterize_clip(clip, tri, w, h, cull_back=cull_back, counters=True)
    e = _entry(f, f.counters)
    plain = rasterize_clip(clip, tri, w, h, cull_back=cull_back)
    e["plain_same"] = bool(np.array_equal(plain.triangle_id, f.triangle_id) and np.array_equal(plain.depth, f.depth))
    return e


def _mesh_frame(pos, tri, cam) -> dict:
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    f = rasterize(pos, tri, view, proj, cam.width, cam.height, counters=True)
    e = _entry(f, f.counters)
    plain = rasterize(pos, tri, view, proj, cam.width, cam.height)
    e["plain_same"] = bool(np.array_equal(plain.triangle_id, f.triangle_id) and np.array_equal(plain.depth, f.depth))
    return e


def _rendered(sc: Scene, terrain=None, **kw) -> dict:
    """A rendered frame's raster outputs (its mesh rasterized again, with barycentrics) and Report.counters."""
    fr = render(sc.with_(outputs=("depth", "counters", "mesh")), terrain=terrain, **kw)
    cam = sc.camera
    e = _mesh_frame(fr.mesh.positions, fr.mesh.triangles, cam)
    e["render_ids"] = digest(fr.triangle_id)
    e["render_depth"] = digest(fr.depth)
    e["report_counters"] = fr.report.counters
    return e


def terrain_frames(out: dict) -> None:
    btf = _module("benchmarks/bench_terrain_frame.py")
    hm = Heightmap.example()
    cam = Camera.default_for(hm, btf.WIDTH, btf.HEIGHT)
    base = LodConfig()
    terrain = Terrain.prepare(hm, roots=base.roots, tess=base.tess)  # as bench_terrain_frame.py prepares it
    for tol in (1.0, 0.25):
        out[f"terrain_frame/DEM {tol}"] = _rendered(Scene(hm, camera=cam, mesh="lod",
                                                          lod=LodConfig(tolerance_px=tol)), terrain)
    hm = Heightmap.fbm(1025, seed=7, dx=10.0, max_height=800.0)
    cam = Camera.default_for(hm, btf.WIDTH, btf.HEIGHT)
    terrain = Terrain.prepare(hm, roots=base.roots, tess=base.tess)
    for target in btf.FBM_TARGETS:
        tol, _ = btf.tolerance_for(hm, cam, terrain, target)
        out[f"terrain_frame/fBm {target}"] = _rendered(Scene(hm, camera=cam, mesh="lod",
                                                             lod=LodConfig(tolerance_px=tol)), terrain)
    fly = Scene(hm, camera=cam).camera_path(8, preset="high")[3]
    tol, _ = btf.tolerance_for(hm, fly, terrain, 340_000)
    out["terrain_frame/fBm flyover"] = _rendered(Scene(hm, camera=fly, mesh="lod", lod=LodConfig(tolerance_px=tol)),
                                                 terrain)


def raster_frames(out: dict, sizes=("1e4", "1e5", "1e6", "1e7")) -> None:
    br = _module("benchmarks/bench_raster.py")
    for k in sizes:
        hm = br.terrain(br.SIZES[k])
        for w, h in br.RESOLUTIONS:
            cam = Camera.default_for(hm, width=w, height=h)
            pos, tri = br.frame_mesh(hm, cam)
            out[f"raster/{k} {w}x{h}"] = _mesh_frame(pos, tri, cam)


def counter_frames(out: dict) -> None:
    """bench_counters.py's whole frames against llvmpipe (1920x1080, three spacings, two cameras)."""
    hm = Heightmap.example()
    terrain = Terrain.prepare(hm)
    cams = {"flyover": Scene(hm, camera=Camera.default_for(hm, 1920, 1080)).camera_path(4)[2],
            "whole": Camera.default_for(hm, 1920, 1080)}
    for spacing in ("equal", "fractional_even", "fractional_odd"):
        lod = LodConfig(policy="continuous", spacing="fractional_odd") if spacing == "fractional_odd" else \
            LodConfig(spacing=spacing)
        for cname, cam in cams.items():
            out[f"counters/{spacing} {cname}"] = _rendered(Scene(hm, camera=cam, mesh="lod", lod=lod), terrain)


def oracle_frames(out: dict) -> None:
    """The inputs of the tests that compare the rasterizer with llvmpipe."""
    tr = _module("tests/kernels/test_raster.py")
    for seed in (0, 1):
        for name, v in tr._random_sets(np.random.default_rng(seed), 2000).items():
            clip = v.astype(np.float32)
            tris = np.arange(len(clip) - len(clip) % 3, dtype=np.int32).reshape(-1, 3)
            out[f"oracle/random {seed} {name}"] = _clip_frame(clip, tris, 80, 60)
    pos, tri, cam = tr.terrain_frame()
    out["oracle/terrain_frame"] = _mesh_frame(pos, tri, cam)
    hm = Heightmap.fbm(64, 64, seed=5, max_height=300.0)
    (x0, z0), (x1, z1) = hm.bounds_xz
    cx, cz = 0.5 * (x0 + x1), 0.5 * (z0 + z1)
    hh = float(hm.heights[32, 32])
    cam = Camera(position=(cx, hh + 3.0, cz), target=(cx + 200.0, hh - 20.0, cz - 150.0), width=96, height=72,
                 near=2.0, far=5000.0, fov_y_deg=70.0)
    eye = cam.position
    pos, _, tri = grid_mesh(hm.heights, hm.dx, hm.dz, (hm.origin[0] - eye[0], eye[1], hm.origin[1] - eye[2]))
    out["oracle/camera_down"] = _mesh_frame(pos, tri, cam)
    rng = np.random.default_rng(0)
    w, h, n = 64, 48, 9
    gx, gy = np.meshgrid(np.round(np.linspace(0, w, n)) + 0.5, np.round(np.linspace(0, h, n)) + 0.5)
    clip = tr.window_to_clip(np.stack([gx.ravel(), gy.ravel()], 1), w, h, rng.uniform(-0.5, 0.5, n * n))
    front, back = [], []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            front += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
            back += [[a + 1, a, a + n]]
    front, back = np.array(front, np.int32), np.array(back, np.int32)
    for k, (tris, cull) in enumerate([(front, False), (back, False), (np.vstack([front, back]), True),
                                      (np.vstack([back, front]), True)]):
        out[f"oracle/fill {k}"] = _clip_frame(clip, tris, w, h, cull)
    clip = np.array([[-0.9, -0.9, 1.0, 1.0], [0.9, -0.8, 1.0, 1.0], [0.0, 0.9, 1.0, 1.0],
                     [-0.9, 0.9, 0.0, 1.0], [0.9, 0.9, 2.0, 1.0], [0.0, -0.9, 0.0, 1.0]], np.float32)
    out["oracle/depth_one"] = _clip_frame(clip, np.array([[0, 1, 2], [3, 4, 5]], np.int32), 32, 24)
    tc = _module("tests/kernels/test_counters.py")
    for args, (w, h), key in (((5, 3000, 1.2), (200, 120), "random"), ((1, 300), (96, 64), "passed"),
                              ((2, 200), (96, 64), "quads"), ((3, 400, 0.2), (64, 64), "records"),
                              ((4, 5000, 1.1), (320, 200), "threads")):
        kw = {"clipped": False} if key == "quads" else {}
        clip, tri = tc._triangles(*args, **kw)
        out[f"oracle/counters {key}"] = _clip_frame(clip, tri, w, h)
    rng = np.random.default_rng(6)
    culled = []
    for _ in range(120):
        c = rng.uniform(-2, 2, (3, 4)).astype(np.float32)
        c[:, 3] = rng.uniform(-1, 2, 3) if rng.random() < 0.5 else rng.uniform(0.1, 2, 3)
        f = rasterize_clip(c, np.array([[0, 1, 2]], np.int32), 64, 64, cull_back=True, counters=True)
        culled.append((digest(f.triangle_id, f.depth), f.counters))
    out["oracle/culled_clipped"] = {"ids": digest(np.frombuffer(json.dumps(culled).encode(), np.uint8)),
                                    "values": {}}
    gc = _module("tests/rendering/test_gl_counters.py")
    hm = Heightmap.example()
    cams = Scene(hm, camera=Camera.default_for(hm, gc.W, gc.H)).camera_path(4)
    dem = (hm, [Camera.default_for(hm, gc.W, gc.H), cams[2]], Terrain.prepare(hm))
    for spacing in ("equal", "fractional_even", "fractional_odd"):
        for k, fr in enumerate(gc._frames(dem, spacing)):
            e = _mesh_frame(fr.mesh.positions, fr.mesh.triangles, fr.scene.camera)
            e["report_counters"] = fr.report.counters
            out[f"gl_counters/{spacing} {k}"] = e


def compare(now: dict, before: dict) -> list[str]:
    bad = []
    for name, b in before.items():
        n = now.get(name)
        if n is None:
            bad.append(f"{name}: missing")
            continue
        for k in ("ids", "depth", "bary", "counters", "stats", "render_ids", "render_depth", "plain_same"):
            if k in b and b[k] != n.get(k):
                bad.append(f"{name}: {k} differs")
        if b.get("report_counters") != n.get("report_counters"):
            bad.append(f"{name}: report counters differ")
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="write the hashes to this JSON file")
    ap.add_argument("--compare", default=None, help="compare with this JSON file (exit 1 on a difference)")
    ap.add_argument("--only", default=None, help="comma-separated groups: terrain,raster,counters,oracle")
    a = ap.parse_args(argv)
    groups = {"terrain": terrain_frames, "raster": raster_frames, "counters": counter_frames,
              "oracle": oracle_frames}
    out: dict = {}
    for g in (a.only.split(",") if a.only else groups):
        t0 = time.perf_counter()
        groups[g](out)
        print(f"{g}: {time.perf_counter() - t0:.0f} s", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1, sort_keys=True))
    if a.compare:
        before = json.loads(Path(a.compare).read_text())
        if a.only:
            before = {k: v for k, v in before.items() if k.split("/")[0] in {
                {"terrain": "terrain_frame", "raster": "raster", "counters": "counters",
                 "oracle": "oracle"}[g] for g in a.only.split(",")} | ({"gl_counters"} if "oracle" in a.only else
                                                                       set())}
        bad = compare(out, before)
        print(f"{len(before)} frames compared: " + ("all identical" if not bad else f"{len(bad)} differences"))
        for line in bad:
            print("  " + line)
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
