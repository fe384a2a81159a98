"""Every example runs, with tiny settings."""

import csv
import importlib.util
import json
import sys
from pathlib import Path

import nbclient
import nbformat
import numpy as np
import pytest

from terrainwarp import Heightmap, schemes
from terrainwarp.cli import main
from terrainwarp.experiments.pareto import summarise

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # as an import does: a dataclass looks its module up by name
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


@pytest.fixture
def bands():
    """examples/custom_scheme.py registers "bands" process-wide: removed again after the test, with any copy of
    the example run as a plugin (so a later --plugin runs it anew)."""
    yield
    if "bands" in schemes.SCHEMES:
        schemes.unregister_scheme("bands")
    for name in [m for m in sys.modules if m.endswith("custom_scheme")]:
        del sys.modules[name]


def test_custom_scheme_is_at_most_80_lines_reported_beside_cdlod_and_fitted(tmp_path, bands):
    assert len((EXAMPLES / "custom_scheme.py").read_text().splitlines()) <= 80
    rows, fit = _load("custom_scheme").main(["--out", str(tmp_path), "--frames", "2", "--width", "64", "--height",
                                             "48", "--workers", "0"])
    assert {r["policy"] for r in rows} == {"bands", "cdlod"} and not any(r["error"] for r in rows)
    summ = {r["setting"]: r for r in summarise(rows)}
    fine, coarse = (summ[f"bands={v:g}"] for v in schemes.sweep_values("bands", Heightmap.example(), quick=True))
    assert fine["p99_px"] < coarse["p99_px"] and fine["triangles"] > 10 * coarse["triangles"]
    # the bands meet without skirts where they differ: background seen through the cracks, far more at the coarse
    # setting (both have open edges far away: check_watertight counts 837 on the fine one's frames at 64x48)
    assert coarse["see_through_px"] > 10 * max(fine["see_through_px"], 1)
    assert {p.name for p in tmp_path.iterdir()} >= {"frames.csv", "pareto.png", "report.md"}
    assert fit.met and fit.policy == "bands" and fit.validated.worst_p99 <= 2.0
    assert schemes.scheme_range("bands", Heightmap.example())[0] <= fit.value


def test_custom_scheme_as_a_plugin_of_report_on_a_worker_process_and_of_fit(tmp_path, capsys, bands):
    """The command line runs the example as a plugin: the report's worker process (which cannot import a file
    run by path) gets the scheme by value, and the fit takes the name."""
    plugin = str(EXAMPLES / "custom_scheme.py")
    small = ["--frames", "2", "--width", "64", "--height", "48", "--no-progress"]
    assert main(["report", "--plugin", plugin, "--policies", "bands,cdlod", "--quick", "--workers", "1",
                 "--no-images", "--out", str(tmp_path / "r"), *small]) == 0
    with open(tmp_path / "r" / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["policy"] for r in rows} == {"bands", "cdlod"} and all(r["error"] == "" for r in rows)
    assert "bands=" in (tmp_path / "r" / "report.md").read_text()
    assert main(["--plugin", plugin, "fit", "--policy", "bands", "--budget-px", "2", "--out", str(tmp_path / "f"),
                 *small]) == 0
    assert json.loads((tmp_path / "f" / "fit.json").read_text())["policy"] == "bands"
    assert "met: worst-frame p99" in capsys.readouterr().out


def test_the_notebook_runs_with_tiny_settings_and_shows_pictures_and_tables(tmp_path):
    """examples/terrainwarp.ipynb executed in a Jupyter kernel (nbclient): its parameters cell replaced by tiny
    sizes; every cell runs, the frames come back as PNG pictures, the report, error and fit as HTML tables."""
    nb = nbformat.read(EXAMPLES / "terrainwarp.ipynb", as_version=4)
    nbformat.validate(nb)
    params = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(params) == 1 and all(not c.get("outputs") for c in nb.cells if c.cell_type == "code")
    params[0].source = "WIDTH, HEIGHT = 96, 64\nFRAMES = 2\nBUDGET_PX = 2.0"
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    shown = [[k for o in c.outputs for k in o.get("data", {})] for c in nb.cells if c.cell_type == "code"]
    html = [o["data"]["text/html"] for c in nb.cells if c.cell_type == "code" for o in c.outputs
            if "text/html" in o.get("data", {})]
    assert sum("image/png" in s for s in shown) >= 3  # the frame, the CDLOD frame, the plot
    assert len(html) == 3 and all(h.startswith("<table>") for h in html)  # report, error, fit
    assert "frame cost" in html[0] and "primary" in html[1] and "met: worst-frame p99" in html[2]
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "cdlod 4000 m:" in text and "chunked 4 px:" in text


def test_lod_flyover_holds_its_state_and_every_frame_is_watertight(tmp_path):
    rows = _load("lod_flyover").main(["--out", str(tmp_path), "--frames", "3", "--width", "96", "--height", "64"])
    assert [r["frame"] for r in rows] == [0, 1, 2]
    assert all(r["cracks"] == 0 and r["t_junctions"] == 0 and r["triangles"] > 0 for r in rows)
    assert len({r["patches"] for r in rows}) > 1  # the selection follows the camera
    assert (tmp_path / "frame_02.png").exists() and len((tmp_path / "flyover.csv").read_text().splitlines()) == 4


def test_fit_budget_meets_its_budget_beside_the_grid_search(tmp_path):
    res = _load("fit_budget").main(["--out", str(tmp_path), "--frames", "2", "--width", "96", "--height", "64",
                                    "--budget-px", "2", "--grid-points", "3"])
    assert res.met and res.validated.worst_p99 <= 2.0 and res.grid["points"] == 3
    assert json.loads((tmp_path / "fit.json").read_text())["met"] is True and (tmp_path / "fit.png").exists()


def test_scheme_comparison_names_each_schemes_cheapest_setting_per_budget(tmp_path):
    table = _load("scheme_comparison").main(["--out", str(tmp_path), "--frames", "2", "--width", "96", "--height",
                                             "64", "--workers", "0"])
    assert {row[1] for row in table} == {"sse", "cdlod", "clipmaps", "chunked"}
    for budget, _, setting, p99, *_ in table:
        assert setting == "-" or p99 <= budget
    assert (tmp_path / "pareto.png").exists() and "cdlod" in (tmp_path / "report.md").read_text()


def test_real_geotiff_reads_the_srtm_tile_with_its_crs_holes_and_a_decimated_part(tmp_path):
    got = _load("real_geotiff").main(["--out", str(tmp_path), "--width", "96", "--height", "64"])
    ref = Heightmap.example()
    assert got["shape"] == ref.shape and got["no_data"] == 20 * 30
    assert abs(got["dx"] - ref.dx) / ref.dx < 1e-3 and abs(got["dz"] - ref.dz) / ref.dz < 1e-3
    hm = Heightmap.load(tmp_path / "srtm.tif")
    holes = np.isnan(hm.heights)
    assert holes[100:120, 200:230].all() and np.array_equal(hm.heights[~holes], ref.heights[~holes])
    assert got["part_shape"] == (86, 101) and abs(got["part_dx"] - 2 * got["dx"]) / got["dx"] < 1e-2
    assert (tmp_path / "frame.png").exists() and (tmp_path / "part.png").exists()
