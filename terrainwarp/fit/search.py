"""Search: the constrained optimiser on a relaxed model, its polish on the hard model, and the exact tries that
calibrate both, until the exact pipeline confirms a setting on every camera.

**On the model** (no frame drawn). Minimise ``log(mean cost)`` subject to every camera's ``log p99 + b_c <= log
target`` (``b_c`` the camera's calibration, 0 until an exact try measured it; ``target = budget * (1 - rel_tol /
2)``) by a reduced-gradient method (:func:`reduced_gradient`): the main knob is held on the constraint's boundary
by Newton steps on the soft worst camera, and the other knobs take Adam steps along the reduced gradient, the
temperature of the relaxed model annealed from 0.3 to 0.02 (``jax.jacrev`` of the relaxed model). Then
:func:`polish` on the hard model (the real selection, the probes' errors): the main knob's largest feasible value
by bisection, and coordinate moves of the others (each followed by that bisection) kept when they lower the cost.

**On the exact pipeline** (:func:`calibrated_search`). Integer knobs (``tess``, a level, a grid) are enumerated:
each value is one candidate model, ranked first by its main knob's line alone and fitted whole when it is about
to be tried; the candidate with the lowest optimistic cost (an untried one's prediction divided by
:data:`UNTRIED_BIAS`) is tried. A try measures the cameras the model puts near the worst, worst first, and stops at
the first over the budget; each measured camera's calibration becomes ``log exact - log hard`` at the main knob's
value, and the model is solved again from there (moves of the other knobs limited to a trust radius in the unit
box that grows after a good prediction and shrinks after a bad one). A feasible try within ``rel_tol`` under the
budget is measured on every camera; the search stops when no candidate's optimistic cost beats the best confirmed
cost by more than ``rel_tol``, or when a model's next setting is the one just tried. The cheapest feasible
provisional try is then measured on every camera (a camera that fails makes it infeasible).

:func:`bracket_search` is the one-knob search on the exact pipeline alone (a registered scheme without a model,
and the bisection baseline): log-space bisection until a feasible and an infeasible value are known, then log-log
interpolation of the error between them, leaning to the infeasible end, until the cost gap is within ``rel_tol``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from .exact import Evaluation, Exact
from .knobs import Knob
from .optimise import Model, NonFiniteModel, Prediction, reduced_gradient
from .timings import part

__all__ = ["Model", "Prediction", "Calibration", "Candidate", "reduced_gradient", "polish", "calibrated_search",
           "bracket_search", "close_to_bound", "NonFiniteModel"]

FLOOR = 1e-3  # px: errors below this calibrate as this (a camera whose samples are all on vertices reads 0)


@dataclass
class Calibration:
    """Each camera's calibration, ``log exact p99 - log hard p99``, from the tries that measured it: at the main
    knob's unit coordinate ``t``, the line through the camera's last two points at different ``t`` (its slope
    within +-5), the last point's value with one, 0 with none."""

    n: int
    points: dict[int, list[tuple[float, float]]] = field(default_factory=dict)

    def at(self, t: float) -> np.ndarray:
        out = np.zeros(self.n)
        for k, pts in self.points.items():
            (t2, b2) = pts[-1]
            prior = [(t1, b1) for t1, b1 in pts[:-1] if abs(t1 - t2) > 1e-4]
            if prior:
                t1, b1 = prior[-1]
                out[k] = b2 + float(np.clip((b2 - b1) / (t2 - t1), -5.0, 5.0)) * (t - t2)
            else:
                out[k] = b2
        return out

    def add(self, k: int, t: float, b: float) -> None:
        self.points.setdefault(k, []).append((float(t), float(b)))


@dataclass
class Candidate:
    """One integer combination's model, its fixed values, calibration and latest solution."""

    model: Model
    fixed: dict[str, float]
    calib: Calibration
    values: dict[str, float] = field(default_factory=dict)
    pred: Prediction | None = None
    u: np.ndarray | None = None
    radius: float = 0.15
    tried: int = 0
    feasible: bool = True  # the model meets the budget at ``values`` (else ``values`` is its finest setting)
    shift: np.ndarray | None = None  # per bounded value, log(budget / its bound): 0 for errors, for pops the ratio

    def setting(self) -> dict[str, float]:
        return {**self.fixed, **self.values}

    def offsets(self, t: float) -> np.ndarray:
        """What is added to each bounded value's log before it is compared with the budget: its calibration at the
        main knob's unit coordinate ``t`` and its shift."""
        return self.calib.at(t) + (0.0 if self.shift is None else self.shift)


