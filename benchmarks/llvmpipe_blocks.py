"""Where ``fragment_shader_invocations_llvmpipe`` of a tessellated frame differs from llvmpipe's query, and why.

Our count equals llvmpipe's when llvmpipe draws our clip-space vertices as indexed triangles (bench_counters.py:
"ours vs indexed" is +0.000% on every frame). Against llvmpipe's tessellated draw of the same patches it may
differ by a block or a few. This script draws the frames of bench_counters.py's llvmpipe table with llvmpipe's
tessellation shaders plus a geometry shader that writes out every triangle it rasterizes (patch, tessellation
coordinates, clip position of each vertex), then:

1. rasterizes llvmpipe's own clip positions with our rasterizer (our 4x4-block count on its vertices);
2. matches llvmpipe's triangles to ours (patch and tessellation coordinates) and lists, by bisection on the
   block sums, the triangles whose blocks differ with the blocks and how far their vertices are apart.

What it showed (issue 46's note has the numbers): llvmpipe's evaluation shader places vertices 1 to ~100 ulp
(clip space) from ours, a few hundredths of a 1/256 sub-pixel step in the window, which moves a covered centre in
or out of a triangle now and then: a 4x4 block. And llvmpipe applies the viewport transform to tessellation output
in C, with separate roundings (x * (1/w) * scale + translate), where a vertex shader's output goes through its
fused JIT path (which the rasterizer follows, so indexed draws of our vertices match to the block): with that
transform (``_window`` in kernels/raster.py without ``_fma``, a temporary edit), our rasterizer on llvmpipe's
own vertices gives its query exactly on all six frames.

    .venv/bin/python benchmarks/llvmpipe_blocks.py     # ~1 min on 2 cores; prints its findings
"""

from __future__ import annotations

import sys

import numpy as np

from terrainwarp import Camera, Heightmap, Scene, render
from terrainwarp.experiments import gl
from terrainwarp.kernels.raster import clip_coordinates, rasterize_clip
from terrainwarp.lod import Terrain
from terrainwarp.scene import LodConfig

W, H = 1920, 1080
# the evaluation shader of experiments.gl with the tessellation coordinates passed on, and a geometry shader that
# appends every triangle (patch, then u, v, x, y, z, w of each vertex) to a storage buffer and passes it on
_TES = gl._TERRAIN_TES.replace("flat out int pid;", "flat out int pid;\nout vec2 tc;").replace(
    "    pid = p;", "    pid = p;\n    tc = gl_TessCoord.xy;")
_GS = """
#version 450
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;
flat in int pid[];
in vec2 tc[];
flat out int gpid;
layout(std430, binding = 2) buffer Out { uint count; uint cap; float rec[]; };
void main() {
    uint k = atomicAdd(count, 1u);
    if (k < cap) {
        uint o = k * 20u;
        rec[o] = float(pid[0]);
        for (int i = 0; i < 3; ++i) {
            rec[o + 1u + 6u * uint(i)] = tc[i].x;
            rec[o + 2u + 6u * uint(i)] = tc[i].y;
            for (int c = 0; c < 4; ++c) rec[o + 3u + 6u * uint(i) + uint(c)] = gl_in[i].gl_Position[c];
        }
    }
    for (int i = 0; i < 3; ++i) {
        gl_Position = gl_in[i].gl_Position;
        gpid = pid[0];
        EmitVertex();
    }
    EndPrimitive();
}
"""
_FS = gl._ID_FS.replace("flat in int pid;", "flat in int gpid;").replace("out_id = pid;", "out_id = gpid;")


def llvmpipe_triangles(frame) -> tuple[np.ndarray, dict[str, int]]:
    """llvmpipe's triangles of a LOD frame in the order it rasterized them: (T, 20) float32 rows (patch, then u, v,
    x, y, z, w per vertex), and the pipeline statistics of the draw."""
    hm, cam, pl, mesh = frame.scene.heightmap, frame.scene.camera, frame.patches, frame.mesh
    g = gl.GLTerrain(W, H, hm.heights, hm.dx, hm.dz, frame.scene.lod.spacing)
    try:
        with g.ctx:
            g.prog = g.ctx.program(vertex_shader=gl._TERRAIN_VS, tess_control_shader=gl._TERRAIN_TCS,
                                   tess_evaluation_shader=_TES.replace("SPACING",
                                                                       gl._GL_SPACING[frame.scene.lod.spacing]),
                                   geometry_shader=_GS, fragment_shader=_FS)
            g.vao = g.ctx.vertex_array(g.prog, [])
            rows, cols = hm.heights.shape
            g.prog["heights"].value = 0
            g.prog["grid_max"].value = (float(cols - 1), float(rows - 1))
            g.prog["tex_size"].value = (float(cols), float(rows))
            g.prog["cell"].value = (g.dx, g.dz)
            cap = 2 * mesh.n_triangles + 16
            out = g.ctx.buffer(np.array([0, cap], np.uint32).tobytes() + bytes(4 * 20 * cap))
            out.bind_to_storage_buffer(2)
        g.set_camera(cam.position, hm.origin, cam.view_matrix(relative=True), cam.proj_matrix())
        t_off = np.concatenate([[0], np.cumsum(np.bincount(mesh.patch_id[mesh.triangles[:, 0]], minlength=len(pl)))])
        rec = gl.patch_records(pl.origin, pl.size, pl.outer, pl.inner, hm.origin, hm.dx, hm.dz)
        stats = g.draw(rec, gl.batches(t_off), counters=True)[4]
        with g.ctx:
            raw = np.frombuffer(out.read(), np.uint32)
            n = int(raw[0])
            tris = np.frombuffer(out.read(), np.float32)[2:2 + 20 * n].reshape(n, 20).copy()
            out.release()
    finally:
        g.close()
    return tris, stats


