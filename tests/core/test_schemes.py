"""The scheme registry (terrainwarp.schemes): the built-in schemes register through it, a user's scheme becomes a
name the sources, the report and the fit take, and bad registrations are refused with the argument named."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp import schemes
from terrainwarp.rendering.sources import CdlodSource, ClipmapSource, SourceBase


@pytest.fixture
def registered():
    """Names registered by the test, removed afterwards (the registry is process-wide)."""
    names: list[str] = []
    yield names
    for n in names:
        if n in schemes.SCHEMES:
            schemes.unregister_scheme(n)


class _Flat(SourceBase):
    def mesh_for(self, camera):  # pragma: no cover - never drawn here
        raise AssertionError


def test_the_builtins_register_through_the_registry():
    assert schemes.scheme_names(builtin=True) == ("cdlod", "clipmaps", "chunked", "cesium")
    assert tw.rendering.sources.SCHEMES is schemes.SCHEMES  # the old import path is the same mapping
    spec = schemes.get_scheme("clipmaps")
    assert (spec.parameter, spec.lo, spec.hi, spec.odd_integer, spec.larger_is_finer) == ("n", 15, 4095, True, True)
    with pytest.raises(TypeError):
        schemes.SCHEMES["x"] = spec  # read-only: registration is the one way in


def test_a_registered_name_is_a_source_a_range_and_sweep_values(registered):
    hm = tw.Heightmap.fbm(33, seed=1)
    made = []

    def make(heightmap, value, *, cache, **params):
        made.append((value, params))
        return _Flat(cache=cache)

    schemes.register_scheme("flat", make, parameter="spacing_m", lo=2.0, hi=200.0, larger_is_finer=False)
    registered.append("flat")
    assert "flat" in schemes.scheme_names(builtin=False) and "flat" in schemes.SCHEMES
    cache: dict = {}
    src = schemes.scheme_source("flat", hm, 10.0, cache=cache, device="cpu")
    assert isinstance(src, _Flat) and src.cache is cache and made == [(10.0, {"device": "cpu"})]
    assert schemes.scheme_range("flat", hm) == (2.0, 200.0)
    # 4 values evenly spaced in log space, fine to coarse (a larger spacing is coarser), 2 of them quick
    assert schemes.sweep_values("flat", hm) == [2.0, 9.28, 43.09, 200.0]
    assert schemes.sweep_values("flat", hm, quick=True) == [9.28, 200.0]
    with pytest.raises(ValueError, match="value: expected a finite spacing_m in the range of 'flat'"):
        schemes.scheme_source("flat", hm, 1000.0)
    with pytest.raises(TypeError, match="value: expected a number"):
        schemes.scheme_source("flat", hm, "10")


def test_builtin_values_are_checked_and_odd_integers_rounded_up():
    hm = tw.Heightmap.fbm(65, seed=2)
    src = schemes.scheme_source("clipmaps", hm, 30.2)
    assert isinstance(src, ClipmapSource) and src.scheme.n == 31
    assert isinstance(schemes.scheme_source("cdlod", hm, 200.0, cache={}), CdlodSource)
    for name, bad in (("clipmaps", 9000), ("cdlod", 0.0), ("chunked", math.inf), ("chunked", -1.0)):
        with pytest.raises(ValueError, match=f"value: .*{name}"):
            schemes.scheme_source(name, hm, bad)
    assert schemes.scheme_source("chunked", hm, 0.0).scheme.max_sse_px == 0.0  # a zero threshold: full detail


@pytest.mark.parametrize("kwargs, match", [
    (dict(name="cdlod"), "already registered"),
    (dict(name="sse"), "built-in LOD policy"),
    (dict(name="grid"), "built-in LOD policy"),
    (dict(name="two words"), "name: expected a word"),
    (dict(name=""), "name: expected a word"),
    (dict(lo=5.0, hi=5.0), "lo, hi"),
    (dict(lo=math.nan), "lo, hi"),
    (dict(lo=-math.inf), "lo, hi"),
    (dict(parameter="near m"), "parameter: expected a Python identifier"),
])
def test_bad_registrations_name_the_argument(kwargs, match, registered):
    args = dict(name="mine", make=lambda *a, **k: None, parameter="p", lo=1.0, hi=2.0, larger_is_finer=True)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        schemes.register_scheme(args.pop("name"), args.pop("make"), **args)
    assert "mine" not in schemes.SCHEMES


def test_make_must_be_callable_and_replacing_needs_asking(registered):
    with pytest.raises(TypeError, match="make: expected a callable"):
        schemes.register_scheme("mine", None, parameter="p", lo=1, hi=2, larger_is_finer=True)
    with pytest.raises(TypeError, match="sweep: expected a callable"):
        schemes.register_scheme("mine", print, parameter="p", lo=1, hi=2, larger_is_finer=True, sweep=3)
    first = schemes.register_scheme("mine", print, parameter="p", lo=1, hi=2, larger_is_finer=True)
    registered.append("mine")
    with pytest.raises(ValueError, match="replace=True"):
        schemes.register_scheme("mine", repr, parameter="p", lo=1, hi=2, larger_is_finer=True)
    second = schemes.register_scheme("mine", repr, parameter="p", lo=1, hi=2, larger_is_finer=True, replace=True)
    assert schemes.get_scheme("mine") is second is not first
    with pytest.raises(ValueError, match="already registered"):
        schemes.register_scheme("cdlod", repr, parameter="p", lo=1, hi=2, larger_is_finer=True, replace=True)
    with pytest.raises(ValueError, match="built-in scheme"):
        schemes.unregister_scheme("chunked")
    schemes.unregister_scheme("mine")
    with pytest.raises(ValueError, match="expected a registered scheme"):
        schemes.get_scheme("mine")


def test_the_fit_takes_a_registered_name(registered):
    from terrainwarp.fit import knobs

    hm = tw.Heightmap.fbm(33, seed=1)
    schemes.register_scheme("odd", lambda *a, **k: None, parameter="n", lo=3, hi=99, larger_is_finer=True,
                            odd_integer=True)
    registered.append("odd")
    k = knobs("odd", hm)[0]
    assert (k.name, k.lo, k.hi, k.coarser_up, k.integer) == ("n", 3.0, 99.0, False, True)
    assert k.choices == tuple(float(v) for v in range(3, 100, 2))
    assert k.snap(10.0) == 11


def test_load_plugin_runs_a_file_once_and_imports_a_module(tmp_path, registered):
    f = tmp_path / "myplugin.py"
    f.write_text("import terrainwarp as tw\nRUNS = []\nRUNS.append(1)\n"
                 "tw.schemes.register_scheme('plug', print, parameter='p', lo=1, hi=2, larger_is_finer=True)\n")
    registered.append("plug")
    mod = schemes.load_plugin(f)
    assert "plug" in schemes.SCHEMES and getattr(mod, schemes.PLUGIN_FLAG) is True
    assert schemes.load_plugin(str(f)) is mod and mod.RUNS == [1]  # once per path
    assert schemes.load_plugin("json").__name__ == "json"
    with pytest.raises(ValueError, match="plugin: expected a .py file"):
        schemes.load_plugin(tmp_path / "missing.py")
    bad = tmp_path / "bad.py"
    bad.write_text("raise RuntimeError('broken plugin')\n")
    with pytest.raises(ValueError, match="bad.py failed: RuntimeError: broken plugin"):
        schemes.load_plugin(bad)
    assert not any(m.endswith("_bad") for m in sys.modules)  # a failed plugin leaves no half module
    with pytest.raises(ValueError, match="cannot import 'no_such_module_xyz'"):
        schemes.load_plugin("no_such_module_xyz")


def test_sweep_values_stay_inside_the_range():
    hm = tw.Heightmap.fbm(65, seed=3)
    for name in schemes.scheme_names(builtin=True):
        lo, hi = schemes.scheme_range(name, hm)
        vals = schemes.sweep_values(name, hm)
        assert vals and all(lo - 0.01 <= v <= hi + 0.01 for v in vals), (name, vals, lo, hi)
        assert len(set(vals)) == len(vals)
    assert schemes.sweep_values("clipmaps", hm) == [255.0, 127.0, 63.0, 31.0]
    assert schemes.sweep_values("chunked", hm, quick=True) == [2.0, 8.0]
    assert np.isclose(schemes.sweep_values("cdlod", hm)[0] / schemes.sweep_values("cdlod", hm)[-1], 8.0, rtol=1e-3)


@pytest.mark.parametrize(("name", "params"), [
    ("cdlod", {"first_range": 700.0, "ratio": 3.0, "morph_start_ratio": 0.5, "grid": 16}),
    ("clipmaps", {"n": 31, "transition_ratio": 0.15}),
    ("chunked", {"max_sse_px": 2.5, "tile": 16}),
])
def test_a_scheme_named_in_the_lod_config_draws_its_source(name, params):
    """render of mesh='lod' with LodConfig(policy=<scheme>, params=...) is the frame of the scheme's source made
    from the same values (bit for bit), and every knob changes what is drawn."""
    from conftest import digest

    hm = tw.Heightmap.fbm(129, seed=2, dx=20.0, max_height=500.0)
    cam = tw.Scene(hm, camera=tw.Camera.default_for(hm, 128, 96)).camera_path(3)[1]  # near the ground: every level
    sc = tw.Scene(hm, camera=cam, mesh="lod", outputs=("image", "depth", "mesh"),
                  lod=tw.LodConfig(policy=name, params=params))
    by_name = tw.render(sc)
    rest = {k: v for k, v in params.items() if k != schemes.SCHEMES[name].parameter}
    src = schemes.scheme_source(name, hm, params[schemes.SCHEMES[name].parameter], **rest)
    by_source = tw.render(sc.with_(mesh="grid"), source=src)
    assert digest(by_name.image) == digest(by_source.image) and digest(by_name.depth) == digest(by_source.depth)
    assert by_name.report.info["lod"]["policy"] == name
    spec = schemes.SCHEMES[name]
    for k in spec.knobs:
        other = [c for c in (k.choices or (k.lo, k.hi)) if c != params.get(k.name, k.default)][0]
        changed = tw.render(sc.with_(lod=tw.LodConfig(policy=name, params={**params, k.name: other})))
        assert digest(changed.mesh.positions) != digest(by_name.mesh.positions), k.name
    default = tw.render(sc.with_(lod=tw.LodConfig(policy=name)))  # every knob at its default
    assert default.mesh.n_triangles > 0


def test_scheme_knobs_are_checked_when_registered(registered):
    def make(hm, v, *, cache, **kw):  # pragma: no cover - never drawn here
        raise AssertionError

    for knobs, match in (((schemes.SchemeKnob("p", 0, 1, 0.5),), "distinct"),
                         ((schemes.SchemeKnob("a", 1, 0, 0.5),), "lo < hi"),
                         ((schemes.SchemeKnob("a", 0, 1, 0.5, log=True),), "lo > 0"),
                         ((schemes.SchemeKnob("a", 0, 1, 2.0),), "mine.a")):
        with pytest.raises(ValueError, match=match):
            schemes.register_scheme("mine", make, parameter="p", lo=1, hi=2, larger_is_finer=True, knobs=knobs)
    registered.append("mine")
    spec = schemes.register_scheme("mine", make, parameter="p", lo=1, hi=2, larger_is_finer=True,
                                   knobs=(schemes.SchemeKnob("n", 2, 9, 4, integer=True, choices=(2, 4, 8)),))
    assert spec.check_params({"p": 1.5, "n": 8}) == {"p": 1.5, "n": 8}
    with pytest.raises(ValueError, match=r"mine.n: expected one of \[2, 4, 8\]"):
        spec.check_params({"n": 3})
    with pytest.raises(TypeError, match="mine.n: expected an integer"):
        spec.check_params({"n": 4.0})
