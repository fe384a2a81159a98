"""``Report.counters``: every family's frame counted as it draws, the same for any thread count, nothing
counted unless asked, and in report.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

import terrainwarp.kernels.raster as raster
import terrainwarp.rendering.pipeline as pipeline
from terrainwarp import Camera, Heightmap, LodConfig, Scene, render
from terrainwarp.kernels.counters import PIPELINE_COUNTERS
from terrainwarp.kernels.parallel import set_threads
from terrainwarp.lod.peers import delatin_mesh
from terrainwarp.rendering.sources import PeerSource
from terrainwarp.schemes import scheme_source


@pytest.fixture(scope="module")
def small():
    hm = Heightmap.fbm(97, seed=5, dx=20.0, max_height=500.0)
    cams = Scene(hm, camera=Camera.default_for(hm, 160, 96)).camera_path(3)
    return hm, cams


def _families(hm):
    cache: dict = {}
    return {"sse": (dict(mesh="lod", lod=LodConfig(roots=4, tess=8)), None),
            "continuous": (dict(mesh="lod", lod=LodConfig(roots=4, tess=8).with_policy("continuous", 4.0)), None),
            "grid": ({}, None),
            "cdlod": ({}, scheme_source("cdlod", hm, 800.0, cache=cache)),
            "clipmaps": ({}, scheme_source("clipmaps", hm, 31, cache=cache)),
            "chunked": ({}, scheme_source("chunked", hm, 2.0, cache=cache)),
            "delatin": ({}, PeerSource(delatin_mesh(hm, 2.0), hm, cache=cache))}


def test_every_family_counts_its_draws_the_same_for_any_thread_count(small):
    hm, cams = small
    for name, (kw, src) in _families(hm).items():
        got = []
        for threads in (1, 2, 3, 8):
            try:
                set_threads(threads)
                got.append([render(Scene(hm, camera=c, outputs=("depth", "counters"), **kw), source=src)
                            .report.counters for c in cams])
            finally:
                set_threads(None)
        assert all(g == got[0] for g in got), name
        c = got[0][1]
        assert list(c) == list(PIPELINE_COUNTERS), name
        assert c["primitives_generated"] == c["clipping_input_primitives"] > 0
        assert c["samples_passed"] >= c["pixels_covered"] > 0
        assert c["fragment_shader_invocations"] >= c["samples_covered"]  # helper lanes: whole 2x2 quads
        assert 0 < c["quad_efficiency"] <= 1 and c["overdraw"] >= 1
        if kw.get("mesh") == "lod":
            assert c["draw_calls"] == 1 and c["tess_control_shader_patches"] * 4 == c["vertices_submitted"]
        else:
            assert c["tess_control_shader_patches"] == 0 and c["vertices_submitted"] == 3 * c["primitives_submitted"]
            assert c["vertex_shader_invocations_llvmpipe"] >= c["vertex_shader_invocations"] > 0


def test_a_scene_that_asks_for_no_counters_counts_nothing(small, monkeypatch):
    hm, cams = small

    def boom(*a, **k):
        raise AssertionError("counted without being asked")

    monkeypatch.setattr(pipeline, "indexed_draw_counters", boom)
    monkeypatch.setattr(raster, "raster_counters", boom)
    for name, (kw, src) in _families(hm).items():
        f = render(Scene(hm, camera=cams[0], outputs=("depth", "error"), **kw), source=src)
        assert f.report.counters is None, name


def test_counters_are_in_report_json_and_the_table(small, tmp_path):
    hm, cams = small
    f = render(Scene(hm, camera=cams[1], mesh="lod", lod=LodConfig(roots=4, tess=8), outputs=("depth", "counters")))
    f.save(tmp_path)
    saved = json.loads((tmp_path / "report.json").read_text())["counters"]
    assert saved == {k: v for k, v in f.report.counters.items()}
    assert "samples_passed=" in f.report.table()
    # the tessellator's counters are the draw's: one invocation per domain point, no point shared
    assert f.report.counters["tess_evaluation_shader_invocations"] == int(np.asarray(f.report.stage("mesh")
                                                                                      .counters["vertices"]))
