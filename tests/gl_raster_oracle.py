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

import ctypes
import time

import numpy as np

GL_TEXTURE_2D = 0x0DE1
GL_DEPTH_COMPONENT32F = 0x8CAC
GL_DEPTH_COMPONENT = 0x1902
GL_FLOAT = 0x1406
CHUNK = 20000

_VS = """
#version 450
in vec4 in_clip;
void main() { gl_Position = in_clip; }
"""
_FS = """
#version 450
uniform int id_offset;
layout(location = 0) out int out_id;
void main() { out_id = gl_PrimitiveID + id_offset + 1; }
"""

def _new_context():
    import moderngl

    return moderngl.create_context(standalone=True, backend="egl", require=450)


def available() -> bool:
    """Whether an EGL OpenGL 4.5 context can be created."""
    try:
        _new_context().release()
        return True
    except Exception:  # noqa: BLE001 -- any failure means no oracle
        return False


def renderer() -> str:
    ctx = _new_context()
    try:
        return f"{ctx.info['GL_RENDERER']} / {ctx.info['GL_VERSION']}"
    finally:
        ctx.release()


def _depth32f(ctx, width: int, height: int):
    """A depth texture re-specified as GL_DEPTH_COMPONENT32F (moderngl defaults to 24 bits)."""
    tex = ctx.depth_texture((width, height))
    load = ctx.mglo._context.load
    bind = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_uint)(load("glBindTexture"))
    teximage = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                                ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p)(
                                    load("glTexImage2D"))
    bind(GL_TEXTURE_2D, tex.glo)
    teximage(GL_TEXTURE_2D, 0, GL_DEPTH_COMPONENT32F, width, height, 0, GL_DEPTH_COMPONENT, GL_FLOAT, None)
    bind(GL_TEXTURE_2D, 0)
    return tex


class GLRaster:
    """An llvmpipe framebuffer of one size in a context of its own; ``draw`` returns (ids, depth, seconds).

    The context is made current when created and moderngl issues its calls to whatever context is
    current: another library that makes its own EGL context current (VTK does, even when only a
    ``pyvista.Plotter`` is created) must not run between creating a ``GLRaster`` and using it. Create
    one, use it, ``close()`` it.
    """

    def __init__(self, width: int, height: int):
        import moderngl

        ctx = _new_context()
        self.ctx, self.width, self.height = ctx, width, height
        self.prog = ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        self.color = ctx.texture((width, height), 1, dtype="i4")
        self.depth = _depth32f(ctx, width, height)
        self.fbo = ctx.framebuffer(color_attachments=[self.color], depth_attachment=self.depth)
        self._moderngl = moderngl

    def upload(self, clip: np.ndarray, triangles: np.ndarray):
        """Upload vertex and index buffers (kept apart from the timed draw)."""
        ctx = self.ctx
        vbo = ctx.buffer(np.ascontiguousarray(clip, dtype=np.float32).tobytes())
        tri = np.ascontiguousarray(triangles, dtype=np.int32)
        vaos = []
        for s in range(0, len(tri), CHUNK):
            ibo = ctx.buffer(tri[s:s + CHUNK].tobytes())
            vao = ctx.vertex_array(self.prog, [(vbo, "4f", "in_clip")], index_buffer=ibo,
                                   index_element_size=4)
            vaos.append((s, vao, ibo))
        return vbo, vaos

    def draw(self, uploaded, *, cull_back: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
        """Clear, draw, ``glFinish``; returns ids (H, W) int32 (-1 background), depth (H, W) float32
        window depth (1.0 background), row 0 at the top, and the draw time in seconds."""
        ctx, mgl = self.ctx, self._moderngl
        vbo, vaos = uploaded
        self.fbo.use()
        ctx.viewport = (0, 0, self.width, self.height)
        ctx.enable(mgl.DEPTH_TEST)
        ctx.depth_func = "<"
        if cull_back:
            ctx.enable(mgl.CULL_FACE)
            ctx.front_face = "ccw"
            ctx.cull_face = "back"
        else:
            ctx.disable(mgl.CULL_FACE)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.finish()
        t0 = time.perf_counter()
        for s, vao, _ in vaos:
            self.prog["id_offset"].value = s
            vao.render(mgl.TRIANGLES)
        ctx.finish()
        dt = time.perf_counter() - t0
        ids = np.frombuffer(self.color.read(), dtype=np.int32).reshape(self.height, self.width)[::-1] - 1
        dep = np.frombuffer(self.depth.read(), dtype=np.float32).reshape(self.height, self.width)[::-1]
        return np.ascontiguousarray(ids), np.ascontiguousarray(dep), dt

    def close(self) -> None:
        self.fbo.release()
        self.color.release()
        self.depth.release()
        self.prog.release()
        self.ctx.release()

    def release(self, uploaded) -> None:
        vbo, vaos = uploaded
        for _, vao, ibo in vaos:
            vao.release()
            ibo.release()
        vbo.release()


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
