"""A real OpenGL 4.5 driver (Mesa's llvmpipe here, any driver through EGL) drawing terrainwarp's frames as a
GPU would, with its pipeline statistics (ARB_pipeline_statistics_query) and draw times: the oracle the
counters are checked against (tests) and the driver the cost model is fitted to (:mod:`.calibrate`).

* :class:`GLTerrain`: a quadtree frame's patches, one 4-vertex ``GL_PATCHES`` primitive each (the control
  points carry nothing: the corners come from a storage buffer of per-patch records, :func:`patch_records`),
  a tessellation control shader that sets ``gl_TessLevelOuter/Inner`` from the records (the PatchList's
  ``outer``/``inner``, OpenGL order), a ``layout(quads, <spacing>, ccw)`` evaluation shader that places the
  domain point on the patch's extent in heightmap cells (u along +x, v along +z), clamps it to the grid as
  terrainwarp's domain shader does, samples the heightmap from an ``R32F`` texture (``GL_LINEAR``, clamp to
  edge, texel centres: sample (i, j) at ((j + 0.5) / W, (i + 0.5) / H)) and writes ``mvp * (camera-relative
  position, 1)``, with ``mvp`` = ``proj @ view(relative=True)`` rounded to float32 as the rasterizer uses.
* :class:`GLMesh`: an indexed triangle mesh given in clip coordinates (``terrainwarp.kernels.raster.
  clip_coordinates``: the vertex shader passes them on, so llvmpipe rasterizes bit-identical vertices), drawn
  as one ``glDrawElements`` per draw range (the draws a family issues).

Both draw into a framebuffer with an ``R32I`` id target (the patch or triangle number, -1 background) and a
32-bit float depth attachment (``GL_LESS``, cleared to 1.0), in a context of their own, made current for each
call (several may be open at once): create one, use it, ``close()`` it. Readback is flipped once so that images
have row 0 at the top.

llvmpipe (Mesa 22.3) draws wrong geometry once one tessellated draw call generates more than about 65,536
vertices: :class:`GLTerrain` draws the patches in consecutive batches of fewer than ``BATCH_VERTICES``
(:func:`batches`; a uniform ``base`` offsets ``gl_PrimitiveID`` so patch numbers stay global).

:data:`GL_COUNTERS` maps terrainwarp's counter names (lower-case GL names) to the query targets;
``primitives_generated`` and ``samples_passed`` are GL's own queries, the others ARB_pipeline_statistics_query's.
"""

from __future__ import annotations

import ctypes
import time
from typing import Any

import numpy as np

from ..kernels.raster import clip_coordinates

__all__ = ["GL_COUNTERS", "GLUnavailable", "new_context", "depth32f", "renderer", "Statistics", "GLTerrain",
           "GLMesh", "FrameDriver", "patch_records", "batches", "BATCH_VERTICES"]

GL_COUNTERS = {
    "vertices_submitted": 0x82EE,
    "primitives_submitted": 0x82EF,
    "vertex_shader_invocations": 0x82F0,
    "tess_control_shader_patches": 0x82F1,
    "tess_evaluation_shader_invocations": 0x82F2,
    "clipping_input_primitives": 0x82F6,
    "clipping_output_primitives": 0x82F7,
    "fragment_shader_invocations": 0x82F4,
    "primitives_generated": 0x8C87,
    "samples_passed": 0x8914,
}
_GL_QUERY_RESULT = 0x8866
_GL_TEXTURE_2D = 0x0DE1
_GL_DEPTH_COMPONENT32F = 0x8CAC
_GL_DEPTH_COMPONENT = 0x1902
_GL_FLOAT = 0x1406
BATCH_VERTICES = 60000  # 3 x triangles per tessellated draw; llvmpipe breaks past ~65,536 generated vertices
_GL_SPACING = {"equal": "equal_spacing", "fractional_even": "fractional_even_spacing",
               "fractional_odd": "fractional_odd_spacing"}


class GLUnavailable(OSError):
    """No OpenGL 4.5 context through EGL here (or moderngl is not installed: ``pip install moderngl``)."""


