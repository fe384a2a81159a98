"""A real OpenGL 4.5 tessellator (Mesa llvmpipe through EGL) as a test oracle.

Each patch is one GL_PATCHES primitive of 4 vertices. The tessellation control shader reads the
patch's 6 levels from a storage buffer (so NaN and any float32 bit pattern reach the hardware
unchanged); the evaluation shader has ``layout(quads, <spacing>, ccw)`` and passes ``gl_TessCoord``
and the patch number on; a geometry shader appends every triangle's three tess coordinates, in the
order the primitive generator emitted them, to a storage buffer with an atomic counter and emits
nothing (so nothing is rasterized).

llvmpipe (Mesa 22.3) draws wrong geometry once one tessellated draw call generates more than about
65,536 vertices, so patches are drawn in batches bounded by our own triangle counts.

Usage::

    oracle = GLOracle()                     # raises OracleUnavailable without EGL / GL 4.5
    tris = oracle.triangles(levels, "fractional_odd")   # levels (P, 6): outer[4], inner[2]
    # tris[p] is a set of rotation-normalised triangles (24-byte keys: u0 v0 u1 v1 u2 v2 float32)
"""

from __future__ import annotations

import numpy as np

__all__ = ["GLOracle", "OracleUnavailable", "normalise", "normalise_array", "triangle_set"]

_VS = """
#version 450
void main() { gl_Position = vec4(0.0); }
"""

_TCS = """
#version 450
layout(vertices = 4) out;
layout(std430, binding = 1) readonly buffer Levels { float lv[]; };
uniform int base;
void main() {
    gl_out[gl_InvocationID].gl_Position = vec4(0.0);
    int p = (base + gl_PrimitiveID) * 6;
    if (gl_InvocationID == 0) {
        gl_TessLevelOuter[0] = lv[p + 0];
        gl_TessLevelOuter[1] = lv[p + 1];
        gl_TessLevelOuter[2] = lv[p + 2];
        gl_TessLevelOuter[3] = lv[p + 3];
        gl_TessLevelInner[0] = lv[p + 4];
        gl_TessLevelInner[1] = lv[p + 5];
    }
}
"""

_TES = """
#version 450
layout(quads, SPACING, ccw) in;
uniform int base;
out vec2 tc;
flat out int pid;
void main() {
    tc = gl_TessCoord.xy;
    pid = base + gl_PrimitiveID;
    gl_Position = vec4(gl_TessCoord.xy, 0.0, 1.0);
}
"""

_GS = """
#version 450
layout(triangles) in;
layout(points, max_vertices = 1) out;
in vec2 tc[];
flat in int pid[];
layout(std430, binding = 2) buffer Out { uint count; uint cap; float rec[]; };
void main() {
    uint k = atomicAdd(count, 1u);
    if (k < cap) {
        uint o = k * 8u;
        rec[o + 0u] = float(pid[0]);
        rec[o + 1u] = tc[0].x; rec[o + 2u] = tc[0].y;
        rec[o + 3u] = tc[1].x; rec[o + 4u] = tc[1].y;
        rec[o + 5u] = tc[2].x; rec[o + 6u] = tc[2].y;
        rec[o + 7u] = 0.0;
    }
}
"""

_GL_SPACING = {"equal": "equal_spacing", "fractional_even": "fractional_even_spacing",
               "fractional_odd": "fractional_odd_spacing"}
_BATCH_VERTICES = 48000  # well under llvmpipe's ~65,536 generated vertices per draw


class OracleUnavailable(RuntimeError):
    """EGL or an OpenGL 4.5 context is not available on this machine."""


def normalise(tri) -> tuple:
    """Rotate a triangle (3 (u, v) tuples) so its smallest vertex comes first; winding is kept."""
    tri = [tuple(float(c) for c in p) for p in tri]
    k = min(range(3), key=lambda j: tri[j])
    return tuple(tri[k:] + tri[:k])


