"""Inverse rendering: recover a heightmap from rendered depth and shaded images, starting flat.

The target is a 129 x 129 window of the bundled SRTM DEM. Eight cameras on a ring look down at it; each
renders a depth image and a hillshaded image through the differentiable ops of ``terrainwarp.diff``
(displace -> rasterize -> interpolate -> antialias). Starting from a flat terrain at the targets' mean
height, optax Adam fits the heights to the images, as a pyramid of corrections (coarse ones settle first)
with a small curvature prior; the RMSE in metres against the true heights is printed every tenth of the
run, recorded per iteration and plotted.

    python examples/inverse_rendering.py --out out/inverse_rendering [--size 129 --views 8 --iters 200]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

import terrainwarp as tw
from terrainwarp import diff
from terrainwarp.io.files import new_figure, save_figure, write_json
from terrainwarp.kernels.displacement import grid_mesh

SUN = np.array([-0.5, 0.75, -0.45]) / np.linalg.norm([-0.5, 0.75, -0.45])


def target_heightmap(size: int) -> tuple[np.ndarray, float, float]:
    """A size x size window of the bundled DEM (native spacing), cut around its centre."""
    hm = tw.Heightmap.example()
    r0 = (hm.shape[0] - size) // 2
    c0 = (hm.shape[1] - size) // 2
    return np.asarray(hm.heights[r0:r0 + size, c0:c0 + size], np.float32), hm.dx, hm.dz


def ring_cameras(heights: np.ndarray, dx: float, dz: float, views: int, width: int, height: int) -> list[tw.Camera]:
    """``views`` cameras on a ring around the terrain, 50 degrees above the horizon, each framing it all."""
    ex, ez = (heights.shape[1] - 1) * dx, (heights.shape[0] - 1) * dz
    centre = np.array([ex / 2, float(heights.mean()), ez / 2])
    dist = 1.25 * math.hypot(ex, ez)
    cams = []
    for k in range(views):
        a = 2 * math.pi * (k + 0.125) / views
        off = dist * np.array([math.cos(a) * math.cos(0.87), math.sin(0.87), math.sin(a) * math.cos(0.87)])
        cams.append(tw.Camera(position=tuple(centre + off), target=tuple(centre), fov_y_deg=40.0, width=width,
                              height=height, near=0.05 * dist, far=4.0 * dist))
    return cams


def shade(heights: jax.Array, dx: float, dz: float) -> jax.Array:
    """Per-sample Lambert shade of the surface under SUN (normals from central differences), (H*W,)."""
    gz, gx = jnp.gradient(heights, dz, dx)
    n = jnp.stack([-gx, jnp.ones_like(gx), -gz], -1)
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    return jnp.clip(n @ jnp.asarray(SUN, jnp.float32), 0.0, 1.0).reshape(-1)


def make_renderer(shape: tuple[int, int], dx: float, dz: float, cams: list[tw.Camera]):
    """render(heights) -> (views, H, W, 2) antialiased (depth / scale, shade) images, differentiable."""
    _, uv, tri = grid_mesh(np.zeros(shape, np.float32), dx, dz, (0.0, 0.0, 0.0))
    nbr = diff.topology(tri)
    mats = [(np.asarray(c.position, np.float32), c.view_matrix(relative=True), c.proj_matrix()) for c in cams]
    scale = float(np.linalg.norm(np.asarray(cams[0].position) - np.asarray(cams[0].target)))

    def render(heights: jax.Array) -> jax.Array:
        s = shade(heights, dx, dz)
        imgs = []
        for (eye, view, proj), cam in zip(mats, cams, strict=True):
            pos = diff.displace(heights, dx, dz, uv, eye)                 # camera-relative (n, 3)
            clip = diff.clip_positions(pos, view, proj)
            ids, _ = diff.rasterize(clip, tri, cam.width, cam.height)
            depth = -(pos @ jnp.asarray(view[2, :3], jnp.float32)) / scale  # distance along the view axis
            attr = jnp.stack([depth, s], axis=1)
            col = diff.interpolate(attr, ids, clip, tri)
            imgs.append(diff.antialias(col, ids, clip, tri, nbr))
        return jnp.stack(imgs)

    return render


def pyramid_sizes(size: int) -> list[int]:
    """Sides of the correction pyramid: size, (size - 1) / 2 + 1, ... down to 9 or more samples."""
    sizes = [size]
    while (sizes[-1] - 1) % 2 == 0 and (sizes[-1] - 1) // 2 + 1 >= 9:
        sizes.append((sizes[-1] - 1) // 2 + 1)
    return sizes[::-1]


def fit(size: int = 129, views: int = 8, width: int = 320, height: int = 240, iters: int = 200,
        lr: float = 40.0, smooth: float = 0.1, log=print) -> dict:
    """Fit the heights; returns the per-iteration RMSE (metres) and loss, timings and the heights."""
    truth, dx, dz = target_heightmap(size)
    cams = ring_cameras(truth, dx, dz, views, width, height)
    render = jax.jit(make_renderer(truth.shape, dx, dz, cams))
    target = render(jnp.asarray(truth))
    scale = float(np.linalg.norm(np.asarray(cams[0].position) - np.asarray(cams[0].target)))

    levels = pyramid_sizes(size)

    def heights_of(params):
        # a pyramid of corrections, coarsest first, each upsampled to full size and added to the flat
        # start: low frequencies, seen by many pixels, settle first
        return h0 + sum(jax.image.resize(d, truth.shape, "linear") for d in params)

    def loss_fn(params):
        # images, plus a small curvature prior: a sample between pixel centres in every view is seen by
        # none, and would otherwise keep whatever its neighbours' gradients left it at
        h = heights_of(params)
        lap = h[1:-1, 2:] + h[1:-1, :-2] + h[2:, 1:-1] + h[:-2, 1:-1] - 4.0 * h[1:-1, 1:-1]
        return jnp.mean((render(h) - target) ** 2) + smooth * jnp.mean((lap / scale) ** 2)

    step_grad = jax.jit(jax.value_and_grad(loss_fn))
    opt = optax.adam(optax.cosine_decay_schedule(lr, iters, alpha=0.02))
    h0 = jnp.full(truth.shape, float(truth.mean()), jnp.float32)
    params = [jnp.zeros((n, n), jnp.float32) for n in levels]
    state = opt.init(params)
    rmse, losses = [], []
    t0 = time.perf_counter()
    for it in range(iters + 1):
        h = heights_of(params)
        rmse.append(float(np.sqrt(np.mean((np.asarray(h) - truth) ** 2))))
        val, g = step_grad(params)
        losses.append(float(val))
        if it % max(iters // 10, 1) == 0 or it == iters:
            log(f"iter {it:4d}  loss {float(val):.3e}  RMSE {rmse[-1]:8.3f} m")
        if it == iters:
            break
        upd, state = opt.update(g, state, params)
        params = optax.apply_updates(params, upd)
    secs = time.perf_counter() - t0
    return {"size": size, "views": views, "width": width, "height": height, "iters": iters, "lr": lr, "smooth": smooth,
            "rmse_m": rmse, "loss": losses, "seconds": secs, "seconds_per_iter": secs / (iters + 1),
            "drop": rmse[0] / rmse[-1], "heights": np.asarray(h), "truth": truth}


def plot(res: dict, path: Path) -> Path:
    fig, ax = new_figure(1, 3, figsize=(13, 3.8))
    ax[0].semilogy(res["rmse_m"])
    ax[0].set(xlabel="Adam iteration", ylabel="RMSE against the true heights (m)",
              title=f"{res['size']}² heights, {res['views']} views, drop {res['drop']:.0f}x")
    ax[0].grid(True, which="both", alpha=0.3)
    lo, hi = float(res["truth"].min()), float(res["truth"].max())
    for a, img, name in ((ax[1], res["truth"], "true heights"), (ax[2], res["heights"], "recovered")):
        im = a.imshow(img, vmin=lo, vmax=hi, cmap="terrain")
        a.set(title=name, xticks=[], yticks=[])
    fig.colorbar(im, ax=ax[1:], label="m")
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/inverse_rendering")
    ap.add_argument("--size", type=int, default=129, help="heightmap window, samples per side")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--lr", type=float, default=40.0, help="Adam step in metres (cosine-decayed)")
    ap.add_argument("--smooth", type=float, default=0.1, help="weight of the curvature prior")
    a = ap.parse_args(argv)
    res = fit(a.size, a.views, a.width, a.height, a.iters, a.lr, a.smooth)
    out = Path(a.out)
    plot(res, out / "inverse_rendering.png")
    write_json(out / "inverse_rendering.json", {k: v for k, v in res.items() if k not in ("heights", "truth")})
    print(f"RMSE {res['rmse_m'][0]:.2f} m -> {res['rmse_m'][-1]:.2f} m ({res['drop']:.1f}x) in {res['iters']} "
          f"iterations, {res['seconds_per_iter'] * 1e3:.0f} ms each; wrote {out}")
    return res


if __name__ == "__main__":
    main()
