"""Each family's fit problem: its knobs split into the continuous ones a model differentiates and the integer ones
enumerated, and one model (:mod:`terrainwarp.fit.relaxed`) per integer combination, on its probes
(:mod:`terrainwarp.fit.probe`).

A family with a model: ``sse`` and ``distance`` (one :class:`terrainwarp.fit.relaxed.QuadtreeModel` per ``tess``).
The others (and a registered scheme of yours) are fitted on the exact pipeline alone
(:func:`terrainwarp.fit.search.bracket_search`, one knob).
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..lod.cdlod import CdlodSelection
from ..lod.quadtree import PatchList, Terrain, uniform_patches
from ..measure.cost import Cost
from ..mesh import Mesh
from ..rendering.pipeline import Frame, render
from ..rendering.sources import scene_source
from ..scene import POLICY_TABLE, Scene
from .exact import prepared, references_for
from .jaxrt import use_cache
from .knobs import LEVEL_SCALE, Knob, apply, knobs, values_of
from .ladder import ladder_surfaces
from .probe import Sight, pop_pairs, probe_cameras, sight, surfaces_of
from .search import Calibration, Candidate
from .timings import say

__all__ = ["Problem", "problem", "relaxed_model", "MODELLED", "POPPED", "FEATURES", "cost_weights"]

#: the families with a model
MODELLED = ("sse", "distance", "continuous", "cdlod")
#: the families whose model predicts popping as well (a fit with a pop bound); the others are fitted with one on
#: the exact pipeline alone
POPPED = ("sse", "distance")

#: what the models count of a frame's draws, and the pipeline counters each stands for
FEATURES = {"patches": ("tess_control_shader_patches",), "domain_points": ("tess_evaluation_shader_invocations",),
            "triangles": ("primitives_generated", "triangles", "clipping_input_primitives",
                          "clipping_output_primitives"),
            "vertices": ("vertex_shader_invocations", "vertex_shader_invocations_llvmpipe", "vertices_submitted"),
            "draw_calls": ("draw_calls",)}


def cost_weights(cost: Cost | None) -> dict[str, float]:
    """The weight of each model feature in the fit's cost: triangles (None), one counter, or a cost model's
    weights on the counters the features stand for (the others are not modelled)."""
    if cost is None or cost.name == "triangles":
        return {"triangles": 1.0}
    weights = cost.model.weights if cost.model is not None else {cost.name: 1.0}
    out: dict[str, float] = {}
    for feat, counters in FEATURES.items():
        w = sum(float(weights.get(c, 0.0)) for c in counters)
        if w:
            out[feat] = w
    return out or {"triangles": 1e-6}  # a cost of what no model counts: its gradient is left to the exact tries


@dataclass
class Problem:
    """A fit's problem: the family's knobs, those fitted, how a setting becomes a scene and its key.

    Attributes:
        policy: the family.
        all_knobs: every knob of the family (:func:`terrainwarp.fit.knobs`).
        names: the knobs fitted, the main knob first.
        start: every fitted knob's value in the scene (the search's reference point).
        cands: one model per integer combination (empty: no model, the search is on the exact pipeline alone).
        terrains: the Terrains the models prepared, by (roots, tess) (the exact tries reuse them).
    """

    policy: str
    scene: Scene
    all_knobs: tuple[Knob, ...]
    names: list[str]
    start: dict[str, float]
    cands: list[Candidate]
    terrains: dict[tuple, Terrain]

    def knob(self, name: str) -> Knob:
        return next(k for k in self.all_knobs if k.name == name)

    def snap(self, values: Mapping[str, float]) -> dict[str, float]:
        """``values`` snapped to their knobs (integers to their allowed values, the others to 6 significant
        digits, so that settings the search reaches twice are one key)."""
        out = {}
        for name, v in values.items():
            k = self.knob(name) if any(k.name == name for k in self.all_knobs) else None
            v = k.snap(v) if k is not None else v
            out[name] = v if isinstance(v, int) else float(f"{float(v):.6g}")
        return out

    def key(self, values: Mapping[str, float]) -> tuple:
        return tuple(sorted(self.snap(values).items()))

    def make(self, values: Mapping[str, float]) -> Scene:
        return apply(self.scene, self.policy, values)

    def coarseness(self, values: Mapping[str, float]) -> float:
        """How far toward its coarse end the main knob of ``values`` is: its unit coordinate, turned where a
        larger value is finer (0 for a knob that is neither, or absent)."""
        main = self.knob(self.names[0])
        if main.coarser_up is None or main.name not in values:
            return 0.0
        u = main.to_unit(float(values[main.name]))
        return u if main.coarser_up else 1.0 - u


def problem(scene: Scene, policy: str, names: Sequence[str] | str | None, cams: list[Camera], refs: list[Frame],
            cost_of: Cost | None, *, device: str = "cpu", cache: dict | None = None, models: bool = True,
            budget_px: float | None = None, max_pop_px: float | None = None,
            on_step: Callable[[], None] | None = None) -> Problem:
    """The problem of fitting ``names`` of ``policy`` (None: the main knob; ``"all"``: every knob; the main knob
    is always fitted: it carries the budget) on ``scene`` over ``cams``; ``models``: build the family's models
    (False: the knobs alone, for a search on the exact pipeline); with ``max_pop_px`` (and ``budget_px``), the
    models that can (:data:`POPPED`) predict each consecutive pair's pop too, and the others are not built."""
    all_knobs = knobs(policy, scene.heightmap, scene.lod if not scene.lod.is_scheme else None, cache=cache)
    known = [k.name for k in all_knobs]
    if names is None:
        chosen = [known[0]]
    elif names == "all":
        chosen = list(known)
    else:
        if isinstance(names, str) or not all(isinstance(n, str) for n in names):
            raise TypeError(f"knobs: expected None, 'all' or a list of knob names, got {names!r}")
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"knobs: {policy!r} has no knob {unknown}; its knobs are {known}")
        chosen = [known[0], *(n for n in known[1:] if n in names)]
    start = values_of(scene, policy, chosen)
    for k in all_knobs:  # a knob the scene leaves to the scheme's per-heightmap default: the middle of its range
        if k.name in start and not math.isfinite(start[k.name]):
            start[k.name] = k.snap(k.from_unit(0.5))
    if policy in POLICY_TABLE and not scene.lod.is_scheme and scene.lod.policy != policy:
        start[known[0]] = float(getattr(scene.lod, POLICY_TABLE[policy].field))
    prob = Problem(policy, scene, tuple(all_knobs), chosen, start, [], {})
    if max_pop_px is not None and policy not in POPPED:
        return prob
    if models and policy in MODELLED:
        use_cache()  # JAX's compiled programs kept in the user's cache folder (terrainwarp.fit.jaxrt)
    if models and policy in ("sse", "distance"):
        prob.cands = _quadtree_candidates(prob, cams, refs, cost_of, device, on_step, budget_px, max_pop_px)
    elif models and policy == "continuous":
        prob.cands = _continuous_candidates(prob, cams, refs, cost_of, device, on_step)
    elif models and policy == "cdlod":
        prob.cands = _cdlod_candidates(prob, cams, refs, cost_of, device, on_step)
    return prob


