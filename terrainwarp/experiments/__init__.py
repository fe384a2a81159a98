"""Experiment tools on top of the library: sweeps and Pareto reports (:mod:`.pareto`), the Dask runner
(:mod:`.runner`), the stability suite and its extreme cases, plots."""
