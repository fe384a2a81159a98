"""Knobs: the settings a fit moves, named and discoverable, and the one map from knob values to a :class:`Scene`.

Every family's knobs live in :class:`terrainwarp.LodConfig` (a fitted setting is one scene, which saves to TOML
and loads back): the quadtree policies' fields (``tolerance_px``, ``k``, ``target_px``, ``level``, ``tess``,
``hysteresis``, a log-multiplier of the threshold per level as ``level_log_scale_<L>``), and a scheme's knobs in
``LodConfig.params`` (its main parameter and the :class:`terrainwarp.schemes.SchemeKnob` it declares)::

    from terrainwarp.fit import apply, knobs

    for k in knobs("cdlod", hm):
        print(k.name, k.lo, k.hi, k.integer, k.log)       # first_range, ratio, morph_start_ratio, grid
    scene = apply(scene, "cdlod", {"first_range": 3000.0, "ratio": 2.5, "grid": 16})

A knob is searched in a unit box (:meth:`Knob.to_unit` / :meth:`Knob.from_unit`): log space for a size or a
ratio, linear otherwise; integer knobs snap to their allowed values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from ..heightmap import Heightmap
from ..kernels.checks import check_choice, is_number
from ..lod.quadtree import layout
from ..scene import MAX_TESS, POLICY_TABLE, QUADTREE_TESS, LodConfig, Scene
from ..schemes import SCHEMES, get_scheme, scheme_range

__all__ = ["Knob", "knobs", "check_knob_names", "apply", "values_of", "main_knob", "LEVEL_SCALE", "MAX_LEVEL_SCALE"]

LEVEL_SCALE = "level_log_scale_"  # + level: the knob of that level's threshold multiplier (log)
MAX_LEVEL_SCALE = 3.0  # a level's threshold searched within a factor e^3 (20) of the base either way
MAX_HYSTERESIS = 0.75  # the band searched: [0, 0.75] (LodConfig allows [0, 1))
MIN_CONTINUOUS_CELLS = 4  # the continuous policy's finest level: patches of 4 cells a side


class Knob(NamedTuple):
    """One knob of a family.

    Attributes:
        name: its name (a ``LodConfig`` field, ``level_log_scale_<L>``, or a scheme's knob).
        lo, hi: the range searched, both ends included.
        integer: an integer knob (``choices`` when only some integers are allowed).
        log: searched in log space.
        choices: the allowed values of an integer knob, ascending (None: every integer in the range).
        coarser_up: True when a larger value draws a coarser mesh, False when finer, None when neither always.
        doc: what it does.
    """

    name: str
    lo: float
    hi: float
    integer: bool = False
    log: bool = False
    choices: tuple[float, ...] | None = None
    coarser_up: bool | None = None
    doc: str = ""

    def snap(self, v: float) -> float | int:
        """``v`` clipped to the range; an integer knob's rounded to the nearest allowed value (in log space for a
        log knob: 12 snaps to 16 between 8 and 16 only past their geometric mean)."""
        v = float(np.clip(float(v), self.lo, self.hi))
        if not self.integer:
            return v
        opts = np.asarray(self.choices if self.choices is not None else np.arange(math.ceil(self.lo),
                                                                                  math.floor(self.hi) + 1), float)
        d = np.abs(np.log(opts) - math.log(v)) if self.log else np.abs(opts - v)
        return int(opts[int(np.argmin(d))])

    def to_unit(self, v: float) -> float:
        """``v`` in the unit box: 0 at ``lo``, 1 at ``hi`` (log or linear)."""
        v = float(np.clip(float(v), self.lo, self.hi))
        if self.log:
            return (math.log(v) - math.log(self.lo)) / (math.log(self.hi) - math.log(self.lo))
        return (v - self.lo) / (self.hi - self.lo)

    def from_unit(self, u: float) -> float:
        """The value at ``u`` of the unit box (not snapped)."""
        u = float(np.clip(u, 0.0, 1.0))
        if self.log:
            return math.exp(math.log(self.lo) + u * (math.log(self.hi) - math.log(self.lo)))
        return self.lo + u * (self.hi - self.lo)

    @property
    def values(self) -> tuple[float, ...] | None:
        """An integer knob's allowed values (None for a continuous knob)."""
        if not self.integer:
            return None
        return tuple(self.choices) if self.choices is not None else tuple(
            float(v) for v in range(math.ceil(self.lo), math.floor(self.hi) + 1))


