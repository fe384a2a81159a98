"""Tests of the bottom-up polygon merging (taylor-barrett-continuous-resolution.txt): merge rules against a
sequential Python reference, the incremental passes against the per-tolerance algorithm, multi-tolerance
reuse, coverage, watertight triangulation and TIN morphing."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import digest

from terrainwarp import Camera, Heightmap, check_watertight
from terrainwarp.kernels.polytree import FLAG_HIGH_J, FLAG_LOW_J
from terrainwarp.lod.polytree import (
    build_polytree,
    default_tolerances,
    gradients,
    merge_rectangles,
)
from terrainwarp.rendering import rasterize

# ------------------------------------------------------------------------------------------------
# references
# ------------------------------------------------------------------------------------------------


def _ref_merge(h: np.ndarray, tol: float) -> list[tuple[int, int, int, int]]:
    """The paper's recursive merge (part 2, c-h), sequential, with linear searches instead of the
    polytree: borders A, B, then C; a pair merges when its extents along the border are equal and
    |dXgr| + |dYgr| <= tol (float32 gradients, as the kernel)."""
    ch, cw = h.shape[0] - 1, h.shape[1] - 1
    n = 1
    while n < max(ch, cw):
        n *= 2

    def grads(r):
        i0, i1, j0, j1 = r
        z1, z2, z3, z4 = h[i0, j0], h[i0, j1], h[i1, j1], h[i1, j0]
        return np.float32((z2 - z1) + (z3 - z4)), np.float32((z4 - z1) + (z3 - z2))

    def find(polys, i, j):
        for p in polys:
            if p[0] <= i < p[1] and p[2] <= j < p[3]:
                return p
        raise AssertionError("uncovered cell")

    def border(polys, vertical, fixed, start, end):
        p = start
        while p < end:
            a = find(polys, p, fixed - 1) if vertical else find(polys, fixed - 1, p)
            b = find(polys, p, fixed) if vertical else find(polys, fixed, p)
            k = 0 if vertical else 2
            if a[k] == b[k] and a[k + 1] == b[k + 1]:
                ga, gb = grads(a), grads(b)
                if abs(ga[0] - gb[0]) + abs(ga[1] - gb[1]) <= np.float32(tol):
                    a[:] = [a[0], b[1], a[2], b[3]]
                    polys.remove(b)
            p = min(a[k + 1], b[k + 1])

    def node(i0, j0, s):
        if i0 >= ch or j0 >= cw:
            return []
        if s == 1:
            return [[i0, i0 + 1, j0, j0 + 1]]
        hs = s // 2
        polys = node(i0, j0, hs) + node(i0, j0 + hs, hs) + node(i0 + hs, j0, hs) + node(i0 + hs, j0 + hs, hs)
        ni1, nj1 = min(i0 + s, ch), min(j0 + s, cw)
        if j0 + hs < cw:
            border(polys, True, j0 + hs, i0, min(i0 + hs, ni1))
            if i0 + hs < ch:
                border(polys, True, j0 + hs, i0 + hs, ni1)
        if i0 + hs < ch:
            border(polys, False, i0 + hs, j0, nj1)
        return polys

    return sorted(tuple(p) for p in node(0, 0, n))


class _RefPasses:
    """The per-tolerance algorithm, sequential: every pass merges every node that does not hold a single
    polygon since an earlier pass (step j), level by level, each from a copy of its sons' records, finding
    polygons with section 2.1's search (descent to the topmost single node, father pointers, merge
    pointers), and counts what it does."""

    def __init__(self, h: np.ndarray):
        self.h = np.asarray(h, np.float32)
        self.ch, self.cw = self.h.shape[0] - 1, self.h.shape[1] - 1
        n = max(self.ch, self.cw)
        self.depth = int(np.ceil(np.log2(n))) if n > 1 else 0
        self.frozen = [[False] * 4 ** (self.depth - m) for m in range(self.depth + 1)]

    def corner(self, k: int, m: int) -> tuple[int, int]:
        i = j = 0
        for b in range(self.depth - m):
            j |= ((k >> (2 * b)) & 1) << b
            i |= ((k >> (2 * b + 1)) & 1) << b
        return i << m, j << m

    def grads(self, r) -> tuple[np.float32, np.float32]:
        h = self.h
        z1, z2, z3, z4 = h[r[0], r[2]], h[r[0], r[3]], h[r[1], r[3]], h[r[1], r[2]]
        return np.float32((z2 - z1) + (z3 - z4)), np.float32((z4 - z1) + (z3 - z2))

    def find(self, r: int, c: int, m: int, lo: int, fwd: list) -> tuple[int, int]:
        code = sum((((c >> b) & 1) << (2 * b)) | (((r >> b) & 1) << (2 * b + 1)) for b in range(self.depth))
        lv, steps = m - 1, 0
        while True:
            steps += 1
            q = self.single[lv][code >> (2 * lv)]
            if q >= 0:
                break
            lv -= 1
        while lv < m - 1:
            q, lv, steps = self.father[lv][q], lv + 1, steps + 1
        q -= lo
        while fwd[q] >= 0:
            q, steps = fwd[q], steps + 1
        return q, steps

    def border(self, sc: list, fwd: list, m: int, lo: int, vertical: bool, fixed: int, p: int, end: int):
        st = self.stats
        while p < end:
            (a, sa), (b, sb) = (self.find(p, fixed - 1, m, lo, fwd), self.find(p, fixed, m, lo, fwd)) if vertical \
                else (self.find(fixed - 1, p, m, lo, fwd), self.find(fixed, p, m, lo, fwd))
            st[0], st[4], st[5] = st[0] + 1, st[4] + sa + sb, max(st[5], sa, sb)
            ra, rb = sc[a][0], sc[b][0]
            k0 = 0 if vertical else 2
            ok = False
            if ra[k0] == rb[k0] and ra[k0 + 1] == rb[k0 + 1]:
                ga, gb = self.grads(ra), self.grads(rb)
                if np.float32(abs(ga[0] - gb[0]) + abs(ga[1] - gb[1])) <= self.tol:
                    keep = (13, 14) if vertical else (7, 11)
                    sc[a] = [[ra[0], rb[1], ra[2], rb[3]], (sc[a][1] & keep[0]) | (sc[b][1] & keep[1])]
                    fwd[b], ok = a, True
                    st[3] += 1
                else:
                    st[2] += 1
            else:
                st[1] += 1
            if not ok:
                sc[a][1] |= 2 if vertical else 8
                sc[b][1] |= 1 if vertical else 4
            p = min(ra[k0 + 1], rb[k0 + 1])

    def node(self, m: int, k: int, rec: list):
        """Merge node k of level m (its sons' records are level m-1's) and append its records to ``rec``."""
        i0, j0 = self.corner(k, m)
        s, ch, cw = 1 << m, self.ch, self.cw
        if m == 0 or self.frozen[m][k]:
            rec.append([[i0, min(i0 + s, ch), j0, min(j0 + s, cw)], 0])
            return
        lo, hi = self.first[m - 1][4 * k], self.first[m - 1][4 * k + 4]
        sc = [[list(r), f] for r, f in self.recs[m - 1][lo:hi]]
        fwd = [-1] * len(sc)
        half = 1 << (m - 1)
        i1, j1, im, jm = min(i0 + s, ch), min(j0 + s, cw), i0 + half, j0 + half
        if jm < cw:
            self.border(sc, fwd, m, lo, True, jm, i0, min(im, i1))
            if im < ch:
                self.border(sc, fwd, m, lo, True, jm, im, i1)
        if im < ch:
            self.border(sc, fwd, m, lo, False, im, j0, j1)
        out_of = {}
        for q in range(len(sc)):
            if fwd[q] < 0:
                out_of[q] = len(rec)
                rec.append(sc[q])
        for q in range(len(sc)):
            f = q
            while fwd[f] >= 0:
                f = fwd[f]
            self.father[m - 1][lo + q] = out_of[f]

    def run(self, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One pass: the root's (rects (P, 4) in record order, grads (P, 2) float32, flags (P,), counters (6,))."""
        self.tol, self.stats = np.float32(tol), [0] * 6
        self.recs, self.father, self.single, self.first = [], [], [], []
        for m in range(self.depth + 1):
            n = 4 ** (self.depth - m)
            rec, single, first = [], [-1] * n, [0] * (n + 1)
            for k in range(n):
                first[k] = len(rec)
                i0, j0 = self.corner(k, m)
                if i0 < self.ch and j0 < self.cw and not (m < self.depth and self.frozen[m + 1][k >> 2]):
                    self.node(m, k, rec)  # (not visited: outside, or under a node that keeps its polygon)
                    if len(rec) - first[k] == 1:
                        single[k] = first[k]
            first[n] = len(rec)
            self.recs.append(rec)
            self.father.append([-1] * len(rec))
            self.single.append(single)
            self.first.append(first)
        for m in range(self.depth + 1):  # step j
            self.frozen[m] = [f or q >= 0 for f, q in zip(self.frozen[m], self.single[m], strict=True)]
        root = self.recs[self.depth]
        return (np.array([r for r, _ in root], np.int32).reshape(-1, 4),
                np.array([self.grads(r) for r, _ in root], np.float32).reshape(-1, 2),
                np.array([f for _, f in root], np.int32), np.array(self.stats, np.int64))


