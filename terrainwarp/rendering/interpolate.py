"""Differentiable resolve for JAX: perspective-correct attribute interpolation from the visibility pass.

The Warp kernel ``terrainwarp.kernels.raster.interpolate_kernel`` is called through
``warp.jax_kernel(..., enable_backward=True)`` (works on the CPU backend with jax 0.10.2 and
warp-lang 1.19). Gradients reach the vertex attributes and, through the barycentrics recomputed from
clip coordinates at each pixel centre (as nvdiffrast's ``interpolate``), the clip-space positions and
hence anything upstream in JAX (vertex positions, camera matrices). The triangle id image is discrete:
no gradient flows through coverage (silhouettes) -- an antialiasing pass would be needed for that.

Example::

    frags = rasterize(pos, tri, view, proj, w, h)                 # numpy, non-differentiable
    clip = clip_positions(jnp.asarray(pos), view, proj)            # (n, 4), differentiable
    img = interpolate(jnp.asarray(attr), frags.triangle_id, clip, tri)   # (h, w, C)
    jax.grad(lambda c, a: interpolate(a, frags.triangle_id, c, tri).sum(), argnums=(0, 1))(clip, attr)

Precision: float32 throughout, like a GPU. Near silhouettes and at grazing angles the barycentrics
(ratios of cross products) lose digits; finite-difference checks need float64 references.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from jax.typing import ArrayLike

from ..kernels.raster import interpolate_kernel

__all__ = ["interpolate", "clip_positions"]

_KERNEL = None


def _kernel():  # -> the callable warp.jax_kernel returns
    """The JAX wrapper of the interpolation kernel, built on first use (building it is not free)."""
    global _KERNEL
    if _KERNEL is None:
        _KERNEL = wp.jax_kernel(interpolate_kernel, num_outputs=1, enable_backward=True)
    return _KERNEL


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
    c = jnp.asarray(clip, jnp.float32)
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"clip: expected shape (n, 4), got {tuple(c.shape)}")
    if a.ndim != 2 or a.shape[0] != c.shape[0]:
        raise ValueError(f"attr: expected shape ({c.shape[0]}, C), got {tuple(a.shape)}")
    ids = jnp.asarray(np.asarray(triangle_id) if not isinstance(triangle_id, jnp.ndarray) else triangle_id,
                      jnp.int32)
    if ids.ndim != 2:
        raise ValueError(f"triangle_id: expected shape (H, W), got {tuple(ids.shape)}")
    tri = jnp.asarray(triangles, jnp.int32)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(f"triangles: expected shape (m, 3), got {tuple(tri.shape)}")
    h, w = ids.shape
    pix = jnp.broadcast_to(ids[..., None], (h, w, a.shape[1]))
    (out,) = _kernel()(pix, c, tri, a)
    return out[..., 0] if squeeze else out
