"""Multi-knob fits against the tuners users would pick instead, on the same exact evaluation and the same frame
accounting (issue 33): ``fit_lod(knobs=...)`` (JAX model + exact tries), plain bisection of the main knob, random
search, Optuna's TPE with constraints and CMA-ES (the ``cma`` package), each seeded, each capped at ``--trials``
settings.

Problems (a ground-level path: the default 8-camera flyover at 2% of the extent above the ground):

* ``sse-levels``: the sse tolerance and a log multiplier of each level's threshold (tess 8: 4 knobs on the DEM);
* ``sse-tess``: the sse tolerance and ``tess``;
* ``cdlod``: CDLOD's first range, distance ratio, morph start ratio and grid;
* ``continuous``: the continuous policy's target_px and its patch level;
* ``sse-pop``: the sse tolerance and the hysteresis band, with a pop budget, on a jittering path.

For each problem and budget: every method's exact frames until its best setting measured on every camera is
within 2% of the best cost any method found ("frames to target"; "-" when it never was), its final cost and worst
p99, and its wall time. ``--fbm N`` runs the problems on an N^2 fBm instead of the DEM. The reference frames of a
path are rendered once and shared by every method (they are not counted as frames of any).

    python benchmarks/bench_fit_knobs.py [--problems sse-levels,sse-tess,...] [--budgets 1,2] [--methods ...]
        [--trials 150] [--width 960 --height 540] [--fbm 4097] [--out-stage fit_knobs]

``--merge stage,stage,...`` writes one section (``--out-stage``, default ``fit_knobs``) from earlier runs' JSON
(runs split across processes), with two more tables: the one-knob fit against bisection, and the one-knob and
multi-knob fitted settings priced by the shipped llvmpipe cost model (:mod:`terrainwarp.measure.cost`; 8 frames
each, the settings as fitted for triangles).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from _common import RESULTS, md_table, write_result

from terrainwarp import Camera, Heightmap, LodConfig, Scene
from terrainwarp.fit import baselines, fit_lod, plot_convergence
from terrainwarp.fit.exact import Exact, references_for
from terrainwarp.fit.families import problem
from terrainwarp.measure.cost import cost as resolve_cost

#: problem -> (policy, knobs, LodConfig changes, pop budget px or None)
PROBLEMS = {
    "sse-levels": ("sse", "levels", {"tess": 8}, None),
    "sse-tess": ("sse", ["tess"], {}, None),
    "cdlod": ("cdlod", ["ratio", "morph_start_ratio", "grid"], {}, None),
    "continuous": ("continuous", ["level"], {}, None),
    "sse-pop": ("sse", ["hysteresis"], {}, 0.25),
}
METHODS = ("fit_lod", "bisection", "random", "tpe", "cmaes")


def _jitter_path(scene: Scene, n: int) -> list[Camera]:
    """The bench_popping path: along the default diagonal, jittering +-2% of it back and forth."""
    from bench_popping import jitter_path

    c = scene.camera
    return jitter_path(scene.heightmap, n, c.width, c.height)


def _knob_names(policy: str, spec, scene: Scene) -> list[str]:
    from terrainwarp.fit import knobs

    ks = knobs(policy, scene.heightmap, scene.lod if not scene.lod.is_scheme else None)
    if spec == "levels":
        return [k.name for k in ks if k.name.startswith("level_log_scale_")]
    return list(spec)


def run_problem(name: str, hm: Heightmap, budget: float, args, refs_cache: dict) -> dict:
    policy, spec, lod_kw, pop = PROBLEMS[name]
    scene = Scene(hm, camera=Camera.default_for(hm, args.width, args.height), lod=LodConfig(**lod_kw))
    cams = _jitter_path(scene, args.frames) if pop is not None else scene.camera_path(args.frames)
    key = ("jitter" if pop is not None else "ground", args.frames)
    if key not in refs_cache:
        refs_cache[key] = references_for(scene, cams)
    refs = refs_cache[key]
    names = _knob_names(policy, spec, scene)
    cost_of = resolve_cost(args.cost)
    cost_of = None if cost_of.name == "triangles" else cost_of
    out: dict = {"problem": name, "policy": policy, "budget_px": budget, "max_pop_px": pop, "methods": {}}
    for method in args.methods:
        if method == "bisection" and name == "sse-pop":
            continue
        t0, c0 = time.perf_counter(), time.process_time()
        if method == "fit_lod":
            r = fit_lod(scene, budget, policy, cams, knobs=names, references=refs, max_pop_px=pop, cost=args.cost)
            res = {"frames": r.evaluations, "trace": r.trace, "trace_s": r.trace_s,
                   "best": r.validated.cost if r.met else math.inf, "worst_p99": r.validated.worst_p99,
                   "values": r.values, "settings": sum(1 for h in r.history if h["stage"] in ("try", "bracket")),
                   "met": r.met, "timings": r.timings}
            res["wall_s"], res["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
            t1 = time.perf_counter()
            one = fit_lod(scene, budget, policy, cams, references=refs, max_pop_px=pop, cost=args.cost)
            out["one_knob"] = {"frames": one.evaluations, "best": one.validated.cost if one.met else math.inf,
                               "values": one.values, "met": one.met, "wall_s": time.perf_counter() - t1,
                               "timings": one.timings}
        else:
            prob = problem(scene, policy, names if method != "bisection" else None, cams, refs, cost_of,
                           models=False)
            ex = Exact(prob.make, prob.key, cams, refs, budget, pop, cost_of, terrains=dict(prob.terrains),
                       started=t0, coarseness=prob.coarseness)
            if method == "bisection":
                baselines.bisection(ex, prob)
            else:
                baselines.BLACK_BOX[method](ex, prob, trials=args.trials, seed=args.seed)
            b = ex.best()
            res = {"frames": ex.frames, "trace": ex.trace, "trace_s": ex.trace_s, "best": b.cost if b else math.inf,
                   "worst_p99": b.worst_p99 if b else math.nan, "values": b.values if b else {},
                   "settings": len(ex.evals), "met": b is not None}
            res["wall_s"], res["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        out["methods"][method] = res
        print(f"{name} {budget:g} px {method}: {res['best']:.6g} in {res['frames']} frames, {res['wall_s']:.1f} s, "
              f"{res['cpu_s']:.1f} CPU s"
              + (f" ({', '.join(f'{k} {v:.1f}' for k, v in res['timings'].items())})" if "timings" in res else ""),
              flush=True)
    return out


def seconds_to(m: dict, target: float) -> float | None:
    """The wall seconds after which a method's best confirmed cost was within ``target`` (None: never)."""
    for (_, c), t in zip(m["trace"], m.get("trace_s") or [], strict=False):
        if c <= target:
            return t
    return None


