"""Benchmark: drawing a diagnosis's figures with fixed margins against Matplotlib's
constrained layout, in one process.

    python benchmarks/bench_figures.py [--out reports/bench_figures.md]

Diagnoses ``datasets/concealed/stiction.csv`` once, then draws its figures (the PNG
bytes ``ewb-ident diagnose`` writes) both ways, alternately, five times each: as the
package lays them out (:func:`ewb_ident.reporting.style.fixed_margins`) and with the
same figures switched to ``layout="constrained"``, which measures every label before
drawing. The first round of each is dropped (font caches); medians of the rest.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

import bench_fit  # noqa: E402

from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.diagnosis.diagnose import diagnose  # noqa: E402
from ewb_ident.reporting.figures import figures_of  # noqa: E402
from ewb_ident.reporting.style import png_bytes  # noqa: E402

TRACE = ROOT / "datasets" / "concealed" / "stiction.csv"
ROUNDS = 6


def draw(result, constrained: bool) -> float:
    t0 = time.perf_counter()
    for _, fig in figures_of(result):
        if constrained:
            fig.set_layout_engine("constrained")
        png_bytes(fig, dpi=90, tight=False)  # as write_diagnosis draws them
    return time.perf_counter() - t0


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    result = diagnose(read_trace(TRACE))
    times: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(ROUNDS):
        for constrained in (False, True):
            times[constrained].append(draw(result, constrained))
    fixed, constrained = (statistics.median(times[k][1:]) for k in (False, True))
    report.row(f"trace: {TRACE.relative_to(ROOT)}; {len(figures_of(result))} figures")
    report.row("")
    report.row("| layout | all figures drawn |")
    report.row("|---|---|")
    report.row(f"| fixed margins (the package's) | {fixed:.2f} s |")
    report.row(f"| constrained layout | {constrained:.2f} s ({constrained / fixed:.2f}x) |")
    report.write()


if __name__ == "__main__":
    main()