def new_context() -> Any:
    """A standalone moderngl context through EGL, OpenGL 4.5 (:class:`GLUnavailable` when there is none)."""
    try:
        import moderngl  # lazy: heavy optional dependency
    except ImportError as e:
        raise GLUnavailable(f"moderngl is not installed ({e}); pip install moderngl") from None
    try:
        return moderngl.create_context(standalone=True, backend="egl", require=450)
    except Exception as e:  # noqa: BLE001 -- any failure means no driver
        raise GLUnavailable(f"no OpenGL 4.5 context through EGL: {e}") from None


def renderer(ctx: Any) -> str:
    """``GL_RENDERER / GL_VERSION`` of a context."""
    return f"{ctx.info['GL_RENDERER']} / {ctx.info['GL_VERSION']}"


def _gl(ctx: Any, name: str, restype: Any, *argtypes: Any) -> Any:
    """A raw GL function of the context (through eglGetProcAddress)."""
    return ctypes.CFUNCTYPE(restype, *argtypes)(ctx.mglo._context.load(name))


def depth32f(ctx: Any, width: int, height: int) -> Any:
    """A depth texture re-specified as GL_DEPTH_COMPONENT32F (moderngl defaults to 24 bits)."""
    tex = ctx.depth_texture((width, height))
    u, i = ctypes.c_uint, ctypes.c_int
    bind = _gl(ctx, "glBindTexture", None, u, u)
    teximage = _gl(ctx, "glTexImage2D", None, u, i, i, i, i, i, u, u, ctypes.c_void_p)
    bind(_GL_TEXTURE_2D, tex.glo)
    teximage(_GL_TEXTURE_2D, 0, _GL_DEPTH_COMPONENT32F, width, height, 0, _GL_DEPTH_COMPONENT, _GL_FLOAT, None)
    bind(_GL_TEXTURE_2D, 0)
    return tex


class Statistics:
    """Every query of :data:`GL_COUNTERS` around a block of draws: ``begin()``, draw, ``end()`` -> counts."""

    def __init__(self, ctx: Any):
        u = ctypes.c_uint
        self._gen = _gl(ctx, "glGenQueries", None, ctypes.c_int, ctypes.POINTER(u))
        self._begin = _gl(ctx, "glBeginQuery", None, u, u)
        self._end = _gl(ctx, "glEndQuery", None, u)
        self._get = _gl(ctx, "glGetQueryObjectui64v", None, u, u, ctypes.POINTER(ctypes.c_uint64))
        self._delete = _gl(ctx, "glDeleteQueries", None, ctypes.c_int, ctypes.POINTER(u))
        self._ids = (u * len(GL_COUNTERS))()
        self._gen(len(GL_COUNTERS), self._ids)

    def begin(self) -> None:
        for q, target in zip(self._ids, GL_COUNTERS.values(), strict=True):
            self._begin(target, q)

    def end(self) -> dict[str, int]:
        for target in GL_COUNTERS.values():
            self._end(target)
        out = {}
        for q, name in zip(self._ids, GL_COUNTERS, strict=True):
            v = ctypes.c_uint64()
            self._get(q, _GL_QUERY_RESULT, ctypes.byref(v))
            out[name] = int(v.value)
        return out

    def release(self) -> None:
        self._delete(len(GL_COUNTERS), self._ids)


