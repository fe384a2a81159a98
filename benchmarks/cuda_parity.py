"""The same inputs on two Warp devices (the CPU and CUDA), every kernel module's outputs compared.

Integer outputs (tessellator points and triangles, raster coverage and triangle ids, LOD selection, polytree
and bintree nodes, scheme meshes' triangles) must be bit-identical; float outputs are compared in ulps (units
in the last place of their dtype: the count of representable values between the two), with the largest seen,
the number of elements that differ and where NaNs differ. ``--fuse-fp off`` compiles every kernel module with
``fuse_fp=False`` (no multiply-add contraction: LLVM's Strict FP fusion on the CPU, ``--fmad=false`` for
NVRTC): float outputs that then agree bit for bit differed by contraction alone; what still differs comes from
the math libraries (CUDA's libdevice against the CPU's). Warp's ``fast_math`` is off by default on both.

Without a GPU, ``--b cpu --b-threads 1`` compares the CPU on every core with the CPU on one thread (the
project's bit-identical-for-any-thread-count rule): the dry run of scripts/gpu-check.sh.

    python benchmarks/cuda_parity.py                          # cpu vs cuda:0, the sizes of the GPU check
    python benchmarks/cuda_parity.py --fuse-fp off            # the same with no FMA contraction
    python benchmarks/cuda_parity.py --b cpu --b-threads 1 --size tiny --out /tmp/p   # CPU-only dry run
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import warp as wp
from _common import md_table, write_result

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from cuda_codegen import kernel_modules  # noqa: E402

SIZES = {  # heightmap side, frame width, height, patches
    "tiny": {"side": 65, "w": 96, "h": 64, "patches": 64},
    "full": {"side": 513, "w": 1280, "h": 720, "patches": 2000},
}
FLOAT_ULPS = 64  # float outputs within this many ulps pass (the table gives the largest seen)


# ------------------------------------------------------------------------------------------------
# comparison
# ------------------------------------------------------------------------------------------------


def _ordered(a: np.ndarray) -> np.ndarray:
    """Float bits as integers ordered like the floats (-0.0 and 0.0 both 0)."""
    it = {4: np.int32, 8: np.int64, 2: np.int16}[a.dtype.itemsize]
    i = a.view(it).astype(np.int64)
    sign = np.int64(1) << (8 * a.dtype.itemsize - 1)
    return np.where(i < 0, -(i + sign), i)


def compare(a: np.ndarray, b: np.ndarray) -> dict:
    """elements, differing, max ulps (floats), max |a - b|, NaN positions that differ, shape/dtype equality."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return {"n": a.size, "diff": -1, "ulps": float("nan"), "abs": float("nan"), "nan": 0,
                "note": f"shape/dtype {a.shape} {a.dtype} vs {b.shape} {b.dtype}"}
    if a.dtype.kind != "f":
        d = a != b
        return {"n": a.size, "diff": int(d.sum()), "ulps": 0.0, "abs": float(np.abs(a.astype(np.int64) - b).max())
                if d.any() else 0.0, "nan": 0, "note": ""}
    na, nb = np.isnan(a), np.isnan(b)
    both = ~na & ~nb
    ul = np.abs(_ordered(a[both]) - _ordered(b[both])) if both.any() else np.zeros(0, np.int64)
    diff = int((ul > 0).sum()) + int((na != nb).sum())
    ab = np.abs(a[both].astype(np.float64) - b[both].astype(np.float64))
    return {"n": a.size, "diff": diff, "ulps": float(ul.max()) if ul.size else 0.0,
            "abs": float(ab.max()) if ab.size else 0.0, "nan": int((na != nb).sum()), "note": ""}


def verdict(kind: str, c: dict) -> str:
    if c["diff"] < 0:
        return "MISMATCH (" + c["note"] + ")"
    if c["diff"] == 0:
        return "bit-identical"
    if kind == "int" or c["nan"]:
        return "MISMATCH"
    return f"within {FLOAT_ULPS} ulps" if c["ulps"] <= FLOAT_ULPS else "MISMATCH"


