"""ewb-ident: fit, quantify and diagnose a physical model of an EWB test rig.

Every public function computes in float64 whatever JAX's global setting
(:mod:`ewb_ident.model.numerics`).

>>> import ewb_ident as ei
>>> ei.configure()   # optional: the CLI's set-up (float64 throughout, programs kept on disk)
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
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# The one setting made at import: XLA's small-loop threshold, into ``XLA_FLAGS`` (and
# nothing else; no JAX is imported). :mod:`ewb_ident.runtime.config` says why import time
# is the only reliable moment; the rest of the set-up is :func:`configure`'s.
_config = importlib.import_module(".runtime.config", __name__)
#: XLA's small-loop threshold the package asks for, and the one in effect
#: (:mod:`ewb_ident.runtime.config`).
SMALL_LOOP_BYTES = _config.SMALL_LOOP_BYTES
XLA_SMALL_LOOP_BYTES = _config.XLA_SMALL_LOOP_BYTES

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
    "simulate_chain": "model.predict",
    "simulate_motor": "model.predict",
    "Trace": "data.trace",
    "TraceError": "data.trace",
    "InputError": "data.trace",
    "EWBIdentError": "data.trace",
    "read_trace": "data.readers",
    "write_trace": "data.writers",
    "fit_corrected": "diagnosis.corrected",
    "CorrectedFit": "diagnosis.corrected",
    "CorrectedModel": "diagnosis.corrected",
    "LearnedSpec": "diagnosis.learned_spec",
    "validate": "inference.validate",
    "ValidationResult": "inference.validate",
    "configure": "runtime.config",
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
    from ewb_ident.diagnosis.learned_spec import LearnedSpec as LearnedSpec
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
    from ewb_ident.model.params import PARAMS as PARAMS
    from ewb_ident.model.params import SEED as SEED
    from ewb_ident.model.params import EWBParams as EWBParams
    from ewb_ident.model.predict import simulate_chain as simulate_chain
    from ewb_ident.model.predict import simulate_motor as simulate_motor
    from ewb_ident.runtime.config import configure as configure


def __dir__() -> list[str]:
    """The public names (imported on first use) and the version."""
    return sorted([*__all__, "__version__", "SMALL_LOOP_BYTES", "XLA_SMALL_LOOP_BYTES"])


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    raise AttributeError(f"module 'ewb_ident' has no attribute {name!r}")
