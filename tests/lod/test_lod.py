import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, LodConfig, Scene, check_watertight, render
from terrainwarp.io.files import digest
from terrainwarp.kernels import parallel
from terrainwarp.kernels.parallel import set_threads
from terrainwarp.kernels.tessellator import SPACING_CODES
from terrainwarp.lod import (
    POLICY_CLASSES,
    ContinuousPolicy,
    DistancePolicy,
    LodState,
    ScreenErrorPolicy,
    Terrain,
    continuous_factors,
    edge_pixels,
    make_policy,
    quadtree,
    select,
    tile_from_key,
    tile_key,
    tile_name,
)
from terrainwarp.rendering.reference_tessellator import SPACINGS as REFERENCE_SPACINGS
from terrainwarp.scene import LOD_POLICIES, MAX_TESS, POLICY_TABLE, QUADTREE_TESS, SPACINGS, check_tess


def test_keys_round_trip():
    rng = np.random.default_rng(0)
    z = rng.integers(0, 20, 1000)
    x = rng.integers(0, 2**28, 1000)
    y = rng.integers(0, 2**28, 1000)
    k = tile_key(z, x, y)
    assert len(np.unique(k)) == len(np.unique(np.stack([z, x, y], 1), axis=0))
    z2, x2, y2 = tile_from_key(k)
    assert np.array_equal(z, z2) and np.array_equal(x, x2) and np.array_equal(y, y2)
    assert tile_name(tile_key(3, 5, 7)) == "3/5/7"
    with pytest.raises(ValueError):
        tile_key(-1, 0, 0)


def _flat(n=257):
    return Heightmap.from_array(np.zeros((n, n), np.float32), 1.0)


