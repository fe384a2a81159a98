"""GPU profiles (``terrainwarp.measure.gpu``: published rates, a bottleneck model) checked against published
terrain tables, and fits under each profile (issue 45). Three parts, each writing its own results file:

* ``whitepaper`` (results/gpu_whitepaper.md): NVIDIA's "DirectX 11 Terrain Tessellation" (Cantlay, 2011) table
  of fps and triangles per target triangle width, 1..10 px at 1920x1200, against our frame of the sample's rule
  (``_dx11_terrain.Dx11Source``: each patch edge's factor the projected sphere diameter over the target width,
  capped at 64, fractional_even) on a terrain of the kind it used (fBm, seven octaves): our triangles beside the
  table's, and each profile's modelled ms beside the table's, with the rank correlation and the error after one
  free overhead constant (least squares), on our frames and on our frames with the geometry counters scaled to
  the table's triangle counts.
* ``clipmap`` (results/gpu_clipmap.md): GPU Gems 2 ch. 2 (Asirvatham and Hoppe): 11 levels of 255^2 grids at
  1024x768 on a GeForce 6800 GT, 130 fps with frustum culling, 60 M triangles/s, against our clipmap frame
  (``terrainwarp.lod.clipmaps``, n = 255) priced by the nv40 profile (the 6800 GT's rates) and the others, with
  the stage each finds bound.
* ``fits`` (results/gpu_fits.md): the sse-tess and CDLOD multi-knob fits (as bench_fit_knobs.py's) minimising
  llvmpipe's model, each GPU profile and the worst of the GPU profiles, each fitted setting priced by every model.

No rate is fitted here: the profiles' rates are the shipped files' (docs/gpu_profiles.rst), and the only free
number is the whitepaper check's overhead constant.

    python benchmarks/bench_gpu_profiles.py [--parts whitepaper,clipmap,fits] [--scale 1]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from _common import md_table, write_result
from _dx11_terrain import Dx11Source

from terrainwarp import Camera, Heightmap, LodConfig, Scene, render
from terrainwarp.fit import fit_lod, knobs
from terrainwarp.fit.exact import references_for
from terrainwarp.lod.clipmaps import Clipmap
from terrainwarp.lod.quadtree import Terrain
from terrainwarp.measure.cost import shipped_model
from terrainwarp.measure.gpu import shipped_profiles
from terrainwarp.rendering.sources import ClipmapSource

#: NVIDIA, "DirectX 11 Terrain Tessellation" (Cantlay, January 2011), p. 19: target triangle width (px), fps,
#: triangles, at 1920x1200 (fliphtml5.com/lvgc/xhjd/DirectX_11_Terrain_Tessellation_-_NVIDIA_Developer/19/)
WHITEPAPER = ((1, 35, 14_546_300), (2, 68, 4_736_714), (3, 94, 2_465_020), (4, 114, 1_569_450),
              (5, 131, 1_106_962), (6, 143, 841_350), (7, 152, 683_860), (8, 162, 570_924), (9, 169, 484_998),
              (10, 175, 414_516))
#: GPU Gems 2 ch. 2 (Asirvatham and Hoppe, 2005): the geometry clipmap on a GeForce 6800 GT at 1024x768
GEMS = {"levels": 11, "n": 255, "width": 1024, "height": 768, "fps": 130.0, "tris_per_s": 60e6}
GEOMETRY = ("clipping_input_primitives", "clipping_output_primitives", "primitives_generated", "primitives_submitted",
            "vertices_submitted", "vertex_shader_invocations", "tess_control_shader_patches",
            "tess_evaluation_shader_invocations", "bytes_vertex", "bytes_index", "bytes_heightmap")


# ------------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------------
def spearman(a, b) -> float:
    """Spearman's rank correlation (average ranks for ties)."""
    def ranks(x):
        x = np.asarray(x, np.float64)
        order = np.argsort(x, kind="stable")
        r = np.empty(len(x))
        r[order] = np.arange(len(x), dtype=np.float64)
        for v in np.unique(x):
            r[x == v] = r[x == v].mean()
        return r
    ra, rb = ranks(a), ranks(b)
    return float(np.corrcoef(ra, rb)[0, 1])


def overhead_fit(measured_ms, modelled_ms) -> dict:
    """One free constant c (least squares of measured - modelled): c, the RMS error after it (ms), the mean and
    worst relative error, and the free-slope fit's slope (how much faster the table's time grows than the
    model's)."""
    m, y = np.asarray(modelled_ms, np.float64), np.asarray(measured_ms, np.float64)
    c = float(np.mean(y - m))
    err = y - (m + c)
    slope = float(np.polyfit(m, y, 1)[0]) if np.ptp(m) > 0 else math.nan
    return {"c": c, "rms": float(np.sqrt(np.mean(err ** 2))), "mean_rel": float(np.mean(np.abs(err) / y)),
            "max_rel": float(np.max(np.abs(err) / y)), "slope": slope}


