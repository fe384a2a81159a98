"""Fit LOD thresholds against a screen-space error budget (pixels) at the lowest cost, with JAX and optax,
validated by the exact pipeline.

Parameters live in a :class:`LodParams` pytree (log-space, so every value stays positive):
``log_tolerance_px`` (the screen-space-error policy, malafeev2014 / Cesium), ``log_k`` (the distance
policy of deaconu2021: split within ``k`` node sizes), ``log_target_px`` (pixels per triangle edge of the
continuous fractional_odd factors). One policy is fitted at a time.

Relaxation (documented, and biased where said):

* Discrete policies: every node of the complete quadtree gets a split probability
  ``s = sigmoid((log metric - log threshold) / temperature)`` (sse: split above the tolerance; distance:
  split below ``k * size``), 0 at the deepest level and for culled nodes. A node is a drawn leaf with
  probability ``prod(ancestors' s) * (1 - s)``. Expected cost = sum of leaf probabilities times the
  patch's ``2 T^2`` triangles. Bias: the 2:1 balance pass's forced splits and the doubled edges are left
  out, so the relaxed cost is slightly low.
* Error: a leaf's screen error is taken as its projected geometric error (the d/dist estimate), and the
  frame's error as a soft maximum over leaves weighted by their probabilities. Bias: this estimate
  is pessimistic (maximum vertical error, seen face on) compared with the exact per-pixel p99, so the
  relaxed fit lands on a too-fine setting; the validation step corrects it.
* Continuous factors: ``f = softclamp(L * focal / (d * target), 1, 64)`` per edge from the edge's
  endpoints; cost ``2 * inner_u * inner_v`` per patch; the error of a patch at vertex spacing ``s`` is
  interpolated log-log between the geometric errors of the pyramid levels (spacing ``S_L / T``).
* The temperature anneals from 1 to 0.05 over the optimisation (optax Adam), so the relaxed selection
  approaches the exact one.

Validation: after the relaxed fit, the exact pipeline (select + tessellate + rasterize + the primary error
at the heightmap's samples, :mod:`terrainwarp.measure.sample_error`, which has no triangulation floor, so
small budgets are reachable) runs over the camera path, and the parameter is corrected by
Newton steps in log space, ``log t <- log t + (log budget - log p99) / slope``, with the slope
``d log(error) / d log(t)`` from ``jax.grad`` of the relaxed model, then bisection once bracketed. A
fit that misses the budget in validation is reported as missed, never as met.

A validation measures the cameras worst first (those ever over the budget, then by their latest p99) and
stops at the first frame over the budget: the worst frame decides, so an infeasible value costs one or two
measured frames, not the whole path; the frames left unmeasured are only selected and meshed for their
triangle count (``FitResult.mesh_only_frames``), so every validation's cost is the whole path's. A try is
provisional (:meth:`_Exact.plan`): it measures only the critical cameras (within half of the highest latest
p99, at least two, and any camera ever over the budget), less those that met the budget at the same or a
coarser value. The cameras skipped are measured once, when the search is over, on the value it returns; if
one of them is then over the budget, that value becomes the infeasible end and the search goes on, so a
fit's value is always measured on every camera. Before, a feasible try measured all 8 cameras: the 4097^2
fBm's sse 0.5 px fit at 1080p took 42 frames (five feasible tries). (Not with a popping bound, which needs
the consecutive pairs.)

Popping as a constraint: ``fit_lod(..., max_pop_px=P)`` also measures, per consecutive camera pair, the pop
between the previous camera's selection (held) and the current one, both drawn for the current camera
(:func:`terrainwarp.rendering.pipeline.pop_stats`), and accepts a value only if the worst pair's pop p99 is
within ``P`` as well. Coarser settings pop more, so the constraint moves the fit toward finer settings.

The schemes (:data:`terrainwarp.schemes.SCHEMES`: the ones engines ship, ``cdlod``'s first range,
``clipmaps``' ring size n, odd, ``chunked``'s pixel threshold, and any registered since) are fitted by the
same exact validation, but with no relaxed model (it exists only for the quadtree policies): the budget is
bracketed directly on the exact pipeline, by bisection in log space over the scheme's range
(:func:`terrainwarp.schemes.scheme_range`) until a feasible and an infeasible value are known, then
by the same log-log interpolation; clipmaps' n is snapped to odd integers.

Baseline: a grid search over the same parameter on the exact pipeline, in the same run.
"""

from __future__ import annotations

import math
import sys
import time
from collections import namedtuple
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap, StreamedHeightmap
from ..io.display import html_table
from ..io.files import save_figure
from ..kernels.checks import check_int, check_number
from ..lod.policies import ContinuousPolicy, continuous_factors, edge_pixels
from ..lod.quadtree import Terrain, node_metrics, select
from ..measure.cost import Cost
from ..measure.cost import cost as resolve_cost
from ..rendering.pipeline import Frame, pop_stats, render
from ..rendering.rows import frame_row
from ..scene import LOD_POLICIES, POLICY_TABLE, LodConfig, Scene
from ..schemes import SCHEMES, scheme_range, scheme_source

__all__ = ["LodParams", "FitResult", "Evaluation", "Knob", "knob", "fit_lod", "evaluate", "grid_search",
           "evaluations_from_rows", "relaxed_model", "plot_fit"]

LodParams = namedtuple("LodParams", [f"log_{s.field}" for s in POLICY_TABLE.values()],
                       defaults=[math.log(getattr(LodConfig(), s.field)) for s in POLICY_TABLE.values()])
LodParams.__doc__ = ("Fitted parameters (a pytree), in log space: ``log_`` + each policy's ``POLICY_TABLE`` field "
                     "(log_tolerance_px, log_k, log_target_px), defaults the logs of the LodConfig defaults.")
# A grid search's evaluator: the parameter values -> their exact evaluations, in the same order.
Evaluator = Callable[[list[float]], list["Evaluation"]]


class Knob(NamedTuple):
    """The one parameter a fit moves: its name, the range it searches, which way is coarser, and whether it
    is an odd integer (clipmaps' n)."""

    field: str
    fit_range: tuple[float, float]
    coarser_up: bool
    odd_integer: bool = False

    def snap(self, v: float) -> float:
        """``v`` clipped to the range (and to the next odd integer inside it for an odd-integer knob)."""
        lo, hi = self.fit_range
        v = float(np.clip(v, lo, hi))
        if self.odd_integer:
            v = float(int(math.ceil(v)) | 1)
            v = v if v <= hi else v - 2.0
        return v


def knob(policy: str, heightmap: Heightmap | None = None, cache: dict | None = None) -> Knob:
    """The fitted parameter of ``policy``: a quadtree policy's ``POLICY_TABLE`` row, or a scheme's
    :data:`SCHEMES` row with its range on ``heightmap`` (:func:`terrainwarp.schemes.scheme_range`)."""
    if policy in SCHEMES:
        if heightmap is None:
            raise ValueError(f"heightmap: the scheme {policy!r} has a range that depends on the heightmap")
        spec = SCHEMES[policy]
        return Knob(spec.parameter, scheme_range(policy, heightmap, cache=cache), not spec.larger_is_finer,
                    spec.odd_integer)
    spec = POLICY_TABLE[policy]
    return Knob(spec.field, spec.fit_range, spec.coarser_up)


