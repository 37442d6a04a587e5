"""Do the 90 % intervals of a hardware change hold the true change? (issue 11, item 4)

Each case draws a fresh unit of the independent rig (``validation_rigs/other_rig.py``: wide motor,
gap, bell and mu ranges, pad radius 0.10-0.25 m), records it before and after a planted
change (pad change: c by +20...+60 um, b by up to +-8 %, mu by up to +-5 %; a warm motor:
R by 0...+20 %), with its own profile (open-loop steps, PID position control closed at
the logging rate, staircase), rate (100 Hz to 1 kHz) and channel subset (all, or no
current), and runs ``ewb_ident.inference.compare`` on the pair. For every parameter with an
interval, the row holds the true change (zero for an unchanged one) and whether the
90 % interval holds it. The seed (default 20261128; the first run, before the motor's
identified combinations replaced L, kb and M without current, used 20261126) is this
study's own.

    python -m studies.compare_coverage [N] [--seed S] [--out reports/compare_coverage]

Rows are appended to ``OUT/cases_SEED.csv`` after each case, so a run resumes;
``OUT/README.md`` holds coverage per parameter and by channel subset.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import time
from pathlib import Path

import numpy as np

from ewb_ident.data.outputs import write_text
from ewb_ident.runtime import programs
from validation_rigs.other_rig import draw_rig, record

ROOT = Path(__file__).resolve().parents[1]

SEED = 20261128
OUT = ROOT / "reports" / "compare_coverage"
PROFILES = ("steps", "steps2", "position", "staircase")
RATES = (100.0, 200.0, 500.0, 1000.0)
SUBSETS = {"all": (), "no current": ("current_A",)}
HEADLINE = ("a", "b", "c", "mu", "F_rt", "R", "motor_gain_rad_per_V_s", "motor_lag_s")


def run_case(k: int, seed: int = SEED) -> list[dict]:
    import jax

    from ewb_ident.inference.compare import compare
    from ewb_ident.inference.fit_result import motor_combination_values

    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng([seed, k])
    old = draw_rig(rng)
    new = dataclasses.replace(
        old,
        c=old.c + rng.uniform(20e-6, 60e-6),
        b=old.b * float(np.exp(rng.uniform(-0.08, 0.08))),
        mu=old.mu * (1.0 + rng.uniform(-0.05, 0.05)),
        R=old.R * (1.0 + rng.uniform(0.0, 0.2)),
    )
    subset = list(SUBSETS)[k % len(SUBSETS)]
    profile = PROFILES[int(rng.integers(len(PROFILES)))]
    rate = float(RATES[int(rng.integers(len(RATES)))])
    seeds = rng.integers(2**31, size=2)
    kw = dict(profile=profile, rate_hz=rate, drop=SUBSETS[subset])
    t_old, _ = record(old, seed=int(seeds[0]), name=f"old{k}", **kw)
    t_new, _ = record(new, seed=int(seeds[1]), name=f"new{k}", **kw)
    t0 = time.perf_counter()
    result = compare([t_old], [t_new])
    seconds = round(time.perf_counter() - t0, 1)
    ok = bool(result.old.converged and result.new.converged)
    rows = []
    motor = ("R", "L", "kb", "kT", "M", "v")
    combos = [motor_combination_values(**{n: getattr(r, n) for n in motor}) for r in (old, new)]
    for ch in result.changes:
        if ch.low90 is None:
            continue
        if ch.name in combos[0]:  # without current: the identified motor combinations
            true = combos[1][ch.name] - combos[0][ch.name]
        elif hasattr(old, ch.name):
            true = getattr(new, ch.name) - getattr(old, ch.name)
        else:
            continue
        rows.append({
            "case": k, "subset": subset, "profile": profile, "rate_hz": rate,
            "param": ch.name, "true_delta": true, "delta": ch.delta, "low90": ch.low90,
            "high90": ch.high90, "held": bool(ch.low90 <= true <= ch.high90),
            "changed": true != 0.0, "flagged": bool(ch.changed), "fits_converged": ok,
            "seconds": seconds,
        })  # fmt: skip
    programs.release()
    return rows


def report(rows: list[dict], n_cases: int, seed: int = SEED) -> str:
    import pandas as pd

    df = pd.DataFrame(rows)
    df["held"] = df["held"].astype(str) == "True"
    lines = [
        "# Coverage of the 90 % intervals of a hardware change",
        "",
        f"Command: `python -m studies.compare_coverage {n_cases} --seed {seed}` "
        f"({df['case'].nunique()} fresh pairs of the independent rig). A planted pad change "
        "(c, b, mu) and a warm motor (R); every other parameter unchanged (true change 0). "
        "Without current the motor's change is given for its identified gain and lag.",
        "",
        "| parameter | pairs | interval holds the true change | changed in truth |",
        "|---|---|---|---|",
    ]
    order = [p for p in HEADLINE if p in set(df["param"])]
    order += sorted(set(df["param"]) - set(order))
    for p in order:
        sub = df[df["param"] == p]
        changed = sub["changed"].astype(str) == "True"
        lines.append(
            f"| {p} | {len(sub)} | {int(sub['held'].sum())}/{len(sub)} "
            f"({sub['held'].mean():.0%}) | {int(changed.sum())} |"
        )
    lines += ["", "By channel subset (a, b, c, mu together):", ""]
    head = df[df["param"].isin(["a", "b", "c", "mu"])]
    for s, sub in head.groupby("subset"):
        lines.append(f"- {s}: {int(sub['held'].sum())}/{len(sub)} ({sub['held'].mean():.0%})")
    lines.append(
        f"- both subsets: {int(head['held'].sum())}/{len(head)} ({head['held'].mean():.0%})"
    )
    conv = df.groupby("case")["fits_converged"].first().astype(str) == "True"
    lines += ["", f"Both fits converged in {int(conv.sum())}/{len(conv)} pairs."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("n", type=int, nargs="?", default=40)
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / f"cases_{args.seed}.csv"  # one store per seed: runs never mix

    def stored() -> list[dict]:
        return list(csv.DictReader(io.StringIO(store.read_text()))) if store.exists() else []

    if not args.report_only:
        done = {int(r["case"]) for r in stored()}
        for k in range(args.n):
            if k in done:
                continue
            rows = run_case(k, args.seed)
            new = not store.exists()
            with open(store, "a", newline="") as handle:
                w = csv.DictWriter(handle, fieldnames=list(rows[0]))
                if new:
                    w.writeheader()
                w.writerows(rows)
            print(f"case {k}: " + ", ".join(f"{r['param']} {r['held']}" for r in rows), flush=True)
    rows = stored()
    if rows:
        write_text(args.out / "README.md", report(rows, args.n, args.seed))
        print(f"wrote {args.out / 'README.md'}")


if __name__ == "__main__":
    main()
