"""Baselines a fit is measured against, on the same exact evaluation and the same frame accounting
(:class:`terrainwarp.fit.exact.Exact`): the grid search and plain bisection over one knob, and the black-box
tuners users would pick instead for many knobs: random search, Optuna's TPE with constraints, and CMA-ES (the
``cma`` package) with a penalty for infeasible settings; each seeded.

Every try of a baseline is a setting of the fitted knobs in their unit box (integer knobs snapped), measured on
every camera, worst first by the latest measured p99, stopping at the first frame over the budget (so an
infeasible setting costs few frames, as it does the fit). Optuna and cma are the optional extra ``tune``
(``pip install -e '.[tune]'``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from ..camera import Camera
from ..measure.cost import Cost
from ..measure.cost import cost as resolve_cost
from ..rendering.pipeline import Frame
from ..scene import Scene
from .exact import Evaluation, Exact
from .families import Problem, problem
from .search import bracket_search

__all__ = ["grid_search", "bisection", "random_search", "tpe", "cmaes", "BLACK_BOX", "BASELINES", "run_baselines"]


class _Tries:
    """Evaluate unit-box points of a problem's fitted knobs on ``exact``, worst camera first."""

    def __init__(self, exact: Exact, prob: Problem) -> None:
        self.exact, self.prob = exact, prob
        self.knobs = [prob.knob(n) for n in prob.names]
        self.latest: dict[int, float] = {}

    def values(self, u: np.ndarray) -> dict[str, float]:
        return self.prob.snap({**self.prob.start, **{k.name: k.from_unit(float(x))
                                                      for k, x in zip(self.knobs, u, strict=True)}})

    def __call__(self, u: np.ndarray, stage: str) -> Evaluation:
        n = len(self.exact.cams)
        order = sorted(range(n), key=lambda k: (-self.latest.get(k, math.inf), k))
        e = self.exact(self.values(u), order=order, stage=stage)
        for k, p in zip(e.frames if e.frames is not None else range(n), e.p99_px, strict=True):
            self.latest[k] = p
        return e

    def violation(self, e: Evaluation) -> float:
        """How far ``e`` is from feasible (0: feasible), in log px (+1 when a constraint is not measured)."""
        v = max(0.0, math.log(max(e.worst_p99, 1e-9) / self.exact.budget_px))
        if self.exact.max_pop_px is not None:
            pop = e.worst_pop
            v += 1.0 if math.isnan(pop) else max(0.0, math.log(max(pop, 1e-9) / max(self.exact.max_pop_px, 1e-9)))
        return v if math.isfinite(v) else 1e3


def grid_search(exact: Exact, prob: Problem, points: int = 24, evaluator: Callable | None = None) -> dict:
    """``points`` log-spaced values of the main knob (repeats dropped after snapping), each on every camera; the
    cheapest that meets the constraints. ``evaluator(values) -> [Evaluation]`` runs them elsewhere (the command
    line's sweep runner); default: on ``exact`` (counted there)."""
    k = prob.knob(prob.names[0])
    t0 = time.perf_counter()
    values = list(dict.fromkeys(prob.snap({k.name: k.from_unit(t)})[k.name] for t in np.linspace(0.0, 1.0, points)))
    if evaluator is None:
        evs = [exact({**prob.start, k.name: v}, stop=False, stage="grid") for v in values]
    else:
        evs = evaluator(values)
    ok = [e for e in evs if e.meets(exact.budget_px, exact.max_pop_px)]
    best = min(ok, key=lambda e: e.cost) if ok else None
    return {"points": len(values), "evaluations": len(values) * len(exact.cams), "wall_s": time.perf_counter() - t0,
            "value": None if best is None else best.values[k.name], "cost": None if best is None else best.cost,
            "worst_p99_px": None if best is None else best.worst_p99,
            "table": [[e.values[k.name], e.worst_p99, e.cost] + ([e.worst_pop] if exact.max_pop_px is not None else [])
                      for e in evs]}


def bisection(exact: Exact, prob: Problem, *, max_tries: int = 40, rel_tol: float = 0.02) -> Evaluation | None:
    """Plain bisection of the main knob in its unit coordinate (log space), the other knobs at the scene's values:
    the coarsest feasible setting it brackets."""
    fixed = {n: v for n, v in prob.start.items() if n != prob.names[0]}
    return bracket_search(exact, prob.knob(prob.names[0]), fixed, exact.budget_px, rel_tol=rel_tol,
                          max_tries=max_tries, interpolate=False)


