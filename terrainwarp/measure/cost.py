"""What a frame costs a GPU: a cost of its pipeline statistics (``Report.counters``), deterministic (the same
counters give the same cost on every machine), that reports rank by and fits minimise.

A cost is one of (:func:`cost`):

* ``"triangles"``: the frame's triangles (the mesh drawn);
* a counter name (:data:`terrainwarp.kernels.counters.PIPELINE_COUNTERS`): that counter;
* a :class:`CostModel`, ``cost = intercept + sum_i w_i * counter_i`` in milliseconds of a real driver, the weights
  fitted by least squares (non-negative) to that driver's measured frame times
  (:mod:`terrainwarp.experiments.calibrate`); ``"llvmpipe"`` (or ``"model"``) is the model that ships with the
  package (``llvmpipe.json`` beside this module, fitted to Mesa's llvmpipe on the machine named in it), and a
  path to a weights file written by ``terrainwarp calibrate --gl`` is a user's;
* a GPU profile (:class:`terrainwarp.measure.gpu.GpuProfile`): ms of a bottleneck model with a GPU's published
  rates, ``"gpu:gf100"`` (a shipped profile: :func:`terrainwarp.measure.gpu.shipped_profiles`) or
  ``"gpu:path/to/mine.toml"`` (a user's);
* a list of any of these (:class:`WorstOf`): each frame's worst modelled ms over them, for a setting that has to
  hold on every GPU it ships to.

A weights file is JSON: ``{"name", "driver", "features", "weights" (ms per unit of each feature),
"intercept_ms", "r2_heldout", "frames", "families", "command", "sha256"}``; ``sha256`` is the hash of the rest
(sorted keys), checked on load, so a damaged or hand-edited file is refused by name. The JSON is strict
(:func:`terrainwarp.io.files.strict_json`): an ``r2_heldout`` that is undefined (NaN: the held-out frames' times
do not vary) is ``null`` with an ``r2_heldout_reason``, and loads back as NaN.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from ..io.files import dumps_strict, strict_json
from ..kernels.checks import check_number
from ..kernels.counters import PIPELINE_COUNTERS
from .gpu import GpuProfile, shipped_profile

__all__ = ["CostModel", "Cost", "WorstOf", "cost", "cost_model", "shipped_model", "MODEL_FEATURES", "COST_NAMES",
           "GPU_PREFIX"]

#: The counters a cost model may weigh (a calibration fits these and keeps the ones it needs).
MODEL_FEATURES = ("draw_calls", "tess_control_shader_patches", "tess_evaluation_shader_invocations",
                  "vertex_shader_invocations_llvmpipe", "primitives_generated", "clipping_output_primitives",
                  "fragment_shader_invocations_llvmpipe", "samples_passed", "bytes_heightmap")
#: The names :func:`cost` takes besides a path or a model.
COST_NAMES = ("triangles", "llvmpipe", "model", *PIPELINE_COUNTERS)
#: the prefix of a GPU profile's name (``gpu:gf100``) or file (``gpu:mine.toml``)
GPU_PREFIX = "gpu:"
_SHIPPED = "llvmpipe.json"


@dataclass(frozen=True)
class CostModel:
    """A linear model of a driver's frame time (ms) in the frame's pipeline statistics.

    Attributes:
        name: what it models (``"llvmpipe"``); driver: the renderer it was fitted to (GL_RENDERER / GL_VERSION and
            the threads it ran on).
        weights: ms per unit of each counter (non-negative); intercept_ms: the per-frame constant.
        r2_heldout: R^2 of the model on the calibration frames left out of the fit; frames: frames measured (fit
            and held out); families: frames per mesh family; command: the command that made it.
    """

    name: str
    weights: dict[str, float]
    intercept_ms: float = 0.0
    driver: str = ""
    r2_heldout: float = math.nan
    frames: int = 0
    families: dict[str, int] = field(default_factory=dict)
    command: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.weights, Mapping) or not self.weights:
            raise ValueError(f"weights: expected a non-empty mapping of counter names to ms, got {self.weights!r}")
        bad = [k for k in self.weights if k not in PIPELINE_COUNTERS]
        if bad:
            raise ValueError(f"weights: expected counter names among {list(PIPELINE_COUNTERS)}, got {bad}")
        for k, v in (*self.weights.items(), ("intercept_ms", self.intercept_ms)):
            check_number(f"weights[{k!r}]", v, 0.0)

    def __call__(self, counters: Mapping[str, Any]) -> float:
        """The modelled frame time (ms) of a frame's counters (a ``Report.counters`` or a report row)."""
        missing = [k for k in self.weights if k not in counters]
        if missing:
            raise ValueError(f"counters: expected the counters {missing} of cost model {self.name!r} "
                             "(render with outputs including 'counters')")
        return float(self.intercept_ms + math.fsum(w * float(counters[k]) for k, w in self.weights.items()))

    def to_json(self) -> str:
        """The weights file's text: strict JSON (a NaN ``r2_heldout`` is ``null`` and ``r2_heldout_reason``), its
        ``sha256`` the hash of the rest as written."""
        d = strict_json(asdict(self))
        d["features"] = list(self.weights)
        d["sha256"] = _digest(d)
        return dumps_strict(d, indent=2, sort_keys=True) + "\n"

    @classmethod
    def from_json(cls, text: str, where: str = "weights") -> CostModel:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{where}: not a cost model's JSON: {e}") from None
        if not isinstance(d, dict) or "weights" not in d or "sha256" not in d:
            raise ValueError(f"{where}: expected a weights file of terrainwarp calibrate (keys 'weights', 'sha256')")
        want = d.pop("sha256")
        if _digest(d) != want:
            raise ValueError(f"{where}: checksum mismatch: the file was changed after terrainwarp calibrate wrote it")
        d.pop("features", None)
        for k in ("r2_heldout",):  # strict JSON's null (a reason beside it) is the NaN it stands for
            if d.get(k, 0.0) is None:
                d[k] = math.nan
                d.pop(f"{k}_reason", None)
        unknown = sorted(set(d) - {f.name for f in cls.__dataclass_fields__.values()})
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown}")
        return cls(**d)

    @classmethod
    def load(cls, path: str | Path) -> CostModel:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"cost: no such weights file: {p}")
        return cls.from_json(p.read_text(), str(p))

    def describe(self) -> str:
        """One line: what it is and how well it fits."""
        terms = " + ".join(f"{w:.3g} x {k}" for k, w in self.weights.items() if w > 0)
        return (f"{self.name} cost model ({self.driver}): ms = {self.intercept_ms:.3g} + {terms}; R^2 on held-out "
                f"frames {self.r2_heldout:.3f} ({self.frames} frames)")


