"""Run every benchmarks/bench_*.py in turn (each in its own process), then rebuild BENCHMARKS.md."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    rc = 0
    for b in sorted(HERE.glob("bench_*.py")):
        print(f"== {b.name}", flush=True)
        r = subprocess.run([sys.executable, str(b), *sys.argv[1:]], cwd=HERE.parent)
        rc = rc or r.returncode
    subprocess.run([sys.executable, str(HERE / "collect.py")], cwd=HERE.parent)
    return rc


if __name__ == "__main__":
    sys.exit(main())
