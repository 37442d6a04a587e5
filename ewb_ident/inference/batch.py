"""One trace of a batch: read it, fit the whole chain, and keep what the campaign's
table needs as a plain record (JSON-ready, picklable, the same on a Dask worker).

The fit is :func:`ewb_ident.inference.least_squares.fit` on the one trace, as
``ewb-ident fit TRACE`` runs it; with the job's sampler settings, the posterior of
:func:`ewb_ident.inference.posterior.sample` too (``batch --posterior``: each interval is
then the 90 % HDI). A trace that cannot be read or fitted gives a record with
``status: "error"`` and its message on one line; the campaign goes on. The diagnosis and
the corrected model (``batch --diagnose``) sit a layer above, in
:mod:`ewb_ident.diagnosis.batch`, which runs this first.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ewb_ident.data.campaign import Entry, file_hash, with_pad_radius
from ewb_ident.data.metrics import Z90
from ewb_ident.data.readers import read_trace
from ewb_ident.data.stages import CHANNELS
from ewb_ident.data.trace import Trace, error_line
from ewb_ident.inference.compare import EFFECTIVE_WITHOUT_CURRENT
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.log_posterior import SamplerSettings
from ewb_ident.model.params import MODEL_PARAMS, PARAMS

#: What the interval of a row comes from: the robust standard error, or the posterior's
#: 90 % HDI (``batch --posterior``).
FROM_STDERR = "stderr"
FROM_POSTERIOR = "posterior"


# A frozen record of its fields, like the package's other records: alike in shape only.
@dataclass(frozen=True)
class TraceJob:
    """Everything a worker needs to fit one trace (plain values, picklable).

    Attributes
    ----------
    trace
        The path as given (the table's ``trace`` column).
    path
        The file to read.
    mapping
        Column-mapping file, or ``None``.
    r_eff_m
        Pad radius override, m, or ``None`` (sidecar, else default).
    fill_gaps, check_units
        As ``--fill-gaps`` and the opposite of ``--no-unit-check``.
    key
        Hash of the trace's bytes (table, sidecar, mapping) and these settings: a
        record under this key can be reused.
    hashes
        SHA-256 of the trace's table, sidecar and mapping files (``None``: no such file).
    posterior
        Sampler settings when the posterior is sampled (``batch --posterior``), else
        ``None``.
    diagnose
        Whether the trace is diagnosed (``batch --diagnose``;
        :func:`ewb_ident.diagnosis.batch.run_job`).
    """

    trace: str
    path: str
    mapping: str | None
    r_eff_m: float | None
    fill_gaps: bool
    check_units: bool
    key: str
    hashes: dict[str, str | None] = field(default_factory=dict, compare=False)
    posterior: SamplerSettings | None = None
    diagnose: bool = False


def make_job(
    entry: Entry,
    *,
    fill_gaps: bool,
    check_units: bool,
    version: str,
    posterior: SamplerSettings | None = None,
    diagnose: bool = False,
) -> TraceJob:
    """The job of a campaign entry, keyed by its files' hashes and the settings (the
    sampler's settings and the diagnosis among them, when asked for: a record made
    without them is not reused for a run with them, nor the other way round)."""
    side = entry.path.with_suffix(".json")
    identity = {
        "trace_sha256": file_hash(entry.path),
        "sidecar_sha256": file_hash(side) if side.is_file() else None,
        "mapping_sha256": file_hash(entry.mapping) if entry.mapping is not None else None,
        "r_eff_m": entry.r_eff_m,
        "fill_gaps": fill_gaps,
        "check_units": check_units,
        "stage": "chain",
        "version": version,
    }
    if posterior is not None:  # (absent otherwise: a plain batch's keys stay as they were)
        identity["posterior"] = dataclasses.asdict(posterior)
    if diagnose:
        identity["diagnose"] = True
    key = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:24]
    return TraceJob(
        entry.trace,
        str(entry.path.resolve()),  # a worker's working folder is not ours
        None if entry.mapping is None else str(entry.mapping.resolve()),
        entry.r_eff_m,
        fill_gaps,
        check_units,
        key,
        {k: identity[k] for k in ("trace_sha256", "sidecar_sha256", "mapping_sha256")},
        posterior,
        diagnose,
    )


def _why(result) -> str | None:
    """Why a fit is not trustworthy, in a line (``None`` for status ``ok``): the
    solver's message, or the acceptance warning that rejected it."""
    if result.status == "ok":
        return None
    if result.status == "poor_fit":
        marks = ("acceptance", "flat", "not finite")
        return next((w for w in result.warnings if any(m in w for m in marks)), result.message)
    return result.message


