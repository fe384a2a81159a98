import pytest
import warp as wp

import terrainwarp
from terrainwarp.io.files import digest  # noqa: F401  (the one digest; tests import it from here)

terrainwarp.configure(quiet=True)  # Warp's log level before any kernel loads (importing changes nothing)

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param
