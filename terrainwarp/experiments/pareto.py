"""Error against run time: sweep LOD settings and peers over a camera path, measure every frame against
the full-resolution reference, and draw the Pareto front.

A sweep is a list of settings (policy, parameter) crossed with the scene's cameras. Every frame is
measured by ``render``'s error stage, with the full-resolution grid rendered once per camera: the primary
error ``p99_px``/``max_px``/``mean_px`` at the heightmap's samples (:mod:`terrainwarp.measure.sample_error`;
0 for every family's full-detail mesh), the per-pixel grid-image error as the secondary
``image_err_p99_px``/``image_err_max_px``/``image_err_mean_px`` (it carries a triangulation floor), see-through pixels,
coverage and PSNR/SSIM; and popping for the pair (frame - 1, frame): ``pop_p99_px``, ``pop_max_px``,
``popped_samples`` (samples moving by more than 0.5 px; NaN for frame 0), the selection of camera frame - 1
(held) against that of camera frame, both drawn for camera frame (:func:`terrainwarp.rendering.pipeline.pop_stats`;
stateless, as the frames are: no hysteresis).
Policies: ``grid`` (the full-resolution mesh), ``sse`` (screen-space-error tolerance, px), ``distance``
(k node sizes), ``continuous`` (target pixels per edge, fractional_odd), the peers ``martini`` and
``delatin`` (max error in metres; their view-independent meshing time is reported apart from render
time, and their measured vertical error beside the setting), and the other mesh families of the source
papers: ``polytree`` (taylor-barrett bottom-up merging; param = tolerance level of 64; built once) and
``bintree`` (mrbsp right-triangle bisection with the apparent-size LOD rule, hole fixing and forced
splits; param = tree depth M; selected per frame); and the schemes engines ship,
:data:`terrainwarp.schemes.SCHEMES` (``cdlod``: first range in metres; ``clipmaps``: ring size
n; ``chunked``: Cesium's maximum screen-space error in px; and any scheme registered since), selected per
frame, their pyramids built once per worker (reported as ``peer_mesh_ms``).

Every frame is made by :func:`terrainwarp.render`: the grid and the LOD policies from the scene, the
peers, polytree and bintree as prebuilt mesh sources (:mod:`terrainwarp.rendering.sources`). A row is
:func:`terrainwarp.rendering.rows.frame_row`'s (one schema: the report's stages, the error, the counters).

Cost: what a GPU would pay, from the frame's pipeline statistics (every frame counts them): ``cost_ms``, the
sweep's cost model (:class:`terrainwarp.measure.cost.CostModel`, the shipped llvmpipe model unless given) of
the counters, and reports rank by a :class:`terrainwarp.measure.cost.Cost` (``cost_ms`` by default,
``triangles`` or any counter), with triangles beside it. This simulator's CPU milliseconds
(:attr:`terrainwarp.rendering.Report.frame_ms`, ``select + mesh + raster``) are measured too, but kept out of
``report.md`` and ``pareto.png``, which are then byte-identical across runs, thread counts and machines (as is
``frames.csv`` without its timing columns): they go to ``timing.md`` with the jobs' record. The error and
reference stages are measurement, not cost.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import pickle
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..fit.verdict import MIN_SAMPLES, PIXELS_PER_SAMPLE
from ..heightmap import Heightmap, StreamedHeightmap
from ..io.files import new_figure, output_set, save_figure, write_text
from ..lod.bintree import Bintree
from ..lod.peers import delatin_mesh, martini_mesh, mesh_vertical_error
from ..lod.polytree import build_polytree, default_tolerances
from ..lod.quadtree import Terrain
from ..measure.cost import Cost, CostModel, cost, shipped_model
from ..rendering.pipeline import Frame, MeshSource, Report, pop_stats, render
from ..rendering.rows import ROW_COLUMNS, TIMING_COLUMNS, frame_row
from ..rendering.sources import BintreeSource, PeerSource, PolytreeSource
from ..scene import LOD_POLICIES, Scene
from ..schemes import PLUGIN_FLAG, SCHEMES, register_scheme, scheme_source, sweep_values
from .runner import Job, Runner, SweepResult, pending_jobs
from .winners import budget_verdicts, verdict_lines

__all__ = ["Setting", "SweepContext", "default_settings", "sweep", "run_sweep", "summarise", "write_report",
           "with_image_floor", "TIMING_COLUMNS", "COLUMNS", "image_floor", "pareto", "budget_table", "complete"]

_PEERS = ("martini", "delatin")  # the peer meshers (terrainwarp.lod.peers)
_FAMILIES = (*_PEERS, "polytree", "bintree")  # mesh families built once per worker, apart from frames


def _built(policy: str) -> bool:
    """Whether ``policy`` is drawn as a mesh source built apart from frames: a family, or a registered scheme."""
    return policy in _FAMILIES or policy in SCHEMES


@dataclass(frozen=True)
class Setting:
    policy: str
    param: float

    @property
    def label(self) -> str:
        return "grid" if self.policy == "grid" else f"{self.policy}={self.param:g}"


def default_settings(heightmap: Heightmap, quick: bool = False) -> list[Setting]:
    """A range of each policy's parameter, from fine to coarse."""
    lo, hi = heightmap.height_range
    relief = max(hi - lo, 1e-6)
    s = [Setting("grid", 0.0)]
    sse = (0.5, 1.0, 2.0, 4.0, 8.0) if not quick else (1.0, 4.0)
    dist = (8.0, 4.0, 2.0, 1.0) if not quick else (4.0, 1.0)
    cont = (2.0, 4.0, 8.0, 16.0) if not quick else (4.0, 16.0)
    peer = tuple(relief * f for f in ((0.0005, 0.002, 0.008, 0.03) if not quick else (0.002, 0.03)))
    s += [Setting("sse", v) for v in sse] + [Setting("distance", v) for v in dist]
    s += [Setting("continuous", v) for v in cont]
    s += [Setting("martini", round(v, 4)) for v in peer] + [Setting("delatin", round(v, 4)) for v in peer]
    rows, cols = heightmap.shape
    if rows * cols <= 2_000_000:  # the polytree keeps ~32 bytes per cell per quadtree level
        s += [Setting("polytree", float(t)) for t in ((2, 4, 8, 12) if not quick else (4, 12))]
    m_full = 2 * max(1, math.ceil(math.log2(max(rows, cols, 2) - 1))) + 1
    if m_full <= 22:  # 2^(M+1) tree nodes
        s += [Setting("bintree", float(m)) for m in ((m_full, m_full + 2) if not quick else (m_full,))]
    return s + _scheme_settings(heightmap, quick)


