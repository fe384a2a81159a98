import json
import subprocess
import sys

import pytest

from terrainwarp.cli import main


def test_demo_writes_three_files(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--width", "96", "--height", "64"]) == 0
    out = capsys.readouterr().out
    assert "raster" in out and "total" in out
    assert {p.name for p in tmp_path.iterdir()} == {"frame.png", "depth.exr", "report.json"}
    rep = json.loads((tmp_path / "report.json").read_text())
    assert [s["name"] for s in rep["stages"]] == ["normal_map", "mesh", "raster", "shade"]
    assert rep["info"]["width"] == 96


def test_render_scene_file(tmp_path):
    s = tmp_path / "s.toml"
    s.write_text('[heightmap]\nexample = "topobathy"\n[camera]\nwidth = 48\nheight = 32\n')
    assert main(["render", str(s), "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "frame.png").exists()


@pytest.mark.parametrize("argv", [["render", "missing.toml"], ["bogus"], ["demo", "--width", "x"],
                                  ["demo", "--width", "0"]])
def test_bad_arguments_one_line_exit_2(argv, tmp_path):
    r = subprocess.run([sys.executable, "-m", "terrainwarp.cli", *argv, "--out", str(tmp_path)]
                       if argv[0] != "bogus" else [sys.executable, "-m", "terrainwarp.cli", *argv],
                       capture_output=True, text=True)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("terrainwarp:")]
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr
    assert not any(tmp_path.iterdir())


def test_lod_writes_picture_and_table(tmp_path, capsys):
    assert main(["lod", "--out", str(tmp_path), "--tolerance-px", "2", "--width", "160", "--height", "120"]) == 0
    assert (tmp_path / "lod.png").stat().st_size > 1000
    rows = (tmp_path / "patches.csv").read_text().splitlines()
    stats = json.loads(capsys.readouterr().out.splitlines()[0])
    assert len(rows) == 1 + stats["patches"]
    assert rows[0].startswith("key,zoom_x_y,level")
