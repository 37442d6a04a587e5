"""``ewb-ident study``: run a study file (TOML) or script."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ewb_ident.cli.options import EXIT_UNTRUSTWORTHY, OutDir, app, check_out, fail, writing


# The signature is the command's options (Typer): alike in shape to the other commands'
# signatures, each option its own.
@app.command()
def study(
    definition: Annotated[Path, typer.Argument(help="Study definition (TOML), see studies/.")],
    out: OutDir,
    scheduler: Annotated[
        str | None,
        typer.Option(help="Dask scheduler address (tcp://host:8786); default: in-process."),
    ] = None,
) -> None:
    """Run a study of synthetic rig cases (your own recordings: ewb-ident batch).

    Writes OUT/results.csv (one row per case and parameter) and OUT/report.md. Exits 3
    when any case failed (its error is in results.csv)."""
    check_out(out)
    import re

    address = r"(tcp|tls|ws|wss)://[^\s:/]+:\d{1,5}|inproc://\S+"
    if scheduler is not None and not re.fullmatch(address, scheduler):
        fail(f"--scheduler {scheduler!r} is not a scheduler address; give one like tcp://host:8786")
    from rich.progress import Progress

    from ewb_ident.data.outputs import write_run
    from ewb_ident.study import (
        StudyError,
        cluster_description,
        failed_cases,
        load_study,
        run_study,
        summarise,
    )

    try:
        spec = load_study(definition)
    except StudyError as err:
        fail(str(err))
    client = None
    if scheduler is not None and spec.script is None:
        from ewb_ident.study import ClusterError, connect

        try:  # before anything is written
            client = connect(scheduler, say=lambda text: typer.echo(text, err=True))
        except ClusterError as err:
            fail(str(err))
        info = cluster_description(client)
        typer.echo(
            f"running on the Dask cluster at {info['address']} with {info['workers']} worker(s)"
        )
    if spec.script is not None:
        table, report = _run_script(spec, out)
    else:
        with Progress(transient=True) as bar:
            job = bar.add_task(f"study {spec.name}", total=len(spec.cases()) or None)
            try:
                table = run_study(
                    spec,
                    scheduler=client,
                    progress=lambda done, total: bar.update(job, completed=done, total=total),
                )
            except StudyError as err:
                fail(str(err))
            finally:
                if client is not None:
                    client.close()
        report = summarise(spec, table)
        with writing(out):
            write_run(out, "study", _tables(out, table, report))
    typer.echo(report)
    typer.echo(f"wrote {out / 'results.csv'} and {out / 'report.md'}")
    failed = failed_cases(table)
    if failed:
        total = len(spec.cases()) if spec.script is None else failed
        typer.echo(
            f"{failed} of {total} cases failed (their errors are in {out / 'results.csv'})",
            err=True,
        )
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _tables(out: Path, table, report: str):
    """The writers of a study's results.csv and report.md."""
    return [
        (out / "results.csv", lambda tmp: table.to_csv(tmp, index=False)),
        (out / "report.md", lambda tmp: tmp.write_text(report, encoding="utf-8")),
    ]


def _run_script(spec, out: Path):
    """Run a script study into a staging folder inside OUT, and move what it wrote
    into OUT with results.csv and report.md as one set, only once it has returned: a
    script that raises, or an interrupt, leaves OUT as it was (a folder this run made
    is removed). The staging folder starts with the files an earlier run of the same
    script left in OUT, so a script resumes from a complete run."""
    from rich.progress import Progress

    from ewb_ident.data.outputs import staged_run, staged_writers, write_run
    from ewb_ident.study import ScriptError, run_script

    run = f"study {spec.script}"  # a rerun of the same script resumes from its files
    with staged_run(out, run) as stage, Progress(transient=True) as bar:
        job = bar.add_task(f"study {spec.name}", total=None)
        try:
            table, report = run_script(
                spec,
                stage,
                progress=lambda done, total: bar.update(job, completed=done, total=total),
            )
        except ScriptError as err:
            typer.echo(f"error: {str(err).splitlines()[0] if str(err) else err}", err=True)
            raise typer.Exit(EXIT_UNTRUSTWORTHY) from None
        writers = _tables(out, table, report)
        skip = [w[0].name for w in writers]
        with writing(out):
            write_run(out, "study", staged_writers(stage, out, skip) + writers, run=run)
    return table, report