def wall_verdict(r: dict) -> tuple[str, float | None]:
    """fit_lod's wall time against the best black-box tuner's time to reach fit_lod's cost (within 2%), or their
    whole run's wall time where none reached it: ("yes"/"no", the tuners' seconds)."""
    fit = r["methods"].get("fit_lod")
    tuners = [r["methods"][m] for m in ("random", "tpe", "cmaes") if m in r["methods"]]
    if fit is None or not tuners or not math.isfinite(fit["best"]):
        return "", None
    reach = [t for t in (seconds_to(m, fit["best"] * 1.02) for m in tuners) if t is not None]
    theirs = min(reach) if reach else min(m["wall_s"] for m in tuners)
    return ("yes" if fit["wall_s"] * 5 <= theirs else "no"), theirs


def frames_to(trace: list, target: float) -> int | None:
    """The exact frames after which the best confirmed cost was within ``target`` (None: never)."""
    for frames, c in trace:
        if c <= target:
            return frames
    return None


def table(results: list[dict], cost_label: str) -> tuple[str, list[str]]:
    rows, notes = [], []
    for r in results:
        best = min(m["best"] for m in r["methods"].values())
        target = best * 1.02
        bb = [frames_to(r["methods"][m]["trace"], target) for m in ("random", "tpe", "cmaes") if m in r["methods"]]
        bb_best = min((f for f in bb if f is not None), default=None)
        wall_ok, theirs = wall_verdict(r)
        for name, m in r["methods"].items():
            ft = frames_to(m["trace"], target)
            st = seconds_to(m, target)
            verdict = ""
            if name == "fit_lod":
                ok = ft is not None and (bb_best is None or ft * 5 <= bb_best)
                verdict = ("yes" if ok else "no") + (f"; wall {wall_ok} (tuners {theirs:.1f} s)" if wall_ok else "")
            compile_s = m.get("timings", {}).get("compile")
            rows.append([r["problem"], r["budget_px"], name, "-" if ft is None else ft, m["frames"], m["settings"],
                         "-" if not math.isfinite(m["best"]) else round(m["best"], 5 if m["best"] < 100 else 0),
                         "-" if not math.isfinite(m["best"]) else f"{100 * (m['best'] / best - 1):+.1f}%",
                         "-" if math.isnan(m["worst_p99"]) else round(m["worst_p99"], 3), round(m["wall_s"], 1),
                         "-" if m.get("cpu_s") is None else round(m["cpu_s"], 1), "-" if st is None else round(st, 1),
                         "" if compile_s is None else f"{compile_s:.1f} ({100 * compile_s / m['wall_s']:.0f}%)",
                         verdict])
    header = ["problem", "budget px", "method", "frames to target", "frames", "settings", f"best {cost_label}",
              "vs best", "worst p99 px", "wall s", "CPU s", "wall s to target", "compile s (share)",
              "target met (fit_lod): frames; wall"]
    return md_table(header, rows), notes