def _blocks(clip: np.ndarray, tris: np.ndarray) -> int:
    """The 4x4 blocks with a covered centre, per triangle, summed (our rasterizer)."""
    if len(tris) == 0:
        return 0
    return rasterize_clip(clip, tris, W, H, counters=True).counters["fragment_shader_invocations_llvmpipe"] // 16


def _block_set(clip: np.ndarray) -> set[tuple[int, int]]:
    """The window 4x4 blocks (bx, by) with a covered centre of one triangle."""
    f = rasterize_clip(clip, np.array([[0, 1, 2]], np.int32), W, H)
    ys, xs = np.nonzero(f.triangle_id >= 0)
    return {(int(x) // 4, int(H - 1 - y) // 4) for y, x in zip(ys, xs, strict=True)}


def _pairs(frame, theirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Our and llvmpipe's clip positions of the same triangles ((T, 3, 4) each, matched by patch and tessellation
    coordinates, llvmpipe's vertex order), and how many of llvmpipe's found no match."""
    mesh, pl, hm, cam = frame.mesh, frame.patches, frame.scene.heightmap, frame.scene.camera
    oc = clip_coordinates(mesh.positions, cam.view_matrix(relative=True), cam.proj_matrix())
    rec = gl.patch_records(pl.origin, pl.size, pl.outer, pl.inner, hm.origin, hm.dx, hm.dz)
    pid = mesh.patch_id
    tc = (mesh.uv * (np.array(hm.shape[::-1], np.float64) - 1) - rec[pid, 0:2]) / rec[pid, 2:4]
    vert = {(int(pid[v]), round(float(tc[v, 0]), 3), round(float(tc[v, 1]), 3)): v for v in np.unique(mesh.triangles)}
    ours, their, missed = [], [], 0
    for row in theirs:
        vs = [vert.get((int(row[0]), round(float(row[1 + 6 * i]), 3), round(float(row[2 + 6 * i]), 3)))
              for i in range(3)]
        if None in vs:
            missed += 1
            continue
        ours.append(oc[vs])
        their.append(row[[3, 4, 5, 6, 9, 10, 11, 12, 15, 16, 17, 18]].reshape(3, 4))
    return np.array(ours, np.float32), np.array(their, np.float32), missed


def _differing(ours: np.ndarray, theirs: np.ndarray, lo: int, hi: int, out: list[int]) -> None:
    """The triangles in [lo, hi) whose block counts differ, by bisection on the sums."""
    tri = lambda n: np.arange(3 * n, dtype=np.int32).reshape(n, 3)  # noqa: E731
    if _blocks(ours[lo:hi].reshape(-1, 4), tri(hi - lo)) == _blocks(theirs[lo:hi].reshape(-1, 4), tri(hi - lo)):
        return
    if hi - lo == 1:
        out.append(lo)
        return
    mid = (lo + hi) // 2
    _differing(ours, theirs, lo, mid, out)
    _differing(ours, theirs, mid, hi, out)


def explain(name: str, frame) -> None:
    """Print where the frame's llvmpipe block count differs from ours and why."""
    theirs, stats = llvmpipe_triangles(frame)
    ours_n = frame.report.counters["fragment_shader_invocations_llvmpipe"]
    n = len(theirs)
    tclip = theirs[:, [3, 4, 5, 6, 9, 10, 11, 12, 15, 16, 17, 18]].reshape(-1, 4).astype(np.float32)
    theirs_n = 16 * _blocks(tclip, np.arange(3 * n, dtype=np.int32).reshape(n, 3))
    print(f"{name}: ours {ours_n:,}, llvmpipe's query {stats['fragment_shader_invocations']:,}; our rasterizer on "
          f"llvmpipe's own vertices (its {n:,} triangles as its evaluation shader placed them): {theirs_n:,}",
          flush=True)
    po, pt, missed = _pairs(frame, theirs)
    same = int(np.sum(np.all(po == pt, axis=(1, 2))))
    print(f"  {len(po):,} triangles matched ({missed} not); {same:,} with bit-identical clip positions", flush=True)
    idx: list[int] = []
    _differing(po, pt, 0, len(po), idx)
    for k in idx:
        bo, bt = _block_set(po[k]), _block_set(pt[k])
        ulp = int(np.abs(po[k].view(np.int32).astype(np.int64) - pt[k].view(np.int32).astype(np.int64)).max())
        wo = (po[k][:, :2] / po[k][:, 3:4] + 1) * 0.5 * [W, H] * 256
        wt = (pt[k][:, :2] / pt[k][:, 3:4] + 1) * 0.5 * [W, H] * 256
        print(f"  triangle {k}: 4x4 blocks only with our vertices {sorted(bo - bt)}, only with llvmpipe's "
              f"{sorted(bt - bo)}; clip positions {ulp} ulp apart at most, window positions (1/256 px) ours "
              f"{np.round(wo, 2).tolist()} llvmpipe's {np.round(wt, 2).tolist()}", flush=True)


def main() -> int:
    hm = Heightmap.example()
    terrain = Terrain.prepare(hm)
    cams = {"flyover": Scene(hm, camera=Camera.default_for(hm, W, H)).camera_path(4)[2],
            "whole terrain": Camera.default_for(hm, W, H)}
    for spacing in ("fractional_odd", "fractional_even"):
        lod = LodConfig(policy="continuous", spacing="fractional_odd") if spacing == "fractional_odd" else \
            LodConfig(spacing=spacing)
        for cname, cam in reversed(cams.items()):
            f = render(Scene(hm, camera=cam, mesh="lod", lod=lod, outputs=("depth", "counters", "mesh", "patches")),
                       terrain=terrain)
            explain(f"{spacing}, {cname}", f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
