"""Shading modes: hillshade, level / patch colours, wireframe overlay, splat-map multi-texturing, cracks."""

from __future__ import annotations

import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp.kernels.normals import sobel_normals
from terrainwarp.kernels.raster import clip_coordinates, rasterize
from terrainwarp.kernels.shading import (
    CRACK_COLOUR,
    DEFAULT_SPLAT_RULES,
    SplatRule,
    find_cracks,
    hillshade,
    shade,
    splat_map,
)

I4 = np.eye(4, dtype=np.float32)
UP = np.array([0.0, 1.0, 0.0], np.float32)


def quad_scene(w=64, h=48, gap=0.0):
    """Two quads side by side facing the camera (identity matrices, NDC = positions), split at x = 0;
    ``gap`` (NDC) opens a crack between them."""
    g = gap / 2
    pos = np.array([[-0.8, -0.7, 0], [-g, -0.7, 0], [-g, 0.7, 0], [-0.8, 0.7, 0],
                    [g, -0.7, 0], [0.8, -0.7, 0], [0.8, 0.7, 0], [g, 0.7, 0]], np.float32)
    tri = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
    f = rasterize(pos, tri, I4, I4, w, h)
    normals = np.tile([0.0, 0.0, 1.0], (8, 1)).astype(np.float32)
    return pos, tri, f, normals


def test_hillshade_background_is_sky_and_relief_changes_the_shade():
    pos, tri, f, normals = quad_scene()
    sky = (0.1, 0.2, 0.3)
    rgb, n = hillshade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], sky=sky)
    bg = f.triangle_id < 0
    assert np.allclose(rgb[bg], sky) and np.all(n[bg] == 0)
    tilted = normals.copy()
    tilted[4:] = [0.0, 1.0, 0.0]  # facing the sun (azimuth 315, elevation 45) much more
    rgb2, _ = hillshade(f.triangle_id, f.barycentrics, tri, tilted, pos[:, 1], sky=sky)
    right = f.triangle_id >= 2
    assert np.abs(rgb2[right] - rgb[right]).max() > 0.05
    assert np.array_equal(rgb2[f.triangle_id == 0], rgb[f.triangle_id == 0])


def test_level_and_patch_modes_colour_by_the_vertex_attribute():
    pos, tri, f, normals = quad_scene()
    level = np.array([0, 0, 0, 0, 3, 3, 3, 3], np.int32)
    rgb, _, c = shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], mode="level", level=level)
    assert c["mode"] == "level"
    left, right = rgb[f.triangle_id == 0], rgb[f.triangle_id == 2]
    # one colour per level (the same Lambert factor everywhere: normals are equal)
    assert np.ptp(left, axis=0).max() < 1e-6 and np.ptp(right, axis=0).max() < 1e-6
    assert np.abs(left[0] - right[0]).max() > 0.1
    rgb_p, _, _ = shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], mode="patch", patch_id=level)
    assert np.abs(rgb_p[f.triangle_id == 0][0] - rgb_p[f.triangle_id == 2][0]).max() > 0.02
    assert np.array_equal(rgb_p[f.triangle_id == 0][0], rgb_p[f.triangle_id == 1][0])  # same patch
    with pytest.raises(ValueError, match="level"):
        shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], mode="level")
    with pytest.raises(ValueError, match="mode"):
        shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], mode="toon")


def test_wireframe_draws_the_triangle_edges_only():
    w, h = 96, 72
    pos, tri, f, normals = quad_scene(w, h)
    clip = clip_coordinates(pos, I4, I4)
    rgb, _, c = shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], mode="wireframe", clip=clip,
                      wire_px=1.0)
    dark = np.all(rgb < 0.06, axis=-1)
    assert dark.sum() == c["edge_pixels"] > 0
    # edges: the two quad outlines and the two diagonals, ~1.5 px wide; interior far from edges is not dark
    ys, xs = np.nonzero(dark)
    assert np.all(f.triangle_id[ys, xs] >= 0)
    per_quad = 2 * (0.8 * w / 2 + 1.4 * h / 2) + np.hypot(0.8 * w / 2, 1.4 * h / 2)
    assert 0.8 * 2 * per_quad < dark.sum() < 2.5 * 2 * per_quad
    # the centroid of triangle (0, 2, 3), NDC (-0.533, 0.233): far from every edge
    cx, cy = (-0.8 / 3 * 2 + 1) * w / 2, (0.7 / 3 + 1) * h / 2
    assert f.triangle_id[h - 1 - int(cy), int(cx)] == 1 and not dark[h - 1 - int(cy), int(cx)]