def timing_table(results: list[dict]) -> str:
    """fit_lod's wall time by part (FitResult.timings), multi-knob and one-knob."""
    rows = []
    for r in results:
        for label, m in (("multi-knob", r["methods"].get("fit_lod")), ("one knob", r.get("one_knob"))):
            if m and m.get("timings"):
                t = m["timings"]
                rows.append([r["problem"], r["budget_px"], label, m["frames"], round(m["wall_s"], 2),
                             *(round(t.get(k, 0.0), 2) for k in ("compile", "relaxed", "hard", "probes", "exact",
                                                                  "other"))])
    return md_table(["problem", "budget px", "fit", "frames", "wall s", "compile", "relaxed model",
                     "hard model + polish", "probes", "exact frames", "other"], rows)


def savings(results: list[dict]) -> str:
    rows = []
    for r in results:
        if "one_knob" not in r or "fit_lod" not in r["methods"]:
            continue
        one, multi = r["one_knob"]["best"], r["methods"]["fit_lod"]["best"]
        rows.append([r["problem"], r["budget_px"], round(one, 5 if one < 100 else 0),
                     round(multi, 5 if multi < 100 else 0),
                     "-" if not (math.isfinite(one) and math.isfinite(multi)) else f"{100 * (multi / one - 1):+.1f}%",
                     r["one_knob"]["frames"], r["methods"]["fit_lod"]["frames"]])
    return md_table(["problem", "budget px", "one-knob fit", "multi-knob fit", "saved", "one-knob frames",
                     "multi-knob frames"], rows)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--problems", default=",".join(PROBLEMS))
    ap.add_argument("--budgets", default="1,2")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--trials", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=540)
    ap.add_argument("--fbm", type=int, default=0, help="an N^2 fBm (seed 1, 10 m, 1500 m high) instead of the DEM")
    ap.add_argument("--cost", default="triangles")
    ap.add_argument("--out-stage", default=None)
    ap.add_argument("--merge", default=None, help="stages of earlier runs (their JSON) to write as one section")
    ap.add_argument("--refresh-one-knob", default=None,
                    help="stages whose fit_lod runs (multi-knob, one-knob) to run again with this code")
    ap.add_argument("--fresh", action="store_true",
                    help="fit_lod alone: a fresh process with warm caches and a cold machine against a fit repeated "
                         "in one process (stage fit_knobs_fresh)")
    ap.add_argument("--merge-cost", default=None,
                    help="with --merge: stages of fit_lod runs with --cost llvmpipe (one-knob against multi-knob)")
    args = ap.parse_args()
    if args.fresh:
        fresh(args)
        return
    if args.refresh_one_knob:
        for st in args.refresh_one_knob.split(","):
            refresh_one_knob(st, args)
    if args.merge:
        merge(args)
    if args.merge or args.refresh_one_knob:
        return
    args.methods = [m for m in args.methods.split(",") if m]
    hm = (Heightmap.fbm(args.fbm, seed=1, dx=10.0, max_height=1500.0) if args.fbm else Heightmap.example())
    refs_cache: dict = {}
    results = []
    t0 = time.perf_counter()
    for name in args.problems.split(","):
        for b in (float(x) for x in args.budgets.split(",")):
            results.append(run_problem(name, hm, b, args, refs_cache))
    stage = args.out_stage or ("fit_knobs" if not args.fbm else f"fit_knobs_fbm{args.fbm}") + (
        "" if args.cost == "triangles" else f"_{args.cost}")
    label = resolve_cost(args.cost).label
    body, _ = table(results, label)
    where = f"{args.fbm}^2 fBm (seed 1)" if args.fbm else "the bundled SRTM DEM"
    text = (f"{where}, {args.width}x{args.height}, {args.frames} cameras (the default ground-level path; sse-pop: a "
            f"jittering path with a pop budget of 0.25 px); cost: {label} per frame (mean over the path). Every "
            f"method evaluates settings on the same exact pipeline: a try measures the cameras worst first and stops "
            f"at the first frame over the budget; `frames` counts the frames measured; `frames to target`: the "
            f"frames after which its best setting measured on every camera was within 2% of the best cost any "
            f"method found; black-box tuners capped at {args.trials} settings, seed {args.seed}. `target met`: "
            f"fit_lod reached the target in at most 1/5 of the frames of the best black-box tuner that reached it; "
            f"`wall`: fit_lod's wall time at most 1/5 of the best tuner's wall time to reach fit_lod's cost (within "
            f"2%), or of their whole {args.trials}-setting run where none reached it. `wall s to target`: the wall "
            f"seconds after which the method's best was within 2% of the best cost; `compile s`: JAX's tracing and "
            f"compiling (or reading the persistent cache) inside fit_lod. fit_lod's wall time is the multi-knob fit "
            f"alone (the one-knob fit is timed apart). The machine is shared (2 cores): ratios within this run are "
            f"what count. Total {time.perf_counter() - t0:.0f} s.\n\n{body}\n\n"
            f"Cost saved by the multi-knob fit against the one-knob fit (the main knob alone) at the same budget:\n\n"
            f"{savings(results)}\n\nfit_lod's wall time by part (FitResult.timings, s):\n\n{timing_table(results)}\n\n"
            f"One knob against bisection:\n\n{one_knob_vs_bisection(results)}\n")
    write_result(stage, f"Multi-knob fits against black-box tuners ({where})", text)
    (RESULTS / f"{stage}.json").write_text(json.dumps(results, indent=1, default=float))
    for r in results:
        traces = {m: v["trace"] for m, v in r["methods"].items()}
        best = min(m["best"] for m in r["methods"].values())
        plot_convergence(traces, Path(RESULTS) / f"{stage}_{r['problem']}_{r['budget_px']:g}px.png",
                         title=f"{r['problem']} at {r['budget_px']:g} px", cost_label=label, target=best * 1.02)


