"""What a new user hit in their first hour with the README open (issue 44, defects 10 and 11, and item 3): errors
that named no argument, a spacing silently assumed, an empty frame without a word, and a first snippet that printed
a CUDA warning and a line per kernel module."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import terrainwarp as tw
from terrainwarp.heightmap import DefaultSpacingWarning
from terrainwarp.io.files import write_image
from terrainwarp.rendering.pipeline import EmptyFrameWarning

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene():
    hm = tw.Heightmap.fbm(17, seed=1, dx=10.0)
    return tw.Scene(hm, camera=tw.Camera.default_for(hm, 32, 24), outputs=("depth",))


def test_camera_default_for_names_the_heightmap():
    with pytest.raises(TypeError, match=r"^heightmap: expected a terrainwarp Heightmap or StreamedHeightmap, got str"):
        tw.Camera.default_for("x", 64, 36)


def test_render_names_a_bad_state_terrain_reference_or_scene(scene):
    for kw, name in ((dict(state="x"), "state"), (dict(terrain=3), "terrain"), (dict(reference="f"), "reference")):
        with pytest.raises(TypeError, match=rf"^{name}: expected a terrainwarp \w+ or None, got"):
            tw.render(scene, **kw)
    with pytest.raises(TypeError, match=r"^scene: expected a terrainwarp Scene, got"):
        tw.render(scene.heightmap)


def test_render_on_a_gpu_this_machine_lacks_says_so_naming_device(scene):
    if wp.is_cuda_available():  # a GPU machine: a device it does not have
        with pytest.raises(ValueError, match=r"^device: expected one of the devices Warp sees \('cpu', 'cuda:0'"):
            tw.render(scene, device="cuda:99")
    else:
        with pytest.raises(ValueError, match=r"^device: 'cuda:0' asks for an NVIDIA GPU, but Warp finds no"):
            tw.render(scene, device="cuda:0")
    with pytest.raises(ValueError, match=r"^device: expected one of the devices Warp sees"):
        tw.render(scene, device="tpu")
    with pytest.raises(TypeError, match=r"^device: expected a device name"):
        tw.render(scene, device=0)


def test_knobs_of_an_unknown_policy_lists_every_policy_with_knobs(scene):
    with pytest.raises(ValueError, match=r"^policy: expected one of \[") as e:
        tw.fit.knobs("nope", scene.heightmap)
    for name in ("sse", "distance", "continuous", "cdlod", "clipmaps", "chunked"):
        assert repr(name) in str(e.value), name


def test_an_image_without_spacing_says_once_that_1_m_is_assumed(tmp_path):
    path = tmp_path / "hills.png"
    write_image(path, (np.arange(64, dtype=np.uint16).reshape(8, 8) * 100))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        hm = tw.Heightmap.load(path)
    said = [w for w in seen if issubclass(w.category, DefaultSpacingWarning)]
    assert len(said) == 1 and re.match(r"^dx: hills\.png carries no sample spacing; 1 m assumed", str(said[0].message))
    assert said[0].filename == __file__  # pointed at the caller's line
    assert hm.dx == hm.dz == 1.0 and "1 m assumed" in hm.meta["spacing"]
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert tw.Heightmap.load(path, dx=30.0).dx == 30.0
    assert not [w for w in seen if issubclass(w.category, DefaultSpacingWarning)]


def test_a_1x1_heightmap_says_why_its_frame_is_empty():
    hm = tw.Heightmap.from_array(np.full((1, 1), 5.0, np.float32), dx=10.0)
    cam = tw.Camera(position=(0.0, 50.0, 50.0), target=(0.0, 5.0, 0.0), width=16, height=12)
    with pytest.warns(EmptyFrameWarning, match=r"^heightmap: 1x1 samples make no triangle"):
        f = tw.render(tw.Scene(hm, camera=cam, outputs=("depth", "report")))
    assert f.mesh.n_triangles == 0 and f.report.info["empty"].startswith("heightmap: 1x1 samples")


def test_the_readmes_first_snippet_prints_only_what_it_asks_for(tmp_path):
    """No CUDA-driver warning, no Warp greeting, no 'Module ... load took' lines: the report's table alone. The
    README names Heightmap.from_array beside the other constructors."""
    readme = (ROOT / "README.md").read_text()
    snippet = re.search(r"## Python\n\n```python\n(.*?)```", readme, re.S).group(1)
    assert "tw.Heightmap.from_array(" in snippet and "print(frame.report.table())" in snippet
    env = {k: v for k, v in os.environ.items() if k != "TERRAINWARP_VERBOSE"}
    r = subprocess.run([sys.executable, "-c", snippet.replace("1280, 720", "320, 180")], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].split()[:3] == ["stage", "time_ms", "counters"] and lines[-1].startswith("host ")
    assert not [ln for ln in lines if "Warp" in ln or "Module" in ln]
    assert (tmp_path / "out" / "my_frame" / "frame.png").exists()


# ------------------------------------------------------------------------------------------------
# the command says what it does before each slow step (item 2)
# ------------------------------------------------------------------------------------------------
def test_stability_says_what_it_runs(tmp_path, capsys):
    """(report and fit: tests/test_cli.py::test_report_and_fit_state_the_path_and_show_primary_image_and_pop_errors)"""
    from terrainwarp.cli import main

    assert main(["stability", "--out", str(tmp_path / "s"), "--cases", "tess_64"]) == 0
    assert capsys.readouterr().err.splitlines() == ["terrainwarp: running 1 extreme cases through every stage on "
                                                    "33 x 33 grids"]
    assert main(["stability", "--out", str(tmp_path / "t"), "--cases", "tess_64", "--no-progress"]) == 0
    assert capsys.readouterr().err == ""  # --no-progress: a program reading stderr gets nothing else


def test_a_render_beyond_4k_says_its_memory_first():
    from terrainwarp.cli import frame_memory_note

    hm = tw.Heightmap.fbm(17, seed=1)
    big = tw.Scene(hm, camera=tw.Camera.default_for(hm, 16384, 16384), outputs=("depth",))
    assert frame_memory_note(big) == "rendering 16384x16384 (268 Mpixel, depth): about 4.0 GiB of frame buffers"
    assert frame_memory_note(big.with_(outputs=("image", "depth", "report"))).endswith("about 6.8 GiB of frame buffers")
    assert frame_memory_note(big.with_(camera=big.camera.with_(width=3840, height=2160))) is None
