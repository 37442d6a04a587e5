"""``ewb-ident compare``: what changed between two recordings of one rig."""

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
    Status,
    app,
    bad_input_errors,
    check_out,
    fail,
    read_traces,
    writing,
)


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
    check_out(out)
    from ewb_ident.data.outputs import json_writer, write_run
    from ewb_ident.inference.compare import compare as run_compare

    try:
        trs_old = read_traces(old, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        trs_new = read_traces(new, (stage,), mapping, fill_gaps, no_unit_check, r_eff)
        with Status("comparing") as say:
            result = run_compare(trs_old, trs_new, stage=stage, progress=say)
    except bad_input_errors() as err:
        fail(str(err))
    with writing(out):
        write_run(out, "compare", [(out / "compare.json", json_writer(result.to_json()))])
    typer.echo(result.summary())
    typer.echo(f"wrote {out / 'compare.json'}")
    if not (result.old.converged and result.new.converged):
        raise typer.Exit(EXIT_UNTRUSTWORTHY)
