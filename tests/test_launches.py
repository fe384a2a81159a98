"""The device fixture's check (tests/launches.py): launches are recorded by device, and a launch on another
device than the test's is reported."""

import numpy as np
import warp as wp
from launches import LaunchRecorder

from terrainwarp.kernels.parallel import launch, view


@wp.kernel(enable_backward=False)
def _double(offset: int, a: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    i = wp.tid() + offset
    out[i] = 2.0 * a[i]


def test_launches_are_recorded_by_device_and_other_devices_reported():
    a = np.arange(8, dtype=np.float32)
    out = wp.empty(8, dtype=wp.float32, device="cpu")
    with LaunchRecorder() as rec:
        launch(_double, 8, [view(a, wp.float32, "cpu")], [out], "cpu")  # the parallel helper
        wp.launch(_double, 8, inputs=[0, view(a, wp.float32, "cpu")], outputs=[out])  # the default device
    assert np.array_equal(out.numpy(), 2 * a)
    key = _double.key
    assert rec.seen == {str(wp.get_device()): {key}}
    assert rec.elsewhere("cpu") == ({} if str(wp.get_device()) == "cpu" else {str(wp.get_device()): [key]})
    assert rec.elsewhere("cuda:0") == {"cpu": [key]}  # a test on cuda:0 that ran this would fail
    assert wp.launch is not None and "LaunchRecorder" not in getattr(wp.launch, "__qualname__", "")