def _scheme_settings(heightmap: Heightmap, quick: bool) -> list[Setting]:
    """A few settings of each registered scheme (:data:`terrainwarp.schemes.SCHEMES`), fine to coarse, inside
    its range on ``heightmap`` (:func:`terrainwarp.schemes.sweep_values`): for the built-ins CDLOD's first
    range at 8, 4, 2, 1 times its seam-free minimum, clipmaps' n from 255 down to 31, chunked's pixel threshold
    from 1 to 8 (Cesium's default 2 among them)."""
    return [Setting(name, v) for name in SCHEMES for v in sweep_values(name, heightmap, quick)]


@dataclass(frozen=True)
class SweepContext:
    """What every job of a report sweep shares; sent to each worker once.

    ``token`` identifies the scene without its camera: a worker keeps its Terrain and peer meshes for the
    next sweep of the same scene (e.g. other cameras)."""

    token: str
    scene: Scene
    cameras: tuple
    images: bool
    device: str
    need_lod: bool
    schemes: dict = field(default_factory=dict)  # user schemes the sweep draws: name -> pickled SchemeSpec
    cost_model: CostModel | None = None  # the model of each row's cost_ms (None: the shipped one)


_STATE: dict = {}  # per worker process: the context's Terrain, mesh sources and normal map, made once


def _state(ctx: SweepContext) -> dict:
    if _STATE.get("token") != ctx.token:
        _STATE.clear()
        # the first copy of the scene this process received: a later copy (same token, same content) is
        # another object, and a Terrain belongs to the heightmap object it was prepared from
        _STATE.update(token=ctx.token, scene=ctx.scene, terrain=None, prepare_ms=0.0, sources={}, cache={})
        _register_user_schemes(ctx.schemes)
    if ctx.need_lod and _STATE["terrain"] is None:
        t0 = time.perf_counter()
        hm, lod = _STATE["scene"].heightmap, ctx.scene.lod
        _STATE["terrain"] = Terrain.prepare(hm, roots=lod.roots, tess=lod.tess, device=ctx.device)
        _STATE["prepare_ms"] = (time.perf_counter() - t0) * 1e3
    if not _STATE.get("warm"):
        _STATE["warm"] = True
        try:
            _warm_up(ctx)
        except Exception:  # noqa: BLE001 - only an optimisation: a real problem shows in the job itself
            pass
    return _STATE


def _outputs(ctx: SweepContext) -> tuple[str, ...]:
    return ("error", "counters", "image") if ctx.images else ("error", "counters")


def _warm_up(ctx: SweepContext) -> None:
    """Load this process's Warp modules (from the kernel cache) with tiny frames, so that loading them is not
    timed in the first frame each worker renders."""
    scene = _STATE["scene"]
    cam = ctx.cameras[0].with_(width=16, height=12)
    render(scene.with_(camera=cam, mesh="grid", outputs=_outputs(ctx)), device=ctx.device)
    if _STATE["terrain"] is not None:
        for s in (Setting("sse", 2.0), Setting("continuous", 8.0)):
            lod = scene.lod.with_policy(s.policy, s.param)
            render(scene.with_(camera=cam, mesh="lod", lod=lod, outputs=_outputs(ctx)), terrain=_STATE["terrain"],
                   device=ctx.device)


def _reference_job(ctx: SweepContext, k: int) -> tuple:
    """Camera k's full-resolution grid frame: (triangle_id, depth, image or None)."""
    f = render(ctx.scene.with_(camera=ctx.cameras[k], mesh="grid", outputs=("depth", "image") if ctx.images else
                               ("depth",)), device=ctx.device)
    return f.triangle_id, f.depth, f.image


def _peer_job(ctx: SweepContext, setting: Setting) -> tuple:
    """A Martini/Delatin mesh of the heightmap (view-independent: built once per sweep, then shared) and its
    measured vertical error."""
    hm = ctx.scene.heightmap
    peer = (martini_mesh if setting.policy == "martini" else delatin_mesh)(hm, setting.param)
    return peer, mesh_vertical_error(hm, peer)


