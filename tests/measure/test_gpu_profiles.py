"""GPU profiles (terrainwarp.measure.gpu): every shipped profile's units and monotonicity, its sources, the
profile file's checks, selection through cost(), the worst-of cost, and the modelled costs of real frames,
byte-identical across runs and thread counts."""

from __future__ import annotations

import hashlib
import math
import struct
import tomllib
from importlib import resources

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, LodConfig, Scene, render
from terrainwarp.kernels.counters import PIPELINE_COUNTERS
from terrainwarp.kernels.parallel import set_threads
from terrainwarp.measure.cost import WorstOf, cost, shipped_model
from terrainwarp.measure.gpu import STAGES, GpuProfile, shipped_profile, shipped_profiles
from terrainwarp.schemes import scheme_source

NAMES = sorted(shipped_profiles())
ZERO = dict.fromkeys(PIPELINE_COUNTERS, 0)


def _toml(name: str) -> dict:
    """The shipped file's own numbers, read apart from the class under test."""
    return tomllib.loads(resources.files("terrainwarp.measure").joinpath(f"gpu_profiles/{name}.toml").read_text())


def test_the_shipped_profiles_are_the_four_classes_and_the_clipmap_gpu():
    assert NAMES == ["gcn", "gf100", "mali", "nv40", "rdna"]
    kinds = {n: shipped_profile(n).architecture for n in NAMES}
    assert kinds["mali"] == "tile-based" and all(k == "immediate" for n, k in kinds.items() if n != "mali")


@pytest.mark.parametrize("name", NAMES)
def test_units_each_stage_is_its_counters_over_its_published_rate(name):
    raw, p = _toml(name), shipped_profile(name)
    assert set(p.rates) | set(p.unmodelled) == set(STAGES)  # every stage either has a rate or says why not
    for stage in p.rates:
        table = raw["rates"][stage]
        assert len(table["source"]) > 40, stage  # a citation, not a placeholder
        mhz = table.get("clock_mhz", raw["clock_mhz"])
        for counter, key in STAGES[stage]:
            if counter.startswith("tess_") and not p.tessellation:
                continue  # refused (no tessellator): test_a_gpu_without_a_tessellator_refuses_patches
            per_s = table[key] * (mhz * 1e6 if key.endswith("_per_clock") else 1.0)
            n = 1_234_567
            want = 1e3 * n / per_s
            assert p.stage_ms({**ZERO, counter: n})[stage] == pytest.approx(want, rel=1e-12), (stage, counter)
            if sum(counter in dict(STAGES[s]) for s in p.rates) == 1:  # the counter feeds this stage alone
                assert p({**ZERO, counter: n}) == pytest.approx(raw.get("overhead_ms", 0.0) + want, rel=1e-12)
    # a stage's time is in ms: one second of the slowest stage's work costs 1000 ms
    stage = next(iter(p.rates))
    counter, key = STAGES[stage][0]
    assert p({**ZERO, counter: p.per_second(stage)[key]}) == pytest.approx(1000.0)


@pytest.mark.parametrize("name", NAMES)
def test_monotone_more_of_any_counter_never_costs_less(name):
    p = shipped_profile(name)
    rng = np.random.default_rng(7)
    for _ in range(60):
        c = {k: float(rng.integers(0, 10_000_000)) for k in PIPELINE_COUNTERS}
        if not p.tessellation:
            c["tess_control_shader_patches"] = c["tess_evaluation_shader_invocations"] = 0.0
        base = p(c)
        assert base >= p.overhead_ms
        for k in PIPELINE_COUNTERS:
            if k.startswith("tess_") and not p.tessellation:
                continue
            for more in (1.0, 1e3, 1e7):
                assert p({**c, k: c[k] + more}) >= base, (k, more)
        assert p.bound(c) in p.rates


def test_the_bound_stage_and_the_small_triangle_penalty():
    p = shipped_profile("gf100")
    # one quad per 1-pixel triangle (4 lanes, 1 covered): setup-bound; the same pixels in big triangles: shade
    tiny = {**ZERO, "clipping_input_primitives": 2_000_000, "fragment_shader_invocations": 8_000_000,
            "samples_passed": 2_000_000}
    big = {**tiny, "clipping_input_primitives": 20_000, "fragment_shader_invocations": 2_200_000}
    assert p.bound(tiny) == "setup" and p.bound(big) == "shade"
    assert p(tiny) / p(big) == pytest.approx((2e6 / 4) / (2.2e6 / 32))  # 7.3x: 4 tris/clk against 32 lanes/clk


def test_a_gpu_without_a_tessellator_refuses_patches():
    with pytest.raises(ValueError, match="no tessellator"):
        shipped_profile("nv40")({**ZERO, "tess_control_shader_patches": 1})


