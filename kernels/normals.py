"""Vertex normals of a heightmap, one kernel over the whole grid.

Sobel (deaconu2021, "Shading"): the 3x3 Sobel derivative filters over the 8 neighbours, divided by
8*dx and 8*dz so that they return the exact slope of a plane; n = normalize(-dh/dx, 1, -dh/dz).
Border samples outside the grid take a constant height (``border="constant"``, 0 by default, as the
paper says) or repeat the edge sample (``border="clamp"``). Heights are differenced relative to the
centre sample (a local reference), so millimetre relief on an 8,848 m base survives float32.
"""

from __future__ import annotations

import numpy as np
import warp as wp

BORDERS = {"constant": 0, "clamp": 1}


@wp.func
def _fetch_rel(h: wp.array2d(dtype=wp.float32), i: int, j: int, ref: float, border: int, c: float) -> float:
    if border == 0 and (i < 0 or j < 0 or i >= h.shape[0] or j >= h.shape[1]):
        return c - ref
    ii = wp.clamp(i, 0, h.shape[0] - 1)
    jj = wp.clamp(j, 0, h.shape[1] - 1)
    return h[ii, jj] - ref


@wp.func
def sobel_normal(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float, border: int,
                 c: float) -> wp.vec3:
    r = h[i, j]
    a = _fetch_rel(h, i - 1, j - 1, r, border, c)
    b = _fetch_rel(h, i - 1, j, r, border, c)
    d = _fetch_rel(h, i - 1, j + 1, r, border, c)
    e = _fetch_rel(h, i, j - 1, r, border, c)
    f = _fetch_rel(h, i, j + 1, r, border, c)
    g = _fetch_rel(h, i + 1, j - 1, r, border, c)
    k = _fetch_rel(h, i + 1, j, r, border, c)
    m = _fetch_rel(h, i + 1, j + 1, r, border, c)
    gx = ((d + 2.0 * f + m) - (a + 2.0 * e + g)) / (8.0 * dx)
    gz = ((g + 2.0 * k + m) - (a + 2.0 * b + d)) / (8.0 * dz)
    return wp.normalize(wp.vec3(-gx, 1.0, -gz))


@wp.kernel(enable_backward=False)
def _sobel_kernel(
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    border: int,
    c: float,
    # outputs
    out_n: wp.array2d(dtype=wp.vec3),
):
    i, j = wp.tid()
    out_n[i, j] = sobel_normal(h, i, j, dx, dz, border, c)


def sobel_normals(heights: np.ndarray, dx: float, dz: float, border: str = "clamp", constant: float = 0.0,
                  device: str = "cpu") -> np.ndarray:
    """(H, W, 3) float32 unit normals of ``heights`` by the Sobel filter."""
    if border not in BORDERS:
        raise ValueError(f"border: expected one of {sorted(BORDERS)}, got {border!r}")
    h = wp.array(np.ascontiguousarray(heights, dtype=np.float32), dtype=wp.float32, device=device)
    out = wp.empty(h.shape, dtype=wp.vec3, device=device)
    wp.launch(_sobel_kernel, dim=h.shape, inputs=[h, float(dx), float(dz), BORDERS[border], float(constant)],
              outputs=[out], device=device)
    return out.numpy().reshape(h.shape[0], h.shape[1], 3)
