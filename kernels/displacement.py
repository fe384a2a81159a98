"""Meshes displaced by the heightmap (the domain-shader side of the pipeline).

The full-resolution grid mesh: one vertex per sample, two counter-clockwise (seen from +y) triangles
per cell, split along the (i, j+1)-(i+1, j) diagonal. Positions are camera-relative: the host
subtracts the eye from the grid origin in float64, and the kernel adds ``j*dx`` and ``i*dz`` in float32
to that offset, so a terrain 10,000 km from the world origin is as precise as one at the origin.

No-data holes: a NaN height makes its vertex a hole. No triangle references a hole vertex (a cell
whose triangle touches one drops that triangle: count per cell, ``wp.utils.array_scan``, emit), so
holes render as background; the hole vertex itself stays in the vertex array (index ``i*W + j`` is
kept for every sample) so that every position is finite. It sits at the lowest finite height of the
mesh (:func:`hole_height`), never at height 0 or at the eye: a hole moves no bound and no height range
(the hypsometric tint's, a bounding box, an exported mesh's extent). :func:`drop_nonfinite_triangles`
applies the same rule to any displaced mesh (the LOD frame's).

Every launch goes through the parallel-launch helper (:func:`terrainwarp.kernels.parallel.launch`): the
outermost index range split across CPU threads, each chunk given its offset; results do not depend on the
thread count.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .parallel import empty, launch, scan, view


def hole_height(heights: np.ndarray) -> float:
    """Where a no-data hole's vertex sits: the lowest finite height (0.0 when there is none), so a vertex
    that no triangle uses lies inside the mesh's height range."""
    h = np.asarray(heights)
    fin = h[np.isfinite(h)]
    return float(fin.min()) if fin.size else 0.0


@wp.kernel(enable_backward=False)
def _grid_vertices_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    dx: float,
    dz: float,
    rel_origin: wp.vec3,
    fill: float,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
    out_uv: wp.array(dtype=wp.vec2),
):
    i, j = wp.tid()
    i += offset
    w = h.shape[1]
    k = i * w + j
    hv = h[i, j]
    if wp.isnan(hv):
        hv = fill  # a hole: no triangle uses this vertex; finite, inside the height range (hole_height)
    out_pos[k] = wp.vec3(rel_origin[0] + float(j) * dx, hv - rel_origin[1], rel_origin[2] + float(i) * dz)
    out_uv[k] = wp.vec2(float(j) / float(wp.max(w - 1, 1)), float(i) / float(wp.max(h.shape[0] - 1, 1)))


@wp.func
def write_quad(out_tri: wp.array2d(dtype=wp.int32), t: int, v00: int, v01: int, v10: int, v11: int):
    """Quad (v00, v01 one step along +x, v10 one step along +z, v11) as triangles t and t + 1 of the grid
    mesh's split: (v00, v10, v01), (v01, v10, v11), counter-clockwise seen from +y."""
    out_tri[t, 0] = v00
    out_tri[t, 1] = v10
    out_tri[t, 2] = v01
    out_tri[t + 1, 0] = v01
    out_tri[t + 1, 1] = v10
    out_tri[t + 1, 2] = v11


@wp.kernel(enable_backward=False)
def _grid_triangles_kernel(
    offset: int,
    w: int,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    i, j = wp.tid()  # cell (i, j)
    i += offset
    cells_w = w - 1
    t = 2 * (i * cells_w + j)
    v00 = i * w + j
    v01 = v00 + 1
    v10 = v00 + w
    write_quad(out_tri, t, v00, v01, v10, v10 + 1)


@wp.func
def _cell_tri_ok(h: wp.array2d(dtype=wp.float32), i: int, j: int, t: int) -> int:
    """1 if triangle t (0: v00-v10-v01, 1: v01-v10-v11) of cell (i, j) touches no NaN sample."""
    ok = int(1)
    if wp.isnan(h[i + 1, j]) or wp.isnan(h[i, j + 1]):
        ok = 0
    if t == 0 and wp.isnan(h[i, j]):
        ok = 0
    if t == 1 and wp.isnan(h[i + 1, j + 1]):
        ok = 0
    return ok


@wp.kernel(enable_backward=False)
def _hole_count_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    # outputs
    out_count: wp.array(dtype=wp.int32),
):
    i, j = wp.tid()  # cell (i, j)
    i += offset
    out_count[i * (h.shape[1] - 1) + j] = _cell_tri_ok(h, i, j, 0) + _cell_tri_ok(h, i, j, 1)


