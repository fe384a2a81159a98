"""Shared helpers for benchmarks: markdown tables, result files, timing.

Importing this module configures the process as the ``terrainwarp`` command does
(:func:`terrainwarp.runtime.configure_from_env`). Each benchmark prints its table and writes it to
benchmarks/results/<stage>.md together with the command that made it and the machine it ran on.
``python benchmarks/collect.py`` rebuilds the root BENCHMARKS.md from those files.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path

from terrainwarp.runtime import configure_from_env

# a benchmark measures what the terrainwarp command does: quiet Warp, freed frame memory kept mapped
# (TERRAINWARP_KEEP_MEMORY=0 and TERRAINWARP_VERBOSE=1 as for the command)
configure_from_env()

RESULTS = Path(__file__).resolve().parent / "results"


def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.3e}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"


def write_result(stage: str, title: str, body: str, out_dir: Path | None = None) -> Path:
    """Write ``<out_dir or benchmarks/results>/<stage>.md`` (atomically) and print it."""
    out_dir = RESULTS if out_dir is None else Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cmd = "python " + " ".join([os.path.relpath(sys.argv[0], Path(__file__).resolve().parents[1]), *sys.argv[1:]])
    text = (f"## {title}\n\nCommand: `{cmd}` (from the repository root, in `.venv`)  \n"
            f"Run: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {machine()}\n\n{body.strip()}\n")
    p = out_dir / f"{stage}.md"
    tmp = p.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(p)
    print(text)
    return p


def best_of(fn: Callable[[], object], repeat: int = 3) -> tuple[float, object]:
    """Minimum wall time in seconds over ``repeat`` calls (after the caller's warm-up) and the last result."""
    best = float("inf")
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out
