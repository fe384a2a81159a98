"""The differentiable displacement stage: heightmap samples to camera-relative vertex positions.

Forward and backward are Warp kernels (``terrainwarp.kernels.gradients``) called from JAX through
``warp.jax_callable``. The backward is deterministic: vertices are grouped by bilinear cell, and each height
sample adds the gradients of the vertices of the four cells around it in a fixed order (no float atomics);
the eye's gradient is a sum over fixed blocks of vertices, the blocks in order.
"""

import functools

import jax
import jax.numpy as jnp
import warp as wp
from jax.typing import ArrayLike

from ..kernels.gradients import displace_backward, displace_forward
from .contracts import callable_of

__all__ = ["displace"]


def _forward(heights: wp.array2d(dtype=wp.float32), uv: wp.array(dtype=wp.vec2), eye: wp.array(dtype=wp.float32),
             dx: float, dz: float, out: wp.array2d(dtype=wp.float32)):
    displace_forward(heights, uv, (dx, dz), eye, out)


def _backward(uv: wp.array(dtype=wp.vec2), g: wp.array2d(dtype=wp.float32),
              out_heights: wp.array2d(dtype=wp.float32), out_eye: wp.array(dtype=wp.float32)):
    displace_backward(uv, g, out_heights, out_eye)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _displace(heights, uv, eye, dx, dz):
    (out,) = callable_of(_forward, 1)(heights, uv, eye, dx, dz, output_dims={"out": (uv.shape[0], 3)})
    return out


def _displace_fwd(heights, uv, eye, dx, dz):
    return _displace(heights, uv, eye, dx, dz), (heights.shape, uv)


def _displace_bwd(dx, dz, res, g):
    shape, uv = res
    gh, geye = callable_of(_backward, 2)(uv, jnp.asarray(g, jnp.float32),
                                         output_dims={"out_heights": shape, "out_eye": (3,)})
    return gh, jnp.zeros_like(uv), geye


_displace.defvjp(_displace_fwd, _displace_bwd)


def displace(heights: ArrayLike, dx: float, dz: float, uv: ArrayLike, eye: ArrayLike) -> jax.Array:
    """Displace surface points by the heightmap, camera-relative (the tessellator's domain-shader step).

    Heightmap sample (i, j) sits at world (j dx, h, i dz) (``terrainwarp.camera``'s convention). The point
    at ``uv`` = (u, v) in [0, 1] lies at grid coordinates (u (W-1), v (H-1)) and takes the bilinear height
    there (``terrainwarp.kernels.sampling.sample_bilinear``, clamped to the grid).

    Args:
        heights: (H, W) float32 heights in metres (differentiable).
        dx, dz: sample spacing in metres along columns (x) and rows (z).
        uv: (n, 2) float32 surface points (no gradient: a point's cell is discrete).
        eye: (3,) float32 camera position in world space (differentiable).

    Returns:
        (n, 3) float32 positions relative to the eye: ``(u (W-1) dx - eye_x, h - eye_y, v (H-1) dz - eye_z)``.
    """
    h = jnp.asarray(heights, jnp.float32)
    if h.ndim != 2 or min(h.shape) < 1:
        raise ValueError(f"heights: expected shape (H, W), got {tuple(h.shape)}")
    p = jnp.asarray(uv, jnp.float32)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"uv: expected shape (n, 2), got {tuple(p.shape)}")
    e = jnp.asarray(eye, jnp.float32).reshape(-1)
    if e.shape != (3,):
        raise ValueError(f"eye: expected 3 numbers, got shape {tuple(jnp.shape(eye))}")
    if p.shape[0] == 0:
        return jnp.zeros((0, 3), jnp.float32) + 0.0 * (jnp.sum(h) + jnp.sum(e))
    return _displace(h, p, e, float(dx), float(dz))
