"""Fitting LOD thresholds to a screen-error budget (:mod:`.lod_fit`) and the differentiable path
(:mod:`.diffpath`, imports JAX)."""

from .lod_fit import FitResult, LodParams, evaluate, fit_lod, grid_search, relaxed_model

__all__ = ["LodParams", "FitResult", "fit_lod", "evaluate", "grid_search", "relaxed_model"]
