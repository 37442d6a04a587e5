"""The ``ewb-ident`` command line: parse, validate, call the library, write files.

Every command reads traces, does its work in memory, and writes its files only at the
end, atomically. Bad input (a trace, a mapping, an option) prints one line naming the
file, column, row and what to do, and exits with code 2; nothing is written.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help=(
        "Fit the EWB rig model (DC motor -> worm pinion -> wedge -> caliper) to rig traces, "
        "say how certain the parameters are, and find the physics the model leaves out.\n\n"
        "Traces are CSV/Parquet/MATLAB tables in the trace format v1 (time_s, voltage_V, "
        "theta_deg, x_m, force_N, torque_Nm, current_A) with an optional JSON sidecar."
    ),
    pretty_exceptions_enable=False,
)

EXIT_BAD_INPUT = 2
#: Done and written, but not trustworthy: not converged, or outside the stated acceptance.
EXIT_UNTRUSTWORTHY = 3

Traces = Annotated[list[Path], typer.Argument(help="Trace files (.csv, .parquet, .mat).")]
OutDir = Annotated[Path, typer.Option("--out", "-o", help="Output folder (created if absent).")]
Mapping = Annotated[
    Path | None,
    typer.Option("--map", help="Column mapping (JSON/TOML): source name -> column and unit."),
]
FillGaps = Annotated[
    bool, typer.Option("--fill-gaps", help="Interpolate interior gaps of up to 5 samples.")
]
NoUnitCheck = Annotated[
    bool, typer.Option("--no-unit-check", help="Skip the plausibility checks of units.")
]
REff = Annotated[
    float | None,
    typer.Option(
        "--r-eff",
        help="Effective pad radius, m, for every trace (overrides the sidecar; default: "
        "the sidecar's r_eff_m, else 0.15 m with a warning).",
    ),
]
WithOption = Annotated[
    str | None,
    typer.Option(
        "--with",
        help="Catalog mechanisms to add to the chain, e.g. 'backlash' or "
        "'force_hysteresis,sensor_delay[force_N]' (whole chain, one trace).",
    ),
]
WithDiagnosisOption = Annotated[
    Path | None,
    typer.Option("--with-diagnosis", help="Folder of an earlier `diagnose`: add what it found."),
]


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _check_out(out: Path, *, folder: bool = True) -> None:
    """Refuse an output location that cannot be written, before any work starts."""
    import os

    if folder and out.exists() and not out.is_dir():
        _fail(f"--out {out}: exists and is not a folder; name a folder (it is created)")
    if not folder and out.is_dir():
        _fail(f"{out}: is a folder; name a file to write")
    probe = out if folder and out.exists() else out.parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        _fail(f"{out}: cannot write there ({probe} is not a writable folder); choose another")
    # Permissions do not tell everything (an immutable or read-only mounted folder, or
    # root): try to create a file there, and remove it.
    import tempfile

    try:
        fd, name = tempfile.mkstemp(dir=probe, prefix=".ewb-ident-probe-")
        os.close(fd)
        os.unlink(name)
    except OSError as err:
        _fail(f"{out}: cannot write there ({probe}: {err.strerror}); choose another")


class _status:
    """A one-line status on a terminal's stderr (``diagnose``, ``report``): what the
    long computation is doing now and for how long; silent when stderr is not a
    terminal (scripts, CI)."""

    def __init__(self, what: str):
        self.what = what
        self.live = None

    def __enter__(self):
        import time

        self.t0 = time.perf_counter()
        if not sys.stderr.isatty():
            return lambda text: None
        from rich.console import Console

        self.live = Console(stderr=True).status(self.what)
        self.live.start()

        def say(text: str) -> None:
            self.live.update(f"{self.what}: {text} ({time.perf_counter() - self.t0:.0f} s)")

        return say

    def __exit__(self, *exc) -> None:
        if self.live is not None:
            self.live.stop()


def _names(text: str | None) -> list[str] | None:
    if text is None:
        return None
    return [n.strip() for n in text.split(",") if n.strip()]


def _assignments(text: str | None, option: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in _names(text) or []:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            _fail(f"{option} takes NAME=VALUE pairs separated by commas, got {item!r}")
    return out


def _read(paths: list[Path], stages, mapping, fill_gaps, no_unit_check, r_eff=None):
    import dataclasses
    import math

    from ewb_ident.data.trace import read_trace

    if r_eff is not None and not (math.isfinite(r_eff) and 0.02 <= r_eff <= 0.5):
        _fail(f"--r-eff must be a pad radius within 0.02 to 0.5 m, got {r_eff!r}")
    out = []
    for p in paths:
        tr = read_trace(
            p,
            mapping=mapping,
            stages=stages,
            nan_policy="interpolate" if fill_gaps else "raise",
            check_units=not no_unit_check,
        )
        if r_eff is not None:
            side = dict(tr.sidecar) | {"r_eff_m": float(r_eff), "_r_eff_source": "--r-eff"}
            tr = dataclasses.replace(tr, sidecar=side)
        out.append(tr)
    return out


def _bad_input_errors() -> tuple[type[Exception], ...]:
    from ewb_ident.data.trace import TraceError
    from ewb_ident.inference.least_squares import FitError

    return (TraceError, FitError)


@app.command()
def fit(
    traces: Traces,
    out: OutDir,
    stage: Annotated[
        str, typer.Option(help="chain (from voltage alone), or motor, gap, force, torque.")
    ] = "chain",
    free: Annotated[
        str | None, typer.Option(help="Parameters to vary, e.g. 'a,b,c,mu' (default: per stage).")
    ] = None,
    per_trace: Annotated[
        str | None,
        typer.Option(help="Free parameters fitted per trace, e.g. 'c,p0' after a pad change."),
    ] = None,
    fix: Annotated[
        str | None, typer.Option(help="Fixed values in SI units, e.g. 'R=1.1,L=0.002'.")
    ] = None,
    integrator: Annotated[
        str, typer.Option(help="exponential (default) or heun (the seed's, at 0.01 s).")
    ] = "exponential",
    with_: WithOption = None,
    with_diagnosis: WithDiagnosisOption = None,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Least-squares fit; writes OUT/fit.json and prints a summary."""
    _check_out(out)
    mechanisms = _mechanism_option(with_, with_diagnosis)
    if mechanisms is not None:
        _corrected_options(traces, stage, free, per_trace, fix, integrator)
        _fit_corrected(traces[0], out, mechanisms, mapping, fill_gaps, no_unit_check, r_eff)
        return
    from ewb_ident.data.outputs import write_json
    from ewb_ident.inference.least_squares import fit as run_fit
    from ewb_ident.model.integrate import EXPONENTIAL, SEED_HEUN
    from ewb_ident.reporting.summaries import fit_summary

    if integrator not in ("exponential", "heun"):
        _fail(f"--integrator must be exponential or heun, got {integrator!r}")
    try:
        trs = _read(traces, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        result = run_fit(
            trs,
            stage=stage,
            free=_names(free),
            per_trace=_names(per_trace),
            fixed=_assignments(fix, "--fix"),
            integrator=SEED_HEUN if integrator == "heun" else EXPONENTIAL,
        )
    except _bad_input_errors() as err:
        _fail(str(err))
    document = result.to_json() | {"traces": [str(p) for p in traces]}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "fit.json", document)
    typer.echo(fit_summary(result))
    typer.echo(f"wrote {out / 'fit.json'}")
    if result.status != "ok":
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _corrected_options(traces, stage, free, per_trace, fix, integrator) -> None:
    """Refuse options the corrected model does not take (it is one trace, whole chain)."""
    if (
        len(traces) != 1
        or stage != "chain"
        or free
        or per_trace
        or fix
        or integrator != ("exponential")
    ):
        _fail(
            "--with/--with-diagnosis take one trace, whole chain, default parameters and "
            "integrator: drop --stage, --free, --per-trace, --fix and --integrator, or give "
            "one trace"
        )


