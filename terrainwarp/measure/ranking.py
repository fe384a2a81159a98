"""Rankings that say how sure they are: the cheapest of several candidate settings under a cost model, and whether
it stays the cheapest when the model's rates are wrong by up to a factor (:func:`verdict`).

A model's *rates* are what its cost divides by: a GPU profile's stage rates
(:class:`terrainwarp.measure.gpu.GpuProfile`: the frame's time is the overhead plus the slowest stage), or a
linear cost model's weights read as rates (:class:`terrainwarp.measure.cost.CostModel`: the time is the intercept
plus the sum of its terms). Multiplying a rate by ``m`` divides its term's time by ``m``. A candidate's cost is
the mean over its frames (report rows or ``Report.counters``).

The winner is **robust** when no combination of the rates, each multiplied by a factor on a grid of
``1/factor .. factor`` (5 points per rate in log space: 1/3, 1/sqrt 3, 1, sqrt 3, 3 for the default 3; 3 points
when 5 per rate would pass :data:`MAX_GRID` combinations), makes another candidate cheaper. When one does,
``flip`` names the smallest change that does it: a single rate first (scanned finely, :data:`SCAN` points),
else the grid combination that changes the fewest rates. Deterministic: the same rows give the same verdict.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .cost import CostModel
from .gpu import STAGES, GpuProfile

__all__ = ["Verdict", "verdict", "rate_terms", "MAX_GRID", "SCAN"]

MAX_GRID = 20000  # combinations of the full grid before it falls back to 3 points per rate
SCAN = 24  # factors per rate (log-spaced, both ways) in the single-rate scan


@dataclass(frozen=True)
class Verdict:
    """The cheapest candidate under a model and how sure that is.

    Attributes:
        model: the model's name; winner: the cheapest candidate's label; cost: its mean cost (ms); bound: the stage
            most of its frames are bound by (GPU profiles; "" for a linear model).
        robust: no rate combination within the factor changes the winner; flip: the smallest change that does
            (``"setup x0.33 -> cdlod"``), "" when robust; factor: the factor checked.
    """

    model: str
    winner: str
    cost: float
    bound: str
    robust: bool
    flip: str
    factor: float

    def row(self) -> list[str]:
        """[winner, cost, bound, robust, flip] as table cells."""
        return [self.winner, f"{self.cost:.4g}", self.bound or "-", "yes" if self.robust else "no",
                self.flip or "-"]


def rate_terms(model: CostModel | GpuProfile, rows: Sequence[Mapping[str, Any]]
               ) -> tuple[list[str], np.ndarray, str, float]:
    """(rate names, (frames, rates) float64 ms of each term, ``"max"`` or ``"sum"``, overhead ms) of ``rows``."""
    if isinstance(model, GpuProfile):
        names = [s for s in STAGES if s in model.rates]
        t = [[model.stage_ms(r)[s] for s in names] for r in rows]
        return names, np.array(t, np.float64).reshape(len(rows), len(names)), "max", float(model.overhead_ms)
    if isinstance(model, CostModel):
        names = [k for k, w in model.weights.items() if w > 0]
        t = [[model.weights[k] * float(r[k]) for k in names] for r in rows]
        return names, np.array(t, np.float64).reshape(len(rows), len(names)), "sum", float(model.intercept_ms)
    raise TypeError(f"model: expected a CostModel or a GpuProfile, got {type(model).__name__}")


def _costs(terms: list[np.ndarray], combine: str, overhead: float, mult: np.ndarray) -> np.ndarray:
    """(G, C) mean cost of each candidate (its (F, K) terms) under each of G rate multipliers (G, K)."""
    out = np.empty((len(mult), len(terms)), np.float64)
    for c, t in enumerate(terms):
        scaled = t[None, :, :] / mult[:, None, :]
        per_frame = scaled.max(axis=2) if combine == "max" else scaled.sum(axis=2)
        out[:, c] = overhead + per_frame.mean(axis=1)
    return out


def _name(model: CostModel | GpuProfile, k: str) -> str:
    if isinstance(model, GpuProfile):
        return f"{k} ({'/'.join(model.rates[k])})"
    return f"1/weight of {k}"


def _describe(model, names: list[str], m: np.ndarray, labels: list[str], c: int) -> str:
    """``"setup x0.33, shade x3 -> label"``: the rates ``m`` changes (a rate x f: f times faster)."""
    parts = [f"{_name(model, names[k])} x{m[k]:.2g}" for k in range(len(names)) if not math.isclose(m[k], 1.0)]
    return ", ".join(parts) + f" -> {labels[c]}"


def _grid(k: int, factor: float) -> np.ndarray:
    """Every combination of the per-rate factors (5 or 3 log-spaced points in [1/factor, factor])."""
    pts = 5 if 5 ** k <= MAX_GRID else 3
    levels = np.exp(np.linspace(-math.log(factor), math.log(factor), pts))
    return np.stack(np.meshgrid(*([levels] * k), indexing="ij"), -1).reshape(-1, k)


def verdict(candidates: Mapping[str, Sequence[Mapping[str, Any]]], model: CostModel | GpuProfile,
            factor: float = 3.0) -> Verdict:
    """The cheapest of ``candidates`` (label -> its frames' counters) under ``model``, and whether it stays the
    cheapest with every rate multiplied by up to ``factor`` either way (see the module docstring).

    Raises:
        ValueError: no candidate, or a candidate without frames.
    """
    if not candidates:
        raise ValueError("candidates: expected at least one setting")
    labels = list(candidates)
    terms, names, combine, overhead = [], [], "max", 0.0
    for lab in labels:
        if not candidates[lab]:
            raise ValueError(f"candidates[{lab!r}]: expected at least one frame")
        names, t, combine, overhead = rate_terms(model, candidates[lab])
        terms.append(t)
    k = len(names)
    base = np.array([np.mean([model(r) for r in candidates[lab]]) for lab in labels])  # the model's own costs
    win = int(np.argmin(base))
    bound = ""
    if combine == "max":
        hits = np.bincount(terms[win].argmax(axis=1), minlength=k)
        bound = names[int(np.argmax(hits))]
    flip = _single_flip(model, terms, names, combine, overhead, win, labels, factor) if len(labels) > 1 else ""
    if not flip and len(labels) > 1:
        flip = _grid_flip(model, terms, names, combine, overhead, win, labels, factor)
    return Verdict(model.name, labels[win], float(base[win]), bound, not flip, flip, float(factor))


def _single_flip(model, terms, names, combine, overhead, win, labels, factor) -> str:
    """The single-rate change of least |log| that makes another candidate cheapest ("" when none does)."""
    k = len(names)
    f = np.exp(np.linspace(-math.log(factor), math.log(factor), 2 * SCAN + 1))
    f = f[~np.isclose(f, 1.0)]
    f = f[np.argsort(np.abs(np.log(f)), kind="stable")]
    mult = np.ones((k * len(f), k))
    for j in range(k):
        mult[j * len(f):(j + 1) * len(f), j] = f
    winners = np.argmin(_costs(terms, combine, overhead, mult), axis=1)
    flips = np.nonzero(winners != win)[0]
    if not len(flips):
        return ""
    best = min(flips, key=lambda g: (abs(math.log(mult[g].prod())), g))
    return _describe(model, names, mult[best], labels, int(winners[best]))


def _grid_flip(model, terms, names, combine, overhead, win, labels, factor) -> str:
    """The grid combination changing the fewest rates (then the least) that makes another candidate cheapest."""
    mult = _grid(len(names), factor)
    winners = np.argmin(_costs(terms, combine, overhead, mult), axis=1)
    flips = np.nonzero(winners != win)[0]
    if not len(flips):
        return ""
    changed = (~np.isclose(mult, 1.0)).sum(axis=1)
    flips = flips[changed[flips] > 0]  # the unchanged rates are the model itself: its winner is the base one
    if not len(flips):
        return ""
    best = min(flips, key=lambda g: (changed[g], float(np.abs(np.log(mult[g])).sum()), g))
    return _describe(model, names, mult[best], labels, int(winners[best]))
