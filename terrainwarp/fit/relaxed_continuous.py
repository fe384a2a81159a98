"""The continuous policy's model (JAX): one uniform patch level, per-edge fractional factors.

Its knob is ``target_px`` (its ``level`` is an integer, one model per level). A patch's factors follow the
policy's own rule (:func:`terrainwarp.lod.policies.continuous_factors`, a soft clamp in the relaxed model) from
its edges' projected lengths (:func:`terrainwarp.lod.policies.edge_pixels`, fixed per camera: the patches of a
level do not depend on the target). Its samples' error is read off probes of the level's patches tessellated at
one uniform factor each (a geometric ladder from 1 to 64, :func:`factor_ladder`), interpolated in
log factor between the two rungs around the patch's mean inner factor. Cost: the patch's domain points,
triangles and patch (exact in ``hard``, :func:`terrainwarp.kernels.tessellator.count_patches`; relaxed, ``2 n_u
n_v`` triangles and ``(n_u + 1)(n_v + 1)`` points, ``n`` the odd segment count's mean, :func:`_segments`). What
the model leaves out: a patch's outer edges tessellated apart from its inner factor (the probes tessellate the
whole patch at one factor).
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
from ..lod.policies import ContinuousPolicy, continuous_factors, edge_pixels
from ..lod.quadtree import PatchList, Terrain, select
from ..scene import MAX_TESS, LodConfig
from .knobs import Knob
from .probe import CameraProbe
from .relaxed import hard_percentile, soft_quantile, sorted_pairs
from .search import Prediction

__all__ = ["ContinuousModel", "factor_ladder"]


def factor_ladder(terrain: Terrain, level: int, ratio: float = 1.2) -> np.ndarray:
    """The uniform factors a level's probes tessellate at: 1 up to 64 by about ``ratio`` (fractional vertices
    fall between the samples, so factors past one segment per cell still change the error), float64 ascending."""
    n = max(2, int(math.ceil(math.log(MAX_TESS) / math.log(ratio))) + 1)
    return np.unique(np.round(np.geomspace(1.0, float(MAX_TESS), n), 3))


def _segments(f):
    """The segments fractional_odd spacing makes of factor ``f`` on average: the odd count at or above ``f`` is
    ``f + 1`` on average over its interval, and 1 at ``f = 1`` (a smooth bridge between)."""
    return f + 1.0 - jnp.exp(-2.0 * (f - 1.0))


@dataclass(eq=False)
class ContinuousModel:
    """The continuous policy at one ``level`` over a camera path.

    Attributes:
        probes: per camera, one resolution per rung of ``factors``.
        factors: the ladder (:func:`factor_ladder`).
        patches: per camera, the level's visible patches (:func:`terrainwarp.lod.select`).
        knobs: ``[target_px]``; fixed: the other knobs' values; config: values -> LodConfig.
    """

    terrain: Terrain
    cams: list[Camera]
    probes: list[CameraProbe]
    factors: np.ndarray
    patches: list[PatchList]
    knobs: Sequence[Knob]
    fixed: Mapping[str, float]
    config: Callable[[Mapping[str, float]], LodConfig]
    weights: Mapping[str, float]
    relaxed_samples: int = 1 << 13
    device: str = "cpu"

    @cached_property
    def _edges(self) -> list[np.ndarray]:
        hm = self.terrain.heightmap
        return [edge_pixels(hm, c.position, c.focal_px, pl.origin, pl.size) for c, pl in
                zip(self.cams, self.patches, strict=True)]

    def _patch_of(self, pl: PatchList, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Each sample's patch (index into ``pl``), -1 where none is drawn."""
        t, level = self.terrain, int(self.config(self.fixed).level)
        s = t.root_cells / 2.0 ** level
        nx, nz = t.roots[0] << level, t.roots[1] << level
        lookup = np.full(nx * nz, -1, np.int64)
        lx = np.rint(pl.origin_cells[:, 0] / s).astype(np.int64)
        ly = np.rint(pl.origin_cells[:, 1] / s).astype(np.int64)
        lookup[ly * nx + lx] = np.arange(len(pl))
        x = np.minimum(np.floor(cols / s).astype(np.int64), nx - 1)
        y = np.minimum(np.floor(rows / s).astype(np.int64), nz - 1)
        return lookup[y * nx + x]

    @cached_property
    def _data(self) -> dict[str, Any]:
        """Per camera, padded and stacked: the edges' projected lengths (C, P, 4) and their mask, each kept sample's
        patch (C, V), the pairs' sorted log errors (C, R*V) and each sorted pair's (rung, sample) index."""
        subs = [p.subset(self.relaxed_samples) for p in self.probes]
        R = len(self.factors)
        V = max(max(len(p.rows) for p in subs), 1)
        P = max(max(len(e) for e in self._edges), 1)
        edges = np.ones((len(subs), P, 4), np.float32)
        patch = np.zeros((len(subs), V), np.int32)
        smask = np.zeros((len(subs), V), np.float32)
        logv = np.full((len(subs), R * V), 30.0, np.float32)
        pidx = np.zeros((len(subs), R * V), np.int32)
        pmask = np.zeros((len(subs), R * V), np.float32)
        for c, (p, pl, e) in enumerate(zip(subs, self.patches, self._edges, strict=True)):
            edges[c, :len(e)] = np.minimum(e, 1e6)
            own = self._patch_of(pl, p.rows, p.cols)
            n = len(p.rows)
            patch[c, :n] = np.maximum(own, 0)
            smask[c, :n] = own >= 0
            lv, perm = sorted_pairs(p)
            logv[c, :len(lv)] = lv
            pidx[c, :len(lv)] = (perm // n) * V + perm % n if n else perm
            pmask[c, :len(lv)] = 1.0
        return {"edges": edges, "patch": patch, "smask": smask, "logv": logv, "pidx": pidx, "pmask": pmask,
                "logf": np.log(self.factors).astype(np.float32)}

    @cached_property
    def _jitted(self):
        return jax.jit(self._relaxed)

    def relaxed(self, u: jnp.ndarray, temp: float) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(cost per camera (C,), log p99 px per camera (C,)) at unit coordinate ``u`` (target_px) and ``temp``."""
        return self._jitted(u, jnp.asarray(temp, jnp.float32), self._data)

    def _relaxed(self, u: jnp.ndarray, temp: jnp.ndarray, data: dict[str, Any]) -> tuple[jnp.ndarray, jnp.ndarray]:
        k = self.knobs[0]
        target = jnp.exp(math.log(k.lo) + jnp.clip(u[0], 0.0, 1.0) * (math.log(k.hi) - math.log(k.lo)))
        t = jnp.maximum(temp, 0.05)
        soft = lambda x, a, b: a + t * jax.nn.softplus((x - a) / t) - t * jax.nn.softplus((x - b) / t)  # noqa: E731
        logf, R = data["logf"], len(self.factors)
        w = self.weights

        def camera(_, cam):
            edges, patch, smask, logv, pidx, pmask = cam
            _, inner = continuous_factors(edges, target, xp=jnp, clamp=soft)
            fu, fv = inner[:, 0], inner[:, 1]
            nu, nv = _segments(fu), _segments(fv)
            cost = jnp.sum(w.get("patches", 0.0) + w.get("triangles", 0.0) * 2.0 * nu * nv
                           + w.get("domain_points", 0.0) * (nu + 1.0) * (nv + 1.0) + w.get("vertices", 0.0) * 4.0)
            f = jnp.log(jnp.maximum(0.5 * (fu + fv), 1.0))[patch]
            i = jnp.clip(jnp.searchsorted(logf, f) - 1, 0, R - 2)
            a = jnp.clip((f - logf[i]) / (logf[i + 1] - logf[i]), 0.0, 1.0)
            V = patch.shape[0]
            wts = jnp.zeros(R * V).at[i * V + jnp.arange(V)].add((1.0 - a) * smask)
            wts = wts.at[(i + 1) * V + jnp.arange(V)].add(a * smask)
            return None, (cost, soft_quantile(logv, wts[pidx] * pmask))

        xs = (data["edges"], data["patch"], data["smask"], data["logv"], data["pidx"], data["pmask"])
        _, (costs, errs) = jax.lax.scan(camera, None, xs)
        return costs, errs

    def hard(self, values: Mapping[str, float]) -> Prediction:
        """The real factors of each patch (the policy's rule, float32 as the selection makes them), counted exactly;
        each sample's error interpolated between the rungs around its patch's mean inner factor."""
        cfg = self.config({**self.fixed, **values})
        costs, p99 = [], []
        logf = np.log(self.factors)
        for pl, e, probe in zip(self.patches, self._edges, self.probes, strict=True):
            outer, inner = continuous_factors(e, cfg.target_px)
            outer, inner = outer.astype(np.float32), inner.astype(np.float32)
            pts, tris = count_patches(outer, inner, cfg.spacing, self.device)
            feats = {"patches": float(len(pl)), "domain_points": float(pts.sum()), "triangles": float(tris.sum()),
                     "vertices": 4.0 * len(pl), "draw_calls": 1.0}
            costs.append(sum(self.weights.get(f, 0.0) * x for f, x in feats.items()))
            own = self._patch_of(pl, probe.rows, probe.cols)
            f = np.log(np.maximum(0.5 * (inner[:, 0] + inner[:, 1]), 1.0))[np.maximum(own, 0)]
            i = np.clip(np.searchsorted(logf, f) - 1, 0, len(logf) - 2)
            a = np.clip((f - logf[i]) / (logf[i + 1] - logf[i]), 0.0, 1.0)
            cols = np.arange(len(f))
            err = (1.0 - a) * probe.err[i, cols] + a * probe.err[i + 1, cols]
            p99.append(hard_percentile(np.where(own >= 0, err, np.nan)))
        return Prediction(np.asarray(costs), np.asarray(p99))


def continuous_patches(terrain: Terrain, cams: list[Camera], level: int, device: str = "cpu") -> list[PatchList]:
    """Each camera's visible patches of ``level`` (the continuous policy's selection; its factors do not matter)."""
    return [select(terrain, c, ContinuousPolicy(1.0, level=level), device=device) for c in cams]
