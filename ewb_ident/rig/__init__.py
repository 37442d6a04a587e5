"""Synthetic brake rig: traces of the EWB test rig with documented truth.

This module is the *truth generator* for tests, datasets and studies. Its physics and
its integrator are written here, independently of the fitting model (it imports only
:mod:`ewb_ident.data.trace`), so that a test that fits a generated trace checks the model
against something it does not share code with.

The rig
-------
A DC motor driven by the applied voltage ``V`` (zero-order hold over each logging
interval) turns the worm pinion (angle ``theta``, rad internally, degrees in traces)::

    L di/dt = V - R i - kb omega
    M domega/dt = kT i - v omega - tau_load - tau_friction
    dtheta/dt = omega

The wedge-side angle ``theta_w`` (degrees; equal to the pinion angle unless there is
``backlash``) sets the piston displacement and the clamping force (generalized bell)::

    x = p2 theta_w**2 + p1 theta_w + p0
    F = F_rt / (1 + |(x - c) / a|**(2 b))
    T = 2 mu F r_eff                      (brake torque at the disc)

The disc is either held at a prescribed speed by a dynamometer (``drag``: constant or a
linear ramp) or coasts on a flywheel (``coast``: ``J domega_d/dt = -T``). The sliding
friction needs sliding: ``T`` is scaled by ``clip(omega_d / 0.1 rad/s, -1, 1)``, which is
1 unless the disc is (nearly) stopped.

Integration: ``jax.lax.scan`` over the logging samples with a fixed-step classical RK4
inner loop (an integer number of sub-steps per sample, at most ``fine_step_s``, default
20 us), jit-compiled in float64 and cached by the static settings (which effects are
switched on, the number of sub-steps, ...), so that many traces with different
parameter values reuse one compiled function.

Catalog effects (:data:`EFFECTS`, ids as in CONTRACTS.md) can be switched on, alone or
together; each is a frozen dataclass holding its physical parameters.
"""

from ewb_ident.rig.effects import EFFECTS as EFFECTS
from ewb_ident.rig.effects import Backlash as Backlash
from ewb_ident.rig.effects import CurrentLimit as CurrentLimit
from ewb_ident.rig.effects import ForceHysteresis as ForceHysteresis
from ewb_ident.rig.effects import FrictionFade as FrictionFade
from ewb_ident.rig.effects import FrictionSpeed as FrictionSpeed
from ewb_ident.rig.effects import RigEffect as RigEffect
from ewb_ident.rig.effects import SensorDelay as SensorDelay
from ewb_ident.rig.effects import SensorOffset as SensorOffset
from ewb_ident.rig.effects import Stiction as Stiction
from ewb_ident.rig.effects import WedgeLoadTorque as WedgeLoadTorque
from ewb_ident.rig.params import VARIED_PARAMS as VARIED_PARAMS
from ewb_ident.rig.params import RigError as RigError
from ewb_ident.rig.params import RigParams as RigParams
from ewb_ident.rig.params import SensorNoise as SensorNoise
from ewb_ident.rig.params import theta_for_gap as theta_for_gap
from ewb_ident.rig.params import vary as vary
from ewb_ident.rig.simulate import CleanRun as CleanRun
from ewb_ident.rig.simulate import simulate_rig as simulate_rig

__all__ = [
    "EFFECTS",
    "Backlash",
    "CleanRun",
    "CurrentLimit",
    "ForceHysteresis",
    "FrictionFade",
    "FrictionSpeed",
    "RigEffect",
    "RigError",
    "RigParams",
    "SensorDelay",
    "SensorNoise",
    "SensorOffset",
    "Stiction",
    "WedgeLoadTorque",
    "simulate_rig",
    "theta_for_gap",
    "vary",
]