def one_knob_vs_bisection(results: list[dict]) -> str:
    """The one-knob fit (fit_lod, knobs=None) against plain bisection of the same knob, per problem and budget:
    frames, cost, wall time (target: at most 2x bisection's wall, cost within 2% of the better)."""
    rows = []
    for r in results:
        one, bis = r.get("one_knob"), r["methods"].get("bisection")
        if one is None or bis is None:
            continue
        best = min(one["best"], bis["best"])
        wall = one.get("wall_s")
        rows.append([r["problem"], r["budget_px"], one["frames"], bis["frames"], round(one["best"]), round(bis["best"]),
                     f"{100 * (one['best'] / best - 1):+.1f}%", "-" if wall is None else round(wall, 1),
                     round(bis["wall_s"], 1),
                     "-" if wall is None else ("yes" if wall <= 2 * bis["wall_s"] and one["best"] <= 1.02 * best
                                               else "no")])
    return md_table(["problem", "budget px", "fit_lod frames", "bisection frames", "fit_lod triangles",
                     "bisection triangles", "fit_lod vs best of the two", "fit_lod wall s", "bisection wall s",
                     "wall <= 2x bisection, within 2%"], rows)


def priced(results: list[dict], width: int, height: int, frames: int) -> str:
    """The one-knob and the multi-knob fitted settings of each problem priced by the shipped llvmpipe model."""
    from terrainwarp.fit import apply
    from terrainwarp.fit.exact import evaluate

    hm = Heightmap.example()
    model = resolve_cost("llvmpipe")
    refs_cache: dict = {}
    rows = []
    for r in results:
        if "one_knob" not in r or "fit_lod" not in r["methods"]:
            continue
        policy, _, lod_kw, pop = PROBLEMS[r["problem"]]
        scene = Scene(hm, camera=Camera.default_for(hm, width, height), lod=LodConfig(**lod_kw))
        cams = _jitter_path(scene, frames) if pop is not None else scene.camera_path(frames)
        key = pop is not None
        if key not in refs_cache:
            refs_cache[key] = references_for(scene, cams)
        ms = [evaluate(apply(scene, policy, v), cams, refs_cache[key], cost_of=model).cost
              for v in (r["one_knob"]["values"], r["methods"]["fit_lod"]["values"])]
        rows.append([r["problem"], r["budget_px"], round(ms[0], 3), round(ms[1], 3),
                     f"{100 * (ms[1] / ms[0] - 1):+.1f}%"])
    return md_table(["problem", "budget px", "one-knob fit, modelled ms", "multi-knob fit, modelled ms", "saved"],
                    rows)


