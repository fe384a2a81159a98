"""Curvature of a heightmap: the directional approximations of curtis2004 and the surface curvatures of
geomorphometry, each one kernel over the whole grid.

Directional curvature (curtis2004, "Determining curvature"), in the four directions ``DIRECTIONS``:
x (+column), z (+row), diagonal (+x, +z) and diagonal (+x, -z), with step lengths dx, dz and
sqrt(dx^2 + dz^2) (= dx*sqrt(2) when dx = dz). Along a direction the terrain is a plane curve y(t) and
Equation 1 gives ``k = |y''| / (1 + y'^2)^(3/2)`` (1/m). Methods (``CURVATURE_METHODS``):

* ``two_normal``: y' = slope of the tangent at the vertex, from its normal (s = -(n.u)/n.y for the unit
  horizontal direction u); y'' = (s_next - s_vertex) / L.
* ``three_normal``: the same for the pairs (previous, vertex) and (vertex, next), the two curvatures
  averaged. Reinforcement (``distance`` d > 1): the same with the neighbours d samples away (step d*L),
  and the result is the product (scale*k_1) * (scale*k_d), which pushes values away from 1.
* ``three_vertex``: the chords to the two neighbours have slopes s1, s2; y'' = (s2 - s1) / L, y' =
  (s1 + s2) / 2.
* ``edge_angle``: 1 - cos(phi), phi the angle between the consecutive edges (vertex - previous) and
  (next - vertex) of the section (so pi - the angle between the edges radiating from the vertex:
  straight ground gives 0, a right angle 1), clamped to [0, 1]; computed as sin^2/(1 + cos) so that
  small angles keep their precision in float32. Dimensionless.

``scale`` multiplies every value (curtis2004's curvature scaling parameter); edge_angle is clamped
before scaling.

Surface curvatures (``SURFACE_SCHEMES``: Zevenbergen & Thorne 1987, Evans 1979 / Young 1978 as in
Florinsky 2016) from the 3x3 window's p = dh/dx, q = dh/dz, r = d2h/dx2, t = d2h/dz2, s = d2h/dxdz,
w = 1 + p^2 + q^2; sign: positive on convex ground (a dome, a ridge):

* mean H = -((1 + q^2) r - 2 p q s + (1 + p^2) t) / (2 w^(3/2))
* Gaussian K = (r t - s^2) / w^2
* profile kv = -(p^2 r + 2 p q s + q^2 t) / ((p^2 + q^2) w^(3/2))   (normal curvature along the gradient)
* plan kp = -(q^2 r - 2 p q s + p^2 t) / (p^2 + q^2)^(3/2)         (curvature of the contour line)

profile and plan are 0 where the gradient is exactly 0.

Precision and no data: all differences are taken relative to the centre sample (Sterbenz: exact for
nearby float32 values), so a flat terrain gives exactly 0 and a sloped plane a few ulp of its float32
samples. Missing samples (NaN, or outside the grid) are skipped: a 3-point stencil with a missing
neighbour shifts to the two samples on the other side (exact on quadratics), a normal pair with a
missing neighbour is dropped, and a direction with no usable samples gives 0. In the 3x3 surface
window a missing sample is replaced by its reflection through the centre (2c - opposite, or c), which
is exact on planes. A NaN centre gives NaN (no data) in every output; no other output is ever NaN.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .checks import check_choice, check_int
from .normals import (
    CPU_ONLY,
    END_CPU_ONLY,
    NAN_FREE,
    check_spacing,
    device_heights,
    fetch,
    interior_span,
    row_block,
    row_launch,
    vertex_normals_device,
)
from .normals import METHODS as NORMAL_METHODS
from .parallel import empty, launch

DIRECTIONS = ("x", "z", "diag_xz", "diag_x_negz")
CURVATURE_METHODS = {"two_normal": 0, "three_normal": 1, "three_vertex": 2, "edge_angle": 3}
SURFACE_SCHEMES = {"zevenbergen_thorne": 0, "evans_young": 1}
SURFACE_FIELDS = ("mean", "gaussian", "profile", "plan")

# ---------------------------------------------------------------------------------------------------
# direction tables
# ---------------------------------------------------------------------------------------------------


@wp.func
def dir_offset(d: int) -> wp.vec2i:
    """(di, dj) grid step of direction d: x, z, diagonal (+x,+z), diagonal (+x,-z)."""
    if d == 0:
        return wp.vec2i(0, 1)
    if d == 1:
        return wp.vec2i(1, 0)
    if d == 2:
        return wp.vec2i(1, 1)
    return wp.vec2i(-1, 1)


@wp.func
def _nan() -> float:
    return wp.nan


# ---------------------------------------------------------------------------------------------------
# section-curve functions
# ---------------------------------------------------------------------------------------------------


@wp.func
def _chords(h: wp.array2d(dtype=wp.float32), i: int, j: int, di: int, dj: int, L: float) -> wp.vec4:
    """(ok, s1, s2, where) for the 3-sample stencil through (i, j) along (di, dj) with step L:
    chord slopes s1 (first->middle) and s2 (middle->last); where = 0 centred, -1 when the vertex is the
    first sample (forward stencil), +1 when it is the last (backward). ok = 0 when no stencil fits."""
    c = h[i, j]
    p = fetch(h, i - di, j - dj, 2, 0.0)
    n = fetch(h, i + di, j + dj, 2, 0.0)
    if p[1] > 0.0 and n[1] > 0.0:
        return wp.vec4(1.0, (c - p[0]) / L, (n[0] - c) / L, 0.0)
    if n[1] > 0.0:
        nn = fetch(h, i + 2 * di, j + 2 * dj, 2, 0.0)
        if nn[1] > 0.0:
            return wp.vec4(1.0, (n[0] - c) / L, (nn[0] - n[0]) / L, -1.0)
    if p[1] > 0.0:
        pp = fetch(h, i - 2 * di, j - 2 * dj, 2, 0.0)
        if pp[1] > 0.0:
            return wp.vec4(1.0, (p[0] - pp[0]) / L, (c - p[0]) / L, 1.0)
    return wp.vec4(0.0)


@wp.func
def eq1(ypp: float, yp: float) -> float:
    """curtis2004 Equation 1: |y''| / (1 + y'^2)^(3/2)."""
    w = 1.0 + yp * yp
    return wp.abs(ypp) / (w * wp.sqrt(w))


@wp.func
def three_vertex_k(ch: wp.vec4, L: float) -> float:
    if ch[0] == 0.0:
        return 0.0
    s1 = ch[1]
    s2 = ch[2]
    yp = 0.5 * (s1 + s2)
    if ch[3] < 0.0:
        yp = 0.5 * (3.0 * s1 - s2)
    elif ch[3] > 0.0:
        yp = 0.5 * (3.0 * s2 - s1)
    return eq1((s2 - s1) / L, yp)


@wp.func
def edge_angle_k(ch: wp.vec4) -> float:
    """1 - cos(angle between the chord directions (1, s1) and (1, s2)), in [0, 1]."""
    if ch[0] == 0.0:
        return 0.0
    s1 = ch[1]
    s2 = ch[2]
    inv = 1.0 / wp.sqrt((1.0 + s1 * s1) * (1.0 + s2 * s2))
    sn = (s2 - s1) * inv
    cs = (1.0 + s1 * s2) * inv
    v = float(1.0)
    if cs > 0.0:
        v = sn * sn / (1.0 + cs)
    else:
        v = 1.0 - cs
    return wp.clamp(v, 0.0, 1.0)


@wp.func
def _slope_from_normal(n: wp.vec3, ux: float, uz: float) -> float:
    return -(n[0] * ux + n[2] * uz) / n[1]


@wp.func
def _normal_pair_k(h: wp.array2d(dtype=wp.float32), nrm: wp.array2d(dtype=wp.vec3), i: int, j: int, di: int,
                   dj: int, L: float, ux: float, uz: float, sc: float, side: int) -> wp.vec2:
    """(ok, k) of the normal pair (vertex, vertex + side*(di, dj)); y' = the vertex's slope."""
    a = i + side * di
    b = j + side * dj
    if fetch(h, a, b, 2, 0.0)[1] == 0.0:
        return wp.vec2(0.0, 0.0)
    sn = _slope_from_normal(nrm[a, b], ux, uz)
    return wp.vec2(1.0, eq1((sn - sc) / L, sc))


@wp.func
def _three_normal_k(h: wp.array2d(dtype=wp.float32), nrm: wp.array2d(dtype=wp.vec3), i: int, j: int, di: int,
                    dj: int, L: float, ux: float, uz: float, sc: float) -> wp.vec2:
    kn = _normal_pair_k(h, nrm, i, j, di, dj, L, ux, uz, sc, 1)
    kp = _normal_pair_k(h, nrm, i, j, di, dj, L, ux, uz, sc, -1)
    cnt = kn[0] + kp[0]
    if cnt == 0.0:
        return wp.vec2(0.0, 0.0)
    return wp.vec2(1.0, (kn[1] + kp[1]) / cnt)


@wp.func
def dir_length(di: int, dj: int, dx: float, dz: float) -> float:
    """Step length of the grid step (di, dj)."""
    return wp.sqrt(float(di * di) * dz * dz + float(dj * dj) * dx * dx)


@wp.func
def chord_k(h: wp.array2d(dtype=wp.float32), i: int, j: int, di: int, dj: int, L: float, method: int) -> float:
    """three_vertex (method 2) or edge_angle (3) along (di, dj), before scaling."""
    if method == 2:
        return three_vertex_k(_chords(h, i, j, di, dj, L), L)
    return edge_angle_k(_chords(h, i, j, di, dj, L))


@wp.func
def _chord_at(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float, method: int,
              scale: float) -> wp.vec4:
    """The general path of :func:`_chord_kernel` at (i, j) (NaN at a NaN height)."""
    if wp.isnan(h[i, j]):
        return wp.vec4(_nan())
    k = wp.vec4(0.0)
    for d in range(4):
        o = dir_offset(d)
        k[d] = scale * chord_k(h, i, j, o[0], o[1], dir_length(o[0], o[1], dx, dz), method)
    return k


@wp.func
def _directional_at(h: wp.array2d(dtype=wp.float32), nrm: wp.array2d(dtype=wp.vec3), i: int, j: int, dx: float,
                    dz: float, method: int, scale: float, distance: int) -> wp.vec4:
    """The four directions at (i, j) (NaN at a NaN height)."""
    if wp.isnan(h[i, j]):
        return wp.vec4(_nan())
    k = wp.vec4(0.0)
    for d in range(4):
        k[d] = directional_k(h, nrm, i, j, d, dx, dz, method, scale, distance)
    return k


@wp.func
def directional_k(h: wp.array2d(dtype=wp.float32), nrm: wp.array2d(dtype=wp.vec3), i: int, j: int, d: int,
                  dx: float, dz: float, method: int, scale: float, distance: int) -> float:
    o = dir_offset(d)
    di = o[0]
    dj = o[1]
    L = dir_length(di, dj, dx, dz)
    if method >= 2:
        return scale * chord_k(h, i, j, di, dj, L, method)
    ux = float(dj) * dx / L
    uz = float(di) * dz / L
    sc = _slope_from_normal(nrm[i, j], ux, uz)
    if method == 0:
        r = _normal_pair_k(h, nrm, i, j, di, dj, L, ux, uz, sc, 1)
        if r[0] == 0.0:
            r = _normal_pair_k(h, nrm, i, j, di, dj, L, ux, uz, sc, -1)
        return scale * r[1]
    k1 = _three_normal_k(h, nrm, i, j, di, dj, L, ux, uz, sc)
    if distance <= 1:
        return scale * k1[1]
    kd = _three_normal_k(h, nrm, i, j, di * distance, dj * distance, L * float(distance), ux, uz, sc)
    return (scale * k1[1]) * (scale * kd[1])


# ---------------------------------------------------------------------------------------------------
# surface curvature (3x3 window)
# ---------------------------------------------------------------------------------------------------


@wp.func
def _win(h: wp.array2d(dtype=wp.float32), i: int, j: int, a: int, b: int, c: float) -> float:
    """Height of window sample (i+a, j+b) minus the centre c; a missing sample is reflected."""
    v = fetch(h, i + a, j + b, 2, 0.0)
    if v[1] > 0.0:
        return v[0] - c
    r = fetch(h, i - a, j - b, 2, 0.0)
    if r[1] > 0.0:
        return c - r[0]
    return 0.0


@wp.func
def surface_k(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float, scheme: int) -> wp.vec4:
    c = h[i, j]
    # z1..z9 relative to the centre; row -1 is -z
    z1 = _win(h, i, j, -1, -1, c)
    z2 = _win(h, i, j, -1, 0, c)
    z3 = _win(h, i, j, -1, 1, c)
    z4 = _win(h, i, j, 0, -1, c)
    z6 = _win(h, i, j, 0, 1, c)
    z7 = _win(h, i, j, 1, -1, c)
    z8 = _win(h, i, j, 1, 0, c)
    z9 = _win(h, i, j, 1, 1, c)
    p = float(0.0)
    q = float(0.0)
    r = float(0.0)
    t = float(0.0)
    s = ((z9 - z7) - (z3 - z1)) / (4.0 * dx * dz)
    if scheme == 0:
        p = (z6 - z4) / (2.0 * dx)
        q = (z8 - z2) / (2.0 * dz)
        r = (z6 + z4) / (dx * dx)
        t = (z8 + z2) / (dz * dz)
    else:
        p = ((z3 - z1) + (z6 - z4) + (z9 - z7)) / (6.0 * dx)
        q = ((z7 - z1) + (z8 - z2) + (z9 - z3)) / (6.0 * dz)
        r = ((z1 + z3 + z4 + z6 + z7 + z9) - 2.0 * (z2 + z8)) / (3.0 * dx * dx)
        t = ((z1 + z2 + z3 + z7 + z8 + z9) - 2.0 * (z4 + z6)) / (3.0 * dz * dz)
    p2 = p * p
    q2 = q * q
    w = 1.0 + p2 + q2
    sw = wp.sqrt(w)
    mean = -((1.0 + q2) * r - 2.0 * p * q * s + (1.0 + p2) * t) / (2.0 * w * sw)
    gauss = (r * t - s * s) / (w * w)
    g2 = p2 + q2
    prof = float(0.0)
    plan = float(0.0)
    if g2 > 0.0:
        prof = -(p2 * r + 2.0 * p * q * s + q2 * t) / (g2 * w * sw)
        plan = -(q2 * r - 2.0 * p * q * s + p2 * t) / (g2 * wp.sqrt(g2))
    return wp.vec4(mean, gauss, prof, plan)


@wp.func
def _surface_at(h: wp.array2d(dtype=wp.float32), i: int, j: int, dx: float, dz: float, scheme: int,
                out_k: wp.array3d(dtype=wp.float32)):
    """The general path of :func:`_surface_kernel` at (i, j) (NaN at a NaN height)."""
    v = wp.vec4(_nan())
    if not wp.isnan(h[i, j]):
        v = surface_k(h, i, j, dx, dz, scheme)
    for c in range(4):
        out_k[c, i, j] = v[c]


# ---------------------------------------------------------------------------------------------------
# interior rows: one native loop per row (see kernels/normals.py: the same float operations in the same
# order, one per statement where Warp has one; a NaN in the window or a border sample goes the general way)
# ---------------------------------------------------------------------------------------------------


@wp.func
def dir_lengths(dx: float, dz: float) -> wp.vec4:
    """Step length L of each direction, as :func:`directional_k` computes it."""
    ls = wp.vec4(0.0)
    for d in range(4):
        o = dir_offset(d)
        ls[d] = dir_length(o[0], o[1], dx, dz)
    return ls


@wp.func_native(CPU_ONLY + """
    const float* p = (const float*)h.data;
    float* o = (float*)out.data;
    const int W = (int)h.shape[1];
    const int R_ = 1;
""" + NAN_FREE + """
    const float* u = p + (int64_t)(i - 1) * W;
    const float* c = p + (int64_t)i * W;
    const float* d = p + (int64_t)(i + 1) * W;
    // (previous, next) sample of each direction: x, z, diagonal (+x, +z), diagonal (+x, -z)
    #define TW_CHORDS(D, PREV, NEXT, L)                 \\
        const float s1_##D = (c[j] - (PREV)) / (L);     \\
        const float s2_##D = ((NEXT) - c[j]) / (L);
    if (method == 2) {  // three_vertex: eq1((s2 - s1) / L, (s1 + s2) / 2)
        #define TW_K(D, L)                                          \\
            {                                                       \\
                const float t = s1_##D + s2_##D;                    \\
                const float yp = 0.5f * t;                          \\
                const float ypp = (s2_##D - s1_##D) / (L);          \\
                const float yy = yp * yp;                           \\
                const float w = 1.0f + yy;                          \\
                const float sw = wp::sqrt(w);                       \\
                const float den = w * sw;                           \\
                const float kk = wp::abs(ypp) / den;                \\
                o[4 * k + D] = scale * kk;                          \\
            }
        for (int j = j0; j < j1; ++j) {
            const int64_t k = (int64_t)i * W + j;
            TW_CHORDS(0, c[j - 1], c[j + 1], L0) TW_K(0, L0)
            TW_CHORDS(1, u[j], d[j], L1) TW_K(1, L1)
            TW_CHORDS(2, u[j - 1], d[j + 1], L2) TW_K(2, L2)
            TW_CHORDS(3, d[j - 1], u[j + 1], L3) TW_K(3, L3)
        }
        #undef TW_K
    } else {  // edge_angle: 1 - cos of the turn between the chords, as sin^2 / (1 + cos), clamped to [0, 1]
        #define TW_K(D, L)                                          \\
            {                                                       \\
                const float a1 = s1_##D * s1_##D;                   \\
                const float b1 = 1.0f + a1;                         \\
                const float a2 = s2_##D * s2_##D;                   \\
                const float b2 = 1.0f + a2;                         \\
                const float bb = b1 * b2;                           \\
                const float inv = 1.0f / wp::sqrt(bb);              \\
                const float sn = (s2_##D - s1_##D) * inv;           \\
                const float a12 = s1_##D * s2_##D;                  \\
                const float cs = (1.0f + a12) * inv;                \\
                const float sn2 = sn * sn;                          \\
                float v = 1.0f - cs;                                \\
                if (cs > 0.0f) v = sn2 / (1.0f + cs);               \\
                o[4 * k + D] = scale * wp::clamp(v, 0.0f, 1.0f);    \\
            }
        for (int j = j0; j < j1; ++j) {
            const int64_t k = (int64_t)i * W + j;
            TW_CHORDS(0, c[j - 1], c[j + 1], L0) TW_K(0, L0)
            TW_CHORDS(1, u[j], d[j], L1) TW_K(1, L1)
            TW_CHORDS(2, u[j - 1], d[j + 1], L2) TW_K(2, L2)
            TW_CHORDS(3, d[j - 1], u[j + 1], L3) TW_K(3, L3)
        }
        #undef TW_K
    }
    #undef TW_CHORDS
    return 1;
""" + END_CPU_ONLY)
def _chord_row(h: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.vec4), i: int, j0: int, j1: int,
               method: int, scale: float, L0: float, L1: float, L2: float, L3: float) -> int:
    """three_vertex (method 2) or edge_angle (3) of row i, columns [j0, j1) (centred stencils in every
    direction); 0 (nothing written) when the window has a NaN."""
    ...


