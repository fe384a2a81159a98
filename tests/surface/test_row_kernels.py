"""The row kernels of normals and curvature (kernels/normals.py, kernels/curvature.py): the native interior
loop (a row whose window is inside the grid and NaN-free) gives the general per-sample path's bits, and
neither depends on the thread count."""

import numpy as np
import pytest
import warp as wp
from conftest import digest

from terrainwarp import Heightmap, compute_curvature, compute_normals
from terrainwarp.kernels import parallel
from terrainwarp.kernels.normals import vertex_normals_device
from terrainwarp.kernels.parallel import set_threads
from terrainwarp.surface.differential import surface_curvature

NORMALS = ["sobel", "edge"]  # the row kernels; triangle and quad keep the per-sample kernel
CHORDS = ["three_vertex", "edge_angle"]
NORMAL_BASED = [("two_normal", {}), ("three_normal", {}), ("two_normal", {"normals": "edge"}),
                ("three_normal", {"normals": "sobel", "scale": 2.0}),
                ("three_normal", {"distance": 2})]  # reinforced: the general path everywhere
SCHEMES = ["zevenbergen_thorne", "evans_young"]


def rough(shape=(61, 75), seed=11):
    """fBm plus steep noise (chords turning by more than 90 degrees: edge_angle's cos <= 0 branch), a flat
    patch (zero gradient: profile and plan are 0 there) and an 8,848 m offset (cancellation)."""
    rng = np.random.default_rng(seed)
    h = Heightmap.fbm(max(shape), seed=seed, max_height=900.0).heights[:shape[0], :shape[1]].astype(np.float64)
    h += rng.normal(0.0, 40.0, shape) * (rng.random(shape) < 0.3)
    h[20:26, 30:38] = 1234.5
    return (h + 8848.0).astype(np.float32)


def bits(a):
    return np.ascontiguousarray(a).view(np.uint32)


def general_everywhere(h):
    """``h`` with a NaN in column 0 of every third row: every row's 3-row window then holds a NaN, so every
    row takes the general path; columns >= 3 (beyond the NaN's reach, 2 samples for a one-sided chord
    stencil) are the same samples with the same neighbours as in ``h``."""
    g = h.copy()
    g[::3, 0] = np.nan
    return g


FAR = (slice(None), slice(3, None))


@pytest.mark.parametrize("method", NORMALS)
@pytest.mark.parametrize("border", ["constant", "clamp", "skip"])
def test_normals_fast_path_is_general_path(method, border):
    h = rough()
    fast = compute_normals(h, method, border=border, constant=500.0, dx=1.3, dz=0.8)
    slow = compute_normals(general_everywhere(h), method, border=border, constant=500.0, dx=1.3, dz=0.8)
    assert np.array_equal(bits(fast[FAR]), bits(slow[FAR]))
    assert not np.array_equal(bits(fast[:, :1]), bits(slow[:, :1]))  # the NaN column did change (control)


@pytest.mark.parametrize("method", NORMALS)
def test_normals_non_contiguous_input_takes_general_path(method):
    a = rough((40, 90))
    strided = wp.array(a, dtype=wp.float32, device="cpu")[:, ::2]  # not contiguous: no native rows
    assert not strided.is_contiguous
    contiguous = wp.array(np.ascontiguousarray(a[:, ::2]), dtype=wp.float32, device="cpu")
    slow = vertex_normals_device(strided, 1.3, 0.8, method, "clamp").numpy()
    fast = vertex_normals_device(contiguous, 1.3, 0.8, method, "clamp").numpy()
    assert np.array_equal(bits(fast), bits(slow))


@pytest.mark.parametrize("method", CHORDS)
@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_chord_curvature_fast_path_is_general_path(method, scale):
    h = rough()
    fast = compute_curvature(h, method, scale=scale, dx=1.3, dz=0.8)
    slow = compute_curvature(general_everywhere(h), method, scale=scale, dx=1.3, dz=0.8)
    assert np.array_equal(bits(fast[FAR]), bits(slow[FAR]))
    if method == "edge_angle":  # the steep noise reaches the cos <= 0 branch and the clamp at 1
        assert (fast[FAR] > 0.5).any()


@pytest.mark.parametrize(("method", "kw"), NORMAL_BASED)
def test_normal_based_curvature_fast_path_is_general_path(method, kw):
    h = rough()
    fast = compute_curvature(h, method, dx=1.3, dz=0.8, **kw)
    slow = compute_curvature(general_everywhere(h), method, dx=1.3, dz=0.8, **kw)
    far = (slice(None), slice(3 * kw.get("distance", 1), None))
    assert np.array_equal(bits(fast[far]), bits(slow[far]))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_surface_curvature_fast_path_is_general_path(scheme):
    h = rough()
    fast = surface_curvature(h, scheme, dx=1.3, dz=0.8)
    slow = surface_curvature(general_everywhere(h), scheme, dx=1.3, dz=0.8)
    for name in fast:
        assert fast[name].flags.c_contiguous
        assert np.array_equal(bits(fast[name][FAR]), bits(slow[name][FAR])), name
    assert (fast["profile"][21:25, 31:37] == 0).all()  # the flat patch: zero gradient


def test_one_far_nan_changes_only_its_neighbourhood():
    """A NaN sends its rows down the general path; everything beyond its stencil reach stays bit-identical."""
    h = rough()
    holed = h.copy()
    holed[30, 40] = np.nan
    keep = np.ones(h.shape, bool)
    keep[28:33, 38:43] = False
    for m in NORMALS:
        assert np.array_equal(bits(compute_normals(h, m)[keep]), bits(compute_normals(holed, m)[keep]))
    for m in [*CHORDS, "two_normal", "three_normal"]:
        assert np.array_equal(bits(compute_curvature(h, m)[keep]), bits(compute_curvature(holed, m)[keep]))
    for s in SCHEMES:
        a, b = surface_curvature(h, s), surface_curvature(holed, s)
        assert all(np.array_equal(bits(a[k][keep]), bits(b[k][keep])) for k in a)


def _digests(h):
    out = {}
    for m in NORMALS:
        for border in ("constant", "clamp", "skip"):
            out[f"normals.{m}.{border}"] = digest(compute_normals(h, m, border=border))
    for m in CHORDS:
        out[f"curvature.{m}"] = digest(compute_curvature(h, m))
    for m, kw in NORMAL_BASED:
        out[f"curvature.{m}.{kw}"] = digest(compute_curvature(h, m, **kw))
    for s in SCHEMES:
        out[f"surface.{s}"] = digest(*surface_curvature(h, s).values())
    return out


def test_identical_for_any_thread_count():
    h = rough((97, 64))
    h[::17, 5::23] = np.nan  # some rows native, some general, in every chunk
    got = {}
    try:
        parallel.set_min_items(1)
        for n in (1, 2, 3, 5):
            set_threads(n)
            got[n] = _digests(h)
    finally:
        parallel.set_min_items(None)
        set_threads(None)
    for n in (2, 3, 5):
        assert got[n] == got[1], n
