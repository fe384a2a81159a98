"""An OpenGL oracle for the rasterizer: Mesa's llvmpipe (OpenGL 4.5 through EGL) via moderngl.

The same clip-space vertices are drawn by llvmpipe into a framebuffer object with a 32-bit float
depth attachment (``GL_DEPTH_COMPONENT32F``, ``GL_LESS``) and ``gl_PrimitiveID + 1`` written to an
``R32I`` colour target. The vertex shader passes clip coordinates through unchanged, so both
rasterizers start from bit-identical float32 clip positions. Readback is bottom-up; it is flipped
once here so that images have row 0 at the top, as terrainwarp's do.

llvmpipe (Mesa 22.3) draws wrong geometry past ~65,536 vertices in one tessellated draw; draws here
are plain, but are still split into chunks of ``CHUNK`` triangles with a primitive-id offset.
"""

from __future__ import annotations

import numpy as np

from terrainwarp.experiments.gl import GLMesh, new_context
from terrainwarp.experiments.gl import renderer as context_renderer

CHUNK = 20000


def available() -> bool:
    """Whether an EGL OpenGL 4.5 context can be created."""
    try:
        new_context().release()
        return True
    except Exception:  # noqa: BLE001 -- any failure means no oracle
        return False


def renderer() -> str:
    ctx = new_context()
    try:
        return context_renderer(ctx)
    finally:
        ctx.release()


class GLRaster(GLMesh):
    """An llvmpipe framebuffer of one size in a context of its own
    (:class:`terrainwarp.experiments.gl.GLMesh`); ``draw`` returns (ids, depth, seconds), drawing in
    chunks of ``CHUNK`` triangles.

    The context is made current when created and moderngl issues its calls to whatever context is
    current: another library that makes its own EGL context current (VTK does, even when only a
    ``pyvista.Plotter`` is created) must not run between creating a ``GLRaster`` and using it. Create
    one, use it, ``close()`` it.
    """

    def draw(self, uploaded, *, cull_back: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
        """Clear, draw, ``glFinish``; returns ids (H, W) int32 (-1 background), depth (H, W) float32
        window depth (1.0 background), row 0 at the top, and the draw time in seconds."""
        n = uploaded[1].size // 12
        chunks = np.array([(s, min(s + CHUNK, n)) for s in range(0, n, CHUNK)], np.int64).reshape(-1, 2)
        ids, dep, dt, _, _ = super().draw(uploaded, chunks, cull_back=cull_back)
        return ids, dep, dt


def gl_rasterize(clip: np.ndarray, triangles: np.ndarray, width: int, height: int, *,
                 cull_back: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Draw (m, 3) int32 triangles over (n, 4) float32 clip-space vertices with llvmpipe.

    Returns:
        ids (H, W) int32 (-1 background) and depth (H, W) float32 window depth, row 0 at the top.
    """
    if not len(triangles):
        return np.full((height, width), -1, np.int32), np.ones((height, width), np.float32)
    g = GLRaster(width, height)
    try:
        up = g.upload(clip, triangles)
        ids, dep, _ = g.draw(up, cull_back=cull_back)
        g.release(up)
    finally:
        g.close()
    return ids, dep
