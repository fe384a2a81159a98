"""Displacement from a stack of overview windows: the interior fast path (no clamps, a multiply by 2^-shift)
gives the bits of the plain rule (clamped bilinear samples, a division), at window edges and the grid's."""

from __future__ import annotations

import numpy as np
import warp as wp

from terrainwarp.kernels.parallel import launch
from terrainwarp.kernels.stack import _bilinear, _holds, stack_displace


@wp.kernel(enable_backward=False)
def _plain_kernel(offset: int, grid: wp.array(dtype=wp.vec2), data: wp.array(dtype=wp.float32),
                  table: wp.array(dtype=wp.vec4i), shift: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int64),
                  full: wp.array(dtype=wp.vec2i), n_win: int, eye_y: float, dx: float, dz: float,
                  pos: wp.array(dtype=wp.vec3), nrm: wp.array(dtype=wp.vec3), win: wp.array(dtype=wp.int32)):
    """The rule as stack.py's docstring states it, with no fast path: the reference."""
    k = wp.tid() + offset
    g = grid[k]
    w = n_win - 1
    for m in range(n_win):
        t = table[m]
        s = float(1 << shift[m])
        if _holds(t[0], t[2], full[m][0], int(wp.floor(g[0] / s))) and _holds(t[1], t[3], full[m][1],
                                                                               int(wp.floor(g[1] / s))):
            w = m
            break
    t = table[w]
    s = float(1 << shift[w])
    u = g[0] / s - float(t[0])
    v = g[1] / s - float(t[1])
    st = int(start[w])
    h = _bilinear(data, st, t[2], t[3], u, v)
    hx = _bilinear(data, st, t[2], t[3], u + 1.0, v) - _bilinear(data, st, t[2], t[3], u - 1.0, v)
    hz = _bilinear(data, st, t[2], t[3], u, v + 1.0) - _bilinear(data, st, t[2], t[3], u, v - 1.0)
    p = pos[k]
    pos[k] = wp.vec3(p[0], h - eye_y, p[2])
    nrm[k] = wp.normalize(wp.vec3(-hx / (2.0 * dx * s), 1.0, -hz / (2.0 * dz * s)))
    win[k] = shift[w]


def _stack(rng):
    """A 257^2 random grid's overviews at steps 1, 2 and 8 (point sampled), one window of each: a small one
    inside, one touching the grid's first rows, and the whole coarsest overview."""
    full = rng.normal(0.0, 50.0, (257, 257)).astype(np.float32)
    over = {s: np.ascontiguousarray(full[::s, ::s]) for s in (1, 2, 8)}
    boxes = [(0, 40, 60, 50, 70), (1, 0, 10, 60, 90), (3, 0, 0, 33, 33)]  # (shift, r0, c0, rows, cols)
    windows = [(sh, r0, c0, over[1 << sh][r0:r0 + rows, c0:c0 + cols]) for sh, r0, c0, rows, cols in boxes]
    return windows, [over[1 << w[0]].shape for w in windows]


def test_stack_displace_equals_the_plain_rule_inside_windows_and_at_every_edge():
    rng = np.random.default_rng(4)
    windows, shapes = _stack(rng)
    n = 20000
    gx = rng.uniform(-2.0, 258.0, n).astype(np.float32)
    gz = rng.uniform(-2.0, 258.0, n).astype(np.float32)
    ints = rng.random(n) < 0.3  # vertices on grid points, as tessellated patches mostly are
    gx[ints], gz[ints] = np.round(gx[ints]), np.round(gz[ints])
    uv = np.stack([gx, gz], 1)
    pos0 = rng.normal(0.0, 100.0, (n, 3)).astype(np.float32)

    pos, nrm, win = stack_displace(uv, pos0.copy(), windows, shapes, 12.5, 10.0, 10.0)

    data = np.concatenate([w[3].reshape(-1) for w in windows])
    starts = np.concatenate([[0], np.cumsum([w[3].size for w in windows])[:-1]]).astype(np.int64)
    ref_pos = wp.array(pos0.copy(), dtype=wp.vec3)
    ref_nrm = wp.empty(n, dtype=wp.vec3)
    ref_win = wp.empty(n, dtype=wp.int32)
    launch(_plain_kernel, n, [
        wp.array(uv, dtype=wp.vec2), wp.array(data, dtype=wp.float32),
        wp.array(np.array([(w[2], w[1], w[3].shape[1], w[3].shape[0]) for w in windows], np.int32), dtype=wp.vec4i),
        wp.array(np.array([w[0] for w in windows], np.int32), dtype=wp.int32), wp.array(starts, dtype=wp.int64),
        wp.array(np.array([(c, r) for r, c in shapes], np.int32), dtype=wp.vec2i), len(windows), 12.5, 10.0, 10.0],
        [ref_pos, ref_nrm, ref_win], "cpu")
    assert set(np.unique(win)) == {0, 1, 3}  # every window was read
    np.testing.assert_array_equal(win, ref_win.numpy())
    np.testing.assert_array_equal(pos.view(np.uint32), ref_pos.numpy().reshape(-1, 3).view(np.uint32))
    np.testing.assert_array_equal(nrm.view(np.uint32), ref_nrm.numpy().reshape(-1, 3).view(np.uint32))