def test_splat_map_rules_and_atlas_layout():
    hh, ww = 24, 32
    heights = np.tile(np.linspace(0.0, 1000.0, ww, dtype=np.float32), (hh, 1))
    normals = np.tile(UP, (hh, ww, 1))
    atlas, grid = splat_map(heights, normals)
    assert grid == 2 and atlas.shape == (2 * hh, 2 * ww, 4)  # 5 textures: a 2 x 2 atlas (deaconu2021)
    assert np.all(atlas[hh:] == 0)  # the bottom cells hold no textures
    assert np.all(atlas[:hh, ww:, 1:] == 0)  # texture 5 (cell 1) uses the red channel only
    grass, snow = atlas[:hh, :ww, 0], atlas[:hh, :ww, 3]
    assert grass[:, 0].min() == 1.0 and grass[:, -1].max() == 0.0
    assert snow[:, -1].min() == 1.0 and snow[:, 0].max() == 0.0
    rock = atlas[:hh, :ww, 2]
    assert rock.max() == 0.0  # flat: no rock
    steep = np.tile(np.array([0.0, 0.5, 0.866], np.float32), (hh, ww, 1))  # 60 degrees
    atlas2, _ = splat_map(heights, steep)
    assert atlas2[:hh, :ww, 2].min() == 1.0
    one, g1 = splat_map(heights, normals, rules=[SplatRule((1, 0, 0))])
    assert g1 == 1 and one.shape == (hh, ww, 4) and np.all(one[..., 0] == 1)
    nine, g9 = splat_map(heights, normals, rules=[SplatRule((1, 0, 0))] * 9)
    assert g9 == 2 and nine.shape == (2 * hh, 2 * ww, 4)
    with pytest.raises(ValueError, match="normals"):
        splat_map(heights, normals[:, :, :2])


def test_splat_shading_uses_the_texture_of_the_place():
    hm = tw.Heightmap.fbm(64, 64, seed=4, max_height=900.0)

    nmap = sobel_normals(hm.heights, hm.dx, hm.dz, border="clamp")
    scene = tw.Scene(hm, camera=tw.Camera.default_for(hm, width=96, height=64), shading="splat",
                     outputs=("image",))
    fr = tw.render(scene)
    assert fr.image.shape == (64, 96, 3)
    atlas, grid = splat_map(hm.heights, nmap)
    assert grid == 2
    # the highest visible pixels are snow (bright), the lowest grass (green dominant)
    m = fr.mesh
    ids = fr.triangle_id
    vis = ids >= 0
    bw = np.c_[fr.barycentrics[vis], 1 - fr.barycentrics[vis].sum(1)]
    hpix = np.einsum("nk,nk->n", bw, (m.positions[:, 1] + m.eye[1])[m.triangles[ids[vis]]])
    img = fr.image[vis].astype(float)
    hi = img[hpix > np.quantile(hpix, 0.98)].mean(0)
    lo = img[hpix < np.quantile(hpix, 0.05)].mean(0)
    assert hi.min() > 150 and lo[1] > lo[0] and lo[1] > lo[2]
    rules = DEFAULT_SPLAT_RULES
    assert len(rules) == 5


def test_cracks_are_background_seen_through_the_terrain():
    w, h = 64, 48
    pos, tri, f, normals = quad_scene(w, h, gap=0.0)
    assert find_cracks(f.triangle_id).sum() == 0
    pos, tri, f, normals = quad_scene(w, h, gap=3.0 / w)  # ~1.5 px wide gap
    cr = find_cracks(f.triangle_id)
    assert cr.sum() >= 0.9 * 1.4 * h / 2
    assert np.all(f.triangle_id[cr] == -1)
    cols = np.unique(np.nonzero(cr)[1])
    assert cols.min() >= w // 2 - 2 and cols.max() <= w // 2 + 1
    rgb, _, c = shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], mode="cracks")
    assert c["crack_pixels"] == cr.sum()
    assert np.all(rgb[cr] == np.float32(CRACK_COLOUR))
    # the sky around the terrain is not a crack
    assert not cr[0].any() and not cr[:, 0].any()