def _digest(d: dict) -> str:
    return hashlib.sha256(json.dumps({k: v for k, v in d.items() if k != "sha256"}, sort_keys=True).encode()
                          ).hexdigest()


def shipped_model() -> CostModel:
    """The llvmpipe model that ships with the package."""
    return CostModel.from_json(resources.files(__package__).joinpath(_SHIPPED).read_text(), _SHIPPED)


@dataclass(frozen=True)
class WorstOf:
    """The worst of several cost models: a frame's cost is the largest of its modelled ms under ``models`` (cost
    models, GPU profiles), so a setting fitted for it holds on each of them.

    ``weights`` (the fit's linear surrogate) is the largest weight of each counter over the models."""

    models: tuple

    def __post_init__(self) -> None:
        if len(self.models) < 1:
            raise ValueError("cost: expected at least one cost model in the list")

    @property
    def name(self) -> str:
        return "worst of " + ", ".join(m.name for m in self.models)

    def __call__(self, counters: Mapping[str, Any]) -> float:
        """The largest modelled ms of the frame over the models."""
        return max(float(m(counters)) for m in self.models)

    @property
    def weights(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for m in self.models:
            for k, w in m.weights.items():
                out[k] = max(out.get(k, 0.0), float(w))
        return out

    def describe(self) -> str:
        return f"the worst modelled ms per frame over: {'; '.join(m.describe() for m in self.models)}"


@dataclass(frozen=True)
class Cost:
    """A cost reports and fits rank by: ``name`` (a column name: ``"triangles"``, a counter, ``"cost_ms"`` for a
    model) and ``of(row)``, the cost of a report row or a frame's counters (with ``triangles``). ``model``: the
    :class:`CostModel`, :class:`terrainwarp.measure.gpu.GpuProfile` or :class:`WorstOf` that prices a frame."""

    name: str
    label: str
    model: CostModel | GpuProfile | WorstOf | None = None

    @property
    def needs_counters(self) -> bool:
        return self.name != "triangles"

    def of(self, row: Mapping[str, Any]) -> float:
        if self.model is not None:
            return self.model(row)
        if self.name not in row:
            raise ValueError(f"cost: the row has no {self.name!r} (render with outputs including 'counters')")
        return float(row[self.name])


def cost_model(spec: object) -> CostModel | GpuProfile:
    """The one model ``spec`` names: ``"llvmpipe"``/``"model"``, ``"gpu:<name>"``, ``"gpu:<file>.toml"``, a
    weights file (``*.json``), a :class:`CostModel` or a :class:`terrainwarp.measure.gpu.GpuProfile`."""
    if isinstance(spec, CostModel | GpuProfile):
        return spec
    if spec in ("llvmpipe", "model"):
        return shipped_model()
    if isinstance(spec, Path) and spec.suffix == ".toml":
        return GpuProfile.load(spec)
    if isinstance(spec, Path) or (isinstance(spec, str) and spec.endswith(".json")):
        return CostModel.load(spec)
    if isinstance(spec, str) and spec.startswith(GPU_PREFIX):
        rest = spec[len(GPU_PREFIX):]
        return GpuProfile.load(rest) if rest.endswith(".toml") else shipped_profile(rest)
    raise ValueError(f"cost: expected a cost model ('llvmpipe', 'gpu:<name>', 'gpu:<file>.toml', a weights file "
                     f"(.json), a CostModel or a GpuProfile), got {spec!r}")


def cost(spec: str | Path | CostModel | GpuProfile | Cost | list | tuple | None = None) -> Cost:
    """The cost named by ``spec``: None or ``"llvmpipe"`` / ``"model"`` (the shipped model), ``"triangles"``, a
    counter name, a :class:`CostModel`, the path of a weights file (``*.json``), a GPU profile
    (``"gpu:gf100"``, ``"gpu:mine.toml"`` or a :class:`terrainwarp.measure.gpu.GpuProfile`), or a list of models
    (:class:`WorstOf`: each frame's worst modelled ms over them)."""
    if isinstance(spec, Cost):
        return spec
    if spec is None:
        spec = "llvmpipe"
    if isinstance(spec, list | tuple):
        models = tuple(cost_model(s) for s in spec)
        w = WorstOf(models)
        return Cost("cost_ms", f"worst modelled ms over {', '.join(m.name for m in models)}", w)
    if isinstance(spec, str) and (spec == "triangles" or spec in PIPELINE_COUNTERS):
        return Cost(spec, spec)
    if isinstance(spec, str) and not (spec in ("llvmpipe", "model") or spec.endswith(".json")
                                      or spec.startswith(GPU_PREFIX)):
        raise ValueError(f"cost: expected 'triangles', a counter name ({', '.join(PIPELINE_COUNTERS)}), 'llvmpipe', "
                         f"'gpu:<profile>' or 'gpu:<file>.toml', a weights file (.json) or a list of models, got "
                         f"{spec!r}")
    if not isinstance(spec, str | Path | CostModel | GpuProfile):
        raise TypeError(f"cost: expected a name, a CostModel, a GpuProfile, a list of them or a weights file's path, "
                        f"got {type(spec).__name__}")
    m = cost_model(spec)
    return Cost("cost_ms", f"modelled {m.name} ms", m)
