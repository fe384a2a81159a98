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
