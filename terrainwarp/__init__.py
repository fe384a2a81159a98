"""terrainwarp: a deterministic, differentiable CPU simulator of the GPU terrain pipeline.

Public API::

    Heightmap, StreamedHeightmap, Camera, Scene, LodConfig, render, Frame, Report, Mesh, rasterize, Fragments,
    orbit, flyover,
    Terrain, LodState, select, fit_lod, FitResult, compute_normals, compute_curvature,
    tessellate_patch, tessellate_patches, Tessellation, check_watertight, WatertightReport,
    rasterize_clip, clip_coordinates, build_polytree, Polytree, set_threads, configure

``import terrainwarp`` changes nothing process-wide (Warp's log level, stderr, the allocator, fork handlers):
``terrainwarp.configure(quiet=True, keep_memory=True)`` does, when asked (see :mod:`terrainwarp.runtime`).

Differentiable resolve for JAX (imports JAX): ``terrainwarp.diff`` (rasterize, interpolate, antialias, displace).
"""

from __future__ import annotations

from .camera import Camera, flyover, orbit
from .fit.lod_fit import FitResult, fit_lod
from .heightmap import Heightmap, StreamedHeightmap
from .kernels.parallel import set_threads
from .kernels.raster import Fragments, clip_coordinates, rasterize, rasterize_clip
from .kernels.tessellator import Tessellation, tessellate_patches
from .lod.bintree import Bintree, select_bintree
from .lod.polytree import Polytree, build_polytree
from .lod.quadtree import LodState, Terrain, select
from .lod.visibility import precompute_visibility
from .mesh import Mesh
from .rendering.pipeline import Frame, Report, render
from .rendering.reference_tessellator import tessellate_patch
from .rendering.watertight import WatertightReport, check_watertight
from .runtime import configure
from .scene import LodConfig, Scene
from .surface.differential import compute_curvature, compute_normals

__version__ = "0.1.0"
__all__ = ["fit_lod", "FitResult", "Heightmap", "StreamedHeightmap", "Camera", "Scene", "render", "Frame", "Report",
           "Mesh", "rasterize", "Fragments",
           "orbit", "flyover", "compute_normals", "compute_curvature", "Terrain", "LodState", "LodConfig", "select",
           "tessellate_patch", "tessellate_patches", "Tessellation", "check_watertight", "WatertightReport",
           "rasterize_clip", "clip_coordinates", "Bintree", "select_bintree", "precompute_visibility",
           "build_polytree", "Polytree", "set_threads", "configure", "__version__"]
