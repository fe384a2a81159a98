"""make test's time: per-file and slowest-test durations of the test suite (pytest --durations=0), optionally
beside an earlier run's, written to benchmarks/results/make_test.md.

Not a bench_*.py (``make bench`` does not run the whole suite): run it by hand, after ``terrainwarp warmup``::

    .venv/bin/python benchmarks/suite_durations.py                       # runs the suite (~10 min on 2 cores)
    .venv/bin/python benchmarks/suite_durations.py --after OUT.txt --before BASE.txt --note "..."

``--after``/``--before``: the output of ``pytest -q --durations=0`` of a run made earlier (this one's and a
baseline's). On a machine shared with other work, wall times carry the load: compare files of runs made under
similar load, or time the slow files alone, one tree after the other.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import md_table, write_result

ROOT = Path(__file__).resolve().parents[1]
_LINE = re.compile(r"\s*([\d.]+)s (call|setup|teardown)\s+(\S+)")
_TOTAL = re.compile(r"(\d+) passed.* in ([\d.]+)s")


def durations(text: str) -> dict[str, float]:
    """Seconds per test (setup + call + teardown) from pytest's ``--durations=0`` output."""
    out: dict[str, float] = collections.defaultdict(float)
    for line in text.splitlines():
        m = _LINE.match(line)
        if m:
            out[m.group(3)] += float(m.group(1))
    return dict(out)


def per_file(tests: dict[str, float]) -> dict[str, float]:
    out: dict[str, float] = collections.Counter()
    for node, s in tests.items():
        out[node.split("::")[0]] += s
    return dict(out)


def wall(text: str) -> str:
    m = _TOTAL.search(text)
    return f"{m.group(1)} passed in {float(m.group(2)):.0f} s" if m else "?"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--after", type=Path, help="a run's pytest --durations=0 output (default: run the suite now)")
    ap.add_argument("--before", type=Path, help="a baseline run's output, for the before column")
    ap.add_argument("--files", type=int, default=30, help="files in the table")
    ap.add_argument("--tests", type=int, default=30, help="slowest tests in the table")
    ap.add_argument("--note", default="", help="a sentence on how the runs were made (load, machine)")
    args = ap.parse_args()
    if args.after is None:
        with tempfile.TemporaryDirectory() as d:
            args.after = Path(d) / "after.txt"
            r = subprocess.run([sys.executable, "-m", "pytest", "-q", "--durations=0", "-p", "no:cacheprovider"],
                               cwd=ROOT, capture_output=True, text=True, env={**os.environ, "MPLBACKEND": "Agg"})
            args.after.write_text(r.stdout + r.stderr)
            after_text = args.after.read_text()
    else:
        after_text = args.after.read_text()
    before_text = args.before.read_text() if args.before else ""
    a, b = durations(after_text), durations(before_text)
    fa, fb = per_file(a), per_file(b)
    files = sorted(set(fa) | set(fb), key=lambda f: -max(fa.get(f, 0.0), fb.get(f, 0.0)))[:args.files]
    head = ["file", *(["before s"] if b else []), "after s"]
    rows = [[f, *([round(fb.get(f, 0.0), 1)] if b else []), round(fa.get(f, 0.0), 1)] for f in files]
    body = md_table(head, rows)
    slow = sorted(a, key=lambda n: -a[n])[:args.tests]
    body += "\n\nSlowest tests (this run):\n\n" + md_table(
        ["test", *(["before s"] if b else []), "after s"],
        [[n, *([round(b[n], 1) if n in b else "new"] if b else []), round(a[n], 1)] for n in slow])
    body += (f"\n\nThis run: {wall(after_text)} (sum of test durations {sum(a.values()):.0f} s)"
             + (f"; before: {wall(before_text)} (sum {sum(b.values()):.0f} s)" if b else "") + ". "
             + args.note + "\n")
    write_result("make_test", "make test: per-file and slowest-test durations", body)


if __name__ == "__main__":
    main()
