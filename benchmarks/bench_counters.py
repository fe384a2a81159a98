"""What a frame would cost a GPU: the pipeline statistics of one frame of every family, terrainwarp's against
Mesa llvmpipe's ARB_pipeline_statistics_query in the three spacings, and what counting costs.

* Counters per family: the bundled DEM at 1920x1080 from ``Camera.default_for`` (the whole terrain in view), each
  family at one setting, ``render(..., outputs=("depth", "counters"))``; the modelled cost is the shipped llvmpipe
  model (``terrainwarp.measure.cost.shipped_model``).
* Against llvmpipe: LOD frames of each spacing at 1920x1080 from the scene's flyover (``camera_path(4)[2]``,
  clipped at the near plane and the viewport) and from the default camera (``equal``, ``fractional_even``: the
  sse policy; ``fractional_odd``: the continuous policy), drawn by llvmpipe with real tessellation shaders
  (``terrainwarp.experiments.gl.GLTerrain``) and as plain indexed triangles of the same clip-space vertices
  (``GLMesh``): ours, the tessellated draw's and the indexed draw's counters, the relative differences.
* Counting overhead: the frames of bench_terrain_frame (the DEM at 1 and 0.25 px, an fBm 1025^2 at ~340k
  triangles, its flyover at ~340k), select + mesh + raster (``Report.frame_ms``) of renders of depth only and of
  depth + counters, alternating, fastest of ``--reps`` each after a warm-up; and the counters checked equal for 1,
  2, 3 and 8 kernel threads.

    .venv/bin/python benchmarks/bench_counters.py            # ~2 min on 2 cores
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import md_table, write_result

from terrainwarp import Camera, Heightmap, Scene, render
from terrainwarp.experiments.gl import FrameDriver
from terrainwarp.kernels.counters import PIPELINE_COUNTERS
from terrainwarp.kernels.parallel import set_threads, threads
from terrainwarp.lod import Terrain
from terrainwarp.lod.bintree import Bintree
from terrainwarp.lod.peers import delatin_mesh, martini_mesh
from terrainwarp.lod.polytree import build_polytree, default_tolerances
from terrainwarp.measure.cost import shipped_model
from terrainwarp.rendering.sources import BintreeSource, PeerSource, PolytreeSource
from terrainwarp.scene import LodConfig
from terrainwarp.schemes import scheme_range, scheme_source

W, H = 1920, 1080
MODEL = shipped_model()


def family_frames(hm: Heightmap, cam: Camera) -> list[tuple[str, str, object]]:
    """(family, setting, frame) of every family at one setting each."""
    terrain = Terrain.prepare(hm)
    cache: dict = {}
    relief = float(np.ptp(hm.heights))
    out = []
    for pol, v in (("sse", 1.0), ("distance", 2.0), ("continuous", 8.0)):
        lod = LodConfig().with_policy(pol, v)
        out.append((pol, f"{v:g}", render(Scene(hm, camera=cam, mesh="lod", lod=lod, outputs=("depth", "counters")),
                                          terrain=terrain)))
    out.append(("grid", "-", render(Scene(hm, camera=cam, outputs=("depth", "counters")))))
    first = 2.0 * scheme_range("cdlod", hm, cache=cache)[0]
    tree = build_polytree(hm, default_tolerances(hm, 64))
    m_full = 2 * int(np.ceil(np.log2(max(hm.shape) - 1))) + 1
    for name, setting, src in (
            ("cdlod", f"first_range {first:.0f} m", scheme_source("cdlod", hm, first, cache=cache)),
            ("clipmaps", "n 127", scheme_source("clipmaps", hm, 127, cache=cache)),
            ("chunked", "2 px", scheme_source("chunked", hm, 2.0, cache=cache)),
            ("martini", f"{0.002 * relief:.2f} m", PeerSource(martini_mesh(hm, 0.002 * relief), hm, cache=cache)),
            ("delatin", f"{0.002 * relief:.2f} m", PeerSource(delatin_mesh(hm, 0.002 * relief), hm, cache=cache)),
            ("polytree", "level 4", PolytreeSource(tree, 4, cache=cache)),
            ("bintree", f"M {m_full}", BintreeSource(Bintree.build(hm, m_full), cache=cache))):
        out.append((name, setting, render(Scene(hm, camera=cam, outputs=("depth", "counters")), source=src)))
    return out


def per_family_table(frames) -> str:
    rows = []
    for c in (*PIPELINE_COUNTERS, "modelled llvmpipe ms", "triangles"):
        vals = []
        for _, _, f in frames:
            v = (MODEL(f.report.counters) if c == "modelled llvmpipe ms" else f.mesh.n_triangles if c == "triangles"
                 else f.report.counters[c])
            vals.append(f"{v:.3g}" if isinstance(v, float) else f"{v:,}")
        rows.append([c, *vals])
    return md_table(["counter", *(f"{n} ({s})" for n, s, _ in frames)], rows)


GL_ROWS = ("vertices_submitted", "primitives_submitted", "vertex_shader_invocations", "tess_control_shader_patches",
           "tess_evaluation_shader_invocations", "primitives_generated", "clipping_input_primitives",
           "clipping_output_primitives", "fragment_shader_invocations_llvmpipe", "samples_passed")


def llvmpipe_table(hm: Heightmap) -> tuple[str, list[str]]:
    """Ours against llvmpipe per spacing and camera; the largest relative difference per counter."""
    terrain = Terrain.prepare(hm)
    cams = {"flyover": Scene(hm, camera=Camera.default_for(hm, W, H)).camera_path(4)[2],
            "whole terrain": Camera.default_for(hm, W, H)}
    rows, worst = [], {}
    driver = FrameDriver()
    for spacing in ("equal", "fractional_even", "fractional_odd"):
        lod = LodConfig(policy="continuous", spacing="fractional_odd") if spacing == "fractional_odd" else \
            LodConfig(spacing=spacing)
        for cname, cam in cams.items():
            f = render(Scene(hm, camera=cam, mesh="lod", lod=lod, outputs=("depth", "counters", "mesh", "patches")),
                       terrain=terrain)
            tess, flat = driver.statistics(f), driver.statistics(f, indexed=True)
            for gl in (tess, flat):
                gl["fragment_shader_invocations_llvmpipe"] = gl["fragment_shader_invocations"]
            for c in GL_ROWS:
                ours = f.report.counters[c]
                d_t = (ours - tess[c]) / tess[c] if tess[c] else 0.0
                d_f = (ours - flat[c]) / flat[c] if flat[c] and c not in GL_ROWS[:5] else float("nan")
                worst[c] = max(worst.get(c, 0.0), abs(d_t), 0.0 if np.isnan(d_f) else abs(d_f))
                rows.append([spacing, cname, c, f"{ours:,}", f"{tess[c]:,}", f"{d_t:+.3%}",
                             "-" if np.isnan(d_f) else f"{flat[c]:,}", "-" if np.isnan(d_f) else f"{d_f:+.3%}"])
    driver.close()
    table = md_table(["spacing", "camera", "counter", "ours", "llvmpipe tessellated", "ours vs tess",
                      "llvmpipe indexed", "ours vs indexed"], rows)
    lines = [f"{c}: {'equal everywhere' if worst[c] == 0 else f'at most {worst[c]:.3%} apart'}" for c in GL_ROWS]
    return table, lines


def _frame(sc: Scene, terrain: Terrain) -> tuple[float, float]:
    """(select + mesh + raster wall ms, CPU ms of the whole render: every thread of this process)."""
    c0 = time.process_time()
    ms = render(sc, terrain=terrain).report.frame_ms
    return ms, (time.process_time() - c0) * 1e3


def overhead_rows(reps: int) -> list[list]:
    """select + mesh + raster of depth-only and depth + counters renders of bench_terrain_frame's frames."""
    frames = []
    dem = Heightmap.example()
    cam = Camera.default_for(dem, W, H)
    t_dem = Terrain.prepare(dem)
    frames += [(f"DEM {dem.shape[1]}x{dem.shape[0]} {tol:g} px", dem, cam, t_dem, tol) for tol in (1.0, 0.25)]
    fbm = Heightmap.fbm(1025, seed=7, dx=10.0, max_height=800.0)
    t_fbm = Terrain.prepare(fbm)
    fly = Scene(fbm, camera=Camera.default_for(fbm, W, H)).camera_path(8, preset="high")[3]
    frames += [("fBm 1025x1025 ~340k", fbm, Camera.default_for(fbm, W, H), t_fbm, 0.4071),
               ("fBm 1025x1025 flyover ~340k", fbm, fly, t_fbm, 0.6313)]
    rows = []
    for label, hm, c, terrain, tol in frames:
        sc = Scene(hm, camera=c, mesh="lod", lod=LodConfig(tolerance_px=tol), outputs=("depth",))
        counted = sc.with_(outputs=("depth", "counters"))
        for s in (sc, counted):
            _frame(s, terrain)
        plain, count = [], []
        for _ in range(reps):
            plain.append(_frame(sc, terrain))
            count.append(_frame(counted, terrain))
        f = render(counted, terrain=terrain)
        same = [f.report.counters]
        for n in (1, 2, 3, 8):
            set_threads(n)
            same.append(render(counted, terrain=terrain).report.counters)
        set_threads(None)
        if any(s != same[0] for s in same):
            raise RuntimeError(f"{label}: counters differ between thread counts")
        a, b = min(p[0] for p in plain), min(c[0] for c in count)
        ca, cb = min(p[1] for p in plain), min(c[1] for c in count)
        rows.append([label, f.mesh.n_triangles, f"{f.report.counters['samples_passed']:,}", round(ca, 2), round(cb, 2),
                     f"{cb / ca - 1:+.1%}", round(a, 2), round(b, 2), f"{b / a - 1:+.1%}", "equal"])
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=9, help="timed renders of each kind per frame (the least counts)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    hm = Heightmap.example()
    cam = Camera.default_for(hm, W, H)
    fams = family_frames(hm, cam)
    gl_table, gl_lines = llvmpipe_table(hm)
    over = overhead_rows(max(1, args.reps))
    body = "\n\n".join([
        f"### Counters of one frame per family (DEM {hm.shape[1]}x{hm.shape[0]}, {W}x{H}, the whole terrain in view)",
        "Draws as each family issues them: the quadtree policies one patch draw through the tessellator, CDLOD one "
        "draw per node (a partly selected node one per quadrant, as its reference), clipmaps one per ring block "
        "with a quad drawn and one per level's stitches, chunked one per chunk, the grid, Martini, Delatin, the "
        "polytree and the bintree one indexed draw. `vertex_shader_invocations`: distinct vertices per draw; "
        "`_llvmpipe`: Mesa's vertex splitter (equal to its query). `fragment_shader_invocations`: 4 per 2x2 quad "
        "a triangle touches (helper lanes); `_llvmpipe`: 16 per 4x4 block. Modelled ms: " + MODEL.describe() + ".",
        per_family_table(fams),
        f"### Ours against llvmpipe's query ({W}x{H}, Mesa llvmpipe through EGL)",
        "Tessellated: the same PatchList through real tessellation shaders (llvmpipe evaluates each vertex with its "
        "own float rounding and emits a patch's triangles in its own order); indexed: our mesh as plain indexed "
        "triangles of our clip-space vertices (input-assembler counters, which count indices there, not shown). "
        "Largest difference over the six frames: " + "; ".join(gl_lines) + ".",
        gl_table,
        f"### What counting costs ({threads()} kernel threads)",
        "`render` with `outputs=(\"depth\",)` and with `(\"depth\", \"counters\")`, alternating, the least of "
        f"{args.reps} each: CPU ms of the whole call (`time.process_time`, every thread of this process: the work "
        "done, which other load on this shared machine disturbs far less than wall time) and wall ms of select + "
        "mesh + raster (`Report.frame_ms`; noisy here, +-20% between rounds of the same frame); counters checked "
        "equal for 1, 2, 3 and 8 threads.",
        md_table(["frame", "triangles", "samples passed", "CPU ms", "CPU ms counting", "overhead (CPU)",
                  "frame ms", "frame ms counting", "overhead (wall)", "counters, 1/2/3/8 threads"], over),
        f"Whole benchmark: {time.perf_counter() - t0:.0f} s."])
    write_result("counters", "Pipeline statistics per frame (bench_counters.py)", body)


if __name__ == "__main__":
    main()
