"""Differentiable perspective-correct interpolation (nvdiffrast's ``interpolate``), and the vertex
transform to clip space.

Forward and backward are Warp kernels (``terrainwarp.kernels.gradients``) called from JAX through
``warp.jax_callable``: the forward interpolates every channel of a pixel at once; the backward is
deterministic (each triangle adds its own pixels in row-major order, then each vertex its triangle corners
in a fixed order; no float atomics), bit-identical on every run and for any thread count.

Example::

    ids, _ = rasterize(clip, tri, w, h)                                  # not differentiable
    img = interpolate(attr, ids, clip, tri)                              # (h, w, C)
    jax.grad(lambda c, a: interpolate(a, ids, c, tri).sum(), argnums=(0, 1))(clip, attr)

Precision: float32 throughout, like a GPU. Near silhouettes and at grazing angles the barycentrics (ratios
of cross products) lose digits; finite-difference checks need float64 references.
"""

import jax
import jax.numpy as jnp
import warp as wp
from jax.typing import ArrayLike

from ..kernels.gradients import interpolate_backward, interpolate_forward
from .contracts import callable_of, clip_array, id_image, triangle_array

__all__ = ["interpolate", "clip_positions"]


def _forward(ids: wp.array2d(dtype=wp.int32), clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32),
             attr: wp.array2d(dtype=wp.float32), out: wp.array3d(dtype=wp.float32)):
    interpolate_forward(ids, clip, tris, attr, out)


def _backward(ids: wp.array2d(dtype=wp.int32), clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32),
              attr: wp.array2d(dtype=wp.float32), g: wp.array3d(dtype=wp.float32),
              out_clip: wp.array2d(dtype=wp.float32), out_attr: wp.array2d(dtype=wp.float32)):
    interpolate_backward(ids, clip, tris, attr, g, out_clip, out_attr)


@jax.custom_vjp
def _interpolate(attr, ids, clip, tris):
    h, w = ids.shape
    (out,) = callable_of(_forward, 1)(ids, clip, tris, attr, output_dims={"out": (h, w, attr.shape[1])})
    return out


def _interpolate_fwd(attr, ids, clip, tris):
    return _interpolate(attr, ids, clip, tris), (attr, ids, clip, tris)


def _interpolate_bwd(res, g):
    attr, ids, clip, tris = res
    gclip, gattr = callable_of(_backward, 2)(ids, clip, tris, attr, jnp.asarray(g, jnp.float32),
                                             output_dims={"out_clip": clip.shape, "out_attr": attr.shape})
    return gattr, None, gclip, None


_interpolate.defvjp(_interpolate_fwd, _interpolate_bwd)


def clip_positions(positions: ArrayLike, view: ArrayLike, proj: ArrayLike) -> jax.Array:
    """(n, 3) positions -> (n, 4) clip coordinates ``(proj @ view) @ (p, 1)`` in float32, differentiable
    with respect to all three arguments."""
    p = jnp.asarray(positions, jnp.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions: expected shape (n, 3), got {p.shape}")
    mvp = jnp.asarray(proj, jnp.float32) @ jnp.asarray(view, jnp.float32)
    return jnp.concatenate([p, jnp.ones((p.shape[0], 1), jnp.float32)], axis=1) @ mvp.T


def interpolate(attr: ArrayLike, triangle_id: ArrayLike, clip: ArrayLike, triangles: ArrayLike) -> jax.Array:
    """Interpolate per-vertex attributes at every pixel centre, perspective-correctly.

    The barycentrics are recomputed from ``clip`` at each pixel centre (as nvdiffrast's ``interpolate``
    does with the ``rast`` output), so gradients reach the clip positions as well as the attributes; none
    flow through coverage (that is :func:`terrainwarp.diff.antialias`'s job).

    Args:
        attr: (n, C) float32 vertex attributes, or (n,) for one channel (differentiable).
        triangle_id: (H, W) int32 visible triangle per pixel, -1 for background (from ``rasterize``).
        clip: (n, 4) float32 clip-space vertices, the ones the visibility pass used (differentiable).
        triangles: (m, 3) int32 vertex indices.

    Returns:
        (H, W, C) float32 jax array ((H, W) for 1-D ``attr``), 0 on background.
    """
    a = jnp.asarray(attr, jnp.float32)
    squeeze = a.ndim == 1
    if squeeze:
        a = a[:, None]
    c = clip_array(clip)
    if a.ndim != 2 or a.shape[0] != c.shape[0]:
        raise ValueError(f"attr: expected shape ({c.shape[0]}, C), got {tuple(a.shape)}")
    tri = triangle_array(triangles, c.shape[0])
    ids = id_image(triangle_id, tri.shape[0])
    if tri.shape[0] == 0 or ids.size == 0:
        out = jnp.zeros((*ids.shape, a.shape[1]), jnp.float32) + 0.0 * jnp.sum(a) + 0.0 * jnp.sum(c)
    else:
        out = _interpolate(a, ids, c, tri)
    return out[..., 0] if squeeze else out

