"""``ewb-ident diagnose``: find the physics the model leaves out."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

# The shared options and checks this command uses. These lists, and the trace options
# (--map, --fill-gaps, ...) in the signatures, repeat across the commands by design:
# Typer reads each command's options from its own signature.
from ewb_ident.cli.options import (
    FillGaps,
    Mapping,
    NoUnitCheck,
    OutDir,
    REff,
    Status,
    app,
    bad_input_errors,
    check_out,
    fail,
    name_list,
    read_traces,
    writing,
)


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
    check_out(out)
    from ewb_ident.diagnosis.diagnose import diagnose as run_diagnose
    from ewb_ident.diagnosis.session import DiagnoseError
    from ewb_ident.reporting.figures import write_diagnosis

    if not bic_threshold > 0:
        fail(f"--bic-threshold must be a positive number, got {bic_threshold!r}")
    try:
        (tr,) = read_traces([trace], None, mapping, fill_gaps, no_unit_check, r_eff)
        with Status("diagnosing") as say:
            result = run_diagnose(
                tr, bic_threshold=bic_threshold, catalog=name_list(catalog), progress=say
            )
    except (*bad_input_errors(), DiagnoseError) as err:
        fail(str(err))
    with writing(out):
        paths = write_diagnosis(result, out, extra={"traces": [str(trace)]}, figures=figures)
    typer.echo(result.summary())
    typer.echo(f"wrote {out / 'diagnosis.json'} and {len(paths) - 1} figure(s)")
