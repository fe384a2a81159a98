"""Vertex normals (kernels/normals.py via terrainwarp.compute_normals): exactness on analytic surfaces,
convergence order, Sobel == skimage up to scale, borders, float32 cancellation, NaN holes, tiny grids."""

import numpy as np
import pytest
from analytic_surfaces import SURFACES, angle_deg, exact_normals, grid, paraboloid, plane, sinusoid, sphere_cap
from conftest import digest

from terrainwarp import Heightmap, compute_normals
from terrainwarp.kernels.normals import sobel_normals
from terrainwarp.surface.differential import decode_normal_map, normal_map_image

METHODS = ["sobel", "edge", "triangle", "quad"]
DX, DZ = 1.3, 0.8  # deliberately unequal: a swapped spacing must show
INNER = (slice(2, -2), slice(2, -2))


def normals(h, method, dx=DX, dz=DZ, device="cpu", **kw):
    kw.setdefault("border", "skip")
    return compute_normals(np.asarray(h), method, dx=dx, dz=dz, device=device, **kw)


def err_deg(surf, method, sp=1.0, inner=True, swap=False, **kw):
    dx, dz = DX * sp, DZ * sp
    h, xx, zz = grid(surf, 40, 30, dx, dz)
    n = normals(h, method, *((dz, dx) if swap else (dx, dz)), **kw)
    e = angle_deg(n, exact_normals(surf, xx, zz))
    return float((e[INNER] if inner else e).max())


# --- exactness ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_plane_exact_everywhere(method, device):
    # border="skip" (one-sided differences at the border) is exact on a plane up to the border; the
    # only error is the float32 rounding of the samples (|h| <= 25 m: ulp 2e-6 m over >= 0.8 m).
    h, xx, zz = grid(plane(), 40, 30, DX, DZ)
    n = normals(h, method, device=device)
    assert np.max(angle_deg(n, exact_normals(plane(), xx, zz))) < 2e-4


@pytest.mark.parametrize("method,bound", [("sobel", 1e-4), ("edge", 1e-4), ("triangle", 0.1), ("quad", 0.1)])
def test_paraboloid_interior_bound(method, bound, device):
    # Sobel and edge are central differences: exact on quadratics (only float32 rounding left);
    # triangle and quad average one-sided slopes: O(h^2) error, measured 0.078 and 0.083 degrees.
    e = err_deg(paraboloid(), method, device=device)
    assert e < bound
    # a swapped spacing (dx <-> dz) is caught by the same bound
    assert err_deg(paraboloid(), method, swap=True, device=device) > 10 * bound


@pytest.mark.parametrize("method,bound", [("sobel", 0.035), ("edge", 0.025), ("triangle", 0.015), ("quad", 0.02)])
def test_sphere_cap_bound(method, bound, device):
    assert err_deg(sphere_cap(), method, device=device) < bound
    assert err_deg(sphere_cap(), method, swap=True, device=device) > 10 * bound


@pytest.mark.parametrize("method", METHODS)
def test_convergence_order_two(method):
    # interior error on a sinusoid at spacing s and s/2: second order (ratio ~4)
    e1 = err_deg(sinusoid(), method, 1.0)
    e2 = err_deg(sinusoid(), method, 0.5)
    order = np.log2(e1 / e2)
    assert 1.8 < order < 2.2, (e1, e2, order)


def test_normals_unit_and_sign(device):
    # a plane rising along +x tilts its normal to -x; rising along +z tilts it to -z
    for method in METHODS:
        hx = normals(np.tile(np.arange(6, dtype=np.float32), (5, 1)), method, 1.0, 1.0, device=device)
        assert np.all(hx[..., 0] < 0) and np.allclose(hx[..., 2], 0, atol=1e-7)
        hz = normals(np.tile(np.arange(5, dtype=np.float32)[:, None], (1, 6)), method, 1.0, 1.0, device=device)
        assert np.all(hz[..., 2] < 0) and np.allclose(hz[..., 0], 0, atol=1e-7)
        assert np.allclose(np.linalg.norm(hx, axis=-1), 1.0, atol=1e-6)


# --- Sobel against scikit-image ------------------------------------------------------------------------

def test_sobel_matches_skimage():
    # skimage.filters.sobel_v = d/dcol with the 1-2-1 smoothing normalised by 4 (weights sum to 4 per
    # side): on our grid sobel_v(h) = 2*dx * dh/dx = -2*dx * n.x/n.y, sobel_h(h) = -2*dz * n.z/n.y,
    # same sign (both differentiate towards increasing index). Compared away from the border (skimage
    # reflects; we use constant/clamp/skip).
    from skimage.filters import sobel_h, sobel_v

    rng = np.random.default_rng(1)
    h = (rng.random((24, 31)) * 50).astype(np.float32)
    n = compute_normals(h, "sobel", dx=DX, dz=DZ)
    gx = -n[..., 0].astype(np.float64) / n[..., 1]
    gz = -n[..., 2].astype(np.float64) / n[..., 1]
    sv = sobel_v(h.astype(np.float64))
    sh = sobel_h(h.astype(np.float64))
    i = (slice(1, -1), slice(1, -1))
    scale = np.abs(sv[i]).max()
    np.testing.assert_allclose(2 * DX * gx[i], sv[i], atol=1e-5 * scale)
    np.testing.assert_allclose(2 * DZ * gz[i], sh[i], atol=1e-5 * np.abs(sh[i]).max())


