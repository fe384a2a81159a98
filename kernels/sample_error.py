"""Screen-space error at the heightmap's samples: the drawn surface's height above every sample, and the
pixel distance between two points above one sample, as Warp launches over samples.

Measurement, not pipeline: the per-sample kernels run in float64 (the float32 pipeline is measured, its
rounding is not hidden by the measurement's own). The maths is :mod:`terrainwarp.measure.sample_error`'s
(see there); in short:

1. :func:`surface_at_samples`: a top-down "raster" whose pixels are the heightmap's samples, done as a
   scatter over triangles: each triangle visits the samples in its (x, z) bounding box and claims those
   inside it (an inclusive float64 test: within 8 float32 ulps of the coordinates outside an edge, the
   rounding by which a sample and a vertex at the same place may differ) with an atomic min of its id, so the
   lowest-numbered triangle holding a sample wins, whatever the launch order. Then, per sample, that
   triangle's plane is evaluated in float64 at the sample's exact camera-relative (x, z) (float32, computed
   as :func:`terrainwarp.kernels.displacement.grid_mesh` places its vertices). A sample that is a vertex
   (same x and z, bit for bit) takes the vertex's height exactly.

   Not :func:`terrainwarp.kernels.raster.rasterize` with an orthographic camera: its fill rule gives the
   samples on a mesh's outer boundary to no triangle, and a triangle smaller than a cell (the bintree's
   level-M vertex grid is finer than the bundled DEM's samples) may hold a sample yet cover no pixel
   centre, so the sample would get a neighbour's plane extrapolated (measured: up to 0.49 m on 2.5% of
   the DEM's samples with a pixel-centre look-up nudged off the boundary).
2. :func:`sample_displacement`: per sample P = (x, h, z), its visibility in the frame (viewport, near and
   far planes, depth test against a full-detail depth buffer with a tolerance) and the pixel distance
   between the projections of (x, y_a, z) and (x, y_b, z) (y_a = h for the primary error).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .metrics import to_window
from .parallel import atomic_min_i32, launch, view
from .pool import pooled_array

NONE = 2147483647  # no triangle covers the sample (the cover map's initial value)
CONTAIN_ULPS = 8.0  # slack of the inclusive point-in-triangle test, float32 ulps of the coordinates
DEPTH_REL_TOL = 1.0e-4  # relative slack of view depths (float32 positions and the rasterizer's depth plane)
DEPTH_ULPS = 8.0  # float32 ulps of window depth the depth buffer may be off by (quantisation + plane rounding)

# sample states (out_state of sample_displacement)
VISIBLE = 0  # measured
NO_DATA = 1  # the sample's height is NaN
OUTSIDE = 2  # outside the viewport, in front of the near plane or beyond the far plane
HIDDEN = 3  # fails the depth test against the full-detail frame
MISSING = 4  # visible, but no drawn surface above or below it (culled patch, hole)

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def _sample_xz(rel_origin: wp.vec3, dx: float, dz: float, i: int, j: int) -> wp.vec2d:
    """Camera-relative (x, z) of sample (i, j), rounded as grid_mesh's float32 vertices are."""
    x = rel_origin[0] + float(j) * dx
    z = rel_origin[2] + float(i) * dz
    return wp.vec2d(wp.float64(x), wp.float64(z))


@wp.func
def _vertex(pos: wp.array(dtype=wp.vec3), k: int, offset: wp.vec3d) -> wp.vec3d:
    p = pos[k]
    return wp.vec3d(wp.float64(p[0]) + offset[0], wp.float64(p[1]) + offset[1], wp.float64(p[2]) + offset[2])


