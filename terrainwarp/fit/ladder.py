"""The continuous policy's probe surfaces (:mod:`terrainwarp.fit.probe`): a level's patches drawn at one uniform
factor (a rung of :func:`terrainwarp.fit.relaxed_continuous.factor_ladder`), at the samples the cameras see, without
tessellating every patch.

At one uniform factor every patch of a level is the same tessellation of its domain: one pattern per factor
(:func:`terrainwarp.kernels.tessellator.tessellate_patches` of one patch). A sample's local position in its patch
is one of the ``(s + 1)^2`` points of an ``s``-cell patch, so the pattern triangles that may hold it are listed
once per (factor, s). For each sample this module then does what tessellating every patch and
:func:`terrainwarp.kernels.sample_error.surface_at` would: it places those triangles' vertices as the domain
shader does (the patch's 2^-16-cell lattice, :func:`terrainwarp.kernels.sampling.sample_grid`'s height, the
camera-relative float32 position), takes the lowest-numbered triangle that holds the sample (the same inclusive
float64 test, patches numbered in the list's order) and evaluates its plane there, in the same float64
arithmetic: the surface is the one the pipeline draws, bit for bit (tested against tessellating and measuring
every patch). Work grows with the samples seen, not with the factor: a factor-64 rung of a level of 4-cell patches
is 8,192 triangles a patch where the cameras see ~25 samples.

Patches that reach past the grid (their points clamp to its border, which bends their triangles) are tessellated
and measured as they are; each sample takes the lowest-numbered triangle of the two kinds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..camera import relative_origin
from ..heightmap import Heightmap
from ..kernels.sample_error import CONTAIN_ULPS, NONE, surface_at
from ..kernels.sampling import sample_grid
from ..kernels.tessellator import FXP_ONE, frame_lattice, tessellate_patches
from ..lod.quadtree import PatchList
from ..mesh import Mesh
from .probe import Sight, surfaces_of

__all__ = ["ladder_surfaces"]

MESH_BELOW = 10  # a rung with fewer triangles than this many per sample seen is tessellated whole (cheaper)
F32_ULP = 5.9604644775390625e-08  # 2^-24: the kernels' float32 ulp factor
REACH = 0.01  # cells, at least: how far outside a pattern triangle's box a sample may still be held (the test's
#               slack, CONTAIN_ULPS float32 ulps of the coordinates, is ~0.002 cells on a 41 km terrain of 10 m cells)


@dataclass(frozen=True)
class _Level:
    """One level's patches (the list's order is the triangles' numbering) and what places their points."""

    hm: Heightmap
    pl: PatchList
    cells: int  # the patches' side in cells
    box: np.ndarray  # (P, 4) int64 lattice ranges (x0, z0, x1, z1), 2^-16 cells
    eye_l: np.ndarray  # (2,) int64 the eye on the lattice
    eye_rem: np.ndarray  # (3,) float32 the eye's remainder (x, y, z)
    cell: np.ndarray  # (2,) float32 metres per lattice step
    rel: np.ndarray  # (3,) float32 the measuring eye's grid origin (relative_origin)
    spacing: str
    filter: str
    border: np.ndarray  # (P,) bool: the patch reaches past the grid
    eye: tuple[float, float, float]
    reach: float  # cells: how far outside a pattern triangle's box a sample may still be held