def test_geometric_error_zero_on_plane_and_exact_on_bump(device):
    i, j = np.mgrid[0:129, 0:129]
    plane = Heightmap.from_array((0.3 * j - 0.7 * i + 5.0).astype(np.float32))
    t = Terrain.prepare(plane, roots=1, tess=8, device=device)
    for _mn, _mx, err in t.stats:
        assert err.max() <= 1e-4  # float32 rounding of the bilinear weights only
    h = np.zeros((129, 129), np.float32)
    h[37, 53] = 10.0  # a one-sample bump, not on any vertex of levels < depth
    t = Terrain.prepare(Heightmap.from_array(h), roots=1, tess=8, device=device)
    assert t.depth == 4
    # at level L the node spacing is 2**(4-L) cells; (37, 53) is on the vertex grid only at the deepest level
    for lvl, (mn, mx, err) in enumerate(t.stats):
        s = 128 / 2**lvl
        node = (int(37 // s), int(53 // s))
        assert mx[node] == 10.0 and mn[node] == 0.0
        if lvl == t.depth:
            assert err.max() == 0.0
        else:
            assert err[node] == 10.0  # the node's surface is 0 there: the whole bump is error
    assert t.stats[0][2][0, 0] == 10.0


def test_flat_terrain_camera_over_middle_is_symmetric(device):
    hm = _flat()
    t = Terrain.prepare(hm, roots=4, tess=8, device=device)
    cam = Camera(position=(128.0, 40.0, 128.0), target=(128.0, 0.0, 128.0), up=(0.0, 0.0, -1.0), fov_y_deg=120,
                 width=256, height=256, near=0.5, far=1000.0)
    pl = select(t, cam, DistancePolicy(k=3.0), device=device)
    assert len(np.unique(pl.level)) > 1
    n = t.roots[0] << t.depth
    cells = {(int(lv), int(x), int(y)) for lv, (_, x, y) in zip(pl.level, np.stack(tile_from_key(pl.key), 1))}
    for lv, x, y in cells:
        m = n >> (t.depth - lv)
        assert (lv, m - 1 - x, y) in cells and (lv, x, m - 1 - y) in cells and (lv, y, x) in cells


@pytest.fixture(scope="module")
def dem_terrain():
    return Terrain.prepare(Heightmap.example(), roots=16, tess=8)


def _cams(hm, n=4):
    (x0, z0), (x1, z1) = hm.bounds_xz
    base = Camera.default_for(hm, 320, 240)
    cams = [base]
    for k in range(n - 1):
        px = x0 + (x1 - x0) * (0.2 + 0.2 * k)
        pz = z0 + (z1 - z0) * (0.8 - 0.15 * k)
        y = float(hm.sample([px], [pz])[0]) + 300.0
        cams.append(Camera(position=(px, y, pz), target=(0.5 * (x0 + x1), y - 600.0, z0), width=320, height=240,
                           near=1.0, far=1e6))
    return cams


@pytest.mark.parametrize("policy", [ScreenErrorPolicy(0.5), ScreenErrorPolicy(2.0), DistancePolicy(3.0)])
def test_balance_and_matching_edge_spacing(dem_terrain, policy, device):
    for cam in _cams(dem_terrain.heightmap):
        pl = select(dem_terrain, cam, policy, device=device)
        nb = pl.neighbour_level
        has = nb >= 0
        diff = np.abs(nb - pl.level[:, None])[has]
        assert diff.max() <= 1
        # every shared edge: both sides place vertices with the same spacing (edge length / factor)
        _check_shared_edges(pl)


def _check_shared_edges(pl):
    # index edges by their world endpoints; same-level neighbours share the whole edge, a coarse edge is
    # shared with two finer half-edges: compare the spacing (length / factor) along each
    o, s, f = pl.origin, pl.size, pl.outer
    segs = {}
    for p in range(len(pl)):
        x0, z0 = o[p]
        x1, z1 = x0 + s[p, 0], z0 + s[p, 1]
        edges = [((x0, z0), (x0, z1), s[p, 1]), ((x0, z0), (x1, z0), s[p, 0]), ((x1, z0), (x1, z1), s[p, 1]),
                 ((x0, z1), (x1, z1), s[p, 0])]
        for e, (a, b, length) in enumerate(edges):
            segs.setdefault("x" if a[0] == b[0] else "z", []).append((a, b, length / f[p, e], p))
    checked = 0
    for axis, lst in segs.items():
        by_line = {}
        for a, b, sp, p in lst:
            key = a[0] if axis == "x" else a[1]
            by_line.setdefault(round(key, 6), []).append((a, b, sp, p))
        for items in by_line.values():
            for i, (a, b, sp, p) in enumerate(items):
                lo, hi = (a[1], b[1]) if axis == "x" else (a[0], b[0])
                for a2, b2, sp2, p2 in items[i + 1:]:
                    lo2, hi2 = (a2[1], b2[1]) if axis == "x" else (a2[0], b2[0])
                    if min(hi, hi2) - max(lo, lo2) > 1e-9:  # overlapping: a shared edge
                        assert sp == pytest.approx(sp2, rel=1e-12), (p, p2)
                        checked += 1
    assert checked > 0


def test_culling_never_removes_a_visible_patch(dem_terrain, device):
    hm = dem_terrain.heightmap
    for cam in _cams(hm, 3):
        pl = select(dem_terrain, cam, ScreenErrorPolicy(1.0), device=device)
        assert pl.stats["culled"] >= 0
        f = render(Scene(hm, camera=cam, outputs=("depth",)))
        tri = f.triangle_id[f.triangle_id >= 0]
        cw = hm.shape[1] - 1
        cell = tri // 2
        ci, cj = cell // cw, cell % cw
        covered = np.zeros(len(ci), bool)
        for (ox, oz), sc in zip(pl.origin_cells, pl.size_cells):
            covered |= (cj + 1 > ox) & (cj < ox + sc) & (ci + 1 > oz) & (ci < oz + sc)
        assert covered.all()


def test_culling_drops_patches_behind_the_camera(dem_terrain, device):
    hm = dem_terrain.heightmap
    (x0, z0), (x1, z1) = hm.bounds_xz
    cam = Camera(position=(0.5 * (x0 + x1), 1500.0, 0.5 * (z0 + z1)), target=(x1, 1400.0, 0.5 * (z0 + z1)),
                 width=160, height=120, near=1.0, far=1e6)
    pl = select(dem_terrain, cam, DistancePolicy(1.0), device=device)
    assert pl.stats["culled"] > 0
    assert np.all(pl.origin[:, 0] + pl.size[:, 0] > 0.5 * (x0 + x1) - 1.0)  # nothing behind the eye


def test_hysteresis_lowers_level_changes(device):
    hm = Heightmap.fbm(257, seed=3, dx=10.0, max_height=400.0)
    t = Terrain.prepare(hm, roots=4, tess=8, device=device)
    path = []
    for k in range(40):  # back and forth along a line, small steps
        s = 0.5 + 0.03 * np.sin(k * 1.3)
        path.append(Camera(position=(1280.0 * s, 900.0, 2600.0), target=(1280.0, 0.0, 1280.0), width=320,
                           height=240, near=1.0, far=1e5))

    def changes(h):
        st = LodState()
        prev = None
        n = 0
        for cam in path:
            pl = select(t, cam, ScreenErrorPolicy(1.0, hysteresis=h), st, device=device)
            cur = set(pl.key.tolist())
            if prev is not None:
                n += len(cur ^ prev)
            prev = cur
        return n

    plain, hyst = changes(0.0), changes(0.5)
    assert plain > 0
    assert hyst < plain


def test_dist_zero_camera_inside_node_is_defined(device):
    hm = Heightmap.fbm(129, seed=1, dx=1.0, max_height=50.0)
    t = Terrain.prepare(hm, roots=1, tess=8, device=device)
    ground = float(hm.sample([64.0], [64.0])[0])
    cam = Camera(position=(64.0, ground + 0.5, 64.0), target=(100.0, ground, 100.0), width=64, height=64,
                 near=0.01, far=1e4)
    pl = select(t, cam, ScreenErrorPolicy(1.0), device=device)
    assert np.all(np.isfinite(pl.metric)) or np.all(pl.metric[pl.distance > 0] < 3e38)
    assert pl.level.max() == t.depth  # inside the box: infinite screen error, split to the bottom
    assert np.all(np.isfinite(pl.outer))


def test_continuous_factors_shared_edges_bitwise(dem_terrain, device):
    cam = _cams(dem_terrain.heightmap)[1]
    pl = select(dem_terrain, cam, ContinuousPolicy(target_px=6.0, level=3), device=device)
    assert (pl.level == 3).all()
    assert pl.outer.min() >= 1.0 and pl.outer.max() <= 64.0
    assert len(np.unique(pl.outer)) > 5  # actually continuous
    # east edge of a patch == west edge of the patch to its right, bit for bit
    lut = {(round(o[0], 6), round(o[1], 6)): i for i, o in enumerate(pl.origin)}
    n = 0
    for i, (o, s) in enumerate(zip(pl.origin, pl.size)):
        j = lut.get((round(o[0] + s[0], 6), round(o[1], 6)))
        if j is not None:
            assert pl.outer[i, 2] == pl.outer[j, 0]
            n += 1
        j = lut.get((round(o[0], 6), round(o[1] + s[1], 6)))
        if j is not None:
            assert pl.outer[i, 3] == pl.outer[j, 1]
            n += 1
    assert n > 10


def test_selection_is_deterministic(dem_terrain, device):
    cam = _cams(dem_terrain.heightmap)[2]
    a = select(dem_terrain, cam, ScreenErrorPolicy(0.7), device=device)
    b = select(dem_terrain, cam, ScreenErrorPolicy(0.7), device=device)
    for x, y in zip(a[:-1], b[:-1]):
        assert np.array_equal(x, y)


def test_bad_input():
    hm = Heightmap.fbm(33, seed=0)
    with pytest.raises(ValueError, match="tess"):
        Terrain.prepare(hm, tess=65)
    with pytest.raises(ValueError, match="roots"):
        Terrain.prepare(hm, roots=0)
    t = Terrain.prepare(hm, roots=1, tess=4)
    cam = Camera.default_for(hm)
    with pytest.raises(ValueError, match="tolerance_px"):
        select(t, cam, ScreenErrorPolicy(float("nan")))
    with pytest.raises(ValueError, match="hysteresis"):
        select(t, cam, ScreenErrorPolicy(1.0, hysteresis=1.5))
    with pytest.raises(TypeError, match="policy"):
        select(t, cam, "fast")
    with pytest.raises(TypeError, match="terrain"):
        select(hm, cam)
    big = Terrain.prepare(Heightmap.fbm(321, seed=0, dx=1.0), roots=1, tess=40, depth=2)
    cam = Camera(position=(1.0, 1500.0, 1.0), target=(200.0, 0.0, 200.0), near=0.1, far=1e4)
    uniform = select(big, cam, DistancePolicy(thresholds=(1e9, 0.0)))  # one level: no doubling, allowed
    assert set(uniform.level.tolist()) == {1}
    d = np.unique(uniform.distance)
    with pytest.raises(ValueError, match="tess"):  # mixed levels would need 2 * 40 > 64
        select(big, cam, DistancePolicy(thresholds=(1e9, 0.5 * (d[0] + d[1]))))


def test_policy_table_drives_config_policies_and_validation():
    assert set(POLICY_CLASSES) == set(POLICY_TABLE) == set(LOD_POLICIES)
    for name, spec in POLICY_TABLE.items():
        cfg = LodConfig().with_policy(name, 3.5)
        assert cfg.policy == name and getattr(cfg, spec.field) == 3.5 and cfg.value == 3.5
        assert cfg.spacing == (spec.spacing or "equal")
        p = make_policy(cfg)
        assert type(p) is POLICY_CLASSES[name] and getattr(p, spec.field) == 3.5
        lo, hi = spec.fit_range
        assert 0 < lo < hi
        with pytest.raises(ValueError, match=spec.field):
            LodConfig(policy=name, **{spec.field: -1.0})
        with pytest.raises(ValueError, match=spec.field):  # the policy object validates with the same rule
            POLICY_CLASSES[name](**{spec.field: float("nan")})
        with pytest.raises(ValueError, match="hysteresis"):
            LodConfig(policy=name, hysteresis=1.0)
    assert make_policy(LodConfig(policy="continuous", level=2)).level == 2
    LodConfig(policy="distance", k=0.0)  # k >= 0 is allowed, tolerances must be positive
    LodConfig(policy="sse", k=-1.0)  # only the chosen policy's parameter is checked
    with pytest.raises(ValueError, match="level"):
        LodConfig(policy="continuous", level=-1)
    with pytest.raises(TypeError, match="LodConfig"):
        make_policy("sse")
    # the spacing names come from the Warp tessellator's codes
    assert SPACINGS == tuple(SPACING_CODES) == REFERENCE_SPACINGS


def test_continuous_select_uses_the_one_factor_rule(dem_terrain, device):
    cam = _cams(dem_terrain.heightmap)[1]
    pl = select(dem_terrain, cam, ContinuousPolicy(target_px=6.0, level=3), device=device)
    px = edge_pixels(dem_terrain.heightmap, cam.position, cam.focal_px, pl.origin, pl.size)
    outer, inner = continuous_factors(px, 6.0)
    assert np.array_equal(outer.astype(np.float32), pl.outer) and np.array_equal(inner.astype(np.float32), pl.inner)
    # the rule by hand: clamp(L * focal / d / target, 1, 64), inner the means of opposite edges
    o = pl.origin[0]
    a = np.array([o[0], dem_terrain.heightmap.sample(o[0], o[1]), o[1]])
    b = np.array([o[0], dem_terrain.heightmap.sample(o[0], o[1] + pl.size[0, 1]), o[1] + pl.size[0, 1]])
    f = np.linalg.norm(b - a) * cam.focal_px / np.linalg.norm(0.5 * (a + b) - np.asarray(cam.position)) / 6.0
    assert pl.outer[0, 0] == pytest.approx(min(max(f, 1.0), 64.0), rel=1e-6)


# -- issue 20 item 8: LOD numbers are validated when the configuration is made, by one rule -------------------
@pytest.mark.parametrize("kw, match", [
    ({"roots": 0}, "roots"), ({"roots": -4}, "roots"), ({"roots": (2, 0)}, "roots"), ({"roots": 2.0}, "roots"),
    ({"roots": True}, "roots"), ({"tess": 16.0}, "tess"), ({"tess": 0}, "tess"), ({"tess": 3}, "tess"),
    ({"tess": 64}, "tess"), ({"policy": "continuous", "tess": 65}, "tess"),
    ({"policy": "continuous", "tess": 8.0}, "tess"), ({"policy": "distance", "tess": 12}, "tess")])
def test_lod_config_refuses_bad_roots_and_tess_at_construction(kw, match):
    with pytest.raises((ValueError, TypeError), match=match):
        LodConfig(**kw)


def test_one_tess_rule_for_config_terrain_and_render():
    assert QUADTREE_TESS == (1, 2, 4, 8, 16, 32) and MAX_TESS == 64
    for t in QUADTREE_TESS:
        for policy in LOD_POLICIES:
            assert LodConfig(policy=policy, tess=t).tess == t
    for t in (3, 12, 40, 64):  # the continuous policy has no doubled edges: any level the hardware takes
        assert LodConfig(policy="continuous", spacing="fractional_odd", tess=t).tess == t
    # the same range in every message: the configuration's, the terrain's and check_tess's
    hm = Heightmap.fbm(33, seed=0)
    msgs = []
    for make in (lambda: LodConfig(policy="continuous", tess=65), lambda: Terrain.prepare(hm, tess=65),
                 lambda: check_tess(65)):
        with pytest.raises(ValueError) as e:
            make()
        msgs.append(str(e.value).removeprefix("lod."))
    assert msgs[0] == msgs[1] == msgs[2] and f"1..{MAX_TESS}" in msgs[0]
    with pytest.raises(ValueError, match=f"power of two in 1..{QUADTREE_TESS[-1]}"):
        LodConfig(policy="sse", tess=64)
    with pytest.raises(ValueError, match="roots"):
        Terrain.prepare(hm, roots=(0, 2))
    with pytest.raises(TypeError, match="roots"):
        Terrain.prepare(hm, roots=2.5)


def _neighbour_levels_brute(pl, terrain):
    """Neighbour levels by painting every drawn leaf's finest cells with its level (-1 elsewhere)."""
    nx, nz = terrain.roots
    d = terrain.depth
    grid = np.full((nz << d, nx << d), -1, np.int64)
    _, x, y = tile_from_key(pl.key)
    for lv, xi, yi in zip(pl.level, x, y):
        s = 1 << (d - int(lv))
        grid[yi * s:(yi + 1) * s, xi * s:(xi + 1) * s] = lv
    out = np.empty((len(pl), 4), np.int64)
    for i, (lv, xi, yi) in enumerate(zip(pl.level, x, y)):
        s = 1 << (d - int(lv))
        x0, y0, q1, q3 = xi * s, yi * s, s // 4, (3 * s) // 4
        probes = (((x0 - 1, y0 + q1), (x0 - 1, y0 + q3)), ((x0 + q1, y0 - 1), (x0 + q3, y0 - 1)),
                  ((x0 + s, y0 + q1), (x0 + s, y0 + q3)), ((x0 + q1, y0 + s), (x0 + q3, y0 + s)))
        for e, pair in enumerate(probes):
            out[i, e] = max(grid[py, px] if 0 <= px < grid.shape[1] and 0 <= py < grid.shape[0] else -1
                            for px, py in pair)
    return out


def test_tree_map_neighbour_levels_match_painted_grid(device):
    """The tree map's walk finds the same neighbour levels as a painted finest-level grid: every leaf drawn
    (a wide camera looking down), levels 1..5 with forced balance splits, roots beyond the grid (-1)."""
    hm = Heightmap.fbm(257, seed=3, dx=1.0, max_height=60.0)
    t = Terrain.prepare(hm, roots=(3, 2), tess=4, device=device)
    cam = Camera(position=(40.0, 70.0, 60.0), target=(40.0, 0.0, 60.0), up=(0, 0, -1), fov_y_deg=170.0,
                 width=64, height=64, near=0.1, far=5000.0)
    pl = select(t, cam, DistancePolicy(thresholds=(1e9, 40.0, 40.0, 40.0, 40.0)), device=device)
    assert pl.stats["forced_splits"] > 0 and pl.stats["culled"] == 0 and len(np.unique(pl.level)) == 5
    nbr = _neighbour_levels_brute(pl, t)
    assert (nbr == -1).any() and np.array_equal(pl.neighbour_level, nbr)


@pytest.mark.parametrize("policy", [ScreenErrorPolicy(0.5, hysteresis=0.25), DistancePolicy(k=1.5),
                                    ContinuousPolicy(4.0, level=2)])
def test_select_is_identical_for_any_thread_count(policy):
    hm = Heightmap.fbm(257, seed=5, dx=2.0, max_height=80.0)
    t = Terrain.prepare(hm, roots=4, tess=8)
    cams = [Camera.default_for(hm), Camera(position=(100.0, 40.0, 400.0), target=(256.0, 0.0, 256.0))]
    seen = set()
    parallel.set_min_items(1)  # split even the smallest launch
    try:
        for n in (1, 2, 3, 8):
            set_threads(n)
            st, d = LodState(), []
            for cam in cams:
                pl = select(t, cam, policy, st)
                d.append(digest(*pl[:-1], st.split_keys) + repr(sorted(pl.stats.items())))
            seen.add("".join(d))
    finally:
        parallel.set_min_items(None)
        set_threads(None)
    assert len(seen) == 1


def test_terrain_bad_input_names_the_argument():
    hm = Heightmap.from_array(np.ones((9, 9)))
    with pytest.raises(ValueError, match="tess"):
        Terrain.prepare(hm, tess=0)
    with pytest.raises(ValueError, match="roots"):
        Terrain.prepare(hm, roots=-2)


def test_level_multipliers_move_one_level_threshold(device):
    """level_log_scale multiplies one level's split threshold: zeros are the plain policy bit for bit; a coarser
    multiplier at level 1 splits fewer level-1 nodes (sse), a finer one at level 1 of the distance policy more."""
    hm = Heightmap.fbm(257, seed=5, dx=10.0, max_height=800.0)
    cam = Scene(hm, camera=Camera.default_for(hm, 320, 240)).camera_path(3)[1]
    t = Terrain.prepare(hm, roots=4, tess=8, device=device)
    plain = select(t, cam, make_policy(LodConfig(tolerance_px=0.5, tess=8)), device=device)
    zeros = select(t, cam, make_policy(LodConfig(tolerance_px=0.5, tess=8, level_log_scale=(0.0, 0.0, 0.0))),
                   device=device)
    assert np.array_equal(plain.key, zeros.key)
    coarse = select(t, cam, make_policy(LodConfig(tolerance_px=0.5, tess=8, level_log_scale=(0.0, 2.0))),
                    device=device)
    assert len(coarse) < len(plain)
    assert (coarse.level == 2).sum() > (plain.level == 2).sum()  # level-1 nodes split less: more level-2 leaves
    near = select(t, cam, make_policy(LodConfig(policy="distance", k=1.0, tess=8)), device=device)
    far = select(t, cam, make_policy(LodConfig(policy="distance", k=1.0, tess=8, level_log_scale=(0.0, 1.0))),
                 device=device)
    assert len(far) > len(near)
    with pytest.raises(ValueError, match="level_scale"):
        make_policy(LodConfig()).__class__(level_scale=(float("nan"),))


def test_uniform_patches_tile_the_grid_at_one_level(device):
    """uniform_patches(level): every node of the level inside the grid, their cells covering the grid exactly
    once, factor T everywhere, tessellated into a watertight mesh."""
    from terrainwarp.lod.quadtree import uniform_patches

    hm = Heightmap.fbm(100, 77, seed=1, dx=5.0)
    t = Terrain.prepare(hm, roots=2, tess=4, device=device)
    for L in range(t.depth + 1):
        pl = uniform_patches(t, L)
        s = t.root_cells / 2**L
        cells = np.zeros((hm.shape[0] - 1, hm.shape[1] - 1), int)
        for (c0, r0) in pl.origin_cells:
            cells[int(r0):int(r0 + s), int(c0):int(c0 + s)] += 1
        assert (cells == 1).all(), L
        assert (pl.outer == t.tess).all() and (pl.level == L).all() and np.all(np.diff(pl.key) > 0)
    sc = Scene(hm, camera=Camera.default_for(hm, 64, 48), mesh="lod", lod=LodConfig(roots=2, tess=4),
               outputs=("mesh",))
    f = render(sc, t, patches=uniform_patches(t, 1), device=device)
    assert check_watertight(f).n_cracks == 0
    with pytest.raises(ValueError, match="level"):
        uniform_patches(t, t.depth + 1)


def multi_launch_select(terrain, camera, policy, state=None):
    """The selection as the multi-launch path makes it (one select-level launch per level, the balance's passes
    and the neighbour levels each a launch; a streamed terrain's path): the reference of the one-launch walk."""
    view = quadtree._view(terrain, camera)
    prev = state.split_keys if (state is not None and policy.hysteresis > 0) else np.zeros(0, np.int64)
    tree, split_keys, visited = quadtree._descend(terrain, view, policy, prev, "cpu")
    tree, forced = quadtree._balance(terrain, view, policy, tree, split_keys, "cpu")
    if state is not None:
        state.split_keys = np.unique(np.concatenate(split_keys) if split_keys else np.zeros(0, np.int64))
        state.frames += 1
    return quadtree._patch_list(terrain, camera, policy, tree, {"nodes_visited": visited, "forced_splits": forced})


def test_the_one_launch_selection_equals_the_multi_launch_path():
    """Every field and count of every PatchList, and the hysteresis state along a path, for the three policies
    (with hysteresis and level multipliers) on terrains whose grids leave nodes outside, with forced splits."""
    policies = [ScreenErrorPolicy(1.0), ScreenErrorPolicy(0.3, hysteresis=0.2),
                ScreenErrorPolicy(2.0, level_scale=(0.5, -0.5, 0.3)), DistancePolicy(k=2.0),
                DistancePolicy(k=6.0, hysteresis=0.1), ContinuousPolicy(target_px=4.0, level=2)]
    forced = 0
    for hm, roots, tess in ((Heightmap.fbm(129, seed=5, dx=10.0, max_height=300.0), 4, 8),
                            (Heightmap.fbm(200, seed=2, dx=5.0, max_height=200.0), 3, 4)):
        t = Terrain.prepare(hm, roots=roots, tess=tess)
        cam0 = Camera.default_for(hm, width=160, height=100)
        cams = Scene(heightmap=hm, camera=cam0).camera_path(4) + [cam0]
        for policy in policies:
            s1, s2 = LodState(), LodState()
            for cam in cams:
                got, want = select(t, cam, policy, s1), multi_launch_select(t, cam, policy, s2)
                for name, a, b in zip(got._fields, got, want, strict=True):
                    if isinstance(a, np.ndarray):
                        assert a.dtype == b.dtype and np.array_equal(a, b), name
                    else:
                        assert a == b, name
                assert np.array_equal(s1.split_keys, s2.split_keys)
                forced += got.stats["forced_splits"]
    assert forced > 0
