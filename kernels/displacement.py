"""Meshes displaced by the heightmap (the domain-shader side of the pipeline).

The full-resolution grid mesh: one vertex per sample, two counter-clockwise (seen from +y) triangles
per cell, split along the (i, j+1)-(i+1, j) diagonal. Positions are camera-relative: the host
subtracts the eye from the grid origin in float64, and the kernel adds ``j*dx`` and ``i*dz`` in float32
to that offset, so a terrain 10,000 km from the world origin is as precise as one at the origin.
"""

from __future__ import annotations

import numpy as np
import warp as wp


@wp.kernel(enable_backward=False)
def _grid_vertices_kernel(
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    rel_origin: wp.vec3,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
    out_uv: wp.array(dtype=wp.vec2),
):
    i, j = wp.tid()
    w = h.shape[1]
    k = i * w + j
    out_pos[k] = wp.vec3(rel_origin[0] + float(j) * dx, h[i, j] - rel_origin[1], rel_origin[2] + float(i) * dz)
    out_uv[k] = wp.vec2(float(j) / float(wp.max(w - 1, 1)), float(i) / float(wp.max(h.shape[0] - 1, 1)))


@wp.kernel(enable_backward=False)
def _grid_triangles_kernel(
    w: int,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    i, j = wp.tid()  # cell (i, j)
    cells_w = w - 1
    t = 2 * (i * cells_w + j)
    v00 = i * w + j
    v01 = v00 + 1
    v10 = v00 + w
    v11 = v10 + 1
    out_tri[t, 0] = v00
    out_tri[t, 1] = v10
    out_tri[t, 2] = v01
    out_tri[t + 1, 0] = v01
    out_tri[t + 1, 1] = v10
    out_tri[t + 1, 2] = v11


def grid_mesh(heights: np.ndarray, dx: float, dz: float, rel_origin: tuple[float, float, float],
              device: str = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full-resolution grid mesh.

    Args:
        heights: (H, W) float32.
        rel_origin: (x0 - eye_x, eye_y, z0 - eye_z): grid origin relative to the eye, and the eye
            height (subtracted from every height).

    Returns:
        positions (H*W, 3) float32 camera-relative, uv (H*W, 2) float32 in [0, 1],
        triangles (2*(H-1)*(W-1), 3) int32.
    """
    hh, ww = heights.shape
    h = wp.array(np.ascontiguousarray(heights, dtype=np.float32), dtype=wp.float32, device=device)
    pos = wp.empty(hh * ww, dtype=wp.vec3, device=device)
    uv = wp.empty(hh * ww, dtype=wp.vec2, device=device)
    wp.launch(_grid_vertices_kernel, dim=(hh, ww), inputs=[h, float(dx), float(dz), wp.vec3(*rel_origin)],
              outputs=[pos, uv], device=device)
    m = 2 * max(hh - 1, 0) * max(ww - 1, 0)
    tri = wp.empty((max(m, 1), 3), dtype=wp.int32, device=device)
    if m:
        wp.launch(_grid_triangles_kernel, dim=(hh - 1, ww - 1), inputs=[ww], outputs=[tri], device=device)
    return (pos.numpy().reshape(-1, 3), uv.numpy().reshape(-1, 2), tri.numpy()[:m].reshape(-1, 3))
