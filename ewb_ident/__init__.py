"""ewb-ident: fit, quantify and diagnose a physical model of an EWB test rig.

Every public function computes in float64 whatever JAX's global setting
(:mod:`ewb_ident.model.numerics`).

>>> import ewb_ident as ei
>>> trace = ei.read_trace("datasets/steps_200hz.csv")
>>> result = ei.fit(trace)              # whole chain from voltage
>>> result.params[0].a, result.stderr["a"], result.metrics["force_N"]
>>> posterior = ei.sample(trace)      # emcee posterior of a, b, c, mu, ...
>>> diagnosis = ei.diagnose(trace)    # where the model misses, and what physics

The names below are imported on first use, so that ``ewb-ident --help`` does not pay
for importing JAX.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_PUBLIC = {
    "FitError": "inference.problem",
    "FitResult": "inference.fit_result",
    "fit": "inference.least_squares",
    "DiagnoseError": "diagnosis.session",
    "DiagnosisResult": "diagnosis.result",
    "diagnose": "diagnosis.diagnose",
    "PosteriorResult": "inference.posterior_result",
    "SampleError": "inference.log_posterior",
    "sample": "inference.posterior",
    "channel_metrics": "data.metrics",
    "PARAMS": "model.params",
    "SEED": "model.params",
    "EWBParams": "model.params",
    "Integrator": "model.integrate",
    "NumericalWarning": "model.integrate",
    "simulate_chain": "model.integrate",
    "simulate_motor": "model.integrate",
    "Trace": "data.trace",
    "TraceError": "data.trace",
    "read_trace": "data.readers",
    "write_trace": "data.writers",
}

__all__ = sorted(_PUBLIC)

if TYPE_CHECKING:
    from ewb_ident.data.metrics import channel_metrics as channel_metrics
    from ewb_ident.data.readers import read_trace as read_trace
    from ewb_ident.data.trace import Trace as Trace
    from ewb_ident.data.trace import TraceError as TraceError
    from ewb_ident.data.writers import write_trace as write_trace
    from ewb_ident.diagnosis.diagnose import diagnose as diagnose
    from ewb_ident.diagnosis.result import DiagnosisResult as DiagnosisResult
    from ewb_ident.diagnosis.session import DiagnoseError as DiagnoseError
    from ewb_ident.inference.fit_result import FitResult as FitResult
    from ewb_ident.inference.least_squares import fit as fit
    from ewb_ident.inference.log_posterior import SampleError as SampleError
    from ewb_ident.inference.posterior import sample as sample
    from ewb_ident.inference.posterior_result import PosteriorResult as PosteriorResult
    from ewb_ident.inference.problem import FitError as FitError
    from ewb_ident.model.integrate import Integrator as Integrator
    from ewb_ident.model.integrate import NumericalWarning as NumericalWarning
    from ewb_ident.model.integrate import simulate_chain as simulate_chain
    from ewb_ident.model.integrate import simulate_motor as simulate_motor
    from ewb_ident.model.params import PARAMS as PARAMS
    from ewb_ident.model.params import SEED as SEED
    from ewb_ident.model.params import EWBParams as EWBParams


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    raise AttributeError(f"module 'ewb_ident' has no attribute {name!r}")
