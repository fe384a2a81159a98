"""Every example runs, with tiny settings."""

import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_first_frame(tmp_path):
    f = _load("first_frame").main(["--out", str(tmp_path), "--width", "64", "--height", "48"])
    assert (tmp_path / "frame.png").exists() and f.image.shape == (48, 64, 3)


def test_error_vs_time(tmp_path):
    summ = _load("error_vs_time").main(["--out", str(tmp_path), "--frames", "1", "--width", "64", "--height", "48",
                                        "--quick"])
    assert {r["policy"] for r in summ} >= {"grid", "sse", "martini", "delatin"}
    assert (tmp_path / "pareto.png").exists()


def test_inverse_rendering(tmp_path):
    res = _load("inverse_rendering").main(["--out", str(tmp_path), "--size", "33", "--views", "8", "--width", "96",
                                           "--height", "72", "--iters", "120"])
    assert res["drop"] >= 10.0, res["rmse_m"][::10]  # RMSE in metres against the true heights, from flat
    assert (tmp_path / "inverse_rendering.png").exists() and (tmp_path / "inverse_rendering.json").exists()


def test_streamed_terrain(tmp_path):
    rows = _load("streamed_terrain").main(["--out", str(tmp_path), "--size", "16385", "--frames", "2", "--width",
                                           "160", "--height", "90"])
    assert (tmp_path / "walk_1.png").exists() and rows[0]["tiles_read"] > 0
    assert rows[1]["hits"] > 0 and rows[1]["tiles_read"] < rows[0]["tiles_read"]
