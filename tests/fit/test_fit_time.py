"""What makes a fit fast, kept honest: the timings add up to the wall time, the relaxed models' programs are
compiled once (in process, and across processes through JAX's persistent cache in the user's cache folder, which
checks its entries), the progress bar keeps moving and says when it compiles, and a relaxed model that turns
non-finite stops the optimiser (never a NaN step) and the fit falls back to the exact search. No wall-clock limit
is asserted anywhere here."""

import json
import os
import subprocess
import sys
import time
import zlib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fit_scenes import fit_scene

from terrainwarp.fit import fit_lod, jaxrt, optimise, search
from terrainwarp.fit.knobs import Knob
from terrainwarp.fit.relaxed import bucket, camera_mask, soft_quantile
from terrainwarp.fit.timings import PARTS, Clock, Progress


@pytest.fixture(scope="module")
def scene():
    return fit_scene(65, max_height=400.0, feature_size=32.0, size=(96, 64))


def test_timings_add_up_to_the_wall_time(scene):
    sc, cams, refs = scene
    res = fit_lod(sc, 1.5, "sse", cams, knobs=["level_log_scale_1", "hysteresis"], references=refs)
    assert set(res.timings) == set(PARTS) and all(v >= 0.0 for v in res.timings.values())
    assert sum(res.timings.values()) == pytest.approx(res.wall_s, rel=0.05)
    assert res.timings["exact"] > 0.0 and res.timings["relaxed"] > 0.0 and res.timings["hard"] > 0.0
    assert res.timing_line().startswith(f"fit took {res.wall_s:.1f} s: compile ")
    assert res.to_dict()["timings"] == res.timings
    # the same fit again in this process compiles nothing more
    n = jaxrt.compiled_count()
    again = fit_lod(sc, 1.5, "sse", cams, knobs=["level_log_scale_1", "hysteresis"], references=refs)
    assert jaxrt.compiled_count() == n and again.values == res.values and again.evaluations == res.evaluations


def test_clock_charges_each_second_to_the_innermost_part():
    c = Clock()
    c.enter("exact")
    c.enter("compile")
    c.leave()
    c.leave()
    got = c.close()
    assert set(got) == set(PARTS) and sum(got.values()) >= 0.0
    with pytest.raises(ValueError, match="name"):
        c.enter("lunch")


def test_progress_bar_refreshes_while_a_step_runs_and_says_what_it_does(capsys):
    bar = Progress(True, 3, "fit test", refresh_s=0.02)
    try:
        bar.say("compiling the relaxed model")
        for _ in range(500):  # wait for the helper thread; no time limit is asserted
            if bar.refreshes >= 2:
                break
            time.sleep(0.01)
        assert bar.refreshes >= 2
        bar()
    finally:
        bar.close()
    err = capsys.readouterr().err
    assert "fit test" in err and "compiling the relaxed model" in err
    quiet = Progress(False, 3, "off")
    quiet.say("x")
    quiet()
    quiet.close()
    assert quiet.refreshes == 0 and capsys.readouterr().err == ""


def test_a_camera_that_sees_nothing_has_the_floor_error_and_a_finite_gradient():
    """grid_1x4097 of the stability suite: no weight at all used to give log p99 = the padding and a NaN
    gradient."""
    logv = jnp.asarray([0.1, 0.5, 30.0, 30.0], jnp.float32)
    f = lambda a: soft_quantile(logv, a * jnp.zeros(4, jnp.float32), n=2)  # noqa: E731
    v, g = jax.value_and_grad(f)(jnp.float32(1.0))
    assert float(v) == pytest.approx(np.log(1e-4)) and np.isfinite(float(g))
    # padding past the pairs' length changes nothing
    w = jnp.asarray([1.0, 2.0, 0.0, 0.0], jnp.float32)
    assert float(soft_quantile(logv, w, n=2)) == float(soft_quantile(logv[:2], w[:2]))
    assert [bucket(n) for n in (0, 1, 3, 8, 9)] == [1, 1, 4, 8, 16] and bucket(5, 256) == 256


