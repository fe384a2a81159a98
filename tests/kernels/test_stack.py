"""Displacement from a stack of overview windows: the interior fast path (no clamps, a multiply by 2^-shift)
gives the bits of the plain rule (clamped bilinear samples, a division; an overview's last, shorter cell where
it ends on the grid's clamped last sample), at window edges and the grid's."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from terrainwarp.kernels.parallel import launch
from terrainwarp.kernels.stack import _bilinear, _holds, stack_displace


@wp.func
def _plain_coord(g: float, s: int, last: int) -> float:
    """g / s; past the overview's last lattice sample, when the grid's last sample ``last`` is not on the lattice,
    the fraction of the way from that sample to ``last``, after its index."""
    u = g / float(s)
    first = last - last % s
    if last % s != 0 and g > float(first):
        u = (g - float(first)) / float(last - first) + float(first / s)
    return u


@wp.kernel(enable_backward=False)
def _plain_kernel(offset: int, grid: wp.array(dtype=wp.vec2), data: wp.array(dtype=wp.float32),
                  table: wp.array(dtype=wp.vec4i), shift: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int64),
                  full: wp.array(dtype=wp.vec2i), n_win: int, last: wp.vec2i, eye_y: float, dx: float, dz: float,
                  pos: wp.array(dtype=wp.vec3), nrm: wp.array(dtype=wp.vec3), win: wp.array(dtype=wp.int32)):
    """The rule as stack.py's docstring states it, with no fast path: the reference."""
    k = wp.tid() + offset
    g = grid[k]
    w = n_win - 1
    for m in range(n_win):
        t = table[m]
        sm = 1 << shift[m]
        if _holds(t[0], t[2], full[m][0], int(wp.floor(_plain_coord(g[0], sm, last[0])))) and _holds(
                t[1], t[3], full[m][1], int(wp.floor(_plain_coord(g[1], sm, last[1])))):
            w = m
            break
    t = table[w]
    s = float(1 << shift[w])
    u = _plain_coord(g[0], 1 << shift[w], last[0]) - float(t[0])
    v = _plain_coord(g[1], 1 << shift[w], last[1]) - float(t[1])
    st = int(start[w])
    h = _bilinear(data, st, t[2], t[3], u, v)
    hx = _bilinear(data, st, t[2], t[3], u + 1.0, v) - _bilinear(data, st, t[2], t[3], u - 1.0, v)
    hz = _bilinear(data, st, t[2], t[3], u, v + 1.0) - _bilinear(data, st, t[2], t[3], u, v - 1.0)
    p = pos[k]
    pos[k] = wp.vec3(p[0], h - eye_y, p[2])
    nrm[k] = wp.normalize(wp.vec3(-hx / (2.0 * dx * s), 1.0, -hz / (2.0 * dz * s)))
    win[k] = shift[w]


H, W = 250, 237  # neither a multiple of 2 or 8 plus one: the coarser overviews end on a clamped last sample


