"""Regression tests for issue 9 (every rig's recordings) and the misuse bugs of issue 11
that this work touched: each bug named in the issue, once, by what it does."""

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ewb_ident.cli import app
from ewb_ident.data.readers import read_trace
from ewb_ident.data.trace import Trace
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.problem import FitError

DATA = Path(__file__).parents[1] / "datasets"
runner = CliRunner()


def _without(tmp_path: Path, name: str, columns: list[str]) -> Path:
    """A copy of a shipped trace (and its sidecar) with some columns removed."""
    src = DATA / f"{name}.csv"
    if not src.exists():
        src = DATA / "concealed" / f"{name}.csv"
    df = pd.read_csv(src).drop(columns=columns)
    out = tmp_path / f"{name}_no_{'_'.join(c.split('_')[0] for c in columns)}.csv"
    df.to_csv(out, index=False)
    out.with_suffix(".json").write_text(src.with_suffix(".json").read_text())
    return out


def test_fit_without_force_fits_what_is_recorded(tmp_path):
    """Was: LinAlgError traceback. Now the bell is fitted through the torque, mu held."""
    path = _without(tmp_path, "steps_200hz", ["force_N"])
    out = runner.invoke(app, ["fit", str(path), "--out", str(tmp_path / "o")])
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "o" / "fit.json").read_text())
    assert "mu" not in doc["free"] and {"a", "b", "c", "F_rt"} <= set(doc["free"])
    assert any("no force_N" in w for w in doc["warnings"])
    truth = json.loads((DATA / "steps_200hz.truth.json").read_text())["params"]
    # mu F_rt is what the torque determines.
    product = doc["params"]["mu"] * doc["params"]["F_rt"]
    assert abs(product / (truth["mu"] * truth["F_rt"]) - 1) < 0.02


def test_multi_trace_per_trace_from_the_cli(tmp_path):
    """Was: LinAlgError unless theta0_deg was listed by hand. The start angle is always
    per trace; --per-trace adds to it."""
    out = runner.invoke(
        app,
        [
            "fit",
            str(DATA / "steps_200hz.csv"),
            str(DATA / "staircase_200hz.csv"),
            "--per-trace",
            "c,p0",
            "--out",
            str(tmp_path),
        ],
    )
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["per_trace_params"] == ["theta0_deg", "p0", "c"]
    assert doc["converged"] is True
    assert [set(p["params"]) for p in doc["per_trace"]] == [{"theta0_deg", "p0", "c"}] * 2


def test_fix_is_honoured_for_default_free_parameters(tmp_path):
    """Was: --fix silently ignored for parameters that are free by default."""
    out = runner.invoke(
        app,
        [
            "fit",
            str(DATA / "steps_200hz.csv"),
            "--stage",
            "motor",
            "--fix",
            "R=1.1,L=0.002",
            "--out",
            str(tmp_path),
        ],
    )
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["params"]["R"] == 1.1 and doc["params"]["L"] == 0.002
    assert "R" not in doc["free"] and "L" not in doc["free"]


@pytest.mark.parametrize(
    ("fix", "message"),
    [
        ("Z=1", "unknown parameter 'Z'"),
        ("r=1.1", "did you mean 'R'"),
        ("F_rt=nan", "outside its bounds"),
        ("F_rt=-3500", "outside its bounds"),
        ("F_rt=inf", "outside its bounds"),
    ],
)
def test_bad_fix_is_refused_before_work(tmp_path, fix, message):
    out = runner.invoke(
        app, ["fit", str(DATA / "steps_200hz.csv"), "--fix", fix, "--out", str(tmp_path / "o")]
    )
    assert out.exit_code == 2 and message in out.output, out.output
    assert not (tmp_path / "o").exists()


def test_fixed_and_free_at_once_is_refused():
    trace = read_trace(DATA / "steps_200hz.csv")
    with pytest.raises(FitError, match="both fixed"):
        fit(trace, stage="force", free=["a", "b"], fixed={"a": 1e-3})


