"""Vertex normals of a heightmap, one kernel over the whole grid.

Methods (``METHODS``), all spacing-aware (dx along columns/x, dz along rows/z) and in world units;
each returns n = normalize(-dh/dx, 1, -dh/dz) for its estimate of the gradient:

* ``sobel`` (deaconu2021, "Shading"): the 3x3 Sobel derivative filters over the 8 neighbours,
  divided by 8*dx and 8*dz so that they return the exact slope of a plane. Border samples outside the
  grid take a constant height (``border="constant"``, 0 by default, as the paper says), repeat the edge
  sample (``border="clamp"``, a texture's clamp-to-edge), or are treated as missing (``border="skip"``,
  one-sided differences: exact on a plane up to the border).
* ``edge`` (curtis2004, "Normal based approximations"): the slopes of the two edges along x are
  averaged, likewise along z; the two slopes become the tangents (1, sx, 0) and (0, sz, 1) whose cross
  product, normalised, is the normal (the reading of "converted to vectors, added together" that is
  exact on a plane).
* ``triangle``: the four triangles (centre, +x, +z), (centre, +z, -x), ... of the 4-neighbourhood;
  their unit normals are averaged and normalised.
* ``quad``: the four quads of the 8-neighbourhood; each quad's normal is the normalised average of
  its two triangles split along the diagonal through the centre (equal to the quad's normal when it is
  planar); the four quad normals are averaged and normalised.

Precision: every difference is taken between two samples (or a sample and the centre, the local
reference) before any sum, so millimetre relief on an 8,848 m base survives float32 (neighbouring
samples within a factor 2 of each other subtract exactly, Sterbenz).

No data: a NaN height is a hole. A NaN neighbour is skipped and the remaining weights renormalised
(one-sided differences when a side is missing, the edge method when no triangle or quad is complete);
it never makes a normal NaN. A NaN centre gets the normal of the central differences of its
neighbours (or (0, 1, 0) when it has none). Outside the grid, edge/triangle/quad skip the missing
samples the same way. Normals are unit length and finite everywhere.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .checks import check_choice
from .parallel import MIN_ITEMS, empty, launch, view

BORDERS = {"constant": 0, "clamp": 1, "skip": 2}
METHODS = {"sobel": 0, "edge": 1, "triangle": 2, "quad": 3}

# ---------------------------------------------------------------------------------------------------
# sample access
# ---------------------------------------------------------------------------------------------------


@wp.func
def fetch(h: wp.array2d(dtype=wp.float32), i: int, j: int, border: int, c: float) -> wp.vec2:
    """(height, 1) for a usable sample, (0, 0) for a missing one (NaN, or outside with border 2)."""
    if i < 0 or j < 0 or i >= h.shape[0] or j >= h.shape[1]:
        if border == 0:
            return wp.vec2(c, 1.0)
        if border == 2:
            return wp.vec2(0.0, 0.0)
    ii = wp.clamp(i, 0, h.shape[0] - 1)
    jj = wp.clamp(j, 0, h.shape[1] - 1)
    v = h[ii, jj]
    if wp.isnan(v):
        return wp.vec2(0.0, 0.0)
    return wp.vec2(v, 1.0)


@wp.func
def _slope_1d(lo: wp.vec2, c: float, c_ok: float, hi: wp.vec2, step: float) -> float:
    """Slope along one axis from the samples below/above the centre: central difference when both
    exist, one-sided when one side and the centre exist, 0 otherwise."""
    if lo[1] > 0.0 and hi[1] > 0.0:
        return (hi[0] - lo[0]) / (2.0 * step)
    if c_ok > 0.0 and hi[1] > 0.0:
        return (hi[0] - c) / step
    if c_ok > 0.0 and lo[1] > 0.0:
        return (c - lo[0]) / step
    return 0.0


@wp.func
def _grad_normal(gx: float, gz: float) -> wp.vec3:
    return wp.normalize(wp.vec3(-gx, 1.0, -gz))


# ---------------------------------------------------------------------------------------------------
# per-vertex normal functions
# ---------------------------------------------------------------------------------------------------


@wp.func
def sobel_normal(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float, border: int,
                 c: float) -> wp.vec3:
    """Sobel normal; rows with a missing end are dropped and the 1-2-1 weights renormalised."""
    if i >= 1 and j >= 1 and i < h.shape[0] - 1 and j < h.shape[1] - 1:
        # inside the grid: the general path's operations, in its order, without its per-sample checks; a
        # NaN neighbour makes a sum NaN and falls through to the general path (the same bits either way)
        fx = float(0.0)
        fz = float(0.0)
        fx += 1.0 * (h[i - 1, j + 1] - h[i - 1, j - 1])
        fz += 1.0 * (h[i + 1, j - 1] - h[i - 1, j - 1])
        fx += 2.0 * (h[i, j + 1] - h[i, j - 1])
        fz += 2.0 * (h[i + 1, j] - h[i - 1, j])
        fx += 1.0 * (h[i + 1, j + 1] - h[i + 1, j - 1])
        fz += 1.0 * (h[i + 1, j + 1] - h[i - 1, j + 1])
        if wp.isfinite(fx) and wp.isfinite(fz):
            return _grad_normal(fx / (4.0 * 2.0 * dx), fz / (4.0 * 2.0 * dz))
    ctr = fetch(h, i, j, border, c)
    sx = float(0.0)
    wx = float(0.0)
    sz = float(0.0)
    wz = float(0.0)
    for r in range(-1, 2):
        w = 2.0 - float(wp.abs(r))
        lo = fetch(h, i + r, j - 1, border, c)
        hi = fetch(h, i + r, j + 1, border, c)
        if lo[1] > 0.0 and hi[1] > 0.0:
            sx += w * (hi[0] - lo[0])
            wx += w
        lo = fetch(h, i - 1, j + r, border, c)
        hi = fetch(h, i + 1, j + r, border, c)
        if lo[1] > 0.0 and hi[1] > 0.0:
            sz += w * (hi[0] - lo[0])
            wz += w
    gx = float(0.0)
    gz = float(0.0)
    if wx > 0.0:
        gx = sx / (wx * 2.0 * dx)
    else:
        gx = _slope_1d(fetch(h, i, j - 1, border, c), ctr[0], ctr[1], fetch(h, i, j + 1, border, c), dx)
    if wz > 0.0:
        gz = sz / (wz * 2.0 * dz)
    else:
        gz = _slope_1d(fetch(h, i - 1, j, border, c), ctr[0], ctr[1], fetch(h, i + 1, j, border, c), dz)
    return _grad_normal(gx, gz)


@wp.func
def edge_normal(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float) -> wp.vec3:
    if i >= 1 and j >= 1 and i < h.shape[0] - 1 and j < h.shape[1] - 1:  # inside: central differences, as below
        ex = (h[i, j + 1] - h[i, j - 1]) / (2.0 * dx)
        ez = (h[i + 1, j] - h[i - 1, j]) / (2.0 * dz)
        if wp.isfinite(ex) and wp.isfinite(ez) and wp.isfinite(h[i, j]):
            return _grad_normal(ex, ez)
    ctr = fetch(h, i, j, 2, 0.0)
    gx = _slope_1d(fetch(h, i, j - 1, 2, 0.0), ctr[0], ctr[1], fetch(h, i, j + 1, 2, 0.0), dx)
    gz = _slope_1d(fetch(h, i - 1, j, 2, 0.0), ctr[0], ctr[1], fetch(h, i + 1, j, 2, 0.0), dz)
    return _grad_normal(gx, gz)


@wp.func
def _tri_normal(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Unit normal of triangle (a, b, c), oriented to +y."""
    n = wp.cross(b - a, c - a)
    if n[1] < 0.0:
        n = -n
    return wp.normalize(n)


