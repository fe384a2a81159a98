"""Exact evaluation: a setting drawn by :func:`terrainwarp.render` from every camera of a path and measured, with
the accounting every method of a fit shares (frames measured, frames only meshed, the history of tries).

A setting is a :class:`Scene` (``mesh = "lod"``, its ``LodConfig``): the fit's knob values applied to the
scene (:func:`terrainwarp.fit.knobs.apply`). Its evaluation is the primary error of each frame
(``Frame.error.p99_px``, at the heightmap's samples), the frame's cost (triangles, a counter or a cost model) and,
when asked, the pop between consecutive frames. A setting with hysteresis draws the path in order with one
:class:`terrainwarp.lod.LodState`, as an application would.

:class:`Exact` is what a fit and every baseline call: one evaluation per setting (cached by its knob values),
frames measured counted in ``frames``, frames drawn only for their cost in ``mesh_only``. A try may measure the
cameras in a given order and stop at the first frame over the budget (the worst frame decides), and may measure
only some cameras (the others drawn for their cost); a later call completes it.

Frames a try draws whatever the others show (the cameras drawn only for their cost, every frame of a try that
does not stop early, the references) are drawn on other threads beside the measured sequence: which frames are
counted does not change, nor any frame (the kernels' outputs do not depend on the threads).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Collection, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..camera import Camera
from ..kernels.parallel import started, threads
from ..lod.quadtree import LodState, Terrain
from ..measure.cost import Cost
from ..rendering.pipeline import Frame, pop_stats, render
from ..rendering.rows import frame_row
from ..scene import Scene
from .timings import part

__all__ = ["Evaluation", "Exact", "evaluate", "evaluations_from_rows", "references_for", "MISSING_TOL"]

#: the share of a frame's visible samples that may have no drawn surface above them (a culled patch's border);
#: a setting that leaves more of the terrain undrawn (clipmaps with too few levels) does not meet any budget
MISSING_TOL = 1e-3


@dataclass
class Evaluation:
    """The exact pipeline at one setting over the camera path.

    ``p99_px``, ``max_px``, ``missing``: the primary error and the share of visible samples with no surface, per
    measured frame; ``image_p99_px``: the grid-image error per measured frame (secondary); ``pop_p99_px``: per
    consecutive pair (frame k-1 -> k), only when popping was measured (else empty); ``triangles`` and ``costs``:
    every frame's, in path order (``costs`` empty: the triangles are the cost). ``frames``: the cameras measured,
    in the order they were (None: all, in path order). ``visible``, ``covered``: per measured frame, the visible
    heightmap samples the p99 is taken over and the pixels the frame covers (empty when not recorded)."""

    values: dict[str, float]
    p99_px: list[float]
    max_px: list[float]
    triangles: list[int]
    frame_ms: list[float]
    image_p99_px: list[float] = field(default_factory=list)
    pop_p99_px: list[float] = field(default_factory=list)
    frames: list[int] | None = None
    costs: list[float] = field(default_factory=list)
    missing: list[float] = field(default_factory=list)
    visible: list[int] = field(default_factory=list)
    covered: list[int] = field(default_factory=list)

    @property
    def value(self) -> float:
        """The first knob's value (the one-knob fit's parameter)."""
        return next(iter(self.values.values()))

    @property
    def complete(self) -> bool:
        return self.frames is None or len(self.frames) == len(self.triangles)

    @property
    def worst_p99(self) -> float:
        """The worst measured frame's p99 (+inf where a frame leaves more than :data:`MISSING_TOL` undrawn)."""
        if any(m > MISSING_TOL for m in self.missing):
            return math.inf
        return max(self.p99_px) if self.p99_px else 0.0

    @property
    def worst_pop(self) -> float:
        """The worst pair's pop p99 (px); NaN when popping was not measured, 0 for one camera."""
        return max(self.pop_p99_px) if self.pop_p99_px else (math.nan if len(self.triangles) > 1 else 0.0)

    def meets(self, budget_px: float, max_pop_px: float | None = None) -> bool:
        """Worst-frame p99 within ``budget_px`` and, when given, the worst pair's pop p99 within ``max_pop_px``
        (a setting whose popping was not measured does not meet a pop bound)."""
        return self.worst_p99 <= budget_px and (max_pop_px is None or self.worst_pop <= max_pop_px)

    @property
    def cost(self) -> float:
        """The mean cost per frame: of ``costs``, or of the triangles when the cost is the triangles."""
        return float(np.mean(self.costs if self.costs else self.triangles))