def test_a_null_direction_never_reaches_the_solver():
    """Without current, kb and v trade off exactly: asked to fit both, one is held."""
    trace = read_trace(DATA / "steps_200hz.csv")
    trace = Trace(
        name=trace.name,
        time_s=trace.time_s,
        channels={k: v for k, v in trace.channels.items() if k != "current_A"},
        sidecar=trace.sidecar,
    )
    result = fit(trace, stage="motor", free=["kb", "M", "v", "theta0_deg"])
    assert len(set(result.free) & {"kb", "v"}) == 1
    assert any("cannot tell" in w for w in result.warnings)
    assert result.converged


def test_a_poor_fit_says_so_and_exits_3(tmp_path):
    """Was: torque doubled after the fit's own model -> converged: true, exit 0."""
    df = pd.read_csv(DATA / "steps_200hz.csv")
    half = len(df) // 2
    df.loc[half:, "force_N"] *= 0.5  # force halved after mid-trace: no model fits this
    path = tmp_path / "halved.csv"
    df.to_csv(path, index=False)
    path.with_suffix(".json").write_text((DATA / "steps_200hz.json").read_text())
    out = runner.invoke(app, ["fit", str(path), "--out", str(tmp_path / "o")])
    assert out.exit_code == 3, out.output
    doc = json.loads((tmp_path / "o" / "fit.json").read_text())
    assert doc["status"] == "poor_fit" and doc["acceptable"] is False
    assert any("outside the seed paper's acceptance" in w for w in doc["warnings"])
    assert "POOR FIT" in out.output


def test_a_fit_that_does_not_converge_exits_3(tmp_path):
    """One solver step cannot converge: converged false in fit.json, exit code 3."""
    trace = read_trace(DATA / "steps_200hz.csv")
    result = fit(trace, stage="force", max_steps=1)
    assert not result.converged and result.status == "not_converged"
    assert any("did not converge" in w for w in result.warnings)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["simulate", "{tmp}/t.csv", "--vary", "5"], "--vary is a relative spread"),
        (["simulate", "{tmp}/t.csv", "--duration", "1e6"], "--duration must be within"),
        (["fit", "{data}/steps_200hz.csv", "--out", "{tmp}/file.txt"], "is not a folder"),
        (["validate", "{data}/steps_200hz.csv", "--params", "{tmp}/none.json", "--out", "{tmp}/v"],
         "cannot read it as fit.json"),
    ],
)  # fmt: skip
def test_bad_options_are_refused_before_work(tmp_path, args, message):
    (tmp_path / "file.txt").write_text("x")
    argv = [a.format(tmp=tmp_path, data=DATA) for a in args]
    out = runner.invoke(app, argv)
    assert out.exit_code == 2 and message in out.output, out.output
    assert not (tmp_path / "t.csv").exists() and not (tmp_path / "v").exists()


def test_validate_on_another_trace_of_the_same_unit_and_of_another_unit(tmp_path):
    """Fitted on one trace, checked on a second trace of the same unit (passes at the
    noise floor) and on a trace of a different unit (the mismatch is reported)."""
    runner.invoke(app, ["fit", str(DATA / "steps_200hz.csv"), "--out", str(tmp_path / "f")])
    params = tmp_path / "f" / "fit.json"
    same = runner.invoke(
        app,
        ["validate", str(DATA / "staircase_200hz.csv"), "--params", str(params), "--out",
         str(tmp_path / "same")],
    )  # fmt: skip
    assert same.exit_code == 0, same.output
    doc = json.loads((tmp_path / "same" / "validate.json").read_text())
    assert doc["verdict"] == "at_noise_floor", doc["summary"]
    assert (tmp_path / "same" / "validate.png").stat().st_size > 10_000
    other = runner.invoke(
        app,
        ["validate", str(DATA / "seed_steps_100hz.csv"), "--params", str(params), "--out",
         str(tmp_path / "other")],
    )  # fmt: skip
    doc = json.loads((tmp_path / "other" / "validate.json").read_text())
    assert doc["verdict"] != "at_noise_floor"
    worst = max(doc["metrics"].values(), key=lambda m: m["noise_ratio"])
    assert worst["noise_ratio"] > 3
    assert other.exit_code in (0, 3)