@wp.func_native(CPU_ONLY + """
    const float* p = (const float*)h.data;
    const float* nv = (const float*)nrm.data;
    float* o = (float*)out.data;
    const int W = (int)h.shape[1];
    const int R_ = 1;
""" + NAN_FREE + """
    const float Ls[4] = {L0, L1, L2, L3};
    const float uxs[4] = {ux0, ux1, ux2, ux3};
    const float uzs[4] = {uz0, uz1, uz2, uz3};
    const int64_t offs[4] = {1, W, (int64_t)W + 1, 1 - (int64_t)W};  // (di, dj) of x, z, (+x, +z), (+x, -z)
    // y' of the normal n (components n[0], n[1], n[2]) along (ux, uz): -(n.x ux + n.z uz) / n.y
    for (int j = j0; j < j1; ++j) {
        const int64_t k = (int64_t)i * W + j;
        for (int dd = 0; dd < 4; ++dd) {
            const float L = Ls[dd];
            const float ux = uxs[dd];
            const float uz = uzs[dd];
            const float* nc = nv + 3 * k;
            const float a0 = nc[0] * ux;
            const float b0 = nc[2] * uz;
            const float sc = (0.0f - (a0 + b0)) / nc[1];
            const float scsc = sc * sc;
            const float w = 1.0f + scsc;
            const float den = w * wp::sqrt(w);
            const float* nn = nv + 3 * (k + offs[dd]);
            const float an = nn[0] * ux;
            const float bn = nn[2] * uz;
            const float sn = (0.0f - (an + bn)) / nn[1];
            const float kn = wp::abs((sn - sc) / L) / den;
            float kk = kn;
            if (method == 1) {
                const float* np_ = nv + 3 * (k - offs[dd]);
                const float ap = np_[0] * ux;
                const float bp = np_[2] * uz;
                const float sp = (0.0f - (ap + bp)) / np_[1];
                const float kp = wp::abs((sp - sc) / L) / den;
                kk = (kn + kp) / 2.0f;
            }
            o[4 * k + dd] = scale * kk;
        }
    }
    return 1;
""" + END_CPU_ONLY)
def _normal_pair_row(h: wp.array2d(dtype=wp.float32), nrm: wp.array2d(dtype=wp.vec3), out: wp.array2d(dtype=wp.vec4),
                     i: int, j0: int, j1: int, method: int, scale: float, L0: float, L1: float, L2: float, L3: float,
                     ux0: float, ux1: float, ux2: float, ux3: float, uz0: float, uz1: float, uz2: float,
                     uz3: float) -> int:
    """two_normal (method 0) or three_normal (1, distance 1) of row i, columns [j0, j1); 0 (nothing
    written) when the window has a NaN."""
    ...