def _feasible(p: Prediction, offsets: np.ndarray, target: float) -> bool:
    return bool(np.all(np.maximum(p.bounded, FLOOR) * np.exp(offsets) <= target))


Offsets = Callable[[float], np.ndarray]  # the main knob's unit coordinate -> each camera's calibration


def _main_line(model: Model, base: dict[str, float], main: Knob, target: float, calib: Offsets,
               iters: int) -> tuple[dict[str, float], Prediction | None]:
    """The coarsest value of the main knob whose hard prediction is feasible (bisection in its unit coordinate;
    the main knob's error grows toward its coarse end). None: infeasible even at its finest."""
    fine, coarse = (0.0, 1.0) if main.coarser_up else (1.0, 0.0)

    def at(t: float) -> tuple[dict[str, float], Prediction]:
        v = {**base, main.name: main.from_unit(t)}
        return v, model.hard(v)

    v, p = at(coarse)
    if _feasible(p, calib(coarse), target):
        return v, p
    best = at(fine)
    if not _feasible(best[1], calib(fine), target):
        return best[0], None
    a, b = fine, coarse
    for _ in range(iters):
        m = 0.5 * (a + b)
        vm, pm = at(m)
        if _feasible(pm, calib(m), target):
            a, best = m, (vm, pm)
        else:
            b = m
    return best


def polish(model: Model, values: dict[str, float], target: float, calib: Offsets, *,
           center: dict[str, float] | None = None, radius: float = 1.0, sweeps: int = 2, iters: int = 8,
           history: list | None = None) -> tuple[dict[str, float], Prediction | None]:
    """The hard model's best setting near ``values``: the main knob (the first) at its largest feasible value,
    then coordinate moves of each other knob by a step (halved each sweep, within ``radius`` of ``center`` in unit
    coordinates), each followed by the main knob's line, kept when the hard cost falls."""
    knobs = list(model.knobs)
    main, others = knobs[0], knobs[1:]
    center = values if center is None else center
    cur, pred = _main_line(model, values, main, target, calib, iters)
    step = 0.1
    for _ in range(sweeps if others else 0):
        for k in others:
            c = k.to_unit(center[k.name])
            for d in (step, -step):
                t = float(np.clip(k.to_unit(cur[k.name]) + d, max(0.0, c - radius), min(1.0, c + radius)))
                trial = {**cur, k.name: k.from_unit(t)}
                tv, tp = _main_line(model, trial, main, target, calib, iters)
                if tp is not None and (pred is None or tp.mean_cost < pred.mean_cost):
                    cur, pred = tv, tp
                    break
        step /= 2.0
    if history is not None:
        history.append({"stage": "polish", "values": dict(cur), "cost": None if pred is None else pred.mean_cost,
                        "p99_px": None if pred is None else [float(x) for x in pred.p99_px]})
    return cur, pred


# ------------------------------------------------------------------------------------------------
# model and exact pipeline together
# ------------------------------------------------------------------------------------------------
def _line_only(cand: Candidate, target: float) -> None:
    """``cand`` with only its main knob moved (the hard model's line): a cheap first ranking of the integer
    combinations."""
    knobs = list(cand.model.knobs)
    if cand.u is None:
        cand.u = np.array([0.5] * len(knobs))
    start = {k.name: k.from_unit(x) for k, x in zip(knobs, cand.u, strict=True)}
    with part("hard"):
        cand.values, cand.pred = _main_line(cand.model, start, knobs[0], target, cand.offsets, 10)
        cand.feasible = cand.pred is not None
        if cand.pred is None:  # infeasible even at its finest by the model: its finest, tried if nothing else is
            cand.pred = cand.model.hard(cand.values)
    cand.u = np.array([k.to_unit(cand.values[k.name]) for k in knobs])


def _solve(cand: Candidate, target: float, exact: Exact, *, first: bool,
           on_step: Callable[[], None] | None) -> None:
    """Fit ``cand`` on its model under its calibration: the reduced-gradient optimiser (over the whole box the
    first time, else within the trust radius of the latest solution; not for one knob, whose line is exact on the
    hard model), then the polish from its point and from the latest solution, the cheaper kept."""
    model = cand.model
    knobs = list(model.knobs)
    if cand.u is None:
        cand.u = np.array([0.5] * len(knobs))
    if len(knobs) == 1:
        _line_only(cand, target)
        return
    if first:
        box = None
    else:
        box = (np.clip(cand.u - cand.radius, 0, 1), np.clip(cand.u + cand.radius, 0, 1))
        box[0][0], box[1][0] = 0.0, 1.0  # the main knob is free: the polish's line sets it
    u = reduced_gradient(model, cand.u, math.log(target), cand.offsets(cand.u[0]), box=box,
                         history=exact.history, rounds=5 if first else 2, on_step=on_step)
    centre = {k.name: k.from_unit(x) for k, x in zip(knobs, cand.u, strict=True)}
    starts = [{k.name: k.from_unit(x) for k, x in zip(knobs, u, strict=True)}, centre]
    best: tuple[dict[str, float], Prediction | None] = ({}, None)
    with part("hard"):
        for start in starts:
            v, p = polish(model, start, target, cand.offsets, center=centre, radius=1.0 if first else cand.radius,
                          history=exact.history)
            if p is not None and (best[1] is None or p.mean_cost < best[1].mean_cost):
                best = (v, p)
    if best[1] is None:  # nothing feasible by the model near here: the main knob's line from the last solution
        _line_only(cand, target)
        return
    cand.values, cand.pred, cand.feasible = best[0], best[1], True
    cand.u = np.array([k.to_unit(cand.values[k.name]) for k in knobs])


