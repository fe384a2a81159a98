"""The fuzz suite's full run (issue 31): mutated heightmap files, scene files and command lines through the
loaders and ``terrainwarp.cli.main``, in a worker subprocess that a crash or a hang (over 20 s) cannot take
down with the run; every finding kept with its input.

Targets (tests/fuzz_corpus.py): PNG (1- to 16-bit, every colour type), TIFF (8/16-bit, float32; strips,
tiles; none/deflate/LZW), GeoTIFF (rasterio: tiled deflate, striped, int16/uint16/float32, projected and
geographic CRSs, nodata, scale/offset, a vertical unit; loaded whole, with windows/bounds/decimation, and
streamed: ``Heightmap.open`` whole or by windows, compared with the in-memory load), ``.npy`` (header fields
and bodies), scene TOML (``Scene.load``, its camera and camera path) and command lines (every command).
The run is deterministic for a seed; the table counts each verdict (tests/fuzz_runner.py says what each one
means). Exit status 1 when there is a finding.

    python benchmarks/bench_fuzz.py [--cases 10000] [--seed 0] [--findings out/fuzz] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

from _common import write_result

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the suite lives beside the tests that run its bounded subset

from fuzz_runner import FINDINGS, GUARD_MB, HANG_S, MEMORY_MB, counts_table, fuzz, plan_for  # noqa: E402

QUICK_CASES = 600


def _top(counter: Counter, n: int = 8) -> str:
    return "; ".join(f"{k} ({v})" for k, v in counter.most_common(n))


def _details(counts, args, plan: dict[str, int]) -> str:
    lines = [f"Seed {args.seed}; {sum(plan.values())} cases in {counts.wall_s:.0f} s wall "
             f"({counts.wall_s / 60:.1f} min) on one worker process; hang limit {HANG_S:.0f} s per case, address "
             f"space {args.memory_mb} MiB, size guard told {GUARD_MB} MiB; worker restarts: {counts.restarts}. "
             f"Findings kept under `{args.findings}` (input files and finding.json).", "",
             counts_table(counts), "",
             "Verdicts: *ok* loaded (and passed the loader's own rules; a streamed GeoTIFF also equals its in-memory "
             "load) or the command succeeded; *ValueError / TypeError / OSError* a refusal of that kind whose message "
             "names the input (the file, the argument or the key); *refused* a command that exited 2 with its one "
             "`terrainwarp: error:` line naming an argument, nothing left in `--out`. Every other column is a "
             "finding: *crash* (the worker died: signal or exit), *hang* (over the limit), *exception* (any other "
             "type escaped), *unnamed* (an allowed type naming no input), *bad-result*, *traceback* (the CLI let an "
             "exception out or printed one), *cli-output* (no one error line, an odd exit code, files left in "
             "`--out`, or native stderr beside the error line).", ""]
    for t, c in counts.classes.items():
        lines.append(f"- {t}: exception classes {_top(c)}")
    for t, c in counts.warnings.items():
        lines.append(f"- {t}: Python warnings {_top(c, 4)}")
    for t, c in counts.native.items():
        lines.append(f"- {t}: printed on file descriptor 2 by native code in {sum(c.values())} case(s): {_top(c, 3)}; "
                     "cases " + "; ".join(f"{k[:40]}: {counts.native_cases[(t, k)][:5]}" for k, _ in c.most_common(3)))
    if counts.findings:
        groups = Counter((f["target"], f["verdict"], f.get("type"), (f.get("message") or "")[:100])
                         for f in counts.findings)
        lines += ["", "Findings (target, verdict, type, message: cases):", ""]
        lines += [f"- {t}, {v}, {ty}: {m!r}: {n}" for (t, v, ty, m), n in groups.most_common(30)]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10000, help="generated cases, split over the targets")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--findings", default="out/fuzz", help="folder for the findings and the worker's log")
    ap.add_argument("--memory-mb", type=int, default=MEMORY_MB, help="the worker's address-space limit")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_CASES} cases; prints, leaves the results file alone")
    args = ap.parse_args()
    n = QUICK_CASES if args.quick else args.cases
    plan = plan_for(n)
    out = Path(args.findings)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    counts = fuzz(plan, seed=args.seed, findings=out / f"seed{args.seed}", progress=True, log=out / "worker.log",
                  memory_mb=args.memory_mb)
    body = _details(counts, args, plan)
    title = f"Fuzz suite: {n} mutated inputs through the loaders and the CLI"
    if args.quick:
        print(body)
    else:
        write_result("fuzz", title, body)
    bad = sum(counts.verdicts[t][k] for t in counts.verdicts for k in FINDINGS)
    print(f"{n} cases in {time.perf_counter() - t0:.0f} s: {bad} finding(s)", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