def _user_schemes(settings: list[Setting]) -> dict[str, bytes]:
    """The specs of the schemes registered by the user that ``settings`` draw, each pickled for the workers (which
    only know the built-in ones): by value for a plugin run from a file (:func:`terrainwarp.schemes.load_plugin`:
    a worker cannot import it by name), by reference for an importable module."""
    specs = [SCHEMES[n] for n in dict.fromkeys(s.policy for s in settings) if n in SCHEMES and not SCHEMES[n].builtin]
    if not specs:
        return {}
    import cloudpickle  # lazy: heavy optional dependency

    for spec in specs:
        module = sys.modules.get(getattr(spec.make, "__module__", ""))
        if module is not None and getattr(module, PLUGIN_FLAG, False):
            cloudpickle.register_pickle_by_value(module)
    return {spec.name: cloudpickle.dumps(spec) for spec in specs}


_RECEIVED: dict[str, bytes] = {}  # per worker process: the user schemes registered from a sweep's context


def _register_user_schemes(sent: dict[str, bytes]) -> None:
    """Register the user schemes a sweep sent (:func:`_user_schemes`) that this process does not know, or knows
    from an earlier sweep in another version; a scheme registered in this process (an in-process sweep) stays."""
    for name, blob in sent.items():
        if (name in SCHEMES and name not in _RECEIVED) or _RECEIVED.get(name) == blob:
            continue
        spec = pickle.loads(blob)
        register_scheme(name, spec.make, parameter=spec.parameter, lo=spec.lo, hi=spec.hi,
                        larger_is_finer=spec.larger_is_finer, odd_integer=spec.odd_integer, sweep=spec.sweep,
                        fit_range=spec.fit_range, replace=name in SCHEMES, doc=spec.doc, knobs=spec.knobs,
                        default=spec.default)
        _RECEIVED[name] = blob


def _timed_build(make):
    t0 = time.perf_counter()
    value = make()
    return value, (time.perf_counter() - t0) * 1e3


def _source(ctx: SweepContext, refs: dict, setting: Setting) -> MeshSource:
    """The mesh source of a martini / delatin / polytree / bintree / scheme setting, built once per worker
    process (a peer mesh by :func:`_peer_job` for the whole sweep when it could be; one polytree for every
    level; one bintree per depth; a scheme's pyramids once for all its settings). The sources share one cache
    (the normal map, the schemes' pyramids)."""
    st_ = _STATE
    if setting in st_["sources"]:
        return st_["sources"][setting]
    hm, device, cache = st_["scene"].heightmap, ctx.device, st_["cache"]
    if setting.policy in _PEERS:
        built = refs.get(("peer", setting))
        if built is None or isinstance(built, BaseException):
            built = _peer_job(ctx, setting)
        src = PeerSource(built[0], hm, built[1], cache=cache)
    elif setting.policy == "polytree":  # taylor-barrett: view-independent levels of one polytree
        if "polytree" not in st_:
            st_["polytree"] = _timed_build(lambda: build_polytree(hm, default_tolerances(hm, 64), device=device))
        tree, ms = st_["polytree"]
        src = PolytreeSource(tree, int(setting.param), ms, cache=cache)
    elif setting.policy in SCHEMES:  # selected per frame by the scheme's own rule (built-in or registered)
        src = scheme_source(setting.policy, hm, setting.param, cache=cache, device=device)
    else:  # mrbsp bintree: the paper's apparent-size rule at tree depth M = param, per frame
        key = ("bintree", int(setting.param))
        if key not in st_:
            st_[key] = _timed_build(lambda: Bintree.build(hm, int(setting.param), device=device))
        tree, ms = st_[key]
        src = BintreeSource(tree, ms, cache=cache)
    st_["sources"][setting] = src
    return src


def _frame_job(ctx: SweepContext, refs: dict, setting: Setting, k: int) -> dict:
    """One row: ``setting`` rendered from camera k and measured against that camera's reference."""
    st_ = _state(ctx)
    scene, cam, device = st_["scene"], ctx.cameras[k], ctx.device
    if isinstance(refs[k], BaseException):
        raise RuntimeError(f"reference frame {k} failed: {refs[k]}")
    tri, depth, image = refs[k]
    ref = Frame(scene.with_(camera=cam, mesh="grid"), Report(), image=image, depth=depth, triangle_id=tri)
    sc = scene.with_(camera=cam, outputs=_outputs(ctx))
    built_ms, peer_err, src, terrain = 0.0, math.nan, None, None
    if _built(setting.policy):
        src = _source(ctx, refs, setting)
        f = render(sc, reference=ref, device=device, source=src)
        built_ms, peer_err = src.build_ms, src.error_m
    elif setting.policy == "grid":
        sc = sc.with_(mesh="grid")
        f = render(sc, reference=ref, device=device)
    else:
        sc, terrain = sc.with_(mesh="lod", lod=scene.lod.with_policy(setting.policy, setting.param)), st_["terrain"]
        f = render(sc, terrain=terrain, reference=ref, device=device)
    pop = {"pop_p99_px": math.nan, "pop_max_px": math.nan, "popped_samples": math.nan}
    if k > 0:
        p = pop_stats(sc, ctx.cameras[k - 1], f, ref, terrain=terrain, source=src, device=device)
        pop = {"pop_p99_px": p.p99_px, "pop_max_px": p.max_px, "popped_samples": p.popped}
    model = ctx.cost_model if ctx.cost_model is not None else shipped_model()
    return frame_row(f, peer_mesh_ms=built_ms, peer_error_m=peer_err, **pop, cost_ms=model(f.report.counters),
                     prepare_ms=st_["prepare_ms"])


