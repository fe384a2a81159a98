"""Per-pixel screen-space error against the full-resolution reference, as one Warp launch over pixels.

This is measurement, not pipeline: it runs in float64 (Warp's ``wp.float64`` types) so that the
error of the float32 pipeline is not hidden by the rounding of the measurement itself. The maths is
:mod:`terrainwarp.measure.error`'s (see there): P interpolated from the visible triangle with the pixel's
barycentrics, R the reference grid's height under P (two triangles per cell, the (i, j+1)-(i+1, j)
diagonal), error = distance between the projections of P and R in pixels; beside it the estimate
``|P.y - R.y| * focal_px / |P|``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .parallel import launch

vec3d = wp.types.vector(length=3, dtype=wp.float64)
mat44d = wp.types.matrix(shape=(4, 4), dtype=wp.float64)


@wp.func
def _ref_height(h: wp.array2d(dtype=wp.float32), u: wp.float64, v: wp.float64) -> wp.float64:
    rows = h.shape[0]
    cols = h.shape[1]
    uc = wp.clamp(u, wp.float64(0.0), wp.float64(cols - 1))
    vc = wp.clamp(v, wp.float64(0.0), wp.float64(rows - 1))
    j = wp.min(int(wp.floor(uc)), wp.max(cols - 2, 0))
    i = wp.min(int(wp.floor(vc)), wp.max(rows - 2, 0))
    fx = uc - wp.float64(j)
    fz = vc - wp.float64(i)
    j1 = wp.min(j + 1, cols - 1)
    i1 = wp.min(i + 1, rows - 1)
    h00 = wp.float64(h[i, j])
    h01 = wp.float64(h[i, j1])
    h10 = wp.float64(h[i1, j])
    h11 = wp.float64(h[i1, j1])
    one = wp.float64(1.0)
    if fx + fz <= one:
        return h00 + fx * (h01 - h00) + fz * (h10 - h00)
    return h11 + (one - fx) * (h10 - h11) + (one - fz) * (h01 - h11)


@wp.func
def to_window(m: mat44d, p: vec3d, w: int, hgt: int) -> wp.vec4d:
    """Window (x, y) in pixels (origin bottom-left), clip z and clip w of camera-relative p under the
    view-projection m, in float64: the one projection the measuring kernels use."""
    x = m[0, 0] * p[0] + m[0, 1] * p[1] + m[0, 2] * p[2] + m[0, 3]
    y = m[1, 0] * p[0] + m[1, 1] * p[1] + m[1, 2] * p[2] + m[1, 3]
    cz = m[2, 0] * p[0] + m[2, 1] * p[1] + m[2, 2] * p[2] + m[2, 3]
    cw = m[3, 0] * p[0] + m[3, 1] * p[1] + m[3, 2] * p[2] + m[3, 3]
    half = wp.float64(0.5)
    return wp.vec4d((x / cw * half + half) * wp.float64(w), (y / cw * half + half) * wp.float64(hgt), cz, cw)


@wp.kernel(enable_backward=False)
def _pixel_error_kernel(
    offset: int,
    tri_id: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec2),
    pos: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    h: wp.array2d(dtype=wp.float32),
    eye: vec3d,
    origin_xz: wp.vec2d,
    spacing: wp.vec2d,
    mvp: mat44d,
    focal_px: wp.float64,
    width: int,
    height: int,
    # outputs
    out_err: wp.array(dtype=wp.float64),
    out_approx: wp.array(dtype=wp.float64),
):
    k = wp.tid() + offset
    t = tri_id[k]
    if t < 0:
        out_err[k] = wp.float64(-1.0)
        out_approx[k] = wp.float64(-1.0)
        return
    b = bary[k]
    b0 = wp.float64(b[0])
    b1 = wp.float64(b[1])
    b2 = wp.float64(1.0) - b0 - b1
    a = pos[tris[t, 0]]
    c = pos[tris[t, 1]]
    d = pos[tris[t, 2]]
    p = vec3d(b0 * wp.float64(a[0]) + b1 * wp.float64(c[0]) + b2 * wp.float64(d[0]),
              b0 * wp.float64(a[1]) + b1 * wp.float64(c[1]) + b2 * wp.float64(d[1]),
              b0 * wp.float64(a[2]) + b1 * wp.float64(c[2]) + b2 * wp.float64(d[2]))
    u = (p[0] + eye[0] - origin_xz[0]) / spacing[0]
    v = (p[2] + eye[2] - origin_xz[1]) / spacing[1]
    ry = _ref_height(h, u, v) - eye[1]
    r = vec3d(p[0], ry, p[2])
    pp = to_window(mvp, p, width, height)
    rp = to_window(mvp, r, width, height)
    if rp[3] > wp.float64(0.0):
        dx = pp[0] - rp[0]
        dy = pp[1] - rp[1]
        out_err[k] = wp.sqrt(dx * dx + dy * dy)
    else:
        out_err[k] = wp.float64(1.0e300)
    dist = wp.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
    if dist > wp.float64(0.0):
        out_approx[k] = wp.abs(p[1] - ry) * focal_px / dist
    else:
        out_approx[k] = wp.float64(1.0e300)


def pixel_error(triangle_id: np.ndarray, barycentrics: np.ndarray, positions: np.ndarray, triangles: np.ndarray,
                heights: np.ndarray, eye, origin_xz, spacing, mvp: np.ndarray, focal_px: float,
                device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float64 exact error and d/dist estimate in pixels; -1 on background, 1e300 where the
    reference point is behind the camera."""
    hh, ww = triangle_id.shape
    n = hh * ww
    err = wp.empty(n, dtype=wp.float64, device=device)
    approx = wp.empty(n, dtype=wp.float64, device=device)
    m = max(len(triangles), 1)
    tri = np.zeros((m, 3), np.int32)
    tri[: len(triangles)] = triangles
    pos = np.zeros((max(len(positions), 1), 3), np.float32)
    pos[: len(positions)] = positions
    launch(_pixel_error_kernel, dim=n, inputs=[
        wp.array(np.ascontiguousarray(triangle_id, np.int32).reshape(-1), dtype=wp.int32, device=device),
        wp.array(np.ascontiguousarray(barycentrics, np.float32).reshape(-1, 2), dtype=wp.vec2, device=device),
        wp.array(pos, dtype=wp.vec3, device=device), wp.array(tri, dtype=wp.int32, device=device),
        wp.array(np.ascontiguousarray(heights, np.float32), dtype=wp.float32, device=device),
        vec3d(*[float(v) for v in eye]), wp.vec2d(*[float(v) for v in origin_xz]),
        wp.vec2d(*[float(v) for v in spacing]), mat44d(*np.asarray(mvp, np.float64).reshape(-1).tolist()),
        float(focal_px), int(ww), int(hh)], outputs=[err, approx], device=device)
    return err.numpy().reshape(hh, ww), approx.numpy().reshape(hh, ww)
