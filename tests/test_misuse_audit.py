"""Issue 38, "no silent wrong answers": misuse a new user tries, as regression tests.

Each class is checked where it enters (one function each), so these tests go through
that entry from both sides where both exist: the Python API and the command line. A
refusal is one line on stderr naming the input and what to do, exit 2, nothing written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import ewb_ident as ei
from ewb_ident.cli import app
from ewb_ident.data.trace import COLUMNS, TraceError
from ewb_ident.data.writers import write_trace
from ewb_ident.rig.simulate import simulate_rig

runner = CliRunner()


@pytest.fixture(scope="module")
def simulated():
    """A 1 s, 200 Hz apply-hold-release of the synthetic rig, and its truth."""
    return simulate_rig(
        profile="steps",
        duration_s=1.0,
        t_start_s=0.05,
        t_apply_s=0.35,
        t_hold_s=0.2,
        t_release_s=0.3,
        seed=3,
    )


@pytest.fixture(scope="module")
def rig(tmp_path_factory, simulated) -> Path:
    """That trace written as a user's CSV with its sidecar."""
    return write_trace(simulated[0], tmp_path_factory.mktemp("rig") / "rig.csv")


@pytest.fixture(scope="module")
def rig_trace(rig):
    return ei.read_trace(rig)


def refused(result, out: Path | None = None) -> str:
    """The one line of a refusal (exit 2, nothing written)."""
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    if out is not None:
        assert not out.exists() or not any(out.iterdir())
    return lines[0]


# ----------------------------------------------------------------------- 1a. units

#: (column, the unit the values are logged in, the unit the mapping declares, what the
#: refusal says). Every channel, each way a factor of its unit family can go wrong.
WRONG_UNITS = [
    ("x_m", "m", "mm", r"stroke .* outside the plausible 1e-05 to 0\.01 m: looks like metres"),
    ("x_m", "mm", "um", r"stroke .* outside the plausible .*: looks like millimetres"),
    ("x_m", "mm", "m", r"\|x\| reaches .* outside the plausible .*: looks like millimetres"),
    ("theta_deg", "deg", "rad", r"lead of .* m/deg, outside the plausible 2\.5e-07 to 2\.5e-05"),
    ("theta_deg", "rad", "deg", r"\|theta\| stays below .*: looks like radians"),
    ("voltage_V", "V", "mV", r"peak \|V\| is 0\.004 V .* 0\.12 to 100 V: looks like volts"),
    ("voltage_V", "mV", "V", r"peak \|V\| is 4000 V, outside .*: looks like millivolts"),
    ("current_A", "A", "mA", r"peak \|i\| is .* plausible 0\.05 to 200 A: looks like amperes"),
    ("current_A", "mA", "A", r"peak \|i\| is .*: looks like milliamperes"),
    ("force_N", "N", "kN", r"peak \|F\| is .* plausible 0 to 50000 N: looks like newtons"),
    ("time_s", "s", "ms", r"sample rate 200000 Hz .*: looks like seconds"),
    ("time_s", "ms", "s", r"sample rate 0\.2 Hz .*: looks like milliseconds"),
    ("disc_speed_rad_s", "rpm", "rad/s", r"disc speed's peak .*: looks like revolutions per"),
]

#: The size of each unit in the column's own unit (theta_deg in degrees).
IN_COLUMN_UNIT = {
    "m": 1.0, "mm": 1e-3, "um": 1e-6, "deg": 1.0, "rad": 180.0 / math.pi, "V": 1.0,
    "mV": 1e-3, "A": 1.0, "mA": 1e-3, "N": 1.0, "kN": 1e3, "s": 1.0, "ms": 1e-3,
    "rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0,
}  # fmt: skip


def logged(rig: Path, folder: Path, column: str, unit: str, declared: str):
    """``rig`` with ``column`` logged in ``unit`` as 'src', and a mapping declaring it
    ``declared``."""
    df = pd.read_csv(rig)
    df[column] = df[column] / IN_COLUMN_UNIT[unit]
    path = folder / "logged.csv"
    df.rename(columns={column: "src"}).to_csv(path, index=False)
    side = json.loads(rig.with_suffix(".json").read_text())
    side.pop("sample_rate_hz")  # a sidecar's rate would be refused first for time_s
    path.with_suffix(".json").write_text(json.dumps(side))
    mapping = folder / "map.json"
    mapping.write_text(json.dumps({"src": {"column": column, "unit": declared}}))
    return path, mapping


@pytest.mark.parametrize(("column", "unit", "declared", "message"), WRONG_UNITS)
def test_a_wrong_declared_unit_is_refused_on_every_channel(
    rig, tmp_path, column, unit, declared, message
):
    path, mapping = logged(rig, tmp_path, column, unit, declared)
    with pytest.raises(TraceError, match=message) as err:
        ei.read_trace(path, mapping=mapping)
    text = str(err.value)
    assert f"column 'src' (mapped to '{column}')" in text
    assert f"the mapping declares 'src' in '{declared}'" in text
    if column != "theta_deg":  # the lead names the units of theta and x together
        assert f"is it '{unit}'?" in text


def test_a_wrong_declared_unit_is_refused_by_the_cli_and_nothing_is_written(rig, tmp_path):
    path, mapping = logged(rig, tmp_path, "x_m", "m", "mm")
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["fit", str(path), "--map", str(mapping), "--out", str(out)]))
    assert "the piston's stroke (max - min of x) is 2.7" in line, line
    assert "e-06 m (after conversion from 'mm'), outside the plausible 1e-05 to 0.01 m" in line
    assert "looks like metres ('m')" in line
    assert "--no-unit-check" in line and not out.exists()