#: The columns of a sweep's table, in order (the runner adds ``error`` and ``retries``): the job's setting and frame,
#: then :data:`terrainwarp.rendering.rows.ROW_COLUMNS` (the report's stages, the primary error ``p99_px``,
#: ``max_px``, ``mean_px`` at the samples and the rest of ``FrameError``, popping from the frame before, the
#: modelled cost, the counters).
COLUMNS = ("policy", "param", "setting", "frame", *ROW_COLUMNS)


def _scene_token(scene: Scene, device: str) -> str:
    """Identifies what a worker keeps between sweeps (Terrain, peer meshes): the scene but its camera."""
    h = hashlib.sha256()
    hm = scene.heightmap
    h.update(np.ascontiguousarray(hm.heights).tobytes())
    h.update(repr((hm.shape, hm.dx, hm.dz, scene.lod, scene.light_azimuth_deg, scene.light_elevation_deg,
                   scene.cull_back, scene.shading, device)).encode())
    return h.hexdigest()[:32]


def _fingerprint(scene: Scene, cameras: list[Camera], images: bool, device: str,
                 cost_model: CostModel | None = None) -> str:
    """Identifies a sweep's inputs (the partial file of another sweep is not resumed)."""
    model = None if cost_model is None else cost_model.to_json()
    return hashlib.sha256(repr((_scene_token(scene, device), list(cameras), images, model)).encode()).hexdigest()[:32]


def sweep_jobs(settings: list[Setting], n_cameras: int) -> list:
    """The sweep's jobs: one per (setting, camera), keyed by (setting's place in the list, frame)."""
    return [Job(id=f"{s.policy}={s.param!r}|{k}", sort_key=(i, k),
                fields={"policy": s.policy, "param": s.param, "setting": s.label, "frame": k}, args=(s, k))
            for i, s in enumerate(settings) for k in range(n_cameras)]


def run_sweep(scene: Scene, cameras: list[Camera], settings: list[Setting], *, progress: bool = True,
              images: bool = True, device: str = "cpu", scheduler: str | None = None, workers: int | None = None,
              out: str | Path | None = None, runner: Runner | None = None,
              cost_model: CostModel | None = None, say: Callable[[str], None] | None = None) -> SweepResult:
    """:func:`sweep`, returning the :class:`terrainwarp.experiments.runner.SweepResult` (rows plus what the run cost).

    ``runner`` (a :class:`terrainwarp.experiments.runner.Runner`) overrides ``scheduler`` and ``workers``. ``say``
    is given a line before each step that precedes the frames (the reference frames, the peer meshes).
    """
    if cost_model is not None and not isinstance(cost_model, CostModel):
        raise TypeError(f"cost_model: expected a CostModel or None, got {type(cost_model).__name__}")
    if runner is not None:
        return _run_sweep(runner, scene, cameras, settings, progress, images, device, out, cost_model, say)
    with Runner(scheduler, workers) as runner:
        return _run_sweep(runner, scene, cameras, settings, progress, images, device, out, cost_model, say)


def _run_sweep(runner: Runner, scene: Scene, cameras: list[Camera], settings: list[Setting], progress: bool,
               images: bool, device: str, out: str | Path | None, cost_model: CostModel | None,
               say: Callable[[str], None] | None = None) -> SweepResult:
    say = say or (lambda line: None)
    cameras = list(cameras)
    jobs = sweep_jobs(list(settings), len(cameras))
    fp = _fingerprint(scene, cameras, images, device, cost_model)
    ctx = SweepContext(_scene_token(scene, device), scene, tuple(cameras), images, device,
                       any(s.policy in LOD_POLICIES for s in settings), _user_schemes(settings), cost_model)
    ctx_h = runner.share(ctx)
    todo = pending_jobs(jobs, out, fp)
    need = sorted({j.args[1] for j in todo})  # references only for frames still to do
    if need:
        say(f"rendering the full-resolution reference frame of each of {len(need)} cameras")
    refs = dict(zip(need, runner.map(_reference_job, need, ctx_h)))
    peers = list(dict.fromkeys(j.args[0] for j in todo if j.args[0].policy in _PEERS))
    if peers:
        say(f"meshing {len(peers)} Martini/Delatin settings (view-independent, once per sweep)")
    refs.update(zip((("peer", s) for s in peers), runner.map(_peer_job, peers, ctx_h)))
    refs_h = runner.share(refs)  # reference frames by camera, peer meshes by ("peer", setting)
    return runner.run(jobs, _frame_job, ctx_h, refs_h, out=out, fingerprint=fp, columns=COLUMNS,
                      to_csv=rows_to_csv, progress=progress, desc="report")