@wp.func
def _weights(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, p: wp.vec2d) -> wp.vec3d:
    """Barycentric weights of (x, z) = p in triangle abc projected on the xz plane; (-1e300, ...) when
    the projection is degenerate."""
    det = (b[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (b[2] - a[2])
    if det == wp.float64(0.0):
        return wp.vec3d(wp.float64(-1.0e300), wp.float64(0.0), wp.float64(0.0))
    wb = ((p[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (p[1] - a[2])) / det
    wc = ((b[0] - a[0]) * (p[1] - a[2]) - (p[0] - a[0]) * (b[2] - a[2])) / det
    return wp.vec3d(wp.float64(1.0) - wb - wc, wb, wc)


@wp.func
def _plane_y(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, p: wp.vec2d) -> wp.float64:
    """Height of triangle abc's plane at (x, z) = p; a vertex at p gives its own height exactly."""
    if a[0] == p[0] and a[2] == p[1]:
        return a[1]
    if b[0] == p[0] and b[2] == p[1]:
        return b[1]
    if c[0] == p[0] and c[2] == p[1]:
        return c[1]
    w = _weights(a, b, c, p)
    if w[0] == wp.float64(-1.0e300):
        return wp.float64(wp.nan)
    return w[0] * a[1] + w[1] * b[1] + w[2] * c[1]


@wp.func
def _inside(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, p: wp.vec2d) -> wp.bool:
    """Whether (x, z) = p lies in triangle abc's xz projection or within CONTAIN_ULPS float32 ulps of the
    largest camera-relative coordinate outside one of its edges (vertices and samples are float32 rounded
    differently: a sample on a mesh's border must not fall off it). Degenerate projections hold nothing."""
    det = (b[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (b[2] - a[2])
    if det == wp.float64(0.0):
        return False
    m = wp.max(wp.max(wp.max(wp.abs(a[0]), wp.abs(a[2])), wp.max(wp.abs(b[0]), wp.abs(b[2]))),
               wp.max(wp.max(wp.abs(c[0]), wp.abs(c[2])), wp.max(wp.abs(p[0]), wp.abs(p[1]))))
    tol = wp.float64(CONTAIN_ULPS) * wp.float64(5.9604644775390625e-08) * m
    s = wp.sign(det)
    # signed distances (positive inside) of p from the edges bc, ca, ab
    e0 = s * ((c[0] - b[0]) * (p[1] - b[2]) - (c[2] - b[2]) * (p[0] - b[0]))
    e1 = s * ((a[0] - c[0]) * (p[1] - c[2]) - (a[2] - c[2]) * (p[0] - c[0]))
    e2 = s * ((b[0] - a[0]) * (p[1] - a[2]) - (b[2] - a[2]) * (p[0] - a[0]))
    l0 = wp.sqrt((c[0] - b[0]) * (c[0] - b[0]) + (c[2] - b[2]) * (c[2] - b[2]))
    l1 = wp.sqrt((a[0] - c[0]) * (a[0] - c[0]) + (a[2] - c[2]) * (a[2] - c[2]))
    l2 = wp.sqrt((b[0] - a[0]) * (b[0] - a[0]) + (b[2] - a[2]) * (b[2] - a[2]))
    return e0 >= -tol * l0 and e1 >= -tol * l1 and e2 >= -tol * l2


@wp.func
def _view_depth(d: wp.float32, near: wp.float64, far: wp.float64) -> wp.float64:
    """View depth (clip w) of window depth d in [0, 1) under gluPerspective(near, far)."""
    zn = wp.float64(2.0) * wp.float64(d) - wp.float64(1.0)
    return wp.float64(2.0) * far * near / ((far + near) - zn * (far - near))


@wp.func
def _one_sided(depth: wp.array2d(dtype=wp.float32), r: int, c: int, dr: int, dc: int, dc0: wp.float64,
               near: wp.float64, far: wp.float64) -> wp.float64:
    """|view depth change| from pixel (r, c) to (r + dr, c + dc); -1 when that pixel is off the image or
    background."""
    r1 = r + dr
    c1 = c + dc
    if r1 < 0 or c1 < 0 or r1 >= depth.shape[0] or c1 >= depth.shape[1]:
        return wp.float64(-1.0)
    d = depth[r1, c1]
    if d >= wp.float32(1.0):
        return wp.float64(-1.0)
    return wp.abs(_view_depth(d, near, far) - dc0)


@wp.func
def _minmod(a: wp.float64, b: wp.float64) -> wp.float64:
    """The smaller of two one-sided differences (-1: missing): an occluding edge on one side does not
    widen the tolerance."""
    if a < wp.float64(0.0):
        return wp.max(b, wp.float64(0.0))
    if b < wp.float64(0.0):
        return a
    return wp.min(a, b)


@wp.func
def _depth_tolerance(depth: wp.array2d(dtype=wp.float32), r: int, c: int, dref: wp.float64, near: wp.float64,
                     far: wp.float64) -> wp.float64:
    """Slack of the depth test at pixel (r, c) whose view depth is dref (see the module docstring of
    terrainwarp.measure.sample_error): relative rounding, depth-buffer quantisation, one pixel's change."""
    gx = _minmod(_one_sided(depth, r, c, 0, -1, dref, near, far), _one_sided(depth, r, c, 0, 1, dref, near, far))
    gy = _minmod(_one_sided(depth, r, c, -1, 0, dref, near, far), _one_sided(depth, r, c, 1, 0, dref, near, far))
    quant = wp.float64(DEPTH_ULPS) * wp.float64(5.9604644775390625e-08) * dref * dref * (far - near) / (far * near)
    return wp.float64(DEPTH_REL_TOL) * dref + quant + gx + gy


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _cover_kernel(
    offset: int,
    pos: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    eye_shift: wp.vec3d,
    rel_origin: wp.vec3,
    dx: float,
    dz: float,
    rows: int,
    cols: int,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    t = wp.tid() + offset
    a = _vertex(pos, tris[t, 0], eye_shift)
    b = _vertex(pos, tris[t, 1], eye_shift)
    c = _vertex(pos, tris[t, 2], eye_shift)
    ox = wp.float64(rel_origin[0])
    oz = wp.float64(rel_origin[2])
    lo = wp.float64(-1.0)
    gx0 = wp.clamp((wp.min(a[0], wp.min(b[0], c[0])) - ox) / wp.float64(dx), lo, wp.float64(cols))
    gx1 = wp.clamp((wp.max(a[0], wp.max(b[0], c[0])) - ox) / wp.float64(dx), lo, wp.float64(cols))
    gz0 = wp.clamp((wp.min(a[2], wp.min(b[2], c[2])) - oz) / wp.float64(dz), lo, wp.float64(rows))
    gz1 = wp.clamp((wp.max(a[2], wp.max(b[2], c[2])) - oz) / wp.float64(dz), lo, wp.float64(rows))
    slack = wp.float64(1.0e-6)
    j0 = wp.max(int(wp.floor(gx0 - slack)), 0)
    j1 = wp.min(int(wp.ceil(gx1 + slack)), cols - 1)
    i0 = wp.max(int(wp.floor(gz0 - slack)), 0)
    i1 = wp.min(int(wp.ceil(gz1 + slack)), rows - 1)
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            if _inside(a, b, c, _sample_xz(rel_origin, dx, dz, i, j)):
                atomic_min_i32(out_tri, i, j, t)  # a true atomic: chunks run on several threads


@wp.func
def _surface_y(t: int, pos: wp.array(dtype=wp.vec3), tris: wp.array2d(dtype=wp.int32), eye_shift: wp.vec3d,
               rel_origin: wp.vec3, dx: float, dz: float, i: int, j: int) -> wp.float64:
    """The height of triangle t's plane above sample (i, j) (NaN for NONE)."""
    if t == NONE:
        return wp.float64(wp.nan)
    return _plane_y(_vertex(pos, tris[t, 0], eye_shift), _vertex(pos, tris[t, 1], eye_shift),
                    _vertex(pos, tris[t, 2], eye_shift), _sample_xz(rel_origin, dx, dz, i, j))


@wp.kernel(enable_backward=False)
def _surface_kernel(
    offset: int,
    cover: wp.array2d(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    eye_shift: wp.vec3d,
    rel_origin: wp.vec3,
    dx: float,
    dz: float,
    # outputs
    out_y: wp.array2d(dtype=wp.float64),
):
    i, j = wp.tid()
    i += offset
    out_y[i, j] = _surface_y(cover[i, j], pos, tris, eye_shift, rel_origin, dx, dz, i, j)


@wp.kernel(enable_backward=False)
def _surface_list_kernel(
    offset: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    cover: wp.array2d(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    eye_shift: wp.vec3d,
    rel_origin: wp.vec3,
    dx: float,
    dz: float,
    # outputs
    out_y: wp.array(dtype=wp.float64),
    out_tri: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    i = rows[k]
    j = cols[k]
    t = cover[i, j]
    out_tri[k] = t
    out_y[k] = _surface_y(t, pos, tris, eye_shift, rel_origin, dx, dz, i, j)


@wp.func
def _displace_sample(hv: wp.float32, a_in: wp.float64, b: wp.float64, use_sample: int, p: wp.vec2d,
                     depth: wp.array2d(dtype=wp.float32), rel_origin: wp.vec3, mvp: wp.mat44d, near: wp.float64,
                     far: wp.float64, width: int, height: int) -> wp.vec3d:
    """(error px: NaN unless VISIBLE, +inf behind the eye; state; pixel index or -1) of the sample at (x, z) = p
    with height hv, between (x, a_in, z) (or the sample itself with ``use_sample``) and (x, b, z)."""
    nan = wp.float64(wp.nan)
    if wp.isnan(hv):
        return wp.vec3d(nan, wp.float64(NO_DATA), wp.float64(-1.0))
    py = wp.float64(hv - rel_origin[1])  # float32, as grid_mesh's vertex
    s = to_window(mvp, wp.vec3d(p[0], py, p[1]), width, height)
    if not (s[3] > wp.float64(0.0) and s[2] >= -s[3] and s[2] <= s[3] and s[0] >= wp.float64(0.0)
            and s[1] >= wp.float64(0.0) and s[0] < wp.float64(width) and s[1] < wp.float64(height)):
        return wp.vec3d(nan, wp.float64(OUTSIDE), wp.float64(-1.0))
    col = wp.min(int(wp.floor(s[0])), width - 1)
    row = height - 1 - wp.min(int(wp.floor(s[1])), height - 1)
    d = depth[row, col]
    if d < wp.float32(1.0):  # background: nothing in front of the sample
        dref = _view_depth(d, near, far)
        # the tolerance is >= 0: a sample no deeper than the buffer passes without it (same result)
        if s[3] > dref and s[3] > dref + _depth_tolerance(depth, row, col, dref, near, far):
            return wp.vec3d(nan, wp.float64(HIDDEN), wp.float64(-1.0))
    pix = wp.float64(row * width + col)
    a = py
    if use_sample == 0:
        a = a_in
    if wp.isnan(a) or wp.isnan(b):
        return wp.vec3d(nan, wp.float64(MISSING), pix)
    pa = to_window(mvp, wp.vec3d(p[0], a, p[1]), width, height)
    pb = to_window(mvp, wp.vec3d(p[0], b, p[1]), width, height)
    if pa[3] > wp.float64(0.0) and pb[3] > wp.float64(0.0):
        ex = pa[0] - pb[0]
        ey = pa[1] - pb[1]
        return wp.vec3d(wp.sqrt(ex * ex + ey * ey), wp.float64(VISIBLE), pix)
    return wp.vec3d(wp.float64(wp.inf), wp.float64(VISIBLE), pix)  # a surface point behind the eye: unbounded


@wp.kernel(enable_backward=False)
def _displacement_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    ya: wp.array2d(dtype=wp.float64),
    yb: wp.array2d(dtype=wp.float64),
    use_sample: int,
    depth: wp.array2d(dtype=wp.float32),
    rel_origin: wp.vec3,
    dx: float,
    dz: float,
    mvp: wp.mat44d,
    near: wp.float64,
    far: wp.float64,
    width: int,
    height: int,
    # outputs
    out_err: wp.array2d(dtype=wp.float64),
    out_state: wp.array2d(dtype=wp.int32),
    out_pix: wp.array2d(dtype=wp.int32),
):
    i, j = wp.tid()
    i += offset
    r = _displace_sample(h[i, j], ya[i, j], yb[i, j], use_sample, _sample_xz(rel_origin, dx, dz, i, j), depth,
                         rel_origin, mvp, near, far, width, height)
    out_err[i, j] = r[0]
    out_state[i, j] = int(r[1])
    out_pix[i, j] = int(r[2])


@wp.kernel(enable_backward=False)
def _displacement_list_kernel(
    offset: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    h: wp.array2d(dtype=wp.float32),
    ya: wp.array(dtype=wp.float64),
    yb: wp.array(dtype=wp.float64),
    use_sample: int,
    depth: wp.array2d(dtype=wp.float32),
    rel_origin: wp.vec3,
    dx: float,
    dz: float,
    mvp: wp.mat44d,
    near: wp.float64,
    far: wp.float64,
    width: int,
    height: int,
    # outputs
    out_err: wp.array(dtype=wp.float64),
    out_state: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    i = rows[k]
    j = cols[k]
    r = _displace_sample(h[i, j], ya[k], yb[k], use_sample, _sample_xz(rel_origin, dx, dz, i, j), depth,
                         rel_origin, mvp, near, far, width, height)
    out_err[k] = r[0]
    out_state[k] = int(r[1])


# ------------------------------------------------------------------------------------------------
# host drivers
# ------------------------------------------------------------------------------------------------


def surface_at_samples(positions: np.ndarray, triangles: np.ndarray, offset: tuple[float, float, float],
                       rel_origin: tuple[float, float, float], spacing: tuple[float, float], shape: tuple[int, int],
                       device: str = "cpu") -> np.ndarray:
    """The drawn surface's camera-relative height above every heightmap sample.

    Args:
        positions: (n, 3) float32 vertex positions relative to the mesh's eye; triangles: (m, 3) int32.
        offset: mesh eye minus the measuring eye (float64; zero when both are the frame camera's).
        rel_origin: (x0 - eye_x, eye_y, z0 - eye_z) of the measuring eye, as grid_mesh takes it.
        spacing: (dx, dz) metres; shape: (rows, cols) of the heightmap.

    Returns:
        (rows, cols) float64 height relative to the measuring eye, NaN where no triangle lies above or
        below the sample. Two launches (over triangles, then over samples).
    """
    rows, cols = int(shape[0]), int(shape[1])
    cover, args = _cover(positions, triangles, offset, rel_origin, spacing, shape, device)
    out = pooled_array((rows, cols), wp.float64, device, keep=2)  # popping holds two surfaces at once
    launch(_surface_kernel, dim=(rows, cols), inputs=[cover, *args], outputs=[out], device=device)
    return out.numpy()


def surface_at(positions: np.ndarray, triangles: np.ndarray, offset: tuple[float, float, float],
               rel_origin: tuple[float, float, float], spacing: tuple[float, float], shape: tuple[int, int],
               rows: np.ndarray, cols: np.ndarray, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """:func:`surface_at_samples` at the listed samples only (the same values, bit for bit), and the triangle
    that holds each.

    Args:
        positions, triangles, offset, rel_origin, spacing, shape: as :func:`surface_at_samples`.
        rows, cols: (n,) int32 the samples (row i along +z, column j along +x).

    Returns:
        (height (n,) float64 relative to the measuring eye, NaN where no triangle holds the sample; the
        lowest-numbered triangle holding it (n,) int32, :data:`NONE` where none does).
    """
    r = np.ascontiguousarray(rows, np.int32).reshape(-1)
    c = np.ascontiguousarray(cols, np.int32).reshape(-1)
    n = len(r)
    y, tri = np.empty(n, np.float64), np.empty(n, np.int32)
    if n:
        cover, args = _cover(positions, triangles, offset, rel_origin, spacing, shape, device)
        y_wp, t_wp = view(y, wp.float64, device), view(tri, wp.int32, device)
        launch(_surface_list_kernel, dim=n, inputs=[view(r, wp.int32, device), view(c, wp.int32, device), cover,
                                                    *args], outputs=[y_wp, t_wp], device=device)
        if y_wp.ptr != y.ctypes.data:  # not a view (a CUDA device): copy back
            y, tri = y_wp.numpy(), t_wp.numpy()
    return y, tri


def _cover(positions: np.ndarray, triangles: np.ndarray, offset: tuple[float, float, float],
           rel_origin: tuple[float, float, float], spacing: tuple[float, float], shape: tuple[int, int],
           device: str) -> tuple[wp.array, list]:
    """The cover map (rows, cols) int32 (each sample's lowest-numbered holding triangle, NONE where none) and the
    surface kernels' other inputs (positions, triangles, offset, origin, dx, dz)."""
    rows, cols = int(shape[0]), int(shape[1])
    pos = np.ascontiguousarray(positions, np.float32).reshape(-1, 3)
    tri = np.ascontiguousarray(triangles, np.int32).reshape(-1, 3)
    pos_wp = view(pos if len(pos) else np.zeros((1, 3), np.float32), wp.vec3, device)
    tri_wp = view(tri if len(tri) else np.zeros((1, 3), np.int32), wp.int32, device)
    off = wp.vec3d(*[float(v) for v in offset])
    org = wp.vec3(*[float(v) for v in rel_origin])
    dx, dz = float(spacing[0]), float(spacing[1])
    # heightmap-sized buffers from the frame-buffer pool: an error pass per frame along a path or a fit would
    # otherwise fault ~0.5 GB of fresh memory in each time (a 4097^2 fBm; 0.6-16 ms/MB on this VM)
    cover = pooled_array((rows, cols), wp.int32, device)
    cover.fill_(NONE)
    if len(tri):
        launch(_cover_kernel, dim=len(tri), inputs=[pos_wp, tri_wp, off, org, dx, dz, rows, cols],
               outputs=[cover], device=device)
    return cover, [pos_wp, tri_wp, off, org, dx, dz]


def sample_displacement(heights: np.ndarray, ya: np.ndarray | None, yb: np.ndarray, depth: np.ndarray,
                        rel_origin: tuple[float, float, float], spacing: tuple[float, float], mvp: np.ndarray,
                        near: float, far: float, device: str = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample: visibility against ``depth`` and the pixel distance between (x, ya, z) and (x, yb, z).

    Args:
        heights: (rows, cols) float32 heightmap (NaN = no data).
        ya: (rows, cols) float64 first height relative to the eye, or None: the sample itself.
        yb: (rows, cols) float64 second height relative to the eye (NaN = no surface).
        depth: (H, W) float32 full-detail window depth of the frame, 1.0 on background, row 0 at the top.
        rel_origin: (x0 - eye_x, eye_y, z0 - eye_z); spacing: (dx, dz).
        mvp: (4, 4) float64 ``proj @ view(relative=True)``; near, far: its planes.

    Returns:
        (error (rows, cols) float64 px, NaN unless VISIBLE, +inf where a point is behind the eye;
        state (rows, cols) int32, one of VISIBLE, NO_DATA, OUTSIDE, HIDDEN, MISSING;
        pixel (rows, cols) int32 image index row * W + col of the sample, -1 unless VISIBLE or MISSING).
    """
    rows, cols = heights.shape
    hh, ww = depth.shape
    yb_wp = view(yb, wp.float64, device)  # heightmap-sized inputs: not copied on the CPU
    ya_wp = yb_wp if ya is None else view(ya, wp.float64, device)
    err = pooled_array((rows, cols), wp.float64, device)
    state = pooled_array((rows, cols), wp.int32, device)
    pix = pooled_array((rows, cols), wp.int32, device)
    launch(_displacement_kernel, dim=(rows, cols), inputs=[
        view(heights, wp.float32, device), ya_wp, yb_wp, int(ya is None), view(depth, wp.float32, device),
        wp.vec3(*[float(v) for v in rel_origin]), float(spacing[0]), float(spacing[1]),
        wp.mat44d(*np.asarray(mvp, np.float64).reshape(-1).tolist()), float(near), float(far), int(ww), int(hh)],
        outputs=[err, state, pix], device=device)
    return err.numpy(), state.numpy(), pix.numpy()


def displacement_at(heights: np.ndarray, rows: np.ndarray, cols: np.ndarray, ya: np.ndarray | None, yb: np.ndarray,
                    depth: np.ndarray, rel_origin: tuple[float, float, float], spacing: tuple[float, float],
                    mvp: np.ndarray, near: float, far: float, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_displacement` at the listed samples only (the same values, bit for bit).

    Args:
        rows, cols: (n,) int32 the samples; ya (or None: the sample itself), yb: (n,) float64 the two heights
            relative to the eye at those samples; the others as :func:`sample_displacement`.

    Returns:
        (error (n,) float64 px, state (n,) int32), as :func:`sample_displacement`'s at those samples.
    """
    r = np.ascontiguousarray(rows, np.int32).reshape(-1)
    c = np.ascontiguousarray(cols, np.int32).reshape(-1)
    n = len(r)
    err, state = np.empty(n, np.float64), np.empty(n, np.int32)
    if not n:
        return err, state
    hh, ww = depth.shape
    b = np.ascontiguousarray(yb, np.float64).reshape(-1)
    a = b if ya is None else np.ascontiguousarray(ya, np.float64).reshape(-1)
    e_wp, s_wp = view(err, wp.float64, device), view(state, wp.int32, device)
    launch(_displacement_list_kernel, dim=n, inputs=[
        view(r, wp.int32, device), view(c, wp.int32, device), view(heights, wp.float32, device),
        view(a, wp.float64, device), view(b, wp.float64, device), int(ya is None), view(depth, wp.float32, device),
        wp.vec3(*[float(v) for v in rel_origin]), float(spacing[0]), float(spacing[1]),
        wp.mat44d(*np.asarray(mvp, np.float64).reshape(-1).tolist()), float(near), float(far), int(ww), int(hh)],
        outputs=[e_wp, s_wp], device=device)
    if e_wp.ptr != err.ctypes.data:  # not a view (a CUDA device): copy back
        err, state = e_wp.numpy(), s_wp.numpy()
    return err, state
