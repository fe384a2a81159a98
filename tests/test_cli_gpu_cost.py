"""The command line's --cost with GPU profiles: report ranks by one and prints the winner per budget under each
model; fit takes several models separated by commas; a bad profile is one line and exit 2."""

from __future__ import annotations

import json

from terrainwarp.cli import main


def _scene(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text('[heightmap]\nfbm = { rows = 65, seed = 3, dx = 20.0, max_height = 400.0 }\n'
                     '[camera]\nwidth = 64\nheight = 48\n[lod]\nroots = 4\ntess = 8\n')
    return scene


def test_report_by_a_gpu_profile_prints_each_models_winner(tmp_path, capsys):
    rep = tmp_path / "rep"
    assert main(["report", str(_scene(tmp_path)), "--frames", "2", "--quick", "--policies", "grid,sse,cdlod",
                 "--workers", "0", "--no-images", "--no-progress", "--cost", "gpu:rdna", "--out", str(rep)]) == 0
    out = capsys.readouterr().out
    assert "cost: modelled rdna ms" in out and "winner per budget under each cost model" in out
    for name in ("llvmpipe", "gf100", "gcn", "rdna", "mali"):
        assert f"  {name}  " in out or f" {name}  " in out, name
    md = (rep / "report.md").read_text()
    assert "GPU profile rdna" in md and "## Winner per budget under each cost model" in md


def test_fit_for_several_gpus_and_a_bad_profile(tmp_path, capsys):
    fit = tmp_path / "fit"
    assert main(["fit", str(_scene(tmp_path)), "--frames", "2", "--budget-px", "2", "--no-progress", "--cost",
                 "gpu:gf100,gpu:mali", "--out", str(fit)]) == 0
    assert json.loads((fit / "fit.json").read_text())["cost"] == "worst modelled ms over gf100, mali"
    capsys.readouterr()
    assert main(["fit", str(_scene(tmp_path)), "--budget-px", "2", "--cost", "gpu:gf200", "--out",
                 str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gf200" in err[0] and "gf100" in err[0]
