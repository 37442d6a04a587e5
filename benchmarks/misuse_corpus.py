# ruff: noqa: E501 - the corpus is a table, one case a line
"""Misuse corpus: bad files, bad options, impossible requests, each through the CLI.

    python -m benchmarks.misuse_corpus [--out reports/misuse.md]

Every case runs one ``ewb-ident`` command in this process (Typer's CliRunner, the same
code path as the installed script after its entry point) in a fresh temporary folder,
and is scored by: its exit code against the expected one (2: refused before any work,
3: done but untrustworthy), its first line of output, whether a Python traceback
escaped, and which files it left behind. A case passes when the exit code is the
expected one, no traceback escaped, and a refused run wrote nothing. The table is
printed and written to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import stat
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from typer.testing import CliRunner  # noqa: E402

from ewb_ident.cli import app  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "datasets"
STEPS = DATA / "steps_200hz.csv"


def _copy(tmp: Path, name: str = "t", edit: Callable[[list[str]], list[str]] | None = None):
    lines = STEPS.read_text().splitlines()
    if edit:
        lines = edit(lines)
    path = tmp / f"{name}.csv"
    path.write_text("\n".join(lines) + "\n")
    (tmp / f"{name}.json").write_text((DATA / "steps_200hz.json").read_text())
    return path


def _drop(col: str):
    def edit(lines):
        head = lines[0].split(",")
        j = head.index(col)
        return [",".join(c for k, c in enumerate(r.split(",")) if k != j) for r in lines]

    return edit


def _cell(row: int, col: str, value: str):
    def edit(lines):
        j = lines[0].split(",").index(col)
        cells = lines[row].split(",")
        cells[j] = value
        lines[row] = ",".join(cells)
        return lines

    return edit


def _scale(col: str, k: float, from_row: int = 1):
    def edit(lines):
        j = lines[0].split(",").index(col)
        out = lines[:from_row]
        for r in lines[from_row:]:
            cells = r.split(",")
            cells[j] = repr(float(cells[j]) * k)
            out.append(",".join(cells))
        return out

    return edit


def _reverse(col: str):
    def edit(lines):
        rows = [r.split(",") for r in lines]
        j = rows[0].index(col)
        for row, value in zip(rows[1:], [r[j] for r in rows[1:]][::-1], strict=True):
            row[j] = value
        return [",".join(r) for r in rows]

    return edit


def cases(tmp: Path) -> list[tuple[str, list[str], int]]:
    """(name, argv, expected exit code); files are made under ``tmp``."""
    o = str(tmp / "out")
    ro = tmp / "readonly"
    ro.mkdir()
    os.chmod(ro, stat.S_IRUSR | stat.S_IXUSR)
    (tmp / "afile").write_text("x")
    (tmp / "bad.toml").write_text("study = 5\n")
    (tmp / "evil.toml").write_text('[study]\nscript = "/etc/passwd.py"\n')
    t = str(_copy(tmp))
    issue38 = _issue38_files(tmp)
    return [
        ("fit: time runs backwards", ["fit", str(_copy(tmp, "back", _cell(10, "time_s", "0.0"))), "--out", o], 2),
        ("fit: empty cell", ["fit", str(_copy(tmp, "empty", _cell(20, "force_N", ""))), "--out", o], 2),
        ("fit: x logged in mm", ["fit", str(_copy(tmp, "mm", _scale("x_m", 1e3))), "--out", o], 2),
        ("fit: theta in radians", ["fit", str(_copy(tmp, "rad", _scale("theta_deg", 3.14159 / 180))), "--out", o], 2),
        ("fit: no such file", ["fit", str(tmp / "nope.csv"), "--out", o], 2),
        ("fit: --fix unknown name", ["fit", t, "--fix", "Z=1", "--out", o], 2),
        ("fit: --fix typo r", ["fit", t, "--fix", "r=1.1", "--out", o], 2),
        ("fit: --fix F_rt=nan", ["fit", t, "--fix", "F_rt=nan", "--out", o], 2),
        ("fit: --fix F_rt=-3500", ["fit", t, "--fix", "F_rt=-3500", "--out", o], 2),
        ("fit: --fix and --free same name", ["fit", t, "--stage", "force", "--free", "a,b", "--fix", "a=0.001", "--out", o], 2),
        ("fit: unknown stage", ["fit", t, "--stage", "brake", "--out", o], 2),
        ("fit: --out is a file", ["fit", t, "--out", str(tmp / "afile")], 2),
        ("fit: --out below a file", ["fit", t, "--out", str(tmp / "afile" / "o")], 2),
        ("fit: --out read-only (root writes anyway)", ["fit", t, "--out", str(ro / "o")], 0 if os.geteuid() == 0 else 2),
        ("fit: --r-eff 15", ["fit", t, "--r-eff", "15", "--out", o], 2),
        ("fit: force halved after 1.5 s (poor fit)", ["fit", str(_copy(tmp, "half", _scale("force_N", 0.5, from_row=301))), "--out", o], 3),
        ("fit: Heun at the seed's step", ["fit", str(DATA / "seed_steps_100hz.csv"), "--stage", "motor", "--integrator", "heun", "--out", o], 3),
        ("fit: without force_N", ["fit", str(_copy(tmp, "noF", _drop("force_N"))), "--out", o], 0),
        ("fit: without current_A", ["fit", str(_copy(tmp, "noI", _drop("current_A"))), "--out", o], 0),
        ("fit: --with unknown", ["fit", t, "--with", "gremlins", "--out", o], 2),
        ("fit: --with sensor_delay (no channel)", ["fit", t, "--with", "sensor_delay", "--out", o], 2),
        ("sample: --walkers 0", ["sample", t, "--walkers", "0", "--out", o], 2),
        ("sample: --ensembles 1", ["sample", t, "--ensembles", "1", "--out", o], 2),
        ("simulate: --vary 5", ["simulate", str(tmp / "s.csv"), "--vary", "5"], 2),
        ("simulate: --duration 1e6", ["simulate", str(tmp / "s.csv"), "--duration", "1e6"], 2),
        ("simulate: path below a file", ["simulate", str(tmp / "afile" / "s.csv")], 2),
        ("simulate: unknown effect", ["simulate", str(tmp / "s.csv"), "--effect", "gremlins"], 2),
        ("study: study = 5", ["study", str(tmp / "bad.toml"), "--out", o], 2),
        ("study: script outside its folder", ["study", str(tmp / "evil.toml"), "--out", o], 2),
        ("study: a folder", ["study", str(tmp), "--out", o], 2),
        ("validate: no fit.json", ["validate", t, "--params", str(tmp / "none.json"), "--out", o], 2),
        ("diagnose: --out is a file", ["diagnose", t, "--out", str(tmp / "afile")], 2),
        ("report: --out below a file", ["report", t, "--out", str(tmp / "afile" / "o")], 2),
        ("compare: missing --new", ["compare", "--old", t, "--out", o], 2),
        ("unknown command", ["dance"], 2),
        # Issue 38: a fresh audit's cases (tests/test_misuse_audit.py holds their messages).
        ("fit: x in m, mapping declares mm", ["fit", issue38["x_in_m"], "--map", issue38["map_mm"], "--out", o], 2),
        ("fit: theta in deg, mapping declares rad", ["fit", issue38["theta_in_deg"], "--map", issue38["map_rad"], "--out", o], 2),
        ("fit: x in mm with --no-unit-check", ["fit", str(_copy(tmp, "mm2", _scale("x_m", 1e3))), "--no-unit-check", "--out", o], 2),
        ("fit: the same trace twice", ["fit", t, t, "--out", o], 2),
        ("fit: --out ''", ["fit", t, "--out", ""], 2),
        ("fit: --out a dangling link", ["fit", t, "--out", issue38["dangling"]], 2),
        ("fit: --out a 300-character name", ["fit", t, "--out", str(tmp / ("y" * 300))], 2),
        ("fit: sidecar r_eff_m given twice", ["fit", issue38["dup_key"], "--out", o], 2),
        ("validate: fit.json with L = 0", ["validate", t, "--params", issue38["fit_L0"], "--out", o], 2),
        ("validate: fit.json with R = -1", ["validate", t, "--params", issue38["fit_Rneg"], "--out", o], 2),
        ("simulate: --params with L = 0", ["simulate", str(tmp / "s.csv"), "--params", issue38["fit_L0"]], 2),
        ("simulate: --seed -1", ["simulate", str(tmp / "s.csv"), "--seed", "-1", "--vary", "0.1"], 2),
        ("compare: NEW without torque_Nm", ["compare", "--old", t, "--new", str(_copy(tmp, "noT", _drop("torque_Nm"))), "--out", o], 2),
        ("sample: --walkers 2000000", ["sample", t, "--walkers", "2000000", "--out", o], 2),
        ("sample: --ensembles 5000 --draws 5000", ["sample", t, "--ensembles", "5000", "--draws", "5000", "--out", o], 2),
        ("diagnose: --catalog ''", ["diagnose", t, "--catalog", "", "--out", o], 2),
        ("study: an empty [rig] list", ["study", issue38["empty_rig"], "--out", o], 2),
        ("study: repeats = 1000000000", ["study", issue38["huge"], "--out", o], 2),
        ("study: effects as a string", ["study", issue38["effects_str"], "--out", o], 2),
        ("study: unknown [task] option", ["study", issue38["task_opt"], "--out", o], 2),
        ("study: --scheduler malformed", ["study", issue38["empty_rig"], "--scheduler", "tcp://host", "--out", o], 2),
        ("study: a script that raises", ["study", issue38["raises"], "--out", o], 3),
        ("fit: x_m reversed in time", ["fit", issue38["x_reversed"], "--out", o], 2),
        ("diagnose: x_m reversed in time", ["diagnose", issue38["x_reversed"], "--out", o], 2),
        ("diagnose: x in mm with --no-unit-check", ["diagnose", str(_copy(tmp, "mm3", _scale("x_m", 1e3))), "--no-unit-check", "--out", o], 2),
        ("fit: sidecar r_eff_m 0.5 (as --r-eff 0.5)", ["fit", issue38["r_eff_half"], "--stage", "torque", "--out", o], 0),
        ("study: every case fails", ["study", issue38["all_fail"], "--out", o], 3),
    ]  # fmt: skip


def _issue38_files(tmp: Path) -> dict[str, str]:
    """The files issue 38's cases read: wrongly declared units, a duplicate sidecar key,
    parameters files outside the bounds, study definitions."""
    import json

    out: dict[str, str] = {}
    lines = STEPS.read_text().splitlines()
    for name, column, source in (("x_in_m", "x_m", "lvdt"), ("theta_in_deg", "theta_deg", "pot")):
        path = tmp / f"{name}.csv"
        path.write_text("\n".join([lines[0].replace(column, source), *lines[1:]]) + "\n")
        out[name] = str(path)
    (tmp / "map_mm.json").write_text(json.dumps({"lvdt": {"column": "x_m", "unit": "mm"}}))
    (tmp / "map_rad.json").write_text(json.dumps({"pot": {"column": "theta_deg", "unit": "rad"}}))
    out["map_mm"], out["map_rad"] = str(tmp / "map_mm.json"), str(tmp / "map_rad.json")
    dup = _copy(tmp, "dup")
    dup.with_suffix(".json").write_text('{"r_eff_m": 0.15, "r_eff_m": 0.5}')
    out["dup_key"] = str(dup)
    (tmp / "link").symlink_to(tmp / "nowhere")
    out["dangling"] = str(tmp / "link")
    truth = json.loads((DATA / "steps_200hz.truth.json").read_text())["params"]
    for name, key, value in (("fit_L0", "L", 0.0), ("fit_Rneg", "R", -1.0)):
        (tmp / f"{name}.json").write_text(json.dumps({"params": truth | {key: value}}))
        out[name] = str(tmp / f"{name}.json")
    head = '[study]\nname = "s"\ntask = "fit"\n'
    for name, text in (
        ("empty_rig", head + "[rig]\nprofile = []\n"),
        ("huge", head + "repeats = 1000000000\n"),
        ("effects_str", head + "[rig]\neffects = 'backlash'\n"),
        ("task_opt", head + "[task]\nspeed = 'fast'\n"),
        ("raises", '[study]\nname = "s"\nscript = "raises.py"\n'),
    ):
        (tmp / f"{name}.toml").write_text(text)
        out[name] = str(tmp / f"{name}.toml")
    (tmp / "raises.py").write_text("def run(out, progress=None):\n    raise KeyError('lost')\n")
    (tmp / "all_fail.toml").write_text(
        head + "repeats = 2\n[rig]\nduration_s = 0.5\n[task]\nstage = 'nowhere'\n"
    )
    out["all_fail"] = str(tmp / "all_fail.toml")
    out["x_reversed"] = str(_copy(tmp, "x_reversed", _reverse("x_m")))
    half = _copy(tmp, "r_half")
    half.with_suffix(".json").write_text(
        json.dumps(json.loads(half.with_suffix(".json").read_text()) | {"r_eff_m": 0.5})
    )
    out["r_eff_half"] = str(half)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "misuse.md")
    args = ap.parse_args()
    runner = CliRunner()
    rows = []
    with tempfile.TemporaryDirectory() as base:
        names = [c[0] for c in cases(Path(tempfile.mkdtemp(dir=base)))]
        for k, name in enumerate(names):
            tmp = Path(tempfile.mkdtemp(dir=base))
            _, argv, expected = cases(tmp)[k]
            before = {p for p in tmp.rglob("*")}
            res = runner.invoke(app, argv)
            after = {p for p in tmp.rglob("*") if p.is_file()} - before
            tb = res.exception is not None and not isinstance(res.exception, SystemExit)
            first = (res.output.strip().splitlines() or [""])[0][:110]
            wrote = sorted(str(p.relative_to(tmp)) for p in after)
            ok = res.exit_code == expected and not tb and (expected != 2 or not wrote)
            rows.append((name, expected, res.exit_code, tb, wrote, first, ok))
            print(f"{'ok  ' if ok else 'FAIL'} {res.exit_code} (want {expected}) {name}: {first}")
            os.chmod(tmp / "readonly", stat.S_IRWXU)
    lines = [
        "# Misuse corpus",
        "",
        "Command: `python -m benchmarks.misuse_corpus`",
        "",
        f"**{sum(r[-1] for r in rows)}/{len(rows)} cases behave** (expected exit code, no "
        f"traceback, nothing written when refused); tracebacks: {sum(r[3] for r in rows)}.",
        "",
        "| case | expected | exit | traceback | files written | first line |",
        "|---|---|---|---|---|---|",
    ]
    for name, exp, code, tb, wrote, first, _ in rows:
        w = ", ".join(wrote) if wrote else "-"
        lines.append(
            f"| {name} | {exp} | {code} | {'yes' if tb else 'no'} | {w} | "
            f"{first.replace('|', '/')} |"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    sys.exit(0 if all(r[-1] for r in rows) else 1)


if __name__ == "__main__":
    main()
