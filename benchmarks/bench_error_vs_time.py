"""Error against run time: the sweep of `terrainwarp report` on the bundled SRTM DEM and on a 4097x4097
fractal terrain, each with a fixed 8-camera flyover at 1920x1080, with the peers Martini and Delatin.

    python benchmarks/bench_error_vs_time.py [--quick] [--only jacksboro|fbm4097] [--frames 8]

For p99 error budgets of 0.5, 1, 2 and 4 px: the modelled GPU cost (the shipped llvmpipe cost model of the
frame's counters), triangles and this simulator's CPU milliseconds per frame of each policy and peer (the
cheapest setting by modelled cost whose worst-frame p99 meets the budget), and the two ratios of the project's bar:
view-dependent LOD triangles / Delatin triangles, and LOD select + tessellate time / Delatin meshing time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from _common import md_table, write_result

from terrainwarp import Camera, Heightmap, LodConfig, Scene
from terrainwarp.experiments.pareto import (
    Setting,
    budget_table,
    default_settings,
    image_floor,
    pareto,
    summarise,
    sweep,
    write_report,
)

BUDGETS = (0.5, 1.0, 2.0, 4.0)
OUT = Path(__file__).resolve().parents[1] / "out" / "bench_error_vs_time"


def terrains(only: str | None, quick: bool):
    if only in (None, "jacksboro"):
        yield "jacksboro", Heightmap.example(), LodConfig(roots=16, tess=16)
    if only in (None, "fbm4097"):
        n = 1025 if quick else 4097
        yield f"fbm{n}", Heightmap.fbm(n, seed=7, dx=1.0, max_height=400.0, feature_size=n / 4), \
            LodConfig(roots=64, tess=16)


def settings_for(hm: Heightmap, quick: bool, big: bool) -> list[Setting]:
    s = default_settings(hm, quick=quick)
    if big:  # Delatin at fine errors on 16.8M samples takes minutes: keep the two coarsest
        peers = [x for x in s if x.policy == "delatin"]
        s = [x for x in s if x.policy != "delatin"] + peers[-2:]
    return s


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", default=None)
    ap.add_argument("--frames", type=int, default=8)
    a = ap.parse_args()
    for name, hm, lod in terrains(a.only, a.quick):
        body = []
        t0 = time.perf_counter()
        sc = Scene(hm, camera=Camera.default_for(hm, 1920, 1080), lod=lod)
        cams = sc.camera_path(a.frames)
        # in this process (workers=0): frames timed inside Dask workers run 1.5-2x slower (bench_sweep.py),
        # and one process keeps the timings from sharing the 2 cores
        rows = sweep(sc, cams, settings_for(hm, a.quick, hm.shape[0] > 2000), images=False, workers=0)
        write_report(sc, cams, rows, OUT / name, path=sc.path_info(a.frames))
        summ = summarise(rows)
        tab = budget_table(summ, BUDGETS)
        body.append(f"### {name}: {hm.shape[0]}x{hm.shape[1]}, {len(cams)} cameras at 1920x1080, LOD {lod.roots} "
                    f"roots, tess {lod.tess} (sweep {time.perf_counter() - t0:.0f} s)\n\n"
                    f"Path: {sc.path_info(a.frames)['text']}. Budgets on the primary error (per visible heightmap "
                    "sample; every family's full-detail mesh scores 0); `image_err_p99_px` is the old per-pixel "
                    "grid-image error at the same setting, `pop_p99_px` the worst consecutive pair's pop.\n")
        by_setting = {r["setting"]: r for r in summ}
        tab = [[*r[:6], *((round(by_setting[r[2]]["frame_ms"], 2), round(by_setting[r[2]]["peer_mesh_ms"], 1))
                          if r[2] in by_setting else ("-", "-")), *r[6:]] for r in tab]
        body.append(md_table(["budget_px", "policy", "cheapest setting", "p99_px", "modelled GPU ms", "triangles",
                              "CPU ms/frame", "peer mesh ms", "image_err_p99_px", "pop_p99_px"], tab))
        # the project's bar: LOD vs Delatin at each budget
        bar = []
        for b in BUDGETS:
            lod_ok = [r for r in summ if r["policy"] in ("sse", "distance", "continuous") and r["p99_px"] <= b]
            del_ok = [r for r in summ if r["policy"] == "delatin" and r["p99_px"] <= b]
            if lod_ok and del_ok:
                lb = min(lod_ok, key=lambda r: r["triangles"])
                db = min(del_ok, key=lambda r: r["triangles"])
                bar.append([b, lb["setting"], int(lb["triangles"]), db["setting"], int(db["triangles"]),
                            round(lb["triangles"] / db["triangles"], 3), round(lb["select_ms"] + lb["mesh_ms"], 2),
                            round(db["peer_mesh_ms"], 1),
                            round((lb["select_ms"] + lb["mesh_ms"]) / max(db["peer_mesh_ms"], 1e-9), 4)])
            else:
                bar.append([b, "-", "-", "-", "-", "-", "-", "-", "-"])
        body.append("\nLOD against Delatin (best of each meeting the budget):\n")
        body.append(md_table(["budget_px", "LOD setting", "LOD tris", "Delatin setting", "Delatin tris",
                              "tris ratio", "LOD select+tess ms", "Delatin mesh ms", "time ratio"], bar))
        floor = min(r["p99_px"] for r in summ if r["policy"] in ("sse", "distance"))
        old = image_floor(summ)
        body.append(f"\nFinest LOD setting's worst-frame p99 (primary): {floor:.3g} px. The old yardstick's floor "
                    "(grid-image p99 of each family's finest setting here; the tessellator mirrors its diagonals "
                    "about each patch's centre lines, the reference grid does not): "
                    + ", ".join(f"{k} {v:.3g} px" for k, v in old.items())
                    + f". Pareto front (modelled GPU cost): {', '.join(r['setting'] for r in pareto(summ))}; "
                    f"(CPU time): {', '.join(r['setting'] for r in pareto(summ, 'frame_ms'))}. "
                    f"Full tables and the plot: `out/bench_error_vs_time/{name}/report.md` (copied to "
                    "docs/pareto.png for the DEM).\n")
        write_result(f"error_vs_time_{name}", f"Error against run time: {name} (bench_error_vs_time.py)",
                     "\n".join(body))


if __name__ == "__main__":
    main()
