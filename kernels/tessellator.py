"""The fixed-function quad tessellator and the domain shader, as Warp kernels over a whole frame.

The rules (level clamping and rounding per spacing, culling, 16.16 fixed-point point placement,
ring-by-ring stitching, winding) are those of the Direct3D 11 reference tessellator, stated with
their specification sections in :mod:`terrainwarp.rendering.reference_tessellator` (the pure-Python
reference these kernels are tested against, itself tested against Mesa's llvmpipe).
This file ports them to ``@wp.func``.

One frame, one launch per stage, no loop over patches on the host:

1. ``_count_kernel`` (one thread per patch): points and triangles of each patch.
2. ``wp.utils.array_scan`` of both counts (exclusive; entry P is the total).
3. ``_emit_kernel`` (one thread per patch): the 16.16 domain coordinates and patch id of each point,
   and the triangles (global indices, counter-clockwise in (u, v)), in the reference's order.
4. ``_displace_kernel`` (one thread per point, the domain shader): the point's exact position on a
   lattice of 2^-16 heightmap cells, its height by bilinear or bicubic filtering of the heightmap
   (:func:`terrainwarp.kernels.sampling.sample_height`), and its camera-relative float32 position.

Crack-free displacement: every patch's extent is given to the kernel as integer lattice coordinates
(2^-16 heightmap cells, rounded once on the host from float64). A point's lattice coordinate along
each axis is ``a + floor((b - a) * t / 2^16)`` for ``t <= 1/2`` and ``b - floor((b - a) * (2^16 - t)
/ 2^16)`` beyond, with ``[a, b]`` the patch's range and ``t`` its 16.16 domain coordinate, so it is
exact whenever the patch spans a whole number of cells, and mirror-symmetric. Everything after
that (grid coordinate, height, position) is a function of the lattice point alone, so two patches
that place a vertex at the same lattice point produce it bit-identically: equal factors on a shared
edge of equal length always do; a coarse edge with factor 2L beside two fine edges with factor L
(the LOD issue's doubled edges) does when L is a power of two (the fixed-point reciprocals 2^16/L
are then exact; otherwise the GPU itself places the points up to 2^-16 of the edge apart).

Camera-relative float32: the host splits the eye into an integer lattice part and a sub-lattice
remainder; the kernel converts the exact int64 difference ``lattice - eye`` to float32 (error
2^-24 relative to the distance from the eye) and scales it by the cell size, so terrains far from
the world origin, or large ones, keep their precision near the camera.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np
import warp as wp

from .checks import check_bool, check_choice
from .counters import patch_draw_counters
from .device import device_named
from .parallel import empty, launch, scan, view
from .pool import pooled_arrays, take
from .sampling import sample_height

__all__ = ["Tessellation", "DeviceTessellation", "tessellate_domains", "tessellate_patches",
           "tessellate_patches_device", "SPACING_CODES", "FILTER_CODES", "tessellate_device", "count_patches",
           "FrameLattice", "frame_lattice"]

# the spacing names (OpenGL: equal_spacing, fractional_even_spacing, fractional_odd_spacing) and the codes the
# kernels take: the one list of spacing names (terrainwarp.scene.SPACINGS and the reference tessellator derive theirs)
SPACING_CODES = {"equal": 0, "fractional_even": 1, "fractional_odd": 2}
FILTER_CODES = {"bilinear": 0, "bicubic": 1}
FILTER_TEXELS = {"bilinear": 4, "bicubic": 16}  # heightmap texels a domain point fetches
FXP_ONE = 65536
FXP_HALF = 32768

vec6i = wp.types.vector(length=6, dtype=wp.int32)
vec6f = wp.types.vector(length=6, dtype=wp.float32)
vec4l = wp.types.vector(length=4, dtype=wp.int64)

# ------------------------------------------------------------------------------------------------
# levels (rules 2-6 of terrainwarp.rendering.reference_tessellator)
# ------------------------------------------------------------------------------------------------


@wp.func
def _fmax(a: float, b: float) -> float:
    """IEEE fmax: a NaN operand is dropped."""
    if wp.isnan(b):
        return a
    if wp.isnan(a):
        return b
    if a > b:
        return a
    return b


@wp.func
def _fmin(a: float, b: float) -> float:
    if wp.isnan(b):
        return a
    if wp.isnan(a):
        return b
    if a < b:
        return a
    return b


@wp.func
def _process(o: wp.vec4, inner: wp.vec2, spacing: int):
    """-> (status: 0 culled, 1 minimal unit quad, 2 regular; six 16.16 levels; six parities (1 odd))."""
    fx = vec6i()
    odd = vec6i()
    culled = int(0)
    for e in range(4):
        if not (o[e] > 0.0):
            culled = 1
    if culled == 1:
        return 0, fx, odd
    lo = float(1.0)
    hi = float(64.0)
    if spacing == 1:
        lo = 2.0
    if spacing == 2:
        hi = 63.0
    lv = vec6f()
    for e in range(4):
        x = _fmin(hi, _fmax(lo, o[e]))
        if spacing == 0:
            x = wp.ceil(x)
        lv[e] = x
    lo_in = lo
    if spacing == 2:
        big = int(0)
        for e in range(4):
            if lv[e] > 1.0000076293945312:  # 1 + 2^-17
                big = 1
        for a in range(2):
            if inner[a] > 1.0000076293945312:
                big = 1
        if big == 1:
            lo_in = lo + 1.52587890625e-05  # + 2^-16: force a picture frame
    for a in range(2):
        x = _fmin(hi, _fmax(lo_in, inner[a]))
        if spacing == 0:
            x = wp.ceil(x)
        lv[4 + a] = x
    all_one = int(1)
    for s in range(6):
        if spacing == 0:
            odd[s] = int(lv[s]) % 2
            if s >= 4 and lv[s] == 1.0:
                odd[s] = 0
        elif spacing == 2:
            odd[s] = 1
        fx[s] = int(wp.rint(lv[s] * 65536.0))  # 16.16, nearest, ties to even
        if fx[s] != 65536:
            all_one = 0
    if all_one == 1 and spacing != 1:
        return 1, fx, odd
    return 2, fx, odd


# ------------------------------------------------------------------------------------------------
# one edge (rule 7)
# ------------------------------------------------------------------------------------------------


@wp.func
def _fxp_ceil(x: int) -> int:
    if (x & 0xFFFF) != 0:
        return (x & 0x7FFF0000) + 65536
    return x


@wp.func
def _num_points(fx: int, odd: int) -> int:
    if odd == 1:
        return (_fxp_ceil(32768 + (fx + 1) / 2) * 2) >> 16
    return ((_fxp_ceil((fx + 1) / 2) * 2) >> 16) + 1


@wp.func
def _remove_msb(v: int) -> int:
    if v <= 0:
        return 0
    b = int(1)
    while b * 2 <= v:
        b = b * 2
    return v - b


@wp.func
def _reciprocal(n: int) -> int:
    """round(2^16 / n)."""
    return (131072 + n) / (2 * n)


@wp.func
def _half_points(fx: int, odd: int) -> int:
    half = (fx + 1) / 2
    if odd == 1 or half == 32768:
        half += 32768
    return _fxp_ceil(half) >> 16


@wp.func
def _edge(fx: int, odd: int) -> vec6i:
    """The constants of an edge of level ``fx`` that place its points (:func:`_place_on`): points in
    the half, split point, fraction, the two 16.16 reciprocals, parity. Worked out once per edge."""
    half = (fx + 1) / 2
    if odd == 1 or half == 32768:
        half += 32768
    fl = half & 0x7FFF0000
    ce = _fxp_ceil(half)
    frac = half - fl
    nhalf = ce >> 16
    split = int(0)
    if ce == fl:
        split = nhalf + 1
    elif odd == 1:
        if fl == 65536:
            split = 0
        else:
            split = (_remove_msb((fl >> 16) - 1) << 1) + 1
    else:
        split = (_remove_msb(fl >> 16) << 1) + 1
    nfs = (fl * 2) >> 16
    ncs = (ce * 2) >> 16
    if odd == 1:
        nfs -= 1
        ncs -= 1
    rf = int(0)
    if nfs > 0:  # else no point reads it
        rf = _reciprocal(nfs)
    rc = int(0)
    if ncs > 0:
        rc = _reciprocal(ncs)
    return vec6i(nhalf, split, frac, rf, rc, odd)


@wp.func
def _place_on(c: vec6i, point_in: int) -> int:
    """16.16 position of partition point ``point_in`` on the edge with constants ``c`` (:func:`_edge`)."""
    nhalf = c[0]
    point = point_in
    flip = int(0)
    if point >= nhalf:
        point = 2 * nhalf - point - c[5]
        flip = 1
    if point == nhalf:
        return 32768
    idx_f = point
    if point > c[1]:
        idx_f = point - 1
    frac = c[2]
    lf = wp.int64(idx_f * c[3])
    lc = wp.int64(point * c[4])
    loc = int((lf * wp.int64(65536 - frac) + lc * wp.int64(frac) + wp.int64(32768)) >> wp.int64(16))
    if flip == 1:
        return 65536 - loc
    return loc


@wp.func
def _place(fx: int, odd: int, point_in: int) -> int:
    """16.16 position of partition point ``point_in`` on an edge of level ``fx``."""
    return _place_on(_edge(fx, odd), point_in)


@wp.func
def _final_point_position(i: int) -> int:
    """The reference's ruler-function table {0, 32, 16, 8, 17, 4, 18, 9, ...}[i] for i in 1..32."""
    if i == 1:
        return 32
    j = i - 1
    k = int(0)
    while (j >> k) & 1 == 0:
        k += 1
    return (16 >> k) + (j >> (k + 1))