def _quadtree_candidates(prob: Problem, cams: list[Camera], refs: list[Frame], cost_of: Cost | None, device: str,
                         on_step: Callable[[], None] | None, budget_px: float | None = None,
                         max_pop_px: float | None = None) -> list[Candidate]:
    """One QuadtreeModel per ``tess`` (every power of two when ``tess`` is fitted, else the scene's)."""
    scene, policy = prob.scene, prob.policy
    ints = [n for n in prob.names if prob.knob(n).integer]
    combos = list(itertools.product(*(prob.knob(n).values for n in ints))) or [()]
    from .relaxed import QuadtreeModel  # lazy: imports JAX

    weights = cost_weights(cost_of)
    seen = sight(scene.heightmap, cams, refs, device)
    out = []
    for i, combo in enumerate(combos):
        say(f"probes: model {i + 1}/{len(combos)}")
        fixed_int = {n: int(v) for n, v in zip(ints, combo, strict=True)}
        base = prob.make({**prob.start, **fixed_int})
        lod = base.lod
        terrain = prepared(prob.terrains, scene.heightmap, lod.roots, lod.tess, device)
        cont = [prob.knob(n) for n in prob.names if not prob.knob(n).integer
                and not (n.startswith(LEVEL_SCALE) and int(n[len(LEVEL_SCALE):]) >= terrain.depth)]
        every = values_of(base, policy, [k.name for k in prob.all_knobs])  # the knobs not fitted keep the scene's
        fixed = {**{n: v for n, v in every.items() if n not in {k.name for k in cont}}, **fixed_int}
        meshes = [render(base.with_(camera=cams[0], outputs=("mesh",)), terrain,
                         patches=_touching(uniform_patches(terrain, L), seen), device=device).mesh
                  for L in range(terrain.depth)]
        surfaces = [*surfaces_of(scene.heightmap, meshes, seen, device), None]
        probes = probe_cameras(scene.heightmap, cams, refs, surfaces, seen, device=device)
        pops = None if max_pop_px is None else pop_pairs(scene.heightmap, cams, refs, surfaces, probes, seen, device)
        model = QuadtreeModel(terrain, cams, probes, policy, cont, fixed,
                              lambda v, p=prob: p.make(v).lod, weights, device=device, pops=pops)
        model.prepare()
        n = len(cams) + (0 if pops is None else len(cams) - 1)
        shift = np.zeros(n)
        if pops is not None:  # a pop compared with its bound as an error with the budget
            shift[len(cams):] = math.log(budget_px / max(max_pop_px, 1e-6))
        out.append(Candidate(model, fixed_int, Calibration(n), shift=shift,
                             u=np.array([k.to_unit(prob.start[k.name]) for k in cont])))
        if on_step is not None:
            on_step()
    return out


