"""Scaling with CPU threads: each stage and the whole frame at 1, 2 (and 4, 8 where the machine has them)
threads, as speed-up against 1 thread in the same run, with the parallel efficiency (speed-up / threads).

Stages, each through the parallel-launch helper (``terrainwarp.set_threads``), best of ``--reps`` (the thread
counts taking turns in each repetition) after a warm-up at every thread count:

* frame: ``render(Scene(mesh="lod", outputs=("depth",)))`` of a 1025^2 fBm at 1920x1080 (terrain
  prepared once, untimed), counted as every table counts it (``Report.frame_ms`` = select + mesh +
  raster), and its ``mesh`` (tessellate + displace) and ``raster`` stages from the same reports;
* tessellate: ``tessellate_patches`` on that frame's patches; raster: ``rasterize`` of its mesh;
* normals (sobel, quad), curvature (three_normal, three_vertex), pyramids (``node_stats``), fBm noise on a
  ``--size``^2 heightmap.

Wall time on a machine shared with other work is only a lower bound on the speed-up: the load average
at the start is printed with the table.

    .venv/bin/python benchmarks/bench_threads.py            # ~1 min on 2 cores
    .venv/bin/python benchmarks/bench_threads.py --quick    # smaller sizes
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

from _common import md_table, write_result

import terrainwarp as tw
from terrainwarp.kernels import parallel
from terrainwarp.kernels.noise import fbm
from terrainwarp.kernels.pyramid import node_stats
from terrainwarp.kernels.raster import rasterize
from terrainwarp.kernels.tessellator import tessellate_patches
from terrainwarp.lod import Terrain

WIDTH, HEIGHT = 1920, 1080


def thread_counts() -> list[int]:
    cores = len(os.sched_getaffinity(0))
    return [n for n in (1, 2, 4, 8) if n == 1 or n <= cores] or [1]


def frame_stages(size: int, tol: float) -> tuple[dict[str, Callable[[], float]], str]:
    """Per-stage timers of one LOD frame (each returns seconds) and a label."""
    hm = tw.Heightmap.fbm(size, seed=7, dx=10.0, max_height=800.0)
    cam = tw.Camera.default_for(hm, WIDTH, HEIGHT)
    lod = tw.LodConfig(tolerance_px=tol)
    terrain = Terrain.prepare(hm, roots=lod.roots, tess=lod.tess)
    sc = tw.Scene(hm, camera=cam, mesh="lod", lod=lod, outputs=("depth", "mesh"))
    f = tw.render(sc, terrain=terrain)
    mesh, pl = f.mesh, f.patches
    patches = {"origin_xz": pl.origin, "size": pl.size, "outer": pl.outer, "inner": pl.inner, "level": pl.level}
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    reports: list = []

    def frame() -> float:
        r = tw.render(sc, terrain=terrain).report
        reports.append(r)
        return r.frame_ms / 1e3

    def tess() -> float:
        t0 = time.perf_counter()
        tessellate_patches(patches, hm.heights, hm.dx, hm.dz, cam.position, spacing=lod.spacing,
                           filter=lod.filter, origin=hm.origin)
        return time.perf_counter() - t0

    def ras() -> float:
        t0 = time.perf_counter()
        rasterize(mesh.positions, mesh.triangles, view, proj, WIDTH, HEIGHT)
        return time.perf_counter() - t0

    timers = {"frame (select + mesh + raster)": frame,
              "  frame: select stage": lambda: tw.render(sc, terrain=terrain).report.stage_ms("select") / 1e3,
              "  frame: mesh stage": lambda: tw.render(sc, terrain=terrain).report.stage_ms("mesh") / 1e3,
              "  frame: raster stage": lambda: tw.render(sc, terrain=terrain).report.stage_ms("raster") / 1e3,
              "tessellate_patches": tess, "rasterize 1080p": ras}
    label = f"fBm {size}^2, {mesh.n_triangles:,} triangles, {len(mesh.positions):,} vertices, {WIDTH}x{HEIGHT}"
    return timers, label


def grid_stages(size: int) -> dict[str, Callable[[], float]]:
    hm = tw.Heightmap.fbm(size, seed=3, dx=5.0, max_height=500.0)

    def timed(fn: Callable[[], object]) -> Callable[[], float]:
        def run() -> float:
            t0 = time.perf_counter()
            fn()
            return time.perf_counter() - t0
        return run

    return {f"normals sobel {size}^2": timed(lambda: tw.compute_normals(hm, "sobel")),
            f"normals quad {size}^2": timed(lambda: tw.compute_normals(hm, "quad")),
            f"curvature three_normal {size}^2": timed(lambda: tw.compute_curvature(hm, "three_normal")),
            f"curvature three_vertex {size}^2": timed(lambda: tw.compute_curvature(hm, "three_vertex")),
            f"pyramids (node_stats, 16 roots, tess 16) {size}^2":
                timed(lambda: node_stats(hm.heights, (4, 4), (size - 1) / 4, 5, 16)),
            f"fBm noise {size}^2": timed(lambda: fbm(size, size, seed=1))}


def measure(timers: dict[str, Callable[[], float]], counts: list[int], reps: int) -> dict[str, dict[int, float]]:
    """Best time of each stage at each thread count; the counts take turns in every repetition, so a load
    that comes and goes on a shared machine falls on all of them alike."""
    out: dict[str, dict[int, float]] = {k: dict.fromkeys(counts, float("inf")) for k in timers}
    try:
        for n in counts:  # warm-up (and compile, on the first count)
            tw.kernels.parallel.set_threads(n)
            for fn in timers.values():
                fn()
        for _ in range(reps):
            for name, fn in timers.items():
                for n in counts:
                    tw.kernels.parallel.set_threads(n)
                    out[name][n] = min(out[name][n], fn())
    finally:
        tw.kernels.parallel.set_threads(None)
    return out


def table(times: dict[str, dict[int, float]], counts: list[int]) -> str:
    header = ["stage", "1 thread ms"]
    for n in counts[1:]:
        header += [f"{n} threads ms", f"speed-up x{n}", f"efficiency x{n}"]
    rows = []
    for name, t in times.items():
        row: list = [name, 1e3 * t[1]]
        for n in counts[1:]:
            s = t[1] / t[n]
            row += [1e3 * t[n], f"{s:.2f}x", f"{100 * s / n:.0f}%"]
        rows.append(row)
    return md_table(header, rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller heightmaps (fBm 513^2, grids 1025^2)")
    ap.add_argument("--size", type=int, default=2049, help="side of the heightmap of the grid stages")
    ap.add_argument("--reps", type=int, default=5, help="timed repetitions (best of), after one warm-up")
    args = ap.parse_args(argv)
    counts = thread_counts()
    load0 = os.getloadavg()[0]
    frame_size, grid_size = (513, 1025) if args.quick else (1025, args.size)
    timers, label = frame_stages(frame_size, 0.5)
    timers |= grid_stages(grid_size)
    times = measure(timers, counts, max(1, args.reps))
    body = (f"Frame: {label}. Thread counts: {counts} (cores this process may use: "
            f"{len(os.sched_getaffinity(0))}); load average at the start {load0:.2f}, at the end "
            f"{os.getloadavg()[0]:.2f}. Wall time, best of {args.reps} (thread counts taking turns) after a warm-up; "
            f"speed-up = 1-thread "
            f"time / n-thread time in the same run; efficiency = speed-up / n.\n\n" + table(times, counts) + "\n\n"
            "Outputs are bit-identical for every thread count (tests/kernels/test_parallel.py). Launch split: "
            f"`kernels/parallel.py`, at most threads x oversplit chunks, at least "
            f"{parallel.MIN_ITEMS} items each by default.")
    write_result("threads", "Scaling with CPU threads (bench_threads.py)", body)


if __name__ == "__main__":
    main()
