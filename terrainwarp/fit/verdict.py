"""What a fit's verdict says beside met or missed: the constraint that held the setting where it is, the knobs
that ended on their range limits, the frames whose p99 rests on too few samples, and the family's own full-detail
floor of the image error on every camera.

* :func:`binding_constraint`: the budget on camera k, the pop budget (pair k-1 -> k), or the main knob at a
  range limit (the setting cannot go coarser inside the range: the budget is not what stopped it); the other
  fitted knobs on a limit are listed apart (:func:`knobs_at_limits`): the best setting may lie outside their
  ranges.
* :func:`sparse_frames`: a frame whose p99 is taken over fewer than :data:`MIN_SAMPLES` visible samples, or fewer
  than one per :data:`PIXELS_PER_SAMPLE` covered pixels (a camera that looks off the terrain, or at it from so
  close that a handful of samples cover the screen): its p99 says little.
* :func:`image_floor`: per camera, the image error (against the fixed-diagonal grid) of the family's own
  full-detail setting (:func:`full_detail`): the triangulation floor an image-error value carries.
* :func:`assess`: a saved setting measured over its path without fitting (``terrainwarp evaluate``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera, Viewport
from ..lod.quadtree import Terrain, layout
from ..measure.cost import cost as resolve_cost
from ..rendering.pipeline import Frame, render
from ..scene import POLICY_TABLE, QUADTREE_TESS, Budget, CameraPath, Scene
from ..schemes import SCHEMES, scheme_range
from .exact import Evaluation, evaluate, references_for
from .knobs import Knob, apply, knobs

__all__ = ["binding_constraint", "knobs_at_limits", "sparse_frames", "image_floor", "full_detail", "describe",
           "annotate", "assess", "Assessment", "MIN_SAMPLES", "PIXELS_PER_SAMPLE"]

MIN_SAMPLES = 1000  # a frame's p99 over fewer visible samples is flagged
PIXELS_PER_SAMPLE = 50  # ... or over fewer than one visible sample per this many covered pixels


def _limit(k: Knob, v: float) -> str | None:
    """``"lower"`` / ``"upper"`` when ``v`` sits on that end of the knob's range (within 1e-6 relative), else None."""
    tol = 1e-6 * max(abs(k.lo), abs(k.hi), 1e-12)
    if abs(v - k.lo) <= tol:
        return "lower"
    if abs(v - k.hi) <= tol:
        return "upper"
    return None


def knobs_at_limits(values: dict[str, float], knobs: Sequence[Knob]) -> list[dict[str, Any]]:
    """The fitted knobs whose value sits on an end of their range: name, ``limit`` (``"lower"``/``"upper"``),
    value, range, and which way that end draws (``"finer"``, ``"coarser"`` or None when neither always)."""
    out = []
    for k in knobs:
        if k.name not in values:
            continue
        lim = _limit(k, float(values[k.name]))
        if lim is None:
            continue
        way = None if k.coarser_up is None else ("coarser" if (lim == "upper") == bool(k.coarser_up) else "finer")
        out.append({"knob": k.name, "limit": lim, "value": float(values[k.name]), "range": [k.lo, k.hi],
                    "end": way})
    return out


