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

**Compiled once per machine.** A model is a static spec (a hashable :class:`typing.NamedTuple`: the family, the
tree's depth, which knob plays which role) and its data (one pytree of arrays: the probes' pairs, the tree's
metrics, parents and balance maps, the knobs' ranges, the fixed values, the cost weights), padded to a few
fixed sizes (:func:`bucket`: powers of two of the cameras, the roots and the samples). The relaxed function
(``spec.relaxed(data, u, temp)``) is pure and takes the data as an argument, so one program serves every model
of the same spec and sizes, and JAX's persistent cache (:mod:`terrainwarp.fit.jaxrt`) keeps it across processes.
Padded cameras see nothing (cost 0, error at the floor), padded nodes are invisible, padded pairs weigh 0.

**The hard model** reads the real selection (:func:`terrainwarp.lod.select`, one launch a camera) and works on
every camera at once in numpy: each kept sample's node at each level is found once, a patch's counts are read
off a table of the factor rows seen before (:func:`terrainwarp.kernels.tessellator.count_patches` on the rows
new to it), and the percentile is numpy's, camera by camera, over at most :data:`HARD_SAMPLES` of a camera's kept
samples (a fixed subset beyond: its cost does not grow with the terrain).
"""

from __future__ import annotations

import functools
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
from ..lod.policies import make_policy
from ..lod.quadtree import LodState, PatchList, Terrain, node_metrics, select
from ..scene import LodConfig
from .knobs import LEVEL_SCALE, Knob
from .probe import FLOOR_PX, CameraProbe
from .relaxed_tree import balance_maps, forces, inside_counts, node_of, subset, tree_probs
from .search import Prediction

__all__ = ["soft_quantile", "sorted_pairs", "QuadtreeModel", "QuadtreeSpec", "hard_percentile", "hard_percentiles",
           "HARD_SAMPLES", "hard_probes",
           "bucket", "knob_arrays", "relaxed_values", "PaddedModel", "CountTable", "relaxed_call", "pad_to",
           "camera_mask"]

Q = 0.99  # the percentile the budget bounds
LOG_FLOOR = math.log(FLOOR_PX)  # the log error of a camera that sees no sample
PAD_LOGV = 30.0  # the padding's log error: it sorts after every real pair (errors are clipped to 1e6 px)
MIN_PAIRS = 256  # the fewest samples a camera's relaxed pairs are padded to
HARD_MEMO = 4096  # the hard predictions a model keeps
#: the most kept samples of a camera the hard model reads (a deterministic subset beyond,
#: :meth:`terrainwarp.fit.probe.CameraProbe.subset`): its p99 then costs the same on any terrain. No camera of the
#: bundled DEM's paths keeps more (at most 29,924 at 960x540); on a 4097^2 fBm one keeps up to 2^20
HARD_SAMPLES = 1 << 16


# ------------------------------------------------------------------------------------------------
# padding, knobs, the weighted percentile
# ------------------------------------------------------------------------------------------------
def bucket(n: int, least: int = 1) -> int:
    """The padded size of ``n`` items: the power of two at or above it (and at least ``least``)."""
    n = max(int(n), int(least), 1)
    return 1 << (n - 1).bit_length()


def knob_arrays(knobs: Sequence[Knob]) -> dict[str, np.ndarray]:
    """The knobs' ranges as the relaxed functions read them: ``klo`` (log lo for a log knob) and ``kspan`` (log hi
    - log lo, or hi - lo), float32 (K,)."""
    lo = [math.log(k.lo) if k.log else k.lo for k in knobs]
    span = [math.log(k.hi) - math.log(k.lo) if k.log else k.hi - k.lo for k in knobs]
    return {"klo": np.asarray(lo, np.float32), "kspan": np.asarray(span, np.float32)}


def relaxed_values(u: jnp.ndarray, data: Mapping[str, Any], logs: Sequence[bool]) -> list:
    """The knob values at unit coordinates ``u`` (traceable; ``data``'s :func:`knob_arrays`)."""
    out = []
    for i, is_log in enumerate(logs):
        x = data["klo"][i] + jnp.clip(u[i], 0.0, 1.0) * data["kspan"][i]
        out.append(jnp.exp(x) if is_log else x)
    return out


def sorted_pairs(probe: CameraProbe) -> tuple[np.ndarray, np.ndarray]:
    """(log errors of every (resolution, sample) pair, sorted ascending; the permutation that sorts the pairs of
    ``probe.err`` flattened resolution-major)."""
    lv = np.log(np.clip(probe.err.reshape(-1).astype(np.float64), 1e-6, 1e6))
    perm = np.argsort(lv, kind="stable")
    return lv[perm].astype(np.float32), perm.astype(np.int32)


def soft_quantile(logv: jnp.ndarray, w: jnp.ndarray, q: float = Q, n: Any = None) -> jnp.ndarray:
    """The ``q`` quantile of the sorted values ``logv`` (N,) with weights ``w`` (N,), in the same order: the hard
    weighted quantile as its value, with the quantile's implicit derivative in ``w`` (the density around it taken
    over the pairs within 0.1% of the weight either side, at least 16 pairs). ``n``: the length the window is
    reckoned on (default N; a padded model passes its pairs' unpadded length). With no weight at all (a camera
    that sees no sample): the floor's log (:data:`terrainwarp.fit.probe.FLOOR_PX`), gradient 0."""
    n = logv.shape[0] if n is None else n
    cw = jnp.cumsum(w)
    total = jnp.maximum(cw[-1], 1e-12)
    cws = jax.lax.stop_gradient(cw)
    k = jnp.clip(jnp.searchsorted(cws, q * cws[-1]), 0, n - 1)
    q0 = logv[k]
    m = jnp.maximum(16, n // 1000)
    lo, hi = jnp.clip(k - m, 0, n - 1), jnp.clip(k + m, 0, n - 1)
    span = jnp.maximum(logv[hi] - logv[lo], 1e-3)
    dens = jax.lax.stop_gradient(jnp.maximum((cws[hi] - cws[lo]) / jnp.maximum(cws[-1], 1e-30), 1e-6) / span)
    frac = cw[k] / total
    return jnp.where(cws[-1] > 0, q0 - (frac - jax.lax.stop_gradient(frac)) / dens, LOG_FLOOR)


def hard_probes(probes: Sequence[CameraProbe], n: int = HARD_SAMPLES) -> list[tuple[CameraProbe, np.ndarray]]:
    """Each camera's probe as the hard model reads it: at most ``n`` of its kept samples (the deterministic subset
    of :meth:`CameraProbe.subset`), with their indices among the kept ones."""
    return [(p.subset(n), subset(len(p.rows), n)) for p in probes]


def hard_percentile(values: np.ndarray, q: float = 99.0) -> float:
    """``np.percentile`` of the finite values (0 when there are none), to the bit: its linear interpolation, in
    the values' dtype, between the two order statistics around ``(n - 1) q / 100``, found by one partition
    (without numpy's general-case overhead; tested against it)."""
    v = values[np.isfinite(values)]
    n = v.size
    if not n:
        return 0.0
    x = (n - 1) * (q / 100.0)
    i = math.floor(x)
    if x >= n - 1:
        return float(v.max())
    p = np.partition(v, (i, i + 1))
    a, b, g = p[i], p[i + 1], x - i
    d = b - a
    return float(b - d * (1 - g) if g >= 0.5 else a + d * g)


def hard_percentiles(values: np.ndarray, valid: np.ndarray, q: float = 99.0) -> np.ndarray:
    """:func:`hard_percentile` of each row of ``values`` (C, V) over its ``valid`` (C, V) entries."""
    return np.asarray([hard_percentile(v[ok], q) for v, ok in zip(values, valid, strict=True)])


class CountTable:
    """The domain points and triangles of each patch factor row (outer[4], inner[2]) of one spacing, counted once:
    :func:`terrainwarp.kernels.tessellator.count_patches` runs on the rows the table has not seen."""

    def __init__(self, spacing: str, device: str = "cpu") -> None:
        self.spacing, self.device = spacing, device
        self.known: dict[bytes, tuple[int, int]] = {}

    def totals(self, outer: np.ndarray, inner: np.ndarray) -> tuple[int, int]:
        """(domain points, triangles) of the patches (P, 4) and (P, 2), summed."""
        if not len(outer):
            return 0, 0
        rows = np.ascontiguousarray(np.concatenate([np.asarray(outer, np.float32), np.asarray(inner, np.float32)],
                                                   axis=1))
        uniq, first, inv = np.unique(rows.view(np.dtype((np.void, 24))).ravel(), return_index=True,
                                     return_inverse=True)
        keys = [u.tobytes() for u in uniq]
        new = [i for i, k in enumerate(keys) if k not in self.known]
        if new:
            pts, tris = count_patches(rows[first[new], :4], rows[first[new], 4:], self.spacing, self.device)
            for i, p, t in zip(new, pts, tris, strict=True):
                self.known[keys[i]] = (int(p), int(t))
        mult = np.bincount(inv.ravel(), minlength=len(keys)).astype(np.int64)
        counts = np.asarray([self.known[k] for k in keys], np.int64)
        return int(counts[:, 0] @ mult), int(counts[:, 1] @ mult)


# ------------------------------------------------------------------------------------------------
# what the padded models share
# ------------------------------------------------------------------------------------------------
@functools.partial(jax.jit, static_argnums=0)
def _relaxed_jit(spec, data, u, temp):
    return spec.relaxed(data, jnp.asarray(u, jnp.float32), jnp.asarray(temp, jnp.float32))


def relaxed_call(spec, data, u, temp) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``spec.relaxed(data, u, temp)`` jitted (one program per spec and padded sizes)."""
    return _relaxed_jit(spec, data, u, temp)


class PaddedModel:
    """What every model with a padded relaxed function shares (``spec``, ``data``, ``cams``, ``predict``): the
    relaxed model at its own cameras, the padded layout of the bounded values (each camera's p99, then each pair's
    pop), and the hard model with a memo of the settings seen."""

    cams: list[Camera]

    @property
    def padded_cameras(self) -> int:
        return int(self.data["cmask"].shape[0])

    def padded(self, values: np.ndarray, fill: float) -> np.ndarray:
        """``values`` (one per bounded value) laid out as the padded model's bounded output; ``fill`` on padding."""
        c, cb = len(self.cams), self.padded_cameras
        values = np.asarray(values, np.float32)
        out = np.full(cb + (cb - 1 if self.spec.pops else 0), fill, np.float32)
        out[:c] = values[:c]
        if self.spec.pops:
            out[cb:cb + c - 1] = values[c:]
        return out

    def hard(self, values: Mapping[str, float]) -> Prediction:
        """The hard model at ``values`` (:meth:`predict`), each setting computed once (the polish's lines meet the
        same settings again; the prediction is a function of the values alone)."""
        memo = self.__dict__.setdefault("_hard_memo", {})
        key = tuple(sorted((k, float(v)) for k, v in values.items()))
        if key not in memo:
            if len(memo) >= HARD_MEMO:
                memo.clear()
            memo[key] = self.predict(values)
        return memo[key]

    def relaxed(self, u: jnp.ndarray, temp: float) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(cost per camera (C,), log p99 px per camera (C,), then with a pop bound each consecutive pair's log pop
        p99 (C-1,)) at unit coordinates ``u`` and temperature ``temp`` (jitted; differentiable in ``u``)."""
        cost, b = relaxed_call(self.spec, self.data, u, temp)
        c, cb = len(self.cams), self.padded_cameras
        if self.spec.pops:
            return cost[:c], jnp.concatenate([b[:c], b[cb:cb + c - 1]])
        return cost[:c], b[:c]


def pad_to(a: np.ndarray, shape: tuple[int, ...], fill: float = 0.0) -> np.ndarray:
    """``a`` in the top corner of a ``fill``-ed array of ``shape`` (same dtype)."""
    out = np.full(shape, fill, a.dtype)
    out[tuple(slice(0, s) for s in a.shape)] = a
    return out


def camera_mask(c: int) -> np.ndarray:
    """1 on the real cameras of a padded camera axis."""
    out = np.zeros(bucket(c), np.float32)
    out[:c] = 1.0
    return out


# ------------------------------------------------------------------------------------------------
# the quadtree policies: the relaxed model
# ------------------------------------------------------------------------------------------------
class QuadtreeSpec(NamedTuple):
    """The static part of a :class:`QuadtreeModel` (its program): the tree's depth, the policy (sse splits above
    its threshold, distance below), whether the cameras chain (hysteresis), whether pops are predicted, and per
    fitted knob its space and role (index in ``u``; -1: fixed, read from the data)."""

    kind: str
    depth: int
    sse: bool
    chained: bool
    pops: bool
    logs: tuple[bool, ...]
    main: int
    scales: tuple[int, ...]
    hyst: int

    def relaxed(self, data: Mapping[str, Any], u: jnp.ndarray, temp: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        return quadtree_relaxed(self, data, u, temp)


def _thresholds(spec: QuadtreeSpec, d: Mapping[str, Any], v: list) -> tuple[list, Any]:
    """log threshold per level (sse: px; distance: m, the level's node size in), and the hysteresis band."""
    base = jnp.log(v[spec.main]) if spec.main >= 0 else d["base"]
    thr = [base + (v[s] if s >= 0 else d["scale"][L]) + d["size"][L] for L, s in enumerate(spec.scales)]
    return thr, (v[spec.hyst] if spec.hyst >= 0 else d["hyst"])


def quadtree_relaxed(spec: QuadtreeSpec, d: Mapping[str, Any], u: jnp.ndarray,
                     temp: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(cost per padded camera, log p99 per padded camera [, log pop p99 per padded pair]) (pure; see the module
    docstring)."""
    thr, h = _thresholds(spec, d, relaxed_values(u, d, spec.logs))
    depth, parents, maps = spec.depth, d["parent"], d["balance"]
    sign = 1.0 if spec.sse else -1.0  # sse splits above the threshold, distance below
    # the kernel's band: a node not split at the camera before needs threshold * (1 + h) (sse) or is split
    # below threshold * (1 - h) (distance); one split before, the other way round
    fresh, held = (jnp.log1p(h), jnp.log1p(-h)) if spec.sse else (jnp.log1p(-h), jnp.log1p(h))

    def camera(prev, cam):
        metric, vis_c, logv, gidx, mask = cam
        split = []  # each level's split probability where reached: the policy's, then the balance's
        for L in range(depth + 1):
            if L == depth:
                split.append(jnp.zeros_like(vis_c[L]))
                continue
            s = jax.nn.sigmoid(sign * (metric[L] - (thr[L] + fresh)) / temp)
            if spec.chained:
                held_s = jax.nn.sigmoid(sign * (metric[L] - (thr[L] + held)) / temp)
                s = prev[L] * held_s + (1.0 - prev[L]) * s
            split.append(s * vis_c[L])
        force = [jnp.zeros_like(v) for v in vis_c]
        for _ in range(2):  # the balance reads the tree it changes: two rounds
            inside, total = tree_probs(split, force, vis_c, parents)
            force = forces(total, inside, vis_c, maps)
        inside, total = tree_probs(split, force, vis_c, parents)
        leaves = [r * (1.0 - s) * v for r, s, v in zip(inside, total, vis_c, strict=True)]
        splits = [r * s for r, s in zip(inside, total, strict=True)]
        cost = d["unit_cost"] * sum(jnp.sum(lf) for lf in leaves)
        w = jnp.concatenate(leaves)[gidx] * mask
        return (splits if spec.chained else prev), (cost, soft_quantile(logv, w, n=d["npairs"]), leaves)

    # scan over the cameras (the leading axis of every array): the body is traced once
    xs = (list(d["metric"]), list(d["vis"]), d["logv"], d["gidx"], d["mask"])
    init = [jnp.zeros_like(d["vis"][L][0]) for L in range(depth + 1)]
    _, (costs, errs, leaves) = jax.lax.scan(camera, init, xs)
    if not spec.pops:
        return costs, errs
    return costs, jnp.concatenate([errs, _relaxed_pops(leaves, d["pop"], depth)])


def _relaxed_pops(leaves: list, data: Mapping[str, Any], depth: int) -> jnp.ndarray:
    """Each consecutive pair's log pop p99: per sample, the probability of each pair of levels (drawn at one for
    the camera before, at the other now) weighs that pair's pop, and of the same level, no pop."""
    R = depth + 1
    pairs = [(a, b) for a in range(R) for b in range(a + 1, R)]

    def pair(_, x):
        before, now, node, logv, idx, mask = x
        A = jnp.stack([before[L][node[L]] for L in range(R)])  # (R, V): drawn at L for the camera before
        B = jnp.stack([now[L][node[L]] for L in range(R)])
        w = [A[a] * B[b] + A[b] * B[a] for a, b in pairs] + [jnp.sum(A * B, axis=0)]
        return None, soft_quantile(logv, jnp.concatenate(w)[idx] * mask, n=data["npairs"])

    before = [lv[:-1] for lv in leaves]
    now = [lv[1:] for lv in leaves]
    _, out = jax.lax.scan(pair, None, (before, now, data["node"], data["logv"], data["idx"], data["mask"]))
    return out


# ------------------------------------------------------------------------------------------------
# the quadtree policies: the model
# ------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class QuadtreeModel(PaddedModel):
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
        hard_samples: the samples the hard model reads per camera (:data:`HARD_SAMPLES`).
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
    pops: list[np.ndarray] | None = None
    hard_samples: int = HARD_SAMPLES  # :func:`terrainwarp.fit.probe.pop_pairs`: the pop constraint's probes

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
    def _inside(self) -> list[tuple[int, int]]:
        return inside_counts(self.terrain)

    @cached_property
    def _sizes(self) -> tuple[list[int], list[int]]:
        """Per level, the nodes of its full grid, and the padded count (the roots padded to a power of two)."""
        (nx, nz), R = self.terrain.roots, self.terrain.depth + 1
        return [(nx * nz) << (2 * L) for L in range(R)], [bucket(nx * nz) << (2 * L) for L in range(R)]

    @cached_property
    def spec(self) -> QuadtreeSpec:
        names = [k.name for k in self.knobs]
        main = "tolerance_px" if self.policy == "sse" else "k"
        h = float(self.fixed.get("hysteresis", 0.0))
        return QuadtreeSpec("quadtree", self.terrain.depth, self.policy == "sse",
                            "hysteresis" in names or h > 0, self.pops is not None, tuple(k.log for k in self.knobs),
                            names.index(main) if main in names else -1,
                            tuple(names.index(f"{LEVEL_SCALE}{L}") if f"{LEVEL_SCALE}{L}" in names else -1
                                  for L in range(self.terrain.depth + 1)),
                            names.index("hysteresis") if "hysteresis" in names else -1)

    @cached_property
    def data(self) -> dict[str, Any]:
        """The arrays the relaxed model reads (one pytree, numpy, padded: see the module docstring)."""
        tree, (_, padded), R = self._tree, self._sizes, self.terrain.depth + 1
        cb = bucket(len(self.cams))
        main = "tolerance_px" if self.policy == "sse" else "k"
        maps = [tuple(pad_to(a, (padded[L], 8)) for a in m) for L, m in enumerate(balance_maps(self.terrain))]
        per = self._per_patch
        return {"metric": [pad_to(m, (cb, padded[L])) for L, m in enumerate(tree["metric"])],
                "vis": [pad_to(v, (cb, padded[L])) for L, v in enumerate(tree["vis"])],
                "parent": [pad_to(p, (padded[L],)) for L, p in enumerate(tree["parent"])], "balance": maps,
                **self._pairs, **knob_arrays(self.knobs), "cmask": camera_mask(len(self.cams)),
                "base": np.float32(math.log(self.fixed[main]) if main in self.fixed else 0.0),
                "scale": np.asarray([self.fixed.get(f"{LEVEL_SCALE}{L}", 0.0) for L in range(R)], np.float32),
                "size": np.asarray([0.0 if self.policy == "sse" else math.log(s) for s in tree["size"]], np.float32),
                "hyst": np.float32(self.fixed.get("hysteresis", 0.0)),
                "unit_cost": np.float32(sum(self.weights.get(f, 0.0) * per[f] for f in per)),
                **({"pop": self._pop_data} if self.pops is not None else {})}

    @cached_property
    def _pairs(self) -> dict[str, np.ndarray]:
        """The relaxed subsets of every camera, padded and stacked, in each camera's sorted order of log error:
        ``logv`` (C, N) the pairs' log errors, ascending (padding last), ``gidx`` (C, N) each pair's node in the
        levels' padded nodes laid end to end (level 0 first), ``mask`` (C, N) 0 on the padding; ``npairs`` the
        unpadded length (the most pairs of any camera)."""
        subs = [p.subset(self.relaxed_samples) for p in self.probes]
        R = self.terrain.depth + 1
        v = max(max(len(p.rows) for p in subs), 1)
        n, cb = R * bucket(v, MIN_PAIRS), bucket(len(subs))
        offset = np.concatenate([[0], np.cumsum(self._sizes[1])[:-1]]).astype(np.int64)
        logv = np.full((cb, n), PAD_LOGV, np.float32)
        gidx = np.zeros((cb, n), np.int32)
        mask = np.zeros((cb, n), np.float32)
        for c, p in enumerate(subs):
            node = np.stack([node_of(p.rows, p.cols, self.terrain, L, self._inside[L]) + offset[L]
                             for L in range(R)]).reshape(-1)  # resolution-major, as the probe's errors
            lv, perm = sorted_pairs(p)
            logv[c, :len(lv)] = lv
            gidx[c, :len(lv)] = node[perm]
            mask[c, :len(lv)] = 1.0
        return {"logv": logv, "gidx": gidx, "mask": mask, "npairs": np.int32(R * v)}

    @cached_property
    def _per_patch(self) -> dict[str, float]:
        """Features of one patch at the terrain's T (no doubled edge)."""
        t = float(self.terrain.tess)
        pts, tris = count_patches(np.full((1, 4), t, np.float32), np.full((1, 2), t, np.float32),
                                  self.config(self.fixed).spacing)
        return {"patches": 1.0, "domain_points": float(pts[0]), "triangles": float(tris[0]), "vertices": 4.0,
                "draw_calls": 0.0}

    @cached_property
    def _pop_data(self) -> dict[str, np.ndarray]:
        """For the cameras after the first, padded and stacked: each kept sample's node per level ``node`` (C-1, R,
        V), the sorted log pops of every (level pair, sample) and (no change, sample) entry ``logv`` (C-1, (P+1) V),
        each sorted entry's index ``idx`` in that layout and ``mask``; ``npairs``: the unpadded length."""
        R = self.terrain.depth + 1
        kept = [(p, pairs, subset(len(p.rows), self.relaxed_samples))
                for p, pairs in zip(self.probes[1:], self.pops, strict=True)]
        v = max(max((len(k) for _, _, k in kept), default=1), 1)
        V, P, n = bucket(v, MIN_PAIRS), R * (R - 1) // 2, bucket(len(self.cams)) - 1
        node = np.zeros((n, R, V), np.int32)
        logv = np.full((n, (P + 1) * V), PAD_LOGV, np.float32)
        idx = np.zeros((n, (P + 1) * V), np.int32)
        mask = np.zeros((n, (P + 1) * V), np.float32)
        for c, (p, pairs, keep) in enumerate(kept):
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
        return {"node": node, "logv": logv, "idx": idx, "mask": mask, "npairs": np.int32((P + 1) * v)}

    def prepare(self) -> None:
        """Build what the hard model reads, and the relaxed model's data where there is more than one knob (a
        one-knob model is fitted on its hard line alone); what is not built here is built on first use."""
        _ = self._hard_data, self._leaf_map
        if len(self.knobs) > 1:
            _ = self.data

    # -- the hard model -----------------------------------------------------------------------------
    def predict(self, values: Mapping[str, float]) -> Prediction:
        """The model at temperature 0: the real selection (balance and edge factors included) per camera, in path
        order with one hysteresis state; its draws counted exactly (:class:`CountTable`); each sample's error read
        off the probe of its leaf's level."""
        cfg = self.config({**self.fixed, **values})
        policy = make_policy(cfg)
        state = LodState() if cfg.hysteresis > 0 else None
        pls = [select(self.terrain, cam, policy, state, device=self.device) for cam in self.cams]
        table = self._counts(cfg.spacing)
        costs = []
        for pl in pls:
            pts, tris = table.totals(pl.outer, pl.inner)
            feats = {"patches": float(len(pl)), "domain_points": float(pts), "triangles": float(tris),
                     "vertices": 4.0 * len(pl), "draw_calls": 1.0}
            costs.append(sum(self.weights.get(f, 0.0) * x for f, x in feats.items()))
        nodes, err, ok = self._hard_data
        now = np.stack([self._levels_of(pl, nodes[c], self._lines[c]) for c, pl in enumerate(pls)])
        C, R, V = err.shape
        flat = (np.arange(C)[:, None] * R + np.maximum(now, 0)) * V + np.arange(V)[None, :]
        p99 = hard_percentiles(err.reshape(-1)[flat], ok & (now >= 0))
        pops = None
        if self.pops is not None:
            keep = [k for _, k in self._hard_probes]
            pops = np.asarray([hard_percentile(self._pop_of(self._levels_of(pls[c - 1], nodes[c],
                                                                            self._lines[c])[ok[c]],
                                                            now[c][ok[c]], self.pops[c - 1][:, keep[c]]))
                               for c in range(1, len(pls))])
        return Prediction(np.asarray(costs), p99, pops)

    def _counts(self, spacing: str) -> CountTable:
        tables = self.__dict__.setdefault("_count_tables", {})
        if spacing not in tables:
            tables[spacing] = CountTable(spacing, self.device)
        return tables[spacing]

    @cached_property
    def _hard_data(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per camera, padded to the most kept samples: each kept sample's node at every level in the levels' full
        grids laid end to end (C, R, V) int64, its error at every level (C, R, V) float32, and which are real
        (C, V) bool."""
        t, R = self.terrain, self.terrain.depth + 1
        offset = np.concatenate([[0], np.cumsum(self._sizes[0])[:-1]]).astype(np.int64)
        probes = [p for p, _ in self._hard_probes]
        v = max(max(len(p.rows) for p in probes), 1)
        nodes = np.zeros((len(probes), R, v), np.int64)
        err = np.ones((len(probes), R, v), np.float32)
        ok = np.zeros((len(probes), v), bool)
        for c, p in enumerate(probes):
            n = len(p.rows)
            nodes[c, :, :n] = np.stack([node_of(p.rows, p.cols, t, L, self._inside[L]) + offset[L] for L in range(R)])
            err[c, :, :n] = p.err
            ok[c, :n] = True
        return nodes, err, ok

    @cached_property
    def _hard_probes(self) -> list[tuple[CameraProbe, np.ndarray]]:
        return hard_probes(self.probes, self.hard_samples)

    @cached_property
    def _offsets(self) -> np.ndarray:
        """Where each level's full grid starts with the levels laid end to end."""
        return np.concatenate([[0], np.cumsum(self._sizes[0])[:-1]]).astype(np.int64)

    @cached_property
    def _leaf_map(self) -> np.ndarray:
        """Scratch: each node of the full grids laid end to end, its level where it is a drawn leaf, else -1."""
        return np.full(int(sum(self._sizes[0])), -1, np.int8)

    def _levels_of(self, pl: PatchList, nodes: np.ndarray, line: np.ndarray | None = None) -> np.ndarray:
        """The level of the drawn leaf of ``pl`` over each sample of ``nodes`` (R, V) (-1 where none covers it; the
        deepest where several would). ``line``: the samples' finest nodes (:attr:`_lines`), when their nodes are
        one ancestor line: the drawn leaf's level is then carried down the tree once and read once a sample."""
        t = self.terrain
        lvl = pl.level.astype(np.int64)
        s = t.root_cells / 2.0 ** lvl
        lx = np.rint(pl.origin_cells[:, 0] / s).astype(np.int64)
        ly = np.rint(pl.origin_cells[:, 1] / s).astype(np.int64)
        at = self._offsets[lvl] + ly * (t.roots[0] << lvl) + lx
        lm = self._leaf_map
        lm[at] = lvl
        if line is not None:
            off, size = self._offsets, self._sizes[0]
            acc = lm[off[0]:off[0] + size[0]]
            for L in range(1, len(size)):
                seg = lm[off[L]:off[L] + size[L]]
                acc = np.where(seg >= 0, seg, acc[self._parents[L]])  # the deepest drawn leaf above each node
            lm[at] = -1
            return acc[line].astype(np.int64)
        g = lm[nodes]
        lm[at] = -1
        levels = np.arange(len(nodes), dtype=np.int8)[:, None]
        return np.where(g == levels, levels, np.int8(-1)).max(axis=0).astype(np.int64)  # the deepest drawn leaf

    @cached_property
    def _parents(self) -> list[np.ndarray]:
        """Per level (from 1), each node's parent in the level above (indices in the levels' full grids)."""
        out: list[np.ndarray] = [np.zeros(0, np.int64)]
        for L in range(1, self.terrain.depth + 1):
            nx = self.terrain.roots[0] << L
            y, x = np.divmod(np.arange(self._sizes[0][L], dtype=np.int64), nx)
            out.append((y // 2) * (nx // 2) + x // 2)
        return out

    @cached_property
    def _lines(self) -> list[np.ndarray | None]:
        """Per camera, each kept sample's finest node (in the deepest level's full grid) where every sample's nodes
        are one ancestor line and carrying the leaves down the tree costs less than reading every level (else
        None: :meth:`_levels_of` reads the levels one by one)."""
        nodes, _, ok = self._hard_data
        R, off = self.terrain.depth + 1, self._offsets
        out = []
        for c in range(len(nodes)):
            n = int(ok[c].sum())
            if sum(self._sizes[0]) >= R * max(n, 1):
                out.append(None)
                continue
            loc = nodes[c, :, :n] - off[:, None]
            up, nested = loc[R - 1], True
            for L in range(R - 1, 0, -1):
                up = self._parents[L][up]
                if not np.array_equal(up, loc[L - 1]):
                    nested = False
                    break
            out.append(np.concatenate([loc[R - 1], np.zeros(nodes.shape[2] - n, np.int64)]) if nested else None)
        return out

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
