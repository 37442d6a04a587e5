"""``ewb-ident batch`` over a small campaign of synthetic recordings, and
``simulate --set``.

The campaign: two hardware versions of a rig (units varied by 1 %), the second with the
bell's centre c moved by a planted +50 um (``simulate --set``); one trace of the first
without a current sensor; one broken file. Truth comes from each trace's truth.json.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ewb_ident.cli import app
from ewb_ident.inference.population import group_change, random_effects, two_level

runner = CliRunner()
C_DEFAULT = 9.57e-4
C_PLANTED = C_DEFAULT + 5.0e-5
CONTRACT = ["parameter", "unit", "estimate", "stderr", "low_90", "high_90", "interval_from",
            "converged", "status", "verdict", "findings"]
#: Parameters whose truth is the simulated value whatever the unit (the motor's M and v
#: are identified as M/kT and v/kT with kT held, so their truth depends on it).
CHECKED = ("p2", "p1", "p0", "F_rt", "a", "b", "c", "mu")


def _simulate(path: Path, seed: int, *extra: str) -> None:
    args = ["simulate", str(path), "--duration", "2.2", "--seed", str(seed), "--vary", "0.01"]
    got = runner.invoke(app, [*args, *extra])
    assert got.exit_code == 0, got.output


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """The campaign's folder, with manifest.csv (path, hardware, unit, date)."""
    root = tmp_path_factory.mktemp("campaign")
    rows = []
    for k, seed in enumerate((1, 2, 3)):
        _simulate(root / f"v1_{k}.csv", seed)
        rows.append(("v1", f"U{k}", f"2026-03-0{k + 1}", f"v1_{k}.csv"))
    for k, seed in enumerate((11, 12)):
        _simulate(root / f"v2_{k}.csv", seed, "--set", f"c={C_PLANTED!r}")
        rows.append(("v2", f"U{k}", f"2026-04-0{k + 1}", f"v2_{k}.csv"))
    lean = root / "v1_2.csv"  # no current sensor on this one
    pd.read_csv(lean).drop(columns=["current_A"]).to_csv(lean, index=False)
    (root / "broken.csv").write_text("time_s,voltage_V\n0,1\n0.005,2\nabc,3\n")
    rows.append(("v1", "U9", "2026-03-09", "broken.csv"))
    manifest = pd.DataFrame(rows, columns=["hardware", "unit", "date", "path"])
    manifest.to_csv(root / "manifest.csv", index=False)
    return root


