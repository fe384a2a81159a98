"""Selection per frame: how long each LOD family takes to decide what to draw, at 1920x1080, on the DEM's and a
4097^2 fBm's default camera paths (16 cameras, ``Scene.camera_path(16)``, 2% of the extent above the ground).

Per family, the median over the 16 frames (after one warm pass over them) of the wall time of its ``select``
(the call ``render`` times as its ``select`` stage), and of the part of it spent inside kernel launches
(``terrainwarp.kernels.parallel.kernel_clock``; the rest is host work: allocation, numpy, Python):

* CDLOD (``first_range`` twice its smallest safe value, grid 16, as bench_schemes draws it): the tree walked in one
  launch (``CdlodTree``); beside it, in the same process, the same selection walked as numpy walks it, one
  select-level launch per tree level (the implementation it replaced, kept in ``tests/lod/test_cdlod.py`` as the
  reference the one-launch walk must equal), and their ratio.
* Chunked LOD (2 px, 32-quad tiles) and geometry clipmaps (n = 255, Losasso & Hoppe's height rule).
* The quadtree screen-space-error policy (``LodConfig`` defaults: 16 roots, T = 16, 1 px, and 0.25 px;
  ``terrainwarp.lod.select``: the descent, the 2:1 balance, the neighbour levels and edge factors), walked in one
  launch (``QuadtreeWalk``); beside it the multi-launch path a streamed terrain still takes (one launch per level,
  per balance pass and for the neighbour levels), and their ratio.

Targets (issue 34): CDLOD, clipmaps and chunked <= 0.3 ms; the quadtree policies <= 1 ms at up to 1,000 patches.
The CDLOD paper reports 0.075-0.085 ms per frame on a 3.16 GHz Core 2 (its own, larger scenes).

    .venv/bin/python benchmarks/bench_select.py     # ~1 min on 2 cores
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from _common import md_table, write_result

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.kernels.parallel import kernel_clock
from terrainwarp.lod import Terrain, select
from terrainwarp.lod.cdlod import Cdlod
from terrainwarp.lod.chunked import ChunkedLod
from terrainwarp.lod.clipmaps import Clipmap
from terrainwarp.lod.policies import make_policy
from terrainwarp.scene import LodConfig

_TESTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests")
sys.path[:0] = [_TESTS, os.path.join(_TESTS, "lod")]
from test_cdlod import _per_level_walk  # noqa: E402 - the per-level walk the one-launch one replaced
from test_lod import multi_launch_select  # noqa: E402 - the quadtree's multi-launch path (streamed terrains)

WIDTH, HEIGHT = 1920, 1080
FRAMES = 16
CDLOD_GRID = 16


def timed(fn, cams: list[Camera]) -> tuple[float, float, list]:
    """(median wall ms, median ms inside launches, the results) of ``fn(cam)`` over the cameras, after a warm
    pass."""
    for cam in cams:
        fn(cam)
    wall, kern, out = [], [], []
    for cam in cams:
        with kernel_clock() as k:
            t0 = time.perf_counter()
            out.append(fn(cam))
            wall.append((time.perf_counter() - t0) * 1e3)
        kern.append(k[0] * 1e3)
    return float(np.median(wall)), float(np.median(kern)), out


def spread(values: list[int], what: str) -> str:
    """``median / max what`` over the frames."""
    return f"{np.median(values):.0f} / {max(values)} {what}"


def rows_for(name: str, hm: Heightmap, launches: list) -> tuple[list[list[object]], list[object]]:
    cams = Scene(heightmap=hm, camera=Camera.default_for(hm, width=WIDTH, height=HEIGHT)).camera_path(FRAMES)
    rows = []

    def row(family: str, setting: str, ms: float, kern: float, drawn: str, nodes: str, target: float) -> None:
        rows.append([name, family, setting, drawn, nodes, f"{ms:.3f}", f"{kern:.3f}", f"{ms - kern:.3f}",
                     f"<= {target:g}", "yes" if ms <= target else "no"])

    c = Cdlod(hm, 1.0, grid=CDLOD_GRID)
    c.first_range = 2.0 * c.min_first_range
    ms, kern, sels = timed(c.select, cams)
    row("CDLOD", f"first_range {c.first_range:.0f} m", ms, kern, spread([len(x.size) for x in sels], "quadrants"),
        spread([x.stats["nodes_visited"] for x in sels], ""), 0.3)
    walk_ms, walk_kern, refs = timed(lambda cam: _per_level_walk(c, cam), cams)
    assert all(np.array_equal(r[0], x.origin) and np.array_equal(r[5], x.order)
               for r, x in zip(refs, sels, strict=True)), "the walks must agree"
    row("CDLOD, one launch per level (replaced)", "same", walk_ms, walk_kern, "same", "same", 0.3)
    ratio = [name, f"{walk_ms / ms:.1f}x"]
    replay_us, launch_us = c.terrain.cached(("cdlod_tree", c.grid, c.device), lambda: None).launch_cost()
    launches.append([name, "CDLOD walk (20 arguments)", f"{replay_us:.1f}", f"{launch_us:.1f}",
                     f"{launch_us - replay_us:.1f}"])

    ch = ChunkedLod(hm, 2.0, tile=32)
    ms, kern, sels = timed(ch.select, cams)
    row("chunked", "2 px, tile 32", ms, kern, spread([len(x.level) for x in sels], "chunks"),
        spread([x.stats["nodes_visited"] for x in sels], ""), 0.3)

    cm = Clipmap(hm, 255)
    ms, kern, sels = timed(cm.select, cams)
    row("clipmaps", "n 255", ms, kern, spread([x.stats["levels_drawn"] for x in sels], "levels"), "-", 0.3)

    for tol in (1.0, 0.25):
        lod = LodConfig(tolerance_px=tol)
        t = Terrain.prepare(hm, roots=lod.roots, tess=lod.tess)
        pol = make_policy(lod)
        ms, kern, sels = timed(lambda cam, t=t, pol=pol: select(t, cam, pol), cams)
        row("quadtree sse", f"{tol:g} px, 16 roots, T 16", ms, kern, spread([len(x) for x in sels], "patches"),
            spread([x.stats["nodes_visited"] for x in sels], ""), 1.0)
        if tol == 1.0:
            multi_ms, multi_kern, refs = timed(lambda cam, t=t, pol=pol: multi_launch_select(t, cam, pol), cams)
            assert all(np.array_equal(r.key, x.key) and np.array_equal(r.outer, x.outer)
                       for r, x in zip(refs, sels, strict=True)), "the paths must agree"
            row("quadtree sse, multi-launch path (streamed terrains')", "same", multi_ms, multi_kern, "same", "same",
                1.0)
            ratio.append(f"{multi_ms / ms:.1f}x")
    return rows, ratio


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the DEM only, printed (not written)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    maps = [("DEM 403x344", Heightmap.example())]
    if not args.quick:
        maps.append(("fBm 4097^2", Heightmap.fbm(4097, seed=7, dx=10.0, max_height=800.0)))
    rows, ratios, launches = [], [], []
    for name, hm in maps:
        r, q = rows_for(name, hm, launches)
        rows += r
        ratios.append(q)
    body = (f"Median over the {FRAMES} frames of each heightmap's default camera path at {WIDTH}x{HEIGHT} (after a "
            "warm pass) of one `select` call; `kernels ms`: the part inside kernel launches (`kernel_clock`), `host "
            "ms` the rest. CDLOD's per-level walk is the implementation the one-launch walk replaced, run here in the "
            "same process on the same cameras (their selections are asserted equal).\n\n"
            + md_table(["heightmap", "family", "setting", "drawn (median / max)", "nodes visited (median / max)",
                        "select ms", "kernels ms",
                        "host ms", "target ms", "met"], rows)
            + "\n\nThe walks they replaced / one launch (same process, same cameras, equal selections):\n\n"
            + md_table(["heightmap", "CDLOD", "quadtree sse 1 px"], ratios)
            + "\n\nWhat recording the launch saves (`TreeWalk.launch_cost`: best of 200 of a replay of the recorded "
              "launch against `wp.launch` of the same launch, its arguments packed again; the walk itself included in "
              "both):\n\n"
            + md_table(["heightmap", "launch", "replay us", "wp.launch us", "saved per frame us"], launches)
            + f"\n\nWhole benchmark: {time.perf_counter() - t0:.0f} s.")
    print(body)
    if not args.quick:
        write_result("select", "Selection per frame (issue 34)", body)


if __name__ == "__main__":
    main()
