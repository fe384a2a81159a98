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
whole patch at one factor). ``hard`` counts every camera's patches in one launch and reads every sample at
once (numpy). The relaxed function is pure (:class:`ContinuousSpec`, the data padded as
:mod:`terrainwarp.fit.relaxed` says; a padded patch costs nothing).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, NamedTuple

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
    relaxed_values,
    soft_quantile,
    sorted_pairs,
)
from .search import Prediction

__all__ = ["ContinuousModel", "ContinuousSpec", "factor_ladder", "continuous_patches"]

MIN_PATCHES = 64  # the fewest patches a camera's edges are padded to


def factor_ladder(terrain: Terrain, level: int, ratio: float = 1.2) -> np.ndarray:
    """The uniform factors a level's probes tessellate at: 1 up to 64 by about ``ratio`` (fractional vertices
    fall between the samples, so factors past one segment per cell still change the error), float64 ascending."""
    n = max(2, int(math.ceil(math.log(MAX_TESS) / math.log(ratio))) + 1)
    return np.unique(np.round(np.geomspace(1.0, float(MAX_TESS), n), 3))


def _segments(f):
    """The segments fractional_odd spacing makes of factor ``f`` on average: the odd count at or above ``f`` is
    ``f + 1`` on average over its interval, and 1 at ``f = 1`` (a smooth bridge between)."""
    return f + 1.0 - jnp.exp(-2.0 * (f - 1.0))