@pytest.fixture(scope="module")
def first_run(campaign, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out"
    args = ["batch", str(campaign / "manifest.csv"), "--out", str(out), "--group-by", "hardware"]
    return runner.invoke(app, args), out, args


def _truth(campaign: Path, trace: str) -> dict[str, float]:
    return json.loads((campaign / trace).with_suffix(".truth.json").read_text())["params"]


def test_table_columns_errors_and_exit_code(campaign, first_run):
    got, out, _ = first_run
    assert got.exit_code == 3, got.output
    assert "1 of 6 traces not trustworthy: 1 failed" in got.stdout
    assert "0 reused, 6 fitted" in got.stdout
    table = pd.read_parquet(out / "results.parquet")
    # trace, the manifest's metadata ('unit' renamed: the table's unit is the parameter's)
    assert list(table.columns[:4]) == ["trace", "hardware", "meta_unit", "date"]
    assert list(table.columns[4:15]) == CONTRACT
    assert {"force_N_nrmse_pct", "current_A_nrmse_pct", "message"} <= set(table.columns)
    csv = pd.read_csv(out / "results.csv")
    assert list(csv.columns) == list(table.columns)
    np.testing.assert_allclose(csv["estimate"], table["estimate"], rtol=1e-12)
    broken = table[table["trace"] == "broken.csv"]
    assert len(broken) == 1 and broken["status"].iloc[0] == "error"
    assert "column 'time_s', row 3" in broken["message"].iloc[0]
    assert "\n" not in broken["message"].iloc[0]
    ok = table[table["trace"] != "broken.csv"]
    assert (ok["status"] == "ok").all() and ok["converged"].all()
    assert (ok["interval_from"] == "stderr").all()
    # not diagnosed, not sampled: no verdict, no findings, only the fit's rows
    assert table["verdict"].isna().all() and table["findings"].isna().all()
    assert (table["model"] == "baseline").all() and table["posterior_converged"].isna().all()
    # without current, the effective L, kb, M (and the held R, v) have no rows
    lean = set(ok.loc[ok["trace"] == "v1_2.csv", "parameter"])
    assert not lean & {"R", "L", "kb", "M", "v"} and {"a", "b", "c", "mu"} <= lean
    assert ok.loc[ok["trace"] == "v1_2.csv", "current_A_nrmse_pct"].isna().all()
    page = (out / "index.html").read_text()
    assert "broken.csv" in page and "parameters.png" in page and (out / "parameters.png").exists()
    doc = json.loads((out / "batch.json").read_text())
    assert doc["where"] == {"kind": "in-process", "address": None, "workers": 1}
    assert len(doc["inputs"]) == 6 and all(len(i["sha256"]) == 64 for i in doc["inputs"])


def test_per_trace_intervals_hold_the_truth(campaign, first_run):
    _, out, _ = first_run
    table = pd.read_parquet(out / "results.parquet")
    rows = table[table["parameter"].isin(CHECKED)]
    truth = np.array([_truth(campaign, t)[p] for t, p in zip(rows["trace"], rows["parameter"],
                                                             strict=True)])
    held = (rows["low_90"].to_numpy() <= truth) & (truth <= rows["high_90"].to_numpy())
    assert len(rows) == 5 * len(CHECKED)
    assert held.mean() >= 0.75, rows.loc[~held, ["trace", "parameter"]]
    c = rows[rows["parameter"] == "c"]
    assert held[(rows["parameter"] == "c").to_numpy()].all(), c


def test_the_planted_change_is_found(campaign, first_run):
    got, out, _ = first_run
    changes = pd.read_csv(out / "changes.csv")
    c = changes.set_index("parameter").loc["c"]
    assert (c["before"], c["after"], c["n_before"], c["n_after"]) == ("v1", "v2", 3, 2)
    true = [np.mean([_truth(campaign, f"{g}_{k}.csv")["c"] for k in ks])
            for g, ks in (("v1", (0, 1, 2)), ("v2", (0, 1)))]
    assert bool(c["changed"]) and c["low_90"] <= true[1] - true[0] <= c["high_90"]
    others = changes[changes["parameter"].isin(["a", "b", "mu", "F_rt"])]
    assert not others["changed"].any(), others
    assert "changed: c v1 -> v2" in got.stdout
    pop = pd.read_csv(out / "population.csv")
    assert {"all", "v1", "v2"} == set(pop["group"])
    row = pop[(pop["group"] == "all") & (pop["parameter"] == "c")].iloc[0]
    assert row["n_traces"] == 5 and row["tau_low_90"] <= row["tau"] <= row["tau_high_90"]
    # the manifest's unit column: U0 and U1 have a trace of each version, U2 one
    assert row["unit_column"] == "meta_unit" and row["n_units"] == 3
    assert row["tau_unit_low_90"] <= row["tau_unit"] <= row["tau_unit_high_90"]
    assert row["tau_trace_low_90"] <= row["tau_trace"] <= row["tau_trace_high_90"]


def test_a_rerun_resumes_without_fitting(campaign, first_run, tmp_path):
    _, out, args = first_run
    before = pd.read_parquet(out / "results.parquet")
    again = runner.invoke(app, args)
    assert again.exit_code == 3
    assert "6 reused, 0 fitted" in again.stdout
    pd.testing.assert_frame_equal(pd.read_parquet(out / "results.parquet"), before)
    # the same campaign as a Parquet manifest: the same traces, nothing to fit
    manifest = pd.read_csv(campaign / "manifest.csv")
    manifest.to_parquet(campaign / "manifest.parquet")
    same = runner.invoke(app, ["batch", str(campaign / "manifest.parquet"), "--out", str(out)])
    assert same.exit_code == 3 and "6 reused, 0 fitted" in same.stdout
    # a per-row pad radius is a new setting for that trace only: it alone is refitted
    manifest["r_eff_m"] = [0.16, None, None, None, None, None]
    manifest.to_csv(campaign / "radius.csv", index=False)
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    one = runner.invoke(app, ["batch", str(campaign / "radius.csv"), "--out", str(copy)])
    assert one.exit_code == 3 and "5 reused, 1 fitted" in one.stdout
    table = pd.read_parquet(copy / "results.parquet").set_index("trace")
    assert (table.loc["v1_0.csv", "r_eff_m"] == 0.16).all()
    assert (table.loc["v1_1.csv", "r_eff_m"] == 0.15).all()


def test_a_dask_cluster_of_processes_gives_the_same_table(campaign, first_run, tmp_path):
    from distributed import LocalCluster

    _, out, _ = first_run
    remote = tmp_path / "remote"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:
        got = runner.invoke(app, ["batch", str(campaign / "manifest.csv"), "--out", str(remote),
                                  "--group-by", "hardware", "--scheduler",
                                  cluster.scheduler_address])
    assert got.exit_code == 3, got.output
    assert f"on the Dask cluster at {cluster.scheduler_address} with 1 worker" in got.stdout
    pd.testing.assert_frame_equal(pd.read_parquet(remote / "results.parquet"),
                                  pd.read_parquet(out / "results.parquet"), rtol=1e-9)
    doc = json.loads((remote / "batch.json").read_text())
    assert doc["where"]["kind"] == "dask" and doc["where"]["workers"] == 1


def test_the_worker_timeout_default_is_the_documented_one():
    from ewb_ident.study import WORKER_TIMEOUT_S

    got = runner.invoke(app, ["batch", "--help"])
    assert f"default: {WORKER_TIMEOUT_S:g}," in " ".join(got.output.split())


def test_a_scheduler_without_workers_gives_up(campaign, tmp_path):
    from distributed import LocalCluster

    out = tmp_path / "out"
    with LocalCluster(n_workers=0, processes=True, dashboard_address=":0") as cluster:
        got = runner.invoke(app, ["batch", str(campaign), "--out", str(out), "--scheduler",
                                  cluster.scheduler_address, "--worker-timeout", "1"])
    assert got.exit_code == 2
    assert "waiting up to 1 s for a worker" in got.stderr
    assert "no worker joined within 1 s" in got.stderr
    assert not out.exists()


def _bad_inputs(root: Path) -> dict[str, tuple[list[str], str]]:
    (root / "nopath.csv").write_text("file,hardware\nv1_0.csv,v1\n")
    (root / "empty.csv").write_text("path,hardware\n")
    (root / "missing.csv").write_text("path,hardware\nv1_0.csv,v1\nnot_there.csv,v2\n")
    (root / "garbage.parquet").write_bytes(b"not a parquet file")
    m = str(root / "manifest.csv")
    return {
        "no path column": ([str(root / "nopath.csv")], "no 'path' column"),
        "empty": ([str(root / "empty.csv")], "the manifest has no rows"),
        "missing file": ([str(root / "missing.csv")], "row 2: trace not_there.csv not found"),
        "unreadable": ([str(root / "garbage.parquet")], "cannot read the manifest"),
        "no source": ([str(root / "nowhere")], "no such file or folder"),
        "empty glob": ([str(root / "*.mat")], "the pattern matches no trace files"),
        "trace as manifest": ([str(root / "v1_0.csv")], "it looks like a trace, not a manifest"),
        "group-by": ([m, "--group-by", "operator"], "--group-by operator: not a metadata column"),
        "r_eff": ([m, "--r-eff", "3"], "r_eff_m must be a pad radius"),
        "trend column": ([m, "--trend", "cycle"], "--trend cycle: not a metadata column"),
        "trend text": ([m, "--trend", "hardware"], "--trend hardware: 'v1' is not a number"),
        "split-on alone": ([m, "--split-on", "force_N"], "--split-on is a setting of --cycles"),
        "unreachable": ([m, "--scheduler", "tcp://127.0.0.1:1"], "no Dask scheduler answered"),
        "steps alone": ([m, "--steps", "100"], "--steps is a setting of --posterior"),
        "bad steps": ([m, "--posterior", "--steps", "0"], "--steps"),
        "unit column": ([m, "--unit-column", "rig"], "--unit-column rig: not a metadata column"),
    }


@pytest.mark.parametrize("case", ["no path column", "empty", "missing file", "unreadable",
                                  "no source", "empty glob", "trace as manifest", "group-by",
                                  "r_eff", "trend column", "trend text", "split-on alone",
                                  "unreachable", "steps alone", "bad steps", "unit column"])
def test_bad_input_is_one_line_exit_2_and_nothing_written(campaign, tmp_path, case):
    args, message = _bad_inputs(campaign)[case]
    out = tmp_path / "out"
    t0 = time.perf_counter()
    got = runner.invoke(app, ["batch", *args, "--out", str(out)])
    assert got.exit_code == 2, got.output
    lines = [ln for ln in got.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and message in lines[0], got.stderr
    assert not out.exists()
    assert time.perf_counter() - t0 < 8.0


def test_a_folder_and_a_glob_are_campaigns_too(campaign, tmp_path):
    got = runner.invoke(app, ["batch", str(campaign / "v2_*.csv"), "--out", str(tmp_path)])
    assert got.exit_code == 0, got.output
    table = pd.read_csv(tmp_path / "results.csv")
    assert set(table["trace"]) == {str(campaign / "v2_0.csv"), str(campaign / "v2_1.csv")}
    assert list(table.columns[1:12]) == CONTRACT and not (tmp_path / "changes.csv").exists()
    # a folder that holds the output folder: the batch's own tables are not traces
    own = campaign / "own_out"
    first = runner.invoke(app, ["batch", str(campaign), "--out", str(own)])
    again = runner.invoke(app, ["batch", str(campaign), "--out", str(own)])
    assert first.exit_code == again.exit_code == 3  # manifest.csv is no trace: an error row
    assert " reused, 0 fitted" in again.stdout
    assert "own_out" not in " ".join(pd.read_csv(own / "results.csv")["trace"])


def test_a_per_row_mapping_reads_a_log_with_other_names_and_units(campaign, first_run,
                                                                  tmp_path):
    _, out, _ = first_run
    log = pd.read_csv(campaign / "v1_0.csv")
    german = pd.DataFrame({
        "Zeit": log["time_s"] * 1e3, "Spannung": log["voltage_V"], "Strom": log["current_A"] * 1e3,
        "Winkel": np.deg2rad(log["theta_deg"]), "Kolbenweg": log["x_m"] * 1e3,
        "Spannkraft": log["force_N"] / 1e3, "Bremsmoment": log["torque_Nm"],
    })
    german.to_csv(tmp_path / "log.csv", index=False, float_format="%.17g")
    mapping = Path(__file__).parents[1] / "datasets" / "mapping_example.toml"
    pd.DataFrame({"path": ["log.csv"], "map": [str(mapping)]}).to_csv(tmp_path / "m.csv",
                                                                      index=False)
    got = runner.invoke(app, ["batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "o")])
    assert got.exit_code == 0, got.output
    mine = pd.read_csv(tmp_path / "o" / "results.csv").set_index("parameter")
    theirs = pd.read_parquet(out / "results.parquet")
    theirs = theirs[theirs["trace"] == "v1_0.csv"].set_index("parameter")
    for name in ("a", "b", "c", "mu"):
        assert mine.loc[name, "estimate"] == pytest.approx(theirs.loc[name, "estimate"],
                                                           rel=1e-6)
    doc = json.loads((tmp_path / "o" / "batch.json").read_text())
    assert doc["inputs"][0]["map_sha256"] is not None


# ---------------------------------------------------------------- random effects


def test_random_effects_intervals_hold_their_level():
    """Seeded draws from the random-effects model: the mean's and tau's 90 % intervals
    hold the truth at about their nominal rate."""
    rng = np.random.default_rng(7)
    mean_held, tau_held, n = 0, 0, 400
    for _ in range(n):
        s = rng.uniform(0.5, 2.0, size=8)
        y = 10.0 + rng.normal(0.0, 1.5, size=8) + rng.normal(0.0, s)
        comb = random_effects(y, s)
        mean_held += comb.low90 <= 10.0 <= comb.high90
        tau_held += comb.tau_low90 <= 1.5 <= comb.tau_high90
    assert 0.85 <= mean_held / n <= 0.96 and 0.85 <= tau_held / n <= 0.95


def test_random_effects_are_the_same_at_any_scale():
    """tau and its interval scale with the data: the gap polynomial's p2 (~4e-9, tau^2
    ~1e-19) once got an upper bound from brentq's absolute tolerance, not the data, and
    Paule-Mandel's tau sits inside the Q-profile interval."""
    rng = np.random.default_rng(3)
    s = rng.uniform(0.05, 0.2, 100)
    y = 3.8 + rng.normal(0.0, 0.3, 100) + rng.normal(0.0, s)
    one, tiny = random_effects(y, s), random_effects(y * 1e-9, s * 1e-9)
    for field in ("mean", "low90", "high90", "tau", "tau_low90", "tau_high90"):
        assert getattr(tiny, field) == pytest.approx(getattr(one, field) * 1e-9, rel=1e-6)
    assert one.tau_low90 <= one.tau <= one.tau_high90


def test_random_effects_without_spread_is_the_weighted_mean():
    comb = random_effects([1.0, 1.0, 1.0], [0.1, 0.2, 0.2])
    assert comb.mean == pytest.approx(1.0) and comb.tau == 0.0 and comb.tau_low90 == 0.0
    one = random_effects([2.0], [0.5])
    assert one.tau is None and one.low90 == pytest.approx(2.0 - 1.6449 * 0.5, rel=1e-4)
    moved = group_change("c", random_effects([1e-3, 1.01e-3], [1e-5, 1e-5]),
                         random_effects([1.2e-3, 1.21e-3], [1e-5, 1e-5]))
    assert moved.changed and moved.low90 < 2e-4 < moved.high90


def test_two_levels_separate_the_unit_spread_from_the_trace_spread():
    """Seeded campaigns of 8 rig units x 4 traces with a known unit-to-unit spread (1.5)
    and trace-to-trace spread within a unit (0.8): the two-level combination's 90 %
    intervals of the mean, tau_unit and tau_trace hold the truth at about 90 %, and its
    estimates centre on the truth; the one-level combination, which takes the 32 traces
    as 32 independent draws, gives the mean an interval far too narrow."""
    rng = np.random.default_rng(11)
    n, units, per_unit, tau_unit, tau_trace = 300, 8, 4, 1.5, 0.8
    label = np.repeat(np.arange(units), per_unit)
    held = dict.fromkeys(("mean", "tau_unit", "tau_trace", "one_level_mean"), 0)
    tau_u, tau_t = [], []
    for _ in range(n):
        s = rng.uniform(0.3, 1.0, units * per_unit)
        y = (10.0 + rng.normal(0.0, tau_unit, units)[label]
             + rng.normal(0.0, tau_trace, units * per_unit) + rng.normal(0.0, s))
        got = two_level(y, s, [f"U{u}" for u in label])
        assert (got.units.n, got.n_traces, got.repeated) == (units, units * per_unit, units)
        held["mean"] += got.low90 <= 10.0 <= got.high90
        held["tau_unit"] += got.units.tau_low90 <= tau_unit <= got.units.tau_high90
        held["tau_trace"] += got.tau_trace_low90 <= tau_trace <= got.tau_trace_high90
        one = random_effects(y, s)
        held["one_level_mean"] += one.low90 <= 10.0 <= one.high90
        tau_u.append(got.units.tau)
        tau_t.append(got.tau_trace)
    rate = {k: v / n for k, v in held.items()}
    assert all(0.85 <= rate[k] <= 0.96 for k in ("mean", "tau_unit", "tau_trace")), rate
    assert rate["one_level_mean"] < 0.75, rate
    assert np.median(tau_u) == pytest.approx(tau_unit, rel=0.12)
    assert np.median(tau_t) == pytest.approx(tau_trace, rel=0.08)


def test_two_levels_with_one_trace_per_unit_are_one_level():
    """No unit with a second trace: nothing to say about tau_trace, and the combination
    over the units is the one-level one; a trace with no unit is a unit of its own."""
    y, s = [1.0, 1.3, 0.8, 1.1], [0.1, 0.2, 0.1, 0.15]
    two, one = two_level(y, s, ["A", "B", None, "D"]), random_effects(y, s)
    assert two.tau_trace is None and two.repeated == 0 and two.units.n == 4
    for field in ("mean", "low90", "high90"):
        assert getattr(two, field) == pytest.approx(getattr(one, field), rel=1e-12)
    assert two.units.tau == pytest.approx(one.tau, rel=1e-9)
    # two traces of one unit, agreeing within their errors: the unit's weighted mean
    same = two_level([1.0, 1.02, 2.0], [0.1, 0.1, 0.1], ["A", "A", "B"])
    assert same.tau_trace == 0.0 and same.units.n == 2 and same.repeated == 1
    means = random_effects([1.01, 2.0], [0.1 / np.sqrt(2.0), 0.1])
    assert same.units.mean == pytest.approx(means.mean, rel=1e-12)
    assert same.units.tau == pytest.approx(means.tau, rel=1e-9)


# ---------------------------------------------------------------- simulate --set


def test_simulate_set_changes_the_truth(tmp_path):
    out = tmp_path / "t.csv"
    got = runner.invoke(app, ["simulate", str(out), "--set", "c=1.0e-3", "--set", "mu=0.4"])
    assert got.exit_code == 0, got.output
    truth = json.loads(out.with_suffix(".truth.json").read_text())["params"]
    assert truth["c"] == 1.0e-3 and truth["mu"] == 0.4 and truth["a"] == 6.295e-4


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("wheels=4", "unknown parameter 'wheels'"),
        ("mu=1.5", "mu must be a finite number within (0, 1)"),
        ("a=-1e-3", "a must be a finite number within (0, 0.01) m"),
        ("c=big", "'big' is not a number"),
        ("c", "--set takes NAME=VALUE"),
    ],
)
def test_simulate_set_refuses_bad_settings(tmp_path, setting, message):
    out = tmp_path / "t.csv"
    got = runner.invoke(app, ["simulate", str(out), "--set", setting])
    assert got.exit_code == 2
    lines = got.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and not out.exists()


def test_simulate_through_c_drives_the_piston_past_c(tmp_path):
    out = tmp_path / "t.csv"
    got = runner.invoke(app, ["simulate", str(out), "--profile", "through_c", "--set", "c=1e-3"])
    assert got.exit_code == 0, got.output
    truth = json.loads(out.with_suffix(".truth.json").read_text())
    x = pd.read_csv(out)["x_m"]
    p = truth["params"]
    assert truth["profile"]["kind"] == "through_c"
    assert x.max() > p["c"] + 0.2 * p["a"]  # held at c + 0.3 a, less the sensor noise
