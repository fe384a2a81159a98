"""What a frame costs a real GPU, without the GPU: a bottleneck model of the frame's pipeline statistics
(``Report.counters``) with named rates, each one a vendor's published figure (:class:`GpuProfile`).

**The model.** A frame's time is a fixed overhead plus the time of its slowest stage; each stage's time is the
work its counters count divided by the stage's rate (:data:`STAGES`):

* ``tessellator``: ``tess_control_shader_patches`` / ``patches_per_clock`` +
  ``tess_evaluation_shader_invocations`` / ``domain_points_per_clock``;
* ``vertex``: (``vertex_shader_invocations`` + ``tess_evaluation_shader_invocations``) / ``vertices_per_clock``;
* ``setup``: ``clipping_input_primitives`` / ``triangles_per_clock`` (triangles per clock x engines);
* ``shade``: ``fragment_shader_invocations`` (4 lanes per 2x2 quad) / ``pixels_per_clock``;
* ``rop``: ``samples_passed`` / ``samples_per_clock``;
* ``memory``: (``bytes_vertex`` + ``bytes_index`` + ``bytes_heightmap``) / ``bytes_per_second``.

The ``shade`` stage carries the small-triangle penalty: ``fragment_shader_invocations`` counts 4 lanes for every
2x2 quad a triangle touches, helper lanes included, so its time is the covered samples over the quad efficiency
(``Report.counters['quad_efficiency']``) over the rasterizers' pixel rate; a 1-pixel triangle costs a whole quad,
and at least one setup clock. A stage a profile does not give a rate for is not modelled: it costs nothing, and
the profile's ``unmodelled`` table says why (most often: no vendor publishes that rate). Bytes are counted before
any cache (``terrainwarp.kernels.counters``), and framebuffer traffic is not counted, in any profile.

**Profiles** are TOML files of rates, each rate with its source (``gpu_profiles/*.toml`` beside this module ship
with the package; docs/gpu_profiles.rst tables them)::

    name = "gf100"
    gpu = "NVIDIA GeForce GTX 480 (GF100, Fermi), 2010"
    architecture = "immediate"          # or "tile-based"
    clock_mhz = 700.0                   # the clock of the *_per_clock rates (a stage may set its own)
    overhead_ms = 0.0                   # the fixed per-frame time
    tessellation = true                 # false: the GPU has no tessellator (a patch draw is refused)

    [rates.setup]
    triangles_per_clock = 4.0
    source = "NVIDIA GF100 whitepaper (2010): four Raster Engines, up to four triangles set up per clock"

    [unmodelled]
    tessellator = "no per-clock tessellator rate is published for GF100"

Select one with ``cost="gpu:gf100"`` (shipped) or ``cost="gpu:path/to/mine.toml"`` (:func:`terrainwarp.measure.
cost.cost`). Every cost here is deterministic: the same counters give the same bytes on every run and machine.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

from ..kernels.checks import check_number
from ..kernels.counters import INDEX_BYTES, PATCH_RECORD_BYTES

__all__ = ["GpuProfile", "STAGES", "ARCHITECTURES", "shipped_profiles", "shipped_profile", "SHIPPED_DIR"]

#: stage -> ((counter, rate key), ...): the work of a stage is the sum over its counters of counter / rate
STAGES: dict[str, tuple[tuple[str, str], ...]] = {
    "tessellator": (("tess_control_shader_patches", "patches_per_clock"),
                    ("tess_evaluation_shader_invocations", "domain_points_per_clock")),
    "vertex": (("vertex_shader_invocations", "vertices_per_clock"),
               ("tess_evaluation_shader_invocations", "vertices_per_clock")),
    "setup": (("clipping_input_primitives", "triangles_per_clock"),),
    "shade": (("fragment_shader_invocations", "pixels_per_clock"),),
    "rop": (("samples_passed", "samples_per_clock"),),
    "memory": (("bytes_vertex", "bytes_per_second"), ("bytes_index", "bytes_per_second"),
               ("bytes_heightmap", "bytes_per_second")),
}
ARCHITECTURES = ("immediate", "tile-based")
SHIPPED_DIR = "gpu_profiles"
#: the memory stage's bytes per unit of the counters the fit's relaxed models count (the surrogate of
#: :attr:`GpuProfile.weights`): 3 indices a triangle, a 12-byte vertex (indexed_draw_counters' default), a patch
#: record, a domain point's 4 bilinear 4-byte texels
SURROGATE_BYTES = {"primitives_generated": 3 * INDEX_BYTES, "vertex_shader_invocations": 12,
                   "tess_control_shader_patches": PATCH_RECORD_BYTES, "tess_evaluation_shader_invocations": 16}
_TOP_KEYS = {"name", "gpu", "architecture", "clock_mhz", "overhead_ms", "tessellation", "rates", "unmodelled",
             "notes"}


def _rate_keys(stage: str) -> tuple[str, ...]:
    return tuple(dict.fromkeys(k for _, k in STAGES[stage]))


@dataclass(frozen=True)
class GpuProfile:
    """A GPU's published rates, as a bottleneck model of a frame's pipeline statistics (see the module docstring).

    Attributes:
        name: the profile's short name (``"gf100"``); gpu: the GPU it describes; architecture: ``"immediate"``
            or ``"tile-based"``.
        clock_mhz: the clock of the per-clock rates; overhead_ms: the fixed per-frame time (ms).
        rates: stage -> {rate key: value}: units per clock (``*_per_clock``) or per second (``*_per_second``).
        clocks_mhz: stage -> its own clock where it is not ``clock_mhz``.
        sources: stage -> where its rates come from (every modelled stage cites one).
        unmodelled: stage -> why the profile gives it no rate.
        tessellation: False for a GPU without a tessellator (a frame with patches is refused).
        origin: the file it was read from (``"gpu_profiles/gf100.toml"``).
    """

    name: str
    gpu: str
    architecture: str
    clock_mhz: float
    rates: Mapping[str, Mapping[str, float]]
    sources: Mapping[str, str]
    overhead_ms: float = 0.0
    clocks_mhz: Mapping[str, float] = field(default_factory=dict)
    unmodelled: Mapping[str, str] = field(default_factory=dict)
    tessellation: bool = True
    notes: str = ""
    origin: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"{self.origin or 'profile'}: name: expected a non-empty profile name, got {self.name!r}")
        where = f"{self.origin}: profile {self.name!r}" if self.origin else f"profile {self.name!r}"
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"{where}: architecture: expected one of {list(ARCHITECTURES)}, got "
                             f"{self.architecture!r}")
        check_number(f"{where}: clock_mhz", self.clock_mhz, 0.0, lo_open=True)
        check_number(f"{where}: overhead_ms", self.overhead_ms, 0.0)
        if not self.rates:
            raise ValueError(f"{where}: rates: expected at least one stage of {list(STAGES)}")
        for stage, table in self.rates.items():
            _check_stage(where, stage, table, self.sources.get(stage))
        for stage, mhz in self.clocks_mhz.items():
            if stage not in self.rates:
                raise ValueError(f"{where}: rates.{stage}.clock_mhz: the stage has no rates")
            check_number(f"{where}: rates.{stage}.clock_mhz", mhz, 0.0, lo_open=True)
        for stage in self.unmodelled:
            if stage not in STAGES or stage in self.rates:
                raise ValueError(f"{where}: unmodelled.{stage}: expected a stage of {list(STAGES)} without rates")

    # -- the model ---------------------------------------------------------------------------------------
    def per_second(self, stage: str) -> dict[str, float]:
        """Stage ``stage``'s rates in units per second."""
        mhz = float(self.clocks_mhz.get(stage, self.clock_mhz))
        return {k: float(v) * (mhz * 1e6 if k.endswith("_per_clock") else 1.0)
                for k, v in self.rates[stage].items()}

    def stage_ms(self, counters: Mapping[str, Any]) -> dict[str, float]:
        """Each modelled stage's time (ms) for a frame's counters, in :data:`STAGES` order."""
        missing = sorted({c for s in self.rates for c, _ in STAGES[s] if c not in counters})
        if missing:
            raise ValueError(f"counters: expected the counters {missing} of GPU profile {self.name!r} "
                             "(render with outputs including 'counters')")
        if not self.tessellation and float(counters.get("tess_control_shader_patches", 0) or 0) > 0:
            raise ValueError(f"counters: GPU profile {self.name!r} ({self.gpu}) has no tessellator, and the frame "
                             "draws patches")
        out = {}
        for stage in STAGES:
            if stage in self.rates:
                rate = self.per_second(stage)
                out[stage] = 1e3 * math.fsum(float(counters[c]) / rate[k] for c, k in STAGES[stage])
        return out

    def __call__(self, counters: Mapping[str, Any]) -> float:
        """The modelled frame time (ms): the overhead plus the slowest stage's time."""
        return float(self.overhead_ms + max(self.stage_ms(counters).values()))

    def bound(self, counters: Mapping[str, Any]) -> str:
        """The stage the frame is bound by (the first of the slowest, in :data:`STAGES` order)."""
        t = self.stage_ms(counters)
        return max(t, key=lambda s: t[s])

    def scaled(self, factors: Mapping[str, float]) -> GpuProfile:
        """This profile with each named stage's rates multiplied by ``factors[stage]`` (a faster stage: > 1)."""
        bad = sorted(set(factors) - set(self.rates))
        if bad:
            raise ValueError(f"factors: expected stages of profile {self.name!r} ({list(self.rates)}), got {bad}")
        rates = {s: {k: v * float(factors.get(s, 1.0)) for k, v in t.items()} for s, t in self.rates.items()}
        return replace(self, rates=rates)

    @property
    def weights(self) -> dict[str, float]:
        """ms per unit of each counter summed over the stages (the sum of the stage times: an upper bound of the
        slowest stage's time, linear in the counters), the memory stage's bytes also spread over the counters that
        fetch them (:data:`SURROGATE_BYTES`): the relaxed fit's surrogate of this profile. The fit's exact tries
        price every frame with the profile itself."""
        out: dict[str, float] = {}
        for stage in self.rates:
            rate = self.per_second(stage)
            for c, k in STAGES[stage]:
                out[c] = out.get(c, 0.0) + 1e3 / rate[k]
        if "memory" in self.rates:
            per_byte = 1e3 / self.per_second("memory")["bytes_per_second"]
            for c, b in SURROGATE_BYTES.items():
                out[c] = out.get(c, 0.0) + b * per_byte
        return out

    def describe(self) -> str:
        """One line: what it models and its rates."""
        terms = "; ".join(f"{s} " + ", ".join(f"{_fmt(v)} {k}" for k, v in t.items()) for s, t in self.rates.items())
        off = f", unmodelled: {', '.join(self.unmodelled)}" if self.unmodelled else ""
        return (f"GPU profile {self.name} ({self.gpu}; {self.architecture}, {_fmt(self.clock_mhz)} MHz): ms = "
                f"{_fmt(self.overhead_ms)} + max over stages ({terms}){off}")

    # -- files ---------------------------------------------------------------------------------------------
    @classmethod
    def from_toml(cls, text: str, where: str = "profile") -> GpuProfile:
        """A profile from the TOML text of a profile file (see the module docstring)."""
        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"{where}: not a GPU profile's TOML: {e}") from None
        unknown = sorted(set(d) - _TOP_KEYS)
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(_TOP_KEYS)}")
        for key in ("name", "gpu", "architecture", "clock_mhz", "rates"):
            if key not in d:
                raise ValueError(f"{where}: expected the key {key!r}")
        rates, sources, clocks = {}, {}, {}
        if not isinstance(d["rates"], dict):
            raise ValueError(f"{where}: rates: expected tables [rates.<stage>]")
        for stage, table in d["rates"].items():
            if not isinstance(table, dict):
                raise ValueError(f"{where}: rates.{stage}: expected a table of rates and a source")
            table = dict(table)
            sources[stage] = table.pop("source", "")
            if "clock_mhz" in table:
                clocks[stage] = table.pop("clock_mhz")
            rates[stage] = table
        unmodelled = d.get("unmodelled", {})
        if not isinstance(unmodelled, dict) or not all(isinstance(v, str) for v in unmodelled.values()):
            raise ValueError(f"{where}: unmodelled: expected a table of stage = \"why\"")
        tess = d.get("tessellation", True)
        if not isinstance(tess, bool):
            raise TypeError(f"{where}: tessellation: expected true or false, got {tess!r}")
        return cls(name=d["name"], gpu=str(d["gpu"]), architecture=d["architecture"], clock_mhz=d["clock_mhz"],
                   rates=rates, sources=sources, overhead_ms=d.get("overhead_ms", 0.0), clocks_mhz=clocks,
                   unmodelled=unmodelled, tessellation=tess, notes=str(d.get("notes", "")), origin=where)

    @classmethod
    def load(cls, path: str | Path) -> GpuProfile:
        """A profile from a TOML file (FileNotFoundError naming it when there is none)."""
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"cost: no such GPU profile file: {p}")
        return cls.from_toml(p.read_text(), str(p))


