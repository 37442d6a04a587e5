"""Benchmark: two commands with the program cache filled, with and without what shortens
their start: stored programs loaded ahead (the diagnosis), and dask kept out (the
posterior).

    python -m benchmarks.bench_filled_start [--out reports/bench_filled_start.md]

Both are per process, so each side runs in a fresh one, ``ewb-ident`` through its entry
point (``cli.main``), the two sides alternately, :data:`ROUNDS` times each, in one
program cache filled by a run before them; the table gives the median wall time of a
process and the range.

- ``ewb-ident diagnose`` of ``bench_speed.py``'s stiction trace at 1 kHz (the slowest
  filled diagnosis row of issue 12): as the package runs it, the programs the last
  diagnosis of a trace of this shape used loaded in a background thread
  (:func:`ewb_ident.runtime.store.prefetching`), against the same with that scope
  made a no-op.
- ``ewb-ident sample --min-ess 1000`` of ``datasets/steps_200hz.csv``: as the package runs
  it, dask never imported (``cli.main``), against the same with ``import dask`` before
  the command (the CLI then leaves it in, and xarray and ArviZ use it).

The last column says whether the two sides wrote the same results (``diagnosis.json``,
and ``summary.json``, the timings aside).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import bench_fit, bench_speed

ROOT = Path(__file__).resolve().parents[1]
ROUNDS = 5

_CHILD = """
import contextlib, sys
side = sys.argv[1]
if side == "no-ahead":
    import ewb_ident.diagnosis.diagnose as d
    d.prefetching = lambda label: contextlib.nullcontext()
elif side == "dask":
    import dask  # noqa: F401  (imported before the command: the CLI leaves it in)
from ewb_ident.cli import main
sys.argv = ["ewb-ident", *sys.argv[2:]]
main()
"""


def _run(side: str, args: list[str], out: Path, cache: str) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, side, *args, "--out", str(out)],
        capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, EWB_IDENT_CACHE=cache),
    )  # fmt: skip
    elapsed = time.perf_counter() - t0
    if proc.returncode not in (0, 3):
        raise SystemExit(f"{side} {' '.join(args)} failed: {proc.stderr[-500:]}")
    return elapsed


def _without_timings(doc):
    if isinstance(doc, dict):
        return {k: _without_timings(v) for k, v in doc.items() if not k.startswith("timing")}
    if isinstance(doc, list):
        return [_without_timings(v) for v in doc]
    return doc


def _compare(
    args: list[str], sides: tuple[str, str], result: str, folder: Path, without: str
) -> str:
    """Alternate fresh processes of both sides in one filled cache; a table row."""
    times: dict[str, list[float]] = {s: [] for s in sides}
    with tempfile.TemporaryDirectory() as cache:
        _run(sides[0], args, folder / "fill", cache)
        for k in range(ROUNDS):
            for s in sides:
                times[s].append(_run(s, args, folder / f"{s}_{k}", cache))
    docs = [
        _without_timings(json.loads((folder / f"{s}_{k}" / result).read_text()))
        for s in sides
        for k in range(ROUNDS)
    ]
    same = all(d == docs[0] for d in docs)
    ours, theirs = (statistics.median(times[s]) for s in sides)
    ranges = [f"{statistics.median(times[s]):.2f} s ({min(times[s]):.2f}-{max(times[s]):.2f})"
              for s in sides]  # fmt: skip
    return (
        f"| `ewb-ident {args[0]}` | {ranges[0]} | {ranges[1]} ({without}) | "
        f"{theirs / ours:.2f}x | {'yes' if same else '**no**'} |"
    )


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    report.row(f"{ROUNDS} fresh processes per side, alternately, one filled cache per row")
    report.row("")
    report.row("| command | the package | without it | ratio | same results |")
    report.row("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        stiction = bench_speed._simulated_stiction(folder, 1000)
        args = ["diagnose", str(stiction)]
        sides = ("ahead", "no-ahead")
        report.row(_compare(args, sides, "diagnosis.json", folder, "no programs loaded ahead"))
        sample = ["sample", str(bench_speed.TRACE_FIT), "--min-ess", "1000", "--no-progress"]
        sides = ("no-dask", "dask")
        report.row(_compare(sample, sides, "summary.json", folder, "dask imported first"))
    report.write()


if __name__ == "__main__":
    main()
