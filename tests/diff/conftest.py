import jax
import pytest


@pytest.fixture
def jax_device(request, device):
    """The test's Warp device as JAX's default device (the ops run their Warp kernels on the device of JAX's
    arrays): the CPU, or JAX's GPU for "cuda:0". The scenes are drawn on the CPU (tw.rasterize), so the test is
    marked ``host_launches``: the device fixture then checks that the op's kernels ran on the device."""
    try:
        dev = jax.devices("cpu" if device == "cpu" else "gpu")[0]
    except RuntimeError:
        pytest.skip(f"JAX has no backend for {device} here (Warp sees it)")
    request.node.add_marker(pytest.mark.host_launches)
    with jax.default_device(dev):
        yield device
