"""The ``terrainwarp`` command line.

Every command that takes a scene file uses the demo scene (the bundled SRTM DEM, default camera) when
none is given. ``--plugin FILE.py`` (or a module name; before or after the command, repeatable) runs a plugin
first, so the LOD schemes it registers (:func:`terrainwarp.schemes.register_scheme`) are names that
``report --policies`` and ``fit --policy`` take. Outputs go under ``--out DIR``, written as one set
(:func:`terrainwarp.io.files.output_set`): renamed into place only when every file is written. Bad arguments,
paths and scene files, a full disk or any other failure print one line on stderr and exit 2; Ctrl-C (SIGINT),
SIGTERM and SIGHUP print one line and exit 128 + the signal (130, 143, 129). Either way ``--out`` is left as it
was (the previous run's files whole, nothing new) except for a sweep's partial journal, from which a rerun
resumes; a signal that arrives while the set is being switched waits until it is whole
(:func:`terrainwarp.io.files.interrupts_deferred`). Before it starts, a command finishes a commit that a killed
run left half done and removes a killed run's temporaries (:func:`terrainwarp.io.files.recover`). A run that
succeeds says which files in ``--out`` it did not write (left from an earlier run; never deleted).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
import tomllib
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import __version__
from .camera import Camera, DepthPrecisionWarning
from .experiments.calibrate import FAMILIES as CALIBRATION_FAMILIES
from .experiments.calibrate import calibrate
from .experiments.extreme import CASES as EXTREME_CASES
from .experiments.pareto import Setting, complete, default_settings, run_sweep, summarise, sweep, write_report
from .experiments.plots import mesh_pieces, plot_patches
from .experiments.runner import Runner
from .experiments.stability import EXPLANATIONS, FAIL, run_suite, write_stability_md
from .experiments.winners import budget_verdicts
from .fit import (
    Evaluation,
    FitResult,
    assess,
    evaluations_from_rows,
    export,
    fit_lod,
    pixel_knobs,
    plot_convergence,
    plot_fit,
    rescale,
)
from .fit.baselines import BASELINES, run_baselines
from .fit.exact import references_for
from .fit.export import FORMATS
from .fit.knobs import check_knob_names, main_knob
from .heightmap import Heightmap, StreamedHeightmap
from .io.files import dumps_strict, interrupt_handler, output_set, recover, write_json, write_text
from .kernels.parallel import default_threads
from .measure.cost import Cost, CostModel, cost
from .rendering.pipeline import render
from .rendering.reference_tessellator import tessellation_json, write_tessellation_picture
from .runtime import configure_from_env
from .scene import (
    LOD_POLICIES,
    MAX_TESS,
    PATH_PRESETS,
    POLICY_TABLE,
    QUADTREE_TESS,
    SPACINGS,
    LodConfig,
    Scene,
    check_tess,
)
from .schemes import SCHEMES, load_plugin
from .warmup import warmup

__all__ = ["main", "sweep_evaluator", "split_timings"]


_LOD = LodConfig()  # the defaults of the LOD options
#: What ``fit`` writes (and convergence.png with --baselines): its help, its "wrote:" line and the README say these
FIT_FILES = ("fit.json", "fit.png", "fitted.toml", "report.md", "timing.json", "timing.md")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit code 2, no usage dump
        print(f"terrainwarp: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _scene(args: argparse.Namespace) -> Scene:
    """The command's scene: its file (every key applied; a flag that overrides one says so on stderr), or the
    demo scene."""
    if getattr(args, "scene", None):
        sc = Scene.load(args.scene)
    else:
        sc = Scene(Heightmap.example("jacksboro"), name="demo")
    cam = sc.camera
    _note_overrides(args, [("--width", getattr(args, "width", None), "camera", "width", cam.width),
                           ("--height", getattr(args, "height", None), "camera", "height", cam.height)])
    if getattr(args, "width", None) is not None or getattr(args, "height", None) is not None:
        w = cam.width if args.width is None else args.width
        h = cam.height if args.height is None else args.height
        sc = sc.with_(camera=cam.with_(width=w, height=h))  # (the default view does not depend on the viewport)
    return sc


def _say(message: str) -> None:
    """What the command is doing, on stderr (stdout carries its results): one line before each step that takes
    more than a moment, so no wait is silent."""
    print(f"terrainwarp: {message}", file=sys.stderr, flush=True)


def _quiet(message: str) -> None:
    """``--no-progress``: nothing said (a program reading stderr gets one line on an error, nothing else)."""


def _sayer(args: argparse.Namespace):
    """:func:`_say`, or nothing with ``--no-progress`` (the progress bars' switch: these lines are progress too)."""
    return _quiet if getattr(args, "no_progress", False) else _say


# Peak memory a frame adds per pixel, by the most demanding output it asks for (bytes; measured as the peak RSS
# growth of 2048^2 and 4096^2 renders of the demo DEM): the rasterizer's depth|id keys, ids and depth; the image's
# colour; the normals' attribute images; the error's reference frame and maps.
_BYTES_PER_PIXEL = {"depth": 16, "image": 27, "normals": 48, "curvature": 48, "error": 62}
_4K = 3840 * 2160


def frame_memory_note(scene: Scene) -> str | None:
    """The line ``render`` says before a frame of more pixels than 4K (3840 x 2160): its size and about how much
    memory its buffers take; None for smaller frames."""
    w, h = scene.camera.width, scene.camera.height
    if w * h <= _4K:
        return None
    per_px = max((_BYTES_PER_PIXEL.get(o, 16) for o in scene.outputs), default=16) + 5 * ("counters" in scene.outputs)
    return (f"rendering {w}x{h} ({w * h / 1e6:.0f} Mpixel, {', '.join(scene.outputs)}): about "
            f"{w * h * per_px / 2**30:.1f} GiB of frame buffers")


def _file_tables(args: argparse.Namespace) -> dict:
    """The scene file's tables as written (the keys it sets), {} for the demo scene."""
    if not getattr(args, "scene", None):
        return {}
    try:
        return tomllib.loads(Path(args.scene).read_text())
    except (OSError, ValueError):  # Scene.load says what is wrong with the file
        return {}


def _note_overrides(args: argparse.Namespace, flags: list[tuple[str, object, str, str, object]]) -> None:
    """Say on stderr which flags override a key the scene file sets: ``(flag, value given or None, table, key,
    the scene's value)``."""
    tables = None
    for flag, given, table, key, current in flags:
        if given is None or given == current:
            continue
        tables = _file_tables(args) if tables is None else tables
        if key in tables.get(table, {}):
            print(f"terrainwarp: note: {flag} {given} overrides the scene's [{table}] {key} = {current!r}",
                  file=sys.stderr)


def _whole(sc: Scene, command: str) -> Scene:
    """A streamed scene's heightmap read whole, for a command that measures every frame against the
    full-resolution grid (a terrain too large for memory is refused, naming its size)."""
    if not isinstance(sc.heightmap, StreamedHeightmap):
        return sc
    hm = sc.heightmap.load()
    print(f"terrainwarp: note: {command} measures every frame against the full-resolution grid: the streamed "
          f"heightmap {hm.name} ({hm.shape[0]} x {hm.shape[1]}) is read whole", file=sys.stderr)
    return sc.with_(heightmap=hm)


def _write_scene(sc: Scene, out: Path) -> Path:
    """``scene.toml`` in ``out``: the scene the command ran (its file's keys, flags applied), which
    ``terrainwarp render`` takes back."""
    return sc.save(out / "scene.toml")


def _cmd_render(args: argparse.Namespace) -> int:
    sc = _scene(args)
    if "report" not in sc.outputs:
        sc = sc.with_(outputs=(*sc.outputs, "report"))
    note = frame_memory_note(sc)
    if note:
        _say(note)
    frame = render(sc)
    frame.report.info["scene_file"] = sc.to_dict()  # the scene drawn, every key (report.json)
    written = frame.save(args.out)
    print(frame.report.table())
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def _positive_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (v > 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {s}")
    return v


def _int_at_least(s: str, least: int) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if v < least:
        raise argparse.ArgumentTypeError(f"expected an integer >= {least}, got {v}")
    return v


def _nonnegative_int(s: str) -> int:
    return _int_at_least(s, 0)


def _positive_int(s: str) -> int:
    return _int_at_least(s, 1)


def _tess_level(s: str) -> int:
    """A tessellation level by the one rule (:func:`terrainwarp.scene.check_tess`); the policy's part of the
    rule (powers of two for a quadtree) is checked with the policy, by ``LodConfig``."""
    try:
        return check_tess(_int_at_least(s, 1))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("tess: ")) from None


_LOD_FLAGS = ("policy", *(s.field for s in POLICY_TABLE.values()), "level", "hysteresis", "roots", "tess")


def _lod_config(args: argparse.Namespace, scene_lod: LodConfig, notes: bool = True) -> LodConfig:
    """The scene's ``[lod]`` with the LOD flags given applied over it (each that overrides a key of the file
    says so), validated by LodConfig's rules before any work: the policy's parameter, the hysteresis, the
    level, the roots and the tessellation level (a power of two for a quadtree policy)."""
    given = {k: getattr(args, k) for k in _LOD_FLAGS if getattr(args, k, None) is not None}
    _note_overrides(args, [] if not notes else [("--" + k.replace("_", "-"), v, "lod", k, getattr(scene_lod, k))
                                                for k, v in given.items()])
    try:
        if given.get("policy", scene_lod.policy) != scene_lod.policy:  # another policy: its own knobs
            keep = {f: getattr(scene_lod, f) for f in ("roots", "tess", "hysteresis", "level", "filter",
                                                       "level_log_scale")}
            spacing = POLICY_TABLE[given["policy"]].spacing if given["policy"] in POLICY_TABLE else None
            scene_lod = LodConfig(policy=given["policy"], **keep, **({"spacing": spacing} if spacing else {}))
        return replace(scene_lod, **given)
    except (TypeError, ValueError) as e:  # name the option: "lod.tess: ..." -> "--tess: ..."
        name, _, rest = str(e).removeprefix("lod.").partition(":")
        raise ValueError(f"--{name.replace('_', '-')}:{rest}" if name in given else str(e)) from None


def _file_lod(args: argparse.Namespace) -> LodConfig:
    """The scene file's ``[lod]`` table, read before its heightmap (a bad one: the defaults here, and Scene.load
    names what is wrong)."""
    try:
        return LodConfig(**_file_tables(args).get("lod", {}))
    except (TypeError, ValueError):
        return LodConfig()


def _cmd_lod(args: argparse.Namespace) -> int:
    _lod_config(args, _file_lod(args), notes=False)  # the flags checked against the file's [lod] before any work
    sc = _scene(args)
    cfg = _lod_config(args, sc.lod)
    sc = sc.with_(mesh="lod", lod=cfg)
    frame = render(sc.with_(outputs=("patches", "mesh")))  # quadtree policies, schemes, streamed terrains alike
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    patches = frame.patches if frame.patches is not None else mesh_pieces(frame.mesh)
    patches.to_csv(out / "patches.csv")
    culled = f", {patches.stats['culled']} culled" if "culled" in patches.stats else ""
    plot_patches(sc.heightmap, patches, sc.camera, out / "lod.png", title=f"{cfg.policy}: {len(patches)} "
                 f"{'patches' if frame.patches is not None else 'pieces'}{culled}",
                 light=(sc.light_azimuth_deg, sc.light_elevation_deg))
    _write_scene(sc, out)
    print(dumps_strict({**patches.stats, "levels": np.bincount(patches.level).tolist() if len(patches) else []}))
    print(f"wrote: {out / 'lod.png'}, {out / 'patches.csv'}, {out / 'scene.toml'}")
    return 0


def _path_overrides(args: argparse.Namespace, sc: Scene) -> None:
    d = sc.path
    _note_overrides(args, [("--frames", args.frames, "path", "n", d.n),
                           ("--path", args.path, "path", "clearance", d.clearance),
                           ("--path", args.path, "path", "preset", d.preset)])


def _cmd_report(args: argparse.Namespace) -> int:
    given = _scene(args)
    sc = _whole(given, "report")
    _path_overrides(args, sc)
    args.budget_px = None
    _budget_defaults(args, sc, ("cost",), {"cost": "llvmpipe"})
    cams = sc.camera_path(args.frames, preset=args.path)
    path = sc.path_info(args.frames, preset=args.path)
    settings = default_settings(sc.heightmap, quick=args.quick)
    own = Setting(sc.lod.policy, float(sc.lod.value)) if sc.lod.value is not None else None
    if own is not None and own not in settings and (own.policy in LOD_POLICIES or own.policy in SCHEMES):
        settings.append(own)  # the scene's own [lod] setting, beside the sweep's
    if args.policies:
        want = set(args.policies.split(","))
        bad = want - {s.policy for s in settings}
        if bad:
            raise ValueError(f"--policies: unknown {sorted(bad)}")
        settings = [s for s in settings if s.policy in want]
    ranking = cost(_cost_spec(args.cost))  # checked before the sweep runs
    # jobs run on a Dask LocalCluster (one process per core) or --scheduler; rows are saved to
    # frames.csv.partial as they arrive, so a rerun after an interruption resumes where it stopped
    say = _sayer(args)
    with _runner(args.scheduler, args.workers, say) as runner:
        rows = run_sweep(sc, cams, settings, progress=not args.no_progress, images=not args.no_images,
                         out=Path(args.out) / "frames.csv", cost_model=_sweep_model(ranking), runner=runner,
                         say=say).rows
    failed = [r for r in rows if r["error"]]
    for r in failed[:5]:
        print(f"failed: {r['setting']} frame {r['frame']}: {r['error']}", file=sys.stderr)
    paths = [*write_report(sc, cams, rows, args.out, path=path, cost_of=ranking), _write_scene(given, Path(args.out))]
    print(f"path: {path['text']}")
    print(f"cost: {ranking.label}")
    for r in summarise(rows, ranking):
        if r["failed"] == r["frames"]:
            print(f"{r['setting']:>18}  every frame failed ({r['failed']})")
            continue
        print(f"{r['setting']:>18}  p99 {r['p99_px']:8.3f} px  image p99 {r['image_err_p99_px']:8.3f} px  "
              f"pop p99 {r['pop_p99_px']:7.3f} px  cost {r['cost']:10.4g}  {r['triangles']:>9.0f} tris  "
              f"{r['frame_ms']:9.2f} CPU ms" + (f"  ({r['failed']} of {r['frames']} frames failed)" if r["failed"]
                                                else ""))
    print("winner per budget under each cost model (robust: the same winner with every rate x1/3..x3):")
    whole = complete(summarise(rows, ranking))  # the settings whose every frame rendered
    names = {r["setting"] for r in whole}
    for b, name, v in budget_verdicts(whole, [r for r in rows if r["setting"] in names]):
        print(f"  {b:4g} px  {name:>9}  " + ("no setting meets it" if v is None else
              f"{v.winner:>18}  {v.cost:9.4g} ms  bound {v.bound or '-':>6}  robust "
              + ("yes" if v.robust else f"no ({v.flip})")))
    print("wrote: " + ", ".join(str(p) for p in paths))
    if failed:
        print(f"terrainwarp: {len(failed)} of {len(rows)} frames failed (frames.csv has their errors); a rerun into "
              f"{args.out} runs them again", file=sys.stderr)
    return 1 if failed else 0


def _budget_defaults(args: argparse.Namespace, sc: Scene, keys: tuple[str, ...], fallback: dict) -> None:
    """The ``[budget]`` keys a flag leaves out, from the scene (else ``fallback``); a flag that overrides one the
    file sets says so. Sets ``args.budget_px``, ``args.max_pop_px``, ``args.cost`` (those in ``keys``)."""
    b = sc.budget
    given = {"budget_px": args.budget_px, "max_pop_px": getattr(args, "max_pop_px", None), "cost": args.cost}
    scene = {} if b is None else {"budget_px": b.budget_px, "max_pop_px": b.max_pop_px,
                                  "cost": b.cost if isinstance(b.cost, str) else ",".join(b.cost)}
    _note_overrides(args, [("--" + k.replace("_", "-"), given[k], "budget", k, scene.get(k)) for k in keys])
    for k in keys:
        v = given[k] if given[k] is not None else scene.get(k, fallback.get(k))
        if v is None and k == "budget_px":
            raise ValueError("--budget-px: expected the p99 budget in pixels (or a [budget] budget_px in the scene)")
        setattr(args, k, v)


def _cost_spec(text: str) -> str | list[str]:
    """``--cost``: one cost, or several separated by commas (the worst of them per frame)."""
    parts = [p.strip() for p in text.split(",") if p.strip()]
    return parts if len(parts) > 1 else text


def _sweep_model(c: Cost) -> CostModel | None:
    """The linear model a sweep writes as each row's ``cost_ms`` (None: the shipped one); other costs (GPU
    profiles, lists) price the rows afterwards."""
    return c.model if isinstance(c.model, CostModel) else None


def _runner(scheduler: str | None, workers: int | None, say) -> Runner:
    """The sweep's runner, each slow step said first: the kernels compiled here (so no worker compiles them),
    then the worker processes started or the scheduler reached."""
    _warmup(say)
    if scheduler is not None:
        say(f"connecting to the Dask scheduler at {scheduler}")
    elif workers != 0:
        n = workers or default_threads()
        say(f"starting {n} worker process{'es' if n > 1 else ''} (dask LocalCluster; a few seconds)")
    t0 = time.perf_counter()
    runner = Runner(scheduler, workers)
    if runner.where != "in-process":
        say(f"workers ready in {time.perf_counter() - t0:.1f} s")
    return runner


def _warmup(say) -> None:
    """The kernel modules missing from the cache compiled now, a line each (none when all are cached, or with
    ``--no-progress``)."""
    warmup(progress=say is not _quiet)


def sweep_evaluator(scene: Scene, cameras: list[Camera], policy: str, workers: int | None = None,
                    scheduler: str | None = None, device: str = "cpu", cost_of: Cost | None = None):
    """A grid-search evaluator (:func:`terrainwarp.fit.grid_search`) that runs the evaluations as jobs of the
    sweep runner (:func:`terrainwarp.experiments.pareto.sweep`, dask.distributed): ``workers`` local worker
    processes (None: one per core) or an existing ``scheduler``; the workers prepare their own terrain and
    references, and the table is the same as in-process. ``cost_of``: the fit's cost (None: triangles)."""
    knob = main_knob(policy, scene.heightmap, None if scene.lod.is_scheme else scene.lod).name

    def run(values: list[float]) -> list[Evaluation]:
        rows = sweep(scene, cameras, [Setting(policy, v) for v in values], progress=False, images=False,
                     device=device, scheduler=scheduler, workers=workers,
                     cost_model=None if cost_of is None else _sweep_model(cost_of))
        return evaluations_from_rows(rows, policy, values, knob, None if cost_of is None or cost_of.name == "triangles"
                                     else cost_of)

    return run


def _cmd_fit(args: argparse.Namespace) -> int:
    given = _scene(args)
    sc = _whole(given, "fit")
    _path_overrides(args, sc)
    _note_overrides(args, [("--policy", args.policy, "lod", "policy", sc.lod.policy)])
    args.policy = args.policy or sc.lod.policy  # the scene's [lod] policy unless --policy says otherwise
    _budget_defaults(args, sc, ("budget_px", "max_pop_px", "cost"), {"cost": "triangles"})
    cams = sc.camera_path(args.frames, preset=args.path)
    path = sc.path_info(args.frames, preset=args.path)
    spec = _cost_spec(args.cost)
    fit_cost = cost(spec)  # checked before the fit runs
    check_knob_names(args.policy, sc.heightmap, args.knobs, None if sc.lod.is_scheme else sc.lod)
    say = _sayer(args)
    grid_evaluator = None if args.workers == 0 else sweep_evaluator(sc, cams, args.policy, args.workers,
                                                                    cost_of=fit_cost)
    _warmup(say)
    if grid_evaluator is not None and args.grid_points:
        _runner(None, args.workers, say).close()  # the grid search's workers, started now; its sweeps reuse them
    refs = _references(sc, cams, say)  # shared by the fit, its curve and the baselines
    res = fit_lod(sc, args.budget_px, policy=args.policy, cameras=cams, knobs=args.knobs,
                  grid_points=args.grid_points, grid_evaluator=grid_evaluator, progress=not args.no_progress,
                  max_pop_px=args.max_pop_px, cost=spec, references=refs, floor=True)  # (named: fitted.toml's cost)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    curve = []
    if args.curve_budgets:
        say(f"fitting {len(args.curve_budgets)} more budget(s) for the cost-against-budget curve")
    for b in args.curve_budgets:
        r = fit_lod(sc, b, policy=args.policy, cameras=cams, knobs=args.knobs, progress=not args.no_progress,
                    max_pop_px=args.max_pop_px, cost=spec, references=refs)
        if r.met:
            curve.append((b, r.validated.cost))
    if args.baselines:
        say(f"running the baselines {', '.join(args.baselines)} on the same frames")
    runs = run_baselines(sc, args.policy, args.knobs, cams, refs, args.budget_px, args.baselines,
                         max_pop_px=args.max_pop_px, cost=fit_cost, trials=args.trials)
    doc, timing = split_timings({**res.to_dict(), "path": {k: v for k, v in path.items() if k != "waypoints_m"},
                                 "baselines": runs})
    write_json(out / "fit.json", doc)
    plot_fit(res, out / "fit.png", sorted([*curve, (args.budget_px, res.validated.cost)]) if curve and res.met
             else None)
    res.scene.with_(heightmap=given.heightmap).save(out / "fitted.toml")  # streamed as the scene file said
    if runs:
        plot_convergence({"fit_lod": res.trace, **{m: r["trace"] for m, r in runs.items()}}, out / "convergence.png",
                         title=f"{args.policy} at {args.budget_px:g} px", cost_label=res.cost)
    write_text(out / "report.md", "\n".join(_fit_report_lines(args, res, path, len(cams), runs)))
    write_json(out / "timing.json", timing)
    write_text(out / "timing.md", "\n".join(_fit_timing_lines(args, res, runs)))
    print(f"path: {path['text']}")
    print(res.message)
    print(res.timing_line())
    written = [*FIT_FILES, *(["convergence.png"] if runs else [])]
    print("wrote: " + ", ".join(str(out / w) for w in written))
    return 0 if res.met else 1


def _references(sc: Scene, cams: list[Camera], say) -> list:
    """The full-resolution reference frame of each camera, said first, and a line every quarter of them."""
    done = [0]
    say(f"rendering the full-resolution reference frame of each of {len(cams)} cameras")

    def tick() -> None:
        done[0] += 1
        if done[0] < len(cams) and done[0] % max(1, len(cams) // 4) == 0:
            say(f"  references: {done[0]}/{len(cams)}")

    return references_for(sc, cams, on_frame=tick)


def _fit_report_lines(args: argparse.Namespace, res: FitResult, path: dict, n_cams: int,
                      runs: dict | None = None) -> list[str]:
    """The fit's report.md: the path, the fit against the grid search and the baselines, the primary, image and
    pop errors."""
    v, g = res.validated, res.grid
    pop = "" if args.max_pop_px is None else f", worst pair pop p99 <= {args.max_pop_px:g} px"
    shown = ", ".join(f"{k} = {res.values[k]:.4g}" for k in res.knobs)
    lines = ["# Fit", "", f"policy {args.policy}, budget {args.budget_px:g} px{pop}, {n_cams} cameras", "",
             f"Knobs fitted: {', '.join(res.knobs)}; the fitted scene is fitted.toml.", "",
             f"Camera path: {path['text']}.", "",
             "Error: the primary error (per visible heightmap sample, px; no triangulation floor). Beside it, "
             "the per-pixel grid-image error of the chosen setting (secondary; it carries a triangulation floor) "
             f"worst frame {max(v.image_p99_px, default=float('nan')):.3g} px"
             + ("" if not v.pop_p99_px else f"; popping: the worst consecutive pair's pop p99 {v.worst_pop:.3g} px, "
                f"max over pairs of the pop p99 (the previous camera's selection held)") + ".", "",
             f"| method | value | worst p99 px | {res.cost}/frame | pipeline evaluations |",
             "|---|---|---|---|---|",
             f"| fit | {shown} | {v.worst_p99:.3g} | {v.cost:.4g} | {res.evaluations} |"]
    for name, r in (runs or {}).items():
        best = "none met the budget" if r["values"] is None else ", ".join(f"{k} = {x:.4g}"
                                                                           for k, x in r["values"].items())
        lines.append(f"| {name} | {best} | {r['worst_p99_px']:.3g} | {r['cost']:.4g} | {r['frames']} |")
    if g:
        if g["value"] is None:
            lines.append(f"| grid search ({g['points']} points) | none met the budget | | | {g['evaluations']} |")
        else:
            lines.append(f"| grid search ({g['points']} points) | {g['value']:.4g} | {g['worst_p99_px']:.3g} | "
                         f"{g['cost']:.4g} | {g['evaluations']} |")
    lines += ["", res.message, "", f"Pixels are at the fitted viewport: {_knob_words(res.scene, res.budget_px)}"
              + ("" if len(res.viewports) < 2 else f"; the setting is fitted on {len(res.viewports)} viewports: "
                 + ", ".join(vp.text for vp in res.viewports)) + ". Another viewport: terrainwarp export "
              "fitted.toml --as json --viewport WxH@FOV (terrainwarp.fit.rescale).", "",
              *(_frame_table(v, res.image_floor_p99_px, res.sparse) if v is not None and v.complete else []),
              "This run's wall times: [timing.md](timing.md).", ""]
    if res.mesh_only_frames:
        lines += [f"Frames only selected and meshed for their triangle count (not in the evaluations): "
                  f"{res.mesh_only_frames}. A try measures its critical cameras worst first and stops at the first "
                  "over the budget; the fitted value is measured on every camera.", ""]
    return lines


def _fit_timing_lines(args: argparse.Namespace, res: FitResult, runs: dict | None) -> list[str]:
    """The fit's timing.md: each method's wall time and the validated frames' CPU ms (they differ run to run;
    timing.json holds the same numbers)."""
    lines = ["# This run's timings", "", f"policy {args.policy}, budget {args.budget_px:g} px: wall seconds of this "
             "simulator, not a GPU's (they differ from run to run and machine to machine).", "",
             res.timing_line() + ".", "",
             "| method | wall s |", "|---|---|", f"| fit | {res.wall_s:.1f} (relaxed model {res.model_s:.1f}) |"]
    lines += [f"| {name} | {r['wall_s']:.1f} |" for name, r in (runs or {}).items()]
    if res.grid:
        lines.append(f"| grid search ({res.grid['points']} points) | {res.grid['wall_s']:.1f} |")
    if res.validated is not None:
        lines += ["", "Validated frames, CPU ms: " + ", ".join(f"{t:.1f}" for t in res.validated.frame_ms)]
    return [*lines, ""]


def split_timings(doc: object) -> tuple[object, object]:
    """(``doc`` without its wall times, the wall times): every key ending in ``_s`` or ``_ms`` (seconds and
    milliseconds measured on this machine), and ``timings`` (a fit's wall time by part), moves to the second, at
    the same place in the tree; what is left is the same on every run."""
    if isinstance(doc, dict):
        kept, moved = {}, {}
        for k, v in doc.items():
            if str(k).endswith(("_s", "_ms")) or k == "timings":
                moved[k] = v
                continue
            kept[k], t = split_timings(v)
            if t not in (None, {}, []):
                moved[k] = t
        return kept, moved
    if isinstance(doc, list) and any(isinstance(v, dict) for v in doc):
        pairs = [split_timings(v) for v in doc]
        return [p[0] for p in pairs], ([p[1] for p in pairs] if any(p[1] for p in pairs) else None)
    return doc, None


def _cmd_evaluate(args: argparse.Namespace) -> int:
    sc = _scene(args)
    cams = sc.camera_path(args.frames) if args.frames is not None else None
    a = assess(sc, budget_px=args.budget_px, max_pop_px=args.max_pop_px, cost=args.cost, cameras=cams,
               floor=not args.no_floor)
    out = Path(args.out)
    doc = {**a.to_dict(), "scene": args.scene, "path": sc.path_info(args.frames)["text"],
           "pixel_knobs": pixel_knobs(sc, a.budget_px)}
    doc, timing = split_timings(doc)  # the frames' CPU ms: timing.json, so evaluate.json is the same every run
    write_json(out / "evaluate.json", doc)
    write_json(out / "timing.json", timing)
    write_text(out / "report.md", "\n".join(_evaluate_report_lines(sc, a, doc["path"])))
    print(f"path: {doc['path']}")
    print(a.message)
    print("wrote: " + ", ".join(str(out / w) for w in ("evaluate.json", "timing.json", "report.md")))
    return 0 if a.met else 1


def _evaluate_report_lines(sc: Scene, a, path: str) -> list[str]:
    """evaluate's report.md: the verdict, then one row per camera (the image error beside its floor)."""
    v = a.evaluation
    lines = ["# Evaluate", "", f"Setting: policy {sc.lod.policy} ({_knob_words(sc, a.budget_px)}).", "",
             f"Camera path: {path}.", "", a.message, "", *_frame_table(v, a.image_floor_p99_px, a.sparse)]
    return lines


def _knob_words(sc: Scene, budget_px: float) -> str:
    """Each pixel knob at the scene's viewport and as an angle."""
    vp = sc.pixel_viewport
    words = [f"{n} = {d['px']:.4g} px = {d['mrad']:.4g} mrad" for n, d in pixel_knobs(sc, budget_px).items()]
    return "; ".join(words) + f" at {vp.text} ({vp.focal_px:.1f} px per radian)"


def _frame_table(v: Evaluation, floor: list[float], sparse: list[dict]) -> list[str]:
    """Per camera: the primary p99, the image p99 beside the family's full-detail floor, the samples, a flag."""
    flagged = {s["camera"]: s["why"] for s in sparse}
    rows = ["| camera | p99 px | image p99 px (floor) | visible samples | covered px | triangles | note |",
            "|---|---|---|---|---|---|---|"]
    for k, p in enumerate(v.p99_px):
        img = v.image_p99_px[k] if k < len(v.image_p99_px) else float("nan")
        fl = f" ({floor[k]:.3g})" if k < len(floor) else ""
        vis = v.visible[k] if k < len(v.visible) else ""
        cov = v.covered[k] if k < len(v.covered) else ""
        note = f"too few samples for a p99: {flagged[k]}" if k in flagged else ""
        rows.append(f"| {k} | {p:.3g} | {img:.3g}{fl} | {vis} | {cov} | {v.triangles[k]} | {note} |")
    return rows + ["", "The image error is measured against the fixed-diagonal full-resolution grid; beside it, in "
                       "brackets, the same family's full-detail frame's (its triangulation floor): only the "
                       "difference is the setting's.", ""]


def _viewport_arg(text: str) -> tuple[int, int, float | None]:
    """``WxH`` or ``WxH@FOV`` (fov_y in degrees)."""
    size, _, fov = text.partition("@")
    w, _, h = size.lower().partition("x")
    try:
        return int(w), int(h), (float(fov) if fov else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT or WIDTHxHEIGHT@FOV_Y_DEG, got {text!r}") from None


def _cmd_export(args: argparse.Namespace) -> int:
    sc = _scene(args)
    out = Path(args.out)
    written = []
    stem = Path(args.scene).stem if args.scene else sc.name
    if args.viewport is not None:
        w, h, fov = args.viewport
        r = rescale(sc, w, h, sc.pixel_viewport.fov_y_deg if fov is None else fov, budget_px=args.budget_px,
                    confirm=not args.no_confirm)
        print(f"rescale ({r.action}): {r.message}")
        print(f"rule: {r.rule}")
        sc = r.scene
        stem = f"{stem}-{w}x{h}"
        written.append(sc.save(out / f"{stem}.toml"))
    written.append(export(sc, args.as_, out / f"{stem}.{args.as_}.json"))
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def _cmd_stability(args: argparse.Namespace) -> int:
    n = 129 if args.full else 33
    cases = [c for c in args.cases.split(",") if c] if args.cases else None
    bad = [c for c in cases or [] if c not in EXTREME_CASES]
    if bad:
        raise ValueError(f"--cases: unknown {bad}; expected some of {list(EXTREME_CASES)}")
    say = _sayer(args)
    _warmup(say)
    say(f"running {len(cases or EXTREME_CASES)} extreme cases through every stage on {n} x {n} grids")
    rows = run_suite(n, cases=cases, progress=not args.no_progress)
    cmd = "terrainwarp stability --out DIR" + (" --full" if args.full else "")
    path = write_stability_md(rows, args.out, command=cmd, n=n)
    counts = {}
    for r in rows:
        counts[r.status] = counts.get(r.status, 0) + 1
    print(", ".join(f"{v} {k}" for k, v in counts.items()))
    print(f"wrote: {path}")
    unexplained = [r for r in rows if r.status == FAIL and not any(k in r.note for k in EXPLANATIONS)]
    for r in unexplained:
        print(f"FAIL {r.case}/{r.stage}: {r.note}", file=sys.stderr)
    return 1 if unexplained else 0


def _cmd_tessellate(args: argparse.Namespace) -> int:
    out = Path(args.out)
    doc = tessellation_json(args.outer, args.inner, args.spacing)
    paths = [write_tessellation_picture(out / "tessellation.png", args.outer, args.inner, args.spacing),
             write_json(out / "tessellation.json", doc)]
    levels = lambda a: "[" + ", ".join("nan" if x is None else f"{x:g}" for x in a) + "]"  # noqa: E731
    print(f"{doc['spacing']}: outer {levels(doc['outer'])}, inner {levels(doc['inner'])}: {doc['n_points']} "
          f"points, {doc['n_triangles']} triangles" + ("" if doc["n_triangles"] else " (patch discarded)"))
    print("wrote: " + ", ".join(str(p) for p in paths))
    return 0


# ------------------------------------------------------------------------------------------------
# warmup
# ------------------------------------------------------------------------------------------------
def _cmd_warmup(args: argparse.Namespace) -> int:
    try:
        res = warmup(args.device, workers=args.workers)
    except (TypeError, ValueError) as e:  # name the option: "device: ..." -> "--device: ..."
        raise type(e)(f"--{e}" if str(e).startswith(("device:", "workers:")) else str(e)) from None
    if res.compiled:
        print(f"compiled {len(res.compiled)} kernel modules in {res.seconds:.1f} s "
              f"({res.workers or 'no'} worker processes); {len(res.cached)} were cached; cache: {res.cache_dir}")
    else:
        print(f"all {len(res.cached)} kernel modules are compiled; cache: {res.cache_dir}")
    return 0


# ------------------------------------------------------------------------------------------------
# bench
# ------------------------------------------------------------------------------------------------
BENCHMARKS_DIR = Path(__file__).resolve().parents[1] / "benchmarks"  # a source checkout's benchmarks/


def _benchmarks() -> dict[str, Path]:
    """The benchmarks by name (``bench_<name>.py`` in ``BENCHMARKS_DIR``); ValueError when there are none."""
    found = {b.stem.removeprefix("bench_"): b for b in sorted(BENCHMARKS_DIR.glob("bench_*.py"))}
    if not (BENCHMARKS_DIR / "run_all.py").is_file() or not found:
        raise ValueError(f"bench: no benchmarks at {BENCHMARKS_DIR} (an installed wheel has none; run "
                         f"'terrainwarp bench' from a source checkout)")
    return found


def _cmd_bench(args: argparse.Namespace) -> int:
    found = _benchmarks()
    if args.list:
        print("\n".join(found))
        return 0
    unknown = [n for n in args.names if n not in found]
    if unknown:
        raise ValueError(f"bench: unknown benchmark(s) {unknown}; expected some of {list(found)}")
    root = BENCHMARKS_DIR.parent
    if not args.names:  # all of them, then BENCHMARKS.md: benchmarks/run_all.py
        return subprocess.run([sys.executable, str(BENCHMARKS_DIR / "run_all.py")], cwd=root).returncode
    rc = 0
    for n in dict.fromkeys(args.names):
        print(f"== {found[n].name}", flush=True)
        rc = rc or subprocess.run([sys.executable, str(found[n])], cwd=root).returncode
    subprocess.run([sys.executable, str(BENCHMARKS_DIR / "collect.py")], cwd=root)
    return rc


# ------------------------------------------------------------------------------------------------
# the parser
# ------------------------------------------------------------------------------------------------
class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default, except where there is none to show (None, a flag)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or action.default is False or action.default is argparse.SUPPRESS \
                or action.default == [] or not action.help:
            return action.help or ""
        return super()._get_help_string(action)


def _command(sub, name: str, help: str, func) -> _Parser:
    c = sub.add_parser(name, help=help, description=help[:1].upper() + help[1:] + ".", formatter_class=_Help)
    c.set_defaults(func=func)
    _add_plugin(c)  # also after the command; the plugins run before parsing (main)
    return c


def _add_scene(c: argparse.ArgumentParser, out: str, viewport: bool = True) -> None:
    c.add_argument("scene", nargs="?", default=None, help="scene TOML file (default: the demo scene)")
    _add_out(c, out)
    if viewport:
        _add_viewport(c)


def _add_out(c: argparse.ArgumentParser, out: str) -> None:
    c.add_argument("--out", default=out, metavar="DIR", help="output folder (created if missing)")


def _add_viewport(c: argparse.ArgumentParser) -> None:
    c.add_argument("--width", type=_positive_int, default=None, help="viewport width in pixels (default: the "
                   "scene camera's)")
    c.add_argument("--height", type=_positive_int, default=None, help="viewport height in pixels (default: the "
                   "scene camera's)")


def _add_demo_render_lod(sub) -> None:
    d = _command(sub, "demo", "render the bundled real DEM (frame.png, depth.exr, report.json)", _cmd_render)
    _add_out(d, "out/demo")
    _add_viewport(d)
    d.set_defaults(scene=None)
    _add_scene(_command(sub, "render", "render a scene file (the outputs its [render] table asks for, and "
                        "report.json)", _cmd_render), "out/render")
    lo = _command(sub, "lod", "select LOD patches: top-down picture (lod.png) and table (patches.csv)", _cmd_lod)
    _add_scene(lo, "out/lod")
    lo.add_argument("--policy", choices=[*LOD_POLICIES, *SCHEMES], default=None,
                    help=f"LOD policy or scheme (default: the scene's [lod] policy, else {_LOD.policy})")
    for spec in POLICY_TABLE.values():  # --tolerance-px, --k, --target-px
        lo.add_argument("--" + spec.field.replace("_", "-"), type=_positive_float, default=None,
                        help=f"{spec.help} (policy {spec.name}; default: the scene's, else "
                             f"{getattr(_LOD, spec.field)})")
    lo.add_argument("--level", type=_nonnegative_int, default=None,
                    help=f"continuous: the level of the uniform patch grid (default: the scene's, else {_LOD.level})")
    lo.add_argument("--hysteresis", type=float, default=None,
                    help="band in [0, 1) between the split and merge thresholds (default: the scene's, else "
                         f"{_LOD.hysteresis})")
    lo.add_argument("--roots", type=_positive_int, default=None,
                    help=f"root nodes of the quadtree (default: the scene's, else {_LOD.roots})")
    lo.add_argument("--tess", type=_tess_level, default=None,
                    help=f"tessellation level of every patch: a power of two in 1..{QUADTREE_TESS[-1]} for a "
                         f"quadtree policy, 1..{MAX_TESS} for continuous (default: the scene's, else {_LOD.tess})")


def _add_path(c: argparse.ArgumentParser) -> None:
    c.add_argument("--path", choices=list(PATH_PRESETS), default=None,
                   help="camera path clearance: ground (2%% of the extent) or high (10%%) (default: the scene's "
                        "[path] preset or clearance, else ground)")


def _nonnegative_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (v >= 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {s}")
    return v


def _add_report_fit(sub) -> None:
    rp = _command(sub, "report", "sweep LOD settings and peers over the camera path: frames.csv, pareto.png, "
                  "report.md", _cmd_report)
    _add_scene(rp, "out/report")
    rp.add_argument("--frames", type=_positive_int, default=None, help="cameras on the path (default: the "
                    "scene's [path] n, or 8)")
    rp.add_argument("--policies", default=None,
                    help="comma-separated subset of grid,sse,distance,continuous,martini,delatin,polytree,bintree "
                         "and the schemes " + ",".join(SCHEMES) + " (default: all)")
    _add_path(rp)
    rp.add_argument("--quick", action="store_true", help="two settings per policy")
    rp.add_argument("--no-images", action="store_true", help="skip shading (no PSNR/SSIM)")
    rp.add_argument("--no-progress", action="store_true", help="no progress bar")
    rp.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="run the jobs on this Dask scheduler's cluster (default: a local cluster)")
    rp.add_argument("--workers", type=_nonnegative_int, default=None,
                    help="local worker processes (default: one per core; 0: in this process)")
    rp.add_argument("--cost", default=None, metavar="COST",
                    help="what the report ranks by: llvmpipe (the shipped cost model, modelled ms), a GPU profile "
                         "(gpu:gf100, gpu:gcn, gpu:rdna, gpu:mali, gpu:nv40 or gpu:FILE.toml), several of them "
                         "separated by commas (the worst per frame), triangles, a counter name (e.g. "
                         "fragment_shader_invocations) or a weights file of terrainwarp calibrate (default: the "
                         "scene's [budget] cost, else llvmpipe)")
    ft = _command(sub, "fit", f"fit LOD thresholds to a screen-space error budget: {', '.join(FIT_FILES)} "
                  "(and convergence.png with --baselines)", _cmd_fit)
    _add_scene(ft, "out/fit")
    ft.add_argument("--budget-px", type=_positive_float, default=None,
                    help="p99 screen error budget, pixels (default: the scene's [budget] budget_px; one is needed)")
    ft.add_argument("--policy", choices=[*LOD_POLICIES, *SCHEMES], default=None,
                    help="LOD policy or registered scheme to fit (default: the scene's [lod] policy, else sse)")
    ft.add_argument("--frames", type=_positive_int, default=None, help="cameras on the path (default: the "
                    "scene's [path] n, or 8)")
    _add_path(ft)
    ft.add_argument("--max-pop-px", type=_nonnegative_float, default=None, metavar="PX",
                    help="also bound the worst consecutive pair's pop p99, pixels (default: the scene's [budget] "
                         "max_pop_px, else no bound)")
    ft.add_argument("--grid-points", type=_nonnegative_int, default=0,
                    help="also run a grid search baseline with N points (0: none)")
    ft.add_argument("--workers", type=_nonnegative_int, default=0,
                    help="grid search on the sweep runner with N worker processes (0: in this process)")
    ft.add_argument("--curve-budgets", type=_positive_float, nargs="*", default=[], metavar="PX",
                    help="also fit these budgets for the cost-against-budget curve")
    ft.add_argument("--cost", default=None, metavar="COST",
                    help="what the fit minimises: triangles, a counter name, llvmpipe (the shipped cost model), a "
                         "GPU profile (gpu:gf100, ..., gpu:FILE.toml), several models separated by commas (the worst "
                         "per frame: one setting for every GPU listed) or a weights file of terrainwarp calibrate "
                         "(default: the scene's [budget] cost, else triangles)")
    ft.add_argument("--knobs", type=_knob_list, default=None, metavar="A,B,C|all",
                    help="the knobs to fit together (terrainwarp.fit.knobs; default: the policy's main knob alone)")
    ft.add_argument("--baselines", type=_baseline_list, default=[], metavar="M,N",
                    help=f"also run these tuners on the same exact evaluation ({','.join(BASELINES)}; the black-box "
                         "ones need the extra 'tune'), for convergence.png")
    ft.add_argument("--trials", type=_positive_int, default=150, help="settings each black-box tuner tries")
    ft.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_evaluate_export(sub) -> None:
    ev = _command(sub, "evaluate", "measure a saved setting over its camera path without fitting: error, cost and "
                  "verdict (evaluate.json, report.md); exit 1 when it misses the budget", _cmd_evaluate)
    _add_scene(ev, "out/evaluate", viewport=False)
    ev.add_argument("--budget-px", type=_positive_float, default=None,
                    help="p99 screen error budget, pixels (default: the scene's [budget])")
    ev.add_argument("--max-pop-px", type=_nonnegative_float, default=None, metavar="PX",
                    help="also bound the worst pair's pop p99 (default: the scene's [budget])")
    ev.add_argument("--cost", default=None, metavar="COST", help="the cost to report (default: the scene's [budget] "
                    "cost, else triangles)")
    ev.add_argument("--frames", type=_positive_int, default=None,
                    help="cameras of the path (default: all; a recorded path: that many, evenly spaced)")
    ev.add_argument("--no-floor", action="store_true", help="skip the family's full-detail image floor (one frame "
                    "per camera)")
    ex = _command(sub, "export", "write a LOD setting as the engine takes it: CDLOD's level count, leaf size, grid "
                  "and per-level ranges and morphs, Cesium's maximumScreenSpaceError, or the whole setting as JSON",
                  _cmd_export)
    _add_scene(ex, "out/export", viewport=False)
    ex.add_argument("--as", dest="as_", choices=list(FORMATS), required=True, help="the engine's terms")
    ex.add_argument("--viewport", type=_viewport_arg, default=None, metavar="WxH[@FOV]",
                    help="rescale to this viewport first (terrainwarp.fit.rescale: confirmed on exact frames at it), "
                         "and write the rescaled scene beside the export (default: the scene's viewport)")
    ex.add_argument("--budget-px", type=_positive_float, default=None,
                    help="with --viewport: the budget to confirm (default: the scene's [budget])")
    ex.add_argument("--no-confirm", action="store_true", help="with --viewport: the rule alone, no exact frames")


def _knob_list(text: str) -> list[str] | str:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError("expected knob names separated by commas, or all")
    return "all" if names == ["all"] else names


def _baseline_list(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in BASELINES]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"expected some of {','.join(BASELINES)}, got {text!r}")
    return names


def _add_calibrate(sub) -> None:
    c = _command(sub, "calibrate", "fit the cost model's weights to a real driver's frame times: weights.json, "
                 "calibration.csv, calibration.md", _cmd_calibrate)
    c.add_argument("--gl", action="store_true", help="measure the OpenGL driver EGL finds (Mesa's llvmpipe here; a "
                   "GPU's where there is one): the only driver kind so far, required")
    _add_out(c, "out/calibrate")
    c.add_argument("--frames-per-family", type=lambda s: _int_at_least(s, 2), default=50, metavar="N",
                   help="frames of every family")
    c.add_argument("--seed", type=_nonnegative_int, default=0, help="seed of the frames' choice and the held-out split")
    c.add_argument("--reps", type=_positive_int, default=3, help="timed draws per frame (the least counts)")
    c.add_argument("--families", default=None, help="comma-separated subset of " + ",".join(CALIBRATION_FAMILIES)
                   + " (default: all)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")


def _cmd_calibrate(args: argparse.Namespace) -> int:
    if not args.gl:
        raise ValueError("--gl: calibrate measures a driver through OpenGL; give --gl")
    fams = tuple(args.families.split(",")) if args.families else CALIBRATION_FAMILIES
    os.environ.setdefault("LP_NUM_THREADS", "0")  # llvmpipe on one thread (read when its first context is made)
    command = (f"terrainwarp calibrate --gl --out {args.out} --frames-per-family {args.frames_per_family} --seed "
               f"{args.seed} --reps {args.reps}" + (f" --families {args.families}" if args.families else ""))
    model, paths = calibrate(args.out, frames_per_family=args.frames_per_family, seed=args.seed, reps=args.reps,
                             families=fams, progress=not args.no_progress, command=command)
    print(model.describe())
    print("wrote: " + ", ".join(str(p) for p in paths))
    print(f"use it: terrainwarp report --cost {paths[0]}")
    return 0


def _add_stability_tessellate_bench(sub) -> None:
    st = _command(sub, "stability", "run the extreme-case stability suite through every stage: stability.md",
                  _cmd_stability)
    st.add_argument("--out", required=True, metavar="DIR", help="output folder for stability.md")
    st.add_argument("--full", action="store_true", help="129 x 129 grids instead of 33 x 33")
    st.add_argument("--cases", default=None, help="comma-separated subset of terrainwarp.experiments.extreme.CASES "
                    "(default: all)")
    st.add_argument("--no-progress", action="store_true", help="no progress bar")
    te = _command(sub, "tessellate", "one quad patch through the GPU tessellator: tessellation.png and "
                  "tessellation.json (points and triangles)", _cmd_tessellate)
    te.add_argument("--outer", type=float, nargs=4, required=True, metavar="L",
                    help="4 outer levels: u=0, v=0, u=1, v=1 edges (gl_TessLevelOuter order)")
    te.add_argument("--inner", type=float, nargs=2, required=True, metavar="L", help="2 inner levels: along u, v")
    te.add_argument("--spacing", choices=list(SPACINGS), default=SPACINGS[0], help="tessellation spacing")
    _add_out(te, "out/tessellate")
    w = _command(sub, "warmup", "compile every kernel module missing from Warp's kernel cache now (what a first "
                 "run does by itself), one line per module", _cmd_warmup)
    w.add_argument("--device", default="cpu", help="the Warp device to compile for (cpu, cuda:0, ...)")
    w.add_argument("--workers", type=_nonnegative_int, default=None,
                   help="worker processes (default: one per usable core; 0: in this process)")
    b = _command(sub, "bench", "run the benchmarks of benchmarks/ (all, then BENCHMARKS.md, or those named); "
                 "a source checkout only", _cmd_bench)
    b.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run, e.g. lod frame (default: all)")
    b.add_argument("--list", action="store_true", help="list the benchmarks' names and exit")


def _add_plugin(c: argparse.ArgumentParser) -> None:
    c.add_argument("--plugin", action="append", default=None, metavar="FILE.py|MODULE",
                   help="run this plugin first (repeatable): the LOD schemes it registers become policy names")


def build_parser() -> argparse.ArgumentParser:
    """The ``terrainwarp`` parser; its scheme names are those registered when it is built (:func:`main` runs the
    ``--plugin`` files first)."""
    p = _Parser(prog="terrainwarp", description="A deterministic CPU simulator of the GPU terrain pipeline.",
                epilog="'terrainwarp COMMAND --help' shows a command's options.")
    p.add_argument("--version", action="version", version=f"terrainwarp {__version__}")
    _add_plugin(p)
    sub = p.add_subparsers(dest="cmd", required=True, parser_class=_Parser, metavar="COMMAND")
    _add_demo_render_lod(sub)
    _add_report_fit(sub)
    _add_evaluate_export(sub)
    _add_calibrate(sub)
    _add_stability_tessellate_bench(sub)
    return p


# ------------------------------------------------------------------------------------------------
# main: one line and exit 2 on bad input, and --out left as it was found
# ------------------------------------------------------------------------------------------------
def _run_plugins(argv: list[str]) -> None:
    """Run the ``--plugin`` files and modules of ``argv`` (before the parser is built: what they register are
    choices of its options); ValueError with the plugin's error."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--plugin", action="append", default=[])
    for plugin in pre.parse_known_args(argv)[0].plugin:
        load_plugin(plugin)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        _run_plugins(argv)
    except ValueError as e:
        print(f"terrainwarp: error: --plugin: {_one_line(e).removeprefix('plugin: ')}", file=sys.stderr)
        return 2
    parser = build_parser()
    if not argv:  # bare `terrainwarp`: the usage and the commands, on stderr, exit 2 (as for a missing argument)
        parser.print_help(sys.stderr)
        return 2
    args = parser.parse_args(argv)
    configure_from_env()  # quiet Warp, kept frame memory: what a command run wants (import alone sets nothing)
    with _signals_interrupt(), _warnings_one_line():
        return _run(args)


_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextlib.contextmanager
def _signals_interrupt():
    """SIGINT, SIGTERM and SIGHUP raise :class:`terrainwarp.io.files.Interrupted` (a KeyboardInterrupt) for the
    command's run, held back while an output set is switched; the handlers before are restored after."""
    before = {}
    try:
        for s in _SIGNALS:
            before[s] = signal.signal(s, interrupt_handler)
    except ValueError:  # not the main thread: signals stay as they are
        pass
    try:
        yield
    finally:
        for s, h in before.items():
            signal.signal(s, h)


@contextlib.contextmanager
def _warnings_one_line():
    """terrainwarp's warnings (:class:`terrainwarp.camera.DepthPrecisionWarning`...) as one line each on stderr,
    ``terrainwarp: warning: ...``, each text once (a path's cameras may repeat it)."""
    seen: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = str(message).splitlines()[0] if str(message) else category.__name__
        if text not in seen:
            seen.add(text)
            print(f"terrainwarp: warning: {text}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("always", DepthPrecisionWarning)
        warnings.showwarning = show
        yield


def _run(args: argparse.Namespace) -> int:
    out = _OutDir(args.out) if getattr(args, "out", None) else None
    oset = None
    try:
        if out is not None:
            out.check()
        with (output_set(args.out) if out is not None else contextlib.nullcontext()) as oset, \
                warnings.catch_warnings():
            warnings.showwarning = _warning_line
            rc = int(args.func(args) or 0)
    except (ValueError, TypeError, OSError) as e:
        if out is not None:
            out.clean_up()
        print(f"terrainwarp: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        signum = getattr(e, "signum", signal.SIGINT)
        whole = oset is not None and oset.committed  # the signal came as the new set was switched: keep it
        if out is not None and not whole:
            out.clean_up()
        by = "" if signum == signal.SIGINT else f" by {signal.Signals(signum).name}"
        then = " after its files were written" if whole else ""
        print(f"terrainwarp: interrupted{by}{then}" + (f" (a rerun resumes from {out.journals()[0]})" if out is
                                                      not None and out.journals() and not whole else ""),
              file=sys.stderr)
        return 128 + int(signum)
    if out is not None:
        out.note_stale()
    return rc


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as one line on stderr, as the command's errors are (``terrainwarp: warning: ...``)."""
    print(f"terrainwarp: warning: {str(message).splitlines()[0] if str(message) else category.__name__}",
          file=sys.stderr)


def _one_line(e: BaseException) -> str:
    """The first line of the error that started it all: an OSError raised while cleaning up after another
    (a temporary file that cannot be removed from a read-only folder) hides the real one in its context."""
    while isinstance(e, OSError) and isinstance(e.__context__, OSError) and not e.__suppress_context__:
        e = e.__context__
    if isinstance(e, OSError) and e.strerror and e.filename:
        return f"{e.filename}: {e.strerror}"
    return str(e).splitlines()[0] if str(e) else type(e).__name__


class _OutDir:
    """``--out``: checked before the command runs (a folder, or a path whose nearest existing ancestor is a
    writable folder); on failure the files and folders the run created are removed again (nothing that was
    there before is touched); on success, the files that were there before and that the run did not write
    are named."""

    DEPTH = 2  # the commands write into --out and at most one folder below

    def __init__(self, out: str) -> None:
        self.path = Path(out)
        self.before: dict[Path, tuple[int, int, int]] | None = None
        self.dirs: set[Path] = set()
        self.anchor = self.path

    def check(self) -> None:
        p = self.path
        if p.exists() and not p.is_dir():
            raise ValueError(f"--out: {p} is a file, expected a folder")
        a = p
        while not a.exists() and a != a.parent:
            a = a.parent
        if not a.is_dir():
            raise ValueError(f"--out: {p} lies under the file {a}, expected a folder")
        if not os.access(a, os.W_OK | os.X_OK):
            raise ValueError(f"--out: cannot write in {a} (read-only or no permission)")
        self.anchor = a
        done = recover(p, self.DEPTH)  # a killed run's commit finished, its temporaries removed
        if done["committed"]:
            print(f"terrainwarp: note: finished the commit of an earlier run that was killed while switching its "
                  f"files in {p}: {', '.join(done['committed'][:5])}", file=sys.stderr)
        if done["removed"]:
            print(f"terrainwarp: note: removed {len(done['removed'])} temporary file(s) that a killed run left in "
                  f"{p}", file=sys.stderr)
        self.before = self._files()
        self.dirs = self._dirs()

    def _walk(self) -> list[Path]:
        if not self.path.is_dir():
            return []
        found, level = [], [self.path]
        for _ in range(self.DEPTH):
            level = [c for d in level for c in sorted(d.iterdir())]
            found += level
            level = [c for c in level if c.is_dir() and not c.is_symlink()]
        return found

    def _files(self) -> dict[Path, tuple[int, int, int]]:
        return {f: (st.st_ino, st.st_mtime_ns, st.st_size) for f in self._walk() if not f.is_dir()
                for st in (f.lstat(),)}

    def _dirs(self) -> set[Path]:
        ancestors = {self.path, *self.path.parents}
        return {d for d in [*self._walk(), *ancestors] if d.is_dir()}

    def journals(self) -> list[Path]:
        """A sweep's partial journals (``*.partial``) in ``--out``: what a rerun resumes from."""
        return [f for f in self._files() if f.name.endswith(".partial")]

    def clean_up(self) -> None:
        """Remove what a failed run created: new files, then new (empty) folders, ``--out`` itself included. A
        sweep's partial journal stays, so that a rerun resumes (the files the run would have replaced are as they
        were: the run's writes were an output set)."""
        if self.before is None:
            return
        for f in self._files():
            if f not in self.before and not f.name.endswith(".partial"):
                with contextlib.suppress(OSError):  # the one error to report is the command's
                    f.unlink()
        new_dirs = [d for d in [*self._walk(), self.path, *self.path.parents] if d.is_dir() and d not in self.dirs]
        for d in sorted(new_dirs, key=lambda d: len(d.parts), reverse=True):
            with contextlib.suppress(OSError):
                if not any(d.iterdir()):
                    d.rmdir()

    def note_stale(self) -> None:
        """Name the files in ``--out`` that were there before and that this run did not write."""
        if not self.before:
            return
        now = self._files()
        stale = sorted(str(f.relative_to(self.path)) for f, sig in self.before.items() if now.get(f) == sig)
        if stale:
            more = f" and {len(stale) - 5} more" if len(stale) > 5 else ""
            print(f"terrainwarp: note: {self.path} also holds {len(stale)} file(s) this run did not write (from an "
                  f"earlier run?): {', '.join(stale[:5])}{more}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())


