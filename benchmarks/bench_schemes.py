"""Which LOD scheme, at which setting, meets a screen-error budget at the lowest cost and without popping
(issue 18): CDLOD, geometry clipmaps and Chunked LOD with skirts beside the quadtree policies (sse, distance,
continuous), on the same frames.

For each heightmap (the bundled DEM and an fBm) and path (flyover at 2% and 10% clearance), every family is
evaluated on a ladder of settings (coarse to fine); for each budget (1, 2, 16 px) the coarsest ladder setting
whose worst-frame p99 primary error (``measure.sample_error``) meets the budget is refined by bisection toward
the coarser neighbour that fails. Each row: the primary error p99 / max (worst frame), the modelled GPU cost
(the shipped llvmpipe cost model of the frame's pipeline statistics, ``terrainwarp.measure.cost``: ms that
llvmpipe on one thread would take to draw the frame as the family draws it, mean over frames), draw calls,
triangles, this simulator's select + mesh + raster CPU ms (``Report.frame_ms`` of a render without counting,
mean over frames; select ms apart), and popping between consecutive frames of a dense path (each measured
camera and the one before it on a path of ``DENSE`` frames, 0.2% of the path apart: the selection of that frame
drawn for the measured camera against the measured camera's own, ``measure.popping``; worst p99 / max).
Winners among the families that meet the budget: lowest modelled cost (the ranking), fewest triangles, least
CPU time, least popping. Then the same families re-ranked under each GPU profile (``terrainwarp.measure.gpu``:
published rates, a bottleneck model) beside llvmpipe, each winner with its bound stage and whether it stays the
winner with every rate x1/3..x3 (``terrainwarp.measure.ranking.verdict``), from the same frames' counters.

Usage: ``python benchmarks/bench_schemes.py [--fbm 1025] [--width 640 --height 360] [--frames 5]``
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from _common import RESULTS, md_table, write_result

from terrainwarp import Heightmap, LodConfig, Scene, render
from terrainwarp.camera import Camera, flyover
from terrainwarp.experiments.winners import report_models
from terrainwarp.kernels.lod import select_level
from terrainwarp.lod import Terrain
from terrainwarp.lod.cdlod import Cdlod
from terrainwarp.lod.chunked import ChunkedLod
from terrainwarp.lod.clipmaps import Clipmap
from terrainwarp.measure.cost import shipped_model
from terrainwarp.measure.ranking import verdict
from terrainwarp.measure.sample_error import popping, sample_error
from terrainwarp.rendering.pipeline import Frame, pop_stats
from terrainwarp.rendering.sources import CdlodSource, ChunkedSource, ClipmapSource

BUDGETS = (1.0, 2.0, 16.0)
NOTE_HEAD = "### Closing note"  # written by hand below the tables from their numbers; kept when rerun
DENSE = 500  # frames of the dense path popping is measured on (consecutive frames 0.2% of the path apart)
LOD = {"roots": 16, "tess": 16}  # the quadtree policies' layout (as bench_yardstick)
CDLOD_GRID = 16
CHUNK_TILE = 32


@dataclass
class Ctx:
    """One heightmap and path: its cameras, their grid frames (visibility), the policies' Terrain."""

    hm: Heightmap
    cams: list[Camera]
    before: list[Camera]  # the frame before each camera on the dense path
    refs: list[Frame]
    terrain: Terrain
    cache: dict
    clearance: float


@dataclass
class Family:
    """A family's ladder of settings (coarse to fine) and how to evaluate one setting."""

    name: str
    ladder: list[float]
    geometric: bool  # bisect geometrically (ratios) or by odd integers (clipmap n)
    run: Callable[[Ctx, float], dict]


def _path(hm: Heightmap, clearance: float, n: int, width: int, height: int) -> tuple[list[Camera], list[Camera]]:
    """``n`` measured cameras evenly along the path (as bench_yardstick's), and the frame before each on a
    path of ``DENSE`` frames."""
    (x0, z0), (x1, z1) = hm.bounds_xz
    ext = max(x1 - x0, z1 - z0)
    wps = [(x0 + 0.15 * (x1 - x0), z0 + 0.2 * (z1 - z0)), (x0 + 0.85 * (x1 - x0), z0 + 0.75 * (z1 - z0))]
    dense = flyover(hm, wps, clearance * ext, DENSE, width=width, height=height)
    at = np.linspace(1, DENSE - 1, n).round().astype(int)
    return [dense[i] for i in at], [dense[i - 1] for i in at]


MODEL = shipped_model()