@wp.func
def triangle_normal(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float) -> wp.vec3:
    ctr = fetch(h, i, j, 2, 0.0)
    if ctr[1] == 0.0:
        return edge_normal(h, i, j, dx, dz)
    acc = wp.vec3(0.0)
    cnt = int(0)
    o = wp.vec3(0.0)
    for q in range(4):
        sx = 1
        sz = 1
        if q == 1 or q == 2:
            sx = -1
        if q >= 2:
            sz = -1
        a = fetch(h, i, j + sx, 2, 0.0)
        b = fetch(h, i + sz, j, 2, 0.0)
        if a[1] > 0.0 and b[1] > 0.0:
            pa = wp.vec3(float(sx) * dx, a[0] - ctr[0], 0.0)
            pb = wp.vec3(0.0, b[0] - ctr[0], float(sz) * dz)
            acc += _tri_normal(o, pa, pb)
            cnt += 1
    if cnt == 0:
        return edge_normal(h, i, j, dx, dz)
    return wp.normalize(acc)


@wp.func
def quad_normal(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float) -> wp.vec3:
    ctr = fetch(h, i, j, 2, 0.0)
    if ctr[1] == 0.0:
        return edge_normal(h, i, j, dx, dz)
    acc = wp.vec3(0.0)
    cnt = int(0)
    o = wp.vec3(0.0)
    for q in range(4):
        sx = 1
        sz = 1
        if q == 1 or q == 2:
            sx = -1
        if q >= 2:
            sz = -1
        a = fetch(h, i, j + sx, 2, 0.0)
        b = fetch(h, i + sz, j, 2, 0.0)
        d = fetch(h, i + sz, j + sx, 2, 0.0)
        if a[1] > 0.0 and b[1] > 0.0 and d[1] > 0.0:
            pa = wp.vec3(float(sx) * dx, a[0] - ctr[0], 0.0)
            pb = wp.vec3(0.0, b[0] - ctr[0], float(sz) * dz)
            pd = wp.vec3(float(sx) * dx, d[0] - ctr[0], float(sz) * dz)
            acc += wp.normalize(_tri_normal(o, pa, pd) + _tri_normal(o, pd, pb))
            cnt += 1
    if cnt == 0:
        return triangle_normal(h, i, j, dx, dz)
    return wp.normalize(acc)


