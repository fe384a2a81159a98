"""A setting at another viewport: :func:`rescale`, each family by its own rule, confirmed on exact frames.

A fitted setting's pixel budget belongs to the viewport it was fitted at (``Scene.pixel_viewport``): a length
``e`` metres at distance ``d`` covers ``e * f / d`` pixels, ``f = height / (2 tan(fov_y / 2))`` the viewport's
pixels per radian. Going from a viewport of ``f`` to one of ``f'`` (``s = f' / f``), the same p99 budget in
pixels asks each family for (:data:`RULES`):

* ``sse``, ``chunked``, ``cesium``: the same pixel threshold. Their test (projected geometric error in pixels)
  is evaluated at the viewport the frame is drawn in, so it already refines where ``f'`` makes an error larger.
* ``distance``: ``k * s``. Its split distance is ``k`` node sizes; at ``s`` times the pixels per radian the same
  pixel error lies ``s`` times farther away.
* ``cdlod``: ``first_range * s`` (every range grows with it: they are multiples of the first); ratio, morph and
  grid are kept.
* ``clipmaps``: ``n * s`` rounded to the next odd integer (each ring's extent, in samples, grows with the
  distance its error is seen from).
* ``continuous``: the same target pixels per edge. A smooth surface's chord error would ask for
  ``target_px * sqrt(s)`` (the chord error of an edge of ``L`` pixels is ``L^2 / f``), but a heightmap's error is
  what an edge skips of its samples, the same in pixels: measured, keeping the target lands at 0.96-1.33 of the
  budget where ``sqrt(s)`` lands at 0.95-1.35 (``benchmarks/results/rescale.md``).

None of them is exact on a real terrain: levels change in whole steps, and a terrain is not self-similar. So
:func:`rescale` measures the rule's setting with exact frames at the new viewport (the scene's cameras at that
viewport) against the budget and, when it misses (or, with ``tighten``, when it has room), searches the main knob
on the exact pipeline from there (:func:`terrainwarp.fit.search.bracket_search`). It says which it did
(:attr:`Rescaled.action`).

:func:`pixel_knobs` gives each pixel knob of a setting at its viewport and as an angle (the same threshold at any
viewport of the same pixels per radian).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from ..camera import Camera, Viewport
from ..measure.cost import cost as resolve_cost
from ..scene import CameraPath, Scene
from ..schemes import scheme_default
from .exact import Evaluation, Exact, references_for
from .families import problem
from .knobs import apply, values_of
from .search import bracket_search

__all__ = ["Rule", "RULES", "Rescaled", "rescale", "rule_values", "pixel_knobs", "at_viewport", "focal_ratio"]


class Rule(NamedTuple):
    """How one family's main knob follows the viewport: ``kind`` ``"px"`` (kept: a pixel threshold evaluated at
    the viewport it runs in), ``"focal"`` (times s), ``"focal_odd"`` (times s, the next odd integer) or
    ``"sqrt_focal"`` (times sqrt(s)), s the ratio of pixels per radian; ``text`` says why."""

    knob: str
    kind: str
    text: str


RULES: dict[str, Rule] = {
    "sse": Rule("tolerance_px", "px", "kept: the projected error is tested in pixels of the viewport drawn"),
    "chunked": Rule("max_sse_px", "px", "kept: the projected error is tested in pixels of the viewport drawn"),
    "cesium": Rule("max_sse_px", "px", "kept: Cesium tests geometricError * viewportHeight / (distance * 2 "
                                       "tan(fovy/2)) in the viewport drawn"),
    "distance": Rule("k", "focal", "times s: the same pixel error lies s times farther away"),
    "cdlod": Rule("first_range", "focal", "times s: every range (a multiple of the first) grows with the pixels "
                                          "per radian"),
    "clipmaps": Rule("n", "focal_odd", "times s, odd: each ring's extent grows with the distance its error is "
                                       "seen from"),
    "continuous": Rule("target_px", "px", "kept: a heightmap's error is what an edge of target_px pixels skips of "
                                          "its samples (measured closer than sqrt(s))"),
}


def focal_ratio(a: Viewport, b: Viewport) -> float:
    """s = pixels per radian of ``b`` over those of ``a``."""
    return Viewport(*b).focal_px / Viewport(*a).focal_px


def at_viewport(cameras: list[Camera], viewport: Viewport) -> list[Camera]:
    """Each camera at ``viewport`` (its width, height and field of view; position, aim and clip planes kept), the
    repeats of a multi-viewport path dropped (order kept)."""
    vp = Viewport.of(*viewport)
    return list(dict.fromkeys(c.with_(width=vp.width, height=vp.height, fov_y_deg=vp.fov_y_deg) for c in cameras))


def _main_value(scene: Scene, policy: str) -> float:
    v = values_of(scene, policy, [RULES[policy].knob])[RULES[policy].knob]
    if math.isnan(v):  # a scheme's parameter left to its default
        v = float(scheme_default(policy, scene.heightmap))
    return float(v)


def rule_values(scene: Scene, viewport: Viewport) -> dict[str, float]:
    """The main knob's value by the family's rule (:data:`RULES`) for ``viewport``, from ``scene``'s setting at
    its ``pixel_viewport``."""
    policy = scene.lod.policy
    if policy not in RULES:
        raise ValueError(f"scene.lod.policy: no viewport rule for {policy!r}; the families with one are "
                         f"{list(RULES)}")
    rule = RULES[policy]
    s = focal_ratio(scene.pixel_viewport, viewport)
    v = _main_value(scene, policy)
    new = {"px": v, "focal": v * s, "sqrt_focal": v * math.sqrt(s),
           "focal_odd": float(int(math.ceil(v * s)) | 1)}[rule.kind]
    return {rule.knob: new}


def pixel_knobs(scene: Scene, budget_px: float | None = None) -> dict[str, dict[str, Any]]:
    """Each pixel knob of the setting (and ``budget_px`` when given) at its viewport and as an angle: name ->
    ``{"px", "mrad", "deg", "viewport"}``; the same threshold holds at another viewport as that angle, as
    ``angle * focal`` pixels there."""
    vp = scene.pixel_viewport
    policy = scene.lod.policy
    names = [RULES[policy].knob] if policy in RULES and RULES[policy].kind in ("px", "sqrt_focal") else []
    vals = {n: _main_value(scene, policy) for n in names}
    if budget_px is not None:
        vals["budget_px"] = float(budget_px)
    return {n: {"px": v, "mrad": 1e3 * vp.to_radians(v), "deg": math.degrees(vp.to_radians(v)),
                "viewport": list(vp)} for n, v in vals.items()}


@dataclass
class Rescaled:
    """A setting rescaled to another viewport.

    Attributes:
        scene: the setting at the new viewport (its cameras moved there, ``viewport`` set), to save or export.
        action: ``"confirmed"`` (the rule's setting meets the budget on exact frames), ``"corrected"`` (it did not,
            or had room with ``tighten``; the main knob was searched on exact frames from it), ``"missed"`` (no
            setting in range meets it), or ``"rule"`` (not measured: ``confirm=False``).
        rule_values: the rule's value of the main knob; values: the value kept.
        evaluation: the exact evaluation of ``values`` at the new viewport (None with ``confirm=False``).
        frames: exact frames measured; message: one line saying what was done.
    """

    scene: Scene
    action: str
    rule_values: dict[str, float]
    values: dict[str, float]
    evaluation: Evaluation | None = None
    frames: int = 0
    message: str = ""
    rule: str = ""
    history: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        e = self.evaluation
        return {"action": self.action, "rule": self.rule, "rule_values": self.rule_values, "values": self.values,
                "viewport": list(self.scene.pixel_viewport), "frames": self.frames, "message": self.message,
                "worst_p99_px": None if e is None else e.worst_p99, "cost": None if e is None else e.cost}


def rescale(scene: Scene, width: int, height: int, fov_y_deg: float, *, budget_px: float | None = None,
            confirm: bool = True, tighten: bool = False, rel_tol: float = 0.02, max_tries: int = 8,
            device: str = "cpu") -> Rescaled:
    """The setting of ``scene`` (a fitted LOD scene) for a viewport of ``width`` x ``height`` pixels and
    ``fov_y_deg``: the family's rule (:data:`RULES`), then, unless ``confirm`` is False, exact frames at the new
    viewport from the scene's cameras (:meth:`Scene.camera_path` moved to it) against the budget (``budget_px``,
    else the scene's ``[budget]``), correcting the main knob on the exact pipeline when the rule's setting misses
    (or, with ``tighten``, has room beyond ``rel_tol``).

    Raises:
        ValueError: not a LOD scene, a family without a rule, a bad viewport, or no budget to confirm against.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a Scene, got {type(scene).__name__}")
    if scene.mesh != "lod":
        raise ValueError("scene: expected a LOD setting (mesh = 'lod'), got a grid scene")
    vp = Viewport.of(width, height, fov_y_deg)
    policy = scene.lod.policy
    rv = rule_values(scene, vp)
    cams = at_viewport(scene.camera_path(), vp)
    new = apply(scene, policy, rv).with_(viewport=vp, path=CameraPath.of(cams), camera=scene.camera.with_(
        width=vp.width, height=vp.height))
    rule = f"{RULES[policy].knob} {RULES[policy].text} (s = {focal_ratio(scene.pixel_viewport, vp):.4g})"
    if not confirm:
        return Rescaled(new, "rule", rv, dict(rv), rule=rule,
                        message=f"{_shown(rv)} by the rule at {vp.text}, not measured")
    bud = scene.budget
    budget_px = budget_px if budget_px is not None else (bud.budget_px if bud is not None else None)
    if budget_px is None:
        raise ValueError("budget_px: the scene has no [budget] table to confirm against; give budget_px, or "
                         "confirm=False")
    return _confirm(new, policy, cams, rv, budget_px, bud, tighten, rel_tol, max_tries, device, rule)


