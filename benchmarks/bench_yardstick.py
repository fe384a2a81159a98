"""The primary error (at the heightmap's samples, terrainwarp.measure.sample_error) of every family's finest
setting, beside the floor the per-pixel grid-image error (terrainwarp.measure.error.frame_error) carries on
the same cameras; and the cost of measuring a 4097^2 heightmap."""

from __future__ import annotations

import resource
import time

from _common import md_table, write_result

from terrainwarp import Heightmap, LodConfig, Scene, render
from terrainwarp.camera import flyover
from terrainwarp.lod import Terrain
from terrainwarp.lod.bintree import Bintree, select_bintree
from terrainwarp.lod.peers import delatin_mesh, martini_mesh
from terrainwarp.lod.polytree import build_polytree
from terrainwarp.measure.sample_error import sample_error

W, H = 1920, 1080
LOD = {"roots": 16, "tess": 16}
FAMILIES = ("grid", "quadtree", "martini", "delatin", "bintree", "polytree")


def _path(hm: Heightmap, clearance: float, n: int, width: int = W, height: int = H):
    (x0, z0), (x1, z1) = hm.bounds_xz
    ext = max(x1 - x0, z1 - z0)
    wps = [(x0 + 0.15 * (x1 - x0), z0 + 0.2 * (z1 - z0)), (x0 + 0.85 * (x1 - x0), z0 + 0.75 * (z1 - z0))]
    return flyover(hm, wps, clearance * ext, n, width=width, height=height)


def finest_rows(hm: Heightmap) -> list[list[object]]:
    terrain = Terrain.prepare(hm, **LOD)
    tree, poly = Bintree.build(hm), build_polytree(hm, [0.0])
    mar, dela = martini_mesh(hm, 0.0), delatin_mesh(hm, 0.0)
    rows = []
    for clearance in (0.02, 0.10):
        worst = {k: [0.0, 0.0] for k in FAMILIES}
        old = [0.0, 0.0]
        for cam in _path(hm, clearance, 3):
            grid = render(Scene(hm, cam, outputs=("depth", "mesh")))
            lod = render(Scene(hm, cam, outputs=("mesh", "error"), mesh="lod",
                               lod=LodConfig(tolerance_px=1e-6, **LOD)), terrain=terrain, reference=grid)
            meshes = {"grid": grid.mesh, "quadtree": lod.mesh, "martini": mar.to_mesh(hm, cam),
                      "delatin": dela.to_mesh(hm, cam), "bintree": select_bintree(tree, cam, lod=False).mesh,
                      "polytree": poly.mesh(0, eye=cam.position)}
            for k, m in meshes.items():
                e = sample_error(hm, cam, m, grid.depth)
                worst[k] = [max(worst[k][0], e.p99_px), max(worst[k][1], e.max_px)]
            old = [max(old[0], lod.error.p99_px), max(old[1], lod.error.max_px)]
        rows.append([hm.name, f"{clearance:.0%}"] + [f"{worst[k][0]:.1e} / {worst[k][1]:.1e}" for k in FAMILIES]
                    + [f"{old[0]:.2f} / {old[1]:.2f}"])
    return rows


def big_rows() -> list[list[object]]:
    big = Heightmap.fbm(4097, seed=0, dx=10.0, max_height=1000.0)
    cam = _path(big, 0.02, 2)[0]
    grid = render(Scene(big, cam, outputs=("depth", "mesh")))
    terrain = Terrain.prepare(big, **LOD)
    lod = render(Scene(big, cam, outputs=("mesh",), mesh="lod", lod=LodConfig(tolerance_px=1.0, **LOD)),
                 terrain=terrain)
    rows = []
    for name, mesh in (("grid", grid.mesh), ("quadtree sse 1 px", lod.mesh)):
        t0 = time.perf_counter()
        e = sample_error(big, cam, mesh, grid.depth)
        rows.append([name, mesh.n_triangles, (time.perf_counter() - t0) * 1e3, e.p99_px, e.visible,
                     resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024])
    return rows


def main() -> None:
    rows = finest_rows(Heightmap.example()) + finest_rows(Heightmap.fbm(257, seed=1, dx=10.0, max_height=400.0))
    body = ("Finest setting of every family (quadtree sse 1e-6 px with every patch at the deepest level, Martini "
            "and Delatin at error 0, the bintree's level M drawn whole, the polytree at tolerance 0), "
            f"{W}x{H}, three flyover cameras per clearance; worst p99 / max px over the cameras. `old` is the "
            "per-pixel grid-image error (`frame_error`) of the finest quadtree frame: the triangulation floor the "
            "primary error does not have. The bintree on the DEM is not 0: its level-M vertex grid (side / 512) "
            "does not fall on the 344 x 403 samples.\n\n"
            + md_table(["heightmap", "clearance", *FAMILIES, "old (quadtree)"], rows))
    body += ("\n\nMeasuring a 4097^2 fBm (16.8M samples) at 1920x1080, 2% clearance, CPU: one scatter over the "
             "triangles, two launches over the samples (`ms` = the whole `sample_error` call; `peak_MB` = the "
             "process's peak RSS so far, including rendering the 33.5M-triangle grid).\n\n"
             + md_table(["mesh", "triangles", "ms", "p99_px", "visible", "peak_MB"], big_rows()))
    write_result("yardstick", "Yardstick (bench_yardstick.py)", body)


if __name__ == "__main__":
    main()