def _ref_passes(h: np.ndarray, tols, stop_at_one: bool = True) -> list[tuple]:
    """:class:`_RefPasses` over ascending tolerances, stopping like :func:`build_polytree`."""
    ref, out = _RefPasses(h), []
    for tol in tols:
        out.append(ref.run(tol))
        if stop_at_one and len(out[-1][0]) == 1:
            break
    return out


def _sorted(rects: np.ndarray) -> list[tuple[int, int, int, int]]:
    return sorted(tuple(int(v) for v in r) for r in rects)


def _check_watertight(mesh, shape: tuple[int, int]) -> None:
    """Private watertight check: after merging vertices by exact position, every edge not on the terrain
    border is used by exactly two triangles (in opposite directions), border edges by one, and no vertex
    lies in the interior of another triangle's edge."""
    hh, ww = shape
    pos = mesh.positions
    _, vid = np.unique(pos, axis=0, return_inverse=True)
    vid = vid.reshape(-1)
    tri = vid[mesh.triangles]
    assert np.all((tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2]))
    directed = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    d_keys, d_counts = np.unique(directed, axis=0, return_counts=True)
    assert d_counts.max() == 1, "a directed edge is used twice (inconsistent orientation or overlap)"
    und = np.sort(directed, axis=1)
    keys, counts = np.unique(und, axis=0, return_counts=True)
    # grid coordinates of the merged vertices
    gj = np.rint(mesh.uv[:, 0] * (ww - 1)).astype(np.int64)
    gi = np.rint(mesh.uv[:, 1] * (hh - 1)).astype(np.int64)
    first = np.zeros(vid.max() + 1, np.int64)
    first[vid] = np.arange(len(vid))
    ei, ej = gi[first[keys]], gj[first[keys]]
    on_border = ((ei[:, 0] == ei[:, 1]) & ((ei[:, 0] == 0) | (ei[:, 0] == hh - 1))) | \
        ((ej[:, 0] == ej[:, 1]) & ((ej[:, 0] == 0) | (ej[:, 0] == ww - 1)))
    assert np.all(counts[on_border] == 1)
    assert np.all(counts[~on_border] == 2), f"{int(np.sum(counts[~on_border] != 2))} gap or T-junction edges"
    # no vertex strictly inside an edge (T-junction)
    vi, vj = gi[first], gj[first]
    for s in range(0, len(keys), 512):
        ai, aj = ei[s:s + 512, 0, None], ej[s:s + 512, 0, None]
        bi, bj = ei[s:s + 512, 1, None], ej[s:s + 512, 1, None]
        cross = (bi - ai) * (vj[None] - aj) - (bj - aj) * (vi[None] - ai)
        dot = (vi[None] - ai) * (bi - ai) + (vj[None] - aj) * (bj - aj)
        ln = (bi - ai) ** 2 + (bj - aj) ** 2
        assert not np.any((cross == 0) & (dot > 0) & (dot < ln)), "a vertex lies inside an edge"
    # counter-clockwise seen from +y and the projected area equals the grid's
    p = mesh.positions.astype(np.float64)
    a, b, c = p[mesh.triangles[:, 0]], p[mesh.triangles[:, 1]], p[mesh.triangles[:, 2]]
    ny = (b[:, 2] - a[:, 2]) * (c[:, 0] - a[:, 0]) - (b[:, 0] - a[:, 0]) * (c[:, 2] - a[:, 2])
    assert np.all(ny > 0)
    return float(ny.sum() / 2.0)




