"""Fit a LOD family's knobs to a screen-space error budget (pixels) at the lowest cost, validated by the exact
pipeline: :func:`fit_lod`.

The problem: minimise the mean cost per frame over a camera path (triangles, a pipeline counter or a cost
model, :mod:`terrainwarp.measure.cost`) subject to every frame's p99 primary error (at the heightmap's samples)
within the budget, and optionally the worst consecutive pair's pop p99 within ``max_pop_px``. The knobs are the
family's (:func:`terrainwarp.fit.knobs`): one (``knobs=None``: the policy's main parameter), a list, or
``"all"``; the result is a :class:`terrainwarp.Scene` that draws the setting (it saves to TOML and loads back).

How (by module):

* :mod:`.probe`: each camera's error at every resolution the family draws, measured once (per structure: per
  ``tess``);
* :mod:`.relaxed`: the models (JAX) of each camera's cost and p99 error in the continuous knobs, relaxed and hard;
* :mod:`.search`: a reduced-gradient method on the relaxed model (``jax.grad``: Newton steps that hold the budget
  on the main knob, Adam on the other knobs' reduced gradient), its polish on the hard model, and the exact tries
  that calibrate the model per camera until the exact pipeline confirms a setting on every camera; integer knobs
  enumerated, one model each;
* :mod:`.exact`: the exact evaluations and their accounting (frames measured, frames drawn for their cost only);
* families without a model (:data:`terrainwarp.fit.families.MODELLED` lists those with one) are fitted on the
  exact pipeline alone (:func:`terrainwarp.fit.search.bracket_search`, one knob), and so is a fit whose relaxed
  model turns out not finite (:class:`terrainwarp.fit.optimise.NonFiniteModel`: said in the history);
* :mod:`.timings`: where the time went (``FitResult.timings``) and the progress bar; :mod:`.jaxrt`: the relaxed
  models' programs, compiled once per machine (JAX's persistent cache in the user's cache folder).

A fit that misses the budget on the exact pipeline is reported as missed, never as met.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, Viewport
from ..heightmap import StreamedHeightmap
from ..io.display import html_table
from ..kernels.checks import check_choice, check_int, check_number
from ..measure.cost import Cost
from ..measure.cost import cost as resolve_cost
from ..rendering.pipeline import Frame
from ..scene import LOD_POLICIES, Scene
from ..schemes import SCHEMES
from .baselines import grid_search
from .exact import MISSING_TOL, Evaluation, Exact, evaluate, references_for
from .families import Problem, problem
from .search import NonFiniteModel, bracket_search, calibrated_search, close_to_bound
from .timings import PARTS, Clock, Progress, part, running
from .verdict import annotate
from .viewport import pixel_knobs

__all__ = ["FitResult", "fit_lod", "Progress"]


@dataclass
class FitResult:
    """What a fit found, validated by the exact pipeline.

    Attributes:
        policy: the family fitted; budget_px, max_pop_px: the constraints; cost: what was minimised.
        met: True only if the exact pipeline's worst-frame p99 is within the budget (and the worst pair's pop p99
            within ``max_pop_px`` when given) on every camera.
        values: the fitted knobs' values (name -> value); scene: the :class:`Scene` that draws them, with the exact
            cameras measured (its ``[path]``), the viewport its pixel knobs are measured at and its budget: it
            loads back to the same frames, and ``terrainwarp evaluate`` on it reproduces ``validated``.
        validated: the exact evaluation of ``values`` on every camera (with the pop of each consecutive pair,
            measured for the record when ``max_pop_px`` is None: not counted in ``evaluations``).
        evaluations: exact frames the fit measured (error against the reference); mesh_only_frames: frames drawn
            only for their cost (the cameras a try did not need to measure).
        knobs: the knobs fitted; model_s: seconds from the models' start to the result (the search); wall_s: the
            whole call.
        timings: the whole call's seconds by part (:data:`terrainwarp.fit.timings.PARTS`: ``compile``,
            ``relaxed``, ``hard``, ``probes``, ``exact``, ``other``); they add up to ``wall_s``.
        history: the fit's steps (the relaxed rounds, the polishes, the exact tries); trace: (exact frames, best
            confirmed cost) each time the best improved.
        grid: the grid search baseline of the one-knob fit, when asked for.
        viewports: the viewports the cameras were drawn at (the first is the scene's ``viewport``, where the pixel
            knobs are measured).
        binding: the constraint that holds the setting (:func:`terrainwarp.fit.verdict.binding_constraint`: the
            budget on camera k, the pop budget, or the main knob at a range limit); at_limits: the fitted knobs on
            an end of their range; sparse: the validated frames whose p99 rests on too few samples
            (:func:`terrainwarp.fit.verdict.sparse_frames`); image_floor_p99_px: per camera, the family's
            full-detail image error (the floor of ``validated.image_p99_px``; with ``floor=True``, as the CLI fits).
    """

    policy: str
    budget_px: float
    met: bool
    values: dict[str, float]
    scene: Scene
    validated: Evaluation | None
    evaluations: int
    wall_s: float
    message: str = ""
    history: list[dict] = field(default_factory=list)
    grid: dict | None = None
    max_pop_px: float | None = None
    mesh_only_frames: int = 0
    cost: str = "triangles"
    knobs: list[str] = field(default_factory=list)
    model_s: float = 0.0
    trace: list[tuple[int, float]] = field(default_factory=list)
    viewports: list[Viewport] = field(default_factory=list)
    binding: dict = field(default_factory=dict)
    at_limits: list[dict] = field(default_factory=list)
    sparse: list[dict] = field(default_factory=list)
    image_floor_p99_px: list[float] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    trace_s: list[float] = field(default_factory=list)  # seconds from the call to each entry of ``trace``

    def timing_line(self) -> str:
        """One line: the wall time and its parts (:attr:`timings`)."""
        names = {"compile": "compile", "relaxed": "relaxed model", "hard": "hard model + polish", "probes": "probes",
                 "exact": f"{self.evaluations} exact frames", "other": "other"}
        parts = ", ".join(f"{names[k]} {self.timings.get(k, 0.0):.1f}" for k in PARTS)
        return f"fit took {self.wall_s:.1f} s: {parts} s"

    @property
    def value(self) -> float:
        """The main knob's value (the one-knob fit's parameter)."""
        return self.values[self.knobs[0]]

    def _repr_html_(self) -> str:
        """The fit in HTML tables (Jupyter): the result, then each camera of the validated setting."""
        v = self.validated
        head = html_table(("policy", "budget_px", "met", *self.knobs, "worst p99 px", f"{self.cost}/frame",
                           "exact frames", "wall s"),
                          [(self.policy, self.budget_px, self.met, *(self.values[k] for k in self.knobs),
                            v.worst_p99 if v else math.nan, v.cost if v else math.nan, self.evaluations, self.wall_s)],
                          caption=self.message)
        if v is None or not v.complete:
            return head
        return head + html_table(("camera", "p99_px", "max_px", "triangles", "frame_ms"),
                                 [(k, *r) for k, r in enumerate(zip(v.p99_px, v.max_px, v.triangles, v.frame_ms))])

    def to_dict(self) -> dict:
        v = self.validated
        return {"policy": self.policy, "budget_px": self.budget_px, "max_pop_px": self.max_pop_px, "cost": self.cost,
                "met": self.met, "knobs": self.knobs, "values": self.values, "lod": dict(self.scene.lod.__dict__),
                "message": self.message, "evaluations": self.evaluations, "mesh_only_frames": self.mesh_only_frames,
                "wall_s": self.wall_s, "model_s": self.model_s, "timings": dict(self.timings),
                "error": "primary: per visible heightmap sample, px (terrainwarp.measure.sample_error); "
                         "image_p99_px: the per-pixel grid-image error (secondary, with a triangulation floor: "
                         "image_floor_p99_px, the family's own full-detail frame's, per camera)",
                **self._engine_dict(),
                "validated": None if v is None else {"p99_px": v.p99_px, "max_px": v.max_px,
                                                     "image_p99_px": v.image_p99_px,
                                                     "image_floor_p99_px": self.image_floor_p99_px,
                                                     "samples_visible": v.visible, "covered_px": v.covered,
                                                     "pop_p99_px": v.pop_p99_px,
                                                     "triangles": v.triangles, "frame_ms": v.frame_ms,
                                                     "worst_p99_px": v.worst_p99, "worst_pop_p99_px": v.worst_pop,
                                                     "mean_triangles": float(np.mean(v.triangles)),
                                                     "costs": v.costs, "mean_cost": v.cost},
                "history": self.history, "trace": self.trace, "grid": self.grid}


    def _engine_dict(self) -> dict:
        """The viewport, the pixel knobs as angles, what binds, the limits and the sparse frames (JSON)."""
        return {"viewport": list(self.scene.pixel_viewport), "viewports": [list(v) for v in self.viewports],
                "pixel_knobs": pixel_knobs(self.scene, self.budget_px) if self.scene.mesh == "lod" else {},
                "binding": self.binding, "at_limits": self.at_limits, "sparse_frames": self.sparse}


def fit_lod(scene: Scene, budget_px: float, policy: str = "sse", cameras: list[Camera] | None = None, *,
            knobs: Sequence[str] | str | None = None, cost: str | Cost | object = "triangles",
            max_pop_px: float | None = None, references: list[Frame] | None = None, rel_tol: float = 0.02,
            max_tries: int = 8, grid_points: int = 0, grid_evaluator=None, gradient: str = "relaxed",
            device: str = "cpu", progress: bool = False, steps: int | None = None,
            max_validations: int | None = None, viewports: Sequence[Sequence[float]] | None = None,
            floor: bool = False) -> FitResult:
    """Fit ``policy``'s knobs so that every frame's p99 screen error over the camera path is within ``budget_px``
    at the lowest mean cost per frame.

    Args:
        scene: the scene (heightmap, its ``LodConfig``'s structure: roots, tess, spacing); its camera path unless
            ``cameras``.
        budget_px: the budget, pixels (> 0).
        policy: ``"sse"``, ``"distance"``, ``"continuous"`` or a registered scheme (``"cdlod"``, ``"clipmaps"``,
            ``"chunked"``, yours).
        knobs: None (the policy's main knob, as before multi-knob fits), ``"all"`` or a list of knob names
            (:func:`terrainwarp.fit.knobs`); the main knob is always fitted.
        cost: ``"triangles"``, a counter name, ``"llvmpipe"`` (the shipped cost model), a
            :class:`terrainwarp.measure.cost.CostModel` or a weights file, a GPU profile (``"gpu:gf100"``,
            ``"gpu:mine.toml"``), or a list of models: each frame's worst modelled ms over them is minimised, a
            setting that holds on every GPU listed (:func:`terrainwarp.measure.cost.cost`).
        max_pop_px: also bound the worst consecutive pair's pop p99 (px); every try then measures the whole path.
        references: the full-detail grid frames of the cameras (with depth), when the caller has them.
        rel_tol: a try within ``rel_tol`` under the budget ends the search; cost gaps within it are not chased.
        max_tries: exact tries of the search (confirmations not counted).
        grid_points: also run a grid search over the main knob with that many points (the old baseline).
        grid_evaluator: how the grid search runs (see :func:`terrainwarp.fit.baselines.grid_search`).
        gradient: ``"relaxed"`` (the relaxed models' ``jax.grad``) or, for the continuous policy's one-knob fit,
            ``"pixels"``: until the budget is bracketed, Newton steps in log space with d log(mean pixel error above
            the p99) / d log(target_px) of the worst frame, through the Warp resolve kernel
            (:func:`terrainwarp.fit.diffpath.log_slope`; one extra frame each).
        progress: a progress bar on stderr (reference frames, models built, optimiser steps, exact frames).
        steps, max_validations: accepted from earlier versions: ``max_validations`` sets ``max_tries``; ``steps``
            is unused (the optimiser's schedule is fixed).
        viewports: ``[(w, h, fov_y_deg), ...]``: the cameras at each, one setting for all; floor: image floors too.

    Raises:
        ValueError, TypeError: a bad budget, policy, knob name, cost, count, or a streamed heightmap.
    """
    max_tries = max_tries if max_validations is None else max_validations
    _check(scene, budget_px, policy, max_tries, grid_points, max_pop_px, steps)
    if gradient not in ("relaxed", "pixels") or (gradient == "pixels" and (policy != "continuous" or knobs)):
        raise ValueError("gradient: expected 'relaxed', or 'pixels' with the continuous policy's one-knob fit "
                         f"(knobs=None), got {gradient!r}")
    cost_of = resolve_cost(cost)
    cost_of = None if cost_of.name == "triangles" else cost_of
    t0 = time.perf_counter()
    clock = Clock()
    cams, vps = _at_viewports(list(cameras) if cameras is not None else scene.camera_path(), viewports)
    if not cams:
        raise ValueError("cameras: expected at least one camera")
    bar = Progress(progress, len(cams) * (2 + max_tries + grid_points), f"fit {policy} {budget_px:g} px")
    job = _Job(scene, budget_px, policy, cams, knobs, cost_of, max_pop_px, rel_tol, max_tries, device, bar, t0,
               vps, cost, floor)
    try:
        with running(clock, bar):
            res = _run(job, references, gradient, grid_points, grid_evaluator)
        bar.expect(0)  # the total was an estimate: the bar ends full at the steps taken
    finally:
        bar.close()
    res.timings = clock.close()
    res.wall_s = time.perf_counter() - t0
    return res


@dataclass
class _Job:
    scene: Scene
    budget_px: float
    policy: str
    cams: list[Camera]
    knobs: Sequence[str] | str | None
    cost_of: Cost | None
    max_pop_px: float | None
    rel_tol: float
    max_tries: int
    device: str
    bar: Progress
    t0: float
    vps: list[Viewport]
    cost: object
    floor: bool


def _run(job: _Job, references: list[Frame] | None, gradient: str, grid_points: int, grid_evaluator) -> FitResult:
    """The fit of :func:`fit_lod`, each part on the running clock (:mod:`terrainwarp.fit.timings`)."""
    budget_px, cams, device, bar = job.budget_px, job.cams, job.device, job.bar
    with part("exact"):
        refs = references_for(job.scene, cams, references, device, on_frame=bar)
    with part("probes"):
        prob = problem(job.scene, job.policy, job.knobs, cams, refs, job.cost_of, device=device, on_step=bar,
                       budget_px=budget_px, max_pop_px=job.max_pop_px)
    exact = Exact(prob.make, prob.key, cams, refs, budget_px, job.max_pop_px, job.cost_of, device, on_frame=bar,
                  terrains=dict(prob.terrains), started=job.t0, coarseness=prob.coarseness)
    t_model = time.perf_counter()
    if gradient == "pixels":
        good = _one_knob(exact, prob, budget_px, job.rel_tol, job.max_tries, newton=_pixel_newton(exact, prob))
    elif prob.cands:
        try:
            good = calibrated_search(exact, prob.cands, budget_px, prob.snap, rel_tol=job.rel_tol,
                                     max_tries=job.max_tries, on_step=bar)
            if good is not None:  # close the cost gap the model left on the exact pipeline's own bracket
                good = _main_line(exact, prob, good, budget_px, job.rel_tol, job.max_tries)
        except NonFiniteModel as e:  # never a NaN step: the main knob on the exact pipeline instead
            exact.history.append({"stage": "fallback", "reason": str(e), "to": "bracket_search"})
            good = _one_knob(exact, prob, budget_px, job.rel_tol, job.max_tries)
    else:
        good = _one_knob(exact, prob, budget_px, job.rel_tol, job.max_tries)
    res = _result(exact, prob, good, budget_px, job.cost_of)
    res.model_s = time.perf_counter() - t_model
    if job.max_pop_px is None and len(cams) > 1 and res.validated is not None:  # popping, for the record
        with part("exact"):
            res.validated = evaluate(res.scene, cams, refs, terrain=exact.terrain_for(res.scene), device=device,
                                     values=res.values, pops=True, cost_of=job.cost_of)
    with part("exact"):
        annotate(res, prob.all_knobs, cams, refs, job.vps, job.cost, tried=[*exact.evals.values()], floor=job.floor,
                 device=device)
    if grid_points:
        with part("exact"):
            res.grid = grid_search(exact, prob, grid_points, evaluator=grid_evaluator)
    return res


def _at_viewports(cams: list[Camera], viewports: Sequence[Sequence[float]] | None
                  ) -> tuple[list[Camera], list[Viewport]]:
    """The cameras at each of the checked viewports in turn (the first is the fitted scene's ``viewport``; the mean
    cost is over them all), and the viewports (None: the cameras as they are, no viewports)."""
    vps = _viewports(viewports)
    return [c.with_(width=v.width, height=v.height, fov_y_deg=v.fov_y_deg) for v in vps for c in cams] or cams, vps


def _viewports(viewports: Sequence[Sequence[float]] | None) -> list[Viewport]:
    """The checked viewports (empty for None)."""
    if viewports is None:
        return []
    if isinstance(viewports, str) or not isinstance(viewports, Sequence) or not viewports:
        raise TypeError(f"viewports: expected a list of (width, height, fov_y_deg), got {viewports!r}")
    out = []
    for i, v in enumerate(viewports):
        if not isinstance(v, Sequence) or len(v) != 3:
            raise TypeError(f"viewports[{i}]: expected (width, height, fov_y_deg), got {v!r}")
        try:
            out.append(Viewport.of(*v))
        except (TypeError, ValueError) as e:
            raise type(e)(f"viewports[{i}].{e}") from None
    return list(dict.fromkeys(out))


def _one_knob(exact: Exact, prob: Problem, budget_px: float, rel_tol: float, max_tries: int,
             newton=None) -> Evaluation | None:
    """The main knob on the exact pipeline alone (the other fitted knobs at the scene's values); ``newton``: the
    step before the budget is bracketed (:func:`terrainwarp.fit.search.bracket_search`)."""
    fixed = {n: v for n, v in prob.start.items() if n != prob.names[0]}
    return bracket_search(exact, prob.knob(prob.names[0]), fixed, budget_px, rel_tol=rel_tol,
                          max_tries=max(max_tries, 12), newton=newton)


def _main_line(exact: Exact, prob: Problem, good: Evaluation, budget_px: float, rel_tol: float,
               max_tries: int) -> Evaluation | None:
    """The main knob on the exact pipeline, the other knobs at the best setting's values, from the bracket the tries
    along that line give (:func:`terrainwarp.fit.search.bracket_search` with ``seed``): nothing is measured when a
    try there already lands within ``rel_tol`` under the budget (or the pop bound) or the bracket's cost gap is
    within ``rel_tol``."""
    if close_to_bound(exact, good, rel_tol):
        return good
    fixed = {n: v for n, v in good.values.items() if n != prob.names[0]}
    return bracket_search(exact, prob.knob(prob.names[0]), fixed, budget_px, rel_tol=rel_tol,
                          max_tries=max_tries, seed=True)


def _pixel_newton(exact: Exact, prob: Problem):
    """The continuous policy's Newton step in log(target_px) with the worst frame's pixel-error slope
    (:func:`terrainwarp.fit.diffpath.log_slope`), clamped to a factor e either way; recorded in the history."""
    from .diffpath import log_slope  # lazy: imports JAX

    name = prob.names[0]

    def step(e: Evaluation, log_target: float) -> float:
        v = float(e.values[name])
        sc = prob.make(e.values)
        order = e.frames if e.frames is not None else range(len(e.p99_px))
        w = list(order)[int(np.argmax(e.p99_px))]
        with part("relaxed"):
            _, slope = log_slope(sc.heightmap, exact.cams[w], v, sc.lod.level, exact.terrain_for(sc),
                                 cull_back=sc.cull_back, device=exact.device)
        exact.frames += 1
        exact.history.append({"stage": "pixel_slope", "value": v, "camera": w, "dlog_err_dlog_value": slope})
        s = (log_target - math.log(max(e.worst_p99, 1e-9))) / slope if slope > 1e-3 else \
            (1.0 if exact.meets(e) else -1.0)
        return v * math.exp(min(max(s, -1.0), 1.0))

    return step


def _check(scene: Scene, budget_px: float, policy: str, max_tries: int, grid_points: int,
           max_pop_px: float | None, steps: int | None) -> None:
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a Scene, got {type(scene).__name__}")
    check_int("max_tries", max_tries, 1)
    check_int("grid_points", grid_points, 0)
    if steps is not None:
        check_int("steps", steps, 1)
    check_choice("policy", policy, [*LOD_POLICIES, *SCHEMES])
    check_number("budget_px", budget_px, 0.0, lo_open=True)
    if max_pop_px is not None:
        check_number("max_pop_px", max_pop_px, 0.0)
    if isinstance(scene.heightmap, StreamedHeightmap):
        raise ValueError("scene.heightmap: fit_lod measures every frame against the full-resolution grid; fit on "
                         "StreamedHeightmap.load() (or a part of the terrain that fits)")


def _undrawn(ev: Evaluation) -> str:
    """Why a worst-frame p99 is infinite when a frame left visible samples undrawn (:data:`MISSING_TOL`)."""
    worst = max(ev.missing, default=0.0)
    return "" if worst <= MISSING_TOL else (f" (a frame leaves {worst:.2%} of its visible samples undrawn, over the "
                                            f"{MISSING_TOL:.1%} allowed)")


def _result(exact: Exact, prob: Problem, good: Evaluation | None, budget_px: float,
            cost_of: Cost | None) -> FitResult:
    """The fit's result: the cheapest setting measured on every camera that met the constraints, or, when none
    did, the finest setting of the main knob measured on every camera (met only if even that meets them)."""
    pop = exact.max_pop_px
    pop_txt = "" if pop is None else f" and worst pair pop p99 <= {pop:g} px"
    label = "triangles" if cost_of is None else cost_of.label
    common = {"history": exact.history, "max_pop_px": pop, "mesh_only_frames": exact.mesh_only, "cost": label,
              "knobs": list(prob.names), "trace": list(exact.trace), "trace_s": list(exact.trace_s)}
    if good is None:
        main = prob.knob(prob.names[0])
        finest = {**prob.start, main.name: main.lo if main.coarser_up is not False else main.hi}
        floor = exact(finest, stop=False, stage="floor")
        if exact.meets(floor):  # a setting that meets the budget is never reported impossible: the answer
            good = floor
        else:
            values = dict(floor.values)
            msg = (f"budget {budget_px:g} px{pop_txt} cannot be met: even the finest setting ({main.name} = "
                   f"{values[main.name]:g}) has a worst-frame p99 error of {floor.worst_p99:.3g} px"
                   + _undrawn(floor)
                   + ("" if pop is None else f" and a worst pair pop p99 of {floor.worst_pop:.3g} px"))
            return FitResult(prob.policy, budget_px, False, values, prob.make(values), floor, exact.frames,
                             0.0, msg, **common)
    values = dict(good.values)
    shown = ", ".join(f"{k} = {values[k]:.4g}" for k in prob.names)
    msg = (f"met: worst-frame p99 {good.worst_p99:.3g} px <= {budget_px:g} px"
           + ("" if pop is None else f", worst pair pop p99 {good.worst_pop:.3g} px <= {pop:g} px")
           + f" with {shown}, {good.cost:.4g} {label} per frame")
    return FitResult(prob.policy, budget_px, True, values, prob.make(values), good, exact.frames, 0.0, msg,
                     **common)
