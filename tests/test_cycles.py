"""Long recordings as a campaign: ``ewb-ident batch LOG --cycles`` on a short synthetic
endurance log (a minute at 200 Hz, a cycle every 6 s) with a planted fade of mu, from
CSV, Parquet and .mat; the split rule on its edge cases; the fast, memory-bounded reader
of long tables; the trend's interval level. The hour at 1 kHz is studies/endurance.py."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io
from typer.testing import CliRunner

from ewb_ident.cli import app
from ewb_ident.data.cycles import CycleError, CycleRule, split_cycles
from ewb_ident.data.readers import MAX_SAMPLES, from_arrays, read_trace
from ewb_ident.data.trace import TraceError
from ewb_ident.data.writers import write_trace
from ewb_ident.inference.population import trend
from ewb_ident.rig.endurance import simulate_endurance

runner = CliRunner()
DURATION_S, PERIOD_S, RATE_HZ = 36.0, 6.0, 200.0
MU_DRIFT = -0.2  # mu 20 % lower at the log's end: a strong fade, for a short log


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """The log as CSV, Parquet and .mat (one sidecar), and its truth."""
    root = tmp_path_factory.mktemp("endurance")
    trace, truth = simulate_endurance(duration_s=DURATION_S, period_s=PERIOD_S,
                                      sample_rate_hz=RATE_HZ, drift={"mu": MU_DRIFT}, seed=5)
    write_trace(trace, root / "log.csv")
    write_trace(trace, root / "log.parquet")
    scipy.io.savemat(root / "log.mat", {"time_s": trace.time_s, **trace.channels})
    return root, trace, truth


@pytest.fixture(scope="module")
def runs(log, tmp_path_factory):
    root, _, _ = log
    out = {}
    for ext in ("csv", "parquet", "mat"):
        dest = tmp_path_factory.mktemp("out") / ext
        got = runner.invoke(app, ["batch", str(root / f"log.{ext}"), "--cycles", "--out",
                                  str(dest)])
        out[ext] = (got, dest)
    return out


def test_the_split_finds_every_cycle_at_its_apply(log, runs):
    _, trace, truth = log
    for got, dest in runs.values():
        assert got.exit_code == 0, got.output
        assert "6 apply cycles (0 partial, not fitted) where force_N rises above" in got.output
        cycles = pd.read_csv(dest / "cycles.csv")
        assert len(cycles) == 6 and not cycles["partial"].any()
        # each window starts at rest, a second before its apply's rise, inside its period
        starts = np.array([c["t_start_s"] for c in truth["cycles"]])
        rise = cycles["rise_s"].to_numpy()
        np.testing.assert_allclose(rise - cycles["t_start_s"].to_numpy(), 1.0)
        assert np.all((rise > starts + 1.0) & (rise < starts + 2.0))
        assert cycles["samples"].nunique() == 1  # one length: one compiled program
        assert (dest / "cycles.png").stat().st_size > 0
        assert "The split into apply cycles" in (dest / "index.html").read_text()
        kept = json.loads((dest / "batch.json").read_text())["settings"]["split"]
        assert kept["logs"][0]["cycles"] == 6 and kept["rule"]["lead_s"] == 1.0


def test_the_fade_is_recovered_within_its_interval_from_every_format(log, runs):
    _, _, truth = log
    mu0 = truth["params"]["mu"]
    per_hour = mu0 * MU_DRIFT / (DURATION_S / 3600.0)
    tables = {}
    for ext, (_, dest) in runs.items():
        trends = pd.read_csv(dest / "trend.csv").set_index("parameter")
        mu = trends.loc["mu"]
        assert mu["against"] == "time_h" and mu["n_traces"] == 6
        assert mu["slope_low_90"] <= per_hour <= mu["slope_high_90"], ext
        assert mu["trend"] and -20 < mu["drift_pct"] < -15
        assert not trends.drop(index="mu")["trend"].any()  # nothing else drifts
        tables[ext] = pd.read_parquet(dest / "results.parquet")
        assert {"log", "cycle", "t_start_s", "t_rise_s", "time_h"} <= set(tables[ext].columns)
    # the same samples from every format: the same fits
    for ext in ("parquet", "mat"):
        np.testing.assert_array_equal(tables[ext]["estimate"], tables["csv"]["estimate"])


def test_a_rerun_reuses_every_cycle(log, runs):
    root, _, _ = log
    _, dest = runs["parquet"]
    got = runner.invoke(app, ["batch", str(root / "log.parquet"), "--cycles", "--out",
                              str(dest)])
    assert got.exit_code == 0 and "6 reused, 0 fitted" in got.output


def test_cycles_on_a_dask_cluster_of_processes_give_the_same_table(log, runs, tmp_path):
    """The cycles are split here and written under OUT/cycles/; each is fitted on a worker
    process of a real LocalCluster (not threads) that reads its cycle's file, and the
    table, the trend and the split are those of the run in this process."""
    from distributed import LocalCluster

    root, _, _ = log
    _, here = runs["parquet"]
    remote = tmp_path / "remote"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:
        got = runner.invoke(app, ["batch", str(root / "log.parquet"), "--cycles", "--out",
                                  str(remote), "--scheduler", cluster.scheduler_address])
    assert got.exit_code == 0, got.output
    assert f"on the Dask cluster at {cluster.scheduler_address} with 2 worker" in got.stdout
    assert "0 reused, 6 fitted" in got.stdout
    doc = json.loads((remote / "batch.json").read_text())
    assert doc["where"]["kind"] == "dask" and doc["where"]["workers"] == 2
    mine, theirs = (pd.read_parquet(d / "results.parquet") for d in (remote, here))
    # the cycles' files are under each run's own folder; everything else is the same
    assert [Path(t).relative_to(remote) for t in mine["trace"]] == \
        [Path(t).relative_to(here) for t in theirs["trace"]]
    pd.testing.assert_frame_equal(mine.drop(columns="trace"), theirs.drop(columns="trace"),
                                  rtol=1e-9)
    for name in ("trend", "cycles"):
        a, b = (pd.read_csv(d / f"{name}.csv") for d in (remote, here))
        cols = [c for c in a.columns if c != "trace"]
        pd.testing.assert_frame_equal(a[cols], b[cols], rtol=1e-9)


def test_a_log_too_long_for_a_trace_points_to_cycles(tmp_path):
    n = MAX_SAMPLES + 10
    path = tmp_path / "long.csv"
    pd.DataFrame({"time_s": np.arange(n) / 1000.0, "x_m": np.zeros(n)}).to_csv(path,
                                                                                index=False)
    with pytest.raises(TraceError, match=r"a trace is at most 600,000 samples .*--cycles"):
        read_trace(path)
    got = runner.invoke(app, ["batch", str(path), "--cycles", "--out", str(tmp_path / "o")])
    assert got.exit_code == 2, got.output
    assert "long.csv: " in got.output and len(got.output.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_a_long_csv_reads_exactly_and_a_bad_row_is_one_line(tmp_path):
    n = MAX_SAMPLES + 5
    rng = np.random.default_rng(3)
    x = rng.standard_normal(n) * 10.0 ** rng.integers(-9, 4, n)
    path = tmp_path / "long.csv"
    pd.DataFrame({"time_s": np.arange(n) / 1000.0, "force_N": x}).to_csv(path, index=False)
    with open(path, "a") as handle:
        handle.write("\n")  # a trailing blank line is no row
    got = read_trace(path, max_samples=2 * n, check_units=False)
    np.testing.assert_array_equal(got["force_N"], x)  # bit for bit, as Python's float()
    with open(path, "a") as handle:
        handle.write("1,2,3\n")
    with pytest.raises(TraceError, match=r"long.csv: not a readable CSV file \(CSV parse error"):
        read_trace(path, max_samples=2 * n, check_units=False)


def _log_with_applies(force_at, n=6000, rate=200.0):
    t = np.arange(n) / rate
    force = np.zeros(n)
    for a, b in force_at:
        force[(t >= a) & (t < b)] = 3000.0
    return from_arrays("log", t, force_N=force, theta_deg=force / 10.0)


def test_the_rule_on_partial_merged_and_spurious_applies():
    # cut by the start; two halves 0.1 s apart (one apply); a 20 ms spike; cut by the end
    trace = _log_with_applies([(0.0, 1.0), (5.0, 6.0), (6.1, 7.0), (12.0, 12.02),
                               (15.0, 16.5), (29.5, 30.0)])
    split = split_cycles(trace)
    assert [c.partial for c in split.cycles] == [True, False, False, True]
    whole = split.complete
    assert [c.rise_s for c in whole] == [5.0, 15.0]
    assert whole[0].fall_s == pytest.approx(6.995)  # the merged apply
    assert all(c.stop - c.start == whole[0].stop - whole[0].start for c in whole)
    assert whole[0].t_start_s == pytest.approx(4.0)
    # the window: 1 s lead + the longest apply (2 s) + 1 s tail
    assert (whole[0].stop - whole[0].start) / 200.0 == pytest.approx(4.0, abs=0.01)
    on_theta = split_cycles(trace, dataclasses.replace(CycleRule(), channel="theta_deg"))
    assert on_theta.channel == "theta_deg" and len(on_theta.complete) == 2


def test_a_log_without_a_complete_apply_is_refused():
    with pytest.raises(CycleError, match="every apply found is cut by the log's start or end"):
        split_cycles(_log_with_applies([(0.0, 3.0)]))


def test_split_on_a_missing_channel_is_one_line(log, tmp_path):
    root, _, _ = log
    got = runner.invoke(app, ["batch", str(root / "log.csv"), "--cycles", "--split-on",
                              "pressure", "--out", str(tmp_path / "o")])
    assert got.exit_code == 2
    assert "cannot split on 'pressure'" in got.output and not (tmp_path / "o").exists()


@pytest.mark.parametrize(("extra", "message"), [
    (["--group-by", "operator"], "--group-by operator: not a metadata column"),
    (["--trend", "log"], "--trend log: the log's name is not a number"),
    (["--scheduler", "tcp://127.0.0.1:1"], "no Dask scheduler answered"),
])
def test_a_bad_option_is_refused_before_the_log_is_split(log, tmp_path, extra, message):
    root, _, _ = log
    out = tmp_path / "o"
    got = runner.invoke(app, ["batch", str(root / "log.parquet"), "--cycles", *extra,
                              "--out", str(out)])
    assert got.exit_code == 2 and message in got.output
    assert not out.exists()  # no cycle written


def test_trend_intervals_hold_their_level():
    """Seeded draws from the meta-regression model: the slope's 90 % interval holds the
    truth at about its nominal rate."""
    rng = np.random.default_rng(11)
    held, n = 0, 400
    for _ in range(n):
        x = np.sort(rng.uniform(0.0, 1.0, 20))
        s = rng.uniform(0.5, 2.0, 20)
        y = 5.0 - 2.0 * x + rng.normal(0.0, 1.0, 20) + rng.normal(0.0, s)
        tr = trend("mu", x, y, s)
        held += tr.slope_low90 <= -2.0 <= tr.slope_high90
    assert 0.85 <= held / n <= 0.95
