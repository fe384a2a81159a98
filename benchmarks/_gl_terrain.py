"""A tessellated terrain frame drawn by Mesa's llvmpipe with real OpenGL 4.5 tessellation shaders.

The GPU way of drawing the patches terrainwarp selects: one ``GL_PATCHES`` primitive of 4 control
points per patch (the control points carry nothing: the corners come from per-patch data), a
tessellation control shader that sets ``gl_TessLevelOuter/Inner`` from a storage buffer (the
PatchList's ``outer``/``inner``, OpenGL order), a ``layout(quads, <spacing>, ccw)`` evaluation shader
that places the domain point on the patch's extent in heightmap cells (u along +x, v along +z),
clamps it to the grid as terrainwarp's domain shader does, samples the heightmap from an ``R32F``
texture (``GL_LINEAR``, clamp to edge, texel-centre addressing: sample (i, j) at texture coordinate
((j + 0.5) / W, (i + 0.5) / H)) and writes ``mvp * (camera-relative position, 1)``; a fragment shader
that writes the patch number to an ``R32I`` target, into a framebuffer with a 32-bit float depth
attachment (``GL_LESS``). The ``mvp`` uniform is ``proj @ view(relative=True)`` rounded to float32,
as terrainwarp's rasterizer uses.

llvmpipe (Mesa 22.3) draws wrong geometry once one tessellated draw call generates more than about
65,536 vertices, so the patches are drawn in consecutive batches whose triangle count times 3 stays
under ``BATCH_VERTICES`` (a uniform ``base`` offsets ``gl_PrimitiveID`` so patch numbers stay global).

A context of its own per :class:`GLTerrain` (see ``tests/gl_raster_oracle.py``): create, use, close.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from gl_raster_oracle import _depth32f, _new_context  # noqa: E402

BATCH_VERTICES = 60000  # 3 x triangles per draw; llvmpipe breaks past ~65,536 generated vertices
GL_SPACING = {"equal": "equal_spacing", "fractional_even": "fractional_even_spacing",
              "fractional_odd": "fractional_odd_spacing"}

_VS = """
#version 450
void main() { gl_Position = vec4(0.0); }
"""

_TCS = """
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

_TES = """
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

_FS = """
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


class GLTerrain:
    """llvmpipe drawing tessellated terrain patches at one viewport; ``draw`` -> (patch ids, depth, seconds)."""

    def __init__(self, width: int, height: int, heights: np.ndarray, dx: float, dz: float, spacing: str = "equal"):
        import moderngl

        self._mgl = moderngl
        ctx = _new_context()
        self.ctx, self.width, self.height = ctx, width, height
        self.renderer = f"{ctx.info['GL_RENDERER']} / {ctx.info['GL_VERSION']}"
        self.prog = ctx.program(vertex_shader=_VS, tess_control_shader=_TCS,
                                tess_evaluation_shader=_TES.replace("SPACING", GL_SPACING[spacing]),
                                fragment_shader=_FS)
        self.vao = ctx.vertex_array(self.prog, [])
        h = np.ascontiguousarray(heights, dtype=np.float32)
        rows, cols = h.shape
        self.tex = ctx.texture((cols, rows), 1, data=h.tobytes(), dtype="f4")  # row i = texture row i
        self.tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.tex.repeat_x = self.tex.repeat_y = False  # clamp to edge
        self.tex.use(0)
        self.prog["heights"].value = 0
        self.prog["grid_max"].value = (float(cols - 1), float(rows - 1))
        self.prog["tex_size"].value = (float(cols), float(rows))
        self.dx, self.dz = float(dx), float(dz)
        self.prog["cell"].value = (self.dx, self.dz)
        self.color = ctx.texture((width, height), 1, dtype="i4")
        self.depth = _depth32f(ctx, width, height)
        self.fbo = ctx.framebuffer(color_attachments=[self.color], depth_attachment=self.depth)
        self.ssbo = None

    def set_camera(self, eye, grid_origin, view: np.ndarray, proj: np.ndarray) -> None:
        """Eye (world x, y, z, float64), the grid's world (x, z) origin and the OpenGL matrices (relative view)."""
        e = np.asarray(eye, np.float64)
        ec = (e[[0, 2]] - np.asarray(grid_origin, np.float64)) / (self.dx, self.dz)
        ei = np.floor(ec)
        rem = (ec - ei) * (self.dx, self.dz)
        self.prog["eye_cells"].value = (float(ei[0]), float(ei[1]))
        self.prog["eye_rem"].value = (float(rem[0]), float(e[1]), float(rem[1]))
        mvp = (np.asarray(proj, np.float64) @ np.asarray(view, np.float64)).astype(np.float32)
        self.prog["mvp"].write(np.ascontiguousarray(mvp.T).tobytes())  # GLSL matrices are column-major

    def draw(self, records: np.ndarray, ranges: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Upload the (P, 12) patch records, clear, draw every batch, ``glFinish``.

        Returns:
            patch ids (H, W) int32 (-1 background), depth (H, W) float32 window depth (1.0 background),
            row 0 at the top, the seconds from the upload to the end of ``glFinish``, and the CPU seconds
            this process (every llvmpipe thread) spent meanwhile.
        """
        ctx, mgl = self.ctx, self._mgl
        data = np.ascontiguousarray(records, np.float32).tobytes()
        if self.ssbo is None or self.ssbo.size != max(len(data), 48):
            if self.ssbo is not None:
                self.ssbo.release()
            self.ssbo = ctx.buffer(reserve=max(len(data), 48))
        self.fbo.use()
        ctx.viewport = (0, 0, self.width, self.height)
        ctx.enable(mgl.DEPTH_TEST)
        ctx.disable(mgl.CULL_FACE)
        ctx.depth_func = "<"
        ctx.patch_vertices = 4
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.color.write(np.full(self.width * self.height, -1, np.int32).tobytes())
        ctx.finish()
        t0, c0 = time.perf_counter(), time.process_time()
        if data:
            self.ssbo.write(data)
        self.ssbo.bind_to_storage_buffer(1)
        base = self.prog["base"]
        for start, stop in ranges:
            base.value = start
            self.vao.render(mode=mgl.PATCHES, vertices=4 * (stop - start))
        ctx.finish()
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        ids = np.frombuffer(self.color.read(), dtype=np.int32).reshape(self.height, self.width)[::-1]
        dep = np.frombuffer(self.depth.read(), dtype=np.float32).reshape(self.height, self.width)[::-1]
        return np.ascontiguousarray(ids), np.ascontiguousarray(dep), dt, dc

    def close(self) -> None:
        for o in (self.ssbo, self.fbo, self.color, self.depth, self.tex, self.vao, self.prog):
            if o is not None:
                o.release()
        self.ctx.release()


def run_saved(path: str, reps: int) -> tuple[float, float]:
    """Best draw wall and CPU seconds of ``reps`` after a warm-up, for a frame saved by the benchmark (child
    processes)."""
    d = np.load(path)
    g = GLTerrain(int(d["width"]), int(d["height"]), d["heights"], float(d["dx"]), float(d["dz"]),
                  str(d["spacing"]))
    try:
        g.set_camera(d["eye"], d["grid_origin"], d["view"], d["proj"])
        ranges = [tuple(r) for r in d["ranges"].tolist()]
        g.draw(d["records"], ranges)
        runs = [g.draw(d["records"], ranges)[2:] for _ in range(reps)]
        return min(r[0] for r in runs), min(r[1] for r in runs)
    finally:
        g.close()


if __name__ == "__main__":
    print(*run_saved(sys.argv[1], int(sys.argv[2])))