# ------------------------------------------------------------------------------------------------
# patch layout: g = (points on outer edges 0..3, inner partition points along u, along v)
# ------------------------------------------------------------------------------------------------


@wp.func
def _layout(fx: vec6i, odd: vec6i) -> vec6i:
    g = vec6i()
    for e in range(4):
        g[e] = _num_points(fx[e], odd[e])
    for a in range(2):
        m = 3
        if odd[4 + a] == 1:
            m = 4
        g[4 + a] = wp.max(m, _num_points(fx[4 + a], odd[4 + a]))
    return g


@wp.func
def _ring_count(g: vec6i, r: int, e: int) -> int:
    """Points (both ends included) on edge e of ring r."""
    if r == 0:
        return g[e]
    if e % 2 == 0:
        return g[5] - 2 * r
    return g[4] - 2 * r


@wp.func
def _num_triangles(g: vec6i, odd: vec6i) -> int:
    nu = g[4]
    nv = g[5]
    n_rings = wp.min((nu + 1) >> 1, (nv + 1) >> 1)
    t = int(0)
    for e in range(4):
        t += g[e] + _ring_count(g, 1, e) - 2
    for ring in range(2, n_rings):
        for e in range(4):
            t += 2 * _ring_count(g, ring, e)
    r = n_rings - 1
    if nu > nv and odd[5] == 1:
        t += 2 * (_ring_count(g, r, 1) - 1)
    elif nv >= nu and odd[4] == 1:
        t += 2 * (_ring_count(g, r, 0) - 1)
    return t


# ------------------------------------------------------------------------------------------------
# what a launch writes (W_* flags) and what the domain shader reads
# ------------------------------------------------------------------------------------------------

# the per-point outputs a launch writes besides triangles (the flags of _Out.flags)
W_DOMAIN = wp.constant(1)
W_PATCH_ID = wp.constant(2)
W_POSITION = wp.constant(4)
W_UV = wp.constant(8)
W_LEVEL = wp.constant(16)
W_SWAP = wp.constant(32)  # store triangles counter-clockwise seen from +y
W_CELLS = wp.constant(64)  # uv in grid cells (column, row), not normalised (a streamed heightmap's displacement)
OPTIONAL_FIELDS = {"uv": 8, "domain": 1, "patch_id": 2, "level": 16}  # Tessellation fields made on request


@wp.struct
class _Out:
    """One emit launch's outputs (only those in ``flags`` are written) and the domain shader's inputs."""

    flags: int
    dom: wp.array(dtype=wp.vec2i)
    pid: wp.array(dtype=wp.int32)
    tri: wp.array(dtype=wp.vec3i)
    pos: wp.array(dtype=wp.vec3)
    uv: wp.array(dtype=wp.vec2)
    lev: wp.array(dtype=wp.int32)
    box: wp.array(dtype=vec4l)
    level: wp.array(dtype=wp.int32)
    h: wp.array2d(dtype=wp.float32)
    eye_lx: wp.int64
    eye_lz: wp.int64
    eye_rem: wp.vec3
    cell: wp.vec2
    method: int


# ------------------------------------------------------------------------------------------------
# stitching (rule 9)
# ------------------------------------------------------------------------------------------------


@wp.func
def _tri(o: _Out, t: int, vb: int, a: int, b: int, c: int) -> int:
    if o.flags & W_SWAP:  # counter-clockwise seen from +y: GL's (a, b, c) stored as (a, c, b)
        o.tri[t] = wp.vec3i(vb + a, vb + c, vb + b)
    else:
        o.tri[t] = wp.vec3i(vb + a, vb + b, vb + c)
    return t + 1


