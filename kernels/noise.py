"""Procedural terrain: fractal Brownian motion (fBm) of 2D gradient noise, as a Warp kernel.

The lattice gradients come from an integer hash of (lattice x, lattice z, octave seed), not from a
random table, so any window of an arbitrarily large terrain can be generated on its own and equals
the same window of the whole (tile-by-tile generation of 16k x 16k heightmaps). All arithmetic is
uint32 and float32 in a fixed order: the same seed gives the same bits on every run and device.

Range: 2D Perlin gradient noise lies in [-sqrt(2)/2, sqrt(2)/2]; the kernel divides the octave sum by
``sqrt(2)/2 * sum(amplitudes)`` so the output is guaranteed to lie in [-1, 1] without a global
min/max pass (which tiles could not agree on).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .checks import check_device
from .parallel import launch


@wp.func
def hash_u32(x: wp.uint32, y: wp.uint32, s: wp.uint32) -> wp.uint32:
    # A few rounds of a multiply-xorshift mixer (murmur3 finaliser) over the three words. Warp's codegen
    # declares an integer literal as int32, so constants >= 2^31 are written as their int32 values (same
    # 32 bits: 0x9E3779B9, 0x85EBCA6B, 0xC2B2AE35, 0x846CA68B) and no compiler warns about a narrowing.
    h = s * wp.uint32(-1640531527) + x * wp.uint32(-2048144789) + y * wp.uint32(-1028477387)
    h = h ^ (h >> wp.uint32(16))
    h = h * wp.uint32(0x7FEB352D)
    h = h ^ (h >> wp.uint32(15))
    h = h * wp.uint32(-2073254261)
    h = h ^ (h >> wp.uint32(16))
    return h


@wp.func
def _grad(ix: int, iz: int, seed: wp.uint32, dx: float, dz: float) -> float:
    h = hash_u32(wp.uint32(ix), wp.uint32(iz), seed)
    # 8 unit-ish gradient directions (the classic 2D Perlin set), chosen by the low bits.
    k = int(h & wp.uint32(7))
    gx = float(0.0)
    gz = float(0.0)
    if k == 0:
        gx = 1.0
    elif k == 1:
        gx = -1.0
    elif k == 2:
        gz = 1.0
    elif k == 3:
        gz = -1.0
    elif k == 4:
        gx = 0.70710678
        gz = 0.70710678
    elif k == 5:
        gx = -0.70710678
        gz = 0.70710678
    elif k == 6:
        gx = 0.70710678
        gz = -0.70710678
    else:
        gx = -0.70710678
        gz = -0.70710678
    return gx * dx + gz * dz


@wp.func
def _fade(t: float) -> float:
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


@wp.func
def perlin2(x: float, z: float, seed: wp.uint32) -> float:
    fx = wp.floor(x)
    fz = wp.floor(z)
    ix = int(fx)
    iz = int(fz)
    tx = x - fx
    tz = z - fz
    n00 = _grad(ix, iz, seed, tx, tz)
    n10 = _grad(ix + 1, iz, seed, tx - 1.0, tz)
    n01 = _grad(ix, iz + 1, seed, tx, tz - 1.0)
    n11 = _grad(ix + 1, iz + 1, seed, tx - 1.0, tz - 1.0)
    u = _fade(tx)
    v = _fade(tz)
    a = n00 + (n10 - n00) * u
    b = n01 + (n11 - n01) * u
    return a + (b - a) * v


@wp.kernel(enable_backward=False)
def _fbm_kernel(
    offset: int,
    row0: int,
    col0: int,
    step: int,
    base_frequency: float,
    octaves: int,
    lacunarity: float,
    gain: float,
    seed: int,
    ridged: int,
    # outputs
    out_h: wp.array2d(dtype=wp.float32),
):
    i, j = wp.tid()
    i += offset
    x = float(col0 + j * step) * base_frequency  # integer sample index first: a strided window equals
    z = float(row0 + i * step) * base_frequency  # those samples of the whole, bit for bit
    amp = float(1.0)
    total = float(0.0)
    norm = float(0.0)
    freq = float(1.0)
    for o in range(octaves):
        s = wp.uint32(seed) * wp.uint32(-1640531535) + wp.uint32(o) * wp.uint32(40503)  # 2654435761
        n = perlin2(x * freq + float(o) * 17.31, z * freq - float(o) * 9.73, s)
        if ridged != 0:
            n = 0.70710678 - 2.0 * wp.abs(n)  # ridges where the noise crosses zero, same range
        total += amp * n
        norm += amp
        amp *= gain
        freq *= lacunarity
    out_h[i, j] = total / (0.70710678 * norm)


MAX_OCTAVES = 64  # octaves of one fBm: past ~24 (lacunarity 2) a float32 noise coordinate resolves nothing more


def fbm(rows: int, cols: int, *, seed: int = 0, base_frequency: float = 1.0 / 256.0, octaves: int = 8,
        lacunarity: float = 2.0, gain: float = 0.5, ridged: bool = False, row0: int = 0, col0: int = 0,
        step: int = 1, device: str = "cpu") -> np.ndarray:
    """fBm in [-1, 1], float32 (rows, cols), of the window starting at sample (row0, col0), every ``step``-th
    sample (sample (row0 + i * step, col0 + j * step) of the whole: a point-sampled overview)."""
    if int(step) < 1:
        raise ValueError(f"step: expected a positive integer, got {step!r}")
    check_device("device", device)
    out = wp.empty((rows, cols), dtype=wp.float32, device=device)
    launch(_fbm_kernel, dim=(rows, cols),
           inputs=[int(row0), int(col0), int(step), float(base_frequency), int(octaves), float(lacunarity),
                   float(gain), int(seed) & 0x7FFFFFFF, int(bool(ridged))],
           outputs=[out], device=device, min_items=1024)
    return out.numpy()
