"""``ewb-ident batch``: refit a campaign of recorded traces, in this process or on a
Dask cluster, and write its table, population, changes and report."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from ewb_ident.cli.options import (
    EXIT_UNTRUSTWORTHY,
    FillGaps,
    Mapping,
    NoUnitCheck,
    OutDir,
    REff,
    Status,
    app,
    check_out,
    command_line,
    fail,
    writing,
)


@app.command()
def batch(
    source: Annotated[
        str,
        typer.Argument(
            help="Manifest (.csv/.parquet with a 'path' column and metadata columns), a "
            "folder of traces, or a glob (quoted).",
            show_default=False,
        ),
    ],
    out: OutDir,
    scheduler: Annotated[
        str | None,
        typer.Option(help="Dask scheduler address (tcp://host:8786); default: in-process."),
    ] = None,
    group_by: Annotated[
        str | None,
        typer.Option(
            "--group-by",
            help="Metadata column whose groups are compared (changes.*; every group against "
            "the first in sorted order) and plotted against.",
        ),
    ] = None,
    worker_timeout: Annotated[
        float | None,
        typer.Option(
            help="Seconds to wait for a first Dask worker before giving up (default: 120, "
            "ewb_ident.study.WORKER_TIMEOUT_S).",
            show_default=False,
        ),
    ] = None,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Refit every trace of a campaign (whole chain): writes OUT/results.{parquet,csv},
    OUT/population.*, OUT/changes.* (with --group-by), OUT/index.html and OUT/batch.json.
    A rerun into the same OUT reuses the traces whose files and settings are unchanged.
    Exits 3 when a trace failed, did not converge or is outside the acceptance."""
    import math

    from ewb_ident.study import CONNECT_TIMEOUT_S, WORKER_TIMEOUT_S

    check_out(out)
    worker_timeout = WORKER_TIMEOUT_S if worker_timeout is None else worker_timeout
    if not (math.isfinite(worker_timeout) and worker_timeout > 0):
        fail(f"--worker-timeout must be a positive number of seconds, got {worker_timeout!r}")
    import ewb_ident
    from ewb_ident.data.campaign import CampaignError, resolve_campaign
    from ewb_ident.inference.batch import make_job
    from ewb_ident.reporting.campaign import RESULT_COLUMNS

    try:
        campaign = resolve_campaign(source, mapping=mapping, r_eff_m=r_eff,
                                    reserved=RESULT_COLUMNS, exclude=out)
    except CampaignError as err:
        fail(str(err))
    for old, new in campaign.renamed.items():
        typer.echo(f"{source}: metadata column {old!r} is {new!r} in the results table "
                   f"({old!r} is the parameter's unit there)", err=True)
    group_by = campaign.renamed.get(group_by, group_by)
    if group_by is not None and group_by not in campaign.metadata_columns:
        have = ", ".join(campaign.metadata_columns) or "none (give a manifest)"
        fail(f"--group-by {group_by}: not a metadata column of {source} (columns: {have})")
    try:
        jobs = [make_job(e, fill_gaps=fill_gaps, check_units=not no_unit_check,
                         version=ewb_ident.__version__) for e in campaign.entries]
    except OSError as err:
        fail(f"{err.filename}: cannot read it ({err.strerror}); check its permissions")
    client = None
    if scheduler is not None:
        from ewb_ident.study import ClusterError, connect

        try:
            client = connect(scheduler, connect_timeout=CONNECT_TIMEOUT_S,
                             worker_timeout=worker_timeout,
                             say=lambda text: typer.echo(text, err=True))
        except ClusterError as err:
            fail(str(err))
    try:
        _run(campaign, jobs, out, client, group_by, source,
             {"map": mapping, "r_eff_m": r_eff, "fill_gaps": fill_gaps,
              "check_units": not no_unit_check, "group_by": group_by, "stage": "chain",
              "worker_timeout_s": worker_timeout})
    finally:
        if client is not None:
            client.close()


