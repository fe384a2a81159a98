"""The stability suite (terrainwarp.experiments.stability, terrainwarp.experiments.extreme): every extreme case
through every stage with no unexplained failure, deterministic hashes, the float32 remedies measured against naive
float32,
NaN holes, exact zeros on a flat plane, tile-by-tile fBm, and a stage that raises reported as a failed row.
Bad input across the API and the command line is tested in the packages it reaches (tests/core, tests/io,
tests/test_cli*.py)."""

from __future__ import annotations

import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp.experiments.extreme import CASES, TESS_FACTORS, ExtremeCase, case_names, get_case
from terrainwarp.experiments.stability import (
    EXPLANATIONS,
    FAIL,
    PASS,
    RAISED,
    STAGES,
    run_case,
    run_suite,
    stage_hashes,
    write_stability_md,
)
from terrainwarp.kernels.displacement import drop_nonfinite_triangles, grid_mesh
from terrainwarp.kernels.noise import fbm
from terrainwarp.rendering import pipeline
from terrainwarp.rendering.watertight import check_watertight, lod_boundary

# the fit stage's cases: the degenerate grids (grid_1x4097 read a camera that sees no sample as NaN), flat,
# spikes, NaN holes; they share the relaxed model's programs (padded sizes), compiled once per machine
FIT_CASES = ["everest", "cam_on_surface", "nan_holes", "grid_1x1", "grid_2x2", "grid_3x3", "grid_1x4097", "flat",
             "spikes"]


@pytest.fixture(scope="module")
def suite_rows():
    rows = run_suite(17, stages=tuple(s for s in STAGES if s != "fit"))
    return rows + run_suite(17, cases=FIT_CASES, stages=("fit",))


def _row(rows, case, stage):
    return next(r for r in rows if r.case == case and r.stage == stage)


# -- the catalogue -------------------------------------------------------------------------------
def test_catalogue_covers_the_issue():
    names = set(CASES)
    for n in ("cliff", "spikes", "flat", "relief_1e-06", "relief_1e+06", "spacing_0.001", "spacing_1e+04", "everest",
              "far_1e+05", "far_1e+07", "cam_on_surface", "cam_in_patch_bounds", "cam_below", "cam_straight_down",
              "cam_grazing", "cam_near_far", "cam_fov_0.1", "cam_fov_179", "nan_holes", "dtype_int16",
              "dtype_uint16", "dtype_float16", "dtype_float64", "grid_1x1", "grid_2x2", "grid_3x3", "grid_1x4097"):
        assert n in names
    assert sorted(str(c.factor) for c in CASES.values() if c.group == "tess") == sorted(str(f) for f in TESS_FACTORS)
    assert all(c.catches for c in CASES.values())
    sc = get_case("cam_fov_179").build(9)
    assert sc.camera.fov_y_deg == 179.0
    assert get_case("cam_near_far").build(9).camera.near == 1e-4
    assert get_case("far_1e+07").build(9).heightmap.origin == (1e7, 1e7)
    assert get_case("dtype_float16").build(9).heightmap.meta["source_dtype"] == "float16"
    assert get_case("grid_1x4097").build(9).heightmap.shape == (1, 4097)
    with pytest.raises(ValueError, match="name"):
        get_case("nope")
    with pytest.raises(ValueError, match="n:"):
        get_case("flat").build(1)


def test_suite_every_case_and_stage_no_unexplained_failure(suite_rows, tmp_path):
    cases = {r.case for r in suite_rows}
    assert cases == set(CASES)
    for name in case_names():
        stages = {r.stage for r in suite_rows if r.case == name}
        want = {"tessellate"} if CASES[name].group == "tess" else set(STAGES) - {"fit"}
        assert stages >= want, (name, stages)
    assert {r.status for r in suite_rows} <= {PASS, RAISED, FAIL}
    unexplained = [r for r in suite_rows if r.status == FAIL and not any(k in r.note for k in EXPLANATIONS)]
    assert not unexplained, unexplained
    # every non-tess terrain renders a finite grid frame: the raster and error stages pass everywhere
    assert all(r.status == PASS for r in suite_rows if r.stage in ("raster", "error", "normals", "curvature",
                                                                    "sampling", "select", "fit"))
    assert sorted(r.case for r in suite_rows if r.stage == "fit") == sorted(FIT_CASES)
    p = write_stability_md(suite_rows, tmp_path, n=17)
    text = p.read_text()
    assert "| everest | normals | pass |" in text and "## Summary" in text
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".")]  # no temporary left


