"""A command that fails or is interrupted leaves ``--out`` as it was (issue 31, defects 4-6): the previous
set of files whole, nothing new but a sweep's resumable journal, one line on stderr.

* a full disk while overwriting an earlier run (a 2 MiB tmpfs, mounted in a private mount namespace with
  ``unshare``): the error names the file, its size and the cause; the earlier 1920x1080 set stays whole;
* SIGINT while ``render`` writes its files: exit 130, one line, nothing new in ``--out``;
* Ctrl-C (SIGINT to the process group, as a terminal sends it) during ``report`` on Dask workers: one line,
  exit 130, the journal kept, and a rerun resumes from it to the uninterrupted table.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

CLI = [sys.executable, "-m", "terrainwarp.cli"]
ENV = {k: v for k, v in os.environ.items() if k != "TERRAINWARP_VERBOSE"}

_FULL_DISK = r"""
import hashlib, json, os, subprocess, sys
d = sys.argv[1]
subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", d], check=True)
cli = [sys.executable, "-m", "terrainwarp.cli", "demo", "--out", d + "/y"]
state = lambda: {f: hashlib.sha256(open(os.path.join(d, "y", f), "rb").read()).hexdigest()
                 for f in sorted(os.listdir(d + "/y"))}
first = subprocess.run(cli + ["--width", "1920", "--height", "1080"], capture_output=True, text=True)
before = state()
second = subprocess.run(cli + ["--width", "2200", "--height", "1240"], capture_output=True, text=True)
print(json.dumps({"first": first.returncode, "before": before, "rc": second.returncode, "err": second.stderr,
                  "after": state()}))
