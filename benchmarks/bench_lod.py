"""LOD selection, reproducing the structure of Table 1 of deaconu2021 on a 4097x4097 fBm heightmap
(4, 16, 32, 64 roots; LOD off and on; tessellation level 1 and 32), and the growth of selection time
with the number of leaf nodes (10^3 .. 10^6), and the 1M-leaf selection at 1 and 2 threads against the
selection before the tree map (``terrainwarp/lod/quadtree.py`` at ``--baseline-rev``, loaded from git into
this process; the figure BENCHMARKS.md gave for it when git cannot supply it).

    python benchmarks/bench_lod.py [--size 4097] [--quick] [--baseline-rev REV]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import numpy as np
from _common import md_table, write_result

from terrainwarp import Camera, Heightmap
from terrainwarp.camera import flyover
from terrainwarp.io.files import digest
from terrainwarp.kernels.parallel import set_threads
from terrainwarp.lod import DistancePolicy, LodState, ScreenErrorPolicy, Terrain, select

PAPER = {  # deaconu2021 Table 1: processed vertices (CPU), frames per second on a GTX 1050
    (4, False, 1): (256, 5720.53), (4, False, 32): (256, 2351.13), (4, True, 32): (4194304, 447.27),
    (16, False, 1): (1024, 5211.73), (16, False, 32): (1024, 1368.60), (16, True, 32): (16777216, 294.07),
    (32, False, 1): (2048, 5246.13), (32, False, 32): (2048, 1369.6), (32, True, 32): (33554432, 254.93),
    (64, False, 1): (4096, 4450.53), (64, False, 32): (4096, 742.80), (64, True, 32): (67108864, 152.13),
}


BASELINE_REV = "6ad8d76"  # the last revision with the Morton-code + searchsorted neighbour search
BASELINE_1M_MS = 4239.0  # BENCHMARKS.md's depth-7 (1,048,576 leaves) select_ms for that revision


def baseline_quadtree(rev: str) -> ModuleType | None:
    """``terrainwarp/lod/quadtree.py`` as it was at ``rev``, imported beside today's (None without git)."""
    root = Path(__file__).resolve().parents[1]
    try:
        src = subprocess.run(["git", "show", f"{rev}:terrainwarp/lod/quadtree.py"], cwd=root, check=True,
                             capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    spec = importlib.util.spec_from_loader("terrainwarp.lod._quadtree_baseline", loader=None)
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "terrainwarp.lod"
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    exec(compile(src, f"{rev}:terrainwarp/lod/quadtree.py", "exec"), mod.__dict__)
    return mod


def patch_digest(pl) -> str:
    return digest(pl.level, pl.key, pl.origin, pl.size, pl.origin_cells, pl.size_cells, pl.outer, pl.inner,
                  pl.neighbour_level, pl.distance, pl.metric, pl.geometric_error,
                  np.frombuffer(repr(sorted(pl.stats.items())).encode(), np.uint8))


def million_leaves(hm: Heightmap, top: Camera, rev: str, reps: int) -> str:
    """The 1M-leaf selection (64 roots, T = 4, depth 7, every node split) at 1 and 2 threads, and before."""
    d = 7
    terrain = Terrain.prepare(hm, roots=64, tess=4, depth=d)
    pol = DistancePolicy(thresholds=(1e12,) * (d + 1))
    old = baseline_quadtree(rev)
    before_ms, same, src = BASELINE_1M_MS, "not checked", "BENCHMARKS.md (git unavailable)"
    if old is not None:
        set_threads(1)  # as it ran: one launch per level on one thread, the rest numpy
        old_t = old.Terrain(terrain.heightmap, terrain.roots, terrain.tess, terrain.depth, terrain.root_cells,
                            terrain.stats)
        old.select(old_t, top, pol)  # warm-up
        ts, ref = [], None
        for _ in range(max(1, reps - 1)):
            t0 = time.perf_counter()
            ref = old.select(old_t, top, pol)
            ts.append(time.perf_counter() - t0)
        before_ms, src = 1e3 * min(ts), f"{rev}, this process"
        same = None
    rows, ms = [], {}
    for n in (1, 2):
        set_threads(n)
        select(terrain, top, pol)  # warm-up
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            pl = select(terrain, top, pol)
            ts.append(time.perf_counter() - t0)
        ms[n] = 1e3 * min(ts)
        if old is not None:
            same = (same is not False) and patch_digest(pl) == patch_digest(ref)
        rows.append([n, len(pl), pl.stats["nodes_visited"], ms[n], before_ms, before_ms / ms[n], ms[1] / ms[n]])
    set_threads(None)
    same_txt = same if isinstance(same, str) else ("yes" if same else "NO")
    return ("\n1M-leaf selection (64 roots, T = 4, depth 7, every node split: the depth-7 row above), best of "
            f"{reps} after a warm-up; `before_ms`: the selection before the tree map ({src}); outputs identical "
            f"to it (digest of every PatchList field and the stats): {same_txt}. Target: < 500 ms.\n\n"
            + md_table(["threads", "leaves", "nodes_visited", "select_ms", "before_ms", "speed_up", "vs_1_thread"],
                       rows))


def domain_points(outer: np.ndarray, inner: np.ndarray) -> int:
    """Points of integer-spacing quad patches: boundary points (sum of outer levels) + (inner - 1)^2."""
    if len(outer) == 0:
        return 0
    return int(outer.sum() + ((inner[:, 0] - 1) * (inner[:, 1] - 1)).sum())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=4097)
    ap.add_argument("--quick", action="store_true", help="fewer cameras and leaf counts")
    ap.add_argument("--baseline-rev", default=BASELINE_REV, help="git revision of the selection to compare with")
    ap.add_argument("--reps", type=int, default=3, help="timed runs of the 1M-leaf selection")
    a = ap.parse_args()
    t0 = time.perf_counter()
    hm = Heightmap.fbm(a.size, seed=2021, dx=1.0, max_height=600.0, feature_size=a.size / 4)
    t_gen = time.perf_counter() - t0
    (x0, z0), (x1, z1) = hm.bounds_xz
    L = x1 - x0
    cams = flyover(hm, [(0.1 * L, 0.9 * L), (0.5 * L, 0.5 * L), (0.9 * L, 0.2 * L)], clearance=80.0,
                   n=3 if a.quick else 8, width=1920, height=1080, fov_y_deg=60.0, near=1.0, far=4 * L)
    rows = []
    for roots in (4, 16, 32, 64):
        for lod, tess in ((False, 1), (False, 32), (True, 32)):
            t0 = time.perf_counter()
            terrain = Terrain.prepare(hm, roots=roots, tess=tess, depth=None if lod else 0)
            t_prep = time.perf_counter() - t0
            pol = DistancePolicy(k=2.0)
            select(terrain, cams[0], pol)  # warm-up
            n_p, n_v, n_c, ts = [], [], [], []
            for cam in cams:
                t0 = time.perf_counter()
                pl = select(terrain, cam, pol)
                ts.append(time.perf_counter() - t0)
                n_p.append(len(pl))
                n_c.append(pl.stats["culled"])
                n_v.append(domain_points(pl.outer, pl.inner))
            paper_v, paper_fps = PAPER[(roots, lod, tess)]
            full = terrain.n_leaves_full * (tess + 1) ** 2 if lod else roots * (tess + 1) ** 2
            rows.append([roots, "on" if lod else "off", tess, terrain.depth, f"{terrain.roots[0]}x{terrain.roots[1]}",
                         float(np.mean(n_p)), float(np.mean(n_c)), float(np.mean(n_v)), full,
                         paper_v, paper_fps, 1e3 * float(np.median(ts)), t_prep])
    body = [f"Heightmap: {a.size}x{a.size} fBm (seed 2021, generated in {t_gen:.2f} s), dx = 1 m, heights 0..600 m. "
            f"Distance policy k = 2 (split while the eye is within 2 node sizes of the node's box), "
            f"{len(cams)}-camera flyover at 1920x1080, 60 degree fov, 80 m clearance; means over the path. "
            "`points` are the domain points the tessellator generates for the selected, unculled patches "
            "(integer spacing, doubled edges included); `all_leaves_points` is what drawing every leaf of "
            "the full tree (no culling, no LOD) would generate, the quantity deaconu2021's LOD-on rows "
            "count (their 64-root row equals 64 * 4^... leaves: 67,108,864). The paper's frame rates are "
            "for a GTX 1050 and are not comparable with a CPU selection time; they are listed for the "
            "structure.\n",
            md_table(["roots", "LOD", "T", "depth", "grid", "patches", "culled", "points", "all_leaves_points",
                      "paper_vertices", "paper_fps", "select_ms", "prepare_s"], rows)]
    # growth of selection time with the number of leaves (every node split: worst case)
    grow = []
    depths = (2, 3, 4, 5) if a.quick else (2, 3, 4, 5, 6, 7)
    top = Camera(position=(0.5 * L, 4.0 * L, 0.5 * L), target=(0.5 * L, 0.0, 0.5 * L), up=(0, 0, -1),
                 fov_y_deg=60.0, width=1920, height=1080, near=1.0, far=10 * L)
    for d in depths:
        terrain = Terrain.prepare(hm, roots=64, tess=min(64, max(1, 512 >> d)), depth=d)
        pol = DistancePolicy(thresholds=(1e12,) * (d + 1))
        select(terrain, top, pol)
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            pl = select(terrain, top, pol)
            ts.append(time.perf_counter() - t0)
        grow.append([d, len(pl), pl.stats["nodes_visited"], 1e3 * min(ts), 1e6 * min(ts) / max(len(pl), 1)])
    body.append("\nSelection time against the number of leaves (64 roots, every node split, camera above the "
                "middle seeing the whole terrain; best of 3):\n")
    body.append(md_table(["depth", "leaves", "nodes_visited", "select_ms", "us_per_leaf"], grow))
    if not a.quick and a.size == 4097:
        body.append(million_leaves(hm, top, a.baseline_rev, a.reps))
    # hysteresis (malafeev2014): level changes along a camera moving back and forth
    terrain = Terrain.prepare(hm, roots=16, tess=16)
    path = []
    for k in range(200):
        s = 0.5 + 0.02 * np.sin(k * 0.7) + 0.0004 * k  # jitter back and forth while drifting slowly
        path.append(Camera(position=(s * L, 400.0, 0.9 * L), target=(0.5 * L, 0.0, 0.3 * L), width=1920,
                           height=1080, fov_y_deg=60.0, near=1.0, far=4 * L))
    hyst = []
    for h in (0.0, 0.1, 0.25, 0.5):
        st = LodState()
        prev, changes, tris = None, 0, []
        for cam in path:
            pl = select(terrain, cam, ScreenErrorPolicy(1.0, hysteresis=h), st)
            cur = set(pl.key.tolist())
            if prev is not None:
                changes += len(cur ^ prev)
            prev = cur
            tris.append(domain_points(pl.outer, pl.inner))
        hyst.append([h, changes, round(changes / (len(path) - 1), 2), float(np.mean(tris))])
    body.append("\nHysteresis (screen-space error 1 px, split above tol * (1 + h), merge below tol * (1 - h)): "
                "patches that appear or disappear between consecutive frames of a 200-frame path that jitters "
                "back and forth while drifting:\n")
    body.append(md_table(["band h", "patch changes", "per frame", "mean points"], hyst))
    write_result("lod", "LOD selection (bench_lod.py): deaconu2021 Table 1 structure", "\n".join(body))


if __name__ == "__main__":
    main()