@wp.func
def _affine(g: vec6i, r: int, e: int) -> wp.vec4i:
    """The patch-local indices of the points on edge e of ring r, in the reference's storage order, as
    (start, step, last, wrap): point k is ``start + step * k``, except point ``last`` (the ring's closing
    point, on edge 3 only), which is ``wrap``. Worked out once per row; :func:`_at` reads a point."""
    b = int(0)
    if r > 0:
        b = g[0] + g[1] + g[2] + g[3] - 4 + (r - 1) * (2 * g[4] + 2 * g[5] - 4 - 4 * r)
        mu = g[4] - 2 * r
        mv = g[5] - 2 * r
        if mu == 1:  # a column at u = 1/2, stored with v decreasing
            if e == 0:
                return wp.vec4i(b, 1, -1, b)
            if e == 1:
                return wp.vec4i(b + mv - 1, 0, -1, b)
            if e == 2:
                return wp.vec4i(b + mv - 1, -1, -1, b)
            return wp.vec4i(b, 0, -1, b)
        if mv == 1:  # a row at v = 1/2, stored with u increasing
            if e == 0:
                return wp.vec4i(b, 0, -1, b)
            if e == 1:
                return wp.vec4i(b, 1, -1, b)
            if e == 2:
                return wp.vec4i(b + mu - 1, 0, -1, b)
            return wp.vec4i(b + mu - 1, -1, -1, b)
    off = int(0)
    for j in range(e):
        off += _ring_count(g, r, j) - 1
    last = int(-1)
    if e == 3:
        last = _ring_count(g, r, 3) - 1
    return wp.vec4i(b + off, 1, last, b)


@wp.func
def _at(a: wp.vec4i, k: int) -> int:
    if k == a[2]:
        return a[3]
    return a[0] + a[1] * k


@wp.func
def _stitch_transition(out: _Out, t_in: int, vb: int, g: vec6i, e: int,
                       in_half_in: int, in_odd: int, out_half_in: int, out_odd: int) -> int:
    """Outer ring edge e -> first inner ring edge e, in ruler-function order (StitchTransition)."""
    t = t_in
    a0 = _affine(g, 0, e)
    a1 = _affine(g, 1, e)
    in_half = in_half_in - in_odd
    out_half = out_half_in - out_odd
    o = int(0)
    i = int(0)
    if 0 < out_half:
        t = _tri(out, t, vb, _at(a0, o), _at(a0, o + 1), _at(a1, i))
        o += 1
    for k in range(1, 33):
        f = _final_point_position(k)
        if f < in_half:
            t = _tri(out, t, vb, _at(a1, i), _at(a0, o), _at(a1, i + 1))
            i += 1
        if f < out_half:
            t = _tri(out, t, vb, _at(a0, o), _at(a0, o + 1), _at(a1, i))
            o += 1
    if in_odd != out_odd or in_odd == 1:
        if in_odd == out_odd:  # quad in the middle
            t = _tri(out, t, vb, _at(a1, i), _at(a0, o), _at(a1, i + 1))
            t = _tri(out, t, vb, _at(a1, i + 1), _at(a0, o), _at(a0, o + 1))
            i += 1
            o += 1
        elif in_odd == 0:  # triangle pointing inside
            t = _tri(out, t, vb, _at(a1, i), _at(a0, o), _at(a0, o + 1))
            o += 1
        else:  # triangle pointing outside
            t = _tri(out, t, vb, _at(a1, i), _at(a0, o), _at(a1, i + 1))
            i += 1
    for kk in range(32):
        f = _final_point_position(32 - kk)
        if f < out_half:
            t = _tri(out, t, vb, _at(a0, o), _at(a0, o + 1), _at(a1, i))
            o += 1
        if f < in_half:
            t = _tri(out, t, vb, _at(a1, i), _at(a0, o), _at(a1, i + 1))
            i += 1
    if 0 < out_half:
        t = _tri(out, t, vb, _at(a0, o), _at(a0, o + 1), _at(a1, i))
    return t


@wp.func
def _stitch_regular(out: _Out, t_in: int, vb: int, g: vec6i, trapezoid: int,
                    diagonals: int, n_in: int, ro: int, eo: int, ri: int, ei: int, rev: int) -> int:
    """A strip between two rows (StitchRegular). diagonals: 0 mirrored, 1 inside-to-outside,
    2 inside-to-outside except the middle quad. The inner row may be read reversed (rev=1)."""
    t = t_in
    ao = _affine(g, ro, eo)
    ai = _affine(g, ri, ei)
    di = int(1)
    i = int(0)
    if rev == 1:  # inner point k is row point n_in - 1 - k
        di = -1
        i = n_in - 1
    o = int(0)
    if trapezoid == 1:
        t = _tri(out, t, vb, _at(ao, o), _at(ao, o + 1), _at(ai, i))
        o += 1
    a_o = _at(ao, o)
    a_i = _at(ai, i)
    for p in range(n_in - 1):
        oi = int(0)
        if diagonals == 0 and p < n_in / 2:
            oi = 1
        if diagonals == 2 and p == n_in / 2 - 1:
            oi = 1
        b_o = _at(ao, o + 1)
        b_i = _at(ai, i + di)
        if oi == 1:
            t = _tri(out, t, vb, a_o, b_i, a_i)
            t = _tri(out, t, vb, a_o, b_o, b_i)
        else:
            t = _tri(out, t, vb, a_i, a_o, b_o)
            t = _tri(out, t, vb, a_i, b_o, b_i)
        a_o = b_o
        a_i = b_i
        i += di
        o += 1
    if trapezoid == 1:
        t = _tri(out, t, vb, a_o, _at(ao, o + 1), a_i)
    return t


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _count_kernel(
    offset: int,
    outer: wp.array(dtype=wp.vec4),
    inner: wp.array(dtype=wp.vec2),
    spacing: int,
    # outputs
    out_nv: wp.array(dtype=wp.int32),
    out_nt: wp.array(dtype=wp.int32),
):
    p = wp.tid() + offset
    status, fx, odd = _process(outer[p], inner[p], spacing)
    if status == 0:
        out_nv[p] = 0
        out_nt[p] = 0
    elif status == 1:
        out_nv[p] = 4
        out_nt[p] = 2
    else:
        g = _layout(fx, odd)
        out_nv[p] = g[0] + g[1] + g[2] + g[3] - 4 + (g[4] - 2) * (g[5] - 2)
        out_nt[p] = _num_triangles(g, odd)


@wp.func
def _lattice(a: wp.int64, b: wp.int64, s: int) -> wp.int64:
    """Lattice coordinate at 16.16 domain coordinate s of the range [a, b], mirror-symmetric."""
    if s <= 32768:
        return a + (((b - a) * wp.int64(s)) >> wp.int64(16))
    return b - (((b - a) * wp.int64(65536 - s)) >> wp.int64(16))


@wp.func
def _grid(n: wp.int64) -> float:
    """Lattice coordinate (2^-16 cells) -> grid coordinate (cells), one rounding."""
    return float(n >> wp.int64(16)) + float(n & wp.int64(65535)) * 1.52587890625e-05


