"""Benchmark: traces per minute of a batch refit, in this process and on a local Dask
cluster of 1 and of 2 worker processes, in one run.

    python -m benchmarks.bench_batch [N] [--report reports/bench_batch.md]   (N = 200)

N synthetic traces (position-controlled apply, 3 s at 200 Hz, each another rig unit with
5 % parameter spread) are fitted as whole chains (fit only: the traces are made first and
passed in memory; reading a 3 s trace adds ~10 ms). Three ways, one after the other:

* in process: ``fit`` in a loop, as ``ewb-ident batch`` runs without ``--scheduler``;
* a Dask ``LocalCluster`` of 1 worker process (1 thread), then of 2, each mapped over
  the traces as ``batch --scheduler`` maps its traces.

For each: the time to the first result (start-up and compilation of the fit's programs;
the compilation cache, ``EWB_IDENT_CACHE``, is warm after the first way), and the
throughput over the remaining N - 1 traces (warm: the per-trace cost that scales), as
traces per minute; the cluster's own start-up is timed apart. Then the ratios, and the
estimates of the three ways compared. The load average of the machine before and after
is printed: on a shared machine the figures are lower bounds of what it can do.

(A vectorised ``fit_batch``, one ``vmap``-ed solver per group of equal-length traces,
was measured here at 0.59x the loop's speed on the 2-core CPU, every trace waiting for the
slowest, and was removed: processes are the one batch path.)
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from ewb_ident import rig  # noqa: E402
from ewb_ident.inference.least_squares import fit  # noqa: E402


def fit_values(trace) -> tuple[dict[str, float], bool, float]:
    """A fit's estimates, convergence and the time it finished (what a worker sends
    back: a FitResult holds solver state that does not pickle)."""
    jax.config.update("jax_enable_x64", True)  # in a worker process too
    res = fit(trace)
    return {k: float(v) for k, v in res.values.items()}, bool(res.converged), time.time()


def _rates(t0: float, done: list[float], n: int) -> dict[str, float]:
    """First result after ``t0`` (s), and warm traces per minute over the others."""
    done = sorted(done)
    first = done[0] - t0
    warm = done[-1] - done[0]
    return {"first_s": first, "total_s": done[-1] - t0,
            "warm_per_min": 60.0 * (n - 1) / warm if warm > 0 else float("nan"),
            "overall_per_min": 60.0 * n / (done[-1] - t0)}


def in_process(traces) -> tuple[dict[str, float], list]:
    t0 = time.time()
    out = [fit_values(t) for t in traces]
    return _rates(t0, [o[2] for o in out], len(traces)), out


def on_cluster(traces, workers: int) -> tuple[dict[str, float], list]:
    from distributed import Client, LocalCluster

    t_start = time.time()
    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                     dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.wait_for_workers(workers)
        up = time.time() - t_start
        t0 = time.time()
        out = client.gather(client.map(fit_values, traces, pure=False))
    rates = _rates(t0, [o[2] for o in out], len(traces))
    # a worker's first trace compiles: the warm rate over each worker's later traces is
    # the span from the earliest first result to the last result
    return rates | {"cluster_start_s": up}, out


def main(n: int, report: Path | None) -> None:
    load0 = os.getloadavg()
    lines = [f"machine: {os.cpu_count()} cores, {platform.machine()}, jax {jax.__version__}; "
             f"load average before: {load0[0]:.1f} (1 min), {load0[1]:.1f} (5 min)"]
    print(lines[-1], flush=True)
    t0 = time.perf_counter()
    traces = [
        rig.simulate_rig(
            rig.vary(rig.RigParams(), np.random.default_rng([7, k]), 0.05),
            profile="position",
            seed=k,
            name=f"unit{k}",
        )[0]
        for k in range(n)
    ]
    lines.append(f"generated {n} traces (3 s, 200 Hz) in {time.perf_counter() - t0:.1f} s")
    print(lines[-1], flush=True)
    results = {}
    ways = (("in process", lambda: in_process(traces)),
            ("Dask, 1 worker", lambda: on_cluster(traces, 1)),
            ("Dask, 2 workers", lambda: on_cluster(traces, 2)))
    for name, run in ways:
        rates, out = run()
        results[name] = (rates, out)
        extra = (f"; cluster start {rates['cluster_start_s']:.1f} s"
                 if "cluster_start_s" in rates else "")
        lines.append(f"{name:<16} first result {rates['first_s']:5.1f} s, all {n} in "
                     f"{rates['total_s']:6.1f} s: {rates['warm_per_min']:6.0f} traces/min warm, "
                     f"{rates['overall_per_min']:6.0f} overall{extra}")
        print(lines[-1], flush=True)
    base = results["in process"][1]
    worst = max(abs(o[0][p] / b[0][p] - 1) for _, out in results.values()
                for o, b in zip(out, base, strict=True) for p in ("a", "b", "c", "mu"))
    conv = ", ".join(f"{sum(o[1] for o in out)}/{n}" for _, out in results.values())
    r1 = results["Dask, 1 worker"][0]
    r2 = results["Dask, 2 workers"][0]
    rp = results["in process"][0]
    load1 = os.getloadavg()
    lines += [
        f"2 workers / 1 worker: {r2['warm_per_min'] / r1['warm_per_min']:.2f}x warm, "
        f"{r2['overall_per_min'] / r1['overall_per_min']:.2f}x overall; "
        f"1 worker / in process: {r1['warm_per_min'] / rp['warm_per_min']:.2f}x warm",
        f"converged {conv} (in process, 1 worker, 2 workers); largest relative difference "
        f"of a, b, c, mu from the in-process fits: {worst:.1e}",
        f"load average after: {load1[0]:.1f} (1 min), {load1[1]:.1f} (5 min)",
    ]
    print("\n".join(lines[-3:]))
    if report is not None:
        busy = max(load0[0], load1[0]) > 1.5
        text = [
            f"# benchmarks/bench_batch.py {n}",
            "",
            f"Run {time.strftime('%Y-%m-%d')} on the project machine (2 cores, no GPU).",
            "",
            "```",
            *lines,
            "```",
            "",
            "*warm*: traces per minute after each process's first result (its compilation); "
            "*overall*: all N over the whole time, compilation included (the cluster's "
            "start-up excluded, given apart).",
            "",
            ("The machine was busy with other work during this run (load average above the "
             "2 cores before or after): every figure is lower than on an idle machine, the "
             "2-worker figure most, as its second worker competes with the other work for "
             "the same cores." if busy else "The machine was otherwise idle."),
        ]
        report.write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("n", nargs="?", type=int, default=200)
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    main(args.n, args.report)