def ladder_surfaces(heightmap: Heightmap, pl: PatchList, factors: np.ndarray, at: Sight, eye: tuple,
                    spacing: str, filter: str, mesh: Callable[[float], Mesh], device: str = "cpu") -> list[np.ndarray]:
    """Each rung's surface height (world m, float64 (U,), ``at``'s samples; NaN where no patch holds one): the
    patches of ``pl`` (one level, in their drawing order) tessellated at each uniform factor of ``factors``,
    displaced as seen from ``eye`` (the mesh's eye), as :func:`terrainwarp.fit.probe.surfaces_of` measures
    ``mesh(factor)`` (the rung drawn whole: used where it has fewer than :data:`MESH_BELOW` triangles a sample
    seen, and on a heightmap with no-data holes, whose triangles the pipeline drops)."""
    lv = _level(heightmap, pl, eye, spacing, filter)
    rank = _ranks(lv)
    pairs = {b: _sample_patches(lv, rank, at, border=b) for b in (False, True)}  # (sample, patch) pairs
    out = []
    for f in factors:
        uv, tris = _pattern(lv, float(f), device)
        if heightmap.has_nodata or len(pl) * len(tris) <= MESH_BELOW * max(len(at.rows), 1):
            out.append(surfaces_of(heightmap, [mesh(float(f))], at, device)[0])
            continue
        y = np.full(len(at.rows), np.nan)
        best = np.full(len(at.rows), np.iinfo(np.int64).max)
        _interior(lv, pairs[False], uv, tris, at, y, best, device)
        _border(lv, float(f), len(tris), pairs[True], at, y, best, device)
        out.append(y + float(eye[1]))
    return out


def _level(hm: Heightmap, pl: PatchList, eye: tuple, spacing: str, filter: str) -> _Level:
    """The lattice of ``pl``'s patches and the eye, as the tessellator's host side computes them."""
    p = len(pl)
    one = {"origin_xz": np.zeros((1, 2)), "size": np.ones(1), "outer": np.ones((1, 4), np.float32),
           "inner": np.ones((1, 2), np.float32)}
    patches = {"origin_xz": pl.origin, "size": pl.size, "outer": np.ones((p, 4), np.float32),
               "inner": np.ones((p, 2), np.float32), "level": pl.level} if p else one
    lat = frame_lattice(patches, hm.heights, hm.dx, hm.dz, eye, spacing, filter, hm.origin)
    box, el_int, rem, cell = lat.box[:p], lat.eye_cell, lat.eye_rem, lat.cell
    lim = np.array([(hm.shape[1] - 1) << 16, (hm.shape[0] - 1) << 16], np.int64)
    border = (box[:, 2] > lim[0]) | (box[:, 3] > lim[1]) | (box[:, 0] < 0) | (box[:, 1] < 0)
    cells = int(round(float(pl.size_cells[0]))) if p else 1
    rel = np.asarray(relative_origin(hm.origin, eye), np.float32)
    far = max(abs(float(rel[0])), abs(float(rel[2]))) + max(hm.shape[1] * hm.dx, hm.shape[0] * hm.dz)
    reach = REACH + 4.0 * CONTAIN_ULPS * F32_ULP * far / min(hm.dx, hm.dz)
    return _Level(hm, pl, cells, box, np.asarray(el_int, np.int64), np.asarray(rem, np.float32),
                  np.asarray(cell, np.float32), rel, spacing, filter, border,
                  tuple(float(v) for v in eye), reach)


def _ranks(lv: _Level) -> np.ndarray:
    """(nz, nx) int64 each patch's place in the list by its (row, column) of the level's grid (-1: none)."""
    s = lv.cells
    px = np.rint(lv.pl.origin_cells[:, 0] / s).astype(np.int64)
    py = np.rint(lv.pl.origin_cells[:, 1] / s).astype(np.int64)
    out = np.full((int(py.max(initial=0)) + 2, int(px.max(initial=0)) + 2), -1, np.int64)
    out[py, px] = np.arange(len(px))
    return out


def _pattern(lv: _Level, f: float, device: str) -> tuple[np.ndarray, np.ndarray]:
    """One patch at uniform factor ``f``: its points' 16.16 domain coordinates (n, 2) int64 and its triangles
    (m, 3) int32, as the mesh numbers and orders them."""
    t = tessellate_patches({"origin_xz": np.zeros((1, 2)), "size": np.ones(1), "outer": np.full((1, 4), f, np.float32),
                            "inner": np.full((1, 2), f, np.float32)}, np.zeros((2, 2), np.float32), 1.0, 1.0,
                           (0.0, 0.0, 0.0), spacing=lv.spacing, device=device, need=("domain",))
    uv = np.rint(np.asarray(t.domain, np.float64) * FXP_ONE).astype(np.int64)
    return uv, np.asarray(t.triangles, np.int32)