@wp.func
def vertex_normal(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float, method: int,
                  border: int, c: float) -> wp.vec3:
    if method == 0:
        return sobel_normal(h, i, j, dx, dz, border, c)
    if method == 1:
        return edge_normal(h, i, j, dx, dz)
    if method == 2:
        return triangle_normal(h, i, j, dx, dz)
    return quad_normal(h, i, j, dx, dz)


# ---------------------------------------------------------------------------------------------------
# interior rows: one native loop per row
# ---------------------------------------------------------------------------------------------------
#
# On the CPU a row whose stencils lie inside the grid and read no NaN takes a plain C++ loop over
# contiguous memory instead of the per-sample functions above: clang vectorises it (8 samples per
# instruction), which it never does with Warp's own loops (runtime byte strides, vec3 returns). The loop
# does the general path's float operations in its order, one operation per statement where Warp's
# generated code has one (so no multiply-add is fused that Warp's is not), with wp::neg's 0 - x and the
# wp:: functions Warp calls: its outputs are the general path's bits (tests/surface/test_row_kernels.py
# compares the two). A row with a NaN in its window, the border ring and a non-contiguous array take
# the general path; so does CUDA (one sample per thread, as before): every native body starts with
# CPU_ONLY and ends with END_CPU_ONLY.
CPU_ONLY = """
#if defined(__CUDA_ARCH__)
    return 0;
#else
"""
END_CPU_ONLY = """
#endif
"""

# The window rows i-R..i+R, columns j0-R..j1+R-1 have no NaN (p: contiguous (H, W) floats, i in range).
NAN_FREE = """
    int bad_ = 0;
    for (int r_ = i - R_; r_ <= i + R_; ++r_) {
        const float* q_ = p + (int64_t)r_ * W;
        for (int c_ = j0 - R_; c_ < j1 + R_; ++c_)
            bad_ |= (q_[c_] != q_[c_]);
    }
    if (bad_) return 0;
"""

