"""Curvature (kernels/curvature.py via terrainwarp.compute_curvature / analysis.surface_curvature):
error bounds on analytic surfaces, convergence order, exact zeros, float32 cancellation, NaN
containment, tiny grids."""

import numpy as np
import pytest
from analytic_surfaces import (
    cylinder_ridge,
    exact_directional,
    exact_edge_angle,
    exact_surface,
    grid,
    paraboloid,
    plane,
    sinusoid,
    sphere_cap,
)
from conftest import digest

from terrainwarp import Heightmap, compute_curvature
from terrainwarp.surface.differential import DIRECTIONS, max_curvature, surface_curvature

METHODS = ["two_normal", "three_normal", "three_vertex", "edge_angle"]
SCHEMES = ["zevenbergen_thorne", "evans_young"]
DX, DZ = 1.3, 0.8
INNER = (slice(3, -3), slice(3, -3))
EPS32 = float(np.finfo(np.float32).eps)


def curv(h, method, dx=DX, dz=DZ, device="cpu", **kw):
    return compute_curvature(np.asarray(h), method, dx=dx, dz=dz, device=device, **kw)


def gis(h, scheme="zevenbergen_thorne", dx=DX, dz=DZ, device=None):
    """The GIS schemes' curvatures (numpy, on the host whatever ``device`` a test runs)."""
    return np.stack(list(surface_curvature(np.asarray(h), scheme, dx=dx, dz=dz).values()), -1)


def exact_for(method, surf, xx, zz, dx, dz):
    if method == "edge_angle":
        return exact_edge_angle(surf, xx, zz, dx, dz)
    return exact_directional(surf, xx, zz, dx, dz)


def err(surf, method, sp=1.0, swap=False, extent=(40, 30), **kw):
    dx, dz = DX * sp, DZ * sp
    h, xx, zz = grid(surf, extent[0], extent[1], dx, dz)
    k = curv(h, method, *((dz, dx) if swap else (dx, dz)), **kw)
    return float(np.abs(k - exact_for(method, surf, xx, zz, dx, dz))[INNER].max())


# --- exact zeros ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("base", [0.0, 8848.0, -420.0, 1e6])
def test_flat_is_exactly_zero(base, device):
    h = np.full((7, 9), base, np.float32)
    for m in METHODS:
        for nm in ["sobel", "edge", "triangle", "quad"]:
            k = compute_curvature(h, m, normals=nm, dx=DX, dz=DZ, distance=2, device=device)
            assert np.all(k == 0.0), (m, nm)
    for s in SCHEMES:
        assert np.all(gis(h, s) == 0.0)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("offset", [0.0, 8848.0])
def test_sloped_plane_only_rounding(method, offset, device):
    # the only curvature of a sloped plane is the rounding of its float32 samples: a second difference
    # of a few ulp of the largest height over the step^2 (plus a few eps of the slope for the
    # normal-based methods, which difference slopes read off unit normals)
    s = plane(0.3, -0.7)
    h, _, _ = grid(s, 40, 30, DX, DZ, offset=offset)
    k = curv(h, method, device=device)
    ulp = float(np.spacing(np.float32(np.abs(h).max())))
    lmin = min(DX, DZ)
    bound = 4 * ulp / lmin**2 + 16 * EPS32 * (1 + 0.7**2) / lmin
    if method == "edge_angle":  # 1 - cos of an angle of a few ulp / step
        bound = (4 * ulp / lmin) ** 2
    assert k.max() <= bound, (k.max(), bound)


# --- analytic surfaces ---------------------------------------------------------------------------------

# (method, kwargs, surface, bound on the max interior error); swapping dx and dz must break the bound.
CASES = [
    ("three_vertex", {}, paraboloid, 1e-5),  # exact on quadratics: float32 rounding only
    ("two_normal", {"normals": "edge"}, paraboloid, 1e-5),  # slopes are linear: forward difference exact
    ("three_normal", {"normals": "edge"}, paraboloid, 1e-5),
    ("two_normal", {}, paraboloid, 6e-4),  # quad normals (the paper's): O(h^2) slope error
    ("three_normal", {}, paraboloid, 6e-4),
    ("edge_angle", {}, paraboloid, 1e-6),  # against its own definition on exact heights
    ("three_vertex", {}, sphere_cap, 3e-5),
    ("three_normal", {}, sphere_cap, 1.5e-4),
    ("two_normal", {}, sphere_cap, 1.5e-3),  # first order: forward difference of slopes
    ("edge_angle", {}, sphere_cap, 1e-7),
    ("three_vertex", {}, cylinder_ridge, 2e-5),
    ("three_normal", {}, cylinder_ridge, 1e-4),
    ("two_normal", {}, cylinder_ridge, 1e-3),
    ("edge_angle", {}, cylinder_ridge, 5e-8),
    ("three_vertex", {}, sinusoid, 1e-3),
]


