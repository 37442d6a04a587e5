"""``ewb-ident batch --diagnose --posterior``: each trace's diagnosis, corrected model
and posterior in the campaign's table, in this process and on a Dask cluster of worker
processes, and resumed.

The campaign: two short traces of the synthetic rig, one of the seed's physics and one
with friction hysteresis in caliper and wedge planted (``simulate --effect
force_hysteresis``, h = 0.03), whose corrected bell (a, c) the diagnosis recovers. The
sampler runs few steps (its chains do not converge, which the table and the exit code
say): the test is of the plumbing, the sampler's own accuracy is tested in
``test_posterior.py``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from ewb_ident.cli import app
from ewb_ident.data.campaign import Entry
from ewb_ident.inference.batch import make_job
from ewb_ident.inference.log_posterior import SamplerSettings

runner = CliRunner()
SAMPLER = ["--steps", "100", "--max-steps", "100", "--min-ess", "10"]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("diagnosed")
    for name, extra in (("plain", ()), ("hyst", ("--effect", "force_hysteresis"))):
        got = runner.invoke(
            app,
            [
                "simulate",
                str(root / f"{name}.csv"),
                "--duration",
                "2.2",
                "--seed",
                "2",
                "--vary",
                "0.01",
                *extra,
            ],
        )
        assert got.exit_code == 0, got.output
    pd.DataFrame({"path": ["plain.csv", "hyst.csv"], "unit": ["U1", "U2"]}).to_csv(
        root / "manifest.csv", index=False
    )
    return root


@pytest.fixture(scope="module")
def run(campaign, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out"
    args = [
        "batch",
        str(campaign / "manifest.csv"),
        "--out",
        str(out),
        "--diagnose",
        "--posterior",
        *SAMPLER,
    ]
    return runner.invoke(app, args), out, args


def test_verdict_findings_and_the_corrected_model_per_trace(campaign, run):
    got, out, _ = run
    # the chains of 100 steps are too short to converge: written, and said, exit 3
    assert got.exit_code == 3, got.output
    assert "diagnosis: 1 of 2 traces carry a finding: hyst.csv (force_hysteresis)" in got.stdout
    assert "posteriors did not converge (more --steps)" in got.stdout
    table = pd.read_parquet(out / "results.parquet")
    verdict = table.groupby("trace")["verdict"].first()
    assert verdict["plain.csv"] == "none" and verdict["hyst.csv"] == "found"
    assert set(table.loc[table["trace"] == "plain.csv", "findings"]) == {""}
    assert set(table.loc[table["trace"] == "hyst.csv", "findings"]) == {"force_hysteresis"}
    # the corrected model: rows of its own, for the trace with the finding only
    fixed = table[table["model"] == "corrected"]
    assert set(fixed["trace"]) == {"hyst.csv"}
    assert {"a", "b", "c", "mu", "force_hysteresis.h"} <= set(fixed["parameter"])
    truth = json.loads((campaign / "hyst.truth.json").read_text())
    rows = {
        m: table[(table["trace"] == "hyst.csv") & (table["model"] == m)].set_index("parameter")
        for m in ("baseline", "corrected")
    }
    h = rows["corrected"].loc["force_hysteresis.h"]
    assert h["unit"] == "1" and h["low_90"] < 0.03 < h["high_90"]
    for name in ("a", "c"):  # the corrected bell is nearer the truth than the baseline's
        true = truth["params"][name]
        assert abs(rows["corrected"].loc[name, "estimate"] - true) < abs(
            rows["baseline"].loc[name, "estimate"] - true
        )
    assert (
        rows["corrected"].loc["a", "force_N_nrmse_pct"]
        < rows["baseline"].loc["a", "force_N_nrmse_pct"]
    )
    assert "corrected by force_hysteresis" in rows["corrected"].loc["a", "message"]


def test_posterior_intervals_are_hdis_and_the_population_is_the_fits(run):
    _, out, _ = run
    table = pd.read_parquet(out / "results.parquet")
    model = table[table["parameter"].isin(["a", "b", "c", "mu"])]
    assert (model["interval_from"] == "posterior").all()
    assert model["posterior_mean"].notna().all() and model["posterior_sd"].notna().all()
    # HDIs, not estimate +- 1.645 stderr
    half = (model["high_90"] - model["low_90"]) / 2
    assert not ((half - 1.6449 * model["stderr"]).abs() < 1e-6 * half).all()
    unsettled = table["posterior_converged"].eq(False).fillna(False)
    assert unsettled.any()
    assert table.loc[unsettled, "message"].str.contains("posterior not converged").all()
    # the population combines the fit every trace shares, not the corrected models
    pop = pd.read_csv(out / "population.csv")
    assert "force_hysteresis.h" not in set(pop["parameter"])
    assert pop.set_index("parameter").loc["a", "n_traces"] == 2
    page = (out / "index.html").read_text()
    assert "1 of 2 traces carry a finding" in page and "hyst.csv" in page
    assert "did not converge" in page and "posterior (emcee), diagnosis" in page
    settings = json.loads((out / "batch.json").read_text())["settings"]
    assert settings["diagnose"] and settings["posterior"]["n_steps"] == 100
    assert settings["posterior"]["hdi_prob"] == 0.9


def test_a_rerun_resumes_and_other_options_refit(campaign, run, tmp_path):
    _, out, args = run
    before = pd.read_parquet(out / "results.parquet")
    again = runner.invoke(app, args)
    assert again.exit_code == 3 and "2 reused, 0 fitted" in again.stdout
    pd.testing.assert_frame_equal(pd.read_parquet(out / "results.parquet"), before)
    # the options are in each trace's key: a record made with others is not reused
    entry = Entry("plain.csv", campaign / "plain.csv")
    keys = {
        make_job(entry, fill_gaps=False, check_units=True, version="x", **kw).key
        for kw in (
            {},
            {"diagnose": True},
            {"posterior": SamplerSettings(n_steps=100)},
            {"posterior": SamplerSettings(n_steps=200)},
        )
    }
    assert len(keys) == 4
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    plain = runner.invoke(app, ["batch", str(campaign / "manifest.csv"), "--out", str(copy)])
    assert plain.exit_code == 0 and "0 reused, 2 fitted" in plain.stdout
    table = pd.read_parquet(copy / "results.parquet")
    assert table["verdict"].isna().all() and (table["interval_from"] == "stderr").all()


@pytest.mark.slow  # ~1.5 min on two cores: the worker compiles the diagnosis's programs
def test_on_a_dask_cluster_of_processes_the_table_is_the_same(campaign, run, tmp_path):
    from distributed import LocalCluster

    _, out, _ = run
    remote = tmp_path / "remote"
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0"
    ) as cluster:
        got = runner.invoke(
            app,
            [
                "batch",
                str(campaign / "manifest.csv"),
                "--out",
                str(remote),
                "--diagnose",
                "--posterior",
                *SAMPLER,
                "--scheduler",
                cluster.scheduler_address,
            ],
        )
    assert got.exit_code == 3, got.output
    assert "with 1 worker" in got.stdout and "1 of 2 traces carry a finding" in got.stdout
    pd.testing.assert_frame_equal(
        pd.read_parquet(remote / "results.parquet"),
        pd.read_parquet(out / "results.parquet"),
        rtol=1e-9,
    )