def _try(exact: Exact, cand: Candidate, budget: float, snap: Callable[[dict], dict]) -> Evaluation:
    """One exact try of ``cand``'s setting: the cameras the model puts within half the budget (at least two),
    worst first, stopping at the first over; then the calibration of the cameras measured."""
    pred = cand.pred
    est = np.maximum(pred.p99_px, FLOOR) * np.exp(cand.calib.at(cand.u[0])[:len(pred.p99_px)])
    order = [int(k) for k in np.argsort(-est, kind="stable")]
    # the critical cameras: those the model puts within 25% of the worst (10% once the candidate is calibrated),
    # at least two; the others are measured once, on the setting the search ends with (a camera that then fails
    # makes that setting infeasible)
    near = 0.9 if cand.tried else 0.75
    measure = {k for k in order[:2]} | {k for k in order if est[k] >= near * est[order[0]]}
    setting = snap(cand.setting())
    e = exact(setting, order=order, measure=measure, stage="try")
    _calibrate(cand, e, setting)
    cand.tried += 1
    return e


def _calibrate(cand: Candidate, e: Evaluation, setting: dict[str, float]) -> None:
    """Each measured camera's offset: log exact - log hard, both at the setting tried (its snapped values)."""
    values = {k: setting[k] for k in cand.values}
    with part("hard"):
        hard = cand.model.hard(values)
    t = cand.model.knobs[0].to_unit(values[cand.model.knobs[0].name])
    frames = e.frames if e.frames is not None else list(range(len(e.p99_px)))
    before = cand.calib.at(t)
    for k, p in zip(frames, e.p99_px, strict=True):
        cand.calib.add(k, t, math.log(max(p, FLOOR)) - math.log(max(float(hard.p99_px[k]), FLOOR)))
    if hard.pop_px is not None and e.pop_p99_px:
        n = len(hard.p99_px)
        for k, p in enumerate(e.pop_p99_px):
            cand.calib.add(n + k, t, math.log(max(p, FLOOR)) - math.log(max(float(hard.pop_px[k]), FLOOR)))
    good = bool(np.all(np.abs(cand.calib.at(t) - before) < 0.05))
    cand.radius = min(cand.radius * 2.0, 0.5) if good else max(cand.radius / 2.0, 0.02)


#: an untried candidate's predicted cost is taken as this much too high at most (its calibration is unknown: the
#: probes of two triangles a patch read 5-20% high, sse-tess at 2 px on the DEM): it is tried while its prediction
#: divided by this beats the best cost found
UNTRIED_BIAS = 1.25


def calibrated_search(exact: Exact, cands: list[Candidate], budget: float, snap: Callable[[dict], dict], *,
                      rel_tol: float = 0.02, max_tries: int = 8,
                      on_step: Callable[[], None] | None = None) -> Evaluation | None:
    """The model-based search over the integer combinations ``cands`` (see the module docstring). Returns the
    best setting measured on every camera that meets the constraints, or None."""
    target = budget * (1.0 - 0.5 * rel_tol)
    for c in cands:  # rank the integer combinations by their main knob's line; a candidate is fitted whole when
        _line_only(c, target)  # it is about to be tried
    solved: set[int] = set()
    done: set[int] = set()
    tries = 0
    while tries < max_tries:
        live = [c for c in cands if c.pred is not None and id(c) not in done]
        if not live:
            break
        cand = _pick(live)
        if id(cand) not in solved:
            solved.add(id(cand))
            _solve(cand, target, exact, first=True, on_step=on_step)
            cand = _pick([c for c in cands if c.pred is not None and id(c) not in done])
        best = _incumbent(exact)
        if best is not None and (not cand.feasible or _optimistic(cand) >= best.cost * (1 - rel_tol)):
            break  # nothing a model knows of is cheaper by more than rel_tol
        setting = snap(cand.setting())
        seen = exact.evals.get(exact.key(setting))
        if seen is not None and seen.complete:
            done.add(id(cand))  # converged on a setting measured whole already
            continue
        e = _try(exact, cand, budget, snap)
        tries += 1
        if exact.meets(e) and close_to_bound(exact, e, rel_tol):  # close under a bound: confirm it
            whole = exact(e.values, stage="confirm")
            _calibrate(cand, whole, e.values)
            if exact.meets(whole):
                done.add(id(cand))
                continue
        before = snap(cand.setting())
        _solve(cand, target, exact, first=False, on_step=on_step)
        if not exact.meets(e) and cand.pred is not None:
            _step_finer(cand, e, rel_tol)
        if cand.pred is not None and snap(cand.setting()) == before:
            done.add(id(cand))  # the model's next setting is the one just tried
    _confirm_best(exact)
    return exact.best()