def _hm(h, dx=1.0):
    return Heightmap.from_array(np.asarray(h, np.float32), dx)


# ------------------------------------------------------------------------------------------------
# merging
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(65, 65), (17, 33)])
def test_plane_merges_to_one_polygon_at_any_tolerance(shape, device):
    ii, jj = np.mgrid[0:shape[0], 0:shape[1]]
    h = 100.0 + 0.5 * jj - 0.25 * ii  # dyadic slopes: exact in float32
    hm = _hm(h)
    for tol in (0.0, 0.5, 10.0, 1e4):
        r = merge_rectangles(hm, tol, device=device)
        assert _sorted(r) == [(0, shape[0] - 1, 0, shape[1] - 1)], tol
    pt = build_polytree(hm, [0.0, 1.0, 2.0], device=device)
    assert pt.n_levels == 1 and pt.polygons.n_polygons(0) == 1  # stops once the root holds one polygon


def test_flat_non_power_of_two_grid_is_one_polygon(device):
    hm = _hm(np.full((40, 23), 7.0))
    assert _sorted(merge_rectangles(hm, 0.0, device=device)) == [(0, 39, 0, 22)]


def test_generic_plane_merges_with_a_float32_sized_tolerance(device):
    ii, jj = np.mgrid[0:33, 0:33]
    hm = _hm(1234.567 + 0.37 * jj + 0.11 * ii)
    # float32 rounding of the heights: gradients of coplanar rectangles differ by a few ulps of 1250 m
    assert len(merge_rectangles(hm, 8 * np.spacing(np.float32(1300.0)) * 4, device=device)) == 1


