"""``ewb-ident validate``: a fitted model simulated on a trace it was not fitted to."""

from __future__ import annotations

from pathlib import Path
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
    app,
    bad_input_errors,
    check_out,
    fail,
    read_traces,
    writing,
)


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
    check_out(out)
    from ewb_ident.data.outputs import json_text, write_run
    from ewb_ident.diagnosis.corrected import CorrectedModel
    from ewb_ident.diagnosis.session import DiagnoseError
    from ewb_ident.inference.validate import ValidateError, load_document, load_params
    from ewb_ident.inference.validate import validate as run_validate
    from ewb_ident.reporting.report_figures import validation_figure
    from ewb_ident.reporting.summaries import validation_summary

    try:
        p = load_params(params)
        model = CorrectedModel.from_json(load_document(params), str(params))
        (tr,) = read_traces([trace], None, mapping, fill_gaps, no_unit_check, r_eff)
        result = run_validate(tr, p, model)
    except (*bad_input_errors(), ValidateError, DiagnoseError) as err:
        fail(str(err))
    text = json_text(result.to_json() | {"trace_file": str(trace), "params_file": str(params)})
    fig = validation_figure(tr, result)
    with writing(out):
        write_run(
            out,
            "validate",
            [
                (out / "validate.json", lambda tmp: tmp.write_text(text, encoding="utf-8")),
                (out / "validate.png", lambda tmp: fig.savefig(tmp, format="png", dpi=110)),
            ],
        )
    typer.echo(validation_summary(result, str(params)))
    typer.echo(f"wrote {out / 'validate.json'} and {out / 'validate.png'}")
    if not result.passes_seed:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)
