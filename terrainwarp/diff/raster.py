"""The visibility pass for JAX (nvdiffrast's ``rasterize``): not differentiable.

The same rules and pixels as :func:`terrainwarp.rendering.rasterize` (``terrainwarp.kernels.raster.rasterize_clip``),
called from JAX through ``warp.jax_callable``, so it runs under ``jax.jit`` beside the differentiable ops.
"""

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from jax.typing import ArrayLike

from ..kernels.checks import check_viewport
from ..kernels.raster import rasterize_clip
from .contracts import callable_of, clip_array, triangle_array

__all__ = ["rasterize"]


def _forward(clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32), width: int, height: int,
             cull_back: int, out_id: wp.array2d(dtype=wp.int32), out_depth: wp.array2d(dtype=wp.float32)):
    frags = rasterize_clip(clip.numpy().reshape(-1, 4), tris.numpy().reshape(-1, 3), width, height,
                           cull_back=bool(cull_back), device=str(out_id.device))
    wp.copy(out_id, wp.array(np.ascontiguousarray(frags.triangle_id), dtype=wp.int32, device=out_id.device))
    wp.copy(out_depth, wp.array(np.ascontiguousarray(frags.depth), dtype=wp.float32, device=out_depth.device))


def rasterize(clip: ArrayLike, triangles: ArrayLike, width: int, height: int, *,
              cull_back: bool = False) -> tuple[jax.Array, jax.Array]:
    """Rasterize triangles given clip-space vertices; the visible triangle and its depth per pixel.

    Args:
        clip: (n, 4) float32 clip-space positions (x, y, z, w), OpenGL conventions (no gradient).
        triangles: (m, 3) int32 vertex indices, counter-clockwise front faces.
        width, height: viewport in pixels.
        cull_back: drop clockwise (back-facing) triangles.

    Returns:
        ``(triangle_id (H, W) int32, -1 for background; depth (H, W) float32 window depth in [0, 1], 1.0 for
        background)``, row 0 at the top: the images :func:`terrainwarp.rendering.rasterize` gives, bit for bit.
    """
    c = jax.lax.stop_gradient(clip_array(clip))
    tri = triangle_array(triangles, c.shape[0])
    width, height = check_viewport(width, height)
    if c.shape[0] == 0 or tri.shape[0] == 0:
        return jnp.full((height, width), -1, jnp.int32), jnp.ones((height, width), jnp.float32)
    ids, depth = callable_of(_forward, 2)(c, tri, int(width), int(height), int(bool(cull_back)),
                                          output_dims={"out_id": (height, width), "out_depth": (height, width)})
    return ids, depth