# ------------------------------------------------------------------------------------------------
# cases: each returns {output name: array} on a device (the inputs do not depend on it)
# ------------------------------------------------------------------------------------------------


def _scene(sz: dict):
    from terrainwarp import Camera, Heightmap

    hm = Heightmap.fbm(sz["side"], seed=7, dx=10.0, max_height=600.0, feature_size=sz["side"] / 4)
    cam = Camera.default_for(hm, sz["w"], sz["h"])
    return hm, cam


def case_tessellator(dev: str, sz: dict) -> dict:
    from terrainwarp.kernels.tessellator import tessellate_domains

    rng = np.random.default_rng(11)
    lv = rng.uniform(0.5, 48.0, (sz["patches"], 6)).astype(np.float32)
    out = {}
    for sp in ("equal", "fractional_even", "fractional_odd"):
        d = tessellate_domains(lv[:, :4], lv[:, 4:], sp, device=dev)
        out |= {f"{sp} uv": d["uv"], f"{sp} triangles": d["triangles"], f"{sp} vertex_offsets": d["vertex_offsets"]}
    return out


def case_displacement(dev: str, sz: dict) -> dict:
    from terrainwarp.lod import Terrain, select
    from terrainwarp.rendering import tessellate_patches

    hm, cam = _scene(sz)
    pl = select(Terrain.prepare(hm, roots=8, tess=16), cam)  # on the CPU: the same patches for both devices
    pt = {"origin_xz": pl.origin, "size": pl.size, "outer": pl.outer, "inner": pl.inner, "level": pl.level}
    out = {}
    for filt in ("bilinear", "bicubic"):
        t = tessellate_patches(pt, hm.heights, hm.dx, hm.dz, cam.position, spacing="fractional_odd", filter=filt,
                               origin=hm.origin, device=dev)
        out |= {f"{filt} positions": t.positions, f"{filt} triangles": t.triangles}
    return out


def case_raster(dev: str, sz: dict) -> dict:
    from terrainwarp.kernels.displacement import grid_mesh
    from terrainwarp.rendering import clip_coordinates, rasterize, rasterize_clip

    hm, cam = _scene(sz)
    e = cam.position
    pos, _, tri = grid_mesh(hm.heights, hm.dx, hm.dz, (hm.origin[0] - e[0], e[1], hm.origin[1] - e[2]))
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    clip = clip_coordinates(pos, view, proj)  # on the CPU: the rasterizer's own inputs, the same bits
    fc = rasterize_clip(clip, tri, cam.width, cam.height, device=dev)
    fp = rasterize(pos, tri, view, proj, cam.width, cam.height, device=dev)  # the vertex transform on dev
    counted = rasterize_clip(clip, tri, cam.width, cam.height, counters=True, device=dev).counters
    return {"clip given: counters": np.array([counted[k] for k in sorted(counted)], np.int64),
            "clip given: triangle_id": fc.triangle_id, "clip given: coverage": fc.triangle_id >= 0,
            "clip given: depth": fc.depth, "clip given: barycentrics": fc.barycentrics,
            "transform on device: triangle_id": fp.triangle_id, "transform on device: depth": fp.depth}


def case_lod(dev: str, sz: dict) -> dict:
    from terrainwarp.lod import DistancePolicy, ScreenErrorPolicy, Terrain, select

    hm, cam = _scene(sz)
    t = Terrain.prepare(hm, roots=8, tess=16, device=dev)
    out = {"pyramid max": np.concatenate([lv[1].ravel() for lv in t.stats])}
    for name, pol in (("sse", ScreenErrorPolicy(1.0)), ("distance", DistancePolicy(2.0))):
        pl = select(t, cam, pol, device=dev)
        out |= {f"{name} level": pl.level, f"{name} origin": pl.origin, f"{name} outer": pl.outer,
                f"{name} inner": pl.inner}
    return out


