import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from terrainwarp.cli import FIT_FILES, main
from terrainwarp.scene import Scene

ROOT = Path(__file__).resolve().parents[1]


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


def _run(argv):
    """main's exit code, whether it returns or argparse exits."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


# -- issue 20 item 8: numbers refused when parsed, by the LodConfig / policy-table rule ------------------
@pytest.mark.parametrize("argv, option", [
    (["lod", "--tess", "3"], "--tess"), (["lod", "--tess", "16.0"], "--tess"), (["lod", "--tess", "0"], "--tess"),
    (["lod", "--policy", "continuous", "--tess", "65"], "--tess"), (["lod", "--roots", "0"], "--roots"),
    (["lod", "--hysteresis", "1.5"], "--hysteresis"), (["lod", "--level", "-1"], "--level"),
    (["fit", "--budget-px", "1", "--grid-points", "-1"], "--grid-points"),
    (["fit", "--budget-px", "1", "--workers", "-1"], "--workers"), (["fit", "--budget-px", "1", "--frames", "0"],
                                                                    "--frames"),
    (["report", "--frames", "-2"], "--frames"), (["render", "--width", "-5"], "--width")])
def test_bad_numbers_refused_at_once_naming_the_option(argv, option, tmp_path, capsys, monkeypatch):
    import terrainwarp.cli as cli

    monkeypatch.setattr(cli, "_scene", lambda args: pytest.fail("work started before the numbers were checked"))
    assert _run([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option in err[0], err
    assert not (tmp_path / "o").exists()


def test_lod_tess_rule_follows_the_policy(tmp_path, capsys):
    # the continuous policy has no doubled edges: any level 1..64 (the quadtree policies: powers of two)
    assert main(["lod", "--policy", "continuous", "--tess", "3", "--level", "1", "--width", "48", "--height", "32",
                 "--out", str(tmp_path)]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[0])["tess"] == 3


# -- issue 20 item 9: help, usage, version, progress, tessellate's summary, bench ----------------------------
def _subcommands():
    from terrainwarp.cli import build_parser

    p = build_parser()
    return p, next(a for a in p._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_every_option_has_help_and_shows_its_default():
    _, subs = _subcommands()
    assert set(subs) == {"demo", "render", "lod", "report", "fit", "evaluate", "export", "calibrate", "stability",
                         "tessellate", "warmup", "bench"}
    for name, sp in subs.items():
        fmt = sp.formatter_class(prog=name)
        for a in sp._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            assert a.help, f"{name} {a.option_strings or a.dest}: no help text"
            if a.default is not None and a.default is not False and a.default != []:
                assert "(default: %(default)s)" in fmt._get_help_string(a) or "default" in a.help, \
                    f"{name} {a.option_strings}: default {a.default!r} not shown"
    for opt in ("--out", "--width", "--height", "--roots", "--tess", "--hysteresis", "--policy"):
        assert opt in subs["lod"].format_help()
    assert "(default: out/lod)" in " ".join(subs["lod"].format_help().split())


def test_bare_command_prints_usage_and_version(capsys):
    assert main([]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: terrainwarp") and all(c in err for c in ("demo", "fit", "bench", "tessellate"))
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    from terrainwarp import __version__

    assert capsys.readouterr().out.strip() == f"terrainwarp {__version__}"


def test_fit_command_shows_progress_unless_told_not_to(monkeypatch, tmp_path, capsys):
    import terrainwarp.cli as cli

    seen = []

    def fake_fit(*a, **kw):
        seen.append(kw.get("progress"))
        raise ValueError("stop here")

    monkeypatch.setattr(cli, "fit_lod", fake_fit)
    base = ["fit", "--budget-px", "1", "--frames", "1", "--width", "32", "--height", "24", "--out", str(tmp_path)]
    assert main(base) == 2
    assert main([*base, "--no-progress"]) == 2
    assert seen == [True, False]


def test_tessellate_prints_a_summary_and_what_it_wrote(tmp_path, capsys):
    assert main(["tessellate", "--outer", "3", "5", "1", "7", "--inner", "4", "4", "--out", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    doc = json.loads((tmp_path / "tessellation.json").read_text())
    assert len(lines) == 2 and f"{doc['n_triangles']} triangles" in lines[0] and not lines[0].startswith("{")
    assert lines[1] == f"wrote: {tmp_path / 'tessellation.png'}, {tmp_path / 'tessellation.json'}"


def _fake_benchmarks(root):
    b = root / "benchmarks"
    b.mkdir()
    (b / "run_all.py").write_text("print('run_all ran')\n")
    (b / "collect.py").write_text("print('collect ran')\n")
    for n in ("alpha", "beta"):
        (b / f"bench_{n}.py").write_text(f"print('{n} ran')\n")
    return b


def test_bench_lists_runs_all_or_named_and_refuses_unknown(monkeypatch, tmp_path, capfd):
    import terrainwarp.cli as cli

    assert main(["bench", "--list"]) == 0  # the real benchmarks/ of this checkout
    assert {"lod", "frame", "tessellate"} <= set(capfd.readouterr().out.split())
    monkeypatch.setattr(cli, "BENCHMARKS_DIR", _fake_benchmarks(tmp_path))
    assert main(["bench"]) == 0
    assert capfd.readouterr().out.split("\n")[0] == "run_all ran"
    assert main(["bench", "beta"]) == 0
    out = capfd.readouterr().out
    assert "beta ran" in out and "alpha ran" not in out and "collect ran" in out
    assert main(["bench", "beta", "gamma"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gamma" in err[0] and "alpha" in err[0]
    monkeypatch.setattr(cli, "BENCHMARKS_DIR", tmp_path / "site-packages" / "benchmarks")  # an installed wheel
    for argv in (["bench"], ["bench", "--list"], ["bench", "lod"]):
        assert main(argv) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "no benchmarks" in err[0] and "source checkout" in err[0]


def test_report_and_fit_state_the_path_and_show_primary_image_and_pop_errors(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text('[heightmap]\nfbm = { rows = 65, seed = 3, dx = 20.0, max_height = 400.0 }\n'
                     '[camera]\nwidth = 64\nheight = 48\n[lod]\nroots = 4\ntess = 8\n')
    rep = tmp_path / "rep"
    assert main(["report", str(scene), "--frames", "2", "--quick", "--policies", "grid,sse,martini", "--workers", "0",
                 "--no-images", "--path", "high", "--out", str(rep)]) == 0
    out, err = capsys.readouterr()
    # each slow step said on stderr before it runs (issue 44: no silent wait; --no-progress: not said)
    assert "terrainwarp: rendering the full-resolution reference frame of each of 2 cameras" in err.splitlines()
    assert "terrainwarp: meshing 2 Martini/Delatin settings (view-independent, once per sweep)" in err.splitlines()
    assert "path: flyover of 2 cameras" in out and "10.0% of the" in out and "image p99" in out and "pop p99" in out
    md = (rep / "report.md").read_text()
    assert "'high'" in md and "Popping" in md
    header = (rep / "frames.csv").read_text().splitlines()[0].split(",")
    want = {"p99_px", "image_err_p99_px", "image_err_max_px", "pop_p99_px", "pop_max_px", "popped_samples"}
    assert want <= set(header)
    fit = tmp_path / "fit"
    assert main(["fit", str(scene), "--frames", "2", "--budget-px", "2", "--max-pop-px", "50",
                 "--out", str(fit)]) == 0
    assert "terrainwarp: rendering the full-resolution reference frame of each of 2 cameras" in \
        capsys.readouterr().err.splitlines()
    doc = json.loads((fit / "fit.json").read_text())
    assert doc["path"]["preset"] == "ground" and doc["path"]["clearance_fraction"] == pytest.approx(0.02)
    assert doc["max_pop_px"] == 50 and len(doc["validated"]["pop_p99_px"]) == 1
    assert len(doc["validated"]["image_p99_px"]) == 2
    md = (fit / "report.md").read_text()
    assert "Camera path: flyover of 2 cameras" in md and "2.0% of the" in md and "grid-image error" in md
    assert "pop p99" in md
    assert sorted(p.name for p in fit.iterdir()) == sorted(FIT_FILES)  # what the help and the README say


def test_fit_help_and_readme_name_the_files_fit_writes():
    """fit --help named fit.json, fit.png and report.md, the README fit.json, fit.png and fitted.toml; it writes
    all four (issue 44, defect 9)."""
    _, subs = _subcommands()
    assert subs["fit"].description.startswith("Fit LOD thresholds to a screen-space error budget: "
                                              + ", ".join(FIT_FILES))
    readme = (ROOT / "README.md").read_text().splitlines()
    line = next(ln for ln in readme if ln.startswith("terrainwarp fit ") and "#" in ln)
    named = [w.strip(",") for w in line.split("#", 1)[1].split() if w.strip(",").endswith((".json", ".png", ".toml",
                                                                                           ".md"))]
    assert sorted(named) == sorted(FIT_FILES)


def test_cli_stability_writes_report_and_rejects_bad_args(tmp_path):
    out = tmp_path / "stab"
    r = subprocess.run([sys.executable, "-m", "terrainwarp.cli", "stability", "--out", str(out), "--cases",
                        "tess_nan,tess_64", "--no-progress"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = (out / "stability.md").read_text()
    assert "| tess_64 | tessellate | pass |" in text and "| tess_nan | tessellate | pass |" in text
    assert sorted(p.name for p in out.iterdir()) == ["stability.md"]
    for argv in (["stability"], ["stability", "--out", str(tmp_path / "x"), "--cases", "atlantis"],
                 ["stability", "--out", str(tmp_path / "x"), "--fast"]):
        r = subprocess.run([sys.executable, "-m", "terrainwarp.cli", *argv], capture_output=True, text=True)
        assert r.returncode == 2
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("terrainwarp: error:"), r.stderr
        assert not (tmp_path / "x").exists()


def test_fit_with_knobs_and_baselines_writes_the_fitted_scene_and_the_convergence(tmp_path, capsys):
    """``fit --knobs tess --baselines bisection,random``: the fitted setting is a scene file that loads back to the
    fitted values, and the tuners ran on the same frames beside the fit."""
    scene = tmp_path / "s.toml"
    scene.write_text('[heightmap]\nfbm = { rows = 65, seed = 3, dx = 20.0, max_height = 400.0 }\n'
                     '[camera]\nwidth = 64\nheight = 48\n[lod]\nroots = 4\ntess = 8\n')
    out = tmp_path / "fit"
    assert main(["fit", str(scene), "--frames", "2", "--budget-px", "2", "--no-progress", "--knobs", "tess",
                 "--baselines", "bisection,random", "--trials", "4", "--grid-points", "0", "--out", str(out)]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["knobs"] == ["tolerance_px", "tess"] and set(doc["baselines"]) == {"bisection", "random"}
    assert doc["baselines"]["random"]["settings"] <= 4 and doc["baselines"]["bisection"]["frames"] > 0
    loaded = Scene.load(out / "fitted.toml")
    assert loaded.lod.tess == doc["values"]["tess"] and loaded.lod.tolerance_px == pytest.approx(
        doc["values"]["tolerance_px"])
    assert (out / "convergence.png").stat().st_size > 0
    timing = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("fit took ")]
    assert len(timing) == 1 and all(w in timing[0] for w in ("compile", "relaxed model", "hard model", "probes",
                                                              "exact frames", "other"))
    # the wall times by part: timing.json (fit.json is the same bytes on every run)
    timings = json.loads((out / "timing.json").read_text())["timings"]
    assert set(timings) == {"compile", "relaxed", "hard", "probes", "exact", "other"} and "timings" not in doc
    assert main(["fit", str(scene), "--budget-px", "2", "--knobs", "warp_factor", "--no-progress",
                 "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("terrainwarp: error: knobs: 'sse' has no knob ['warp_factor']") and err.count("\n") == 1
    assert not (tmp_path / "bad").exists()
