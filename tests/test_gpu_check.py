"""scripts/gpu-check.sh, tried here as far as it goes without a GPU: its --cpu-only dry run (the CPU standing in
for cuda:0, the tree copied as a device call carries it, the packages the GPU machine lacks hidden) runs every
stage and writes what a device call can bring back; and the parity script's comparison sees a 1-ulp change."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

COMPARE = """
import numpy as np, cuda_parity as cp
a = np.linspace(-3, 3, 101, dtype=np.float32)
b = a.copy(); b[7] = np.nextafter(b[7], np.float32(9))
assert cp.compare(a, a)["diff"] == 0 and cp.verdict("float", cp.compare(a, a)) == "bit-identical"
c = cp.compare(a, b); assert (c["diff"], c["ulps"]) == (1, 1.0) and cp.verdict("float", c).startswith("within")
b[8] += 1.0; assert cp.verdict("float", cp.compare(a, b)) == "MISMATCH"
n = a.copy(); n[3] = np.nan; assert cp.compare(a, n)["nan"] == 1 and cp.verdict("float", cp.compare(a, n)) == "MISMATCH"
i = np.arange(10, dtype=np.int32); j = i.copy(); j[4] = 5
assert cp.verdict("int", cp.compare(i, i)) == "bit-identical" and cp.verdict("int", cp.compare(i, j)) == "MISMATCH"
assert cp.verdict("int", cp.compare(i, i[:9])).startswith("MISMATCH")
print("compared")
"""


def test_parity_comparison_sees_one_ulp_and_any_integer_change():
    out = subprocess.run([sys.executable, "-c", COMPARE], cwd=ROOT / "benchmarks", capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip().endswith("compared"), out.stderr[-2000:]


def test_cpu_only_dry_run_runs_every_stage_and_writes_what_a_device_call_brings_back(tmp_path):
    out = tmp_path / "out"
    p = subprocess.run(["bash", str(ROOT / "scripts" / "gpu-check.sh"), "--cpu-only", "--quick", str(out)],
                       capture_output=True, text=True, env={"PATH": "/usr/bin:/bin", "GPU_CHECK_PAYLOAD": "0",
                                                            "HOME": str(Path.home())}, timeout=600)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    readme = (out / "README.md").read_text()
    for stage in ("compile (Warp's cache, cpu): ok", "parity (fuse_fp on): ok", "frame timings: ok",
                  "device tests (-k cpu): ok", "parity (fuse_fp off): ok", "calibration (GL): ok",
                  "codegen (sm_90 PTX): ok"):
        assert stage in readme, readme
    files = sorted(f.name for f in out.iterdir())
    assert len(files) <= 8 and all(re.fullmatch(r"[A-Za-z0-9._-]+", f) for f in files)  # the device's limits
    parity = (out / "cuda_parity.md").read_text()
    assert "0 mismatch(es)" in parity and parity.count("bit-identical") > 40
    assert re.search(r"\d+ passed", (out / "tests.log").read_text())
    assert "| tessellator |" in (out / "codegen.md").read_text()
    assert "R^2 held out" in (out / "calibration_gpu.md").read_text()
    assert "Warp from .venv" in readme and "terrainwarp from" in (out / "run.log").read_text()
