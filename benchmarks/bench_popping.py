"""Hysteresis against popping (issue 17 item 2): the pop of each consecutive frame pair, for hysteresis bands
0, 0.1, 0.25 and 0.5, on a ground-level path (2% of the extent above the bundled DEM) that jitters back and
forth while drifting (the path of bench_lod.py's hysteresis table); and the polytree's TIN morph against
the same polytree switching whole levels.

The pop of pair (t-1, t): camera t drawn with the LOD selected at t-1 (held, with the hysteresis state as it
was) against the LOD selected at t, per visible heightmap sample, in pixels
(terrainwarp.rendering.pipeline.pop_stats). `popped` counts samples moving by more than 0.5 px.

    python benchmarks/bench_popping.py [--frames 48] [--width 1920 --height 1080] [--no-morph]
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace

import numpy as np
from _common import md_table, write_result
from bench_polytree import MorphSource

from terrainwarp import Camera, Heightmap, LodConfig, Scene, render
from terrainwarp.lod import LodState, Terrain
from terrainwarp.lod.polytree import build_polytree, default_tolerances
from terrainwarp.rendering.pipeline import pop_stats
from terrainwarp.rendering.sources import SourceBase
from terrainwarp.scene import GROUND_CLEARANCE

BANDS = (0.0, 0.1, 0.25, 0.5)


def jitter_path(hm: Heightmap, n: int, width: int, height: int) -> list[Camera]:
    """``n`` cameras along the default path's diagonal at 2% of the extent above the ground, jittering back
    and forth (+-2% of the diagonal) while drifting slowly forward; each looks 25% of the extent ahead."""
    (x0, z0), (x1, z1) = hm.bounds_xz
    ext = max(x1 - x0, z1 - z0)
    a = np.array([x0 + 0.15 * (x1 - x0), z0 + 0.85 * (z1 - z0)])
    b = np.array([x0 + 0.85 * (x1 - x0), z0 + 0.15 * (z1 - z0)])
    d = (b - a) / np.linalg.norm(b - a)
    clearance = GROUND_CLEARANCE * ext

    def ground(p):
        j = int(np.clip(round((p[0] - hm.origin[0]) / hm.dx), 0, hm.shape[1] - 1))
        i = int(np.clip(round((p[1] - hm.origin[1]) / hm.dz), 0, hm.shape[0] - 1))
        return float(np.nanmax(hm.heights[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3]))

    cams = []
    for k in range(n):
        s = 0.3 + 0.02 * math.sin(k * 0.7) + 0.002 * k
        p = a + s * (b - a)
        t = p + 0.25 * ext * d
        cams.append(Camera(position=(p[0], ground(p) + clearance, p[1]), target=(t[0], ground(t), t[1]),
                           width=width, height=height, fov_y_deg=60.0, near=clearance * 1e-2, far=4 * ext))
    return cams


def _pairs(pops: list) -> list:
    p99 = [p.p99_px for p in pops]
    return [float(np.median(p99)), max(p99), max(p.max_px for p in pops), int(sum(p.popped for p in pops)),
            int(max(p.popped for p in pops)), int(sum(p.popped_pixels for p in pops))]


def hysteresis_rows(sc: Scene, terrain: Terrain, cams: list[Camera], refs: list) -> list[list]:
    rows = []
    for h in BANDS:
        scene = sc.with_(lod=replace(sc.lod, hysteresis=h))
        state, prev, pops, err, tris, changes = LodState(), None, [], [], [], 0
        for k, cam in enumerate(cams):
            s_k = scene.with_(camera=cam)
            f = render(s_k, terrain, state=state, reference=refs[k])
            err.append(f.error.p99_px)
            tris.append(f.mesh.n_triangles)
            if prev is not None:
                pops.append(pop_stats(s_k, cams[k - 1], f, refs[k], terrain=terrain, held=prev.patches))
                changes += len(set(f.patches.key.tolist()) ^ set(prev.patches.key.tolist()))
            prev = f
        rows.append([h, *_pairs(pops), changes, max(err), int(np.mean(tris))])
    return rows


class _LevelSource(SourceBase):
    """The polytree without morphing: the continuous level rounded to a whole level per frame."""

    def __init__(self, morph: MorphSource) -> None:
        super().__init__()
        self.morph = morph

    def mesh_for(self, camera: Camera):
        m = self.morph
        d = float(np.linalg.norm(np.asarray(camera.position) - m.centre))
        return m.tree.mesh(int(round(m.tree.level_for_distance(d, *m.span, levels=m.levels))),
                           eye=camera.position), 0.0


def morph_rows(sc: Scene, cams: list[Camera], refs: list) -> tuple[list[list], str]:
    hm = sc.heightmap
    t0 = time.perf_counter()
    pt = build_polytree(hm, default_tolerances(hm, 64))
    build_s = time.perf_counter() - t0
    full = 2 * (hm.shape[0] - 1) * (hm.shape[1] - 1)
    counts = np.array([pt.n_triangles(t) for t in range(pt.n_levels)])
    lo, hi = (int(np.argmin(np.abs(counts - f * full))) for f in (0.1, 0.01))
    hmin, hmax = hm.height_range
    ctr = np.array([hm.origin[0] + 0.5 * (hm.shape[1] - 1) * hm.dx, 0.5 * (hmin + hmax),
                    hm.origin[1] + 0.5 * (hm.shape[0] - 1) * hm.dz])
    dists = [float(np.linalg.norm(np.asarray(c.position) - ctr)) for c in cams]
    morph = MorphSource(pt, ctr, (min(dists), max(dists)), (lo, hi))
    rows = []
    for name, src in (("polytree, whole levels", _LevelSource(morph)), ("polytree, TIN morph", morph)):
        pops, err = [], []
        for k, cam in enumerate(cams):
            s_k = sc.with_(camera=cam)
            f = render(s_k, reference=refs[k], source=src)
            err.append(f.error.p99_px)
            if k:
                pops.append(pop_stats(s_k, cams[k - 1], f, refs[k], source=src))
        rows.append([name, *_pairs(pops), max(err)])
    note = (f"Polytree of 64 tolerances built in {build_s:.1f} s; the level follows the camera's distance to the "
            f"terrain's centre linearly from level {lo} ({counts[lo]} triangles) at the nearest camera to level "
            f"{hi} ({counts[hi]} triangles) at the farthest (bench_polytree.py's MorphSource); 'whole levels' "
            "rounds that level, 'TIN morph' morphs between the two levels around it.")
    return rows, note


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--tolerance-px", type=float, default=1.0)
    ap.add_argument("--no-morph", action="store_true")
    a = ap.parse_args()
    hm = Heightmap.example()
    cams = jitter_path(hm, a.frames, a.width, a.height)
    sc = Scene(hm, camera=cams[0], mesh="lod", lod=LodConfig(tolerance_px=a.tolerance_px, roots=16, tess=16),
               outputs=("error",))
    terrain = Terrain.prepare(hm, roots=16, tess=16)
    refs = [render(sc.with_(camera=c, mesh="grid", outputs=("depth",))) for c in cams]
    t0 = time.perf_counter()
    hyst = hysteresis_rows(sc, terrain, cams, refs)
    cols = ["median pair pop p99 px", "worst pair pop p99 px", "pop max px", "popped samples (sum)",
            "popped samples (worst pair)", "popped pixels (sum)"]
    (x0, z0), (x1, z1) = hm.bounds_xz
    clearance = GROUND_CLEARANCE * max(x1 - x0, z1 - z0)
    body = (f"Bundled SRTM DEM, {len(cams)}-frame ground-level path (2% of the extent, {clearance:.0f} m, "
            f"above the ground; jittering +-2% of the diagonal back and forth while drifting), {a.width}x{a.height}, "
            f"60 degree fov; sse policy at {a.tolerance_px:g} px (16 roots, tess 16) with a hysteresis band h "
            "(LodState carried across frames). Pop of pair (t-1, t): camera t drawn with the selection held from "
            "t-1 against its own, per visible heightmap sample (`terrainwarp.rendering.pipeline.pop_stats`); "
            "popped = samples moving by more than 0.5 px. `patch changes`: patches appearing or disappearing "
            f"between frames. Hysteresis table: {time.perf_counter() - t0:.0f} s.\n\n"
            + md_table(["band h", *cols, "patch changes", "worst frame p99 px", "mean triangles"], hyst))
    if not a.no_morph:
        morph, note = morph_rows(sc.with_(mesh="grid"), cams, refs)
        body += "\n\n" + note + "\n\n" + md_table(["mesh", *cols, "worst frame p99 px"], morph)
    print(body)
    write_result("popping", "Hysteresis and morphing against popping (bench_popping.py)", body)


if __name__ == "__main__":
    main()
