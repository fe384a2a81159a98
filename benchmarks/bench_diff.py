"""Differentiable ops (terrainwarp.diff): forward and backward cost of each op at a few sizes, the
interpolate + antialias backward / forward ratio at 1080p (issue 22: at most 3x), and the inverse
rendering example's convergence.

The scene: a grid mesh of an fBm heightmap seen at three-quarter view, 3 attribute channels. Each op is
timed alone (jitted; the forward alone, then the VJP alone with the forward's residuals ready), best of
``--repeat``, on ``--threads`` CPU threads.

    .venv/bin/python benchmarks/bench_diff.py            # 320x240, 640x480, 1920x1080 + the example
    .venv/bin/python benchmarks/bench_diff.py --quick    # 320x240 only, a short example run
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from _common import best_of, md_table, write_result  # noqa: E402

import terrainwarp as tw  # noqa: E402
from terrainwarp import diff  # noqa: E402
from terrainwarp.kernels import parallel  # noqa: E402
from terrainwarp.kernels.displacement import grid_mesh  # noqa: E402


def scene(size: int, width: int, height: int):
    hm = tw.Heightmap.fbm(size, seed=2, dx=10.0, max_height=400.0, feature_size=size / 6)
    heights = np.asarray(hm.heights, np.float32)
    cam = tw.Camera.default_for(hm, width, height)
    eye = np.asarray(cam.position, np.float32)
    _, uv, tri = grid_mesh(heights, hm.dx, hm.dz, (0.0, 0.0, 0.0))
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    return heights, hm.dx, hm.dz, uv, tri, eye, view, proj


def time_op(fwd, args, repeat: int) -> tuple[float, float]:
    """(forward s, backward s) of ``fwd(*args)``: jitted forward; jitted VJP with the residuals given."""
    f = jax.jit(fwd)
    jax.block_until_ready(f(*args))
    tf, out = best_of(lambda: jax.block_until_ready(f(*args)), repeat)
    out, vjp = jax.vjp(fwd, *args)
    ct = jnp.ones_like(out)
    b = jax.jit(vjp)
    jax.block_until_ready(b(ct))
    tb, _ = best_of(lambda: jax.block_until_ready(b(ct)), repeat)
    return tf, tb


def bench_size(size: int, width: int, height: int, repeat: int) -> list[list[object]]:
    heights, dx, dz, uv, tri, eye, view, proj = scene(size, width, height)
    nbr = diff.topology(tri)
    h = jnp.asarray(heights)
    pos = diff.displace(h, dx, dz, uv, eye)
    clip = diff.clip_positions(pos, view, proj)
    ids, _ = diff.rasterize(clip, tri, width, height)
    attr = jnp.concatenate([pos[:, 1:2] / 400.0, jnp.asarray(uv)], axis=1)  # 3 channels
    col = diff.interpolate(attr, ids, clip, tri)
    covered = int(np.count_nonzero(np.asarray(ids) >= 0))
    t_r, _ = best_of(lambda: jax.block_until_ready(diff.rasterize(clip, tri, width, height)), repeat)
    rows = []
    ops = {
        "displace": (lambda hh, e: diff.displace(hh, dx, dz, uv, e), (h, jnp.asarray(eye))),
        "interpolate": (lambda a, c: diff.interpolate(a, ids, c, tri), (attr, clip)),
        "antialias": (lambda co, c: diff.antialias(co, ids, c, tri, nbr), (col, clip)),
        "interpolate + antialias": (lambda a, c: diff.antialias(diff.interpolate(a, ids, c, tri), ids, c, tri, nbr),
                                    (attr, clip)),
    }
    label = f"{width}x{height}, {len(tri):,} tris, {covered:,} px covered"
    rows.append([label, "rasterize", t_r * 1e3, "-", "-"])
    for name, (fn, args) in ops.items():
        tf, tb = time_op(fn, args, repeat)
        rows.append([label, name, tf * 1e3, tb * 1e3, tb / tf])
    return rows


def example(quick: bool) -> tuple[str, dict]:
    path = ROOT.parent / "examples" / "inverse_rendering.py"
    spec = importlib.util.spec_from_file_location("inverse_rendering", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    args = ["--size", "33", "--width", "96", "--height", "72", "--iters", "120"] if quick else []
    res = mod.main(["--out", str(ROOT / "results" / "diff_example"), *args])
    r = res["rmse_m"]
    marks = sorted({0, 10, 25, 50, 100, len(r) // 2, len(r) - 1} & set(range(len(r))))
    table = md_table(["iteration", "RMSE (m)"], [[k, r[k]] for k in marks])
    cmd = " ".join(["examples/inverse_rendering.py", *args])
    text = (f"Inverse rendering (`{cmd}`): {res['size']}² window of the "
            f"bundled DEM, {res['views']} views of {res['width']}x{res['height']} (depth + hillshade, antialiased), "
            f"flat start, optax Adam (lr {res['lr']:g} m, cosine decay), curvature prior {res['smooth']:g}: RMSE "
            f"**{r[0]:.1f} m -> {r[-1]:.2f} m ({res['drop']:.1f}x)** in {res['iters']} iterations, "
            f"{res['seconds_per_iter'] * 1e3:.0f} ms each (all views, forward + backward).\n\n{table}\n\n"
            f"![convergence](diff_example/inverse_rendering.png)")
    return text, res


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    if a.threads:
        tw.kernels.parallel.set_threads(a.threads)
    sizes = [(129, 320, 240)] if a.quick else [(129, 320, 240), (257, 640, 480), (513, 1920, 1080)]
    rows = []
    for size, w, h in sizes:
        rows += bench_size(size, w, h, a.repeat)
    body = (f"Threads: {parallel.threads()}. Times in ms, best of {a.repeat}; backward = the VJP alone (the "
            f"forward's residuals ready). Ratio = backward / forward.\n\n"
            + md_table(["frame", "op", "forward ms", "backward ms", "bwd / fwd"], rows))
    text, _ = example(a.quick)
    write_result("diff", "Differentiable ops (terrainwarp.diff)", body + "\n\n" + text)


if __name__ == "__main__":
    main()
