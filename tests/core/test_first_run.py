"""The first run compiles the kernels with a line per module, not in silence (issue 44, item 1); afterwards nothing
is printed. Each run is a subprocess against a temporary Warp kernel cache (WARP_CACHE_PATH) that holds the real
cache's compiled modules except a few small ones, so only those compile (a second or two, not a minute); the real
cache is only read."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import warp as wp

from terrainwarp import warmup as wu
from terrainwarp.kernels.device import start

MISSING = ("noise", "metrics", "visibility")  # the smallest modules: compiled by the runs below


@pytest.fixture(scope="module")
def compiled() -> dict[str, Path]:
    """Every kernel module's folder in the real cache (compiled now if missing: make test's warmup did that)."""
    start()
    wu.warmup(progress=False)
    dev = wp.get_device("cpu")
    return {n: wu._binary(m, dev).parent for n, m in wu.kernel_modules().items()}


def _cache_without(tmp: Path, compiled: dict[str, Path], missing: tuple[str, ...]) -> Path:
    base = tmp / "warp-cache"
    root = base / wp.config.version
    root.mkdir(parents=True)
    for name, folder in compiled.items():
        if name not in missing:
            (root / folder.name).symlink_to(folder, target_is_directory=True)
    return base


def _run(code: str, cache: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "WARP_CACHE_PATH": str(cache)}
    env.pop("TERRAINWARP_VERBOSE", None)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)


def test_a_first_render_compiles_what_is_missing_with_a_line_each_then_says_nothing(tmp_path, compiled):
    """The shading module (with the terrain noise's hash it shares) compiles here: its stderr is the progress lines
    alone, so no compiler line either (issue 20: the first run printed four -Wconstant-conversion warnings)."""
    cache = _cache_without(tmp_path, compiled, ("shading",))
    code = ("import terrainwarp as tw; hm = tw.Heightmap.fbm(17, seed=1); "
            "tw.render(tw.Scene(hm, camera=tw.Camera.default_for(hm, 16, 12), outputs=('image',)))")
    r = _run(code, cache)
    assert r.returncode == 0 and r.stdout == "", r.stderr
    lines = r.stderr.splitlines()
    assert lines == ["compiling kernels, first run only: 0/1 (each as it is first needed; 'terrainwarp warmup' "
                     "compiles them all at once, in parallel)",
                     "compiling kernels, first run only: 1/1 shading"]  # no CUDA warning, no Warp lines
    assert _run(code, cache).stderr == ""  # compiled once: the next process finds it


def test_warmup_compiles_in_worker_processes_and_the_command_reports_it(tmp_path, compiled):
    cache = _cache_without(tmp_path, compiled, MISSING)
    code = ("import json, terrainwarp.warmup as w; r = w.warmup(workers=2); "
            "print(json.dumps([sorted(r.compiled), len(r.cached), r.workers, w.pending()]))")
    r = _run(code, cache)
    assert r.returncode == 0, r.stderr
    got, n_cached, workers, pending = json.loads(r.stdout)
    assert got == sorted(MISSING) and n_cached == len(compiled) - len(MISSING) and workers == 2 and pending == []
    lines = r.stderr.splitlines()
    assert "0/3 (once per machine: 2 worker processes" in lines[0]
    tail = [line.removeprefix("compiling kernels, first run only: ").split() for line in lines[1:]]
    assert [t[0] for t in tail] == ["1/3", "2/3", "3/3"] and sorted(t[1] for t in tail) == sorted(MISSING)



def test_the_warmup_command_says_all_is_compiled(compiled, capsys):
    from terrainwarp.cli import main

    assert main(["warmup"]) == 0
    out, err = capsys.readouterr()
    assert err == "" and out.startswith(f"all {len(compiled)} kernel modules are compiled; cache: ")
    assert main(["warmup", "--device", "tpu"]) == 2
    assert capsys.readouterr().err.startswith("terrainwarp: error: --device: expected one of the devices Warp sees")


def test_warmup_validates_its_arguments():
    with pytest.raises(ValueError, match=r"^device: 'cuda:7' asks for an NVIDIA GPU|^device: expected one of"):
        wu.warmup("cuda:7", progress=False)
    with pytest.raises(TypeError, match="^workers: expected an integer"):
        wu.warmup(workers=1.5, progress=False)