def test_compare_is_a_command(tmp_path):
    out = runner.invoke(app, ["compare", "--help"])
    assert out.exit_code == 0 and "--old" in out.output and "--new" in out.output


def test_diagnose_without_current(tmp_path):
    """Was: KeyError 'current_A' (metrics and the chain figure) on every trace without a
    current sensor. Also: the diagnosis reports its progress step by step."""
    from ewb_ident.diagnosis.diagnose import diagnose
    from ewb_ident.reporting.figures import write_diagnosis

    path = _without(tmp_path, "clean_steps", ["current_A"])
    steps: list[str] = []
    result = diagnose(read_trace(path), progress=steps.append)
    paths = write_diagnosis(result, tmp_path / "d", figures=True)
    doc = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    assert doc["verdict"] == "none", doc["mismatches"]
    assert "current_A" not in doc["baseline"]["metrics"]
    assert {"a", "b", "c", "mu"} <= set(doc["baseline"]["params"])
    assert np.isfinite(doc["baseline"]["params"]["a"])
    assert any(p.name == "chain.png" for p in paths)
    assert steps[0] == "baseline fits of every stage"


def test_unstable_heun_says_so_and_exits_3(tmp_path):
    """Was: ValueError traceback (non-finite metrics) and an empty --out."""
    out = runner.invoke(
        app,
        [
            "fit",
            str(DATA / "seed_steps_100hz.csv"),
            "--stage",
            "motor",
            "--integrator",
            "heun",
            "--out",
            str(tmp_path),
        ],
    )
    assert out.exit_code == 3, out.output
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["converged"] is False
    assert any("Heun" in w and "unstable" in w for w in doc["warnings"])


def test_a_sidecar_nested_too_deep_and_a_table_too_long_are_refused_early(tmp_path):
    deep = tmp_path / "deep.csv"
    deep.write_text((DATA / "steps_200hz.csv").read_text())
    deep.with_suffix(".json").write_text("[" * 100_000 + "]" * 100_000)
    out = runner.invoke(app, ["fit", str(deep), "--out", str(tmp_path / "o")])
    assert out.exit_code == 2 and "nested too deeply" in out.output
    big = tmp_path / "big.csv"
    with open(big, "w") as handle:
        handle.write("time_s,voltage_V\n")
        handle.write("".join(f"{k / 1000:.3f},0\n" for k in range(600_010)))
    out = runner.invoke(app, ["fit", str(big), "--out", str(tmp_path / "o")])
    assert out.exit_code == 2 and "too long" in out.output
    assert not (tmp_path / "o").exists()


def test_report_figures_survive_a_long_trace_name(tmp_path):
    """Was: 'File name too long' for a legal 249-character trace name."""
    from ewb_ident.reporting.html import build_report, write_report

    trace = read_trace(DATA / "staircase_200hz.csv")
    long = Trace(
        name="x" * 249, time_s=trace.time_s, channels=trace.channels, sidecar=trace.sidecar
    )
    result = fit(long, stage="force")
    page, figures = build_report([long], result)
    assert all(len(name) < 80 for name in figures)
    write_report(tmp_path, page, figures)
    assert (tmp_path / "index.html").exists()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("study = 5\n", "must be a [study] table"),
        ('[study]\nseed = "abc"\n', "seed must be a non-negative whole number"),
        ('[study]\nscript = "/etc/passwd.py"\n', "in the study file's own folder"),
        ('[study]\nscript = "../evil.py"\n', "in the study file's own folder"),
    ],
)
def test_bad_study_files_are_refused(tmp_path, text, message):
    path = tmp_path / "s.toml"
    path.write_text(text)
    out = runner.invoke(app, ["study", str(path), "--out", str(tmp_path / "o")])
    assert out.exit_code == 2 and message in out.output, out.output
    out = runner.invoke(app, ["study", str(tmp_path), "--out", str(tmp_path / "o")])
    assert out.exit_code == 2 and "is a folder" in out.output
    path.write_bytes(b"\xff\xfe\x00bad")
    out = runner.invoke(app, ["study", str(path), "--out", str(tmp_path / "o")])
    assert out.exit_code == 2 and "not a UTF-8" in out.output