class ContinuousSpec(NamedTuple):
    """The static part of a :class:`ContinuousModel`: the rungs of its factor ladder and its knob's space."""

    kind: str
    rungs: int
    pops: bool
    logs: tuple[bool, ...]

    def relaxed(self, data: Mapping[str, Any], u: jnp.ndarray, temp: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        return continuous_relaxed(self, data, u, temp)


def continuous_relaxed(spec: ContinuousSpec, d: Mapping[str, Any], u: jnp.ndarray,
                       temp: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(cost per padded camera, log p99 per padded camera) at unit coordinate ``u`` (target_px) (pure)."""
    target = relaxed_values(u, d, spec.logs)[0]
    t = jnp.maximum(temp, 0.05)
    soft = lambda x, a, b: a + t * jax.nn.softplus((x - a) / t) - t * jax.nn.softplus((x - b) / t)  # noqa: E731
    logf, R, w = d["logf"], spec.rungs, d["w"]

    def camera(_, cam):
        edges, pvalid, patch, smask, logv, pidx, pmask = cam
        _, inner = continuous_factors(edges, target, xp=jnp, clamp=soft)
        fu, fv = inner[:, 0], inner[:, 1]
        nu, nv = _segments(fu), _segments(fv)
        cost = jnp.sum((w[0] + w[1] * 2.0 * nu * nv + w[2] * (nu + 1.0) * (nv + 1.0) + w[3] * 4.0) * pvalid)
        f = jnp.log(jnp.maximum(0.5 * (fu + fv), 1.0))[patch]
        i = jnp.clip(jnp.searchsorted(logf, f) - 1, 0, R - 2)
        a = jnp.clip((f - logf[i]) / (logf[i + 1] - logf[i]), 0.0, 1.0)
        V = patch.shape[0]
        wts = jnp.zeros(R * V).at[i * V + jnp.arange(V)].add((1.0 - a) * smask)
        wts = wts.at[(i + 1) * V + jnp.arange(V)].add(a * smask)
        return None, (cost, soft_quantile(logv, wts[pidx] * pmask, n=d["npairs"]))

    xs = (d["edges"], d["pvalid"], d["patch"], d["smask"], d["logv"], d["pidx"], d["pmask"])
    _, (costs, errs) = jax.lax.scan(camera, None, xs)
    return costs, errs


@dataclass(eq=False)
class ContinuousModel(PaddedModel):
    """The continuous policy at one ``level`` over a camera path.

    Attributes:
        probes: per camera, one resolution per rung of ``factors``.
        factors: the ladder (:func:`factor_ladder`).
        patches: per camera, the level's visible patches (:func:`terrainwarp.lod.select`).
        knobs: ``[target_px]``; fixed: the other knobs' values; config: values -> LodConfig.
        hard_samples: the samples the hard model reads per camera (:data:`terrainwarp.fit.relaxed.HARD_SAMPLES`).
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
    hard_samples: int = HARD_SAMPLES

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
    def spec(self) -> ContinuousSpec:
        return ContinuousSpec("continuous", len(self.factors), False, tuple(k.log for k in self.knobs))

    @cached_property
    def data(self) -> dict[str, Any]:
        """Per camera, padded and stacked: the edges' projected lengths (C, P, 4) and which patches are real, each
        kept sample's patch (C, V), the pairs' sorted log errors (C, R*V) and each sorted pair's (rung, sample)
        index; the ladder's log factors, the cost weights (patches, triangles, domain points, vertices)."""
        subs = [p.subset(self.relaxed_samples) for p in self.probes]
        R, cb = len(self.factors), bucket(len(subs))
        v = max(max(len(p.rows) for p in subs), 1)
        V, P = bucket(v, MIN_PAIRS), bucket(max(max(len(e) for e in self._edges), 1), MIN_PATCHES)
        edges, pvalid = np.ones((cb, P, 4), np.float32), np.zeros((cb, P), np.float32)
        patch, smask = np.zeros((cb, V), np.int32), np.zeros((cb, V), np.float32)
        logv = np.full((cb, R * V), PAD_LOGV, np.float32)
        pidx, pmask = np.zeros((cb, R * V), np.int32), np.zeros((cb, R * V), np.float32)
        for c, (p, pl, e) in enumerate(zip(subs, self.patches, self._edges, strict=True)):
            edges[c, :len(e)], pvalid[c, :len(e)] = np.minimum(e, 1e6), 1.0
            own = self._patch_of(pl, p.rows, p.cols)
            n = len(p.rows)
            patch[c, :n] = np.maximum(own, 0)
            smask[c, :n] = own >= 0
            lv, perm = sorted_pairs(p)
            logv[c, :len(lv)] = lv
            pidx[c, :len(lv)] = (perm // n) * V + perm % n if n else perm
            pmask[c, :len(lv)] = 1.0
        w = self.weights
        return {"edges": edges, "pvalid": pvalid, "patch": patch, "smask": smask, "logv": logv, "pidx": pidx,
                "pmask": pmask, "npairs": np.int32(R * v), "logf": np.log(self.factors).astype(np.float32),
                "w": np.asarray([w.get(f, 0.0) for f in ("patches", "triangles", "domain_points", "vertices")],
                                np.float32), "cmask": camera_mask(len(subs)), **knob_arrays(self.knobs)}

    def prepare(self) -> None:
        """Build what the hard model reads, and the relaxed model's data where there is more than one knob (a
        one-knob model is fitted on its hard line alone); what is not built here is built on first use."""
        _ = self._hard_samples
        if len(self.knobs) > 1:
            _ = self.data

    @cached_property
    def _hard_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every camera's edges laid end to end (sum P, 4), each patch's camera (sum P,), and per camera, padded to
        the most kept samples: each sample's patch in that layout (C, V) int64, its error per rung (C, R, V) and
        which samples are drawn (C, V) bool."""
        probes = [p for p, _ in hard_probes(self.probes, self.hard_samples)]
        C, R = len(probes), len(self.factors)
        v = max(max(len(p.rows) for p in probes), 1)
        start = np.concatenate([[0], np.cumsum([len(e) for e in self._edges])]).astype(np.int64)
        own = np.zeros((C, v), np.int64)
        err, ok = np.ones((C, R, v), np.float32), np.zeros((C, v), bool)
        for c, (pl, p) in enumerate(zip(self.patches, probes, strict=True)):
            o = self._patch_of(pl, p.rows, p.cols)
            n = len(p.rows)
            own[c, :n], err[c, :, :n], ok[c, :n] = start[c] + np.maximum(o, 0), p.err, o >= 0
        edges = np.concatenate(self._edges) if self._edges else np.zeros((0, 4))
        camera = np.repeat(np.arange(C), np.diff(start))
        return edges, camera, own, err, ok

    def predict(self, values: Mapping[str, float]) -> Prediction:
        """The real factors of each patch (the policy's rule, float32 as the selection makes them), counted exactly
        (one count launch for every camera); each sample's error interpolated between the rungs around its patch's
        mean inner factor."""
        cfg = self.config({**self.fixed, **values})
        edges, camera, own, err, ok = self._hard_samples
        outer, inner = continuous_factors(edges, cfg.target_px)
        outer, inner = outer.astype(np.float32), inner.astype(np.float32)
        pts, tris = count_patches(outer, inner, cfg.spacing, self.device)
        C = len(self.cams)
        npts = np.bincount(camera, weights=pts, minlength=C)
        ntri = np.bincount(camera, weights=tris, minlength=C)
        costs = []
        for c, pl in enumerate(self.patches):
            feats = {"patches": float(len(pl)), "domain_points": float(npts[c]), "triangles": float(ntri[c]),
                     "vertices": 4.0 * len(pl), "draw_calls": 1.0}
            costs.append(sum(self.weights.get(f, 0.0) * x for f, x in feats.items()))
        logf = np.log(self.factors)
        fl = np.log(np.maximum(0.5 * (inner[:, 0] + inner[:, 1]), 1.0))
        f = fl[own] if len(fl) else np.zeros(own.shape, np.float32)  # no patch drawn: every sample invalid
        i = np.clip(np.searchsorted(logf, f) - 1, 0, len(logf) - 2)
        a = np.clip((f - logf[i]) / (logf[i + 1] - logf[i]), 0.0, 1.0)
        e = (1.0 - a) * np.take_along_axis(err, i[:, None, :], axis=1)[:, 0] + a * np.take_along_axis(
            err, (i + 1)[:, None, :], axis=1)[:, 0]
        return Prediction(np.asarray(costs), hard_percentiles(e, ok))


def continuous_patches(terrain: Terrain, cams: list[Camera], level: int, device: str = "cpu") -> list[PatchList]:
    """Each camera's visible patches of ``level`` (the continuous policy's selection; its factors do not matter)."""
    return [select(terrain, c, ContinuousPolicy(1.0, level=level), device=device) for c in cams]