def _mechanism_option(with_: str | None, with_diagnosis: Path | None) -> list[str] | None:
    """Mechanism variants from --with and/or an earlier diagnosis (None: neither given)."""
    if with_ is None and with_diagnosis is None:
        return None
    names = _names(with_) or []
    if with_diagnosis is not None:
        import json

        path = with_diagnosis / "diagnosis.json" if with_diagnosis.is_dir() else with_diagnosis
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            found = [f["mechanism"] for f in doc["findings"] if f.get("catalog", True)]
        except (OSError, ValueError, KeyError, TypeError) as err:
            _fail(f"--with-diagnosis {with_diagnosis}: cannot read diagnosis.json ({err})")
        found = [m for m in found if not m.startswith("unexplained_")]
        if not found:
            _fail(
                f"--with-diagnosis {with_diagnosis}: the diagnosis found no catalog mechanism "
                "(verdict none or unexplained); fit without it"
            )
        names += [m for m in found if m not in names]
    if not names:
        _fail("--with: name at least one catalog mechanism")
    return names


def _fit_corrected(trace, out, mechanisms, mapping, fill_gaps, no_unit_check, r_eff) -> None:
    from ewb_ident.data.outputs import write_json
    from ewb_ident.diagnosis.diagnose import DiagnoseError, fit_corrected
    from ewb_ident.reporting.summaries import corrected_summary

    try:
        (tr,) = _read([trace], ("chain",), mapping, fill_gaps, no_unit_check, r_eff)
        result = fit_corrected(tr, mechanisms)
    except (*_bad_input_errors(), DiagnoseError) as err:
        _fail(str(err))
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "fit.json", result.to_json() | {"traces": [str(trace)]})
    typer.echo(corrected_summary(result))
    typer.echo(f"wrote {out / 'fit.json'}")
    if not result.converged:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


