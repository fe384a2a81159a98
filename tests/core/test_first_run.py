"""The first run says, once, that Warp compiles the kernels (issue 20, item 11): it took a minute with no
word. Run in subprocesses against a temporary Warp kernel cache (WARP_CACHE_PATH); the real cache is
never touched."""

import os
import subprocess
import sys

from terrainwarp.io.native import first_compile_note


def _run(code, cache):
    env = {**os.environ, "WARP_CACHE_PATH": str(cache)}
    env.pop("TERRAINWARP_VERBOSE", None)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)


def test_first_run_says_once_that_kernels_are_compiled(tmp_path):
    cache = tmp_path / "warp-cache"
    first = _run("import terrainwarp as tw; tw.Heightmap.fbm(9)", cache)
    assert first.returncode == 0, first.stderr
    lines = first.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("terrainwarp: compiling Warp kernels on first use; they are "
                                                   f"cached in {os.path.realpath(cache)}")
    assert lines[0].endswith(" (about a minute, once)")
    assert first.stdout == ""
    again = _run("import terrainwarp as tw; tw.Heightmap.fbm(9)", cache)
    assert (again.returncode, again.stdout, again.stderr) == (0, "", "")


def test_note_only_without_cached_terrainwarp_kernels(tmp_path):
    assert first_compile_note(None) is None
    assert first_compile_note(tmp_path / "missing").startswith("terrainwarp: compiling Warp kernels")
    assert first_compile_note(tmp_path) is not None  # empty
    (tmp_path / "wp_other.module_abc").mkdir()  # another program's kernels do not count
    assert first_compile_note(tmp_path) is not None
    (tmp_path / "wp_terrainwarp.kernels.noise_459b100").mkdir()
    assert first_compile_note(tmp_path) is None
