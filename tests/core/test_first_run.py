"""The first run says, once, that Warp compiles the kernels (issue 20, item 11): it took a minute with no
word. The note is for a person at a terminal; through a pipe (the CLI's callers, which expect one line on
an error) nothing extra is printed. Run in subprocesses against a temporary Warp kernel cache
(WARP_CACHE_PATH) with stderr on a pseudo-terminal; the real cache is never touched."""

import io
import os
import pty
import subprocess
import sys

import warp as wp

from terrainwarp.io.native import first_compile_note, say_first_compile

# what the terrainwarp command does on start (runtime.configure_from_env), then a first kernel
CODE = "import terrainwarp as tw; from terrainwarp import runtime; runtime.configure_from_env(); tw.Heightmap.fbm(9)"


def _env(cache):
    env = {**os.environ, "WARP_CACHE_PATH": str(cache)}
    env.pop("TERRAINWARP_VERBOSE", None)
    return env


def _run_on_tty(cache):
    """(exit code, what the process wrote on its stderr, a terminal)."""
    master, slave = pty.openpty()
    try:
        p = subprocess.Popen([sys.executable, "-c", CODE], env=_env(cache), stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=slave)
        os.close(slave)
        chunks = []
        while True:
            try:
                b = os.read(master, 4096)
            except OSError:  # EIO: the child closed the terminal
                break
            if not b:
                break
            chunks.append(b)
        rc = p.wait(timeout=600)
    finally:
        os.close(master)
    return rc, b"".join(chunks).decode().replace("\r\n", "\n")


def test_first_run_on_a_terminal_says_once_that_kernels_are_compiled(tmp_path):
    cache = tmp_path / "warp-cache"
    rc, err = _run_on_tty(cache)
    assert rc == 0, err
    assert err == (f"terrainwarp: compiling Warp kernels on first use; they are cached in "
                   f"{os.path.realpath(cache)}{os.sep}{wp.config.version} (about a minute, once)\n")
    assert _run_on_tty(cache) == (0, "")  # once: the kernels are cached now


def test_first_run_through_a_pipe_prints_nothing(tmp_path):
    r = subprocess.run([sys.executable, "-c", CODE], env=_env(tmp_path / "c"), capture_output=True, text=True,
                       timeout=600)
    assert (r.returncode, r.stdout, r.stderr) == (0, "", "")  # no compiler warnings either


def test_note_only_without_cached_terrainwarp_kernels(tmp_path):
    assert first_compile_note(None) is None
    assert first_compile_note(tmp_path / "missing").startswith("terrainwarp: compiling Warp kernels")
    assert first_compile_note(tmp_path) is not None  # empty
    (tmp_path / "wp_other.module_abc").mkdir()  # another program's kernels do not count
    assert first_compile_note(tmp_path) is not None
    tty, pipe = io.StringIO(), io.StringIO()
    tty.isatty = lambda: True
    assert say_first_compile(tmp_path, tty) and tty.getvalue().count("\n") == 1
    assert not say_first_compile(tmp_path, pipe) and pipe.getvalue() == ""
    (tmp_path / "wp_terrainwarp.kernels.noise_459b100").mkdir()
    assert first_compile_note(tmp_path) is None
    assert not say_first_compile(tmp_path, tty) and tty.getvalue().count("\n") == 1