def _confirm(new: Scene, policy: str, cams: list[Camera], rv: dict[str, float], budget_px: float, bud,
             tighten: bool, rel_tol: float, max_tries: int, device: str, rule: str) -> Rescaled:
    """The rule's setting measured at the new viewport, and corrected on the main knob when asked or needed."""
    max_pop = bud.max_pop_px if bud is not None else None
    cost_of = resolve_cost(bud.cost if bud is not None else "triangles")
    cost_of = None if cost_of.name == "triangles" else cost_of
    refs = references_for(new, cams, device=device)
    prob = problem(new, policy, None, cams, refs, cost_of, device=device, models=False)
    exact = Exact(prob.make, prob.key, cams, refs, budget_px, max_pop, cost_of, device, coarseness=prob.coarseness)
    main = prob.knob(RULES[policy].knob)
    first = exact(rv, stop=False, stage="rule")
    vp = new.pixel_viewport
    text = f"{_shown(first.values)} by the rule at {vp.text}: worst-frame p99 {first.worst_p99:.3g} px"
    if exact.meets(first) and not tighten:
        return Rescaled(new.with_(lod=prob.make(first.values).lod), "confirmed", rv, dict(first.values), first,
                        exact.frames, text + f" <= {budget_px:g} px: confirmed on {len(cams)} exact frames", rule,
                        exact.history)
    best = bracket_search(exact, main, {}, budget_px, rel_tol=rel_tol, max_tries=max_tries, seed=True)
    if best is None:
        return Rescaled(new, "missed", rv, dict(first.values), first, exact.frames,
                        text + f" > {budget_px:g} px, and no {main.name} in range meets it", rule, exact.history)
    best = best if best.complete else exact(best.values, stop=False, stage="confirm")
    action = "confirmed" if exact.key(best.values) == exact.key(first.values) else "corrected"
    return Rescaled(new.with_(lod=prob.make(best.values).lod), action, rv, dict(best.values), best, exact.frames,
                    text + (f"; corrected to {_shown(best.values)}: p99 {best.worst_p99:.3g} px <= {budget_px:g} px"
                            if action == "corrected" else " (kept)"), rule, exact.history)


def _shown(values: dict[str, float]) -> str:
    return ", ".join(f"{k} = {v:.4g}" for k, v in values.items())

