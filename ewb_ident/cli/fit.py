"""``ewb-ident fit``: least squares of the seed chain (or a stage), optionally with
catalog mechanisms."""

from __future__ import annotations

from typing import Annotated

import typer

# The shared options and checks this command uses. These lists, and the trace options
# (--map, --fill-gaps, ...) in the signatures, repeat across the commands by design:
# Typer reads each command's options from its own signature.
from ewb_ident.cli.options import (
    EXIT_UNTRUSTWORTHY,
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
    read_traces,
    writing,
)


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
    fix: FixOption = None,
    integrator: IntegratorOption = "exponential",
    with_: WithOption = None,
    with_diagnosis: WithDiagnosisOption = None,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Least-squares fit; writes OUT/fit.json and prints a summary."""
    check_out(out)
    mechanisms = mechanism_option(with_, with_diagnosis)
    if mechanisms is not None:
        corrected_options(traces, stage, free, per_trace, fix, integrator)
        _fit_corrected(traces[0], out, *mechanisms, mapping, fill_gaps, no_unit_check, r_eff)
        return
    from ewb_ident.data.outputs import json_writer, write_run
    from ewb_ident.inference.least_squares import fit as run_fit
    from ewb_ident.reporting.summaries import fit_summary

    method = integrator_option(integrator)
    try:
        trs = read_traces(traces, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        result = run_fit(
            trs,
            stage=stage,
            free=name_list(free),
            per_trace=name_list(per_trace),
            fixed=assignments(fix, "--fix"),
            integrator=method,
        )
    except bad_input_errors() as err:
        fail(str(err))
    document = result.to_json() | {"traces": [str(p) for p in traces]}
    with writing(out):
        write_run(out, "fit", [(out / "fit.json", json_writer(document))])
    typer.echo(fit_summary(result))
    typer.echo(f"wrote {out / 'fit.json'}")
    if result.status != "ok":
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _fit_corrected(
    trace, out, mechanisms, learned, mapping, fill_gaps, no_unit_check, r_eff
) -> None:
    from ewb_ident.data.outputs import json_writer, write_run
    from ewb_ident.diagnosis.corrected import fit_corrected
    from ewb_ident.diagnosis.session import DiagnoseError
    from ewb_ident.reporting.summaries import corrected_summary

    try:
        (tr,) = read_traces([trace], ("chain",), mapping, fill_gaps, no_unit_check, r_eff)
        result = fit_corrected(tr, mechanisms, learned)
    except (*bad_input_errors(), DiagnoseError) as err:
        fail(str(err))
    document = result.to_json() | {"traces": [str(trace)]}
    with writing(out):
        write_run(out, "fit", [(out / "fit.json", json_writer(document))])
    typer.echo(corrected_summary(result))
    typer.echo(f"wrote {out / 'fit.json'}")
    if not result.converged:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)
