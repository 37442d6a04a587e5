"""Benchmark: the posterior's convergence checks. Its autocorrelation times,
ewb-ident's vectorised :func:`ewb_ident.inference.chains.autocorr_time` against emcee's
``emcee.autocorr.integrated_time`` (one FFT per walker and parameter), and its R-hats,
one parameter after another against side by side, in one process.

1. Both on chains of the shape the posterior's convergence checks see (the whole chain
   of ``steps_200hz.csv``: 56 walkers, 14 parameters; 100 to 400 steps), alternately,
   the median of :data:`REPEATS` calls each; the largest relative difference of the times.
   The R-hat of 14 parameters (two ensembles of 384 steps), each way alternately.
2. The whole posterior (``sample(trace, min_ess=1000)`` of ``datasets/steps_200hz.csv``,
   the bench's posterior row), warm, with either function in the convergence checks,
   alternately, :data:`RUNS` each: its sampling step's median seconds, and whether the
   two summaries agree.

Run from the repository root: ``python -m benchmarks.bench_autocorr``. Writes
``reports/bench_autocorr.md``.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import emcee
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from benchmarks import bench_fit  # noqa: E402
from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.inference import chains  # noqa: E402
from ewb_ident.inference.posterior import sample  # noqa: E402
from ewb_ident.runtime.threads import parallel_map, threads  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

#: Calls of each function per chain shape; posterior runs with each.
REPEATS, RUNS = 20, 4


def emcees(x: np.ndarray) -> np.ndarray:
    return emcee.autocorr.integrated_time(x, tol=0)


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    report.row(
        "| chain (steps, walkers, params) | emcee | ewb-ident | ratio "
        "| largest relative difference |"
    )
    report.row("|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for n_t in (100, 200, 400):
        x = rng.standard_normal((n_t, 56, 14)).cumsum(axis=0)
        times: dict[str, list[float]] = {"emcee": [], "ours": []}
        for _ in range(REPEATS):
            for name, fn in (("emcee", emcees), ("ours", chains.autocorr_time)):
                t0 = time.perf_counter()
                fn(x)
                times[name].append(time.perf_counter() - t0)
        a, b = emcees(x), chains.autocorr_time(x)
        te, to = statistics.median(times["emcee"]), statistics.median(times["ours"])
        report.row(
            f"| ({n_t}, 56, 14) | {1e3 * te:.1f} ms | {1e3 * to:.1f} ms | {te / to:.1f}x "
            f"| {np.max(np.abs(a - b) / np.abs(a)):.1e} |"
        )
    # R-hat of every parameter, as the final convergence check computes it.
    post = [rng.standard_normal((384, 56, 14)).cumsum(axis=0) for _ in range(2)]
    chains.import_arviz()

    def one(j: int) -> float:
        return chains.split_rhat([p[:, :, j] for p in post])

    ways = {"one after another": lambda: [one(j) for j in range(14)],
            "side by side": lambda: parallel_map(one, range(14))}  # fmt: skip
    rh: dict[str, list[float]] = {k: [] for k in ways}
    for _ in range(REPEATS // 2):
        for name, fn in ways.items():
            t0 = time.perf_counter()
            fn()
            rh[name].append(time.perf_counter() - t0)
    serial, side = (statistics.median(rh[k]) for k in ways)
    equal = ways["one after another"]() == ways["side by side"]()
    report.row("")
    report.row(
        f"R-hat of 14 parameters (2 ensembles, 384 steps, 56 walkers): one after another "
        f"{1e3 * serial:.0f} ms, side by side ({threads()} threads) {1e3 * side:.0f} ms "
        f"({serial / side:.2f}x); values {'equal' if equal else 'DIFFERENT'}."
    )
    trace = read_trace(ROOT / "datasets" / "steps_200hz.csv")
    sample(trace, min_ess=1000.0)  # compiles
    runs: dict[str, list[float]] = {"emcee": [], "ours": []}
    summaries: dict[str, str] = {}
    ours = chains.autocorr_time
    for _ in range(RUNS):
        for name, fn in (("emcee", emcees), ("ours", ours)):
            chains.autocorr_time = fn
            res = sample(trace, min_ess=1000.0)
            runs[name].append(res.timing["sampling_s"])
            summaries[name] = str(
                {n: (s["mean"], s["hdi_low"], s["hdi_high"]) for n, s in res.stats.items()}
            )
    chains.autocorr_time = ours
    se, so = statistics.median(runs["emcee"]), statistics.median(runs["ours"])
    same = "equal" if summaries["emcee"] == summaries["ours"] else "DIFFERENT"
    report.row("")
    report.row(
        f"Whole posterior of datasets/steps_200hz.csv (warm, {RUNS} runs each, alternately): "
        f"sampling step {se:.2f} s with emcee's function, {so:.2f} s with ewb-ident's "
        f"({se / so:.2f}x); the parameters' means and HDIs {same}."
    )
    report.write()


if __name__ == "__main__":
    main()
