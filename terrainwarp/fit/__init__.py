"""Fitting a LOD family's knobs to a screen-error budget at the lowest cost.

* :func:`fit_lod` (:mod:`.lod_fit`): the fit; :class:`FitResult` its result (``.scene``, ``.values``,
  ``.evaluations``).
* :func:`knobs`, :func:`apply` (:mod:`.knobs`): a family's knobs, and the scene a setting draws.
* :mod:`.exact`: exact evaluation and its accounting; :mod:`.probe`: the error probes; :mod:`.relaxed`: the JAX
  models; :mod:`.search`: the optimiser and the exact tries; :mod:`.families`: each family's problem;
  :mod:`.baselines`: grid search, bisection, random search, TPE and CMA-ES on the same accounting;
  :mod:`.plots`: pictures; :mod:`.diffpath`: the differentiable path through the Warp kernels (imports JAX).
"""

from .baselines import grid_search
from .exact import Evaluation, Exact, evaluate, evaluations_from_rows
from .knobs import Knob, apply, knobs, values_of
from .lod_fit import FitResult, fit_lod
from .plots import plot_convergence, plot_fit

__all__ = ["fit_lod", "FitResult", "knobs", "apply", "values_of", "Knob", "Evaluation", "Exact", "evaluate",
           "evaluations_from_rows", "grid_search", "plot_fit", "plot_convergence"]
