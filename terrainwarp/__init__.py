"""terrainwarp: a deterministic, differentiable CPU simulator of the GPU terrain pipeline.

Public API::

    Heightmap, StreamedHeightmap, Camera, Scene, LodConfig, render, Frame, Report, Mesh, rasterize, Fragments,
    orbit, flyover,
    Terrain, LodState, select, fit_lod, FitResult, compute_normals, compute_curvature,
    tessellate_patch, tessellate_patches, Tessellation, check_watertight, WatertightReport,
    rasterize_clip, clip_coordinates, build_polytree, Polytree, set_threads

Differentiable resolve for JAX (imports JAX): ``terrainwarp.diff`` (rasterize, interpolate, antialias, displace).
"""

from __future__ import annotations

import os as _os

import warp as _wp

from .io.native import native_stderr_silenced as _native_stderr_silenced
from .io.native import say_first_compile as _say_first_compile

if _os.environ.get("TERRAINWARP_VERBOSE", "") == "":
    _wp.config.log_level = _wp.LOG_WARNING  # no per-module "load took ... ms" lines
    # Warp's native library prints "Could not find or load the NVIDIA CUDA driver" on every start of a
    # machine without a GPU (the CPU is what we run on); silence its stderr while it initialises only.
    with _native_stderr_silenced():
        _wp.init()
# Said once, on a terminal, when no kernel is cached yet: this run compiles them (about a minute on a CPU).
_say_first_compile(_wp.config.kernel_cache_dir)

from .camera import Camera, flyover, orbit  # noqa: E402
from .fit.lod_fit import FitResult, fit_lod  # noqa: E402
from .heightmap import Heightmap, StreamedHeightmap  # noqa: E402
from .kernels.parallel import keep_frame_memory as _keep_frame_memory  # noqa: E402
from .kernels.parallel import set_threads  # noqa: E402
from .kernels.raster import Fragments, clip_coordinates, rasterize, rasterize_clip  # noqa: E402
from .kernels.tessellator import Tessellation, tessellate_patches  # noqa: E402
from .lod.bintree import Bintree, select_bintree  # noqa: E402
from .lod.polytree import Polytree, build_polytree  # noqa: E402
from .lod.quadtree import LodState, Terrain, select  # noqa: E402
from .lod.visibility import precompute_visibility  # noqa: E402
from .mesh import Mesh  # noqa: E402
from .rendering.pipeline import Frame, Report, render  # noqa: E402
from .rendering.reference_tessellator import tessellate_patch  # noqa: E402
from .rendering.watertight import WatertightReport, check_watertight  # noqa: E402
from .scene import LodConfig, Scene  # noqa: E402
from .surface.differential import compute_curvature, compute_normals  # noqa: E402

# freed frame memory stays mapped for the next frame (TERRAINWARP_KEEP_MEMORY=0: glibc's defaults)
_keep_frame_memory()

__version__ = "0.1.0"
__all__ = ["fit_lod", "FitResult", "Heightmap", "StreamedHeightmap", "Camera", "Scene", "render", "Frame", "Report",
           "Mesh", "rasterize", "Fragments",
           "orbit", "flyover", "compute_normals", "compute_curvature", "Terrain", "LodState", "LodConfig", "select",
           "tessellate_patch", "tessellate_patches", "Tessellation", "check_watertight", "WatertightReport",
           "rasterize_clip", "clip_coordinates", "Bintree", "select_bintree", "precompute_visibility",
           "build_polytree", "Polytree", "set_threads", "__version__"]
