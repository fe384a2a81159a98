"""examples/curvature_lines.py runs end to end with tiny settings (a 48 x 48 crop, small pictures)."""

import importlib.util
import json
from pathlib import Path

from matplotlib.image import imread

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "curvature_lines.py"


def _load():
    spec = importlib.util.spec_from_file_location("curvature_lines", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_curvature_lines_example_tiny(tmp_path):
    mod = _load()
    index = mod.main(["--out", str(tmp_path), "--crop", "48", "--size-px", "200"])
    names = {"normal_map", "max_curvature"} | {f"fig3{k}" for k in mod.FIG3} | {f"fig4{k}" for k in mod.FIG4}
    assert set(index) == names
    for n in names:
        assert (tmp_path / f"{n}.png").stat().st_size > 200
    meta = json.loads((tmp_path / "index.json").read_text())
    assert meta["shape"] == [48, 48] and set(meta["pictures"]) == names
    assert index["fig3a"]["segments"] > 0 and index["fig4a"]["segments"] > 0
    assert imread(tmp_path / "normal_map.png").shape == (48, 48, 3)


def test_curvature_lines_example_only(tmp_path):
    index = _load().main(["--out", str(tmp_path), "--crop", "24", "--size-px", "120", "--only", "fig3j,fig4h"])
    assert set(index) == {"fig3j", "fig4h"}
