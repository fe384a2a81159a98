"""Quad-domain tessellation exactly as a Direct3D 11 / OpenGL 4 GPU generates it (host reference).

This module is the readable, pure-Python statement of the fixed-function tessellator for the QUAD
domain; :mod:`terrainwarp.kernels.tessellator` runs the same rules as Warp kernels over a whole frame,
and the tests check both against Mesa's llvmpipe (a real OpenGL 4.5 implementation whose tessellator
is the D3D11 reference tessellator) bit for bit.

Sources: the OpenGL 4.6 core specification, section 11.2.2 ("Tessellation Primitive Generation"),
with 11.2.2.2 ("Quad Tessellation"); the Direct3D 11.3 functional specification, "Tessellator" chapter
(partitioning, TessFactor range and rounding, fixed-point arithmetic, pattern); and the D3D11 reference
tessellator that defines it bit for bit (Mesa: src/gallium/auxiliary/tessellator/tessellator.cpp),
cited below by function name (``CHWTessellator::...``). "GL" and "ref" below mean those. The rules:

1. Levels (GL 11.2.2.2; ref ``TessellateQuadDomain``): ``outer[0]`` is the u=0 edge, ``outer[1]`` v=0,
   ``outer[2]`` u=1, ``outer[3]`` v=1 (the same order as D3D's ``SV_TessFactor`` Ueq0, Veq0, Ueq1, Veq1);
   ``inner[0]`` runs along u, ``inner[1]`` along v. Levels are float32.
2. Culling (GL 11.2.2: a patch with any relevant outer level <= 0 or NaN is discarded; ref
   ``QuadProcessTessFactors``): the patch produces no points and no triangles.
3. Clamping per spacing (GL 11.2.2, the spacing paragraphs; ref ``QuadProcessTessFactors``): ``equal``
   clamps to [1, 64] then rounds up to an integer (``ceil``); ``fractional_even`` clamps to [2, 64];
   ``fractional_odd`` clamps to [1, 63]. Inner levels that are NaN become the lower bound (the clamp is
   ``fmin(hi, fmax(lo, x))`` with IEEE fmin/fmax, which drop a NaN operand).
4. Picture frame (GL 11.2.2.2: unless every level is one, an inner level of one is treated as 1 + eps;
   ref ``QuadProcessTessFactors``): with ``fractional_odd``, if any outer or inner level exceeds ``1 +
   2^-17`` the inner levels are clamped below by ``1 + 2^-16`` instead of 1; with ``equal`` an inner 1 is
   placed as 2 (rule 5); ``fractional_even`` clamps to 2 anyway.
5. Parity (GL 11.2.2; ref ``QuadProcessTessFactors``, ``isEven``): fractional_even is even,
   fractional_odd is odd; with ``equal`` each level has its own parity from its integer value, and an
   inner level of exactly 1 counts as even (it is then placed like 2: one centre point).
6. Fixed point (D3D spec, fixed-point TessFactor arithmetic; ref ``floatToFixed``): levels are converted
   to unsigned 16.16 fixed point, rounding to nearest, ties to even (checked on llvmpipe). All following
   arithmetic is integer. If every level is exactly 1 with ``equal`` or ``fractional_odd``, the patch is
   the unit quad split into two triangles along the (1,0)-(0,1) diagonal.
7. Point placement on one edge (GL 11.2.2 (the segment lengths); ref ``ComputeTessFactorContext``,
   ``NumPointsForTessFactor``, ``PlacePointIn1D``, ``RemoveMSB``): half of the (rounded) level is split
   into floor and ceil parts; points are placed on the first half of the edge by lerping their position
   on the floor-level and ceil-level partitions (reciprocals ``round(2^16 / n)``) by the fractional part,
   then rounding ``(x + 2^15) >> 16``; the insertion point of the new segment follows the ruler function
   (``RemoveMSB``). The second half mirrors the first (``1 - x``, exact in fixed point), the middle of an
   even partition is exactly 0.5. Thus the two short segments of a fractional level are symmetric about
   the edge's middle, a point's position is continuous in the level, and new points are born on existing
   ones.
8. Points (GL 11.2.2.2; ref ``QuadGeneratePoints``): the outer ring first, from (0,1) down the u=0 edge,
   along v=0, up u=1, back along v=1; then the inner rings spiralling inwards with the inner levels'
   partitions (ring r uses partition points r .. n-1-r); with even inner parity the innermost ring
   degenerates into a row (or column, or single point) through the centre.
9. Stitching (GL 11.2.2.2 leaves the triangulation implementation-dependent; ref
   ``QuadGenerateConnectivity``, ``StitchTransition``, ``StitchRegular``): the outer ring is joined to
   the first inner ring edge by edge with the transition stitch (``StitchTransition``: both rows walked
   in ruler-function order, first half forwards, the middle (a quad or one triangle when the parities
   differ), then the second half backwards, so the triangulation is symmetric about each edge's middle);
   deeper rings are joined with regular trapezoid strips whose diagonals mirror about the middle; with
   odd inner parity a centre strip of quads closes the patch (diagonals inside-to-outside, except the
   middle quad of a strip along v when both parities are odd).
10. Winding (GL 11.2.2, ``cw``/``ccw``; ref ``DefineClockwiseTriangle``): the reference stitches
    triangles "clockwise" in D3D's domain (v down) and orders their corners for the requested output;
    with GL's ``ccw`` every triangle is counter-clockwise in the (u right, v up) domain (checked on
    llvmpipe, corner order included up to rotation). Our triangles are counter-clockwise in (u, v).

Point and triangle ORDER equals the reference tessellator's (points ring by ring; triangles ring by
ring, edge by edge), though only the set of triangles is observable on a GPU.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from ..io.files import save_figure
from ..kernels.checks import check_choice
from ..kernels.tessellator import SPACING_CODES

__all__ = ["reference_tessellate_patch", "patch_counts", "SPACINGS"]

SPACINGS = tuple(SPACING_CODES)  # the spacing names, from the Warp tessellator's codes

FXP_ONE = 1 << 16
FXP_HALF = 1 << 15
_INT_MASK = 0x7FFF0000
_FRAC_MASK = 0x0000FFFF
_EPS = np.float32(2.0**-16)
_ONE_PLUS_HALF_EPS = np.float32(1.0 + 2.0**-17)

# 2^16 / n rounded to nearest (n = 1..64); entry 0 is never used.
RECIPROCAL = [0xFFFFFFFF] + [int(65536.0 / n + 0.5) for n in range(1, 65)]
# Where point i of a half edge ends up at the maximum level under ruler-function split order.
FINAL_POINT_POSITION = [0, 32, 16, 8, 17, 4, 18, 9, 19, 2, 20, 10, 21, 5, 22, 11, 23,
                        1, 24, 12, 25, 6, 26, 13, 27, 3, 28, 14, 29, 7, 30, 15, 31]


# ------------------------------------------------------------------------------------------------
# levels
# ------------------------------------------------------------------------------------------------


def _fmax(a, b):  # IEEE fmax: a NaN operand is dropped
    if math.isnan(b):
        return a
    if math.isnan(a):
        return b
    return a if a > b else b


def _fmin(a, b):
    if math.isnan(b):
        return a
    if math.isnan(a):
        return b
    return a if a < b else b


def to_fixed(x) -> int:
    """float32 level (already clamped to [0, 64]) -> unsigned 16.16 fixed point, nearest, ties to even."""
    return int(round(float(x) * 65536.0))


def process_levels(outer, inner, spacing: str):
    """Clamp, round and convert the levels (rules 2-6).

    Returns ``None`` for a culled patch, else ``(fx, odd, minimal)``: six 16.16 fixed-point levels
    (outer[0..3], inner[0..1]), six parity flags (True = odd) and whether the patch is the minimal
    unit quad.
    """
    o = [np.float32(x) for x in outer]
    i = [np.float32(x) for x in inner]
    if any(not (x > 0) for x in o):
        return None
    integer = spacing == "equal"
    lo, hi = {"equal": (1.0, 64.0), "fractional_even": (2.0, 64.0), "fractional_odd": (1.0, 63.0)}[spacing]
    lo, hi = np.float32(lo), np.float32(hi)
    o = [_fmin(hi, _fmax(lo, x)) for x in o]
    if integer:
        o = [np.float32(math.ceil(x)) for x in o]
    lo_in = lo
    if spacing == "fractional_odd" and any(x > _ONE_PLUS_HALF_EPS for x in o + i):
        lo_in = np.float32(lo + _EPS)
    i = [_fmin(hi, _fmax(lo_in, x)) for x in i]
    if integer:
        i = [np.float32(math.ceil(x)) for x in i]
    if integer:
        odd = [int(x) % 2 == 1 for x in o] + [int(x) % 2 == 1 and x != 1 for x in i]
    else:
        odd = [spacing == "fractional_odd"] * 6
    fx = [to_fixed(x) for x in o + i]
    minimal = (integer or spacing == "fractional_odd") and all(f == FXP_ONE for f in fx)
    return fx, odd, minimal


# ------------------------------------------------------------------------------------------------
# one edge: fixed-point point placement (rule 7)
# ------------------------------------------------------------------------------------------------


def _remove_msb(v: int) -> int:
    return v & ~(1 << (v.bit_length() - 1)) if v > 0 else 0


def _ceil(x: int) -> int:
    return (x & _INT_MASK) + FXP_ONE if x & _FRAC_MASK else x


def num_points(fx: int, odd: bool) -> int:
    """Number of partition points (including both ends) of an edge with level ``fx`` (16.16)."""
    if odd:
        return (_ceil(FXP_HALF + (fx + 1) // 2) * 2) >> 16
    return ((_ceil((fx + 1) // 2) * 2) >> 16) + 1


def context(fx: int, odd: bool):
    """(half-level fraction, number of half points, split point, 1/floor segments, 1/ceil segments)."""
    half = (fx + 1) // 2
    if odd or half == FXP_HALF:
        half += FXP_HALF
    fl = half & _INT_MASK
    ce = _ceil(half)
    frac = half - fl
    nhalf = ce >> 16
    if ce == fl:
        split = nhalf + 1
    elif odd:
        split = 0 if fl == FXP_ONE else (_remove_msb((fl >> 16) - 1) << 1) + 1
    else:
        split = (_remove_msb(fl >> 16) << 1) + 1
    nfs = (fl * 2) >> 16
    ncs = (ce * 2) >> 16
    if odd:
        nfs -= 1
        ncs -= 1
    return frac, nhalf, split, RECIPROCAL[nfs], RECIPROCAL[ncs]


def place(fx: int, odd: bool, point: int) -> int:
    """16.16 position in [0, 1] of partition point ``point`` of an edge with level ``fx``."""
    frac, nhalf, split, inv_f, inv_c = context(fx, odd)
    flip = point >= nhalf
    if flip:
        point = 2 * nhalf - point - (1 if odd else 0)
    if point == nhalf:
        return FXP_HALF
    idx_f = point - 1 if point > split else point
    loc = (idx_f * inv_f * (FXP_ONE - frac) + point * inv_c * frac + FXP_HALF) >> 16
    return FXP_ONE - loc if flip else loc


# ------------------------------------------------------------------------------------------------
# the patch
# ------------------------------------------------------------------------------------------------


class _Layout:
    """Point counts and the index of point k on edge e of ring r (rings as the reference stores them)."""

    def __init__(self, fx, odd):
        self.fx, self.odd = fx, odd
        self.n_out = [num_points(fx[e], odd[e]) for e in range(4)]
        self.n_in = [max(4 if odd[4 + a] else 3, num_points(fx[4 + a], odd[4 + a])) for a in range(2)]

    def counts(self, r: int):
        if r == 0:
            return self.n_out
        mu, mv = self.n_in[0] - 2 * r, self.n_in[1] - 2 * r
        return [mv, mu, mv, mu]

    def base(self, r: int) -> int:
        if r == 0:
            return 0
        nu, nv = self.n_in
        return sum(self.n_out) - 4 + (r - 1) * (2 * nu + 2 * nv - 4 - 4 * r)

    def index(self, r: int, e: int, k: int) -> int:
        m = self.counts(r)
        b = self.base(r)
        if r > 0 and m[1] == 1:  # u collapsed: a column at u=0.5, stored with v decreasing
            c = m[0]
            return b + (k, c - 1, c - 1 - k, 0)[e]
        if r > 0 and m[0] == 1:  # v collapsed: a row at v=0.5, stored with u increasing
            c = m[1]
            return b + (0, k, c - 1, c - 1 - k)[e]
        if e == 3 and k == m[3] - 1:
            return b
        return b + sum(m[j] - 1 for j in range(e)) + k


def _points(lay: _Layout) -> list[tuple[int, int]]:
    fx, odd = lay.fx, lay.odd
    pts = []
    for e in range(4):  # outer ring
        end = lay.n_out[e] - 1
        for p in range(end):
            q = p if e in (1, 2) else end - p
            t = place(fx[e], odd[e], q)
            pts.append((t, FXP_ONE if e == 3 else 0) if e & 1 else (FXP_ONE if e == 2 else 0, t))
    nu, nv = lay.n_in
    n_rings = min(nu, nv) >> 1
    for ring in range(1, n_rings):  # inner rings
        end = (nu - 1 - ring, nv - 1 - ring)
        for e in range(4):
            along, perp = (e + 1) & 1, e & 1
            tp = place(fx[4 + perp], odd[4 + perp], ring if e < 2 else end[perp])
            for p in range(ring, end[along]):
                q = p if e in (1, 2) else end[along] - (p - ring)
                t = place(fx[4 + along], odd[4 + along], q)
                pts.append((tp, t) if along else (t, tp))
    if nu > nv and not odd[5]:  # degenerate centre row
        for p in range(n_rings, nu - n_rings):
            pts.append((place(fx[4], odd[4], p), FXP_HALF))
    elif nv >= nu and not odd[4]:  # degenerate centre column, v decreasing
        for p in range(nv - 1 - n_rings, n_rings - 1, -1):
            pts.append((FXP_HALF, place(fx[5], odd[5], p)))
    return pts


def _stitch_transition(tris, out_idx, in_idx, in_half, in_odd, out_half, out_odd):
    if in_odd:
        in_half -= 1
    if out_odd:
        out_half -= 1
    o = i = 0

    def adv_out():
        nonlocal o
        tris.append((out_idx(o), out_idx(o + 1), in_idx(i)))
        o += 1

    def adv_in():
        nonlocal i
        tris.append((in_idx(i), out_idx(o), in_idx(i + 1)))
        i += 1

    if FINAL_POINT_POSITION[0] < out_half:
        adv_out()
    for k in range(1, 33):
        if FINAL_POINT_POSITION[k] < in_half:
            adv_in()
        if FINAL_POINT_POSITION[k] < out_half:
            adv_out()
    if in_odd != out_odd or in_odd:
        if in_odd == out_odd:  # quad in the middle
            tris.append((in_idx(i), out_idx(o), in_idx(i + 1)))
            tris.append((in_idx(i + 1), out_idx(o), out_idx(o + 1)))
            i += 1
            o += 1
        elif not in_odd:  # triangle pointing inside
            adv_out_only = (in_idx(i), out_idx(o), out_idx(o + 1))
            tris.append(adv_out_only)
            o += 1
        else:  # triangle pointing outside
            adv_in()
    for k in range(32, 0, -1):
        if FINAL_POINT_POSITION[k] < out_half:
            adv_out()
        if FINAL_POINT_POSITION[k] < in_half:
            adv_in()
    if FINAL_POINT_POSITION[0] < out_half:
        adv_out()


_MIRRORED, _IN_TO_OUT, _IN_TO_OUT_EXCEPT_MIDDLE = 0, 1, 2


def _stitch_regular(tris, trapezoid, diagonals, n_in, out_idx, in_idx):
    o = i = 0
    if trapezoid:
        tris.append((out_idx(o), out_idx(o + 1), in_idx(i)))
        o += 1

    def io():  # diagonal inside -> next outside
        tris.append((in_idx(i), out_idx(o), out_idx(o + 1)))
        tris.append((in_idx(i), out_idx(o + 1), in_idx(i + 1)))

    def oi():  # diagonal outside -> next inside
        tris.append((out_idx(o), in_idx(i + 1), in_idx(i)))
        tris.append((out_idx(o), out_idx(o + 1), in_idx(i + 1)))

    for p in range(n_in - 1):
        if diagonals == _MIRRORED:
            (oi if p < n_in // 2 else io)()
        elif diagonals == _IN_TO_OUT_EXCEPT_MIDDLE and p == n_in // 2 - 1:
            oi()
        else:
            io()
        i += 1
        o += 1
    if trapezoid:
        tris.append((out_idx(o), out_idx(o + 1), in_idx(i)))


def _connectivity(lay: _Layout) -> list[tuple[int, int, int]]:
    odd = lay.odd
    nu, nv = lay.n_in
    n_rings = min((nu + 1) >> 1, (nv + 1) >> 1)
    tris: list[tuple[int, int, int]] = []
    for ring in range(1, n_rings):
        m_in = lay.counts(ring)
        for e in range(4):
            axis = (e + 1) & 1

            def out_idx(k, r=ring - 1, e=e):
                return lay.index(r, e, k)

            def in_idx(k, r=ring, e=e):
                return lay.index(r, e, k)

            if ring == 1:
                _stitch_transition(tris, out_idx, in_idx,
                                   context(lay.fx[4 + axis], odd[4 + axis])[1], odd[4 + axis],
                                   context(lay.fx[e], odd[e])[1], odd[e])
            else:
                _stitch_regular(tris, True, _MIRRORED, m_in[e], out_idx, in_idx)
    r = n_rings - 1
    m = lay.counts(r)
    if nu > nv and odd[5]:  # centre strip along u: v_lo row (edge 1) to v_hi row (edge 3 reversed)
        c = m[1]
        _stitch_regular(tris, False, _IN_TO_OUT, c, lambda k: lay.index(r, 1, k),
                        lambda k: lay.index(r, 3, c - 1 - k))
    elif nv >= nu and odd[4]:  # centre strip along v: u_lo column (edge 0) to u_hi column (edge 2 reversed)
        c = m[0]
        _stitch_regular(tris, False, _IN_TO_OUT if not odd[5] else _IN_TO_OUT_EXCEPT_MIDDLE, c,
                        lambda k: lay.index(r, 0, k), lambda k: lay.index(r, 2, c - 1 - k))
    return tris


def check_spacing(spacing: str) -> None:
    check_choice("spacing", spacing, SPACINGS)


def _check_levels(outer, inner) -> tuple[np.ndarray, np.ndarray]:
    try:
        o = np.asarray(outer, dtype=np.float32).reshape(-1)
        i = np.asarray(inner, dtype=np.float32).reshape(-1)
    except (TypeError, ValueError) as e:
        raise TypeError(f"outer, inner: expected numbers, got {outer!r}, {inner!r}") from e
    if o.size != 4:
        raise ValueError(f"outer: expected 4 levels, got {o.size}")
    if i.size != 2:
        raise ValueError(f"inner: expected 2 levels, got {i.size}")
    return o, i


def patch_counts(outer, inner, spacing: str) -> tuple[int, int]:
    """(number of domain points, number of triangles) of one patch, from the layout alone (what the
    count kernel computes)."""
    check_spacing(spacing)
    proc = process_levels(*_check_levels(outer, inner), spacing)
    if proc is None:
        return 0, 0
    fx, odd, minimal = proc
    if minimal:
        return 4, 2
    lay = _Layout(fx, odd)
    nu, nv = lay.n_in
    n_rings = min((nu + 1) >> 1, (nv + 1) >> 1)
    tris = sum(lay.n_out[e] + lay.counts(1)[e] - 2 for e in range(4))
    tris += sum(2 * lay.counts(r)[e] for r in range(2, n_rings) for e in range(4))
    last = lay.counts(n_rings - 1)
    if nu > nv and odd[5]:
        tris += 2 * (last[1] - 1)
    elif nv >= nu and odd[4]:
        tris += 2 * (last[0] - 1)
    return sum(lay.n_out) - 4 + (nu - 2) * (nv - 2), tris


def reference_tessellate_patch(outer, inner, spacing: str) -> tuple[np.ndarray, np.ndarray]:
    """Tessellate one quad patch as the GPU's fixed-function tessellator does: the pure-Python reference that
    :func:`terrainwarp.rendering.tessellate_patches` (one Warp launch for a whole frame) is tested against.

    Args:
        outer: 4 outer levels in ``gl_TessLevelOuter`` order (u=0, v=0, u=1, v=1 edges), float32.
        inner: 2 inner levels (along u, along v), float32.
        spacing: ``"equal"``, ``"fractional_even"`` or ``"fractional_odd"``.

    Returns:
        uv: (n, 2) float32 domain coordinates in [0, 1], each a multiple of 2^-16 (exact).
        triangles: (m, 3) int32 indices into ``uv``, counter-clockwise in the (u right, v up) domain
        (GL's ``ccw``). A culled patch (an outer level <= 0 or NaN) gives n = m = 0.
    """
    check_spacing(spacing)
    o, i = _check_levels(outer, inner)
    proc = process_levels(o, i, spacing)
    if proc is None:
        return np.zeros((0, 2), np.float32), np.zeros((0, 3), np.int32)
    fx, odd, minimal = proc
    if minimal:
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        return uv, np.array([[0, 1, 3], [1, 2, 3]], np.int32)
    lay = _Layout(fx, odd)
    pts = _points(lay)
    tris = _connectivity(lay)
    uv = np.asarray(pts, dtype=np.float64).reshape(-1, 2) / FXP_ONE
    return uv.astype(np.float32), np.asarray(tris, dtype=np.int32).reshape(-1, 3)


# ------------------------------------------------------------------------------------------------
# picture and JSON (the `terrainwarp tessellate` command)
# ------------------------------------------------------------------------------------------------


def tessellation_json(outer, inner, spacing: str) -> dict:
    """One patch as a JSON-ready dict: levels, spacing, points (u, v) and triangles (ccw indices)."""
    uv, tri = reference_tessellate_patch(outer, inner, spacing)
    lv = lambda a: [None if not np.isfinite(x) else float(x) for x in np.asarray(a, np.float32)]  # noqa: E731
    return {"outer": lv(outer), "inner": lv(inner), "spacing": spacing, "n_points": int(uv.shape[0]),
            "n_triangles": int(tri.shape[0]), "points": uv.tolist(), "triangles": tri.tolist()}


def write_tessellation_picture(path: str | Path, outer, inner, spacing: str, size_px: int = 800) -> Path:
    """Draw the domain triangulation of one patch (u right, v up) to a PNG; returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: heavy optional dependency
    from matplotlib.figure import Figure

    uv, tri = reference_tessellate_patch(outer, inner, spacing)
    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    o = ", ".join(f"{x:g}" for x in np.asarray(outer, np.float32))
    i = ", ".join(f"{x:g}" for x in np.asarray(inner, np.float32))
    ax.set_title(f"{spacing}: outer [{o}], inner [{i}]\n{uv.shape[0]} points, {tri.shape[0]} triangles")
    if tri.shape[0]:
        ax.triplot(uv[:, 0], uv[:, 1], tri, color="#1f4e79", linewidth=0.6)
        ax.plot(uv[:, 0], uv[:, 1], "o", color="#c0392b", markersize=2)
    else:
        ax.text(0.5, 0.5, "patch discarded (an outer level <= 0 or NaN)", ha="center", va="center")
    for label, xy in (("outer[0] (u=0)", (-0.06, 0.5)), ("outer[1] (v=0)", (0.5, -0.06)),
                      ("outer[2] (u=1)", (1.06, 0.5)), ("outer[3] (v=1)", (0.5, 1.06))):
        ax.text(*xy, label, ha="center", va="center", fontsize=8, color="#555555",
                rotation=90 if xy[1] == 0.5 else 0)
    ax.set_xlim(-0.12, 1.12)
    ax.set_ylim(-0.12, 1.12)
    ax.set_aspect("equal")
    ax.set_xlabel("u")
    ax.set_ylabel("v")
    return save_figure(fig, path, dpi=100)


def __getattr__(name: str):
    if name == "tessellate_patch":  # the name before it said that it is the reference
        warnings.warn("terrainwarp.rendering.reference_tessellator.tessellate_patch is deprecated and goes in the "
                      "next release; use reference_tessellate_patch", DeprecationWarning, stacklevel=2)
        return reference_tessellate_patch
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
