"""Benchmark: XLA's fast-compile preset against the default, program by program.

    python -m benchmarks.bench_compiler_options [--out reports/bench_compiler_options.md]

First, a whole diagnosis of ``datasets/concealed/stiction.csv`` in one thread, its
mechanism programs compiled with the default options and with the preset, alternately,
twice each: the first call (compiling every program) and the second (warm), and whether
the two diagnoses are the same. Then it captures every program a diagnosis of that
trace (motor mechanisms: a long loop of small kernels) and a fit and posterior of
``datasets/steps_200hz.csv`` (the seed model) compile, with their first arguments, then
compiles each again in this process with the options every program has
(``programs.COMPILER_OPTIONS``) and with XLA's fast-compile preset added
(``programs.FAST_COMPILE``), alternately, twice each: the compile time (the faster of
two) and the median time of one run, and whether the two give the same numbers (largest
difference relative to the largest output). The package gives the preset to the
programs it makes faster (``@program(options=FAST_COMPILE)``). Last, each program with
its options as the package gives them against the same with XLA's own split of the
machine code into parts compiled side by side (``split_table``).
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from benchmarks import bench_fit  # noqa: E402
from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.diagnosis.diagnose import diagnose  # noqa: E402
from ewb_ident.inference.least_squares import fit  # noqa: E402
from ewb_ident.inference.posterior import sample  # noqa: E402
from ewb_ident.runtime import programs, store  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

REPEATS = 15
TRACE = ROOT / "datasets" / "concealed" / "stiction.csv"


def _words(x):
    """``x`` with every number left out: its texts and structure."""
    if isinstance(x, dict):
        return {k: _words(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_words(v) for v in x]
    return None if isinstance(x, (int, float)) and not isinstance(x, bool) else x


def _largest_difference(x, y) -> float:
    """The largest relative difference of corresponding numbers of ``x`` and ``y``."""
    if isinstance(x, dict):
        return max([_largest_difference(x[k], y[k]) for k in x if k in y] or [0.0])
    if isinstance(x, list):
        return max([_largest_difference(a, b) for a, b in zip(x, y, strict=False)] or [0.0])
    if isinstance(x, float) and isinstance(y, float) and x != y:
        return abs(x - y) / max(abs(x), abs(y))
    return 0.0


def whole_diagnosis() -> list[str]:
    """Rows: one-thread diagnosis times (s), first call and warm, without and with the
    preset on the mechanism programs."""
    real = programs._compile
    trace = read_trace(TRACE)
    times: dict[str, list[tuple[float, float]]] = {"default": [], "fast": []}
    docs: list[dict] = []
    store.set_cache_folder(None)
    os.environ["EWB_IDENT_THREADS"] = "1"
    try:
        for _ in range(2):
            for variant in times:
                programs._compile = real if variant == "fast" else (lambda lo, extra=None: real(lo))
                programs.clear_memory()
                jax.clear_caches()
                t0 = time.perf_counter()
                diagnose(trace)
                t1 = time.perf_counter()
                res = diagnose(trace)
                times[variant].append((t1 - t0, time.perf_counter() - t1))
                doc = res.to_json()
                doc.pop("timings_s", None)
                docs.append(doc)
    finally:
        programs._compile = real
        os.environ.pop("EWB_IDENT_THREADS")
    rows = []
    for k, label in ((0, "first call (compiles)"), (1, "warm")):
        d = [t[k] for t in times["default"]]
        f = [t[k] for t in times["fast"]]
        rows.append(
            f"| diagnosis of {TRACE.name}, one thread, {label} | "
            f"{' / '.join(f'{x:.1f}' for x in d)} s | {' / '.join(f'{x:.1f}' for x in f)} s | "
            f"{min(d) / min(f):.2f}x |"
        )
    texts = {json.dumps(_words(d), sort_keys=True) for d in docs}
    params = max(_largest_difference(docs[0]["findings"], d["findings"]) for d in docs[1:])
    bic = max(
        abs(a["delta_bic"] - b["delta_bic"])
        for d in docs[1:]
        for a, b in zip(docs[0]["candidates"], d["candidates"], strict=True)
    )
    words = "the same" if len(texts) == 1 else "DIFFER"
    rows.append(
        f"| the four diagnoses (timings aside) | texts {words}"
        f" | findings' numbers within {params:.0e} relative | candidates' dBIC within {bic:.0e} |"
    )
    return rows


def capture() -> list[tuple[str, object, list]]:
    """(program name, lowered program, its first arguments) of every program compiled."""
    seen: list[tuple[str, object, list]] = []
    real = programs._compile

    def spy(lowered, extra=None):
        name = sys._getframe(1).f_locals.get("name", "?")
        exe = real(lowered, extra)

        def first(leaves):
            if not any(lo is lowered for _, lo, _ in seen):
                seen.append((name.rsplit(".", 1)[-1], lowered, leaves))
            return exe(leaves)

        return first

    store.set_cache_folder(None)  # a wrapped program cannot be stored
    programs.clear_memory()
    jax.clear_caches()
    programs._compile = spy
    try:
        diagnose(read_trace(TRACE))
        steps = read_trace(ROOT / "datasets" / "steps_200hz.csv")
        fit(steps)
        sample(steps, min_ess=1000.0)
    finally:
        programs._compile = real
    return seen


def _times(exes: dict, leaves) -> dict[str, float]:
    """Median run time (s) of each executable, their runs interleaved."""
    times: dict[str, list[float]] = {k: [] for k in exes}
    for _ in range(REPEATS):
        for k, exe in exes.items():
            t0 = time.perf_counter()
            jax.block_until_ready(exe(leaves))
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def compare(lowered, leaves, sets: dict[str, dict] | None = None) -> dict:
    """Compile times (s), run times (s) and the largest relative difference of the
    outputs of two option sets (default: the options every program has against the
    fast-compile preset added)."""
    sets = sets or {"default": programs.COMPILER_OPTIONS,
                    "fast": programs.COMPILER_OPTIONS | programs.FAST_COMPILE}  # fmt: skip
    first, second = sets
    compile_s: dict[str, list[float]] = {k: [] for k in sets}
    exes = {}
    for _ in range(2):
        for k, opts in sets.items():
            jax.clear_caches()  # JAX keeps what it compiled, options and all
            t0 = time.perf_counter()
            exes[k] = lowered.compile(compiler_options=opts)
            compile_s[k].append(time.perf_counter() - t0)
    outs = {k: jax.tree_util.tree_leaves(jax.block_until_ready(e(leaves))) for k, e in exes.items()}
    run_s = _times(exes, leaves)
    diff = max(
        float(np.max(np.abs(np.asarray(a) - np.asarray(b)))) / max(float(np.max(np.abs(a))), 1e-300)
        for a, b in zip(outs[first], outs[second], strict=True)
        if np.asarray(a).size
    )
    return {"compile": {k: min(v) for k, v in compile_s.items()}, "run": run_s, "diff": diff}


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    row = report.row

    row("| whole diagnosis | default | preset on mechanism programs | ratio |")
    row("|---|---|---|---|")
    for r in whole_diagnosis():
        row(r)
    row("")
    row("| program | compile default | compile fast | ratio | run default | run fast | "
        "ratio | largest difference |")  # fmt: skip
    row("|---|---|---|---|---|---|---|---|")
    counts: dict[str, int] = {}
    captured = capture()
    for name, lowered, leaves in captured:
        counts[name] = counts.get(name, 0) + 1
        c = compare(lowered, leaves)
        cd, cf = c["compile"]["default"], c["compile"]["fast"]
        rd, rf = c["run"]["default"], c["run"]["fast"]
        row(f"| {name} #{counts[name]} | {cd:.2f} s | {cf:.2f} s | {cd / cf:.2f}x | "
            f"{rd * 1e3:.2f} ms | {rf * 1e3:.2f} ms | {rd / rf:.2f}x | "
            f"{c['diff']:.1e} |")  # fmt: skip
    split_table(row, captured)
    report.write()


def split_table(row, captured) -> None:
    """Each program compiled with its options as the package gives them and with XLA's
    own split of the machine code (``xla_cpu_parallel_codegen_split_count`` left out),
    alternately: compile and run times, and the largest difference of the outputs."""
    split = "xla_cpu_parallel_codegen_split_count"
    row("")
    row(
        f"| program | compile, XLA's split | compile, {split}="
        f"{programs.COMPILER_OPTIONS.get(split)} | ratio | run ratio | largest difference |"
    )
    row("|---|---|---|---|---|---|")
    counts: dict[str, int] = {}
    totals = [0.0, 0.0]
    for name, lowered, leaves in captured:
        counts[name] = counts.get(name, 0) + 1
        own = programs.COMPILER_OPTIONS | (
            programs.FAST_COMPILE if name == "_mechanism_program" else {}
        )
        xla = {k: v for k, v in own.items() if k != split}
        c = compare(lowered, leaves, {"xla": xla, "package": own})
        cx, cp = c["compile"]["xla"], c["compile"]["package"]
        totals[0] += cx
        totals[1] += cp
        row(f"| {name} #{counts[name]} | {cx:.2f} s | {cp:.2f} s | {cx / cp:.2f}x | "
            f"{c['run']['xla'] / c['run']['package']:.2f}x | {c['diff']:.1e} |")  # fmt: skip
    row(f"| all {len(captured)} | {totals[0]:.2f} s | {totals[1]:.2f} s | "
        f"{totals[0] / totals[1]:.2f}x | | |")  # fmt: skip


if __name__ == "__main__":
    main()
