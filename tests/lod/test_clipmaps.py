"""Geometry clipmaps (terrainwarp.lod.clipmaps): rings centred on the snapped viewer, the transition blend reaches
the coarse level exactly at each level's outer border, crack-free, exact at the finest setting, deterministic."""

import numpy as np
import pytest
from scheme_checks import (
    assert_crack_free,
    assert_fills_view,
    digest_over_threads,
    finest_error,
    ground_path,
    small_terrain,
    top_down,
)

from terrainwarp import Heightmap
from terrainwarp.lod.clipmaps import Clipmap
from terrainwarp.rendering.sources import ClipmapSource, scheme_source

N = 31


@pytest.fixture(scope="module")
def hm():
    return small_terrain()


@pytest.fixture(scope="module")
def clip(hm):
    return Clipmap(hm, N)


def test_rings_are_centred_on_the_snapped_viewer(hm, clip):
    m = (N - 1) // 2
    for cam in ground_path(hm):
        sel = clip.select(cam)
        mesh = clip.mesh(cam, sel)
        assert sel.stats["levels_drawn"] == clip.levels and sel.level[0] == 0
        world = mesh.world_positions()
        for k, (o, s) in enumerate(zip(sel.origin.astype(np.float64), sel.spacing.astype(np.float64))):
            assert (o % (2 * s) == 0).all(), "each level moves in steps of twice its spacing"
            centre = o + m * s
            assert (np.abs(centre - np.array(sel.viewer)) <= s).all(), "centred on the viewer, within a spacing"
            # the level's lattice, clamped to the terrain: its vertices span exactly [origin, origin + (n-1) s]
            mine = world[mesh.patch_id == k]
            lo = np.clip(o, 0, np.array(hm.shape[::-1]) - 1) * (hm.dx, hm.dz)
            hi = np.clip(o + (N - 1) * s, 0, np.array(hm.shape[::-1]) - 1) * (hm.dx, hm.dz)
            assert np.allclose([mine[:, 0].min(), mine[:, 2].min()], lo, atol=1e-3)
            assert np.allclose([mine[:, 0].max(), mine[:, 2].max()], hi, atol=1e-3)
            if k:  # the hole is the finer level's square, in this level's quads
                a0, a1, b0, b1 = sel.hole[k]
                assert a1 - a0 == b1 - b0 == m
                assert np.array_equal(o + np.array([a0, b0]) * s, sel.origin[k - 1])


def _lattice(mesh, k):
    """Level k's vertices as an (n, n, 3) float32 array of camera-relative positions (row b, column a)."""
    return mesh.positions[mesh.patch_id == k].reshape(N, N, 3)


def test_transition_reaches_the_coarse_level_exactly_at_the_outer_border(hm, clip):
    cam = ground_path(hm)[1]
    sel = clip.select(cam)
    mesh = clip.mesh(cam, sel)
    m = (N - 1) // 2
    checked = 0
    for k in range(len(sel.level) - 1):
        fine, coarse = _lattice(mesh, k), _lattice(mesh, k + 1)
        s = float(sel.spacing[k])
        off = ((sel.origin[k] - sel.origin[k + 1]) / (2 * s)).astype(int)  # fine (0, 0) in coarse lattice units
        border = [fine[0, :], fine[-1, :], fine[:, 0], fine[:, -1]]
        coarse_line = [coarse[off[1], off[0]:off[0] + m + 1], coarse[off[1] + m, off[0]:off[0] + m + 1],
                       coarse[off[1]:off[1] + m + 1, off[0]], coarse[off[1]:off[1] + m + 1, off[0] + m]]
        for f, c in zip(border, coarse_line):
            # even vertices are the coarse level's vertices, bit for bit (x, height, z)
            assert np.array_equal(f[::2], c)
            # odd vertices lie on the coarse edge between them: its height (the linear interpolation of the coarse
            # edge, within float32 rounding of the world heights it was interpolated from)
            mid = 0.5 * (c[:-1, 1].astype(np.float64) + c[1:, 1].astype(np.float64))
            ulp = np.spacing(np.abs(f[1::2, 1] + np.float32(cam.position[1]))).astype(np.float64)
            inside = (f[1::2, 0] != f[:-2:2, 0]) | (f[1::2, 2] != f[:-2:2, 2])  # not collapsed by clamping
            assert (np.abs(f[1::2, 1] - mid)[inside] <= 2 * ulp[inside]).all()
            checked += int(inside.sum())
    assert checked > 50
    # and near the viewer (alpha = 0) the finest level is the heightmap's samples exactly
    fine = _lattice(mesh, 0)
    o = sel.origin[0].astype(int)
    centre = fine[m - 2:m + 3, m - 2:m + 3, 1] + np.float32(cam.position[1])
    want = hm.heights[o[1] + m - 2:o[1] + m + 3, o[0] + m - 2:o[0] + m + 3]
    assert np.allclose(centre, want, atol=1e-3)


def test_crack_free_on_a_ground_path_and_from_above(hm, clip):
    src = ClipmapSource(scheme=clip)
    for cam in ground_path(hm):
        mesh, _ = src.mesh_for(cam)
        assert mesh.n_triangles > 0
        assert_crack_free(hm, cam, src, 3.0, "clipmaps")
    cam = top_down(hm, 240.0)
    assert len(np.unique(src.mesh_for(cam)[0].level)) >= 2
    assert_fills_view(hm, cam, src, "clipmaps")


def test_stitches_along_every_inner_border(hm, clip):
    cam = ground_path(hm)[0]
    sel = clip.select(cam)
    tri = clip.mesh(cam, sel).triangles
    n_stitch = 2 * (N - 1) * int(sel.coarser.sum())
    stitches = tri[-n_stitch:]
    # each stitch is three consecutive border vertices of one level: zero area in exact arithmetic
    assert n_stitch > 0 and (np.diff(stitches, axis=1) > 0).all()


def test_finest_setting_scores_zero(hm, device):
    src = scheme_source("clipmaps", hm, 511, device=device)
    assert src.scheme.n == 511
    for cam in ground_path(hm, 2):
        assert finest_error(hm, cam, src, device=device) == 0.0


def test_high_viewer_drops_fine_levels(hm, device):
    clip = Clipmap(hm, N, device=device)
    cam = top_down(hm, 2000.0)
    assert clip.finest_active(cam) > 0
    assert Clipmap(hm, N, active_height_ratio=None, device=device).finest_active(cam) == 0


def test_deterministic(hm, device):
    """Two runs, and any thread count, draw the same bytes."""

    def make():
        return ClipmapSource(scheme=Clipmap(hm, N, device=device))

    assert len(digest_over_threads(make, ground_path(hm), (1, 1, 3))) == 1


@pytest.mark.parametrize("kw, msg", [({"n": 14}, "n"), ({"n": 13}, "n"), ({"transition": 0.0}, "transition"),
                                     ({"levels": 0}, "levels")])
def test_bad_parameters(hm, kw, msg):
    with pytest.raises(ValueError, match=msg):
        Clipmap(hm, **{"n": N, **kw})


def test_no_data_refused():
    a = np.zeros((33, 33), np.float32)
    a[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        Clipmap(Heightmap.from_array(a), N)