def test_no_unit_check_is_the_escape_hatch(rig, tmp_path):
    path, mapping = logged(rig, tmp_path, "theta_deg", "deg", "rad")
    trace = ei.read_trace(path, mapping=mapping, check_units=False)
    assert trace["theta_deg"].max() > 20000.0


def test_a_torque_in_the_wrong_scale_is_refused_by_the_friction_it_implies(rig, tmp_path):
    df = pd.read_csv(rig)
    df["torque_Nm"] *= 1000.0  # N*mm
    path = tmp_path / "nmm.csv"
    df.to_csv(path, index=False)
    with pytest.raises(
        TraceError,
        match=r"column 'torque_Nm', row \d+: .* pad friction "
        r"coefficient T/\(2 F r_eff\) of 3\d\d(\.\d+)?, outside the plausible",
    ):
        ei.read_trace(path)


def test_a_force_in_kilonewtons_read_as_newtons_is_named(rig, tmp_path):
    path, mapping = logged(rig, tmp_path, "force_N", "kN", "N")
    with pytest.raises(
        TraceError,
        match=r"force never rises above 3\.\d+ N .* looks like "
        r"kilonewtons, 'kN'.*check that unit \(is it 'kN'\?\)",
    ):
        ei.read_trace(path, mapping=mapping, stages=["force"])


@pytest.mark.parametrize(
    ("pad_radius", "supply", "rate"), [(0.1, 12.0, 100.0), (0.3, 48.0, 1000.0)]
)
def test_other_rigs_pass_the_unit_checks(pad_radius, supply, rate):
    """Ranges from the physics, not from this project's rig: a small and a large pad
    radius, 12 and 48 V supplies, 100 Hz and 1 kHz."""
    from ewb_ident.data.validation import validate
    from ewb_ident.rig.params import RigParams

    trace, _ = simulate_rig(
        RigParams(r_eff_m=pad_radius),
        profile="position",
        sample_rate_hz=rate,
        duration_s=1.0,
        t_start_s=0.05,
        ramp_s=0.3,
        hold_s=0.3,
        v_max_V=supply,
    )
    validate(trace)


def test_the_shipped_datasets_pass_the_unit_checks():
    root = Path(__file__).parents[1] / "datasets"
    paths = sorted(root.glob("*.csv")) + sorted(root.glob("concealed/*.csv"))
    assert len(paths) >= 10
    for path in paths:
        ei.read_trace(path)


# ----------------------------------------------------------------------- 1b. repeats


def test_the_same_trace_twice_is_refused(rig, rig_trace, tmp_path):
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["fit", str(rig), str(rig), "--out", str(out)]), out)
    assert "trace 2 has the same samples as trace 1" in line and "give each recording once" in line
    copy = dataclasses.replace(rig_trace, name="copy", time_s=rig_trace.time_s + 10.0)
    with pytest.raises(TraceError, match="same samples"):
        ei.fit([rig_trace, copy], stage="force")


# ----------------------------------------------------------------------- 1c. the API


def _bad_traces(trace):
    t = trace.time_s
    nan_force = np.where(np.arange(trace.n) == 7, np.nan, trace["force_N"])
    return {
        "non-uniform": (
            dataclasses.replace(trace, time_s=t[0] + (t - t[0]) ** 1.3),
            r"column 'time_s', row 2: interval .* sampling is not uniform",
        ),
        "backwards": (
            dataclasses.replace(trace, time_s=t[::-1].copy()),
            r"column 'time_s', row 2: time goes from .* not strictly increasing",
        ),
        "nan": (
            dataclasses.replace(trace, channels={**trace.channels, "force_N": nan_force}),
            r"column 'force_N', row 8: empty cell",
        ),
    }


@pytest.mark.parametrize("case", ["non-uniform", "backwards", "nan"])
@pytest.mark.parametrize("function", ["fit", "sample", "diagnose"])
def test_the_api_checks_what_it_is_given_as_the_cli_does(rig_trace, case, function):
    trace, message = _bad_traces(rig_trace)[case]
    with pytest.raises(TraceError, match=message):
        getattr(ei, function)(trace)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"fixed": {"a": "x"}}, TypeError, r"fixed: a='x' is not a number; give its value"),
        ({"free": "a,b,c"}, TypeError, r"free: give a sequence .* free=\['a', 'b', 'c'\], not"),
        ({"per_trace": "c"}, TypeError, r"per_trace: give a sequence of parameter names"),
        ({"fixed": 3}, TypeError, r"fixed: give a dict of parameter names to values"),
    ],
)
def test_the_api_names_a_bad_option(rig_trace, kwargs, error, message):
    with pytest.raises(error, match=message):
        ei.fit(rig_trace, stage="force", **kwargs)
    with pytest.raises(error, match=message):
        ei.sample(rig_trace, stage="force", **kwargs)


@pytest.mark.parametrize("function", ["fit", "sample", "diagnose"])
def test_a_path_instead_of_a_trace_says_read_it_first(rig, function):
    argument = "trace" if function == "diagnose" else "traces"
    with pytest.raises(
        TypeError,
        match=rf"{argument}: got the path '.*rig\.csv', not a Trace; "
        r"read it first: ewb_ident\.read_trace",
    ):
        getattr(ei, function)(str(rig))


# ----------------------------------------------------------------------- 1d. --out


def test_an_earlier_runs_files_are_replaced_as_a_set(tmp_path):
    from ewb_ident.data.outputs import RUN_MANIFEST, write_run

    def writer(text):
        return lambda tmp: tmp.write_text(text)

    out = tmp_path / "out"
    write_run(out, "diagnose", [(out / "diagnosis.json", writer("{}")),
                                (out / "finding_1_backlash.png", writer("png"))])  # fmt: skip
    (out / "notes.txt").write_text("the user's own")
    write_run(out, "diagnose", [(out / "diagnosis.json", writer('{"verdict": "none"}'))])
    assert sorted(p.name for p in out.iterdir()) == [RUN_MANIFEST, "diagnosis.json", "notes.txt"]
    assert json.loads((out / RUN_MANIFEST).read_text())["files"] == ["diagnosis.json"]