def _step_finer(cand: Candidate, e: Evaluation, rel_tol: float) -> None:
    """After an infeasible try, the next setting's main knob at least a factor ``exp(2 rel_tol)`` finer than the one
    tried: where the exact error is flat across a step of the selection (a whole level switches at once), the
    calibrated model moves the knob too little to leave the step (or, read across the step, calls every setting
    infeasible), and the candidate would end there. The search still stops once its cost cannot beat the best."""
    main = cand.model.knobs[0]
    tried, new = float(e.values[main.name]), float(cand.values[main.name])
    f = math.exp(2.0 * rel_tol)
    if main.coarser_up is False:
        bound = min(tried * f, main.hi)
        move = new < bound
    else:
        bound = max(tried / f, main.lo)
        move = new > bound
    if move or not cand.feasible:
        cand.values = {**cand.values, main.name: bound}
        with part("hard"):
            cand.pred = cand.model.hard(cand.values)
        cand.feasible = True  # a try worth its frame: the calibration read across a step is not to be trusted
        cand.u = np.array([k.to_unit(cand.values[k.name]) for k in cand.model.knobs])


def close_to_bound(exact: Exact, e: Evaluation, rel_tol: float) -> bool:
    """Within ``rel_tol`` under the budget, or under the pop bound when there is one."""
    pop = exact.max_pop_px
    return e.worst_p99 >= exact.budget_px * (1 - rel_tol) or (pop is not None and e.worst_pop >= pop * (1 - rel_tol))


def _optimistic(c: Candidate) -> float:
    """The cost a candidate may turn out to have: its prediction, less the most an uncalibrated model is off."""
    return c.pred.mean_cost / (1.0 if c.tried else UNTRIED_BIAS)


def _pick(live: list[Candidate]) -> Candidate:
    """The candidate to try: the one with the lowest optimistic cost (:func:`_optimistic`) among those the model
    says are feasible; with none, the one the model puts closest to the budget at its finest setting (a try there
    calibrates it)."""
    feasible = [c for c in live if c.feasible]
    if feasible:
        return min(feasible, key=_optimistic)
    return min(live, key=lambda c: float(np.max(np.maximum(c.pred.bounded, FLOOR) * np.exp(c.offsets(c.u[0])))))


def _incumbent(exact: Exact) -> Evaluation | None:
    """The cheapest try that met the constraints on the cameras it measured (provisional or whole)."""
    ok = [e for e in exact.evals.values() if exact.meets(e)]
    return min(ok, key=exact.rank) if ok else None


def _confirm_best(exact: Exact) -> None:
    """Measure the cheapest provisional feasible try on every camera, until one holds or none is cheaper than the
    best setting already measured whole."""
    while True:
        best = exact.best()
        pending = [e for e in exact.evals.values() if not e.complete and exact.meets(e)
                   and (best is None or e.cost < best.cost)]
        if not pending:
            return
        e = min(pending, key=exact.rank)
        exact(e.values, stage="confirm")


