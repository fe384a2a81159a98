"""The relaxed model's optimiser: minimise the mean cost on the boundary of the worst camera's error budget by a
reduced-gradient method (:func:`reduced_gradient`), with the Jacobian of the relaxed model from ``jax.jacrev``.
What a family's model provides (:class:`Model`) and predicts (:class:`Prediction`).

The whole solve (every round, every Adam step and Newton restore) is one jitted program per model spec and padded
sizes (:mod:`terrainwarp.fit.relaxed`), compiled once per machine (:func:`terrainwarp.fit.jaxrt.compiled`): one
``lax.while_loop`` whose body evaluates the model and its Jacobian once and then takes the step its phase asks
for (a Newton restore before a step, an Adam step, the restore that ends a round, the round's record), the same
sequence of evaluations the reduced-gradient method makes, less those at a point just evaluated (a restore that
finds the main knob on the boundary moves nothing: the step or the round's record is taken from the same
evaluation). The host sees the result once, at the end. A model
that turns non-finite stops the solve where it was (no step is taken from it) and is reported
(:class:`NonFiniteModel`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

from .jaxrt import compiled
from .knobs import Knob
from .timings import part

__all__ = ["Model", "Prediction", "reduced_gradient", "NonFiniteModel", "MAX_ROUNDS"]

MAX_ROUNDS = 5  # the most annealing rounds of one solve (the program's fixed size)
SHARP = 20.0  # the soft maximum over the cameras: logsumexp(SHARP g) / SHARP
PRE, STEP, POST, RECORD, DONE = range(5)  # the phases of the solve's loop


@dataclass(frozen=True)
class Prediction:
    """A model's prediction for every camera: ``cost`` (C,) and ``p99_px`` (C,); with a pop bound, ``pop_px``
    (C-1,) of each consecutive pair."""

    cost: np.ndarray
    p99_px: np.ndarray
    pop_px: np.ndarray | None = None

    @property
    def mean_cost(self) -> float:
        return float(np.mean(self.cost))

    @property
    def bounded(self) -> np.ndarray:
        """Every bounded value: the cameras' p99, then the pairs' pop p99."""
        return self.p99_px if self.pop_px is None else np.concatenate([self.p99_px, self.pop_px])


class Model(Protocol):
    """What the search needs of a family's model: its continuous knobs, the relaxed model (a static ``spec`` with
    ``spec.relaxed(data, u, temp)``, its padded ``data``, :meth:`padded` to lay per-camera values out as the
    padded output) and the hard one."""

    knobs: Sequence[Knob]
    spec: Any
    data: Any

    def padded(self, values: np.ndarray, fill: float) -> np.ndarray: ...

    def relaxed(self, u: Any, temp: float) -> tuple[Any, Any]: ...

    def hard(self, values: Mapping[str, float]) -> Prediction: ...


class NonFiniteModel(ArithmeticError):
    """The relaxed model (or its Jacobian) is not finite where the optimiser evaluated it."""


class _State(NamedTuple):
    phase: Any
    r: Any
    k: Any
    it: Any
    u: Any
    adam: Any
    bad: Any
    rec: Any  # (MAX_ROUNDS, 3 + n): each round's temperature, log cost, soft worst log p99 and u


def _solve(spec, data, u0, lo, hi, target, off, temps, rounds, steps, lr):
    """The reduced-gradient solve (see :func:`reduced_gradient`), traceable: (u, non-finite, the rounds' record)."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp
    import optax

    n = u0.shape[0]
    opt = optax.adam(lr)
    others = (jnp.arange(n) > 0).astype(jnp.float32)
    cmask = data["cmask"]

    def values(u, temp):
        cost, b = spec.relaxed(data, u, temp)
        worst = jax.scipy.special.logsumexp((b + off) * SHARP) / SHARP  # a soft maximum over the cameras
        out = jnp.stack([jnp.log(jnp.sum(cost * cmask) / jnp.sum(cmask) + 1e-12), worst])
        return out, out

    def newton(u, val, slope):
        """One Newton step of the main knob toward the boundary (at most 0.15 of its range; 0.1 the way the
        constraint asks on a flat model), none when within 0.005 of it: (u, close)."""
        gap = val[1] - target
        flat = jnp.abs(slope) <= 1e-3
        step = jnp.where(flat, jnp.where(gap < 0, 0.1, -0.1) * jnp.where(slope >= 0, 1.0, -1.0),
                         -gap / jnp.where(flat, 1.0, slope))
        close = jnp.abs(gap) < 0.005
        moved = u.at[0].set(jnp.clip(u[0] + jnp.clip(step, -0.15, 0.15), lo[0], hi[0]))
        return jnp.where(close, u, moved), close

    def body(s: _State) -> _State:
        temp = temps[s.r]
        jac, val = jax.jacrev(values, has_aux=True)(s.u, temp)
        bad = ~(jnp.all(jnp.isfinite(val)) & jnp.all(jnp.isfinite(jac)))
        restored, close = newton(s.u, val, jac[1, 0])
        # the step: Adam on the other knobs' reduced gradient dc/ds - (dc/dm / dG/dm) dG/ds
        ok = jnp.abs(jac[1, 0]) > 1e-6
        d = jnp.where(ok, (jac[0] - jac[0, 0] / jnp.where(ok, jac[1, 0], 1.0) * jac[1]) * others, 0.0)
        upd, adam = opt.update(d, s.adam)
        moved = upd * others
        stepped = jnp.clip(s.u + moved, lo, hi)
        settled = (jnp.max(jnp.abs(moved)) < 1e-3) | (s.k + 1 >= steps)
        record = s.rec.at[s.r].set(jnp.concatenate([jnp.stack([temp, val[0], val[1]]), s.u]))
        pre, post = s.phase == PRE, s.phase == POST
        # a restore that finds u on the boundary leaves it there: the step (after PRE) or the record (after POST)
        # would evaluate the model at the same point, so they are taken now, from this evaluation
        step = (s.phase == STEP) | (pre & close)
        rec = (s.phase == RECORD) | (post & close)
        phase = jnp.select([step, rec, pre], [jnp.where(settled, POST, PRE), jnp.where(s.r + 1 >= rounds, DONE, PRE),
                                              STEP], jnp.where(s.it + 1 >= 3, RECORD, POST))
        new = _State(phase, jnp.where(rec, s.r + 1, s.r), jnp.where(step, s.k + 1, jnp.where(rec, 0, s.k)),
                     jnp.where(post & ~close, s.it + 1, 0),
                     jnp.where(step, stepped, jnp.where(pre | post, restored, s.u)),
                     jax.tree_util.tree_map(lambda a, b: jnp.where(step, a, b), adam, s.adam), bad,
                     jnp.where(rec, record, s.rec))
        return jax.tree_util.tree_map(lambda a, b: jnp.where(bad, a, b), s._replace(bad=bad), new)

    u = jnp.clip(u0, lo, hi)
    s0 = _State(jnp.int32(PRE), jnp.int32(0), jnp.int32(0), jnp.int32(0), u, opt.init(jnp.zeros(n, jnp.float32)),
                jnp.bool_(False), jnp.zeros((MAX_ROUNDS, 3 + n), jnp.float32))
    s = jax.lax.while_loop(lambda s: (s.phase != DONE) & ~s.bad, body, s0)
    return s.u, s.bad, s.rec, s.r


def reduced_gradient(model: Model, u0: np.ndarray, log_target: float, offsets: np.ndarray, *,
                     rounds: int = 5, steps: int = 12, lr: float = 0.05, t0: float = 0.3, t1: float = 0.02,
                     box: tuple[np.ndarray, np.ndarray] | None = None, history: list | None = None,
                     on_step: Callable[[], None] | None = None) -> np.ndarray:
    """Minimise the relaxed mean cost on the constraint's boundary: the main knob (coordinate 0) is held where the
    soft worst camera's calibrated log p99 equals ``log_target`` (a Newton step on it before every step, and up to
    three to end a round), and the other knobs take Adam steps along the reduced gradient ``dc/ds - (dc/dm /
    dG/dm) dG/ds`` (``c`` the log cost, ``G`` the worst log p99, ``m`` the main knob, ``s`` the others), at most
    ``steps`` a round (fewer once a step moves less than 1e-3), the temperature annealed from ``t0`` to ``t1``
    over ``rounds`` (at most :data:`MAX_ROUNDS`). ``offsets``: what is added to each bounded value's log (one per
    camera, then per pair). One jitted program (see the module docstring); ``on_step`` is called once, at the end.
    Returns the unit coordinates (within ``box``, default the unit box).

    Raises:
        NonFiniteModel: the model or its Jacobian was not finite where the solve evaluated it (the solve stopped
            there; no step was taken from it).
    """
    n = len(u0)
    if n == 0:
        return np.asarray(u0, np.float64)
    if not 1 <= rounds <= MAX_ROUNDS:
        raise ValueError(f"rounds: expected 1..{MAX_ROUNDS}, got {rounds}")
    lo, hi = (np.zeros(n), np.ones(n)) if box is None else box
    temps = [t0 * (t1 / t0) ** (r / max(rounds - 1, 1)) for r in range(rounds)]
    args = (model.data, np.asarray(u0, np.float32), np.asarray(lo, np.float32), np.asarray(hi, np.float32),
            np.float32(log_target), model.padded(offsets, -1e4),
            np.asarray(temps + [temps[-1]] * (MAX_ROUNDS - rounds), np.float32), np.int32(rounds), np.int32(steps),
            np.float32(lr))
    with part("relaxed"):
        prog = compiled(_solve, "the relaxed model", (model.spec,), *args)
        u, bad, rec, done = (np.asarray(x) for x in prog(*args))
    if history is not None:
        for r in range(int(done)):
            history.append({"stage": "relaxed", "round": r, "temperature": float(rec[r, 0]),
                            "log_cost": float(rec[r, 1]), "max_violation": float(rec[r, 2]) - log_target,
                            "u": [float(x) for x in rec[r, 3:]]})
    if on_step is not None:
        on_step()
    if bool(bad):
        raise NonFiniteModel(f"relaxed model: not finite at u = {[float(x) for x in u]} (round {int(done)}); "
                             "no step was taken from there")
    return np.asarray(u, np.float64)