def test_a_fit_into_an_earlier_diagnosis_folder_leaves_no_finding_behind(rig, tmp_path):
    from ewb_ident.data.outputs import write_run

    out = tmp_path / "out"
    write_run(out, "diagnose", [(out / "finding_1_backlash.png", lambda tmp: tmp.write_text("x"))])
    result = runner.invoke(app, ["fit", str(rig), "--stage", "force", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert not (out / "finding_1_backlash.png").exists() and (out / "fit.json").exists()


# ----------------------------------------------------------------------- 2. blame


@pytest.mark.parametrize("command", ["fit", "diagnose"])
@pytest.mark.parametrize("case", ["x in mm, --no-unit-check", "x reversed in time"])
def test_a_bad_start_value_blames_the_data_not_fix(rig, tmp_path, command, case):
    """x logged in mm and let through with --no-unit-check, or x reversed in time: the
    bell's start width is then metres; the message is about the data, never '--fix'
    (which was not given), and comes before any work (diagnose: no progress line)."""
    if case == "x reversed in time":  # (the short rig's apply and release look alike)
        source = Path(__file__).parents[1] / "datasets" / "steps_200hz.csv"
        df = pd.read_csv(source)
        df["x_m"] = df["x_m"].to_numpy()[::-1]
        options = []
    else:
        source = rig
        df = pd.read_csv(rig)
        df["x_m"] *= 1e3
        options = ["--no-unit-check"]
    path = tmp_path / "bad.csv"
    df.to_csv(path, index=False)
    path.with_suffix(".json").write_text(source.with_suffix(".json").read_text())
    out = tmp_path / "out"
    line = refused(runner.invoke(app, [command, str(path), *options, "--out", str(out)]), out)
    assert "--fix" not in line
    assert "the force stage's data (x_m and force_N) put the start value of a at" in line
    assert "check their units" in line and "that time runs forward" in line


# ----------------------------------------------------------------------- 3. tracebacks


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda tmp: "", r"--out is empty \(it would write into the current folder\)"),
        (lambda tmp: _dangling(tmp), r"a symbolic link to .*nowhere, which does not exist"),
        (lambda tmp: str(tmp / ("y" * 300)), r"--out: the name y{40}\.\.\. is longer than"),
        (lambda tmp: str(tmp / "/".join(["z" * 200] * 21)), r"the path is longer than 4096"),
    ],
)
def test_a_bad_out_is_one_line_before_any_work(rig, tmp_path, monkeypatch, make, message):
    monkeypatch.chdir(tmp_path)  # an empty --out would write here
    out = make(tmp_path)
    line = refused(runner.invoke(app, ["fit", str(rig), "--stage", "force", "--out", out]))
    assert re.search(message, line), line
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]


def _dangling(tmp: Path) -> str:
    link = tmp / "link"
    link.symlink_to(tmp / "nowhere")
    return str(link)


@pytest.fixture(scope="module")
def fit_json(rig, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fit") / "out"
    assert runner.invoke(app, ["fit", str(rig), "--out", str(out)]).exit_code == 0
    return out / "fit.json"


@pytest.mark.parametrize(("name", "value"), [("L", 0), ("R", -1), ("mu", 1.5)])
def test_a_parameters_file_outside_the_bounds_is_refused_by_every_command(
    rig, fit_json, tmp_path, name, value
):
    doc = json.loads(fit_json.read_text())
    doc["params"][name] = value
    bad = tmp_path / "fit.json"
    bad.write_text(json.dumps(doc))
    expected = f"{bad}: params.{name} is {value}, outside its bounds"
    out = tmp_path / "out"
    line = refused(
        runner.invoke(app, ["validate", str(rig), "--params", str(bad), "--out", str(out)]), out
    )
    assert expected in line
    sim = tmp_path / "sim.csv"
    line = refused(runner.invoke(app, ["simulate", str(sim), "--params", str(bad)]))
    assert expected in line and not sim.exists()
    from ewb_ident.inference.validate import ValidateError

    with pytest.raises(ValidateError, match=f"params.{name} is {value}"):
        ei.validate(ei.read_trace(rig), doc["params"])


def test_compare_with_a_channel_missing_on_one_side_names_it(rig, tmp_path):
    df = pd.read_csv(rig).drop(columns=["torque_Nm"])
    new = tmp_path / "new.csv"
    df.to_csv(new, index=False)
    out = tmp_path / "out"
    argv = ["compare", "--old", str(rig), "--new", str(new), "--out", str(out)]
    line = refused(runner.invoke(app, argv), out)
    assert "NEW records no torque_Nm where OLD does, so mu cannot be compared" in line


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--walkers", "2000000"], r"2000000 walkers in 2 ensembles .* need about [\d.e+]+ GB"),
        (["--ensembles", "5000", "--draws", "5000"], r"in 5000 ensembles .* use fewer --walkers"),
    ],
)
def test_sample_settings_that_cannot_fit_in_memory_are_refused(rig, tmp_path, options, message):
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["sample", str(rig), *options, "--out", str(out)]), out)
    assert re.search(message, line), line