def _overview(full, s):
    """Sample (i, j) is the grid's (min(i s, H - 1), min(j s, W - 1)), built here by indexing."""
    rows = np.minimum(np.arange(-(-(H - 1) // s) + 1) * s, H - 1)
    cols = np.minimum(np.arange(-(-(W - 1) // s) + 1) * s, W - 1)
    return np.ascontiguousarray(full[np.ix_(rows, cols)])


def _stack(rng):
    """A 250 x 237 random grid's overviews at steps 1, 2 and 8, one window of each: a small one inside, one
    from the grid's last rows (step 2: the grid's row 249 is the overview's clamped last), and the whole
    coarsest overview (both its last row and column clamped)."""
    full = rng.normal(0.0, 50.0, (H, W)).astype(np.float32)
    over = {s: _overview(full, s) for s in (1, 2, 8)}
    assert over[2].shape == (126, 119) and over[8].shape == (33, 31)
    boxes = [(0, 40, 60, 50, 70), (1, 60, 10, 66, 90), (3, 0, 0, 33, 31)]  # (shift, r0, c0, rows, cols)
    windows = [(sh, r0, c0, over[1 << sh][r0:r0 + rows, c0:c0 + cols]) for sh, r0, c0, rows, cols in boxes]
    return full, windows, [over[1 << w[0]].shape for w in windows]


def _plain(uv, pos0, windows, shapes):
    n = len(uv)
    data = np.concatenate([w[3].reshape(-1) for w in windows])
    starts = np.concatenate([[0], np.cumsum([w[3].size for w in windows])[:-1]]).astype(np.int64)
    ref_pos = wp.array(pos0.copy(), dtype=wp.vec3)
    ref_nrm = wp.empty(n, dtype=wp.vec3)
    ref_win = wp.empty(n, dtype=wp.int32)
    launch(_plain_kernel, n, [
        wp.array(uv, dtype=wp.vec2), wp.array(data, dtype=wp.float32),
        wp.array(np.array([(w[2], w[1], w[3].shape[1], w[3].shape[0]) for w in windows], np.int32), dtype=wp.vec4i),
        wp.array(np.array([w[0] for w in windows], np.int32), dtype=wp.int32), wp.array(starts, dtype=wp.int64),
        wp.array(np.array([(c, r) for r, c in shapes], np.int32), dtype=wp.vec2i), len(windows),
        wp.vec2i(W - 1, H - 1), 12.5, 10.0, 10.0], [ref_pos, ref_nrm, ref_win], "cpu")
    return ref_pos.numpy().reshape(-1, 3), ref_nrm.numpy().reshape(-1, 3), ref_win.numpy()


def test_stack_displace_equals_the_plain_rule_inside_windows_and_at_every_edge():
    rng = np.random.default_rng(4)
    _, windows, shapes = _stack(rng)
    n = 20000
    gx = rng.uniform(-2.0, W + 1.0, n).astype(np.float32)
    gz = rng.uniform(-2.0, H + 1.0, n).astype(np.float32)
    ints = rng.random(n) < 0.3  # vertices on grid points, as tessellated patches mostly are
    gx[ints], gz[ints] = np.round(gx[ints]), np.round(gz[ints])
    uv = np.stack([gx, gz], 1)
    pos0 = rng.normal(0.0, 100.0, (n, 3)).astype(np.float32)

    pos, nrm, win = stack_displace(uv, pos0.copy(), windows, shapes, (H, W), 12.5, 10.0, 10.0)

    ref_pos, ref_nrm, ref_win = _plain(uv, pos0, windows, shapes)
    assert set(np.unique(win)) == {0, 1, 3}  # every window was read
    np.testing.assert_array_equal(win, ref_win)
    np.testing.assert_array_equal(pos.view(np.uint32), ref_pos.view(np.uint32))
    np.testing.assert_array_equal(nrm.view(np.uint32), ref_nrm.view(np.uint32))


def test_vertices_on_the_grids_last_row_and_column_read_its_last_samples_from_every_overview():
    """Where the tessellator clamps a patch that reaches past the grid: on the last row (column), at the columns
    (rows) of each overview's lattice and at the corner, every window gives the grid's own sample, as the
    in-memory bilinear sampler does."""
    full, windows, shapes = _stack(np.random.default_rng(5))
    cols = np.concatenate([np.arange(0, W, 8), [W - 1]]).astype(np.float32)
    rows = np.concatenate([np.arange(0, H, 8), [H - 1]]).astype(np.float32)
    uv = np.concatenate([np.stack([cols, np.full_like(cols, H - 1)], 1),
                         np.stack([np.full_like(rows, W - 1), rows], 1)])
    pos, _, win = stack_displace(uv, np.zeros((len(uv), 3), np.float32), windows, shapes, (H, W), 0.0, 10.0, 10.0)
    want = full[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    assert 3 in win and 1 in win  # the clamped edges of both coarse overviews were read
    np.testing.assert_array_equal(pos[:, 1], want)


def test_windows_assembled_in_one_buffer_are_read_in_place_and_the_shifts_are_optional():
    """A frame assembles its windows straight into one flat buffer (``data``): the same bits as the copied stack,
    and with ``shifts=False`` no per-point window is written or returned."""
    _, windows, shapes = _stack(np.random.default_rng(6))
    data = np.concatenate([w[3].reshape(-1) for w in windows])
    at, views = 0, []
    for sh, r0, c0, h in windows:
        views.append((sh, r0, c0, data[at:at + h.size].reshape(h.shape)))
        at += h.size
    uv = np.random.default_rng(7).uniform(0.0, 236.0, (5000, 2)).astype(np.float32)
    pos0 = np.zeros((len(uv), 3), np.float32)
    a = stack_displace(uv, pos0.copy(), windows, shapes, (H, W), 1.0, 10.0, 10.0)
    b = stack_displace(uv, pos0.copy(), views, shapes, (H, W), 1.0, 10.0, 10.0, data=data, shifts=False)
    assert b[2] is None and np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    with pytest.raises(ValueError, match="data"):
        stack_displace(uv, pos0.copy(), views, shapes, (H, W), 1.0, 10.0, 10.0, data=data[:-1])
