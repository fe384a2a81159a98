import pytest
import warp as wp

import terrainwarp  # noqa: F401  (sets warp's log level before any kernel loads)
from terrainwarp.io.files import digest  # noqa: F401  (the one digest; tests import it from here)

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param