def test_sobel_wrapper_signature_kept():
    h = np.random.default_rng(2).random((9, 7)).astype(np.float32)
    a = sobel_normals(h, 2.0, 3.0, border="clamp", constant=0.0)
    b = compute_normals(h, "sobel", border="clamp", dx=2.0, dz=3.0)
    assert a.shape == (9, 7, 3) and np.array_equal(a, b)


# --- borders -------------------------------------------------------------------------------------------

def test_constant_zero_vs_clamp_border_on_real_dem():
    # Measured (and stated in terrainwarp/analysis.py): on the Jacksboro DEM (heights 236..1076 m) the
    # paper's constant-0 border and clamp-to-edge agree bit for bit inside and differ by 47.9..91.0
    # degrees (median 69.8) on the border ring; clamp vs one-sided skip: up to 16.5 degrees.
    hm = Heightmap.example()
    a = compute_normals(hm, "sobel", border="constant")
    b = compute_normals(hm, "sobel", border="clamp")
    c = compute_normals(hm, "sobel", border="skip")
    ring = np.zeros(hm.shape, bool)
    ring[0] = ring[-1] = ring[:, 0] = ring[:, -1] = True
    assert np.array_equal(a[~ring], b[~ring]) and np.array_equal(a[~ring], c[~ring])
    d = angle_deg(a, b)[ring]
    assert 47.0 < d.min() and d.max() > 90.0 and 69.0 < np.median(d) < 71.0
    assert 16.0 < angle_deg(b, c)[ring].max() < 17.0


def test_constant_border_value_and_skip_on_high_plane():
    # a plane 8,848 m up: constant 0 tilts the border normals; constant = 8848 on flat ground does not;
    # skip keeps the plane exact on the border too.
    h, xx, zz = grid(plane(), 20, 20, 1.0, 1.0, offset=8848.0)
    ex = exact_normals(plane(), xx, zz)
    const0 = compute_normals(h, "sobel", border="constant", constant=0.0)
    assert angle_deg(const0, ex)[0].min() > 45.0
    skip = compute_normals(h, "sobel", border="skip")
    assert angle_deg(skip, ex).max() < 0.1  # float32 ulp at 8848 m is 0.98 mm over a 1 m spacing
    flat = np.full((6, 6), 8848.0, np.float32)
    up = compute_normals(flat, "sobel", border="constant", constant=8848.0)
    assert np.array_equal(up, np.broadcast_to(np.float32([0, 1, 0]), up.shape))


# --- precision and stiff inputs ------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_everest_offset_millimetre_relief(method, device):
    # millimetre relief 8,848 m up: float32 keeps the samples to 0.98 mm; differencing between samples
    # (never summing heights first) gives bit-identical normals with and without the offset.
    rng = np.random.default_rng(3)
    relief = np.round(rng.random((16, 17)) * 8) * 2.0 ** -10  # multiples of the ulp at 8848 m
    h = (8848.0 + relief).astype(np.float32)
    rel = (h.astype(np.float64) - 8848.0).astype(np.float32)
    a, b = normals(h, method, 0.01, 0.01, device=device), normals(rel, method, 0.01, 0.01, device=device)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scale_h,sp", [(1e-6, 1.0), (1e6, 1.0), (1.0, 1e-3), (1.0, 1e4)])
def test_extreme_heights_and_spacings(method, scale_h, sp, device):
    # a paraboloid whose heights are 1e-6 or 1e6 of the spacing, or with spacing 1e-3 / 1e4 m
    s = paraboloid()
    h, xx, zz = grid(s, 40, 30, DX, DZ)
    h = (h.astype(np.float64) * scale_h * sp).astype(np.float32)
    n = normals(h, method, DX * sp, DZ * sp, device=device)
    g = np.stack([-s.hx(xx, zz) * scale_h, np.ones_like(xx), -s.hz(xx, zz) * scale_h], -1)
    ex = g / np.linalg.norm(g, axis=-1, keepdims=True)
    assert np.all(np.isfinite(n)) and np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-6)
    # degrees. Triangle/quad carry their O(h^2) bias, and on near-vertical ground (slopes ~1e5) the
    # average of unit facet normals leans towards the steeper facets: 41 degrees measured, a property of
    # averaging unit normals (curtis2004), not of float32.
    tol = {"sobel": 2e-4, "edge": 2e-4}.get(method, 45.0 if scale_h > 1e3 else 0.2)
    assert angle_deg(n, ex)[INNER].max() < tol


@pytest.mark.parametrize("method", METHODS)
def test_cliff_and_spike_finite(method, device):
    h = np.zeros((9, 9), np.float32)
    h[:, 5:] = 1e4  # a 10 km vertical step
    h[2, 2] = 5e3  # a one-sample spike
    n = normals(h, method, 1.0, 1.0, device=device)
    assert np.all(np.isfinite(n)) and np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-6)
    # beside the step the normal faces away from it: almost horizontal for the central differences,
    # about 45 degrees for triangle/quad (the average of a flat and a vertical facet normal)
    assert n[6, 4, 0] < (-0.99 if method in ("sobel", "edge") else -0.6)