# ------------------------------------------------------------------------------------------------
# the knobs of each family
# ------------------------------------------------------------------------------------------------
def knobs(policy: str, heightmap: Heightmap, lod: LodConfig | None = None, *, cache: dict | None = None
          ) -> tuple[Knob, ...]:
    """The knobs of ``policy`` on ``heightmap``, its main knob first.

    * ``sse`` / ``distance``: ``tolerance_px`` / ``k``; ``level_log_scale_<L>`` for the levels 1..D-1 that split
      (D the deepest level of the quadtree ``lod`` lays out: its ``roots`` and ``tess``; level 0 takes the base
      threshold); ``tess`` (a power of two); ``hysteresis``.
    * ``continuous``: ``target_px`` and ``level`` (the uniform patch level, 0..D).
    * a scheme: its main parameter (its range on ``heightmap``, :func:`terrainwarp.schemes.scheme_range`) and the
      knobs it declares (CDLOD: ``ratio``, ``morph_start_ratio``, ``grid``; clipmaps: ``levels``,
      ``transition_ratio``; chunked: ``tile``).

    Args:
        lod: the configuration whose structure (roots, tess) the level knobs follow (default ``LodConfig()``).
        cache: a dict kept for one heightmap, where a scheme keeps what it prepares to find its range.
    """
    lod = LodConfig() if lod is None else lod
    check_choice("policy", policy, [*POLICY_TABLE, *SCHEMES])  # every policy with knobs, the schemes' too
    if policy in POLICY_TABLE:
        return _quadtree_knobs(policy, heightmap, lod)
    spec = get_scheme(policy)
    lo, hi = scheme_range(policy, heightmap, cache={} if cache is None else cache)
    main = Knob(spec.parameter, lo, hi, integer=spec.odd_integer, log=True,
                choices=tuple(float(v) for v in range(int(math.ceil(lo)) | 1, int(hi) + 1, 2))
                if spec.odd_integer else None, coarser_up=not spec.larger_is_finer, doc=spec.doc)
    extra = []
    for k in spec.knobs:
        hi_k = k.hi
        if policy == "clipmaps" and k.name == "levels":  # more levels than cover the terrain draw nothing more
            hi_k = float(_clipmap_cover(heightmap, int(lo)))
        extra.append(Knob(k.name, float(k.lo), float(hi_k), k.integer, k.log,
                          None if k.choices is None else tuple(float(c) for c in k.choices), None, k.doc))
    return (main, *extra)


def main_knob(policy: str, heightmap: Heightmap, lod: LodConfig | None = None, *,
              cache: dict | None = None) -> Knob:
    """The one knob of the one-knob fit: the policy's ``POLICY_TABLE`` parameter or the scheme's main parameter."""
    return knobs(policy, heightmap, lod, cache=cache)[0]