def _fitted_for_model(args) -> str:
    """The one-knob and the multi-knob fits run with ``--cost llvmpipe`` (the model minimised, not triangles)."""
    if not args.merge_cost:
        return ""
    results, commands = [], []
    for st in args.merge_cost.split(","):
        results += json.loads(_run_file(f"{st}.json").read_text())
        commands += [ln.rstrip() for ln in _run_file(f"{st}.md").read_text().split("\n") if ln.startswith("Command:")]
    return ("\nFitted for the modelled GPU cost instead (fit_lod with `cost=\"llvmpipe\"`: the relaxed model prices "
            "patches, domain points, vertices, clipped primitives and fragments by the shipped weights; the exact "
            "tries price every frame's counters), one knob against several, modelled ms per frame; the multi-knob "
            "fits here ran before every fit ended on the exact line through its best setting (they can only be "
            "cheaper now) ("
            + "; ".join(c.replace("Command: ", "").replace("  ", "") for c in commands) + "):\n\n"
            + savings(results) + "\n")


def refresh_one_knob(stage: str, args) -> None:
    """Run each result's fits again with this code, the multi-knob fit (``fit_lod`` in its methods) and the one-knob
    fit (the same problem, budget, path and references), and update its JSON; the baselines are kept."""
    path = RESULTS / f"{stage}.json"
    results = json.loads(path.read_text())
    hm = Heightmap.example()
    refs_cache: dict = {}
    for r in results:
        policy, _, lod_kw, pop = PROBLEMS[r["problem"]]
        scene = Scene(hm, camera=Camera.default_for(hm, args.width, args.height), lod=LodConfig(**lod_kw))
        cams = _jitter_path(scene, args.frames) if pop is not None else scene.camera_path(args.frames)
        key = pop is not None
        if key not in refs_cache:
            refs_cache[key] = references_for(scene, cams)
        if "fit_lod" in r["methods"]:
            t0 = time.perf_counter()
            m = fit_lod(scene, r["budget_px"], policy, cams, knobs=_knob_names(policy, PROBLEMS[r["problem"]][1],
                                                                                scene),
                        references=refs_cache[key], max_pop_px=pop, cost=args.cost)
            r["methods"]["fit_lod"] = {
                "frames": m.evaluations, "trace": m.trace, "best": m.validated.cost if m.met else math.inf,
                "worst_p99": m.validated.worst_p99, "values": m.values, "met": m.met,
                "settings": sum(1 for h in m.history if h["stage"] in ("try", "bracket")),
                "wall_s": time.perf_counter() - t0}
            print(f"{r['problem']} {r['budget_px']:g} px fit_lod: {r['methods']['fit_lod']['best']:.6g} in "
                  f"{m.evaluations} frames", flush=True)
        one = fit_lod(scene, r["budget_px"], policy, cams, references=refs_cache[key], max_pop_px=pop, cost=args.cost)
        r["one_knob"] = {"frames": one.evaluations, "best": one.validated.cost if one.met else math.inf,
                         "values": one.values, "met": one.met}
        print(f"{r['problem']} {r['budget_px']:g} px one knob: {r['one_knob']['best']:.6g} in {one.evaluations} "
              "frames", flush=True)
    path.write_text(json.dumps(results, indent=1, default=float))