def _summary(ctx: Ctx, meshes: list, frames: list[Frame], pops: list, counted: list[Frame]) -> dict:
    errs = [sample_error(ctx.hm, c, m, r.depth) for c, m, r in zip(ctx.cams, meshes, ctx.refs)]
    return {"p99": max(e.p99_px for e in errs), "max": max(e.max_px for e in errs),
            "cost": float(np.mean([MODEL(f.report.counters) for f in counted])),
            "draws": float(np.mean([f.report.counters["draw_calls"] for f in counted])),
            "tris": float(np.mean([m.n_triangles for m in meshes])),
            "ms": float(np.mean([f.report.frame_ms for f in frames])),
            "sel_ms": float(np.mean([f.report.stage_ms("select") for f in frames])),
            "pop99": max(p.p99_px for p in pops), "popmax": max(p.max_px for p in pops),
            "counters": [dict(f.report.counters) for f in counted]}


def _run_policy(policy: str) -> Callable[[Ctx, float], dict]:
    def run(ctx: Ctx, value: float) -> dict:
        lod = LodConfig(**LOD).with_policy(policy, value)
        frames, pops, counted = [], [], []
        for k, cam in enumerate(ctx.cams):
            scene = Scene(ctx.hm, camera=cam, outputs=("depth", "mesh"), mesh="lod", lod=lod)
            f = render(scene, ctx.terrain)
            frames.append(f)
            counted.append(render(scene.with_(outputs=("counters",)), ctx.terrain))  # counted apart from the timing
            pops.append(pop_stats(scene, ctx.before[k], f, ctx.refs[k], terrain=ctx.terrain))
        return _summary(ctx, [f.mesh for f in frames], frames, pops, counted)
    return run


def _run_source(make: Callable[[Heightmap, float, dict], object]) -> Callable[[Ctx, float], dict]:
    def run(ctx: Ctx, value: float) -> dict:
        src = make(ctx.hm, value, ctx.cache)
        frames, pops, counted = [], [], []
        for k, cam in enumerate(ctx.cams):
            f = render(Scene(ctx.hm, camera=cam, outputs=("depth", "mesh")), source=src)
            frames.append(f)
            counted.append(render(Scene(ctx.hm, camera=cam, outputs=("counters",)), source=src))
            held = src.held_mesh_for(ctx.before[k], cam)
            pops.append(popping(ctx.hm, cam, held, f.mesh, ctx.refs[k].depth))
        return _summary(ctx, [f.mesh for f in frames], frames, pops, counted)
    return run


def _cdlod(hm: Heightmap, mult: float, cache: dict) -> CdlodSource:
    """CDLOD at ``mult`` times its seam-free minimum first range (one scheme object, its pyramids, shared)."""
    key = ("cdlod", hm.name)
    if key not in cache:
        cache[key] = Cdlod(hm, 1.0, grid=CDLOD_GRID)
    scheme = cache[key]
    scheme.first_range = mult * scheme.min_first_range
    return CdlodSource(scheme=scheme, cache=cache)


def _chunked(hm: Heightmap, sse: float, cache: dict) -> ChunkedSource:
    key = ("chunked", hm.name)
    if key not in cache:
        cache[key] = ChunkedLod(hm, 2.0, tile=CHUNK_TILE)
    scheme = cache[key]
    scheme.max_sse_px = sse
    return ChunkedSource(scheme=scheme, cache=cache)


def families() -> list[Family]:
    return [
        Family("sse (tolerance_px)", [64, 16, 4, 2, 1, 0.5, 0.25, 0.1], True, _run_policy("sse")),
        Family("distance (k)", [0.25, 1, 2, 4, 8, 16, 32], True, _run_policy("distance")),
        Family("continuous (target_px)", [64, 16, 8, 4, 2, 1, 0.5], True, _run_policy("continuous")),
        Family("cdlod (first_range / min)", [1, 2, 4, 8, 16, 32, 64], True, _run_source(_cdlod)),
        Family("clipmaps (n)", [15, 31, 63, 127, 255, 511, 1023, 2047], False,
               _run_source(lambda hm, n, cache: ClipmapSource(scheme=Clipmap(hm, int(n)), cache=cache))),
        Family("chunked (max_sse_px)", [64, 16, 4, 2, 1, 0.5, 0.25, 0.1], True, _run_source(_chunked)),
    ]


# ------------------------------------------------------------------------------------------------
# the search
# ------------------------------------------------------------------------------------------------
def _mid(a: float, b: float, geometric: bool) -> float | None:
    if geometric:
        return math.sqrt(a * b)
    m = int(round(0.5 * (a + b))) | 1
    return None if m in (int(a), int(b)) else float(m)


def cheapest(fam: Family, ctx: Ctx, budget: float, seen: dict, steps: int = 2) -> tuple[float, dict] | None:
    """The coarsest evaluated setting whose worst-frame p99 meets ``budget`` (ladder, then bisection)."""
    def ev(v: float) -> dict:
        if v not in seen:
            seen[v] = fam.run(ctx, v)
        return seen[v]

    prev = None
    for v in fam.ladder:
        if ev(v)["p99"] <= budget:
            lo, hi = prev, v  # lo fails (coarser), hi meets
            for _ in range(steps if lo is not None else 0):
                m = _mid(lo, hi, fam.geometric)
                if m is None:
                    break
                if ev(m)["p99"] <= budget:
                    hi = m
                else:
                    lo = m
            return hi, ev(hi)
        prev = v
    return None