@pytest.mark.parametrize("method,kw,surf,bound", CASES, ids=[f"{c[0]}-{c[2].__name__}-{c[1]}" for c in CASES])
def test_directional_error_bound(method, kw, surf, bound, device):
    s = surf()
    assert err(s, method, **kw, device=device) < bound
    assert err(s, method, swap=True, **kw, device=device) > 5 * bound


def test_direction_order_on_cylinder_ridge():
    # a ridge along x curves only along z: x ~ 0, z = 1/R at the crest, the diagonals in between
    s = cylinder_ridge(30.0)
    h, xx, zz = grid(s, 40, 30, 1.0, 1.0)
    for m in ["two_normal", "three_normal", "three_vertex"]:
        k = curv(h, m, 1.0, 1.0)
        c = k.shape[0] // 2  # z = 0 row: the crest
        assert np.all(k[c, 3:-3, 0] < 1e-5)
        assert np.allclose(k[c, 3:-3, 1], 1 / 30.0, rtol=2e-3)
        assert np.allclose(k[c, 3:-3, 2], k[c, 3:-3, 3], rtol=1e-4)
        assert np.all(k[c, 3:-3, 2] < k[c, 3:-3, 1])
        kmax, kdir = max_curvature(k)
        assert np.all(kdir[3:-3, 3:-3] == DIRECTIONS.index("z"))
        assert np.array_equal(kmax, k.max(-1))