def _check_stage(where: str, stage: str, table: Mapping[str, Any], source: str | None) -> None:
    """A stage's rates: a known stage, exactly its rate keys, each a positive finite number, and a source."""
    if stage not in STAGES:
        raise ValueError(f"{where}: rates.{stage}: expected a stage among {list(STAGES)}")
    if not isinstance(source, str) or not source.strip():
        raise ValueError(f"{where}: rates.{stage}.source: every rate cites where it comes from (a published "
                         "figure or a measurement); got none")
    want = set(_rate_keys(stage))
    if not isinstance(table, Mapping) or set(table) != want:
        got = sorted(table) if isinstance(table, Mapping) else table
        raise ValueError(f"{where}: rates.{stage}: expected the rate(s) {sorted(want)}, got {got}")
    for k, v in table.items():
        check_number(f"{where}: rates.{stage}.{k}", v, 0.0, lo_open=True)


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def shipped_profiles() -> dict[str, GpuProfile]:
    """The profiles that ship with the package, by name (sorted)."""
    root = resources.files(__package__).joinpath(SHIPPED_DIR)
    out = {}
    for entry in sorted(root.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            p = GpuProfile.from_toml(entry.read_text(), f"{SHIPPED_DIR}/{entry.name}")
            out[p.name] = p
    return out


def shipped_profile(name: str) -> GpuProfile:
    """The shipped profile ``name`` (ValueError listing the names when there is none)."""
    profiles = shipped_profiles()
    if name not in profiles:
        raise ValueError(f"cost: expected a shipped GPU profile among {sorted(profiles)} (gpu:<name>) or a profile "
                         f"file (gpu:<path>.toml), got gpu:{name}")
    return profiles[name]
