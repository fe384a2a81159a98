import numpy as np
import pytest

from terrainwarp import Heightmap
from terrainwarp.heightmap import HOST_SAMPLES
from terrainwarp.kernels.sampling import sample_grid


def _grid(f, h=12, w=15):
    i, j = np.mgrid[0:h, 0:w].astype(np.float64)
    return f(j, i)


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_plane_reproduced(method):
    def plane(u, v):
        return 3.0 + 0.75 * u - 1.25 * v

    h = _grid(plane).astype(np.float32)
    rng = np.random.default_rng(0)
    u = rng.uniform(0, 14, 500)
    v = rng.uniform(0, 11, 500)
    got = sample_grid(h, u, v, method)
    np.testing.assert_allclose(got, plane(u.astype(np.float32), v.astype(np.float32)), atol=2e-5)


def test_bilinear_exact_at_samples_and_midpoints():
    h = np.array([[0.0, 2.0], [4.0, 8.0]], np.float32)
    got = sample_grid(h, np.array([0.0, 1.0, 0.5, 0.5, 0.0]), np.array([0.0, 1.0, 0.0, 0.5, 0.5]))
    np.testing.assert_array_equal(got, [0.0, 8.0, 1.0, 3.5, 2.0])


def test_bicubic_reproduces_cubic_along_each_axis():
    def cub(t):
        return 0.02 * t**3 - 0.3 * t**2 + 1.5 * t - 2.0

    hx = _grid(lambda u, v: cub(u) + 0 * v).astype(np.float32)
    hz = _grid(lambda u, v: cub(v) + 0 * u).astype(np.float32)
    rng = np.random.default_rng(1)
    t = rng.uniform(1.0, 10.0, 300)  # interior: the 4-sample support is inside the grid
    other = rng.uniform(0, 11, 300)
    np.testing.assert_allclose(sample_grid(hx, t, other, "bicubic"), cub(t), atol=2e-4)
    np.testing.assert_allclose(sample_grid(hz, other, t, "bicubic"), cub(t), atol=2e-4)
    # ... which bilinear does not: the check above is able to fail.
    assert np.abs(sample_grid(hx, t, other, "bilinear") - cub(t)).max() > 1e-2


def test_local_reference_keeps_millimetres_on_everest():
    base = np.float32(8848.0)
    rel = np.array([[0.0, 0.004], [0.002, 0.006]], np.float32)
    h = base + rel
    got = sample_grid(h, np.array([0.5]), np.array([0.5]))
    exact = np.float64(h.astype(np.float64).mean())
    assert abs(float(got[0]) - exact) <= np.spacing(base)  # one ulp at 8848 m is ~1 mm


def test_heightmap_sample_world_coordinates_and_clamp():
    hm = Heightmap.from_array(np.array([[0.0, 10.0], [20.0, 30.0]]), dx=2.0, dz=4.0, origin=(100.0, 50.0))
    got = hm.sample([100.0, 102.0, 101.0, 0.0], [50.0, 54.0, 52.0, 0.0])
    np.testing.assert_allclose(got, [0.0, 30.0, 15.0, 0.0])


def test_bad_method():
    with pytest.raises(ValueError, match="method"):
        sample_grid(np.zeros((2, 2), np.float32), [0.0], [0.0], "nearest")


def test_a_few_points_sampled_on_the_host_are_the_kernels_bits():
    """Heightmap.sample of at most HOST_SAMPLES points runs on the host: the device filter's bits, inside, outside
    and on the grid's samples and border."""
    for hm in (Heightmap.example(), Heightmap.fbm(65, seed=3, dx=7.3, max_height=900.0)):
        rng = np.random.default_rng(1)
        (x0, z0), (x1, z1) = hm.bounds_xz
        x, z = rng.uniform(x0 - 50, x1 + 50, 4 * HOST_SAMPLES), rng.uniform(z0 - 50, z1 + 50, 4 * HOST_SAMPLES)
        x[:HOST_SAMPLES] = np.round(x[:HOST_SAMPLES] / hm.dx) * hm.dx + hm.origin[0]  # on sample columns
        want = sample_grid(hm.heights, (x - hm.origin[0]) / hm.dx, (z - hm.origin[1]) / hm.dz, "bilinear")
        got = np.concatenate([hm.sample(x[i:i + HOST_SAMPLES], z[i:i + HOST_SAMPLES])
                              for i in range(0, len(x), HOST_SAMPLES)])
        assert got.dtype == np.float32 and np.array_equal(got.view(np.uint32), want.view(np.uint32))
        assert hm.sample(x[0], z[0]).shape == ()
