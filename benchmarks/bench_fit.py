"""Benchmark: whole-chain least squares, ewb-ident against the SciPy peer, same process.

    python benchmarks/bench_fit.py [TRACE]        (default: datasets/steps_200hz.csv)

Warm: ``ewb_ident.inference.least_squares``
(everything: start values, two weighted solves, Jacobian,
standard errors, metrics) after one call that compiled it, against the peer
(``scipy_peer.py``: LSODA + least_squares with finite differences) fitting the same 14
parameters with the same weights from the seed values. Medians of repeated runs.
Cold: whole commands in fresh processes, imports and compilation included —
``ewb-ident fit`` with its on-disk cache of compiled programs empty, and again with it
filled by the previous run — against ``python scipy_peer.py TRACE``.
"""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import scipy_peer  # noqa: E402

from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.inference.least_squares import fit  # noqa: E402

ROOT = Path(__file__).parents[1]


def _machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, jax {jax.__version__}"
    )


def _median_time(f, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _run(cmd, env=None):
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, env=env, cwd=ROOT)
    return time.perf_counter() - t0


def _warm(trace):
    """The warm fit's result and median time, and the peer's fit and median time."""
    ours = fit(trace)  # compiles
    assert ours.converged, ours.message
    warm_ours = _median_time(lambda: fit(trace), 7)

    t, V = trace.time_s, trace["voltage_V"]
    chans = ours.trace_metrics[0].keys()
    measured = {c: trace[c] for c in chans}
    sigma = ours.sigma[0]  # the same weights ewb-ident ended with
    start = {"theta0_deg": float(trace["theta_deg"][0])}
    peer = {}

    def run_peer():
        peer["p"], peer["res"] = scipy_peer.fit(
            t, V, measured, sigma, scipy_peer.FREE, start, r_eff=trace.r_eff_m
        )

    warm_peer = _median_time(run_peer, 3)
    return ours, warm_ours, peer, warm_peer


def warm_times(path: str) -> tuple[float, float]:
    """Median warm whole-chain fit times (s) of ewb-ident and of the peer on ``path``."""
    _, warm_ours, _, warm_peer = _warm(read_trace(path))
    return warm_ours, warm_peer


def main(path: str) -> None:
    trace = read_trace(path)
    print(f"machine: {_machine()}")
    print(f"trace: {path} ({trace.n} samples, {trace.sample_rate_hz:g} Hz, {trace.duration_s:g} s)")
    ours, warm_ours, peer, warm_peer = _warm(trace)
    ours_cost = float(np.sum(np.asarray(ours.problem(ours.u, ours.data)) ** 2) / 2)
    peer_cost = float(np.sum(peer["res"].fun ** 2) / 2)
    print("\nwarm fit (median)            ewb-ident    SciPy peer    ratio")
    ratio = warm_peer / warm_ours
    print(f"  time, s                    {warm_ours:9.3f}    {warm_peer:10.2f}    {ratio:5.0f}x")
    print(f"  weighted cost at the end   {ours_cost:9.1f}    {peer_cost:10.1f}")
    print(f"  peer: {peer['res'].nfev} evaluations, status {peer['res'].status}")
    for name in ("a", "b", "c", "mu"):
        print(f"  {name:<3} ewb-ident {ours.values[name]:.6g}   peer {peer['p'][name]:.6g}")

    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        env = dict(os.environ, EWB_IDENT_CACHE=cache)
        cmd = [sys.executable, "-m", "ewb_ident", "fit", path, "--out", out]
        cold_empty = _run(cmd, env)
        cold_cached = _run(cmd, env)
    cold_peer = _run([sys.executable, str(Path(__file__).parent / "scipy_peer.py"), path])
    print("\ncold command (fresh process, imports included)     time, s   peer/ours")
    for label, value in (
        ("ewb-ident fit, empty program cache            ", cold_empty),
        ("ewb-ident fit, cache filled by the run above  ", cold_cached),
    ):
        print(f"  {label}   {value:7.2f}   {cold_peer / value:6.2f}x")
    print(f"  python scipy_peer.py                             {cold_peer:7.2f}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "datasets" / "steps_200hz.csv"))
