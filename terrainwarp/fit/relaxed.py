"""Relaxed models (JAX): each camera's cost and log p99 error as differentiable functions of a family's continuous
knobs, and the same models at temperature 0 (``hard``), read off the real selection.

**Error.** A frame's primary error is a percentile over the visible samples, and each sample's error is what
its resolution's surface misses it by: the probes (:mod:`terrainwarp.fit.probe`) hold that per sample and per
resolution. A model gives each (sample, resolution) pair a weight, the probability that the sample is drawn at
that resolution; the p99 is the weighted 99th percentile of the pairs' errors. Its value is the hard weighted
percentile; its gradient is the percentile's own (implicit) derivative, ``d q / d w_j = -(1[v_j <= q] - F) /
(W f(q))`` with ``f`` the density of the pairs' log errors around ``q`` (:func:`soft_quantile`), so weights
anywhere below or above the percentile move it.

**Selection.** The quadtree policies: every node of the complete tree splits with probability
``sigmoid((log metric - log threshold_L) / temperature)`` (sse: the projected geometric error against
``tolerance_px * exp(m_L)``; distance: the level's threshold ``k * size * exp(m_L)`` against the eye distance),
0 when culled or at the deepest level; a node is a drawn leaf with probability ``prod(ancestors' split) * (1 -
split)``. With a hysteresis band the cameras run in path order: a node split at the camera before (with its
probability) splits above ``threshold * (1 - h)``, another above ``threshold * (1 + h)``, as the selection kernel
does. The 2:1 balance is relaxed as well (:mod:`terrainwarp.fit.relaxed_tree`: a node is forced to split with the
probability that a neighbour in the tree splits a child next to it). Bias left to the exact tries' calibration: the
doubled edge factors are not in the relaxed model (they are in ``hard``, which selects for real). With a pop bound,
each consecutive pair's pop p99 is modelled the same way, from the probabilities that a sample is drawn at one
level for the camera before and at another now. CDLOD (:class:`CdlodModel`) and the
continuous policy (:class:`ContinuousModel`) are below.

**Cost.** Per camera, a linear function of what the selection draws (:data:`FEATURES`: patches, domain points,
triangles, vertices, draw calls) with the fit's cost weights (:func:`cost_weights`); what a cost also counts
that no model predicts (fragments, samples) enters only through the exact tries.

Temperatures anneal (:mod:`terrainwarp.fit.search`) toward 0, where the relaxed selection is the hard one less
what is said above.
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
from ..kernels.tessellator import count_patches
from ..lod.policies import make_policy
from ..lod.quadtree import LodState, Terrain, node_metrics, select
from ..scene import LodConfig
from .knobs import LEVEL_SCALE, Knob
from .probe import CameraProbe
from .relaxed_tree import balance_maps, forces, inside_counts, node_of, subset, tree_probs
from .search import Prediction

__all__ = ["soft_quantile", "sorted_pairs", "QuadtreeModel", "hard_percentile"]

Q = 0.99  # the percentile the budget bounds


# ------------------------------------------------------------------------------------------------
# the weighted percentile
# ------------------------------------------------------------------------------------------------
def sorted_pairs(probe: CameraProbe) -> tuple[np.ndarray, np.ndarray]:
    """(log errors of every (resolution, sample) pair, sorted ascending; the permutation that sorts the pairs of
    ``probe.err`` flattened resolution-major)."""
    lv = np.log(np.clip(probe.err.reshape(-1).astype(np.float64), 1e-6, 1e6))
    perm = np.argsort(lv, kind="stable")
    return lv[perm].astype(np.float32), perm.astype(np.int32)


def soft_quantile(logv: jnp.ndarray, w: jnp.ndarray, q: float = Q) -> jnp.ndarray:
    """The ``q`` quantile of the sorted values ``logv`` (N,) with weights ``w`` (N,), in the same order: the hard
    weighted quantile as its value, with the quantile's implicit derivative in ``w`` (the density around it taken
    over the pairs within 0.1% of the weight either side, at least 16 pairs)."""
    n = logv.shape[0]
    cw = jnp.cumsum(w)
    total = jnp.maximum(cw[-1], 1e-30)
    cws = jax.lax.stop_gradient(cw)
    k = jnp.clip(jnp.searchsorted(cws, q * cws[-1]), 0, n - 1)
    q0 = logv[k]
    m = max(16, n // 1000)
    lo, hi = jnp.clip(k - m, 0, n - 1), jnp.clip(k + m, 0, n - 1)
    span = jnp.maximum(logv[hi] - logv[lo], 1e-3)
    dens = jax.lax.stop_gradient(jnp.maximum((cws[hi] - cws[lo]) / jnp.maximum(cws[-1], 1e-30), 1e-6) / span)
    frac = cw[k] / total
    return q0 - (frac - jax.lax.stop_gradient(frac)) / dens


def hard_percentile(values: np.ndarray, q: float = 99.0) -> float:
    """numpy's percentile of the finite values (0 when there are none)."""
    v = values[np.isfinite(values)]
    return float(np.percentile(v, q)) if v.size else 0.0