def references_for(scene: Scene, cams: list[Camera], references: object = None, device: str = "cpu",
                   on_frame=None) -> list[Frame]:
    """The full-detail grid frame (with depth) of each camera: the caller's, checked, or rendered here."""
    if references is None:
        ahead = _ahead(lambda k, _: render(scene.with_(camera=cams[k], mesh="grid", outputs=("depth",)),
                                           device=device), [(k, True) for k in range(1, len(cams))])
        out = []
        for k, c in enumerate(cams):
            job = ahead.get((k, True))
            out.append(job.result() if job is not None else render(scene.with_(camera=c, mesh="grid",
                                                                              outputs=("depth",)), device=device))
            if on_frame is not None:
                on_frame()
        return out
    refs = list(references) if isinstance(references, list | tuple) else None
    if refs is None or len(refs) != len(cams):
        raise ValueError(f"references: expected a list of {len(cams)} frames (one per camera), got "
                         f"{type(references).__name__}{'' if refs is None else f' of {len(refs)}'}")
    for k, (f, c) in enumerate(zip(refs, cams, strict=True)):
        if not isinstance(f, Frame) or f.depth is None or f.scene.camera != c:
            raise ValueError(f"references[{k}]: expected the grid frame of cameras[{k}] with its depth")
    return refs


def _state_of(scene: Scene) -> LodState | None:
    """A path's hysteresis state for a quadtree setting with a band (None: frames are independent)."""
    return LodState() if not scene.lod.is_scheme and scene.lod.hysteresis > 0 else None