def test_diagonal_step_is_true_length():
    # dx != dz: the diagonal section of a paraboloid h = a x^2 + b z^2 along (dx, dz)/L has
    # h_uu = 2(a dx^2 + b dz^2)/L^2 with L = sqrt(dx^2 + dz^2), not dx*sqrt(2)
    a, b = 0.05, 0.02
    s = paraboloid(a, b, 0.0, 0.0)
    h, xx, zz = grid(s, 30, 30, 2.0, 0.5)
    k = curv(h, "three_vertex", 2.0, 0.5)
    ln2 = 2.0**2 + 0.5**2
    huu = 2 * (a * 4.0 + b * 0.25) / ln2
    c = (k.shape[0] // 2, k.shape[1] // 2)
    hu_x, hu_z = 2 * a * xx[c], 2 * b * zz[c]
    hu = (hu_x * 2.0 + hu_z * 0.5) / np.sqrt(ln2)
    assert abs(k[c][2] - huu / (1 + hu * hu) ** 1.5) < 1e-5


def test_convergence_orders():
    # interior max error on a sinusoid at spacing s and s/2 (spacings where truncation, not float32
    # rounding, dominates): three_vertex is second order; two_normal first order (forward difference
    # of slopes); three_normal is second order where |k| > 0.3 max and first order overall, because it
    # averages the magnitudes of the two one-sided curvatures, which differ in sign near inflections.
    def e(method, sp, mask_strong=False):
        dx, dz = DX * sp, DZ * sp
        h, xx, zz = grid(sinusoid(), 80, 60, dx, dz)
        ex = exact_directional(sinusoid(), xx, zz, dx, dz)
        d = np.abs(curv(h, method, dx, dz) - ex)
        inner = np.zeros(ex.shape, bool)
        inner[3:-3, 3:-3] = True
        if mask_strong:
            inner &= ex > 0.3 * ex.max()
        return d[inner].max()

    def order(method, **kw):
        return np.log2(e(method, 2.0, **kw) / e(method, 1.0, **kw))

    assert 1.9 < order("three_vertex") < 2.1
    assert 0.9 < order("two_normal") < 1.1
    assert 0.85 < order("three_normal") < 1.1
    assert 1.8 < order("three_normal", mask_strong=True) < 2.1


def test_reinforcement_is_product():
    # distance d multiplies (scale*k_1) by (scale*k_d); on a paraboloid with edge normals both factors
    # are the exact curvature, so the result is (scale*k)^2
    s = paraboloid()
    h, xx, zz = grid(s, 40, 30, DX, DZ)
    ex = exact_directional(s, xx, zz, DX, DZ)
    k = curv(h, "three_normal", normals="edge", distance=2, scale=3.0)
    assert np.allclose(k[INNER], (3.0 * ex[INNER]) ** 2, rtol=1e-3)
    k1 = curv(h, "three_normal", normals="edge", scale=3.0)
    assert np.allclose(k1[INNER], 3.0 * ex[INNER], rtol=1e-3)


def test_scale_multiplies():
    h, _, _ = grid(sphere_cap(), 20, 20, 1.0, 1.0)
    for m in METHODS:
        a = curv(h, m, 1.0, 1.0)
        b = curv(h, m, 1.0, 1.0, scale=4.0)
        np.testing.assert_allclose(b, 4.0 * a, rtol=1e-6)


def test_edge_angle_range_and_right_angle():
    # a right-angle corner: 1 - cos(90 degrees) = 1; a 45-degree turn: 1 - cos(45) = 0.2929
    h = np.zeros((5, 5), np.float32)
    h[:, 3:] = np.float32([[1.0, 2.0]])
    k = curv(h, "edge_angle", 1.0, 1.0)
    assert abs(k[2, 2, 0] - (1 - np.cos(np.pi / 4))) < 1e-6
    spike = np.zeros((5, 5), np.float32)
    spike[2, 2] = 100.0
    k = curv(spike, "edge_angle", 1.0, 1.0)
    assert np.all((k >= 0) & (k <= 1)) and k[2, 2, 0] == 1.0  # clamped


# --- GIS surface curvature -------------------------------------------------------------------------------

@pytest.mark.parametrize("scheme", SCHEMES)
def test_surface_curvature_exact_on_paraboloid(scheme):
    # both 3x3 fits are exact on quadratics: float32 rounding only
    s = paraboloid()
    h, xx, zz = grid(s, 40, 30, DX, DZ)
    k = gis(h, scheme)
    ex = exact_surface(s, xx, zz)
    rel = np.abs(k - ex)[INNER].max(axis=(0, 1)) / np.abs(ex[INNER]).max(axis=(0, 1))
    assert np.all(rel < 1e-4), rel
    ks = gis(h, scheme, DZ, DX)  # swapped spacing
    rels = np.abs(ks - ex)[INNER].max(axis=(0, 1)) / np.abs(ex[INNER]).max(axis=(0, 1))
    assert np.all(rels[[0, 2, 3]] > 1e-2)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_surface_curvature_sphere(scheme):
    # sphere of radius R: mean 1/R, Gaussian 1/R^2, profile 1/R (convex = positive), plan 1/rho (the
    # contour circle's radius), away from the summit where plan is singular
    r = 40.0
    s = sphere_cap(r)
    h, xx, zz = grid(s, 40, 30, DX, DZ)
    k = gis(h, scheme)
    m = np.zeros(h.shape, bool)
    m[INNER] = True
    rho = np.hypot(xx, zz)
    np.testing.assert_allclose(k[m][:, 0], 1 / r, rtol=1e-3)
    np.testing.assert_allclose(k[m][:, 1], 1 / r**2, rtol=2e-3)
    np.testing.assert_allclose(k[m][:, 2], 1 / r, rtol=1e-3)
    far = m & (rho > 5)
    np.testing.assert_allclose(k[far][:, 3], 1 / rho[far], rtol=1e-3)


def test_surface_curvature_signs_and_ridge():
    # concave bowl: negative mean; ridge along x (cylinder): mean -t/2 > 0, Gaussian 0
    bowl = (-sphere_cap(40.0).h(*np.meshgrid(np.arange(-5, 6.0), np.arange(-5, 6.0)))).astype(np.float32)
    assert gis(bowl, dx=1.0, dz=1.0)[5, 5, 0] < 0
    s = cylinder_ridge(30.0)
    h, xx, zz = grid(s, 20, 20, 1.0, 1.0)
    k = gis(h, dx=1.0, dz=1.0)
    assert np.all(k[INNER][..., 0] > 0) and np.all(np.abs(k[INNER][..., 1]) < 1e-9)


# --- precision, stiff inputs ------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS + SCHEMES)
def test_everest_offset_bit_identical(method, device):
    # millimetre relief 8,848 m up (multiples of the 0.98 mm float32 ulp there): differences relative
    # to the centre make the result bit-identical to the same relief at 0 m
    rng = np.random.default_rng(4)
    relief = np.round(rng.random((15, 18)) * 6) * 2.0**-10
    h = (8848.0 + relief).astype(np.float32)
    rel = relief.astype(np.float32)
    f = gis if method in SCHEMES else lambda *a: curv(*a, device=device)
    a = f(h, method, 0.01, 0.01)
    b = f(rel, method, 0.01, 0.01)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("scale_h,sp", [(1e-6, 1.0), (1e6, 1.0), (1.0, 1e-3), (1.0, 1e4)])
def test_extreme_heights_and_spacings(scale_h, sp, device):
    # a paraboloid with heights 1e-6 / 1e6 times its spacing, or spacing 1e-3 / 1e4 m: three-vertex
    # keeps its relative error (float32 rounding only)
    s = paraboloid(0.05, -0.03, 0.02, 0.0)
    h, xx, zz = grid(s, 40, 30, DX, DZ)
    h = (h.astype(np.float64) * scale_h * sp).astype(np.float32)
    x, z = xx * sp, zz * sp
    k = curv(h, "three_vertex", DX * sp, DZ * sp, device=device)
    # exact for the scaled surface h_s(x, z) = scale_h * sp * h(x / sp, z / sp)
    out = []
    for di, dj in ((0, 1), (1, 0), (1, 1), (-1, 1)):
        ln = np.hypot(dj * DX, di * DZ)
        ux, uz = dj * DX / ln, di * DZ / ln
        hu = scale_h * (s.hx(x / sp, z / sp) * ux + s.hz(x / sp, z / sp) * uz)
        huu = scale_h / sp * (s.hxx(xx, zz) * ux * ux + 2 * s.hxz(xx, zz) * ux * uz + s.hzz(xx, zz) * uz * uz)
        out.append(np.abs(huu) / (1 + hu * hu) ** 1.5)
    ex = np.stack(out, -1)
    assert np.all(np.isfinite(k))
    rel = np.abs(k - ex)[INNER].max() / ex[INNER].max()
    assert rel < 1e-3, rel
    for m in METHODS + SCHEMES:
        k = gis(h, m, DX * sp, DZ * sp) if m in SCHEMES else curv(h, m, DX * sp, DZ * sp, device=device)
        assert np.all(np.isfinite(k))


@pytest.mark.parametrize("method", METHODS)
def test_cliff_and_spike(method, device):
    h = np.zeros((9, 9), np.float32)
    h[:, 5:] = 1e4
    h[2, 2] = 5e3
    k = curv(h, method, 1.0, 1.0, device=device)
    assert np.all(np.isfinite(k)) and np.all(k >= 0)
    kmax, _ = max_curvature(k)
    if method in ("three_vertex", "edge_angle"):
        assert kmax[2, 2] == kmax[:4, :4].max()  # the spike is the sharpest point of its corner
    else:  # normal-based: the spike's own normal is symmetric (slope 0), its neighbours' are steep
        assert kmax[2, 2] > 0.2
    assert np.all(np.isfinite(gis(h, dx=1.0, dz=1.0)))


# --- no data ----------------------------------------------------------------------------------------------

RADIUS = {"three_vertex": 1, "edge_angle": 1, "two_normal": 2, "three_normal": 2, "zevenbergen_thorne": 1,
          "evans_young": 1}


@pytest.mark.parametrize("method", METHODS + SCHEMES)
def test_nan_hole_contained(method, device):
    # NaN stays exactly at the holes; values change only within the stencil radius (1 for the
    # 3-sample and 3x3 stencils, 2 for the normal-based methods: normals of the neighbours)
    h, _, _ = grid(sinusoid(), 24, 24, 1.0, 1.0)
    holed = h.copy()
    holes = [(8, 9), (0, 3), (15, 15), (15, 16), (16, 15), (16, 16)]
    for ij in holes:
        holed[ij] = np.nan
    f = gis if method in SCHEMES else lambda *a: curv(*a, device=device)
    a = f(h, method, 1.0, 1.0)
    b = f(holed, method, 1.0, 1.0)
    nan = np.isnan(holed)
    assert np.all(np.isnan(b[nan])) and np.all(np.isfinite(b[~nan]))
    r = RADIUS[method]
    near = np.zeros(h.shape, bool)
    for i, j in holes:
        near[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1] = True
    assert np.array_equal(a[~near], b[~near])
    kmax, kdir = max_curvature(b)
    assert np.all(np.isnan(kmax[nan])) and np.all(kdir[nan] == -1) and np.all(kdir[~nan] >= 0)


def test_nan_reinforced_radius(device):
    h, _, _ = grid(sinusoid(), 24, 24, 1.0, 1.0)
    holed = h.copy()
    holed[10, 10] = np.nan
    a = curv(h, "three_normal", 1.0, 1.0, distance=3, device=device)
    b = curv(holed, "three_normal", 1.0, 1.0, distance=3, device=device)
    near = np.zeros(h.shape, bool)
    near[10 - 4:10 + 5, 10 - 4:10 + 5] = True  # normals (1) + the far pair (3)
    assert np.array_equal(a[~near], b[~near]) and np.isfinite(b[~np.isnan(holed)]).all()


# --- tiny grids -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(1, 1), (2, 2), (3, 3), (1, 4), (5, 1)])
def test_tiny_grids(shape, device):
    rng = np.random.default_rng(5)
    h = rng.random(shape).astype(np.float32)
    for m in METHODS:
        k = curv(h, m, distance=2, device=device)
        assert k.shape == (*shape, 4) and np.all(np.isfinite(k)) and np.all(k >= 0)
        if shape == (1, 1):
            assert np.all(k == 0)
    for s in SCHEMES:
        g = gis(h, s)
        assert g.shape == (*shape, 4) and np.all(np.isfinite(g))
    # 3x3 paraboloid: the centre's three-vertex curvature is exact
    if shape == (3, 3):
        s = paraboloid()
        hh, xx, zz = grid(s, 2 * DX, 2 * DZ, DX, DZ)
        k = curv(hh, "three_vertex", device=device)
        ex = exact_directional(s, xx, zz, DX, DZ)
        assert np.abs(k[1, 1] - ex[1, 1]).max() < 1e-5


# --- determinism and validation ----------------------------------------------------------------------------

def test_deterministic_on_dem(device):
    hm = Heightmap.example()
    for m in METHODS:
        assert digest(compute_curvature(hm, m, distance=2, device=device)) == \
            digest(compute_curvature(hm, m, distance=2, device=device))


def test_bad_arguments():
    h = np.zeros((4, 4), np.float32)
    with pytest.raises(ValueError, match="method"):
        compute_curvature(h, "four_normal")
    with pytest.raises(ValueError, match="normals"):
        compute_curvature(h, "two_normal", normals="hex")
    with pytest.raises(ValueError, match="distance"):
        compute_curvature(h, "three_normal", distance=0)
    with pytest.raises(TypeError, match="distance: expected an integer"):
        compute_curvature(h, "three_normal", distance=1.5)
    with pytest.raises(ValueError, match="scale"):
        compute_curvature(h, "three_vertex", scale=-1.0)
    with pytest.raises(ValueError, match="dx"):
        compute_curvature(h, "three_vertex", dx=-1.0)
    with pytest.raises(ValueError, match="scheme"):
        surface_curvature(h, "horn")
    with pytest.raises(ValueError, match="curvature"):
        max_curvature(np.zeros((3, 3, 3), np.float32))


# --- pipeline ------------------------------------------------------------------------------------------------

def test_render_curvature_output_is_its_own_stage():
    import terrainwarp as tw

    hm = tw.Heightmap.example("topobathy")
    f = tw.render(tw.Scene(hm, outputs=("curvature", "report")))
    assert f.curvature.shape == (*hm.shape, 4) and f.curvature.dtype == np.float32
    assert np.array_equal(f.curvature, compute_curvature(hm, "three_normal"))
    assert f.report.stage("curvature") is not None and f.report.stage("curvature").time_ms > 0
    assert f.image is None and f.mesh is None and f.report.stage("raster") is None
    g = tw.render(tw.Scene(hm, outputs=("depth",)))
    assert g.curvature is None and g.report.stage("curvature") is None