def test_a_fit_the_machine_cannot_hold_is_refused_with_its_estimate(
    rig, rig_trace, tmp_path, monkeypatch
):
    """Was: the largest accepted trace (600,000 samples) fitted with an 8 GB peak, and a
    machine with less memory ended in an out-of-memory error."""
    import ewb_ident.inference.memory as memory
    from ewb_ident.inference.problem import FitError

    monkeypatch.setattr(memory, "physical_memory", lambda: 0.25e9)
    message = (
        r"a chain fit of \d+ samples needs about 0\.30\d GB, more than this machine's 0\.25 GB;"
        r" fit a shorter excerpt, or a teacher-forced stage \(--stage force needs about 0\.3"
    )
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["fit", str(rig), "--out", str(out)]), out)
    assert re.search(message, line), line
    with pytest.raises(FitError, match=message):
        ei.fit(rig_trace)


@pytest.mark.parametrize(
    ("samples", "stage", "peak_gb"),
    [(150_000, "chain", 2.23), (300_000, "chain", 4.16), (600_000, "chain", 8.11),
     (600_000, "force", 1.32), (600_000, "torque", 1.33)],
)  # fmt: skip
def test_the_fit_memory_estimate_covers_the_measured_peaks(samples, stage, peak_gb):
    """Peak resident memory of ``ewb-ident fit`` on a 1 kHz position trace: the
    estimate is above it, by at most a fifth."""
    from ewb_ident.inference.memory import fit_memory_bytes

    assert peak_gb <= fit_memory_bytes(samples, stage) / 1e9 <= 1.2 * peak_gb


def test_simulate_refuses_a_negative_seed(tmp_path):
    out = tmp_path / "t.csv"
    argv = ["simulate", str(out), "--seed", "-1", "--vary", "0.1"]
    line = refused(runner.invoke(app, argv))
    assert "--seed must be a non-negative whole number, got -1" in line and not out.exists()


STUDY = '[study]\nname = "s"\ntask = "fit"\n'


@pytest.mark.parametrize(
    ("text", "options", "message"),
    [
        (STUDY + "[rig]\nprofile = []\n", [], r"\[rig\] profile is an empty list"),
        (STUDY + "repeats = 1000000000\n", [], r"1,000,000,000 cases .* more than 10,000"),
        (STUDY + "[rig]\nprofile = 'zigzag'\n", [], r"\[rig\] profile 'zigzag' is unknown"),
        (STUDY + "[rig]\nsample_rate_hz = 'fast'\n", [], r"sample_rate_hz must be a number"),
        (STUDY + "[rig]\neffects = 'backlash'\n", [], r"effects must be a list of catalog"),
        (STUDY, ["--scheduler", "tcp://host"], r"--scheduler 'tcp://host' is not a scheduler"),
        (STUDY + "[task]\nspeed = 'fast'\n", [], r"\[task\] option 'speed' is unknown for task"),
    ],
)
def test_a_study_that_cannot_run_is_refused_whole_before_any_case(tmp_path, text, options, message):
    path = tmp_path / "s.toml"
    path.write_text(text)
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["study", str(path), "--out", str(out), *options]), out)
    assert re.search(message, line), line


def test_a_study_whose_cases_fail_exits_3(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(STUDY + "repeats = 2\n[rig]\nduration_s = 0.5\n[task]\nstage = 'nowhere'\n")
    out = tmp_path / "out"
    result = runner.invoke(app, ["study", str(path), "--out", str(out)])
    assert result.exit_code == 3, result.output
    assert "2 of 2 cases failed" in result.output
    assert (out / "results.csv").exists()


# ----------------------------------------------------------------------- 4. exit codes


def test_a_sidecar_key_given_twice_is_refused(rig, tmp_path):
    path = tmp_path / "dup.csv"
    path.write_text(rig.read_text())
    path.with_suffix(".json").write_text('{"r_eff_m": 0.15, "r_eff_m": 0.5}')
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["fit", str(path), "--out", str(out)]), out)
    assert "dup.json: key 'r_eff_m': the key is given twice" in line


def test_the_friction_check_uses_the_pad_radius_given_on_the_command_line(rig, tmp_path):
    """A sidecar with a wrong radius (0.02 m: a friction coefficient of 2.6) is refused;
    --r-eff 0.15 overrides it before the check, and the fit runs."""
    path = tmp_path / "r.csv"
    path.write_text(rig.read_text())
    path.with_suffix(".json").write_text(json.dumps({"r_eff_m": 0.02}))
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["fit", str(path), "--stage", "torque", "--out", str(out)]))
    assert "pad radius 0.02 m means a pad friction coefficient" in line
    argv = ["fit", str(path), "--stage", "torque", "--r-eff", "0.15", "--out", str(out)]
    assert runner.invoke(app, argv).exit_code == 0


@pytest.mark.parametrize("radius", [0.02, 0.5])
def test_sidecar_and_r_eff_share_one_range(rig, tmp_path, radius):
    path = tmp_path / "r.csv"
    path.write_text(rig.read_text())
    path.with_suffix(".json").write_text(json.dumps({"r_eff_m": radius}))
    # (A 0.02 m radius is refused by the friction its torque would imply: not a range.)
    assert ei.read_trace(path, check_units=False).r_eff_m == radius
    for too_far in (0.0199, 0.501):
        path.with_suffix(".json").write_text(json.dumps({"r_eff_m": too_far}))
        with pytest.raises(TraceError, match=r"is not a number from 0\.02 to 0\.5 m"):
            ei.read_trace(path)
        out = tmp_path / "out"
        argv = ["fit", str(rig), "--r-eff", str(too_far), "--out", str(out)]
        assert "--r-eff must be a pad radius from 0.02 to 0.5 m" in refused(
            runner.invoke(app, argv), out
        )


# ----------------------------------------------------------------------- 5. mutations