def evaluate(setting: Scene, cameras: list[Camera], refs: list[Frame], *, terrain: Terrain | None = None,
             device: str = "cpu", values: Mapping[str, float] | None = None, pops: bool = False,
             cost_of: Cost | None = None, order: list[int] | None = None, stop_above: float | None = None,
             measure: Collection[int] | None = None, known: Evaluation | None = None,
             on_frame: Callable[[], None] | None = None) -> Evaluation:
    """Draw ``setting`` from every camera and measure each frame against its reference (the full-detail grid frame
    of that camera, with depth).

    Args:
        setting: a LOD scene (``mesh = "lod"``), e.g. :func:`terrainwarp.fit.knobs.apply`'s.
        terrain: the :class:`terrainwarp.lod.Terrain` of a quadtree setting's (roots, tess), held by the caller.
        values: the knob values ``setting`` was made from (kept in the evaluation).
        pops: also the pop of each consecutive pair (:func:`terrainwarp.rendering.pipeline.pop_stats`).
        cost_of: the cost of a frame (None: its triangles); a cost of counters renders frames with ``"counters"``.
        order, stop_above: measure the cameras in ``order`` and stop at the first frame whose p99 exceeds
            ``stop_above``; the frames left are drawn only for their cost. Not with ``pops`` or hysteresis (whose
            frames depend on the ones before: they run in path order, and still stop at the first over).
        measure: measure only these cameras (the others only drawn for their cost).
        known: an earlier evaluation of the same setting whose measured cameras are taken as they are.
        on_frame: called after each measured frame (progress).
    """
    state = _state_of(setting)
    if (pops or state is not None) and (measure is not None or known is not None):
        raise ValueError("measure / known: a setting whose frames depend on the frame before (popping, "
                         "hysteresis) is measured on the whole path in order")
    n = len(cameras)
    if pops or state is not None:
        order = list(range(n))
    order = list(range(n)) if order is None else [int(k) for k in order]
    if sorted(order) != list(range(n)):
        raise ValueError(f"order: expected a permutation of the {n} camera indices, got {order!r}")
    if known is not None and (len(known.triangles) != n or known.values != dict(values or {})):
        raise ValueError("known: expected an evaluation of the same setting over the same cameras")
    ev = Evaluation(dict(values or {}), [], [], [0] * n, [], frames=[])
    done = {} if known is None else {k: i for i, k in enumerate(known.frames or range(n))}
    if known is not None:
        ev.triangles = list(known.triangles)
    costs = list(known.costs) if known is not None and known.costs else [0.0] * n
    counted = cost_of is not None and cost_of.needs_counters
    outputs = ("error", "counters") if counted else ("error",)

    def draw(k: int, measured: bool) -> Frame:
        if measured:
            return render(setting.with_(camera=cameras[k], outputs=outputs), terrain, state, refs[k], device=device)
        return render(setting.with_(camera=cameras[k], outputs=("counters",) if counted else ("mesh",)), terrain,
                      state, device=device)

    ahead = {} if state is not None or pops else _ahead(draw, _sure(order, done, measure, known, stop_above))
    prev: Frame | None = None
    stopped = False
    for k in order:
        if k in done:  # measured before at this setting
            _take_known(ev, known, k, done[k])
            continue
        stopped = stopped or (stop_above is not None and bool(ev.p99_px) and ev.worst_p99 > stop_above)
        if stopped or (measure is not None and k not in measure):  # cost only
            if known is None:
                f = ahead.pop((k, False)).result() if (k, False) in ahead else draw(k, False)
                ev.triangles[k] = int(f.mesh.n_triangles)
                costs[k] = cost_of.of(frame_row(f)) if cost_of is not None else 0.0
            continue
        f = ahead.pop((k, True)).result() if (k, True) in ahead else draw(k, True)
        costs[k] = _record(ev, k, frame_row(f), cost_of)
        if pops and prev is not None:
            ev.pop_p99_px.append(pop_stats(setting.with_(camera=cameras[k]), cameras[k - 1], f, refs[k],
                                           terrain=terrain, held=prev.patches, device=device).p99_px)
        prev = f
        if on_frame is not None:
            on_frame()
    ev.costs = costs if cost_of is not None else []
    if ev.complete:  # back to path order, as every complete evaluation
        back = sorted(range(len(ev.frames)), key=lambda i: ev.frames[i])
        for name in _PER_FRAME:
            if getattr(ev, name):
                setattr(ev, name, [getattr(ev, name)[i] for i in back])
        ev.frames = None
    return ev


_PER_FRAME = ("p99_px", "max_px", "missing", "image_p99_px", "frame_ms", "visible", "covered")


def _take_known(ev: Evaluation, known: Evaluation, k: int, i: int) -> None:
    """Camera ``k``'s measurements from ``known`` (its ``i``-th measured frame) appended to ``ev``."""
    ev.frames.append(k)
    for name in _PER_FRAME:
        theirs = getattr(known, name)
        if theirs:
            getattr(ev, name).append(theirs[i])


_FRAMES: dict = {}


def _sure(order: list[int], done: Collection[int], measure: Collection[int] | None, known: Evaluation | None,
          stop_above: float | None) -> list[tuple[int, bool]]:
    """The frames :func:`evaluate` draws whatever the others show, as (camera, measured): the cameras drawn only
    for their cost, and every measured one when nothing stops early."""
    sure = [(k, False) for k in order if known is None and k not in done and measure is not None and k not in measure]
    if stop_above is None:
        sure += [(k, True) for k in order if k not in done and (measure is None or k in measure)]
    return sure


def _ahead(draw: Callable[[int, bool], Frame], jobs: list[tuple[int, bool]]) -> dict:
    """``draw(k, measured)`` of each job started on the frame threads (as many as the kernel launches' threads,
    :func:`terrainwarp.kernels.parallel.threads`; one thread: none started): {job: future}. Every frame is the same
    whichever thread draws it (the kernels' outputs do not depend on the threads)."""
    if threads() < 2 or len(jobs) < 1:
        return {}
    started()  # Warp's runtime up before the threads launch kernels side by side
    pool = _FRAMES.get("pool")
    if pool is None or _FRAMES.get("pid") != os.getpid():
        pool = _FRAMES["pool"] = ThreadPoolExecutor(max_workers=threads(), thread_name_prefix="terrainwarp-frame")
        _FRAMES["pid"] = os.getpid()
    return {job: pool.submit(draw, *job) for job in jobs}


