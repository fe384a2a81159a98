"""The fit's probes measured at the samples the cameras see (the same numbers as measuring the whole grid), the
continuous ladder's rungs placed at those samples (the same surfaces as tessellating every patch), the hard model's
sample cap, and which setting a fit answers on a cost plateau."""

import dataclasses
import math

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, LodConfig, Scene, fit_lod
from terrainwarp.camera import relative_origin
from terrainwarp.fit import apply
from terrainwarp.fit import ladder as ladder_mod
from terrainwarp.fit.exact import Evaluation, Exact, prepared, references_for
from terrainwarp.fit.families import _subset, _touching, problem
from terrainwarp.fit.probe import FLOOR_PX, probe_cameras, sight, surfaces_of
from terrainwarp.fit.relaxed import hard_percentile
from terrainwarp.fit.relaxed_continuous import continuous_patches
from terrainwarp.kernels import sample_error as k
from terrainwarp.lod.quadtree import Terrain, uniform_patches
from terrainwarp.measure.sample_error import surface_heights
from terrainwarp.rendering.pipeline import render


@pytest.fixture(scope="module")
def scene():
    hm = Heightmap.fbm(129, seed=4, dx=20.0, max_height=600.0, feature_size=48.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 128, 96), lod=LodConfig(roots=4, tess=8))
    cams = sc.camera_path(3)
    return sc, cams, references_for(sc, cams)


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.nan_to_num(np.asarray(a, np.float64), nan=-1e300)).view(np.int64)


def test_probes_at_the_samples_seen_are_the_whole_grid_measured(scene):
    sc, cams, refs = scene
    hm = sc.heightmap
    t = Terrain.prepare(hm, roots=4, tess=8)
    base = apply(sc, "sse", {"tolerance_px": 2.0})
    at = sight(hm, cams, refs)
    assert 0 < len(at.rows) < hm.heights.size and all(len(s) <= len(at.rows) for s in at.seen)
    levels = (0, t.depth - 1)
    whole = [render(base.with_(camera=cams[0], outputs=("mesh",)), t, patches=uniform_patches(t, L)).mesh
             for L in levels]
    culled = [render(base.with_(camera=cams[0], outputs=("mesh",)), t, patches=_touching(uniform_patches(t, L), at)
                     ).mesh for L in levels]
    assert culled[1].n_triangles < whole[1].n_triangles  # the patches no camera sees are left out
    got = probe_cameras(hm, cams, refs, [*surfaces_of(hm, culled, at), None], at)
    for cam, ref, probe in zip(cams, refs, got, strict=True):  # the probe as measured over the whole grid
        rel = relative_origin(hm.origin, cam.position)
        mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)
        errs, ok = [], None
        for y in [*(surface_heights(hm, m) for m in whole), np.asarray(hm.heights, np.float64)]:
            e, st, _ = k.sample_displacement(hm.heights, None, y - float(cam.position[1]), ref.depth, rel,
                                             (hm.dx, hm.dz), mvp, cam.near, cam.far)
            ok = (st == k.VISIBLE) if ok is None else ok & (st == k.VISIBLE)
            errs.append(e.copy())
        rows, cols = np.nonzero(ok)
        assert probe.visible == len(rows) > 0
        np.testing.assert_array_equal(probe.rows, rows)
        np.testing.assert_array_equal(probe.cols, cols)
        want = np.stack([np.clip(e[rows, cols], FLOOR_PX, 1e6) for e in errs]).astype(np.float32)
        assert np.array_equal(probe.err.view(np.int32), want.view(np.int32))


def test_ladder_rungs_at_the_samples_are_the_tessellated_rungs_bit_for_bit(monkeypatch):
    # 99 x 115 samples: patches of 4 cells reach past the grid on two sides (their points clamp there)
    hm = Heightmap.fbm(99, 115, seed=7, dx=15.0, max_height=400.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 160, 90), lod=LodConfig())
    cams = sc.camera_path(3)
    refs = references_for(sc, cams)
    at = sight(hm, cams, refs)
    base = apply(sc, "continuous", {"target_px": 3.0, "level": 3})
    t = prepared({}, hm, base.lod.roots, base.lod.tess, "cpu")
    level = min(3, t.depth)
    seen = np.unique(np.concatenate([p.key for p in continuous_patches(t, cams, level)]))

    def rung(f: float):
        pl = uniform_patches(t, level, f)
        return render(base.with_(camera=cams[0], outputs=("mesh",)), t,
                      patches=_touching(_subset(pl, np.isin(pl.key, seen)), at)).mesh

    pl = uniform_patches(t, level)
    pl = _touching(_subset(pl, np.isin(pl.key, seen)), at)
    assert ladder_mod._level(hm, pl, cams[0].position, "fractional_odd", "bilinear").border.any()
    factors = np.array([1.0, 2.986, 7.43, 23.0, 64.0])
    want = surfaces_of(hm, [rung(float(f)) for f in factors], at)
    monkeypatch.setattr(ladder_mod, "MESH_BELOW", 0)  # every rung placed at the samples
    got = ladder_mod.ladder_surfaces(hm, pl, factors, at, cams[0].position, base.lod.spacing, base.lod.filter,
                                     lambda f: pytest.fail("a rung was tessellated"))
    for f, a, b in zip(factors, want, got, strict=True):
        assert np.isfinite(a).sum() > 0.5 * len(a)
        assert np.array_equal(_bits(a), _bits(b)), f"rung {f}: {np.sum(_bits(a) != _bits(b))} samples differ"


