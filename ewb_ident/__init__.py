"""ewb-ident: fit, quantify and diagnose a physical model of an EWB test rig.

Turn on float64 before use (the CLI does): ``jax.config.update("jax_enable_x64", True)``.

>>> import jax; jax.config.update("jax_enable_x64", True)
>>> import ewb_ident as ei
>>> trace = ei.read_trace("datasets/steps_200hz.csv")
>>> result = ei.fit(trace)              # whole chain from voltage
>>> result.params[0].a, result.stderr["a"], result.metrics["force_N"]
"""

from .fit import FitError as FitError
from .fit import FitResult as FitResult
from .fit import fit as fit
from .metrics import channel_metrics as channel_metrics
from .params import PARAMS as PARAMS
from .params import SEED as SEED
from .params import EWBParams as EWBParams
from .simulate import Integrator as Integrator
from .simulate import NumericalWarning as NumericalWarning
from .simulate import simulate_chain as simulate_chain
from .simulate import simulate_motor as simulate_motor
from .traces import Trace as Trace
from .traces import TraceError as TraceError
from .traces import read_trace as read_trace
from .traces import write_trace as write_trace

__version__ = "0.1.0"