def binding_constraint(ev: Evaluation | None, met: bool, budget_px: float, max_pop_px: float | None,
                       main: Knob, at_limits: list[dict[str, Any]], cams_per_viewport: int | None = None,
                       tried: Sequence[Evaluation] = ()) -> dict[str, Any]:
    """The constraint that holds the setting ``ev`` (the fit's validated setting), as ``kind``:

    * ``"knob_limit"``: the main knob sits at the coarse end of its range (``knob``, ``limit``, ``value``): it could
      not go coarser, whatever the budget;
    * ``"budget"``: the budget on ``camera`` (``p99_px``, ``used`` = p99 / budget): the nearest coarser setting
      tried along the main knob (``tried``) exceeded it there (``coarser``: its value and that camera's p99), or,
      with none tried, the camera closest to the budget;
    * ``"pop"``: the pop budget on cameras ``pair`` = (k-1, k) (``pop_p99_px``, ``used``);
    * ``"plateau"``: the coarser settings tried met the budget at no lower cost (``coarser``: the coarsest tried):
      the family draws the same frames there (its coarsest selection on these cameras), so nothing in range is
      cheaper.

    A missed fit (``met`` False) names the budget or pop budget its finest setting exceeds. ``cams_per_viewport``:
    the cameras of one viewport when the path repeats per viewport (``viewport`` and ``viewport_camera`` then
    locate ``camera``). ``text`` says it in words."""
    if ev is None or not ev.p99_px:
        return {"kind": "none", "met": met, "text": "nothing was measured"}
    coarse_end = next((a for a in at_limits if a["knob"] == main.name and a["end"] == "coarser"), None)
    if met and coarse_end is not None:
        used = ev.worst_p99 / budget_px
        return {"kind": "knob_limit", "knob": main.name, "limit": coarse_end["limit"], "value": coarse_end["value"],
                "used": used, "met": met,
                "text": f"{main.name} at its {coarse_end['limit']} range limit ({coarse_end['value']:.4g}, the "
                        f"coarsest in range; the worst-frame p99 uses {used:.0%} of the budget)"}
    step = _next_coarser(ev, main, tried, budget_px, max_pop_px) if met else None
    if step is not None and step.meets(budget_px, max_pop_px):
        return {"kind": "plateau", "met": met, "coarser": {"value": step.values[main.name], "cost": step.cost},
                "used": ev.worst_p99 / budget_px,
                "text": f"no cheaper setting in range: {main.name} up to {step.values[main.name]:.4g} (coarser) "
                        f"also meets the budget at no lower cost ({step.cost:.4g}; the family's coarsest frames on "
                        f"these cameras)"}
    probe = step if step is not None else ev
    over_b = probe.worst_p99 / budget_px
    pops = probe.pop_p99_px if max_pop_px is not None else []
    over_p = max(pops) / max(max_pop_px, 1e-12) if pops else -math.inf
    if pops and (over_p > 1.0 >= over_b if step is not None else over_p >= over_b):
        k = int(np.argmax(pops)) + 1
        return {"kind": "pop", "pair": [k - 1, k], "pop_p99_px": float(ev.pop_p99_px[k - 1]) if ev.pop_p99_px
                else float(pops[k - 1]), "used": over_p, "met": met,
                "text": f"the pop budget on cameras {k - 1} -> {k} ({max_pop_px:g} px"
                        + ("" if step is None else f"; the next coarser {main.name} = {step.values[main.name]:.4g} "
                                                   f"pops {pops[k - 1]:.3g} px there") + ")"}
    order = list(probe.frames) if probe.frames is not None else list(range(len(probe.p99_px)))
    worst = order[int(np.argmax(probe.p99_px))]
    mine = float(ev.p99_px[worst]) if ev.frames is None else float(max(ev.p99_px))
    where = _camera_words(worst, cams_per_viewport)
    out = {"kind": "budget", "camera": worst, "p99_px": mine, "used": mine / budget_px, "met": met, **where[0],
           "text": f"the budget on {where[1]} (p99 {mine:.3g} px of {budget_px:g} px"}
    if step is not None:
        out["coarser"] = {"value": step.values[main.name], "p99_px": float(max(probe.p99_px))}
        out["text"] += f"; at the next coarser {main.name} = {step.values[main.name]:.4g}: {max(probe.p99_px):.3g} px"
    out["text"] += ")"
    return out


def _next_coarser(ev: Evaluation, main: Knob, tried: Sequence[Evaluation], budget_px: float,
                  max_pop_px: float | None) -> Evaluation | None:
    """Of the settings tried that differ from ``ev`` in the main knob alone, on its coarser side: the nearest that
    missed a constraint if any did, else the coarsest measured whole (None: none coarser was tried)."""
    if main.coarser_up is None or main.name not in ev.values:
        return None
    v0 = float(ev.values[main.name])
    sign = 1.0 if main.coarser_up else -1.0
    line = sorted((e for e in tried if e is not ev and set(e.values) == set(ev.values)
                   and all(e.values[n] == ev.values[n] for n in ev.values if n != main.name)
                   and sign * (float(e.values[main.name]) - v0) > 0),
                  key=lambda e: sign * (float(e.values[main.name]) - v0))
    missed = [e for e in line if not e.meets(budget_px, max_pop_px)]
    whole = [e for e in line if e.complete]
    return missed[0] if missed else (whole[-1] if whole else None)


