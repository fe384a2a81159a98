import csv
import io

import pytest

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.experiments.pareto import (
    TIMING_COLUMNS,
    Setting,
    budget_table,
    pareto,
    rows_to_csv,
    summarise,
    sweep,
    write_report,
)


@pytest.fixture(scope="module")
def small():
    hm = Heightmap.fbm(65, 80, seed=9, dx=20.0, max_height=400.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 72))
    return sc, sc.camera_path(2)


SETTINGS = [Setting("grid", 0.0), Setting("sse", 0.1), Setting("sse", 8.0), Setting("continuous", 8.0),
            Setting("delatin", 2.0), Setting("martini", 8.0), Setting("polytree", 4.0), Setting("bintree", 15.0)]


def _strip(text: str) -> list[dict]:
    rows = list(csv.DictReader(io.StringIO(text)))
    for r in rows:
        for k in (*TIMING_COLUMNS, "prepare_ms"):
            r.pop(k, None)
    return rows


def test_sweep_is_reproducible_apart_from_timings(small):
    sc, cams = small
    a = sweep(sc, cams, SETTINGS, progress=False)
    b = sweep(sc, cams, SETTINGS, progress=False)
    assert _strip(rows_to_csv(a)) == _strip(rows_to_csv(b))
    assert len(a) == len(SETTINGS) * len(cams)
    grid = [r for r in a if r["policy"] == "grid"]
    assert all(r["p99_px"] < 1e-2 and r["cracks"] == 0 for r in grid)
    coarse = [r for r in a if r["setting"] == "sse=8"]
    fine = [r for r in a if r["setting"] == "sse=0.1"]
    assert sum(r["triangles"] for r in coarse) < sum(r["triangles"] for r in fine)
    assert all(r["cracks"] == 0 for r in a if r["policy"] in ("sse", "continuous", "polytree", "bintree"))
    assert all(r["triangles"] > 0 and r["peer_mesh_ms"] > 0 for r in a if r["policy"] in ("polytree", "bintree"))


def test_report_files_and_tables(small, tmp_path):
    sc, cams = small
    rows = sweep(sc, cams, SETTINGS[:1] + SETTINGS[4:6], progress=False, images=False)
    paths = {p.name for p in write_report(sc, cams, rows, tmp_path)}
    assert paths == {"frames.csv", "pareto.png", "report.md"}
    summ = summarise(rows)
    front = pareto(summ)
    assert front and all(r in summ for r in front)
    tab = budget_table(summ, budgets=(1e9,))
    assert {r[1] for r in tab} == {"grid", "delatin", "martini"}
    assert "Cheapest setting per budget" in (tmp_path / "report.md").read_text()