_FRESH = """
import json, sys, time
t00 = time.perf_counter()
sys.path.insert(0, {bench!r})
import bench_fit_knobs as B
from terrainwarp import Camera, Heightmap, LodConfig, Scene, fit_lod
from terrainwarp.fit.exact import references_for
a = json.loads({job!r})
policy, spec, lod_kw, pop = B.PROBLEMS[a["problem"]]
hm = Heightmap.fbm(a["fbm"], seed=1, dx=10.0, max_height=1500.0) if a["fbm"] else Heightmap.example()
scene = Scene(hm, camera=Camera.default_for(hm, a["width"], a["height"]), lod=LodConfig(**lod_kw))
cams = B._jitter_path(scene, a["frames"]) if pop is not None else scene.camera_path(a["frames"])
refs = references_for(scene, cams)
t0 = time.perf_counter()
r = fit_lod(scene, a["budget"], policy, cams, knobs=B._knob_names(policy, spec, scene), references=refs,
            max_pop_px=pop)
print(json.dumps({{"wall_s": time.perf_counter() - t0, "timings": r.timings, "frames": r.evaluations,
                   "values": r.values, "process_s": time.perf_counter() - t00}}))
"""


def _fit_in_process(job: dict, env: dict) -> dict:
    import os
    import subprocess
    import sys

    code = _FRESH.format(bench=str(Path(__file__).resolve().parent), job=json.dumps(job))
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, **env})
    if r.returncode:
        raise RuntimeError(r.stderr[-3000:])
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["outer_s"] = time.perf_counter() - t0
    return out


def fresh(args) -> None:
    """Per problem and budget: fit_lod repeated in this process (its second run), then in a fresh process with the
    caches warm (Warp's kernels, JAX's programs), then on a cold machine (empty Warp and JAX caches)."""
    import tempfile

    hm = Heightmap.fbm(args.fbm, seed=1, dx=10.0, max_height=1500.0) if args.fbm else Heightmap.example()
    rows = []
    for name in args.problems.split(","):
        policy, spec, lod_kw, pop = PROBLEMS[name]
        scene = Scene(hm, camera=Camera.default_for(hm, args.width, args.height), lod=LodConfig(**lod_kw))
        cams = _jitter_path(scene, args.frames) if pop is not None else scene.camera_path(args.frames)
        refs = references_for(scene, cams)
        for b in (float(x) for x in args.budgets.split(",")):
            names = _knob_names(policy, spec, scene)
            fit_lod(scene, b, policy, cams, knobs=names, references=refs, max_pop_px=pop)
            t0 = time.perf_counter()
            again = fit_lod(scene, b, policy, cams, knobs=names, references=refs, max_pop_px=pop)
            here = time.perf_counter() - t0
            job = {"problem": name, "budget": b, "fbm": args.fbm, "width": args.width, "height": args.height,
                   "frames": args.frames}
            warm = _fit_in_process(job, {})
            with tempfile.TemporaryDirectory() as wd, tempfile.TemporaryDirectory() as jd:
                cold = _fit_in_process(job, {"WARP_CACHE_PATH": wd, "TERRAINWARP_JAX_CACHE": jd})
            same = warm["values"] == again.values and warm["frames"] == again.evaluations
            rows.append([name, b, again.evaluations, round(here, 2), round(warm["wall_s"], 2),
                         f"{warm['wall_s'] / here:.2f}", "yes" if warm["wall_s"] <= 1.5 * here else "no",
                         round(warm["timings"]["compile"], 2), round(cold["wall_s"], 1),
                         f"{cold['timings']['compile']:.1f} ({100 * cold['timings']['compile'] / cold['wall_s']:.0f}%)",
                         round(cold["process_s"], 1), "yes" if same else "NO"])
            print(rows[-1], flush=True)
    where = f"{args.fbm}^2 fBm (seed 1)" if args.fbm else "the bundled SRTM DEM"
    text = (f"{where}, {args.width}x{args.height}, {args.frames} cameras; fit_lod multi-knob (the problems' knobs), "
            "its references rendered before the clock starts. `repeated`: the second of two fits in one process; "
            "`fresh`: the first fit of a new process, Warp's kernels and JAX's programs cached by earlier runs "
            "(its `compile`: tracing and reading the persistent cache); `cold`: a new process with empty Warp and JAX "
            "caches (`TERRAINWARP_JAX_CACHE`, `WARP_CACHE_PATH` on empty folders): the fit's wall time, its JAX "
            "compile share, and the whole process (imports, kernels compiled for the references, the fit). The "
            "machine is shared (2 cores).\n\n"
            + md_table(["problem", "budget px", "frames", "repeated s", "fresh s", "fresh / repeated",
                        "within 1.5x", "fresh compile s", "cold fit s", "cold JAX compile s (share)",
                        "cold process s", "same values and frames"], rows) + "\n")
    write_result(args.out_stage or "fit_knobs_fresh", f"fit_lod in a fresh process and on a cold machine ({where})",
                 text)