def sweep(scene: Scene, cameras: list[Camera], settings: list[Setting], *, progress: bool = True,
          images: bool = True, device: str = "cpu", scheduler: str | None = None, workers: int | None = None,
          out: str | Path | None = None, cost_model: CostModel | None = None) -> list[dict]:
    """Render every setting from every camera; one row per (setting, frame), sorted by (setting, frame).

    The jobs (setting, camera) run through :mod:`terrainwarp.experiments.runner`: by default on a LocalCluster with one
    worker process per core; the scene and the reference frames (the full-resolution grid, rendered once per
    camera) go to each worker once. Rows carry ``error`` ("" or the job's exception) and ``retries`` (times
    rescheduled after a worker died); everything but those and :data:`TIMING_COLUMNS` is identical whatever
    the number of workers.

    Args:
        images: also shade the frames and report PSNR/SSIM of the hillshaded images (costs a shade pass).
        scheduler: ``tcp://HOST:PORT`` of a Dask scheduler (default: a LocalCluster).
        workers: LocalCluster worker processes (default: one per core; 0: in this process).
        out: CSV path: rows are saved to ``out.partial`` as they arrive and the sorted table to ``out``; a
            sweep interrupted before the end resumes from the partial file without redoing finished jobs.
        cost_model: the model of each row's ``cost_ms`` (None: the shipped llvmpipe model).
    """
    if isinstance(scene.heightmap, StreamedHeightmap):
        raise ValueError("scene.heightmap: a sweep measures every frame against the full-resolution grid; sweep "
                         "StreamedHeightmap.load() (or a part of the terrain that fits)")
    return run_sweep(scene, cameras, settings, progress=progress, images=images, device=device,
                     scheduler=scheduler, workers=workers, out=out, cost_model=cost_model).rows


def _worst(rs: list[dict], key: str) -> float:
    """The largest finite-or-inf value of ``key`` over rows (NaN where none has one: frame 0's popping)."""
    v = [float(r[key]) for r in rs if key in r and not math.isnan(float(r[key]))]
    return max(v) if v else math.nan


#: the counters a summary averages over the frames (besides the cost and triangles)
SUMMARY_COUNTERS = ("draw_calls", "tess_control_shader_patches", "vertex_shader_invocations_llvmpipe",
                    "fragment_shader_invocations", "fragment_shader_invocations_llvmpipe", "samples_passed",
                    "quad_efficiency", "overdraw")


def _mean(rs: list[dict], key: str) -> float:
    v = [float(r[key]) for r in rs if key in r]
    return float(np.mean(v)) if v else math.nan


def summarise(rows: list[dict], cost_of: Cost | None = None) -> list[dict]:
    """One row per setting: worst-frame p99 and max error (primary, and the image error's p99), worst pair's
    pop p99 and max and the popped samples over the path, the mean modelled cost (``cost_ms``), triangles,
    :data:`SUMMARY_COUNTERS` and frame time, and ``cost``: the mean of ``cost_of`` (None: ``cost_ms``) over the
    frames, the cost the report ranks by. Over the frames that did not fail: ``frames`` counts the setting's
    rows and ``failed`` those with an ``error`` (left out of every figure; a setting whose every frame failed has
    NaN figures and ``see_through_px`` None). :func:`complete` says which settings every figure covers."""
    cost_of = cost_of if cost_of is not None else Cost("cost_ms", "modelled ms")
    out = []
    for label in dict.fromkeys(r["setting"] for r in rows):
        every = [r for r in rows if r["setting"] == label]
        rs = [r for r in every if not r.get("error")]
        if not rs:
            out.append(_all_failed(every))
            continue
        popped = [float(r["popped_samples"]) for r in rs if not math.isnan(float(r.get("popped_samples", math.nan)))]
        out.append({"policy": rs[0]["policy"], "param": rs[0]["param"], "setting": label,
                    "p99_px": max(r["p99_px"] for r in rs), "max_px": max(r["max_px"] for r in rs),
                    "image_err_p99_px": _worst(rs, "image_err_p99_px"), "pop_p99_px": _worst(rs, "pop_p99_px"),
                    "pop_max_px": _worst(rs, "pop_max_px"), "popped_samples": sum(popped) if popped else math.nan,
                    "mean_px": _mean(rs, "mean_px"), "cost": float(np.mean([cost_of.of(r) for r in rs])),
                    "cost_ms": _mean(rs, "cost_ms"), "triangles": _mean(rs, "triangles"),
                    **{c: _mean(rs, c) for c in SUMMARY_COUNTERS},
                    "frame_ms": _mean(rs, "frame_ms"), "select_ms": _mean(rs, "select_ms"),
                    "mesh_ms": _mean(rs, "mesh_ms"), "see_through_px": int(sum(r["see_through_px"] for r in rs)),
                    "peer_mesh_ms": rs[0]["peer_mesh_ms"], "peer_error_m": rs[0]["peer_error_m"],
                    "psnr_db": float(np.nanmean([r["psnr_db"] for r in rs])) if any(
                        np.isfinite(r["psnr_db"]) for r in rs) else math.nan,
                    "frames": len(every), "failed": len(every) - len(rs)})
    return out


def _all_failed(every: list[dict]) -> dict:
    """The summary row of a setting none of whose frames rendered: its counts, every figure NaN."""
    r0 = every[0]
    nan = dict.fromkeys(("p99_px", "max_px", "image_err_p99_px", "pop_p99_px", "pop_max_px", "popped_samples",
                         "mean_px", "cost", "cost_ms", "triangles", *SUMMARY_COUNTERS, "frame_ms", "select_ms",
                         "mesh_ms", "peer_mesh_ms", "peer_error_m", "psnr_db"), math.nan)
    return {"policy": r0["policy"], "param": r0["param"], "setting": r0["setting"], **nan, "see_through_px": None,
            "frames": len(every), "failed": len(every)}