@dataclass
class Evaluation:
    """The exact pipeline at one parameter value over the camera path.

    ``p99_px``, ``max_px``: the primary error per frame; ``image_p99_px``: the grid-image error per frame
    (secondary); ``pop_p99_px``: per consecutive pair (frame k-1 -> k, so one fewer than the frames), only
    when popping was measured (else empty); ``costs``: the fit's cost of every frame (a
    :class:`terrainwarp.measure.cost.Cost`; empty: the triangles are the cost)."""

    value: float
    p99_px: list[float]
    max_px: list[float]
    triangles: list[int]
    frame_ms: list[float]
    image_p99_px: list[float] = field(default_factory=list)
    pop_p99_px: list[float] = field(default_factory=list)
    # the cameras whose error was measured, in the order they were (None: all, in path order); a validation
    # stopped at the first frame over the budget measured only a prefix (its triangles are every frame's)
    frames: list[int] | None = None
    costs: list[float] = field(default_factory=list)  # every frame's, in path order, as the triangles

    @property
    def complete(self) -> bool:
        return self.frames is None or len(self.frames) == len(self.triangles)

    @property
    def worst_p99(self) -> float:
        return max(self.p99_px)

    @property
    def worst_pop(self) -> float:
        """The worst pair's pop p99 (px); NaN when popping was not measured, 0 for one camera."""
        return max(self.pop_p99_px) if self.pop_p99_px else (math.nan if len(self.p99_px) > 1 else 0.0)

    def meets(self, budget_px: float, max_pop_px: float | None = None) -> bool:
        """Worst-frame p99 within ``budget_px`` and, when given, the worst pair's pop p99 within
        ``max_pop_px`` (a value whose popping was not measured does not meet a pop bound)."""
        return self.worst_p99 <= budget_px and (max_pop_px is None or self.worst_pop <= max_pop_px)

    @property
    def cost(self) -> float:
        """The mean cost per frame: of ``costs``, or of the triangles when the cost is the triangles."""
        return float(np.mean(self.costs if self.costs else self.triangles))


@dataclass
class FitResult:
    """What a fit found, validated by the exact pipeline.

    Attributes:
        met: True only if the exact pipeline's worst-frame p99 error is within the budget (and the worst
            pair's pop p99 within ``max_pop_px`` when given).
        value: the fitted parameter (tolerance px, k, or target px); params: the LodParams pytree.
        validated: the exact evaluation at ``value`` (per-frame p99, max, image error p99, triangles, ms,
            and the pop p99 of each consecutive pair: measured once more for the record when ``max_pop_px``
            is None, not counted in ``evaluations``).
        evaluations: exact pipeline frame evaluations the fit used (the grid search's are in ``grid``).
        mesh_only_frames: frames of validations stopped at a frame over the budget that were only selected
            and meshed for their triangle count (not measured; milliseconds each; not in ``evaluations``).
        history: the relaxed optimisation (iteration, temperature, loss, cost, error proxy, value) and
            the validation steps.
        grid: the grid search baseline in the same run, or None.
    """

    policy: str
    budget_px: float
    met: bool
    value: float
    params: LodParams
    validated: Evaluation | None
    evaluations: int
    wall_s: float
    message: str = ""
    history: list[dict] = field(default_factory=list)
    grid: dict | None = None
    max_pop_px: float | None = None
    mesh_only_frames: int = 0
    cost: str = "triangles"  # what the fit minimised (a terrainwarp.measure.cost.Cost's name)

    def _repr_html_(self) -> str:
        """The fit in one HTML table (Jupyter): the message, then each camera of the validated value."""
        v = self.validated
        head = html_table(("policy", "budget_px", "met", "value", "worst p99 px", "triangles/frame",
                           "pipeline evaluations", "wall s"),
                          [(self.policy, self.budget_px, self.met, self.value, v.worst_p99 if v else math.nan,
                            v.cost if v else math.nan, self.evaluations, self.wall_s)], caption=self.message)
        if v is None or not v.complete:
            return head
        return head + html_table(("camera", "p99_px", "max_px", "triangles", "frame_ms"),
                                 [(k, *r) for k, r in enumerate(zip(v.p99_px, v.max_px, v.triangles, v.frame_ms))])

    def to_dict(self) -> dict:
        v = self.validated
        return {"policy": self.policy, "budget_px": self.budget_px, "max_pop_px": self.max_pop_px, "cost": self.cost,
                "met": self.met, "value": self.value, "params": self.params._asdict(), "message": self.message,
                "evaluations": self.evaluations, "mesh_only_frames": self.mesh_only_frames, "wall_s": self.wall_s,
                "error": "primary: per visible heightmap sample, px (terrainwarp.measure.sample_error); "
                         "image_p99_px: the per-pixel grid-image error (secondary, with a triangulation floor)",
                "validated": None if v is None else {"p99_px": v.p99_px, "max_px": v.max_px,
                                                     "image_p99_px": v.image_p99_px, "pop_p99_px": v.pop_p99_px,
                                                     "triangles": v.triangles, "frame_ms": v.frame_ms,
                                                     "worst_p99_px": v.worst_p99, "worst_pop_p99_px": v.worst_pop,
                                                     "mean_triangles": float(np.mean(v.triangles)),
                                                     "costs": v.costs, "mean_cost": v.cost},
                "history": self.history, "grid": self.grid}


# ------------------------------------------------------------------------------------------------
# exact pipeline
# ------------------------------------------------------------------------------------------------
def evaluate(scene: Scene, terrain: Terrain | None, cameras: list[Camera], policy: str, value: float,
             refs: list[Frame], device: str = "cpu", *, on_frame: Callable[[], None] | None = None,
             pops: bool = False, cache: dict | None = None, order: list[int] | None = None,
             stop_above: float | None = None, measure: Collection[int] | None = None,
             known: Evaluation | None = None, cost_of: Cost | None = None) -> Evaluation:
    """Run the exact pipeline at one parameter value over all cameras (references given); the frame cost
    is ``Report.frame_ms``; the error is the primary error (``Frame.error.p99_px``), the image error kept
    beside it. ``pops``: also the pop of each consecutive pair (the previous frame's selection held,
    :func:`terrainwarp.rendering.pipeline.pop_stats`). ``on_frame()`` is called after each frame (progress).

    ``order`` and ``stop_above`` (not with ``pops``): measure the cameras in that order and stop at the first
    frame whose p99 exceeds ``stop_above`` (the worst frame decides feasibility: the value is infeasible
    whatever the others measure); the frames left unmeasured are only selected and meshed (milliseconds), so
    the evaluation's triangles, its cost, are still every frame's. ``Evaluation.frames`` lists the cameras
    measured. ``measure`` (with ``order``): measure only these cameras, the others are only meshed (a
    provisional try, :class:`_Exact`). ``known``: an earlier evaluation at the same value whose measured
    cameras are taken as they are, not drawn again (completing a provisional try).

    A scheme (``policy`` in :data:`SCHEMES`; ``terrain`` unused) is drawn as its mesh source
    (:func:`terrainwarp.schemes.scheme_source`, its pyramids kept in ``cache`` across values).
    ``cost_of`` (a :class:`terrainwarp.measure.cost.Cost`; None: triangles): every frame's cost, in
    ``Evaluation.costs``; a cost of counters renders every frame with ``"counters"``."""
    if pops and (order is not None or stop_above is not None or measure is not None or known is not None):
        raise ValueError("order / stop_above / measure / known: popping is measured between consecutive frames of "
                         "the path")
    ev = Evaluation(float(value), [], [], [], [])
    src = scheme_source(policy, scene.heightmap, value, cache=cache, device=device) if policy in SCHEMES else None
    cfg = scene.lod if src is not None else scene.lod.with_policy(policy, value)
    counted = cost_of is not None and cost_of.needs_counters
    if order is not None or stop_above is not None or measure is not None or known is not None:
        return _evaluate_until(ev, scene, terrain, cameras, refs, cfg, src, device, on_frame,
                               list(range(len(cameras))) if order is None else [int(k) for k in order], stop_above,
                               None if measure is None else {int(k) for k in measure}, known, cost_of)
    prev: Frame | None = None
    for k, (cam, ref) in enumerate(zip(cameras, refs)):
        sc = scene.with_(camera=cam, mesh="lod" if src is None else "grid", lod=cfg,
                         outputs=("error", "counters") if counted else ("error",))
        f = render(sc, terrain=terrain, reference=ref, device=device, source=src)
        row = frame_row(f)
        ev.p99_px.append(float(row["p99_px"]))
        ev.max_px.append(float(row["max_px"]))
        ev.image_p99_px.append(float(row["image_err_p99_px"]))
        ev.triangles.append(int(row["triangles"]))
        ev.frame_ms.append(row["frame_ms"])
        if cost_of is not None:
            ev.costs.append(cost_of.of(row))
        if pops and prev is not None:
            ev.pop_p99_px.append(pop_stats(sc, cameras[k - 1], f, ref, terrain=terrain, source=src,
                                           held=None if src is not None else prev.patches, device=device).p99_px)
        prev = f
        if on_frame is not None:
            on_frame()
    return ev


