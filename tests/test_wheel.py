"""The wheel, tested as a user gets it: built from the tracked sources, installed into a fresh virtual environment
outside the repository with no index (its dependencies resolved from those already installed here, reached by a
.pth file), then ``terrainwarp demo`` and a short snippet run there, importing the installed copy."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list, cwd: Path) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    r = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"{args[:4]}: {r.stdout[-2000:]}\n{r.stderr[-4000:]}"
    return r.stdout


def test_the_wheel_installs_offline_into_a_fresh_venv_and_runs(tmp_path):
    src = tmp_path / "src"
    files = subprocess.run(["git", "ls-files", "pyproject.toml", "README.md", "terrainwarp", "kernels"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        (src / f).write_bytes((ROOT / f).read_bytes())
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    _run([*pip, "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index", "-w", tmp_path / "dist", "./src"],
         tmp_path)
    (wheel,) = (tmp_path / "dist").glob("terrainwarp-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "terrainwarp/kernels/raster.py" in names and "terrainwarp/schemes.py" in names
    profiles = {f"terrainwarp/measure/gpu_profiles/{g}.toml" for g in ("gf100", "gcn", "rdna", "mali", "nv40")}
    assert profiles <= set(names)  # the GPU profiles ship as package data
    assert not any(n.startswith(("tests/", "kernels/", "examples/")) for n in names)  # kernels/ maps in, once

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], tmp_path)
    site = Path(sysconfig.get_path("purelib", vars={"base": str(venv), "platbase": str(venv)}))
    (site / "_installed_dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
    _run([*pip, "--python", venv / "bin" / "python", "install", "-q", "--no-index", wheel], tmp_path)  # deps checked

    out = _run([venv / "bin" / "terrainwarp", "demo", "--out", tmp_path / "demo", "--width", "64", "--height", "48"],
               tmp_path)
    assert "wrote:" in out and {p.name for p in (tmp_path / "demo").iterdir()} == {"frame.png", "depth.exr",
                                                                                   "report.json"}
    snippet = ("import terrainwarp as tw\n"
               "tw.configure(quiet=True)\n"
               "hm = tw.Heightmap.fbm(33, seed=1)\n"
               "f = tw.render(tw.Scene(hm, camera=tw.Camera.default_for(hm, 32, 24)))\n"
               "print('installed:', tw.__file__, tw.kernels.__file__, f.image.shape, len(f._repr_png_()) > 100,\n"
               "      ','.join(tw.schemes.scheme_names()))\n")
    line = next(ln for ln in _run([venv / "bin" / "python", "-c", snippet], tmp_path).splitlines()
                if ln.startswith("installed: "))
    where, kernels, *rest = line.removeprefix("installed: ").split()
    assert where.startswith(str(site)) and kernels.startswith(str(site / "terrainwarp" / "kernels"))
    assert rest == ["(24,", "32,", "3)", "True", "cdlod,clipmaps,chunked"]
