"""Calibration of the posterior intervals on synthetic traces with known truth.

For each repeat ``i``: a rig unit is drawn around the nominal rig
(``rig.vary(RigParams(), default_rng([seed, i]), rel=0.05)``, ``--seed``, default
:data:`SEED`: every physical parameter
times a log-normal factor with 5 % spread), a 3 s, 200 Hz trace of the open-loop
``steps`` profile is simulated with the rig's default sensor noise (noise seed ``i``),
and :func:`ewb_ident.inference.posterior.sample` is run with seed ``i`` and default settings
(2 ensembles, adaptation then the Student-t/DE mixture, stopped once converged, noise
model ``auto``,
default priors). ``kT`` is held at the unit's true value: without a load-torque
measurement only ``M/kT`` and ``v/kT`` are identified, so with ``kT`` at the seed value
the "truth" of M and v would be a ratio, not the rig's value.

Recorded per repeat and sampled parameter: the truth, posterior mean and sd, the 90 %
HDI and whether it holds the truth, and the rank statistic of simulation-based
calibration (the fraction of posterior draws below the truth; uniform on (0, 1) for a
calibrated posterior). Truths are drawn from a hardware-variation distribution, not from
the (much wider, weakly informative) priors, so this measures the frequentist coverage
of the Bayesian intervals where rigs actually are; with data that dominate the prior the
two agree.

Usage (from the repository root)::

    python -m studies.calibration --stage chain --repeats 100
    python -m studies.calibration --stage force,torque --repeats 200
    python -m studies.calibration --report-only

    ewb-ident study studies/calibration.toml --out reports/calibration

Each run appends to ``reports/calibration/calibration_<stage>.csv`` (rewritten atomically
after every repeat, so an interrupted study resumes where it stopped) and rewrites
``reports/calibration/README.md`` from every CSV present.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import time
from pathlib import Path

import jax
import numpy as np
from scipy import stats as sps

from ewb_ident import rig
from ewb_ident.data.outputs import write_text
from ewb_ident.inference.posterior import sample

ROOT = Path(__file__).resolve().parents[1]
REPORTS = ROOT / "reports" / "calibration"
SEED = 2025
NOMINAL = 0.90
FIELDS = (
    "repeat",
    "param",
    "truth",
    "mean",
    "sd",
    "hdi_low",
    "hdi_high",
    "inside",
    "rank",
    "ess",
    "r_hat",
    "converged",
    "steps",
    "seconds",
)


NOTES = {
    "force+torque": [
        "Teacher-forced stages condition on the *measured* input channel (x for the force,",
        "force for the torque). The rig's x sensor noise (2 um) times the bell's slope (up",
        "to ~7 N/um) is force noise in the residual; each sample is weighed by the force",
        "sensor's noise and this carried noise at the values being sampled (effective",
        "variance, `docs/least-squares.md`). Weighed by the force sensor's noise alone,",
        "an earlier run (seed 2025, 100 repeats, DEMove alone) held the truth in 72-74 % of",
        "repeats for F_rt, a, b, c, with z mean -0.7 (the bell flattened where x is noisy),",
        "and mu in 88 %.",
        "",
    ],
}
HISTORY = [
    "## How this study found a sampler bug",
    "",
    "The first run of this study used emcee's recommended mix of moves (80 % `DEMove`,",
    "20 % `DESnookerMove`). Over 32 repeats of the chain it gave 75-92 % coverage and",
    "z rms 1.0-1.35 for every parameter: intervals about 12 % too narrow. emcee 3.1.6's",
    "`DESnookerMove` is biased (its direction vector is `delta / sqrt(norm)` instead of",
    "a unit vector; fixed upstream in dfm/emcee#531): alone it samples a 14-dimensional",
    "Gaussian with 40 % too little variance. ewb-ident then used `DEMove` alone (since",
    "stop 24 mixed with a Student-t independence proposal that passes a Pareto k check), and",
    "`tests/test_posterior.py::test_sampler_reproduces_an_analytic_posterior` checks the",
    "sampler against an analytic posterior. The study also found a least-squares start",
    "in a local minimum (repeat 39, a flat bell); the sampler now restarts such a fit",
    "from the teacher-forced stage fits.",
    "",
]


def _truth_of(name: str, params: rig.RigParams, truth: dict) -> float | None:
    base = name.split("[")[0]
    if base == "theta0_deg":
        return float(truth["theta0_deg"])
    return float(getattr(params, base)) if hasattr(params, base) else None


def run_repeat(i: int, stages: tuple[str, ...] | str, seed: int = SEED) -> list[dict]:
    params = rig.vary(rig.RigParams(), np.random.default_rng([seed, i]), rel=0.05)
    trace, truth = rig.simulate_rig(
        params, profile="steps", sample_rate_hz=200.0, duration_s=3.0, seed=i, name=f"cal{i}"
    )
    t0 = time.perf_counter()
    res = sample(trace, stage=stages, fixed={"kT": params.kT}, seed=i)
    seconds = time.perf_counter() - t0
    rows = []
    for name in res.names:
        value = _truth_of(name, params, truth)
        if value is None:
            continue
        s = res.stats[name]
        draws = res.draws[name].reshape(-1)
        rows.append(
            {
                "repeat": i,
                "param": name,
                "truth": value,
                "mean": s["mean"],
                "sd": s["sd"],
                "hdi_low": s["hdi_low"],
                "hdi_high": s["hdi_high"],
                "inside": int(s["hdi_low"] <= value <= s["hdi_high"]),
                "rank": float(np.mean(draws < value)),
                "ess": s["ess"],
                "r_hat": s["r_hat"],
                "converged": int(res.converged),
                "steps": res.diagnostics["n_steps"],
                "seconds": round(seconds, 2),
            }
        )
    return rows


def _read(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _write(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=FIELDS)
    w.writeheader()
    w.writerows(rows)
    text = buf.getvalue()
    write_text(path, text)


def _wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return c - h, c + h


def summarise(rows: list[dict]) -> dict:
    """Coverage per parameter (with a 95 % Wilson interval), z-score spread, SBC ranks."""
    out: dict = {"params": {}}
    repeats = sorted({int(r["repeat"]) for r in rows})
    out["repeats"] = len(repeats)
    by_rep = {i: [r for r in rows if int(r["repeat"]) == i] for i in repeats}
    out["converged"] = sum(int(v[0]["converged"]) for v in by_rep.values())
    out["seconds_median"] = float(np.median([float(v[0]["seconds"]) for v in by_rep.values()]))
    out["steps_median"] = float(np.median([float(v[0]["steps"]) for v in by_rep.values()]))
    abcm = {"a", "b", "c", "mu"}
    joint = [all(int(r["inside"]) for r in v if r["param"] in abcm) for v in by_rep.values()]
    out["joint_abcmu"] = float(np.mean(joint))
    for name in dict.fromkeys(r["param"] for r in rows):
        rs = [r for r in rows if r["param"] == name]
        k, n = sum(int(r["inside"]) for r in rs), len(rs)
        z = np.array([(float(r["mean"]) - float(r["truth"])) / float(r["sd"]) for r in rs])
        ranks = np.array([float(r["rank"]) for r in rs])
        counts = np.histogram(ranks, bins=10, range=(0, 1))[0]
        out["params"][name] = {
            "n": n,
            "coverage": k / n,
            "ci": _wilson(k, n),
            "z_rms": float(np.sqrt(np.mean(z * z))),
            "z_mean": float(np.mean(z)),
            "rank_p": float(sps.chisquare(counts).pvalue),
            "ess_min": float(min(float(r["ess"]) for r in rs)),
        }
    return out


def report(folder: Path = REPORTS) -> str:
    """The Markdown report from every ``calibration_*.csv`` in ``folder``."""
    lines = [
        "# Calibration of the posterior intervals (simulation-based)",
        "",
        "Generated by `studies/calibration.py` (its docstring says exactly what is run).",
        "Per repeat: a rig unit drawn with `rig.vary(RigParams(), rng, rel=0.05)`, a 3 s,",
        "200 Hz `steps` trace with the rig's default sensor noise, and `ewb_ident.sample`",
        "with default settings and seed = repeat (kT held at the unit's true value). A",
        "90 % HDI should hold the truth in 90 % of repeats; the target is 85-95 %.",
        "`z rms` is the spread of (posterior mean - truth) / posterior sd (1 if calibrated);",
        "`rank p` the p-value of a chi-square test of uniformity of the SBC ranks (10 bins).",
        "",
    ]
    for path in sorted(folder.glob("calibration_*.csv")):
        rows = _read(path)
        if not rows:
            continue
        s = summarise(rows)
        stage = path.stem.removeprefix("calibration_")
        lines += [
            f"## Stage `{stage}`: {s['repeats']} repeats",
            "",
            f"Converged: {s['converged']} of {s['repeats']}. Median time per posterior "
            f"{s['seconds_median']:.1f} s ({s['steps_median']:.0f} steps per ensemble, "
            "2 cores shared). Truth inside all four 90 % HDIs of a, b, c, mu at once: "
            f"{100 * s['joint_abcmu']:.0f} % of repeats (the four are not independent).",
            "",
            "| parameter | coverage of the 90 % HDI | 95 % interval | z rms | z mean | rank p |"
            " min ESS |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, p in s["params"].items():
            flag = "" if 0.85 <= p["coverage"] <= 0.95 else " (outside 85-95 %)"
            lines.append(
                f"| `{name}` | {100 * p['coverage']:.0f} %{flag} | {100 * p['ci'][0]:.0f}-"
                f"{100 * p['ci'][1]:.0f} % | {p['z_rms']:.2f} | {p['z_mean']:+.2f} | "
                f"{p['rank_p']:.2f} | {p['ess_min']:.0f} |"
            )
        lines.append("")
        lines += NOTES.get(stage, [])
    lines += HISTORY
    return "\n".join(lines) + "\n"


def run(
    out_dir: Path = REPORTS,
    progress=None,
    stage: str = "chain",
    repeats: int = 100,
    log=None,
    seed: int = SEED,
    first: int = 0,
):
    """Run (or resume) the study into ``out_dir``; returns (table, Markdown report).

    ``stage`` is ``"chain"`` or comma-separated stages (``"force,torque"``).
    """
    import pandas as pd

    jax.config.update("jax_enable_x64", True)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = tuple(stage.split(","))
    stages = names[0] if len(names) == 1 else names
    path = out_dir / f"calibration_{'+'.join(names)}.csv"
    rows = _read(path)
    done = {int(r["repeat"]) for r in rows}
    for i in range(first, repeats):
        if i not in done:
            rows += run_repeat(i, stages, seed)
            _write(path, rows)
            if log:
                cov = summarise(rows)["params"]
                log(
                    f"repeat {i}: "
                    + ", ".join(
                        f"{n} {100 * cov[n]['coverage']:.0f}%" for n in ("a", "b", "c", "mu")
                    )
                )
        if progress:
            progress(i + 1, repeats)
    text = report(out_dir)
    write_text(out_dir / "README.md", text)
    return pd.DataFrame(rows), text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stage", default="chain", help="chain, or e.g. force,torque")
    ap.add_argument("--repeats", type=int, default=100)
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--out", type=Path, default=REPORTS)
    ap.add_argument("--seed", type=int, default=SEED, help="draw other rig units")
    ap.add_argument("--first", type=int, default=0, help="start at this repeat (shard by hand)")
    args = ap.parse_args()
    if args.report_only:
        text = report(args.out)
        write_text(args.out / "README.md", text)
    else:
        _, text = run(
            args.out,
            stage=args.stage,
            repeats=args.repeats,
            log=lambda line: print(line, flush=True),
            seed=args.seed,
            first=args.first,
        )
    print(text)


if __name__ == "__main__":
    main()