def _clearance(ctx: Ctx) -> str:
    return f"{ctx.clearance:.0%}"


def _fmt_setting(fam: Family, v: float) -> str:
    s = str(int(v)) if not fam.geometric else f"{v:.3g}"
    return s + " (coarsest tried)" if v == fam.ladder[0] else s


def profile_rows(ctx: Ctx, budget: float, found: list) -> list[list[object]]:
    """One row per cost model (llvmpipe, the shipped GPU profiles): the winner among the families meeting the
    budget, its modelled ms and bound stage, robust (rates x1/3..x3) and what would flip it."""
    cands = {fam.name.split()[0]: r[1]["counters"] for fam, r in found if r is not None}
    if not cands:
        return []
    return [[ctx.hm.name, _clearance(ctx), f"{budget:g}", m.name, *verdict(cands, m).row()] for m in report_models()]


def budget_rows(fams: list[Family], ctx: Ctx, seen: dict[str, dict],
                summary: list[list[object]], by_model: list[list[object]]) -> list[list[object]]:
    """One row per (budget, family) at the family's cheapest setting, winners starred; appends one row per
    budget to ``summary`` (the winners, with their numbers) and one per budget and cost model to ``by_model``."""
    rows = []
    for budget in BUDGETS:
        found = []
        for fam in fams:
            r = cheapest(fam, ctx, budget, seen.setdefault(fam.name, {}))
            found.append((fam, r))
        by_model += profile_rows(ctx, budget, found)
        ok = [r for _, r in found if r is not None]
        best = {k: min((r[1][k] for r in ok), default=None) for k in ("cost", "tris", "ms")}
        best["pop99"] = min(((r[1]["pop99"], r[1]["popmax"]) for r in ok), default=None)  # ties: the max
        summary.append([ctx.hm.name, _clearance(ctx), f"{budget:g}"] + [
            ", ".join(f"{fam.name.split()[0]} ({r[1][k]:.{d}f})" for fam, r in found if r is not None and
                      ((r[1]["pop99"], r[1]["popmax"]) if k == "pop99" else r[1][k]) == best[k])
            for k, d in (("cost", 2), ("tris", 0), ("ms", 1), ("pop99", 2))])
        for fam, r in found:
            if r is None:
                finest = seen[fam.name][fam.ladder[-1]]
                rows.append([f"{budget:g}", fam.name, "not met", f"{finest['p99']:.2f} (finest)", "", "", "", "", "",
                             ""])
                continue
            v, s = r
            mark = {k: " ★" if s[k] == best[k] else "" for k in ("cost", "tris", "ms")}
            mark["pop99"] = " ★" if (s["pop99"], s["popmax"]) == best["pop99"] else ""
            rows.append([f"{budget:g}", fam.name, _fmt_setting(fam, v), f"{s['p99']:.2f} / {s['max']:.2f}",
                         f"{s['cost']:.2f}{mark['cost']}", f"{s['draws']:.0f}", f"{s['tris']:.0f}{mark['tris']}",
                         f"{s['ms']:.1f}{mark['ms']}", f"{s['sel_ms']:.2f}",
                         f"{s['pop99']:.2f} / {s['popmax']:.2f}{mark['pop99']}"])
    return rows