def test_percent_error_is_the_relative_l2_norm_of_the_residual():
    """By hand: measured (3, 4), simulated (4, 4): |e|_2 / |y|_2 = 1 / 5 = 20 % (the
    relative L1 norm would be 1 / 7 = 14.3 %); RMSE sqrt(1/2); NRMSE over the 1-wide
    span 70.7 %."""
    m = ei.channel_metrics([4.0, 4.0], [3.0, 4.0])
    assert m["percent_error"] == pytest.approx(20.0, rel=1e-12)
    assert m["rmse"] == pytest.approx(math.sqrt(0.5), rel=1e-12)
    assert m["nrmse_pct"] == pytest.approx(100.0 * math.sqrt(0.5), rel=1e-12)


def test_validate_is_at_the_noise_floor_within_one_and_a_half_sensor_noises(simulated):
    """The truth on its own trace misses by its sensor noise alone (ratio below 1); an
    offset of 1.2 sensor noises on the force keeps it within 1.5x, one of 2 noises
    (ratio ~2.2) does not, and the verdict says which channel."""
    from ewb_ident.data.metrics import sensor_noise
    from ewb_ident.model.params import MODEL_PARAMS

    trace, truth = simulated
    params = {k: truth["params"][k] for k in MODEL_PARAMS}
    sd = sensor_noise(trace["force_N"])

    def offset(k):
        force = trace["force_N"] + k * sd
        return ei.validate(
            dataclasses.replace(trace, channels={**trace.channels, "force_N": force}), params
        )

    near, far = offset(1.2), offset(2.0)
    assert near.at_noise_floor and near.verdict == "at_noise_floor"
    assert 1.2 < near.metrics["force_N"]["noise_ratio"] < 1.5
    assert not far.at_noise_floor and far.verdict == "passes_seed_acceptance"
    assert 1.5 < far.metrics["force_N"]["noise_ratio"] < 3.0
    assert far.words.startswith("force_N misses by 2.")


def test_a_flat_bell_is_a_poor_fit_even_within_the_seeds_acceptance():
    """Force alternating 2850/3150 N whatever x: the best bell is flat (b -> 0) at
    F_rt/2 = 3000 N, percent error 5 % (inside the seed's 10 %): still poor_fit."""
    from ewb_ident.data.readers import from_arrays

    n = 400
    rng = np.random.default_rng(0)
    force = 3000.0 + np.where(rng.random(n) < 0.5, -150.0, 150.0)
    trace = from_arrays(
        "flat", np.arange(n) / 200.0, x_m=np.linspace(-8e-4, 1.6e-3, n), force_N=force
    )
    result = ei.fit(trace, stage="force")
    assert result.values["b"] < 0.5
    assert result.metrics["force_N"]["percent_error"] < 10.0
    assert result.status == "poor_fit"
    assert any(w.startswith("the fitted bell is flat (b = ") for w in result.warnings)


# ----------------------------------------------------------------------- also seen


def test_an_empty_catalog_is_refused_not_run_whole(rig, rig_trace, tmp_path):
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["diagnose", str(rig), "--catalog", "", "--out", str(out)]))
    assert "catalog (--catalog) names no id" in line and not out.exists()
    with pytest.raises(TypeError, match=r"catalog: give a sequence of catalog ids"):
        ei.diagnose(rig_trace, catalog="backlash")


@pytest.mark.parametrize("suffix", [".parquet", ".mat"])
def test_parquet_and_mat_obey_the_csv_length_limit_before_loading(tmp_path, suffix):
    from ewb_ident.data.readers import MAX_SAMPLES

    n = MAX_SAMPLES + 1
    columns = {"time_s": np.arange(n) / 1000.0, "x_m": np.zeros(n)}
    path = tmp_path / f"long{suffix}"
    if suffix == ".parquet":
        pd.DataFrame(columns).to_parquet(path)
    else:
        import scipy.io

        scipy.io.savemat(path, columns)
    with pytest.raises(TraceError, match=r"too long: about 600,001 rows; a trace is at most"):
        ei.read_trace(path)


def _study_script(tmp_path: Path, body: str) -> Path:
    (tmp_path / "s.py").write_text(body)
    path = tmp_path / "s.toml"
    path.write_text('[study]\nname = "s"\nscript = "s.py"\n')
    return path


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            "def run(out, progress=None):\n    raise KeyError('lost')\n",
            r"s\.py:2: KeyError: 'lost'",
        ),
        ("def run(out, progress=None):\n    return 3\n", r"run\(\) returned int, not \(table"),
    ],
)
def test_a_study_scripts_own_error_is_one_line_and_exit_3(tmp_path, body, message):
    path = _study_script(tmp_path, body)
    result = runner.invoke(app, ["study", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 3, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and re.search(message, lines[0]), result.output


def test_a_study_script_linked_to_a_file_that_is_not_python_does_not_run(tmp_path):
    (tmp_path / "notes.txt").write_text("raise SystemExit('ran')\n")
    (tmp_path / "s.py").symlink_to(tmp_path / "notes.txt")
    (tmp_path / "s.toml").write_text('[study]\nname = "s"\nscript = "s.py"\n')
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["study", str(tmp_path / "s.toml"), "--out", str(out)]), out)
    assert "or not a .py file" in line


def test_a_study_script_linked_from_outside_its_folder_does_not_run(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "evil.py").write_text("raise SystemExit('ran')\n")
    study = tmp_path / "study"
    study.mkdir()
    (study / "s.py").symlink_to(elsewhere / "evil.py")
    (study / "s.toml").write_text('[study]\nname = "s"\nscript = "s.py"\n')
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["study", str(study / "s.toml"), "--out", str(out)]), out)
    assert "is a link to" in line and "outside the study file's own folder" in line