"""


def _private_mount_namespace() -> list[str] | None:
    """A command prefix that runs a program in a private mount namespace where it may mount a tmpfs."""
    if shutil.which("unshare") is None:
        return None
    for prefix in (["unshare", "-m"], ["unshare", "-rm"]):  # as root; else in a user namespace
        if subprocess.run([*prefix, "true"], capture_output=True).returncode == 0:
            return prefix
    return None


def test_a_full_disk_while_overwriting_leaves_the_earlier_set_whole(tmp_path):
    prefix = _private_mount_namespace()
    if prefix is None:
        pytest.skip("no private mount namespace here to mount a small tmpfs in (the ENOSPC path itself is "
                    "tested in tests/io/test_files.py)")
    (tmp_path / "m").mkdir()
    r = subprocess.run([*prefix, sys.executable, "-c", _FULL_DISK, str(tmp_path / "m")], capture_output=True,
                       text=True, env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["first"] == 0 and sorted(got["before"]) == ["depth.exr", "frame.png", "report.json"]
    assert got["rc"] == 2
    lines = got["err"].strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in got["err"]
    assert "no space left on device writing depth.exr (10.9 MB)" in lines[0], lines  # 2200 x 1240 float32
    assert got["after"] == got["before"]  # the 1920x1080 set, whole; no temporary file left either


def _files(d: Path) -> dict[str, str]:
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(d.rglob("*")) if p.is_file()}


def _wait_for(pred, timeout: float, proc: subprocess.Popen) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.005)
    return False


def test_sigint_while_render_writes_leaves_nothing_new(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "mine.txt").write_text("kept\n")
    before = _files(out)
    p = subprocess.Popen([*CLI, "demo", "--width", "3840", "--height", "2160", "--out", str(out)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV)
    # the moment the issue saw frame.png left alone: its files being written (temporary names in --out)
    started = _wait_for(lambda: any(f.name.startswith(".") for f in out.iterdir()), 300, p)
    p.send_signal(signal.SIGINT)
    err = p.communicate(timeout=120)[1]
    assert started, err
    assert p.returncode == 130, err
    assert err.strip().splitlines() == ["terrainwarp: interrupted"]
    assert _files(out) == before


def test_ctrl_c_during_report_on_workers_prints_one_line_and_keeps_the_journal(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text('[heightmap]\nfbm = { rows = 65, seed = 3 }\n[camera]\nwidth = 64\nheight = 48\n')
    out = tmp_path / "r"
    argv = [*CLI, "report", str(scene), "--out", str(out), "--frames", "3", "--quick", "--no-images",
            "--no-progress", "--workers", "2", "--policies", "sse,distance,grid"]
    p = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV,
                         start_new_session=True)  # its own process group, as a terminal's job
    journal = out / "frames.csv.partial"
    rows = lambda: journal.exists() and journal.read_text().count("\n") >= 3  # noqa: E731 - header + one row
    started = _wait_for(rows, 300, p)
    os.killpg(p.pid, signal.SIGINT)  # the terminal's Ctrl-C: the driver and every worker get it
    err = p.communicate(timeout=120)[1]
    assert started, err
    assert p.returncode == 130, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("terrainwarp: interrupted (a rerun resumes from "), err
    assert sorted(_files(out)) == ["frames.csv.partial"]  # the journal, and nothing else
    kept = [ln.split(",", 1)[0] for ln in journal.read_text().splitlines()[2:]]  # job ids finished before
    assert kept
    r = subprocess.run(argv[:-2] + ["--workers", "0"], capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    assert {"frames.csv", "pareto.png", "report.md"} <= set(_files(out)) and not journal.exists()


# ------------------------------------------------------------------------------------------------
# issue 43: a sweep with failed jobs still reports, a rerun retries them; a cluster that fails to start
# ------------------------------------------------------------------------------------------------
_FLAKY = '''
import os
import terrainwarp as tw
from terrainwarp.schemes import scheme_source

HERE = os.path.dirname(os.path.abspath(__file__))


class Flaky(tw.rendering.SourceBase):
    """Chunked LOD that raises on the second half of the path while the file 'fail' lies beside this plugin."""

    def __init__(self, hm, v, cache):
        self.inner, self.hm = scheme_source("chunked", hm, v, cache=cache), hm

    def __getattr__(self, k):
        return getattr(self.__dict__["inner"], k)

    def mesh_for(self, camera):
        (x0, _), (x1, _) = self.hm.bounds_xz
        late = camera.position[0] > 0.5 * (x0 + x1)
        with open(os.path.join(HERE, "calls.log"), "a") as f:
            f.write(f"{late}\\n")
        if late and os.path.exists(os.path.join(HERE, "fail")):
            raise RuntimeError("flaky frame")
        return self.inner.mesh_for(camera)


tw.schemes.register_scheme("flaky", lambda hm, v, *, cache, **kw: Flaky(hm, v, cache), parameter="v", lo=0.1,
                           hi=64, larger_is_finer=False, replace=True)
'''


@pytest.fixture
def _schemes_restored():
    """The schemes registry as it was (the plugin's scheme must not reach the other tests' policy lists)."""
    from terrainwarp.schemes import SCHEMES, unregister_scheme

    before = set(SCHEMES)
    yield
    for name in set(SCHEMES) - before:
        unregister_scheme(name)


def test_a_report_with_failed_frames_is_written_and_a_rerun_retries_them(tmp_path, capsys, _schemes_restored):
    from terrainwarp.cli import main

    plugin = tmp_path / "flaky.py"
    plugin.write_text(_FLAKY)
    (tmp_path / "fail").touch()
    scene = tmp_path / "s.toml"
    scene.write_text('[heightmap]\nfbm = { rows = 65, seed = 3 }\n[camera]\nwidth = 48\nheight = 32\n')
    out = tmp_path / "r"
    argv = ["report", str(scene), "--plugin", str(plugin), "--policies", "grid,flaky", "--quick", "--frames", "2",
            "--workers", "0", "--no-progress", "--no-images", "--out", str(out)]
    assert main(argv) == 1  # written, and the exit says some frames failed
    err = capsys.readouterr().err
    assert "Traceback" not in err and "cannot convert float NaN" not in err
    assert err.strip().splitlines()[-1].startswith("terrainwarp: 2 of 6 frames failed")
    rows = list(csv.DictReader(io.StringIO((out / "frames.csv").read_text())))
    assert [r["error"] for r in rows if r["policy"] == "flaky"].count("RuntimeError: flaky frame") == 2
    md = (out / "report.md").read_text()
    assert "Failed frames: 2 of 6" in md and "left out of the Pareto fronts" in md
    assert "## Pareto front" in md and "flaky" not in md.split("## Pareto front")[1].split("## Cameras")[0]
    assert (out / "frames.csv.partial").exists()  # the failed frames are to run again
    (tmp_path / "calls.log").unlink()
    (tmp_path / "fail").unlink()
    assert main(argv) == 0
    # the two failed frames alone (frame 1 of each setting: its own mesh, then frame 0's for its popping)
    assert (tmp_path / "calls.log").read_text().split() == ["True", "False"] * 2
    rows = list(csv.DictReader(io.StringIO((out / "frames.csv").read_text())))
    assert all(r["error"] == "" for r in rows) and not (out / "frames.csv.partial").exists()
    assert "Failed frames" not in (out / "report.md").read_text()


def test_a_cluster_that_fails_to_start_is_one_line_and_exit_2(tmp_path):
    die = tmp_path / "die"
    die.mkdir()
    (die / "sitecustomize.py").write_text("import os\nos._exit(3)\n")  # every worker process dies as it starts
    env = {**ENV, "DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON": json.dumps({"PYTHONPATH": str(die)})}
    r = subprocess.run([*CLI, "report", "--quick", "--frames", "1", "--width", "48", "--height", "32", "--workers",
                        "1", "--policies", "grid", "--no-progress", "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith("terrainwarp: error: workers: the local Dask cluster of 1 worker process(es) failed "
                               "to start")
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------------------
# issue 43: SIGTERM and SIGHUP as SIGINT; a killed run leaves the old set or the new one, never a mix
# ------------------------------------------------------------------------------------------------
def _temporaries(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if ".tmp" in p.name or p.name.startswith(".terrain"))


def _earlier_set(out: Path) -> dict[str, str]:
    r = subprocess.run([*CLI, "demo", "--width", "160", "--height", "90", "--out", str(out)], capture_output=True,
                       text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr
    return _files(out)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_while_writing_leave_the_earlier_set_whole(tmp_path, sig):
    out = tmp_path / "o"
    before = _earlier_set(out)
    p = subprocess.Popen([*CLI, "demo", "--width", "1920", "--height", "1080", "--out", str(out)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV)
    started = _wait_for(lambda: bool(_temporaries(out)), 300, p)  # its files being written
    p.send_signal(sig)
    err = p.communicate(timeout=120)[1]
    assert started, err
    assert p.returncode == 128 + sig, err
    assert err.strip().splitlines() == [f"terrainwarp: interrupted by {signal.Signals(sig).name}"]
    assert _files(out) == before and not _temporaries(out)


def test_sigkill_in_the_write_phase_leaves_no_mix_and_the_next_run_no_temporary(tmp_path):
    out = tmp_path / "o"
    before = _earlier_set(out)
    p = subprocess.Popen([*CLI, "demo", "--width", "1920", "--height", "1080", "--out", str(out)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
    started = _wait_for(lambda: bool(_temporaries(out)), 300, p)
    p.kill()
    p.wait(timeout=60)
    assert started
    left = _files(out)
    assert {k: v for k, v in left.items() if k in before} == before  # the earlier set, not one file new
    assert set(left) - set(before) == set(_temporaries(out)) != set()  # and the dead run's temporaries
    r = subprocess.run([*CLI, "tessellate", "--outer", "3", "5", "1", "7", "--inner", "4", "4", "--out", str(out)],
                       capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "removed" in r.stderr and "temporary file(s) that a killed run left" in r.stderr
    assert ".tmp" not in r.stderr  # the stale-file note names no temporary: there is none left
    assert not _temporaries(out)
    assert {k: v for k, v in _files(out).items() if k in before} == before


_KILLED_IN_THE_COMMIT = r"""
import os, signal, sys
import terrainwarp.io.files as files
real = files._roll_forward
def roll_one_then_die(folder, body):  # the commit record is in place: rename one file, then SIGKILL
    os.replace(folder / body["moves"][0][0], folder / body["moves"][0][1])
    os.kill(os.getpid(), signal.SIGKILL)