# ------------------------------------------------------------------------------------------------
# CDLOD selection time against the paper
# ------------------------------------------------------------------------------------------------
def cdlod_select_rows(ctx: Ctx, mults: tuple[float, ...] = (1, 4, 16)) -> list[list[object]]:
    base = Cdlod(ctx.hm, 1.0, grid=CDLOD_GRID)
    # what one select-level launch costs with a single node: the per-level floor of Warp's host-side launch
    t = base.terrain
    one = np.zeros(1, np.int64)
    args = (one, one, one, t.stats_at(0, one, one), (0.0, 0.0, 0.0),
            (1.0, 1.0), np.zeros((6, 4), np.float32), 0, 0.0, 1.0, 0.0, False, np.zeros(0, np.int64))
    select_level(*args)
    t0 = time.perf_counter()
    for _ in range(50):
        select_level(*args)
    floor_ms = (time.perf_counter() - t0) * 1e3 / 50
    rows = []
    for mult in mults:
        base.first_range = mult * base.min_first_range
        ms, tris, nodes = [], [], []
        for cam in ctx.cams:
            base.select(cam)  # warm
            t0 = time.perf_counter()
            sel = base.select(cam)
            ms.append((time.perf_counter() - t0) * 1e3)
            nodes.append(sel.stats["nodes_visited"])
            tris.append(2 * len(sel.lod) * (CDLOD_GRID // 2) ** 2)
        rows.append([ctx.hm.name, f"{mult:g}", f"{np.mean(tris):.0f}", f"{np.mean(nodes):.0f}", base.levels,
                     f"{np.median(ms):.2f}", f"{floor_ms:.3f}", "0.075-0.085"])
    return rows


def _closing_note() -> str:
    """The hand-written closing note (from ``### Closing note`` to the end) of the previous result, kept."""
    p = RESULTS / "schemes.md"
    text = p.read_text() if p.exists() else ""
    at = text.find(NOTE_HEAD)
    return "\n\n" + text[at:].strip() if at >= 0 else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fbm", type=int, default=1025, help="fBm side in samples (the issue asks 4097)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--frames", type=int, default=5, help="cameras per path")
    args = ap.parse_args()
    terrains = [Heightmap.example(), Heightmap.fbm(args.fbm, seed=1, dx=10.0, max_height=1500.0)]
    fams = families()
    sections, sel_rows, summary, by_model = [], [], [], []
    header = ["budget px", "family (parameter)", "setting", "p99 / max px", "modelled GPU ms", "draw calls",
              "triangles", "CPU frame ms", "select ms", "pop p99 / max px"]
    for hm in terrains:
        cache: dict = {}
        terrain = Terrain.prepare(hm, **LOD)
        for clearance in (0.02, 0.10):
            t0 = time.perf_counter()
            cams, before = _path(hm, clearance, args.frames, args.width, args.height)
            refs = [render(Scene(hm, camera=c, outputs=("depth",))) for c in cams]
            ctx = Ctx(hm, cams, before, refs, terrain, cache, clearance)
            for fam in fams:  # compile and warm every family's kernels before anything is timed
                fam.run(Ctx(hm, cams[:1], before[:1], refs[:1], terrain, cache, clearance), fam.ladder[0])
            rows = budget_rows(fams, ctx, {}, summary, by_model)
            if clearance == 0.02:
                sel_rows += cdlod_select_rows(ctx)
            sections.append(f"### {hm.name} {hm.shape[0]}x{hm.shape[1]}, {clearance:.0%} clearance "
                            f"({time.perf_counter() - t0:.0f} s)\n\n" + md_table(header, rows))
            print(sections[-1], flush=True)
    body = (f"Viewport {args.width}x{args.height} (1080p is too slow for this many frames on 2 shared cores), "
            f"{args.frames} flyover cameras per path (popping: against the frame before each on a {DENSE}-frame "
            f"path), CPU. Quadtree policies: roots {LOD['roots']}, tess "
            f"{LOD['tess']}; CDLOD grid {CDLOD_GRID} (setting: first range / its seam-free minimum); chunked tile "
            f"{CHUNK_TILE}, skirts at the least safe depth; clipmaps with Losasso & Hoppe's height rule. Modelled "
            f"GPU ms: {MODEL.describe()}. ★: the winner among the families that meet the budget (lowest modelled "
            "cost: the ranking; fewest triangles, least CPU time, least popping beside it).\n\n"
            "### Winners per budget, ranked by modelled GPU cost (each family at its cheapest setting meeting the "
            "budget; details below)\n\n"
            + md_table(["heightmap", "clearance", "budget px", "lowest modelled GPU ms", "fewest triangles",
                        "least CPU frame ms", "least popping (p99 px)"], summary) + "\n\n"
            + "### The same winners re-ranked under each cost model (llvmpipe's measured weights, the GPU profiles' "
            "published rates)\n\nEach family at the same cheapest setting meeting the budget (the table above), "
            "priced by the model from the same frames' counters: the winner, its modelled ms per frame, the stage "
            "most of its frames are bound by (GPU profiles), robust: it stays the winner with every rate (llvmpipe: "
            "every weight) multiplied by any of 1/3, 1/sqrt 3, 1, sqrt 3, 3 in every combination, else the smallest "
            "change that flips it (a rate x f: f times faster; `terrainwarp.measure.ranking`).\n\n"
            + md_table(["heightmap", "clearance", "budget px", "model", "winner", "modelled ms", "bound stage",
                        "robust (x1/3..x3)", "smallest change that flips it"], by_model) + "\n\n"
            + "\n\n".join(sections)
            + "\n\n### CDLOD selection time per frame (2% clearance)\n\n"
            + md_table(["heightmap", "first_range / min", "triangles", "nodes visited", "levels", "select ms",
                        "one select-level launch ms", "paper ms (3.16 GHz, 105k-446k tris)"], sel_rows))
    write_result("schemes", "LOD schemes on the same frames (bench_schemes.py)", body + _closing_note())


if __name__ == "__main__":
    main()