@wp.func_native(CPU_ONLY + """
    const float* p = (const float*)h.data;
    float* o = (float*)out.data;
    const int W = (int)h.shape[1];
    const int64_t plane = (int64_t)h.shape[0] * W;
    const int R_ = 1;
""" + NAN_FREE + """
    const float* u = p + (int64_t)(i - 1) * W;
    const float* cr = p + (int64_t)i * W;
    const float* d = p + (int64_t)(i + 1) * W;
    const float ds = (4.0f * dx) * dz;
    const float px = 2.0f * dx;
    const float qz = 2.0f * dz;
    const float rx = dx * dx;
    const float tz = dz * dz;
    const float px6 = 6.0f * dx;
    const float qz6 = 6.0f * dz;
    const float rx3 = (3.0f * dx) * dx;
    const float tz3 = (3.0f * dz) * dz;
    #define TW_SURFACE(SCHEME)                                                                      \\
        for (int j = j0; j < j1; ++j) {                                                             \\
            const int64_t k = (int64_t)i * W + j;                                                   \\
            const float c = cr[j];                                                                  \\
            const float z1 = u[j - 1] - c, z2 = u[j] - c, z3 = u[j + 1] - c;                        \\
            const float z4 = cr[j - 1] - c, z6 = cr[j + 1] - c;                                     \\
            const float z7 = d[j - 1] - c, z8 = d[j] - c, z9 = d[j + 1] - c;                        \\
            const float s = ((z9 - z7) - (z3 - z1)) / ds;                                           \\
            float pp, q, r, t;                                                                      \\
            if (SCHEME == 0) {                                                                      \\
                pp = (z6 - z4) / px;                                                                \\
                q = (z8 - z2) / qz;                                                                 \\
                r = (z6 + z4) / rx;                                                                 \\
                t = (z8 + z2) / tz;                                                                 \\
            } else {                                                                                \\
                pp = ((z3 - z1) + (z6 - z4) + (z9 - z7)) / px6;                                     \\
                q = ((z7 - z1) + (z8 - z2) + (z9 - z3)) / qz6;                                      \\
                const float r2 = 2.0f * (z2 + z8);                                                  \\
                r = ((z1 + z3 + z4 + z6 + z7 + z9) - r2) / rx3;                                     \\
                const float t2 = 2.0f * (z4 + z6);                                                  \\
                t = ((z1 + z2 + z3 + z7 + z8 + z9) - t2) / tz3;                                     \\
            }                                                                                       \\
            const float p2 = pp * pp;                                                               \\
            const float q2 = q * q;                                                                 \\
            const float w = (1.0f + p2) + q2;                                                       \\
            const float sw = wp::sqrt(w);                                                           \\
            const float pq2 = (2.0f * pp) * q;                                                      \\
            const float pqs = pq2 * s;                                                              \\
            const float mA = (1.0f + q2) * r;                                                       \\
            const float mB = (1.0f + p2) * t;                                                       \\
            const float mden = (2.0f * w) * sw;                                                     \\
            const float mean = (0.0f - ((mA - pqs) + mB)) / mden;                                   \\
            const float rt = r * t;                                                                 \\
            const float ss = s * s;                                                                 \\
            const float ww = w * w;                                                                 \\
            const float gauss = (rt - ss) / ww;                                                     \\
            const float g2 = p2 + q2;                                                               \\
            float prof = 0.0f, pl = 0.0f;                                                           \\
            if (g2 > 0.0f) {                                                                        \\
                const float p2r = p2 * r;                                                           \\
                const float q2t = q2 * t;                                                           \\
                const float pden = (g2 * w) * sw;                                                   \\
                prof = (0.0f - ((p2r + pqs) + q2t)) / pden;                                         \\
                const float q2r = q2 * r;                                                           \\
                const float p2t = p2 * t;                                                           \\
                const float lden = g2 * wp::sqrt(g2);                                               \\
                pl = (0.0f - ((q2r - pqs) + p2t)) / lden;                                           \\
            }                                                                                       \\
            o[k] = mean;                                                                            \\
            o[plane + k] = gauss;                                                                   \\
            o[2 * plane + k] = prof;                                                                \\
            o[3 * plane + k] = pl;                                                                  \\
        }
    if (scheme == 0) {
        TW_SURFACE(0)
    } else {
        TW_SURFACE(1)
    }
    #undef TW_SURFACE
    return 1;
""" + END_CPU_ONLY)
def _surface_row(h: wp.array2d(dtype=wp.float32), out: wp.array3d(dtype=wp.float32), i: int, j0: int, j1: int,
                 dx: float, dz: float, scheme: int) -> int:
    """Surface curvatures of row i, columns [j0, j1) into the planes out[0..3]; 0 (nothing written) when
    the window has a NaN."""
    ...


