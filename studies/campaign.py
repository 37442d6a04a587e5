"""Study: a synthetic test campaign of several rig units across a hardware change,
refitted by one ``ewb-ident batch`` command (issue 35, done-when 1).

    python -m studies.campaign [--seed S] [--units 8] [--per-side 13] [--work DIR]
                               [--out reports/campaign]

The campaign: ``--units`` rig units, each its own draw of the hardware
(``rig.vary(RigParams(r_eff_m=r), rng, 0.05)``: every parameter 5 % log-normal spread)
with its own pad radius r (0.12, 0.15 or 0.18 m, in each trace's sidecar; for half the
units also in the manifest's ``r_eff_m`` column). Every unit is recorded ``--per-side``
times before and after one hardware change (hardware v1 -> v2: new pads, mu -8 % and the
bell's centre c +40 um; everything else unchanged), each recording with a fresh noise
seed, its own sample rate (100, 200, 500 or 1000 Hz), profile (``through_c``,
``position`` or ``steps``, 3 s) and channel subset (all; no current; no torque; no disc
speed). The traces and a manifest (path, unit, hardware, date, rate, channels,
r_eff_m) go to ``--work``; then one command refits them:

    python -m ewb_ident batch WORK/manifest.csv --out WORK/out --group-by hardware

and the study scores its tables against the truth:

* per-trace intervals: for every trace x parameter row, whether the 90 % interval
  holds the trace's true value (motor M and v are identified as M/kT and v/kT with kT
  held at its nominal value: their truth is scaled alike); target 90 % +- 5;
* the population spread: in each hardware group, whether tau's 90 % interval holds
  the true spread (the standard deviation of the true values of the traces combined);
* the changes (v2 against v1): mu and c found changed, and no other parameter called
  changed (target: no false change in >= 90 % of the unchanged parameters).

The report (``--out``): README.md with the command, the figures and the tables,
coverage.csv (per parameter), rows.csv (every row with its truth), and the batch's
population.csv, changes.csv, index.html and parameters.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
SEED = 20261327
RATES = (100.0, 200.0, 500.0, 1000.0)
PROFILES = ("through_c", "position", "steps")
SUBSETS = {"all": (), "no current": ("current_A",), "no torque": ("torque_Nm",),
           "no disc speed": ("disc_speed_rad_s",)}
SUBSET_P = (0.4, 0.3, 0.15, 0.15)
RADII = (0.12, 0.15, 0.18)
#: The hardware change v1 -> v2 (new pads): relative for mu, absolute (m) for c.
MU_FACTOR, C_SHIFT_M = 0.92, 40e-6
CHANGED = ("mu", "c")


def make_campaign(work: Path, seed: int, units: int, per_side: int) -> pd.DataFrame:
    """Simulate every trace and write it with its truth; the manifest as a table."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from ewb_ident import rig
    from ewb_ident.data.writers import write_trace

    rng = np.random.default_rng(seed)
    rows = []
    for u in range(units):
        radius = RADII[u % len(RADII)]
        v1 = rig.vary(rig.RigParams(r_eff_m=radius), rng, 0.05)
        v2 = dataclasses.replace(v1, mu=v1.mu * MU_FACTOR, c=v1.c + C_SHIFT_M)
        for side, params in (("v1", v1), ("v2", v2)):
            for j in range(per_side):
                rate = float(rng.choice(RATES))
                profile = str(rng.choice(PROFILES))
                subset = str(rng.choice(list(SUBSETS), p=SUBSET_P))
                noise_seed = int(rng.integers(0, 2**31))
                trace, truth = rig.simulate_rig(params, profile=profile, sample_rate_hz=rate,
                                                duration_s=3.0, seed=noise_seed,
                                                name=f"U{u}_{side}_{j}")
                channels = {c: v for c, v in trace.channels.items()
                            if c not in SUBSETS[subset]}
                trace = dataclasses.replace(trace, channels=channels)
                name = f"U{u}_{side}_{j:02d}.csv"
                write_trace(trace, work / name)
                (work / name).with_suffix(".truth.json").write_text(json.dumps(truth))
                day = j + (0 if side == "v1" else per_side + 3)
                rows.append({"path": name, "unit": f"U{u}", "hardware": side,
                             "date": f"2026-03-{1 + day:02d}" if day < 31 else
                                     f"2026-04-{day - 30:02d}",
                             "rate_hz": rate, "profile": profile, "channels": subset,
                             "r_eff_m": radius if u % 2 == 0 else None})
    manifest = pd.DataFrame(rows)
    manifest.to_csv(work / "manifest.csv", index=False)
    return manifest