class _Target:
    """A framebuffer of one size with an R32I id target and a 32-bit float depth attachment, in a context of
    its own, with the statistics queries."""

    def __init__(self, width: int, height: int):
        import moderngl  # lazy: heavy optional dependency

        self._mgl = moderngl
        self.ctx = ctx = new_context()
        self.width, self.height = int(width), int(height)
        self.renderer = renderer(ctx)
        self.color = ctx.texture((self.width, self.height), 1, dtype="i4")
        self.depth = depth32f(ctx, self.width, self.height)
        self.fbo = ctx.framebuffer(color_attachments=[self.color], depth_attachment=self.depth)
        self.stats = Statistics(ctx)
        self.timer = ctx.query(time=True)  # GL_TIME_ELAPSED: the GPU's own clock on a real GPU
        self.last_gpu_ms = float("nan")  # the timer's milliseconds of the last timed draw

    def _clear(self) -> None:
        ctx, mgl = self.ctx, self._mgl
        self.fbo.use()
        ctx.viewport = (0, 0, self.width, self.height)
        ctx.enable(mgl.DEPTH_TEST)
        ctx.depth_func = "<"
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.color.write(np.full(self.width * self.height, -1, np.int32).tobytes())
        ctx.finish()

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        ids = np.frombuffer(self.color.read(), dtype=np.int32).reshape(self.height, self.width)[::-1]
        dep = np.frombuffer(self.depth.read(), dtype=np.float32).reshape(self.height, self.width)[::-1]
        return np.ascontiguousarray(ids), np.ascontiguousarray(dep)

    def _timed(self, draw, counters: bool) -> tuple[dict[str, int] | None, float, float]:
        """Clear, then ``draw()`` inside the statistics queries (when ``counters``) and the timer query, and
        ``glFinish``: (counts, wall s, CPU s of this process: every llvmpipe thread); the timer's milliseconds
        (the draws on the GPU's clock) in ``last_gpu_ms``."""
        self._clear()
        t0, c0 = time.perf_counter(), time.process_time()
        if counters:
            self.stats.begin()
        with self.timer:
            draw()
        got = self.stats.end() if counters else None
        self.ctx.finish()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        self.last_gpu_ms = self.timer.elapsed / 1e6
        return got, wall, cpu

    def close(self) -> None:
        with self.ctx:
            for o in self._objects():
                if o is not None:
                    o.release()
            self.stats.release()
            self.fbo.release()
            self.color.release()
            self.depth.release()
        self.ctx.release()

    def _objects(self) -> list:
        return []


_TERRAIN_VS = """
#version 450
void main() { gl_Position = vec4(0.0); }
"""

_TERRAIN_TCS = """
#version 450
layout(vertices = 4) out;
struct Patch { vec4 box; vec4 outer; vec4 inner; };   // box: (col0, row0, cols, rows) in cells
layout(std430, binding = 1) readonly buffer Patches { Patch pt[]; };
uniform int base;
void main() {
    if (gl_InvocationID == 0) {
        Patch p = pt[base + gl_PrimitiveID];
        gl_TessLevelOuter[0] = p.outer.x;
        gl_TessLevelOuter[1] = p.outer.y;
        gl_TessLevelOuter[2] = p.outer.z;
        gl_TessLevelOuter[3] = p.outer.w;
        gl_TessLevelInner[0] = p.inner.x;
        gl_TessLevelInner[1] = p.inner.y;
    }
}
"""

_TERRAIN_TES = """
#version 450
layout(quads, SPACING, ccw) in;
struct Patch { vec4 box; vec4 outer; vec4 inner; };
layout(std430, binding = 1) readonly buffer Patches { Patch pt[]; };
uniform int base;
uniform sampler2D heights;      // R32F, GL_LINEAR, clamp to edge
uniform vec2 grid_max;          // (W - 1, H - 1)
uniform vec2 tex_size;          // (W, H)
uniform vec2 eye_cells;         // eye (x, z) in cells, integer part (exact in float32)
uniform vec3 eye_rem;           // (x, z) remainder in metres, y = eye height
uniform vec2 cell;              // (dx, dz) metres
uniform mat4 mvp;
flat out int pid;
void main() {
    int p = base + gl_PrimitiveID;
    vec4 box = pt[p].box;
    vec2 g = clamp(box.xy + gl_TessCoord.xy * box.zw, vec2(0.0), grid_max);
    float h = textureLod(heights, (g + 0.5) / tex_size, 0.0).r;
    vec2 rel = (g - eye_cells) * cell - eye_rem.xz;
    gl_Position = mvp * vec4(rel.x, h - eye_rem.y, rel.y, 1.0);
    pid = p;
}
"""

