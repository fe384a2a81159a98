"""Resolve and shading: per-pixel interpolation of vertex attributes and a hillshade.

Hillshade: Lambert's law with a directional light (azimuth/elevation as in GIS hillshading) plus an
ambient term, on a hypsometric tint (colour by height, a fixed 5-stop ramp from low to high over
the heightmap's height range). Background pixels take a sky colour.
"""

from __future__ import annotations

import numpy as np
import warp as wp


@wp.func
def _ramp(t: float) -> wp.vec3:
    # green lowlands -> olive -> brown -> grey rock -> snow
    tt = wp.clamp(t, 0.0, 1.0) * 4.0
    k = int(wp.min(wp.floor(tt), 3.0))
    f = tt - float(k)
    c0 = wp.vec3(0.20, 0.42, 0.22)
    c1 = wp.vec3(0.47, 0.55, 0.30)
    c2 = wp.vec3(0.56, 0.45, 0.30)
    c3 = wp.vec3(0.55, 0.52, 0.50)
    c4 = wp.vec3(0.95, 0.95, 0.97)
    a = c0
    b = c1
    if k == 1:
        a = c1
        b = c2
    elif k == 2:
        a = c2
        b = c3
    elif k == 3:
        a = c3
        b = c4
    return a + (b - a) * f


@wp.kernel(enable_backward=False)
def _hillshade_kernel(
    tri_id: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec2),
    tris: wp.array2d(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    heights: wp.array(dtype=wp.float32),
    h_lo: float,
    h_span: float,
    light: wp.vec3,
    ambient: float,
    sky: wp.vec3,
    # outputs
    out_rgb: wp.array(dtype=wp.vec3),
    out_n: wp.array(dtype=wp.vec3),
):
    p = wp.tid()
    t = tri_id[p]
    if t < 0:
        out_rgb[p] = sky
        out_n[p] = wp.vec3(0.0, 0.0, 0.0)
        return
    b = bary[p]
    b2 = 1.0 - b[0] - b[1]
    i0 = tris[t, 0]
    i1 = tris[t, 1]
    i2 = tris[t, 2]
    n = wp.normalize(b[0] * normals[i0] + b[1] * normals[i1] + b2 * normals[i2])
    hgt = b[0] * heights[i0] + b[1] * heights[i1] + b2 * heights[i2]
    lam = wp.max(wp.dot(n, light), 0.0)
    shade = ambient + (1.0 - ambient) * lam
    out_rgb[p] = _ramp((hgt - h_lo) / h_span) * shade
    out_n[p] = n


def hillshade(triangle_id: np.ndarray, barycentrics: np.ndarray, triangles: np.ndarray, normals: np.ndarray,
              heights: np.ndarray, *, azimuth_deg: float = 315.0, elevation_deg: float = 45.0,
              ambient: float = 0.25, sky: tuple[float, float, float] = (0.62, 0.75, 0.90),
              device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Shade a frame.

    Args:
        triangle_id: (H, W) int32 from the visibility pass; barycentrics: (H, W, 2) float32.
        triangles: (m, 3) int32; normals: (n, 3) float32 unit vertex normals; heights: (n,) float32
            world heights per vertex (for the tint).
        azimuth_deg: light azimuth clockwise from north (-z); elevation_deg: above the horizon.

    Returns:
        rgb (H, W, 3) float32 linear in [0, 1], and per-pixel normals (H, W, 3) float32 (0 on background).
    """
    hh, ww = triangle_id.shape
    az = np.radians(azimuth_deg)
    el = np.radians(elevation_deg)
    # north is -z, east is +x
    light = (float(np.cos(el) * np.sin(az)), float(np.sin(el)), float(-np.cos(el) * np.cos(az)))
    fin = heights[np.isfinite(heights)]
    lo = float(fin.min()) if fin.size else 0.0
    span = max(float(fin.max()) - lo, 1e-6) if fin.size else 1.0
    npx = hh * ww
    rgb = wp.empty(npx, dtype=wp.vec3, device=device)
    nrm = wp.empty(npx, dtype=wp.vec3, device=device)
    m = max(len(triangles), 1)
    tri = np.zeros((m, 3), np.int32)
    tri[: len(triangles)] = triangles
    nv = max(len(normals), 1)
    wp.launch(_hillshade_kernel, dim=npx, inputs=[
        wp.array(triangle_id.reshape(-1), dtype=wp.int32, device=device),
        wp.array(barycentrics.reshape(-1, 2), dtype=wp.vec2, device=device),
        wp.array(tri, dtype=wp.int32, device=device),
        wp.array(np.ascontiguousarray(normals, dtype=np.float32).reshape(nv, 3) if len(normals) else
                 np.zeros((1, 3), np.float32), dtype=wp.vec3, device=device),
        wp.array(np.ascontiguousarray(heights, dtype=np.float32).reshape(-1) if len(heights) else
                 np.zeros(1, np.float32), dtype=wp.float32, device=device),
        lo, span, wp.vec3(*light), float(ambient), wp.vec3(*sky)], outputs=[rgb, nrm], device=device)
    return rgb.numpy().reshape(hh, ww, 3), nrm.numpy().reshape(hh, ww, 3)
