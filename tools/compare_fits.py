"""``ewb-ident fit`` on every shipped trace by two checkouts, and how their fit.json differ.

    python tools/compare_fits.py BEFORE AFTER [--out FOLDER]

``BEFORE`` and ``AFTER`` are checkouts (e.g. ``/work/main`` and this one); each fit runs
in a fresh process with ``PYTHONPATH`` set to its checkout and an on-disk program cache
of its own. The fits: the whole chain and the motor and force stages of each trace in
``datasets/``, the chain of each trace in ``datasets/concealed/``, and the chain with
the mechanism each of three concealed traces hides (``--with``, the mechanism fits'
solver). For each, whether the two fit.json are byte-identical, else the largest
relative difference of each number that differs (keyed by its path in the document).
Exit status 1 if any pair differs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "datasets"
WITH = {"backlash": "backlash", "stiction": "stiction", "force_hysteresis": "force_hysteresis"}


def cases() -> list[tuple[str, Path, list[str]]]:
    """(label, trace, extra options) of every fit compared."""
    out = []
    for path in sorted(DATA.glob("*.csv")):
        for stage in ("chain", "motor", "force"):
            out.append((f"{path.stem} {stage}", path, ["--stage", stage]))
    for path in sorted((DATA / "concealed").glob("*.csv")):
        out.append((f"concealed/{path.stem} chain", path, []))
    for stem, mech in WITH.items():
        path = DATA / "concealed" / f"{stem}.csv"
        out.append((f"concealed/{stem} --with {mech}", path, ["--with", mech]))
    return out


def run(checkout: Path, cache: Path, trace: Path, extra: list[str], out: Path) -> dict | None:
    """fit.json of one fit (``None`` if the command failed)."""
    env = dict(os.environ, PYTHONPATH=str(checkout), EWB_IDENT_CACHE=str(cache))
    cmd = ["nice", sys.executable, "-m", "ewb_ident", "fit", str(trace), "--out", str(out)]
    proc = subprocess.run(cmd + extra, env=env, capture_output=True, text=True, cwd=checkout)
    path = out / "fit.json"
    if proc.returncode or not path.exists():
        print(f"  failed ({checkout}): {proc.stderr.strip()[-400:]}", flush=True)
        return None
    return {"bytes": path.read_bytes(), "doc": json.loads(path.read_text())}


def differences(a, b, path: str = "") -> dict[str, float]:
    """Relative difference of each number that differs between two documents (``inf``
    where the structure or a non-number differs)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: dict[str, float] = {}
        for k in a.keys() | b.keys():
            if k not in a or k not in b:
                out[f"{path}/{k}"] = float("inf")
            else:
                out |= differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return {path: float("inf")}
        out = {}
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            out |= differences(x, y, f"{path}[{i}]")
        return out
    num = (int, float)
    if isinstance(a, num) and isinstance(b, num) and not isinstance(a, bool):
        if a == b:
            return {}
        return {path: abs(a - b) / max(abs(a), abs(b), 1e-300)}
    return {} if a == b else {path: float("inf")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="keep the fit folders here")
    args = ap.parse_args()
    folder = Path(args.out or tempfile.mkdtemp(prefix="compare_fits_"))
    differ = 0
    for label, trace, extra in cases():
        docs = []
        for side, checkout in (("before", args.before), ("after", args.after)):
            out = folder / side / label.replace("/", "_").replace(" ", "_")
            docs.append(run(checkout.resolve(), folder / f"cache_{side}", trace, extra, out))
        if None in docs:
            differ += 1
            print(f"{label}: a side failed", flush=True)
            continue
        if docs[0]["bytes"] == docs[1]["bytes"]:
            print(f"{label}: byte-identical", flush=True)
            continue
        differ += 1
        diff = differences(docs[0]["doc"], docs[1]["doc"])
        worst = sorted(diff.items(), key=lambda kv: -kv[1])[:8]
        print(f"{label}: differs at {len(diff)} values; largest relative differences:")
        for k, v in worst:
            print(f"    {k}: {v:.3g}", flush=True)
    print(f"{differ} of {len(cases())} fits differ; folders in {folder}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