@app.command()
def simulate(
    out: Annotated[Path, typer.Argument(help="Trace file to write (.csv or .parquet).")],
    profile: Annotated[
        str, typer.Option(help="steps (open-loop, as the seed), position, or staircase.")
    ] = "steps",
    rate: Annotated[float, typer.Option(help="Sample rate, Hz (100-1000).")] = 200.0,
    duration: Annotated[float, typer.Option(help="Length of the trace, s.")] = 3.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise and of --vary.")] = 0,
    vary: Annotated[
        float, typer.Option(help="Relative spread of rig parameters, like another unit.")
    ] = 0.0,
    noise_scale: Annotated[
        float, typer.Option(help="Multiplies every sensor's default noise level.")
    ] = 1.0,
    effect: Annotated[
        list[str] | None,
        typer.Option(help="Catalog effect to switch on (repeat for several), e.g. backlash."),
    ] = None,
    params: Annotated[
        Path | None,
        typer.Option("--params", help="fit.json whose fitted parameters the rig takes."),
    ] = None,
) -> None:
    """Synthetic rig trace with documented truth: writes OUT, its sidecar and OUT.truth.json."""
    import dataclasses

    import numpy as np

    from ewb_ident import rig
    from ewb_ident.data.outputs import write_json
    from ewb_ident.data.trace import write_trace

    if out.suffix.lower() not in (".csv", ".parquet"):
        _fail(f"{out}: write a .csv or .parquet trace")
    _check_out(out, folder=False)
    import math

    if not (math.isfinite(duration) and 0 < duration <= 600):
        _fail(f"--duration must be within (0, 600] s, got {duration!r}")
    if not (math.isfinite(vary) and 0 <= vary <= 0.5):
        _fail(f"--vary is a relative spread within [0, 0.5] (0.05: another unit), got {vary!r}")
    if not (math.isfinite(noise_scale) and 0 <= noise_scale <= 100):
        _fail(f"--noise-scale must be within [0, 100], got {noise_scale!r}")
    unknown = [e for e in effect or [] if e not in rig.EFFECTS]
    if unknown:
        _fail(f"unknown effect {unknown[0]!r}; the catalog is {', '.join(rig.EFFECTS)}")
    fitted = {}
    if params is not None:
        from ewb_ident.inference.validate import ValidateError, load_params

        try:
            fitted = load_params(params).as_dict()
        except ValidateError as err:
            _fail(str(err))
    try:
        rig_params = rig.RigParams(**fitted)
        if vary > 0:
            rig_params = rig.vary(rig_params, np.random.default_rng([seed, 1]), rel=vary)
        base = rig.SensorNoise()
        noise = rig.SensorNoise(
            **{f.name: getattr(base, f.name) * noise_scale for f in dataclasses.fields(base)}
        )
        trace, truth = rig.simulate_rig(
            rig_params,
            profile=profile,
            sample_rate_hz=rate,
            duration_s=duration,
            effects=tuple(effect or ()),
            noise=noise,
            seed=seed,
            name=out.stem,
        )
    except rig.RigError as err:
        _fail(str(err))
    out.parent.mkdir(parents=True, exist_ok=True)
    truth_path = out.with_suffix(".truth.json")
    write_trace(trace, out)
    write_json(truth_path, truth)
    typer.echo(f"wrote {out} ({trace.n} samples at {trace.sample_rate_hz:g} Hz) and {truth_path}")


