"""terrainwarp's device side: Warp kernels, one module per pipeline stage.

Import as ``terrainwarp.kernels`` (never as a top-level ``kernels``). Nothing here imports JAX,
pyvista or touches files.
"""
