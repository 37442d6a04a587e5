"""ewb-ident: fit, quantify and diagnose a physical model of an EWB test rig.

Every public function computes in float64 whatever JAX's global setting
(:mod:`ewb_ident.model.numerics`).

>>> import ewb_ident as ei
>>> trace = ei.read_trace("datasets/steps_200hz.csv")
>>> result = ei.fit(trace)              # whole chain from voltage
>>> result.values["a"], result.stderr["a"], result.metrics["force_N"]
>>> posterior = ei.sample(trace)      # emcee posterior of a, b, c, mu, ...
>>> diagnosis = ei.diagnose(trace)    # where the model misses, and what physics

The names below are imported on first use, so that ``ewb-ident --help`` does not pay
for importing JAX.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: XLA's CPU compiler emits a ``while`` loop whose one iteration reads and writes fewer
#: bytes than this as one native loop; a larger one runs as a sequence of kernels
#: dispatched one by one on every iteration (XLA's default threshold: 1024 bytes). The
#: models' loops (the motor's sub-steps, with a Jacobian's tangents: a few kB an
#: iteration) are each some 50-200 kernels of a few numbers, so dispatch dominated them:
#: natively a mechanism's residuals and Jacobian run 1.1-7x faster and compile as fast
#: (``python -m benchmarks.bench_native_loops``), their results equal up to round-off
#: (under 1e-11 relative on the shipped concealed diagnoses). Set through ``XLA_FLAGS``,
#: which XLA reads once, when JAX starts its CPU backend: see :func:`_native_small_loops`.
SMALL_LOOP_BYTES = 1 << 20
_LOOP_KEY = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options="


def _native_small_loops() -> str:
    """Add :data:`SMALL_LOOP_BYTES` to ``XLA_FLAGS`` (into the user's
    ``--xla_backend_extra_options`` if they gave any) unless they set the threshold
    themselves, and return the threshold JAX's backend uses (part of the compiled
    programs' cache key). When JAX's backend was started before this package was
    imported, the flag cannot take effect: a warning says so, and XLA's default holds
    (the fits run slower; their results differ by round-off)."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    for f in flags:
        if f.startswith(_EXTRA) and f"{_LOOP_KEY}=" in f:
            return f.split(f"{_LOOP_KEY}=", 1)[1].split(",", 1)[0]  # the user's own
    bridge = sys.modules.get("jax._src.xla_bridge")
    started = getattr(bridge, "backends_are_initialized", lambda: False)
    if started():
        warnings.warn(
            "ewb_ident was imported after JAX had started its CPU backend, so its XLA "
            f"option ({_EXTRA}{_LOOP_KEY}={SMALL_LOOP_BYTES}) is off and fits and "
            "diagnoses run 2-5x slower; import ewb_ident before any JAX computation, or "
            "set that option in XLA_FLAGS yourself",
            RuntimeWarning,
            stacklevel=3,
        )
        return "default"
    ours = f"{_LOOP_KEY}={SMALL_LOOP_BYTES}"
    given = [i for i, f in enumerate(flags) if f.startswith(_EXTRA)]
    if given:
        flags[given[-1]] += f",{ours}"
    else:
        flags.append(_EXTRA + ours)
    os.environ["XLA_FLAGS"] = " ".join(flags)
    return str(SMALL_LOOP_BYTES)


#: The small-loop threshold in effect (see :data:`SMALL_LOOP_BYTES`).
XLA_SMALL_LOOP_BYTES = _native_small_loops()

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
    "InputError": "data.trace",
    "EWBIdentError": "data.trace",
    "read_trace": "data.readers",
    "write_trace": "data.writers",
    "fit_corrected": "diagnosis.corrected",
    "CorrectedFit": "diagnosis.corrected",
    "CorrectedModel": "diagnosis.corrected",
    "LearnedSpec": "diagnosis.discovery",
    "validate": "inference.validate",
    "ValidationResult": "inference.validate",
}

__all__ = sorted(_PUBLIC)

if TYPE_CHECKING:
    from ewb_ident.data.metrics import channel_metrics as channel_metrics
    from ewb_ident.data.readers import read_trace as read_trace
    from ewb_ident.data.trace import EWBIdentError as EWBIdentError
    from ewb_ident.data.trace import InputError as InputError
    from ewb_ident.data.trace import Trace as Trace
    from ewb_ident.data.trace import TraceError as TraceError
    from ewb_ident.data.writers import write_trace as write_trace
    from ewb_ident.diagnosis.corrected import CorrectedFit as CorrectedFit
    from ewb_ident.diagnosis.corrected import CorrectedModel as CorrectedModel
    from ewb_ident.diagnosis.corrected import fit_corrected as fit_corrected
    from ewb_ident.diagnosis.diagnose import diagnose as diagnose
    from ewb_ident.diagnosis.discovery import LearnedSpec as LearnedSpec
    from ewb_ident.diagnosis.result import DiagnosisResult as DiagnosisResult
    from ewb_ident.diagnosis.session import DiagnoseError as DiagnoseError
    from ewb_ident.inference.fit_result import FitResult as FitResult
    from ewb_ident.inference.least_squares import fit as fit
    from ewb_ident.inference.log_posterior import SampleError as SampleError
    from ewb_ident.inference.posterior import sample as sample
    from ewb_ident.inference.posterior_result import PosteriorResult as PosteriorResult
    from ewb_ident.inference.problem import FitError as FitError
    from ewb_ident.inference.validate import ValidationResult as ValidationResult
    from ewb_ident.inference.validate import validate as validate
    from ewb_ident.model.integrate import Integrator as Integrator
    from ewb_ident.model.integrate import NumericalWarning as NumericalWarning
    from ewb_ident.model.integrate import simulate_chain as simulate_chain
    from ewb_ident.model.integrate import simulate_motor as simulate_motor
    from ewb_ident.model.params import PARAMS as PARAMS
    from ewb_ident.model.params import SEED as SEED
    from ewb_ident.model.params import EWBParams as EWBParams


def __dir__() -> list[str]:
    """The public names (imported on first use) and the version."""
    return sorted([*__all__, "__version__", "SMALL_LOOP_BYTES", "XLA_SMALL_LOOP_BYTES"])


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    raise AttributeError(f"module 'ewb_ident' has no attribute {name!r}")