def _quadtree_knobs(policy: str, heightmap: Heightmap, lod: LodConfig) -> tuple[Knob, ...]:
    spec = POLICY_TABLE[policy]
    lo, hi = spec.fit_range
    main = Knob(spec.field, max(lo, 1e-6), hi, log=True, coarser_up=spec.coarser_up, doc=spec.help)
    if policy == "continuous":
        _, depth, _ = layout(heightmap.shape, lod.roots, MIN_CONTINUOUS_CELLS, None)
        return (main, Knob("level", 0, depth, integer=True, coarser_up=False,
                           doc=f"the uniform patch grid's quadtree level (finer up; patches of at least "
                               f"{MIN_CONTINUOUS_CELLS} cells a side)"))
    _, depth, _ = layout(heightmap.shape, lod.roots, lod.tess if lod.tess in QUADTREE_TESS else 16, None)
    scales = tuple(Knob(f"{LEVEL_SCALE}{L}", -MAX_LEVEL_SCALE, MAX_LEVEL_SCALE, coarser_up=spec.coarser_up,
                        doc=f"log multiplier of level {L}'s split threshold") for L in range(1, depth))
    return (main, *scales,
            Knob("tess", QUADTREE_TESS[0], QUADTREE_TESS[-1], integer=True, log=True,
                 choices=tuple(float(t) for t in QUADTREE_TESS),
                 doc="tessellation level T of every patch (a power of two; 2T on edges toward a finer neighbour)"),
            Knob("hysteresis", 0.0, MAX_HYSTERESIS, doc="band between the split and the merge threshold"))


def _clipmap_cover(heightmap: Heightmap, n: int) -> int:
    """The levels that let clipmaps of ring size ``n`` cover the terrain from anywhere above it (its default)."""
    hh, ww = heightmap.shape
    m = (n - 1) // 2
    return max(1, math.ceil(math.log2(max(max(ww - 1, hh - 1) / max(m - 1, 1), 1.0)) - 1e-12) + 1)


# ------------------------------------------------------------------------------------------------
# knob values <-> scenes
# ------------------------------------------------------------------------------------------------
def check_knob_names(policy: str, heightmap: Heightmap, names: Sequence[str] | str | None,
                     lod: LodConfig | None = None) -> None:
    """Check a fit's ``knobs`` argument before any frame is made: None, ``"all"`` or names of :func:`knobs`.

    Raises:
        TypeError: not None, "all" or a list of strings. ValueError: a name ``policy`` has no knob of (named).
    """
    if names is None or names == "all":
        return
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"knobs: expected None, 'all' or a list of knob names, got {names!r}")
    known = [k.name for k in knobs(policy, heightmap, lod)]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"knobs: {policy!r} has no knob {unknown}; its knobs are {known}")


