"""Fifth blind probe of discovery: six more physics families outside the catalog and
outside ``validation_rigs/uncatalogued_rig.py``'s fourteen and the six of each of
``probe_rig.py``, ``probe2_rig.py``, ``probe3_rig.py`` and ``probe4_rig.py``, one at
each place of the chain (motor electrical, motor mechanical, drive, force law, friction,
a sensor), each with a different kind of dependence (a rate limit, a gate on the voltage
with hysteresis, a slow thermal drift, a count of load cycles, a product of the force
and its rate, a periodic function of the displacement).

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package. The
cases are drawn exactly as ``probe_rig.make_case`` draws its own (its own seed stream).
References taken from "the twin" are from the same case's no-effect run.

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``drive_ramp_limit`` (motor.electrical; voltage and voltage rate): the power stage
  does not apply the logged voltage command ``V`` at once: its set-point ramp generator
  (the acceleration ramp of a DC drive, or an amplifier's slew-rate limit) lets its
  output ``V_o`` [V] change by at most ``S`` [V/s], so a step of ``dV`` takes ``|dV| / S``
  and small changes pass untouched (unlike a linear filter, the delay grows with the
  size of the step). The strength is ``t_10`` [s], the time the ramp takes for 10 V
  (``S = 10 V / t_10``). a: symmetric, ``|dV_o/dt| <= S``: ``V_o`` moves toward ``V`` at
  the rate ``S`` until it reaches it; b: the acceleration ramp only: ``|V_o|`` rises at
  most at ``S`` (same sign as ``V``), falls at once to ``|V|``, and a change of sign
  passes through zero at once, then ramps. ``V_o`` is advanced on the motor's
  sub-steps (``V`` is held over each sample). The term is the voltage removed ``dV = V
  - V_o`` [V]. Inside the closed position loop a slow ramp lets the PI wind up on the
  fastest reversals and overshoot in a short burst (at low force, so still concealed):
  the closed-loop draws range from a small tracking effect to such bursts.
* ``holding_brake_drag`` (motor.mechanical; voltage and direction): the actuator's
  spring-applied holding brake (its fail-safe parking lock) is released by a coil wired
  across the motor terminals, so it drags whenever the terminal voltage is too low to
  hold its armature: a friction torque ``tau = T_b e(V) tanh(omega / omega_eps)`` [N m]
  opposing the motion (``T_b`` [N m] the strength; the sign regularised with
  ``omega_eps = max(0.05 rad/s, 2 H_MAX T_b / M)``, stable on the 0.1 ms sub-steps). a:
  the armature is a relay with hysteresis, released (``e = 0``) once ``|V| > V_p``,
  engaged again (``e = 1``) once ``|V| < V_d``, engaged at the start; ``V_p`` drawn
  0.5-1.5 V, ``V_d = r V_p`` with ``r`` drawn 0.3-0.6; b: a proportional (partial)
  release, the coil's pull ``~ V^2`` against the spring, ``e = max(1 - (V / V_r)^2, 0)``,
  ``V_r`` drawn 0.5-1.5 V. Not the catalog's stiction (a breakaway friction in every
  state of the drive): this one is switched by the voltage, with memory in a.
* ``worm_thermal_growth`` (drive; heat): the motor's copper losses ``P = R i^2`` [W]
  heat its flange and the worm / spindle it carries, which lengthens and pushes the
  piston toward the disc: ``x = gap(theta) + delta`` (the LVDT reads the piston, the
  bell sees it). The heat is integrated on the motor's sub-steps (the current's
  millisecond peaks are between the samples of a slow log). a: no cooling within a
  record, ``delta = d Q / Q_end`` with ``Q = int P dt`` [J] and ``Q_end`` the twin's at
  the end; b: the shaft cools, ``dH/dt = P - H / tau_c`` (``tau_c`` drawn 0.5-2 s, ``H``
  [J]), ``delta = d H / H_max`` with ``H_max`` the twin's largest ``H``. ``d`` [m] is
  the strength. The normalisation compresses into the record a warm-up a real shaft
  takes minutes of such duty for (a few micrometres need kelvins). The motor does not
  change (the twin's current). The term is the x shift ``delta`` [m]. Not the catalog's
  nor the uncatalogued rig's thermal expansion (the piston growing with the braking
  energy or the time): this is driven by the motor current, with the disc cold.
* ``pad_cyclic_softening`` (force.output; force and reversals): a fresh pad's binder
  softens with each load cycle (a Mullins-like stress softening, one reason pad
  compressibility tests precondition the pad with load cycles), so the clamping force at
  a given piston position falls from cycle to cycle: ``F = bell(x) (1 - eps g)``
  (``eps`` [-] the strength, the share lost when ``g = 1``). A load cycle is counted
  when the bell of the piston position falls below 0.05 ``F_rt`` after it has exceeded
  0.4 ``F_rt`` (the release of an apply, as the rig counts applies); the first apply is
  virgin. a: ``g = 1 - rho^N`` with ``N`` the cycles completed and ``rho`` drawn
  0.3-0.6; b: the binder recovers at rest, ``n`` adds one at each completed cycle and
  decays with ``exp(-t / tau_r)`` in between (``tau_r`` drawn 0.5-2 s), ``g = 1 -
  rho^n``. The torque follows the clamping force. The term is the force added [N].
* ``mu_load_rate`` (friction; force and force rate): the pads' friction layer answers a
  change of the normal load with a transient, which a pressure sweep on a dynamometer
  shows as a "mu-p hysteresis" (here: the friction coefficient lower while the clamping
  force rises than while it falls at the same force), so the torque is ``2 mu r_eff F
  m`` with the factor ``m`` [-] below and ``eps`` [-] the strength. a: instantaneous in
  the rate, ``m = 1 - eps tanh(dF/dt / Fdot_0)`` with ``Fdot_0`` a drawn share (0.1-0.3)
  of the twin's largest ``|dF/dt|`` [N/s]; b: a boundary layer that relaxes, ``m = 1 -
  eps (F - L) / F_rt`` with ``tau_b dL/dt = F - L`` (``tau_b`` drawn 0.1-0.5 s, ``L``
  starting at ``F``), i.e. the high-pass of the force. The torque change is a product of
  the force and its (filtered) rate: unlike a lag of the torque reading it vanishes with
  the force and saturates with the rate (a). The term is the mu factor minus one [-].
* ``scale_interpolation_error`` (sensor.x_m; x): the piston displacement is read by
  an incremental magnetic scale (pole pitch ``lambda`` drawn 0.5-1 mm) whose sin / cos
  signals are interpolated; imperfect signals leave a sub-divisional error periodic in
  the position. Reading ``x + A sin(2 pi k x / lambda + phi)`` (``A`` [m] the strength,
  ``phi`` drawn): a ``k = 2``, the error of unequal sin / cos amplitudes (twice per
  pitch); b ``k = 4``, the error of a third harmonic in the signals (four times per
  pitch). The force and torque are those of the true piston. The term is the reading
  minus ``x`` [m].

Families that are not here and why: an H-bridge's dead-time loss is ``driver_lag`` b,
and a PWM's duty resolution (the voltage quantised) acts near zero as that dead band;
a DC bus pumped up by the regenerated energy hardly shows (the open-loop profiles short
the motor to stop it, which returns nothing to the bus); a mechanical end stop at the
released position would be reached at the start of most records (the drawn start angle
is the lowest), not during the releases; a seal's roll-back is ``piston_seal``;
thermal growth from the braking energy is ``thermal_expansion``; a multiplexed ADC's
crosstalk from a neighbouring channel is a linear mix of signals the catalog's gains
and ``torque_current_crosstalk`` already take; a rotating encoder's interpolation error
(a period of a fraction of a degree) is below the angle noise at any realistic size.

Command line
------------
``python -m validation_rigs.probe5_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from validation_rigs.probe_rig import make_probe_case, run_cli
from validation_rigs.uncatalogued_rig import H_MAX, Case, bell, chain, gap_m, lag_foh

FAMILIES: dict[str, dict] = {
    "drive_ramp_limit": {
        "stage": "motor",
        "place": "motor.electrical",
        "depends_on": {"a": ["voltage", "voltage_rate"], "b": ["voltage", "voltage_rate"]},
        "words": "power stage's ramp generator: output V_o moves at most at S = 10 V/t_10; "
        "a symmetric, b |V_o| rises at most at S, falls at once; dV = V - V_o",
    },
    "holding_brake_drag": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["voltage", "direction"], "b": ["voltage", "direction"]},
        "words": "holding brake released by a coil across the motor terminals drags at low "
        "voltage: tau = T_b e(V) tanh(omega/omega_eps); a relay released above V_p, "
        "engaged below V_d; b e = max(1 - (V/V_r)^2, 0)",
    },
    "worm_thermal_growth": {
        "stage": "gap",
        "place": "drive",
        "depends_on": {"a": ["heat"], "b": ["heat"]},
        "words": "worm shaft grows with the motor's copper losses: x = gap(theta) + delta; "
        "a delta = d Q/Q_end, Q = int R i^2 dt; b delta = d H/H_max, "
        "dH/dt = R i^2 - H/tau_c",
    },
    "pad_cyclic_softening": {
        "stage": "force",
        "place": "force.output",
        "depends_on": {"a": ["force", "reversals"], "b": ["force", "reversals", "time"]},
        "words": "pad softens with each load cycle: F = bell(x) (1 - eps g); a g = 1 - rho^N, "
        "N cycles completed; b g = 1 - rho^n, n += 1 per cycle, decaying with tau_r",
    },
    "mu_load_rate": {
        "stage": "torque",
        "place": "friction",
        "depends_on": {"a": ["force", "force_rate"], "b": ["force", "force_rate", "time"]},
        "words": "friction lower while the force rises, higher while it falls: T = 2 mu r F m; "
        "a m = 1 - eps tanh(dF/dt / Fdot_0), b m = 1 - eps (F - L)/F_rt, "
        "tau_b dL/dt = F - L",
    },
    "scale_interpolation_error": {
        "stage": "gap",
        "place": "sensor.x_m",
        "depends_on": {"a": ["x"], "b": ["x"]},
        "words": "magnetic scale's sub-divisional error: x + A sin(2 pi k x/lambda + phi); "
        "a k = 2 (amplitude mismatch), b k = 4 (third harmonic)",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

#: Families run through the motor integration (``worm_thermal_growth`` only to integrate
#: the copper losses on the sub-steps; its motor is the twin's).
_MOTOR = {"drive_ramp_limit", "holding_brake_drag", "worm_thermal_growth"}
#: Families whose cases always record the current (none here).
CURRENT_ALWAYS: frozenset[str] = frozenset()
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe5"
#: Load-cycle thresholds of ``pad_cyclic_softening`` as shares of ``F_rt`` (armed above
#: the first, counted below the second).
CYCLE_ARM, CYCLE_COUNT = 0.4, 0.05

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("drive_ramp_limit", "a"): {
        "open": (8e-4, 2.5e-3),
        "closed": (0.012, 0.035),
        "unit": "t_10 [s]",
    },
    ("drive_ramp_limit", "b"): {
        "open": (8e-4, 2.5e-3),
        "closed": (0.02, 0.05),
        "unit": "t_10 [s]",
    },
    ("holding_brake_drag", "a"): {
        "open": (8e-5, 2.5e-4),
        "closed": (5e-3, 1.5e-2),
        "unit": "T_b [N m]",
    },
    ("holding_brake_drag", "b"): {
        "open": (8e-5, 2.5e-4),
        "closed": (5e-3, 1.5e-2),
        "unit": "T_b [N m]",
    },
    ("worm_thermal_growth", "a"): {
        "open": (4e-6, 1.1e-5),
        "closed": (4e-6, 1.1e-5),
        "unit": "d [m]",
    },
    ("worm_thermal_growth", "b"): {
        "open": (6e-6, 1.6e-5),
        "closed": (6e-6, 1.6e-5),
        "unit": "d [m]",
    },
    ("pad_cyclic_softening", "a"): {
        "open": (0.025, 0.06),
        "closed": (0.025, 0.06),
        "unit": "eps [-]",
    },
    ("pad_cyclic_softening", "b"): {
        "open": (0.04, 0.11),
        "closed": (0.04, 0.11),
        "unit": "eps [-]",
    },
    ("mu_load_rate", "a"): {"open": (0.03, 0.06), "closed": (0.03, 0.06), "unit": "eps [-]"},
    ("mu_load_rate", "b"): {"open": (0.04, 0.09), "closed": (0.04, 0.09), "unit": "eps [-]"},
    ("scale_interpolation_error", "a"): {
        "open": (4e-6, 1e-5),
        "closed": (4e-6, 1e-5),
        "unit": "A [m]",
    },
    ("scale_interpolation_error", "b"): {
        "open": (5e-6, 1.2e-5),
        "closed": (5e-6, 1.2e-5),
        "unit": "A [m]",
    },
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``).

    ``h`` is recorded by ``run_motor`` as ``aux`` at the samples: the ramp's output
    ``V_o`` [V], the brake's engagement ``e`` [-], or the heat ``Q`` / ``H`` [J] of
    ``worm_thermal_growth`` (whose terms are zero: the motor is the twin's). The states
    advance on the accepted sub-steps only (``advance``)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        if family == "drive_ramp_limit":
            rate = 10.0 / prm["t_10"]
            accel_only = form == "b"
            self._v = 0.0

            def f(i, w, th, V):
                self._v = V
                return V - self.h, 0.0

            def adv(i, hstep):
                v, y, dv = self._v, self.h, rate * hstep
                if not accel_only:
                    y += min(max(v - y, -dv), dv)
                elif v * y < 0.0 or y == 0.0:  # through zero at once, then ramp
                    y = math.copysign(min(abs(v), dv), v)
                elif abs(v) <= abs(y):  # falls at once
                    y = v
                else:
                    y += math.copysign(min(abs(v) - abs(y), dv), v)
                self.h = y

            self.f, self.advance = f, adv
        elif family == "holding_brake_drag":
            tb, weps = prm["T_b"], prm["omega_eps"]
            if form == "a":
                vp, vd = prm["V_p"], prm["V_d"]
                self.h = 1.0  # engaged at the start

                def f(i, w, th, V):
                    av = abs(V)
                    if self.h > 0.5 and av > vp:
                        self.h = 0.0
                    elif self.h < 0.5 and av < vd:
                        self.h = 1.0
                    return 0.0, tb * self.h * math.tanh(w / weps)

            else:
                inv = 1.0 / prm["V_r"] ** 2

                def f(i, w, th, V):
                    self.h = max(1.0 - V * V * inv, 0.0)
                    return 0.0, tb * self.h * math.tanh(w / weps)

            self.f = f
        elif family == "worm_thermal_growth":
            r0 = p["R"]
            cool = form == "b"
            tau_c = prm.get("tau_c_s", 1.0)
            self._i = 0.0

            def f(i, w, th, V):
                return 0.0, 0.0

            def adv(i, hstep):  # trapezoidal copper losses over the sub-step [J]
                q = 0.5 * r0 * (self._i * self._i + i * i) * hstep
                self._i = i
                if cool:
                    a = math.exp(-hstep / tau_c)
                    self.h = self.h * a + q * math.sqrt(a)  # heat in mid-step, cooled
                else:
                    self.h += q

            self.f, self.advance = f, adv
        else:
            raise ValueError(family)


def draw_extras(family: str, form: str, rng: np.random.Generator, twin: dict) -> dict:
    """Effect parameters other than the strength (``twin``: the no-effect motor run)."""
    ex: dict = {}
    if family == "holding_brake_drag":
        if form == "a":
            vp, r = float(rng.uniform(0.5, 1.5)), float(rng.uniform(0.3, 0.6))
            ex.update(V_p=vp, drop_share=r, V_d=r * vp)
        else:
            ex["V_r"] = float(rng.uniform(0.5, 1.5))
    elif family == "worm_thermal_growth" and form == "b":
        ex["tau_c_s"] = float(rng.uniform(0.5, 2.0))
    elif family == "pad_cyclic_softening":
        ex["rho"] = float(rng.uniform(0.3, 0.6))
        if form == "b":
            ex["tau_r_s"] = float(rng.uniform(0.5, 2.0))
    elif family == "mu_load_rate":
        if form == "a":
            ex["Fdot_0_share"] = float(rng.uniform(0.1, 0.3))
        else:
            ex["tau_b_s"] = float(rng.uniform(0.1, 0.5))
    elif family == "scale_interpolation_error":
        ex.update(
            pitch_m=float(rng.uniform(0.5e-3, 1.0e-3)),
            order=2 if form == "a" else 4,
            phi=float(rng.uniform(0.0, 2.0 * np.pi)),
        )
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``).
    ``probe_chain`` adds the references it takes from the twin's readings."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "drive_ramp_limit":
        prm.update(t_10=s, S_V_per_s=10.0 / s)
    elif family == "holding_brake_drag":
        prm["T_b"] = s
        prm["omega_eps"] = max(0.05, 2.0 * H_MAX * s / p["M"])
    elif family == "worm_thermal_growth":
        prm["d_m"] = s
    elif family in ("pad_cyclic_softening", "mu_load_rate"):
        prm["eps"] = s
    elif family == "scale_interpolation_error":
        prm["A_m"] = s
    return prm


def _cycles(fb: np.ndarray, f_rt: float, dt: float, tau: float | None) -> np.ndarray:
    """Load-cycle state of ``pad_cyclic_softening`` from the bell force ``fb`` [N]: the
    cycles completed (a release below ``CYCLE_COUNT F_rt`` after ``CYCLE_ARM F_rt``), or
    with ``tau`` [s] their sum decaying with ``exp(-t / tau)``."""
    out = np.zeros(len(fb))
    decay = math.exp(-dt / tau) if tau else 1.0
    armed, n = False, 0.0
    for k in range(len(fb)):
        n *= decay
        if not armed and fb[k] > CYCLE_ARM * f_rt:
            armed = True
        elif armed and fb[k] < CYCLE_COUNT * f_rt:
            armed, n = False, n + 1.0
        out[k] = n
    return out


def probe_chain(
    p: dict, mot: dict, dt: float, w_disc: float, family: str, form: str, prm: dict
) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Noise-free readings with the probe effect (motor effects are already in ``mot``)."""
    rec, _, _, _ = chain(p, mot, dt, w_disc)
    th = mot["th"]
    mu, r, f_rt = p["mu"], p["r_eff"], p["F_rt"]
    x = gap_m(th, p)
    if family == "drive_ramp_limit":
        return rec, mot["dv"], mot["V"], "voltage_V"
    if family == "holding_brake_drag":
        return rec, mot["tau"], mot["V"], "voltage_V"
    if family == "worm_thermal_growth":
        heat = mot["aux"]
        ref = float(heat[-1] if form == "a" else np.max(heat))
        prm["heat_ref_J"] = ref
        delta = prm["d_m"] * heat / max(ref, 1e-12)
        xp = x + delta
        force = bell(xp, p)
        rec["x_m"], rec["force_N"], rec["torque_Nm"] = xp, force, 2.0 * mu * force * r
        return rec, delta, heat, "joule_heat_J" if form == "a" else "heat_state_J"
    if family == "pad_cyclic_softening":
        fb = rec["force_N"]
        n = _cycles(fb, f_rt, dt, prm.get("tau_r_s") if form == "b" else None)
        g = 1.0 - prm["rho"] ** n
        force = fb * (1.0 - prm["eps"] * g)
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, force - fb, n, "load_cycles"
    if family == "mu_load_rate":
        force = rec["force_N"]
        if form == "a":
            fdot = np.gradient(force, dt)
            f0 = prm["Fdot_0_share"] * float(np.max(np.abs(fdot)))
            prm["Fdot_0_N_s"] = f0
            term = -prm["eps"] * np.tanh(fdot / max(f0, 1e-9))
            tin, name = fdot, "force_rate_N_s"
        else:
            tin = force - lag_foh(force, prm["tau_b_s"], dt)
            term = -prm["eps"] * tin / f_rt
            name = "force_highpass_N"
        rec["torque_Nm"] = rec["torque_Nm"] * (1.0 + term)
        return rec, term, tin, name
    if family == "scale_interpolation_error":
        k = 2.0 * math.pi * prm["order"] / prm["pitch_m"]
        term = prm["A_m"] * np.sin(k * x + prm["phi"])
        rec["x_m"] = x + term
        return rec, term, x, "x_m"
    raise ValueError(family)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One case, drawn as ``probe_rig.make_case`` draws its cases; keywords as there."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
