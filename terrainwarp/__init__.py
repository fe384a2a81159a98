"""terrainwarp: a deterministic, differentiable CPU simulator of the GPU terrain pipeline.

The core is re-exported here (``terrainwarp.__all__``, the one list of public names: the API reference is
built from it and a test checks it); everything else is reached by its module:

* :mod:`terrainwarp.lod`: the quadtree (``Terrain``, ``LodState``, ``select``), its policies, the bintree,
  the polytree, the peer meshers and the schemes engines ship (CDLOD, geometry clipmaps, Chunked LOD);
* :mod:`terrainwarp.rendering`: the pipeline's other types (``Report``, ``MeshSource``, the mesh sources),
  the one-launch tessellator and rasterizer, the reference tessellator, the watertightness check;
* :mod:`terrainwarp.schemes`: the LOD scheme registry (built-in schemes and yours, by name);
* :mod:`terrainwarp.fit`, :mod:`terrainwarp.measure`, :mod:`terrainwarp.surface`, :mod:`terrainwarp.io`,
  :mod:`terrainwarp.experiments`, :mod:`terrainwarp.kernels` (the Warp kernels: the "GPU");
* :mod:`terrainwarp.diff`: nvdiffrast-style differentiable ops for JAX (imports JAX; loaded on first use).

``import terrainwarp`` changes nothing process-wide (Warp's log level, stderr, the allocator, fork handlers):
``terrainwarp.configure(quiet=True, keep_memory=True)`` does, when asked (see :mod:`terrainwarp.runtime`).

Names that were here before and moved to their modules still work for one release, with a
``DeprecationWarning`` naming the new place.
"""

import importlib as _importlib
import warnings as _warnings

from . import (
    experiments,
    fit,
    io,
    kernels,
    lod,
    measure,
    rendering,
    schemes,
    surface,
    warmup,  # noqa: F401  (its first-use hook: missing kernels compiled with a progress line)
)
from .camera import Camera
from .fit.lod_fit import fit_lod
from .heightmap import Heightmap
from .rendering.pipeline import Frame, render
from .rendering.watertight import check_watertight
from .runtime import configure
from .scene import LodConfig, Scene
from .surface.differential import compute_curvature, compute_normals

__version__ = "0.1.0"

#: The public names: the core types and functions, then the subpackages (``diff`` imports JAX when first used).
__all__ = ["Heightmap", "Camera", "Scene", "LodConfig", "render", "Frame", "fit_lod", "check_watertight",
           "compute_normals", "compute_curvature", "configure",
           "diff", "experiments", "fit", "io", "kernels", "lod", "measure", "rendering", "schemes", "surface",
           "__version__"]

# Names that moved to their modules: name -> (module, name there). They resolve, with a DeprecationWarning,
# for one release (the one after 0.1.0 drops them).
_MOVED = {
    "StreamedHeightmap": ("terrainwarp.heightmap", "StreamedHeightmap"),
    "Report": ("terrainwarp.rendering", "Report"),
    "Mesh": ("terrainwarp.mesh", "Mesh"),
    "rasterize": ("terrainwarp.rendering", "rasterize"),
    "Fragments": ("terrainwarp.rendering", "Fragments"),
    "rasterize_clip": ("terrainwarp.rendering", "rasterize_clip"),
    "clip_coordinates": ("terrainwarp.rendering", "clip_coordinates"),
    "orbit": ("terrainwarp.camera", "orbit"),
    "flyover": ("terrainwarp.camera", "flyover"),
    "Terrain": ("terrainwarp.lod", "Terrain"),
    "LodState": ("terrainwarp.lod", "LodState"),
    "select": ("terrainwarp.lod", "select"),
    "FitResult": ("terrainwarp.fit", "FitResult"),
    "tessellate_patch": ("terrainwarp.rendering", "reference_tessellate_patch"),
    "tessellate_patches": ("terrainwarp.rendering", "tessellate_patches"),
    "Tessellation": ("terrainwarp.rendering", "Tessellation"),
    "WatertightReport": ("terrainwarp.rendering", "WatertightReport"),
    "Bintree": ("terrainwarp.lod.bintree", "Bintree"),
    "select_bintree": ("terrainwarp.lod.bintree", "select_bintree"),
    "precompute_visibility": ("terrainwarp.lod.visibility", "precompute_visibility"),
    "build_polytree": ("terrainwarp.lod.polytree", "build_polytree"),
    "Polytree": ("terrainwarp.lod.polytree", "Polytree"),
    "set_threads": ("terrainwarp.kernels.parallel", "set_threads"),  # or configure(threads=N)
}
_LAZY = ("diff",)  # subpackages imported on first use (JAX)


def __getattr__(name: str):
    if name in _LAZY:
        return _importlib.import_module(f"{__name__}.{name}")
    if name in _MOVED:
        module, new = _MOVED[name]
        _warnings.warn(f"terrainwarp.{name} is deprecated and goes in the next release; use {module}.{new}",
                       DeprecationWarning, stacklevel=2)
        return getattr(_importlib.import_module(module), new)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
