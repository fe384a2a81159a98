"""Scene catalogues. :mod:`terrainwarp.scenes.extreme` holds the stiff and extreme cases that the
stability suite (:mod:`terrainwarp.stability`) runs through every pipeline stage."""

from .extreme import CASES, ExtremeCase, case_names, get_case

__all__ = ["CASES", "ExtremeCase", "case_names", "get_case"]
