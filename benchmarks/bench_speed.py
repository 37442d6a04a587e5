"""Benchmark: every row of issue 12's speed table, measured in one run on this machine.

    python -m benchmarks.bench_speed [--out reports/bench_speed.md]

Rows (each with its target):

1. warm whole-chain fit against the SciPy peer in the same process, on issue 12's
   traces (clean, 4 s at 200 Hz, every channel, from the independent rig
   ``validation_rigs/other_rig.py``: an open-loop apply and a position-controlled one; see
   ``bench_fit.py``, which also says how the peer is set up);
2. a cold ``ewb-ident fit`` of each (fresh process, empty program cache) against the
   peer's cold command; 3. the same with the cache filled by row 2;
4. ``ewb-ident diagnose`` of 3 s traces: the shipped concealed backlash (200 Hz, a gap
   stage mechanism) and stiction (500 Hz, a motor mechanism: the motor candidates are
   the slowest fits of a diagnosis), ``datasets/position_1khz.csv`` (1 kHz, clean), and
   stiction at issue 12's two rates, 200 Hz and 1 kHz (``ewb-ident simulate --effect
   stiction --vary 0.1 --seed 7``: a unit other than the nominal one), cold and with the
   cache filled; the 500 Hz trace's cold target is the 200 Hz one, the stricter;
5. the whole-chain posterior to ESS >= 1000 for a, b, c, mu (``ewb-ident sample
   --min-ess 1000``) of ``datasets/steps_200hz.csv``, cold (fresh process, empty cache)
   and with the cache filled, and in one Python process: the first call (compiling)
   and the second (warm);
6. the default test suite is timed by CI (``bash .ci/run``), not here.

Every command runs in a fresh process with ``EWB_IDENT_CACHE`` pointing at a temporary
folder, so "cold" means an empty cache and "filled" means filled by the previous run.
The command rows of 4 and 5 run :data:`REPEATS` times (each time a cold run in a new
empty cache, then a filled one): the median, judged against the target, and the range
in brackets (on the 2-core machine two runs of one command differ by up to 10-15 %).
Run it with nothing else on the machine: the figures are wall times.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import bench_fit

ROOT = Path(__file__).resolve().parents[1]

TRACE_FIT = ROOT / "datasets" / "steps_200hz.csv"  # the posterior's
TRACE_200 = ROOT / "datasets" / "concealed" / "backlash.csv"
TRACE_200_MOTOR = ROOT / "datasets" / "concealed" / "stiction.csv"
TRACE_1K = ROOT / "datasets" / "position_1khz.csv"


def _command(args: list[str], cache: str) -> float:
    """Wall time of one ``ewb-ident`` command in a fresh process, s."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "ewb_ident", *args, "--out", out]
        t0 = time.perf_counter()
        proc = subprocess.run(
            cmd, capture_output=True, text=True, cwd=ROOT,
            env=dict(os.environ, EWB_IDENT_CACHE=cache),
        )  # fmt: skip
        elapsed = time.perf_counter() - t0
    if proc.returncode not in (0, 3):  # 3: converged to a poor fit is still a timing
        raise SystemExit(f"{' '.join(args)} failed ({proc.returncode}): {proc.stderr[-500:]}")
    return elapsed


def _simulated_stiction(folder: Path, rate: int) -> Path:
    """A 3 s stiction trace at ``rate`` Hz from the package's rig, another unit
    (``--vary 0.1``), written to ``folder``."""
    path = folder / f"stiction_{rate}hz.csv"
    cmd = [sys.executable, "-m", "ewb_ident", "simulate", str(path), "--rate", str(rate),
           "--effect", "stiction", "--vary", "0.1", "--seed", "7"]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT)
    return path


#: Times each command row's pair (cold, then filled) runs, each pair in an empty cache.
REPEATS = 3


