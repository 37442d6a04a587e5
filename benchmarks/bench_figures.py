"""Benchmark: drawing a diagnosis's figures as the package does against two
alternatives, in one process.

    python -m benchmarks.bench_figures [--out reports/bench_figures.md]

For each of two traces, ``datasets/concealed/stiction.csv`` (500 Hz) and
``bench_speed.py``'s stiction trace at 1 kHz (another unit, simulated), diagnoses it
once, then draws its figures (the PNG bytes ``ewb-ident diagnose`` writes) three ways,
in turn, six times each:

- as the package draws them: fixed margins
  (:func:`ewb_ident.reporting.style.fixed_margins`) and each phase's shading one
  collection of rectangles (:func:`ewb_ident.reporting.style.shade_phases`);
- the same figures switched to ``layout="constrained"``, which measures every label
  before drawing;
- the phases shaded as before, one ``axvspan`` patch per run of a phase (a chattering
  stiction trace has dozens); the PNG bytes must equal the package's.

The first round of each is dropped (font caches); medians of the rest.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from benchmarks import bench_fit, bench_speed  # noqa: E402
from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.diagnosis.diagnose import diagnose  # noqa: E402
from ewb_ident.reporting import figures  # noqa: E402
from ewb_ident.reporting.figures import figures_of  # noqa: E402
from ewb_ident.reporting.style import png_bytes, shade_phases  # noqa: E402
from tests.test_report import one_span_per_run  # noqa: E402  (the shading as it was)

ROOT = Path(__file__).resolve().parents[1]

TRACE = ROOT / "datasets" / "concealed" / "stiction.csv"
ROUNDS = 6


def draw(result, way: str) -> tuple[float, list[bytes]]:
    figures.shade_phases = one_span_per_run if way == "spans" else shade_phases
    try:
        t0 = time.perf_counter()
        pngs = []
        for _, fig in figures_of(result):
            if way == "constrained":
                fig.set_layout_engine("constrained")
            pngs.append(png_bytes(fig, dpi=90, tight=False))  # as write_diagnosis draws
        return time.perf_counter() - t0, pngs
    finally:
        figures.shade_phases = shade_phases


WAYS = {
    "package": "fixed margins, a collection per phase (the package's)",
    "constrained": "constrained layout",
    "spans": "fixed margins, one axvspan per run of a phase",
}


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    folder = tempfile.TemporaryDirectory()
    for trace in (TRACE, bench_speed._simulated_stiction(Path(folder.name), 1000)):
        result = diagnose(read_trace(trace))
        times: dict[str, list[float]] = {way: [] for way in WAYS}
        pngs: dict[str, list[bytes]] = {}
        for _ in range(ROUNDS):
            for way in WAYS:
                elapsed, pngs[way] = draw(result, way)
                times[way].append(elapsed)
        if pngs["spans"] != pngs["package"]:
            raise SystemExit(f"{trace.name}: one span per run drew other PNG bytes")
        runs = int(np.sum(result.labels[1:] != result.labels[:-1])) + 1
        ours = statistics.median(times["package"][1:])
        name = trace.relative_to(ROOT) if trace.is_relative_to(ROOT) else trace.name
        report.row(
            f"trace: {name}; {len(figures_of(result))} figures; {runs} runs of a phase; "
            "one span per run draws the same PNG bytes"
        )
        report.row("")
        report.row("| way | all figures drawn |")
        report.row("|---|---|")
        for way, text in WAYS.items():
            t = statistics.median(times[way][1:])
            ratio = "" if way == "package" else f" ({t / ours:.2f}x)"
            report.row(f"| {text} | {t:.2f} s{ratio} |")
        report.row("")
    folder.cleanup()
    report.write()


if __name__ == "__main__":
    main()