def complete(summary: list[dict]) -> list[dict]:
    """The settings of a summary none of whose frames failed: the ones the fronts, the budget table and the
    plot compare (a worst frame over part of the path would flatter a setting)."""
    return [r for r in summary if not r.get("failed")]


def pareto(summary: list[dict], cost: str = "cost") -> list[dict]:
    """The settings no other setting beats on both p99 error and ``cost`` (a summary column: ``cost``, the
    report's cost, by default)."""
    pts = sorted(complete(summary), key=lambda r: (r["p99_px"], r[cost], r["setting"]))
    front, best = [], math.inf
    for r in pts:
        if r[cost] < best:
            front.append(r)
            best = r[cost]
    return front


def budget_table(summary: list[dict], budgets=(0.5, 1.0, 2.0, 4.0), cost: str = "cost") -> list[list]:
    """For each budget and policy: the cheapest setting by ``cost`` (a summary column) whose worst-frame p99
    (primary error) meets it: [budget, policy, setting, p99_px, cost, triangles, image_err_p99_px (the old
    yardstick at that setting), pop_p99_px]."""
    rows = []
    summary = complete(summary)
    for b in budgets:
        for pol in dict.fromkeys(r["policy"] for r in summary):
            ok = [r for r in summary if r["policy"] == pol and r["p99_px"] <= b]
            if not ok:
                rows.append([b, pol, "-", "-", "-", "-", "-", "-"])
                continue
            r = min(ok, key=lambda r: (r[cost], r["setting"]))
            rows.append([b, pol, r["setting"], round(r["p99_px"], 3), _fmt(r[cost]), int(r["triangles"]),
                         round(r.get("image_err_p99_px", math.nan), 3), round(r.get("pop_p99_px", math.nan), 3)])
    return rows


def _fmt(v: float) -> str:
    return "nan" if math.isnan(v) else f"{v:.4g}"


def image_floor(summary: list[dict]) -> dict[str, float]:
    """The old yardstick's floor in a sweep: per policy (not the grid), the smallest worst-frame grid-image
    p99 over its settings (its finest setting's, as a rule): what the per-pixel error against the
    fixed-diagonal grid cannot go below, whatever the threshold."""
    out: dict[str, float] = {}
    for r in complete(summary):
        v = r.get("image_err_p99_px", math.nan)
        if r["policy"] != "grid" and not math.isnan(v):
            out[r["policy"]] = min(out.get(r["policy"], math.inf), v)
    return out


def with_image_floor(rows: list[dict]) -> list[dict]:
    """``rows`` with ``image_err_floor_p99_px`` beside ``image_err_p99_px``: on each camera, the lowest image p99 of
    the row's family over the sweep's settings (its finest setting's, as a rule: the triangulation floor the image
    error carries on that camera; a family's full-detail frame is not among a sweep's settings, so this is the
    floor as near as the sweep goes); and ``sparse``: 1 where the frame's p99 rests on too few visible samples
    (:data:`terrainwarp.fit.verdict.MIN_SAMPLES`, or fewer than one per
    :data:`terrainwarp.fit.verdict.PIXELS_PER_SAMPLE` covered pixels), else 0."""
    floor: dict[tuple, float] = {}
    for r in rows:
        v = float(r.get("image_err_p99_px", math.nan))
        if not math.isnan(v):
            key = (r["policy"], r["frame"])
            floor[key] = min(floor.get(key, math.inf), v)
    out = []
    for r in rows:
        d = {}
        for k, v in r.items():
            d[k] = v
            if k == "image_err_p99_px":
                d["image_err_floor_p99_px"] = floor.get((r["policy"], r["frame"]), math.nan)
        n, cov = float(r.get("samples_visible", math.nan)), float(r.get("covered", math.nan))
        d["sparse"] = int(n < MIN_SAMPLES or n * PIXELS_PER_SAMPLE < cov) if math.isfinite(n) else 0
        out.append(d)
    return out