def test_the_hard_model_reads_a_fixed_subset_of_at_most_hard_samples(scene):
    sc, cams, refs = scene
    prob = problem(sc, "sse", ["level_log_scale_1"], cams, refs, None)
    m = prob.cands[0].model
    n = min(len(p.rows) for p in m.probes) // 3
    capped = dataclasses.replace(m, hard_samples=n)
    subset = dataclasses.replace(m, probes=[p.subset(n) for p in m.probes])
    assert capped._hard_data[0].shape[2] == n < m._hard_data[0].shape[2]
    for v in ({"tolerance_px": 1.5, "level_log_scale_1": 0.3}, {"tolerance_px": 4.0, "level_log_scale_1": -0.5}):
        a, b, full = capped.predict(v), subset.predict(v), m.predict(v)
        np.testing.assert_array_equal(a.p99_px, b.p99_px)
        np.testing.assert_array_equal(a.cost, full.cost)  # the cost is the selection's, whatever the samples
        assert not np.array_equal(a.p99_px, full.p99_px)


def test_of_equal_costs_the_lower_error_then_the_coarser_setting_is_the_best(scene):
    sc, cams, refs = scene
    prob = problem(sc, "sse", None, cams, refs, None, models=False)
    ex = Exact(prob.make, prob.key, cams, refs, 2.0, coarseness=prob.coarseness)

    def ev(tol: float, p99: float, cost: int) -> Evaluation:
        return Evaluation({"tolerance_px": tol}, [p99] * 3, [p99] * 3, [cost] * 3, [1.0] * 3)

    for e in (ev(1.0, 1.5, 100), ev(3.0, 1.5, 100), ev(2.0, 1.2, 100), ev(5.0, 1.9, 120)):
        ex.evals[prob.key(e.values)] = e
    assert ex.best().values == {"tolerance_px": 2.0}  # the lowest error of the cheapest
    ex.evals.pop(prob.key({"tolerance_px": 2.0}))
    assert ex.best().values == {"tolerance_px": 3.0}  # the same frames' cost and error: the coarser
    assert prob.coarseness({"tolerance_px": 3.0}) > prob.coarseness({"tolerance_px": 1.0})


def test_a_fit_on_a_cost_plateau_tries_the_range_end_and_stops():
    hm = Heightmap.fbm(129, seed=3, dx=30.0, max_height=300.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 320, 180), lod=LodConfig())
    r = fit_lod(sc, 1000.0, "chunked", sc.camera_path(4))
    tries = [h for h in r.history if h["stage"] == "bracket"]
    main = r.knobs[0]
    assert r.met and r.values[main] == pytest.approx(max(h["values"][main] for h in tries))
    assert tries[-1]["values"][main] == pytest.approx(64.0)  # the knob's coarse end, tried after the plateau
    assert len({round(h["cost"], 6) for h in tries[-2:]}) == 1 and len(tries) <= 6
    assert r.binding["kind"] == "knob_limit" and math.isfinite(r.validated.cost)


def test_the_hard_percentile_is_numpys_to_the_bit():
    rng = np.random.default_rng(1)
    for trial in range(400):
        n = int(rng.integers(1, 4000))
        dtype = np.float32 if trial % 2 else np.float64
        v = (rng.lognormal(0.0, rng.uniform(0.1, 4.0), n) * 10 ** rng.uniform(-3, 3)).astype(dtype)
        if trial % 5 == 0:
            v = np.round(v, 1).astype(dtype)  # ties
        v[rng.random(n) < 0.01] = np.nan  # left out, as numpy's percentile of the finite values
        want = float(np.percentile(v[np.isfinite(v)], 99)) if np.isfinite(v).any() else 0.0
        assert hard_percentile(v) == want
    assert hard_percentile(np.array([np.nan])) == 0.0 and hard_percentile(np.array([3.5], np.float32)) == 3.5


def test_the_quadtree_hard_model_reads_leaf_levels_down_the_tree_as_level_by_level(scene):
    sc, cams, refs = scene
    m = problem(sc, "sse", ["level_log_scale_1"], cams, refs, None).cands[0].model
    by_level = dataclasses.replace(m)
    by_level.__dict__["_lines"] = [None] * len(cams)
    assert any(line is not None for line in m._lines)
    for v in ({"tolerance_px": 0.7, "level_log_scale_1": 1.0}, {"tolerance_px": 3.0, "level_log_scale_1": -1.5}):
        np.testing.assert_array_equal(m.predict(v).p99_px, by_level.predict(v).p99_px)
