"""CDLOD (terrainwarp.lod.cdlod): crack-free, continuous across range borders while the camera moves, exact at
its finest setting, deterministic; and the DX11 sample's edge factor against the continuous policy's."""

import math

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
from terrainwarp.camera import Camera
from terrainwarp.lod.cdlod import Cdlod, cdlod_ranges
from terrainwarp.lod.policies import dx11_edge_pixels, edge_pixels
from terrainwarp.measure.sample_error import surface_heights
from terrainwarp.rendering.sources import CdlodSource


@pytest.fixture(scope="module")
def hm():
    return small_terrain()


@pytest.fixture(scope="module")
def cdlod(hm):
    c = Cdlod(hm, 1.0, grid=8)
    c.first_range = math.ceil(c.min_first_range)
    return c


def test_ranges_follow_the_reference():
    rng, start, end = cdlod_ranges(100.0, 2.0, 0.7, 4)
    assert rng[:3].tolist() == [100.0, 300.0, 700.0] and math.isinf(rng[3])
    assert start[0] == pytest.approx(70.0) and start[1] == pytest.approx(70.0 + 230.0 * 0.7)
    assert end[0] == pytest.approx(100.0 - 0.01 * 30.0)  # morph end pulled 1% toward its start
    assert math.isinf(start[3])


def test_crack_free_on_a_ground_path_and_from_above(hm, cdlod):
    src = CdlodSource(scheme=cdlod)
    lods = set()
    for cam in ground_path(hm):
        sel = cdlod.select(cam)
        lods |= set(sel.lod.tolist())
        assert sel.stats["too_small"] == 0
        assert_crack_free(hm, cam, src, 3.0, "cdlod")
    assert len(lods) >= 3
    cam = top_down(hm, 240.0)
    assert len(set(cdlod.select(cam).lod.tolist())) >= 2
    assert_fills_view(hm, cam, src, "cdlod")


def _lod_map(sel, shape):
    """The CDLOD level drawn over each sample (-1 where nothing is)."""
    out = np.full(shape, -1)
    for (x, z), size, lod in zip(sel.origin.astype(int), sel.size.astype(int), sel.lod):
        out[z:z + size, x:x + size] = lod
    return out


def _switches(cdlod, cams):
    """Camera pairs a hair apart (1e-4 m) across which the selection changes."""
    out = []
    for a, b in zip(cams, cams[1:]):
        sa, sb = cdlod.select(a), cdlod.select(b)
        if np.array_equal(sa.lod, sb.lod) and np.array_equal(sa.origin, sb.origin):
            continue
        pa, pb = np.array(a.position), np.array(b.position)
        for _ in range(40):  # bisect the switch down to 1e-4 m
            mid = Camera(position=tuple(0.5 * (pa + pb)), target=a.target, width=a.width, height=a.height)
            sm = cdlod.select(mid)
            if np.array_equal(sm.lod, sa.lod) and np.array_equal(sm.origin, sa.origin):
                pa = np.array(mid.position)
            else:
                pb = np.array(mid.position)
            if np.linalg.norm(pb - pa) < 1e-4:
                break
        out.append((a.with_(position=tuple(pa)), a.with_(position=tuple(pb))))
    return out


def test_vertex_positions_are_continuous_across_range_borders(hm, cdlod):
    (x0, z0), (x1, z1) = hm.bounds_xz
    y = float(hm.heights.max()) + 60.0
    target = (x1 + 500.0, 0.0, z0 + 0.3 * (z1 - z0))
    cams = [Camera(position=(x0 + t * (x1 - x0), y, z0 + 0.5 * (z1 - z0)), target=target, width=96, height=64)
            for t in np.linspace(0.05, 0.6, 24)]
    pairs = _switches(cdlod, cams)
    assert len(pairs) >= 3, "the path must cross range borders"
    ulp = float(np.spacing(np.float32(np.abs(hm.heights).max() + 60.0)))
    switched = 0
    for a, b in pairs:
        sa, sb = cdlod.select(a), cdlod.select(b)
        la, lb = _lod_map(sa, hm.shape), _lod_map(sb, hm.shape)
        switched += bool(((la != lb) & (la >= 0) & (lb >= 0)).any())  # a range border, not the frustum
        ha = surface_heights(hm, cdlod.mesh(a, sa))
        hb = surface_heights(hm, cdlod.mesh(b, sb))
        both = np.isfinite(ha) & np.isfinite(hb)
        assert both.mean() > 0.2
        # the eye moved by < 1e-4 m: the morph moved by far less than a float32 ulp of the heights
        jump = np.abs(ha - hb)[both].max()
        assert jump <= 16 * ulp, f"surface jumped by {jump} m across a range border (float32 ulp {ulp})"
    assert switched >= 2, "the path must cross range borders"


def test_finest_setting_scores_zero(hm, device):
    src = CdlodSource(scheme=Cdlod(hm, 1e9, grid=8, device=device))
    for cam in ground_path(hm, 2):
        assert finest_error(hm, cam, src, device=device) == 0.0


def test_deterministic(hm, cdlod, device):
    """Two runs, and any thread count, draw the same bytes."""

    def make():
        return CdlodSource(scheme=Cdlod(hm, cdlod.first_range, grid=8, device=device))

    assert len(digest_over_threads(make, ground_path(hm), (1, 1, 3))) == 1


@pytest.mark.parametrize("kw, msg", [({"first_range": 0.0}, "first_range"), ({"ratio": 1.0}, "ratio"),
                                     ({"morph_start_ratio": 1.0}, "morph_start_ratio"), ({"grid": 7}, "grid"),
                                     ({"levels": 0}, "levels")])
def test_bad_parameters(hm, kw, msg):
    args = {"first_range": 100.0, **kw}
    with pytest.raises(ValueError, match=msg):
        Cdlod(hm, **args)


def test_dx11_edge_factor_maps_to_the_continuous_policy():
    """Item 4: on a level terrain, for a patch whose edge midpoint lies on the view axis, the DX11 sample's size
    is twice ours (its NDC-to-pixel scale skips the halving); off axis it grows by d / z_view."""
    hm = Heightmap.from_array(np.zeros((65, 65), np.float32), dx=10.0)
    cam = Camera(position=(320.0, 0.0, 900.0), target=(320.0, 0.0, 0.0), width=160, height=90)
    origin = np.array([[270.0, 100.0], [0.0, 100.0]])
    size = np.array([[100.0, 100.0], [100.0, 100.0]])
    ours = edge_pixels(hm, cam.position, cam.focal_px, origin, size)
    theirs = dx11_edge_pixels(hm, cam, origin, size)
    # edge v=0 of patch 0 is centred on the view axis (x = 320): exactly twice ours
    assert theirs[0, 1] == pytest.approx(2.0 * ours[0, 1], rel=1e-9)
    eye = np.array(cam.position)
    mid = np.array([50.0, 0.0, 100.0])  # edge v=0 of patch 1, off axis
    d = np.linalg.norm(mid - eye)
    z_view = float(np.dot(mid - eye, cam.forward))
    assert theirs[1, 1] == pytest.approx(2.0 * ours[1, 1] * d / z_view, rel=1e-9)
    assert theirs[1, 1] > 2.0 * ours[1, 1]
