"""Differentiable rendering for JAX on Warp kernels: nvdiffrast's primitives, on the CPU, deterministic.

The ops, one op's output named as the next op's input (nvdiffrast's contracts, with the visibility pass's
``triangle_id`` image in place of its ``rast`` tensor)::

    pos = displace(heights, dx, dz, uv, eye)                 # (n, 3) camera-relative; d/dheights, d/deye
    clip = clip_positions(pos, view, proj)                   # (n, 4); differentiable
    triangle_id, depth = rasterize(clip, tri, W, H)          # (H, W) int32, (H, W); not differentiable
    color = interpolate(attr, triangle_id, clip, tri)        # (H, W, C); d/dattr, d/dclip
    image = antialias(color, triangle_id, clip, tri, nbr)    # (H, W, C); d/dcolor, d/dclip via coverage

``nbr = topology(tri)`` once per mesh. Every backward pass is deterministic: no float atomics, the same
bits on every run and for any number of threads (``terrainwarp.configure(threads=N)``). What nvdiffrast has that
this lacks: ``texture`` (mipmapped filtering and its gradients), batched (minibatch) rendering, the
``rast_db`` screen-space derivatives for texture filtering, depth peeling, and CUDA speed.

Imports JAX: nothing else in terrainwarp imports this package at the top of a module.
"""

from .antialias import antialias, topology
from .displace import displace
from .interpolate import clip_positions, interpolate
from .raster import rasterize

__all__ = ["antialias", "clip_positions", "displace", "interpolate", "rasterize", "topology"]
