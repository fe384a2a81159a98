"""The LOD scheme registry: the one place scheme names live.

A *scheme* is a LOD method drawn as a :class:`terrainwarp.rendering.MeshSource`, tuned by its main parameter
and any further knobs it declares (:class:`SchemeKnob`): the built-in ``cdlod`` (CDLOD's first range, metres;
its distance ratio, morph start and grid), ``clipmaps`` (the ring size n, odd; its levels and transition width)
and ``chunked`` (Cesium's maximum screen-space error, px; its tile size), registered by
:mod:`terrainwarp.rendering.sources`, and yours. A registered name is a ``LodConfig.policy``: a scene with
``mesh = "lod"`` and ``lod = LodConfig(policy=NAME, params={...})`` draws it (its knob values in ``params``).
A registered name is accepted wherever a scheme is: :func:`scheme_source` (then ``render(scene,
source=...)``), the report sweep (``terrainwarp report --policies NAME``,
:func:`terrainwarp.experiments.pareto.sweep`) and the fit (``fit_lod(scene, budget_px, policy=NAME)``,
``terrainwarp fit --policy NAME``)::

    def make(heightmap, value, *, cache, **params):      # -> a MeshSource at this parameter value
        return MySource(heightmap, value, cache=cache)      # params: your knobs' values, and device

    register_scheme("bands", make, parameter="near_m", lo=50.0, hi=20000.0, larger_is_finer=True)

The command line reads schemes from ``--plugin FILE.py`` (or a module name): :func:`load_plugin` runs it,
and it registers what it defines. ``examples/custom_scheme.py`` is a whole scheme in under 80 lines.
A report sweep on worker processes sends each worker the specs of the user schemes it draws.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import math
import numbers
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, ModuleType
from typing import Any

from .heightmap import Heightmap
from .kernels.checks import check_int, check_number

__all__ = ["SchemeKnob", "SchemeSpec", "SCHEMES", "register_scheme", "unregister_scheme", "get_scheme", "scheme_names",
           "scheme_source", "scheme_range", "scheme_default", "check_value", "sweep_values", "load_plugin",
           "PLUGIN_FLAG"]

#: Set (True) on a module :func:`load_plugin` ran from a file: it cannot be imported by name elsewhere (a
#: worker process), so what it defines travels by value.
PLUGIN_FLAG = "__terrainwarp_plugin__"


@dataclass(frozen=True)
class SchemeKnob:
    """A scheme's knob beside its main parameter: a keyword of its ``make``, a key of ``LodConfig.params``, and
    a dimension the multi-knob fit searches (:func:`terrainwarp.fit.knobs`).

    Attributes:
        name: the keyword (a Python identifier).
        lo, hi: the range, both ends included.
        default: the value when a scene does not give one (None: the scheme's own default, chosen per heightmap).
        integer: an integer knob (values are rounded to the nearest integer, or to the nearest of ``choices``).
        log: searched in log space (a ratio or a size; ``lo`` > 0).
        choices: an integer knob's allowed values, ascending (None: every integer in the range).
        structural: the value changes what the scheme prepares independently of the other knobs (its pyramids,
            e.g. CDLOD's grid): sources made with another value do not share the prepared data.
        doc: one line for listings.
    """

    name: str
    lo: float
    hi: float
    default: float | None
    integer: bool = False
    log: bool = False
    choices: tuple[int, ...] | None = None
    structural: bool = False
    doc: str = ""

    def check(self, scheme: str, v: object) -> float | int:
        """``v`` checked against the range (an integer knob's value an integer in ``choices`` when given)."""
        where = f"{scheme}.{self.name}"
        if self.integer:
            i = check_int(where, v, int(math.ceil(self.lo)), int(math.floor(self.hi)))
            if self.choices is not None and i not in self.choices:
                raise ValueError(f"{where}: expected one of {list(self.choices)}, got {i}")
            return i
        return check_number(where, v, self.lo, self.hi)


@dataclass(frozen=True)
class SchemeSpec:
    """One registered scheme.

    Attributes:
        name: the name ``render``'s sources, the report and the fit know it by.
        make: ``make(heightmap, value, *, cache, **params) -> MeshSource``: the scheme's source with its
            parameter at ``value`` (already checked against the range, and odd for an odd-integer parameter);
            ``cache`` is a dict shared by the sources of one heightmap (keep what does not depend on
            ``value`` there: pyramids, the normal map); ``params`` the scheme's other keywords (``device``).
        parameter: the parameter's name (a keyword of the scheme, a column of the report).
        lo, hi: the range a value must lie in, both ends included (``hi`` may be ``math.inf`` when
            ``fit_range`` makes the searched range finite per heightmap).
        larger_is_finer: True when a larger value draws more detail (a range), False when it draws less (a
            threshold). Zero is a valid value only for a threshold (0 px: full detail; a zero range draws
            nothing).
        odd_integer: the parameter is an odd integer (clipmaps' n); values are rounded up to the next odd one.
        sweep: ``sweep(lo, hi) -> 4 values``, fine to coarse, that a report sweeps (``--quick``: the 2nd and
            4th); None: 4 values spaced evenly in log space over the range.
        fit_range: ``fit_range(heightmap, cache, params) -> (lo, hi)``, the finite range on one heightmap;
            None: (``lo``, ``hi``), a zero ``lo`` raised to ``hi / 4096`` (searched in log space).
        builtin: registered by terrainwarp itself (cannot be replaced or removed).
        doc: one line for listings (``terrainwarp fit --help``, the API reference).
        knobs: the scheme's further knobs (:class:`SchemeKnob`), keywords of ``make``.
        default: the main parameter's value when a scene gives none (None: the geometric mean of the searched
            range on the heightmap, :func:`scheme_range`).
    """

    name: str
    make: Callable[..., Any]
    parameter: str
    lo: float
    hi: float
    larger_is_finer: bool
    odd_integer: bool = False
    sweep: Callable[[float, float], list[float]] | None = None
    fit_range: Callable[[Heightmap, dict, dict], tuple[float, float]] | None = None
    builtin: bool = False
    doc: str = ""
    knobs: tuple[SchemeKnob, ...] = ()
    default: float | None = None

    def knob(self, name: str) -> SchemeKnob:
        """The further knob ``name``; ValueError naming the scheme's knobs otherwise."""
        for k in self.knobs:
            if k.name == name:
                return k
        raise ValueError(f"{self.name}: expected a knob of {[self.parameter, *(k.name for k in self.knobs)]}, "
                         f"got {name!r}")

    def check_params(self, params: Mapping[str, object]) -> dict[str, float | int]:
        """A scene's ``LodConfig.params`` for this scheme, each key a knob (or the main parameter) and each value
        in its range; returned checked and converted."""
        out: dict[str, float | int] = {}
        for k, v in params.items():
            if k == self.parameter:
                out[k] = check_value(self, v)
            else:
                out[k] = self.knob(k).check(self.name, v)
        return out


_REGISTRY: dict[str, SchemeSpec] = {}
#: Every registered scheme by name (read-only; changed by :func:`register_scheme` / :func:`unregister_scheme`).
SCHEMES: Mapping[str, SchemeSpec] = MappingProxyType(_REGISTRY)


def register_scheme(name: str, make: Callable[..., Any], *, parameter: str, lo: float, hi: float,
                    larger_is_finer: bool, odd_integer: bool = False,
                    sweep: Callable[[float, float], list[float]] | None = None,
                    fit_range: Callable[[Heightmap, dict, dict], tuple[float, float]] | None = None,
                    replace: bool = False, doc: str = "", builtin: bool = False,
                    knobs: tuple[SchemeKnob, ...] | list[SchemeKnob] = (), default: float | None = None) -> SchemeSpec:
    """Register a scheme under ``name`` (see :class:`SchemeSpec` for the arguments) and return its spec.

    Raises:
        ValueError: a name that is empty, not an identifier-like word, a quadtree policy's or a mesh
            family's name, already registered (unless ``replace``, for a scheme that is not built in),
            an empty or inverted range, or a knob whose name repeats or whose range or default is invalid.
        TypeError: ``make`` (or ``sweep``, ``fit_range``) not callable.
    """
    if not isinstance(name, str) or not name or not name.replace("_", "a").replace("-", "a").isalnum():
        raise ValueError(f"name: expected a word of letters, digits, '_' or '-', got {name!r}")
    if name in _RESERVED:
        raise ValueError(f"name: {name!r} is a built-in LOD policy or mesh family, not a scheme")
    old = _REGISTRY.get(name)
    if old is not None and (old.builtin or not replace):
        raise ValueError(f"name: the scheme {name!r} is already registered"
                         + ("" if old.builtin else " (replace=True replaces it)"))
    for arg, f in (("make", make), ("sweep", sweep), ("fit_range", fit_range)):
        if not callable(f) and (f is not None or arg == "make"):
            raise TypeError(f"{arg}: expected a callable, got {type(f).__name__}")
    if not isinstance(parameter, str) or not parameter.isidentifier():
        raise ValueError(f"parameter: expected a Python identifier, got {parameter!r}")
    lo, hi = float(lo), float(hi)
    if math.isnan(lo) or math.isnan(hi) or not (lo < hi) or math.isinf(lo):
        raise ValueError(f"lo, hi: expected a finite lo below hi, got {lo}, {hi}")
    knobs = tuple(knobs)
    names = [parameter, *(getattr(k, "name", None) for k in knobs)]
    if not all(isinstance(k, SchemeKnob) for k in knobs) or len(set(names)) != len(names):
        raise ValueError(f"knobs: expected SchemeKnob specs with names distinct from each other and from "
                         f"{parameter!r}, got {names[1:]}")
    for k in knobs:
        if not (k.name.isidentifier() and math.isfinite(k.lo) and math.isfinite(k.hi) and k.lo < k.hi
                and (not k.log or k.lo > 0)):
            raise ValueError(f"knobs: {k.name!r} needs an identifier name and a finite range lo < hi (lo > 0 when "
                             f"searched in log space), got {k.lo}, {k.hi}")
        if k.default is not None:
            k.check(name, k.default)
    spec = SchemeSpec(name, make, parameter, lo, hi, bool(larger_is_finer), bool(odd_integer), sweep, fit_range,
                      builtin, doc, knobs, None if default is None else float(default))
    if default is not None:
        check_value(spec, default)
    _REGISTRY[name] = spec
    return spec


def unregister_scheme(name: str) -> None:
    """Remove a scheme you registered (ValueError for a built-in one or an unknown name)."""
    spec = get_scheme(name)
    if spec.builtin:
        raise ValueError(f"name: {name!r} is a built-in scheme; it cannot be removed")
    del _REGISTRY[name]


def get_scheme(name: str) -> SchemeSpec:
    """The spec registered under ``name``; ValueError naming the registered ones otherwise."""
    if name not in _REGISTRY:
        raise ValueError(f"name: expected a registered scheme, one of {sorted(_REGISTRY)}, got {name!r}")
    return _REGISTRY[name]


def scheme_names(*, builtin: bool | None = None) -> tuple[str, ...]:
    """The registered names in registration order (``builtin``: only the built-in ones, or only yours)."""
    return tuple(n for n, s in _REGISTRY.items() if builtin is None or s.builtin == builtin)


def scheme_source(name: str, heightmap: Heightmap, value: float, *, cache: dict | None = None,
                  **params: Any) -> Any:
    """The mesh source of scheme ``name`` with its parameter at ``value`` (rounded up to the next odd integer
    for an odd-integer parameter) and the scheme's other keyword ``params`` (its knobs, checked against their
    ranges, and e.g. ``device``).

    With a ``cache`` (a dict the caller keeps for one heightmap), what a scheme prepares independently of the
    value (the built-ins' pyramids) is made once and shared by every source made with it.

    Raises:
        ValueError: an unknown name, or a value (or a knob's) that is not finite or outside its range.
        TypeError: a value that is not a number (a knob's integer that is not an integer).
    """
    spec = get_scheme(name)
    value = check_value(spec, value, "value")
    for k in spec.knobs:
        if k.name in params and params[k.name] is not None:
            params[k.name] = k.check(name, params[k.name])
    return spec.make(heightmap, value, cache={} if cache is None else cache, **params)


def check_value(spec: SchemeSpec, value: object, name: str | None = None) -> float | int:
    """The main parameter's ``value`` checked against ``spec``'s range (rounded up to the next odd integer for
    an odd-integer parameter, then an ``int``); the error names ``name`` (default: the scheme's parameter)."""
    name = f"{spec.name}.{spec.parameter}" if name is None else name
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a number, got {type(value).__name__}")
    value = float(value)
    if spec.odd_integer and math.isfinite(value):
        value = float(int(math.ceil(value)) | 1)
    zero_ok = not spec.larger_is_finer  # a zero threshold is full detail; a zero range is no range
    if not (math.isfinite(value) and spec.lo <= value <= spec.hi and (value != 0 or zero_ok)):
        raise ValueError(f"{name}: expected a finite {spec.parameter} in the range of {spec.name!r} "
                         f"({spec.lo:g}..{spec.hi:g}), got {value}")
    return int(value) if spec.odd_integer else value


def scheme_range(name: str, heightmap: Heightmap, *, cache: dict | None = None, **params: Any) -> tuple[float, float]:
    """The finite range a sweep or a fit searches for scheme ``name``'s parameter on ``heightmap``: the spec's
    ``fit_range`` (CDLOD's: from its seam-free minimum first range to twice the terrain box's diagonal), else
    (``lo``, ``hi``) with a zero ``lo`` raised to ``hi / 4096``, so the range can be searched in log space."""
    spec = get_scheme(name)
    if spec.fit_range is not None:
        lo, hi = spec.fit_range(heightmap, {} if cache is None else cache, params)
        return float(lo), float(hi)
    return (spec.lo if spec.lo > 0 else spec.hi / 4096.0), spec.hi


def scheme_default(name: str, heightmap: Heightmap, *, cache: dict | None = None, **params: Any) -> float | int:
    """The main parameter's value a scene that gives none draws: the spec's ``default``, else the geometric mean
    of :func:`scheme_range` on ``heightmap`` with the scheme's other ``params`` (snapped to an odd integer for an
    odd-integer parameter)."""
    spec = get_scheme(name)
    if spec.default is not None:
        return check_value(spec, spec.default)
    lo, hi = scheme_range(name, heightmap, cache=cache, **params)
    return check_value(spec, math.sqrt(lo * hi))


def sweep_values(name: str, heightmap: Heightmap, quick: bool = False) -> list[float]:
    """The values of scheme ``name`` a report sweeps on ``heightmap``, fine to coarse, inside its range,
    rounded to 2 decimals, without repeats (``quick``: two of them)."""
    spec = get_scheme(name)
    lo, hi = scheme_range(name, heightmap)
    if spec.sweep is not None:
        vals = [float(v) for v in spec.sweep(lo, hi)]
    else:
        r = hi / lo
        vals = [lo * r ** (t / 3.0) for t in range(4)]
        vals = vals[::-1] if spec.larger_is_finer else vals
    vals = vals[1::2] if quick else vals
    return [round(v, 2) for v in dict.fromkeys(min(max(v, lo), hi) for v in vals)]


def load_plugin(plugin: str | Path) -> ModuleType:
    """Run a plugin: a ``.py`` file (run as a module once per resolved path; later calls return it) or an
    importable module name; what it registers at import becomes a scheme name. Returns the module.

    Raises:
        ValueError: a file that does not exist or is not ``.py``, or a module that cannot be imported (with the
            plugin's own error).
    """
    text = str(plugin)
    if text.endswith(".py") or "/" in text or isinstance(plugin, Path):
        path = Path(text).resolve()
        if not path.is_file() or path.suffix != ".py":
            raise ValueError(f"plugin: expected a .py file or a module name, got {text!r}")
        name = f"terrainwarp_plugin_{hashlib.sha1(str(path).encode()).hexdigest()[:12]}_{path.stem}"
        if name in sys.modules:
            return sys.modules[name]
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        setattr(module, PLUGIN_FLAG, True)
        sys.modules[name] = module  # dataclasses and pickling look a class's module up by name
        try:
            spec.loader.exec_module(module)
        except Exception as e:
            del sys.modules[name]
            raise ValueError(f"plugin: {path} failed: {type(e).__name__}: {e}") from e
        return module
    try:
        return importlib.import_module(text)
    except ImportError as e:
        raise ValueError(f"plugin: cannot import {text!r}: {e}") from e


# The names a scheme cannot take: the quadtree policies, the full grid and the other mesh families.
_RESERVED = frozenset({"grid", "sse", "distance", "continuous", "martini", "delatin", "polytree", "bintree", "lod"})