def case_render(dev: str, sz: dict) -> dict:
    from terrainwarp import LodConfig, Scene, render

    hm, cam = _scene(sz)
    f = render(Scene(hm, camera=cam, mesh="lod", lod=LodConfig(tolerance_px=1.0), outputs=("depth", "mesh")),
               device=dev)
    return {"triangles": f.mesh.triangles, "positions": f.mesh.positions, "triangle_id": f.triangle_id,
            "depth": f.depth}


def case_shade(dev: str, sz: dict) -> dict:
    """render's image (normal map, shading, sRGB codes) and error (reference grid, sample and pixel error)."""
    from terrainwarp import LodConfig, Scene, render

    hm, cam = _scene(sz)
    f = render(Scene(hm, camera=cam, mesh="lod", lod=LodConfig(tolerance_px=2.0), outputs=("image", "error")),
               device=dev)
    return {"image (sRGB codes)": f.image, "error map": f.error.error_map,
            "image error map": f.error.image_error_map}


def case_surface(dev: str, sz: dict) -> dict:
    from terrainwarp import compute_curvature, compute_normals

    hm, _ = _scene(sz)
    out = {f"normals {m}": compute_normals(hm, m, device=dev) for m in ("sobel", "edge", "triangle", "quad")}
    for m in ("two_normal", "three_normal", "three_vertex", "edge_angle"):
        out[f"curvature {m}"] = compute_curvature(hm, m, device=dev)
    return out


def case_polytree(dev: str, sz: dict) -> dict:
    from terrainwarp.lod.polytree import build_polytree, default_tolerances

    hm, _ = _scene({**sz, "side": min(sz["side"], 129)})
    pt = build_polytree(hm, default_tolerances(hm, 20), device=dev)
    pa = pt.polygons
    return {"rects": pa.rects, "flags": pa.flags, "start": pa.start, "gradients": pa.grads}


def case_bintree(dev: str, sz: dict) -> dict:
    from terrainwarp import Camera
    from terrainwarp.lod.bintree import Bintree, select_bintree

    hm, _ = _scene({**sz, "side": min(sz["side"], 257)})
    t = Bintree.build(hm, 14 if sz["side"] < 257 else 16, device=dev)
    (x0, z0), (x1, z1) = hm.bounds_xz
    x, z = x0 + 0.3 * (x1 - x0), z0 + 0.4 * (z1 - z0)
    y = float(t.surface_height(x, z)) + 20.0
    f = select_bintree(t, Camera(position=(x, y, z), target=(x + 1, y - 0.3, z + 1), width=sz["w"], height=sz["h"],
                                 near=0.5, far=1e6))
    return {"vertex heights": t.arrays["vertex_height"].numpy(), "node": f.node, "level": f.level,
            "triangles": f.mesh.triangles, "positions": f.mesh.positions}


def case_schemes(dev: str, sz: dict) -> dict:
    from terrainwarp.lod.cdlod import Cdlod
    from terrainwarp.lod.chunked import ChunkedLod
    from terrainwarp.lod.clipmaps import Clipmap

    hm, cam = _scene({**sz, "side": min(sz["side"], 257)})
    out = {}
    for name, scheme in (("cdlod", Cdlod(hm, 1.0, grid=8, device=dev)), ("clipmaps", Clipmap(hm, 31, device=dev)),
                         ("chunked", ChunkedLod(hm, 1.0, tile=8, device=dev))):
        mesh, _, _ = scheme.frame(cam)
        out |= {f"{name} triangles": mesh.triangles, f"{name} positions": mesh.positions}
    return out