@wp.kernel(enable_backward=False)
def _hole_emit_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    start: wp.array(dtype=wp.int32),
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    i, j = wp.tid()  # cell (i, j)
    i += offset
    w = h.shape[1]
    t = start[i * (w - 1) + j]
    v00 = i * w + j
    v01 = v00 + 1
    v10 = v00 + w
    v11 = v10 + 1
    if _cell_tri_ok(h, i, j, 0) == 1:
        out_tri[t, 0] = v00
        out_tri[t, 1] = v10
        out_tri[t, 2] = v01
        t += 1
    if _cell_tri_ok(h, i, j, 1) == 1:
        out_tri[t, 0] = v01
        out_tri[t, 1] = v10
        out_tri[t, 2] = v11


def grid_mesh(heights: np.ndarray, dx: float, dz: float, rel_origin: tuple[float, float, float],
              device: str = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full-resolution grid mesh.

    Args:
        heights: (H, W) float32; NaN samples are no-data holes (no triangle touches them).
        rel_origin: (x0 - eye_x, eye_y, z0 - eye_z): grid origin relative to the eye, and the eye
            height (subtracted from every height).

    Returns:
        positions (H*W, 3) float32 camera-relative (a hole's vertex at :func:`hole_height`), uv (H*W, 2)
        float32 in [0, 1], triangles (m, 3) int32: m = 2*(H-1)*(W-1) without holes, fewer with them (cell
        order kept).
    """
    hh, ww = heights.shape
    holes = bool(np.isnan(heights).any())
    h = view(heights, wp.float32, device)  # the heightmap: not copied per frame on the CPU
    pos = empty(hh * ww, wp.vec3, device)
    uv = empty(hh * ww, wp.vec2, device)
    launch(_grid_vertices_kernel, (hh, ww), [h, float(dx), float(dz), wp.vec3(*rel_origin),
                                             hole_height(heights) if holes else 0.0], [pos, uv], device)
    m = 2 * max(hh - 1, 0) * max(ww - 1, 0)
    if m and holes:  # count -> scan -> emit
        cells = (hh - 1) * (ww - 1)
        cnt = empty(cells, wp.int32, device)
        launch(_hole_count_kernel, (hh - 1, ww - 1), [h], [cnt], device)
        start = wp.empty_like(cnt)
        scan(cnt, start, inclusive=False)
        m = int(start.numpy()[-1] + cnt.numpy()[-1])
        tri = empty((max(m, 1), 3), wp.int32, device)
        if m:
            launch(_hole_emit_kernel, (hh - 1, ww - 1), [h, start], [tri], device)
        return (pos.numpy().reshape(-1, 3), uv.numpy().reshape(-1, 2), tri.numpy()[:m].reshape(-1, 3))
    tri = empty((max(m, 1), 3), wp.int32, device)
    if m:
        launch(_grid_triangles_kernel, (hh - 1, ww - 1), [ww], [tri], device)
    return (pos.numpy().reshape(-1, 3), uv.numpy().reshape(-1, 2), tri.numpy()[:m].reshape(-1, 3))


@wp.kernel(enable_backward=False)
def _sample_normals_kernel(
    offset: int,
    nmap: wp.array2d(dtype=wp.vec3),
    uv: wp.array(dtype=wp.vec2),
    # outputs
    out_n: wp.array(dtype=wp.vec3),
):
    k = wp.tid() + offset
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
    out = empty(max(n, 1), wp.vec3, device)
    if n:
        launch(_sample_normals_kernel, n,
               [view(nmap, wp.vec3, device),
                wp.array(np.ascontiguousarray(uv, np.float32), dtype=wp.vec2, device=device)], [out], device)
    return out.numpy()[:n].reshape(n, 3)


@wp.func
def _finite(p: wp.vec3) -> int:
    ok = int(1)
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])):
        ok = 0
    return ok


@wp.kernel(enable_backward=False)
def _finite_tri_count_kernel(
    offset: int,
    pos: wp.array(dtype=wp.vec3),
    tri: wp.array2d(dtype=wp.int32),
    # outputs
    out_flag: wp.array(dtype=wp.int32),
):
    t = wp.tid() + offset
    out_flag[t] = _finite(pos[tri[t, 0]]) * _finite(pos[tri[t, 1]]) * _finite(pos[tri[t, 2]])


@wp.kernel(enable_backward=False)
def _finite_tri_emit_kernel(
    offset: int,
    tri: wp.array2d(dtype=wp.int32),
    flag: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    t = wp.tid() + offset
    if flag[t] == 1:
        s = start[t]
        for c in range(3):
            out_tri[s, c] = tri[t, c]


@wp.kernel(enable_backward=False)
def _fill_holes_kernel(
    offset: int,
    pos: wp.array(dtype=wp.vec3),
    fill_y: float,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
):
    """A hole's vertex keeps its finite x and z and takes height ``fill_y`` (a non-finite x or z, which no
    displaced mesh has, becomes 0)."""
    k = wp.tid() + offset
    p = pos[k]
    if _finite(p) == 0:
        x = p[0]
        z = p[2]
        if not wp.isfinite(x):
            x = 0.0
        if not wp.isfinite(z):
            z = 0.0
        p = wp.vec3(x, fill_y, z)
    out_pos[k] = p


def drop_nonfinite_triangles(positions: np.ndarray, triangles: np.ndarray,
                             device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """No-data holes for any displaced mesh: drop every triangle with a non-finite vertex (count ->
    ``wp.utils.array_scan`` -> emit, triangle order kept) and move each non-finite vertex (now used by no
    triangle) to the lowest finite height among the positions (:func:`hole_height` of their y), keeping its
    x and z: the rasterizer gets finite positions, no triangle touches a hole, and no hole vertex lies
    outside the mesh's height range (not at 0, not at the eye).

    Args:
        positions: (n, 3) float32 (NaN where a vertex sampled a NaN height).
        triangles: (m, 3) int32 indices into ``positions``.

    Returns:
        positions (n, 3) float32, all finite (a copy when something changed), triangles (k, 3) int32, k <= m.
    """
    pos_np = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
    tri_np = np.ascontiguousarray(triangles, dtype=np.int32).reshape(-1, 3)
    m = len(tri_np)
    if np.isfinite(pos_np).all():
        return pos_np, tri_np
    pos = wp.array(pos_np, dtype=wp.vec3, device=device)
    out_pos = empty(len(pos_np), wp.vec3, device)
    ok = np.isfinite(pos_np).all(axis=1)
    launch(_fill_holes_kernel, len(pos_np), [pos, hole_height(pos_np[ok, 1])], [out_pos], device)
    if m == 0:
        return out_pos.numpy().reshape(-1, 3), tri_np
    tri = wp.array(tri_np, dtype=wp.int32, device=device)
    flag = empty(m, wp.int32, device)
    launch(_finite_tri_count_kernel, m, [pos, tri], [flag], device)
    start = wp.empty_like(flag)
    scan(flag, start, inclusive=False)
    k = int(start.numpy()[-1] + flag.numpy()[-1])
    out_tri = empty((max(k, 1), 3), wp.int32, device)
    launch(_finite_tri_emit_kernel, m, [tri, flag, start], [out_tri], device)
    return out_pos.numpy().reshape(-1, 3), out_tri.numpy()[:k].reshape(-1, 3)