def _continuous_candidates(prob: Problem, cams: list[Camera], refs: list[Frame], cost_of: Cost | None, device: str,
                           on_step: Callable[[], None] | None) -> list[Candidate]:
    """One ContinuousModel per patch level (every level 0..D when ``level`` is fitted, else the scene's)."""
    from .relaxed_continuous import ContinuousModel, continuous_patches, factor_ladder  # lazy: imports JAX

    scene = prob.scene
    weights = cost_weights(cost_of)
    base0 = prob.make(prob.start)
    levels = prob.knob("level").values if "level" in prob.names else (base0.lod.level,)
    at = sight(scene.heightmap, cams, refs, device)
    out = []
    for i, level in enumerate(int(v) for v in levels):
        say(f"probes: model {i + 1}/{len(levels)}")
        fixed = {"level": level}
        base = prob.make({**prob.start, **fixed})  # a deep level lays its patches out with a smaller T
        terrain = prepared(prob.terrains, scene.heightmap, base.lod.roots, base.lod.tess, device)
        level = min(level, terrain.depth)
        patches = continuous_patches(terrain, cams, level, device)
        seen = np.unique(np.concatenate([pl.key for pl in patches])) if patches else np.zeros(0, np.int64)
        ladder = factor_ladder(terrain, level)

        def rung(f: float, level=level, base=base, terrain=terrain, seen=seen) -> Mesh:
            pl = uniform_patches(terrain, level, f)
            return render(base.with_(camera=cams[0], outputs=("mesh",)), terrain,
                          patches=_touching(_subset(pl, np.isin(pl.key, seen)), at), device=device).mesh

        pl = uniform_patches(terrain, level)
        pl = _touching(_subset(pl, np.isin(pl.key, seen)), at)
        surfaces = ladder_surfaces(scene.heightmap, pl, ladder, at, cams[0].position, base.lod.spacing,
                                   base.lod.filter, rung, device)
        probes = probe_cameras(scene.heightmap, cams, refs, surfaces, at, device=device)
        model = ContinuousModel(terrain, cams, probes, ladder, patches, [prob.knob("target_px")], fixed,
                                lambda v, p=prob: p.make(v).lod, weights, device=device)
        model.prepare()
        out.append(Candidate(model, {"level": level} if "level" in prob.names else {}, Calibration(len(cams)),
                             u=np.array([prob.knob("target_px").to_unit(prob.start["target_px"])])))
        if on_step is not None:
            on_step()
    return out


