"""Making frames: the pipeline (``render``, the one maker of every frame in the project, and its
:class:`Report`), the mesh-source protocol and the sources it draws beside the quadtree policies
(:mod:`.sources`: streamed terrains, peers, polytree, bintree, CDLOD, clipmaps, chunked LOD), the two GPU
stages a user may call on their own (the one-launch tessellator and the rasterizer, from
:mod:`terrainwarp.kernels`), the pure-Python reference tessellator and the watertightness check. The
differentiable ops (JAX) are in :mod:`terrainwarp.diff`; the scheme registry in :mod:`terrainwarp.schemes`.

The package is named ``rendering``, not ``render``, because ``terrainwarp.render`` is the public function."""

from ..kernels.pool import release_buffers
from ..kernels.raster import Fragments, clip_coordinates, rasterize, rasterize_clip
from ..kernels.tessellator import Tessellation, tessellate_patches
from .pipeline import Frame, MeshSource, Report, StageRecord, pop_stats, render
from .reference_tessellator import reference_tessellate_patch
from .sources import (
    BintreeSource,
    CdlodSource,
    ChunkedSource,
    ClipmapSource,
    PeerSource,
    PolytreeSource,
    SourceBase,
    StreamedSource,
    scheme_range,
    scheme_source,
)
from .watertight import WatertightReport, check_watertight

__all__ = ["render", "Frame", "Report", "StageRecord", "pop_stats", "MeshSource", "SourceBase", "StreamedSource",
           "PeerSource", "PolytreeSource", "BintreeSource", "CdlodSource", "ClipmapSource", "ChunkedSource",
           "scheme_source", "scheme_range", "tessellate_patches", "Tessellation", "reference_tessellate_patch",
           "rasterize", "rasterize_clip", "clip_coordinates", "Fragments", "check_watertight", "WatertightReport",
           "release_buffers"]