def test_a_full_disk_is_one_line_and_leaves_nothing(rig, tmp_path, monkeypatch):
    import errno

    import ewb_ident.data.outputs as outputs

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(outputs.os, "fsync", full)
    out = tmp_path / "out"
    line = refused(runner.invoke(app, ["fit", str(rig), "--stage", "force", "--out", str(out)]))
    assert "cannot write the results (No space left on device)" in line
    assert not out.exists()
    sim = tmp_path / "sim" / "t.csv"
    line = refused(runner.invoke(app, ["simulate", str(sim)]))
    assert "No space left on device" in line and not sim.parent.exists()


# ----------------------------------------------------------------------- the corpus


def _corpus():
    from benchmarks import misuse_corpus

    return misuse_corpus


def _run_corpus_case(tmp_path: Path, k: int) -> None:
    _, argv, expected = _corpus().cases(tmp_path)[k]
    before = set(tmp_path.rglob("*"))
    result = runner.invoke(app, argv)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert result.exit_code == expected, result.output
    if expected == 2:
        assert not [p for p in set(tmp_path.rglob("*")) - before if p.is_file()]


def test_the_whole_misuse_corpus_behaves(tmp_path_factory):
    """Every case of benchmarks/misuse_corpus.py, old and new, in the default suite: the
    expected exit code, no traceback, nothing written when refused."""
    names = [c[0] for c in _corpus().cases(tmp_path_factory.mktemp("names"))]
    assert len(names) >= 62
    for k in range(len(names)):
        _run_corpus_case(tmp_path_factory.mktemp("case"), k)


# ----------------------------------------------------------------------- properties

#: Examples per property: 25 for the readers in the default suite, 6 to 12 for the
#: properties that run whole commands (fit, sample, diagnose; about 40 s together);
#: with EWB_MISUSE_PROFILE=slow, 500 and 60 to 120 (about 10 min):
#: ``EWB_MISUSE_PROFILE=slow python -m pytest tests/test_misuse_audit.py -k any_``.
settings.register_profile(
    "misuse",
    max_examples=25,
    deadline=None,
    database=None,  # nothing written into the checkout
    derandomize=True,  # the same examples on every run of the default suite
    suppress_health_check=[HealthCheck.too_slow],
)
# The slow profile explores: new random examples on each run.
settings.register_profile(
    "misuse-slow", settings.get_profile("misuse"), max_examples=500, derandomize=False
)
SLOW_PROFILE = settings.get_profile("misuse-slow")
PROFILE = SLOW_PROFILE if os.environ.get("EWB_MISUSE_PROFILE") == "slow" else \
    settings.get_profile("misuse")  # fmt: skip

CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64).map(repr),
    st.integers(-(10**6), 10**6).map(str),
    st.sampled_from(["", "nan", "n/a", "1,5", "1e400", " 3 ", "true", "0x10", "-"]),
)
NAMES = st.sampled_from([*COLUMNS, "t", "angle", "lvdt", "junk", "", "time_s"])
SIDECARS = st.dictionaries(
    st.sampled_from(["r_eff_m", "sample_rate_hz", "disc_mode", "disc_inertia_kg_m2", "x"]),
    st.one_of(
        st.floats(allow_nan=False, width=64),
        st.integers(),
        st.text(max_size=5),
        st.none(),
        st.booleans(),
    ),  # fmt: skip
    max_size=4,
)
MAPPINGS = st.one_of(
    st.none(),
    st.dictionaries(
        st.sampled_from(["t", "angle", "lvdt", "junk", "x_m"]),
        st.one_of(
            st.sampled_from(list(COLUMNS)),
            st.fixed_dictionaries(
                {
                    "column": st.sampled_from(list(COLUMNS)),
                    "unit": st.sampled_from(["mm", "m", "rad", "deg", "ms", "kN", "inch", "V"]),
                }
            ),  # fmt: skip
        ),
        max_size=3,
    ),
)


def _one_line_trace_error(call) -> None:
    """``call()`` returns, or raises a TraceError of one line; nothing else."""
    try:
        call()
    except TraceError as err:
        assert "\n" not in str(err) and str(err).strip(), repr(err)


@PROFILE
@given(
    names=st.lists(NAMES, min_size=1, max_size=5),
    rows=st.lists(st.lists(CELLS, min_size=5, max_size=5), max_size=80),
    sidecar=st.one_of(st.none(), SIDECARS),
    mapping=MAPPINGS,
    check_units=st.booleans(),
)
def test_any_table_is_read_or_refused_in_one_line(names, rows, sidecar, mapping, check_units):
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "t.csv"
        lines = [",".join(names), *(",".join(r[: len(names)]) for r in rows)]
        path.write_text("\n".join(lines) + "\n")
        if sidecar is not None:
            path.with_suffix(".json").write_text(json.dumps(sidecar))
        _one_line_trace_error(lambda: ei.read_trace(path, mapping=mapping, check_units=check_units))


#: Each channel times every factor between two units of its family (length 1e3 and
#: 1e6, angle 57.3, voltage, current and force 1e3, torque N*mm and kN*m, disc speed
#: rpm as rad/s): the rig's trace so scaled is refused naming the column. (A disc speed
#: a tenth of the true one is a slower disc, not a wrong unit: not in the list.)
UNIT_FACTORS = [
    *[("x_m", k) for k in (1e-6, 1e-3, 1e3, 1e6)],
    *[("theta_deg", k) for k in (math.pi / 180.0, 180.0 / math.pi)],
    *[(c, k) for c in ("voltage_V", "current_A", "force_N", "torque_Nm") for k in (1e-3, 1e3)],
    ("disc_speed_rad_s", 60.0 / (2.0 * math.pi)),
]