def true_values(work: Path, trace: str) -> dict[str, float]:
    """A trace's true parameters in the fit's terms (M and v per nominal kT)."""
    from ewb_ident import rig

    p = json.loads((work / trace).with_suffix(".truth.json").read_text())["params"]
    scale = rig.RigParams().kT / p["kT"]
    return p | {"M": p["M"] * scale, "v": p["v"] * scale}


def main() -> None:
    from ewb_ident.study import markdown_table

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--units", type=int, default=8)
    parser.add_argument("--per-side", type=int, default=13)
    parser.add_argument("--work", type=Path, default=Path("/tmp/ewb-campaign"))
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "campaign")
    args = parser.parse_args()
    work, out = args.work, args.out
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    out.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    manifest = make_campaign(work, args.seed, args.units, args.per_side)
    made = time.perf_counter() - t0
    print(f"simulated {len(manifest)} traces in {made:.0f} s", flush=True)

    cmd = ["batch", str(work / "manifest.csv"), "--out", str(work / "out"), "--group-by",
           "hardware"]
    t0 = time.perf_counter()
    with open(work / "batch.log", "w") as log:
        code = subprocess.call([sys.executable, "-m", "ewb_ident", *cmd], stdout=log,
                               stderr=subprocess.STDOUT,
                               env=os.environ | {"PYTHONPATH": str(ROOT)})
    wall = time.perf_counter() - t0
    print(f"batch: exit {code} in {wall:.0f} s", flush=True)
    res = pd.read_csv(work / "out" / "results.csv")
    pop = pd.read_csv(work / "out" / "population.csv")
    changes = pd.read_csv(work / "out" / "changes.csv")

    # per-trace intervals
    ok = res[(res["status"] == "ok") & res["parameter"].notna()].copy()
    truths = {t: true_values(work, t) for t in ok["trace"].unique()}
    ok["truth"] = [truths[t][p] for t, p in zip(ok["trace"], ok["parameter"], strict=True)]
    ok["held"] = (ok["low_90"] <= ok["truth"]) & (ok["truth"] <= ok["high_90"])
    ok["z"] = (ok["estimate"] - ok["truth"]) / ok["stderr"]
    meta = manifest.set_index("path")
    ok["rate_hz"] = [meta.loc[t, "rate_hz"] for t in ok["trace"]]
    ok["profile"] = [meta.loc[t, "profile"] for t in ok["trace"]]
    ok = ok.rename(columns={"channels": "channel_subset"}) if "channels" in ok else ok
    coverage = (ok.groupby("parameter", sort=False)
                .agg(rows=("held", "size"), held_pct=("held", "mean"),
                     z_rms=("z", lambda z: float(np.sqrt(np.mean(z**2)))))
                .reset_index())
    coverage["held_pct"] *= 100
    overall = 100 * ok["held"].mean()
    by = {}
    for col in ("rate_hz", "channel_subset", "profile"):
        by[col] = (ok.groupby(col)["held"].agg(["size", "mean"])
                   .rename(columns={"size": "rows", "mean": "held_pct"}).reset_index())
        by[col]["held_pct"] *= 100

    # population spread: tau's interval against the true spread of each group's traces
    spread_rows = []
    for r in pop[pop["group"] != "all"].itertuples():
        sub = ok[(ok["hardware"] == r.group) & (ok["parameter"] == r.parameter)]
        true_sd = float(np.std(sub["truth"], ddof=1))
        spread_rows.append({
            "group": r.group, "parameter": r.parameter, "n_traces": r.n_traces,
            "true_spread": true_sd, "tau": r.tau, "tau_low_90": r.tau_low_90,
            "tau_high_90": r.tau_high_90,
            "held": bool(r.tau_low_90 <= true_sd <= r.tau_high_90)})
    spread = pd.DataFrame(spread_rows)

    # changes
    ch = changes.copy()
    ch["planted"] = ch["parameter"].isin(CHANGED)
    found = ch[ch["planted"]]
    unchanged = ch[~ch["planted"]]
    false = int(unchanged["changed"].sum())
    # the true change of each group mean: c moves by C_SHIFT_M in every unit; mu by
    # (MU_FACTOR - 1) of each unit's mu, so of the v1 traces' mean mu
    v1_mu = ok[(ok["hardware"] == "v1") & (ok["parameter"] == "mu")]["truth"].mean()
    true_delta = {"c": C_SHIFT_M, "mu": (MU_FACTOR - 1) * v1_mu}
    ch["true_delta"] = [true_delta.get(p, 0.0) for p in ch["parameter"]]
    ch["interval_holds_truth"] = (ch["low_90"] <= ch["true_delta"]) & \
        (ch["true_delta"] <= ch["high_90"])
    found_ok = bool(found["changed"].all()) and len(found) == len(CHANGED)
    load1 = os.getloadavg()

    ok.to_csv(out / "rows.csv", index=False)
    coverage.to_csv(out / "coverage.csv", index=False)
    for name in ("population.csv", "changes.csv", "index.html", "parameters.png"):
        shutil.copy(work / "out" / name, out / name)
    subsets = manifest["channels"].value_counts().to_dict()
    rates = manifest["rate_hz"].value_counts().sort_index().to_dict()
    text = [
        "# A synthetic campaign refitted by one `ewb-ident batch` command",
        "",
        f"Made by `python -m studies.campaign --seed {args.seed} --units {args.units} "
        f"--per-side {args.per_side}` (its docstring says what is drawn), which ran",
        "",
        "```",
        "python -m ewb_ident batch WORK/manifest.csv --out WORK/out --group-by hardware",
        "```",
        "",
        f"{len(manifest)} traces: {args.units} rig units (5 % log-normal spread of every "
        f"parameter; pad radius 0.12 / 0.15 / 0.18 m), each recorded {args.per_side} times "
        "before and after a hardware change v1 -> v2 (new pads: mu x 0.92, c + 40 um). "
        f"Rates {', '.join(f'{k:g} Hz: {v}' for k, v in rates.items())}; channels "
        f"{', '.join(f'{k}: {v}' for k, v in subsets.items())}; profiles through_c, "
        "position, steps (3 s). Fresh noise seeds from the study's seed.",
        "",
        f"Simulated in {made:.0f} s; the batch took {wall:.0f} s (exit {code}; "
        f"{int((res.drop_duplicates('trace')['status'] == 'ok').sum())} of "
        f"{res['trace'].nunique()} traces ok). Load average before {load0[0]:.1f}, after "
        f"{load1[0]:.1f} on 2 cores (shared machine).",
        "",
        "## Per-trace 90 % intervals (target 90 % +- 5)",
        "",
        f"All rows: **{overall:.1f} %** of {len(ok)} trace x parameter rows hold the truth.",
        "",
        markdown_table(coverage),
        "",
        *[line for col, frame in by.items()
          for line in (f"By {col}:", "", markdown_table(frame), "")],
        "## The population spread (tau) per hardware group",
        "",
        f"tau's 90 % interval holds the true spread (SD of the combined traces' true "
        f"values) for {int(spread['held'].sum())} of {len(spread)} group x parameter rows.",
        "",
        markdown_table(spread),
        "",
        "## The hardware change v1 -> v2",
        "",
        f"Planted changes found: {'all' if found_ok else 'NOT all'} "
        f"({', '.join(f'{r.parameter} {r.delta_pct:+.1f} %' for r in found.itertuples())}; "
        f"true: mu {100 * (MU_FACTOR - 1):+.0f} %, c +{C_SHIFT_M * 1e6:.0f} um). "
        f"False changes: {false} of {len(unchanged)} unchanged parameters "
        f"(no false change in {100 * (1 - false / max(len(unchanged), 1)):.0f} %; "
        "target >= 90 %).",
        "",
        markdown_table(ch[["parameter", "before_mean", "after_mean", "delta", "low_90",
                           "high_90", "true_delta", "interval_holds_truth", "delta_pct",
                           "p_changed", "changed", "planted"]]),
        "",
        f"The change's 90 % interval holds the true change (c: +{C_SHIFT_M * 1e6:.0f} um; mu: "
        f"{100 * (MU_FACTOR - 1):+.0f} % of the v1 traces' mean true mu; the others: 0) for "
        f"{int(ch['interval_holds_truth'].sum())} of {len(ch)} parameters.",
        "",
        "Files: coverage.csv, rows.csv (every row with its truth), population.csv, "
        "changes.csv, index.html and parameters.png (the batch's).",
    ]
    (out / "README.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


if __name__ == "__main__":
    main()