def _evaluate_until(ev: Evaluation, scene: Scene, terrain: Terrain | None, cameras: list[Camera], refs: list[Frame],
                    cfg: LodConfig, src, device: str, on_frame: Callable[[], None] | None, order: list[int],
                    stop_above: float | None, measure: set[int] | None = None,
                    known: Evaluation | None = None, cost_of: Cost | None = None) -> Evaluation:
    """:func:`evaluate`'s frames in ``order``, stopping after the first whose p99 exceeds ``stop_above``; only
    the cameras in ``measure`` (None: all) are measured (the others only meshed, or counted when the cost is
    counters); those ``known`` measured are copied."""
    if sorted(order) != list(range(len(cameras))):
        raise ValueError(f"order: expected a permutation of the {len(cameras)} camera indices, got {order!r}")
    if known is not None and (known.value != ev.value or len(known.triangles) != len(cameras)):
        raise ValueError("known: expected an evaluation of the same value over the same cameras")
    done = {} if known is None else {k: i for i, k in enumerate(known.frames or range(len(cameras)))}
    tris = [0] * len(cameras) if known is None else list(known.triangles)
    costs = [0.0] * len(cameras) if known is None or not known.costs else list(known.costs)
    counted = cost_of is not None and cost_of.needs_counters
    ev.frames = []
    mesh = "lod" if src is None else "grid"
    for k in order:
        if k in done:  # measured before at this value
            i = done[k]
            ev.frames.append(k)
            for mine, theirs in ((ev.p99_px, known.p99_px), (ev.max_px, known.max_px),
                                 (ev.image_p99_px, known.image_p99_px), (ev.frame_ms, known.frame_ms)):
                mine.append(theirs[i])
            continue
        if (stop_above is not None and ev.p99_px and max(ev.p99_px) > stop_above) or \
                (measure is not None and k not in measure):  # infeasible, or not asked for: cost only
            if known is None:
                f = render(scene.with_(camera=cameras[k], mesh=mesh, lod=cfg,
                                       outputs=("counters",) if counted else ("mesh",)),
                           terrain=terrain, device=device, source=src)
                tris[k] = int(f.mesh.n_triangles)
                costs[k] = cost_of.of(frame_row(f)) if cost_of is not None else 0.0
            continue
        outputs = ("error", "counters") if counted else ("error",)
        sc = scene.with_(camera=cameras[k], mesh=mesh, lod=cfg, outputs=outputs)
        f = render(sc, terrain=terrain, reference=refs[k], device=device, source=src)
        row = frame_row(f)
        ev.frames.append(k)
        ev.p99_px.append(float(row["p99_px"]))
        ev.max_px.append(float(row["max_px"]))
        ev.image_p99_px.append(float(row["image_err_p99_px"]))
        ev.frame_ms.append(row["frame_ms"])
        tris[k] = int(row["triangles"])
        costs[k] = cost_of.of(row) if cost_of is not None else 0.0
        if on_frame is not None:
            on_frame()
    ev.triangles = tris
    ev.costs = costs if cost_of is not None else []
    return ev


def evaluations_from_rows(rows: list[dict], policy: str, values: list[float],
                          cost_of: Cost | None = None) -> list[Evaluation]:
    """The :class:`Evaluation` of each value from a sweep's rows (:func:`terrainwarp.experiments.pareto.sweep`:
    the job's ``policy``, ``param``, ``frame`` and ``error``, then :func:`terrainwarp.rendering.rows.frame_row`'s
    columns), for a grid search run on the sweep runner; ``cost_of``: the cost of each row (None: triangles).
    A failed row raises RuntimeError."""
    evs = []
    for v in values:
        rs = sorted((r for r in rows if r["policy"] == policy and r["param"] == v), key=lambda r: r["frame"])
        if any(r.get("error") for r in rs):
            raise RuntimeError(f"grid search: evaluating {policy} = {v:g} failed: "
                               f"{rs[0]['error']}")
        pops = [float(r["pop_p99_px"]) for r in rs[1:] if "pop_p99_px" in r]
        evs.append(Evaluation(v, [r["p99_px"] for r in rs], [r["max_px"] for r in rs],
                              [int(r["triangles"]) for r in rs], [r["frame_ms"] for r in rs],
                              [float(r["image_err_p99_px"]) for r in rs if "image_err_p99_px" in r], pops,
                              costs=[] if cost_of is None else [cost_of.of(r) for r in rs]))
    return evs


def grid_search(scene: Scene, terrain: Terrain | None, cameras: list[Camera], policy: str, budget_px: float,
                refs: list[Frame], points: int = 24, device: str = "cpu", evaluator: Evaluator | None = None, *,
                on_frame: Callable[[], None] | None = None, max_pop_px: float | None = None,
                cache: dict | None = None, cost_of: Cost | None = None) -> dict:
    """Evaluate ``points`` log-spaced values of the policy's fit range (:func:`knob`; a scheme's odd integers
    snapped, repeats dropped) on the exact pipeline; the cheapest that meets the budget (and ``max_pop_px``,
    the worst pair's pop p99, when given: then the pops are measured too).

    ``evaluator(values) -> [Evaluation]`` runs the evaluations; default: here, one after another, on the
    caller's ``terrain`` and ``refs`` (:func:`evaluate`). The command line (``terrainwarp fit --workers N``)
    passes one that runs them as jobs of the sweep runner (dask.distributed), whose workers prepare their
    own terrain and references; the table is the same. ``on_frame()`` is called once per frame evaluated
    (progress; after the evaluator returns when there is one). ``cost_of``: the cost (None: triangles).
    """
    check_int("points", points, 1)
    kn = knob(policy, scene.heightmap, cache)
    t0 = time.perf_counter()
    values = list(dict.fromkeys(kn.snap(v) for v in np.geomspace(*kn.fit_range, points)))
    if evaluator is None:
        evs = [evaluate(scene, terrain, cameras, policy, v, refs, device, on_frame=on_frame,
                        pops=max_pop_px is not None, cache=cache, cost_of=cost_of) for v in values]
    else:
        evs = evaluator(values)
        for _ in range(len(values) * len(cameras) if on_frame is not None else 0):
            on_frame()
    ok = [e for e in evs if e.meets(budget_px, max_pop_px)]
    best = min(ok, key=lambda e: e.cost) if ok else None
    return {"points": len(values), "evaluations": len(values) * len(cameras), "wall_s": time.perf_counter() - t0,
            "value": None if best is None else best.value, "cost": None if best is None else best.cost,
            "worst_p99_px": None if best is None else best.worst_p99,
            "table": [[e.value, e.worst_p99, e.cost] + ([e.worst_pop] if max_pop_px is not None else []) for e in evs]}


