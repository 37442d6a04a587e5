"""Benchmark: refit N traces by a Python loop of fits and on a Dask cluster.

    python -m benchmarks.bench_batch [N]        (default N = 100)

N synthetic traces (position-controlled apply, 200 Hz, 3 s, each another rig unit with
5 % parameter spread) are fitted as whole chains by a Python loop of ``fit`` in this
process, and by ``fit`` mapped over a Dask ``LocalCluster`` of one single-threaded worker
process per core (how ``ewb-ident study --scheduler`` scales out). Wall times include
compilation (and the cluster's start-up). Both must agree on every estimate.

(A vectorised ``fit_batch``, one ``vmap``-ed solver per group of equal-length traces,
was measured here at 0.59x the loop's speed on the 2-core CPU, every trace waiting for the
slowest, and was removed: processes are the one batch path.)
"""

from __future__ import annotations

import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from ewb_ident import rig  # noqa: E402
from ewb_ident.inference.least_squares import fit  # noqa: E402


def fit_values(trace) -> tuple[dict[str, float], bool]:
    """A fit's estimates and status (what a worker sends back: a FitResult holds solver
    state that does not pickle)."""
    jax.config.update("jax_enable_x64", True)  # in a worker process too
    res = fit(trace)
    return {k: float(v) for k, v in res.values.items()}, bool(res.converged)


def main(n: int) -> None:
    print(f"machine: {os.cpu_count()} cores, jax {jax.__version__}")
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
    print(f"generated {n} traces in {time.perf_counter() - t0:.1f} s")

    t0 = time.perf_counter()
    loop = [fit(t) for t in traces]
    t_loop = time.perf_counter() - t0
    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    with (
        LocalCluster(n_workers=os.cpu_count(), threads_per_worker=1, processes=True) as cluster,
        Client(cluster) as client,
    ):
        spread = client.gather(client.map(fit_values, traces, pure=False))
    t_dask = time.perf_counter() - t0

    print(f"Python loop of fit():  {t_loop:7.1f} s  ({t_loop / n:.2f} s per trace)")
    print(f"Dask, {os.cpu_count()} processes: {t_dask:7.1f} s  ({t_dask / n:.2f} s per trace)")
    worst = max(
        abs(d[0][p] / s.values[p] - 1)
        for d, s in zip(spread, loop, strict=True)
        for p in ("a", "b", "c", "mu")
    )
    print(
        f"speed-up of Dask over the loop: {t_loop / t_dask:.2f}x; converged "
        f"{sum(r.converged for r in loop)}/{n} (loop), {sum(ok for _, ok in spread)}/{n} "
        f"(Dask); largest relative difference of a, b, c, mu: {worst:.1e}"
    )


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100)
