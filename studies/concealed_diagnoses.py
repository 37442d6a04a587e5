"""Diagnose every shipped concealed-effect trace and tabulate the outcome.

Run from the repository root: ``python -m studies.concealed_diagnoses``. For each
``datasets/concealed/NAME.csv`` it writes ``reports/diagnosis/NAME/`` (``diagnosis.json``
and figures, exactly what ``ewb-ident diagnose`` writes) and then
``reports/diagnosis/README.md``: the planted effects beside what the diagnosis found,
whether the baseline passes the seed's acceptance (percent error < 10 % on force and
torque, i.e. the effect is concealed), the first finding in words, and the time taken.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from ewb_ident.data.outputs import write_text  # noqa: E402
from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.diagnosis.diagnose import diagnose  # noqa: E402
from ewb_ident.reporting.figures import write_diagnosis  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "datasets" / "concealed"
OUT = ROOT / "reports" / "diagnosis"


def _pct(metrics: dict, ch: str) -> float | None:
    return (metrics.get(ch) or {}).get("percent_error")


def main() -> None:
    rows = []
    for path in sorted(DATA.glob("*.csv")):
        name = path.stem
        truth = json.loads(path.with_suffix(".truth.json").read_text())
        planted = list(truth.get("effects") or {}) or ["none"]
        trace = read_trace(path)
        t0 = time.perf_counter()
        res = diagnose(trace)
        seconds = time.perf_counter() - t0
        write_diagnosis(res, OUT / name, extra={"traces": [f"datasets/concealed/{path.name}"]})
        f_pct, t_pct = (
            _pct(res.baseline_metrics, "force_N"),
            _pct(res.baseline_metrics, "torque_Nm"),
        )
        concealed = f_pct is not None and t_pct is not None and f_pct < 10 and t_pct < 10
        found = [f.effect for f in res.findings] or ["none"]
        first = res.findings[0].explanation if res.findings else "fits to the noise"
        rows.append((name, planted, f_pct, t_pct, concealed, res.verdict, found, first, seconds))
        print(f"{name}: planted {planted} -> {res.verdict} {found} ({seconds:.0f} s)", flush=True)

    lines = [
        "# Diagnoses of the shipped concealed-effect traces",
        "",
        "Produced by `python -m studies.concealed_diagnoses` from `datasets/concealed/` "
        "(made by `python datasets/make_concealed.py`). Each folder holds `diagnosis.json` "
        "and the figures `ewb-ident diagnose` writes. *Baseline %* is the seed model's "
        "whole-chain percent error (relative L2) on force / torque: below 10 % the seed's "
        "acceptance passes and the effect is concealed.",
        "",
        "| trace | planted | baseline % force / torque | concealed | verdict | found | s |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, planted, f_pct, t_pct, concealed, verdict, found, _, sec in rows:
        lines.append(
            f"| [{name}]({name}/diagnosis.json) | {', '.join(planted)} | "
            f"{f_pct:.2f} / {t_pct:.2f} | {'yes' if concealed else 'no'} | {verdict} | "
            f"{', '.join(found)} | {sec:.0f} |"
        )
    lines += ["", "What the diagnosis says first, in words:", ""]
    for name, *_, first, _ in rows:
        lines.append(f"- **{name}**: {first}")
    text = "\n".join(lines) + "\n"
    write_text(OUT / "README.md", text)
    print(text)


if __name__ == "__main__":
    main()