class _NanSpec(NamedTuple):
    """A toy model: cost exp(-u0 - 3 u1), log p99 u0 + u1 - 1, NaN once u1 passes 0.6."""

    kind: str = "nan-toy"
    pops: bool = False

    def relaxed(self, data, u, temp):
        bad = jnp.where(u[1] > 0.6, jnp.nan, 0.0)
        cost = jnp.exp(-u[0] - 3.0 * u[1]) * data["cmask"] + bad
        return cost, (u[0] + u[1] - 1.0) * data["cmask"]


class _NanModel:
    knobs = (Knob("a", 0.0, 1.0), Knob("b", 0.0, 1.0))
    spec = _NanSpec()
    data = {"cmask": camera_mask(1)}

    def padded(self, values, fill):
        return np.asarray(values, np.float32)[:1]


def test_a_non_finite_relaxed_model_stops_the_optimiser_and_the_fit_falls_back(scene, monkeypatch):
    with pytest.raises(optimise.NonFiniteModel, match="not finite"):
        optimise.reduced_gradient(_NanModel(), np.array([0.5, 0.5]), 0.0, np.zeros(1), rounds=2)
    ok = optimise.reduced_gradient(_NanModel(), np.array([0.5, 0.1]), 0.0, np.zeros(1), rounds=1, steps=2)
    assert np.all(np.isfinite(ok))

    def nan_solve(*a, **k):
        raise optimise.NonFiniteModel("relaxed model: not finite at u = [nan]")

    monkeypatch.setattr(search, "reduced_gradient", nan_solve)
    sc, cams, refs = scene
    res = fit_lod(sc, 1.5, "sse", cams, knobs=["level_log_scale_1"], references=refs)
    assert res.met and any(h["stage"] == "fallback" for h in res.history)
    assert not any(h["stage"] == "relaxed" for h in res.history)


def test_cache_folder_opt_out_and_entries_checked(tmp_path, monkeypatch):
    monkeypatch.delenv(jaxrt.CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert jaxrt.cache_dir() == tmp_path / "xdg" / "terrainwarp" / "jax"
    monkeypatch.setenv(jaxrt.CACHE_ENV, "off")
    assert jaxrt.cache_dir() is None
    monkeypatch.setenv(jaxrt.CACHE_ENV, str(tmp_path / "mine"))
    assert jaxrt.cache_dir() == tmp_path / "mine"
    folder = tmp_path / "c"
    folder.mkdir()
    whole = zlib.compress(np.random.default_rng(0).bytes(4000))
    (folder / "good-cache").write_bytes(whole)
    (folder / "cut-old-cache").write_bytes(whole[:40])
    (folder / "cut-new-cache").write_bytes(whole[:40])  # maybe still being written by another process
    old = time.time() - 3600
    os.utime(folder / "cut-old-cache", (old, old))
    assert jaxrt.check_entries(folder) == (3, 1)
    assert sorted(p.name for p in folder.glob("*-cache")) == ["cut-new-cache", "good-cache"]
    assert jaxrt.check_entries(folder) == (1, 0)  # the good entry is not read again
    assert "good-cache" in (folder / "verified.txt").read_text()


_FIT = """
import json, sys
from terrainwarp import Camera, Heightmap, LodConfig, Scene, fit_lod
hm = Heightmap.fbm(65, seed=4, dx=20.0, max_height=400.0, feature_size=32.0)
sc = Scene(hm, camera=Camera.default_for(hm, 96, 64), lod=LodConfig(roots=4, tess=8))
r = fit_lod(sc, 1.5, "sse", sc.camera_path(2), knobs=["level_log_scale_1"])
print(json.dumps({"values": r.values, "frames": r.evaluations}))
"""


def test_a_second_fit_in_a_fresh_process_compiles_nothing(tmp_path):
    """The relaxed model's programs land in the cache folder; a second process finds them all there (it writes no
    new entry) and fits the same values on the same frames."""
    env = {**os.environ, jaxrt.CACHE_ENV: str(tmp_path / "jax")}
    runs, entries = [], []
    for _ in range(2):
        r = subprocess.run([sys.executable, "-c", _FIT], capture_output=True, text=True, env=env)
        assert r.returncode == 0, r.stderr[-2000:]
        runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
        entries.append(sorted(p.name for p in (tmp_path / "jax").glob("*-cache")))
    assert entries[0] and entries[1] == entries[0]
    assert runs[0] == runs[1]
