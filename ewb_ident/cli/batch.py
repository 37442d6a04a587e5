"""``ewb-ident batch``: refit a campaign of recorded traces, in this process or on a
Dask cluster, and write its table, population, changes and report."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

# The shared options and checks this command uses. These lists, and the trace options
# (--map, --fill-gaps, ...) in the signatures, repeat across the commands by design:
# Typer reads each command's options from its own signature.
from ewb_ident.cli.options import (
    EXIT_UNTRUSTWORTHY,
    SAMPLER_OPTIONS,
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
    sampler_settings,
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
    cycles: Annotated[
        bool,
        typer.Option(
            "--cycles",
            help="SOURCE is a long recording (an endurance log; or a folder, glob or manifest "
            "of them): split each into its apply cycles and fit every cycle. Writes "
            "OUT/cycles/ (the cycles as traces), cycles.{csv,parquet,png} (the split) and "
            "trend.* (each parameter against time_h).",
        ),
    ] = False,
    split_on: Annotated[
        str | None,
        typer.Option(
            "--split-on",
            help="Channel the cycles are found on (default: force_N, else x_m, else "
            "theta_deg).",
            show_default=False,
        ),
    ] = None,
    trend: Annotated[
        str | None,
        typer.Option(
            help="Numeric metadata column each parameter's linear trend is fitted against "
            "(trend.*; default with --cycles: time_h, hours into the log).",
            show_default=False,
        ),
    ] = None,
    unit_column: Annotated[
        str | None,
        typer.Option(
            "--unit-column",
            help="Metadata column naming each trace's rig unit: the population separates "
            "the unit-to-unit spread from the trace-to-trace spread within a unit (default: "
            "the manifest's 'unit' column, when it has one).",
            show_default=False,
        ),
    ] = None,
    diagnose: Annotated[
        bool,
        typer.Option(
            "--diagnose",
            help="Diagnose every trace as 'ewb-ident diagnose' does: fills verdict and "
            "findings, and adds the corrected model's rows (model: corrected) for a trace "
            "with a finding.",
        ),
    ] = False,
    posterior: Annotated[
        bool,
        typer.Option(
            "--posterior",
            help="Sample every trace's posterior (emcee, as 'ewb-ident sample'): each "
            "interval is the 90 % HDI (interval_from: posterior).",
        ),
    ] = False,
    # The sampler's settings under --posterior, alike in shape: one option each, no
    # default shown (SamplerSettings holds the defaults).
    steps: Annotated[
        int | None,
        typer.Option(help="With --posterior: MCMC steps per ensemble planned (default 2000).",
                     show_default=False),
    ] = None,
    max_steps: Annotated[
        int | None,
        typer.Option(help="With --posterior: extend each run until converged or this many "
                     "steps (default 10x --steps).", show_default=False),
    ] = None,
    min_ess: Annotated[
        float | None,
        typer.Option(help="With --posterior: ESS every parameter needs (default 400).",
                     show_default=False),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option(help="With --posterior: seed of the MCMC, the same for every trace "
                     "(default 0).", show_default=False),
    ] = None,
    mapping: Mapping = None,
    fill_gaps: FillGaps = False,
    no_unit_check: NoUnitCheck = False,
    r_eff: REff = None,
) -> None:
    """Refit every trace of a campaign (whole chain; with --posterior and --diagnose also
    its posterior, diagnosis and corrected model): writes OUT/results.{parquet,csv},
    OUT/population.*, OUT/changes.* (with --group-by), OUT/trend.* (with --trend or
    --cycles), OUT/index.html and OUT/batch.json. A rerun into the same OUT reuses the
    traces whose files and settings are unchanged. Exits 3 when a trace failed, did not
    converge or is outside the acceptance, or its posterior or diagnosis did not."""
    import dataclasses
    import math

    from ewb_ident.study import CONNECT_TIMEOUT_S, WORKER_TIMEOUT_S

    check_out(out)
    worker_timeout = WORKER_TIMEOUT_S if worker_timeout is None else worker_timeout
    if not (math.isfinite(worker_timeout) and worker_timeout > 0):
        fail(f"--worker-timeout must be a positive number of seconds, got {worker_timeout!r}")
    sampler = _sampler(posterior, steps, max_steps, min_ess, seed)
    import ewb_ident
    from ewb_ident.data.campaign import CampaignError, resolve_campaign
    from ewb_ident.inference.batch import make_job
    from ewb_ident.reporting.campaign import RESULT_COLUMNS

    if split_on is not None and not cycles:
        fail("--split-on is a setting of --cycles; add --cycles or drop it")
    try:
        campaign = resolve_campaign(source, mapping=mapping, r_eff_m=r_eff,
                                    reserved=RESULT_COLUMNS, exclude=out, logs=cycles)
    except CampaignError as err:
        fail(str(err))
    for old, new in campaign.renamed.items():
        typer.echo(f"{source}: metadata column {old!r} is {new!r} in the results table "
                   f"({old!r} is the parameter's unit there)", err=True)
    group_by = campaign.renamed.get(group_by, group_by)
    if unit_column is None and "unit" in campaign.renamed:  # the manifest's own 'unit'
        unit_column = "unit"
    unit_column = campaign.renamed.get(unit_column, unit_column)
    # Every check of the command line before the logs are split (which writes cycles/).
    from ewb_ident.data.cycles import CYCLE_COLUMNS

    if cycles:
        trend = "time_h" if trend is None else trend
    columns = (*campaign.metadata_columns, *(CYCLE_COLUMNS if cycles else ()))
    for option, column in (("--group-by", group_by), ("--trend", trend),
                           ("--unit-column", unit_column)):
        if column is not None and column not in columns:
            have = ", ".join(columns) or "none (give a manifest)"
            fail(f"{option} {column}: not a metadata column of {source} (columns: {have})")
    if trend is not None:
        _check_numeric(campaign, trend, source, cycles)
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
        split = None
        if cycles:
            campaign, split = _split_logs(campaign, out, split_on, fill_gaps,
                                          not no_unit_check)
            mapping = None  # the cycles are written in SI units under the format's names
        try:
            jobs = [make_job(e, fill_gaps=fill_gaps, check_units=not no_unit_check,
                             version=ewb_ident.__version__, posterior=sampler,
                             diagnose=diagnose) for e in campaign.entries]
        except OSError as err:
            fail(f"{err.filename}: cannot read it ({err.strerror}); check its permissions")
        _run(campaign, jobs, out, client, group_by, source,
             {"map": mapping, "r_eff_m": r_eff, "fill_gaps": fill_gaps,
              "check_units": not no_unit_check, "group_by": group_by, "stage": "chain",
              "worker_timeout_s": worker_timeout, "trend": trend, "cycles": cycles,
              "split": None if split is None else split[2], "unit_column": unit_column,
              "diagnose": diagnose,
              "posterior": None if sampler is None else dataclasses.asdict(sampler)},
             split)
    finally:
        if client is not None:
            client.close()


def _sampler(posterior: bool, steps, max_steps, min_ess, seed):
    """The sampler settings of --posterior (``None`` without it); a sampler option
    without --posterior, or a setting that cannot be used, is one line, exit 2."""
    given = {"n_steps": steps, "max_steps": max_steps, "min_ess": min_ess, "seed": seed}
    given = {k: v for k, v in given.items() if v is not None}
    if not posterior:
        if given:
            fail(
                f"{SAMPLER_OPTIONS[next(iter(given))]} is a setting of --posterior; add "
                "--posterior or drop it"
            )
        return None
    return sampler_settings(**given)


def _split_logs(campaign, out: Path, channel, fill_gaps: bool, check_units: bool):
    """The campaign of the logs' apply cycles, their files written under OUT/cycles/;
    a log that cannot be read or split is one line, exit 2, and no cycle file is left;
    nor is one when the split is interrupted."""
    import time

    from ewb_ident.data.campaign import file_hash
    from ewb_ident.data.cycles import CycleRule, cycle_campaign
    from ewb_ident.data.outputs import missing_folders, removed_if_interrupted
    from ewb_ident.data.trace import InputError

    rule = CycleRule(channel=channel)
    folder = out / "cycles"
    t0 = time.perf_counter()
    with removed_if_interrupted(None if folder.exists() else folder, missing_folders(out)):
        try:
            cycles, splits, table = cycle_campaign(campaign, folder, rule=rule,
                                                   fill_gaps=fill_gaps, check_units=check_units)
        except InputError as err:
            fail(str(err))
    for log in splits:
        s = log.split
        typer.echo(f"{log.name}: {len(s.complete)} apply cycles ({len(s.cycles) - len(s.complete)}"
                   f" partial, not fitted) where {s.channel} rises above {s.threshold:.4g}; "
                   f"read and split in {time.perf_counter() - t0:.1f} s", err=True)
    logs = [{"log": e.trace, "sha256": file_hash(e.path), "channel": s.split.channel,
             "threshold": s.split.threshold, "cycles": len(s.split.complete),
             "partial": len(s.split.cycles) - len(s.split.complete)}
            for e, s in zip(campaign.entries, splits, strict=True)]
    return cycles, (splits, table, {"rule": vars(rule), "logs": logs})


def _check_numeric(campaign, column: str, source: str, cycles: bool) -> None:
    if cycles and column == "log":
        fail("--trend log: the log's name is not a number; fit the trend against time_h, "
             "cycle, t_start_s or t_rise_s")
    values = [e.metadata.get(column) for e in campaign.entries]
    for v in values:
        if v is None:
            continue
        try:
            float(v)
        except (TypeError, ValueError):
            fail(f"--trend {column}: {v!r} is not a number; the trend is fitted against a "
                 f"numeric column of {source} (a time, a cycle count, a date as days)")


def _run(campaign, jobs, out: Path, client, group_by, source: str, settings,
         split=None) -> None:
    from ewb_ident.study import cluster_description, run_batch

    where = cluster_description(client)
    ran = ("in this process" if client is None else
           f"on the Dask cluster at {where['address']} with {where['workers']} worker(s)")
    typer.echo(f"batch of {len(jobs)} traces from {source}, running {ran}")
    out.mkdir(parents=True, exist_ok=True)
    with Status("batch") as say:

        def progress(done: int, total: int, record: dict[str, Any], reused: bool) -> None:
            spent = sum(record.get(k) or 0.0 for k in ("fit_seconds", "posterior_seconds",
                                                       "diagnose_seconds"))
            how = "reused" if reused else f"{spent:.1f} s"
            said = f": {record['message']}" if record["status"] == "error" else ""
            found = (f", diagnosis {record['verdict']} {', '.join(record['findings'])}".rstrip()
                     if record.get("verdict") is not None else "")
            say(f"{done}/{total} {record['trace']}: {record['status']}{found} ({how}){said}")

        records, reused = run_batch(jobs, out, client=client, progress=progress)
    fitted = len(jobs) - reused
    counts = {"traces": len(jobs), "reused": reused, "fitted": fitted}
    for status in ("ok", "error", "not_converged", "poor_fit"):
        counts[status] = sum(r["status"] == status for r in records)
    counts |= _extra_counts(records, settings)
    provenance = _provenance(campaign, jobs, records, where, settings, counts)
    _write(out, campaign, records, group_by, provenance, settings, split)
    typer.echo(f"{reused} reused, {fitted} fitted; wrote {out / 'results.parquet'}, "
               f"results.csv, population.*{', changes.*' if group_by else ''}"
               f"{', trend.*' if settings['trend'] else ''}"
               f"{', cycles.*' if settings['cycles'] else ''}, index.html and batch.json")
    if settings["diagnose"]:
        hits = [f"{r['trace']} ({', '.join(r['findings']) or r['verdict']})" for r in records
                if r.get("verdict") in ("found", "unexplained")]
        more = f", and {len(hits) - 5} more" if len(hits) > 5 else ""
        typer.echo(f"diagnosis: {len(hits)} of {len(jobs)} traces carry a finding"
                   + (f": {', '.join(hits[:5])}{more}" if hits else ""))
    bad = len(jobs) - counts["ok"]
    if bad:
        typer.echo(f"{bad} of {len(jobs)} traces not trustworthy: {counts['error']} failed, "
                   f"{counts['not_converged']} did not converge, {counts['poor_fit']} outside "
                   "the acceptance (see the flagged list in index.html)")
    unsettled = counts.get("posterior_not_converged", 0) + counts.get("diagnosis_failed", 0)
    if unsettled:
        typer.echo(f"{counts.get('posterior_not_converged', 0)} posteriors did not converge "
                   f"(more --steps), {counts.get('diagnosis_failed', 0)} diagnoses failed "
                   "(see index.html and the message column)")
    if bad or unsettled:
        raise typer.Exit(EXIT_UNTRUSTWORTHY)


def _extra_counts(records, settings) -> dict[str, int]:
    """Traces whose posterior (the fit's or the corrected model's) did not converge or
    could not run, diagnoses that failed, traces with a finding."""
    counts = {}
    if settings["posterior"]:
        counts["posterior_not_converged"] = sum(
            r.get("posterior_converged") is False
            or (r.get("corrected") or {}).get("posterior_converged") is False for r in records)
    if settings["diagnose"]:
        counts["diagnosis_failed"] = sum(r.get("diagnosis_message") is not None
                                         for r in records)
        counts["with_findings"] = sum(r.get("verdict") in ("found", "unexplained")
                                      for r in records)
    return counts


def _provenance(campaign, jobs, records, where, settings, counts) -> dict[str, Any]:
    import platform

    import ewb_ident
    from ewb_ident.inference.batch import record_path
    from ewb_ident.reporting.provenance import package_versions

    versions = {"ewb_ident": ewb_ident.__version__, "python": platform.python_version()}
    versions |= package_versions(
        ("jax", "numpy", "scipy", "pandas", "pyarrow", "dask", "distributed")
    )
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


def _write(out: Path, campaign, records, group_by, provenance, settings, split) -> None:
    from ewb_ident.data.outputs import json_writer, null_nonfinite, write_run
    from ewb_ident.reporting.campaign import (
        campaign_page,
        changes_table,
        parameter_figure,
        population_table,
        results_table,
        split_figure,
        trend_figure,
        trend_table,
    )

    results = results_table(records, [e.metadata for e in campaign.entries],
                            campaign.metadata_columns)
    trend, units = settings["trend"], settings["unit_column"]
    population = population_table(results, group_by, units=units)
    changes = changes_table(results, group_by) if group_by else None
    if changes is not None:
        changes.attrs["group_by"] = group_by
    trends = trend_table(results, trend) if trend is not None else None
    png = (trend_figure(results, trend, trends) if trend is not None
           else parameter_figure(results, group_by))
    split_png = split_figure(split[0]) if split is not None else None
    page = campaign_page(results, population, changes, against=group_by,
                         figure=None if png is None else "parameters.png",
                         provenance=provenance, trends=trends,
                         cycles=None if split is None else split[1],
                         split_file=None if split_png is None else "cycles.png")
    tables = {"results": results, "population": population}
    if changes is not None:
        tables["changes"] = changes
    if trends is not None:
        tables["trend"] = trends
    if split is not None:
        tables["cycles"] = split[1]
    writers = []
    for name, frame in tables.items():
        writers += [
            (out / f"{name}.parquet", lambda tmp, f=frame: f.to_parquet(tmp, index=False)),
            (out / f"{name}.csv", lambda tmp, f=frame: f.to_csv(tmp, index=False)),
        ]
    if png is not None:
        writers.append((out / "parameters.png", lambda tmp: tmp.write_bytes(png)))
    if split_png is not None:
        writers.append((out / "cycles.png", lambda tmp: tmp.write_bytes(split_png)))
    writers += [
        (out / "batch.json", json_writer(null_nonfinite(provenance))),
        (out / "index.html", lambda tmp: tmp.write_text(page, encoding="utf-8")),
    ]
    # One run's files as a set: an earlier run's changes.* or parameters.png that this
    # run did not write (no --group-by, no plotted parameter) would contradict it.
    with writing(out):
        write_run(out, "batch", writers)
    _echo_tables(population, changes, trends)


def _echo_tables(population, changes, trends=None) -> None:
    from ewb_ident.data.units import shown_unit

    def shown(unit: str, v) -> str:
        _, k = shown_unit(unit)
        return "–" if v is None or v != v else f"{v * k:.4g}"

    pop = population[population["group"] == "all"] if not population.empty else population
    if not pop.empty:
        typer.echo("population (random effects; 90 % intervals; a, c, p-coefficients in mm/µm/nm):")
        for r in pop.itertuples():
            spread = (f"tau {shown(r.unit, r.tau)}  (n = {r.n_traces})" if r.n_units is None
                      or r.n_units != r.n_units else
                      f"tau_unit {shown(r.unit, r.tau_unit)}, tau_trace "
                      f"{shown(r.unit, r.tau_trace)}  (n = {r.n_traces} in {int(r.n_units)} units)")
            typer.echo(f"  {r.parameter:<5} mean {shown(r.unit, r.mean)} "
                       f"[{shown(r.unit, r.low_90)}, {shown(r.unit, r.high_90)}]  {spread}")
    if changes is not None and not changes.empty:
        moved = changes[changes["changed"]]
        typer.echo("changed: " + (", ".join(
            f"{r.parameter} {r.before} -> {r.after} {r.delta_pct:+.1f} % "
            f"[{100 * r.low_90 / r.before_mean:+.1f}, {100 * r.high_90 / r.before_mean:+.1f}] %"
            for r in moved.itertuples()) or "no parameter (P(|change| > tolerance) > 0.95)"))
    if trends is not None and not trends.empty:
        every = trends[trends["group"] == "all"]
        typer.echo(f"trend against {every['against'].iloc[0]} (drift over its range, 90 % "
                   "interval; * : P(|drift| > tolerance) > 0.95):")
        for r in every.itertuples():
            typer.echo(f"  {r.parameter:<5} {r.drift_pct:+.2f} % [{r.drift_low_90_pct:+.2f}, "
                       f"{r.drift_high_90_pct:+.2f}] %{'  *' if r.trend else ''}")