def fit_job(job: TraceJob) -> dict[str, Any]:
    """Read and fit one trace (and sample its posterior when the job says so); never
    raises for a bad trace, a failed solve or a failed sampler.

    Returns
    -------
    dict
        ``key``, ``trace``, ``status`` (``ok``, ``not_converged``, ``poor_fit`` or
        ``error``), ``message`` (the error, one line; else ``None``), ``converged``,
        ``params`` (per free model parameter: ``unit``, ``estimate``, ``stderr``,
        ``low_90``, ``high_90``, ``interval_from``, and with the posterior its
        ``posterior_mean`` and ``posterior_sd``; SI units; without ``current_A`` the
        motor's ``L``, ``kb`` and ``M`` are effective values, with ``R`` and ``v`` held,
        and are left out, as ``compare`` leaves them), ``metrics`` (NRMSE, %, per
        recorded channel), ``r_eff_m``, ``warnings`` and ``fit_seconds``; with the
        posterior ``posterior_converged`` and ``posterior_message`` (why not, or the
        sampler's error).
    """
    return fitted(job)[0]


def fitted(job: TraceJob) -> tuple[dict[str, Any], Trace | None]:
    """:func:`fit_job`'s record, and the trace as read (``None`` when it could not be
    read or fitted), for a diagnosis of the same trace."""
    t0 = time.perf_counter()
    record: dict[str, Any] = {"key": job.key, "trace": job.trace, "params": {}, "metrics": {},
                              "warnings": [], "r_eff_m": None, "converged": None}
    try:
        trace = read_trace(
            job.path,
            mapping=job.mapping,
            stages=("chain",),
            nan_policy="interpolate" if job.fill_gaps else "raise",
            check_units=job.check_units,
        )
        trace = with_pad_radius(trace, job.r_eff_m)
        result = fit(trace)
    except Exception as err:  # a failed trace is a row of the table, not a crash
        return record | {"status": "error", "message": error_line(err),
                         "fit_seconds": time.perf_counter() - t0}, None
    effective = () if trace.has("current_A") else EFFECTIVE_WITHOUT_CURRENT
    names = [n for n in result.free if n in MODEL_PARAMS and n not in effective]
    record["params"] = parameter_rows(
        {n: float(result.values[n]) for n in names}, result.stderr, PARAMS_UNITS
    )
    metrics = result.trace_metrics[0]
    record["metrics"] = {ch: (metrics.get(ch) or {}).get("nrmse_pct") for ch in CHANNELS
                         if ch in metrics}
    record |= {
        "status": result.status,
        "message": _why(result),
        "converged": bool(result.converged),
        "r_eff_m": float(result.r_eff[0][0]),
        "warnings": list(result.warnings),
        "fit_seconds": time.perf_counter() - t0,
    }
    if job.posterior is not None:
        from ewb_ident.inference.posterior import sample

        t1 = time.perf_counter()
        try:
            post = sample(trace, settings=job.posterior)
        except Exception as err:  # the fit's row stands, with the sampler's error
            record |= {"posterior_converged": False,
                       "posterior_message": f"posterior not sampled: {error_line(err)}"}
        else:
            record |= with_posterior(record["params"], post)
        record["posterior_seconds"] = time.perf_counter() - t1
    return record, trace


#: The SI unit of every model parameter.
PARAMS_UNITS = {name: spec.unit for name, spec in PARAMS.items()}


def parameter_rows(
    values: dict[str, float],
    stderrs: dict[str, float | None],
    units: dict[str, str],
) -> dict[str, dict[str, Any]]:
    """Per parameter (those of ``values`` with a unit in ``units``): ``unit``,
    ``estimate``, ``stderr`` and the 90 % interval ``estimate +- 1.645 stderr``
    (``interval_from``: ``stderr``; all ``None`` without a usable standard error)."""
    rows = {}
    for name, est in values.items():
        if name not in units:
            continue
        se = stderrs.get(name)
        ok = se is not None and se == se and se > 0
        rows[name] = {
            "unit": units[name],
            "estimate": float(est),
            "stderr": float(se) if ok else None,
            "low_90": est - Z90 * se if ok else None,
            "high_90": est + Z90 * se if ok else None,
            "interval_from": FROM_STDERR if ok else None,
        }
    return rows


def with_posterior(params: dict[str, dict[str, Any]], post) -> dict[str, Any]:
    """Put a posterior's 90 % HDIs in place of the standard-error intervals of
    ``params`` (in place), for the parameters it sampled; returns the record's
    ``posterior_converged`` and ``posterior_message`` (its warnings, when it did not
    converge)."""
    for name, row in params.items():
        st = post.stats.get(name) or {}
        lo, hi = st.get("hdi_low"), st.get("hdi_high")
        if st.get("source") != "posterior" or lo is None or hi is None:
            continue
        row |= {"low_90": float(lo), "high_90": float(hi), "interval_from": FROM_POSTERIOR,
                "posterior_mean": st.get("mean"), "posterior_sd": st.get("sd")}
    first = " ".join((post.warnings or ("no reason given",))[0].split())
    said = None if post.converged else f"posterior not converged: {first}"
    return {"posterior_converged": bool(post.converged), "posterior_message": said}


def record_path(folder: Path, key: str) -> Path:
    """Where a trace's record is kept for resuming: ``folder/traces/<key>.json``."""
    return Path(folder) / "traces" / f"{key}.json"