def normalise_array(tris: np.ndarray) -> set:
    """Vectorised :func:`normalise` of (m, 3, 2) triangles, as a set of 24-byte keys (float32 bits)."""
    t = np.ascontiguousarray(tris, dtype=np.float32).reshape(-1, 3, 2)
    if t.shape[0] == 0:
        return set()
    # lexicographic (u, then v), exactly: u is a multiple of 2^-16, so steps of 2^17 u exceed any v in [0, 1]
    key = t[:, :, 0].astype(np.float64) * 131072.0 + t[:, :, 1]
    k = np.argmin(key, axis=1)
    idx = (k[:, None] + np.arange(3)[None, :]) % 3
    rot = np.ascontiguousarray(np.take_along_axis(t, idx[:, :, None], axis=1))
    return set(rot.reshape(-1, 6).view(np.dtype((np.void, 24))).reshape(-1).tolist())


def triangle_set(uv: np.ndarray, triangles: np.ndarray) -> set:
    """The set of normalised triangles of a mesh in domain coordinates (see :func:`normalise_array`)."""
    return normalise_array(np.asarray(uv, np.float32)[np.asarray(triangles, np.int64).reshape(-1, 3)])


class GLOracle:
    """Capture the triangles Mesa's tessellator generates for quad patches."""

    def __init__(self):
        try:
            import moderngl

            self._mgl = moderngl
            self.ctx = moderngl.create_context(standalone=True, backend="egl", require=450)
        except Exception as e:  # no EGL / no GL 4.5 / no moderngl
            raise OracleUnavailable(str(e)) from e
        self.renderer = self.ctx.info.get("GL_RENDERER", "?")
        self._programs = {}
        self._fbo = self.ctx.simple_framebuffer((1, 1))

    def _program(self, spacing: str):
        if spacing not in self._programs:
            prog = self.ctx.program(vertex_shader=_VS, tess_control_shader=_TCS,
                                    tess_evaluation_shader=_TES.replace("SPACING", _GL_SPACING[spacing]),
                                    geometry_shader=_GS)
            vao = self.ctx.vertex_array(prog, [])
            self._programs[spacing] = (prog, vao)
        return self._programs[spacing]

    def raw(self, levels: np.ndarray, spacing: str, max_triangles: np.ndarray | None = None) -> list[np.ndarray]:
        """Per patch, an (m, 3, 2) float32 array of the triangles' tess coords in emission order
        (the order between triangles is whatever the GPU's threads made it; only the set counts).

        Args:
            levels: (P, 6) float32 outer[0..3], inner[0..1] per patch.
            spacing: "equal", "fractional_even" or "fractional_odd".
            max_triangles: (P,) an upper bound of each patch's triangle count (for batching); 8192
                (level 64 everywhere) when not given.
        """
        lv = np.ascontiguousarray(levels, dtype=np.float32).reshape(-1, 6)
        n = lv.shape[0]
        bound = np.full(n, 8192, np.int64) if max_triangles is None else np.asarray(max_triangles, np.int64)
        prog, vao = self._program(spacing)
        self.ctx.patch_vertices = 4
        self._fbo.use()
        lbuf = self.ctx.buffer(lv.tobytes())
        lbuf.bind_to_storage_buffer(1)
        out: list[list[np.ndarray]] = [[] for _ in range(n)]
        start = 0
        while start < n:
            stop, total = start, 0
            while stop < n and (stop == start or total + 3 * bound[stop] <= _BATCH_VERTICES):
                total += 3 * bound[stop]
                stop += 1
            cap = int(max(total // 3, 1)) + 16
            obuf = self.ctx.buffer(np.array([0, cap], np.uint32).tobytes() + bytes(cap * 32))
            obuf.bind_to_storage_buffer(2)
            prog["base"].value = start
            vao.render(mode=self._mgl.PATCHES, vertices=4 * (stop - start))
            self.ctx.finish()
            data = obuf.read()
            count = int(np.frombuffer(data[:4], np.uint32)[0])
            if count > cap:
                raise RuntimeError(f"oracle: {count} triangles exceed the buffer of {cap}")
            rec = np.frombuffer(data[8:8 + count * 32], np.float32).reshape(-1, 8)
            pid = rec[:, 0].astype(np.int64)
            for p in range(start, stop):
                out[p].append(rec[pid == p, 1:7].reshape(-1, 3, 2))
            obuf.release()
            start = stop
        lbuf.release()
        return [np.concatenate(o) if o else np.zeros((0, 3, 2), np.float32) for o in out]

    def triangles(self, levels: np.ndarray, spacing: str, max_triangles=None) -> list[set]:
        """Per patch, the set of normalised triangles (see :func:`normalise_array`)."""
        return [normalise_array(r) for r in self.raw(levels, spacing, max_triangles)]
