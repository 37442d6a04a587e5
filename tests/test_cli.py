"""The command line: contract files, readable summaries, exit code 2 on bad input."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ewb_ident.cli import app

DATA = Path(__file__).parents[1] / "datasets"
runner = CliRunner()


def test_help_explains_every_command():
    out = runner.invoke(app, ["--help"])
    assert out.exit_code == 0
    import re

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    documented = set(re.findall(r"^ewb-ident (\w+)", readme, flags=re.M))
    assert {"fit", "sample", "diagnose", "report", "validate", "compare"} <= documented
    for command in sorted(documented | {"simulate", "study"}):
        assert command in out.output
        sub = runner.invoke(app, [command, "--help"])
        assert sub.exit_code == 0 and "Usage" in sub.output


def test_version_answers_fast_without_jax():
    code = "import sys, ewb_ident.cli as c; print('jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"  # the CLI module imports no JAX before a command
    assert "ewb-ident" in runner.invoke(app, ["--version"]).output


def test_diagnose_imports_no_scipy_stats_or_signal():
    """About 1 s of import at every diagnose: its modules compute what they need of
    them (ewb_ident.diagnosis.filters)."""
    code = (
        "import sys, ewb_ident.diagnosis.diagnose, ewb_ident.reporting.figures; "
        "print([m for m in ('scipy.stats', 'scipy.signal') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_fit_writes_the_contract_and_a_summary(tmp_path):
    out = runner.invoke(app, ["fit", str(DATA / "staircase_200hz.csv"), "--out", str(tmp_path)])
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert {"params", "stderr", "metrics", "converged"} <= set(doc)
    assert doc["converged"] is True
    assert "force_N" in doc["metrics"] and "seed %" in out.output and "NRMSE" in out.output


def test_stage_and_fixed_options(tmp_path):
    args = ["fit", str(DATA / "staircase_200hz.csv"), "--out", str(tmp_path), "--stage"]
    out = runner.invoke(app, [*args, "force", "--free", "a,c", "--fix", "b=2.7,F_rt=3630"])
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["free"] == ["a", "c"] and doc["params"]["b"] == 2.7


def _bad_trace(tmp_path: Path) -> Path:
    src = (DATA / "staircase_200hz.csv").read_text().splitlines()
    src[10], src[11] = src[11], src[10]  # rows 10 and 11 swapped: time goes backwards
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(src) + "\n")
    return bad


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--stage", "brake"], "unknown stage 'brake'"),
        (["--free", "mu", "--stage", "force"], "parameter 'mu' is not fitted by stage 'force'"),
        (["--fix", "b"], "--fix takes NAME=VALUE"),
        (["--integrator", "euler"], "--integrator must be exponential or heun"),
    ],
)
def test_bad_options_exit_2_and_write_nothing(tmp_path, args, message):
    out_dir = tmp_path / "out"
    out = runner.invoke(
        app, ["fit", str(DATA / "staircase_200hz.csv"), "--out", str(out_dir), *args]
    )
    assert out.exit_code == 2
    assert message in out.output
    assert not (out_dir / "fit.json").exists()


def test_bad_trace_gives_one_line_exit_2_and_no_output(tmp_path):
    out_dir = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "ewb_ident",
            "fit",
            str(_bad_trace(tmp_path)),
            "--out",
            str(out_dir),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert "bad.csv: column 'time_s', row 11" in lines[0]
    assert not out_dir.exists() or not any(out_dir.iterdir())


def test_a_thread_count_that_is_not_a_number_exits_2_before_any_work(tmp_path):
    out_dir = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "ewb_ident", "diagnose", str(DATA / "concealed" / "stiction.csv"),
         "--out", str(out_dir)],
        capture_output=True, text=True,
        env=dict(os.environ, EWB_IDENT_THREADS="all"),
    )  # fmt: skip
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == (
        "error: EWB_IDENT_THREADS='all' is not a whole number; set it to the number of "
        "threads to use (1: none besides the calling thread), or unset it"
    )
    assert not out_dir.exists()


def test_the_command_exits_with_its_code_after_its_output_and_exit_callbacks(tmp_path):
    """``main`` ends the process without the interpreter's teardown: the output must be
    complete and flushed, the ``atexit`` callbacks (``--verbose``'s summary) run, and
    the exit code the command's, in a first run and in one that reads the disk cache."""
    for run in ("first", "second"):
        out_dir = tmp_path / run
        proc = subprocess.run(
            [sys.executable, "-m", "ewb_ident", "--verbose", "fit",
             str(DATA / "staircase_200hz.csv"), "--stage", "force", "--out", str(out_dir)],
            capture_output=True, text=True,
            env=dict(os.environ, EWB_IDENT_CACHE=str(tmp_path / "cache")),
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.rstrip().endswith(f"wrote {out_dir / 'fit.json'}")
        assert json.loads((out_dir / "fit.json").read_text())["converged"] is True
        stats = proc.stderr.strip().splitlines()[-1]
        assert stats.startswith("compiled programs:")
        # One program (the fit's), compiled in the first run and read from disk in the
        # second; each of the solver's further steps reuses it in memory.
        calls, reused, memory, disk = map(
            int,
            re.search(r"(\d+) calls, (\d+) reused \((\d+) in memory, (\d+) from", stats).groups(),
        )
        assert (disk, reused, memory) == (
            {"first": 0, "second": 1}[run],
            calls - 1 + disk,
            calls - 1,
        ), stats
    proc = subprocess.run(
        [sys.executable, "-m", "ewb_ident", "fit", str(DATA / "staircase_200hz.csv"),
         "--stage", "brake", "--out", str(tmp_path / "bad")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 2 and "unknown stage 'brake'" in proc.stderr


def test_missing_file_is_a_clear_error(tmp_path):
    out = runner.invoke(app, ["fit", str(tmp_path / "nope.csv"), "--out", str(tmp_path / "o")])
    assert out.exit_code == 2 and "nope.csv" in out.output


def test_simulate_writes_trace_and_truth_that_fit_reads(tmp_path):
    target = tmp_path / "syn.csv"
    out = runner.invoke(app, ["simulate", str(target), "--profile", "position", "--rate", "500"])
    assert out.exit_code == 0, out.output
    truth = json.loads((tmp_path / "syn.truth.json").read_text())
    assert truth["sample_rate_hz"] == 500.0 and truth["params"]["b"] == 2.82
    again = tmp_path / "again.csv"
    runner.invoke(app, ["simulate", str(again), "--profile", "position", "--rate", "500"])
    assert target.read_text() == again.read_text()  # same seed, same numbers


def test_simulate_refuses_unknown_effect(tmp_path):
    out = runner.invoke(app, ["simulate", str(tmp_path / "x.csv"), "--effect", "gremlins"])
    assert out.exit_code == 2 and "unknown effect 'gremlins'" in out.output
    assert not (tmp_path / "x.csv").exists()


def test_a_semicolon_decimal_comma_csv_is_read_and_said_once(tmp_path):
    """An Excel export from much of Europe is read (not refused), and the command says
    once how it read it."""
    lines = (DATA / "steps_200hz.csv").read_text().splitlines()
    eu = [lines[0].replace(",", ";")]
    eu += [";".join(c.replace(".", ",") for c in line.split(",")) for line in lines[1:]]
    (tmp_path / "eu.csv").write_text("\n".join(eu) + "\n")
    out = runner.invoke(app, ["fit", str(tmp_path / "eu.csv"), "--out", str(tmp_path / "f")])
    assert out.exit_code == 0, out.output
    assert out.output.count("read as ';'-separated, decimal comma") == 1
    ref = runner.invoke(app, ["fit", str(DATA / "steps_200hz.csv"), "--out", str(tmp_path / "g")])
    assert ref.exit_code == 0
    a = json.loads((tmp_path / "f" / "fit.json").read_text())["params"]
    b = json.loads((tmp_path / "g" / "fit.json").read_text())["params"]
    assert a == b


def test_help_shows_flags_plainly_and_keeps_sentences_whole():
    """A flag takes no value, so its help shows no type ("<bool>"); a command's
    description is reflowed to the terminal, not broken where its docstring's lines end."""
    env = {"COLUMNS": "100", "NO_COLOR": "1"}
    commands = [c.name or c.callback.__name__ for c in app.registered_commands]
    for args in ([], *([c] for c in commands)):
        res = runner.invoke(app, [*args, "--help"], env=env)
        assert res.exit_code == 0, args
        assert "<bool>" not in res.output, args
    text = runner.invoke(app, ["--help"], env=env).output
    words = " ".join(w for line in text.splitlines() for w in line.strip("│ ").split())
    # sample's docstring breaks its line after "OUT/summary.json,": the help does not.
    assert "OUT/summary.json, OUT/posterior.nc (ArviZ)" in words
    assert "\n│           OUT/summary.json," not in text