# o[3k..3k+2] = _grad_normal(GX, GZ): wp::normalize(vec3(wp::neg(GX), 1, wp::neg(GZ))), as vec.h has it
GRAD_NORMAL = """
        {
            const float a0 = 0.0f - (GX);
            const float a1 = 1.0f;
            const float a2 = 0.0f - (GZ);
            const float l = wp::sqrt(a0 * a0 + a1 * a1 + a2 * a2);
            float r0 = 0.0f, r1 = 0.0f, r2 = 0.0f;
            if (l > kEps) { r0 = a0 / l; r1 = a1 / l; r2 = a2 / l; }
            o[3 * k] = r0;
            o[3 * k + 1] = r1;
            o[3 * k + 2] = r2;
        }
"""


@wp.func_native(CPU_ONLY + """
    const float* p = (const float*)h.data;
    float* o = (float*)out.data;
    const int W = (int)h.shape[1];
    const int R_ = 1;
""" + NAN_FREE + """
    const float sx = 2.0f * dx;
    const float sz = 2.0f * dz;
    const float* u = p + (int64_t)(i - 1) * W;
    const float* c = p + (int64_t)i * W;
    const float* d = p + (int64_t)(i + 1) * W;
    for (int j = j0; j < j1; ++j) {
        const int64_t k = (int64_t)i * W + j;
        const float ex = (c[j + 1] - c[j - 1]) / sx;
        const float ez = (d[j] - u[j]) / sz;
""" + GRAD_NORMAL.replace("GX", "ex").replace("GZ", "ez") + """
    }
    return 1;
""" + END_CPU_ONLY)
def _edge_row(h: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.vec3), i: int, j0: int, j1: int, dx: float,
              dz: float) -> int:
    """Edge normals of row i, columns [j0, j1) (all inside, 1 from the border); 0 (nothing written) when
    the window has a NaN."""
    ...


@wp.func_native(CPU_ONLY + """
    const float* p = (const float*)h.data;
    float* o = (float*)out.data;
    const int W = (int)h.shape[1];
    const int R_ = 1;
""" + NAN_FREE + """
    const float sx = 8.0f * dx;
    const float sz = 8.0f * dz;
    const float* u = p + (int64_t)(i - 1) * W;
    const float* c = p + (int64_t)i * W;
    const float* d = p + (int64_t)(i + 1) * W;
    for (int j = j0; j < j1; ++j) {
        const int64_t k = (int64_t)i * W + j;
        float fx = 0.0f;
        float fz = 0.0f;
        float t;
        t = 1.0f * (u[j + 1] - u[j - 1]); fx = fx + t;
        t = 1.0f * (d[j - 1] - u[j - 1]); fz = fz + t;
        t = 2.0f * (c[j + 1] - c[j - 1]); fx = fx + t;
        t = 2.0f * (d[j] - u[j]);         fz = fz + t;
        t = 1.0f * (d[j + 1] - d[j - 1]); fx = fx + t;
        t = 1.0f * (d[j + 1] - u[j + 1]); fz = fz + t;
        const float gx = fx / sx;
        const float gz = fz / sz;
""" + GRAD_NORMAL.replace("GX", "gx").replace("GZ", "gz") + """
    }
    return 1;
""" + END_CPU_ONLY)
def _sobel_row(h: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.vec3), i: int, j0: int, j1: int, dx: float,
               dz: float) -> int:
    """Sobel normals of row i, columns [j0, j1) (all inside, 1 from the border); 0 (nothing written) when
    the window has a NaN."""
    ...


@wp.func
def row_block(h: wp.array2d(dtype=wp.float32), i: int, b: int, width: int) -> wp.vec2i:
    """Columns [j0, j1) of block b (``width`` columns each) of row i."""
    j0 = b * width
    return wp.vec2i(j0, wp.min(j0 + width, h.shape[1]))


@wp.func
def interior_span(h: wp.array2d(dtype=wp.float32), i: int, cols: wp.vec2i, r: int, fast: int) -> wp.vec2i:
    """The part of ``cols`` of row i whose stencil of radius r lies inside the grid (empty: (j0, j0))."""
    a = wp.max(cols[0], r)
    e = wp.min(cols[1], h.shape[1] - r)
    if fast == 0 or i < r or i >= h.shape[0] - r or a >= e:
        return wp.vec2i(cols[0], cols[0])
    return wp.vec2i(a, e)