_ID_FS = """
#version 450
flat in int pid;
layout(location = 0) out int out_id;
void main() { out_id = pid; }
"""


def patch_records(origin: np.ndarray, size: np.ndarray, outer: np.ndarray, inner: np.ndarray,
                  grid_origin, dx: float, dz: float) -> np.ndarray:
    """(P, 12) float32 storage-buffer records: box (col0, row0, cols, rows), outer[4], inner[2], pad[2].

    Args:
        origin, size: (P, 2) float64 world (x, z) corner and extent of each patch (PatchList).
        outer, inner: (P, 4), (P, 2) float32 levels, OpenGL order.
        grid_origin: world (x, z) of sample (0, 0); dx, dz: spacing in metres.
    """
    p = len(origin)
    rec = np.zeros((p, 12), np.float32)
    scale = np.array([1.0 / dx, 1.0 / dz])
    rec[:, 0:2] = (np.asarray(origin, np.float64) - np.asarray(grid_origin, np.float64)) * scale
    rec[:, 2:4] = np.asarray(size, np.float64).reshape(p, -1) * scale
    rec[:, 4:8] = outer
    rec[:, 8:10] = inner
    return rec


def batches(triangle_offsets: np.ndarray, limit: int = BATCH_VERTICES) -> list[tuple[int, int]]:
    """Consecutive (start, stop) patch ranges with 3 x triangles <= ``limit`` (a patch alone may exceed it)."""
    t = np.asarray(triangle_offsets, np.int64)
    out, start, n = [], 0, len(t) - 1
    while start < n:
        stop = start + 1
        while stop < n and 3 * (t[stop + 1] - t[start]) <= limit:
            stop += 1
        out.append((start, stop))
        start = stop
    return out


class GLTerrain(_Target):
    """The driver drawing tessellated terrain patches at one viewport (see the module docstring)."""

    def __init__(self, width: int, height: int, heights: np.ndarray, dx: float, dz: float, spacing: str = "equal"):
        super().__init__(width, height)
        ctx, mgl = self.ctx, self._mgl
        self.prog = ctx.program(vertex_shader=_TERRAIN_VS, tess_control_shader=_TERRAIN_TCS,
                                tess_evaluation_shader=_TERRAIN_TES.replace("SPACING", _GL_SPACING[spacing]),
                                fragment_shader=_ID_FS)
        self.vao = ctx.vertex_array(self.prog, [])
        h = np.ascontiguousarray(heights, dtype=np.float32)
        rows, cols = h.shape
        self.tex = ctx.texture((cols, rows), 1, data=h.tobytes(), dtype="f4")  # row i = texture row i
        self.tex.filter = (mgl.LINEAR, mgl.LINEAR)
        self.tex.repeat_x = self.tex.repeat_y = False  # clamp to edge
        self.tex.use(0)
        self.prog["heights"].value = 0
        self.prog["grid_max"].value = (float(cols - 1), float(rows - 1))
        self.prog["tex_size"].value = (float(cols), float(rows))
        self.dx, self.dz = float(dx), float(dz)
        self.prog["cell"].value = (self.dx, self.dz)
        self.ssbo = None

    def _objects(self) -> list:
        return [self.ssbo, self.tex, self.vao, self.prog]

    def set_camera(self, eye, grid_origin, view: np.ndarray, proj: np.ndarray) -> None:
        """Eye (world x, y, z, float64), the grid's world (x, z) origin and the OpenGL matrices (relative view)."""
        with self.ctx:
            self._set_camera(eye, grid_origin, view, proj)

    def _set_camera(self, eye, grid_origin, view: np.ndarray, proj: np.ndarray) -> None:
        e = np.asarray(eye, np.float64)
        ec = (e[[0, 2]] - np.asarray(grid_origin, np.float64)) / (self.dx, self.dz)
        ei = np.floor(ec)
        rem = (ec - ei) * (self.dx, self.dz)
        self.prog["eye_cells"].value = (float(ei[0]), float(ei[1]))
        self.prog["eye_rem"].value = (float(rem[0]), float(e[1]), float(rem[1]))
        mvp = (np.asarray(proj, np.float64) @ np.asarray(view, np.float64)).astype(np.float32)
        self.prog["mvp"].write(np.ascontiguousarray(mvp.T).tobytes())  # GLSL matrices are column-major

    def draw(self, records: np.ndarray, ranges: list[tuple[int, int]], *, counters: bool = False
             ) -> tuple[np.ndarray, np.ndarray, float, float, dict[str, int] | None]:
        """Upload the (P, 12) patch records, clear, draw every batch, ``glFinish``.

        Returns:
            patch ids (H, W) int32 (-1 background), depth (H, W) float32 window depth (1.0 background), row 0 at
            the top; the seconds from the upload to the end of ``glFinish`` and the CPU seconds this process
            (every llvmpipe thread) spent meanwhile; the pipeline statistics of the draws (``counters``).
        """
        with self.ctx:
            return self._draw(records, ranges, counters)

    def _draw(self, records: np.ndarray, ranges: list[tuple[int, int]], counters: bool):
        ctx, mgl = self.ctx, self._mgl
        data = np.ascontiguousarray(records, np.float32).tobytes()
        if self.ssbo is None or self.ssbo.size != max(len(data), 48):
            if self.ssbo is not None:
                self.ssbo.release()
            self.ssbo = ctx.buffer(reserve=max(len(data), 48))
        ctx.disable(mgl.CULL_FACE)
        ctx.patch_vertices = 4
        base = self.prog["base"]

        def run() -> None:
            if data:
                self.ssbo.write(data)
            self.ssbo.bind_to_storage_buffer(1)
            for start, stop in ranges:
                base.value = start
                self.vao.render(mode=mgl.PATCHES, vertices=4 * (stop - start))

        got, dt, dc = self._timed(run, counters)
        ids, dep = self._read()
        return ids, dep, dt, dc, got