@pytest.mark.parametrize(("column", "factor"), UNIT_FACTORS)
def test_every_channel_scaled_by_a_unit_factor_is_refused(rig_trace, column, factor):
    from ewb_ident.data.validation import validate

    scaled = {**rig_trace.channels, column: rig_trace[column] * factor}
    trace = dataclasses.replace(rig_trace, channels=scaled)
    with pytest.raises(TraceError) as err:
        validate(trace, stages=("chain",))
    text = str(err.value)
    assert "\n" not in text
    named = {column}
    if column in ("force_N", "torque_Nm") and factor < 1.0:
        named |= {"force_N", "torque_Nm"}  # the friction they imply, or no clamping
    if column in ("x_m", "theta_deg"):
        named |= {"theta_deg"}  # the gap's lead names the pinion angle
    assert any(f"column '{c}'" in text for c in named), text


def examples(default: int, slow: int) -> settings:
    """The property profile with ``default`` examples (``slow`` with
    EWB_MISUSE_PROFILE=slow): the commands' properties run whole commands."""
    return settings(PROFILE, max_examples=slow if PROFILE is SLOW_PROFILE else default)


#: Output folders: mostly a good one, so that the other inputs decide.
OUTS = st.sampled_from(["out", "out", "out", "", "a/../out", "x" * 300])


def _result_or_one_line(argv: list[str], out: str, result_file: str) -> int:
    """Run ``ewb-ident ARGV --out OUT`` (``out`` relative to a fresh folder; "" is
    given as "") and check the invariant: exit 0 or 3 with OUT/RESULT_FILE, or exit 2
    with one line and nothing written; never a traceback. Returns the exit code."""
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        target = str(Path(folder) / out) if out else ""
        argv = [*argv, "--out", target]
        result = runner.invoke(app, argv)
        assert result.exception is None or isinstance(result.exception, SystemExit), (
            argv,
            result.output,
        )
        assert result.exit_code in (0, 2, 3), (argv, result.output)
        event(f"exit {result.exit_code}")  # (pytest --hypothesis-show-statistics)
        if result.exit_code == 2:
            lines = [line for line in result.output.splitlines() if line.strip()]
            assert len(lines) == 1 or "Usage:" in result.output, result.output
            assert not [p for p in Path(folder).rglob("*") if p.is_file()], argv
        else:
            assert (Path(target) / result_file).is_file(), argv
        return result.exit_code


@examples(12, 120)
@given(
    stage=st.sampled_from(["force", "torque", "gap", "brake"]),
    fix=st.one_of(st.none(), st.sampled_from(["a=1e-3", "mu=2", "R=x", "b", "F_rt=nan", "Z=1"])),
    free=st.one_of(st.none(), st.sampled_from(["a,b", "mu", "a,,", "kb", ""])),
    r_eff=st.one_of(st.none(), st.sampled_from(["0.15", "0.5", "0.51", "-1", "nan", "x"])),
    out=OUTS,
)
def test_any_fit_options_give_a_result_or_one_line(rig, stage, fix, free, r_eff, out):
    """Random option sets on the short trace: exit 0 or 3 with fit.json, or exit 2 with
    one line and nothing written; never a traceback."""
    argv = ["fit", str(rig), "--stage", stage]
    for option, value in (("--fix", fix), ("--free", free), ("--r-eff", r_eff)):
        if value is not None:
            argv += [option, value]
    _result_or_one_line(argv, out, "fit.json")


@pytest.fixture(scope="module")
def inputs(rig, tmp_path_factory) -> dict[str, str]:
    """Files the commands' properties pass: traces (the rig's, without torque, too
    short, with an empty cell, x in mm, none), priors files and mappings."""
    folder = tmp_path_factory.mktemp("inputs")
    df = pd.read_csv(rig)
    side = rig.with_suffix(".json").read_text()
    traces = {
        "rig": df,
        "no_torque": df.drop(columns=["torque_Nm"]),
        "short": df.head(12),
        "empty_cell": df.astype({"force_N": object}).assign(
            force_N=lambda d: d["force_N"].where(d.index != 40, "")
        ),
        "x_in_mm": df.assign(x_m=df["x_m"] * 1e3),
    }
    out = {"missing": str(folder / "missing.csv")}
    for name, frame in traces.items():
        frame.to_csv(folder / f"{name}.csv", index=False)
        (folder / f"{name}.json").write_text(side)
        out[name] = str(folder / f"{name}.csv")
    for name, text in {
        "priors_ok": '[a]\ndist = "lognormal"\nmedian = 7e-4\nsigma_log = 1.0\nlower = 1e-6\n',
        "priors_unknown": '[Z]\ndist = "normal"\nmean = 1\nsd = 1\n',
        "priors_family": '[a]\ndist = "cauchy"\nloc = 1\n',
        "priors_keys": '[mu]\ndist = "normal"\nmean = 0.3\n',
        "priors_bad_toml": "[a\ndist = ",
        "priors_bounds": '[a]\ndist = "uniform"\nlower = 1\nupper = 0\n',
    }.items():
        (folder / f"{name}.toml").write_text(text)
        out[name] = str(folder / f"{name}.toml")
    for name, doc in {
        "map_ok": {"force_N": {"column": "force_N", "unit": "N"}},
        "map_kn": {"force_N": {"column": "force_N", "unit": "kN"}},
        "map_unknown": {"force_N": {"column": "brake_force", "unit": "N"}},
    }.items():
        (folder / f"{name}.json").write_text(json.dumps(doc))
        out[name] = str(folder / f"{name}.json")
    out["map_missing"] = str(folder / "nomap.json")
    return out


#: An option's value that is no value: the option is a flag.
FLAG = "<flag>"