def case_sample_error(dev: str, sz: dict) -> dict:
    from terrainwarp import LodConfig, Scene, render
    from terrainwarp.measure.sample_error import sample_error

    hm, cam = _scene(sz)
    depth = render(Scene(hm, camera=cam, outputs=("depth",))).depth  # the CPU's: the same reference
    mesh = render(Scene(hm, camera=cam, mesh="lod", lod=LodConfig(tolerance_px=2.0), outputs=("mesh",))).mesh
    e = sample_error(hm, cam, mesh, depth, keep_map=True, device=dev)
    return {"error map": e.error_map, "visible/hidden/missing": np.array([e.visible, e.hidden,
                                                                                    e.missing])}


def case_noise(dev: str, sz: dict) -> dict:
    from terrainwarp.kernels.noise import fbm

    return {"fbm": fbm(sz["side"], sz["side"], seed=3, device=dev)}


def case_diff(dev: str, sz: dict) -> dict:
    """interpolate, antialias and their gradients through JAX, on JAX's device for ``dev``."""
    import jax  # lazy: heavy optional dependency
    import jax.numpy as jnp

    from terrainwarp import diff
    from terrainwarp.rendering import rasterize_clip

    try:
        jdev = jax.devices("cpu" if dev == "cpu" else "gpu")[0]
    except RuntimeError:
        return {}
    rng = np.random.default_rng(5)
    n = 400
    clip = np.c_[rng.uniform(-1.2, 1.2, (n, 2)), rng.uniform(0.1, 0.9, n), np.ones(n)].astype(np.float32)
    tri = rng.integers(0, n, (300, 3)).astype(np.int32)
    ids = rasterize_clip(clip, tri, 64, 48).triangle_id
    attr = rng.normal(size=(n, 3)).astype(np.float32)
    nbr = diff.topology(tri)
    with jax.default_device(jdev):
        def loss(c, a):
            img = diff.antialias(diff.interpolate(a, ids, c, tri), ids, c, tri, nbr)
            return jnp.sum(jnp.sin(3.0 * img))

        img = diff.interpolate(jnp.asarray(attr), ids, jnp.asarray(clip), tri)
        gc, ga = jax.grad(loss, argnums=(0, 1))(jnp.asarray(clip), jnp.asarray(attr))
        return {"interpolate": np.asarray(img), "d/dclip": np.asarray(gc), "d/dattr": np.asarray(ga)}


CASES: dict[str, tuple[str, Callable]] = {  # name -> (what must match: "int" outputs exactly, floats in ulps)
    "tessellator": ("domain points (16.16 fixed point) and triangles", case_tessellator),
    "displacement": ("tessellate_patches: displaced positions, triangles", case_displacement),
    "raster": ("coverage, triangle ids, depth, barycentrics, pipeline statistics", case_raster),
    "lod": ("pyramids and LOD selection (sse, distance)", case_lod),
    "render": ("a whole LOD frame through render()", case_render),
    "shade": ("render's image and error outputs", case_shade),
    "surface": ("normals and curvature, every method", case_surface),
    "polytree": ("polygons at 20 tolerances", case_polytree),
    "bintree": ("tree and one frame's selection", case_bintree),
    "schemes": ("CDLOD, clipmaps, chunked meshes", case_schemes),
    "sample_error": ("the primary error map", case_sample_error),
    "noise": ("fBm heights", case_noise),
    "diff": ("interpolate + antialias and gradients (JAX)", case_diff),
}


# ------------------------------------------------------------------------------------------------
# driver
# ------------------------------------------------------------------------------------------------


def set_fuse_fp(enabled: bool) -> None:
    """Every kernel module's ``fuse_fp`` option, set before it is first compiled."""
    for name in kernel_modules():
        wp.set_module_options({"fuse_fp": enabled}, importlib.import_module(name))


def run_case(fn: Callable, dev: str, threads: int | None, sz: dict) -> tuple[dict, float]:
    from terrainwarp.kernels.parallel import set_threads

    set_threads(threads)
    try:
        t0 = time.perf_counter()
        out = fn(dev, sz)
        return {k: np.asarray(v) for k, v in out.items()}, time.perf_counter() - t0
    finally:
        set_threads(None)