# ---------------------------------------------------------------------------------------------------
# kernels
# ---------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _chord_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    method: int,
    scale: float,
    width: int,
    fast: int,
    # outputs
    out_k: wp.array2d(dtype=wp.vec4),
):
    """three_vertex / edge_angle by rows: the chord methods read only heights."""
    i, b = wp.tid()
    i += offset
    cols = row_block(h, i, b, width)
    s = interior_span(h, i, cols, 1, fast)
    if s[0] < s[1]:
        ls = dir_lengths(dx, dz)
        if _chord_row(h, out_k, i, s[0], s[1], method, scale, ls[0], ls[1], ls[2], ls[3]) == 0:
            s = wp.vec2i(s[0], s[0])
    for j in range(cols[0], s[0]):
        out_k[i, j] = _chord_at(h, i, j, dx, dz, method, scale)
    for j in range(s[1], cols[1]):
        out_k[i, j] = _chord_at(h, i, j, dx, dz, method, scale)


@wp.kernel(enable_backward=False)
def _normal_based_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    nrm: wp.array2d(dtype=wp.vec3),
    dx: float,
    dz: float,
    method: int,
    scale: float,
    distance: int,
    width: int,
    fast: int,
    # outputs
    out_k: wp.array2d(dtype=wp.vec4),
):
    """two_normal / three_normal by rows (native rows for distance 1)."""
    i, b = wp.tid()
    i += offset
    cols = row_block(h, i, b, width)
    s = interior_span(h, i, cols, 1, fast)
    if s[0] < s[1] and distance == 1:
        ls = wp.vec4(0.0)
        ux = wp.vec4(0.0)
        uz = wp.vec4(0.0)
        for d in range(4):
            o = dir_offset(d)
            L = dir_length(o[0], o[1], dx, dz)
            ls[d] = L
            ux[d] = float(o[1]) * dx / L
            uz[d] = float(o[0]) * dz / L
        if _normal_pair_row(h, nrm, out_k, i, s[0], s[1], method, scale, ls[0], ls[1], ls[2], ls[3], ux[0], ux[1],
                            ux[2], ux[3], uz[0], uz[1], uz[2], uz[3]) == 0:
            s = wp.vec2i(s[0], s[0])
    else:
        s = wp.vec2i(s[0], s[0])
    for j in range(cols[0], s[0]):
        out_k[i, j] = _directional_at(h, nrm, i, j, dx, dz, method, scale, distance)
    for j in range(s[1], cols[1]):
        out_k[i, j] = _directional_at(h, nrm, i, j, dx, dz, method, scale, distance)