# ---------------------------------------------------------------------------------------------------
# kernels
# ---------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _sobel_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    border: int,
    c: float,
    width: int,
    fast: int,
    # outputs
    out_n: wp.array2d(dtype=wp.vec3),
):
    i, b = wp.tid()
    i += offset
    cols = row_block(h, i, b, width)
    s = interior_span(h, i, cols, 1, fast)
    if s[0] < s[1]:
        if _sobel_row(h, out_n, i, s[0], s[1], dx, dz) == 0:
            s = wp.vec2i(s[0], s[0])
    for j in range(cols[0], s[0]):
        out_n[i, j] = sobel_normal(h, i, j, dx, dz, border, c)
    for j in range(s[1], cols[1]):
        out_n[i, j] = sobel_normal(h, i, j, dx, dz, border, c)


@wp.kernel(enable_backward=False)
def _edge_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    width: int,
    fast: int,
    # outputs
    out_n: wp.array2d(dtype=wp.vec3),
):
    i, b = wp.tid()
    i += offset
    cols = row_block(h, i, b, width)
    s = interior_span(h, i, cols, 1, fast)
    if s[0] < s[1]:
        if _edge_row(h, out_n, i, s[0], s[1], dx, dz) == 0:
            s = wp.vec2i(s[0], s[0])
    for j in range(cols[0], s[0]):
        out_n[i, j] = edge_normal(h, i, j, dx, dz)
    for j in range(s[1], cols[1]):
        out_n[i, j] = edge_normal(h, i, j, dx, dz)


@wp.kernel(enable_backward=False)
def _normals_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    method: int,
    border: int,
    c: float,
    # outputs
    out_n: wp.array2d(dtype=wp.vec3),
):
    i, j = wp.tid()
    i += offset
    out_n[i, j] = vertex_normal(h, i, j, dx, dz, method, border, c)


@wp.kernel(enable_backward=False)
def _encode_kernel(
    offset: int,
    n: wp.array2d(dtype=wp.vec3),
    swap_yz: int,
    # outputs
    out_rgb: wp.array3d(dtype=wp.uint8),
):
    i, j = wp.tid()
    i += offset
    v = n[i, j]
    if swap_yz != 0:
        v = wp.vec3(v[0], v[2], v[1])
    for k in range(3):
        out_rgb[i, j, k] = wp.uint8(wp.clamp(wp.floor((v[k] * 0.5 + 0.5) * 255.0 + 0.5), 0.0, 255.0))


# ---------------------------------------------------------------------------------------------------
# host wrappers
# ---------------------------------------------------------------------------------------------------


def device_heights(heights: np.ndarray, device: str) -> wp.array:
    a = np.asarray(heights)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"heights: expected a non-empty (H, W) array, got shape {a.shape}")
    with np.errstate(over="ignore"):
        f = np.ascontiguousarray(a, dtype=np.float32)
    if np.isinf(f).any():
        raise ValueError(f"heights: expected finite heights or NaN (no data), got {int(np.isinf(f).sum())} "
                         "infinite values (after conversion to float32)")
    return view(f, wp.float32, device)  # the CPU reads the heights in place


def check_spacing(dx: float, dz: float) -> tuple[float, float]:
    out = []
    for name, v in (("dx", dx), ("dz", dz)):
        f = float(v)
        if not (np.isfinite(f) and f > 0.0):
            raise ValueError(f"{name}: expected a positive finite spacing, got {v!r}")
        out.append(f)
    return out[0], out[1]


