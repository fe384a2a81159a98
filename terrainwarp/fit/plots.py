"""Pictures of fits: one fit's steps (:func:`plot_fit`) and methods side by side, the best feasible cost against the
exact frames each needed (:func:`plot_convergence`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..io.files import save_figure
from .lod_fit import FitResult

__all__ = ["plot_fit", "plot_convergence"]

_TRIES = ("try", "confirm", "bracket", "floor", "grid")


def plot_fit(result: FitResult, path: str | Path, budgets_curve: list[tuple[float, float]] | None = None) -> Path:
    """fit.png: the relaxed optimisation (its constraint violation per round), the exact tries (worst p99 against
    the budget, the chosen one marked) and, if given, the fitted cost against the budget. Legends sit below the
    panels."""
    import matplotlib  # lazy: heavy optional dependency

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rel = [h for h in result.history if h.get("stage") == "relaxed"]
    val = [h for h in result.history if h.get("stage") in _TRIES]
    n = 3 if budgets_curve else 2
    fig, ax = plt.subplots(1, n, figsize=(5 * n, 4.6))
    if rel:
        (line,) = ax[0].plot(range(len(rel)), [h["max_violation"] for h in rel], "o-",
                             label="worst camera's log p99 - log target")
        ax[0].axhline(0.0, color="grey", ls=":", lw=0.8)
        ax[0].set_xlabel("reduced-gradient round (all candidates)")
        ax[0].set_title("relaxed model (JAX)")
        _legend_below(ax[0], [line])
    if val:
        _plot_tries(ax[1], val, result)
    if budgets_curve:
        b, c = zip(*budgets_curve)
        ax[2].plot(b, c, "o-")
        ax[2].set(xscale="log", yscale="log", xlabel="budget (px)", ylabel=f"fitted {result.cost} per frame",
                  title="cost against budget")
    fig.tight_layout()
    return save_figure(fig, path, dpi=100, bbox_inches="tight")


def _legend_below(ax, handles: list) -> None:
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize=8, frameon=False)


def _plot_tries(ax, val: list[dict], result: FitResult) -> None:
    x = list(range(len(val)))
    (tries,) = ax.plot(x, [min(h["worst_p99_px"], 1e6) for h in val], "o-", label="exact worst-frame p99 (px)")
    budget = ax.axhline(result.budget_px, color="r", ls=":", label="budget")
    handles = [tries, budget]
    chosen = [i for i, h in enumerate(val) if h["values"] == result.values]
    if chosen:
        i = chosen[-1]
        (mark,) = ax.plot([i], [val[i]["worst_p99_px"]], "*", ms=16, color="C2", markeredgecolor="k", zorder=5,
                          label=f"chosen ({result.evaluations} exact frames)")
        handles.append(mark)
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xlabel("exact try")
    ax.set_title(f"exact tries: {'met' if result.met else 'MISSED'}")
    _legend_below(ax, handles)


def plot_convergence(traces: Mapping[str, Sequence[tuple[int, float]]], path: str | Path, *, title: str = "",
                     cost_label: str = "cost per frame", target: float | None = None) -> Path:
    """One line per method: the best feasible cost (measured on every camera) against the exact frames spent to
    find it (``traces[method]``: (frames, cost) each time the best improved); ``target``: a horizontal line (the
    best cost any method found, + 2%)."""
    import matplotlib  # lazy: heavy optional dependency

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    right = max((f for tr in traces.values() for f, _ in tr), default=1)
    for name, tr in traces.items():
        pts = [(f, c) for f, c in tr if math.isfinite(c)]
        if not pts:
            continue
        xs, ys = [p[0] for p in pts] + [right], [p[1] for p in pts] + [pts[-1][1]]
        ax.step(xs, ys, where="post", label=name, lw=1.6)
        ax.plot(xs[:-1], ys[:-1], "o", ms=3, color=ax.lines[-1].get_color())
    if target is not None:
        ax.axhline(target, color="grey", ls=":", lw=1, label="best + 2%")
    ax.set(xscale="log", xlabel="exact frames measured", ylabel=f"best feasible {cost_label}", title=title)
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)