@wp.kernel(enable_backward=False)
def _surface_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    scheme: int,
    width: int,
    fast: int,
    # outputs
    out_k: wp.array3d(dtype=wp.float32),
):
    """The four surface curvatures into the planes out_k[0..3] (mean, Gaussian, profile, plan)."""
    i, b = wp.tid()
    i += offset
    cols = row_block(h, i, b, width)
    s = interior_span(h, i, cols, 1, fast)
    if s[0] < s[1]:
        if _surface_row(h, out_k, i, s[0], s[1], dx, dz, scheme) == 0:
            s = wp.vec2i(s[0], s[0])
    for j in range(cols[0], s[0]):
        _surface_at(h, i, j, dx, dz, scheme, out_k)
    for j in range(s[1], cols[1]):
        _surface_at(h, i, j, dx, dz, scheme, out_k)


@wp.kernel(enable_backward=False)
def _max_kernel(
    offset: int,
    k: wp.array2d(dtype=wp.vec4),
    # outputs
    out_k: wp.array2d(dtype=wp.float32),
    out_dir: wp.array2d(dtype=wp.int32),
):
    i, j = wp.tid()
    i += offset
    v = k[i, j]
    best = v[0]
    bd = int(0)
    for d in range(1, 4):
        if v[d] > best:
            best = v[d]
            bd = d
    if wp.isnan(v[0]):
        out_k[i, j] = v[0]
        out_dir[i, j] = -1
    else:
        out_k[i, j] = best
        out_dir[i, j] = bd