def _candidates(uv: np.ndarray, tris: np.ndarray, s: int, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """For each local point (a, b) of an ``s``-cell patch (id ``b * (s + 1) + a``), the pattern triangles whose
    domain box, widened by ``reach`` cells, holds it, in the pattern's order: (ptr (points + 1,), tri)."""
    t = uv[tris].astype(np.float64) / FXP_ONE * s  # (m, 3, 2) in cells
    lo, hi = t.min(axis=1) - reach, t.max(axis=1) + reach
    a0 = np.clip(np.ceil(lo[:, 0]), 0, s).astype(np.int64)
    a1 = np.clip(np.floor(hi[:, 0]), -1, s).astype(np.int64)
    b0 = np.clip(np.ceil(lo[:, 1]), 0, s).astype(np.int64)
    b1 = np.clip(np.floor(hi[:, 1]), -1, s).astype(np.int64)
    wa, wb = np.maximum(a1 - a0 + 1, 0), np.maximum(b1 - b0 + 1, 0)
    n = wa * wb
    tri = np.repeat(np.arange(len(tris)), n)
    k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    pid = (np.repeat(b0, n) + k // np.repeat(np.maximum(wa, 1), n)) * (s + 1) + np.repeat(a0, n) + k % np.repeat(
        np.maximum(wa, 1), n)
    q = np.stack([pid % (s + 1), pid // (s + 1)], axis=1).astype(np.float64)
    near = _distance(t[tri], q) <= reach  # in the triangle or within reach of it
    pid, tri = pid[near], tri[near]
    order = np.argsort(pid, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(pid, minlength=(s + 1) ** 2))])
    return ptr, tri[order]


def _distance(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(K,) the distance of each point ``q`` (K, 2) from its triangle ``t`` (K, 3, 2) (0 inside)."""
    d = np.full(len(q), np.inf)
    inside = np.ones(len(q), bool)
    area = ((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1]
                                                                                                 - t[:, 0, 1]))
    sg = np.where(area < 0, -1.0, 1.0)
    for i in range(3):
        a, b = t[:, i], t[:, (i + 1) % 3]
        e = b - a
        cross = (e[:, 0] * (q[:, 1] - a[:, 1]) - e[:, 1] * (q[:, 0] - a[:, 0])) * sg
        inside &= cross >= 0
        u = np.clip(((q - a) * e).sum(axis=1) / np.maximum((e * e).sum(axis=1), 1e-300), 0.0, 1.0)
        d = np.minimum(d, np.hypot(*(q - (a + u[:, None] * e)).T))
    return np.where(inside, 0.0, d)


def _interior(lv: _Level, pairs: tuple[np.ndarray, np.ndarray], uv: np.ndarray, tris: np.ndarray, at: Sight,
              y: np.ndarray, best: np.ndarray, device: str) -> None:
    """The samples held by the patches that lie inside the grid (``pairs``: (sample, patch)): ``y`` and ``best``
    (the holding triangle's global number, patch-major) set where a triangle holds one."""
    s, m = lv.cells, len(tris)
    smp, pat = pairs
    if not len(smp):
        return
    ptr, cand = _candidates(uv, tris, s, lv.reach)
    a = at.cols[smp].astype(np.int64) - np.rint(lv.pl.origin_cells[pat, 0]).astype(np.int64)
    b = at.rows[smp].astype(np.int64) - np.rint(lv.pl.origin_cells[pat, 1]).astype(np.int64)
    pid = b * (s + 1) + a
    cnt = ptr[pid + 1] - ptr[pid]
    k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    tri = cand[np.repeat(ptr[pid], cnt) + k]
    smp, pat = np.repeat(smp, cnt), np.repeat(pat, cnt)
    verts = _vertices(lv, uv, pat, tris[tri], device)  # (T, 3, 3) float64
    p = _sample_xz(lv, at.rows[smp], at.cols[smp])
    ok = _inside(verts, p)
    glob = pat * m + tri
    smp, glob, verts, p = smp[ok], glob[ok], verts[ok], p[ok]
    order = np.lexsort((glob, smp))  # per sample, the lowest-numbered holder first
    first = order[np.concatenate([[True], smp[order][1:] != smp[order][:-1]])] if len(order) else order
    take = glob[first] < best[smp[first]]
    first = first[take]
    best[smp[first]] = glob[first]
    y[smp[first]] = _plane_y(verts[first], p[first])


def _sample_patches(lv: _Level, rank: np.ndarray, at: Sight, *, border: bool) -> tuple[np.ndarray, np.ndarray]:
    """(sample, patch) pairs: each sample with every patch whose closed square holds it (up to four on patch
    corners), of the patches inside the grid (or, with ``border``, of those reaching past it)."""
    s = lv.cells
    r, c = at.rows.astype(np.int64), at.cols.astype(np.int64)
    smp, pat = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            px, py = c // s - dx, r // s - dy
            on = ((dx == 0) | (c % s == 0)) & ((dy == 0) | (r % s == 0)) & (px >= 0) & (py >= 0)
            on &= (px < rank.shape[1]) & (py < rank.shape[0])
            k = np.flatnonzero(on)
            q = rank[py[k], px[k]]
            keep = q >= 0
            k, q = k[keep], q[keep]
            keep = lv.border[q] == border
            smp.append(k[keep])
            pat.append(q[keep])
    return np.concatenate(smp), np.concatenate(pat)


def _vertices(lv: _Level, uv: np.ndarray, pat: np.ndarray, corners: np.ndarray, device: str) -> np.ndarray:
    """(T, 3, 3) float64 the camera-relative positions (float32, as the domain shader writes them) of the pattern
    points ``corners`` (T, 3) in the patches ``pat`` (T,)."""
    su, sv = uv[corners, 0], uv[corners, 1]  # (T, 3) 16.16
    box = lv.box[pat]
    nx = np.clip(_lattice(box[:, 0:1], box[:, 2:3], su), 0, (lv.hm.shape[1] - 1) << 16)
    nz = np.clip(_lattice(box[:, 1:2], box[:, 3:4], sv), 0, (lv.hm.shape[0] - 1) << 16)
    gx, gz = _grid(nx), _grid(nz)
    h = sample_grid(lv.hm.heights, gx, gz, lv.filter, device=device)
    px = (nx - lv.eye_l[0]).astype(np.float32) * lv.cell[0] - lv.eye_rem[0]
    pz = (nz - lv.eye_l[1]).astype(np.float32) * lv.cell[1] - lv.eye_rem[2]
    py = h - lv.eye_rem[1]
    return np.stack([px, py, pz], axis=-1).astype(np.float64)


def _lattice(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The tessellator's lattice coordinate at 16.16 domain coordinate ``s`` of the range [a, b], mirror-symmetric."""
    return np.where(s <= 32768, a + (((b - a) * s) >> 16), b - (((b - a) * (65536 - s)) >> 16))


def _grid(n: np.ndarray) -> np.ndarray:
    """Lattice coordinate (2^-16 cells) -> float32 grid coordinate, one rounding (the kernel's ``_grid``)."""
    return (n >> 16).astype(np.float32) + (n & 65535).astype(np.float32) * np.float32(1.52587890625e-05)


def _sample_xz(lv: _Level, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(T, 2) float64 camera-relative (x, z) of the samples, float32 as the kernels place them."""
    x = lv.rel[0] + cols.astype(np.float32) * np.float32(lv.hm.dx)
    z = lv.rel[2] + rows.astype(np.float32) * np.float32(lv.hm.dz)
    return np.stack([x, z], axis=-1).astype(np.float64)


def _inside(v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The kernels' inclusive point-in-triangle test (``_inside``) of the points ``p`` (T, 2) in the triangles
    ``v`` (T, 3, 3), in the same float64 arithmetic."""
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 2] - a[:, 2]) - (c[:, 0] - a[:, 0]) * (b[:, 2] - a[:, 2])
    m = np.maximum(np.maximum(np.maximum(np.abs(a[:, 0]), np.abs(a[:, 2])), np.maximum(np.abs(b[:, 0]),
                                                                                        np.abs(b[:, 2]))),
                   np.maximum(np.maximum(np.abs(c[:, 0]), np.abs(c[:, 2])), np.maximum(np.abs(p[:, 0]),
                                                                                       np.abs(p[:, 1]))))
    tol = CONTAIN_ULPS * F32_ULP * m
    sg = np.sign(det)
    e0 = sg * ((c[:, 0] - b[:, 0]) * (p[:, 1] - b[:, 2]) - (c[:, 2] - b[:, 2]) * (p[:, 0] - b[:, 0]))
    e1 = sg * ((a[:, 0] - c[:, 0]) * (p[:, 1] - c[:, 2]) - (a[:, 2] - c[:, 2]) * (p[:, 0] - c[:, 0]))
    e2 = sg * ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 2]) - (b[:, 2] - a[:, 2]) * (p[:, 0] - a[:, 0]))
    l0 = np.sqrt((c[:, 0] - b[:, 0]) * (c[:, 0] - b[:, 0]) + (c[:, 2] - b[:, 2]) * (c[:, 2] - b[:, 2]))
    l1 = np.sqrt((a[:, 0] - c[:, 0]) * (a[:, 0] - c[:, 0]) + (a[:, 2] - c[:, 2]) * (a[:, 2] - c[:, 2]))
    l2 = np.sqrt((b[:, 0] - a[:, 0]) * (b[:, 0] - a[:, 0]) + (b[:, 2] - a[:, 2]) * (b[:, 2] - a[:, 2]))
    return (det != 0.0) & (e0 >= -tol * l0) & (e1 >= -tol * l1) & (e2 >= -tol * l2)


