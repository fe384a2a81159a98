"""Table 2 of mrbsp-lod-visibility.txt on this machine: a ground observer (1.8 m above the terrain, 800 x
600, 60 degree field of view) walks a closed path on the bundled SRTM DEM and on a 256 x 256-cell fBm
landscape, each a 65,536-triangle MRBSP tree (M = 16); per frame: triangles drawn and time (selection
+ rasterization) for brute force (every level-M triangle in the frustum), LOD (apparent-size rule,
hole fixing, forced split propagation), VIS (precomputed cell visibility), and both. Also: the LOD
update time, the visibility precomputation (time, storage, conservativeness against the rasterizer).

    python benchmarks/bench_bintree.py [--frames N] [--cells C]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import md_table, write_result

from terrainwarp import Camera, Heightmap
from terrainwarp.lod.bintree import Bintree, select_bintree
from terrainwarp.lod.visibility import precompute_visibility
from terrainwarp.rendering import rasterize

W, H = 800, 600


def path(tree: Bintree, n: int) -> list[Camera]:
    (x0, z0), (x1, z1) = tree.heightmap.bounds_xz
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n
        x = x0 + (x1 - x0) * (0.5 + 0.3 * np.cos(a))
        z = z0 + (z1 - z0) * (0.5 + 0.3 * np.sin(a))
        y = float(tree.surface_height(x, z)) + 1.8
        d = np.array([-np.sin(a), 0.0, np.cos(a)])  # walking along the circle
        cams.append(Camera(position=(x, y, z), target=(x + d[0], y - 0.05, z + d[2]), fov_y_deg=60.0, width=W,
                           height=H, near=0.5, far=2.0 * tree.side))
    return cams


def run(name: str, hm: Heightmap, frames: int, cells: int) -> tuple[str, dict]:
    tree = Bintree.build(hm, 16)
    tree = Bintree.build(hm, 16)  # warm: the first build compiles the kernels
    t0 = time.perf_counter()
    table = precompute_visibility(tree, cells, tree.depth - 6)
    pre_s = time.perf_counter() - t0
    paper = precompute_visibility(tree, cells, tree.depth - 6, raised=False)
    cams = path(tree, frames)
    methods = {"Brute": dict(lod=False), "LOD": dict(lod=True), "VIS": dict(lod=False, vis=True),
               "Both": dict(lod=True, vis=True)}
    acc = {m: {"tris": [], "select": [], "raster": [], "toggle": []} for m in methods}
    missed = {"raised": 0, "paper": 0}
    seen_total = kept_vis = 0
    state = table.state()
    pstate = paper.state()
    for i, cam in enumerate(cams):
        ids_brute = None
        for m, kw in methods.items():
            vis = None
            if kw.get("vis"):
                t0 = time.perf_counter()
                state.move_to(cam.position[0], cam.position[2])
                acc[m]["toggle"].append(time.perf_counter() - t0)
                vis = state
            f = select_bintree(tree, cam, lod=kw["lod"], visibility=vis)
            if i == 0:  # warm-up of this method's path
                f = select_bintree(tree, cam, lod=kw["lod"], visibility=vis)
            best = (float("inf"), 0.0)
            for _ in range(3):  # best of 3 per frame: selection + rasterization
                f = select_bintree(tree, cam, lod=kw["lod"], visibility=vis)
                t0 = time.perf_counter()
                fr = rasterize(f.mesh.positions, f.mesh.triangles, cam.view_matrix(relative=True),
                               cam.proj_matrix(), W, H)
                tr = time.perf_counter() - t0
                if tr + f.stats["select_ms"] / 1e3 < sum(best):
                    best = (f.stats["select_ms"] / 1e3, tr)
            acc[m]["raster"].append(best[1])
            acc[m]["select"].append(best[0])
            acc[m]["tris"].append(f.stats["triangles"])
            if m == "Brute":
                ids_brute = f.node[fr.triangle_id[fr.triangle_id >= 0]]
                seen = np.unique(ids_brute)
                seen_total += len(seen)
            if m == "VIS":
                missed["raised"] += int(np.count_nonzero(~np.isin(seen, f.node)))
                kept_vis += f.stats["triangles"]
        pstate.move_to(cam.position[0], cam.position[2])
        fp = select_bintree(tree, cam, lod=False, visibility=pstate)
        missed["paper"] += int(np.count_nonzero(~np.isin(seen, fp.node)))
    brute_t = np.mean(acc["Brute"]["select"]) + np.mean(acc["Brute"]["raster"])
    rows = []
    for m in methods:
        a = acc[m]
        t = np.mean(a["select"]) + np.mean(a["raster"])
        rows.append([m, f"{np.mean(a['tris']):,.0f}",
                     f"{100 * np.mean(a['tris']) / np.mean(acc['Brute']['tris']):.1f}", f"{t:.4f}",
                     f"{1e3 * np.mean(a['select']):.2f}", f"{1e3 * np.mean(a['raster']):.2f}",
                     f"{100 * t / brute_t:.1f}"])
    table_md = md_table(["Method", "Tris", "Tris (%)", "Time (s)", "select (ms)", "rasterize (ms)", "Time (%)"],
                        rows)
    lod_ms = 1e3 * np.mean(acc["LOD"]["select"])
    toggle_ms = 1e3 * np.mean(acc["VIS"]["toggle"])
    info = {
        "name": name, "lod_ms": lod_ms, "toggle_ms": toggle_ms, "pre_s": pre_s, "paper_pre_s": paper.preprocess_s,
        "storage": table.storage_bytes, "full": table.full_bytes, "paper_storage": paper.storage_bytes,
        "cells": cells, "lc": table.coarse_level, "missed": missed, "seen": seen_total, "kept": kept_vis,
        "frames": frames, "build_s": tree.build_s, "hm": repr(hm), "side": tree.side,
    }
    return table_md, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--cells", type=int, default=16)
    args = ap.parse_args()
    parts = ["Paper (PowerPC 117 MHz, 65,536 triangles, 800x600): Brute 7,238 tris 0.68 s 100%; LOD 3,008 "
             "0.35 s 51.5%; VIS 2,755 0.28 s 41.2%; Both 1,732 0.18 s 26.5%; LOD update 1/320 s = 3.1 ms.\n"]
    terrains = [("SRTM DEM (jacksboro, 344x403 samples in a 31.7 km root square)", Heightmap.example()),
                ("fBm 256x256 cells (257x257 samples, 10 m spacing, 0-600 m)",
                 Heightmap.fbm(257, seed=7, dx=10.0, max_height=600.0, feature_size=128.0))]
    for name, hm in terrains:
        tab, i = run(name, hm, args.frames, args.cells)
        seen_per = i["seen"] / i["frames"]
        hidden_pct = 100 * (1 - i["seen"] / max(i["kept"], 1))
        parts.append(
            f"### {name}\n\nTree M = 16 (65,536 level-16 triangles, each one {i['side'] / 256:.4g} m cell in area), "
            f"built in {1e3 * i['build_s']:.1f} ms. {i['frames']} frames on a closed ground path (eye 1.8 m above "
            f"the terrain, looking along the path), frustum culling in every method; time = selection + our "
            f"CPU rasterizer at {W}x{H}, mean over frames of the best of 3 runs per frame. Our rasterizer has a "
            f"fixed per-pixel cost (clear, resolve) that the paper's per-triangle time did not, so Time (%) "
            f"shrinks less than Tris (%).\n\n{tab}\n\n"
            f"- LOD update (selection with hole fix and forced split propagation): **{i['lod_ms']:.2f} ms** per "
            f"frame (paper: 3.1 ms on a 117 MHz PowerPC); visibility toggling on cell crossings: "
            f"{i['toggle_ms']:.3f} ms per frame.\n"
            f"- Visibility precomputation: {i['cells']}x{i['cells']} cells, blockees at level {i['lc']} "
            f"({2 ** i['lc']} nodes): {i['pre_s']:.2f} s; stored changes {i['storage']:,} bytes (full per-cell "
            f"bitsets would be {i['full']:,} bytes).\n"
            f"- Conservativeness on the path: level-16 triangles the rasterizer shows in the brute-force frame but "
            f"VIS drops: **{i['missed']['raised']}** (raised end points, the default); with the paper's "
            f"vertex-to-vertex sampling at the surface (`raised=False`, {i['paper_pre_s']:.2f} s, "
            f"{i['paper_storage']:,} bytes): {i['missed']['paper']}. Triangles shown per frame: {seen_per:,.0f}; "
            f"VIS keeps {i['kept'] / i['frames']:,.0f}, so {hidden_pct:.1f}% "
            f"of what it keeps is hidden (or sub-pixel).\n")
    write_result("bintree", "MRBSP tree, apparent-size LOD and precomputed visibility (Table 2 of mrbsp)",
                 "\n".join(parts))


if __name__ == "__main__":
    main()