class _Times:
    """Wall times of one row over :data:`REPEATS` runs: the median (judged against the
    target) and the range."""

    def __init__(self, times: list[float]):
        self.times = sorted(times)
        self.median = self.times[len(self.times) // 2]

    def __str__(self) -> str:
        lo, hi = self.times[0], self.times[-1]
        return (
            f"{self.median:.1f} s ({lo:.1f}-{hi:.1f})"
            if len(self.times) > 1
            else (f"{self.median:.1f} s")
        )

    def met(self, limit: float) -> str:
        return "yes" if self.median <= limit else "no"


def _cold_and_filled(args: list[str]) -> tuple[_Times, _Times]:
    """``ewb-ident ARGS`` cold (empty cache) then filled, :data:`REPEATS` times."""
    runs = []
    for _ in range(REPEATS):
        with tempfile.TemporaryDirectory() as cache:
            runs.append((_command(args, cache), _command(args, cache)))
    return _Times([c for c, _ in runs]), _Times([f for _, f in runs])


_POSTERIOR_TWICE = """
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from ewb_ident.data.readers import read_trace
from ewb_ident.inference.posterior import sample
trace = read_trace(sys.argv[1])
times = []
for _ in range(2):
    t0 = time.perf_counter()
    res = sample(trace, min_ess=1000.0)
    times.append(time.perf_counter() - t0)
    assert res.converged and min(res.stats[n]["ess"] for n in ("a", "b", "c", "mu")) >= 1000
print(json.dumps(times))
"""


def _in_process_posterior() -> tuple[float, float]:
    """``sample(..., min_ess=1000)`` twice in one fresh process (empty program cache):
    the first call compiles, the second is the warm figure (issue 12's "warm")."""
    with tempfile.TemporaryDirectory() as cache:
        proc = subprocess.run(
            [sys.executable, "-c", _POSTERIOR_TWICE, str(TRACE_FIT)],
            capture_output=True, text=True, cwd=ROOT,
            env=dict(os.environ, EWB_IDENT_CACHE=cache),
        )  # fmt: skip
    if proc.returncode:
        raise SystemExit(f"posterior twice failed: {proc.stderr[-500:]}")
    first, second = json.loads(proc.stdout.strip().splitlines()[-1])
    return first, second


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    row = report.row

    row("| row | ewb-ident | peer | ratio or time | target | met |")
    row("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for path in bench_fit.issue_traces(Path(folder)):
            w = bench_fit.warm(path)
            r = w["peer"] / w["ours"]
            row(f"| warm whole-chain fit, {path.name} | {w['ours']:.3f} s | {w['peer']:.1f} s | "
                f"{r:.0f}x | >= 300x | {'yes' if r >= 300 else 'no'} |")  # fmt: skip
            c = bench_fit.cold(path, w["problem"])
            for label, key, target in (("empty cache", "empty", 10), ("filled", "filled", 25)):
                r = c["peer"] / c[key]
                row(f"| cold `ewb-ident fit` {path.name}, {label} | {c[key]:.2f} s | "
                    f"{c['peer']:.1f} s | {r:.1f}x | >= {target}x | "
                    f"{'yes' if r >= target else 'no'} |")  # fmt: skip
    folder = tempfile.TemporaryDirectory()
    stiction = [_simulated_stiction(Path(folder.name), rate) for rate in (200, 1000)]
    diagnoses = [(TRACE_200, 15.0), (TRACE_200_MOTOR, 15.0), (TRACE_1K, 30.0),
                 (stiction[0], 15.0), (stiction[1], 30.0)]  # fmt: skip
    for trace, limit in diagnoses:
        cold, filled = _cold_and_filled(["diagnose", str(trace)])
        row(f"| `ewb-ident diagnose` {trace.name}, cold | {cold} | | | <= {limit:g} s | "
            f"{cold.met(limit)} |")  # fmt: skip
        row(f"| `ewb-ident diagnose` {trace.name}, cache filled | {filled} | | | "
            f"<= 5 s | {filled.met(5)} |")  # fmt: skip
    folder.cleanup()
    cold, filled = _cold_and_filled(["sample", str(TRACE_FIT), "--min-ess", "1000",
                                     "--no-progress"])  # fmt: skip
    row(f"| posterior to ESS >= 1000, cold | {cold} | | | <= 15 s | {cold.met(15)} |")
    row(f"| posterior to ESS >= 1000, cache filled | {filled} | | | <= 5 s | "
        f"{filled.met(5)} |")  # fmt: skip
    cold, warm = _in_process_posterior()
    row(f"| posterior to ESS >= 1000 in one Python process, first call | {cold:.1f} s | | | "
        f"<= 15 s | {'yes' if cold <= 15 else 'no'} |")  # fmt: skip
    row(f"| the same, second call (warm) | {warm:.1f} s | | | <= 5 s | "
        f"{'yes' if warm <= 5 else 'no'} |")  # fmt: skip
    report.write()


if __name__ == "__main__":
    main()
