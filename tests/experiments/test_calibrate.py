"""The cost model: weights fitted to llvmpipe's frame times (terrainwarp calibrate --gl) on a handful of frames,
the weights file's checks, and the shipped model."""

from __future__ import annotations

import json

import gl_raster_oracle as gl  # noqa: E402
import numpy as np
import pytest

from terrainwarp import Heightmap
from terrainwarp.cli import main
from terrainwarp.experiments.calibrate import FAMILIES, calibrate, calibration_frames, fit_cost_model
from terrainwarp.kernels.counters import PIPELINE_COUNTERS
from terrainwarp.measure.cost import MODEL_FEATURES, CostModel, cost, shipped_model

needs_gl = pytest.mark.skipif(not gl.available(), reason="no EGL / OpenGL 4.5 context (llvmpipe) on this machine")


def test_frames_cover_every_family_seeded():
    hm = Heightmap.example()
    a = calibration_frames(hm, 5, seed=3)
    assert [f.family for f in a] == [f.family for f in calibration_frames(hm, 5, seed=3)]
    assert {f.family for f in a} == set(FAMILIES) and all(sum(f.family == n for f in a) == 5 for n in FAMILIES)
    assert len({(f.camera.width, f.camera.height) for f in a}) == 3  # the viewports vary
    assert [f.family for f in calibration_frames(hm, 5, seed=4)] != [f.family for f in a]


def test_the_fit_recovers_known_weights_and_holds_out_a_quarter():
    rng = np.random.default_rng(0)
    truth = {"clipping_output_primitives": 8e-5, "fragment_shader_invocations_llvmpipe": 4e-6,
             "tess_control_shader_patches": 0.01}
    rows = []
    for k in range(80):
        r = {c: float(rng.uniform(0, 1e6)) for c in MODEL_FEATURES}
        r["tess_control_shader_patches"] = float(rng.uniform(0, 2000))
        r["family"] = ("a", "b")[k % 2]
        r["gl_cpu_ms"] = 0.5 + sum(w * r[c] for c, w in truth.items())
        rows.append(r)
    model, fit = fit_cost_model(rows)
    assert fit["r2_heldout"] > 0.999 and int(fit["held_out"].sum()) == 20
    for c, w in model.weights.items():
        assert w == pytest.approx(truth.get(c, 0.0), rel=1e-6, abs=1e-12), c
    assert model.intercept_ms == pytest.approx(0.5, rel=1e-6)
    with pytest.raises(ValueError, match="rows"):
        fit_cost_model(rows[:5])


@needs_gl
def test_calibrate_on_llvmpipe_writes_a_model_that_loads_and_ranks(tmp_path):
    model, paths = calibrate(tmp_path, frames_per_family=3, families=("sse", "grid", "cdlod", "delatin"), reps=1,
                             progress=False, command="test")
    assert {p.name for p in paths} == {"weights.json", "calibration.csv", "calibration.md"}
    loaded = CostModel.load(tmp_path / "weights.json")
    assert loaded == model and model.frames == 12 and "llvmpipe" in model.driver
    assert np.isfinite(model.r2_heldout) and "R^2 held out" in (tmp_path / "calibration.md").read_text()
    assert cost(str(tmp_path / "weights.json")).model == model
    assert set(model.weights) == set(MODEL_FEATURES)


def test_weights_files_are_checked(tmp_path):
    m = shipped_model()
    assert m.name == "llvmpipe" and m.r2_heldout >= 0.9 and m.frames >= 50 * len(FAMILIES)
    assert all(k in PIPELINE_COUNTERS for k in m.weights) and m.command.startswith("terrainwarp calibrate --gl")
    p = tmp_path / "w.json"
    d = json.loads(m.to_json())
    d["weights"]["samples_passed"] = 1.0  # edited by hand: the checksum no longer matches
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="checksum"):
        CostModel.load(p)
    p.write_text("not json")
    with pytest.raises(ValueError, match="JSON"):
        CostModel.load(p)
    with pytest.raises(FileNotFoundError, match="weights file"):
        cost(str(tmp_path / "missing.json"))
    with pytest.raises(ValueError, match="counter names"):
        CostModel("x", {"pixels": 1.0})
    with pytest.raises(ValueError, match=">= 0"):
        CostModel("x", {"samples_passed": -1.0})
    with pytest.raises(ValueError, match="counters"):
        m({"samples_passed": 1})  # a row without the model's counters
    with pytest.raises(TypeError, match="cost"):
        cost(3)
    with pytest.raises(ValueError, match="frames_per_family"):
        calibrate(tmp_path / "c", frames_per_family=1)
    with pytest.raises(ValueError, match=r"families\[1\]"):
        calibrate(tmp_path / "c", families=("sse", "nope"))


def test_calibrate_needs_the_gl_flag(tmp_path, capsys):
    assert main(["calibrate", "--out", str(tmp_path / "c")]) == 2
    assert "--gl" in capsys.readouterr().err
    assert main(["calibrate", "--gl", "--out", str(tmp_path / "c"), "--families", "sse,nope"]) == 2
    assert "families" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_a_gpu_is_fitted_to_its_own_clock_and_named_after_its_renderer():
    from terrainwarp.experiments.calibrate import model_name, time_column

    llvm = "llvmpipe (LLVM 15.0.6, 256 bits) / 4.5 (Core Profile) Mesa 22.3.6"
    assert time_column(llvm) == "gl_cpu_ms" and model_name(llvm) == "llvmpipe"
    gpu = "NVIDIA GeForce RTX 3080/PCIe/SSE2 / 4.6.0 NVIDIA 535.104.05"
    assert time_column(gpu) == "gl_gpu_ms" and model_name(gpu) == "nvidia-geforce-rtx-3080"
    assert model_name("AMD Radeon RX 5700 XT (radeonsi, navi10, LLVM 15.0.7, DRM 3.49)") == "amd-radeon-rx-5700-xt"
    rng = np.random.default_rng(1)
    rows = [{**{c: float(rng.uniform(0, 1e6)) for c in MODEL_FEATURES}, "family": ("a", "b")[k % 2]}
            for k in range(40)]
    for r in rows:  # a GPU: its timer query says 1 ns per fragment lane; its CPU time says nothing of the work
        r["gl_gpu_ms"] = 0.2 + 1e-6 * r["fragment_shader_invocations_llvmpipe"]
        r["gl_cpu_ms"], r["driver"] = 0.05, gpu
    model, fit = fit_cost_model(rows, target=time_column(gpu), name=model_name(gpu))
    assert model.name == "nvidia-geforce-rtx-3080" and "GL_TIME_ELAPSED" in model.driver
    assert model.weights["fragment_shader_invocations_llvmpipe"] == pytest.approx(1e-6, rel=1e-6)