@wp.func
def _displace(out: _Out, k: int, b: vec4l, u: int, v: int):
    """The domain shader: point k at 16.16 domain coordinate (u, v) of the patch with lattice range b."""
    h = out.h
    # Patches may reach past the grid (the quadtree's roots cover it with power-of-two nodes): points
    # beyond it are clamped to the border, so the terrain ends there (the triangles that collapse
    # have zero area and are culled by the rasterizer).
    nx = wp.clamp(_lattice(b[0], b[2], u), wp.int64(0), wp.int64(h.shape[1] - 1) << wp.int64(16))
    nz = wp.clamp(_lattice(b[1], b[3], v), wp.int64(0), wp.int64(h.shape[0] - 1) << wp.int64(16))
    gx = _grid(nx)
    gz = _grid(nz)
    if out.flags & W_POSITION:
        hgt = sample_height(h, gx, gz, out.method)
        px = float(nx - out.eye_lx) * out.cell[0] - out.eye_rem[0]
        pz = float(nz - out.eye_lz) * out.cell[1] - out.eye_rem[2]
        out.pos[k] = wp.vec3(px, hgt - out.eye_rem[1], pz)
    if out.flags & W_UV:
        if out.flags & W_CELLS:
            out.uv[k] = wp.vec2(gx, gz)
        else:
            out.uv[k] = wp.vec2(gx / float(wp.max(h.shape[1] - 1, 1)), gz / float(wp.max(h.shape[0] - 1, 1)))


@wp.func
def _point(out: _Out, k: int, p: int, b: vec4l, u: int, v: int) -> int:
    """Point k of patch p at 16.16 domain coordinate (u, v): its domain and patch id, and (the domain
    shader, fused so the domain never round-trips through memory) its displaced position, uv and level."""
    f = out.flags
    if f & W_DOMAIN:
        out.dom[k] = wp.vec2i(u, v)
    if f & W_PATCH_ID:
        out.pid[k] = p
    if f & W_LEVEL:
        out.lev[k] = out.level[p]
    if f & (W_POSITION | W_UV):
        _displace(out, k, b, u, v)
    return k + 1


@wp.kernel(enable_backward=False)
def _emit_kernel(
    offset: int,
    outer: wp.array(dtype=wp.vec4),
    inner: wp.array(dtype=wp.vec2),
    spacing: int,
    v_off: wp.array(dtype=wp.int32),
    t_off: wp.array(dtype=wp.int32),
    # outputs (those in out.flags)
    out: _Out,
):
    p = wp.tid() + offset
    status, fx, odd = _process(outer[p], inner[p], spacing)
    vb = v_off[p]
    t = t_off[p]
    if status == 0:
        return
    b = vec4l()
    if out.flags & (W_POSITION | W_UV):
        b = out.box[p]
    if status == 1:
        k = _point(out, vb, p, b, 0, 0)
        k = _point(out, k, p, b, 65536, 0)
        k = _point(out, k, p, b, 65536, 65536)
        k = _point(out, k, p, b, 0, 65536)
        t = _tri(out, t, vb, 0, 1, 3)
        t = _tri(out, t, vb, 1, 2, 3)
        return
    g = _layout(fx, odd)
    nu = g[4]
    nv = g[5]
    k = vb
    # outer ring: down u=0, along v=0, up u=1, back along v=1
    for e in range(4):
        end = g[e] - 1
        ce = _edge(fx[e], odd[e])
        for q0 in range(end):
            q = end - q0
            if e == 1 or e == 2:
                q = q0
            s = _place_on(ce, q)
            if e == 0:
                k = _point(out, k, p, b, 0, s)
            elif e == 1:
                k = _point(out, k, p, b, s, 0)
            elif e == 2:
                k = _point(out, k, p, b, 65536, s)
            else:
                k = _point(out, k, p, b, s, 65536)
    # inner rings, spiralling inwards
    n_rings = wp.min(nu, nv) >> 1
    for ring in range(1, n_rings):
        for e in range(4):
            along = (e + 1) & 1
            perp = e & 1
            end_along = g[4 + along] - 1 - ring
            perp_point = ring
            if e >= 2:
                perp_point = g[4 + perp] - 1 - ring
            tp = _place(fx[4 + perp], odd[4 + perp], perp_point)
            ca = _edge(fx[4 + along], odd[4 + along])
            for pp in range(ring, end_along):
                q = end_along - (pp - ring)
                if e == 1 or e == 2:
                    q = pp
                s = _place_on(ca, q)
                if along == 1:
                    k = _point(out, k, p, b, tp, s)
                else:
                    k = _point(out, k, p, b, s, tp)
    # degenerate centre row / column of an even inner partition
    if nu > nv and odd[5] == 0:
        cu = _edge(fx[4], odd[4])
        for pp in range(n_rings, nu - n_rings):
            k = _point(out, k, p, b, _place_on(cu, pp), 32768)
    elif nv >= nu and odd[4] == 0:
        cv = _edge(fx[5], odd[5])
        for pp in range(n_rings, nv - n_rings):
            k = _point(out, k, p, b, 32768, _place_on(cv, nv - 1 - pp))
    # connectivity, ring by ring, edge by edge
    n_rings_c = wp.min((nu + 1) >> 1, (nv + 1) >> 1)
    for ring in range(1, n_rings_c):
        for e in range(4):
            axis = (e + 1) & 1
            if ring == 1:
                t = _stitch_transition(out, t, vb, g, e, _half_points(fx[4 + axis], odd[4 + axis]),
                                       odd[4 + axis], _half_points(fx[e], odd[e]), odd[e])
            else:
                t = _stitch_regular(out, t, vb, g, 1, 0, _ring_count(g, ring, e), ring - 1, e, ring, e, 0)
    r = n_rings_c - 1
    if nu > nv and odd[5] == 1:
        t = _stitch_regular(out, t, vb, g, 0, 1, _ring_count(g, r, 1), r, 1, r, 3, 1)
    elif nv >= nu and odd[4] == 1:
        diag = int(1)
        if odd[5] == 1:
            diag = 2
        t = _stitch_regular(out, t, vb, g, 0, diag, _ring_count(g, r, 0), r, 0, r, 2, 1)


# ------------------------------------------------------------------------------------------------
# host
# ------------------------------------------------------------------------------------------------


def _levels(outer, inner) -> tuple[np.ndarray, np.ndarray]:
    o = np.asarray(outer, dtype=np.float32)
    i = np.asarray(inner, dtype=np.float32)
    if o.ndim != 2 or o.shape[1] != 4:
        raise ValueError(f"outer: expected shape (P, 4), got {o.shape}")
    if i.shape != (o.shape[0], 2):
        raise ValueError(f"inner: expected shape ({o.shape[0]}, 2), got {i.shape}")
    return np.ascontiguousarray(o), np.ascontiguousarray(i)


def _spacing_code(spacing: str) -> int:
    check_choice("spacing", spacing, SPACING_CODES)
    return SPACING_CODES[spacing]


