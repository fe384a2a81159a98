"""The relaxed model's optimiser: minimise the mean cost on the boundary of the worst camera's error budget by a
reduced-gradient method (:func:`reduced_gradient`), with the Jacobian of the relaxed model from ``jax.jacrev``.
What a family's model provides (:class:`Model`) and predicts (:class:`Prediction`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from .knobs import Knob

__all__ = ["Model", "Prediction", "reduced_gradient"]


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
    """What the search needs of a family's model: its continuous knobs, the relaxed model and the hard one."""

    knobs: Sequence[Knob]

    def relaxed(self, u: Any, temp: float) -> tuple[Any, Any]: ...

    def hard(self, values: Mapping[str, float]) -> Prediction: ...


def _jacobian(model: Model):
    """The jitted (log mean cost, soft worst calibrated log p99) of ``model`` and their gradients in ``u``, made once
    per model."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp

    fn = getattr(model, "_rg_fn", None)
    if fn is None:
        def values(u, temp, off, sharp):
            cost, logp = model.relaxed(u, temp)
            g = logp + off
            worst = jax.scipy.special.logsumexp(g * sharp) / sharp  # a soft maximum over the cameras
            return jnp.stack([jnp.log(jnp.mean(cost) + 1e-12), worst])

        fn = jax.jit(lambda u, temp, off, sharp: (values(u, temp, off, sharp),
                                                  jax.jacrev(values)(u, temp, off, sharp)))
        model._rg_fn = fn
    return fn


def reduced_gradient(model: Model, u0: np.ndarray, log_target: float, offsets: np.ndarray, *,
                     rounds: int = 5, steps: int = 12, lr: float = 0.05, t0: float = 0.3, t1: float = 0.02,
                     box: tuple[np.ndarray, np.ndarray] | None = None, history: list | None = None,
                     on_step: Callable[[], None] | None = None) -> np.ndarray:
    """Minimise the relaxed mean cost on the constraint's boundary: the main knob (coordinate 0) is held where the
    soft worst camera's calibrated log p99 equals ``log_target`` (a Newton step on it after every move), and the
    other knobs take Adam steps along the reduced gradient ``dc/ds - (dc/dm / dG/dm) dG/ds`` (``c`` the log cost,
    ``G`` the worst log p99, ``m`` the main knob, ``s`` the others), the temperature annealed from ``t0`` to
    ``t1``. Returns the unit coordinates (within ``box``, default the unit box)."""
    import jax.numpy as jnp  # lazy: heavy optional dependency
    import optax

    n = len(u0)
    if n == 0:
        return np.asarray(u0, np.float64)
    lo, hi = (np.zeros(n), np.ones(n)) if box is None else box
    fn = _jacobian(model)
    off, sharp = jnp.asarray(offsets, jnp.float32), jnp.float32(20.0)
    opt = optax.adam(lr)
    u = np.clip(np.asarray(u0, np.float64), lo, hi)
    state = opt.init(jnp.zeros(n, jnp.float32))
    for r in range(rounds):
        temp = jnp.float32(t0 * (t1 / t0) ** (r / max(rounds - 1, 1)))
        for _ in range(steps):
            u = _restore(fn, u, temp, off, sharp, log_target, lo, hi, iters=1)
            (c, g), jac = (np.asarray(x, np.float64) for x in fn(jnp.asarray(u, jnp.float32), temp, off, sharp))
            dcost, dworst = jac[0], jac[1]
            d = np.zeros(n)
            if abs(dworst[0]) > 1e-6:
                d[1:] = dcost[1:] - dcost[0] / dworst[0] * dworst[1:]
            upd, state = opt.update(jnp.asarray(d, jnp.float32), state)
            moved = np.asarray(upd, np.float64) * (np.arange(n) > 0)
            u = np.clip(u + moved, lo, hi)
            if on_step is not None:
                on_step()
            if np.max(np.abs(moved)) < 1e-3:
                break  # settled at this temperature
        u = _restore(fn, u, temp, off, sharp, log_target, lo, hi)
        if history is not None:
            (c, g), _ = fn(jnp.asarray(u, jnp.float32), temp, off, sharp)
            history.append({"stage": "relaxed", "round": r, "temperature": float(temp), "log_cost": float(c),
                            "max_violation": float(g) - log_target, "u": [float(x) for x in u]})
    return u


def _restore(fn, u: np.ndarray, temp, off, sharp, log_target: float, lo: np.ndarray, hi: np.ndarray,
             iters: int = 3) -> np.ndarray:
    """Newton steps on the main knob (coordinate 0) toward the constraint's boundary, each at most 0.15 of its
    unit range; a flat model moves it 0.1 the way the constraint asks."""
    import jax.numpy as jnp  # lazy: heavy optional dependency

    u = u.copy()
    for _ in range(iters):
        (c, g), jac = fn(jnp.asarray(u, jnp.float32), temp, off, sharp)
        gap, slope = float(g) - log_target, float(jac[1][0])
        if abs(gap) < 0.005:
            break
        step = -gap / slope if abs(slope) > 1e-3 else (0.1 if gap < 0 else -0.1) * (1.0 if slope >= 0 else -1.0)
        u[0] = float(np.clip(u[0] + np.clip(step, -0.15, 0.15), lo[0], hi[0]))
    return u
