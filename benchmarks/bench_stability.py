"""Scale: fractal heightmaps from 1k to 16k generated tile by tile, through pyramid building, LOD selection
and one 1920x1080 LOD frame, with time and peak memory per stage; plus the stability suite in full.

Each size runs in its own process, so ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` (the process's peak
resident memory, which only grows) belongs to that size alone. ``tracemalloc`` peaks count host (numpy)
allocations per stage; Warp's own device buffers are not seen by tracemalloc, only by maxrss.

The heightmap is generated tile by tile (1024 x 1024 fBm windows, ``terrainwarp.kernels.noise.fbm``
with ``row0``/``col0``) straight into its final array, so generation never holds more than the
heightmap plus one tile. The camera is the same for every size (1,500 m above the southern part of the
terrain, looking north at 400 m), so the frame needs about the same patches whatever the heightmap's
size: what grows with the size is the heightmap itself and its pyramids.

    python benchmarks/bench_stability.py [--sizes 1025,2049,4097,8193,16385] [--budget-s 420] [--no-suite]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import tracemalloc

import numpy as np
from _common import md_table, write_result

TILE = 1024
MB = 1024.0 * 1024.0


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def one(n: int) -> dict:
    """Run one size in this process and return its measurements."""
    # lazy: the RSS at start is measured before terrainwarp (and Warp) are imported in this process
    import terrainwarp as tw
    from terrainwarp.kernels.noise import fbm
    from terrainwarp.lod import ScreenErrorPolicy, Terrain, select

    out: dict = {"n": n, "rss_start_mb": _maxrss_mb()}
    tracemalloc.start()

    def stage(name, fn):
        tracemalloc.reset_peak()
        t0 = time.perf_counter()
        r = fn()
        out[f"{name}_s"] = time.perf_counter() - t0
        out[f"{name}_peak_mb"] = tracemalloc.get_traced_memory()[1] / MB
        out[f"{name}_rss_mb"] = _maxrss_mb()
        return r

    def generate():
        h = np.empty((n, n), np.float32)
        for r in range(0, n, TILE):
            for c in range(0, n, TILE):
                t = fbm(min(TILE, n - r), min(TILE, n - c), seed=11, base_frequency=1.0 / 512.0, row0=r, col0=c)
                h[r:r + t.shape[0], c:c + t.shape[1]] = (t + np.float32(1.0)) * np.float32(500.0)
        return tw.Heightmap(heights=h, dx=10.0, dz=10.0, name=f"fbm{n}")  # no copy (from_array would make one)

    hm = stage("generate", generate)
    terrain = stage("prepare", lambda: Terrain.prepare(hm, roots=16, tess=16))
    (x0, z0), (x1, z1) = hm.bounds_xz
    cx = 0.5 * (x0 + x1)
    cam = tw.Camera(position=(cx, 1500.0, z1 - 2000.0), target=(cx, 400.0, z1 - 12000.0), width=1920, height=1080,
                    near=1.0, far=1e6)
    patches = stage("select", lambda: select(terrain, cam, ScreenErrorPolicy(1.0)))
    scene = tw.Scene(hm, camera=cam, outputs=("depth",), mesh="lod", lod={"roots": 16, "tess": 16})
    frame = stage("frame", lambda: tw.render(scene, terrain=terrain))
    tracemalloc.stop()
    out.update(patches=len(patches), triangles=frame.mesh.n_triangles, levels=int(patches.level.max()),
               covered=int((frame.depth < 1.0).sum()), heightmap_mb=hm.heights.nbytes / MB,
               finite=bool(np.all(np.isfinite(frame.depth)) and np.all(np.isfinite(frame.mesh.positions))),
               rss_peak_mb=_maxrss_mb())
    return out


def scale(sizes: list[int], budget_s: float) -> list[dict]:
    rows: list[dict] = []
    t_start = time.perf_counter()
    last = 0.0
    for n in sizes:
        spent = time.perf_counter() - t_start
        if rows and spent + 4.5 * last > budget_s:  # the next size costs ~4x the last one
            print(f"skip {n}: {spent:.0f} s spent, ~{4.5 * last:.0f} s more would exceed --budget-s {budget_s:.0f}")
            rows.append({"n": n, "skipped": f"time budget ({budget_s:.0f} s)"})
            continue
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, __file__, "--one", str(n)], capture_output=True, text=True)
        last = time.perf_counter() - t0
        if r.returncode != 0:
            msg = (r.stderr.strip().splitlines() or ["?"])[-1]
            print(f"{n}: failed ({msg})")
            rows.append({"n": n, "skipped": f"failed: {msg[:80]}"})
            continue
        d = json.loads(r.stdout.strip().splitlines()[-1])
        d["wall_s"] = last
        print(f"{n}: {last:.1f} s, peak rss {d['rss_peak_mb']:.0f} MB")
        rows.append(d)
    return rows


def suite_table(full: bool) -> tuple[str, float]:
    from terrainwarp.experiments.stability import EXPLANATIONS, FAIL, PASS, RAISED, run_suite  # lazy: see one()

    t0 = time.perf_counter()
    rows = run_suite(129 if full else 33)
    dt = time.perf_counter() - t0
    by_stage: dict[str, dict[str, int]] = {}
    for r in rows:
        d = by_stage.setdefault(r.stage, {PASS: 0, RAISED: 0, FAIL: 0})
        d[r.status] = d.get(r.status, 0) + 1
    tab = md_table(["stage", "pass", "raised", "FAIL"], [[s, d[PASS], d[RAISED], d[FAIL]] for s, d in by_stage.items()])
    pick = {("everest", "normals"), ("everest", "curvature"), ("everest", "sampling"), ("far_1e+07", "raster"),
            ("far_1e+05", "raster"), ("relief_1e+06", "normals"), ("spacing_0.001", "normals")}
    rem = md_table(["case", "stage", "float32 with remedy", "float32 without"],
                   [[r.case, r.stage, r.error, r.naive] for r in rows if (r.case, r.stage) in pick])
    fails = [f"- {r.case}/{r.stage}: {r.note}; why: "
             f"{next((v for k, v in EXPLANATIONS.items() if k in r.note), 'UNEXPLAINED')}" for r in rows
             if r.status == FAIL]
    return (f"Stability suite on {129 if full else 33}^2 grids ({dt:.0f} s; `terrainwarp stability --out DIR "
            f"--full` writes the per-case table): outcomes per stage\n\n{tab}\n\n" + "\n".join(fails) +
            f"\n\nThe float32 remedies, measured (error against the float64 reference):\n\n{rem}\n"), dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="1025,2049,4097,8193,16385")
    ap.add_argument("--budget-s", type=float, default=420.0, help="skip larger sizes that would exceed this")
    ap.add_argument("--no-suite", action="store_true")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one is not None:
        print(json.dumps(one(args.one)))
        return
    sizes = [int(s) for s in args.sizes.split(",") if s]
    rows = scale(sizes, args.budget_s)
    done = [r for r in rows if "skipped" not in r]
    hdr = ["size", "heightmap MB", "generate s", "prepare s", "select s", "frame s", "patches", "triangles",
           "tracemalloc peak MB (gen / prep / select / frame)", "peak RSS MB", "RSS / heightmap", "finite"]
    tab = []
    for r in rows:
        if "skipped" in r:
            tab.append([f"{r['n']}^2", "", "", "", "", "", "", "", r["skipped"], "", "", ""])
            continue
        tab.append([f"{r['n']}^2", round(r["heightmap_mb"], 1), round(r["generate_s"], 2), round(r["prepare_s"], 2),
                    round(r["select_s"], 3), round(r["frame_s"], 2), r["patches"], r["triangles"],
                    " / ".join(f"{r[k + '_peak_mb']:.0f}" for k in ("generate", "prepare", "select", "frame")),
                    round(r["rss_peak_mb"]), round(r["rss_peak_mb"] / r["heightmap_mb"], 2), r["finite"]])
    body = ("Fractal (fBm) heightmaps generated tile by tile (1024^2 windows), dx = 10 m, heights 0..1000 m; "
            "pyramids (16 roots, T = 16), screen-error selection (1 px), one 1920x1080 LOD frame (depth) from a "
            "fixed camera 1,500 m up looking north. Each size in its own process.\n\n" + md_table(hdr, tab))
    if len(done) >= 2:
        a, b = done[0], done[-1]
        k = b["heightmap_mb"] / a["heightmap_mb"]
        body += (f"\n\nGrowth {a['n']}^2 -> {b['n']}^2 (heightmap x{k:.0f}): "
                 f"prepare x{b['prepare_s'] / a['prepare_s']:.1f}, select x{b['select_s'] / a['select_s']:.1f}, "
                 f"frame x{b['frame_s'] / a['frame_s']:.1f}, patches x{b['patches'] / max(a['patches'], 1):.2f}, "
                 f"peak RSS x{b['rss_peak_mb'] / a['rss_peak_mb']:.1f}. "
                 "Memory is dominated by the heightmap and the pyramids (O(N^2)); the frame's own patches and "
                 "triangles grow only with the levels the frame needs.")
    if not args.no_suite:
        st, _ = suite_table(full=True)
        body += "\n\n" + st
    write_result("stability", "Stability and scale", body)


if __name__ == "__main__":
    main()
