"""Two identical runs of ``demo``, ``render`` (every output a scene can ask for) and ``lod`` write the same
bytes: the sha256 of every file matches (issue 20, "Done when"; item 2: the EXR files once carried the time
of writing). The one exception is what is measured, not computed: the stage times in ``report.json``
(``time_ms``, ``total_ms``, every ``*_ms`` key), which are compared with those keys left out.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import pytest

from terrainwarp.cli import main

SMALL = ["--width", "48", "--height", "32"]
EVERY_OUTPUT = """
[heightmap]
example = "jacksboro"
[camera]
width = 48
height = 32
[render]
mesh = "lod"
outputs = ["image", "depth", "normals", "curvature", "report", "mesh", "patches", "error"]
[lod]
roots = 4
tess = 8
"""


def _without_times(o: object) -> object:
    if isinstance(o, dict):
        return {k: _without_times(v) for k, v in o.items() if not k.endswith("_ms")}
    if isinstance(o, list):
        return [_without_times(v) for v in o]
    return o


def _fingerprints(d: Path) -> dict[str, str]:
    out = {}
    for f in sorted(p for p in d.rglob("*") if p.is_file()):
        data = f.read_bytes()
        if f.name == "report.json":  # measured stage times differ run to run; everything else must not
            data = json.dumps(_without_times(json.loads(data)), sort_keys=True).encode()
        out[str(f.relative_to(d))] = hashlib.sha256(data).hexdigest()
    return out


@pytest.mark.parametrize("command", ["demo", "render", "lod"])
def test_two_identical_runs_write_identical_files(command, tmp_path, capsys):
    argv = {"demo": ["demo", *SMALL], "lod": ["lod", *SMALL]}.get(command)
    if argv is None:
        scene = tmp_path / "every_output.toml"
        scene.write_text(EVERY_OUTPUT)
        argv = ["render", str(scene)]
    runs = []
    for name in ("a", "b"):
        # a new wall-clock second for each run: a timestamp written to the second (EXR/TIFF DateTime) shows
        time.sleep(1.0 - time.time() % 1.0 + 0.01)
        assert main([*argv, "--out", str(tmp_path / name)]) == 0
        runs.append(_fingerprints(tmp_path / name))
    capsys.readouterr()
    assert runs[0].keys() == runs[1].keys() and runs[0]
    if command == "render":
        assert {"frame.png", "depth.exr", "normals.exr", "curvature.exr", "error_px.exr", "mesh.vtp",
                "patches.csv", "report.json"} <= set(runs[0])
    differ = sorted(k for k in runs[0] if runs[0][k] != runs[1][k])
    assert not differ, f"files that differ between two identical runs: {differ}"


SMALL_SCENE = '[heightmap]\nfbm = { rows = 33, seed = 3, dx = 20.0, max_height = 400.0 }\n[camera]\nwidth = 40\n' \
              'height = 30\n[lod]\nroots = 2\ntess = 4\n'


def _untimed_files(d: Path) -> dict[str, str]:
    """Every file's sha256, but the timing files the README names (``timing.*``: wall times and CPU ms), with
    report.json's ``*_ms`` keys and frames.csv's timing columns left out."""
    import csv
    import io

    from terrainwarp.rendering.rows import TIMING_COLUMNS

    out = {}
    for f in sorted(p for p in d.rglob("*") if p.is_file() and not p.name.startswith("timing.")):
        data = f.read_bytes()
        if f.name == "report.json":
            data = json.dumps(_without_times(json.loads(data)), sort_keys=True).encode()
        if f.name == "frames.csv":
            rows = [{k: v for k, v in r.items() if k not in TIMING_COLUMNS and k != "prepare_ms"}
                    for r in csv.DictReader(io.StringIO(data.decode()))]
            data = json.dumps(rows).encode()
        out[str(f.relative_to(d))] = hashlib.sha256(data).hexdigest()
    return out


@pytest.mark.parametrize("command", ["fit", "report", "evaluate"])
def test_fit_and_report_write_the_same_bytes_but_their_timing_files(command, tmp_path, capsys):
    """Issue 43 (finding 9): fit.json held wall_s, model_s and the validated frames' frame_ms, and the fit's
    report.md a wall-s column (evaluate.json the frames' frame_ms); they live in timing.json / timing.md now, the
    timing files the README names."""
    scene = tmp_path / "s.toml"
    scene.write_text(SMALL_SCENE + "[render]\nmesh = \"lod\"\n[budget]\nbudget_px = 2.0\n")
    argv = {"evaluate": ["evaluate", str(scene), "--frames", "2"],
            "fit": ["fit", str(scene), "--frames", "2", "--budget-px", "2", "--no-progress"],
            "report": ["report", str(scene), "--frames", "2", "--quick", "--policies", "grid,sse", "--workers", "0",
                       "--no-images", "--no-progress"]}[command]
    runs = []
    for name in ("a", "b"):
        assert main([*argv, "--out", str(tmp_path / name)]) == 0
        runs.append(_untimed_files(tmp_path / name))
    capsys.readouterr()
    assert runs[0] == runs[1]
    timing = {p.name for p in (tmp_path / "a").iterdir() if p.name.startswith("timing.")}
    want = {"fit": {"timing.json", "timing.md"}, "report": {"timing.md"}, "evaluate": {"timing.json"}}
    assert timing == want[command]
    if command == "fit":
        doc = json.loads((tmp_path / "a" / "fit.json").read_text())
        assert "wall_s" not in doc and "frame_ms" not in doc["validated"]
        assert json.loads((tmp_path / "a" / "timing.json").read_text())["wall_s"] > 0
