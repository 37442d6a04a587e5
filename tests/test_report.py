"""The validation report: its content, and that it renders in a real browser."""

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from ewb_ident.data.readers import read_trace
from ewb_ident.inference.least_squares import fit
from ewb_ident.reporting.html import build_report, write_report

DATA = Path(__file__).parents[1] / "datasets"


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    trace = read_trace(DATA / "staircase_200hz.csv")
    result = fit(trace)
    page, figures = build_report([trace], result)
    out = tmp_path_factory.mktemp("report")
    return write_report(out, page, figures), page, figures


def test_report_holds_every_section_and_the_seed_values(report):
    path, page, figures = report
    for text in (
        "1. Data",
        "2. Parameters",
        "3. Measured against simulated",
        "4. The clamping-force curve",
        "seed (Table 2)",
        "seed&#x27;s reported % error",
        "units slip",
        "RMS residual by phase",
        "Summary",
        "7. Provenance",
        "SHA-256",
        "r_eff",
    ):
        assert text in page, text
    # x is shown in mm, as its heading says (not metres in e-notation)
    trace = read_trace(DATA / "staircase_200hz.csv")
    rmse_mm = fit(trace).metrics["x_m"]["rmse"] * 1e3
    assert f'piston gap x (mm)</td><td class="">{rmse_mm:.4g}<' in page
    assert {"bell.png", "fit_0_staircase_200hz.png", "overview_0_staircase_200hz.png"} <= set(
        figures
    )
    assert all(data[:8] == b"\x89PNG\r\n\x1a\n" for data in figures.values())
    assert path.read_text() == page and (path.parent / "bell.png").exists()
    assert page.count("data:image/png;base64,") == len(figures)  # self-contained


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium not installed")
def test_report_renders_in_headless_chromium(report, tmp_path):
    from PIL import Image

    path, _, _ = report
    shot = tmp_path / "shot.png"
    subprocess.run(
        [
            "chromium",
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={tmp_path / 'profile'}",
            "--window-size=1100,2400",
            f"--screenshot={shot}",
            path.as_uri(),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    image = Image.open(shot).convert("L")
    assert image.size == (1100, 2400)
    extrema = image.getextrema()
    assert extrema[0] < 60 and extrema[1] > 200  # text and figures drawn, not a blank page


@pytest.fixture(scope="module")
def hysteresis():
    """The README's main job: its trace, baseline fit and diagnosis (computed once)."""
    from ewb_ident.diagnosis.diagnose import diagnose

    path = DATA / "concealed" / "force_hysteresis.csv"
    trace = read_trace(path)
    return path, trace, fit(trace), diagnose(trace)


def test_report_of_a_concealed_trace_names_the_missing_physics(hysteresis):
    _, trace, result, diagnosis = hysteresis
    page, figures = build_report([trace], result, diagnosis=diagnosis)
    assert "6. Diagnosis: physics the model leaves out" in page
    assert "force_hysteresis" in page and "friction hysteresis in caliper and wedge" in page
    assert "NRMSE % before" in page
    assert {"mismatch.png", "finding_1_force_hysteresis.png"} <= set(figures)
    assert "linearised" in page  # no corrected posterior given: the page says so


def test_report_with_a_finding_shows_both_models_and_the_banner(hysteresis):
    """Issue 10: when the diagnosis rejects the baseline, a banner says its intervals are
    conditional on a model that leaves physics out, and the corrected parameters stand
    beside the baseline's with the corrected posterior's HDIs, the truth inside them."""
    import json

    from ewb_ident.inference.log_posterior import SamplerSettings
    from ewb_ident.inference.posterior import sample_corrected

    path, trace, result, diagnosis = hysteresis
    assert diagnosis.corrected_mechanisms() == ["force_hysteresis"]
    assert diagnosis.corrected.mechanisms == ("force_hysteresis",)  # the posterior's start
    cpost = sample_corrected(
        trace, corrected=diagnosis.corrected, settings=SamplerSettings(n_steps=800, seed=2)
    )
    page, _ = build_report([trace], result, diagnosis=diagnosis, corrected_posterior=cpost)
    assert "rejects the baseline model" in page and "2b. Corrected model" in page
    assert "force_hysteresis.h" in page and "corrected 90 %" in page
    assert "HDIs of its posterior (MCMC, converged)" in page
    assert "<b>Corrected</b> with force_hysteresis" in page  # in the summary at the top
    truth = json.loads(path.with_suffix(".truth.json").read_text())["params"]
    stats = cpost.to_summary_json()["params"]
    for p in ("a", "b", "c", "mu"):
        assert stats[p]["hdi_low"] <= truth[p] <= stats[p]["hdi_high"], p
        assert f"{stats[p]['hdi_low'] * (1e3 if p in 'ac' else 1):.4g} … " in page, p


def test_report_command_writes_a_page(tmp_path):
    """The README's headline command, through the CLI (posterior and diagnosis off here:
    they have their own tests below and in test_posterior / test_diagnose)."""
    from typer.testing import CliRunner

    from ewb_ident.cli import app

    out = CliRunner().invoke(
        app,
        [
            "report",
            str(DATA / "staircase_200hz.csv"),
            "--no-posterior",
            "--no-diagnose",
            "--out",
            str(tmp_path),
        ],
    )
    assert out.exit_code == 0, out.output
    page = (tmp_path / "index.html").read_text()
    assert "2. Parameters" in page and "4. The clamping-force curve" in page
    # The terminal output ends with a, b, c, mu and their 90 % intervals, in mm for a, c.
    assert "a, b, c, mu with 90 % intervals:" in out.output
    rows = [line.split() for line in out.output.splitlines() if line.startswith("  ")]
    a_row = next(r for r in rows if r[:2] == ["a", "baseline"])
    assert "mm" in a_row and 0.3 < float(a_row[2]) < 1.5  # a in mm, not m
    assert any(r[:2] == ["mu", "baseline"] for r in rows)


def test_report_renders_the_posterior_section():
    from ewb_ident.inference.log_posterior import SamplerSettings
    from ewb_ident.inference.posterior import sample

    trace = read_trace(DATA / "staircase_200hz.csv")
    result = fit(trace, stage="force")
    settings = SamplerSettings(n_steps=300, max_steps=300, seed=1)
    post = sample(trace, stage="force", settings=settings)
    page, figures = build_report([trace], result, posterior=post)
    assert "5. Posterior (MCMC)" in page and "pair.png" in figures
    assert "posterior mean" in page and "90 % interval" in page
    # the measured-vs-simulated figure's band: 90 % posterior predictive of the force,
    # which holds about 90 % of the measured samples when the model is right
    from ewb_ident.reporting.html import _predictive_bands

    lo, hi = _predictive_bands(post, trace)["force_N"]
    inside = float(np.mean((trace["force_N"] >= lo) & (trace["force_N"] <= hi)))
    assert 0.8 < inside < 0.97, inside


def one_span_per_run(ax, t, labels) -> None:
    """The phases' shading as it was drawn before :func:`shade_phases` used collections:
    one ``axvspan`` per run of a phase (``benchmarks/bench_figures.py`` times both)."""
    from ewb_ident.reporting.style import PHASE_COLOURS

    start = 0
    for k in range(1, t.size + 1):
        if k == t.size or labels[k] != labels[start]:
            colour = PHASE_COLOURS.get(str(labels[start]), "#ffffff")
            ax.axvspan(t[start], t[min(k, t.size - 1)], color=colour, lw=0, zorder=0)
            start = k


def test_phase_shading_draws_the_pixels_of_one_axvspan_per_run():
    """``shade_phases`` draws one collection per phase colour; the figure must be the
    one a span per run gives (pixels, and x limits to round-off), on chattering labels whose runs
    include one-sample ones, and an axis whose curve ends before the shading does."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ewb_ident.reporting.style import PHASE_COLOURS, shade_phases

    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 3.0, 3001)
    names = np.array(list(PHASE_COLOURS) + ["unknown"])
    labels = names[np.repeat(rng.integers(0, names.size, 600), rng.integers(1, 20, 600))][: t.size]

    def draw(shade) -> tuple[bytes, list]:
        fig = Figure(figsize=(6, 4), dpi=80)
        axes = fig.subplots(2, 1)
        for k, ax in enumerate(axes):
            shade(ax, t, labels)
            ax.plot(t[: t.size // (k + 1)], np.sin(t[: t.size // (k + 1)]), color="k")
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        return bytes(canvas.buffer_rgba()), [ax.get_xlim() for ax in axes]

    pixels, limits = draw(shade_phases)
    want_pixels, want_limits = draw(one_span_per_run)
    assert len(set(labels)) == names.size and np.sum(labels[1:] != labels[:-1]) > 100
    np.testing.assert_allclose(limits, want_limits, rtol=1e-12)  # a span's xmin + width
    assert pixels == want_pixels


def test_report_takes_the_samplers_options_and_logs_progress_without_a_terminal(tmp_path):
    """`report --steps/--min-ess` reach the sampler (a bad value is refused before any
    work, in the option's spelling); in a batch log (stderr not a terminal) the MCMC
    and the diagnosis say how far they are, line by line."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "ewb_ident", "report", str(DATA / "staircase_200hz.csv")]
    bad = subprocess.run(
        [*cmd, "--steps", "5", "--out", str(tmp_path / "bad")], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "--steps must be an integer >= 10" in bad.stderr
    assert not (tmp_path / "bad").exists()
    proc = subprocess.run(
        [*cmd, "--stage", "force", "--steps", "300", "--min-ess", "50",
         "--out", str(tmp_path / "r")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode in (0, 3), proc.stderr
    assert "sampling: " in proc.stderr and " steps (" in proc.stderr
    assert "diagnosing: baseline fits of every stage" in proc.stderr
    page = (tmp_path / "r" / "index.html").read_text()
    assert "2. Parameters" in page


def _tables(page: str) -> dict[str, list[list[str]]]:
    """The page's tables by the heading of the section they are in: rows of cell texts
    (the first row is the header)."""
    import html as _html
    import re

    out: dict[str, list[list[str]]] = {}
    for section in re.split(r"(?=<h2>)", re.sub(r"<img[^>]*>", "", page)):
        head = re.match(r"<h2>(.*?)</h2>", section)
        name = _html.unescape(head.group(1)) if head else "top"
        for k, table in enumerate(re.findall(r"<table>(.*?)</table>", section, flags=re.S)):
            rows = [
                [_html.unescape(re.sub(r"<[^>]+>", "", c)).strip()
                 for c in re.findall(r"<t[hd][^>]*>(.*?)</t[hd]>", row, flags=re.S)]
                for row in re.findall(r"<tr>(.*?)</tr>", table, flags=re.S)
            ]  # fmt: skip
            out[f"{name} #{k}"] = rows
    return out


def _column(tables, section: str, column: str) -> dict[str, str]:
    """Row label -> cell of ``column`` in the first table of ``section`` that has it."""
    for name, rows in tables.items():
        if name.startswith(section) and column in rows[0]:
            j = rows[0].index(column)
            return {r[0]: r[j] for r in rows[1:]}
    raise AssertionError(f"no column {column!r} in section {section!r}")


def _agree(shown: list[str]) -> bool:
    """Numbers shown with different precision agree when each is the other rounded:
    every value lies within half a unit of the last digit of the coarsest."""
    import decimal

    values = [decimal.Decimal(s) for s in shown]
    step = max(decimal.Decimal(1).scaleb(v.as_tuple().exponent) for v in values)
    return max(values) - min(values) <= step / 2 + step / 1000


def test_every_quantity_the_report_shows_twice_has_one_value_and_one_unit(hysteresis):
    """The report of a shipped trace (the main job's, with its diagnosis): a baseline
    parameter or error shown in more than one place (the summary, section 2, section 2b,
    section 3) has one value there, to the digits shown, and a parameter has one unit
    in every table and in the summary (a and c in mm)."""
    import html as _html
    import re

    _, trace, result, diagnosis = hysteresis
    page, _ = build_report([trace], result, diagnosis=diagnosis)
    tables = _tables(page)
    top = page.split("<b>Summary</b>")[1].split("</ul>")[0]
    summary = _html.unescape(re.sub(r"<[^>]+>", "", top))
    baseline_line = summary.split("Baseline")[1].split("Corrected")[0]

    # units: one per parameter, in every table that has a unit column, and in the summary
    units: dict[str, set[str]] = {}
    for rows in tables.values():
        if rows[0][:2] == ["parameter", "unit"]:
            for r in rows[1:]:
                units.setdefault(r[0], set()).add(r[1])
    for name, seen in units.items():
        assert len(seen) == 1, f"{name} shown in {seen}"
    assert units["a"] == units["c"] == {"mm"}
    for name in ("a", "c"):
        assert re.search(rf"\b{name} = [\d.]+ mm \[", baseline_line), baseline_line

    # baseline parameters: the summary, section 2 and section 2b
    ls = _column(tables, "2. Parameters", "least squares")
    base = _column(tables, "2b.", "baseline")
    for name in ("a", "b", "c", "mu"):
        in_summary = re.search(rf"\b{name} = ([\d.e+-]+)", baseline_line).group(1)
        assert _agree([ls[name], base[name], in_summary]), (name, ls[name], base[name], in_summary)

    # baseline errors: the summary, section 3 and section 2b
    from ewb_ident.reporting.style import CHANNEL_LABELS

    err3 = _column(tables, "3. Measured", "% error")
    nrmse3 = _column(tables, "3. Measured", "NRMSE %")
    err2b = _column(tables, "2b.", "% error baseline")
    nrmse2b = _column(tables, "2b.", "NRMSE % baseline")
    for ch in ("force_N", "torque_Nm"):
        label = CHANNEL_LABELS[ch]
        in_summary = re.search(rf"{ch} ([\d.]+) %", summary).group(1)
        shown = [err3[label], err2b[ch], in_summary]
        assert _agree(shown), (ch, "% error", shown)
        assert _agree([nrmse3[label], nrmse2b[ch]]), (ch, "NRMSE", nrmse3[label], nrmse2b[ch])


def test_provenance_names_versions_commit_seeds_and_unit_conversions():
    """The provenance says what made the numbers (package versions; the commit when run
    from a checkout; the MCMC seeds) and how each mapped column was converted."""
    import dataclasses

    import jax

    from ewb_ident.reporting.provenance import provenance_rows

    trace = read_trace(DATA / "staircase_200hz.csv")
    mapped = {"x_m": {"source": "piston_mm", "unit": "mm"}, "force_N": {"source": "F"}}
    trace = dataclasses.replace(trace, sidecar={**trace.sidecar, "_mapped": mapped})
    rows = dict((k.strip(), v) for k, v in provenance_rows([trace], "ewb-ident report X", [7, 8]))
    assert f"jax {jax.__version__}" in rows["packages"]
    assert rows["MCMC seeds"] == "7, 8"
    assert "piston_mm [mm → SI] → x_m" in rows["column mapping"]
    assert "F → force_N" in rows["column mapping"]
    if (Path(__file__).parents[1] / ".git").exists():
        assert len(rows["commit"].removeprefix("<code>").removesuffix("</code>")) == 40


def test_the_report_says_why_least_squares_and_posterior_intervals_differ_where_they_do():
    """Where a parameter's posterior interval and its least-squares one (estimate ± Z90
    standard errors) differ in width by more than half, one sentence names it and says
    which to quote; where they agree, nothing is said."""
    from types import SimpleNamespace

    from ewb_ident.data.metrics import Z90
    from ewb_ident.reporting.summaries import ls_posterior_note

    fit = SimpleNamespace(free=("a", "c"), stderr={"a": 1e-5, "c": 2e-5})
    post = {
        "params": {
            "a": {"hdi_low": 0.0, "hdi_high": 2 * Z90 * 1e-5 * 1.2},  # agrees
            "c": {"hdi_low": 0.0, "hdi_high": 2 * Z90 * 2e-5 * 0.3},  # far narrower
        }
    }
    note = ls_posterior_note(fit, post)
    assert "For c they differ" in note and "quote the posterior interval" in note
    post["params"]["c"]["hdi_high"] = 2 * Z90 * 2e-5
    assert ls_posterior_note(fit, post) == ""