def test_suite_is_deterministic(suite_rows):
    again = run_suite(17, cases=["everest", "nan_holes", "cam_grazing", "tess_63.99", "grid_3x3"])
    h0, h1 = stage_hashes(suite_rows), stage_hashes(again)
    assert h1 and all(h0[k] == v for k, v in h1.items())


def test_suite_rejects_unknown_names():
    with pytest.raises(ValueError, match="cases"):
        run_suite(9, cases=["everest", "bogus"])
    with pytest.raises(ValueError, match="stages"):
        run_suite(9, stages=("sampling", "shade"))


# -- the float32 remedies, measured ----------------------------------------------------------------
def test_remedies_beat_naive_float32(suite_rows):
    def num(s):
        return float(s.split()[0])

    # Everest base, millimetre relief: pairwise differences keep the normals; a naive convolution does not
    r = _row(suite_rows, "everest", "normals")
    assert num(r.error) < 1e-6 and num(r.naive) > 1e-3
    r = _row(suite_rows, "everest", "curvature")
    assert num(r.error) < 1e-6 and num(r.naive) > 0.1
    # 10,000 km from the origin: camera-relative float32 positions are exact to < 1 mm, absolute ones are not
    r = _row(suite_rows, "far_1e+07", "raster")
    assert num(r.error) < 1e-3 and num(r.naive) > 0.05
    assert "px changed" in r.naive
    # sampling relative to the cell's first sample beats weighting absolute heights on the Everest base
    r = _row(suite_rows, "everest", "sampling")
    assert num(r.error) < num(r.naive)


# -- exact zeros, NaN holes -------------------------------------------------------------------------
def test_flat_plane_zero_curvature_and_exactly_zero_error():
    hm = tw.Heightmap.from_array(np.zeros((17, 17)), 1.0)
    assert np.all(tw.compute_curvature(hm, "three_vertex") == 0)
    assert np.all(tw.compute_curvature(hm, "three_normal") == 0)
    # an eye whose coordinates float32 represents exactly: the camera-relative heights are exact, error 0
    cam = tw.Camera(position=(8.0, 32.0, 40.0), target=(8.0, 0.0, 8.0), width=64, height=48, near=0.5, far=500.0)
    fr = tw.render(tw.Scene(hm, camera=cam, outputs=("error",)))
    assert fr.error.covered > 200 and fr.error.max_px == 0.0


def _holes():
    h = 0.1 * np.add.outer(np.arange(33.0), np.arange(33.0))
    h[10:22, 10:22] = np.nan
    return tw.Heightmap.from_array(h, 1.0, allow_nan=True)


def test_nan_holes_no_triangle_touches_a_hole_and_render_as_background():
    hm = _holes()
    pos, uv, tri = grid_mesh(hm.heights, 1.0, 1.0, (0.0, 0.0, 0.0))
    assert np.all(np.isfinite(pos))
    assert not np.isnan(hm.heights.reshape(-1)[tri]).any()
    ok = np.isfinite(hm.heights)
    t0 = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:]  # (i,j), (i+1,j), (i,j+1)
    t1 = ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]  # (i,j+1), (i+1,j), (i+1,j+1)
    assert len(tri) == int(t0.sum() + t1.sum()) < 2 * 32 * 32
    cam = tw.Camera(position=(16.0, 60.0, 16.001), target=(16.0, 0.0, 16.0), up=(0.0, 0.0, -1.0), width=64,
                    height=64, near=1.0, far=1000.0)
    fr = tw.render(tw.Scene(hm, camera=cam, outputs=("image", "depth", "normals", "error")))
    assert fr.triangle_id[32, 32] == -1 and fr.depth[32, 32] == 1.0  # the hole's centre is background
    assert (fr.triangle_id >= 0).sum() > 500
    assert np.all(np.isfinite(fr.normals)) and np.all(np.isfinite(fr.depth))
    e = fr.error
    assert np.isfinite(e.max_px) and e.max_px >= 0 and e.covered == (fr.triangle_id >= 0).sum()
    # normals and curvature do not spread NaN
    assert np.all(np.isfinite(tw.compute_normals(hm, "sobel")))
    k = tw.compute_curvature(hm, "three_normal")
    assert np.array_equal(np.isnan(k).any(-1), np.isnan(hm.heights))


