"""Fitting LOD thresholds to a screen-error budget (:mod:`.lod_fit`) and the differentiable path
(:mod:`.diffpath`, imports JAX at import)."""

from .lod_fit import (
    Evaluation,
    FitResult,
    LodParams,
    evaluate,
    evaluations_from_rows,
    fit_lod,
    grid_search,
    plot_fit,
    relaxed_model,
)

__all__ = ["LodParams", "FitResult", "Evaluation", "fit_lod", "evaluate", "grid_search", "evaluations_from_rows",
           "relaxed_model", "plot_fit"]
