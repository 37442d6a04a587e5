"""Study: a 1 h, 1 kHz endurance log with a planted slow fade, refitted as a campaign of
apply cycles by one command from each of CSV, Parquet and .mat.

    python -m studies.endurance [--work DIR] [--out reports/endurance] [--minutes 60]

The log (:func:`ewb_ident.rig.endurance.simulate_endurance`): one ``through_c`` apply
every 10 s (360 cycles, 3.6 M samples at 1 kHz, every channel), the pad friction mu
falling linearly by 10 % over the hour, every other parameter constant. It is written
as CSV, Parquet and MATLAB v5 .mat into DIR (about 0.9 GB), and each file goes through

    python -m ewb_ident batch DIR/endurance.<ext> --cycles --out DIR/out_<ext>

timed, with its peak memory (the child's maximum resident set), and each format's
reading alone (``read_trace`` of the 3.6 M rows) likewise. The report (``--out``) holds
README.md (the figures below), each run's trend.csv and cycles.csv, and the CSV run's
index.html, parameters.png, cycles.png and results.csv.

Checks: mu's slope (per hour) holds the planted -0.035 / h in its 90 % interval, from
each format; the three formats give the same table; the other parameters' drift
intervals hold their true zero at about the nominal rate (none flagged as a trend).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

FORMATS = ("csv", "parquet", "mat")
MU_DRIFT = -0.10  # relative change of mu over the hour
SEED = 20261127


def _child(args: list[str], log: Path) -> tuple[float, float, int]:
    """Run a child process; its wall time (s), peak resident memory (MB, from
    ``/usr/bin/time``) and exit code."""
    peak_file = log.with_suffix(".peak")
    t0 = time.perf_counter()
    with open(log, "w") as handle:
        code = subprocess.call(["/usr/bin/time", "-f", "%M", "-o", str(peak_file), *args],
                               stdout=handle, stderr=subprocess.STDOUT,
                               env=os.environ | {"PYTHONPATH": str(ROOT)})
    wall = time.perf_counter() - t0
    peak = float(peak_file.read_text().split()[-1]) / 1024.0
    return wall, peak, code


ROOT = Path(__file__).resolve().parents[1]
READ = """
import sys, time
from ewb_ident.data.readers import MAX_LOG_SAMPLES, read_trace
t0 = time.perf_counter()
trace = read_trace(sys.argv[1], max_samples=MAX_LOG_SAMPLES)
print(f"read {trace.n} samples in {time.perf_counter() - t0:.2f} s")
"""


def make_logs(work: Path, minutes: float) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import scipy.io

    from ewb_ident.data.writers import write_trace
    from ewb_ident.rig.endurance import simulate_endurance

    t0 = time.perf_counter()
    trace, truth = simulate_endurance(duration_s=60.0 * minutes, period_s=10.0,
                                      sample_rate_hz=1000.0, drift={"mu": MU_DRIFT}, seed=SEED)
    made = time.perf_counter() - t0
    for ext in ("csv", "parquet"):
        write_trace(trace, work / f"endurance.{ext}")
    scipy.io.savemat(work / "endurance.mat", {"time_s": trace.time_s, **trace.channels})
    (work / "endurance.truth.json").write_text(json.dumps(truth, indent=1))
    return {"samples": trace.n, "simulated_s": made, "truth": truth}


def main() -> None:
    from ewb_ident.study import markdown_table

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/ewb-endurance"))
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "endurance")
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--keep-logs", action="store_true",
                        help="reuse the logs an earlier run of the same length left in --work")
    args = parser.parse_args()
    work, out = args.work, args.out
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    kept = work / "endurance.truth.json"
    if args.keep_logs and kept.is_file() and all(
            (work / f"endurance.{ext}").is_file() for ext in FORMATS):
        truth = json.loads(kept.read_text())
        log = {"samples": int(round(args.minutes * 60_000)), "simulated_s": float("nan"),
               "truth": truth}
        if len(truth["cycles"]) != int(round(args.minutes * 6)):
            raise SystemExit(f"{kept}: the kept logs are of another length; drop --keep-logs")
    else:
        log = make_logs(work, args.minutes)
    truth = log["truth"]
    mu0 = truth["params"]["mu"]
    hours = args.minutes / 60.0
    slope_true = mu0 * MU_DRIFT / hours  # per hour
    print(f"simulated {log['samples']:,} samples in {log['simulated_s']:.0f} s", flush=True)
    sizes = {ext: (work / f"endurance.{ext}").stat().st_size / 1e6 for ext in FORMATS}

    rows, tables = [], {}
    for ext in FORMATS:
        path = work / f"endurance.{ext}"
        # (the peak through /usr/bin/time: a child's own ru_maxrss would start from this
        # process's, which holds the log)
        _, read_mb, _ = _child([sys.executable, "-c", READ, str(path)],
                               work / f"read_{ext}.log")
        read_s = (work / f"read_{ext}.log").read_text().split()[-2]
        dest = work / f"out_{ext}"
        shutil.rmtree(dest, ignore_errors=True)
        cmd = [sys.executable, "-m", "ewb_ident", "batch", str(path), "--cycles", "--out",
               str(dest)]
        wall, peak, code = _child(cmd, work / f"batch_{ext}.log")
        print(f"{ext}: read {read_s} s ({read_mb:.0f} MB); batch {wall:.0f} s, exit {code}",
              flush=True)
        trend = pd.read_csv(dest / "trend.csv")
        tables[ext] = pd.read_csv(dest / "results.csv")
        every = trend[trend["group"] == "all"].set_index("parameter")
        mu = every.loc["mu"]
        others = every.drop(index="mu")
        held = ((others["drift_low_90"] <= 0) & (others["drift_high_90"] >= 0))
        cycles = pd.read_csv(dest / "cycles.csv")
        rows.append({
            "format": ext, "file_MB": round(sizes[ext]), "read_s": float(read_s),
            "read_peak_MB": round(read_mb), "batch_s": round(wall), "batch_peak_MB": round(peak),
            "batch_exit": code,
            "cycles": int((~cycles["partial"]).sum()),
            "mu_slope_per_h [90 %]": f"{mu['slope']:+.6f} [{mu['slope_low_90']:+.6f}, "
                                     f"{mu['slope_high_90']:+.6f}]",
            "mu_held": bool(mu["slope_low_90"] <= slope_true <= mu["slope_high_90"]),
            "mu_drift_pct [90 %]": f"{mu['drift_pct']:+.3f} [{mu['drift_low_90_pct']:+.3f}, "
                                   f"{mu['drift_high_90_pct']:+.3f}]",
            "mu_flagged": bool(mu["trend"]),
            "others_zero_held": f"{int(held.sum())}/{len(held)}",
            "others_flagged": int(others["trend"].sum()),
        })
        keep = out / ext
        keep.mkdir(exist_ok=True)
        for name in ("trend.csv", "cycles.csv"):
            shutil.copy(dest / name, keep / name)
        if ext == "csv":
            for name in ("index.html", "parameters.png", "cycles.png", "results.csv",
                         "population.csv"):
                shutil.copy(dest / name, keep / name)
    load_after = os.getloadavg()
    same = all(
        np.allclose(tables[e]["estimate"], tables["csv"]["estimate"], rtol=0, atol=0,
                    equal_nan=True)
        for e in FORMATS)
    summary = pd.DataFrame(rows)
    text = [
        "# Endurance log: 1 h at 1 kHz as a campaign of apply cycles",
        "",
        f"Made by `python -m studies.endurance --minutes {args.minutes:g}` (seed {SEED}); "
        "each format refitted by one command, "
        "`python -m ewb_ident batch WORK/endurance.<ext> --cycles --out WORK/out_<ext>`.",
        "",
        f"The log: {log['samples']:,} samples at 1 kHz, one `through_c` apply every 10 s, "
        f"every channel; mu falls linearly from {mu0:g} by {-100 * MU_DRIFT:g} % over the "
        f"log (true slope {slope_true:+.5f} / h), every other parameter constant. "
        + (f"Simulated in {log['simulated_s']:.0f} s." if log["simulated_s"] == log["simulated_s"]
           else "The logs of an earlier run of this script (--keep-logs)."),
        "",
        markdown_table(summary),
        "",
        f"The three formats give identical tables (every estimate equal): {same}.",
        "",
        "* `read_s`, `read_peak_MB`: `read_trace` of the whole log alone (a fresh process; "
        "its peak resident memory, Python and the libraries included).",
        "* `batch_s`, `batch_peak_MB`: the whole command (read, split, write the cycles, "
        "fit every cycle in this process, tables and report).",
        "* `mu_held`: the planted slope inside mu's 90 % interval; `others_zero_held`: the "
        "other parameters whose drift interval holds their true zero; `others_flagged`: "
        "of them, how many were called a trend (P(|drift| > 1 %) > 0.95).",
        "",
        f"Load average (1, 5, 15 min) before: {', '.join(f'{v:.1f}' for v in load_before)}; "
        f"after: {', '.join(f'{v:.1f}' for v in load_after)} on 2 cores "
        "(the machine was shared with other work: timings are upper bounds).",
        "",
        "Files: `csv/` holds the CSV run's report (index.html, parameters.png: the "
        "per-cycle estimates and their trends; cycles.png: the split), results.csv, "
        "population.csv, trend.csv and cycles.csv (every cycle's boundaries); `parquet/` "
        "and `mat/` their trend.csv and cycles.csv.",
    ]
    (out / "README.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


if __name__ == "__main__":
    main()