def _camera_words(k: int, per: int | None) -> tuple[dict[str, int], str]:
    if per is None or per <= 0:
        return {}, f"camera {k}"
    return {"viewport": k // per, "viewport_camera": k % per}, f"camera {k} (viewport {k // per}, camera {k % per})"


def sparse_frames(ev: Evaluation | None) -> list[dict[str, Any]]:
    """The measured frames whose p99 rests on too few visible samples: fewer than :data:`MIN_SAMPLES`, or fewer than
    one per :data:`PIXELS_PER_SAMPLE` covered pixels; each with its camera, samples, covered pixels and why."""
    if ev is None or not ev.visible:
        return []
    order = ev.frames if ev.frames is not None else range(len(ev.visible))
    out = []
    for k, n, cov in zip(order, ev.visible, ev.covered, strict=True):
        why = []
        if n < MIN_SAMPLES:
            why.append(f"{n} visible samples < {MIN_SAMPLES}")
        if n * PIXELS_PER_SAMPLE < cov:
            why.append(f"one sample per {cov / max(n, 1):.0f} covered pixels (> {PIXELS_PER_SAMPLE})")
        if why:
            out.append({"camera": int(k), "samples_visible": int(n), "covered_px": int(cov), "why": "; ".join(why)})
    return out


def full_detail(scene: Scene, policy: str) -> Scene:
    """``scene`` drawn by ``policy`` at its full detail: every node split to the samples (sse, distance), the
    continuous grid at its deepest level, CDLOD's LOD 0 everywhere, clipmaps' largest ring, every chunk or tile at
    the samples (chunked, cesium); a registered scheme of yours: its main parameter at the fine end of its range."""
    hm = scene.heightmap
    if policy in POLICY_TABLE:
        lod = scene.lod if not scene.lod.is_scheme else None
        tess = lod.tess if lod is not None and lod.tess in QUADTREE_TESS else 16
        roots = lod.roots if lod is not None else 16
        if policy == "continuous":
            depth = layout(hm.shape, roots, 4, None)[1]
            return apply(scene, policy, {"target_px": POLICY_TABLE[policy].fit_range[0], "level": depth})
        return apply(scene, policy, {POLICY_TABLE[policy].field: 1e-6 if policy == "sse" else 1e6,
                                     "tess": tess, "hysteresis": 0.0})
    spec = SCHEMES[policy]
    lo, hi = scheme_range(policy, hm)
    value = hi if spec.larger_is_finer else (0.0 if spec.lo == 0 else lo)
    if policy == "clipmaps":  # the finest ring covering the terrain from anywhere over it (not the largest ring)
        value = min(hi, float((2 * max(hm.shape) - 1) | 1))
    return apply(scene, policy, {spec.parameter: value})


def image_floor(scene: Scene, policy: str, cameras: list[Camera], refs: list[Frame], *,
                device: str = "cpu") -> list[float]:
    """Per camera, the p99 image error (px, against the fixed-diagonal grid ``refs``) of ``policy``'s full-detail
    setting on ``scene`` (:func:`full_detail`): the floor of that family's image-error column on that camera."""
    setting = full_detail(scene, policy)
    lod = setting.lod
    terrain = None if lod.is_scheme else Terrain.prepare(setting.heightmap, roots=lod.roots, tess=lod.tess,
                                                         device=device)
    out = []
    for c, ref in zip(cameras, refs, strict=True):
        f = render(setting.with_(camera=c, outputs=("error",)), terrain, reference=ref, device=device)
        out.append(float(f.error.image_err_p99_px))
    return out


def describe(binding: dict[str, Any], at_limits: list[dict[str, Any]], sparse: list[dict[str, Any]]) -> str:
    """One sentence for a fit's message: what binds, the other knobs on their limits, the sparse frames."""
    parts = [f"binding: {binding['text']}"] if binding.get("kind") not in (None, "none") else []
    others = [a for a in at_limits if not (binding.get("kind") == "knob_limit" and a["knob"] == binding["knob"])]
    if others:
        parts.append("knobs at their range limits: " + ", ".join(f"{a['knob']} ({a['limit']} limit, {a['value']:.4g})"
                                                                 for a in others)
                     + " (the best setting may lie outside their ranges)")
    if sparse:
        parts.append(f"{len(sparse)} frame(s) with too few visible samples for a p99: cameras "
                     + ", ".join(str(s["camera"]) for s in sparse))
    return "; ".join(parts)


def annotate(res: Any, knobs: Sequence[Knob], cameras: list[Camera], refs: list[Frame], viewports: list[Viewport],
             cost: object, *, tried: Sequence[Evaluation] = (), floor: bool = True, device: str = "cpu") -> None:
    """Complete a fit's result ``res`` (a :class:`terrainwarp.fit.FitResult`) in place: the binding constraint,
    the knobs on their range limits, the sparse frames (``tried``: the settings the fit measured, to find the next
    coarser one), the image floor per camera (``floor``), and the fitted
    scene with the exact cameras it was measured on, its viewport and its budget (so that it loads back to the
    same frames and ``terrainwarp evaluate`` reproduces ``res.validated``); the message says what binds."""
    main = next(k for k in knobs if k.name == res.knobs[0])
    fitted = [k for k in knobs if k.name in res.knobs]
    res.viewports = list(viewports) or [cameras[0].viewport]
    res.at_limits = knobs_at_limits(res.values, fitted)
    per = len(cameras) // len(viewports) if len(viewports) > 1 else None
    res.binding = binding_constraint(res.validated, res.met, res.budget_px, res.max_pop_px, main, res.at_limits, per,
                                     tried)
    res.sparse = sparse_frames(res.validated)
    if floor and res.validated is not None:
        res.image_floor_p99_px = image_floor(res.scene, res.policy, cameras, refs, device=device)
    said = describe(res.binding, res.at_limits, res.sparse)
    res.message = res.message + (f"; {said}" if said else "")
    if res.policy == "cesium" and res.validated is not None:  # the answer in Cesium's own terms
        res.message += (f"; Cesium: maximumScreenSpaceError = {res.values['max_sse_px']:.4g} at "
                        f"{res.viewports[0].text} gives a true worst-frame p99 of {res.validated.worst_p99:.3g} px")
    res.scene = res.scene.with_(path=CameraPath.of(cameras), viewport=res.viewports[0],
                                budget=Budget(res.budget_px, res.max_pop_px, _cost_name(cost)))


def _cost_name(cost: object) -> str | tuple[str, ...]:
    """The fit's cost as a scene file names it: a name or a path, a list of them; a model given as an object is
    saved as ``"triangles"`` (a file cannot name it: save it as a weights file or a profile and fit with that)."""
    if isinstance(cost, str | Path):
        return str(cost)
    if isinstance(cost, list | tuple) and cost and all(isinstance(c, str | Path) for c in cost):
        return tuple(str(c) for c in cost)
    return "triangles"


@dataclass
class Assessment:
    """A saved setting measured over its path without fitting (:func:`assess`, ``terrainwarp evaluate``).

    Attributes:
        scene: the setting; evaluation: its exact evaluation over the cameras (the pop of each consecutive pair
            measured when there are two or more); met: the verdict against ``budget_px`` (and ``max_pop_px``);
        binding: the constraint closest to its bound (:func:`binding_constraint`); sparse: the frames with too
            few samples for a p99 (:func:`sparse_frames`); image_floor_p99_px: per camera, the family's
            full-detail image error (empty when not asked); message: the verdict in one line.
    """

    scene: Scene
    evaluation: Evaluation
    budget_px: float
    max_pop_px: float | None
    cost: str
    met: bool
    binding: dict[str, Any]
    sparse: list[dict[str, Any]]
    image_floor_p99_px: list[float] = field(default_factory=list)
    message: str = ""

    def to_dict(self) -> dict[str, Any]:
        v = self.evaluation
        return {"policy": self.scene.lod.policy, "lod": dict(self.scene.to_dict()["lod"]),
                "viewport": list(self.scene.pixel_viewport), "budget_px": self.budget_px,
                "max_pop_px": self.max_pop_px, "cost": self.cost, "met": self.met, "message": self.message,
                "binding": self.binding, "sparse_frames": self.sparse,
                "frames": {"p99_px": v.p99_px, "max_px": v.max_px, "image_p99_px": v.image_p99_px,
                           "image_floor_p99_px": self.image_floor_p99_px, "samples_visible": v.visible,
                           "covered_px": v.covered, "pop_p99_px": v.pop_p99_px, "triangles": v.triangles,
                           "costs": v.costs, "frame_ms": v.frame_ms},
                "worst_p99_px": v.worst_p99, "worst_pop_p99_px": v.worst_pop if v.pop_p99_px else None,
                "mean_cost": v.cost}


def assess(scene: Scene, *, budget_px: float | None = None, max_pop_px: float | None = None, cost: object = None,
           cameras: list[Camera] | None = None, floor: bool = True, device: str = "cpu") -> Assessment:
    """Measure the LOD setting ``scene`` over its camera path (``cameras``: others) on the exact pipeline, without
    fitting: each frame's p99 and cost, the pop of consecutive pairs, the verdict against ``budget_px`` (default: the
    scene's ``[budget]``), what is closest to its bound, the sparse frames and (``floor``) the image floor. On a
    fitted scene this reproduces the fit's ``validated`` evaluation (the same cameras, the same frames).

    Raises:
        ValueError: a grid scene, or no budget (neither given nor in the scene).
    """
    if scene.mesh != "lod":
        raise ValueError("scene: the scene draws the full grid (render.mesh = 'grid'); evaluate takes a LOD setting "
                         "(a fitted scene: terrainwarp fit writes fitted.toml)")
    bud = scene.budget
    budget_px = budget_px if budget_px is not None else (bud.budget_px if bud is not None else None)
    if budget_px is None:
        raise ValueError("budget_px: the scene has no [budget] table; give the budget (--budget-px)")
    max_pop_px = max_pop_px if max_pop_px is not None else (bud.max_pop_px if bud is not None else None)
    spec = cost if cost is not None else (list(bud.cost) if bud is not None and isinstance(bud.cost, tuple)
                                          else bud.cost if bud is not None else "triangles")
    cost_of = resolve_cost(spec)
    label = cost_of.label
    cost_of = None if cost_of.name == "triangles" else cost_of
    cams = list(cameras) if cameras is not None else scene.camera_path()
    refs = references_for(scene, cams, device=device)
    lod = scene.lod
    terrain = None if lod.is_scheme else Terrain.prepare(scene.heightmap, roots=lod.roots, tess=lod.tess,
                                                         device=device)
    ev = evaluate(scene, cams, refs, terrain=terrain, device=device, pops=len(cams) > 1, cost_of=cost_of)
    met = ev.meets(budget_px, max_pop_px)
    main = knobs(lod.policy, scene.heightmap, None if lod.is_scheme else lod)[0]
    binding = binding_constraint(ev, met, budget_px, max_pop_px, main, [])
    sparse = sparse_frames(ev)
    floor_px = image_floor(scene, lod.policy, cams, refs, device=device) if floor else []
    verdict = "met" if met else "missed"
    msg = (f"{verdict}: worst-frame p99 {ev.worst_p99:.3g} px {'<=' if met else '>'} {budget_px:g} px"
           + ("" if max_pop_px is None else f", worst pair pop p99 {ev.worst_pop:.3g} px (bound {max_pop_px:g})")
           + f" over {len(cams)} cameras, {ev.cost:.4g} {label} per frame")
    said = describe(binding, [], sparse)
    return Assessment(scene, ev, budget_px, max_pop_px, label, met, binding, sparse, floor_px,
                      msg + (f"; {said}" if said else ""))
