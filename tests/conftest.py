import pytest
import warp as wp
from launches import LaunchRecorder

import terrainwarp
from terrainwarp.io.files import digest  # noqa: F401  (the one digest; tests import it from here)

terrainwarp.configure(quiet=True)  # Warp's log level before any kernel loads (importing changes nothing)

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


def pytest_configure(config):
    config.addinivalue_line("markers", "host_launches: a device test whose reference launches kernels on the CPU "
                                       "too (the device fixture then checks only that the device was used)")


@pytest.fixture(params=DEVICES)
def device(request):
    """Each Warp device in turn ("cpu", and "cuda:0" where Warp sees a GPU). Every kernel the test launches
    must run on that device: a code path that drops the device and falls back to the default (cuda:0 on a GPU
    machine) or to the CPU fails the test, naming the kernels. A test marked ``host_launches`` (its reference
    runs on the CPU) needs only one launch on the device."""
    name = str(wp.get_device(request.param))
    with LaunchRecorder() as rec:
        yield request.param
    if request.node.get_closest_marker("host_launches") is not None:
        assert not rec.seen or name in rec.seen, f"nothing launched on {name}: {rec.seen}"
    else:
        assert not rec.elsewhere(name), f"a test on {name} launched kernels on another device: {rec.elsewhere(name)}"


@pytest.fixture
def jax_device(request, device):
    """The test's Warp device as JAX's default device (the diff ops run their Warp kernels on the device of JAX's
    arrays): the CPU, or JAX's GPU for "cuda:0". The scenes are drawn on the CPU (tw.rasterize), so the test is
    marked ``host_launches``: the device fixture then checks that the op's kernels ran on the device."""
    import jax  # lazy: heavy optional dependency

    try:
        dev = jax.devices("cpu" if device == "cpu" else "gpu")[0]
    except RuntimeError:
        pytest.skip(f"JAX has no backend for {device} here (Warp sees it)")
    request.node.add_marker(pytest.mark.host_launches)
    with jax.default_device(dev):
        yield device
