"""CDLOD's model (JAX): distance-range selection with morphing, in its first range, LOD distance ratio and morph
start ratio (the grid is an integer, one model per grid).

**Selection, relaxed.** A node of LOD ``i`` is in range with probability ``q_i = sigmoid((log range_i - log d) /
temperature)`` (``d`` the eye-to-box distance, ``range_i = first_range * (1 + ratio + ... + ratio^i)``, the
coarsest infinite); as the selection walks down from the roots (:meth:`terrainwarp.lod.cdlod.Cdlod.select`), a
reached node out of range is drawn as its parent's quadrant (LOD ``i + 1``), one in range splits with ``q_{i-1}``
and is drawn whole otherwise. Each sample is drawn at a LOD with the probability of the node of its own that is
drawn. **Morph.** A sample drawn at LOD ``j`` morphs toward ``j + 1`` by ``k = clamp((d_s - morph_start_j) /
(morph_end_j - morph_start_j), 0, 1)`` (``d_s`` its eye distance): its error is taken as ``(1 - k) e_j + k e_{j+1}``
(the probes of the two unmorphed LODs), the bound the triangle inequality gives. **Cost**: a whole node draws four
quadrants of ``2 (g/2)^2`` triangles and ``(g + 1)^2`` vertices in one draw, a parent's quadrant one quadrant and
``(g/2 + 1)^2`` vertices in its own draw (the reference's pipeline statistics, :class:`terrainwarp.lod.cdlod.Cdlod`).
``hard`` selects for real and counts exactly.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..lod.cdlod import Cdlod, cdlod_ranges
from ..lod.quadtree import node_metrics
from ..scene import LodConfig
from .knobs import Knob
from .probe import CameraProbe
from .relaxed import hard_percentile, soft_quantile, sorted_pairs
from .search import Prediction

__all__ = ["CdlodModel"]


@dataclass(eq=False)
class CdlodModel:
    """CDLOD with one grid over a camera path.

    Attributes:
        scheme: the :class:`terrainwarp.lod.cdlod.Cdlod` of this grid (its pyramids; the knobs set per setting).
        probes: per camera, one resolution per LOD 0 (finest) .. levels - 1, unmorphed.
        knobs: the fitted continuous knobs among ``first_range``, ``ratio``, ``morph_start_ratio``.
    """

    scheme: Cdlod
    cams: list[Camera]
    probes: list[CameraProbe]
    knobs: Sequence[Knob]
    fixed: Mapping[str, float]
    config: Callable[[Mapping[str, float]], LodConfig]
    weights: Mapping[str, float]
    relaxed_samples: int = 1 << 13
    device: str = "cpu"

    @property
    def levels(self) -> int:
        return int(self.scheme.levels)

    @cached_property
    def _tree(self) -> dict[str, Any]:
        t = self.scheme.terrain
        metrics = [node_metrics(t, c, self.device) for c in self.cams]
        out: dict[str, Any] = {"logd": [], "vis": [], "parent": []}
        for lvl in range(t.depth + 1):
            x, y = metrics[0].x[lvl], metrics[0].y[lvl]
            nxl = t.roots[0] << lvl
            out["parent"].append(((y // 2) * (nxl // 2) + (x // 2)).astype(np.int32) if lvl else
                                 np.zeros(len(x), np.int32))
            out["logd"].append(np.stack([np.log(np.maximum(m.dist[lvl], 1e-6)) for m in metrics]).astype(np.float32))
            out["vis"].append(np.stack([m.inside[lvl] & ~m.culled[lvl] for m in metrics]).astype(np.float32))
        return out

    def _node_of(self, rows: np.ndarray, cols: np.ndarray, lvl: int) -> np.ndarray:
        t = self.scheme.terrain
        s = t.root_cells / 2.0 ** lvl
        nx, nz = t.roots[0] << lvl, t.roots[1] << lvl
        cx = int(t.inside(lvl, np.arange(nx), np.zeros(nx, np.int64)).sum())
        cy = int(t.inside(lvl, np.zeros(nz, np.int64), np.arange(nz)).sum())
        x = np.minimum(np.floor(cols / s).astype(np.int64), max(cx, 1) - 1)
        y = np.minimum(np.floor(rows / s).astype(np.int64), max(cy, 1) - 1)
        return (y * nx + x).astype(np.int32)

    @cached_property
    def _data(self) -> dict[str, Any]:
        """Padded per camera: each kept sample's node per tree level (C, D+1, V), its log eye distance (C, V), the
        pairs' sorted log errors (C, R*V) and each sorted pair's (LOD, sample) index (C, R*V)."""
        subs = [p.subset(self.relaxed_samples) for p in self.probes]
        depth = self.scheme.terrain.depth
        R, V = self.levels, max(max(len(p.rows) for p in subs), 1)
        node = np.zeros((len(subs), depth + 1, V), np.int32)
        logds = np.zeros((len(subs), V), np.float32)
        smask = np.zeros((len(subs), V), np.float32)
        logv = np.full((len(subs), R * V), 30.0, np.float32)
        pidx = np.zeros((len(subs), R * V), np.int32)
        pmask = np.zeros((len(subs), R * V), np.float32)
        for c, p in enumerate(subs):
            n = len(p.rows)
            node[c, :, :n] = np.stack([self._node_of(p.rows, p.cols, lvl) for lvl in range(depth + 1)])
            logds[c, :n] = np.log(np.maximum(p.dist, 1e-6))
            smask[c, :n] = 1.0
            lv, perm = sorted_pairs(p)
            logv[c, :len(lv)] = lv
            pidx[c, :len(lv)] = (perm // n) * V + perm % n if n else perm
            pmask[c, :len(lv)] = 1.0
        return {"logd": list(self._tree["logd"]), "vis": list(self._tree["vis"]), "node": node, "logds": logds,
                "smask": smask, "logv": logv, "pidx": pidx, "pmask": pmask}

    def values(self, u: jnp.ndarray) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.fixed)
        for i, k in enumerate(self.knobs):
            ui = jnp.clip(u[i], 0.0, 1.0)
            out[k.name] = (jnp.exp(math.log(k.lo) + ui * (math.log(k.hi) - math.log(k.lo))) if k.log
                           else k.lo + ui * (k.hi - k.lo))
        return out

    def _ranges(self, v: Mapping[str, Any]) -> tuple[list, list, list]:
        """(log range, morph start, 1 / (morph end - morph start)) per LOD, as :func:`cdlod_ranges`, traceable (the
        coarsest: range +inf, no morph)."""
        fr, r, msr = v["first_range"], v["ratio"], v["morph_start_ratio"]
        rng, start, inv = [], [], []
        total, prev = 0.0, 0.0
        for i in range(self.levels):
            if i == self.levels - 1:
                rng.append(jnp.asarray(60.0)), start.append(jnp.asarray(3e38)), inv.append(jnp.asarray(0.0))
                break
            total = total + r ** i
            ri = fr * total
            si = prev + (ri - prev) * msr
            ei = ri + (si - ri) * 0.01
            rng.append(jnp.log(ri)), start.append(si), inv.append(1.0 / jnp.maximum(ei - si, 1e-6))
            prev = si
        return rng, start, inv

    @cached_property
    def _jitted(self):
        return jax.jit(self._relaxed)

    def relaxed(self, u: jnp.ndarray, temp: float) -> tuple[jnp.ndarray, jnp.ndarray]:
        return self._jitted(u, jnp.asarray(temp, jnp.float32), self._data)

    def _relaxed(self, u: jnp.ndarray, temp: jnp.ndarray, data: dict[str, Any]) -> tuple[jnp.ndarray, jnp.ndarray]:
        v = self.values(u)
        logr, start, inv = self._ranges(v)
        depth, parents, L = self.scheme.terrain.depth, self._tree["parent"], self.levels
        g = float(self.scheme.grid)
        w = self.weights
        whole_cost = (w.get("triangles", 0.0) * 8.0 * (g / 2) ** 2 + w.get("vertices", 0.0) * (g + 1) ** 2
                      + w.get("draw_calls", 0.0))
        quad_cost = (w.get("triangles", 0.0) * 2.0 * (g / 2) ** 2 + w.get("vertices", 0.0) * (g / 2 + 1) ** 2
                     + w.get("draw_calls", 0.0))

        def camera(_, cam):
            logd, vis, node, logds, smask, logv, pidx, pmask = cam
            whole, quad = [], []  # per tree level: each node's probability of being drawn whole / as a quadrant
            reach, cost, split_prev = None, 0.0, None
            for lvl in range(depth + 1):
                i = depth - lvl
                q = jax.nn.sigmoid((logr[i] - logd[lvl]) / temp) if i < L - 1 else jnp.ones_like(logd[lvl])
                reach = jnp.ones_like(q) if lvl == 0 else reach[parents[lvl]] * split_prev[parents[lvl]]
                finer = jax.nn.sigmoid((logr[i - 1] - logd[lvl]) / temp) if i > 0 else jnp.zeros_like(q)
                whole.append(reach * vis[lvl] * q * (1.0 - finer))
                quad.append(reach * vis[lvl] * (1.0 - q) if lvl > 0 else jnp.zeros_like(q))
                split_prev = q * finer * vis[lvl]
                cost = cost + whole_cost * jnp.sum(whole[-1]) + quad_cost * jnp.sum(quad[-1])
            # LOD i: the samples of level depth - i drawn whole, and those of level depth - i + 1 drawn as a quadrant
            # of their parent
            at = [whole[depth - i][node[depth - i]] + (quad[depth - i + 1][node[depth - i + 1]] if i else 0.0)
                  for i in range(L)]
            ds = jnp.exp(logds)
            k = [jnp.clip((ds - start[j]) * inv[j], 0.0, 1.0) for j in range(L - 1)]  # a sample at j morphs to j+1
            pair = [at[j] * (1.0 - k[j] if j < L - 1 else 1.0) + (at[j - 1] * k[j - 1] if j else 0.0)
                    for j in range(L)]
            wts = (jnp.stack(pair) * smask[None, :]).reshape(-1)
            return None, (cost, soft_quantile(logv, wts[pidx] * pmask))

        xs = (list(data["logd"]), list(data["vis"]), data["node"], data["logds"], data["smask"], data["logv"],
              data["pidx"], data["pmask"])
        _, (costs, errs) = jax.lax.scan(camera, None, xs)
        return costs, errs

    @cached_property
    def _sample_nodes(self) -> list[np.ndarray]:
        """Per camera, each kept sample's node per tree level (D+1, V)."""
        depth = self.scheme.terrain.depth
        return [np.stack([self._node_of(p.rows, p.cols, lvl) for lvl in range(depth + 1)]) for p in self.probes]

    def _select(self, c: int, rng: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Camera ``c``'s selection for the ranges ``rng`` (per LOD), as :meth:`Cdlod.select` makes it, from the node
        distances and visibility the model holds: per tree level, the nodes drawn whole and as a parent's quadrant."""
        tree, depth = self._tree, self.scheme.terrain.depth
        whole, quad = [], []
        reach = np.ones(len(tree["vis"][0][c]), bool)
        for lvl in range(depth + 1):
            i = depth - lvl
            if lvl:
                reach = reach_prev[tree["parent"][lvl]]  # noqa: F821 - the level above's
            vis = reach & (tree["vis"][lvl][c] > 0)
            d = np.exp(tree["logd"][lvl][c].astype(np.float64))
            in_range = d < rng[i]
            split = vis & in_range & (d < rng[i - 1]) if i > 0 else np.zeros_like(vis)
            whole.append(vis & in_range & ~split)
            quad.append(vis & ~in_range if lvl else np.zeros_like(vis))
            reach_prev = split  # noqa: F841
        return whole, quad

    def hard(self, values: Mapping[str, float]) -> Prediction:
        """The selection at temperature 0 (:meth:`_select`, what :meth:`Cdlod.select` draws), its draws counted as
        the mesh counts them; each sample's error at its LOD, blended toward the next by its morph factor."""
        v = {**self.fixed, **values}
        rng, start, end = cdlod_ranges(float(v["first_range"]), float(v["ratio"]), float(v["morph_start_ratio"]),
                                       self.levels)
        g, depth = int(self.scheme.grid), self.scheme.terrain.depth
        costs, p99 = [], []
        for c, (probe, nodes) in enumerate(zip(self.probes, self._sample_nodes, strict=True)):
            whole, quad = self._select(c, rng)
            nw, nq = int(sum(w.sum() for w in whole)), int(sum(q.sum() for q in quad))
            feats = {"triangles": 2.0 * (g // 2) ** 2 * (4 * nw + nq), "vertices": float(nw * (g + 1) ** 2
                                                                                           + nq * (g // 2 + 1) ** 2),
                     "draw_calls": float(nw + nq), "patches": 0.0, "domain_points": 0.0}
            costs.append(sum(self.weights.get(f, 0.0) * x for f, x in feats.items()))
            lod = np.full(nodes.shape[1], -1, np.int64)
            for lvl in range(depth + 1):
                lod[whole[lvl][nodes[lvl]]] = depth - lvl
                lod[quad[lvl][nodes[lvl]]] = depth - lvl + 1
            j = np.maximum(lod, 0)
            with np.errstate(invalid="ignore", divide="ignore"):
                k = np.where(np.isfinite(start[j]), np.clip((probe.dist - start[j]) / (end[j] - start[j]), 0, 1), 0.0)
            nxt = np.minimum(j + 1, self.levels - 1)
            cols = np.arange(len(j))
            err = (1.0 - k) * probe.err[j, cols] + k * probe.err[nxt, cols]
            p99.append(hard_percentile(np.where(lod >= 0, err, np.nan)))
        return Prediction(np.asarray(costs), np.asarray(p99))

