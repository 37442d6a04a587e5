"""Diagnose every shipped trace with each optional channel dropped in turn: no crash.

    python -m studies.diagnose_channel_subsets [--shard K/N] [--out reports/diagnosis_subsets]

For every trace under ``datasets/`` (the clean datasets and the concealed ones) and each
of ``current_A``, ``disc_speed_rad_s`` and ``torque_Nm``, the trace without that column
is diagnosed in this process (``ewb_ident.diagnosis.diagnose``). A case passes when the diagnosis
completes; its verdict and findings are recorded beside the planted effects (the
``.truth.json``), so that what a missing channel costs is visible. ``--shard K/N`` runs
every N-th case from the K-th (run the shards at once, then once more without
``--shard`` to merge: cases already in ``OUT/cases/`` are not run again).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path

import jax
import pandas as pd

from ewb_ident.runtime import programs

ROOT = Path(__file__).resolve().parents[1]
DROPS = ("current_A", "disc_speed_rad_s", "torque_Nm")


def cases() -> list[tuple[Path, str]]:
    traces = sorted((ROOT / "datasets").glob("*.csv")) + sorted(
        (ROOT / "datasets" / "concealed").glob("*.csv")
    )
    return [(p, col) for p in traces for col in DROPS]


def run(path: Path, drop: str) -> dict:
    from ewb_ident.data.readers import read_trace
    from ewb_ident.data.trace import Trace
    from ewb_ident.diagnosis.diagnose import diagnose

    truth = json.loads(path.with_suffix(".truth.json").read_text())
    planted = sorted(truth.get("effects", {}))
    full = read_trace(path)
    row = {"trace": path.stem, "dropped": drop, "planted": ",".join(planted) or "none"}
    if not full.has(drop):
        return row | {"status": "column absent already"}
    trace = Trace(
        name=full.name,
        time_s=full.time_s,
        channels={k: v for k, v in full.channels.items() if k != drop},
        sidecar=dict(full.sidecar),
    )
    t0 = time.perf_counter()
    try:
        result = diagnose(trace)
        doc = result.to_json()
        json.dumps(doc, allow_nan=False)  # the contract: plain JSON
    except Exception:  # noqa: BLE001 - a crash is the finding here
        return row | {
            "status": "CRASH",
            "error": traceback.format_exc().strip().splitlines()[-1],
            "seconds": round(time.perf_counter() - t0, 1),
        }
    found = sorted({f["effect"] for f in doc["findings"]})
    return row | {
        "status": "ok",
        "verdict": doc["verdict"],
        "found": ",".join(found) or "-",
        "planted_named": all(e in found for e in planted) if planted else None,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shard", default="0/1")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "diagnosis_subsets")
    args = ap.parse_args()
    k, n = (int(x) for x in args.shard.split("/"))
    jax.config.update("jax_enable_x64", True)
    (args.out / "cases").mkdir(parents=True, exist_ok=True)
    todo = cases()
    for i, (path, drop) in enumerate(todo):
        if i % n != k:
            continue
        target = args.out / "cases" / f"{path.stem}__{drop}.json"
        if target.exists():
            continue
        row = run(path, drop)
        target.write_text(json.dumps(row, indent=1))
        print(f"{i:3d} {path.stem:<32} -{drop:<17} {row['status']:<6} "
              f"{row.get('verdict', '')} {row.get('found', '')} {row.get('seconds', '')}",
              flush=True)  # fmt: skip
        programs.release()
    done = [json.loads(p.read_text()) for p in sorted((args.out / "cases").glob("*.json"))]
    if len(done) < len(todo):
        print(f"{len(done)}/{len(todo)} cases done; run the other shards, then merge")
        return
    df = pd.DataFrame(done)
    df.to_csv(args.out / "results.csv", index=False)
    ran = df[df["status"] != "column absent already"]
    crashes = ran[ran["status"] == "CRASH"]
    concealed = ran[ran["planted"] != "none"]
    clean = ran[ran["planted"] == "none"]
    lines = [
        "# Diagnosis with each optional channel dropped",
        "",
        "Command: `python -m studies.diagnose_channel_subsets` (every trace under "
        "`datasets/`, each of current_A, disc_speed_rad_s, torque_Nm dropped in turn).",
        "",
        f"**{len(ran) - len(crashes)}/{len(ran)} diagnoses completed without an error** "
        f"({len(crashes)} crashed).",
        "",
        f"Planted effects all named: {int(concealed['planted_named'].fillna(False).sum())}"
        f"/{len(concealed)} traces with a concealed effect; clean traces with verdict "
        f"none: {int((clean['verdict'] == 'none').sum())}/{len(clean)}.",
        "",
        "| trace | dropped | planted | verdict | found | s |",
        "|---|---|---|---|---|---|",
    ]
    for _, r in ran.iterrows():
        lines.append(
            f"| {r['trace']} | {r['dropped']} | {r['planted']} | "
            f"{r.get('verdict', r['status'])} | {r.get('found', r.get('error', ''))} | "
            f"{r.get('seconds', '')} |"
        )
    (args.out / "README.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out / 'README.md'}")
    sys.exit(1 if len(crashes) else 0)


if __name__ == "__main__":
    main()
