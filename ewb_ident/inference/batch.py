"""One trace of a batch: read it, fit the whole chain, and keep what the campaign's
table needs as a plain record (JSON-ready, picklable, the same on a Dask worker).

The fit is :func:`ewb_ident.inference.least_squares.fit` on the one trace, as
``ewb-ident fit TRACE`` runs it. A trace that cannot be read or fitted gives a record
with ``status: "error"`` and its message on one line; the campaign goes on.
"""

from __future__ import annotations

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
from ewb_ident.data.trace import error_line
from ewb_ident.inference.compare import EFFECTIVE_WITHOUT_CURRENT
from ewb_ident.inference.least_squares import fit
from ewb_ident.model.params import MODEL_PARAMS, PARAMS

#: What the interval of a least-squares row comes from.
FROM_STDERR = "stderr"


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
    """

    trace: str
    path: str
    mapping: str | None
    r_eff_m: float | None
    fill_gaps: bool
    check_units: bool
    key: str
    hashes: dict[str, str | None] = field(default_factory=dict, compare=False)


def make_job(entry: Entry, *, fill_gaps: bool, check_units: bool, version: str) -> TraceJob:
    """The job of a campaign entry, keyed by its files' hashes and the settings."""
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
    """Read and fit one trace; never raises for a bad trace or a failed solve.

    Returns
    -------
    dict
        ``key``, ``trace``, ``status`` (``ok``, ``not_converged``, ``poor_fit`` or
        ``error``), ``message`` (the error, one line; else ``None``), ``converged``,
        ``params`` (per free model parameter: ``unit``, ``estimate``, ``stderr``,
        ``low_90``, ``high_90``, ``interval_from``; SI units; without ``current_A`` the
        motor's ``L``, ``kb`` and ``M`` are effective values, with ``R`` and ``v`` held,
        and are left out, as ``compare`` leaves them), ``metrics`` (NRMSE, %, per
        recorded channel), ``r_eff_m``, ``warnings`` and ``fit_seconds``.
    """
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
                         "fit_seconds": time.perf_counter() - t0}
    effective = () if trace.has("current_A") else EFFECTIVE_WITHOUT_CURRENT
    for name in result.free:
        if name not in MODEL_PARAMS or name in effective:
            continue
        est = float(result.values[name])
        se = result.stderr.get(name)
        ok = se is not None and se == se and se > 0
        record["params"][name] = {
            "unit": PARAMS[name].unit,
            "estimate": est,
            "stderr": float(se) if ok else None,
            "low_90": est - Z90 * se if ok else None,
            "high_90": est + Z90 * se if ok else None,
            "interval_from": FROM_STDERR if ok else None,
        }
    metrics = result.trace_metrics[0]
    record["metrics"] = {ch: (metrics.get(ch) or {}).get("nrmse_pct") for ch in CHANNELS
                         if ch in metrics}
    return record | {
        "status": result.status,
        "message": _why(result),
        "converged": bool(result.converged),
        "r_eff_m": float(result.r_eff[0][0]),
        "warnings": list(result.warnings),
        "fit_seconds": time.perf_counter() - t0,
    }


def record_path(folder: Path, key: str) -> Path:
    """Where a trace's record is kept for resuming: ``folder/traces/<key>.json``."""
    return Path(folder) / "traces" / f"{key}.json"