def rows_to_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    keys = list(rows[0].keys()) if rows else []
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def plot_pareto(summary: list[dict], path: str | Path, title: str = "", cost_label: str = "modelled ms") -> Path:
    """pareto.png: the worst-frame p99 error against the report's cost (``cost``) and against triangles, each
    setting a marker, each policy a line, the Pareto fronts marked. Nothing in it depends on timings: the same
    rows draw the same bytes."""
    left_out = [r["setting"] for r in summary if r.get("failed")]
    summary = complete(summary)
    if left_out:
        title += f"\n(left out, frames failed: {', '.join(left_out[:6])}{' ...' if len(left_out) > 6 else ''})"
    fig, axes = new_figure(1, 2, figsize=(12, 4.8))
    marks = {"grid": "k*", "sse": "o-", "distance": "s-", "continuous": "^-", "martini": "v--", "delatin": "D--",
             "polytree": "P:", "bintree": "X:", "cdlod": "h-.", "clipmaps": "p-.", "chunked": "d-."}
    others = [r["p99_px"] for r in summary if r["policy"] != "grid" and r["p99_px"] > 0]
    floor = 0.5 * min(others) if others else 1e-3  # the exact grid (0 px) is drawn on this floor
    old = image_floor(summary)

    def y(r):
        return max(r["p99_px"], floor)

    for ax, col, lab in ((axes[0], "cost", f"cost per frame ({cost_label})"),
                         (axes[1], "triangles", "triangles per frame")):
        for pol in dict.fromkeys(r["policy"] for r in summary):
            rs = sorted([r for r in summary if r["policy"] == pol], key=lambda r: (r[col], r["setting"]))
            ax.plot([r[col] for r in rs], [y(r) for r in rs], marks.get(pol, "o-"),
                    label=pol if pol != "grid" else "grid (exact: drawn at the bottom)", ms=6)
        front = pareto(summary, col)
        ax.plot([r[col] for r in front], [y(r) for r in front], color="red", lw=3, alpha=0.3, label="Pareto front")
        if old:
            ax.axhline(min(old.values()), color="gray", ls="--", lw=1,
                       label=f"old yardstick's floor: grid-image p99 {min(old.values()):.2f} px (finest settings)")
        ax.set_ylim(bottom=0.8 * floor)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(lab)
        ax.set_ylabel("p99 screen error at the samples (px), worst frame")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def write_report(scene: Scene, cameras: list[Camera], rows: list[dict], out_dir: str | Path, *,
                 path: dict | None = None, cost_of: Cost | str | None = None) -> list[Path]:
    """frames.csv, pareto.png, report.md and timing.md for a sweep, ranked by ``cost_of`` (a
    :func:`terrainwarp.measure.cost.cost` spec; None: the rows' ``cost_ms``, the sweep's cost model). ``path``:
    :meth:`Scene.path_info` of the cameras (its ``text`` is stated in report.md), None when the cameras are the
    caller's own. report.md and pareto.png hold no timing (byte-identical across runs and machines); this run's
    CPU milliseconds and its jobs go to timing.md. The four are written as one set
    (:func:`terrainwarp.io.files.output_set`): a failure leaves the folder's previous set whole."""
    c = cost_of if isinstance(cost_of, Cost) else (Cost("cost_ms", "modelled ms") if cost_of is None
                                                   else cost(cost_of))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with output_set(out):
        return _write_report(scene, cameras, rows, out, path, c)


def _write_report(scene: Scene, cameras: list[Camera], rows: list[dict], out: Path, path: dict | None,
                  c: Cost) -> list[Path]:
    summ = summarise(rows, c)
    floors = with_image_floor(rows)
    for r in summ:  # the floor on the camera of the worst image p99, beside it
        rs = [f for f in floors if f["setting"] == r["setting"] and not math.isnan(float(f["image_err_p99_px"]))]
        worst = max(rs, key=lambda f: float(f["image_err_p99_px"]), default=None)
        r["image_err_floor_p99_px"] = math.nan if worst is None else worst["image_err_floor_p99_px"]
    hm = scene.heightmap
    paths = [write_text(out / "frames.csv", rows_to_csv(floors)),
             plot_pareto(summ, out / "pareto.png", f"{hm.name}: error against cost, {len(cameras)} cameras at "
                                                   f"{cameras[0].width}x{cameras[0].height}", c.label)]
    head = [f"Heightmap {hm.shape[0]}x{hm.shape[1]}, dx={hm.dx:.4g} m, dz={hm.dz:.4g} m; {len(cameras)} cameras at "
            f"{cameras[0].width}x{cameras[0].height}; LOD: {scene.lod.roots} roots, tess {scene.lod.tess}.", "",
            f"Camera path: {path['text'] if path else 'the cameras given (not a scene path)'}.", ""]
    md = [f"# Error against cost: {hm.name}", "", *head, *_cost_lines(c), "", *_yardstick_lines(summ),
          *_failed_lines(summ),
          "", "## Settings", "", _md(["setting", "p99_px", "max_px", "image_err_p99_px", "image_err_floor_p99_px",
                                      "pop_p99_px", "pop_max_px",
                                      "popped_samples", "cost", "cost_ms", "triangles", *SUMMARY_COUNTERS,
                                      "see_through_px", "psnr_db", "peer_error_m"], summ),
          "", f"## Cheapest setting per budget ({c.label}; budgets on the primary p99)", "",
          "| budget_px | policy | setting | p99_px | cost | triangles | image_err_p99_px | pop_p99_px |",
          "|---|---|---|---|---|---|---|---|"]
    md += ["| " + " | ".join(str(v) for v in r) + " |" for r in budget_table(summ)]
    md += ["", "## Winner per budget under each cost model", "",
           "Every setting meeting the budget, priced by the shipped llvmpipe model and each shipped GPU profile "
           "(terrainwarp.measure.gpu: published rates, a bottleneck model); robust: the winner stays with every rate "
           "multiplied by 1/3..3 (terrainwarp.measure.ranking).", "", *verdict_lines(budget_verdicts(summ, rows))]
    md += ["", f"## Pareto front ({c.label})", "", ", ".join(r["setting"] for r in pareto(summ)),
           "", "## Pareto front (triangles)", "", ", ".join(r["setting"] for r in pareto(summ, "triangles")),
           "", "## Cameras", "", "| frame | position | target |", "|---|---|---|"]
    md += [f"| {k} | {tuple(round(v, 1) for v in cam.position)} | {tuple(round(v, 1) for v in cam.target)} |"
           for k, cam in enumerate(cameras)]
    sparse = sorted({(r["frame"], int(r["samples_visible"])) for r in floors if r["sparse"] and r["policy"] == "grid"}
                    or {(r["frame"], int(r["samples_visible"])) for r in floors if r["sparse"]})
    if sparse:
        md += ["", f"Frames whose p99 rests on too few visible samples (< {MIN_SAMPLES}, or < one per "
               f"{PIXELS_PER_SAMPLE} covered pixels; frames.csv's `sparse`): "
               + ", ".join(f"frame {k} ({n} samples)" for k, n in sparse) + "."]
    md += ["", "This simulator's CPU time per frame: [timing.md](timing.md).", "", "![pareto](pareto.png)", ""]
    timing = [f"# This run's timings: {hm.name}", "", *head, _jobs_line(rows), "",
              "CPU milliseconds of this simulator (select + mesh + raster = frame_ms), not a GPU's: they differ "
              "from run to run and machine to machine. The cost a GPU would pay is report.md's.", "",
              _md(["setting", "frame_ms", "select_ms", "mesh_ms", "cost", "triangles", "peer_mesh_ms"], summ), "",
              "## Pareto front (CPU ms)", "", ", ".join(r["setting"] for r in pareto(summ, "frame_ms")), ""]
    paths.append(write_text(out / "report.md", "\n".join(md)))
    paths.append(write_text(out / "timing.md", "\n".join(timing)))
    return paths