@pytest.mark.parametrize(("sig", "code"), [("SIGINT", 130), ("SIGTERM", 143)])
def test_an_interrupt_ends_the_run_with_its_code_and_no_files(tmp_path, sig, code):
    """Was: a SIGINT swallowed by a JAX callback (the fit finished, exit 0, fit.json
    written), and SIGTERM leaving temporary files behind."""
    import shutil
    import signal
    import subprocess
    import time

    exe = shutil.which("ewb-ident")
    assert exe is not None
    out = tmp_path / "o"
    # A posterior without the on-disk compilation cache (a fit now ends in about 3 s, a
    # signal that lands while the interpreter shuts down, when CPython has restored the
    # default handlers, kills the process instead of testing the handler).
    proc = subprocess.Popen(
        [exe, "sample", str(DATA / "steps_200hz.csv"), "--out", str(out), "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=os.environ | {"EWB_IDENT_CACHE": ""},
    )
    time.sleep(4.0)  # inside imports, compilation, the fit or the sampling
    proc.send_signal(getattr(signal, sig))
    proc.communicate(timeout=60)
    assert proc.returncode == code
    assert not out.exists() or not any(out.iterdir())


def test_the_shipped_mapping_example_reads_a_renamed_log(tmp_path):
    """The README's column-mapping format, by its example file."""
    df = pd.read_csv(DATA / "steps_200hz.csv")
    log = pd.DataFrame(
        {
            "Zeit": df["time_s"] * 1e3,
            "Spannung": df["voltage_V"],
            "Strom": df["current_A"] * 1e3,
            "Winkel": np.radians(df["theta_deg"]),
            "Kolbenweg": df["x_m"] * 1e3,
            "Spannkraft": df["force_N"] / 1e3,
            "Bremsmoment": df["torque_Nm"],
        }
    )
    path = tmp_path / "log.csv"
    log.to_csv(path, index=False)
    trace = read_trace(path, mapping=DATA / "mapping_example.toml")
    ref = read_trace(DATA / "steps_200hz.csv")
    for col in ("time_s", "voltage_V", "current_A", "theta_deg", "x_m", "force_N", "torque_Nm"):
        assert np.allclose(trace[col], ref[col], rtol=1e-9, atol=1e-12), col


def test_r_eff_from_the_command_line_is_used_and_recorded(tmp_path):
    """Was: r_eff silently 0.15 m for every file without a sidecar."""
    path = tmp_path / "nosidecar.csv"
    path.write_text((DATA / "steps_200hz.csv").read_text())
    args = ["fit", str(path), "--stage", "torque"]
    out = runner.invoke(app, [*args, "--out", str(tmp_path / "a")])
    doc_a = json.loads((tmp_path / "a" / "fit.json").read_text())
    assert doc_a["r_eff_m"]["nosidecar"] == {"value": 0.15, "source": "default"}
    assert any("r_eff = 0.15 m (the seed's default)" in w for w in doc_a["warnings"])
    out = runner.invoke(app, [*args, "--r-eff", "0.2", "--out", str(tmp_path / "b")])
    assert out.exit_code == 0, out.output
    doc_b = json.loads((tmp_path / "b" / "fit.json").read_text())
    assert doc_b["r_eff_m"]["nosidecar"] == {"value": 0.2, "source": "--r-eff"}
    # mu scales with 1/r_eff
    assert abs(doc_b["params"]["mu"] * 0.2 / (doc_a["params"]["mu"] * 0.15) - 1) < 1e-6
    out = runner.invoke(app, [*args, "--r-eff", "15", "--out", str(tmp_path / "c")])
    assert out.exit_code == 2 and "--r-eff must be" in out.output


def test_zero_walkers_is_refused_not_replaced(tmp_path):
    """Was: --walkers 0 silently became 32."""
    out = runner.invoke(
        app,
        ["sample", str(DATA / "steps_200hz.csv"), "--walkers", "0", "--out", str(tmp_path / "o")],
    )
    assert out.exit_code == 2 and "--walkers must be an even integer >= 4, got 0" in out.output
    assert not (tmp_path / "o").exists()