# ---------------------------------------------------------------------------------------------------
# host wrappers
# ---------------------------------------------------------------------------------------------------


def directional_curvature(heights: np.ndarray, dx: float, dz: float, method: str = "three_normal",
                          scale: float = 1.0, distance: int = 1, normals: str = "quad",
                          device: str = "cpu") -> np.ndarray:
    """(H, W, 4) float32 curvature in the four ``DIRECTIONS`` by ``method`` (see the module docstring).

    Args:
        heights: (H, W) float heights (metres); NaN = no data.
        dx, dz: spacing along x (columns) and z (rows), > 0.
        method: one of ``CURVATURE_METHODS``.
        scale: curvature scale (> 0), multiplies every value.
        distance: reinforcement distance for ``three_normal`` (1 = none; d > 1 multiplies by the
            curvature of the neighbours d samples away).
        normals: vertex-normal method for the normal-based methods (curtis2004 uses ``"quad"``).

    Returns:
        (H, W, 4) float32, >= 0; 1/m for the Equation-1 methods (times ``scale``; 1/m^2 with
        reinforcement), dimensionless for ``edge_angle``. NaN exactly at NaN heights.
    """
    check_choice("method", method, CURVATURE_METHODS)
    check_choice("normals", normals, NORMAL_METHODS)
    check_int("distance", distance, 1)
    sc = float(scale)
    if not (np.isfinite(sc) and sc > 0.0):
        raise ValueError(f"scale: expected a positive finite number, got {scale!r}")
    dx, dz = check_spacing(dx, dz)
    h = device_heights(heights, device)
    m = CURVATURE_METHODS[method]
    out = empty(h.shape, wp.vec4, device)
    if m <= 1:
        nrm = vertex_normals_device(h, dx, dz, normals, "skip")
        row_launch(_normal_based_kernel, h, [nrm, dx, dz, m, sc, int(distance)], out)
    else:
        row_launch(_chord_kernel, h, [dx, dz, m, sc], out)
    return out.numpy().reshape(h.shape[0], h.shape[1], 4)


