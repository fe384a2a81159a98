"""Making frames: the pipeline (``render``), the reference tessellator, the watertightness check and the
differentiable resolve (:mod:`.interpolate`, imports JAX: not imported here).

The package is named ``rendering``, not ``render``, because ``terrainwarp.render`` is the public function."""

from .pipeline import Frame, Report, render

__all__ = ["render", "Frame", "Report"]