def _record(ev: Evaluation, k: int, row: Mapping[str, Any], cost_of: Cost | None) -> float:
    """Add camera ``k``'s measured frame (its row) to ``ev``; returns its cost (0 when the cost is triangles)."""
    ev.frames.append(k)
    ev.p99_px.append(float(row["p99_px"]))
    ev.max_px.append(float(row["max_px"]))
    seen = row["samples_visible"] + row["samples_missing"]
    ev.missing.append(float(row["samples_missing"]) / seen if seen else 0.0)
    ev.image_p99_px.append(float(row["image_err_p99_px"]))
    ev.frame_ms.append(row["frame_ms"])
    ev.visible.append(int(row["samples_visible"]))
    ev.covered.append(int(row["covered"]))
    ev.triangles[k] = int(row["triangles"])
    return cost_of.of(row) if cost_of is not None else 0.0


def evaluations_from_rows(rows: list[dict], policy: str, values: list[float], knob: str,
                          cost_of: Cost | None = None) -> list[Evaluation]:
    """The :class:`Evaluation` of each value of one knob from a sweep's rows
    (:func:`terrainwarp.experiments.pareto.sweep`: the job's ``policy``, ``param``, ``frame`` and ``error``, then
    :func:`terrainwarp.rendering.rows.frame_row`'s columns), for a grid search run on the sweep runner;
    ``cost_of``: the cost of each row (None: triangles). A failed row raises RuntimeError."""
    evs = []
    for v in values:
        rs = sorted((r for r in rows if r["policy"] == policy and r["param"] == v), key=lambda r: r["frame"])
        if any(r.get("error") for r in rs):
            raise RuntimeError(f"grid search: evaluating {policy} = {v:g} failed: {rs[0]['error']}")
        pops = [float(r["pop_p99_px"]) for r in rs[1:] if "pop_p99_px" in r]
        missing = [float(r["samples_missing"]) / max(r["samples_visible"] + r["samples_missing"], 1) for r in rs]
        evs.append(Evaluation({knob: v}, [r["p99_px"] for r in rs], [r["max_px"] for r in rs],
                              [int(r["triangles"]) for r in rs], [r["frame_ms"] for r in rs],
                              [float(r["image_err_p99_px"]) for r in rs if "image_err_p99_px" in r], pops,
                              costs=[] if cost_of is None else [cost_of.of(r) for r in rs], missing=missing))
    return evs


def prepared(terrains: dict[tuple, Terrain], heightmap, roots, tess: int, device: str) -> Terrain:
    """The Terrain of (roots, tess) from ``terrains``, prepared and kept there on first use."""
    key = (roots, tess)
    if key not in terrains:
        terrains[key] = Terrain.prepare(heightmap, roots=roots, tess=tess, device=device)
    return terrains[key]