# ------------------------------------------------------------------------------------------------
# one knob on the exact pipeline alone
# ------------------------------------------------------------------------------------------------
def bracket_search(exact: Exact, knob: Knob, fixed: Mapping[str, float], budget: float, *, rel_tol: float = 0.02,
                   max_tries: int = 12, interpolate: bool = True,
                   newton: Callable[[Evaluation, float], float] | None = None,
                   seed: bool = False) -> Evaluation | None:
    """One knob on the exact pipeline alone: bisection in its unit coordinate (log space for a log knob) and, with
    ``interpolate``, log-log interpolation of the worst error between the feasible and the infeasible end once both
    are known (leaning to the infeasible end), until the bracket's cost gap is within ``rel_tol`` or a try lands
    within ``rel_tol`` under the budget. Each try measures the cameras worst first (by their latest p99) and stops
    at the first over the budget. ``newton(e, log_target)``, when given, proposes the knob's next value until the
    budget is bracketed (in place of the bisection midpoint). A feasible try that costs no less than the feasible
    one finer than it, before any try failed, puts the search on a cost plateau: the next try is the knob's coarse
    end (the budget holds there too, the search ends; or it fails, and the bracket is bisected). ``seed``: start
    from the bracket that the settings already measured along this line (``fixed`` the same) give: the coarsest
    measured whole that meets the constraints, the finest that does not. Returns the best feasible setting, or
    None."""
    fine, coarse = (0.0, 1.0) if knob.coarser_up is not False else (1.0, 0.0)
    latest: dict[int, float] = {}
    target = math.log(budget * (1.0 - 0.5 * rel_tol))

    def pos(e: Evaluation) -> float:
        return knob.to_unit(e.values[knob.name])

    good, bad = _bracket_of(exact, knob, fixed, pos, coarse) if seed else (None, None)
    # a bracket narrower than 2 rel_tol in log (for an interpolating search) is not refined: the exact error is a
    # step function of the knob (whole levels change at once), and a try inside so narrow a bracket rarely lands
    # on another step while a feasible one costs the whole path
    span = math.log(knob.hi / knob.lo) if knob.log and knob.lo > 0 else 1.0
    narrow = 2.0 * rel_tol / max(span, 1e-9) if interpolate else 1e-3
    if good is not None and close_to_bound(exact, good, rel_tol):
        return exact.best()  # a setting measured whole already lands within rel_tol under a bound
    e = None
    plateau = False  # a feasible try no cheaper than the feasible one finer than it, before any infeasible one
    for _ in range(max_tries + 1):
        if e is not None:
            for k, p in zip(e.frames if e.frames is not None else range(len(e.p99_px)), e.p99_px, strict=True):
                latest[k] = p
            if exact.meets(e):
                if good is not None and abs(pos(e) - coarse) < abs(pos(good) - coarse):
                    plateau = e.cost >= good.cost
                good = e if good is None or abs(pos(e) - coarse) < abs(pos(good) - coarse) else good
                if close_to_bound(exact, e, rel_tol):
                    break
            else:
                bad = e if bad is None or abs(pos(e) - fine) < abs(pos(bad) - fine) else bad
        tg = fine if good is None else pos(good)
        tb = coarse if bad is None else pos(bad)
        if good is not None and bad is not None and (good.cost - bad.cost <= rel_tol * good.cost
                                                     or abs(tg - tb) < narrow):
            break
        t = 0.5 * (tg + tb)
        if newton is not None and e is not None and (good is None or bad is None):
            t = min(max(knob.to_unit(newton(e, target)), 0.0), 1.0)
        if plateau and bad is None:  # on a cost plateau, halving toward the range's end never reaches it: try it
            t = coarse
        if interpolate and good is not None and bad is not None:
            eg = max(math.log(max(good.worst_p99, FLOOR)), target - math.log(4.0))
            eb = max(math.log(max(bad.worst_p99, FLOOR)), target - math.log(4.0))
            f = (target - eg) / (eb - eg) if eb > eg else 0.5
            t = tg + min(max(f, 0.5), 0.7) * (tb - tg)
        v = {**fixed, knob.name: knob.snap(knob.from_unit(t))}
        if e is not None and exact.key(v) in exact.evals:
            break  # nothing left to learn in the bracket
        if _ == max_tries:
            break
        order = sorted(range(len(exact.cams)), key=lambda k: (-latest.get(k, math.inf), k))
        e = exact(v, order=order, stage="bracket")
    return exact.best()


def _bracket_of(exact: Exact, knob: Knob, fixed: Mapping[str, float], pos: Callable[[Evaluation], float],
                coarse: float) -> tuple[Evaluation | None, Evaluation | None]:
    """The bracket the evaluations along ``knob``'s line (the other knobs at ``fixed``) give: (the coarsest measured
    whole that meets the constraints, the finest that does not), None where there is none."""
    line = [e for e in exact.evals.values()
            if all(e.values.get(n) == v for n, v in fixed.items() if n != knob.name)]
    ok = [e for e in line if e.complete and exact.meets(e)]
    no = [e for e in line if not exact.meets(e)]
    good = min(ok, key=lambda e: abs(pos(e) - coarse)) if ok else None
    bad = max(no, key=lambda e: abs(pos(e) - coarse)) if no else None
    return good, bad
