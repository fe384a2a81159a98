"""LOD selection, reproducing the structure of Table 1 of deaconu2021 on a 4097x4097 fBm heightmap
(4, 16, 32, 64 roots; LOD off and on; tessellation level 1 and 32), and the growth of selection time
with the number of leaf nodes (10^3 .. 10^6).

    python benchmarks/bench_lod.py [--size 4097] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import md_table, write_result

from terrainwarp import Camera, Heightmap, flyover
from terrainwarp.lod import DistancePolicy, LodState, ScreenErrorPolicy, Terrain, select

PAPER = {  # deaconu2021 Table 1: processed vertices (CPU), frames per second on a GTX 1050
    (4, False, 1): (256, 5720.53), (4, False, 32): (256, 2351.13), (4, True, 32): (4194304, 447.27),
    (16, False, 1): (1024, 5211.73), (16, False, 32): (1024, 1368.60), (16, True, 32): (16777216, 294.07),
    (32, False, 1): (2048, 5246.13), (32, False, 32): (2048, 1369.6), (32, True, 32): (33554432, 254.93),
    (64, False, 1): (4096, 4450.53), (64, False, 32): (4096, 742.80), (64, True, 32): (67108864, 152.13),
}


def domain_points(outer: np.ndarray, inner: np.ndarray) -> int:
    """Points of integer-spacing quad patches: boundary points (sum of outer levels) + (inner - 1)^2."""
    if len(outer) == 0:
        return 0
    return int(outer.sum() + ((inner[:, 0] - 1) * (inner[:, 1] - 1)).sum())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=4097)
    ap.add_argument("--quick", action="store_true", help="fewer cameras and leaf counts")
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
