"""Precomputed cell-to-cell visibility for ground-based observers (mrbsp-lod-visibility.txt, section 4).

The observer walks on the eye surface, ``eye_height`` (1.8 m) above the terrain. The root square of a
:class:`~terrainwarp.lod.bintree.Bintree` is divided into ``cells`` rectangular cells; for each cell and
each node of a coarse level ``Lc`` of the tree (the "blockees"), a kernel decides whether the node can
be seen from somewhere in the cell (area-to-area, by sampling: ``samples x samples`` eye points per cell
at the cell's highest surface point + eye height, 7 target points per node at the node's highest
subtree point) against coarse blockers (the minimum height of the level-M surface over squares of
``blocker_cells`` per side). Only the base cell's set and the changes between neighbouring cells are
stored; at run time :class:`VisibilityState` toggles node flags as the observer crosses cells (walking a
path of neighbouring cells when it jumps), and finer nodes inherit their coarse ancestor's flag.

Conservativeness: blockers lie below the terrain, raised end points only lift the tested segments and
sampled segments only miss occluders, so every *tested* segment that is unoccluded in the terrain is
found visible. Eye positions between the samples are not covered by an argument, only by the raise to
the cell maximum; the tests and the benchmark measure misses with the rasterizer (0 expected) and the
hidden triangles kept.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..kernels.checks import check_int
from ..kernels.visibility import cell_node_visibility
from .bintree import Bintree

__all__ = ["VisibilityTable", "VisibilityState", "precompute_visibility", "encode", "expand"]

EYE_HEIGHT = 1.8


def _pos_int(name: str, v: object, lo: int = 1) -> int:
    return check_int(name, v, lo)


@dataclass(frozen=True, eq=False)
class VisibilityTable:
    """Stored visibility: the base cell's coarse node set and the cell-to-cell changes.

    Attributes:
        tree: the :class:`Bintree`.
        cells: (rows along z, columns along x).
        coarse_level: Lc, the level of the blockee nodes.
        base: (k,) heap indices of the nodes visible from cell (0, 0), in the hierarchical encoding of
            the paper's Table 1: a node stands for all its level-Lc descendants ("11" for 1100..1111),
            emitted at the coarsest level where a whole subtree is in the set (uint16 when Lc <= 15).
        right_ptr, right_ids: CSR lists (same encoding) of the nodes whose level-Lc descendants toggle
            between cell (i, j) and (i, j + 1), pair index ``i * (cols - 1) + j``.
        down_ptr, down_ids: the same between (i, j) and (i + 1, j), pair index ``i * cols + j``.
        preprocess_s: wall time of the precomputation; params: the sampling parameters.
    """

    tree: Bintree
    cells: tuple[int, int]
    coarse_level: int
    base: np.ndarray
    right_ptr: np.ndarray
    right_ids: np.ndarray
    down_ptr: np.ndarray
    down_ids: np.ndarray
    preprocess_s: float
    params: dict = field(default_factory=dict)

    # -- geometry -----------------------------------------------------------------------------------
    @property
    def n_coarse(self) -> int:
        return 1 << self.coarse_level

    @property
    def storage_bytes(self) -> int:
        """Bytes of the stored table (node ids as uint16 when Lc <= 15, else int32; int32 offsets)."""
        return int(sum(a.nbytes for a in (self.base, self.right_ptr, self.right_ids, self.down_ptr, self.down_ids)))

    @property
    def full_bytes(self) -> int:
        """Bytes of a full per-cell bitset table, for comparison."""
        return self.cells[0] * self.cells[1] * ((self.n_coarse + 7) // 8)

    def cell_of(self, x: float, z: float) -> tuple[int, int]:
        """The (row, column) of the cell containing world (x, z) (clamped to the grid)."""
        rows, cols = self.cells
        t = self.tree
        j = int(np.clip(np.floor((x - t.origin[0]) / t.side * cols), 0, cols - 1))
        i = int(np.clip(np.floor((z - t.origin[1]) / t.side * rows), 0, rows - 1))
        return i, j

    def compute_cells(self, cells: object) -> np.ndarray:
        """Recompute from scratch: (k, 2^Lc) uint8 coarse visibility of the (row, col) ``cells``."""
        c = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        return _compute(self.tree, self.cells, self.coarse_level, c, **self.params)

    def state(self, cell: tuple[int, int] = (0, 0)) -> VisibilityState:
        """A run-time state positioned in ``cell`` (walked to from the base cell)."""
        s = VisibilityState(self)
        s.move_to_cell(cell)
        return s


class VisibilityState:
    """Run-time visibility flags: the current cell and one flag per coarse node, toggled by the stored
    changes as the observer moves."""

    def __init__(self, table: VisibilityTable):
        self.table = table
        self.cell = (0, 0)
        self.coarse = np.zeros(table.n_coarse, np.uint8)
        self.coarse = expand(table.base, table.coarse_level)
        self.toggles = 0
        self._nodes: np.ndarray | None = None

    def _toggle(self, ids: np.ndarray) -> None:
        self.coarse ^= expand(ids, self.table.coarse_level)
        self.toggles += int(ids.size)
        self._nodes = None

    def move_to_cell(self, cell: tuple[int, int]) -> None:
        """Walk to ``cell`` through neighbouring cells (columns first, then rows), toggling on the way."""
        t = self.table
        rows, cols = t.cells
        ti, tj = int(cell[0]), int(cell[1])
        if not (0 <= ti < rows and 0 <= tj < cols):
            raise ValueError(f"cell: expected a cell in [0, {rows}) x [0, {cols}), got {cell}")
        i, j = self.cell
        while j != tj:
            jj = j if tj > j else j - 1
            p = i * (cols - 1) + jj
            self._toggle(t.right_ids[t.right_ptr[p]:t.right_ptr[p + 1]])
            j += 1 if tj > j else -1
        while i != ti:
            ii = i if ti > i else i - 1
            p = ii * cols + j
            self._toggle(t.down_ids[t.down_ptr[p]:t.down_ptr[p + 1]])
            i += 1 if ti > i else -1
        self.cell = (i, j)

    def move_to(self, x: float, z: float) -> None:
        """Move the observer to world (x, z)."""
        self.move_to_cell(self.table.cell_of(x, z))

    def node_flags(self) -> np.ndarray:
        """(2**(M+1) - 1,) uint8 flag per heap node: a node at level >= Lc takes its level-Lc ancestor's
        flag; a coarser node is visible when any of its level-Lc descendants is (root square: 1)."""
        if self._nodes is None:
            t = self.table.tree
            lc = self.table.coarse_level
            out = np.zeros(t.n_nodes, np.uint8)
            out[0] = 1
            for level in range(1, t.depth + 1):
                s = t.level_slice(level)
                if level >= lc:
                    out[s] = np.repeat(self.coarse, 1 << (level - lc))
                else:
                    out[s] = self.coarse.reshape(1 << level, -1).max(axis=1)
            self._nodes = out
        return self._nodes


def encode(mask: np.ndarray, level: int) -> np.ndarray:
    """Hierarchical encoding of a (2**level,) 0/1 mask over the nodes of ``level``: the heap indices of
    the maximal whole subtrees inside it, sorted (uint16 when level <= 15, else int32)."""
    m = np.asarray(mask, bool)
    full = [m]
    for _ in range(level):
        full.append(full[-1].reshape(-1, 2).all(axis=1))
    out = []
    for d in range(level + 1):  # d levels above ``level``
        lv = level - d
        keep = full[d] if d == level else full[d] & ~np.repeat(full[d + 1], 2)
        out.append(np.nonzero(keep)[0] + (1 << lv) - 1)
    ids = np.sort(np.concatenate(out))
    return ids.astype(np.uint16 if level <= 15 else np.int32)


def expand(ids: np.ndarray, level: int) -> np.ndarray:
    """Inverse of :func:`encode`: the (2**level,) uint8 mask (the subtrees are disjoint)."""
    g = np.asarray(ids, np.int64)
    lv = np.floor(np.log2(g + 1)).astype(np.int64)
    start = (g + 1 - (1 << lv)) << (level - lv)
    stop = start + (np.int64(1) << (level - lv))
    d = np.zeros((1 << level) + 1, np.int64)
    np.add.at(d, start, 1)
    np.add.at(d, stop, -1)
    return (np.cumsum(d[:-1]) > 0).astype(np.uint8)


def _cell_eyes(tree: Bintree, cells: tuple[int, int], which: np.ndarray, samples: int, eye_height: float,
               raised: bool) -> np.ndarray:
    rows, cols = cells
    g = tree.grid
    vh = tree.arrays["vertex_height"].numpy().reshape(g + 1, g + 1)  # [gz, gx]
    out = np.empty((len(which), samples * samples, 3), np.float64)
    f = np.linspace(0.0, 1.0, samples) if samples > 1 else np.array([0.5])
    for k, (i, j) in enumerate(which):  # cells asked for: a handful or all (a few hundred), host loop
        gx0, gx1 = int(np.floor(j * g / cols)) - 1, int(np.ceil((j + 1) * g / cols)) + 1
        gz0, gz1 = int(np.floor(i * g / rows)) - 1, int(np.ceil((i + 1) * g / rows)) + 1
        top = float(vh[max(gz0, 0):min(gz1, g) + 1, max(gx0, 0):min(gx1, g) + 1].max())
        xs = tree.origin[0] + (j + f) * tree.side / cols
        zs = tree.origin[1] + (i + f) * tree.side / rows
        xx, zz = np.meshgrid(xs, zs)
        out[k, :, 0] = xx.reshape(-1)
        out[k, :, 1] = (top if raised else tree.surface_height(xx, zz).reshape(-1)) + eye_height
        out[k, :, 2] = zz.reshape(-1)
    return out


def _node_targets(tree: Bintree, level: int, raised: bool) -> np.ndarray:
    s = tree.level_slice(level)
    v = tree.node_vertices()[s]
    g = tree.vertex_grid_xz(v).astype(np.float64)  # (n, 3, 2)
    cen = g.mean(axis=1, keepdims=True)
    pts = np.concatenate([g, 0.5 * (g + g[:, [1, 2, 0]]), cen], axis=1)  # corners, edge midpoints, centroid
    pts = cen + (pts - cen) * (1.0 - 1e-3)  # just inside the node
    hi = tree.arrays["hi"].numpy()[s].astype(np.float64)
    out = np.empty(pts.shape[:2] + (3,), np.float64)
    out[..., 0] = tree.origin[0] + pts[..., 0] * tree.step
    out[..., 1] = hi[:, None] + 1e-3 * max(tree.step, 1.0)
    out[..., 2] = tree.origin[1] + pts[..., 1] * tree.step
    return out


def _blockers(tree: Bintree, blocker_cells: int) -> tuple[np.ndarray, float]:
    g = tree.grid
    k = g // blocker_cells
    vh = tree.arrays["vertex_height"].numpy().reshape(g + 1, g + 1)
    # min over the closed square [i*k, (i+1)*k] of grid vertices: every level-M triangle lies inside one
    # square (k even, or M odd), so its surface there is >= the minimum of the square's vertices.
    a = np.minimum(vh[:-1, :-1], vh[1:, 1:])
    a = np.minimum(a, np.minimum(vh[1:, :-1], vh[:-1, 1:]))  # per grid cell: min of its 4 corners
    return a.reshape(blocker_cells, k, blocker_cells, k).min(axis=(1, 3)), tree.side / blocker_cells


def _compute(tree: Bintree, cells: tuple[int, int], coarse_level: int, which: np.ndarray, *, samples: int,
             eye_height: float, blocker_cells: int, raised: bool) -> np.ndarray:
    # the frame: relative to the root square's corner, so float32 keeps precision far from the origin
    eyes = _cell_eyes(tree, cells, which, samples, eye_height, raised)
    targets = _node_targets(tree, coarse_level, raised)
    blk, bs = _blockers(tree, blocker_cells)
    o = np.array([tree.origin[0], 0.0, tree.origin[1]])
    return cell_node_visibility((eyes - o).astype(np.float32), (targets - o).astype(np.float32), blk, (0.0, 0.0),
                                bs, device=tree.device)


def precompute_visibility(tree: Bintree, cells: int | tuple[int, int] = 16, coarse_level: int | None = None, *,
                          samples: int = 3, eye_height: float = EYE_HEIGHT,
                          blocker_cells: int | None = None, raised: bool = True) -> VisibilityTable:
    """Precompute the cell-to-cell visibility table.

    Args:
        tree: a :class:`Bintree`.
        cells: cells per side, or (rows along z, columns along x).
        coarse_level: Lc, level of the blockee nodes (default max(1, M - 6): 64 times coarser in area).
        samples: eye samples per cell side (samples**2 per cell, corners included when >= 2).
        eye_height: metres above the terrain (the paper: 1.8).
        blocker_cells: blocker squares per side (a power of two dividing G / 2 when M is even; default
            G / 4, at least 1).
        raised: True (default): eye samples at the cell's highest surface point + eye height and targets
            at the node's highest subtree point (each tested segment is then only lifted, see the module
            docstring); False: the paper's vertex-to-vertex sampling at the surface, tighter but it can
            miss a visible triangle (tests/lod/test_visibility.py has a DEM viewpoint where it does).

    Returns:
        :class:`VisibilityTable` (only the base set and the changes kept).
    """
    if not isinstance(tree, Bintree):
        raise TypeError(f"tree: expected a Bintree, got {type(tree).__name__}")
    cr, cc = (cells, cells) if not isinstance(cells, tuple | list) else tuple(cells)
    cr, cc = _pos_int("cells", cr), _pos_int("cells", cc)
    lc = max(1, tree.depth - 6) if coarse_level is None else coarse_level
    lc = _pos_int("coarse_level", lc)
    if lc > tree.depth:
        raise ValueError(f"coarse_level: expected 1..{tree.depth}, got {lc}")
    samples = _pos_int("samples", samples)
    if not (np.isfinite(eye_height) and eye_height >= 0):
        raise ValueError(f"eye_height: expected a finite height >= 0, got {eye_height}")
    g = tree.grid
    bc = max(1, g // 4) if blocker_cells is None else _pos_int("blocker_cells", blocker_cells)
    k = g // bc if bc <= g else 0
    if k == 0 or k * bc != g or (tree.depth % 2 == 0 and k % 2 and g > 1):
        raise ValueError(f"blocker_cells: expected a divisor of the vertex grid ({g}) leaving an even number of "
                         f"grid cells per square, got {bc}")
    params = {"samples": samples, "eye_height": float(eye_height), "blocker_cells": bc, "raised": bool(raised)}
    t0 = time.perf_counter()
    which = np.stack(np.meshgrid(np.arange(cr), np.arange(cc), indexing="ij"), axis=-1).reshape(-1, 2)
    full = _compute(tree, (cr, cc), lc, which, **params).reshape(cr, cc, -1)
    right = (full[:, 1:] ^ full[:, :-1]).reshape(-1, full.shape[-1])
    down = (full[1:, :] ^ full[:-1, :]).reshape(-1, full.shape[-1])

    def csr(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lists = [encode(r, lc) for r in m]  # per neighbouring pair (a few hundred), host loop
        ptr = np.zeros(len(m) + 1, np.int32)
        ptr[1:] = np.cumsum([len(x) for x in lists])
        return ptr, (np.concatenate(lists) if lists else np.zeros(0, np.uint16 if lc <= 15 else np.int32))

    rp, ri = csr(right)
    dp, di = csr(down)
    dt = time.perf_counter() - t0
    base = encode(full[0, 0], lc)
    return VisibilityTable(tree, (cr, cc), lc, base, rp, ri, dp, di, dt, params)