files._roll_forward = roll_one_then_die
from terrainwarp.cli import main
main(sys.argv[1:])
"""


def test_sigkill_in_the_commit_is_finished_by_the_next_run(tmp_path):
    out, fresh = tmp_path / "o", tmp_path / "fresh"
    before = _earlier_set(out)
    argv = ["demo", "--width", "320", "--height", "180", "--out"]
    r = subprocess.run([sys.executable, "-c", _KILLED_IN_THE_COMMIT, *argv, str(out)], env=ENV, timeout=300,
                       capture_output=True, text=True)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert (out / ".terrainwarp-commit.json").exists()  # killed between the commit point and the last rename
    mixed = _files(out)
    assert sum(mixed[k] != before[k] for k in before) == 1  # one file switched, the others not yet
    subprocess.run([*CLI, *argv, str(fresh)], env=ENV, timeout=300, capture_output=True, check=True)
    new = _files(fresh)  # the set the killed run was committing (outputs are deterministic)
    r = subprocess.run([*CLI, "tessellate", "--outer", "2", "2", "2", "2", "--inner", "2", "2", "--out", str(out)],
                       capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "finished the commit of an earlier run that was killed" in r.stderr
    got = _files(out)
    assert {k: got[k] for k in ("frame.png", "depth.exr")} == {k: new[k] for k in ("frame.png", "depth.exr")}
    assert _untimed(out / "report.json") == _untimed(fresh / "report.json") and not _temporaries(out)


def _untimed(path: Path) -> object:
    """A report.json without its wall times (``*_ms``: the one part of it that differs between runs)."""
    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if not k.endswith("_ms")}
        return [strip(v) for v in o] if isinstance(o, list) else o
    return strip(json.loads(path.read_text()))
