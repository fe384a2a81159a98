"""Every JSON the command line writes is strict RFC 8259 JSON (issue 43, finding 6): no ``Infinity`` or ``NaN``
token (Node's ``JSON.parse`` rejects them, jq turns them into 1.797e308); a number JSON cannot hold is ``null``
with its reason in a ``<key>_reason`` sibling. Also: ``fit`` on a GeoTIFF scene writes its outputs (finding 2).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from terrainwarp import Heightmap
from terrainwarp.cli import main
from terrainwarp.io.geotiff import write_tiled


def _strict(text: str) -> object:
    def refuse(token: str) -> None:
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def _every_json(root: Path) -> dict[str, object]:
    return {str(p.relative_to(root)): _strict(p.read_text()) for p in sorted(root.rglob("*.json"))}


def _holed_geotiff(folder: Path) -> Path:
    h = np.array(Heightmap.fbm(65, seed=4, dx=20.0, max_height=400.0).heights)
    h[40:56, 40:56] = np.nan
    return write_tiled(folder / "hole.tif", h.shape, lambda r0, c0, a, b: h[r0:r0 + a, c0:c0 + b], dx=20.0)


def test_every_json_the_cli_writes_is_strict(tmp_path, capsys):
    tif = _holed_geotiff(tmp_path)
    (tmp_path / "hole.toml").write_text('[heightmap]\npath = "hole.tif"\n[camera]\nwidth = 64\nheight = 48\n')
    (tmp_path / "grid.toml").write_text('[heightmap]\nexample = "jacksboro"\n[camera]\nwidth = 48\nheight = 32\n'
                                        '[render]\nmesh = "grid"\noutputs = ["image", "error", "report"]\n')
    out = tmp_path / "out"
    runs = {
        "render": ["render", str(tmp_path / "grid.toml")],  # psnr_db of the grid against itself: infinite
        "fit": ["fit", str(tmp_path / "hole.toml"), "--budget-px", "1", "--frames", "3", "--no-progress"],
        "tessellate": ["tessellate", "--outer", "nan", "2", "3", "4", "--inner", "2", "inf"],
        "lod": ["lod", str(tmp_path / "hole.toml")],
        "calibrate": ["calibrate", "--gl", "--frames-per-family", "6", "--reps", "1", "--families", "grid,sse",
                      "--no-progress"],
    }
    for name, argv in runs.items():
        assert main([*argv, "--out", str(out / name)]) in (0, 1), name
        printed = capsys.readouterr().out
        if name == "lod":  # its statistics, printed as one JSON line
            _strict(next(ln for ln in printed.splitlines() if ln.startswith("{")))
    docs = _every_json(out)
    assert {"render/report.json", "fit/fit.json", "fit/timing.json", "tessellate/tessellation.json",
            "calibrate/weights.json"} <= set(docs)
    rep = docs["render/report.json"]["info"]["error"]
    assert rep["psnr_db"] is None and rep["psnr_db_reason"].startswith("inf: the images are identical")
    fit = docs["fit/fit.json"]
    assert fit["met"] is True and Path(fit["lod"]["policy"]) and (out / "fit" / "fitted.toml").exists()
    assert "beside" not in str(tif)  # (the scene names its GeoTIFF: a whole raster, saved as its path)
    assert (out / "fit" / "fitted.toml").read_text().count("window") == 0


def test_strict_json_names_what_each_null_stood_for():
    from terrainwarp.io.files import dumps_strict

    doc = _strict(dumps_strict({"p99_px": [0.0, float("inf")], "pop_p99_px": float("nan"),
                                "nested": {"cost": float("-inf")}, "n": np.int64(3)}))
    assert doc["p99_px"] == [0.0, None] and doc["p99_px_reason"].startswith("entry 1: inf: unbounded")
    assert doc["pop_p99_px"] is None and doc["pop_p99_px_reason"].startswith("nan: not measured")
    assert doc["nested"] == {"cost": None, "cost_reason": "-inf: minus infinity"} and doc["n"] == 3
