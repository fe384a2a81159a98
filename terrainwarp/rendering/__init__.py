"""Making frames: the pipeline (``render``, the one maker of every frame in the project), the prebuilt mesh
sources it draws beside the LOD policies (:mod:`.sources`: peers, polytree, bintree), the reference
tessellator and the watertightness check. The differentiable ops (JAX) are in :mod:`terrainwarp.diff`.

The package is named ``rendering``, not ``render``, because ``terrainwarp.render`` is the public function."""

from .pipeline import Frame, MeshSource, Report, render
from .sources import BintreeSource, PeerSource, PolytreeSource

__all__ = ["render", "Frame", "Report", "MeshSource", "PeerSource", "PolytreeSource", "BintreeSource"]
