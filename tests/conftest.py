import hashlib

import numpy as np
import pytest
import warp as wp

import terrainwarp  # noqa: F401  (sets warp's log level before any kernel loads)

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()
