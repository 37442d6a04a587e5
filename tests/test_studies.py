"""Batch studies: definitions, reproducible cases, and the same table on a Dask cluster."""

import pandas as pd
import pytest

from ewb_ident.study import StudyError, load_study, run_study, summarise

MINI = """
[study]
name = "mini"
repeats = 2
seed = 5
[rig]
profile = "staircase"
sample_rate_hz = [100, 200]
[task]
stage = "torque"
"""


@pytest.fixture
def mini(tmp_path):
    path = tmp_path / "mini.toml"
    path.write_text(MINI)
    return load_study(path)


def test_grid_and_repeats_make_seeded_cases(mini):
    cases = mini.cases()
    assert len(cases) == 4
    assert [c.rig["sample_rate_hz"] for c in cases] == [100, 100, 200, 200]
    assert len({c.seed for c in cases}) == 4


def test_in_process_and_dask_cluster_give_the_same_table(mini, tmp_path):
    """The CLI's --scheduler path, on a cluster of worker processes (not threads)."""
    from distributed import LocalCluster
    from typer.testing import CliRunner

    from ewb_ident.cli import app

    local = run_study(mini)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True) as cluster:
        out = CliRunner().invoke(
            app,
            [
                "study",
                str(mini.path),
                "--out",
                str(tmp_path / "remote"),
                "--scheduler",
                cluster.scheduler_address,
            ],
        )
    assert out.exit_code == 0, out.output
    remote = pd.read_csv(tmp_path / "remote" / "results.csv")
    cols = ["case", "parameter", "estimate", "truth", "stderr"]
    pd.testing.assert_frame_equal(
        local[cols].reset_index(drop=True),
        remote[cols].reset_index(drop=True),
        check_dtype=False,
        rtol=1e-12,
    )
    assert local["error"].isna().all()
    # mu is recovered: within a few standard errors of the truth in every case
    assert (local["z"].abs() < 4).all()
    assert "coverage_90_pct" in summarise(mini, local)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[study]\ntask = 'dance'\n", "task 'dance' is unknown"),
        ("[rig]\nwheels = 4\n", "key 'wheels' is unknown"),
        ("[study]\nrepeats = 0\n", "repeats must be a positive whole number"),
        ("[study\n", "not valid TOML"),
    ],
)
def test_bad_definitions_name_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(StudyError, match=message):
        load_study(path)


def test_every_drawn_current_limit_acts():
    """The diagnosis accuracy study drew a current limit as 1.8-3.2 A, above a
    position-controlled apply's peak current in 4 of its 8 cases of seed 20261218
    (visibility 0: nothing to find, counted as misses). Drawn against the case's own
    peak, every case's limit changes the recording by many times the noise."""
    from studies import diagnosis_accuracy as da

    plan = da.case_plan()
    cases = [i for i, (k, ids) in enumerate(plan) if k == "single" and ids == ("current_limit",)]
    assert len(cases) == da.N_SINGLE_PER_ID
    for i in cases:
        *_, visibility = da.make_case(i, ("current_limit",), seed=20261218, widen=True)
        assert visibility > 5.0, (i, visibility)


def test_an_unreachable_scheduler_is_one_line_exit_2_and_writes_nothing(tmp_path):
    """No scheduler at the address: refused before anything is written, in one line
    naming the address."""
    from typer.testing import CliRunner

    from ewb_ident.cli import app

    (tmp_path / "mini.toml").write_text(MINI)
    out = tmp_path / "out"
    res = CliRunner().invoke(
        app,
        [
            "study",
            str(tmp_path / "mini.toml"),
            "--out",
            str(out),
            "--scheduler",
            "tcp://127.0.0.1:1",
        ],
    )
    assert res.exit_code == 2
    assert "no Dask scheduler answered" in res.output and "tcp://127.0.0.1:1" in res.output
    assert len(res.output.strip().splitlines()) == 1
    assert not out.exists()
