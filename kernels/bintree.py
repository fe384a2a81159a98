"""Right-triangle bisection tree (MRBSP, mrbsp-lod-visibility.txt sections 2-3) on the device.

The tree is stored as a heap: node ``g`` at level ``L`` (``2**L - 1 <= g < 2**(L+1) - 1``) has children
``2g + 1`` and ``2g + 2``; node 0 is the root square, level 1 its two triangles. A triangle is three
vertex ids ``(apex, b0, b1)`` on an integer grid of ``(G + 1) x (G + 1)`` points (id ``gz * (G + 1) +
gx``), the apex is the right angle and ``(apex, b0, b1)`` is counter-clockwise seen from above (+y).
Splitting from the apex to the hypotenuse midpoint ``c`` gives ``(c, apex, b0)`` and ``(c, b1, apex)``,
both counter-clockwise again.

Kernels, one launch per level (never a loop over nodes):

* vertex heights: per grid point, from the heightmap by the paper's "three closest samples" (the
  plane through the three of the four surrounding samples nearest to the point; the farthest is
  dropped, ties broken in the fixed order (1,1), (0,0), (0,1), (1,0)) or bilinear; clamp to edge.
* split: the children of every node of a level.
* links: the base neighbour (the node of the same level sharing the hypotenuse, -1 on the border)
  through a dense map keyed by the hypotenuse midpoint and direction.
* bounds: per node min/max height of its subtree, bottom-up.
* selection, per frame: per-vertex LOD thresholds ``ceil(M - log2(D / S))`` clamped to [1, M]; per
  level the split/cull flags of every node; the forced-split propagation (ROAM: a split node's base
  neighbour is split too) as a fixed-point iteration; the leaves by count -> scan -> emit; the mesh
  with vertex compaction by mark -> scan -> emit.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .sampling import sample_bilinear

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------

HEIGHT_METHODS = {"nearest3": 0, "bilinear": 1}


@wp.func
def _fetch(h: wp.array2d(dtype=wp.float32), i: int, j: int) -> float:
    return h[wp.clamp(i, 0, h.shape[0] - 1), wp.clamp(j, 0, h.shape[1] - 1)]


@wp.func
def _nearest3(h: wp.array2d(dtype=wp.float32), u: float, v: float) -> float:
    """Plane through the three of the four samples around (u, v) closest to it (clamped to the grid)."""
    uc = wp.clamp(u, 0.0, float(h.shape[1] - 1))
    vc = wp.clamp(v, 0.0, float(h.shape[0] - 1))
    j0 = wp.clamp(int(wp.floor(uc)), 0, wp.max(h.shape[1] - 2, 0))
    i0 = wp.clamp(int(wp.floor(vc)), 0, wp.max(h.shape[0] - 2, 0))
    fu = uc - float(j0)
    fv = vc - float(i0)
    h00 = _fetch(h, i0, j0)
    h10 = _fetch(h, i0, j0 + 1)  # (u+1, v)
    h01 = _fetch(h, i0 + 1, j0)  # (u, v+1)
    h11 = _fetch(h, i0 + 1, j0 + 1)
    r = float(0.0)
    if fu <= 0.5 and fv <= 0.5:  # (1,1) farthest
        r = h00 + fu * (h10 - h00) + fv * (h01 - h00)
    elif fu >= 0.5 and fv >= 0.5:  # (0,0) farthest
        r = h11 + (1.0 - fu) * (h01 - h11) + (1.0 - fv) * (h10 - h11)
    elif fu >= 0.5:  # (0,1) farthest: triangle (0,0), (1,0), (1,1)
        r = h00 + fu * (h10 - h00) + fv * (h11 - h10)
    else:  # (1,0) farthest: triangle (0,0), (0,1), (1,1)
        r = h00 + fv * (h01 - h00) + fu * (h11 - h01)
    return r


# ------------------------------------------------------------------------------------------------
# kernels: build
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _heights_kernel(h: wp.array2d(dtype=wp.float32), g1: int, x0: float, z0: float, step: float, ox: float,
                    oz: float, dx: float, dz: float, method: int,
                    # outputs
                    out_h: wp.array(dtype=wp.float32)):
    t = wp.tid()
    gz = t / g1
    gx = t - gz * g1
    u = (x0 + float(gx) * step - ox) / dx
    v = (z0 + float(gz) * step - oz) / dz
    if method == 0:
        out_h[t] = _nearest3(h, u, v)
    else:
        out_h[t] = sample_bilinear(h, u, v)


@wp.kernel(enable_backward=False)
def _split_kernel(off: int, g1: int,
                  # outputs (read at level L, written at level L + 1)
                  out_apex: wp.array(dtype=wp.int32), out_b0: wp.array(dtype=wp.int32),
                  out_b1: wp.array(dtype=wp.int32)):
    k = wp.tid()
    g = off + k
    a = out_apex[g]
    p = out_b0[g]
    q = out_b1[g]
    pz = p / g1
    qz = q / g1
    cx = (p - pz * g1 + q - qz * g1) / 2
    cz = (pz + qz) / 2
    c = cz * g1 + cx
    l = 2 * g + 1
    out_apex[l] = c
    out_b0[l] = a
    out_b1[l] = p
    out_apex[l + 1] = c
    out_b0[l + 1] = q
    out_b1[l + 1] = a


@wp.func
def _mid_slot(p: int, q: int, g1: int) -> int:
    pz = p / g1
    qz = q / g1
    c = ((pz + qz) / 2) * g1 + (p - pz * g1 + q - qz * g1) / 2
    s = int(0)
    if p > q:
        s = 1
    return 2 * c + s


@wp.kernel(enable_backward=False)
def _link_write_kernel(off: int, g1: int, b0: wp.array(dtype=wp.int32), b1: wp.array(dtype=wp.int32),
                       # outputs
                       out_map: wp.array(dtype=wp.int32)):
    g = off + wp.tid()
    out_map[_mid_slot(b0[g], b1[g], g1)] = g


@wp.kernel(enable_backward=False)
def _link_read_kernel(off: int, g1: int, b0: wp.array(dtype=wp.int32), b1: wp.array(dtype=wp.int32),
                      slots: wp.array(dtype=wp.int32),
                      # outputs
                      out_bn: wp.array(dtype=wp.int32)):
    g = off + wp.tid()
    out_bn[g] = slots[_mid_slot(b1[g], b0[g], g1)]  # the same edge traversed the other way


@wp.kernel(enable_backward=False)
def _bounds_leaf_kernel(off: int, apex: wp.array(dtype=wp.int32), b0: wp.array(dtype=wp.int32),
                        b1: wp.array(dtype=wp.int32), vh: wp.array(dtype=wp.float32),
                        # outputs
                        out_lo: wp.array(dtype=wp.float32), out_hi: wp.array(dtype=wp.float32)):
    g = off + wp.tid()
    ha = vh[apex[g]]
    h0 = vh[b0[g]]
    h1 = vh[b1[g]]
    out_lo[g] = wp.min(ha, wp.min(h0, h1))
    out_hi[g] = wp.max(ha, wp.max(h0, h1))


@wp.kernel(enable_backward=False)
def _bounds_up_kernel(off: int,
                      # outputs (children read, parents written)
                      out_lo: wp.array(dtype=wp.float32), out_hi: wp.array(dtype=wp.float32)):
    g = off + wp.tid()
    out_lo[g] = wp.min(out_lo[2 * g + 1], out_lo[2 * g + 2])
    out_hi[g] = wp.max(out_hi[2 * g + 1], out_hi[2 * g + 2])


# ------------------------------------------------------------------------------------------------
# kernels: selection
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _threshold_kernel(vh: wp.array(dtype=wp.float32), g1: int, rx0: float, rz0: float, step: float, eye_y: float,
                      max_level: int, inv_s: float,
                      # outputs
                      out_t: wp.array(dtype=wp.int32)):
    t = wp.tid()
    gz = t / g1
    gx = t - gz * g1
    d = wp.length(wp.vec3(rx0 + float(gx) * step, vh[t] - eye_y, rz0 + float(gz) * step))
    r = max_level
    x = d * inv_s
    if x > 1.0:  # M - log2(D / S) < M
        r = int(wp.ceil(float(max_level) - wp.log2(x)))
    out_t[t] = wp.clamp(r, 1, max_level)


@wp.kernel(enable_backward=False)
def _select_level_kernel(off: int, level: int, max_level: int, mode: int, hole_fix: int, g1: int,
                         rx0: float, rz0: float, step: float, eye_y: float,
                         apex: wp.array(dtype=wp.int32), b0: wp.array(dtype=wp.int32), b1: wp.array(dtype=wp.int32),
                         vt: wp.array(dtype=wp.int32), lo: wp.array(dtype=wp.float32),
                         hi: wp.array(dtype=wp.float32), planes: wp.array(dtype=wp.vec4), use_frustum: int,
                         vis: wp.array(dtype=wp.uint8), use_vis: int,
                         # outputs (parents read, this level written)
                         out_split: wp.array(dtype=wp.int32), out_cull: wp.array(dtype=wp.int32)):
    g = off + wp.tid()
    par = (g - 1) / 2
    c = out_cull[par]
    a = apex[g]
    p = b0[g]
    q = b1[g]
    if c == 0 and use_frustum != 0:
        az = a / g1
        pz = p / g1
        qz = q / g1
        ax = a - az * g1
        px = p - pz * g1
        qx = q - qz * g1
        xmin = rx0 + float(wp.min(ax, wp.min(px, qx))) * step
        xmax = rx0 + float(wp.max(ax, wp.max(px, qx))) * step
        zmin = rz0 + float(wp.min(az, wp.min(pz, qz))) * step
        zmax = rz0 + float(wp.max(az, wp.max(pz, qz))) * step
        ymin = lo[g] - eye_y
        ymax = hi[g] - eye_y
        for i in range(6):
            pl = planes[i]
            vx = wp.where(pl[0] > 0.0, xmax, xmin)
            vy = wp.where(pl[1] > 0.0, ymax, ymin)
            vz = wp.where(pl[2] > 0.0, zmax, zmin)
            if pl[0] * vx + pl[1] * vy + pl[2] * vz + pl[3] < 0.0:
                c = 1
    if c == 0 and use_vis != 0:
        if vis[g] == wp.uint8(0):
            c = 1
    out_cull[g] = c
    s = int(0)
    if out_split[par] != 0 and c == 0 and level < max_level:
        if mode == 0:
            s = 1
        else:
            ta = vt[a]
            t0 = vt[p]
            t1 = vt[q]
            tmin = wp.min(ta, wp.min(t0, t1))
            if level < tmin:
                s = 1
            elif hole_fix != 0 and ta < t0 and ta < t1:  # paper: the right angle alone is coarser
                s = 1
    out_split[g] = s


@wp.kernel(enable_backward=False)
def _propagate_kernel(bn: wp.array(dtype=wp.int32),
                      # outputs
                      out_split: wp.array(dtype=wp.int32), out_changed: wp.array(dtype=wp.int32)):
    g = wp.tid() + 1
    if out_split[g] != 0:
        n = bn[g]
        if n >= 0:
            if out_split[n] == 0:
                wp.atomic_add(out_changed, 0, 1)
                out_split[n] = 1
                a = n
                while a > 0:
                    a = (a - 1) / 2
                    out_split[a] = 1


@wp.kernel(enable_backward=False)
def _leaf_flag_kernel(split: wp.array(dtype=wp.int32), cull: wp.array(dtype=wp.int32),
                      # outputs
                      out_flag: wp.array(dtype=wp.int32)):
    g = wp.tid() + 1
    f = int(0)
    if split[(g - 1) / 2] != 0 and split[g] == 0 and cull[g] == 0:
        f = 1
    out_flag[g - 1] = f


@wp.kernel(enable_backward=False)
def _leaf_emit_kernel(flag: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32),
                      apex: wp.array(dtype=wp.int32), b0: wp.array(dtype=wp.int32), b1: wp.array(dtype=wp.int32),
                      # outputs
                      out_node: wp.array(dtype=wp.int32), out_tri: wp.array(dtype=wp.int32),
                      out_used: wp.array(dtype=wp.int32)):
    k = wp.tid()
    if flag[k] != 0:
        g = k + 1
        i = start[k]
        out_node[i] = g
        out_tri[3 * i + 0] = apex[g]
        out_tri[3 * i + 1] = b0[g]
        out_tri[3 * i + 2] = b1[g]
        out_used[apex[g]] = 1  # idempotent writes: order-independent
        out_used[b0[g]] = 1
        out_used[b1[g]] = 1


@wp.kernel(enable_backward=False)
def _vertex_emit_kernel(used: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32),
                        vh: wp.array(dtype=wp.float32), g1: int, rx0: float, rz0: float, step: float, eye_y: float,
                        # outputs
                        out_pos: wp.array(dtype=wp.vec3), out_grid: wp.array(dtype=wp.int32)):
    t = wp.tid()
    if used[t] != 0:
        gz = t / g1
        gx = t - gz * g1
        i = start[t]
        out_pos[i] = wp.vec3(rx0 + float(gx) * step, vh[t] - eye_y, rz0 + float(gz) * step)
        out_grid[i] = t


@wp.kernel(enable_backward=False)
def _remap_kernel(start: wp.array(dtype=wp.int32),
                  # outputs
                  out_tri: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out_tri[i] = start[out_tri[i]]


# ------------------------------------------------------------------------------------------------
# host drivers
# ------------------------------------------------------------------------------------------------


def build_tree(heights: np.ndarray, origin: tuple[float, float], spacing: tuple[float, float],
               x0: float, z0: float, side: float, depth: int, method: str = "nearest3",
               device: str = "cpu") -> dict[str, np.ndarray]:
    """Build the whole tree to ``depth`` levels, one launch per level and stage.

    Args:
        heights: (H, W) float32 heightmap, row i along +z, column j along +x.
        origin, spacing: world (x, z) of sample (0, 0) and (dx, dz).
        x0, z0, side: the root square [x0, x0 + side] x [z0, z0 + side] in world metres.
        depth: M >= 1, the deepest level (2**M triangles).
        method: ``"nearest3"`` (paper) or ``"bilinear"`` vertex heights.

    Returns:
        dict with ``apex``, ``b0``, ``b1``: (2**(M+1) - 1,) int32 grid vertex ids per heap node (-1 for
        the root square); ``base_neighbour``: (same,) int32 (-1 on the border and for the root);
        ``lo``, ``hi``: (same,) float32 subtree height bounds; ``vertex_height``: ((G+1)**2,) float32;
        ``grid``: G = 2**floor(M/2) cells per side of the vertex grid.
    """
    if method not in HEIGHT_METHODS:
        raise ValueError(f"method: expected one of {list(HEIGHT_METHODS)}, got {method!r}")
    m = int(depth)
    grid = 1 << (m // 2)
    g1 = grid + 1
    n = (1 << (m + 1)) - 1
    step = float(side) / grid
    h = wp.array(np.ascontiguousarray(heights, np.float32), dtype=wp.float32, device=device)
    vh = wp.empty(g1 * g1, dtype=wp.float32, device=device)
    wp.launch(_heights_kernel, dim=g1 * g1, inputs=[h, g1, float(x0), float(z0), step, float(origin[0]),
                                                     float(origin[1]), float(spacing[0]), float(spacing[1]),
                                                     HEIGHT_METHODS[method]], outputs=[vh], device=device)
    init = np.full(n, -1, np.int32)
    c00, c10, c01, c11 = 0, grid, grid * g1, grid * g1 + grid
    apex0, b00, b10 = init.copy(), init.copy(), init.copy()
    apex0[1], b00[1], b10[1] = c10, c00, c11  # the root square's diagonal (0,0)-(G,G)
    apex0[2], b00[2], b10[2] = c01, c11, c00
    apex, b0, b1 = (wp.array(a, dtype=wp.int32, device=device) for a in (apex0, b00, b10))
    bn = wp.array(init, dtype=wp.int32, device=device)
    slots = wp.empty(2 * g1 * g1, dtype=wp.int32, device=device)
    for level in range(1, m + 1):
        off = (1 << level) - 1
        cnt = 1 << level
        if level < m:
            wp.launch(_split_kernel, dim=cnt, inputs=[off, g1], outputs=[apex, b0, b1], device=device)
        slots.fill_(-1)
        wp.launch(_link_write_kernel, dim=cnt, inputs=[off, g1, b0, b1], outputs=[slots], device=device)
        wp.launch(_link_read_kernel, dim=cnt, inputs=[off, g1, b0, b1, slots], outputs=[bn], device=device)
    lo = wp.zeros(n, dtype=wp.float32, device=device)
    hi = wp.zeros(n, dtype=wp.float32, device=device)
    off = (1 << m) - 1
    wp.launch(_bounds_leaf_kernel, dim=1 << m, inputs=[off, apex, b0, b1, vh], outputs=[lo, hi], device=device)
    for level in range(m - 1, -1, -1):
        wp.launch(_bounds_up_kernel, dim=1 << level, inputs=[(1 << level) - 1], outputs=[lo, hi], device=device)
    return {"apex": apex, "b0": b0, "b1": b1, "base_neighbour": bn, "lo": lo, "hi": hi, "vertex_height": vh,
            "grid": grid}


def select_nodes(tree: dict, depth: int, rel_origin: tuple[float, float], step: float, eye_y: float,
                 short_side: float, *, mode: int, hole_fix: bool, propagate: bool,
                 planes: np.ndarray | None, vis: np.ndarray | None, device: str = "cpu") -> dict:
    """One frame's selection: thresholds, per-level split/cull flags, optional forced splits, the leaves
    and the compacted mesh.

    Args:
        tree: :func:`build_tree`'s output.
        rel_origin: (x0 - eye_x, z0 - eye_z), the root square's corner relative to the eye (float64 on the
            host, cast once). eye_y: the eye's height. step: grid spacing in metres.
        short_side: S, the leg of a level-M triangle, metres.
        mode: 0 every node to depth M (brute force), 1 the LOD rule.
        hole_fix: the paper's rule (split a triangle whose right-angle vertex alone has the lowest threshold).
        propagate: forced split propagation (a split node's base neighbour is split) until stable.
        planes: (6, 4) float32 camera-relative frustum planes, or None for no culling.
        vis: (2**(M+1) - 1,) uint8 per-node visibility (0 = hidden: culled with its subtree), or None.

    Returns:
        dict: ``node`` (m,) int32 heap index per triangle; ``positions`` (n, 3) float32 camera-relative;
        ``triangles`` (m, 3) int32 ccw from above; ``grid_id`` (n,) int32 grid vertex id per vertex;
        ``forced`` number of forced splits; ``iterations`` of the propagation.
    """
    m = int(depth)
    g1 = tree["grid"] + 1
    n = (1 << (m + 1)) - 1
    rx0, rz0 = float(rel_origin[0]), float(rel_origin[1])
    vt = wp.empty(g1 * g1, dtype=wp.int32, device=device)
    wp.launch(_threshold_kernel, dim=g1 * g1,
              inputs=[tree["vertex_height"], g1, rx0, rz0, float(step), float(eye_y), m, 1.0 / float(short_side)],
              outputs=[vt], device=device)
    split = wp.zeros(n, dtype=wp.int32, device=device)
    cull = wp.zeros(n, dtype=wp.int32, device=device)
    split.fill_(0)
    wp.copy(split, wp.array([1], dtype=wp.int32, device=device), 0, 0, 1)  # the root square is always split
    pl = wp.array(planes if planes is not None else np.zeros((6, 4), np.float32), dtype=wp.vec4, device=device)
    va = wp.array(vis if vis is not None else np.zeros(1, np.uint8), dtype=wp.uint8, device=device)
    for level in range(1, m + 1):
        wp.launch(_select_level_kernel, dim=1 << level,
                  inputs=[(1 << level) - 1, level, m, int(mode), int(bool(hole_fix)), g1, rx0, rz0, float(step),
                          float(eye_y), tree["apex"], tree["b0"], tree["b1"], vt, tree["lo"], tree["hi"], pl,
                          int(planes is not None), va, int(vis is not None)],
                  outputs=[split, cull], device=device)
    forced = 0
    iters = 0
    if propagate:
        changed = wp.zeros(1, dtype=wp.int32, device=device)
        while True:
            changed.zero_()
            wp.launch(_propagate_kernel, dim=n - 1, inputs=[tree["base_neighbour"]], outputs=[split, changed],
                      device=device)
            iters += 1
            c = int(changed.numpy()[0])
            forced += c
            if c == 0:
                break
    flag = wp.empty(n - 1, dtype=wp.int32, device=device)
    wp.launch(_leaf_flag_kernel, dim=n - 1, inputs=[split, cull], outputs=[flag], device=device)
    start = wp.empty_like(flag)
    wp.utils.array_scan(flag, start, inclusive=False)
    fl, st = flag.numpy(), start.numpy()
    count = int(st[-1] + fl[-1])
    node = wp.empty(max(count, 1), dtype=wp.int32, device=device)
    tri = wp.empty(max(3 * count, 1), dtype=wp.int32, device=device)
    used = wp.zeros(g1 * g1, dtype=wp.int32, device=device)
    wp.launch(_leaf_emit_kernel, dim=n - 1, inputs=[flag, start, tree["apex"], tree["b0"], tree["b1"]],
              outputs=[node, tri, used], device=device)
    vstart = wp.empty_like(used)
    wp.utils.array_scan(used, vstart, inclusive=False)
    nv = int(vstart.numpy()[-1] + used.numpy()[-1])
    pos = wp.empty(max(nv, 1), dtype=wp.vec3, device=device)
    gid = wp.empty(max(nv, 1), dtype=wp.int32, device=device)
    wp.launch(_vertex_emit_kernel, dim=g1 * g1,
              inputs=[used, vstart, tree["vertex_height"], g1, rx0, rz0, float(step), float(eye_y)],
              outputs=[pos, gid], device=device)
    if count:
        wp.launch(_remap_kernel, dim=3 * count, inputs=[vstart], outputs=[tri], device=device)
    return {"node": node.numpy()[:count], "triangles": tri.numpy()[:3 * count].reshape(-1, 3),
            "positions": pos.numpy()[:nv].reshape(-1, 3), "grid_id": gid.numpy()[:nv], "forced": forced,
            "iterations": iters}