def _run(campaign, jobs, out: Path, client, group_by, source: str, settings) -> None:
    from ewb_ident.study import cluster_description, run_batch

    where = cluster_description(client)
    ran = ("in this process" if client is None else
           f"on the Dask cluster at {where['address']} with {where['workers']} worker(s)")
    typer.echo(f"batch of {len(jobs)} traces from {source}, running {ran}")
    out.mkdir(parents=True, exist_ok=True)
    with Status("batch") as say:

        def progress(done: int, total: int, record: dict[str, Any], reused: bool) -> None:
            how = "reused" if reused else f"{record.get('fit_seconds', 0):.1f} s"
            said = f": {record['message']}" if record["status"] == "error" else ""
            say(f"{done}/{total} {record['trace']}: {record['status']} ({how}){said}")

        records, reused = run_batch(jobs, out, client=client, progress=progress)
    fitted = len(jobs) - reused
    counts = {"traces": len(jobs), "reused": reused, "fitted": fitted}
    for status in ("ok", "error", "not_converged", "poor_fit"):
        counts[status] = sum(r["status"] == status for r in records)
    provenance = _provenance(campaign, jobs, records, where, settings, counts)
    _write(out, campaign, records, group_by, provenance)
    typer.echo(f"{reused} reused, {fitted} fitted; wrote {out / 'results.parquet'}, "
               f"results.csv, population.*{', changes.*' if group_by else ''}, index.html and "
               "batch.json")
    bad = len(jobs) - counts["ok"]
    if bad:
        typer.echo(f"{bad} of {len(jobs)} traces not trustworthy: {counts['error']} failed, "
                   f"{counts['not_converged']} did not converge, {counts['poor_fit']} outside "
                   "the acceptance (see the flagged list in index.html)")
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _provenance(campaign, jobs, records, where, settings, counts) -> dict[str, Any]:
    import platform
    from importlib.metadata import PackageNotFoundError, version

    import ewb_ident
    from ewb_ident.inference.batch import record_path

    versions = {"ewb_ident": ewb_ident.__version__, "python": platform.python_version()}
    for dist in ("jax", "numpy", "scipy", "pandas", "pyarrow", "dask", "distributed"):
        try:
            versions[dist] = version(dist)
        except PackageNotFoundError:
            versions[dist] = None
    inputs = []
    for e, job, rec in zip(campaign.entries, jobs, records, strict=True):
        inputs.append({
            "trace": e.trace, "path": str(e.path), "sha256": job.hashes["trace_sha256"],
            "sidecar_sha256": job.hashes["sidecar_sha256"],
            "map": None if e.mapping is None else str(e.mapping),
            "map_sha256": job.hashes["mapping_sha256"], "r_eff_m": e.r_eff_m,
            "metadata": e.metadata, "key": job.key,
            "record": str(record_path(Path("."), job.key)), "status": rec["status"],
            "fit_seconds": rec.get("fit_seconds"),
        })
    return {
        "command": command_line(),
        "source": campaign.source,
        "source_kind": campaign.kind,
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in settings.items()},
        "where": where,
        "counts": counts,
        "inputs": inputs,
        "versions": versions,
    }


def _write(out: Path, campaign, records, group_by, provenance) -> None:
    from ewb_ident.data.outputs import json_writer, null_nonfinite, write_run
    from ewb_ident.reporting.campaign import (
        campaign_page,
        changes_table,
        parameter_figure,
        population_table,
        results_table,
    )

    results = results_table(records, [e.metadata for e in campaign.entries],
                            campaign.metadata_columns)
    population = population_table(results, group_by)
    changes = changes_table(results, group_by) if group_by else None
    if changes is not None:
        changes.attrs["group_by"] = group_by
    png = parameter_figure(results, group_by)
    page = campaign_page(results, population, changes, against=group_by,
                         figure=None if png is None else "parameters.png",
                         provenance=provenance)
    tables = {"results": results, "population": population}
    if changes is not None:
        tables["changes"] = changes
    writers = []
    for name, frame in tables.items():
        writers += [
            (out / f"{name}.parquet", lambda tmp, f=frame: f.to_parquet(tmp, index=False)),
            (out / f"{name}.csv", lambda tmp, f=frame: f.to_csv(tmp, index=False)),
        ]
    if png is not None:
        writers.append((out / "parameters.png", lambda tmp: tmp.write_bytes(png)))
    writers += [
        (out / "batch.json", json_writer(null_nonfinite(provenance))),
        (out / "index.html", lambda tmp: tmp.write_text(page, encoding="utf-8")),
    ]
    # One run's files as a set: an earlier run's changes.* or parameters.png that this
    # run did not write (no --group-by, no plotted parameter) would contradict it.
    with writing(out):
        write_run(out, "batch", writers)
    _echo_tables(population, changes)


def _echo_tables(population, changes) -> None:
    from ewb_ident.data.units import shown_unit

    def shown(unit: str, v) -> str:
        _, k = shown_unit(unit)
        return "–" if v is None or v != v else f"{v * k:.4g}"

    pop = population[population["group"] == "all"] if not population.empty else population
    if not pop.empty:
        typer.echo("population (random effects; 90 % intervals; a, c, p-coefficients in mm/µm/nm):")
        for r in pop.itertuples():
            typer.echo(f"  {r.parameter:<5} mean {shown(r.unit, r.mean)} "
                       f"[{shown(r.unit, r.low_90)}, "
                       f"{shown(r.unit, r.high_90)}]  tau "
                       f"{shown(r.unit, r.tau)}  (n = {r.n_traces})")
    if changes is not None and not changes.empty:
        moved = changes[changes["changed"]]
        typer.echo("changed: " + (", ".join(
            f"{r.parameter} {r.before} -> {r.after} {r.delta_pct:+.1f} % "
            f"[{100 * r.low_90 / r.before_mean:+.1f}, {100 * r.high_90 / r.before_mean:+.1f}] %"
            for r in moved.itertuples()) or "no parameter (P(|change| > tolerance) > 0.95)"))
