"""Every kernel module compiles to CUDA (sm_90 PTX through NVRTC, no GPU needed): the CUDA side of the
``func_native`` helpers (CPU-only row loops that return 0 on CUDA, true atomics, bit casts) and every kernel
are checked on machines without a GPU. Cold, ~35 s on 2 cores; an unchanged module comes from Warp's cache."""

import re

import pytest
import warp as wp
from cuda_codegen import compile_all, kernel_modules, nvrtc_archs


@pytest.fixture(scope="module")
def ptx():
    if 90 not in nvrtc_archs():
        pytest.skip("this Warp build has no NVRTC for sm_90 (CUDA code generation cannot be checked here)")
    return {name: (path, text) for name, _, path, text in compile_all(90, workers=2)}


def test_every_kernel_module_compiles_to_sm90_ptx_with_each_kernel(ptx):
    names = kernel_modules()
    assert len(names) >= 19 and "terrainwarp.kernels.tessellator" in names  # the list is the folder's modules
    assert set(ptx) == set(names)
    for name in names:
        path, text = ptx[name]
        assert path.suffix == ".ptx" and re.search(r"^\.target sm_90\b", text, re.M), name
        entries = set(re.findall(r"\.entry (\w+)", text))
        for key in wp.get_module(name).kernels:  # each kernel's forward entry point (none is skipped)
            assert any(e.startswith(key) and e.endswith("cuda_kernel_forward") for e in entries), (name, key)


def test_true_atomics_compile_to_cudas(ptx):
    """kernels/parallel.py's atomics (a CAS loop on the CPU) are CUDA's atomicMin / atomicAdd on the GPU: the error
    pass's triangle minimum, the gradients' counts, the rasterizer's list slots. The rasterizer's depth test needs
    none (one thread draws a screen tile)."""
    assert re.search(r"atom\.global\.min\.s32", ptx["terrainwarp.kernels.sample_error"][1])
    assert re.search(r"atom\.global\.add\.(u|s)32", ptx["terrainwarp.kernels.gradients"][1])
    raster = ptx["terrainwarp.kernels.raster"][1]
    assert re.search(r"atom\.global\.add\.(u|s)32", raster) and not re.search(r"atom\.global\.min", raster)