def row_launch(kernel: wp.Kernel, h: wp.array, inputs: list, out: wp.array) -> None:
    """Launch a row kernel (``offset, h, *inputs, width, fast, out``) over ``h``: a whole row per task on
    the CPU, one sample per thread on CUDA; ``fast`` when the native row loops may read ``h`` and write
    ``out`` as contiguous (H, W) arrays."""
    rows, cols = h.shape
    width = cols if h.device.is_cpu else 1
    fast = int(h.is_contiguous and out.is_contiguous)
    launch(kernel, dim=(rows, -(-cols // width)), inputs=[h, *inputs, width, fast], outputs=[out],
           device=h.device, min_items=max(1, -(-MIN_ITEMS // cols)))


def sobel_normals(heights: np.ndarray, dx: float, dz: float, border: str = "clamp", constant: float = 0.0,
                  device: str = "cpu") -> np.ndarray:
    """(H, W, 3) float32 unit normals of ``heights`` by the Sobel filter.

    Args:
        heights: (H, W) float heights (metres); NaN = no data.
        dx, dz: spacing along x (columns) and z (rows).
        border: ``"constant"`` (outside samples = ``constant``), ``"clamp"`` or ``"skip"``.
        constant: the outside height for ``border="constant"``.
    """
    check_choice("border", border, BORDERS)
    dx, dz = check_spacing(dx, dz)
    h = device_heights(heights, device)
    out = empty(h.shape, wp.vec3, device)
    row_launch(_sobel_kernel, h, [dx, dz, BORDERS[border], float(constant)], out)
    return out.numpy().reshape(h.shape[0], h.shape[1], 3)


def vertex_normals_device(h: wp.array, dx: float, dz: float, method: str = "quad", border: str = "constant",
                          constant: float = 0.0) -> wp.array:
    """Device version of :func:`vertex_normals`: (H, W) wp.vec3 array on ``h.device``."""
    out = empty(h.shape, wp.vec3, h.device)
    if method == "sobel":
        row_launch(_sobel_kernel, h, [dx, dz, BORDERS[border], float(constant)], out)
    elif method == "edge":
        row_launch(_edge_kernel, h, [dx, dz], out)
    else:
        launch(_normals_kernel, dim=h.shape,
               inputs=[h, dx, dz, METHODS[method], BORDERS[border], float(constant)], outputs=[out],
               device=h.device)
    return out


def vertex_normals(heights: np.ndarray, dx: float, dz: float, method: str = "quad", border: str = "constant",
                   constant: float = 0.0, device: str = "cpu") -> np.ndarray:
    """(H, W, 3) float32 unit vertex normals by ``method`` (see the module docstring).

    Args:
        heights: (H, W) float heights (metres); NaN = no data.
        dx, dz: spacing along x (columns) and z (rows), > 0.
        method: one of ``METHODS``.
        border, constant: outside samples for ``sobel`` (the other methods always skip them).
    """
    check_choice("method", method, METHODS)
    check_choice("border", border, BORDERS)
    dx, dz = check_spacing(dx, dz)
    h = device_heights(heights, device)
    out = vertex_normals_device(h, dx, dz, method, border, constant)
    return out.numpy().reshape(h.shape[0], h.shape[1], 3)


def encode_normal_map(normals: np.ndarray, layout: str = "xzy", device: str = "cpu") -> np.ndarray:
    """(H, W, 3) uint8 normal-map image: channel = round((component * 0.5 + 0.5) * 255).

    ``layout="xzy"`` (default, deaconu2021 figure 8 style): R = n.x (east), G = n.z (along the rows),
    B = n.y (up), so flat ground is (128, 128, 255), the familiar blue of a normal map.
    ``layout="xyz"`` stores the components in their own order.
    """
    n = np.asarray(normals, dtype=np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals: expected an (H, W, 3) array, got shape {n.shape}")
    if layout not in ("xzy", "xyz"):
        raise ValueError(f"layout: expected 'xzy' or 'xyz', got {layout!r}")
    nd = wp.array(np.ascontiguousarray(n), dtype=wp.vec3, device=device)
    out = wp.empty((n.shape[0], n.shape[1], 3), dtype=wp.uint8, device=device)
    launch(_encode_kernel, dim=n.shape[:2], inputs=[nd, int(layout == "xzy")], outputs=[out], device=device)
    return out.numpy()


def decode_normal_map(rgb: np.ndarray, layout: str = "xzy") -> np.ndarray:
    """Inverse of :func:`encode_normal_map`: (H, W, 3) float32 unit normals (quantised to 1/255)."""
    v = np.asarray(rgb, dtype=np.float32) / 255.0 * 2.0 - 1.0
    if layout == "xzy":
        v = v[..., [0, 2, 1]]
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)