_MESH_VS = """
#version 450
in vec4 in_clip;
void main() { gl_Position = in_clip; }
"""
_MESH_FS = """
#version 450
uniform int id_offset;
layout(location = 0) out int out_id;
void main() { out_id = gl_PrimitiveID + id_offset; }
"""


class GLMesh(_Target):
    """The driver drawing indexed triangles given in clip coordinates (see the module docstring)."""

    def __init__(self, width: int, height: int):
        super().__init__(width, height)
        self.prog = self.ctx.program(vertex_shader=_MESH_VS, fragment_shader=_MESH_FS)
        self._held: list = []

    def _objects(self) -> list:
        return [*self._held, self.prog]

    def upload(self, clip: np.ndarray, triangles: np.ndarray) -> tuple:
        """Vertex and index buffers (kept apart from the timed draws; :meth:`release` them)."""
        with self.ctx:
            return self._upload(clip, triangles)

    def _upload(self, clip: np.ndarray, triangles: np.ndarray) -> tuple:
        vbo = self.ctx.buffer(np.ascontiguousarray(clip, dtype=np.float32).tobytes())
        ibo = self.ctx.buffer(np.ascontiguousarray(triangles, dtype=np.int32).tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "4f", "in_clip")], index_buffer=ibo, index_element_size=4)
        return vbo, ibo, vao

    def release(self, uploaded: tuple) -> None:
        with self.ctx:
            for o in reversed(uploaded):
                o.release()

    def draw(self, uploaded: tuple, draws: np.ndarray | None = None, *, cull_back: bool = False,
             counters: bool = False) -> tuple[np.ndarray, np.ndarray, float, float, dict[str, int] | None]:
        """Clear, draw, ``glFinish``.

        Args:
            uploaded: :meth:`upload`'s buffers.
            draws: (D, 2) int64 triangle ranges [first, stop), one ``glDrawElements`` each, in order (None: one
                draw of every triangle).

        Returns:
            triangle ids (H, W) int32 (-1 background) and depth (H, W) float32, row 0 at the top; the wall and
            CPU seconds of the draws and ``glFinish``; the pipeline statistics (``counters``).
        """
        with self.ctx:
            return self._draw(uploaded, draws, cull_back, counters)

    def _draw(self, uploaded: tuple, draws: np.ndarray | None, cull_back: bool, counters: bool):
        ctx, mgl = self.ctx, self._mgl
        vao = uploaded[2]
        n = uploaded[1].size // 12
        ranges = [(0, n)] if draws is None else [(int(a), int(b)) for a, b in np.asarray(draws).reshape(-1, 2)]
        if cull_back:
            ctx.enable(mgl.CULL_FACE)
            ctx.front_face = "ccw"
            ctx.cull_face = "back"
        else:
            ctx.disable(mgl.CULL_FACE)
        offset = self.prog["id_offset"]

        def run() -> None:
            for a, b in ranges:
                if b > a:
                    offset.value = a
                    vao.render(mgl.TRIANGLES, vertices=3 * (b - a), first=3 * a)

        got, dt, dc = self._timed(run, counters)
        ids, dep = self._read()
        return ids, dep, dt, dc, got


