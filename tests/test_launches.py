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
    default = str(wp.get_device())  # cuda:0 on a GPU machine
    out = wp.empty(8, dtype=wp.float32, device="cpu")
    out_default = wp.empty(8, dtype=wp.float32, device=default)
    with LaunchRecorder() as rec:
        launch(_double, 8, [view(a, wp.float32, "cpu")], [out], "cpu")  # the parallel helper, on the CPU
        wp.launch(_double, 8, inputs=[0, view(a, wp.float32, default)], outputs=[out_default])  # no device given
    assert np.array_equal(out.numpy(), 2 * a) and np.array_equal(out_default.numpy(), 2 * a)
    key = _double.key
    assert rec.seen == {"cpu": {key}, default: {key}}
    assert rec.elsewhere("cpu") == ({} if default == "cpu" else {default: [key]})
    assert rec.elsewhere("cuda:0") == {"cpu": [key]}  # a test on cuda:0 that ran this would fail
    assert "launch" in wp.launch.__qualname__ and "LaunchRecorder" not in wp.launch.__qualname__  # put back
