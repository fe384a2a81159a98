"""Per-node terrain statistics of a quadtree, one launch per level, computed once per heightmap.

A node of level L covers ``S_L = S_0 / 2**L`` cells along each axis from its origin
``(x * S_L, y * S_L)`` (column, row) in sample coordinates. For each node the kernel visits every
heightmap sample inside the node's closed extent (clamped to the grid) and computes:

* min and max height (the 2D range-minimum queries of deaconu2021 "Rendering", done as a min/max
  pyramid: the node's box for frustum culling);
* geometric error: the largest vertical distance between the full-resolution surface and the node's
  own surface, the bilinear interpolation of the node's ``(T+1) x (T+1)`` vertex grid (tessellation
  level T, vertex heights sampled bilinearly from the heightmap, as the domain shader does). It is 0
  exactly when the node's vertices fall on the samples (spacing 1 cell) and on any plane.

Heights are differenced relative to the node's first sample (a local reference) so an Everest-like
base does not eat the relief in float32.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .parallel import launch
from .sampling import sample_bilinear


@wp.kernel(enable_backward=False)
def _node_stats_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    size_cells: float,
    tess: int,
    # outputs
    out_min: wp.array2d(dtype=wp.float32),
    out_max: wp.array2d(dtype=wp.float32),
    out_err: wp.array2d(dtype=wp.float32),
):
    y, x = wp.tid()
    y += offset
    rows = h.shape[0]
    cols = h.shape[1]
    ox = float(x) * size_cells
    oz = float(y) * size_cells
    j0 = int(wp.ceil(ox))
    i0 = int(wp.ceil(oz))
    j1 = int(wp.min(wp.floor(ox + size_cells), float(cols - 1)))
    i1 = int(wp.min(wp.floor(oz + size_cells), float(rows - 1)))
    if j0 > cols - 1 or i0 > rows - 1:
        out_min[y, x] = 0.0
        out_max[y, x] = 0.0
        out_err[y, x] = 0.0
        return
    ref = h[i0, j0]
    lo = float(0.0)
    hi = float(0.0)
    err = float(0.0)
    step = size_cells / float(tess)
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            v = h[i, j] - ref
            lo = wp.min(lo, v)
            hi = wp.max(hi, v)
            # the node surface at this sample: bilinear between the 4 node vertices around it
            a = (float(j) - ox) / step
            b = (float(i) - oz) / step
            ca = wp.min(wp.floor(a), float(tess - 1))
            cb = wp.min(wp.floor(b), float(tess - 1))
            fa = a - ca
            fb = b - cb
            u0 = ox + ca * step
            v0 = oz + cb * step
            h00 = sample_bilinear(h, u0, v0) - ref
            h10 = sample_bilinear(h, u0 + step, v0) - ref
            h01 = sample_bilinear(h, u0, v0 + step) - ref
            h11 = sample_bilinear(h, u0 + step, v0 + step) - ref
            top = h00 + (h10 - h00) * fa
            bot = h01 + (h11 - h01) * fa
            s = top + (bot - top) * fb
            err = wp.max(err, wp.abs(v - s))
    out_min[y, x] = ref + lo
    out_max[y, x] = ref + hi
    out_err[y, x] = err


def node_stats(heights: np.ndarray, roots: tuple[int, int], root_cells: float, depth: int, tess: int,
               device: str = "cpu") -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Min, max and geometric error of every node, level by level.

    Args:
        heights: (H, W) float32.
        roots: (nx, nz) root nodes along x and z.
        root_cells: side of a root node in cells (S_0).
        depth: deepest level D.
        tess: tessellation level T of every node (its own resolution: T segments per side).

    Returns:
        ``depth + 1`` tuples (min, max, err), each (nz * 2**L, nx * 2**L) float32. Errors are made
        monotone: a node's error is at least each child's.
    """
    h = wp.array(np.ascontiguousarray(heights, dtype=np.float32), dtype=wp.float32, device=device)
    nx, nz = roots
    out = []
    for lvl in range(depth + 1):
        shape = (nz << lvl, nx << lvl)
        mn = wp.empty(shape, dtype=wp.float32, device=device)
        mx = wp.empty(shape, dtype=wp.float32, device=device)
        er = wp.empty(shape, dtype=wp.float32, device=device)
        launch(_node_stats_kernel, dim=shape, inputs=[h, float(root_cells) / float(1 << lvl), int(tess)],
               outputs=[mn, mx, er], device=device, min_items=16)  # a node loops over its cells
        out.append((mn.numpy(), mx.numpy(), er.numpy()))
    for lvl in range(depth - 1, -1, -1):  # monotone errors, bottom-up
        child = out[lvl + 1][2]
        cmax = child.reshape(child.shape[0] // 2, 2, child.shape[1] // 2, 2).max(axis=(1, 3))
        mn, mx, er = out[lvl]
        out[lvl] = (mn, mx, np.maximum(er, cmax))
    return out