def gpu_profiles(tessellation: bool = True) -> dict:
    return {n: p for n, p in shipped_profiles().items() if p.tessellation or not tessellation}


# ------------------------------------------------------------------------------------------------
# the whitepaper
# ------------------------------------------------------------------------------------------------
def whitepaper_frames(scale: int) -> tuple[list[dict], dict]:
    """Our frame of the sample's rule for each target width (counters), and the setup."""
    w, h = 1920 // scale, 1200 // scale
    hm = Heightmap.fbm(4097, seed=11, dx=4.0, max_height=800.0, octaves=7, feature_size=1024.0)
    terrain = Terrain.prepare(hm, roots=16, tess=4)
    cam = Scene(hm, camera=Camera.default_for(hm, w, h, fov_y_deg=60.0)).camera_path(5, preset="ground")[1]
    k = 2.0 * cam.focal_px / 64.0  # rings as the sample's: a patch never needs more than 64 at 1 px
    lod = LodConfig(roots=16, tess=4, spacing="fractional_even").with_policy("distance", k)
    out = []
    for width, _, _ in WHITEPAPER:
        t0 = time.perf_counter()
        src = Dx11Source(terrain=terrain, lod=lod, tri_width=float(width) / scale)
        c = dict(render(Scene(hm, camera=cam, outputs=("counters",)), source=src).report.counters)
        c["patches_drawn"] = src.last_patches
        out.append(c)
        print(f"whitepaper {width} px: {c['primitives_generated']} triangles, {src.last_patches} patches "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    setup = {"heightmap": hm, "camera": cam, "k": k, "width": w, "height": h}
    return out, setup


def _scaled(c: dict, ratio: float) -> dict:
    return {**c, **{g: c[g] * ratio for g in GEOMETRY if g in c}}


def whitepaper(args) -> None:
    frames, setup = whitepaper_frames(args.scale)
    profiles = gpu_profiles()
    table_ms = [1000.0 / fps for _, fps, _ in WHITEPAPER]
    rows = []
    for (width, fps, tris), c, ms in zip(WHITEPAPER, frames, table_ms):
        ours = c["primitives_generated"]
        rows.append([width, f"{tris:,}", f"{ours:,}", f"{ours / tris:.2f}", f"{c['quad_efficiency']:.3f}", fps,
                     f"{ms:.2f}", *(f"{p(c):.3g} ({p.bound(c)})" for p in profiles.values())])
    fit_rows = []
    for name, p in profiles.items():
        for label, cs in (("our frames", frames),
                          ("geometry at the table's triangles", [_scaled(c, t / c["primitives_generated"])
                                                                 for (_, _, t), c in zip(WHITEPAPER, frames)])):
            mod = [p(c) for c in cs]
            f = overhead_fit(table_ms, mod)
            fit_rows.append([name, label, f"{spearman(mod, table_ms):.3f}", f"{mod[0]:.3g} .. {mod[-1]:.3g}",
                             f"{f['c']:.2f}", f"{f['rms']:.2f}", f"{100 * f['mean_rel']:.0f}%",
                             f"{100 * f['max_rel']:.0f}%", f"{f['slope']:.2f}"])
    s = setup
    pos = tuple(round(v) for v in s["camera"].position)
    body = (f"Our frame: {s['width']}x{s['height']}, a {s['heightmap'].shape[0]}^2 fBm (seven octaves, 4 m "
            f"spacing, 800 m relief) seen from the scene's ground-level flyover (camera {pos} looking along the "
            f"path, 60 deg field of view); patches from a distance-split quadtree (rings of "
            f"patches that grow with distance, as the sample's tile rings; split while the distance is under "
            f"k = 2 f / 64 = {s['k']:.1f} patch sizes, f the focal length in pixels, so that no patch needs more "
            "than the cap of 64 at 1 px), each edge's factor the sample's rule (the projected diameter of the "
            "sphere around the edge over the target width, capped at 64: `terrainwarp.lod.policies.dx11_edge_pixels`"
            "), fractional_even. One view, as the table's 'default view'.\n\n"
            "The table (NVIDIA, 'DirectX 11 Terrain Tessellation', Cantlay 2011, p. 19) beside ours; modelled ms "
            "per frame of each GPU profile (bound stage in brackets), from our frame's counters:\n\n"
            + md_table(["target px", "table triangles", "our triangles", "ours / table", "our quad efficiency",
                        "table fps", "table ms", *(f"{n} ms" for n in profiles)], rows)
            + "\n\nEach profile against the table's frame times: Spearman rank correlation, the modelled range, the "
            "one free overhead constant c (least squares: table ms = modelled ms + c), the error after it (RMS, mean "
            "and worst relative), and the slope a free line would need (table ms per modelled ms: 1 if the rates "
            "were right). 'Geometry at the table's triangles': our frames' geometry counters scaled to the table's "
            "triangle count at each width (fragments as ours), which takes our scene's difference out of the "
            "check:\n\n"
            + md_table(["profile", "frames", "rank corr.", "modelled ms (1 .. 10 px)", "overhead c ms", "RMS ms",
                        "mean err", "worst err", "slope"], fit_rows))
    write_result("gpu_whitepaper", "GPU profiles against the DX11 terrain tessellation whitepaper "
                                   "(bench_gpu_profiles.py)", body + _note("gpu_whitepaper"))


# ------------------------------------------------------------------------------------------------
# GPU Gems 2 clipmaps
# ------------------------------------------------------------------------------------------------
def clipmap(args) -> None:
    """Our 255-vertex clipmap at 1024x768 on the largest terrain that holds whole levels, the missing coarse
    levels' geometry extrapolated from the measured ones; priced by every profile."""
    n_side = args.clipmap_size
    hm = Heightmap.fbm(n_side, seed=3, dx=30.0, max_height=2500.0, octaves=8, feature_size=2048.0)
    full = int(math.floor(math.log2((n_side - 1) / (GEMS["n"] - 1)))) + 1  # levels whose ring fits the terrain
    (x0, z0), (x1, z1) = hm.bounds_xz
    cx, cz = 0.5 * (x0 + x1), 0.5 * (z0 + z1)
    ground = float(hm.sample(cx, cz))
    fov_y = 2 * math.degrees(math.atan(math.tan(math.radians(45)) * GEMS["height"] / GEMS["width"]))  # 90 deg across
    cams = [Camera(position=(cx, ground + 150.0, cz),
                   target=(cx + 1000 * math.cos(a), ground + 50.0, cz + 1000 * math.sin(a)), fov_y_deg=fov_y,
                   width=GEMS["width"], height=GEMS["height"], near=1.0, far=1e7) for a in (0.3, 1.9, 3.5, 5.1)]
    per_levels = {}
    for levels in (full - 1, full):
        src = ClipmapSource(scheme=Clipmap(hm, GEMS["n"], levels=levels), cache={})
        per_levels[levels] = [dict(render(Scene(hm, camera=c, outputs=("counters",)), source=src).report.counters)
                              for c in cams]
    ext = []
    for c_full, c_less in zip(per_levels[full], per_levels[full - 1]):
        per_level = {g: c_full[g] - c_less[g] for g in (*GEOMETRY, "draw_calls")}  # the coarsest whole level's
        ext.append({**c_full, **{g: c_full[g] + (GEMS["levels"] - full) * per_level[g] for g in per_level}})
    measured_ms = 1000.0 / GEMS["fps"]
    tris = float(np.mean([c["clipping_input_primitives"] for c in ext]))
    rows = [["GPU Gems 2 (6800 GT)", f"{GEMS['tris_per_s'] / GEMS['fps']:,.0f}", "-", f"{measured_ms:.2f}", "-"]]
    for name, p in gpu_profiles(tessellation=False).items():
        ms = float(np.mean([p(c) for c in ext]))
        bound = max(set(p.bound(c) for c in ext), key=[p.bound(c) for c in ext].count)
        rows.append([f"{name} profile", f"{tris:,.0f}", f"{np.mean([c['draw_calls'] for c in ext]):.0f}",
                     f"{ms:.3g}", f"{bound} ({', '.join(f'{s} {v:.2g}' for s, v in p.stage_ms(ext[0]).items())})"])
    c0 = ext[0]
    body = (f"Ours: geometry clipmaps (n = {GEMS['n']}, GPU Gems 2's block culling) on a {n_side}^2 fBm (30 m "
            f"spacing, as the chapter's US data), {GEMS['width']}x{GEMS['height']}, 90-degree horizontal field of "
            f"view (the chapter's culling figure), the viewer 150 m above the ground at the terrain's centre, four "
            f"headings. Levels 0..{full - 1} are whole in the terrain and measured; the chapter's other "
            f"{GEMS['levels'] - full} coarser levels lie past our terrain, so their geometry (triangles, vertices, "
            "draws, bytes) is extrapolated as copies of the coarsest whole level (each level draws the same ring in "
            "its own grid units) and their fragments are not counted (a thin band at the horizon). Mean over the "
            f"headings: {tris:,.0f} triangles, {np.mean([c['vertex_shader_invocations'] for c in ext]):,.0f} "
            f"vertex shader invocations, quad efficiency {c0['quad_efficiency']:.3f} (first heading).\n\n"
            + md_table(["who", "triangles / frame", "draw calls", "ms / frame",
                        "bound stage (stage ms, first heading)"], rows))
    write_result("gpu_clipmap", "GPU profiles against GPU Gems 2's geometry clipmaps (bench_gpu_profiles.py)",
                 body + _note("gpu_clipmap"))


# ------------------------------------------------------------------------------------------------
# fits under each profile
# ------------------------------------------------------------------------------------------------
FIT_PROBLEMS = {"sse-tess": ("sse", ["tess"]), "cdlod": ("cdlod", ["ratio", "morph_start_ratio", "grid"])}


def fits(args) -> None:
    hm = Heightmap.example()
    scene = Scene(hm, camera=Camera.default_for(hm, args.fit_width, args.fit_height))
    cams = scene.camera_path(args.fit_frames)
    refs = references_for(scene, cams)
    models = {"llvmpipe": shipped_model(), **gpu_profiles()}
    costs = ["llvmpipe", "gpu:gf100", "gpu:rdna", "gpu:mali", ["gpu:gf100", "gpu:gcn", "gpu:rdna", "gpu:mali"]]
    rows = []
    for prob, (policy, names) in FIT_PROBLEMS.items():
        all_names = [k.name for k in knobs(policy, hm, None if policy == "cdlod" else scene.lod)]
        for budget in args.budgets:
            for c in costs:
                t0 = time.perf_counter()
                r = fit_lod(scene, budget, policy, cams, knobs=names, references=refs, cost=c)
                counted = [render(r.scene.with_(camera=cam, outputs=("counters",))).report.counters for cam in cams]
                priced = {n: float(np.mean([m(x) for x in counted])) for n, m in models.items()}
                label = c if isinstance(c, str) else "worst of " + ",".join(x.removeprefix("gpu:") for x in c)
                vals = ", ".join(f"{k} {r.values[k]:.4g}" for k in all_names if k in r.values)
                rows.append([prob, f"{budget:g}", label, "yes" if r.met else "no", vals,
                             f"{np.mean(r.validated.triangles):,.0f}", *(f"{v:.3g}" for v in priced.values()),
                             r.evaluations])
                print(f"fit {prob} {budget:g} px {label}: {vals} ({time.perf_counter() - t0:.0f} s)", flush=True)
    body = (f"The bundled SRTM DEM, {args.fit_width}x{args.fit_height}, {args.fit_frames} cameras (the scene's "
            "default ground-level path), fit_lod with the knobs of bench_fit_knobs.py's sse-tess (the sse tolerance "
            "and tess) and cdlod (first range, distance ratio, morph start ratio, grid) problems, minimising each "
            "cost (a list: each frame's worst modelled ms over the profiles); each fitted setting's frames are then "
            "priced by every model (mean modelled ms per frame). The fitted values and costs side by side:\n\n"
            + md_table(["problem", "budget px", "cost minimised", "met", "fitted values", "triangles",
                        *(f"{n} ms" for n in models), "exact frames"], rows))
    write_result("gpu_fits", "Fits under each GPU profile (bench_gpu_profiles.py)", body + _note("gpu_fits"))


def _note(stage: str) -> str:
    """The hand-written notes (from '### Notes' to the end) of the previous result, kept when rerun."""
    from _common import RESULTS

    p = RESULTS / f"{stage}.md"
    text = p.read_text() if p.exists() else ""
    at = text.find("### Notes")
    return "\n\n" + text[at:].strip() if at >= 0 else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="whitepaper,clipmap,fits")
    ap.add_argument("--scale", type=int, default=1, help="divide the whitepaper's 1920x1200 (and widths) by this")
    ap.add_argument("--clipmap-size", type=int, default=8193, help="the clipmap terrain's side in samples")
    ap.add_argument("--fit-width", type=int, default=960)
    ap.add_argument("--fit-height", type=int, default=540)
    ap.add_argument("--fit-frames", type=int, default=8)
    ap.add_argument("--budgets", type=lambda s: [float(x) for x in s.split(",")], default=[2.0])
    args = ap.parse_args()
    for part in args.parts.split(","):
        {"whitepaper": whitepaper, "clipmap": clipmap, "fits": fits}[part](args)


if __name__ == "__main__":
    main()
