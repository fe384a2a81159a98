"""The frames of bench_terrain_frame.py timed three ways on one machine: terrainwarp on a Warp device (CUDA on
the GPU machine), terrainwarp on every CPU core, and the machine's own OpenGL (through EGL: NVIDIA's driver on
the GPU machine, llvmpipe here) drawing the same patches with real tessellation shaders.

Per frame (1920x1080, the DEM at 1 px and 0.25 px, the 1025^2 fBm at about 50k, 340k and 1M triangles and a
low flyover at about 340k, tolerances bisected on the CPU as bench_terrain_frame.py does):

* device / cpu: ``select`` + ``mesh`` + ``raster`` from ``render``'s report, fastest of ``--reps`` renders after
  a warm-up (the first render on a device compiles its modules), the terrain's pyramids prepared once,
  untimed. On CUDA each stage reads its outputs back to the host, as ``render`` returns numpy arrays: the time
  is the simulator's, transfers included. The device frame is compared with the CPU frame pixel by pixel.
* gl: :class:`terrainwarp.experiments.gl.GLTerrain` drawing the frame's PatchList (batches of < 60,000
  generated vertices, as for llvmpipe): wall time from the patch upload to ``glFinish``, and the GPU's own
  time of the draws (``GL_TIME_ELAPSED`` query), best of ``--reps``.

    .venv/bin/python benchmarks/bench_gpu_frame.py --device cuda:0 --out OUT   # on the GPU machine
    .venv/bin/python benchmarks/bench_gpu_frame.py --device cpu --quick        # a dry run here (DEM rows)
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import warp as wp
from _common import md_table, write_result
from bench_terrain_frame import FBM_TARGETS, HEIGHT, STAGES, WIDTH, ours_once, tolerance_for

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.experiments.gl import GLTerrain, batches, patch_records
from terrainwarp.kernels.parallel import threads
from terrainwarp.lod import Terrain
from terrainwarp.scene import LodConfig


def frames(quick: bool):
    """(label, heightmap, camera, terrain, LodConfig) of each frame."""
    base = LodConfig()
    hm = Heightmap.example()
    cam = Camera.default_for(hm, WIDTH, HEIGHT)
    terrain = Terrain.prepare(hm, roots=base.roots, tess=base.tess)
    for tol in (1.0, 0.25):
        yield f"DEM {hm.shape[1]}x{hm.shape[0]}", hm, cam, terrain, LodConfig(tolerance_px=tol)
    if quick:
        return
    hm = Heightmap.fbm(1025, seed=7, dx=10.0, max_height=800.0)
    cam = Camera.default_for(hm, WIDTH, HEIGHT)
    terrain = Terrain.prepare(hm, roots=base.roots, tess=base.tess)
    for target in FBM_TARGETS:
        tol, _ = tolerance_for(hm, cam, terrain, target)
        yield f"fBm 1025x1025 (~{target // 1000}k)", hm, cam, terrain, LodConfig(tolerance_px=tol)
    fly = Scene(hm, camera=cam).camera_path(8, preset="high")[3]
    tol, _ = tolerance_for(hm, fly, terrain, 340_000)
    yield "fBm 1025x1025 flyover (~340k)", hm, fly, terrain, LodConfig(tolerance_px=tol)


def best_render(sc, terrain, device: str, reps: int):
    """(fastest select + mesh + raster ms, its stage records, its frame) over ``reps`` after a warm-up."""
    ours_once(sc, terrain, device)
    best = None
    for _ in range(reps):
        run = ours_once(sc, terrain, device)
        if best is None or run[0] < best[0]:
            best = run
    return best


def gl_draws(hm, cam, cfg, frame, reps: int) -> dict:
    """The frame's PatchList drawn by the machine's OpenGL: best wall ms (upload to glFinish), best GPU ms of
    the draws (timer query), the patch ids image and the renderer."""
    mesh, pl = frame.mesh, frame.patches
    tri_patch = mesh.patch_id[mesh.triangles[:, 0]]
    t_off = np.concatenate([[0], np.cumsum(np.bincount(tri_patch, minlength=len(pl)))])
    rec = patch_records(pl.origin, pl.size, pl.outer, pl.inner, hm.origin, hm.dx, hm.dz)
    ranges = batches(t_off)
    g = GLTerrain(WIDTH, HEIGHT, hm.heights, hm.dx, hm.dz, cfg.spacing)
    try:
        g.set_camera(cam.position, hm.origin, cam.view_matrix(relative=True), cam.proj_matrix())
        g.draw(rec, ranges)  # warm-up: shader compilation
        wall = gpu = float("inf")
        ids = None
        for _ in range(reps):
            ids, _, dt, _, _ = g.draw(rec, ranges)
            wall, gpu = min(wall, dt * 1e3), min(gpu, g.last_gpu_ms)
        renderer = g.renderer
    finally:
        g.close()
    pids = np.where(frame.triangle_id >= 0, tri_patch[np.maximum(frame.triangle_id, 0)], -1)
    return {"gl_ms": wall, "gl_gpu_ms": gpu, "draws": len(ranges), "renderer": renderer,
            "gl_cov_diff": int(((ids >= 0) != (pids >= 0)).sum()), "gl_patch_diff": int((ids != pids).sum())}


def measure(label, hm, cam, terrain, cfg, device: str, reps: int, gl: bool) -> dict:
    sc = Scene(hm, camera=cam, mesh="lod", lod=cfg, outputs=("depth", "mesh", "patches"))
    dev_ms, dev_st, dev_f = best_render(sc, terrain, device, reps)
    cpu_ms, cpu_st, cpu_f = best_render(sc, terrain, "cpu", reps)
    r = {"frame": label, "tol": cfg.tolerance_px, "patches": len(cpu_f.patches), "triangles": cpu_f.mesh.n_triangles,
         "dev_ms": dev_ms, **{f"dev_{s}_ms": dev_st[s].time_ms for s in STAGES}, "cpu_ms": cpu_ms,
         "id_diff": int((dev_f.triangle_id != cpu_f.triangle_id).sum()),
         "dz_max": float(np.abs(dev_f.depth - cpu_f.depth).max()),
         "gl_ms": float("nan"), "gl_gpu_ms": float("nan"), "draws": 0, "renderer": "(not drawn)",
         "gl_cov_diff": -1, "gl_patch_diff": -1}
    if gl:
        try:
            r |= gl_draws(hm, cam, cfg, cpu_f, reps)
        except Exception as e:  # noqa: BLE001 -- no OpenGL here: the device and CPU columns still count
            r["renderer"] = f"(no OpenGL: {type(e).__name__}: {str(e).splitlines()[0][:120] if str(e) else ''})"
    print(f"{label}: {r['triangles']:,} triangles; {device} {dev_ms:.1f} ms, cpu x{threads()} {cpu_ms:.1f} ms, "
          f"gl {r['gl_ms']:.1f} ms (GPU {r['gl_gpu_ms']:.2f} ms); {r['id_diff']} ids differ from the CPU's",
          flush=True)
    return r


def table(rows: list[dict], device: str) -> str:
    return md_table(
        ["frame", "sse tol px", "patches", "triangles", f"{device} ms", "select", "mesh", "raster",
         f"cpu x{threads()} ms", "cpu / device", "gl ms", "gl GPU ms", "gl / device", "draws",
         "ids != cpu px", "max dz vs cpu", "gl coverage diff px", "gl patch diff px"],
        [[r["frame"], round(r["tol"], 4), r["patches"], r["triangles"], r["dev_ms"], r["dev_select_ms"],
          r["dev_mesh_ms"], r["dev_raster_ms"], r["cpu_ms"], r["cpu_ms"] / r["dev_ms"], r["gl_ms"], r["gl_gpu_ms"],
          r["gl_ms"] / r["dev_ms"], r["draws"], r["id_diff"], r["dz_max"], r["gl_cov_diff"], r["gl_patch_diff"]]
         for r in rows])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0", help="the Warp device timed beside the CPU (default cuda:0)")
    ap.add_argument("--quick", action="store_true", help="the DEM rows only")
    ap.add_argument("--no-gl", action="store_true", help="skip the OpenGL draws")
    ap.add_argument("--reps", type=int, default=3, help="timed repetitions (best of), after one warm-up")
    ap.add_argument("--out", type=Path, default=None, help="folder for the table (default benchmarks/results)")
    args = ap.parse_args(argv)
    wp.get_device(args.device)  # an unknown device fails before any work
    t0 = time.perf_counter()
    rows = [measure(*f, args.device, max(1, args.reps), not args.no_gl) for f in frames(args.quick)]
    gpu = wp.get_device(args.device)
    name = gpu.name if gpu.is_cuda else f"the CPU ({os.cpu_count()} cores)"
    body = (f"The frames of bench_terrain_frame.py at {WIDTH}x{HEIGHT}, three ways on this machine: terrainwarp "
            f"on `{args.device}` ({name}; `select` + `mesh` + `raster` from `render`'s report, outputs read back "
            f"to the host as `render` returns them, fastest of {args.reps} after a warm-up), terrainwarp on the "
            f"CPU's {threads()} kernel threads (the same), and the same PatchList drawn by "
            f"{rows[0]['renderer']} through EGL with real tessellation shaders (`experiments.gl.GLTerrain`; wall: "
            "patch upload to `glFinish`; GPU: `GL_TIME_ELAPSED` of the upload and the draws). `ids != cpu`: pixels "
            "whose triangle id differs between the device's frame and the CPU's; gl diffs against the CPU frame as in "
            "bench_terrain_frame.py. Ratios > 1: the device is faster.\n\n" + table(rows, args.device)
            + f"\n\nWhole benchmark: {time.perf_counter() - t0:.0f} s, Warp {wp.__version__}.\n")
    if args.quick:
        print(body)
        if args.out is None:
            return
    write_result("gpu_frame" if gpu.is_cuda else "gpu_frame_dry_run",
                 f"Terrain frame: {args.device} vs {threads()} CPU threads vs OpenGL (bench_gpu_frame.py)", body,
                 out_dir=args.out)


if __name__ == "__main__":
    main()
