"""``ewb-ident sample``: the posterior of the parameters by MCMC."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

# The shared options and checks this command uses. These lists, and the trace options
# (--map, --fill-gaps, ...) in the signatures, repeat across the commands by design:
# Typer reads each command's options from its own signature.
from ewb_ident.cli.options import (
    EXIT_UNTRUSTWORTHY,
    SAMPLER_OPTIONS,
    FillGaps,
    FixOption,
    IntegratorOption,
    Mapping,
    NoUnitCheck,
    OutDir,
    REff,
    Traces,
    WithDiagnosisOption,
    WithOption,
    app,
    assignments,
    bad_input_errors,
    check_out,
    corrected_options,
    fail,
    integrator_option,
    mechanism_option,
    name_list,
    progress_bar,
    read_traces,
    sampler_settings,
    writing,
)


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
    fix: FixOption = None,
    priors: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of priors overriding the defaults (ewb_ident/inference/priors.toml)."
        ),
    ] = None,
    noise: Annotated[
        str, typer.Option(help="auto (AR(1) where the residuals are correlated), white or ar1.")
    ] = "auto",
    steps: Annotated[
        int,
        typer.Option(
            help="Steps per ensemble planned after 200 adaptation steps (stops earlier "
            "once converged)."
        ),
    ] = 2000,
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
    integrator: IntegratorOption = "exponential",
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
    check_out(out)
    mechanisms = mechanism_option(with_, with_diagnosis)
    if mechanisms is not None:
        corrected_options(traces, stage, free, per_trace, fix, integrator)
    import time

    from ewb_ident.inference.log_posterior import SampleError
    from ewb_ident.inference.posterior import sample as run_sample
    from ewb_ident.inference.priors import PriorError

    errors: tuple[type[Exception], ...] = (*bad_input_errors(), SampleError, PriorError)
    if mechanisms is not None:  # the diagnosis's modules only when they are asked for
        from ewb_ident.diagnosis.corrected import fit_corrected
        from ewb_ident.diagnosis.session import DiagnoseError
        from ewb_ident.inference.posterior import sample_corrected

        errors += (DiagnoseError,)
    from ewb_ident.reporting.summaries import posterior_summary

    method = integrator_option(integrator)
    # One keyword per setting: alike in shape to other constructors' calls (problem.Setup).
    settings = sampler_settings(
        noise_model=noise,
        n_walkers=walkers,
        n_steps=steps,
        max_steps=max_steps,
        n_ensembles=ensembles,
        min_ess=min_ess,
        hdi_prob=hdi_prob,
        max_draws=draws,
        seed=seed,
    )
    stages = stage if stage in ("chain", "stages") else tuple(name_list(stage) or ())
    if isinstance(stages, tuple) and len(stages) == 1:
        stages = stages[0]
    bar, progress = progress_bar(no_progress)
    t0 = time.perf_counter()
    try:
        trs = read_traces(
            traces, None if stages == "stages" else stages, mapping, fill_gaps, no_unit_check, r_eff
        )
        # The memory the settings need, from the traces' length, in the options' spelling.
        settings.check(names=SAMPLER_OPTIONS, n_samples=sum(t.n for t in trs))
        if bar is not None:
            bar.start()
        common = dict(priors=priors, settings=settings, progress=progress)
        if mechanisms is None:
            result = run_sample(
                trs,
                stage=stages,
                free=name_list(free),
                per_trace=name_list(per_trace),
                fixed=assignments(fix, "--fix"),
                integrator=method,
                **common,
            )
        else:
            result = sample_corrected(trs[0], fit_corrected(trs[0], *mechanisms), **common)
    except errors as err:
        fail(str(err))
    finally:
        if bar is not None:
            bar.stop()
    _write(out, result, traces)
    typer.echo(posterior_summary(result))
    typer.echo(
        f"wrote {out / 'summary.json'}, {out / 'posterior.nc'} and {out / 'pairs.png'} "
        f"({time.perf_counter() - t0:.1f} s)"
    )
    if not result.converged:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _write(out, result, traces) -> None:
    """summary.json, posterior.nc and pairs.png, atomically."""
    from ewb_ident.data.outputs import json_text, write_run
    from ewb_ident.reporting.report_figures import pair_figure

    text = json_text(result.to_summary_json() | {"traces": [str(p) for p in traces]})
    idata, fig = result.to_inference_data(), pair_figure(result)
    with writing(out):
        write_run(
            out,
            "sample",
            [
                (out / "summary.json", lambda tmp: tmp.write_text(text, encoding="utf-8")),
                # Uncompressed: zlib costs a noticeable share of a cached run to save 8 %.
                (out / "posterior.nc", lambda tmp: idata.to_netcdf(str(tmp), compress=False)),
                (out / "pairs.png", lambda tmp: fig.savefig(tmp, format="png", dpi=110)),
            ],
        )
