"""Benchmark: where an evaluation of a fit with mechanisms spends its time.

    python -m benchmarks.bench_mechanism_cost [--out reports/bench_mechanism_cost.md]

A diagnosis of ``datasets/concealed/stiction.csv`` (a motor mechanism: the slowest
kind) fits 13 mechanism sets; the solver evaluates each set's program, the weighted
residuals and their Jacobian (forward mode, ``jax.jacfwd``), tens to hundreds of times.
This captures every such program's arguments in that diagnosis and compiles, in this
process and with the package's options, the residuals alone and the residuals with the
Jacobian, then runs the two alternately (median of 9 runs each): the ratio says how much
of an evaluation the Jacobian's tangents cost, and the kernel counts (XLA fusions) why.
With motor mechanisms the motor is integrated in sub-steps (``n_sub`` per sample), each
a few dozen kernels of a few numbers. With XLA's default small-loop threshold each kernel
was dispatched on its own on every sub-step, so a program's run time followed its kernel
count times the number of sub-steps; with the package's threshold
(:data:`ewb_ident.SMALL_LOOP_BYTES`) the loop runs natively and the count says how much
code a sub-step is (``bench_native_loops.py`` compares the two).
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("EWB_IDENT_THREADS", "1")  # one thread: the times are one core's

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from benchmarks import bench_fit  # noqa: E402
from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.diagnosis.diagnose import diagnose  # noqa: E402
from ewb_ident.inference import augmented  # noqa: E402
from ewb_ident.runtime import programs, store  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

TRACE = ROOT / "datasets" / "concealed" / "stiction.csv"
REPEATS = 9


def capture() -> list[tuple]:
    """(problem, u, data) of the first call of each mechanism program of the diagnosis."""
    real = augmented._mechanism_program
    seen: dict = {}

    def spy(problem, u, data):
        seen.setdefault(problem, (problem, np.asarray(u), jax.tree_util.tree_map(np.asarray, data)))
        return real(problem, u, data)

    store.set_cache_folder(None)
    augmented._mechanism_program = spy
    try:
        diagnose(read_trace(TRACE))
    finally:
        augmented._mechanism_program = real
    return list(seen.values())


def _compiled(f, u, data):
    """``f`` compiled as the package compiles a mechanism program, its kernel count and
    the seconds the tracing, lowering and compilation took."""
    t0 = time.perf_counter()
    exe = programs._compile(jax.jit(f).lower(u, data), programs.FAST_COMPILE)
    return exe, exe.as_text().count(" fusion("), time.perf_counter() - t0


def compare(problem, u, data) -> dict:
    def residuals(v, d):  # the weighted residuals alone
        pred = problem.predict_trace(v, d)
        chans = problem.channels[0]
        return jnp.concatenate([(pred[ch] - d["meas"][ch]) * d["w"][ch] for ch in chans])

    def with_jacobian(v, d):  # the package's program: residuals, Jacobian, predictions
        return augmented._mechanism_program.__wrapped__(problem, v, d)

    exes = {
        "residuals": _compiled(residuals, u, data),
        "jacobian": _compiled(with_jacobian, u, data),
    }
    times: dict[str, list[float]] = {k: [] for k in exes}
    for _ in range(REPEATS):
        for k, (exe, _, _) in exes.items():
            t0 = time.perf_counter()
            jax.block_until_ready(exe(u, data))
            times[k].append(time.perf_counter() - t0)
    n = int(np.asarray(data["meas"][problem.channels[0][0]]).shape[0])
    return {
        "run": {k: statistics.median(v) for k, v in times.items()},
        "kernels": {k: kern for k, (_, kern, _) in exes.items()},
        "compile": {k: secs for k, (_, _, secs) in exes.items()},
        "substeps": n * problem.n_sub[0],
        "tangents": int(np.asarray(u).size),
    }


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    row = report.row
    row(f"trace: {TRACE.relative_to(ROOT)}; one thread")
    row("")
    row("| mechanisms | stages | parameters | sub-steps | residuals | with Jacobian | ratio "
        "| kernels (residuals / with Jacobian) | per sub-step |")  # fmt: skip
    row("|---|---|---|---|---|---|---|---|---|")
    for problem, u, data in capture():
        c = compare(problem, u, data)
        rr, rj = c["run"]["residuals"], c["run"]["jacobian"]
        names = " + ".join(m.variant for m in problem.templates())
        row(f"| {names} | {', '.join(problem.stages)} | {c['tangents']} | {c['substeps']} | "
            f"{rr * 1e3:.2f} ms | {rj * 1e3:.2f} ms | {rj / rr:.1f}x | "
            f"{c['kernels']['residuals']} / {c['kernels']['jacobian']} | "
            f"{rj / c['substeps'] * 1e6:.2f} us |")  # fmt: skip
    report.write()


if __name__ == "__main__":
    main()
