"""Argument checks shared by the ops of :mod:`terrainwarp.diff` ("expected X, got Y", naming the argument),
and the one way an op calls its Warp host function from JAX (``warp.jax_callable``)."""

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from jax.typing import ArrayLike

from ..kernels.checks import check_triangle_shape, check_triangles
from ..kernels.device import launch_block_dim, quietly, start

__all__ = ["callable_of", "clip_array", "id_image", "triangle_array"]


@functools.cache
def callable_of(func: Callable, num_outputs: int) -> Callable:
    """The JAX callable of a Python function of Warp arrays (``warp.jax_callable``), built once per function.
    The function launches Warp kernels through the parallel-launch helper, so an op's kernels run on
    ``terrainwarp.configure(threads=N)`` CPU threads (``warp.jax_kernel`` launches one kernel on one thread); on a GPU,
    on the device and stream of JAX's arrays. No CUDA graph capture (``JaxCallableGraphMode.NONE``): the ops
    allocate their scratch arrays per call and the rasterizer reads its inputs back to the host, neither of
    which a captured graph may do (on the CPU the mode changes nothing)."""
    start()  # Warp started quietly (terrainwarp.kernels.device), as every entry point does
    with quietly():  # the callable loads its function's (kernel-less) module on first call: here, without a line
        for dev in wp.get_devices():
            wp.get_module(func.__module__).load(dev, block_dim=launch_block_dim(dev))
    return wp.jax_callable(func, num_outputs=num_outputs, graph_mode=wp.JaxCallableGraphMode.NONE)


def clip_array(clip: ArrayLike) -> jax.Array:
    """(n, 4) float32 clip-space positions as a JAX array."""
    c = jnp.asarray(clip, jnp.float32)
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"clip: expected shape (n, 4), got {tuple(c.shape)}")
    return c


def id_image(triangle_id: ArrayLike, m: int) -> jax.Array:
    """(H, W) int32 triangle id image (-1 background) as a JAX array; ids must be below ``m``."""
    ids = triangle_id if isinstance(triangle_id, jax.Array) else np.asarray(triangle_id)
    if ids.ndim != 2:
        raise ValueError(f"triangle_id: expected shape (H, W), got {tuple(ids.shape)}")
    if isinstance(ids, np.ndarray) and ids.size and int(ids.max()) >= m:
        raise ValueError(f"triangle_id: expected ids below {m} (the number of triangles), got {int(ids.max())}")
    return jnp.asarray(ids, jnp.int32)


def triangle_array(triangles: ArrayLike, n: int) -> jax.Array:
    """(m, 3) int32 vertex indices as a JAX array; concrete indices must lie in [0, n)."""
    if isinstance(triangles, jax.Array):  # maybe traced: its values cannot be read here
        check_triangle_shape("triangles", triangles.shape, triangles.dtype)
        return jnp.asarray(triangles, jnp.int32)
    return jnp.asarray(check_triangles("triangles", triangles, n))