def kind_of(a: np.ndarray) -> str:
    return "float" if a.dtype.kind == "f" else "int"


def run(a: str, b: str, b_threads: int | None, size: str, cases: list[str]) -> tuple[list, list]:
    sz = SIZES[size]
    rows, failures = [], []
    for name in cases:
        what, fn = CASES[name]
        run_case(fn, a, None, sz)  # warm-up: compile both devices' modules outside the timing
        run_case(fn, b, b_threads, sz)
        ra, ta = run_case(fn, a, None, sz)
        rb, tb = run_case(fn, b, b_threads, sz)
        if not ra:
            rows.append([name, "(skipped: JAX has no backend for the device)", "", "", "", "", "", "", ""])
            continue
        for out, va in ra.items():
            c = compare(va, rb[out])
            v = verdict(kind_of(va), c)
            if v.startswith("MISMATCH"):
                failures.append(f"{name}: {out}")
            rows.append([name, out, str(va.dtype), c["n"], c["diff"], c["ulps"] if kind_of(va) == "float" else "",
                         f"{c['abs']:.3g}" if c["diff"] else "0", v, f"{ta * 1e3:.0f} / {tb * 1e3:.0f}"])
        print(f"{name}: {len(ra)} outputs, {sum(1 for r in rows if r[0] == name and r[7] != 'bit-identical')} "
              f"not bit-identical", flush=True)
    return rows, failures


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", default="cpu", help="the reference device (default cpu)")
    ap.add_argument("--b", default="cuda:0", help="the device compared with it (default cuda:0)")
    ap.add_argument("--b-threads", type=int, default=None, help="CPU threads on b (a CPU-vs-CPU dry run: 1)")
    ap.add_argument("--size", choices=sorted(SIZES), default="full")
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of " + ", ".join(CASES))
    ap.add_argument("--fuse-fp", choices=("on", "off"), default="on", help="multiply-add contraction in every "
                    "kernel module on both devices (Warp's default: on)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the table (default benchmarks/results)")
    args = ap.parse_args(argv)
    cases = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        ap.error(f"--cases: unknown {unknown}; expected some of {list(CASES)}")
    if args.fuse_fp == "off":
        set_fuse_fp(False)
    for d in (args.a, args.b):
        wp.get_device(d)  # an unknown device fails here, before any work
    t0 = time.perf_counter()
    rows, failures = run(args.a, args.b, args.b_threads, args.size, cases)
    sz = SIZES[args.size]
    b_label = args.b + (f" ({args.b_threads} thread)" if args.b_threads else "")
    body = (f"Every kernel module on `{args.a}` and on `{b_label}`, the same inputs (fBm {sz['side']}^2, "
            f"{sz['w']}x{sz['h']} frames, {sz['patches']} random patches), `fuse_fp` {args.fuse_fp} (multiply-add "
            f"contraction), `fast_math` off. Integer outputs must be bit-identical; floats pass within "
            f"{FLOAT_ULPS} ulps of their dtype (`ulps`: the largest distance seen; `diff`: elements that differ). "
            f"`ms a / b`: one run of the case on each device after a warm-up, inputs and read-back included. "
            f"Warp {wp.__version__}.\n\n"
            + md_table(["case", "output", "dtype", "elements", "diff", "ulps", "max abs", "verdict", "ms a / b"], rows)
            + f"\n\n{len(failures)} mismatch(es)" + (": " + "; ".join(failures) if failures else "")
            + f". Whole run: {time.perf_counter() - t0:.0f} s.")
    stage = "cuda_parity" + ("_nofma" if args.fuse_fp == "off" else "")
    write_result(stage, f"CUDA parity: {args.a} vs {b_label}, fuse_fp {args.fuse_fp} (cuda_parity.py)", body,
                 out_dir=args.out)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