def _relaxed_pops(leaves: list, data: dict[str, Any], depth: int) -> jnp.ndarray:
    """Each consecutive pair's log pop p99: per sample, the probability of each pair of levels (drawn at one for
    the camera before, at the other now) weighs that pair's pop, and of the same level, no pop."""
    R = depth + 1
    pairs = [(a, b) for a in range(R) for b in range(a + 1, R)]

    def pair(_, x):
        before, now, node, logv, idx, mask = x
        A = jnp.stack([before[L][node[L]] for L in range(R)])  # (R, V): drawn at L for the camera before
        B = jnp.stack([now[L][node[L]] for L in range(R)])
        w = [A[a] * B[b] + A[b] * B[a] for a, b in pairs] + [jnp.sum(A * B, axis=0)]
        return None, soft_quantile(logv, jnp.concatenate(w)[idx] * mask)

    before = [lv[:-1] for lv in leaves]
    now = [lv[1:] for lv in leaves]
    _, out = jax.lax.scan(pair, None, (before, now, data["node"], data["logv"], data["idx"], data["mask"]))
    return out


@dataclass(eq=False)
class QuadtreeModel:
    """The sse or distance policy on one terrain (roots, tess) over a camera path.

    Attributes:
        terrain: the quadtree (its ``tess`` fixed: one model per T).
        cams: the path's cameras, in order.
        probes: one probe per camera, one resolution per level 0..D (:func:`terrainwarp.fit.probe.probe_cameras`).
        policy: ``"sse"`` or ``"distance"``.
        knobs: the continuous knobs the model differentiates (``tolerance_px`` / ``k``, ``level_log_scale_<L>``,
            ``hysteresis``), in the order of the unit vector ``u``.
        fixed: the values of the knobs not fitted (a base threshold, level multipliers, hysteresis, tess).
        config: knob values (fitted and fixed) -> the configuration they draw (:func:`terrainwarp.fit.apply`).
        weights: the cost's weights on :data:`FEATURES` (:func:`cost_weights`).
        relaxed_samples: the pairs the relaxed percentile reads per camera (a deterministic subset).
        pops: with them, the model also predicts each consecutive pair's pop p99 (the selection of the camera
            before held, drawn for the camera): the relaxed model weighs each pair of levels by the probability
            that the sample is drawn at one then at the other; the hard one reads each sample's two levels.
    """

    terrain: Terrain
    cams: list[Camera]
    probes: list[CameraProbe]
    policy: str
    knobs: Sequence[Knob]
    fixed: Mapping[str, float]
    config: Callable[[Mapping[str, float]], LodConfig]
    weights: Mapping[str, float]
    relaxed_samples: int = 1 << 13
    device: str = "cpu"
    pops: list[np.ndarray] | None = None  # :func:`terrainwarp.fit.probe.pop_pairs`: the pop constraint's probes

    # -- the data both models read ------------------------------------------------------------------
    @cached_property
    def _tree(self) -> dict[str, Any]:
        t = self.terrain
        metrics = [node_metrics(t, c, self.device) for c in self.cams]
        d: dict[str, Any] = {"metric": [], "vis": [], "parent": [], "size": []}
        for lvl in range(t.depth + 1):
            m0 = metrics[0]
            x, y = m0.x[lvl], m0.y[lvl]
            nxl = t.roots[0] << lvl
            d["parent"].append(((y // 2) * (nxl // 2) + (x // 2)).astype(np.int32) if lvl else
                               np.zeros(len(x), np.int32))
            d["size"].append(float(m0.size[lvl][0]) if len(m0.size[lvl]) else 1.0)
            if self.policy == "sse":
                met = np.stack([np.log(np.clip(m.sse[lvl], 1e-12, 1e30)) for m in metrics])
            else:
                met = np.stack([np.log(np.maximum(m.dist[lvl], 1e-9)) for m in metrics])
            d["metric"].append(met.astype(np.float32))
            d["vis"].append(np.stack([(m.inside[lvl] & ~m.culled[lvl]) for m in metrics]).astype(np.float32))
        return d

    @cached_property
    def _balance_maps(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        return balance_maps(self.terrain)

    @cached_property
    def _inside(self) -> list[tuple[int, int]]:
        return inside_counts(self.terrain)

    @cached_property
    def _pairs(self) -> dict[str, np.ndarray]:
        """The relaxed subsets of every camera, padded to one length and stacked, in each camera's sorted order of
        log error: ``logv`` (C, N) the pairs' log errors, ascending (padding last), ``gidx`` (C, N) each pair's
        node in the levels' nodes laid end to end (level 0 first), ``mask`` (C, N) 0 on the padding."""
        subs = [p.subset(self.relaxed_samples) for p in self.probes]
        R = self.terrain.depth + 1
        n = R * max(max(len(p.rows) for p in subs), 1)
        sizes = [(self.terrain.roots[0] << L) * (self.terrain.roots[1] << L) for L in range(R)]
        offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        logv = np.full((len(subs), n), 30.0, np.float32)  # the padding sorts last
        gidx = np.zeros((len(subs), n), np.int32)
        mask = np.zeros((len(subs), n), np.float32)
        for c, p in enumerate(subs):
            node = np.stack([node_of(p.rows, p.cols, self.terrain, L, self._inside[L]) + offset[L]
                             for L in range(R)]).reshape(-1)  # resolution-major, as the probe's errors
            lv, perm = sorted_pairs(p)
            logv[c, :len(lv)] = lv
            gidx[c, :len(lv)] = node[perm]
            mask[c, :len(lv)] = 1.0
        return {"logv": logv, "gidx": gidx, "mask": mask}

    @cached_property
    def _per_patch(self) -> dict[str, float]:
        """Features of one patch at the terrain's T (no doubled edge)."""
        t = float(self.terrain.tess)
        pts, tris = count_patches(np.full((1, 4), t, np.float32), np.full((1, 2), t, np.float32),
                                  self.config(self.fixed).spacing)
        return {"patches": 1.0, "domain_points": float(pts[0]), "triangles": float(tris[0]), "vertices": 4.0,
                "draw_calls": 0.0}

    # -- the relaxed model --------------------------------------------------------------------------
    def values(self, u: jnp.ndarray) -> dict[str, jnp.ndarray]:
        """The knob values at unit coordinates ``u`` (traceable)."""
        out = {}
        for i, k in enumerate(self.knobs):
            ui = jnp.clip(u[i], 0.0, 1.0)
            out[k.name] = (jnp.exp(math.log(k.lo) + ui * (math.log(k.hi) - math.log(k.lo))) if k.log
                           else k.lo + ui * (k.hi - k.lo))
        return out

    def _thresholds(self, v: Mapping[str, Any]) -> list:
        """log threshold per level (sse: px; distance: m, the level's node size in)."""
        main = "tolerance_px" if self.policy == "sse" else "k"
        base = jnp.log(v[main]) if main in v else math.log(self.fixed[main])
        out = []
        for L in range(self.terrain.depth + 1):
            name = f"{LEVEL_SCALE}{L}"
            m = v[name] if name in v else self.fixed.get(name, 0.0)
            size = 0.0 if self.policy == "sse" else math.log(self._tree["size"][L])
            out.append(base + m + size)
        return out

    @cached_property
    def _data(self) -> dict[str, Any]:
        """The arrays the relaxed model reads, as one pytree (passed to the jitted function, not baked in)."""
        tree, pairs = self._tree, self._pairs  # numpy: made outside any trace, passed as arguments
        return {"metric": list(tree["metric"]), "vis": list(tree["vis"]), **pairs,
                **({"pop": self._pop_data} if self.pops is not None else {})}

    @cached_property
    def _pop_data(self) -> dict[str, np.ndarray]:
        """For the cameras after the first, padded and stacked: each kept sample's node per level ``node`` (C-1, R,
        V), the sorted log pops of every (level pair, sample) and (no change, sample) entry ``logv`` (C-1, (P+1) V),
        each sorted entry's index ``idx`` in that layout and ``mask``."""
        R = self.terrain.depth + 1
        idx_all = []
        for p, pairs in zip(self.probes[1:], self.pops, strict=True):
            keep = subset(len(p.rows), self.relaxed_samples)
            idx_all.append((p, pairs, keep))
        V = max(max((len(k) for _, _, k in idx_all), default=1), 1)
        P = R * (R - 1) // 2
        n = len(idx_all)
        node = np.zeros((n, R, V), np.int32)
        logv = np.full((n, (P + 1) * V), 30.0, np.float32)
        idx = np.zeros((n, (P + 1) * V), np.int32)
        mask = np.zeros((n, (P + 1) * V), np.float32)
        for c, (p, pairs, keep) in enumerate(idx_all):
            m = len(keep)
            node[c, :, :m] = np.stack([node_of(p.rows[keep], p.cols[keep], self.terrain, L, self._inside[L])
                                       for L in range(R)])
            vals = np.concatenate([pairs[:, keep].reshape(-1), np.full(m, 1e-4, np.float32)])  # no change: 0 px
            flat = np.concatenate([(np.arange(P)[:, None] * V + np.arange(m)[None, :]).reshape(-1),
                                   P * V + np.arange(m)])
            order = np.argsort(np.log(np.clip(vals.astype(np.float64), 1e-6, 1e6)), kind="stable")
            logv[c, :len(vals)] = np.log(np.clip(vals[order].astype(np.float64), 1e-6, 1e6))
            idx[c, :len(vals)] = flat[order]
            mask[c, :len(vals)] = 1.0
        return {"node": node, "logv": logv, "idx": idx, "mask": mask}

    @cached_property
    def _jitted(self):
        return jax.jit(self._relaxed)

    def relaxed(self, u: jnp.ndarray, temp: float) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(cost per camera (C,), log p99 px per camera (C,)) at unit coordinates ``u`` and temperature ``temp``
        (jitted; differentiable in ``u``)."""
        return self._jitted(u, jnp.asarray(temp, jnp.float32), self._data)

    def _relaxed(self, u: jnp.ndarray, temp: jnp.ndarray, data: dict[str, Any]) -> tuple[jnp.ndarray, jnp.ndarray]:
        v = self.values(u)
        thr = self._thresholds(v)
        h = v["hysteresis"] if "hysteresis" in v else float(self.fixed.get("hysteresis", 0.0))
        chained = "hysteresis" in v or h > 0  # cameras in path order, each reading the split before
        depth, parents = self.terrain.depth, self._tree["parent"]
        sign = 1.0 if self.policy == "sse" else -1.0  # sse splits above the threshold, distance below
        # the kernel's band: a node not split at the camera before needs threshold * (1 + h) (sse) or is split
        # below threshold * (1 - h) (distance); one split before, the other way round
        fresh, held = (jnp.log1p(h), jnp.log1p(-h)) if self.policy == "sse" else (jnp.log1p(-h), jnp.log1p(h))
        per = self._per_patch
        unit_cost = sum(self.weights.get(f, 0.0) * per[f] for f in per)

        def camera(prev, cam):
            metric, vis_c, logv, gidx, mask = cam
            split = []  # each level's split probability where reached: the policy's, then the balance's
            for L in range(depth + 1):
                if L == depth:
                    split.append(jnp.zeros_like(vis_c[L]))
                    continue
                s = jax.nn.sigmoid(sign * (metric[L] - (thr[L] + fresh)) / temp)
                if chained:
                    held_s = jax.nn.sigmoid(sign * (metric[L] - (thr[L] + held)) / temp)
                    s = prev[L] * held_s + (1.0 - prev[L]) * s
                split.append(s * vis_c[L])
            force = [jnp.zeros_like(v) for v in vis_c]
            for _ in range(2):  # the balance reads the tree it changes: two rounds
                inside, total = tree_probs(split, force, vis_c, parents)
                force = forces(total, inside, vis_c, self._balance_maps)
            inside, total = tree_probs(split, force, vis_c, parents)
            leaves = [r * (1.0 - s) * v for r, s, v in zip(inside, total, vis_c, strict=True)]
            splits = [r * s for r, s in zip(inside, total, strict=True)]
            cost = unit_cost * sum(jnp.sum(lf) for lf in leaves)
            w = jnp.concatenate(leaves)[gidx] * mask
            return (splits if chained else prev), (cost, soft_quantile(logv, w), leaves)

        # scan over the cameras (the leading axis of every array): the body is traced once
        xs = (list(data["metric"]), list(data["vis"]), data["logv"], data["gidx"], data["mask"])
        init = [jnp.zeros_like(data["vis"][L][0]) for L in range(depth + 1)]
        _, (costs, errs, leaves) = jax.lax.scan(camera, init, xs)
        if self.pops is None:
            return costs, errs
        return costs, jnp.concatenate([errs, _relaxed_pops(leaves, data["pop"], depth)])

    # -- the hard model -----------------------------------------------------------------------------
    def hard(self, values: Mapping[str, float]) -> Prediction:
        """The model at temperature 0: the real selection (balance and edge factors included) per camera, in path
        order with one hysteresis state; its draws counted exactly (:func:`terrainwarp.kernels.tessellator.
        count_patches`); each sample's error read off the probe of its leaf's level."""
        cfg = self.config({**self.fixed, **values})
        policy = make_policy(cfg)
        state = LodState() if cfg.hysteresis > 0 else None
        costs, p99, pops, prev = [], [], [], None
        for c, (cam, probe) in enumerate(zip(self.cams, self.probes, strict=True)):
            pl = select(self.terrain, cam, policy, state, device=self.device)
            pts, tris = count_patches(pl.outer, pl.inner, cfg.spacing, self.device)
            feats = {"patches": float(len(pl)), "domain_points": float(pts.sum()), "triangles": float(tris.sum()),
                     "vertices": 4.0 * len(pl), "draw_calls": 1.0}
            costs.append(sum(self.weights.get(f, 0.0) * x for f, x in feats.items()))
            now = self._levels_of(pl, probe)
            p99.append(hard_percentile(np.where(now >= 0, probe.err[np.maximum(now, 0), np.arange(len(now))],
                                                np.nan)))
            if self.pops is not None and prev is not None:
                pops.append(hard_percentile(self._pop_of(self._levels_of(prev, probe), now, self.pops[c - 1])))
            prev = pl
        return Prediction(np.asarray(costs), np.asarray(p99), None if self.pops is None else np.asarray(pops))

    def _pop_of(self, before: np.ndarray, now: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """Each kept sample's pop between its level before and now (0 where the same; NaN where either is not
        drawn)."""
        R = self.terrain.depth + 1
        index = {ab: i for i, ab in enumerate((a, b) for a in range(R) for b in range(a + 1, R))}
        lo, hi = np.minimum(before, now), np.maximum(before, now)
        table = np.full((R, R), -1, np.int64)
        for (a, b), i in index.items():
            table[a, b] = i
        which = table[np.maximum(lo, 0), np.maximum(hi, 0)]
        out = np.where(which >= 0, pairs[np.maximum(which, 0), np.arange(len(now))], 0.0)
        return np.where((before >= 0) & (now >= 0), out, np.nan)

    def _levels_of(self, pl, probe: CameraProbe) -> np.ndarray:
        """Each kept sample's drawn leaf's level (-1 where no drawn leaf covers it)."""
        t = self.terrain
        out = np.full(len(probe.rows), -1, np.int64)
        for L in np.unique(pl.level):
            L = int(L)
            nx, nz = t.roots[0] << L, t.roots[1] << L
            leaf = np.zeros(nx * nz, bool)
            s = t.root_cells / 2.0 ** L
            sel = pl.level == L
            lx = np.rint(pl.origin_cells[sel, 0] / s).astype(np.int64)
            ly = np.rint(pl.origin_cells[sel, 1] / s).astype(np.int64)
            leaf[ly * nx + lx] = True
            hit = leaf[node_of(probe.rows, probe.cols, t, L, self._inside[L])]
            out[hit] = L
        return out