# ------------------------------------------------------------------------------------------------
# relaxed model (JAX)
# ------------------------------------------------------------------------------------------------
def _tree_arrays(terrain: Terrain, metrics: list) -> dict:
    """Stack per-camera node metrics into padded arrays the JAX model indexes."""
    depth = terrain.depth
    out = {"sse": [], "dist": [], "size": [], "vis": [], "parent": []}
    for lvl in range(depth + 1):
        m0 = metrics[0]
        x, y = m0.x[lvl], m0.y[lvl]
        nxl = terrain.roots[0] << lvl
        parent = ((y // 2) * (nxl // 2) + (x // 2)) if lvl > 0 else np.zeros(len(x), np.int64)
        out["parent"].append(parent.astype(np.int32))
        out["size"].append(m0.size[lvl])
        out["sse"].append(np.stack([m.sse[lvl] for m in metrics]))
        out["dist"].append(np.stack([m.dist[lvl] for m in metrics]))
        out["vis"].append(np.stack([(m.inside[lvl] & ~m.culled[lvl]).astype(np.float64) for m in metrics]))
    return out


def relaxed_model(terrain: Terrain, cameras: list[Camera], policy: str, device: str = "cpu"):
    """A function ``(log_value, temperature) -> (expected triangles per frame (mean), error proxy px (max
    over frames of the soft maximum))``, differentiable with JAX, for a discrete policy."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp

    metrics = [node_metrics(terrain, c, device) for c in cameras]
    tree = _tree_arrays(terrain, metrics)
    depth = terrain.depth
    tri_per_patch = 2.0 * terrain.tess ** 2
    sse = [jnp.asarray(np.minimum(a, 1e30)) for a in tree["sse"]]
    dist = [jnp.asarray(np.maximum(a, 1e-9)) for a in tree["dist"]]
    vis = [jnp.asarray(a) for a in tree["vis"]]
    size = [jnp.asarray(a) for a in tree["size"]]
    parent = [jnp.asarray(a) for a in tree["parent"]]

    def split_prob(lvl, log_v, temp):
        if lvl == depth:
            return jnp.zeros_like(vis[lvl])
        if policy == "sse":
            z = (jnp.log(jnp.maximum(sse[lvl], 1e-12)) - log_v) / temp
        else:  # distance: split while dist < k * size
            z = (log_v + jnp.log(size[lvl]) - jnp.log(dist[lvl])) / temp
        return jax.nn.sigmoid(z) * vis[lvl]

    def model(log_v, temp, err_temp=0.25):
        reach = vis[0]
        cost = 0.0
        lse = []
        for lvl in range(depth + 1):
            if lvl > 0:
                reach = reach_prev[:, parent[lvl]] * s_prev[:, parent[lvl]]  # noqa: F821
            s = split_prob(lvl, log_v, temp)
            leaf = reach * (1.0 - s) * vis[lvl]
            cost = cost + leaf.sum(axis=1) * tri_per_patch
            # soft maximum of the leaves' projected error, in log space: log sum p exp(log e / t)
            le = jnp.log(jnp.maximum(jnp.minimum(sse[lvl], 1e6), 1e-6))
            # weights leaf**4: leaves the policy almost surely does not draw do not leak into the maximum
            lse.append(4.0 * jnp.log(jnp.maximum(leaf, 1e-30)) + le / err_temp)
            reach_prev, s_prev = reach, s  # noqa: F841
        stacked = jnp.concatenate(lse, axis=1)
        soft_log_err = err_temp * jax.scipy.special.logsumexp(stacked, axis=1)
        return jnp.mean(cost), jnp.max(soft_log_err)  # (triangles, log error proxy)

    return model


# ------------------------------------------------------------------------------------------------
# the fit
# ------------------------------------------------------------------------------------------------
def fit_lod(scene: Scene, budget_px: float, policy: str = "sse", cameras: list[Camera] | None = None, *,
            steps: int = 60, max_validations: int = 8, rel_tol: float = 0.02, grid_points: int = 0,
            grid_evaluator: Evaluator | None = None, gradient: str = "relaxed", device: str = "cpu",
            progress: bool = False, max_pop_px: float | None = None,
            references: list[Frame] | None = None, cost: str | Cost | object = "triangles") -> FitResult:
    """Fit the ``policy``'s parameter so that the worst frame's p99 screen error over the camera path is
    within ``budget_px`` at the lowest cost (``cost``: triangles by default).

    Args:
        scene: the scene (heightmap, LOD config: roots, tess); its camera path unless ``cameras``.
        budget_px: the screen-space error budget, pixels (> 0).
        policy: ``"sse"``, ``"distance"`` or ``"continuous"`` (a row of ``terrainwarp.scene.POLICY_TABLE``), or
            a registered scheme, ``"cdlod"``, ``"clipmaps"``, ``"chunked"`` or yours (:data:`SCHEMES`, with the
            schemes' default settings: no relaxed fit, the budget bracketed on the exact pipeline; see the
            module docstring).
        steps: optax Adam steps of the relaxed fit (quadtree policies).
        max_validations: exact-pipeline validations (each runs every camera) for the correction.
        rel_tol: stop when the validated p99 lies within ``[budget * (1 - rel_tol), budget]``, or when a feasible
            and an infeasible value bracket the budget with triangle counts within ``rel_tol`` of each other
            (no value between them can be cheaper by more).
        grid_points: if > 0, also run the grid-search baseline with that many points.
        grid_evaluator: how the grid search runs its evaluations (None: in this process; see
            :func:`grid_search`).
        gradient: the slope of the correction steps before the budget is bracketed: ``"relaxed"`` (the
            calibrated relaxed model) or, for the continuous policy, ``"pixels"`` (Newton steps in log space
            with d log(mean pixel error above the p99) / d log(target_px) of the worst frame from
            :mod:`terrainwarp.fit.diffpath`: the per-pixel error through the Warp resolve kernel; one extra
            pipeline run per step, counted in ``evaluations``).
        progress: show a progress bar on stderr (tqdm): the reference frames, the relaxed fit's steps, the
            exact validations' frames and the grid search's frames.
        max_pop_px: if given, also bound the worst consecutive pair's pop p99 (px) over the path
            (:func:`terrainwarp.rendering.pipeline.pop_stats`; measured in every validation and grid point).
        references: the full-detail grid frames of ``cameras`` (with depth), one per camera, when the caller
            has them already (several fits on one path: a 4097^2 reference frame takes seconds); None: rendered
            here.
        cost: what the fit minimises, the mean per frame over the path (:func:`terrainwarp.measure.cost.cost`):
            ``"triangles"``, a counter name (``"fragment_shader_invocations"``, ...), ``"llvmpipe"`` (the
            shipped cost model), a :class:`terrainwarp.measure.cost.CostModel` or a weights file. The relaxed
            model steers by its expected triangles whatever the cost; the exact validations compare the cost
            (a cost of counters renders every validated frame with ``"counters"``).
    """
    _check_fit_arguments(budget_px, policy, gradient, steps, max_validations, grid_points)
    _check_fit_scene(scene, max_pop_px)
    cost_of = resolve_cost(cost)
    cost_of = None if cost_of.name == "triangles" else cost_of
    t_start = time.perf_counter()
    cams = cameras if cameras is not None else scene.camera_path()
    if not cams:
        raise ValueError("cameras: expected at least one camera")
    scheme = policy in SCHEMES
    bar = _Progress(progress, len(cams) * (1 + max_validations + grid_points) + (0 if scheme else steps),
                    f"fit {policy} {budget_px:g} px")
    try:
        terrain = None if scheme else Terrain.prepare(scene.heightmap, roots=scene.lod.roots, tess=scene.lod.tess,
                                                      device=device)
        refs = _references(scene, cams, references, bar, device)
        cache: dict = {}
        exact = _Exact(scene, terrain, cams, refs, policy, device, on_frame=bar, budget_px=budget_px,
                       max_pop_px=max_pop_px, knob=knob(policy, scene.heightmap, cache), cache=cache, cost_of=cost_of)
        if scheme:
            good = _bracket(exact, budget_px, rel_tol, max_validations)
        else:
            model = (_continuous_model(terrain, cams, scene.lod.level) if policy == "continuous"
                     else relaxed_model(terrain, cams, policy, device))
            v = _relaxed_fit(model, exact.knob.fit_range, budget_px, steps, exact.history, on_step=bar)
            good = _validate(exact, model, v, budget_px, rel_tol, max_validations, gradient)
        res = _result(exact, good, budget_px, t_start)
        if max_pop_px is None and len(cams) > 1:  # the chosen setting's popping, for the record (not counted)
            bar.expect(len(cams) * (1 + grid_points))
            res.validated = evaluate(scene, terrain, cams, policy, res.value, refs, device, on_frame=bar, pops=True,
                                     cache=cache, cost_of=cost_of)
        if grid_points:
            bar.expect(len(cams) * grid_points)  # the validations may have stopped early
            res.grid = grid_search(scene, terrain, cams, policy, budget_px, refs, grid_points, device,
                                   evaluator=grid_evaluator, on_frame=bar, max_pop_px=max_pop_px, cache=cache,
                                   cost_of=cost_of)
    finally:
        bar.close()
    return res


class _Progress:
    """A tqdm bar on stderr (``leave=False``, as the sweeps'), or nothing when disabled; call it to advance
    one step."""

    def __init__(self, enabled: bool, total: int, desc: str) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm  # lazy: heavy optional dependency

            self.bar = tqdm(total=total, desc=desc, unit="step", leave=False, file=sys.stderr)

    def __call__(self) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def after(self, x: object) -> object:
        """Advance one step and return ``x`` (for comprehensions)."""
        self()
        return x

    def expect(self, remaining: int) -> None:
        """Set the total to the steps done plus ``remaining``."""
        if self.bar is not None:
            self.bar.total = self.bar.n + remaining
            self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _references(scene: Scene, cams: list[Camera], references: object, bar: _Progress, device: str) -> list[Frame]:
    """The caller's reference frames (checked), or the full-detail grid frame of each camera rendered here."""
    if references is None:
        return [bar.after(render(scene.with_(camera=c, mesh="grid", outputs=("depth",)), device=device))
                for c in cams]
    refs = list(references) if isinstance(references, list | tuple) else None
    if refs is None or len(refs) != len(cams):
        raise ValueError(f"references: expected a list of {len(cams)} frames (one per camera), got "
                         f"{type(references).__name__}{'' if refs is None else f' of {len(refs)}'}")
    for k, (f, c) in enumerate(zip(refs, cams, strict=True)):
        if not isinstance(f, Frame) or f.depth is None or f.scene.camera != c:
            raise ValueError(f"references[{k}]: expected the grid frame of cameras[{k}] with its depth")
    for _ in refs:
        bar()
    return refs


def _check_fit_arguments(budget_px: float, policy: str, gradient: str, steps: int, max_validations: int,
                         grid_points: int) -> None:
    for name, n, least in (("steps", steps, 1), ("max_validations", max_validations, 1),
                           ("grid_points", grid_points, 0)):
        check_int(name, n, least)
    if policy not in LOD_POLICIES and policy not in SCHEMES:
        raise ValueError(f"policy: expected one of {[*LOD_POLICIES, *SCHEMES]}, got {policy!r}")
    if gradient not in ("relaxed", "pixels") or (gradient == "pixels" and policy != "continuous"):
        raise ValueError(f"gradient: expected 'relaxed', or 'pixels' with the continuous policy, got {gradient!r}")
    check_number("budget_px", budget_px, 0.0, lo_open=True)


def _check_fit_scene(scene: Scene, max_pop_px: float | None) -> None:
    if isinstance(scene.heightmap, StreamedHeightmap):
        raise ValueError("scene.heightmap: fit_lod measures every frame against the full-resolution grid and its "
                         "pyramids; fit on StreamedHeightmap.load() (or a part of the terrain that fits)")
    if max_pop_px is not None:
        check_number("max_pop_px", max_pop_px, 0.0)


@dataclass
class _Exact:
    """The exact pipeline over the camera path, one evaluation per value (snapped to the fit range,
    :meth:`Knob.snap`), with the count of frames it ran and the fit's history."""

    scene: Scene
    terrain: Terrain | None
    cams: list[Camera]
    refs: list[Frame]
    policy: str
    device: str
    history: list[dict] = field(default_factory=list)
    n_eval: int = 0
    n_mesh_only: int = 0  # frames of stopped validations only selected and meshed (their triangles)
    evals: dict[float, Evaluation] = field(default_factory=dict)
    on_frame: Callable[[], None] | None = None
    budget_px: float = math.inf
    max_pop_px: float | None = None
    knob: Knob | None = None
    cache: dict = field(default_factory=dict)
    over: set[int] = field(default_factory=set)  # cameras measured over the budget at some value
    latest: dict[int, float] = field(default_factory=dict)  # each camera's latest measured p99
    safe_at: dict[int, float] = field(default_factory=dict)  # the coarsest value each camera met the budget at
    cost_of: Cost | None = None  # the cost minimised (None: triangles)

    def meets(self, e: Evaluation) -> bool:
        return e.meets(self.budget_px, self.max_pop_px)

    def __call__(self, v: float, complete: bool = False, confirm: bool = False) -> Evaluation:
        """The evaluation at ``v`` (snapped).

        Without a pop bound, a try is *provisional*: it measures only the cameras :meth:`plan` gives, in its
        order, stopping at the first frame over the budget (:func:`evaluate`'s ``stop_above``). ``confirm``:
        every camera, still stopping at the first over the budget (the frames a provisional try measured are
        not drawn again); ``complete``: every camera measured, whatever its error."""
        v = self.knob.snap(v)
        old = self.evals.get(v)
        if old is not None and (old.complete or not (complete or confirm)):
            return old
        n = len(self.cams)
        if self.max_pop_px is not None or (complete and old is None):
            e = evaluate(self.scene, self.terrain, self.cams, self.policy, v, self.refs, self.device,
                         on_frame=self.on_frame, pops=self.max_pop_px is not None, cache=self.cache,
                         cost_of=self.cost_of)
        else:
            order, measure = self.plan(v)
            e = evaluate(self.scene, self.terrain, self.cams, self.policy, v, self.refs, self.device,
                         on_frame=self.on_frame, cache=self.cache, order=order,
                         stop_above=None if complete else self.budget_px,
                         measure=None if complete or confirm else measure, known=old, cost_of=self.cost_of)
            if e.complete:  # measured in another order: back to path order, as every complete evaluation
                back = sorted(range(len(e.frames)), key=lambda i: e.frames[i])
                e.p99_px, e.max_px, e.image_p99_px, e.frame_ms = (
                    [a[i] for i in back] for a in (e.p99_px, e.max_px, e.image_p99_px, e.frame_ms))
                e.frames = None
        for k, p in zip(e.frames or range(n), e.p99_px, strict=True):
            self.latest[k] = p
            if p > self.budget_px:
                self.over.add(k)
            elif k not in self.safe_at or _coarser(self.knob, v, self.safe_at[k]):
                self.safe_at[k] = v
        self.evals[v] = e
        measured = n if e.frames is None else len(e.frames)
        before = 0 if old is None else (n if old.frames is None else len(old.frames))
        self.n_eval += measured - before
        if old is None:
            self.n_mesh_only += n - measured
        self.history.append({"stage": "confirm" if old is not None else "validate", "value": v,
                             "worst_p99_px": e.worst_p99, "cost": e.cost, "frames_measured": measured,
                             **({"worst_pop_p99_px": e.worst_pop} if self.max_pop_px is not None else {})})
        return e

    def plan(self, v: float) -> tuple[list[int], set[int] | None]:
        """The order a try at ``v`` measures the cameras in, and the cameras a provisional try measures (None:
        all, for the first try).

        Order: the cameras ever over the budget first, then by their latest measured p99, highest first (the
        worst frame decides, so an infeasible value usually costs one frame). Measured: the critical cameras,
        those within half of the highest latest p99, at least two, and those ever over the budget; less the
        cameras measured within the budget at ``v`` or a coarser value (the error grows with coarser values).
        The others had slack when last measured. The value the search returns is confirmed on every camera
        (:func:`_search`), so a camera that lost its slack costs a further try, never a wrong result."""
        n = len(self.cams)
        if not self.latest:
            return list(range(n)), None
        order = sorted(range(n), key=lambda k: (k not in self.over, -self.latest.get(k, math.inf), k))
        top = max(self.latest.values())
        crit = set(order[:2]) | {k for k, p in self.latest.items() if p >= 0.5 * top} | self.over
        safe = {k for k, at in self.safe_at.items() if at == v or _coarser(self.knob, at, v)}
        return order, (crit - safe) or {order[0]}  # at least one camera: a try has an error


# -- relaxed fit -----------------------------------------------------------------------------------
def _relaxed_fit(model: Callable, fit_range: tuple[float, float], budget_px: float, steps: int,
                 history: list[dict], on_step: Callable[[], None] | None = None) -> float:
    """optax Adam on the relaxed loss ``log(cost) + 20 softplus(log error - log budget)``, the temperature
    annealed from 1 to 0.05, from the middle of the fit range (log space). Returns the value found;
    ``on_step()`` is called after each step (progress)."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp
    import optax

    lo, hi = fit_range
    log_budget = math.log(budget_px)
    tri_scale = float(model(jnp.asarray(math.log(math.sqrt(lo * hi))), 1.0)[0]) + 1.0

    def loss(log_v, temp, weight):
        cost, log_err = model(log_v, temp)
        return jnp.log(cost / tri_scale + 1e-9) + weight * jax.nn.softplus(8.0 * (log_err - log_budget)) / 8.0

    opt = optax.adam(0.08)
    log_v = jnp.asarray(math.log(math.sqrt(lo * hi)))
    state = opt.init(log_v)
    grad = jax.jit(jax.value_and_grad(loss), static_argnums=())
    for it in range(steps):
        temp = float(1.0 * (0.05 / 1.0) ** (it / max(steps - 1, 1)))
        val, g = grad(log_v, temp, 20.0)
        upd, state = opt.update(g, state)
        log_v = jnp.clip(optax.apply_updates(log_v, upd), math.log(lo), math.log(hi))
        if it % 10 == 0 or it == steps - 1:
            c, le = model(log_v, temp)
            history.append({"stage": "relaxed", "iter": it, "temperature": temp, "loss": float(val),
                            "cost": float(c), "error_proxy_px": float(math.exp(float(le))),
                            "value": float(math.exp(float(log_v)))})
        if on_step is not None:
            on_step()
    return float(math.exp(float(log_v)))


# -- exact validation ------------------------------------------------------------------------------
def _search(exact: _Exact, v: float, step: Callable, rel_tol: float, max_validations: int) -> Evaluation | None:
    """The search both fits share: up to ``max_validations`` provisional tries (:meth:`_Exact.__call__`), the
    next value from ``step(e, good, bad)`` (None: stop), then the coarsest feasible value confirmed on every
    camera. A confirmation that fails makes that value the infeasible end, and the search goes on from the
    coarsest feasible value finer than it (three more tries), so what is returned was measured on every
    camera. Returns the confirmed evaluation, or None when nothing met the budget."""
    kn = exact.knob
    good: Evaluation | None = None  # feasible (met), coarsest so far
    bad: Evaluation | None = None  # infeasible, finest so far
    tries = 0
    nv: float | None = v
    for _ in range(3 * max_validations + 8):  # a bound: each pass makes a try or confirms one value
        if nv is not None and tries < max_validations:
            tries += 1
            e = exact(nv)
            if exact.meets(e):
                if good is None or _coarser(kn, e.value, good.value):
                    good = e
            elif bad is None or _coarser(kn, bad.value, e.value):
                bad = e
            if exact.meets(e) and e.worst_p99 >= exact.budget_px * (1 - rel_tol):
                nv = None  # within rel_tol under the budget: close enough (rel_tol, fit_lod)
            else:
                nv = step(e, good, bad)
            if nv is not None:
                nv = kn.snap(nv)
                exact.history.append({"stage": "correct", "next_value": nv})
            continue
        if good is None or good.complete:
            return good
        c = exact(good.value, confirm=True)
        if exact.meets(c):
            return c
        bad = c
        finer = [x for x in exact.evals.values() if exact.meets(x) and _coarser(kn, c.value, x.value)]
        good = max(finer, key=lambda x: x.value if kn.coarser_up else -x.value) if finer else None
        tries = min(tries, max_validations - 3)  # three more tries in the bracket just narrowed
        nv = step(c, good, bad)
        nv = None if nv is None else kn.snap(nv)
    return good if good is not None and good.complete else None


def _validate(exact: _Exact, model: Callable, v: float, budget_px: float, rel_tol: float, max_validations: int,
              gradient: str) -> Evaluation | None:
    """Correct the relaxed value on the exact pipeline; the coarsest value that met the budget (None: none).

    The relaxed error is an estimate: calibrate it on the exact pipeline. Each round evaluates the exact
    pipeline once, sets the offset between exact and relaxed log error there, and solves the relaxed
    model (monotone in the parameter) for the budget with that offset; once a feasible and an
    infeasible value bracket the budget, interpolate in log-log between them (regula falsi)."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp

    spec = exact.knob
    log_model = jax.jit(lambda lv: model(lv, 0.05)[1])
    target = math.log(budget_px * (1.0 - 0.5 * rel_tol))

    def step(e: Evaluation, good: Evaluation | None, bad: Evaluation | None) -> float | None:
        if good is not None and bad is not None:
            return _bracket_step(good, bad, target, rel_tol)
        if gradient == "pixels":
            return float(np.clip(_pixel_step(exact, e, e.value, target, budget_px), *spec.fit_range))
        # an error far below the budget (the primary error is often exactly 0 at fine settings) says only
        # "feasible": calibrating on it would throw the next try to the end of the range
        v = e.value
        offset = math.log(max(e.worst_p99, 0.25 * budget_px)) - float(log_model(jnp.asarray(math.log(v))))
        nv = _solve_relaxed(log_model, spec.fit_range, offset, target)
        # Not bracketed yet: move at least a factor e the right way (coarser after a feasible value,
        # finer after an infeasible one). The exact error is flat over wide ranges (whole levels,
        # the triangulation floor), where a calibrated step alone can stall.
        # After a feasible value with an error under a quarter of the budget, at least e^2: a try that
        # overshoots costs one to three frames (worst camera first), a feasible one its critical cameras.
        coarser = exact.meets(e) == spec.coarser_up
        f = math.e ** 2 if exact.meets(e) and e.worst_p99 < 0.25 * budget_px else math.e
        nv = max(nv, v * f) if coarser else min(nv, v / f)
        return float(np.clip(nv, *spec.fit_range))

    return _search(exact, v, step, rel_tol, max_validations)


def _bracket(exact: _Exact, budget_px: float, rel_tol: float, max_validations: int) -> Evaluation | None:
    """A scheme's fit without a relaxed model: bisection in log space over the knob's range, the fine end
    taken as feasible and the coarse end as not until evaluated, then, once a feasible and an infeasible
    value are known, :func:`_bracket_step`. The coarsest value that met the budget (None: none)."""
    kn = exact.knob
    fine, coarse = (kn.fit_range[0], kn.fit_range[1]) if kn.coarser_up else (kn.fit_range[1], kn.fit_range[0])
    target = math.log(budget_px * (1.0 - 0.5 * rel_tol))

    def step(e: Evaluation, good: Evaluation | None, bad: Evaluation | None) -> float | None:
        if good is not None and bad is not None:
            nv = _bracket_step(good, bad, target, rel_tol)
        else:
            a = good.value if good is not None else fine
            b = bad.value if bad is not None else coarse
            nv = math.sqrt(a * b) if abs(math.log(a / b)) >= _narrow(rel_tol) else None
        if nv is None or kn.snap(nv) in exact.evals:  # nothing left to learn in the bracket
            return None
        return nv

    return _search(exact, kn.snap(math.sqrt(fine * coarse)), step, rel_tol, max_validations)


def _bracket_step(good: Evaluation, bad: Evaluation, target: float, rel_tol: float) -> float | None:
    """The next value between a feasible and an infeasible one (log-log interpolation), or None when
    refining cannot pay: cost is monotone in the parameter, so nothing in the bracket is cheaper than
    bad.cost and the remaining gain is at most the cost gap; the exact error is a step function of the
    parameter (discrete levels), so a narrow bracket is as far as refining can go.

    The step goes 0.5-0.7 of the way from the feasible end to the infeasible one (log bracket). The
    worst-frame error is flat over parts of a bracket and then jumps (whole levels change at once), where
    plain regula falsi crawls from one end: from the infeasible end for the DEM's distance policy at 0.5 px
    (1080p: five tries at 0.52-0.53 px, each 2% closer, until the tries ran out, 4.2% above the grid), from
    the feasible end for its sse policy at 2 px (1080p: three tries at 1.949 px, 8 frames each). A feasible
    try measures every frame and an infeasible one usually one (worst camera first), hence the lean."""
    lg, lb = math.log(good.value), math.log(bad.value)
    if good.cost - bad.cost <= rel_tol * good.cost or abs(lg - lb) < _narrow(rel_tol):
        return None
    # errors far below the budget (0 at fine settings) are clamped to a quarter of it, so the step does not
    # crawl from the feasible end of the bracket
    floor = target - math.log(4.0)
    eg, eb = max(math.log(max(good.worst_p99, 1e-12)), floor), max(math.log(max(bad.worst_p99, 1e-12)), floor)
    t = (target - eg) / (eb - eg) if eb > eg else 0.5
    t = min(max(t, 0.5), 0.7)  # at least halfway, leaning to the infeasible end (see above)
    return math.exp(lg + t * (lb - lg))


def _narrow(rel_tol: float) -> float:
    """The log width under which a bracket is not refined: 2 ``rel_tol`` (0.04 at the default 2%). The exact
    error is a step function of the parameter (discrete levels), so inside a narrower bracket a try
    rarely lands on another step; a feasible try costs the whole path. At 4 ``rel_tol`` the DEM's distance
    2 px and continuous 1 px fits stopped with 7-10% cost gaps left that one more try closed."""
    return 2.0 * rel_tol


def _pixel_step(exact: _Exact, e: Evaluation, v: float, target: float, budget_px: float) -> float:
    """A Newton step in log space with the worst frame's pixel-error slope (:func:`diffpath.log_slope`)."""
    from .diffpath import log_slope  # lazy: imports JAX

    sc = exact.scene
    w = int(np.argmax(e.p99_px))
    w = w if e.frames is None else e.frames[w]  # a stopped validation measured cameras e.frames
    _, slope = log_slope(sc.heightmap, exact.cams[w], v, sc.lod.level, exact.terrain, cull_back=sc.cull_back,
                         device=exact.device)
    exact.n_eval += 1
    exact.history.append({"stage": "pixel_slope", "value": v, "camera": w, "dlog_err_dlog_value": slope})
    step = (target - math.log(max(e.worst_p99, 1e-9))) / slope if slope > 1e-3 else \
        (1.0 if exact.meets(e) == exact.knob.coarser_up else -1.0)
    return v * math.exp(min(max(step, -1.0), 1.0))


def _solve_relaxed(log_model: Callable, fit_range: tuple[float, float], offset: float, target: float) -> float:
    """The value where the relaxed log error plus ``offset`` equals ``target`` (bisection in log space;
    without a sign change, the end of the range nearest the target)."""
    import jax.numpy as jnp  # lazy: heavy optional dependency

    a, b = math.log(fit_range[0]), math.log(fit_range[1])
    fa = float(log_model(jnp.asarray(a))) + offset - target
    fb = float(log_model(jnp.asarray(b))) + offset - target
    if fa * fb > 0:  # no sign change: the end nearest the target
        return math.exp(a if abs(fa) < abs(fb) else b)
    for _ in range(40):
        m = 0.5 * (a + b)
        fm = float(log_model(jnp.asarray(m))) + offset - target
        if (fm > 0) == (fa > 0):
            a, fa = m, fm
        else:
            b = m
    return math.exp(0.5 * (a + b))


def _result(exact: _Exact, good: Evaluation | None, budget_px: float, t_start: float) -> FitResult:
    """The fit's result: the coarsest feasible value, or the finest setting when none met the budget (then
    reported as met only if even that is within it); wall time from ``t_start`` (``time.perf_counter``)."""
    policy, pop = exact.policy, exact.max_pop_px
    spec = exact.knob
    pop_txt = "" if pop is None else f" and worst pair pop p99 <= {pop:g} px"
    if good is None:  # never met: is the budget reachable at all?
        finest = spec.fit_range[0] if spec.coarser_up else spec.fit_range[1]
        floor = exact(finest, complete=True)  # the worst frame's error, for the message
        if not exact.meets(floor):
            msg = (f"budget {budget_px:g} px{pop_txt} cannot be met: even the finest setting ({spec.field} = "
                   f"{finest:g}) has a worst-frame p99 error of {floor.worst_p99:.3g} px"
                   + ("" if pop is None else f" and a worst pair pop p99 of {floor.worst_pop:.3g} px"))
            return FitResult(policy, budget_px, False, finest, _params(policy, finest), floor, exact.n_eval,
                             time.perf_counter() - t_start, msg, exact.history, max_pop_px=pop,
                             mesh_only_frames=exact.n_mesh_only, cost=_cost_name(exact.cost_of))
        good = floor
    res = FitResult(policy, budget_px, exact.meets(good), good.value, _params(policy, good.value), good,
                    exact.n_eval, time.perf_counter() - t_start, "", exact.history, max_pop_px=pop,
                    mesh_only_frames=exact.n_mesh_only, cost=_cost_name(exact.cost_of))
    res.message = (f"met: worst-frame p99 {good.worst_p99:.3g} px <= {budget_px:g} px"
                   + ("" if pop is None else f", worst pair pop p99 {good.worst_pop:.3g} px <= {pop:g} px")
                   + f" with {spec.field} = {good.value:.4g}, {good.cost:.4g} {res.cost} per frame")
    return res


def _cost_name(c: Cost | None) -> str:
    return "triangles" if c is None else c.label


def _coarser(kn: Knob, a: float, b: float) -> bool:
    return a > b if kn.coarser_up else a < b


def _params(policy: str, value: float) -> LodParams:
    """The LodParams of a fitted quadtree policy; a scheme's parameter is not one of them (the defaults)."""
    if policy in SCHEMES:
        return LodParams()
    return LodParams()._replace(**{f"log_{POLICY_TABLE[policy].field}": math.log(value)})


def _continuous_frame(terrain: Terrain, cam: Camera, level: int) -> tuple[np.ndarray, ...]:
    """What the continuous relaxed model needs of one camera: the patches' projected edge lengths
    (:func:`terrainwarp.lod.edge_pixels`, unclamped), eye distances, geometric errors per pyramid level at
    each patch, the levels' vertex spacings (cells) and the patches' sides (cells)."""
    pl = select(terrain, cam, ContinuousPolicy(1.0, level=level))
    edge_px = edge_pixels(terrain.heightmap, cam.position, cam.focal_px, pl.origin, pl.size)
    dist = np.maximum(pl.distance.astype(np.float64), 1e-9)
    # geometric error against vertex spacing (in cells), log-log through the pyramid levels
    errs = []
    for L in range(terrain.depth + 1):
        cells = terrain.root_cells / 2 ** L
        k = np.floor(pl.origin_cells / cells).astype(np.int64)
        st = terrain.stats[L][2]
        k[:, 0] = np.clip(k[:, 0], 0, st.shape[1] - 1)
        k[:, 1] = np.clip(k[:, 1], 0, st.shape[0] - 1)
        errs.append(st[k[:, 1], k[:, 0]].astype(np.float64))
    spacing = np.array([terrain.root_cells / 2 ** L / terrain.tess for L in range(terrain.depth + 1)])
    return edge_px, dist, np.stack(errs, 1), spacing, pl.size_cells.astype(np.float64)


def _continuous_model(terrain: Terrain, cameras: list[Camera], level: int) -> Callable:
    """Relaxed cost/error of the continuous policy: the policy's factor rule
    (:func:`terrainwarp.lod.continuous_factors`) with a soft clamp."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp

    focal = cameras[0].focal_px
    per_cam = [_continuous_frame(terrain, cam, min(level, terrain.depth)) for cam in cameras]

    def softclamp(x, a, b, t=0.5):
        return a + t * jax.nn.softplus((x - a) / t) - t * jax.nn.softplus((x - b) / t)

    def model(log_target, temp, err_temp=0.25):
        costs, errs = [], []
        for edge_px, dist, gerr, spacing, size_cells in per_cam:
            _, inner = continuous_factors(jnp.asarray(edge_px), jnp.exp(log_target), xp=jnp,
                                          clamp=lambda x, a, b: softclamp(x, a, b, jnp.maximum(temp, 0.05)))
            inner_u, inner_v = inner[:, 0], inner[:, 1]
            costs.append(jnp.sum(2.0 * inner_u * inner_v))
            s = jnp.asarray(size_cells) / jnp.maximum(0.5 * (inner_u + inner_v), 1.0)  # cells per segment
            ls = jnp.log(jnp.asarray(spacing))
            le = jnp.log(jnp.maximum(jnp.asarray(gerr), 1e-9))
            # interpolate log error at log spacing (spacing decreases with level)
            x = jnp.log(jnp.maximum(s, 1e-9))
            e = jax.vmap(lambda xi, lei, lsr=ls[::-1]: jnp.interp(xi, lsr, lei[::-1]))(x, le)
            sse = e + jnp.log(focal) - jnp.log(jnp.asarray(dist))  # log of the projected error, px
            errs.append(err_temp * jax.scipy.special.logsumexp(sse / err_temp))
        return jnp.mean(jnp.stack(costs)), jnp.max(jnp.stack(errs))

    return model


def plot_fit(result: FitResult, path: str | Path, budgets_curve: list[tuple[float, float]] | None = None) -> Path:
    """fit.png: the relaxed optimisation (cost and error proxy against iteration), the exact validation steps
    with the chosen try marked, and, if given, the fitted cost against the budget. Legends sit below the
    panels, clear of the curves."""
    import matplotlib  # lazy: heavy optional dependency

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rel = [h for h in result.history if h.get("stage") == "relaxed"]
    val = [h for h in result.history if h.get("stage") == "validate"]
    n = 3 if budgets_curve else 2
    fig, ax = plt.subplots(1, n, figsize=(5 * n, 4.6))
    if rel:
        _plot_relaxed(ax[0], rel, result.budget_px)
    if val:
        _plot_validation(ax[1], val, result)
    if budgets_curve:
        b, c = zip(*budgets_curve)
        ax[2].plot(b, c, "o-")
        ax[2].set_xscale("log")
        ax[2].set_yscale("log")
        ax[2].set_xlabel("budget (px)")
        ax[2].set_ylabel("fitted triangles per frame")
        ax[2].set_title("cost against budget")
    fig.tight_layout()
    return save_figure(fig, path, dpi=100, bbox_inches="tight")


def _legend_below(ax, handles: list) -> None:
    """One legend for ``handles`` under the axes' x label, outside the plotting area."""
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize=8, frameon=False)


def _plot_relaxed(ax, rel: list[dict], budget_px: float) -> None:
    it = [h["iter"] for h in rel]
    (cost,) = ax.plot(it, [h["cost"] for h in rel], "o-", label="expected triangles")
    ax.set_yscale("log")
    a2 = ax.twinx()
    (err,) = a2.plot(it, [h["error_proxy_px"] for h in rel], "s--", color="C1", label="error proxy (px)")
    budget = a2.axhline(budget_px, color="C1", lw=0.8, ls=":", label="budget (px)")
    ax.set_xlabel("iteration (relaxed, annealed)")
    ax.set_title("relaxed fit")
    _legend_below(ax, [cost, err, budget])


def _plot_validation(ax, val: list[dict], result: FitResult) -> None:
    x = list(range(len(val)))
    (tries,) = ax.plot(x, [h["worst_p99_px"] for h in val], "o-", label="exact worst-frame p99 (px)")
    budget = ax.axhline(result.budget_px, color="r", ls=":", label="budget")
    handles = [tries, budget]
    chosen = [i for i, h in enumerate(val) if h["value"] == result.value]
    if chosen:
        i = chosen[-1]
        (mark,) = ax.plot([i], [val[i]["worst_p99_px"]], "*", ms=16, color="C2", markeredgecolor="k", zorder=5,
                          label=f"chosen: {result.value:.4g}")
        handles.append(mark)
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xlabel("exact validation (try)")
    ax.set_title(f"validation: {'met' if result.met else 'MISSED'}")
    _legend_below(ax, handles)
