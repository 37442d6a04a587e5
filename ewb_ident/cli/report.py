"""``ewb-ident report``: the HTML validation report (fit, posterior, diagnosis)."""

from __future__ import annotations

from typing import Annotated

import typer

# The shared options and checks this command uses. These lists, and the trace options
# (--map, --fill-gaps, ...) in the signatures, repeat across the commands by design:
# Typer reads each command's options from its own signature.
from ewb_ident.cli.options import (
    EXIT_UNTRUSTWORTHY,
    FillGaps,
    Mapping,
    NoUnitCheck,
    OutDir,
    REff,
    Status,
    Traces,
    app,
    bad_input_errors,
    check_out,
    command_line,
    fail,
    progress_bar,
    read_traces,
    sampler_settings,
    writing,
)


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
    steps: Annotated[
        int, typer.Option(help="MCMC steps per ensemble planned (as for sample).")
    ] = 2000,
    min_ess: Annotated[float, typer.Option(help="ESS every parameter needs (as for sample).")] = (
        400.0
    ),
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Validation report: OUT/index.html (self-contained) and PNG figures: data, fit,
    bell curve, parameters with 90 % intervals, errors beside the seed's, MCMC
    diagnostics, and the diagnosis of missing physics."""
    check_out(out)
    from ewb_ident.inference.least_squares import fit as run_fit
    from ewb_ident.reporting.html import build_report, write_report
    from ewb_ident.reporting.summaries import headline

    sampler = sampler_settings(n_steps=steps, min_ess=min_ess, seed=seed)
    post = diag = None
    try:
        trs = read_traces(traces, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        result = run_fit(trs, stage=stage)
        if posterior:
            from ewb_ident.inference.posterior import sample as run_sample

            typer.echo("sampling the posterior (emcee, two ensembles) ...")
            bar, progress = progress_bar()
            if bar is not None:
                bar.start()
            try:
                post = run_sample(trs, stage=stage, settings=sampler, progress=progress)
            finally:
                if bar is not None:
                    bar.stop()
        if diagnosis and len(trs) == 1:
            from ewb_ident.diagnosis.diagnose import diagnose as run_diagnose
            from ewb_ident.diagnosis.session import DiagnoseError

            typer.echo("diagnosing missing physics ...")
            try:
                with Status("diagnosing") as say:
                    diag = run_diagnose(trs[0], progress=say)
            except DiagnoseError as err:
                typer.echo(f"no diagnosis: {err}")
        elif diagnosis:
            typer.echo("no diagnosis: it looks at one trace at a time (run `diagnose` on each)")
    except bad_input_errors() as err:
        fail(str(err))
    cpost, cnote = _corrected_posterior(trs, diag, posterior, stage, sampler)
    page, figures = build_report(
        trs,
        result,
        posterior=post,
        diagnosis=diag,
        corrected_posterior=cpost,
        corrected_note=cnote,
        command=command_line(),
    )
    with writing(out):
        path = write_report(out, page, figures)
    if diag is not None:
        typer.echo(diag.summary())
    typer.echo(headline(result, post, diag, cpost))
    typer.echo(f"wrote {path} ({len(figures)} figures)")
    if result.status != "ok" or any(p is not None and not p.converged for p in (post, cpost)):
        typer.echo(
            "the fit or a posterior is not trustworthy (see the report's warnings)", err=True
        )
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _corrected_posterior(trs, diag, posterior: bool, stage: str, sampler):
    """The corrected model's posterior when the diagnosis found catalog physics or a
    learned term, else (None, why not); None, None when there is nothing to correct.
    ``sampler``: the :class:`~ewb_ident.inference.log_posterior.SamplerSettings`."""
    if diag is None or diag.corrected is None:
        return None, None
    if not posterior:
        return None, "its posterior was not run (--no-posterior)"
    if stage != "chain":
        return None, f"its posterior is of the whole chain, and this report is of stage {stage}"
    from ewb_ident.diagnosis.session import DiagnoseError
    from ewb_ident.inference.log_posterior import SampleError
    from ewb_ident.inference.posterior import sample_corrected

    mechs = diag.corrected.mechanisms
    typer.echo(f"sampling the posterior of the corrected model ({', '.join(mechs)}) ...")
    try:
        bar, progress = progress_bar()
        if bar is not None:
            bar.start()
        try:
            post = sample_corrected(trs[0], diag.corrected, settings=sampler, progress=progress)
            return post, None
        finally:
            if bar is not None:
                bar.stop()
    except (DiagnoseError, SampleError) as err:
        typer.echo(f"no corrected posterior: {err}")
        return None, f"its posterior could not be run ({err})"