# --- no data ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("border", ["constant", "clamp", "skip"])
def test_nan_hole_contained(method, border, device):
    h, _, _ = grid(sinusoid(), 20, 20, 1.0, 1.0)
    holed = h.copy()
    holed[7, 9] = np.nan
    holed[0, 3] = np.nan  # a hole on the border
    holed[12:14, 4:6] = np.nan  # a 2x2 hole
    a = normals(h, method, 1.0, 1.0, border=border, device=device)
    b = normals(holed, method, 1.0, 1.0, border=border, device=device)
    assert np.all(np.isfinite(b)) and np.allclose(np.linalg.norm(b, axis=-1), 1, atol=1e-6)
    near = np.zeros(h.shape, bool)
    for i, j in zip(*np.nonzero(np.isnan(holed)), strict=True):
        near[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = True
    assert np.array_equal(a[~near], b[~near])  # nothing beyond the immediate neighbours changes
    # the neighbours still see the surface (one-sided differences): within 6 degrees of the hole-free
    # normal; the hole cells themselves get a finite fill-in from their own neighbours
    ring = near & ~np.isnan(holed)
    assert angle_deg(a[ring], b[ring]).max() < 6.0


def test_all_nan_but_one(device):
    h = np.full((3, 4), np.nan, np.float32)
    h[1, 1] = 5.0
    for m in METHODS:
        n = normals(h, m, device=device)
        assert np.array_equal(n, np.broadcast_to(np.float32([0, 1, 0]), n.shape))


# --- tiny grids --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(1, 1), (2, 2), (3, 3), (1, 5), (4, 1)])
def test_tiny_grids(method, shape, device):
    s = plane()
    h, xx, zz = grid(s, (shape[1] - 1) * DX, (shape[0] - 1) * DZ, DX, DZ)
    assert h.shape == shape
    n = normals(h, method, device=device)
    assert n.shape == (*shape, 3) and np.all(np.isfinite(n))
    if shape == (1, 1):
        assert np.array_equal(n[0, 0], np.float32([0, 1, 0]))
    elif min(shape) > 1:
        assert angle_deg(n, exact_normals(s, xx, zz)).max() < 1e-4


# --- normal map ----------------------------------------------------------------------------------------

def test_normal_map_encoding(device):
    flat = compute_normals(np.zeros((4, 5), np.float32), "sobel", device=device)
    img = normal_map_image(flat, device=device)
    assert img.dtype == np.uint8 and img.shape == (4, 5, 3)
    assert np.all(img == np.uint8([128, 128, 255]))  # the blue of flat ground
    assert np.all(normal_map_image(flat, layout="xyz", device=device) == np.uint8([128, 255, 128]))
    hm = Heightmap.example()
    n = compute_normals(hm, "sobel", border="clamp", device=device)
    rgb = normal_map_image(n, device=device)
    back = decode_normal_map(rgb)
    assert angle_deg(n, back).max() < 0.6  # 8-bit quantisation: 1/255 per component
    # a slope rising to +x tilts the normal to -x: red below 128
    ramp = compute_normals(np.tile(np.arange(5, dtype=np.float32), (3, 1)), "edge", device=device)
    assert np.all(normal_map_image(ramp, device=device)[..., 0] < 128)
    with pytest.raises(ValueError, match="layout"):
        normal_map_image(flat, layout="zyx", device=device)


# --- determinism and validation --------------------------------------------------------------------------

def test_deterministic(device):
    hm = Heightmap.example()
    for m in METHODS:
        assert digest(compute_normals(hm, m, device=device)) == digest(compute_normals(hm, m, device=device))


def test_bad_arguments():
    h = np.zeros((3, 3), np.float32)
    with pytest.raises(ValueError, match="method"):
        compute_normals(h, "sobol")
    with pytest.raises(ValueError, match="border"):
        compute_normals(h, "sobel", border="wrap")
    with pytest.raises(ValueError, match="dx"):
        compute_normals(h, "edge", dx=0.0)
    with pytest.raises(ValueError, match="dz"):
        compute_normals(h, "edge", dz=float("nan"))
    with pytest.raises(ValueError, match="heightmap"):
        compute_normals(np.zeros((0, 3), np.float32))
    with pytest.raises(TypeError, match="heightmap"):
        compute_normals([[1.0]])
    with pytest.raises(ValueError, match="infinite"):
        compute_normals(np.float64([[1.0, 1e39]]))  # overflows float32
    with pytest.raises(ValueError, match="dx, dz"):
        compute_normals(Heightmap.from_array(h), dx=2.0)


def test_all_surfaces_finite():
    for name, f in SURFACES.items():
        h, _, _ = grid(f(), 40, 30, DX, DZ)
        for m in METHODS:
            n = normals(h, m)
            assert np.all(np.isfinite(n)), name