def surface_curvature_planes(heights: np.ndarray, dx: float, dz: float, scheme: str = "zevenbergen_thorne",
                             device: str = "cpu") -> np.ndarray:
    """(4, H, W) float32 planes of :func:`surface_curvature`: mean, Gaussian, profile, plan."""
    check_choice("scheme", scheme, SURFACE_SCHEMES)
    dx, dz = check_spacing(dx, dz)
    h = device_heights(heights, device)
    out = empty((4, *h.shape), wp.float32, device)
    row_launch(_surface_kernel, h, [dx, dz, SURFACE_SCHEMES[scheme]], out)
    return out.numpy()


def surface_curvature(heights: np.ndarray, dx: float, dz: float, scheme: str = "zevenbergen_thorne",
                      device: str = "cpu") -> np.ndarray:
    """(H, W, 4) float32 (mean, Gaussian, profile, plan) curvature; 1/m, 1/m^2, 1/m, 1/m."""
    return np.stack(list(surface_curvature_planes(heights, dx, dz, scheme, device)), axis=-1)


def max_curvature(curvature: np.ndarray, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex maximum over the four directions.

    Args:
        curvature: (H, W, 4) float32 directional curvature.

    Returns:
        ((H, W) float32 maximum, (H, W) int32 index into ``DIRECTIONS`` of the first maximum; -1 and NaN
        at no-data vertices).
    """
    k = np.asarray(curvature, dtype=np.float32)
    if k.ndim != 3 or k.shape[2] != 4:
        raise ValueError(f"curvature: expected an (H, W, 4) array, got shape {k.shape}")
    kd = wp.array(np.ascontiguousarray(k), dtype=wp.vec4, device=device)
    out_k = wp.empty(k.shape[:2], dtype=wp.float32, device=device)
    out_d = wp.empty(k.shape[:2], dtype=wp.int32, device=device)
    launch(_max_kernel, dim=k.shape[:2], inputs=[kd], outputs=[out_k, out_d], device=device)
    return out_k.numpy(), out_d.numpy()