def _run_file(name: str) -> Path:
    """A component run's file: in results/, or in results/fit_knobs_runs/ where merged runs are kept."""
    p = RESULTS / name
    return p if p.exists() else RESULTS / "fit_knobs_runs" / name


def merge(args) -> None:
    results, commands = [], []
    for st in args.merge.split(","):
        results += json.loads(_run_file(f"{st}.json").read_text())
        head = _run_file(f"{st}.md").read_text().split("\n")
        commands += [ln for ln in head if ln.startswith("Command:") or ln.startswith("Run:")]
    body, _ = table(results, "triangles")
    text = ("\n".join(f"{c.rstrip()}  " for c in commands) + "\n\n"
            f"The bundled SRTM DEM, {args.width}x{args.height}, {args.frames} cameras (the default ground-level path; "
            "sse-pop: a jittering path with a pop budget of 0.25 px); cost: triangles per frame (mean over the path). "
            "Every method evaluates settings on the same exact pipeline: a try measures the cameras worst first and "
            "stops at the first frame over the budget; `frames` counts the frames measured; `frames to target`: the "
            "frames after which its best setting measured on every camera was within 2% of the best cost any method "
            f"found; black-box tuners run {args.trials} settings each (seed {args.seed}). The fit_lod rows and the "
            "one-knob fits were run again with the final code (`--refresh-one-knob`, the baselines' rows kept); the "
            "component runs are in `fit_knobs_runs/`. `target met`: fit_lod "
            "reached the target in at most 1/5 of the frames of the best black-box tuner that reached it (or none "
            f"did). Convergence plots: `{args.out_stage or 'fit_knobs'}_<problem>_<budget>px.png`.\n\n{body}\n\n"
            "The multi-knob fit against the one-knob fit (fit_lod, the main knob alone) at the "
            f"same budget, in triangles:\n\n{savings(results)}\n\nThe same two settings priced by the shipped "
            f"llvmpipe cost model (modelled GPU ms per frame, mean over the path; fitted for triangles):\n\n"
            f"{priced(results, args.width, args.height, args.frames)}\n\nOne knob: fit_lod (knobs=None) against plain "
            f"bisection of the same knob on the same accounting:\n\n{one_knob_vs_bisection(results)}\n"
            + _fitted_for_model(args))
    stage = args.out_stage or "fit_knobs"
    write_result(stage, "Multi-knob fits against black-box tuners (the bundled SRTM DEM)", text)
    for r in results:
        best = min(m["best"] for m in r["methods"].values())
        plot_convergence({m: v["trace"] for m, v in r["methods"].items()},
                         RESULTS / f"{stage}_{r['problem']}_{r['budget_px']:g}px.png",
                         title=f"{r['problem']} at {r['budget_px']:g} px", cost_label="triangles", target=best * 1.02)


if __name__ == "__main__":
    main()
