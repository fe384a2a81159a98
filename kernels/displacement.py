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


@wp.kernel(enable_backward=False)
def _sample_normals_kernel(
    nmap: wp.array2d(dtype=wp.vec3),
    uv: wp.array(dtype=wp.vec2),
    # outputs
    out_n: wp.array(dtype=wp.vec3),
):
    k = wp.tid()
    rows = nmap.shape[0]
    cols = nmap.shape[1]
    u = wp.clamp(uv[k][0] * float(cols - 1), 0.0, float(cols - 1))
    v = wp.clamp(uv[k][1] * float(rows - 1), 0.0, float(rows - 1))
    j0 = int(wp.floor(u))
    i0 = int(wp.floor(v))
    j1 = wp.min(j0 + 1, cols - 1)
    i1 = wp.min(i0 + 1, rows - 1)
    fu = u - float(j0)
    fv = v - float(i0)
    a = nmap[i0, j0] + (nmap[i0, j1] - nmap[i0, j0]) * fu
    b = nmap[i1, j0] + (nmap[i1, j1] - nmap[i1, j0]) * fu
    out_n[k] = wp.normalize(a + (b - a) * fv)


def sample_normal_map(nmap: np.ndarray, uv: np.ndarray, device: str = "cpu") -> np.ndarray:
    """Bilinear lookup of an (H, W, 3) normal map at (n, 2) uv in [0, 1] (u along columns), renormalised:
    (n, 3) float32 vertex normals (the normal map of deaconu2021 "Shading", fetched per vertex)."""
    n = len(uv)
    out = wp.empty(max(n, 1), dtype=wp.vec3, device=device)
    if n:
        wp.launch(_sample_normals_kernel, dim=n,
                  inputs=[wp.array(np.ascontiguousarray(nmap, np.float32), dtype=wp.vec3, device=device),
                          wp.array(np.ascontiguousarray(uv, np.float32), dtype=wp.vec2, device=device)],
                  outputs=[out], device=device)
    return out.numpy()[:n].reshape(n, 3)
