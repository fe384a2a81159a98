"""``import terrainwarp`` changes nothing process-wide; :func:`terrainwarp.configure` does, when asked. A first
frame prints nothing (no Warp greeting, no per-module lines, no CUDA-driver warning on a machine without one) and
leaves Warp's settings as it found them.

Each check runs in a fresh interpreter that records what the import (and a first frame) did: Warp's log
level, every ``os.dup2`` (file descriptor 2 pointed elsewhere), every ``os.register_at_fork``, and every C
symbol looked up through ctypes (the ``ctypes.dlsym`` audit event: ``mallopt`` is how the allocator is tuned).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

import pytest

import terrainwarp as tw

_PROBE = r"""
import json, os, sys
stderr_file = os.fstat(2).st_ino
calls = {"dup2": [], "fork": [], "dlsym": []}
real_dup2, real_fork = os.dup2, os.register_at_fork
os.dup2 = lambda a, b, *k: (calls["dup2"].append(b), real_dup2(a, b, *k))[1]
os.register_at_fork = lambda **k: (calls["fork"].append(sys._getframe(1).f_code.co_filename), real_fork(**k))[1]
sys.addaudithook(lambda ev, args: calls["dlsym"].append(str(args[1])) if ev == "ctypes.dlsym" else None)
import warp as wp
before = wp.config.log_level
import terrainwarp as tw
after_import = dict(log_level=wp.config.log_level, **json.loads(json.dumps(calls)))
hm = tw.Heightmap.fbm(33, seed=1)
tw.render(tw.Scene(hm, camera=tw.Camera.default_for(hm, 32, 24), outputs=("image",)))
after_frame = dict(log_level=wp.config.log_level, stderr_same=os.fstat(2).st_ino == stderr_file,
                   **json.loads(json.dumps(calls)))
conf = tw.configure(quiet=True, keep_memory=True)
after_configure = dict(log_level=wp.config.log_level, quiet=conf.quiet, keep=conf.keep_memory, **calls)
print(json.dumps({"before": before, "import": after_import, "frame": after_frame, "configure": after_configure}))
"""


def _ours(filename: str) -> bool:
    from pathlib import Path

    roots = (Path(tw.__file__).parent.resolve(), Path(tw.kernels.__file__).parent.resolve())
    return any(Path(filename).resolve().is_relative_to(r) for r in roots)


def _probe() -> tuple[dict, str, str]:
    """What the probe recorded, and what else it printed on stdout and stderr."""
    env = {k: v for k, v in os.environ.items() if k != "TERRAINWARP_VERBOSE"}
    got = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, check=True, env=env)
    *rest, last = got.stdout.splitlines()
    return json.loads(last), "\n".join(rest), got.stderr


def test_import_and_first_frame_print_nothing_and_leave_log_level_stderr_allocator_and_fork_handlers_alone():
    from terrainwarp.kernels.device import cuda_driver_present

    r, out, err = _probe()
    assert (out, err) == ("", "")  # no Warp greeting, no "Module ... load took" lines, no CUDA-driver warning
    assert 2 not in r["import"]["dup2"]  # the import never touches file descriptor 2
    # Warp's start, on a machine with no CUDA driver, runs with fd 2 on the null device (its native warning),
    # and fd 2 is given back; with a driver it is never touched
    assert r["frame"]["dup2"].count(2) == (0 if cuda_driver_present() else 2) and r["frame"]["stderr_same"]
    for stage in ("import", "frame"):
        assert r[stage]["log_level"] == r["before"], stage  # Warp's own level, as the embedding process set it
        assert not [f for f in r[stage]["fork"] if _ours(f)], stage  # no fork handler of ours (the stdlib has some)
        assert "mallopt" not in r[stage]["dlsym"], stage  # the allocator untouched
    c = r["configure"]  # asked for: kept frame memory; quiet is the default and changes no Warp setting
    assert c["log_level"] == r["before"] and c["quiet"] is True and c["keep"] is True
    assert "mallopt" in c["dlsym"] and not [f for f in c["fork"] if _ours(f)]


def test_configure_validates_and_quiet_false_lets_warps_lines_through_without_changing_its_level():
    import warp as wp

    with pytest.raises(TypeError, match="quiet: expected true or false"):
        tw.configure(quiet=1)
    with pytest.raises(TypeError, match="keep_memory: expected true or false"):
        tw.configure(keep_memory="yes")
    with pytest.raises(TypeError, match="n: expected"):
        tw.configure(threads=1.5)
    code = ("import warp as wp, terrainwarp as tw; b = wp.config.log_level; tw.configure(quiet=False); "
            "tw.Heightmap.fbm(9); print(b, wp.config.log_level)")
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "Module terrainwarp.kernels.noise" in got and "Warp " + wp.config.version in got  # Warp's own lines
    level = got.split()[-2:]
    assert level[0] == level[1]
    try:
        assert tw.configure(threads=3).threads == 3
    finally:
        assert tw.configure(threads=None).threads >= 1


def test_the_command_configures_itself_from_the_environment():
    code = ("import sys, warp as wp; from terrainwarp import cli, runtime; b = wp.config.log_level; "
            "rc = cli.main(['tessellate', '--outer', '1', '1', '1', '1', '--inner', '1', '1', '--out', sys.argv[1]]); "
            "print(rc, runtime.configuration().quiet, runtime.configuration().keep_memory, wp.config.log_level == b)")
    with tempfile.TemporaryDirectory() as d:
        env = {k: v for k, v in os.environ.items() if k not in ("TERRAINWARP_VERBOSE", "TERRAINWARP_KEEP_MEMORY")}
        got = subprocess.run([sys.executable, "-c", code, d], capture_output=True, text=True, check=True, env=env)
        assert got.stdout.split()[-4:] == ["0", "True", "True", "True"]
        env.update(TERRAINWARP_VERBOSE="1", TERRAINWARP_KEEP_MEMORY="0")
        got = subprocess.run([sys.executable, "-c", code, d + "/b"], capture_output=True, text=True, check=True,
                             env=env)
        assert got.stdout.split()[-4:-1] == ["0", "False", "False"]