@pytest.mark.parametrize("col", [21, 32])
def test_ridge_is_never_merged_across_below_its_gradient_jump(col, device):
    ii, jj = np.mgrid[0:65, 0:65]
    slope = 2.0
    h = 0.5 * ii + slope * np.abs(jj - col)  # ridge along i at column `col`
    hm = _hm(h)
    jump = 4.0 * slope  # |Xgr| of a unit cell is 2*slope on either side: the smallest possible jump
    tols = [0.0, 1.0, jump - 0.5, jump, 4 * jump, 64 * jump, 1e6]
    pt = build_polytree(hm, tols, device=device)
    for t, tol in enumerate(pt.polygons.tolerances):
        r = pt.polygons.level(t)
        straddle = (r[:, 2] < col) & (r[:, 3] > col)
        if tol < jump:
            assert not straddle.any(), f"merged across the ridge at tolerance {tol}"
            assert np.all(pt.polygons.flags[pt.polygons.start[t]:pt.polygons.start[t + 1]][r[:, 3] == col]
                          & FLAG_HIGH_J)
            assert np.all(pt.polygons.flags[pt.polygons.start[t]:pt.polygons.start[t + 1]][r[:, 2] == col]
                          & FLAG_LOW_J)
    assert pt.polygons.n_polygons(pt.n_levels - 1) == 1  # a big enough tolerance erases it
    # below the jump, each side of the ridge is a plane: it merges into a few rectangles only
    assert pt.polygons.n_polygons(0) <= 12