# ------------------------------------------------------------------------------------------------
# the evaluator every method of a fit calls
# ------------------------------------------------------------------------------------------------
@dataclass
class Exact:
    """The exact pipeline over a camera path for one policy: one evaluation per setting (its snapped knob values),
    with the frames it measured (``frames``), the frames it drew only for their cost (``mesh_only``) and the
    history of tries.

    Attributes:
        make: knob values -> the setting's scene (:func:`terrainwarp.fit.knobs.apply` of the fit's scene).
        key: knob values -> the hashable key of the setting: its (name, snapped value) pairs, sorted.
        coarseness: knob values -> how far toward its coarse end the main knob is (0..1,
            :meth:`terrainwarp.fit.families.Problem.coarseness`): of settings with the same cost and worst error,
            the coarsest is the best (None: the smallest values).
    """

    make: Callable[[Mapping[str, float]], Scene]
    key: Callable[[Mapping[str, float]], tuple]
    cams: list[Camera]
    refs: list[Frame]
    budget_px: float
    max_pop_px: float | None = None
    cost_of: Cost | None = None
    device: str = "cpu"
    on_frame: Callable[[], None] | None = None
    frames: int = 0
    mesh_only: int = 0
    evals: dict[tuple, Evaluation] = field(default_factory=dict)
    history: list[dict] = field(default_factory=list)
    terrains: dict[tuple, Terrain] = field(default_factory=dict)
    trace: list[tuple[int, float]] = field(default_factory=list)  # (frames so far, best confirmed cost) per change
    trace_s: list[float] = field(default_factory=list)  # seconds from ``started`` to each change of ``trace``
    started: float = field(default_factory=time.perf_counter)
    coarseness: Callable[[Mapping[str, float]], float] | None = None

    def meets(self, e: Evaluation) -> bool:
        return e.meets(self.budget_px, self.max_pop_px)

    def terrain_for(self, setting: Scene) -> Terrain | None:
        """The Terrain of a quadtree setting's (roots, tess), prepared once (None for a scheme)."""
        lod = setting.lod
        if lod.is_scheme:
            return None
        return prepared(self.terrains, setting.heightmap, lod.roots, lod.tess, self.device)

    def __call__(self, values: Mapping[str, float], *, order: list[int] | None = None,
                 measure: Collection[int] | None = None, stop: bool = True, stage: str = "try") -> Evaluation:
        """The evaluation of the setting ``values``.

        Args:
            order: the order to measure the cameras in (default: path order).
            measure: measure only these cameras (a provisional try; the others drawn for their cost). A setting
                whose frames depend on each other (popping bound, hysteresis) is always measured whole.
            stop: stop at the first frame over the budget (the setting is infeasible whatever the rest say).
            stage: the history's label of this try.
        """
        key = self.key(values)
        old = self.evals.get(key)
        if old is not None and (old.complete or (measure is not None and set(measure) <= set(old.frames or ()))):
            return old
        setting = self.make(dict(key))
        whole = self.max_pop_px is not None or _state_of(setting) is not None
        with part("exact"):
            e = evaluate(setting, self.cams, self.refs, terrain=self.terrain_for(setting), device=self.device,
                         values=dict(key), pops=self.max_pop_px is not None,
                         cost_of=self.cost_of, order=None if whole else order,
                         stop_above=self.budget_px if stop else None,
                         measure=None if whole else measure, known=None if whole else old, on_frame=self.on_frame)
        n = len(self.cams)
        measured = n if e.frames is None else len(e.frames)
        before = 0 if old is None else (n if old.frames is None else len(old.frames))
        self.frames += measured - before
        if old is None:
            self.mesh_only += n - measured
        self.evals[key] = e
        self.history.append({"stage": stage, "values": dict(e.values), "worst_p99_px": e.worst_p99, "cost": e.cost,
                             "frames_measured": measured, "complete": e.complete, "frames_total": self.frames,
                             **({"worst_pop_p99_px": e.worst_pop} if self.max_pop_px is not None else {})})
        self._record()
        return e

    def best(self) -> Evaluation | None:
        """The cheapest evaluation measured on every camera that meets the constraints (None: none yet); of equal
        costs the one with the lower worst error, then the coarser (:meth:`rank`)."""
        ok = [e for e in self.evals.values() if e.complete and self.meets(e)]
        return min(ok, key=self.rank) if ok else None

    def rank(self, e: Evaluation) -> tuple:
        """The order of settings that meet the constraints: cost, worst p99, the main knob coarser first
        (``coarseness``: a cost plateau answers its coarsest setting tried, e.g. a tolerance of 63.9 px rather
        than 1 px where both draw the same frames), then the values."""
        return (e.cost, e.worst_p99, 0.0 if self.coarseness is None else -self.coarseness(e.values),
                tuple(e.values.values()))

    def _record(self) -> None:
        b = self.best()
        c = math.inf if b is None else b.cost
        if not self.trace or c < self.trace[-1][1]:
            self.trace.append((self.frames, c))
            self.trace_s.append(time.perf_counter() - self.started)

