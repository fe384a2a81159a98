"""Displacement from a stack of point-sampled overview windows (a streamed heightmap's frame).

A streamed frame holds no heightmap: it holds one window per overview step the frame's patches need,
each the bounding box of those patches (plus a margin) in that overview's samples. A point at grid
coordinate (gx, gz) (cells of the full-resolution grid) reads the finest window that holds its bilinear
footprint and its central differences, so the height of a point depends on its position alone: two
patches that share an edge vertex read the same window and the same height, and the mesh stays
watertight across windows.

Windows (``table`` rows, finest first): (c0, r0, cols, rows) in samples of their overview, the overview's
``shift`` (step 2^shift), and ``start`` into the flat ``data``. A window that reaches its overview's last
column or row clamps there (the grid's edge), as the in-memory sampler clamps.

An overview's samples sit at grid coordinates 0, s, 2s, ..., and its last at the grid's last sample (W - 1,
H - 1) where that is not a multiple of s (:meth:`terrainwarp.io.tiles.TileSource.read`): a point in that last,
shorter cell takes its fraction of the cell's true width (:func:`_overview_coord`), so a vertex on the grid's
last row or column (where the tessellator clamps a patch reaching past the grid) reads the grid's last sample
exactly, as in memory.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .parallel import launch, view

__all__ = ["stack_displace"]


@wp.func
def _fetch(data: wp.array(dtype=wp.float32), start: int, cols: int, rows: int, i: int, j: int) -> float:
    ii = wp.clamp(i, 0, rows - 1)
    jj = wp.clamp(j, 0, cols - 1)
    return data[start + ii * cols + jj]


@wp.func
def _bilinear(data: wp.array(dtype=wp.float32), start: int, cols: int, rows: int, u: float, v: float) -> float:
    """As sampling.sample_bilinear, on one window of the flat stack."""
    uc = wp.clamp(u, 0.0, float(cols - 1))
    vc = wp.clamp(v, 0.0, float(rows - 1))
    j0 = int(wp.floor(uc))
    i0 = int(wp.floor(vc))
    fu = uc - float(j0)
    fv = vc - float(i0)
    ref = _fetch(data, start, cols, rows, i0, j0)
    b = _fetch(data, start, cols, rows, i0, j0 + 1) - ref
    c = _fetch(data, start, cols, rows, i0 + 1, j0) - ref
    d = _fetch(data, start, cols, rows, i0 + 1, j0 + 1) - ref
    a = 0.0
    top = a + (b - a) * fu  # sampling.sample_bilinear's operations, in its order: the same float32 answer
    bot = c + (d - c) * fu
    return ref + (top + (bot - top) * fv)


@wp.func
def _bilinear_in(data: wp.array(dtype=wp.float32), start: int, cols: int, u: float, v: float) -> float:
    """_bilinear where no clamp applies (u in [0, cols - 2), v in [0, rows - 2)): the same operations."""
    j0 = int(wp.floor(u))
    i0 = int(wp.floor(v))
    fu = u - float(j0)
    fv = v - float(i0)
    k = start + i0 * cols + j0
    ref = data[k]
    b = data[k + 1] - ref
    c = data[k + cols] - ref
    d = data[k + cols + 1] - ref
    a = 0.0
    top = a + (b - a) * fu
    bot = c + (d - c) * fu
    return ref + (top + (bot - top) * fv)


@wp.func
def _holds(lo: int, n: int, full: int, k: int) -> bool:
    """Window [lo, lo + n) of an overview ``full`` samples long holds samples k - 1 .. k + 2 (or reaches the
    grid's edge on the side it lacks)."""
    return (k - 1 >= lo or lo == 0) and (k + 2 <= lo + n - 1 or lo + n == full)


@wp.func
def _overview_coord(g: float, r: float, s: int, n: int, last: int) -> float:
    """Overview coordinate of grid coordinate ``g`` (cells) along an axis whose last sample is ``last``, in an
    overview of ``n`` samples at step ``s`` (``r`` = 1/s): g r (exact: a power of two), but in the overview's
    last cell when its last sample is the grid's clamped edge (``last`` not a multiple of s), n - 2 plus the
    fraction of that cell's width, last - (n - 2) s."""
    a = (n - 2) * s
    out = g * r
    if (n - 1) * s != last and g > float(a):
        out = float(n - 2) + (g - float(a)) / float(last - a)
    return out


@wp.kernel(enable_backward=False)
def _stack_kernel(
    offset: int,
    grid: wp.array(dtype=wp.vec2),
    data: wp.array(dtype=wp.float32),
    table: wp.array(dtype=wp.vec4i),
    shift: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int64),
    full: wp.array(dtype=wp.vec2i),
    inv: wp.array(dtype=wp.float32),
    n_win: int,
    last: wp.vec2i,
    eye_y: float,
    dx: float,
    dz: float,
    keep_win: int,
    # outputs
    pos: wp.array(dtype=wp.vec3),
    nrm: wp.array(dtype=wp.vec3),
    win: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    g = grid[k]
    w = n_win - 1
    for m in range(n_win):  # the finest window that holds the point's footprint
        t = table[m]
        r = inv[m]  # 2^-shift: the product is the quotient g / 2^shift, exactly
        u = _overview_coord(g[0], r, 1 << shift[m], full[m][0], last[0])
        v = _overview_coord(g[1], r, 1 << shift[m], full[m][1], last[1])
        if _holds(t[0], t[2], full[m][0], int(wp.floor(u))) and _holds(t[1], t[3], full[m][1], int(wp.floor(v))):
            w = m
            break
    t = table[w]
    s = float(1 << shift[w])
    # exact on the lattice: an integer shift of a float32 below 2^24
    u = _overview_coord(g[0], inv[w], 1 << shift[w], full[w][0], last[0]) - float(t[0])
    v = _overview_coord(g[1], inv[w], 1 << shift[w], full[w][1], last[1]) - float(t[1])
    st = int(start[w])
    up = u + 1.0
    um = u - 1.0
    vp = v + 1.0
    vm = v - 1.0
    h = float(0.0)
    hx = float(0.0)
    hz = float(0.0)
    if um >= 0.0 and vm >= 0.0 and up < float(t[2] - 1) and vp < float(t[3] - 1):  # no clamp applies
        h = _bilinear_in(data, st, t[2], u, v)
        hx = _bilinear_in(data, st, t[2], up, v) - _bilinear_in(data, st, t[2], um, v)
        hz = _bilinear_in(data, st, t[2], u, vp) - _bilinear_in(data, st, t[2], u, vm)
    else:
        h = _bilinear(data, st, t[2], t[3], u, v)
        hx = _bilinear(data, st, t[2], t[3], up, v) - _bilinear(data, st, t[2], t[3], um, v)
        hz = _bilinear(data, st, t[2], t[3], u, vp) - _bilinear(data, st, t[2], t[3], u, vm)
    p = pos[k]
    pos[k] = wp.vec3(p[0], h - eye_y, p[2])
    nrm[k] = wp.normalize(wp.vec3(-hx / (2.0 * dx * s), 1.0, -hz / (2.0 * dz * s)))
    if keep_win != 0:
        win[k] = shift[w]


def stack_displace(grid_uv: np.ndarray, positions: np.ndarray, windows: list[tuple[int, int, int, np.ndarray]],
                   full_shapes: list[tuple[int, int]], grid_shape: tuple[int, int], eye_y: float, dx: float,
                   dz: float, device: str = "cpu", *, data: np.ndarray | None = None,
                   shifts: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Heights, normals and the overview each point read, from a stack of windows.

    Args:
        grid_uv: (N, 2) float32 grid coordinates (column, row) of the points, full-resolution cells.
        positions: (N, 3) float32 camera-relative positions; y is replaced by height - eye_y (in place when
            ``positions`` is a contiguous float32 array on the CPU).
        windows: finest first, (shift, r0, c0, heights (rows, cols) float32) of the step-2^shift overview.
        full_shapes: per window, (rows, cols) of its whole overview (the grid's clamped last row and column
            included: :meth:`terrainwarp.io.tiles.TileSource.level_shape`).
        grid_shape: (H, W) of the full-resolution grid.
        eye_y: the eye's world height (float32 camera-relative, as the tessellator's).
        data: every window's heights back to back, flat float32 (the windows' arrays its views, in order), read in
            place; None: the windows' heights are copied into one such array here.
        shifts: also return each point's window (False: None, and nothing is written for it).

    Returns:
        (positions (N, 3), normals (N, 3), shift (N,) int32 of the window read, or None).
    """
    n = len(grid_uv)
    pos = view(positions, wp.vec3, device)  # written in place on the CPU
    nrm = wp.empty(max(n, 1), dtype=wp.vec3, device=device)
    win = wp.empty(max(n, 1) if shifts else 1, dtype=wp.int32, device=device)
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int32) if shifts else None
    sizes = [int(w[3].size) for w in windows]
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    if data is None:
        data = np.concatenate([np.ascontiguousarray(w[3], np.float32).reshape(-1) for w in windows])
    elif data.dtype != np.float32 or data.ndim != 1 or data.size != sum(sizes):
        raise ValueError(f"data: expected the windows' {sum(sizes)} heights as flat float32, got {data.dtype} "
                         f"{data.shape}")
    table = np.array([(w[2], w[1], w[3].shape[1], w[3].shape[0]) for w in windows], np.int32)
    full = np.array([(fc, fr) for fr, fc in full_shapes], np.int32)
    launch(_stack_kernel, n, inputs=[
        view(grid_uv, wp.vec2, device), view(data, wp.float32, device), wp.array(table, dtype=wp.vec4i, device=device),
        wp.array(np.array([w[0] for w in windows], np.int32), dtype=wp.int32, device=device),
        wp.array(starts, dtype=wp.int64, device=device), wp.array(full, dtype=wp.vec2i, device=device),
        wp.array(np.array([1.0 / (1 << w[0]) for w in windows], np.float32), dtype=wp.float32, device=device),
        len(windows), wp.vec2i(int(grid_shape[1]) - 1, int(grid_shape[0]) - 1), float(eye_y), float(dx), float(dz),
        int(shifts)], outputs=[pos, nrm, win], device=device)
    return pos.numpy()[:n].reshape(-1, 3), nrm.numpy()[:n].reshape(-1, 3), win.numpy()[:n] if shifts else None