@pytest.mark.parametrize("shape,seed", [((33, 33), 1), ((29, 19), 2)])
def test_merge_matches_sequential_reference_and_step_j_reuse(shape, seed, device):
    rng = np.random.default_rng(seed)
    h = np.cumsum(rng.normal(size=shape), axis=1).astype(np.float32) * 3.0
    h[:, : shape[1] // 3] = 5.0  # a flat part that merges early
    hm = _hm(h)
    tols = [0.0, 0.5, 2.0, 5.0, 12.0, 30.0]
    pt = build_polytree(hm, tols, stop_at_one=False, device=device)
    for t, tol in enumerate(tols):
        ref = _ref_merge(hm.heights, tol)
        assert _sorted(pt.polygons.level(t)) == ref, f"tolerance {tol}"
        assert _sorted(merge_rectangles(hm, tol, device=device)) == ref  # one pass equals the pass with reuse
        assert check_watertight(pt.mesh(t)).watertight
    counts = [pt.polygons.n_polygons(t) for t in range(pt.n_levels)]
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[-1]


def test_polygon_array_covers_the_grid_exactly_once_at_every_tolerance(device):
    hm = Heightmap.fbm(49, 37, seed=4, max_height=300.0, feature_size=32.0)
    pt = build_polytree(hm, default_tolerances(hm, 40), device=device)
    pa = pt.polygons
    assert pa.start[0] == 0 and pa.start[-1] == len(pa.rects) and np.all(np.diff(pa.start) >= 1)
    assert pa.n_polygons(pa.n_levels - 1) == 1 and pa.n_levels <= 40
    for t in range(pa.n_levels):
        cover = np.zeros((48, 36), np.int32)
        for i0, i1, j0, j1 in pa.level(t):
            assert i0 < i1 and j0 < j1
            cover[i0:i1, j0:j1] += 1
        assert np.all(cover == 1), t
        np.testing.assert_allclose(pa.grads[pa.start[t]:pa.start[t + 1]], gradients(hm.heights, pa.level(t)),
                                   rtol=0, atol=1e-3)
    assert pa.level_for(-1.0) == 0 and pa.level_for(1e9) == pa.n_levels - 1


def test_deterministic_across_runs(device):
    hm = Heightmap.fbm(65, seed=9, max_height=500.0, feature_size=40.0)
    tols = default_tolerances(hm, 30)
    digests = []
    for _ in range(2):
        pt = build_polytree(hm, tols, device=device)
        m = pt.mesh(5)
        digests.append(digest(pt.polygons.rects, pt.polygons.grads, pt.polygons.flags, pt.polygons.start,
                              pt.pass_stats, m.positions, m.triangles))
    assert digests[0] == digests[1]


def test_bad_input():
    hm = _hm(np.zeros((9, 9)))
    with pytest.raises(TypeError, match="heightmap"):
        build_polytree(np.zeros((9, 9)), [0.0])
    with pytest.raises(ValueError, match="tolerances"):
        build_polytree(hm, [1.0, 0.5])
    with pytest.raises(ValueError, match="tolerances"):
        build_polytree(hm, [-1.0])
    with pytest.raises(ValueError, match="tolerances"):
        build_polytree(hm, [])
    with pytest.raises(ValueError, match="heightmap"):
        build_polytree(_hm(np.zeros((1, 9))), [0.0])
    with pytest.raises(TypeError, match="tolerance"):
        merge_rectangles(hm, "1")
    pt = build_polytree(hm, [0.0])
    with pytest.raises(ValueError, match="t:"):
        pt.polygons.level(3)
    with pytest.raises(ValueError, match="x:"):
        pt.morph_mesh(2.0)
    with pytest.raises(ValueError, match="t:"):
        pt.morph(0)  # a single level: nothing to morph to


# ------------------------------------------------------------------------------------------------
# triangulation and morphing
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rough():
    hm = Heightmap.fbm(65, 57, seed=3, max_height=400.0, dx=10.0, dz=7.5, feature_size=24.0)
    return hm, build_polytree(hm, default_tolerances(hm, 60))


def test_triangulations_are_watertight(rough):
    hm, pt = rough
    area = (hm.shape[0] - 1) * hm.dz * (hm.shape[1] - 1) * hm.dx
    ratios = []
    for t in sorted({0, 3, 8, pt.n_levels // 2, pt.n_levels - 1}):
        m = pt.mesh(t)
        a = _check_watertight(m, hm.shape)
        rep = check_watertight(m)
        assert rep.watertight and rep.n_degenerate == 0 and rep.n_triangles == m.n_triangles, rep
        assert a == pytest.approx(area, rel=1e-5)
        rects = pt.polygons.level(t)
        ratios.append(m.n_triangles / len(rects))
        # every vertex is a heightmap sample with its exact height
        gi = np.rint(m.uv[:, 1] * (hm.shape[0] - 1)).astype(int)
        gj = np.rint(m.uv[:, 0] * (hm.shape[1] - 1)).astype(int)
        np.testing.assert_array_equal(m.positions[:, 1], hm.heights[gi, gj])
    assert all(2.0 <= r < 6.0 for r in ratios) and max(ratios) > 2.0


def test_mesh_is_drawn_by_the_rasterizer(rough):
    hm, pt = rough
    cam = Camera.default_for(hm, 96, 72)
    m = pt.mesh(6, eye=cam.position)
    f = rasterize(m.positions, m.triangles, cam.view_matrix(relative=True), cam.proj_matrix(), 96, 72)
    assert f.stats["pixels_covered"] > 96 * 72 // 4


def test_morph_end_points_equal_the_two_levels(rough):
    hm, pt = rough
    for t in (2, 10):
        mo = pt.morph(t)
        m0 = pt.morph_mesh(float(t))
        fine = pt.mesh(t)
        coarse = pt.mesh(t + 1, split=True)
        # s = 0: the split level t (level t's rectangles cut along the borders of the coarser levels): its
        # vertices are level t's vertices plus the cut points, at their exact sample heights, watertight
        _check_watertight(m0, hm.shape)
        assert check_watertight(m0).watertight
        fine_set = {tuple(p) for p in fine.positions.tolist()}
        m0_set = {tuple(p) for p in m0.positions.tolist()}
        assert fine_set <= m0_set
        assert len(mo.rects) - pt.polygons.n_polygons(t) == mo.split_added >= 0
        if mo.split_added == 0:
            assert m0_set == fine_set
        # s = 1: every vertex sits on a vertex of level t+1 and every level t+1 vertex is reached
        m1 = pt.morph_at(t, 1.0)
        assert {tuple(p) for p in m1.positions.tolist()} == {tuple(p) for p in coarse.positions.tolist()}
        np.testing.assert_array_equal(pt.morph_at(t, 0.0).positions, m0.positions)
        assert {tuple(p) for p in pt.morph_mesh(t + 1.0).positions.tolist()} == \
            {tuple(p) for p in coarse.positions.tolist()}  # the next morph starts where this one ends
        # split levels nest: each split rectangle lies inside one rectangle of the next split level
        ra, _ = pt.split_level(t)
        rb, lb = pt.split_level(t + 1)
        q = rb[lb[ra[:, 0], ra[:, 2]]]
        assert np.all((q[:, 0] <= ra[:, 0]) & (ra[:, 1] <= q[:, 1]) & (q[:, 2] <= ra[:, 2]) & (ra[:, 3] <= q[:, 3]))
        # in between, positions move continuously and heights come from the heightmap
        pa = pt.morph_mesh(t + 0.5).positions
        pb = pt.morph_mesh(t + 0.51).positions
        step = np.abs(pa[:, [0, 2]] - pb[:, [0, 2]]).max()
        full = np.abs((mo.dst - mo.src) * np.array([hm.dz, hm.dx])).max()
        assert step <= 0.011 * full + 1e-4


def test_morph_between_equal_levels_is_static():
    ii, jj = np.mgrid[0:17, 0:17]
    hm = _hm(0.5 * np.abs(jj - 8) + 0.25 * ii)
    pt = build_polytree(hm, [0.0, 0.5, 1.0], stop_at_one=False)  # jump 2: all three levels equal
    assert _sorted(pt.polygons.level(0)) == _sorted(pt.polygons.level(1))
    m = pt.mesh(0)
    for x in (0.0, 0.3, 1.0, 1.7, 2.0):
        mm = pt.morph_mesh(x)
        np.testing.assert_array_equal(mm.positions, m.positions)
        np.testing.assert_array_equal(mm.triangles, m.triangles)


def test_figure5_gradients_and_threshold():
    # two unit polygons with the paper's figure 5 gradients: (7, -9) and (15, -11), difference 10
    hm = _hm([[0.0, 4.0, 12.0], [-4.0, -1.0, 6.0]])
    np.testing.assert_array_equal(gradients(hm.heights, [[0, 1, 0, 1], [0, 1, 1, 2]]), [[7, -9], [15, -11]])
    assert _sorted(merge_rectangles(hm, 9.99)) == [(0, 1, 0, 1), (0, 1, 1, 2)]
    assert _sorted(merge_rectangles(hm, 10.0)) == [(0, 1, 0, 2)]  # <= (the paper merges above 10)


@pytest.mark.parametrize("shape", [(2, 2), (2, 9), (9, 2), (3, 3), (5, 2)])
def test_tiny_grids(shape, device):
    rng = np.random.default_rng(sum(shape))
    hm = _hm(rng.normal(size=shape))
    pt = build_polytree(hm, [0.0, 0.5, 1.0, 100.0], device=device)
    assert pt.polygons.n_polygons(pt.n_levels - 1) == 1
    for t in range(pt.n_levels):
        assert _sorted(pt.polygons.level(t)) == _ref_merge(hm.heights, float(pt.polygons.tolerances[t]))
        assert check_watertight(pt.mesh(t)).watertight
    if pt.n_levels > 1:
        assert check_watertight(pt.morph_mesh(0.5)).n_triangles > 0


def test_level_for_distance():
    hm = Heightmap.fbm(33, seed=1, max_height=200.0, feature_size=8.0)
    pt = build_polytree(hm, default_tolerances(hm, 20))
    last = pt.n_levels - 1
    assert pt.level_for_distance(10.0, 100.0, 1000.0) == 0.0
    assert pt.level_for_distance(5000.0, 100.0, 1000.0) == last
    assert pt.level_for_distance(550.0, 100.0, 1000.0) == pytest.approx(last / 2)
    assert pt.level_for_distance(550.0, 100.0, 1000.0, levels=(1, 3)) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="fine_distance"):
        pt.level_for_distance(1.0, 10.0, 5.0)


def test_polytree_father_pointers_nest_level_by_level():
    from terrainwarp.kernels.polytree import MergeState

    hm = Heightmap.fbm(41, 37, seed=5, max_height=300.0, feature_size=16.0)
    st = MergeState(hm.heights)
    root, _, _ = st.run_pass(20.0)
    levels = [st.level(m) for m in range(st.depth + 1)]
    assert len(levels[0][0]) == 40 * 36 and np.array_equal(levels[-1][0], root)
    assert _sorted(levels[0][0]) == [(i, i + 1, j, j + 1) for i in range(40) for j in range(36)]
    for m in range(st.depth):
        a, f = levels[m]
        c = levels[m + 1][0]
        # every polygon of level m points to the polygon of level m+1 it became part of, which contains it
        assert np.all((f >= 0) & (f < len(c)))
        b = c[f]
        assert np.all((b[:, 0] <= a[:, 0]) & (a[:, 1] <= b[:, 1]) & (b[:, 2] <= a[:, 2]) & (a[:, 3] <= b[:, 3]))
        # and the sons' polygons tile each father exactly
        area = np.zeros(len(c), np.int64)
        np.add.at(area, f, (a[:, 1] - a[:, 0]) * (a[:, 3] - a[:, 2]))
        np.testing.assert_array_equal(area, (c[:, 1] - c[:, 0]) * (c[:, 3] - c[:, 2]))
        assert len(a) >= len(c)  # each level refines the next one
    # following the father pointers from every cell ends at the root polygon covering it (section 2.1)
    lab = np.full((40, 36), -1)
    for c, (i0, _, j0, _) in enumerate(levels[0][0]):
        r = c
        for m in range(st.depth):
            r = levels[m][1][r]
        lab[i0, j0] = r
    for k, (i0, i1, j0, j1) in enumerate(root):
        assert np.all(lab[i0:i1, j0:j1] == k)
    with pytest.raises(ValueError, match="m:"):
        st.level(st.depth + 1)


# ------------------------------------------------------------------------------------------------
# incremental passes against the per-tolerance algorithm
# ------------------------------------------------------------------------------------------------


def _ref_check(pt, ref):
    """Every pass of a Polytree equals the reference's, exactly and in order."""
    pa = pt.polygons
    assert pa.n_levels == len(ref)
    for t, (rects, grads, flags, stats) in enumerate(ref):
        lo, hi = pa.start[t], pa.start[t + 1]
        np.testing.assert_array_equal(pa.rects[lo:hi], rects, err_msg=f"pass {t}")
        np.testing.assert_array_equal(pa.grads[lo:hi], grads, err_msg=f"pass {t}")
        np.testing.assert_array_equal(pa.flags[lo:hi], flags, err_msg=f"pass {t}")
        np.testing.assert_array_equal(pt.pass_stats[t], stats, err_msg=f"pass {t}")


@pytest.mark.parametrize("shape,seed,stop", [((33, 33), 3, True), ((29, 19), 4, False), ((18, 41), 5, True)])
def test_incremental_passes_equal_the_per_tolerance_algorithm(shape, seed, stop, device):
    rng = np.random.default_rng(seed)
    h = np.cumsum(rng.normal(size=shape), axis=0) * 2.0 + np.cumsum(rng.normal(size=shape), axis=1)
    h[: shape[0] // 3, : shape[1] // 4] = 3.0  # a flat corner that freezes at tolerance 0
    hm = _hm(h.astype(np.float32))
    tols = list(default_tolerances(hm, 14)) + ([1e9, 1e9] if not stop else [])
    tols = sorted(tols[:3] + [tols[2]] + tols[3:])  # a repeated tolerance: a pass that merges nothing
    pt = build_polytree(hm, tols, stop_at_one=stop, device=device)
    ref = _ref_passes(hm.heights, tols, stop_at_one=stop)
    assert len(ref) > 5 and len(ref[0][0]) > len(ref[-1][0])
    _ref_check(pt, ref)


def test_incremental_passes_on_quantised_heights_with_ties(device):
    # quantised heights: many similarities exactly equal to a tolerance (d <= tol merges, ties included)
    rng = np.random.default_rng(11)
    hm = _hm(np.round(rng.normal(size=(26, 35)) * 2.0) / 4.0)
    tols = [0.0, 0.25, 0.5, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 16.0, 64.0]
    pt = build_polytree(hm, tols, stop_at_one=False, device=device)
    _ref_check(pt, _ref_passes(hm.heights, tols, stop_at_one=False))


def test_passes_split_across_threads_equal_the_per_tolerance_algorithm(monkeypatch):
    # every pass through the subtree launch (a pass of a small grid merges too few nodes for it otherwise):
    # on 2, 3 and 8 threads the subtrees' undo and merge run on different threads; the passes (polygons, flags,
    # counters) must equal the per-tolerance algorithm and the one-thread run, bit for bit
    from terrainwarp.kernels.parallel import set_threads
    from terrainwarp.kernels.polytree import MergeState

    monkeypatch.setattr(MergeState, "PARALLEL_MIN_NODES", 0)
    rng = np.random.default_rng(21)
    shape = (61, 45)  # depth 6: the subtrees are the 64 nodes of level 3
    h = np.cumsum(rng.normal(size=shape), axis=0) * 2.0 + np.cumsum(rng.normal(size=shape), axis=1)
    h[: shape[0] // 4, : shape[1] // 3] = 1.0  # a flat corner that freezes at tolerance 0
    hm = _hm(h.astype(np.float32))
    tols = sorted(list(default_tolerances(hm, 16)) + [1e9])
    ref = _ref_passes(hm.heights, tols, stop_at_one=False)
    digests = []
    try:
        for n in (1, 2, 3, 8):
            set_threads(n)
            pt = build_polytree(hm, tols, stop_at_one=False)
            _ref_check(pt, ref)
            digests.append(digest(pt.polygons.rects, pt.polygons.grads, pt.polygons.flags, pt.pass_stats))
    finally:
        set_threads(None)
    assert len(set(digests)) == 1
    assert len(ref[0][0]) > 200 and len(ref[-1][0]) == 1  # the passes did real work, down to one polygon
