"""One trace of a batch with its diagnosis (``ewb-ident batch --diagnose``): the fit of
:func:`ewb_ident.inference.batch.fit_job`, then the diagnosis ``ewb-ident diagnose``
runs, and for a trace with a finding the corrected model's parameters (with the
posterior too, when the batch samples it: the corrected model's 90 % HDIs, as
``ewb-ident report`` samples it). The record stays plain (JSON-ready, picklable, the same
on a Dask worker); a diagnosis or corrected sampler that fails leaves the fit's record
standing, with the error on one line.
"""

from __future__ import annotations

import time
from typing import Any

from ewb_ident.data.stages import CHANNELS
from ewb_ident.data.trace import error_line
from ewb_ident.inference.batch import (
    PARAMS_UNITS,
    TraceJob,
    fitted,
    parameter_rows,
    with_posterior,
)


def run_job(job: TraceJob) -> dict[str, Any]:
    """The record of one trace of a batch: :func:`~ewb_ident.inference.batch.fit_job`'s,
    and with ``job.diagnose`` the diagnosis's.

    Returns
    -------
    dict
        The fit's record; with the diagnosis also ``verdict`` (``none``, ``found`` or
        ``unexplained``; ``None`` when the diagnosis could not run), ``findings`` (the
        findings' ids, best supported first), ``diagnosis_message`` (why it could not
        run, one line), ``diagnose_seconds``, and for a trace with a finding
        ``corrected``: the corrected model's ``params`` (the fit's parameters and each
        mechanism's as ``"variant.param"``, rows as the fit's), ``metrics`` (NRMSE, %),
        ``mechanisms``, ``converged`` and, with the posterior, ``posterior_converged`` and
        ``posterior_message``.
    """
    record, trace = fitted(job)
    if not job.diagnose or trace is None:
        return record
    from ewb_ident.diagnosis.diagnose import diagnose

    _release_on_new_shape(trace)
    t0 = time.perf_counter()
    record |= {"verdict": None, "findings": [], "diagnosis_message": None}
    try:
        diag = diagnose(trace)
    except Exception as err:  # the fit stands; the diagnosis's failure is said in its row
        return record | {
            "diagnosis_message": f"diagnosis failed: {error_line(err)}",
            "diagnose_seconds": time.perf_counter() - t0,
        }
    record |= {"verdict": diag.verdict, "findings": [f.effect for f in diag.findings]}
    fix = diag.corrected
    if diag.findings and fix is not None and fix.params:
        record["corrected"] = _corrected(job, record, trace, diag, fix)
    return record | {"diagnose_seconds": time.perf_counter() - t0}


#: The shape (samples, channels) of the trace this process diagnosed last.
_LAST_SHAPE: list[tuple] = []


def _release_on_new_shape(trace) -> None:
    """Drop this process's compiled code when a trace of another shape comes: a
    diagnosis compiles a model per mechanism and trace shape, and a long campaign of many
    shapes would otherwise run into the kernel's limit on memory maps
    (:func:`ewb_ident.diagnosis.diagnose.diagnose`, notes). Traces of one shape, the
    usual campaign, keep reusing them; released programs are reloaded from disk."""
    from ewb_ident.runtime import programs

    shape = (trace.n, tuple(sorted(trace.channels)))
    if _LAST_SHAPE and _LAST_SHAPE[0] != shape:
        programs.release()
    _LAST_SHAPE[:] = [shape]


def _corrected(job: TraceJob, record: dict[str, Any], trace, diag, fix) -> dict[str, Any]:
    """The corrected model's rows: the parameters the fit freed (the same effective ones
    left out) and each finding's mechanism parameters, with their units."""
    units = {n: PARAMS_UNITS[n] for n in record["params"]}
    for f in diag.findings:
        units |= {f"{f.variant}.{p}": u for p, u in f.units.items()}
    rows = parameter_rows({n: v for n, v in fix.params.items() if n in units}, fix.stderr, units)
    out: dict[str, Any] = {
        "params": rows,
        "metrics": {
            ch: (fix.metrics.get(ch) or {}).get("nrmse_pct") for ch in CHANNELS if ch in fix.metrics
        },
        "mechanisms": list(fix.mechanisms),
        "converged": bool(fix.converged),
    }
    if job.posterior is not None:
        from ewb_ident.inference.posterior import sample_corrected

        try:
            post = sample_corrected(trace, fix, settings=job.posterior)
        except Exception as err:  # the corrected fit's rows stand, with the error
            out |= {
                "posterior_converged": False,
                "posterior_message": f"corrected posterior not sampled: {error_line(err)}",
            }
        else:
            out |= with_posterior(rows, post)
    return out
