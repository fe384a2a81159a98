"""Every command fed bad arguments, paths, scene files and heightmaps (issue 20, "Done when"): each run
prints exactly one line on stderr, exits with code 2, and leaves no file in ``--out`` that was not there
before. Output paths (issue 20 item 3): a read-only filesystem, ``--out`` naming a file or a path under a
file, ``demo`` in an unwritable folder, and a reused ``--out`` holding files from an earlier run.

The tests run as root in CI, where permissions are not enforced; the unwritable places used here fail for
root too: a path under a regular file, ``/proc`` (no folder can be made there), and a read-only filesystem
simulated by making the writes fail with EROFS (a real read-only mount needs privileges the tests do not
take). A ``chmod 0o555`` folder is tested only when not running as root.
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import terrainwarp.cli as cli
from terrainwarp.cli import main

SMALL = ["--width", "32", "--height", "24"]
SCENE_COMMANDS = {  # command -> quick arguments (besides the scene and --out)
    "render": SMALL,
    "lod": SMALL,
    "report": [*SMALL, "--frames", "2", "--quick", "--policies", "grid", "--workers", "0", "--no-images",
               "--no-progress"],
    "fit": [*SMALL, "--frames", "2", "--budget-px", "2", "--no-progress"],
}


def _run(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def _files(d: Path) -> set[Path]:
    return {p for p in d.rglob("*")} if d.exists() else set()


def _check_refused(argv: list[str], out: Path, capsys, *, match: str | None = None) -> str:
    """Run ``argv`` with ``--out out``: exit 2, one stderr line, no new file in ``out``; returns the line."""
    before, existed = _files(out), out.exists()
    capsys.readouterr()
    rc = _run([*argv, "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, (argv, rc, err)
    assert len(err) == 1 and err[0].startswith("terrainwarp: error:"), (argv, err)
    assert _files(out) <= before, (argv, sorted(_files(out) - before))
    assert out.exists() == existed, argv
    if match is not None:
        assert match in err[0], (argv, err[0])
    return err[0]


# -- bad scene files and heightmaps -----------------------------------------------------------------------
def _bad_scenes(d: Path) -> dict[str, tuple[Path, str]]:
    """name -> (scene path, a word the error line must hold)."""
    d.mkdir()

    def toml(name: str, text: str) -> Path:
        (d / name).write_text(text)
        return d / name

    (d / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")
    np.save(d / "nan.npy", np.full((9, 9), np.nan, np.float32))
    (d / "heights.txt").write_text("1 2 3\n")
    (d / "a_dir.toml").mkdir()
    return {
        "bad_toml": (toml("bad.toml", "[heightmap\nexample = 1\n"), "TOML"),
        "binary": ((d / "corrupt.png"), "TOML"),
        "unknown_key": (toml("unk.toml", '[heightmap]\nexample = "jacksboro"\n[render]\nspeed = 3\n'), "speed"),
        "unknown_table": (toml("unkt.toml", '[heightmap]\nexample = "jacksboro"\n[weather]\nrain = 1\n'), "weather"),
        "directory": ((d / "a_dir.toml"), "directory"),
        "missing": ((d / "missing.toml"), "missing.toml"),
        "missing_heightmap": (toml("mh.toml", '[heightmap]\npath = "nowhere.png"\n'), "nowhere.png"),
        "heightmap_is_dir": (toml("hd.toml", '[heightmap]\npath = "."\n'), "directory"),
        "heightmap_not_image": (toml("ht.toml", '[heightmap]\npath = "heights.txt"\n'), "heights.txt"),
        "corrupt_png": (toml("cp.toml", '[heightmap]\npath = "corrupt.png"\n'), "corrupt.png"),
        "nan_only": (toml("nan.toml", '[heightmap]\npath = "nan.npy"\n'), "NaN"),
        "bad_example": (toml("ex.toml", '[heightmap]\nexample = "atlantis"\n'), "atlantis"),
        "bad_lod": (toml("lod.toml", '[heightmap]\nexample = "jacksboro"\n[lod]\nroots = 0\n'), "roots"),
        "bad_tess": (toml("tess.toml", '[heightmap]\nexample = "jacksboro"\n[lod]\ntess = 16.0\n'), "tess"),
        "fov_0": (toml("fov.toml", '[heightmap]\nexample = "jacksboro"\n[camera]\nfov_y_deg = 0\n'), "fov"),
        "negative_size": (toml("neg.toml", '[heightmap]\nexample = "jacksboro"\n[camera]\nwidth = -3\n'), "width"),
    }


@pytest.fixture(scope="module")
def bad_scenes(tmp_path_factory) -> dict[str, tuple[Path, str]]:
    return _bad_scenes(tmp_path_factory.mktemp("scenes") / "s")


@pytest.mark.parametrize("command", list(SCENE_COMMANDS))
def test_every_scene_command_refuses_every_bad_scene(command, bad_scenes, tmp_path, capsys):
    out = tmp_path / "out"
    for name, (scene, word) in bad_scenes.items():
        if command == "lod" and name in ("bad_lod", "bad_tess"):  # lod takes its LOD numbers from its options
            continue
        _check_refused([command, str(scene), *SCENE_COMMANDS[command]], out, capsys, match=word)
    (out / "keep.txt").parent.mkdir()
    (out / "keep.txt").write_text("mine")  # an --out that already holds a file: it stays, nothing is added
    for scene, word in list(bad_scenes.values())[:3]:
        _check_refused([command, str(scene), *SCENE_COMMANDS[command]], out, capsys, match=word)
    assert (out / "keep.txt").read_text() == "mine"


# -- bad arguments, every command ------------------------------------------------------------------------
BAD_ARGUMENTS = {
    "demo": [["--width", "0"], ["--width", "x"], ["--height", "-1"], ["--bogus"], ["extra.toml"]],
    "render": [["--width", "1.5"], ["a.toml", "b.toml"], ["--frames", "2"]],
    "lod": [["--policy", "magic"], ["--tolerance-px", "0"], ["--tolerance-px", "nan"], ["--k", "-1"],
            ["--tess", "3"], ["--tess", "16.0"], ["--tess", "128"], ["--roots", "0"], ["--hysteresis", "1"],
            ["--hysteresis", "x"], ["--level", "-1"], ["--policy", "continuous", "--tess", "0"]],
    "report": [["--frames", "0"], ["--policies", "grid,magic", *SMALL, "--frames", "1"], ["--workers", "-1"],
               ["--frames", "x"]],
    "fit": [[], ["--budget-px", "0"], ["--budget-px", "inf"], ["--budget-px", "1", "--grid-points", "-1"],
            ["--budget-px", "1", "--workers", "-1"], ["--budget-px", "1", "--policy", "magic"],
            ["--budget-px", "1", "--frames", "0"], ["--budget-px", "1", "--curve-budgets", "-2"]],
    "stability": [["--cases", "atlantis"], ["--fast"]],
    "tessellate": [["--outer", "3", "5", "1", "--inner", "4", "4"], ["--outer", "1", "1", "1", "1"],
                   ["--outer", "1", "1", "1", "1", "--inner", "4", "4", "--spacing", "pow2"],
                   ["--outer", "a", "1", "1", "1", "--inner", "4", "4"]],
}


@pytest.mark.parametrize("command", list(BAD_ARGUMENTS))
def test_every_command_refuses_bad_arguments(command, tmp_path, capsys):
    out = tmp_path / "out"
    for argv in BAD_ARGUMENTS[command]:
        _check_refused([command, *argv], out, capsys)


def test_bench_refuses_unknown_names_and_a_missing_folder(monkeypatch, capsys):
    for argv in (["bench", "no_such_bench"], ["bench", "--bogus"]):
        assert _run(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("terrainwarp: error:")
    monkeypatch.setattr(cli, "BENCHMARKS_DIR", Path(cli.__file__).parent / "benchmarks")  # as in a wheel
    assert _run(["bench"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no benchmarks" in err[0]


# -- output paths (issue 20 item 3) ----------------------------------------------------------------------
QUICK = {  # the quickest successful run of each command that writes to --out
    "demo": ["demo", *SMALL],
    "render": ["render", *SMALL],
    "lod": ["lod", *SMALL],
    "tessellate": ["tessellate", "--outer", "2", "2", "2", "2", "--inner", "2", "2"],
    "stability": ["stability", "--cases", "flat", "--no-progress"],
    "fit": ["fit", "--budget-px", "2", *SMALL, "--frames", "1", "--no-progress"],
    "report": ["report", *SCENE_COMMANDS["report"]],
}


@pytest.mark.parametrize("command", list(QUICK))
def test_out_naming_a_file_or_a_path_under_a_file(command, tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("mine")
    line = _check_refused(QUICK[command], f, capsys)
    assert "is a file" in line and str(f) in line
    line = _check_refused(QUICK[command], f / "sub" / "dir", capsys)
    assert "under the file" in line and str(f) in line
    assert f.read_text() == "mine"


@pytest.mark.parametrize("command", ["demo", "lod", "tessellate", "stability"])
def test_out_where_no_folder_can_be_made(command, capsys):
    # /proc takes no new folder, for root too
    out = Path("/proc/terrainwarp-no-such-dir/out")
    _check_refused(QUICK[command], out, capsys)


def test_demo_in_an_unwritable_working_folder(monkeypatch, capsys):
    monkeypatch.chdir("/proc")  # the default --out, out/demo, cannot be made here, for root too
    assert _run(["demo", *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("terrainwarp: error:")
    assert not Path("/proc/out").exists()


@pytest.mark.parametrize("command", ["demo", "lod", "tessellate"])
def test_out_in_a_read_only_folder(command, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    if os.geteuid() == 0:
        # root ignores folder permissions (CI runs as root): the kernel's answer for anyone else is what the
        # CLI must act on, so give it that answer for this folder
        real_access = os.access

        def access(path, mode, *args, **kwargs):
            if mode & os.W_OK and Path(path).resolve().is_relative_to(ro.resolve()):
                return False
            return real_access(path, mode, *args, **kwargs)

        monkeypatch.setattr(os, "access", access)
    try:
        _check_refused(QUICK[command], ro / "out", capsys, match=str(ro))
        _check_refused(QUICK[command], ro, capsys, match=str(ro))
    finally:
        ro.chmod(0o755)


def test_read_only_filesystem_reports_the_first_error_not_the_cleanup(monkeypatch, tmp_path, capsys):
    """On a read-only filesystem the write fails with EROFS, and so does removing the temporary file
    (terrainwarp.io.files.atomic_path): the line names the write's error, not the cleanup's. Simulated:
    every rename into place and every removal of a temporary file fails with EROFS."""
    import terrainwarp.io.files as files

    def replace(src, dst):
        raise OSError(errno.EROFS, "Read-only file system (the write)", str(dst))

    real_unlink = Path.unlink

    def unlink(self, missing_ok=False):
        if ".tmp" in self.name:
            real_unlink(self, missing_ok=True)
            raise OSError(errno.EROFS, "Read-only file system (the cleanup)", str(self))
        return real_unlink(self, missing_ok=missing_ok)

    monkeypatch.setattr(files.os, "replace", replace)
    monkeypatch.setattr(Path, "unlink", unlink)
    for argv in (QUICK["demo"], QUICK["tessellate"], QUICK["lod"]):
        line = _check_refused(argv, tmp_path / "out", capsys)
        assert "(the write)" in line and "cleanup" not in line, line


def test_a_failure_after_some_files_were_written_leaves_none(monkeypatch, tmp_path, capsys):
    import terrainwarp.rendering.pipeline as pipeline

    real = pipeline.write_image

    def write_image(path, a):
        if Path(path).suffix == ".exr":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, a)

    monkeypatch.setattr(pipeline, "write_image", write_image)
    out = tmp_path / "deep" / "out"
    line = _check_refused(QUICK["demo"], out, capsys)  # frame.png was written, then depth.exr failed
    assert "No space left" in line and "depth.exr" in line
    assert not (tmp_path / "deep").exists()  # the folders the run made are gone too


def test_reused_out_names_files_this_run_did_not_write(tmp_path, capsys):
    out = tmp_path / "out"
    assert main([*QUICK["lod"], "--out", str(out)]) == 0
    assert "note" not in capsys.readouterr().err
    (out / "old_frame.png").write_bytes(b"from another run")
    assert main([*QUICK["lod"], "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "note" in err[0] and "old_frame.png" in err[0] and "lod.png" not in err[0]
    assert (out / "old_frame.png").read_bytes() == b"from another run"  # named, never deleted
    assert main([*QUICK["tessellate"], "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert all(n in err for n in ("old_frame.png", "lod.png", "patches.csv")) and "tessellation" not in err


# -- the real entry point: no traceback ------------------------------------------------------------------
@pytest.mark.parametrize("argv", [["render", "{scene}", *SMALL], ["lod", "--tess", "3"], ["demo", *SMALL, "--out",
                                                                                          "{file}"]])
def test_entry_point_one_line_no_traceback(argv, bad_scenes, tmp_path):
    f = tmp_path / "a_file"
    f.write_text("x")
    argv = [a.format(scene=bad_scenes["nan_only"][0], file=f) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    r = subprocess.run([sys.executable, "-m", "terrainwarp.cli", *argv], capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("terrainwarp: error:")]
    assert len(lines) == 1, r.stderr
    assert not (tmp_path / "out").exists()


def _scene_files(tmp_path):
    files = {}
    (tmp_path / "bin.toml").write_bytes(b"\xff\xfe\x00binary")
    files["not_toml"] = tmp_path / "bin.toml"
    (tmp_path / "unk.toml").write_text('[heightmap]\nexample = "jacksboro"\n[render]\nspeed = 3\n')
    files["unknown_key"] = tmp_path / "unk.toml"
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")
    (tmp_path / "corrupt.toml").write_text('[heightmap]\npath = "corrupt.png"\n')
    files["corrupt_image"] = tmp_path / "corrupt.toml"
    (tmp_path / "neg.toml").write_text('[heightmap]\nexample = "jacksboro"\n[camera]\nwidth = -3\n')
    files["negative_size"] = tmp_path / "neg.toml"
    (tmp_path / "nan.toml").write_text('[heightmap]\nexample = "jacksboro"\n[camera]\nposition = [nan, 1, 2]\n'
                                       'target = [0, 0, 0]\n')
    files["nan_camera"] = tmp_path / "nan.toml"
    return files


@pytest.mark.parametrize("which", ["not_toml", "unknown_key", "corrupt_image", "negative_size", "nan_camera"])
def test_cli_bad_scene_files_one_line_exit_2_no_output(tmp_path, capsys, which):
    f = _scene_files(tmp_path)[which]
    out = tmp_path / "out"
    assert main(["render", str(f), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("terrainwarp: error:") and "Traceback" not in err[0]
    assert not out.exists() or not any(out.iterdir())
