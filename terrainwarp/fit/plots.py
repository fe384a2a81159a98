"""Pictures of fits: one fit's steps (:func:`plot_fit`) and methods side by side, the best feasible cost against the
exact frames each needed (:func:`plot_convergence`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..io.files import new_figure, save_figure
from .lod_fit import FitResult

__all__ = ["plot_fit", "fit_figure", "plot_convergence"]

_TRIES = ("try", "confirm", "bracket", "floor", "grid")


def plot_fit(result: FitResult, path: str | Path, budgets_curve: list[tuple[float, float]] | None = None) -> Path:
    """fit.png (:func:`fit_figure`), written atomically. The caller's matplotlib backend is left as it was."""
    return save_figure(fit_figure(result, budgets_curve), path, dpi=100, bbox_inches="tight")


def fit_figure(result: FitResult, budgets_curve: list[tuple[float, float]] | None = None):
    """The figure of a fit, one panel for each thing it has to show: the relaxed optimisation (its constraint
    violation per round; only a multi-knob fit has one), the exact tries (worst p99 against the budget, the chosen
    one marked; a log axis spanning at least a factor of four around the budget, so one try still reads on it)
    and, if given with two budgets or more, the fitted cost against the budget. Legends sit below the panels.
    Made without pyplot (:func:`terrainwarp.io.files.new_figure`)."""
    rel = [h for h in result.history if h.get("stage") == "relaxed"]
    val = [h for h in result.history if h.get("stage") in _TRIES]
    curve = sorted(budgets_curve or [])
    panels = [p for p, on in (("relaxed", rel), ("tries", val), ("curve", len(curve) > 1)) if on] or ["tries"]
    fig, axes = new_figure(1, len(panels), figsize=(5 * len(panels), 4.6), squeeze=False)
    ax = dict(zip(panels, axes[0]))
    if rel:
        (line,) = ax["relaxed"].plot(range(len(rel)), [h["max_violation"] for h in rel], "o-",
                                     label="worst camera's log p99 - log target")
        ax["relaxed"].axhline(0.0, color="grey", ls=":", lw=0.8)
        ax["relaxed"].set_xlabel("reduced-gradient round (all candidates)")
        ax["relaxed"].set_title("relaxed model (JAX)")
        _legend_below(ax["relaxed"], [line])
    _plot_tries(ax["tries"], val, result)
    if "curve" in ax:
        b, c = zip(*curve)
        ax["curve"].plot(b, c, "o-")
        ax["curve"].set(xscale="log", yscale="log", xlabel="budget (px)", ylabel=f"fitted {result.cost} per frame",
                        title="cost against budget")
    fig.tight_layout()
    return fig


def _legend_below(ax, handles: list) -> None:
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize=8, frameon=False)


def _plot_tries(ax, val: list[dict], result: FitResult) -> None:
    x = list(range(len(val)))
    ys = [min(h["worst_p99_px"], 1e6) for h in val]
    (tries,) = ax.plot(x, ys, "o-", label="exact worst-frame p99 (px)")
    budget = ax.axhline(result.budget_px, color="r", ls=":", label="budget")
    handles = [tries, budget]
    chosen = [i for i, h in enumerate(val) if h["values"] == result.values]
    if chosen:
        i = chosen[-1]
        (mark,) = ax.plot([i], [val[i]["worst_p99_px"]], "*", ms=16, color="C2", markeredgecolor="k", zorder=5,
                          label=f"chosen ({result.evaluations} exact frames)")
        handles.append(mark)
    ax.set_yscale("log")
    seen = [y for y in [*ys, result.budget_px] if math.isfinite(y) and y > 0]
    if seen:  # at least a factor of 2 each side: one try (or tries close to the budget) gets readable ticks
        ax.set_ylim(min(seen) / 2.0, max(seen) * 2.0)
    ax.set_xticks(x)
    ax.set_xlabel("exact try")
    ax.set_title(f"exact tries: {'met' if result.met else 'MISSED'}")
    _legend_below(ax, handles)


def plot_convergence(traces: Mapping[str, Sequence[tuple[int, float]]], path: str | Path, *, title: str = "",
                     cost_label: str = "cost per frame", target: float | None = None) -> Path:
    """One line per method: the best feasible cost (measured on every camera) against the exact frames spent to
    find it (``traces[method]``: (frames, cost) each time the best improved); ``target``: a horizontal line (the
    best cost any method found, + 2%)."""
    fig, ax = new_figure(figsize=(7, 4.5))
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