@pytest.mark.parametrize("mode", ["level", "patch", "wireframe", "cracks"])
def test_scene_shading_modes_render_and_are_deterministic(mode, tmp_path):
    hm = tw.Heightmap.fbm(40, 40, seed=1)
    scene = tw.Scene(hm, camera=tw.Camera.default_for(hm, width=80, height=60), shading=mode,
                     outputs=("image", "depth", "report"))
    a, b = tw.render(scene), tw.render(scene)
    assert a.image.dtype == np.uint8 and a.image.shape == (60, 80, 3)
    assert np.array_equal(a.image, b.image)
    assert a.report.stage("shade").counters.get("mode") == mode
    written = a.save(tmp_path)
    import OpenImageIO as oiio

    png = oiio.ImageBuf(str(tmp_path / "frame.png")).get_pixels(oiio.UINT8)
    assert np.array_equal(png, a.image)
    exr = oiio.ImageBuf(str(tmp_path / "depth.exr")).get_pixels(oiio.FLOAT)
    assert np.array_equal(exr.reshape(a.depth.shape), a.depth)
    assert len(written) >= 3


def test_scene_rejects_an_unknown_shading():
    hm = tw.Heightmap.fbm(16, 16, seed=1)
    with pytest.raises(ValueError, match="shading"):
        tw.Scene(hm, shading="cel")


def test_srgb8_is_the_correctly_rounded_encoding():
    """Each threshold encodes to its code and the float just below it to the code before (so every float32
    in [0, 1] gets the code nearest the exact transfer function); out-of-range values clamp, NaN is 0."""
    from terrainwarp.kernels.shading import SRGB8_THRESHOLDS, _srgb_encode, srgb8

    t = SRGB8_THRESHOLDS
    below = np.nextafter(t, np.float32(0))
    assert np.array_equal(srgb8(t), np.arange(1, 256, dtype=np.uint8))
    assert np.array_equal(srgb8(below), np.arange(0, 255, dtype=np.uint8))
    x = np.random.default_rng(3).random(200_000, dtype=np.float32) ** 3  # dense near 0 (the linear segment)
    exact = np.array([round(_srgb_encode(float(v)) * 255.0) for v in x[:20_000]])
    assert np.array_equal(srgb8(x[:20_000]).astype(int), exact)
    img = x.reshape(-1, 100, 2)[..., :1].repeat(3, axis=-1)  # any (..., 3) shape
    assert srgb8(img).shape == img.shape and srgb8(img).dtype == np.uint8
    odd = np.array([np.nan, -np.nan, -1.0, -0.0, 0.0, 1.0, 2.0, np.inf, -np.inf], np.float32)
    assert srgb8(odd).tolist() == [0, 0, 0, 0, 0, 255, 255, 255, 0]
    assert srgb8(np.zeros((0, 3), np.float32)).shape == (0, 3)


@pytest.mark.parametrize("mode", ["hillshade", "level", "patch", "wireframe", "cracks"])
def test_encoded_shading_is_srgb8_of_the_float_colour(mode):
    """``encode=True`` (what a frame's image is made with: the kernel encodes each pixel as it shades it) gives
    the bytes of srgb8(the float colour), out-of-range and NaN sky channels included; the per-pixel normals
    are only made when asked for."""
    from terrainwarp.kernels.shading import srgb8

    pos, tri, f, normals = quad_scene(gap=0.2)
    kw = dict(mode=mode, level=np.array([0, 1, 2, 3] * 2, np.int32), patch_id=np.arange(8, dtype=np.int32),
              clip=clip_coordinates(pos, I4, I4), sky=(float("nan"), 2.0, -0.5))
    rgb, n, c = shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], **kw)
    img, none, c8 = shade(f.triangle_id, f.barycentrics, tri, normals, pos[:, 1], encode=True, want_normals=False, **kw)
    assert img.dtype == np.uint8 and img.shape == rgb.shape and none is None and c8 == c
    assert np.array_equal(img, srgb8(rgb))
    assert img[f.triangle_id < 0][0].tolist() == [0, 255, 0]
    assert n.shape == rgb.shape
