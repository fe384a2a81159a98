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
``hard`` selects for real and counts exactly, every camera at once (numpy): a level's nodes each get the LOD
they are drawn at (or none), and each sample reads its node's.

The relaxed function is pure (:class:`CdlodSpec`, the data padded as :mod:`terrainwarp.fit.relaxed` says).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..lod.cdlod import Cdlod, cdlod_ranges
from ..lod.quadtree import node_metrics
from ..scene import LodConfig
from .knobs import Knob
from .probe import CameraProbe
from .relaxed import (
    HARD_SAMPLES,
    MIN_PAIRS,
    PAD_LOGV,
    PaddedModel,
    bucket,
    camera_mask,
    hard_percentiles,
    hard_probes,
    knob_arrays,
    pad_to,
    relaxed_values,
    soft_quantile,
    sorted_pairs,
)
from .search import Prediction

__all__ = ["CdlodModel", "CdlodSpec"]

PARAMS = ("first_range", "ratio", "morph_start_ratio")


class CdlodSpec(NamedTuple):
    """The static part of a :class:`CdlodModel`: the tree's depth, the LOD levels, and per fitted knob its space;
    ``params``: each of :data:`PARAMS`' index in ``u`` (-1: fixed, read from the data)."""

    kind: str
    depth: int
    levels: int
    pops: bool
    logs: tuple[bool, ...]
    params: tuple[int, int, int]

    def relaxed(self, data: Mapping[str, Any], u: jnp.ndarray, temp: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        return cdlod_relaxed(self, data, u, temp)


def _ranges(spec: CdlodSpec, d: Mapping[str, Any], u: jnp.ndarray) -> tuple[list, list, list]:
    """(log range, morph start, 1 / (morph end - morph start)) per LOD, as :func:`cdlod_ranges`, traceable (the
    coarsest: range +inf, no morph)."""
    v = relaxed_values(u, d, spec.logs)
    fr, r, msr = (v[k] if k >= 0 else d["pfix"][i] for i, k in enumerate(spec.params))
    rng, start, inv = [], [], []
    total, prev = 0.0, 0.0
    for i in range(spec.levels):
        if i == spec.levels - 1:
            rng.append(jnp.asarray(60.0)), start.append(jnp.asarray(3e38)), inv.append(jnp.asarray(0.0))
            break
        total = total + r ** i
        ri = fr * total
        si = prev + (ri - prev) * msr
        ei = ri + (si - ri) * 0.01
        rng.append(jnp.log(ri)), start.append(si), inv.append(1.0 / jnp.maximum(ei - si, 1e-6))
        prev = si
    return rng, start, inv


def cdlod_relaxed(spec: CdlodSpec, d: Mapping[str, Any], u: jnp.ndarray,
                  temp: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(cost per padded camera, log p99 per padded camera) (pure; see the module docstring)."""
    logr, start, inv = _ranges(spec, d, u)
    depth, parents, L = spec.depth, d["parent"], spec.levels
    whole_cost, quad_cost = d["whole_cost"], d["quad_cost"]

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
        return None, (cost, soft_quantile(logv, wts[pidx] * pmask, n=d["npairs"]))

    xs = (list(d["logd"]), list(d["vis"]), d["node"], d["logds"], d["smask"], d["logv"], d["pidx"], d["pmask"])
    _, (costs, errs) = jax.lax.scan(camera, None, xs)
    return costs, errs


@dataclass(eq=False)
class CdlodModel(PaddedModel):
    """CDLOD with one grid over a camera path.

    Attributes:
        scheme: the :class:`terrainwarp.lod.cdlod.Cdlod` of this grid (its pyramids; the knobs set per setting).
        probes: per camera, one resolution per LOD 0 (finest) .. levels - 1, unmorphed.
        knobs: the fitted continuous knobs among ``first_range``, ``ratio``, ``morph_start_ratio``.
        hard_samples: the samples the hard model reads per camera (:data:`terrainwarp.fit.relaxed.HARD_SAMPLES`).
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
    hard_samples: int = HARD_SAMPLES

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
    def spec(self) -> CdlodSpec:
        names = [k.name for k in self.knobs]
        return CdlodSpec("cdlod", self.scheme.terrain.depth, self.levels, False, tuple(k.log for k in self.knobs),
                         tuple(names.index(p) if p in names else -1 for p in PARAMS))

    @cached_property
    def data(self) -> dict[str, Any]:
        """Padded per camera: each kept sample's node per tree level (C, D+1, V), its log eye distance (C, V), the
        pairs' sorted log errors (C, R*V) and each sorted pair's (LOD, sample) index (C, R*V); the tree's log
        distances, visibility and parents per level (the roots padded to a power of two); the knobs, the fixed
        values (:data:`PARAMS`) and the cost of a whole node and of a quadrant."""
        subs = [p.subset(self.relaxed_samples) for p in self.probes]
        t, tree = self.scheme.terrain, self._tree
        depth, R, cb = t.depth, self.levels, bucket(len(subs))
        v = max(max(len(p.rows) for p in subs), 1)
        V = bucket(v, MIN_PAIRS)
        node = np.zeros((cb, depth + 1, V), np.int32)
        logds, smask = np.zeros((cb, V), np.float32), np.zeros((cb, V), np.float32)
        logv = np.full((cb, R * V), PAD_LOGV, np.float32)
        pidx, pmask = np.zeros((cb, R * V), np.int32), np.zeros((cb, R * V), np.float32)
        for c, p in enumerate(subs):
            n = len(p.rows)
            node[c, :, :n] = np.stack([self._node_of(p.rows, p.cols, lvl) for lvl in range(depth + 1)])
            logds[c, :n] = np.log(np.maximum(p.dist, 1e-6))
            smask[c, :n] = 1.0
            lv, perm = sorted_pairs(p)
            logv[c, :len(lv)] = lv
            pidx[c, :len(lv)] = (perm // n) * V + perm % n if n else perm
            pmask[c, :len(lv)] = 1.0
        g, w = float(self.scheme.grid), self.weights
        size = [bucket(t.roots[0] * t.roots[1]) << (2 * lvl) for lvl in range(depth + 1)]
        return {"logd": [pad_to(a, (cb, size[i])) for i, a in enumerate(tree["logd"])],
                "vis": [pad_to(a, (cb, size[i])) for i, a in enumerate(tree["vis"])],
                "parent": [pad_to(a, (size[i],)) for i, a in enumerate(tree["parent"])],
                "node": node, "logds": logds, "smask": smask, "logv": logv, "pidx": pidx, "pmask": pmask,
                "npairs": np.int32(R * v), "cmask": camera_mask(len(subs)), **knob_arrays(self.knobs),
                "pfix": np.asarray([self.fixed.get(p, 1.0) for p in PARAMS], np.float32),
                "whole_cost": np.float32(w.get("triangles", 0.0) * 8.0 * (g / 2) ** 2
                                         + w.get("vertices", 0.0) * (g + 1) ** 2 + w.get("draw_calls", 0.0)),
                "quad_cost": np.float32(w.get("triangles", 0.0) * 2.0 * (g / 2) ** 2
                                        + w.get("vertices", 0.0) * (g / 2 + 1) ** 2 + w.get("draw_calls", 0.0))}

    def prepare(self) -> None:
        """Build what the hard model reads, and the relaxed model's data where there is more than one knob (a
        one-knob model is fitted on its hard line alone); what is not built here is built on first use."""
        _ = self._hard_tree, self._hard_samples
        if len(self.knobs) > 1:
            _ = self.data

    # -- the hard model -----------------------------------------------------------------------------
    @cached_property
    def _hard_tree(self) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
        """Per tree level: every camera's node distances (C, N) float64, visibility (C, N) bool, and the parents."""
        tree = self._tree
        return ([np.exp(a.astype(np.float64)) for a in tree["logd"]], [a > 0 for a in tree["vis"]],
                list(tree["parent"]))

    @cached_property
    def _hard_samples(self) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per camera, padded to the most kept samples, flat over (camera, sample): each sample's node at the finest
        tree level as an index into every camera's finest nodes laid end to end (C, V) (None where a sample's nodes
        are not one ancestor line: then ``nodes`` (C, D+1, V), its node per level, is read instead), its eye
        distance (C, V) float32, the flat index of its error at LOD 0 in ``err`` (C, V), ``err`` (C, R, V) float32,
        and which samples are real (C, V) bool."""
        probes = [p for p, _ in hard_probes(self.probes, self.hard_samples)]
        depth, C, parents = self.scheme.terrain.depth, len(probes), self._tree["parent"]
        v = max(max(len(p.rows) for p in probes), 1)
        nodes = np.zeros((C, depth + 1, v), np.int64)
        dist, ok = np.zeros((C, v), np.float32), np.zeros((C, v), bool)
        err = np.ones((C, self.levels, v), np.float32)
        for c, p in enumerate(probes):
            n = len(p.rows)
            nodes[c, :, :n] = np.stack([self._node_of(p.rows, p.cols, lvl) for lvl in range(depth + 1)])
            dist[c, :n], err[c, :, :n], ok[c, :n] = p.dist, p.err, True
        line = nodes[:, depth]
        for lvl in range(depth, 0, -1):  # every sample's node at each level is the ancestor of its finest one
            line = parents[lvl][line]
            if not np.array_equal(line, nodes[:, lvl - 1]):
                break
        else:
            n_fine = len(parents[depth])
            finest = nodes[:, depth] + (np.arange(C) * n_fine)[:, None]
            base = (np.arange(C)[:, None] * self.levels * v) + np.arange(v)[None, :]
            return finest, nodes, dist, base, err, ok
        return None, nodes, dist, (np.arange(C)[:, None] * self.levels * v) + np.arange(v)[None, :], err, ok

    def _select(self, rng: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Every camera's selection for the ranges ``rng`` (per LOD), as :meth:`Cdlod.select` makes it, from the node
        distances and visibility the model holds: per tree level, the nodes drawn whole and as a parent's quadrant
        ((C, N) bool each)."""
        dist, vis_all, parents = self._hard_tree
        depth = self.scheme.terrain.depth
        whole, quad = [], []
        reach = np.ones(vis_all[0].shape, bool)
        split = reach
        for lvl in range(depth + 1):
            i = depth - lvl
            if lvl:
                reach = split[:, parents[lvl]]  # the level above's splits
            vis = reach & vis_all[lvl]
            in_range = dist[lvl] < rng[i]
            split = vis & in_range & (dist[lvl] < rng[i - 1]) if i > 0 else np.zeros_like(vis)
            whole.append(vis & in_range & ~split)
            quad.append(vis & ~in_range if lvl else np.zeros_like(vis))
        return whole, quad

    def _lods(self, whole: list[np.ndarray], quad: list[np.ndarray]) -> np.ndarray:
        """Each kept sample's LOD (C, V) (-1 where no drawn node covers it): that of the deepest level whose node over
        it is drawn, whole (LOD depth - level) or as its parent's quadrant (one coarser)."""
        finest, nodes, _, _, _, _ = self._hard_samples
        depth, parents = self.scheme.terrain.depth, self._tree["parent"]
        if finest is not None:  # each finest node takes the LOD of the deepest drawn node above it, read once
            acc = None
            for lvl in range(depth + 1):
                code = np.where(whole[lvl], depth - lvl, np.where(quad[lvl], depth - lvl + 1, -1))
                acc = code if acc is None else np.where(code >= 0, code, acc[:, parents[lvl]])
            return acc.reshape(-1)[finest]
        lod = np.full(nodes[:, 0].shape, -1, np.int64)
        for lvl in range(depth + 1):
            code = np.where(whole[lvl], depth - lvl, np.where(quad[lvl], depth - lvl + 1, -1))
            at = np.take_along_axis(code, nodes[:, lvl, :], axis=1)
            lod = np.where(at >= 0, at, lod)
        return lod

    def predict(self, values: Mapping[str, float]) -> Prediction:
        """The selection at temperature 0 (:meth:`_select`, what :meth:`Cdlod.select` draws), its draws counted as
        the mesh counts them; each sample's error at its LOD, blended toward the next by its morph factor."""
        v = {**self.fixed, **values}
        rng, start, end = cdlod_ranges(float(v["first_range"]), float(v["ratio"]), float(v["morph_start_ratio"]),
                                       self.levels)
        g = int(self.scheme.grid)
        whole, quad = self._select(rng)
        nw, nq = sum(w.sum(axis=1) for w in whole), sum(q.sum(axis=1) for q in quad)
        costs = []
        for a, b in zip(nw.tolist(), nq.tolist(), strict=True):
            feats = {"triangles": 2.0 * (g // 2) ** 2 * (4 * a + b), "vertices": float(a * (g + 1) ** 2
                                                                                      + b * (g // 2 + 1) ** 2),
                     "draw_calls": float(a + b), "patches": 0.0, "domain_points": 0.0}
            costs.append(sum(self.weights.get(f, 0.0) * x for f, x in feats.items()))
        lod = self._lods(whole, quad)
        _, _, dist, base, err, ok = self._hard_samples
        j = np.maximum(lod, 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(np.isfinite(start[j]), np.clip((dist - start[j]) / (end[j] - start[j]), 0, 1), 0.0)
        nxt = np.minimum(j + 1, self.levels - 1)
        flat, v = err.reshape(-1), err.shape[2]
        e = (1.0 - k) * flat[base + j * v] + k * flat[base + nxt * v]
        return Prediction(np.asarray(costs), hard_percentiles(e, ok & (lod >= 0)))