class FrameDriver:
    """The driver drawing terrainwarp :class:`terrainwarp.rendering.pipeline.Frame` s as their families draw them,
    with one framebuffer per (kind, viewport, spacing) made on first use and kept until :meth:`close`: a LOD frame
    (its ``patches`` and ``mesh``) through the tessellation shaders (:class:`GLTerrain`), any other frame's mesh
    as indexed triangles of its clip-space vertices, one draw per draw call of its family (:class:`GLMesh`,
    ``mesh.draws``: its ranges over the triangles in the order the draws take them). ``indexed=True`` draws a LOD
    frame's mesh as indexed triangles too (one draw)."""

    def __init__(self):
        self.targets: dict[tuple, _Target] = {}
        self.renderer = ""
        self.last: Any = None  # the target of the latest draws(): its last_gpu_ms is the latest draw's GPU time

    def _target(self, key: tuple, make) -> Any:
        if key not in self.targets:
            self.targets[key] = make()
            self.renderer = self.targets[key].renderer
        return self.targets[key]

    def draws(self, frame: Any, *, indexed: bool = False) -> tuple[Any, Any]:
        """(``draw(counters=False)`` -> the target's draw's result, ``release()``) for ``frame``."""
        hm, cam, mesh = frame.scene.heightmap, frame.scene.camera, frame.mesh
        w, h = cam.width, cam.height
        if frame.scene.mesh == "lod" and not indexed:
            pl, spacing = frame.patches, frame.scene.lod.spacing
            g = self._target(("patches", w, h, spacing, id(hm)),
                             lambda: GLTerrain(w, h, hm.heights, hm.dx, hm.dz, spacing))
            g.set_camera(cam.position, hm.origin, cam.view_matrix(relative=True), cam.proj_matrix())
            t_off = np.concatenate([[0], np.cumsum(np.bincount(mesh.patch_id[mesh.triangles[:, 0]],
                                                               minlength=len(pl)))])
            rec = patch_records(pl.origin, pl.size, pl.outer, pl.inner, hm.origin, hm.dx, hm.dz)
            ranges = batches(t_off)
            self.last = g
            return (lambda counters=False: g.draw(rec, ranges, counters=counters)), (lambda: None)
        g = self.last = self._target(("mesh", w, h), lambda: GLMesh(w, h))
        d = None if indexed else mesh.draws
        tri = mesh.triangles if d is None or d.order is None else mesh.triangles[d.order]
        up = g.upload(clip_coordinates(mesh.positions, cam.view_matrix(relative=True), cam.proj_matrix()), tri)
        return (lambda counters=False: g.draw(up, None if d is None else d.ranges, counters=counters)), \
            (lambda: g.release(up))

    def statistics(self, frame: Any, *, indexed: bool = False) -> dict[str, int]:
        """The driver's pipeline statistics of one draw of ``frame`` (see the class docstring)."""
        draw, release = self.draws(frame, indexed=indexed)
        try:
            return draw(True)[4]
        finally:
            release()

    def close(self) -> None:
        for g in self.targets.values():
            g.close()
        self.targets.clear()