def test_profile_files_are_checked_and_a_users_profile_is_selected_by_path(tmp_path):
    good = (resources.files("terrainwarp.measure").joinpath("gpu_profiles/gf100.toml").read_text())
    mine = tmp_path / "mine.toml"
    mine.write_text(good.replace('name = "gf100"', 'name = "mine"').replace("triangles_per_clock = 4.0",
                                                                           "triangles_per_clock = 2.0"))
    c = cost(f"gpu:{mine}")
    assert c.name == "cost_ms" and c.model.name == "mine" and c.label == "modelled mine ms"
    assert c.of({**ZERO, "clipping_input_primitives": 7e8}) == pytest.approx(500.0)  # 7e8 / (2 x 700 MHz)
    assert cost("gpu:gf100").model == shipped_profile("gf100") and "GTX 480" in cost("gpu:gf100").model.describe()
    bad = {"source": good.replace('source = "NVIDIA GF100 whitepaper', 'sauce = "NVIDIA GF100 whitepaper'),
           "pixels_per_clock": good.replace("pixels_per_clock = 32.0", "pixels_per_clock = -32.0"),
           "rates.warp": good.replace("[rates.rop]", '[rates.warp]\nwarps_per_clock = 1.0\nsource = "cited"\n'
                                      "[rates.rop]"),
           "unknown key": "colour = 3\n" + good, "architecture": good.replace('"immediate"', '"deferred"'),
           "not a GPU profile's TOML": "name = ",
           "unmodelled.setup": good.replace('tessellator = "NVIDIA publishes', 'setup = "x"\ntessellator = "NVIDIA '
                                            'publishes')}
    for i, (what, text) in enumerate(bad.items()):
        f = tmp_path / f"bad{i}.toml"
        f.write_text(text)
        with pytest.raises((ValueError, TypeError)) as e:
            cost(f"gpu:{f}")
        assert str(f) in str(e.value) and what in str(e.value), (what, str(e.value))
    with pytest.raises(FileNotFoundError, match="no such GPU profile"):
        cost(f"gpu:{tmp_path / 'missing.toml'}")
    with pytest.raises(ValueError, match="among .*gcn.*gf100"):
        cost("gpu:gf200")


def test_worst_of_prices_each_frame_at_its_worst_model():
    models = [shipped_profile("gf100"), shipped_profile("mali"), shipped_model()]
    c = cost(["gpu:gf100", "gpu:mali", "llvmpipe"])
    assert isinstance(c.model, WorstOf) and c.label == "worst modelled ms over gf100, mali, llvmpipe"
    rng = np.random.default_rng(3)
    for _ in range(20):
        row = {k: float(rng.integers(0, 5_000_000)) for k in PIPELINE_COUNTERS}
        assert c.of(row) == max(m(row) for m in models)
    w = c.model.weights
    assert all(w[k] >= m.weights.get(k, 0.0) for m in models for k in w)
    with pytest.raises(ValueError, match="at least one"):
        cost([])


def _frames(hm, cams):
    cache: dict = {}
    sources = [(dict(mesh="lod", lod=LodConfig(roots=4, tess=8)), None), ({}, scheme_source("cdlod", hm, 800.0,
                                                                                            cache=cache))]
    out = []
    for kw, src in sources:
        for c in cams:
            out.append(render(Scene(hm, camera=c, outputs=("counters",), **kw), source=src).report.counters)
    return out


def test_modelled_costs_are_byte_identical_across_runs_and_thread_counts():
    hm = Heightmap.fbm(97, seed=5, dx=20.0, max_height=500.0)
    cams = Scene(hm, camera=Camera.default_for(hm, 160, 96)).camera_path(2)
    models = [shipped_model(), *(p for p in shipped_profiles().values() if p.tessellation)]
    digests = []
    for threads in (1, 2, 1):
        try:
            set_threads(threads)
            costs = [m(c) for c in _frames(hm, cams) for m in models]
        finally:
            set_threads(None)
        assert all(math.isfinite(x) and x > 0 for x in costs)
        digests.append(hashlib.sha256(struct.pack(f"{len(costs)}d", *costs)).hexdigest())
    assert digests[0] == digests[1] == digests[2]


def test_a_profile_is_a_frozen_value_and_scales_by_stage():
    p = shipped_profile("rdna")
    faster = p.scaled({"setup": 2.0})
    assert faster.rates["setup"]["triangles_per_clock"] == 8.0 and p.rates["setup"]["triangles_per_clock"] == 4.0
    row = {**ZERO, "clipping_input_primitives": 1e7}
    assert faster(row) == pytest.approx(p(row) / 2)
    with pytest.raises(ValueError, match="stages of profile"):
        p.scaled({"tessellator": 2.0})
    assert GpuProfile.from_toml(_toml_text("rdna"), "x") == GpuProfile.from_toml(_toml_text("rdna"), "x")


def _toml_text(name: str) -> str:
    return resources.files("terrainwarp.measure").joinpath(f"gpu_profiles/{name}.toml").read_text()


def test_the_docs_table_is_the_shipped_rates():
    """docs/gpu_profiles.rst's table of rates says what the shipped files say."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "gpu_profiles.rst").read_text()
    body = text[text.index(".. list-table::"):text.index("What is missing matters")]
    rows = [r for r in body.split("   * - ")[2:]]
    got = {}
    for r in rows:
        cells = [c.strip().removeprefix("- ").strip() for c in r.strip().split("\n     ")]
        got[cells[0]] = cells
    assert sorted(got) == NAMES
    for name, cells in got.items():
        p = shipped_profile(name)
        assert cells[1].startswith(p.gpu) and float(cells[2]) == p.clock_mhz
        for col, (stage, key) in zip(cells[3:8], [("setup", "triangles_per_clock"), ("shade", "pixels_per_clock"),
                                                   ("rop", "samples_per_clock"), ("memory", "bytes_per_second"),
                                                   ("vertex", "vertices_per_clock")]):
            want = p.rates.get(stage, {}).get(key)
            assert (col == "\\-") if want is None else float(col) * (1e9 if stage == "memory" else 1) == want, (name,
                                                                                                           stage)
        assert sorted(cells[8].split(", ")) == sorted(p.unmodelled), name
