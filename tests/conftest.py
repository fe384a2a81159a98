import pytest
import warp as wp

import terrainwarp
from terrainwarp.io.files import digest  # noqa: F401  (the one digest; tests import it from here)

terrainwarp.configure(quiet=True)  # Warp's log level before any kernel loads (importing changes nothing)

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


def pytest_configure(config):
    config.addinivalue_line("markers", "host_launches: a device test whose reference launches kernels on the CPU "
                                       "too (the device fixture then checks only that the device was used)")


@pytest.fixture(params=DEVICES)
def device(request, monkeypatch):
    """Each Warp device in turn ("cpu", and "cuda:0" where Warp sees a GPU). Every kernel the test launches
    (wp.launch, which parallel.launch calls) must run on that device: a code path that drops the device and
    falls back to the default (cuda:0 on a GPU machine) or to the CPU fails the test, naming the kernels.
    A test marked ``host_launches`` (its reference runs on the CPU) needs only one launch on the device."""
    name = request.param
    want = wp.get_device(name)
    seen: dict[str, set[str]] = {}
    real = wp.launch

    def launch(kernel, *args, **kw):
        dev = kw.get("device")
        dev = wp.get_device(dev if dev is not None else args[5] if len(args) > 5 else None)
        seen.setdefault(str(dev), set()).add(getattr(kernel, "key", str(kernel)))
        return real(kernel, *args, **kw)

    monkeypatch.setattr(wp, "launch", launch)
    yield name
    monkeypatch.undo()
    elsewhere = {d: sorted(k) for d, k in seen.items() if d != str(want)}
    if request.node.get_closest_marker("host_launches") is not None:
        assert not seen or str(want) in seen, f"nothing launched on {want}: {seen}"
    else:
        assert not elsewhere, f"a test on {want} launched kernels on another device: {elsewhere}"
