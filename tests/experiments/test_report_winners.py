"""The report's winner per budget under each cost model (llvmpipe and the shipped GPU profiles), with its
robustness, from the same rows the report ranks; and the report ranked by a GPU profile."""

from __future__ import annotations

import pytest

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.experiments.pareto import Setting, summarise, sweep, write_report
from terrainwarp.experiments.winners import BUDGETS, budget_verdicts, report_models
from terrainwarp.measure.cost import cost
from terrainwarp.measure.gpu import shipped_profiles


@pytest.fixture(scope="module")
def swept():
    hm = Heightmap.fbm(65, 80, seed=9, dx=20.0, max_height=400.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 72))
    cams = sc.camera_path(2)
    rows = sweep(sc, cams, [Setting("grid", 0.0), Setting("sse", 0.5), Setting("sse", 4.0), Setting("delatin", 2.0),
                            Setting("cdlod", 1500.0)], progress=False, images=False, workers=0)
    return sc, cams, rows


def test_each_model_picks_the_cheapest_setting_that_meets_each_budget(swept):
    _, _, rows = swept
    summ = summarise(rows)
    models = report_models()
    assert [m.name for m in models] == ["llvmpipe", *(n for n, p in shipped_profiles().items() if p.tessellation)]
    got = budget_verdicts(summ, rows)
    assert len(got) == len(BUDGETS) * len(models)
    for (b, name, v), m in zip(got, models * len(BUDGETS)):
        assert name == m.name
        ok = [s["setting"] for s in summ if s["p99_px"] <= b]
        if not ok:
            assert v is None
            continue
        mean = {s: sum(m(r) for r in rows if r["setting"] == s) / sum(r["setting"] == s for r in rows) for s in ok}
        assert v.winner == min(mean, key=mean.get) and v.cost == mean[v.winner]
        assert v.robust == (v.flip == "") and (v.bound == "") == (name == "llvmpipe")


def test_report_md_has_the_winners_and_ranks_by_a_gpu_profile(swept, tmp_path):
    sc, cams, rows = swept
    write_report(sc, cams, rows, tmp_path, cost_of="gpu:rdna")
    md = (tmp_path / "report.md").read_text()
    assert "GPU profile rdna (AMD Radeon RX 5700 XT" in md
    assert "## Winner per budget under each cost model" in md and "| 2 | gf100 |" in md and "| 2 | llvmpipe |" in md
    by_rdna = {r["setting"]: r["cost"] for r in summarise(rows, cost("gpu:rdna"))}
    model = shipped_profiles()["rdna"]
    for s, c in by_rdna.items():
        rs = [r for r in rows if r["setting"] == s]
        assert c == pytest.approx(sum(model(r) for r in rs) / len(rs))