def apply(scene: Scene, policy: str, values: Mapping[str, Any]) -> Scene:
    """The scene that draws ``policy`` with the knob ``values`` (name -> value; knobs left out keep the scene's
    value, or the policy's default): ``mesh = "lod"`` and its ``LodConfig`` set. Integer knobs must be integers
    (a float that is one is taken).

    Raises:
        ValueError: an unknown policy or knob name, or a value the configuration refuses (out of range, tess not
            a power of two for a quadtree policy, ...), named.
        TypeError: a value that is not a number.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a Scene, got {type(scene).__name__}")
    if not isinstance(values, Mapping):
        raise TypeError(f"values: expected a mapping of knob names to values, got {type(values).__name__}")
    for k, v in values.items():
        if not is_number(v):
            raise TypeError(f"values[{k!r}]: expected a number, got {v!r}")
    if policy in POLICY_TABLE:
        return scene.with_(mesh="lod", lod=_quadtree_config(scene.lod, policy, values, scene.heightmap.shape))
    spec = get_scheme(policy)
    names = {spec.parameter, *(k.name for k in spec.knobs)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"values: {policy!r} has no knob {unknown}; its knobs are {sorted(names)}")
    kept = dict(scene.lod.params) if scene.lod.policy == policy else {}
    integer = {k.name for k in spec.knobs if k.integer} | ({spec.parameter} if spec.odd_integer else set())
    new = {k: _as_int(k, v) if k in integer else float(v) for k, v in values.items()}
    lod = LodConfig(**{**scene.lod.__dict__, "policy": policy, "params": {**kept, **new}, "level_log_scale": ()})
    return scene.with_(mesh="lod", lod=lod)


def _quadtree_config(lod: LodConfig, policy: str, values: Mapping[str, Any], shape: tuple[int, int]) -> LodConfig:
    spec = POLICY_TABLE[policy]
    fields = {spec.field, "hysteresis", "tess", *(("level",) if policy == "continuous" else ())}
    scales = {k: v for k, v in values.items() if k.startswith(LEVEL_SCALE)}
    unknown = sorted(set(values) - fields - set(scales))
    if unknown or (scales and policy == "continuous"):
        raise ValueError(f"values: {policy!r} has no knob {unknown or sorted(scales)}; its knobs are "
                         f"{sorted(fields)}" + ("" if policy == "continuous" else f" and {LEVEL_SCALE}<level>"))
    base = lod if lod.policy == policy else lod.with_policy(policy, getattr(lod, spec.field))
    if lod.is_scheme:
        base = LodConfig(**{**lod.__dict__, "policy": "sse", "params": ()}).with_policy(policy,
                                                                                         getattr(lod, spec.field))
    cfg: dict[str, Any] = {k: (_as_int(k, v) if k in ("tess", "level") else float(v)) for k, v in values.items()
                           if k in fields}
    if scales:
        levels = {int(k[len(LEVEL_SCALE):]) for k in scales if k[len(LEVEL_SCALE):].isdigit()}
        if len(levels) != len(scales) or min(levels) < 0:
            raise ValueError(f"values: expected {LEVEL_SCALE}<level> with a level >= 0, got {sorted(scales)}")
        m = list(base.level_log_scale) + [0.0] * (max(levels) + 1 - len(base.level_log_scale))
        for L in levels:
            m[L] = float(scales[f"{LEVEL_SCALE}{L}"])
        cfg["level_log_scale"] = tuple(m)
    if "tess" in cfg and cfg["tess"] > MAX_TESS:
        raise ValueError(f"values['tess']: expected at most {MAX_TESS}, got {cfg['tess']}")
    if policy == "continuous" and "level" in cfg and "tess" not in cfg:
        cfg["tess"] = _continuous_tess(shape, base.roots, cfg["level"], base.tess)
    return LodConfig(**{**base.__dict__, **cfg})


def _continuous_tess(shape: tuple[int, int], roots: int | tuple[int, int], level: int, tess: int) -> int:
    """The layout T a continuous ``level`` needs: ``tess`` lowered to the powers of two below it until the quadtree
    of ``roots`` over ``shape`` is ``level`` deep. T only lays the continuous patches out (their factors are per
    edge), so a level deeper than the scene's tree takes a smaller T rather than being clamped to its depth."""
    t = int(tess)
    while t > 1 and layout(shape, roots, t, None)[1] < level:
        t = 1 << (t.bit_length() - (2 if t & (t - 1) == 0 else 1))
    return t


def values_of(scene: Scene, policy: str, names: Sequence[str]) -> dict[str, float]:
    """The scene's current value of each knob in ``names`` (a scheme's knob left out: its default; a level
    multiplier past the configuration's list: 0)."""
    lod = scene.lod
    out: dict[str, float] = {}
    if policy in POLICY_TABLE:
        for n in names:
            if n.startswith(LEVEL_SCALE):
                L = int(n[len(LEVEL_SCALE):])
                out[n] = float(lod.level_log_scale[L]) if L < len(lod.level_log_scale) else 0.0
            elif lod.is_scheme:
                out[n] = float(getattr(LodConfig(), n))
            else:
                out[n] = float(getattr(lod, n))
        return out
    spec = SCHEMES[policy]
    params = dict(lod.params) if lod.policy == policy else {}
    defaults = {k.name: k.default for k in spec.knobs}
    for n in names:
        v = params.get(n, defaults.get(n))
        out[n] = math.nan if v is None else float(v)
    return out


def _as_int(name: str, v: Any) -> int:
    f = float(v)
    if not f.is_integer():
        raise ValueError(f"values[{name!r}]: expected an integer, got {v!r}")
    return int(f)