def random_search(exact: Exact, prob: Problem, *, trials: int = 150, seed: int = 0) -> Evaluation | None:
    """``trials`` points drawn uniformly in the unit box."""
    tries = _Tries(exact, prob)
    rng = np.random.default_rng(seed)
    for _ in range(trials):
        tries(rng.random(len(tries.knobs)), "random")
    return exact.best()


def tpe(exact: Exact, prob: Problem, *, trials: int = 150, seed: int = 0) -> Evaluation | None:
    """Optuna's TPE sampler (multivariate, seeded) minimising the cost, with the constraint violation set on each
    trial (``Trial.set_constraint``: feasible trials preferred)."""
    import optuna  # lazy: heavy optional dependency

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    tries = _Tries(exact, prob)

    def objective(trial: optuna.Trial) -> float:
        u = np.array([trial.suggest_float(k.name, 0.0, 1.0) for k in tries.knobs])
        e = tries(u, "tpe")
        trial.set_constraint("error", tries.violation(e))
        return e.cost

    sampler = optuna.samplers.TPESampler(seed=seed, multivariate=True)
    optuna.create_study(direction="minimize", sampler=sampler).optimize(objective, n_trials=trials)
    return exact.best()


def cmaes(exact: Exact, prob: Problem, *, trials: int = 150, seed: int = 0, sigma: float = 0.25) -> Evaluation | None:
    """CMA-ES (the ``cma`` package, seeded) in the unit box from its centre, minimising ``log cost + 10 *
    violation`` (an infeasible setting costs more than any feasible one near it). One knob: CMA-ES needs two
    dimensions, so a dummy second coordinate is carried and ignored."""
    import cma  # lazy: heavy optional dependency

    tries = _Tries(exact, prob)
    n = len(tries.knobs)
    dim = max(n, 2)
    es = cma.CMAEvolutionStrategy([0.5] * dim, sigma, {"bounds": [0.0, 1.0], "seed": seed + 1, "verbose": -9,
                                                       "maxfevals": trials})
    done = 0
    while not es.stop() and done < trials:
        xs = es.ask()
        fs = []
        for x in xs:
            if done >= trials:
                fs.append(1e9)
                continue
            e = tries(np.asarray(x[:n]), "cmaes")
            done += 1
            fs.append(math.log(max(e.cost, 1e-12)) + 10.0 * tries.violation(e))
        es.tell(xs, fs)
    return exact.best()


#: the black-box tuners by name
BLACK_BOX = {"random": random_search, "tpe": tpe, "cmaes": cmaes}


#: every baseline :func:`run_baselines` runs, by name
BASELINES = ("bisection", *BLACK_BOX)


def run_baselines(scene: Scene, policy: str, knobs, cams: list[Camera], refs: list[Frame], budget_px: float,
                  methods, *, max_pop_px: float | None = None, cost: str | Cost | object = "triangles",
                  trials: int = 150, seed: int = 0, device: str = "cpu") -> dict[str, dict]:
    """Run each baseline in ``methods`` (:data:`BASELINES`) on its own :class:`Exact` over the same cameras and
    references: name -> {"values" (the best setting measured on every camera, or None), "cost", "worst_p99_px",
    "frames" (exact frames measured), "settings", "trace" ((frames, best cost) when it improved), "wall_s"}.
    Bisection moves the main knob alone."""
    cost_of = resolve_cost(cost)
    cost_of = None if cost_of.name == "triangles" else cost_of
    out = {}
    for m in methods:
        if m not in BASELINES:
            raise ValueError(f"methods: expected some of {list(BASELINES)}, got {m!r}")
        t0 = time.perf_counter()
        prob = problem(scene, policy, None if m == "bisection" else knobs, cams, refs, cost_of, device=device,
                       models=False)
        ex = Exact(prob.make, prob.key, cams, refs, budget_px, max_pop_px, cost_of, device, terrains={},
                   coarseness=prob.coarseness)
        if m == "bisection":
            bisection(ex, prob)
        else:
            BLACK_BOX[m](ex, prob, trials=trials, seed=seed)
        b = ex.best()
        out[m] = {"values": None if b is None else dict(b.values), "cost": math.inf if b is None else b.cost,
                  "worst_p99_px": math.nan if b is None else b.worst_p99, "frames": ex.frames,
                  "settings": len(ex.evals), "trace": list(ex.trace), "wall_s": time.perf_counter() - t0}
    return out
