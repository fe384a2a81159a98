"""The relaxed quadtree (JAX): the probability that each node is in the tree and splits, top-down, with the 2:1
balance's forced splits relaxed bottom-up; the maps from samples and neighbours to nodes. Used by
:class:`terrainwarp.fit.relaxed.QuadtreeModel`."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..lod.quadtree import Terrain

__all__ = ["node_of", "inside_counts", "tree_probs", "forces", "balance_maps", "subset"]


def node_of(rows: np.ndarray, cols: np.ndarray, terrain: Terrain, level: int, inside: tuple[int, int]) -> np.ndarray:
    """Each sample's node at ``level`` (row-major index in the level's full grid), the sample on a node's last
    row or column given to the node before it when the next one lies outside the grid."""
    s = terrain.root_cells / 2.0 ** level
    nx = terrain.roots[0] << level
    x = np.minimum(np.floor(cols / s).astype(np.int64), inside[0] - 1)
    y = np.minimum(np.floor(rows / s).astype(np.int64), inside[1] - 1)
    return (y * nx + x).astype(np.int32)


def inside_counts(terrain: Terrain) -> list[tuple[int, int]]:
    """Per level, the columns and rows of nodes inside the grid (:meth:`Terrain.inside`'s rule: those of
    :meth:`Terrain.inside_counts`, and the first root, which is always inside)."""
    out = []
    for c0, c1 in terrain.inside_counts():
        out.append((max(int(c0) if c1 > 0 else 0, 1), max(int(c1) if c0 > 0 else 0, 1)))
    return out


def tree_probs(policy: list, force: list, vis: list, parents: list) -> tuple[list, list]:
    """Top-down: each level's probability that a node is in the tree, and that it splits given that it is. A node
    the descent reached (its parent split by the policy) splits by the policy or when forced; one a forced split
    made (a leaf of the balance) splits only when forced."""
    inside, total = [], []
    desc = tree = vis[0]
    for L in range(len(policy)):
        if L:
            desc = desc_prev[parents[L]] * policy[L - 1][parents[L]]  # noqa: F821 - set below, one level up
            tree = tree_prev[parents[L]] * total[L - 1][parents[L]]  # noqa: F821
        by_policy = desc * policy[L] / jnp.maximum(tree, 1e-12)
        total.append(1.0 - (1.0 - by_policy) * (1.0 - force[L]))
        inside.append(tree)
        desc_prev, tree_prev = desc, tree  # noqa: F841
    return inside, total


def forces(total: list, inside: list, vis: list, maps: list) -> list:
    """Bottom-up, the 2:1 balance relaxed: the probability that a node is forced to split because a neighbour
    across an edge is in the tree and split with an adjacent child that splits (a leaf two levels finer than it).
    The two deepest levels are never forced."""
    out = [jnp.zeros_like(v) for v in vis]
    for L in range(len(total) - 3, -1, -1):
        nbr, adj, ok = maps[L]
        child = total[L + 1][adj] * ok  # (N_L, 8): each direction's two children of the neighbour touching the node
        m = (inside[L] * total[L])[nbr]
        out[L] = (1.0 - jnp.prod(1.0 - m * child, axis=1)) * vis[L]
    return out


def balance_maps(terrain: Terrain) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per level L below the two deepest: for each node, its neighbour in each direction (twice: one per adjacent
    child), the neighbour's two children at L + 1 that touch it (west, north, east, south), and 1 where both
    exist (row-major indices in each level's full grid)."""
    out = []
    for L in range(max(terrain.depth - 1, 0)):
        nx, nz = terrain.roots[0] << L, terrain.roots[1] << L
        yy, xx = np.meshgrid(np.arange(nz), np.arange(nx), indexing="ij")
        x, y = xx.reshape(-1), yy.reshape(-1)
        nbrs, adjs, oks = [], [], []
        # (dx, dy) of the neighbour and its children's (cx, cy) offsets that touch this node
        for dx, dy, kids in ((-1, 0, ((1, 0), (1, 1))), (0, -1, ((0, 1), (1, 1))), (1, 0, ((0, 0), (0, 1))),
                             (0, 1, ((0, 0), (1, 0)))):
            mx, my = x + dx, y + dy
            inside = (mx >= 0) & (mx < nx) & (my >= 0) & (my < nz)
            m = np.where(inside, my * nx + mx, 0)
            for cx, cy in kids:
                nbrs.append(m)
                adjs.append(np.where(inside, (2 * my + cy) * (2 * nx) + 2 * mx + cx, 0))
                oks.append(inside)
        out.append((np.stack(nbrs, 1).astype(np.int32), np.stack(adjs, 1).astype(np.int32),
                    np.stack(oks, 1).astype(np.float32)))
    return out


def subset(total: int, n: int) -> np.ndarray:
    """The indices of :meth:`CameraProbe.subset` (the same deterministic subset)."""
    if total <= n:
        return np.arange(total)
    return np.sort(np.random.default_rng(0x7E55).choice(total, size=n, replace=False))
