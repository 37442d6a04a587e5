"""Are results unchanged by a change of code? Two checks, each run on the code before and
on the code after (the former from a worktree of the earlier commit, e.g.
``git worktree add ../before d7596c1`` and ``PYTHONPATH=../before python ...``).

    python -m studies.regression diagnose --out DIR [--against EARLIER_DIR]
        Diagnose every shipped concealed trace (``datasets/concealed``) and write each
        ``diagnosis.json``; with ``--against``, compare them field by field with an
        earlier run's and print every number that differs by more than 1e-4 relative
        (and 1e-9 absolute) and every text that differs (timings left out).

        ``--compare-only`` compares the ``diagnosis.json`` files already in DIR.

    python -m studies.regression fits BEFORE.csv AFTER.csv
        Compare two ``results.csv`` of ``convergence_third_rig.py`` or
        ``convergence_other_rigs.py`` run with the same seed: successes, and the largest
        change of each relative error.

    python -m studies.regression accuracy BEFORE_DIR AFTER_DIR
        Compare two runs of ``diagnosis_accuracy.py`` with the same seed and options
        (their ``cases*.csv``): every field of every case both ran that differs (numbers
        by more than 1e-3 relative; the seconds left out), and the summed seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _differences(x, y, path=""):
    if isinstance(x, dict) and isinstance(y, dict):
        out = []
        for k in sorted(set(x) | set(y)):
            if k not in x or k not in y:
                out.append((f"{path}/{k}", "only in one"))
            else:
                out += _differences(x[k], y[k], f"{path}/{k}")
        return out
    if isinstance(x, list) and isinstance(y, list):
        if len(x) != len(y):
            return [(path, f"{len(x)} items against {len(y)}")]
        pairs = enumerate(zip(x, y, strict=True))
        return [d for i, (p, q) in pairs for d in _differences(p, q, f"{path}[{i}]")]
    if isinstance(x, float) and isinstance(y, float):
        tol = max(1e-4 * max(abs(x), abs(y)), 1e-9)
        return [(path, x, y)] if abs(x - y) > tol else []
    return [] if x == y else [(path, str(x)[:120], str(y)[:120])]


def diagnose_all(out: Path, against: Path | None, run: bool = True) -> None:
    if run:
        _diagnose_concealed(out)
    if against is None:
        return
    for path in sorted(out.glob("*.json")):
        new = json.loads(path.read_text())
        old = json.loads((against / path.name).read_text())
        diffs = [d for d in _differences(old, new) if "timings" not in d[0]]
        print(f"{path.stem}: {len(diffs)} differences")
        for d in diffs:
            print("   ", *d)


def _diagnose_concealed(out: Path) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    from ewb_ident.data.readers import read_trace
    from ewb_ident.diagnosis.diagnose import diagnose

    out.mkdir(parents=True, exist_ok=True)
    for path in sorted((ROOT / "datasets" / "concealed").glob("*.csv")):
        t0 = time.perf_counter()
        result = diagnose(read_trace(path))
        doc = result.to_json()
        (out / f"{path.stem}.json").write_text(json.dumps(doc, indent=1, default=str))
        found = [f.effect for f in result.findings]
        print(f"{path.stem}: {result.verdict} {found} ({time.perf_counter() - t0:.1f} s)")


def compare_accuracy(before: Path, after: Path) -> None:
    import pandas as pd

    def cases(folder: Path):
        files = sorted(folder.glob("cases*.csv"))
        return pd.concat([pd.read_csv(f) for f in files]).set_index("case").sort_index()

    b, a = cases(before), cases(after)
    common = b.index.intersection(a.index)
    n_diff = 0
    for c in common:
        for col in (k for k in a.columns if k != "seconds" and k in b.columns):
            x, y = b.at[c, col], a.at[c, col]
            same = (pd.isna(x) and pd.isna(y)) or x == y or str(x) == str(y)
            if not same and isinstance(x, float) and isinstance(y, float):
                same = abs(x - y) <= 1e-3 * max(abs(x), abs(y))
            if not same:
                n_diff += 1
                print(f"case {c} ({b.at[c, 'truth']}): {col} {x!r} -> {y!r}")
    print(
        f"{len(common)} cases in both, {n_diff} differing fields; "
        f"seconds summed over them: before {b.loc[common, 'seconds'].sum():.0f}, "
        f"after {a.loc[common, 'seconds'].sum():.0f}"
    )


def compare_fits(before: Path, after: Path) -> None:
    import numpy as np
    import pandas as pd

    b, a = pd.read_csv(before), pd.read_csv(after)
    ok_b, ok_a = int(b.success.sum()), int(a.success.sum())
    print(f"succeeded: before {ok_b}/{len(b)}, after {ok_a}/{len(a)}")
    changed = list(b.index[b.success != a.success])
    print(f"cases whose success changed: {changed or 'none'}")
    for col in [c for c in b.columns if c.endswith("_rel_err")]:
        d = np.abs(b[col].astype(float) - a[col].astype(float))
        print(f"largest change of {col}: {np.nanmax(d):.2g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    d = sub.add_parser("diagnose")
    d.add_argument("--out", type=Path, required=True)
    d.add_argument("--against", type=Path, default=None)
    d.add_argument("--compare-only", action="store_true")
    c = sub.add_parser("accuracy")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    f = sub.add_parser("fits")
    f.add_argument("before", type=Path)
    f.add_argument("after", type=Path)
    args = ap.parse_args()
    if args.what == "diagnose":
        diagnose_all(args.out, args.against, run=not args.compare_only)
    elif args.what == "accuracy":
        compare_accuracy(args.before, args.after)
    else:
        compare_fits(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