def test_lod_frame_with_holes_drops_triangles_touching_them():
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [np.nan, 0, 1], [1, 0, 1]], np.float32)
    tri = np.array([[0, 2, 1], [1, 2, 4], [2, 3, 4], [0, 3, 1]], np.int32)
    p, t = drop_nonfinite_triangles(pos, tri)
    assert np.array_equal(t, tri[:2]) and np.all(np.isfinite(p)) and np.array_equal(p[:3], pos[:3])
    hm = _holes()
    cam = tw.Camera(position=(16.0, 60.0, 16.001), target=(16.0, 0.0, 16.0), up=(0.0, 0.0, -1.0), width=64,
                    height=64, near=1.0, far=1000.0)
    fr = tw.render(tw.Scene(hm, camera=cam, outputs=("image", "depth", "error", "mesh"), mesh="lod",
                            lod={"roots": 4, "tess": 8}))
    assert np.all(np.isfinite(fr.mesh.positions)) and fr.triangle_id[32, 32] == -1
    assert np.all(np.isfinite(fr.depth)) and np.isfinite(fr.error.max_px) and fr.error.max_px >= 0
    # the dropped triangles are exactly those whose vertices sampled a NaN height (the hole stays a hole)

    assert check_watertight(fr.mesh, allowed=lod_boundary(fr.patches, hm, fr.mesh.eye)).n_open_edges == 0


def test_nan_free_grid_mesh_unchanged_by_hole_path():
    h = np.random.default_rng(1).random((9, 11)).astype(np.float32)
    _, _, t0 = grid_mesh(h, 1.0, 1.0, (0.0, 0.0, 0.0))
    h2 = h.copy()
    h2[-1, -1] = np.nan  # only the last cell's upper triangle goes
    _, _, t1 = grid_mesh(h2, 1.0, 1.0, (0.0, 0.0, 0.0))
    assert len(t0) == 2 * 8 * 10 and np.array_equal(t1, t0[:-1])


# -- determinism across tile sizes ------------------------------------------------------------------
def test_fbm_tiles_equal_the_whole():
    whole = fbm(96, 80, seed=3, base_frequency=1 / 32)
    for tile in (16, 37):
        rows = [np.concatenate([fbm(min(tile, 96 - r), min(tile, 80 - c), seed=3, base_frequency=1 / 32, row0=r,
                                    col0=c) for c in range(0, 80, tile)], 1) for r in range(0, 96, tile)]
        assert np.array_equal(np.concatenate(rows, 0), whole)


def test_an_exception_inside_a_stage_is_a_fail_row_naming_where(monkeypatch):
    """A regression anywhere in a stage (here: the pipeline's select stage raising) is a FAIL row with the
    exception's type and the file:line it came from, never a pass."""
    def broken_select(run, rec):
        raise KeyError("boom")

    monkeypatch.setitem(pipeline._STAGES, "select", broken_select)
    rows = run_case(CASES["flat"], 9, stages=("tessellate", "error", "normals"))
    by = {r.stage: r for r in rows}
    for st in ("tessellate", "error"):  # both draw a LOD frame
        r = by[st]
        assert r.status == FAIL, r
        assert "KeyError" in r.note and f"stage {st}" in r.note and "broken_select" in r.note
        assert "test_stability.py:" in r.note
    assert by["normals"].status == PASS  # the other stages are unaffected

    # a ValueError/TypeError that does not name an argument is a failure too, not a clear error
    def numpy_like(run, rec):
        raise ValueError("operands could not be broadcast together")

    monkeypatch.setitem(pipeline._STAGES, "select", numpy_like)
    r = run_case(CASES["flat"], 9, stages=("error",))[0]
    assert r.status == FAIL and "ValueError" in r.note and "test_stability.py:" in r.note


def test_run_case_records_build_errors():
    def bad(n):
        return tw.Scene(tw.Heightmap.from_array(np.ones((n, n)), -1.0))

    rows = run_case(ExtremeCase("bad", "data", "negative spacing", bad), 5)
    assert len(rows) == 1 and rows[0].status == RAISED and rows[0].note.startswith("dx")
