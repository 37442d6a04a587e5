"""ewb-ident: fit, quantify and diagnose a physical model of an EWB test rig.

Turn on float64 before use (the CLI does): ``jax.config.update("jax_enable_x64", True)``.

>>> import jax; jax.config.update("jax_enable_x64", True)
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
    "FitError": "least_squares",
    "FitResult": "least_squares",
    "fit": "least_squares",
    "DiagnoseError": "diagnose",
    "DiagnosisResult": "diagnose",
    "diagnose": "diagnose",
    "PosteriorResult": "posterior",
    "SampleError": "posterior",
    "sample": "posterior",
    "channel_metrics": "metrics",
    "PARAMS": "params",
    "SEED": "params",
    "EWBParams": "params",
    "Integrator": "simulate",
    "NumericalWarning": "simulate",
    "simulate_chain": "simulate",
    "simulate_motor": "simulate",
    "Trace": "traces",
    "TraceError": "traces",
    "read_trace": "traces",
    "write_trace": "traces",
}

__all__ = sorted(_PUBLIC)

if TYPE_CHECKING:
    from .diagnose import DiagnoseError as DiagnoseError
    from .diagnose import DiagnosisResult as DiagnosisResult
    from .diagnose import diagnose as diagnose
    from .least_squares import FitError as FitError
    from .least_squares import FitResult as FitResult
    from .least_squares import fit as fit
    from .metrics import channel_metrics as channel_metrics
    from .params import PARAMS as PARAMS
    from .params import SEED as SEED
    from .params import EWBParams as EWBParams
    from .posterior import PosteriorResult as PosteriorResult
    from .posterior import SampleError as SampleError
    from .posterior import sample as sample
    from .simulate import Integrator as Integrator
    from .simulate import NumericalWarning as NumericalWarning
    from .simulate import simulate_chain as simulate_chain
    from .simulate import simulate_motor as simulate_motor
    from .traces import Trace as Trace
    from .traces import TraceError as TraceError
    from .traces import read_trace as read_trace
    from .traces import write_trace as write_trace


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    raise AttributeError(f"module 'ewb_ident' has no attribute {name!r}")
