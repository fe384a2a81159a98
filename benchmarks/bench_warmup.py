"""Kernel compilation on a first run, and whether portable compiled kernels could ship in the wheel.

Warp compiles CPU kernels with ``-march=native`` by default (``warp.config.cpu_compiler_flags``): the objects use
this machine's instruction set, and the cache keys them by it. Objects built with ``cpu_compiler_flags=""`` (a
generic x86-64 target) would run on any x86-64 machine, so a wheel could carry them and skip the first-run compile.
This measures both: the compile of every kernel module from an empty cache (``terrainwarp.warmup``: in one process,
module by module, and in worker processes), the objects' size, and the run time of the pipeline's kernels built
each way.

Warp's compiler flags are process-wide and part of every module's hash, so each setting runs in its own process
with its own empty kernel cache (``WARP_CACHE_PATH``); the settings (Warp's default; the same without
``-march=native``; ``""``, a generic target with LLVM's defaults) take turns for ``--rounds`` rounds and the table
gives each one's median and its ratio to the default's (the turns cancel most of the drift of a shared machine,
not all of it: the load average is printed with the table). Workloads, best of ``--repeat``
after a warm-up:

* frame: ``render`` of the demo DEM at 1280x720 (image and depth, the grid mesh);
* lod+error: the same camera with ``mesh="lod"`` and ``outputs=("error",)`` (selection, tessellation, the
  sample-error pass against the reference);
* surface: ``compute_normals`` and ``compute_curvature`` of a 1025^2 fBm;
* raster: ``rasterize`` of the frame's grid mesh at 1920x1080.

    .venv/bin/python benchmarks/bench_warmup.py            # ~15 min on 2 shared cores
    .venv/bin/python benchmarks/bench_warmup.py --rounds 1 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# None: Warp's default (-march=native and its LLVM inlining options); "generic": the same without -march=native (a
# generic x86-64 target, Warp's options kept); "": a generic target with LLVM's defaults
SETTINGS = {"native": None, "generic": "generic", "generic, LLVM defaults": ""}
WORKLOADS = ("frame", "lod+error", "surface", "raster")


def child(flags: str | None, repeat: int) -> dict:
    """One setting in this process: compile everything from an empty cache, then time the workloads."""
    import warp as wp

    if flags == "generic":
        flags = " ".join(t for t in wp.config.cpu_compiler_flags.split() if t != "-march=native")
    wp.config.cpu_compiler_flags = flags if flags is not None else wp.config.cpu_compiler_flags
    import terrainwarp as tw
    from terrainwarp.warmup import warmup

    t0 = time.perf_counter()
    res = warmup(workers=int(os.environ["BENCH_WARMUP_WORKERS"]), progress=False)
    compile_s = time.perf_counter() - t0
    cache = Path(res.cache_dir)
    obj_bytes = sum(p.stat().st_size for p in cache.rglob("wp_terrainwarp.kernels.*.o"))
    hm = tw.Heightmap.example()
    cam = tw.Camera.default_for(hm, 1280, 720)
    frame_sc = tw.Scene(hm, camera=cam, outputs=("image", "depth"))
    lod_sc = tw.Scene(hm, camera=cam, mesh="lod", outputs=("error",))
    fbm = tw.Heightmap.fbm(1025, seed=1, dx=10.0)
    mesh = tw.render(frame_sc.with_(outputs=("mesh",))).mesh
    big = cam.with_(width=1920, height=1080)

    work = {
        "frame": lambda: tw.render(frame_sc),
        "lod+error": lambda: tw.render(lod_sc),
        "surface": lambda: (tw.compute_normals(fbm, "sobel"), tw.compute_curvature(fbm, "three_normal")),
        "raster": lambda: tw.rendering.rasterize(mesh.positions, mesh.triangles, big.view_matrix(relative=True),
                                                 big.proj_matrix(), 1920, 1080),
    }
    times = {}
    for name, fn in work.items():
        fn()  # warm-up (pools, caches)
        best = float("inf")
        for _ in range(repeat):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
        times[name] = best
    return {"compile_s": compile_s, "modules": len(res.compiled), "obj_bytes": obj_bytes, "times": times,
            "workers": res.workers}


def run_child(setting: str, repeat: int, workers: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="tw-bench-warmup-") as cache:
        env = {**os.environ, "WARP_CACHE_PATH": cache, "BENCH_WARMUP_WORKERS": str(workers)}
        out = subprocess.run([sys.executable, __file__, "--child", setting, "--repeat", str(repeat)], env=env,
                             capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2, help="turns of each setting (each compiles from empty)")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs of each workload (best counts)")
    ap.add_argument("--child", choices=list(SETTINGS), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(SETTINGS[args.child], args.repeat)))
        return
    from _common import md_table, write_result  # (the parent only: a child measures Warp as it starts)

    load = os.getloadavg()[0]
    runs: dict[str, list[dict]] = {s: [] for s in SETTINGS}
    parallel: dict[str, list[float]] = {s: [] for s in SETTINGS}
    for r in range(args.rounds):
        for s in SETTINGS:  # one process per setting, taking turns
            runs[s].append(run_child(s, args.repeat, 0))
            print(f"round {r + 1}: {s}: compile {runs[s][-1]['compile_s']:.1f} s (one process), "
                  f"{json.dumps({k: round(v * 1e3, 1) for k, v in runs[s][-1]['times'].items()})} ms", flush=True)
        for s in SETTINGS:  # the parallel compile alone (the warmup of make setup), same turns
            parallel[s].append(run_child(s, 1, os.cpu_count() or 1)["compile_s"])

    def med(s: str, key: str | None = None) -> float:
        vals = [x["times"][key] if key else x["compile_s"] for x in runs[s]]
        return statistics.median(vals)

    others = [s for s in SETTINGS if s != "native"]

    def row(label: str, value) -> list:
        v = {s: value(s) for s in SETTINGS}
        return [label, *(v[s] for s in SETTINGS), *(v[s] / v["native"] for s in others)]

    rows = [row("compile, one process (s)", med),
            row(f"compile, {os.cpu_count()} worker processes (s)", lambda s: statistics.median(parallel[s])),
            row("objects (MiB)", lambda s: runs[s][0]["obj_bytes"] / 2**20)]
    rows += [row(f"{w} (ms)", lambda s, w=w: med(s, w) * 1e3) for w in WORKLOADS]
    body = md_table(["", *SETTINGS, *(f"{s} / native" for s in others)], rows)
    body += (f"\n\n{runs['native'][0]['modules']} kernel modules; medians of {args.rounds} round(s), each setting in "
             f"its own process with an empty kernel cache, workloads best of {args.repeat}; load average "
             f"{load:.1f} at the start on a machine shared with other work. Portable objects would be keyed to "
             "this exact Warp version and its LLVM (the cache name holds both), so a wheel carrying them works "
             "only with the Warp it was built against, and a process must run with those flags to find them. "
             "native: Warp's default (-march=native and its inlining options); generic: the same options without "
             "-march=native; generic, LLVM defaults: cpu_compiler_flags=''.\n")
    write_result("warmup", "Kernel compilation: first run, and portable objects against -march=native", body)


if __name__ == "__main__":
    main()