def _cdlod_candidates(prob: Problem, cams: list[Camera], refs: list[Frame], cost_of: Cost | None, device: str,
                      on_step: Callable[[], None] | None) -> list[Candidate]:
    """One CdlodModel per grid (every grid when ``grid`` is fitted, else the scene's)."""
    from .relaxed_cdlod import CdlodModel  # lazy: imports JAX

    scene = prob.scene
    weights = cost_weights(cost_of)
    every = values_of(prob.make(prob.start), "cdlod", [k.name for k in prob.all_knobs])
    grids = prob.knob("grid").values if "grid" in prob.names else (every["grid"],)
    cont = [prob.knob(n) for n in prob.names if not prob.knob(n).integer]
    at = sight(scene.heightmap, cams, refs, device)
    out = []
    for i, g in enumerate(int(v) for v in grids):
        say(f"probes: model {i + 1}/{len(grids)}")
        fixed = {**{n: v for n, v in every.items() if n not in {k.name for k in cont}}, "grid": g}
        base = prob.make({**prob.start, **fixed})
        scheme = copy.copy(scene_source(base, device).scheme)  # the grid's pyramids, shared; the knobs its own
        meshes = [scheme.mesh(cams[0], _seen_quadrants(scheme.uniform(i), at), morph=False)
                  for i in range(scheme.levels)]
        probes = probe_cameras(scene.heightmap, cams, refs, surfaces_of(scene.heightmap, meshes, at, device), at,
                               device=device)
        model = CdlodModel(scheme, cams, probes, cont, fixed, lambda v, p=prob: p.make(v).lod, weights,
                           device=device)
        model.prepare()
        out.append(Candidate(model, {"grid": g} if "grid" in prob.names else {}, Calibration(len(cams)),
                             u=np.array([k.to_unit(prob.start[k.name]) for k in cont])))
        if on_step is not None:
            on_step()
    return out


def _subset(pl: PatchList, keep: np.ndarray) -> PatchList:
    """The patches of ``pl`` where ``keep``, in their order."""
    return type(pl)(*(a[keep] if isinstance(a, np.ndarray) else a for a in pl))


def _touching(pl: PatchList, at: Sight) -> PatchList:
    """The patches of ``pl`` whose triangles may hold a sample the cameras see (:meth:`Sight.touching`), in their
    order: the surface above every such sample is the one all of ``pl`` draws, bit for bit (a sample takes the
    lowest-numbered triangle holding it, and the patches left out hold none)."""
    return _subset(pl, at.touching(pl.origin_cells[:, 0], pl.origin_cells[:, 1], pl.size_cells))


def _seen_quadrants(sel: CdlodSelection, at: Sight) -> CdlodSelection:
    """The quadrants of ``sel`` that may hold a sample the cameras see, in their order (as :func:`_touching`)."""
    keep = at.touching(sel.origin[:, 0], sel.origin[:, 1], sel.size)
    q = int(keep.sum())
    return CdlodSelection(sel.origin[keep], sel.size[keep], sel.step[keep], sel.lod[keep], {},
                          np.array([[0, q]], np.int32), np.arange(q, dtype=np.int32))


def relaxed_model(scene: Scene, cameras: list[Camera], policy: str = "sse", *, knobs: Sequence[str] | None = None,
                  references: list[Frame] | None = None, device: str = "cpu"):
    """The model a fit of ``policy`` on ``scene`` over ``cameras`` would use (its first integer combination):
    ``model.relaxed(u, temperature) -> (cost per camera, log p99 per camera)`` in the fitted continuous knobs' unit
    coordinates ``u`` (``model.knobs``), and ``model.hard(values)``. For a look at the model itself (the
    stability suite checks its gradients)."""
    refs = references_for(scene, cameras, references, device)
    prob = problem(scene, policy, knobs, cameras, refs, None, device=device)
    if not prob.cands:
        raise ValueError(f"policy: {policy!r} has no model; the families with one are {list(MODELLED)}")
    return prob.cands[0].model