@app.command()
def sample(
    traces: Traces,
    out: OutDir,
    stage: Annotated[
        str,
        typer.Option(
            help="chain (from voltage alone), stages (every teacher-forced stage the traces "
            "serve), or teacher-forced stages, e.g. 'force,torque'."
        ),
    ] = "chain",
    free: Annotated[
        str | None, typer.Option(help="Parameters to sample, e.g. 'a,b,c,mu' (default: per stage).")
    ] = None,
    per_trace: Annotated[
        str | None, typer.Option(help="Free parameters sampled per trace, e.g. 'c,p0'.")
    ] = None,
    fix: Annotated[
        str | None, typer.Option(help="Fixed values in SI units, e.g. 'R=1.1,L=0.002'.")
    ] = None,
    priors: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of priors overriding the defaults "
            "(ewb_ident/inference/priors.toml)."
        ),
    ] = None,
    noise: Annotated[
        str, typer.Option(help="auto (AR(1) where the residuals are correlated), white or ar1.")
    ] = "auto",
    steps: Annotated[int, typer.Option(help="Steps per ensemble.")] = 2000,
    max_steps: Annotated[
        int | None,
        typer.Option(help="Extend the run until converged or this many steps (default 10x)."),
    ] = None,
    walkers: Annotated[
        int | None, typer.Option(help="Walkers per ensemble, even (default max(32, 4 x dim)).")
    ] = None,
    ensembles: Annotated[int, typer.Option(help="Independent ensembles (>= 2).")] = 2,
    min_ess: Annotated[float, typer.Option(help="ESS every parameter needs.")] = 400.0,
    hdi_prob: Annotated[float, typer.Option(help="Probability of the HDIs.")] = 0.9,
    draws: Annotated[
        int, typer.Option(help="Draws stored in posterior.nc with predictive and log-lik.")
    ] = 1000,
    seed: Annotated[int, typer.Option(help="Seed of everything random.")] = 0,
    integrator: Annotated[
        str, typer.Option(help="exponential (default) or heun (the seed's, at 0.01 s).")
    ] = "exponential",
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    with_: WithOption = None,
    with_diagnosis: WithDiagnosisOption = None,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Posterior by MCMC (emcee) from the least-squares fit; writes OUT/summary.json,
    OUT/posterior.nc (ArviZ) and OUT/pairs.png, and prints a summary. With --with or
    --with-diagnosis: the posterior of the chain corrected by those mechanisms."""
    _check_out(out)
    mechanisms = _mechanism_option(with_, with_diagnosis)
    if mechanisms is not None:
        _corrected_options(traces, stage, free, per_trace, fix, integrator)
    import sys
    import time

    from ewb_ident.data.outputs import atomic_write, json_text
    from ewb_ident.diagnosis.diagnose import DiagnoseError, fit_corrected
    from ewb_ident.inference.posterior import SampleError, sample_corrected
    from ewb_ident.inference.posterior import sample as run_sample
    from ewb_ident.inference.priors import PriorError
    from ewb_ident.model.integrate import EXPONENTIAL, SEED_HEUN
    from ewb_ident.reporting.summaries import posterior_summary

    if integrator not in ("exponential", "heun"):
        _fail(f"--integrator must be exponential or heun, got {integrator!r}")
    stages = stage if stage in ("chain", "stages") else tuple(_names(stage) or ())
    if isinstance(stages, tuple) and len(stages) == 1:
        stages = stages[0]
    bar = None
    if not no_progress and sys.stderr.isatty():
        from rich.console import Console
        from rich.progress import Progress

        bar = Progress(console=Console(stderr=True), transient=True)
    task = None

    def progress(done: int, total: int) -> None:
        nonlocal task
        if task is None:
            task = bar.add_task("sampling", total=total)
        bar.update(task, completed=done, total=total)

    t0 = time.perf_counter()
    try:
        trs = _read(
            traces, None if stages == "stages" else stages, mapping, fill_gaps, no_unit_check, r_eff
        )
        if bar is not None:
            bar.start()
        common = dict(
            priors=priors,
            noise_model=noise,
            n_walkers=walkers,
            n_steps=steps,
            max_steps=max_steps,
            n_ensembles=ensembles,
            min_ess=min_ess,
            hdi_prob=hdi_prob,
            max_draws=draws,
            seed=seed,
            progress=None if bar is None else progress,
        )
        if mechanisms is None:
            result = run_sample(
                trs,
                stage=stages,
                free=_names(free),
                per_trace=_names(per_trace),
                fixed=_assignments(fix, "--fix"),
                integrator=SEED_HEUN if integrator == "heun" else EXPONENTIAL,
                **common,
            )
        else:
            result = sample_corrected(trs[0], fit_corrected(trs[0], mechanisms), **common)
    except (*_bad_input_errors(), SampleError, PriorError, DiagnoseError) as err:
        _fail(str(err))
    finally:
        if bar is not None:
            bar.stop()
    text = json_text(result.to_summary_json() | {"traces": [str(p) for p in traces]})
    idata, fig = result.to_inference_data(), result.pair_plot()
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(
        [
            (out / "summary.json", lambda tmp: tmp.write_text(text, encoding="utf-8")),
            (out / "posterior.nc", lambda tmp: idata.to_netcdf(str(tmp))),
            (out / "pairs.png", lambda tmp: fig.savefig(tmp, format="png", dpi=110)),
        ]
    )
    typer.echo(posterior_summary(result))
    typer.echo(
        f"wrote {out / 'summary.json'}, {out / 'posterior.nc'} and {out / 'pairs.png'} "
        f"({time.perf_counter() - t0:.1f} s)"
    )
    if not result.converged:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


@app.command()
def study(
    definition: Annotated[Path, typer.Argument(help="Study definition (TOML), see studies/.")],
    out: OutDir,
    scheduler: Annotated[
        str | None,
        typer.Option(help="Dask scheduler address (tcp://host:8786); default: in-process."),
    ] = None,
) -> None:
    """Run a batch study: writes OUT/results.csv (one row per case and parameter) and
    OUT/report.md."""
    _check_out(out)
    from rich.progress import Progress

    from ewb_ident.data.outputs import atomic_write
    from ewb_ident.study import StudyError, load_study, run_script, run_study, summarise

    try:
        spec = load_study(definition)
    except StudyError as err:
        _fail(str(err))
    out.mkdir(parents=True, exist_ok=True)
    with Progress(transient=True) as bar:
        job = bar.add_task(f"study {spec.name}", total=len(spec.cases()) or None)

        def progress(done, total):
            bar.update(job, completed=done, total=total)

        if spec.script is not None:
            table, report = run_script(spec, out, progress=progress)
        else:
            table = run_study(spec, scheduler=scheduler, progress=progress)
            report = summarise(spec, table)
    atomic_write(
        [
            (out / "results.csv", lambda tmp: table.to_csv(tmp, index=False)),
            (out / "report.md", lambda tmp: tmp.write_text(report, encoding="utf-8")),
        ]
    )
    typer.echo(report)
    typer.echo(f"wrote {out / 'results.csv'} and {out / 'report.md'}")


@app.command()
def report(
    traces: Traces,
    out: OutDir,
    stage: Annotated[str, typer.Option(help="Stage of the least-squares fit.")] = "chain",
    posterior: Annotated[
        bool, typer.Option("--posterior/--no-posterior", help="Run MCMC for 90 % intervals.")
    ] = True,
    diagnosis: Annotated[
        bool,
        typer.Option("--diagnose/--no-diagnose", help="Look for physics the model leaves out."),
    ] = True,
    seed: Annotated[int, typer.Option(help="Seed of the MCMC.")] = 0,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Validation report: OUT/index.html (self-contained) and PNG figures: data, fit,
    bell curve, parameters with 90 % intervals, errors beside the seed's, MCMC
    diagnostics, and the diagnosis of missing physics."""
    _check_out(out)
    from ewb_ident.inference.least_squares import fit as run_fit
    from ewb_ident.reporting.html import build_report, write_report

    post = diag = None
    try:
        trs = _read(traces, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        result = run_fit(trs, stage=stage)
        if posterior:
            from ewb_ident.inference.posterior import sample as run_sample

            typer.echo("sampling the posterior (emcee, two ensembles) ...")
            post = run_sample(trs, stage=stage, seed=seed)
        if diagnosis and len(trs) == 1:
            from ewb_ident.diagnosis.diagnose import DiagnoseError
            from ewb_ident.diagnosis.diagnose import diagnose as run_diagnose

            typer.echo("diagnosing missing physics ...")
            try:
                with _status("diagnosing") as say:
                    diag = run_diagnose(trs[0], progress=say)
            except DiagnoseError as err:
                typer.echo(f"no diagnosis: {err}")
        elif diagnosis:
            typer.echo("no diagnosis: it looks at one trace at a time (run `diagnose` on each)")
    except _bad_input_errors() as err:
        _fail(str(err))
    cpost, cnote = _corrected_posterior(trs, diag, posterior, stage, seed)
    page, figures = build_report(
        trs,
        result,
        posterior=post,
        diagnosis=diag,
        corrected_posterior=cpost,
        corrected_note=cnote,
        command=_command_line(),
    )
    path = write_report(out, page, figures)
    if diag is not None:
        typer.echo(diag.summary())
    typer.echo(f"wrote {path} ({len(figures)} figures)")
    if result.status != "ok" or any(p is not None and not p.converged for p in (post, cpost)):
        typer.echo(
            "the fit or a posterior is not trustworthy (see the report's warnings)", err=True
        )
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _command_line() -> str:
    """The command line as typed when run as ``ewb-ident`` (or ``python -m ewb_ident``);
    from Python, the command and its parsed options."""
    import shlex
    import sys

    import click

    if Path(sys.argv[0]).name in ("ewb-ident", "__main__.py"):
        return shlex.join(["ewb-ident", *sys.argv[1:]])
    ctx = click.get_current_context()
    opts = [f"{k}={v!r}" for k, v in ctx.params.items()]
    return f"{ctx.command_path} ({', '.join(opts)})"


def _corrected_posterior(trs, diag, posterior: bool, stage: str, seed: int):
    """The corrected model's posterior when the diagnosis found catalog physics, else
    (None, why not); None, None when there is nothing to correct."""
    if diag is None or diag.verdict != "found" or not diag.corrected_mechanisms():
        return None, None
    if not posterior:
        return None, "its posterior was not run (--no-posterior)"
    if stage != "chain":
        return None, f"its posterior is of the whole chain, and this report is of stage {stage}"
    from ewb_ident.diagnosis.diagnose import DiagnoseError
    from ewb_ident.inference.posterior import SampleError, sample_corrected

    mechs = diag.corrected_mechanisms()
    typer.echo(f"sampling the posterior of the corrected model ({', '.join(mechs)}) ...")
    try:
        return sample_corrected(trs[0], diag.corrected, seed=seed), None
    except (DiagnoseError, SampleError) as err:
        typer.echo(f"no corrected posterior: {err}")
        return None, f"its posterior could not be run ({err})"


@app.command()
def diagnose(
    trace: Annotated[Path, typer.Argument(help="One trace file (.csv, .parquet, .mat).")],
    out: OutDir,
    catalog: Annotated[
        str | None,
        typer.Option(help="Catalog ids to try, e.g. 'backlash,sensor_delay' (default: all)."),
    ] = None,
    bic_threshold: Annotated[
        float, typer.Option(help="Evidence a mechanism needs: delta BIC <= -THRESHOLD.")
    ] = 10.0,
    figures: Annotated[
        bool, typer.Option("--figures/--no-figures", help="Also write PNG figures.")
    ] = True,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Locate where the model misses the recording, name the missing physics, add it and
    refit; writes OUT/diagnosis.json and figures, and prints a summary."""
    _check_out(out)
    from ewb_ident.diagnosis.diagnose import DiagnoseError
    from ewb_ident.diagnosis.diagnose import diagnose as run_diagnose
    from ewb_ident.reporting.figures import write_diagnosis

    if not bic_threshold > 0:
        _fail(f"--bic-threshold must be a positive number, got {bic_threshold!r}")
    try:
        (tr,) = _read([trace], None, mapping, fill_gaps, no_unit_check, r_eff)
        with _status("diagnosing") as say:
            result = run_diagnose(
                tr, bic_threshold=bic_threshold, catalog=_names(catalog), progress=say
            )
    except (*_bad_input_errors(), DiagnoseError) as err:
        _fail(str(err))
    paths = write_diagnosis(result, out, extra={"traces": [str(trace)]}, figures=figures)
    typer.echo(result.summary())
    typer.echo(f"wrote {out / 'diagnosis.json'} and {len(paths) - 1} figure(s)")


@app.command()
def compare(
    old: Annotated[list[Path], typer.Option("--old", help="Trace(s) before the change.")],
    new: Annotated[list[Path], typer.Option("--new", help="Trace(s) after the change.")],
    out: OutDir,
    stage: Annotated[str, typer.Option(help="Stage of the fits (default: chain).")] = "chain",
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Hardware-change refit: which parameters changed between OLD and NEW traces, with
    90 % intervals and P(changed), and the brake torque at the seed's operating point;
    writes OUT/compare.json. Exits 3 when a fit did not converge."""
    _check_out(out)
    from ewb_ident.data.outputs import write_json
    from ewb_ident.inference.compare import compare as run_compare

    try:
        trs_old = _read(old, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        trs_new = _read(new, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        result = run_compare(trs_old, trs_new, stage=stage)
    except _bad_input_errors() as err:
        _fail(str(err))
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "compare.json", result.to_json())
    typer.echo(result.summary())
    typer.echo(f"wrote {out / 'compare.json'}")
    if not (result.old.converged and result.new.converged):
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


@app.command()
def validate(
    trace: Annotated[Path, typer.Argument(help="A trace the parameters were not fitted to.")],
    params: Annotated[Path, typer.Option("--params", help="fit.json of an earlier fit.")],
    out: OutDir,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Simulate fitted parameters on another trace: per-channel RMSE, NRMSE and percent
    error against the seed's 10 % acceptance and the trace's noise floor; writes
    OUT/validate.json and OUT/validate.png. Exits 3 outside the seed's acceptance."""
    _check_out(out)
    from ewb_ident.data.outputs import atomic_write, json_text
    from ewb_ident.inference.validate import ValidateError, load_params, validation_figure
    from ewb_ident.inference.validate import validate as run_validate
    from ewb_ident.reporting.summaries import validation_summary

    try:
        p = load_params(params)
        (tr,) = _read([trace], None, mapping, fill_gaps, no_unit_check, r_eff)
        result = run_validate(tr, p)
    except (*_bad_input_errors(), ValidateError) as err:
        _fail(str(err))
    text = json_text(result.to_json() | {"trace_file": str(trace), "params_file": str(params)})
    fig = validation_figure(tr, result)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(
        [
            (out / "validate.json", lambda tmp: tmp.write_text(text, encoding="utf-8")),
            (out / "validate.png", lambda tmp: fig.savefig(tmp, format="png", dpi=110)),
        ]
    )
    typer.echo(validation_summary(result, str(params)))
    typer.echo(f"wrote {out / 'validate.json'} and {out / 'validate.png'}")
    if not result.passes_seed:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


@app.callback(invoke_without_command=True)
def _main(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    if version:
        from importlib.metadata import version as _v

        typer.echo(f"ewb-ident {_v('ewb-ident')}")
        raise typer.Exit(0)


def _interrupted(signum, frame) -> None:
    """SIGINT / SIGTERM: end the run now with 130 / 143, leaving no temporary file and
    no final file that was not complete. (An exception raised here could land in a
    callback that swallows it, e.g. JAX's garbage-collection hook, so the process ends
    directly once the atomic writes' temporary files are removed.)"""
    import os
    import signal

    from ewb_ident.data.outputs import remove_pending

    remove_pending()
    sys.stderr.write("interrupted\n")
    sys.stderr.flush()
    os._exit(130 if signum == signal.SIGINT else 143)


def main() -> None:
    """Entry point of the ``ewb-ident`` script: float64 on, then the command."""
    import os
    import signal

    signal.signal(signal.SIGINT, _interrupted)
    signal.signal(signal.SIGTERM, _interrupted)

    import jax

    jax.config.update("jax_enable_x64", True)
    # Compiled XLA code is cached on disk, so a second run of a command skips compilation.
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    cache = os.environ.get("EWB_IDENT_CACHE", str(Path(xdg) / "ewb-ident" / "jax"))
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    app()
