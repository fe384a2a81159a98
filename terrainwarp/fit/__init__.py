"""Fitting a LOD family's knobs to a screen-error budget at the lowest cost.

* :func:`fit_lod` (:mod:`.lod_fit`): the fit; :class:`FitResult` its result (``.scene``, ``.values``,
  ``.evaluations``).
* :func:`knobs`, :func:`apply` (:mod:`.knobs`): a family's knobs, and the scene a setting draws.
* :mod:`.exact`: exact evaluation and its accounting; :mod:`.probe`: the error probes; :mod:`.relaxed`: the JAX
  models; :mod:`.search`: the optimiser and the exact tries; :mod:`.families`: each family's problem;
  :mod:`.baselines`: grid search, bisection, random search, TPE and CMA-ES on the same accounting;
  :mod:`.plots`: pictures; :mod:`.diffpath`: the differentiable path through the Warp kernels (imports JAX).
* What a setting needs to travel: :func:`rescale` (:mod:`.viewport`: the setting at another viewport, each family by
  its rule, confirmed on exact frames), :func:`export` / :func:`read_export` (:mod:`.export`: the setting in CDLOD's
  or Cesium's terms), :func:`assess` (:mod:`.verdict`: a saved setting measured over its path, with what binds).
"""

from .baselines import grid_search
from .exact import Evaluation, Exact, evaluate, evaluations_from_rows
from .export import export, read_export
from .knobs import Knob, apply, knobs, values_of
from .lod_fit import FitResult, fit_lod
from .plots import plot_convergence, plot_fit
from .verdict import Assessment, assess
from .viewport import Rescaled, pixel_knobs, rescale

__all__ = ["fit_lod", "FitResult", "knobs", "apply", "values_of", "Knob", "Evaluation", "Exact", "evaluate",
           "evaluations_from_rows", "grid_search", "plot_fit", "plot_convergence", "rescale", "Rescaled",
           "pixel_knobs", "export", "read_export", "assess", "Assessment"]