def _options(most: int = 3, **choices) -> st.SearchStrategy[list[str]]:
    """Up to ``most`` of the options, each at one of its values, as a flat argv (few at
    a time, so that some option sets are accepted and run); a value "@name" is the file
    ``inputs[name]`` (:func:`_resolved`)."""

    def argv(option: str) -> st.SearchStrategy[list[str]]:
        return st.sampled_from(choices[option]).map(
            lambda v: [option] if v == FLAG else [option, v]
        )

    names = st.lists(st.sampled_from(sorted(choices)), max_size=most, unique=True)
    return names.flatmap(
        lambda picked: st.tuples(*map(argv, picked)).map(
            lambda parts: [a for part in parts for a in part]
        )
    )


def _resolved(argv: list[str], inputs: dict[str, str]) -> list[str]:
    return [inputs[a[1:]] if a.startswith("@") else a for a in argv]


#: Traces: half the time the rig's as recorded, so that the options decide.
TRACES = st.sampled_from(["rig"] * 5 + ["no_torque", "short", "empty_cell", "x_in_mm", "missing"])
#: ``sample``: a run that is accepted stays tiny (the force or torque stage, 8 walkers
#: for 30 steps, 5 draws): every other value of an option that sets its size is one
#: to refuse.
SAMPLE_BASE = ["--stage", "force", "--walkers", "8", "--steps", "30", "--max-steps", "30",
               "--draws", "5", "--min-ess", "5", "--no-progress"]  # fmt: skip


@examples(6, 60)
@given(
    trace=TRACES,
    options=_options(
        **{
            "--stage": ["torque", "brake", "", "force,torque", "chain,force"],
            "--free": ["a,b", "mu", "a,,", "kb", "", "Z"],
            "--per-trace": ["c", "x", ""],
            "--fix": ["a=1e-3", "mu=2", "R=x", "b", "F_rt=nan"],
            "--noise": ["white", "ar1", "pink", ""],
            "--steps": ["0", "-1", "x", "20"],
            "--max-steps": ["0", "10", "-5"],
            "--walkers": ["0", "3", "7", "-8", "2000000", "x"],
            "--ensembles": ["1", "0", "5000", "x"],
            "--min-ess": ["-1", "nan", "inf", "0"],
            "--hdi-prob": ["0.5", "0", "1", "1.5", "nan"],
            "--draws": ["0", "-1", "x", "10"],
            "--seed": ["-1", "7", "x", "1e3"],
            "--integrator": ["heun", "rk4", ""],
            "--with": ["gremlins", "backlash", "sensor_delay", "sensor_offset[force_N]"],
            "--with-diagnosis": ["@missing", "@map_ok"],
            "--priors": [
                "@priors_ok",
                "@priors_unknown",
                "@priors_family",
                "@priors_keys",
                "@priors_bad_toml",
                "@priors_bounds",
                "@missing",
            ],
            "--r-eff": ["0.15", "0.51", "nan", "x"],
        }
    ),  # fmt: skip
    out=OUTS,
)
def test_any_sample_options_give_a_result_or_one_line(inputs, trace, options, out):
    """``sample`` with random option sets, priors files and traces: exit 0 or 3 with
    summary.json, or exit 2 with one line and nothing written; never a traceback."""
    argv = ["sample", inputs[trace], *SAMPLE_BASE, *_resolved(options, inputs)]
    _result_or_one_line(argv, out, "summary.json")


@examples(10, 60)
@given(
    trace=TRACES,
    options=_options(
        **{
            "--catalog": [
                "backlash",
                "sensor_offset,stiction",
                "",
                "gremlins",
                "backlash,,",
                "sensor_delay[force_N]",
                "sensor_delay[nope]",
                "BACKLASH",
            ],
            "--bic-threshold": ["10", "0", "-1", "nan", "inf", "x", "1e9"],
            "--figures": [FLAG],
            "--map": ["@map_ok", "@map_kn", "@map_unknown", "@map_missing"],
            "--r-eff": ["0.15", "0.51", "nan", "x"],
            "--fill-gaps": [FLAG],
            "--no-unit-check": [FLAG],
        }
    ),  # fmt: skip
    out=OUTS,
)
def test_any_diagnose_options_give_a_result_or_one_line(inputs, trace, options, out):
    """``diagnose`` with random option sets, mappings and traces: exit 0 or 3 with
    diagnosis.json, or exit 2 with one line and nothing written; never a traceback."""
    argv = ["diagnose", inputs[trace], "--no-figures", *_resolved(options, inputs)]
    _result_or_one_line(argv, out, "diagnosis.json")


def test_every_error_the_tool_raises_derives_from_one_base():
    """``EWBIdentError`` is the base of every public error class of the package; the
    errors of input stay ``ValueError``\\ s (``InputError``), the study runner's stay
    ``RuntimeError``\\ s."""
    import ast
    import importlib

    root = Path(ei.__file__).parent
    found = []
    for path in sorted(root.rglob("*.py")):
        module = ".".join(path.relative_to(root.parent).with_suffix("").parts)
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.ClassDef) and node.name.endswith("Error"):
                if not node.name.startswith("_"):
                    found.append(getattr(importlib.import_module(module), node.name))
    assert len(found) >= 13, found
    assert [c for c in found if not issubclass(c, ei.EWBIdentError)] == []
    inputs = [c for c in found if issubclass(c, ei.InputError)]
    assert len(inputs) >= 11 and all(issubclass(c, ValueError) for c in inputs)
    others = [c for c in found if c not in inputs and c is not ei.EWBIdentError]
    assert {c.__name__ for c in others} == {"ScriptError", "ClusterError"}
    assert all(issubclass(c, RuntimeError) for c in others)
