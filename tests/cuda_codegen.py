"""CUDA code generation for every kernel module, with no GPU: Warp builds PTX through NVRTC, which ships in its
wheel and needs no driver (``wp.compile_aot_module(module, arch=90, use_ptx=True)``). A ``func_native`` without
a CUDA branch, a host-only call or a type CUDA lacks fails here as it would on the first CUDA launch.

The PTX lands in Warp's kernel cache, named by the module's content hash (as the CPU builds are): an unchanged
module is not compiled again. Used by tests/kernels/test_cuda_codegen.py and by scripts/gpu-check.sh::

    python tests/cuda_codegen.py [--arch 90] [--workers 2]     # every module; prints a table
    python tests/cuda_codegen.py --load cpu,cuda:0 --workers 16  # compile and load every module on the devices
"""

from __future__ import annotations

import argparse
import importlib
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import warp as wp

import terrainwarp

KERNELS_DIR = Path(__file__).resolve().parents[1] / "kernels"


def nvrtc_archs() -> list[int]:
    """The CUDA architectures this Warp build's NVRTC compiles for (empty: no NVRTC)."""
    wp.init()
    from warp._src.context import runtime  # noqa: PLC0415 -- the one place Warp says what NVRTC supports

    return sorted(int(a) for a in (getattr(runtime, "nvrtc_supported_archs", None) or ()))


def kernel_modules() -> list[str]:
    """The kernels/ modules that define Warp kernels, as ``terrainwarp.kernels.<name>``."""
    out = []
    for path in sorted(KERNELS_DIR.glob("*.py")):
        name = f"terrainwarp.kernels.{path.stem}"
        mod = importlib.import_module(name)
        if path.stem != "__init__" and wp.get_module(mod.__name__).kernels:
            out.append(name)
    return out


def compile_ptx(name: str, arch: int = 90) -> tuple[str, float, Path, str]:
    """(module, seconds, the PTX file, its text) of one module compiled for ``sm_<arch>``."""
    t0 = time.perf_counter()
    (path,) = wp.compile_aot_module(importlib.import_module(name), arch=arch, use_ptx=True)
    path = Path(path)
    return name, time.perf_counter() - t0, path, path.read_text()


def compile_all(arch: int = 90, workers: int = 2, names: list[str] | None = None) -> list[tuple]:
    """:func:`compile_ptx` for every module (or ``names``), ``workers`` at a time (NVRTC runs unlocked)."""
    names = kernel_modules() if names is None else names
    with ThreadPoolExecutor(max(1, workers)) as pool:
        return list(pool.map(lambda n: compile_ptx(n, arch), names))


def load_all(devices: list[str], workers: int, fuse_fp: tuple[bool, ...] = (True, False)) -> list[str]:
    """Compile and load every kernel module on ``devices``, ``workers`` modules at a time, once per ``fuse_fp``
    setting (the parity check runs both): later processes find them in Warp's kernel cache. Returns a line a
    setting."""
    mods = [wp.get_module(importlib.import_module(n).__name__) for n in kernel_modules()]
    out = []
    for fuse in fuse_fp:
        for m in mods:
            wp.set_module_options({"fuse_fp": fuse}, m)
        t0 = time.perf_counter()
        wp.force_load(device=devices, modules=mods, max_workers=max(1, workers))
        out.append(f"{len(mods)} modules loaded on {', '.join(devices)} with fuse_fp={fuse} in "
                   f"{time.perf_counter() - t0:.1f} s ({workers} at a time)")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--load", default=None, metavar="DEVICES", help="instead: compile and load every module on "
                    "these devices (comma-separated), with fuse_fp on and off, into Warp's kernel cache")
    args = ap.parse_args()
    terrainwarp.configure(quiet=True)  # no greeting or driver warning in the table
    if args.load:
        print("\n".join(load_all(args.load.split(","), args.workers)))
        return
    archs = nvrtc_archs()
    if args.arch not in archs:
        raise SystemExit(f"this Warp build's NVRTC cannot compile sm_{args.arch} (it can: {archs})")
    t0 = time.perf_counter()
    rows = compile_all(args.arch, args.workers)
    print("| module | kernels | PTX KB | s |\n|---|---|---|---|")
    for name, sec, _, text in rows:
        print(f"| {name.rsplit('.', 1)[1]} | {text.count('.entry ')} | {len(text) / 1e3:.0f} | {sec:.1f} |")
    print(f"\n{len(rows)} modules compiled to sm_{args.arch} PTX in {time.perf_counter() - t0:.1f} s "
          f"({args.workers} at a time; a module compiled before comes from Warp's cache)")


if __name__ == "__main__":
    main()