class _Work:
    """What a frame's count, scan and emit work in besides their outputs, leased from the pool (:func:`.pool.take`)
    and given back when the call is done: the patches' levels, lattice boxes and LOD levels, their counts and
    offsets (P+1: entry P is the total), kept at a power-of-two capacity that grows with the frames (their first P
    entries are the frame's), and the emit launch's :class:`_Out`. On the CPU the host writes and scans them in
    place, through numpy views of the same memory; elsewhere they are copied in and scanned on the device."""

    def __init__(self, device: str) -> None:
        self.device, self.cpu, self.cap = device, wp.get_device(device).is_cpu, -1
        self.out = _Out()
        self.last: dict[str, object] = {}  # the values :meth:`set_frame` set last (:attr:`out` holds them)

    def set_frame(self, flags: int, h: wp.array, eye: tuple, cell: tuple[float, float], method: int) -> None:
        """Set :attr:`out`'s per-call fields: what to write, the heights (let go after the emit), the eye (lattice
        cell x, z and remainder), the cell size, the filter; a value field that holds the same value already is not
        set again (a Warp struct field set costs microseconds; the cell and filter change with the heightmap, the eye
        with the camera)."""
        out, last = self.out, self.last
        out.h = h
        if last.get("eye") != eye:
            out.eye_lx, out.eye_lz = eye[0], eye[1]
            out.eye_rem = wp.vec3(*eye[2])
            last["eye"] = eye
        if last.get("fixed") != (flags, cell, method):
            out.flags, out.cell, out.method = flags, wp.vec2(*cell), method
            last["fixed"] = (flags, cell, method)

    def fit(self, p: int) -> None:
        """Make room for ``p`` patches."""
        if p <= self.cap:
            return
        cap = max(64, 1 << max(p - 1, 0).bit_length())
        dev = self.device
        self.o, self.i, self.box, self.lvl = (empty(cap, t, dev) for t in (wp.vec4, wp.vec2, vec4l, wp.int32))
        self.nv, self.nt, self.v_off, self.t_off = (empty(cap + 1, wp.int32, dev) for _ in range(4))
        self.host = [a.numpy() for a in (self.o, self.i, self.box, self.lvl, self.nv, self.nt, self.v_off,
                                         self.t_off)] if self.cpu else None
        self.out.box, self.out.level = self.box, self.lvl
        self.cap = cap

    def put(self, k: int, a: np.ndarray) -> None:
        """Write the frame's rows of kept input ``k`` (0 levels outer, 1 inner, 2 boxes, 3 LOD levels)."""
        if self.host is not None:
            self.host[k][: len(a)] = a
        elif len(a):
            dst = (self.o, self.i, self.box, self.lvl)[k]
            wp.copy(dst, wp.array(a, dtype=dst.dtype, device="cpu"), count=len(a))

    def count_scan(self, o: np.ndarray, i: np.ndarray, code: int) -> tuple[int, int]:
        """Count the points and triangles of the P patches ``o``, ``i`` and scan them into the offsets: -> the
        totals (points n, triangles m)."""
        p = o.shape[0]
        self.fit(p)
        self.put(0, o)
        self.put(1, i)
        if p:
            launch(_count_kernel, p, [self.o, self.i, code], [self.nv, self.nt], self.device)
        if self.host is not None:  # a prefix sum of some hundred counts: numpy, in place
            for c, off in ((self.host[4], self.host[6]), (self.host[5], self.host[7])):
                off[0] = 0
                np.cumsum(c[:p], out=off[1:p + 1])
            return int(self.host[6][p]), int(self.host[7][p])
        for c, off in ((self.nv, self.v_off), (self.nt, self.t_off)):
            c[p:p + 1].zero_()
            scan(c[:p + 1], off[:p + 1], inclusive=False)
        return int(self.v_off[p:p + 1].numpy()[0]), int(self.t_off[p:p + 1].numpy()[0])

    def offsets(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """The frame's vertex and triangle offsets (P+1,) int32, as host copies."""
        if self.host is not None:
            return self.host[6][:p + 1].copy(), self.host[7][:p + 1].copy()
        return self.v_off[:p + 1].numpy().copy(), self.t_off[:p + 1].numpy().copy()

    def emit(self, p: int, code: int, made: Iterable[str]) -> None:
        """The emit launch over the frame's ``p`` patches, into :attr:`out`, whose arrays ``made`` and heights are
        then let go (the pool lends the outputs again once their holders drop them; were they let go by the next
        call instead, that call would pay for freeing whatever its caller dropped meanwhile)."""
        if p:
            launch(_emit_kernel, p, [self.o, self.i, code, self.v_off, self.t_off], [self.out], self.device,
                   min_items=64, oversplit=4)  # a patch emits tens to thousands of points; near and far ones differ
        for name in (*made, "h"):
            setattr(self.out, name, None)


_WORK_KEPT = 2  # per device: a call, and another on another thread
_OUTPUTS_KEPT = 3  # frames' outputs kept: the one being made, the one before it and one its caller holds
# the per-point outputs (flag, name in _Out, dtype)
_FIELDS = ((W_DOMAIN, "dom", wp.vec2i), (W_PATCH_ID, "pid", wp.int32), (W_POSITION, "pos", wp.vec3),
           (W_UV, "uv", wp.vec2), (W_LEVEL, "lev", wp.int32))


def _count_scan(o: np.ndarray, i: np.ndarray, code: int, device: str):
    """Count and scan: -> (points n, triangles m, levels and offsets as Warp arrays)."""
    p = o.shape[0]
    wo = wp.array(o, dtype=wp.vec4, device=device)
    wi = wp.array(i, dtype=wp.vec2, device=device)
    nv = wp.zeros(p + 1, dtype=wp.int32, device=device)
    nt = wp.zeros(p + 1, dtype=wp.int32, device=device)
    if p:
        launch(_count_kernel, p, [wo, wi, code], [nv, nt], device)
    v_off = wp.empty(p + 1, dtype=wp.int32, device=device)
    t_off = wp.empty(p + 1, dtype=wp.int32, device=device)
    scan(nv, v_off, inclusive=False)
    scan(nt, t_off, inclusive=False)
    return int(v_off.numpy()[p]), int(t_off.numpy()[p]), wo, wi, v_off, t_off


def count_patches(outer, inner, spacing: str, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """The domain points and triangles each patch tessellates to, without emitting them (one count launch): what
    :func:`tessellate_patches` would make of each patch (its ``tess_evaluation_shader_invocations`` and
    ``primitives_generated`` per patch).

    Args:
        outer: (P, 4) float32 outer levels; inner: (P, 2) float32 inner levels; spacing: as
            :func:`tessellate_patches`.

    Returns:
        (points (P,) int32, triangles (P,) int32).
    """
    o, i = _levels(outer, inner)
    code = _spacing_code(spacing)
    p = o.shape[0]
    nv = wp.zeros(max(p, 1), dtype=wp.int32, device=device)
    nt = wp.zeros(max(p, 1), dtype=wp.int32, device=device)
    if p:
        launch(_count_kernel, p, [wp.array(o, dtype=wp.vec4, device=device),
                                  wp.array(i, dtype=wp.vec2, device=device), code], [nv, nt], device)
    return nv.numpy()[:p].copy(), nt.numpy()[:p].copy()


def _emit(wo, wi, code: int, v_off, t_off, out: _Out, device: str) -> None:
    if wo.shape[0]:
        launch(_emit_kernel, wo.shape[0], [wo, wi, code, v_off, t_off], [out], device, min_items=64,
               oversplit=4)  # a patch emits tens to thousands of points; near and far ones differ in size


def tessellate_device(o: np.ndarray, i: np.ndarray, code: int, device: str):
    """Count, scan and emit for P patches (levels (P, 4) and (P, 2) float32, a ``SPACING_CODES`` code), no
    validation: -> (points n, triangles m, Warp arrays domain (16.16), patch id, triangles, vertex and
    triangle offsets). The device part of :func:`tessellate_domains` (timed alone by the benchmarks)."""
    n, m, wo, wi, v_off, t_off = _count_scan(o, i, code, device)
    out = _Out()
    out.flags = W_DOMAIN | W_PATCH_ID
    out.dom = empty(max(n, 1), wp.vec2i, device)
    out.pid = empty(max(n, 1), wp.int32, device)
    out.tri = empty(max(m, 1), wp.vec3i, device)
    _emit(wo, wi, code, v_off, t_off, out, device)
    return n, m, out.dom, out.pid, out.tri, v_off, t_off


def tessellate_domains(outer, inner, spacing: str, device: str = "cpu"):
    """Tessellate P quad patches in one launch (no displacement).

    Args:
        outer: (P, 4) float32 outer levels per patch, ``gl_TessLevelOuter`` order (u=0, v=0, u=1, v=1).
        inner: (P, 2) float32 inner levels per patch (along u, along v).
        spacing: ``"equal"``, ``"fractional_even"`` or ``"fractional_odd"``.

    Returns:
        dict with ``uv`` (n, 2) float32 domain coordinates (exact multiples of 2^-16), ``patch_id``
        (n,) int32, ``triangles`` (m, 3) int32 global indices (counter-clockwise in (u, v)),
        ``vertex_offsets`` and ``triangle_offsets`` (P+1,) int32 (patch p owns
        ``vertex_offsets[p]:vertex_offsets[p+1]``). Each patch's slice equals
        :func:`terrainwarp.rendering.reference_tessellate_patch` with indices shifted by its vertex offset.
    """
    o, i = _levels(outer, inner)
    n, m, dom, pid, tri, v_off, t_off = tessellate_device(o, i, _spacing_code(spacing), device)
    return {
        "uv": (dom.numpy()[:n].astype(np.float64) / FXP_ONE).astype(np.float32).reshape(-1, 2),
        "patch_id": pid.numpy()[:n].copy(),
        "triangles": tri.numpy()[:m].reshape(-1, 3).astype(np.int32),
        "vertex_offsets": v_off.numpy().copy(),
        "triangle_offsets": t_off.numpy().copy(),
    }


class Tessellation(NamedTuple):
    """A displaced, tessellated frame (one entry per domain point unless said otherwise).

    ``uv``, ``domain``, ``patch_id`` and ``level`` are None unless asked for (``need``).

    Attributes:
        positions: (n, 3) float32 camera-relative world positions (world minus ``eye``).
        uv: (n, 2) float32 heightmap coordinates in [0, 1] (u along x, v along z).
        domain: (n, 2) float32 tessellation domain coordinates of each point in its patch.
        patch_id: (n,) int32 index of the patch that produced the point.
        level: (n,) int32 the patch's LOD level (0 when none was given).
        triangles: (m, 3) int32, counter-clockwise seen from above (+y), like the grid mesh: the
            domain's (u, v) = (x, z) frame is left-handed seen from +y, so each GL ccw triangle
            (a, b, c) is stored as (a, c, b).
        vertex_offsets, triangle_offsets: (P+1,) int32 per-patch ranges.
        eye: the float64 world point positions are relative to.
        counters: the pipeline statistics of drawing the patches as one ``GL_PATCHES`` draw
            (:func:`terrainwarp.kernels.counters.patch_draw_counters`: control points, patches, domain points,
            triangles generated, bytes read).
    """

    positions: np.ndarray
    uv: np.ndarray | None
    domain: np.ndarray | None
    patch_id: np.ndarray | None
    level: np.ndarray | None
    triangles: np.ndarray
    vertex_offsets: np.ndarray
    triangle_offsets: np.ndarray
    eye: tuple[float, float, float]
    counters: dict[str, int] | None = None


def _get(patches, name: str, required: bool = True):
    v = patches.get(name) if isinstance(patches, dict) else getattr(patches, name, None)
    if v is None and required:
        raise ValueError(f"patches: expected a field {name!r}")
    return v


def tessellate_patches(patches, heights, dx: float, dz: float, eye, spacing: str = "equal",
                       filter: str = "bilinear", origin=(0.0, 0.0), device: str = "cpu",
                       need: Iterable[str] | None = None, uv_cells: bool = False, *,
                       checked: bool = False) -> Tessellation:
    """Tessellate and displace all patches of a frame (one launch per stage).

    Args:
        patches: an object or dict with ``origin_xz`` (P, 2) world (x, z) of each patch's corner
            with the smallest coordinates (float64, metres), ``size`` (P,) its side in metres or (P, 2)
            its (x, z) extent (a patch square in cells is a rectangle in metres when dx != dz), ``outer``
            (P, 4) and ``inner`` (P, 2) float32 levels, and optionally ``level`` (P,) int32. The
            domain's u runs along +x and v along +z.
        heights: (H, W) float32 heightmap, row i along +z, column j along +x; or a Warp array (used as it
            is: a streamed heightmap passes a zero-strided stand-in of its shape and displaces afterwards).
        dx, dz: sample spacing in metres (> 0).
        eye: world (x, y, z) positions are made relative to (float64).
        spacing: ``"equal"``, ``"fractional_even"`` or ``"fractional_odd"``.
        filter: ``"bilinear"`` or ``"bicubic"`` height sampling (outside the grid: clamped to the edge).
        origin: world (x, z) of sample (0, 0).
        need: the per-point fields to make besides positions (and triangles), any of ``"uv"``,
            ``"domain"``, ``"patch_id"``, ``"level"`` (None: all of them); the others are None. A
            depth-only frame asks for none and stores 12 bytes per point and 12 per triangle.
        uv_cells: ``uv`` in grid cells (column, row) instead of normalised to [0, 1].
        checked: the caller vouches for the arguments, as :func:`terrainwarp.render` does for the patches its
            selection made: ``patches`` has every field (``level`` too) as C-contiguous arrays of exactly the
            shapes and dtypes above (``origin_xz`` and ``size`` (P, 2) float64), finite, sizes positive, extents
            within 2^30 cells of the origin; ``heights`` a 2-D float32 array, ``dx``, ``dz`` positive, ``eye`` 3
            finite numbers, ``spacing`` and ``filter`` valid names. Nothing is checked or converted then; arguments
            that break this give undefined results.

    Returns:
        A :class:`Tessellation`. Not differentiable (discrete topology; heights are sampled with the
        same ``@wp.func`` as :func:`terrainwarp.kernels.sampling.sample_grid`).

    Precision: points sit on a lattice of 2^-16 heightmap cells (exact int64; extents within 2^30
    cells of the heightmap origin); camera-relative x, z carry one float32 rounding of the exact
    lattice offset from the eye (relative error 2^-24 of the distance to the eye); the sampling
    coordinate is float32 (2^-12 cells at column 4,096).
    """
    n, m, v_off, t_off, made, views, e = _tessellate(patches, heights, dx, dz, eye, spacing, filter, origin, device,
                                                     need, uv_cells, host=True, checked=check_bool("checked", checked))
    got = {k: a.numpy() for k, a in made.items()} if views is None else views  # (N, *axes) each

    def field(name: str, rows: int | None = None) -> np.ndarray | None:
        """The frame's rows of an output (N is the frame's count, or 1 when that is 0)."""
        a, k = got.get(name), n if rows is None else rows
        return a if a is None or len(a) == k else a[:k]

    dom = field("dom")
    return Tessellation(
        positions=field("pos"), uv=field("uv"),
        domain=None if dom is None else dom.astype(np.float32) * np.float32(1.0 / FXP_ONE),  # exact
        patch_id=field("pid"), level=field("lev"), triangles=field("tri", m), vertex_offsets=v_off,
        triangle_offsets=t_off, eye=e, counters=patch_draw_counters(len(v_off) - 1, n, m, FILTER_TEXELS[filter]))


class DeviceTessellation(NamedTuple):
    """A frame's tessellation left where it was made (Warp arrays on the device, none copied to the host): what
    :func:`tessellate_patches` reads back. The arrays are frame-sized pool buffers (their first ``n_points`` /
    ``n_triangles`` rows are the frame's); the optional ones are None unless asked for (``need``).

    Attributes:
        n_points, n_triangles: the frame's domain points and triangles.
        positions: vec3 camera-relative positions; triangles: vec3i, counter-clockwise seen from above.
        uv: vec2; domain: vec2i (16.16 fixed point); patch_id, level: int32 per point.
        vertex_offsets, triangle_offsets: (P+1,) int32 per-patch ranges.
        eye: the float64 world point positions are relative to.
    """

    n_points: int
    n_triangles: int
    positions: wp.array
    triangles: wp.array
    uv: wp.array | None
    domain: wp.array | None
    patch_id: wp.array | None
    level: wp.array | None
    vertex_offsets: wp.array
    triangle_offsets: wp.array
    eye: tuple[float, float, float]


def tessellate_patches_device(patches, heights, dx: float, dz: float, eye, spacing: str = "equal",
                              filter: str = "bilinear", origin=(0.0, 0.0), device: str = "cpu",
                              need: Iterable[str] | None = None, uv_cells: bool = False) -> DeviceTessellation:
    """:func:`tessellate_patches` (same arguments, validated the same way) without the copies to the host: the
    device stages alone (count, scan, then emit and displace in one launch)."""
    n, m, v_off, t_off, made, _, e = _tessellate(patches, heights, dx, dz, eye, spacing, filter, origin, device, need,
                                                 uv_cells)
    return DeviceTessellation(n, m, made["pos"], made["tri"], made.get("uv"), made.get("dom"), made.get("pid"),
                              made.get("lev"), wp.array(v_off, dtype=wp.int32, device=device),
                              wp.array(t_off, dtype=wp.int32, device=device), e)


def _tessellate(patches, heights, dx, dz, eye, spacing, filter, origin, device, need, uv_cells, host=False,
                checked=False):
    """:func:`tessellate_patches_device`'s work -> (n, m, offsets (P+1,) int32 on the host, the outputs made and with
    ``host`` their numpy arrays (see :func:`_frame_device`), the eye as floats)."""
    flags = _flags(need) | (W_CELLS if uv_cells else 0) | W_SWAP
    args, e = (_prepare_checked if checked else _prepare_frame)(patches, heights, dx, dz, eye, spacing, filter, origin)
    n, m, v_off, t_off, made, views = _frame_device(args, device, flags, host)
    return n, m, v_off, t_off, made, views, (float(e[0]), float(e[1]), float(e[2]))


class FrameLattice(NamedTuple):
    """Where :func:`tessellate_patches` puts a frame on its 2^-16-cell lattice: each patch's box (P, 4) int64
    (x0, z0, x1, z1 in lattice units), the eye's lattice cell (2,) int64 and its float remainder (x, y, z), the
    cell size (2,) float32 in metres."""

    box: np.ndarray
    eye_cell: np.ndarray
    eye_rem: tuple[float, float, float]
    cell: np.ndarray


def frame_lattice(patches, heights, dx: float, dz: float, eye, spacing: str = "equal", filter: str = "bilinear",
                  origin=(0.0, 0.0)) -> FrameLattice:
    """The lattice of :func:`tessellate_patches` (same arguments, validated the same way) without tessellating:
    for code that places points exactly where the tessellator would."""
    a, _ = _prepare_frame(patches, heights, dx, dz, eye, spacing, filter, origin)
    return FrameLattice(np.asarray(a.box, np.int64), np.asarray(a.eye_cell, np.int64), a.eye_rem,
                        np.asarray(a.cell, np.float32))


def _flags(need: Iterable[str] | None) -> int:
    """``need`` (see :func:`tessellate_patches`) -> W_* flags, positions always."""
    names = OPTIONAL_FIELDS if need is None else ([need] if isinstance(need, str) else list(need))
    bad = [x for x in names if x not in OPTIONAL_FIELDS]
    if bad:
        raise ValueError(f"need: expected names among {list(OPTIONAL_FIELDS)}, got {bad!r}")
    return int(W_POSITION) | sum({OPTIONAL_FIELDS[x] for x in names})


class _FrameArgs(NamedTuple):
    """:func:`tessellate_patches`' arguments, validated and put on the 2^-16-cell lattice by :func:`_prepare_frame`:
    levels (P, 4), (P, 2) float32, the spacing code, patch boxes (P, 4) int64, levels (P,) int32, the heights,
    the eye's lattice cell (2,) int64 and its float remainder (x, y, z), the cell size (2,) float32, the filter
    code."""

    outer: np.ndarray
    inner: np.ndarray
    code: int
    box: np.ndarray
    level: np.ndarray
    heights: np.ndarray | wp.array
    eye_cell: np.ndarray
    eye_rem: tuple[float, float, float]
    cell: np.ndarray
    method: int


def _frame_device(a: _FrameArgs, device, flags: int, host: bool = False):
    """Device stages of :func:`tessellate_patches` (count, scan, then emit and displace in one launch), writing
    what ``flags`` (W_*) asks for -> (n, m, vertex and triangle offsets (P+1,) int32 on the host, the outputs
    made: ``{"tri": ..., and "dom", "pid", "pos", "uv", "lev" as asked}``, frame-sized pool arrays, and with
    ``host`` on the CPU numpy arrays over them, ``(N, *axes)`` each, else None)."""
    o, i, code, box, lvl, h, el_int, eye_rem, cell, method = a
    lease = take(("tessellator", device_named(device).alias), lambda: _Work(device), keep=_WORK_KEPT)
    work = lease.buffer
    # all that does not wait for the counts is set before the count launch (the host code after a launch runs with
    # the caches it emptied: each kind of work once between two launches)
    work.fit(o.shape[0])
    work.put(2, box)
    work.put(3, lvl)
    work.set_frame(flags, h if isinstance(h, wp.array) else view(h, wp.float32, device),  # heights read in place
                   (int(el_int[0]), int(el_int[1]), eye_rem), (float(cell[0]), float(cell[1])), method)
    n, m = work.count_scan(o, i, code)
    v_off, t_off = work.offsets(o.shape[0])
    fields = [(name, max(n, 1), dt) for flag, name, dt in _FIELDS if flags & flag] + [("tri", max(m, 1), wp.vec3i)]
    # frame-sized outputs from the pool, one lease for them all: no fresh pages to fault in on every frame
    got = pooled_arrays([f[1:] for f in fields], device, tag="tessellation", keep=_OUTPUTS_KEPT, host=host)
    arrays, views = got if host else (got, None)
    made = {f[0]: a for f, a in zip(fields, arrays, strict=True)}
    for name, a in made.items():
        setattr(work.out, name, a)
    work.emit(o.shape[0], code, made)
    lease.give_back()
    return n, m, v_off, t_off, made, None if views is None else {f[0]: v for f, v in zip(fields, views, strict=True)}


def _prepare_frame(patches, heights, dx, dz, eye, spacing, filter, origin) -> tuple[_FrameArgs, np.ndarray]:
    """Validate :func:`tessellate_patches`' arguments; -> (the device stages' :class:`_FrameArgs`, the eye)."""
    o, i = _levels(_get(patches, "outer"), _get(patches, "inner"))
    p = o.shape[0]
    org = np.asarray(_get(patches, "origin_xz"), dtype=np.float64)
    size = np.asarray(_get(patches, "size"), dtype=np.float64)
    if org.shape != (p, 2):
        raise ValueError(f"patches.origin_xz: expected shape ({p}, 2), got {org.shape}")
    if size.shape == (p,):  # square in metres
        size = np.repeat(size[:, None], 2, axis=1)
    if size.shape != (p, 2) or not np.isfinite(size).all() or (size <= 0).any():
        raise ValueError(f"patches.size: expected ({p},) or ({p}, 2) positive finite sizes (x, z), got shape "
                         f"{size.shape}")
    if not np.isfinite(org).all():
        raise ValueError("patches.origin_xz: expected finite coordinates, got NaN or inf")
    lvl = _get(patches, "level", required=False)
    lvl = np.zeros(p, np.int32) if lvl is None else np.asarray(lvl, dtype=np.int32).reshape(-1)
    if lvl.shape != (p,):
        raise ValueError(f"patches.level: expected shape ({p},), got {lvl.shape}")
    h = heights if isinstance(heights, wp.array) else np.asarray(heights, dtype=np.float32)
    if h.ndim != 2 or min(h.shape) < 1:
        raise ValueError(f"heights: expected a 2-D (H, W) array, got shape {h.shape}")
    dx, dz = float(dx), float(dz)
    if not (np.isfinite(dx) and np.isfinite(dz) and dx > 0 and dz > 0):
        raise ValueError(f"dx, dz: expected positive finite spacings, got {dx}, {dz}")
    check_choice("filter", filter, FILTER_CODES)
    e = np.asarray(eye, dtype=np.float64).reshape(-1)
    if e.size != 3 or not np.isfinite(e).all():
        raise ValueError(f"eye: expected 3 finite numbers, got {eye!r}")
    code = _spacing_code(spacing)
    x0, z0 = (float(c) for c in np.asarray(origin, dtype=np.float64).reshape(2))
    args = _on_lattice(o, i, code, org, size, lvl, h, dx, dz, e, (x0, z0), filter)
    if (np.abs(args.box) > 2**46).any():
        raise ValueError("patches: expected extents within 2^30 cells of the heightmap origin")
    return args, e


def _prepare_checked(patches, heights, dx, dz, eye, spacing, filter, origin) -> tuple[_FrameArgs, tuple]:
    """:func:`_prepare_frame` for arguments the caller vouches for (``checked=True``): nothing scanned or checked."""
    e = (float(eye[0]), float(eye[1]), float(eye[2]))
    return _on_lattice(_get(patches, "outer"), _get(patches, "inner"), SPACING_CODES[spacing],
                       _get(patches, "origin_xz"), _get(patches, "size"), _get(patches, "level"), heights, float(dx),
                       float(dz), e, (float(origin[0]), float(origin[1])), filter), e


def _on_lattice(o, i, code, org, size, lvl, h, dx: float, dz: float, e, origin, filter) -> _FrameArgs:
    """The frame's :class:`_FrameArgs`: patch extents (``org``, ``size`` (P, 2) float64) and the eye ``e`` on the
    lattice of 2^-16 cells (float64 on the host, rounded once) from ``origin`` (x0, z0) floats."""
    x0, z0 = origin
    scale = (FXP_ONE / dx, FXP_ONE / dz)
    # (x0, z0, x1, z1) per patch: the low corner and the low corner plus the size, each minus the origin, scaled;
    # worked out as four rows of P (a (P, 4) broadcast loops four items at a time), then laid out (P, 4)
    rows = np.empty((4, len(org)))
    for c, o_c in enumerate((x0, z0)):
        np.subtract(org[:, c], o_c, out=rows[c])
        np.subtract(np.add(org[:, c], size[:, c], out=rows[2 + c]), o_c, out=rows[2 + c])
        rows[c::2] *= scale[c]
    box = np.rint(rows, out=rows).T.astype(np.int64, order="C")
    # the eye: its lattice cell and the float64 remainder (the same IEEE operations as on arrays, on two numbers)
    ex, ez = (float(e[0]) - x0) * scale[0], (float(e[2]) - z0) * scale[1]
    ix, iz = math.floor(ex), math.floor(ez)
    cell = np.array([dx / FXP_ONE, dz / FXP_ONE], np.float32)
    return _FrameArgs(o, i, code, box, lvl, h, np.array([ix, iz], np.int64),
                      ((ex - ix) / scale[0], float(e[1]), (ez - iz) / scale[1]), cell, FILTER_CODES[filter])
