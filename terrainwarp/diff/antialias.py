"""Differentiable analytic antialiasing of silhouette and occlusion edges (nvdiffrast's ``antialias``;
Laine et al. 2020, section 3.4). The rules are stated once, in ``terrainwarp.kernels.antialias``.

Forward and backward are Warp kernels called from JAX through ``warp.jax_callable``; the backward is
deterministic (gathers and fixed-order sums, no float atomics): bit-identical on every run and for any
thread count.
"""

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from jax.typing import ArrayLike

from ..kernels.antialias import antialias_backward, antialias_forward
from ..kernels.checks import check_triangles
from .contracts import callable_of, clip_array, id_image, triangle_array

__all__ = ["antialias", "topology"]


def topology(triangles: ArrayLike) -> np.ndarray:
    """The triangle across each edge, which :func:`antialias` needs to tell silhouette edges (as
    nvdiffrast's ``antialias_construct_topology_hash``; compute it once per mesh and pass it on).

    Args:
        triangles: (m, 3) int32 vertex indices (concrete, not traced).

    Returns:
        (m, 3) int32: entry (t, k) is the triangle sharing edge k of t (k = 0: v0-v1, 1: v1-v2, 2: v2-v0),
        -1 on the mesh border and for edges shared by more than two triangles.
    """
    tri = check_triangles("triangles", triangles).astype(np.int64)
    m = len(tri)
    a = tri.reshape(-1)
    b = np.roll(tri, -1, axis=1).reshape(-1)
    key = np.minimum(a, b) * (int(tri.max(initial=0)) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]]) if m else np.zeros(0, np.int64)
    size = np.diff(np.r_[start, len(ks)])
    two = start[size == 2]
    nbr = np.full(3 * m, -1, np.int64)
    nbr[order[two]] = order[two + 1] // 3
    nbr[order[two + 1]] = order[two] // 3
    return nbr.reshape(m, 3).astype(np.int32)


def _forward(color: wp.array3d(dtype=wp.float32), ids: wp.array2d(dtype=wp.int32), clip: wp.array(dtype=wp.vec4),
             tris: wp.array2d(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), out: wp.array3d(dtype=wp.float32)):
    antialias_forward(color, ids, clip, tris, nbr, out)


def _backward(color: wp.array3d(dtype=wp.float32), ids: wp.array2d(dtype=wp.int32), clip: wp.array(dtype=wp.vec4),
              tris: wp.array2d(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), g: wp.array3d(dtype=wp.float32),
              out_color: wp.array3d(dtype=wp.float32), out_clip: wp.array2d(dtype=wp.float32)):
    antialias_backward(color, ids, clip, tris, nbr, g, out_color, out_clip)


@jax.custom_vjp
def _antialias(color, ids, clip, tris, nbr):
    (out,) = callable_of(_forward, 1)(color, ids, clip, tris, nbr, output_dims={"out": color.shape})
    return out


def _antialias_fwd(color, ids, clip, tris, nbr):
    return _antialias(color, ids, clip, tris, nbr), (color, ids, clip, tris, nbr)


def _antialias_bwd(res, g):
    color, ids, clip, tris, nbr = res
    gcolor, gclip = callable_of(_backward, 2)(color, ids, clip, tris, nbr, jnp.asarray(g, jnp.float32),
                                              output_dims={"out_color": color.shape, "out_clip": clip.shape})
    return gcolor, None, gclip, None, None


_antialias.defvjp(_antialias_fwd, _antialias_bwd)


def antialias(color: ArrayLike, triangle_id: ArrayLike, clip: ArrayLike, triangles: ArrayLike,
              neighbours: ArrayLike | None = None) -> jax.Array:
    """Antialias silhouette and occlusion edges analytically, so that gradients reach the geometry through
    coverage.

    For each pair of horizontally or vertically adjacent pixels with different triangle ids, the
    silhouette edge of the nearer triangle that crosses between the two pixel centres blends the pixel whose
    footprint it crosses towards the other, by the covered fraction (see ``terrainwarp.kernels.antialias``
    for the rules).

    Args:
        color: (H, W, C) float32 shaded image, e.g. from :func:`interpolate` (differentiable).
        triangle_id: (H, W) int32 from :func:`rasterize` (-1 background), the ids the colours were made with.
        clip: (n, 4) float32 clip-space vertices the ids were rasterized from (differentiable: gradients
            flow to the two vertices of each blending edge through where it crosses between the centres).
        triangles: (m, 3) int32 vertex indices.
        neighbours: (m, 3) int32 from :func:`topology` (computed here from concrete ``triangles`` when
            omitted; pass it to save that work per call).

    Returns:
        (H, W, C) float32 jax array.
    """
    col = jnp.asarray(color, jnp.float32)
    c = clip_array(clip)
    tri = triangle_array(triangles, c.shape[0])
    ids = id_image(triangle_id, tri.shape[0])
    if col.ndim != 3 or col.shape[:2] != ids.shape:
        raise ValueError(f"color: expected shape ({ids.shape[0]}, {ids.shape[1]}, C), got {tuple(col.shape)}")
    if neighbours is None:
        if isinstance(tri, jax.core.Tracer):
            raise ValueError("neighbours: expected topology(triangles) when triangles are traced")
        neighbours = topology(np.asarray(tri))
    nbr = jnp.asarray(neighbours, jnp.int32)
    if nbr.shape != tri.shape:
        raise ValueError(f"neighbours: expected shape {tuple(tri.shape)}, got {tuple(nbr.shape)}")
    if tri.shape[0] == 0 or ids.size == 0:
        return col + 0.0 * jnp.sum(c)
    return _antialias(col, ids, c, tri, nbr)