def _plane_y(v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The kernels' ``_plane_y``: each triangle's plane height at its point (a vertex there: its own height)."""
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 2] - a[:, 2]) - (c[:, 0] - a[:, 0]) * (b[:, 2] - a[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        wb = ((p[:, 0] - a[:, 0]) * (c[:, 2] - a[:, 2]) - (c[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 2])) / det
        wc = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 2]) - (p[:, 0] - a[:, 0]) * (b[:, 2] - a[:, 2])) / det
        y = (1.0 - wb - wc) * a[:, 1] + wb * b[:, 1] + wc * c[:, 1]
    y = np.where(det == 0.0, np.nan, y)
    for q in (c, b, a):  # the kernel checks a, then b, then c: the first match wins
        y = np.where((q[:, 0] == p[:, 0]) & (q[:, 2] == p[:, 1]), q[:, 1], y)
    return y


def _border(lv: _Level, f: float, per: int, pairs: tuple[np.ndarray, np.ndarray], at: Sight, y: np.ndarray,
            best: np.ndarray, device: str) -> None:
    """The patches that reach past the grid (``pairs``: (sample, patch)), tessellated at ``f`` and measured as the
    pipeline does (their clamped points bend their triangles); a sample takes their triangle where it is numbered
    lower than the inside one."""
    smp, pat = pairs
    if not len(smp):
        return
    k = np.unique(pat)
    near = np.unique(smp)
    pl = lv.pl
    t = tessellate_patches({"origin_xz": pl.origin[k], "size": pl.size[k], "outer": np.full((len(k), 4), f, np.float32),
                            "inner": np.full((len(k), 2), f, np.float32), "level": pl.level[k]}, lv.hm.heights,
                           lv.hm.dx, lv.hm.dz, lv.eye, spacing=lv.spacing, filter=lv.filter, origin=lv.hm.origin,
                           device=device)
    rel = tuple(float(v) for v in relative_origin(lv.hm.origin, lv.eye))
    yy, tri = surface_at(t.positions, t.triangles, (0.0, 0.0, 0.0), rel, (lv.hm.dx, lv.hm.dz), lv.hm.shape,
                         at.rows[near], at.cols[near], device=device)
    held = tri != NONE
    glob = k[tri[held] // per] * per + tri[held] % per
    idx = near[held]
    take = glob < best[idx]
    best[idx[take]] = glob[take]
    y[idx[take]] = yy[held][take]
