"""Which setting wins a budget under each cost model, and how sure that is: the report's per-model winners
(:func:`budget_verdicts`) over a sweep's rows, llvmpipe's measured model beside the shipped GPU profiles
(:mod:`terrainwarp.measure.gpu`), each with its robustness (:func:`terrainwarp.measure.ranking.verdict`)."""

from __future__ import annotations

from collections.abc import Sequence

from ..measure.cost import CostModel, shipped_model
from ..measure.gpu import GpuProfile, shipped_profiles
from ..measure.ranking import Verdict, verdict

__all__ = ["report_models", "budget_verdicts", "verdict_lines", "BUDGETS", "HEADER"]

BUDGETS = (0.5, 1.0, 2.0, 4.0)
HEADER = ("budget_px", "model", "winner", "modelled ms", "bound stage", "robust (rates x1/3..x3)",
          "smallest change that flips it")


def report_models() -> list[CostModel | GpuProfile]:
    """The shipped llvmpipe model and every shipped GPU profile that can draw tessellation (a report has patch
    draws in it), in name order."""
    return [shipped_model(), *(p for p in shipped_profiles().values() if p.tessellation)]


def budget_verdicts(summary: list[dict], rows: list[dict], budgets: Sequence[float] = BUDGETS,
                    models: Sequence[CostModel | GpuProfile] | None = None,
                    factor: float = 3.0) -> list[tuple[float, str, Verdict | None]]:
    """For each budget and model: the verdict over the settings whose worst-frame p99 (``summary``) meets the
    budget, each priced by its frames (``rows`` without an error); None where no setting meets the budget."""
    models = report_models() if models is None else list(models)
    frames: dict[str, list[dict]] = {}
    for r in rows:
        if not r.get("error"):
            frames.setdefault(r["setting"], []).append(r)
    out = []
    for b in budgets:
        cands = {s["setting"]: frames[s["setting"]] for s in summary
                 if s["p99_px"] <= b and frames.get(s["setting"])}
        for m in models:
            out.append((float(b), m.name, verdict(cands, m, factor) if cands else None))
    return out


def verdict_lines(verdicts: list[tuple[float, str, Verdict | None]]) -> list[str]:
    """The verdicts as a Markdown table (a row per budget and model)."""
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "|".join("---" for _ in HEADER) + "|"]
    for b, name, v in verdicts:
        cells = v.row() if v is not None else ["no setting meets it", "-", "-", "-", "-"]
        lines.append(f"| {b:g} | {name} | " + " | ".join(cells) + " |")
    return lines