def _cost_lines(c: Cost) -> list[str]:
    """What the report's cost is."""
    if c.model is not None:
        return [f"Cost (`cost`): {c.model.describe()}."]
    if c.name == "cost_ms":
        return ["Cost (`cost`): `cost_ms`, the sweep's cost model of each frame's pipeline statistics (modelled "
                "ms of the driver it was fitted to; terrainwarp.measure.cost)."]
    return [f"Cost (`cost`): `{c.name}` per frame; `cost_ms` (the sweep's cost model) beside it."]


def _yardstick_lines(summ: list[dict]) -> list[str]:
    """What the report's errors are: the primary error, the old yardstick's floor in this sweep, popping."""
    floor = image_floor(summ)
    pops = [r for r in summ if not math.isnan(r["pop_p99_px"])]
    lines = ["Error (`p99_px`, `max_px`): the primary error, per visible heightmap sample the pixel distance "
             "between the sample and the drawn surface at its (x, z), worst frame (every family's full-detail "
             "mesh scores 0). `image_err_p99_px`: the per-pixel reprojection error against the fixed-diagonal "
             "grid (secondary; the old yardstick); beside it `image_err_floor_p99_px`, the same family's lowest on "
             "that camera over the swept settings (its triangulation floor: only the difference is the setting's; "
             "frames.csv per camera, here the worst camera's). `see_through_px`: background pixels seen through the "
             "terrain (a pixel heuristic; cracks are check_watertight's open edges, not counted in a sweep)."]
    if floor:
        lines += ["", "Old yardstick's floor here (grid-image p99 of each family's finest setting, which the "
                  "primary error scores near 0): " + ", ".join(f"{k} {v:.3g} px" for k, v in floor.items()) + "."]
    if pops:
        worst = max(pops, key=lambda r: r["pop_p99_px"])
        lines += ["", "Popping (frame t drawn with the LOD selected at t-1 against the LOD selected at t, per "
                  "visible sample; stateless selection): worst pair's pop p99 over the settings "
                  f"{worst['pop_p99_px']:.3g} px ({worst['setting']}); pop max up to "
                  f"{max(r['pop_max_px'] for r in pops):.3g} px; samples moving > 0.5 px over the path: up to "
                  f"{max(r['popped_samples'] for r in pops):.0f}."]
    else:
        lines += ["", "Popping: one camera, no frame pair."]
    return lines


def _failed_lines(summ: list[dict]) -> list[str]:
    """What failed: the settings with failed frames, left out of the fronts, the budget table and pareto.png."""
    bad = [r for r in summ if r.get("failed")]
    if not bad:
        return []
    return ["", f"Failed frames: {sum(r['failed'] for r in bad)} of {sum(r['frames'] for r in summ)} (" +
            ", ".join(f"{r['setting']} {r['failed']} of {r['frames']}" for r in bad) + "). Their rows in frames.csv "
            "carry the error; these settings' figures cover the frames that rendered, and they are left out of "
            "the Pareto fronts, the budget table and pareto.png. A rerun into this folder runs the failed frames "
            "again."]


def _jobs_line(rows: list[dict]) -> str:
    """How the sweep's jobs went: failures (with the first error) and retries after a worker died."""
    failed = [r for r in rows if r.get("error")]
    retried = [r for r in rows if r.get("retries", 0)]
    line = f"Jobs (setting, frame): {len(rows)}, failed {len(failed)}, retried after a worker died {len(retried)}."
    if failed:
        line += f" First failure: {failed[0]['setting']} frame {failed[0]['frame']}: {failed[0]['error']}"
    return line


def _md(cols: list[str], rows: list[dict]) -> str:
    def f(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return "nan" if math.isnan(v) else f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    lines += ["| " + " | ".join(f(r[c]) for c in cols) + " |" for r in rows]
    return "\n".join(lines)
