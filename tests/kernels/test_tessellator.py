"""The quad tessellator: closed-form counts, fractional continuity, clamping, culling, agreement with
Mesa's llvmpipe (bit-exact tess coordinates), Warp kernels equal to the Python reference, displacement
and determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import digest
from gl_oracle import GLOracle, OracleUnavailable, triangle_set  # noqa: E402

from terrainwarp import Heightmap, check_watertight
from terrainwarp.kernels.tessellator import SPACING_CODES, tessellate_domains
from terrainwarp.mesh import Mesh
from terrainwarp.rendering import reference_tessellate_patch, tessellate_patches
from terrainwarp.rendering.reference_tessellator import FINAL_POINT_POSITION, patch_counts

SPACINGS = list(SPACING_CODES)
SPECIAL = np.array([0.0, -1.0, np.nan, 0.5, 1.0, 1.0 + 2**-17, 1.5, 2.0, 2.5, 3.0, 4.2, 7.0, 16.7, 31.9, 33.0,
                    63.99, 64.0, 65.0, 1000.0, np.inf], np.float32)


def _random_levels(n, seed, hi=70.0):
    rng = np.random.default_rng(seed)
    lv = rng.uniform(0.5, hi, (n, 6)).astype(np.float32)
    m = rng.random(lv.shape) < 0.3
    lv[m] = rng.choice(SPECIAL, int(m.sum()))
    r = rng.random(n) < 0.3
    lv[r] = np.round(lv[r])
    return lv


def _area(uv, tri):
    a, b, c = (uv[tri[:, k]].astype(np.float64) for k in range(3))
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


# ------------------------------------------------------------------------------------------------
# closed forms and the rules
# ------------------------------------------------------------------------------------------------


def test_closed_form_counts_integer_levels_1_to_64():
    for lv in range(1, 65):
        uv, tri = reference_tessellate_patch([lv] * 4, [lv] * 2, "equal")
        assert uv.shape == ((lv + 1) ** 2, 2) and tri.shape == (2 * lv * lv, 3)
        assert np.all(_area(uv, tri) > 0) and math.isclose(_area(uv, tri).sum(), 1.0, abs_tol=1e-9)
    # mixed integer levels: V = sum(outer) + (I_u - 1)(I_v - 1), T = sum(outer) + 2(I_u + I_v - 4) +
    # 2 (I_u - 2)(I_v - 2), with inner levels of 1 tessellated as 2 (unless every level is 1)
    rng = np.random.default_rng(0)
    for _ in range(200):
        o = rng.integers(1, 65, 4)
        i = rng.integers(1, 65, 2)
        iu, iv = max(i[0], 2), max(i[1], 2)
        s = int(o.sum())
        want = (s + (iu - 1) * (iv - 1), s + 2 * (iu + iv - 4) + 2 * (iu - 2) * (iv - 2))
        if (o == 1).all() and (i == 1).all():
            want = (4, 2)
        assert patch_counts(o, i, "equal") == want
    d = tessellate_domains(np.repeat(np.arange(1, 65, dtype=np.float32)[:, None], 4, 1),
                           np.repeat(np.arange(1, 65, dtype=np.float32)[:, None], 2, 1), "equal")
    lv = np.arange(1, 65)
    assert np.array_equal(np.diff(d["vertex_offsets"]), (lv + 1) ** 2)
    assert np.array_equal(np.diff(d["triangle_offsets"]), 2 * lv * lv)


@pytest.mark.parametrize("spacing", SPACINGS)
def test_levels_above_64_clamp(spacing):
    top = 63.0 if spacing == "fractional_odd" else 64.0
    ref = reference_tessellate_patch([top] * 4, [top] * 2, spacing)
    for big in (64.5, 65.0, 1000.0, np.inf):
        got = reference_tessellate_patch([big] * 4, [big] * 2, spacing)
        assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])


@pytest.mark.parametrize("spacing", SPACINGS)
def test_outer_level_zero_negative_or_nan_discards_the_patch(spacing):
    for bad in (0.0, -0.0, -1.0, -np.inf, np.nan):
        for e in range(4):
            o = [5.0] * 4
            o[e] = bad
            uv, tri = reference_tessellate_patch(o, [5.0, 5.0], spacing)
            assert uv.shape == (0, 2) and tri.shape == (0, 3)
    # NaN or negative INNER levels do not discard: they become the lower bound
    lo = 2.0 if spacing == "fractional_even" else 1.0
    for bad in (np.nan, -3.0, 0.0):
        got = reference_tessellate_patch([5.0] * 4, [bad, 7.0], spacing)
        ref = reference_tessellate_patch([5.0] * 4, [lo, 7.0], spacing)
        if spacing != "fractional_odd":  # fractional_odd forces 1 + 2^-16 either way
            assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
        assert got[1].shape[0] > 0


@pytest.mark.parametrize("spacing", ["fractional_even", "fractional_odd"])
def test_fractional_points_move_continuously_and_are_born_on_existing_ones(spacing):
    step = 1.0 / 32
    levels = np.arange(1.0, 64.0 + step / 2, step, dtype=np.float32)
    n = levels.size
    d = tessellate_domains(np.stack([np.full(n, 3.0), levels, np.full(n, 3.0), np.full(n, 3.0)], 1),
                           np.full((n, 2), 3.0), spacing)
    uv, pid = d["uv"], d["patch_id"]
    prev = None
    for p in range(n):
        pts = np.sort(uv[(pid == p) & (uv[:, 1] == 0.0), 0].astype(np.float64))
        assert pts[0] == 0.0 and pts[-1] == 1.0
        assert np.array_equal(pts, np.sort(1.0 - pts))  # symmetric about the middle, exactly
        assert np.all(np.diff(pts) >= 0)
        if prev is not None:
            # every point now is within one level step of a point before: continuous motion, and a
            # newborn point starts on an existing one (a point's speed is at most 1/level)
            dist = np.abs(pts[:, None] - prev[None, :]).min(1)
            assert dist.max() <= step + 2.0**-15, (spacing, levels[p], dist.max())
            assert pts.size - prev.size in (0, 2)
        prev = pts


def test_fixed_point_details():
    # reciprocal table and the ruler-function table used by the kernel's closed form
    from terrainwarp.rendering.reference_tessellator import RECIPROCAL, place

    assert RECIPROCAL[3] == 0x5555 and RECIPROCAL[6] == 0x2AAB and RECIPROCAL[64] == 0x400
    table = [0, 32, 16, 8, 17, 4, 18, 9, 19, 2, 20, 10, 21, 5, 22, 11, 23,
             1, 24, 12, 25, 6, 26, 13, 27, 3, 28, 14, 29, 7, 30, 15, 31]
    assert FINAL_POINT_POSITION == table
    assert table[1] == 32
    for i in range(2, 33):
        j = i - 1
        k = (j & -j).bit_length() - 1
        assert table[i] == (16 >> k) + (j >> (k + 1))
    # 16.16 rounding ties to even: 1 + 2^-17 is exactly 1.0 in fixed point
    assert reference_tessellate_patch([1 + 2**-17] * 4, [1.0, 1.0], "fractional_odd")[1].shape == (2, 3)
    assert place(3 << 16, True, 1) == 0x5555  # one third, rounded


@pytest.mark.parametrize("spacing", SPACINGS)
def test_triangles_are_ccw_and_cover_the_domain(spacing):
    for lv in _random_levels(40, 5, hi=20.0):
        uv, tri = reference_tessellate_patch(lv[:4], lv[4:], spacing)
        assert patch_counts(lv[:4], lv[4:], spacing) == (uv.shape[0], tri.shape[0])
        if tri.shape[0] == 0:
            continue
        a = _area(uv, tri)
        assert np.all(a >= 0) and math.isclose(a.sum(), 1.0, abs_tol=1e-9)
        assert np.all((uv >= 0) & (uv <= 1)) and np.all(uv * 65536 == np.round(uv * 65536))


def test_bad_arguments():
    with pytest.raises(ValueError, match="spacing"):
        reference_tessellate_patch([1] * 4, [1] * 2, "pow2")
    with pytest.raises(ValueError, match="outer"):
        reference_tessellate_patch([1] * 3, [1] * 2, "equal")
    with pytest.raises(ValueError, match="inner"):
        reference_tessellate_patch([1] * 4, [1] * 3, "equal")
    with pytest.raises(TypeError, match="outer"):
        reference_tessellate_patch(["a"] * 4, [1] * 2, "equal")
    with pytest.raises(ValueError, match="outer"):
        tessellate_domains(np.ones((3, 3)), np.ones((3, 2)), "equal")
    with pytest.raises(ValueError, match="inner"):
        tessellate_domains(np.ones((3, 4)), np.ones((2, 2)), "equal")
    p = {"origin_xz": np.zeros((1, 2)), "size": np.ones(1), "outer": np.ones((1, 4)), "inner": np.ones((1, 2))}
    h = np.zeros((4, 4), np.float32)
    with pytest.raises(ValueError, match="filter"):
        tessellate_patches(p, h, 1.0, 1.0, (0, 0, 0), filter="nearest")
    with pytest.raises(ValueError, match="size"):
        tessellate_patches({**p, "size": -np.ones(1)}, h, 1.0, 1.0, (0, 0, 0))
    with pytest.raises(ValueError, match="dx"):
        tessellate_patches(p, h, 0.0, 1.0, (0, 0, 0))
    with pytest.raises(ValueError, match="eye"):
        tessellate_patches(p, h, 1.0, 1.0, (0, np.nan, 0))
    with pytest.raises(ValueError, match="origin_xz"):
        tessellate_patches({k: v for k, v in p.items() if k != "origin_xz"}, h, 1.0, 1.0, (0, 0, 0))


# ------------------------------------------------------------------------------------------------
# the oracle: Mesa llvmpipe, OpenGL 4.5
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def oracle():
    try:
        return GLOracle()
    except OracleUnavailable as e:  # only where EGL / GL 4.5 genuinely is missing
        pytest.skip(f"no OpenGL 4.5 through EGL: {e}")


def _oracle_grid(spacing, seed):
    ints = np.arange(1, 65, dtype=np.float32)
    uniform = np.repeat(ints[:, None], 6, 1)
    frac = np.repeat((ints[::3] + np.float32(0.37))[:, None], 6, 1)
    special = np.array([[v, 3, 4, 5, 6, 7] for v in SPECIAL] + [[5, 5, 5, 5, v, 3] for v in SPECIAL]
                       + [[v] * 6 for v in SPECIAL], np.float32)
    return np.concatenate([uniform, frac, special, _random_levels(150, seed, hi=24.0),
                           _random_levels(10, seed + 1, hi=70.0)])


@pytest.mark.parametrize("spacing", SPACINGS)
def test_agrees_with_llvmpipe_bit_exactly(oracle, spacing):
    levels = _oracle_grid(spacing, SPACINGS.index(spacing))
    mine = [reference_tessellate_patch(lv[:4], lv[4:], spacing) for lv in levels]
    gl = oracle.triangles(levels, spacing, [max(m[1].shape[0], 1) for m in mine])
    bad = [(lv.tolist(), len(g), m[1].shape[0]) for lv, g, m in zip(levels, gl, mine) if g != triangle_set(*m)]
    assert not bad, f"{len(bad)} of {len(levels)} patches differ from {oracle.renderer}, e.g. {bad[:3]}"
    assert sum(len(g) for g in gl) > 10000  # the comparison saw real work


# ------------------------------------------------------------------------------------------------
# the Warp kernels
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("spacing", SPACINGS)
def test_kernel_equals_tessellate_patch_for_every_patch(spacing, device):
    levels = _random_levels(250, 11 + SPACINGS.index(spacing), hi=48.0)
    d = tessellate_domains(levels[:, :4], levels[:, 4:], spacing, device=device)
    vo, to = d["vertex_offsets"], d["triangle_offsets"]
    for p, lv in enumerate(levels):
        uv, tri = reference_tessellate_patch(lv[:4], lv[4:], spacing)
        assert np.array_equal(d["uv"][vo[p]:vo[p + 1]], uv)
        assert np.array_equal(d["triangles"][to[p]:to[p + 1]], tri + vo[p])
        assert np.all(d["patch_id"][vo[p]:vo[p + 1]] == p)
    empty = tessellate_domains(np.zeros((0, 4)), np.zeros((0, 2)), spacing, device=device)
    assert empty["uv"].shape == (0, 2) and empty["triangles"].shape == (0, 3)


def _patches(n=3, size=32.0, level=8.0, origin=(0.0, 0.0)):
    org = [(origin[0] + c * size, origin[1] + r * size) for r in range(n) for c in range(n)]
    p = len(org)
    return {"origin_xz": np.array(org), "size": np.full(p, size), "outer": np.full((p, 4), level, np.float32),
            "inner": np.full((p, 2), level, np.float32), "level": np.arange(p, dtype=np.int32)}


def test_displacement_reproduces_a_plane_and_stays_precise_far_from_the_origin(device):
    x0, z0 = 6.4e6, -3.2e6  # a terrain 7,000 km from the world origin
    dx, dz = 2.0, 0.5
    j = np.arange(49)
    i = np.arange(193)
    h = (0.25 * j[None, :] * dx - 0.1 * i[:, None] * dz + 1234.5).astype(np.float32)
    pt = _patches(n=3, size=32.0, level=7.3, origin=(x0, z0))
    eye = (x0 + 40.3, 2000.0, z0 + 17.9)
    for filt in ("bilinear", "bicubic"):
        t = tessellate_patches(pt, h, dx, dz, eye, spacing="fractional_odd", filter=filt, origin=(x0, z0),
                               device=device)
        pid = t.patch_id
        wx = pt["origin_xz"][pid, 0] + t.domain[:, 0].astype(np.float64) * pt["size"][pid]
        wz = pt["origin_xz"][pid, 1] + t.domain[:, 1].astype(np.float64) * pt["size"][pid]
        wy = 0.25 * (wx - x0) - 0.1 * (wz - z0) + 1234.5
        assert np.abs(t.positions[:, 0] - (wx - eye[0])).max() < 1e-4
        assert np.abs(t.positions[:, 2] - (wz - eye[2])).max() < 1e-4
        assert np.abs(t.positions[:, 1] - (wy - eye[1])).max() < 2e-3
        assert np.allclose(t.uv[:, 0], (wx - x0) / (48 * dx), atol=1e-6)
        assert np.allclose(t.uv[:, 1], (wz - z0) / (192 * dz), atol=1e-6)
        assert np.array_equal(t.level, pt["level"][pid])
    # seen from above, every triangle is counter-clockwise (normal +y)
    p = t.positions.astype(np.float64)
    a, b, c = (p[t.triangles[:, k]] for k in range(3))
    assert np.all(np.cross(b - a, c - a)[:, 1] > 0)
    assert check_watertight(t).watertight


def test_frame_on_the_real_dem_is_watertight_and_exports(tmp_path):
    hm = Heightmap.example("jacksboro")
    hh, ww = hm.shape
    nx, nz = (ww - 1) // 16, (hh - 1) // 16  # patches of 16 x 16 samples
    rng = np.random.default_rng(4)
    vert = rng.uniform(1, 24, (nx + 1, nz)).astype(np.float32)  # continuous per-edge factors
    hor = rng.uniform(1, 24, (nx, nz + 1)).astype(np.float32)
    org, outer = [], []
    for r in range(nz):
        for c in range(nx):
            org.append((hm.origin[0] + c * 16 * hm.dx, hm.origin[1] + r * 16 * hm.dz))
            outer.append([vert[c, r], hor[c, r], vert[c + 1, r], hor[c, r + 1]])
    p = len(org)
    pt = {"origin_xz": np.array(org), "size": np.tile([16 * hm.dx, 16 * hm.dz], (p, 1)), "outer": np.array(outer),
          "inner": rng.uniform(1, 24, (p, 2)).astype(np.float32)}
    eye = (hm.origin[0] + 100.0, float(hm.heights.max()) + 500, hm.origin[1] - 300.0)
    t = tessellate_patches(pt, hm.heights, hm.dx, hm.dz, eye, spacing="fractional_even", filter="bicubic",
                           origin=hm.origin)
    assert check_watertight(t).watertight
    # the host builds the Mesh (kernels/ never imports the host), as render's mesh stage does
    mesh = Mesh(positions=t.positions, eye=t.eye, triangles=t.triangles, uv=t.uv, level=t.level,
                patch_id=t.patch_id, normals=np.tile(np.float32([0, 1, 0]), (len(t.uv), 1)))
    pd = mesh.to_pyvista()
    assert pd.n_points == t.positions.shape[0] and pd.n_cells == t.triangles.shape[0]
    assert "level" in pd.point_data and "patch_id" in pd.point_data and "Normals" in pd.point_data
    pd.save(tmp_path / "frame.vtp")
    assert (tmp_path / "frame.vtp").stat().st_size > 0
    with pytest.raises(ValueError, match="normals"):
        Mesh(positions=t.positions, eye=t.eye, triangles=t.triangles, uv=t.uv, level=t.level,
             patch_id=t.patch_id, normals=np.zeros((2, 3), np.float32))


def test_tessellate_patches_is_deterministic(device):
    h = np.random.default_rng(1).normal(0, 10, (65, 65)).astype(np.float32)
    pt = _patches(n=2, size=16.0, level=13.7)

    def run():
        t = tessellate_patches(pt, h, 0.5, 0.5, (3.0, 40.0, -2.0), spacing="fractional_even", filter="bicubic",
                               device=device)
        return digest(*t[:8])

    assert run() == run()


def test_a_held_tessellation_keeps_its_outputs_while_later_frames_reuse_freed_ones():
    """The outputs come from the frame-buffer pool (kernels.parallel.pooled_rows): a frame dropped lends its
    buffers to the next, a frame held is never written by another, and the bits do not depend on the reuse."""
    h = np.random.default_rng(3).normal(0, 10, (65, 65)).astype(np.float32)
    big, small = _patches(n=3, size=16.0, level=12.5), _patches(n=2, size=16.0, level=9.0)
    args = (h, 0.5, 0.5, (3.0, 40.0, -2.0))
    held = tessellate_patches(big, *args, spacing="fractional_even")
    before = digest(*held[:8])
    for _ in range(2):  # a shorter frame while `held` is alive, twice: served by other buffers
        tessellate_patches(small, *args, spacing="fractional_even")
    assert digest(*held[:8]) == before
    ptr = held.triangles.__array_interface__["data"][0]
    del held
    again = tessellate_patches(big, *args, spacing="fractional_even")  # the dropped frame's buffers, same bits
    assert again.triangles.__array_interface__["data"][0] == ptr and digest(*again[:8]) == before


@pytest.mark.parametrize("need", [(), ("uv",), ("level", "patch_id"), ("domain",)])
def test_tessellate_patches_need_makes_only_what_is_asked_and_the_same_bits(need, device):
    """A depth-only frame (need=()) stores positions and triangles alone; whatever is made equals the full frame."""
    h = np.random.default_rng(2).normal(0, 10, (65, 65)).astype(np.float32)
    pt = _patches(n=3, size=16.0, level=11.3)
    args = (pt, h, 0.5, 0.5, (3.0, 40.0, -2.0))
    full = tessellate_patches(*args, spacing="fractional_odd", filter="bicubic", device=device)
    t = tessellate_patches(*args, spacing="fractional_odd", filter="bicubic", need=need, device=device)
    for name in ("positions", "triangles", "vertex_offsets", "triangle_offsets", *need):
        assert digest(getattr(t, name)) == digest(getattr(full, name)), name
    for name in {"uv", "domain", "patch_id", "level"} - set(need):
        assert getattr(t, name) is None, name
    with pytest.raises(ValueError, match="need"):
        tessellate_patches(*args, need=("normals",))


def test_cli_tessellate(tmp_path, capsys):
    import json

    from terrainwarp.cli import main

    assert main(["tessellate", "--outer", "3", "5", "1", "7", "--inner", "4", "4", "--spacing", "fractional_odd",
                 "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "wrote:" in printed and "tessellation.json" in printed
    doc = json.loads((tmp_path / "tessellation.json").read_text())
    uv, tri = reference_tessellate_patch([3, 5, 1, 7], [4, 4], "fractional_odd")
    assert doc["triangles"] == tri.tolist() and doc["points"] == uv.tolist()
    assert (tmp_path / "tessellation.png").stat().st_size > 1000
    assert json.loads((tmp_path / "tessellation.json").read_text())["n_triangles"] == tri.shape[0]
    for bad in (["--outer", "3", "5", "1", "--inner", "4", "4"], ["--outer", "1", "1", "1", "1", "--inner", "4", "4",
                                                                 "--spacing", "pow2"]):
        with pytest.raises(SystemExit) as e:
            main(["tessellate", *bad, "--out", str(tmp_path)])
        assert e.value.code == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_reference_tessellator_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="outer"):
        reference_tessellate_patch([1, 2, 3], [1, 1], "equal")
    with pytest.raises(ValueError, match="inner"):
        reference_tessellate_patch([1, 1, 1, 1], [1], "equal")
    with pytest.raises(ValueError, match="spacing"):
        reference_tessellate_patch([1, 1, 1, 1], [1, 1], "odd")
    with pytest.raises(TypeError, match="outer"):
        reference_tessellate_patch(["x"] * 4, [1, 1], "equal")


@pytest.mark.parametrize("spacing", SPACINGS)
def test_count_patches_equals_what_the_tessellator_emits(spacing, device):
    """count_patches (the count launch alone) gives each patch's points and triangles as the emitting kernel makes
    them, special levels (0, NaN, past 64) included."""
    from terrainwarp.kernels.tessellator import count_patches

    lv = _random_levels(300, 11)
    pts, tris = count_patches(lv[:, :4], lv[:, 4:], spacing, device)
    d = tessellate_domains(lv[:, :4], lv[:, 4:], spacing, device)
    assert np.array_equal(pts, np.diff(d["vertex_offsets"]))
    assert np.array_equal(tris, np.diff(d["triangle_offsets"]))
    assert pts.dtype == np.int32 and tris.shape == (300,)
    empty = count_patches(np.zeros((0, 4), np.float32), np.zeros((0, 2), np.float32), spacing, device)
    assert empty[0].shape == (0,) and empty[1].shape == (0,)
