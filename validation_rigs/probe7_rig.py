"""Seventh blind probe of discovery: six more physics families outside the catalog and
outside ``validation_rigs/uncatalogued_rig.py``'s fourteen and the six of each of
``probe_rig.py`` to ``probe6_rig.py``, one at each place of the chain (motor
electrical, motor mechanical, drive, force law, friction, a sensor), each with a
different kind of dependence (a regime switched by a dwell timer, a lag with a
relaxation time, a saturation that leaves its slip behind, an irreversible drift that
saturates, a memory of the largest force, a periodic function of the disc angle).

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package. The
cases are drawn exactly as ``probe_rig.make_case`` draws its own (its own seed stream).
References taken from "the twin" are from the same case's no-effect run.

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``driver_standby_wake`` (motor.electrical; voltage and its history, b also time): the
  driver (or the actuator's control unit) goes to standby once the voltage command has
  stayed inside its zero band ``|V| < V_i`` for ``T_idle`` (its standstill detection
  low-passes ``|V|`` over ``STANDBY_TAU_F`` = 10 ms); in standby it holds its low-side
  switches on (the motor shorted, ``V_o = 0``), and when the command leaves the band it
  wakes up but applies nothing for the wake-up time ``t_w`` [s] while its charge pump
  and bootstrap capacitors charge and its gate drivers come up. ``V_i`` is three times
  the median ``|V|`` of the twin's samples under 20 mV (the closed loop's dither at
  rest), at least 5 mV and at most 19 mV (under the open-loop hold voltages);
  ``T_idle`` is drawn 30-100 ms; the record starts in standby (the rig stood still
  before it). a: ``t_w`` fixed (the strength); b: the bootstrap discharges while the
  driver sleeps, so the wake-up takes the longer the longer the sleep, ``t_w = t_w0 (1 -
  exp(-t_sleep / tau_s))`` (``tau_s`` drawn 0.2-1 s, ``t_w0`` [s] the strength). The
  state machine runs on the motor's sub-steps (a wake-up shorter than a sub-step removes
  that share of it). Open-loop wake-ups of a tenth of a millisecond (a charge pump's
  start) cut every apply short; a closed loop shows some milliseconds (a control unit
  waking on its bus). The term is the voltage removed, ``V`` while off [V]. Not
  ``driver_lag`` (a filter, or a dead band on every command), ``drive_ramp_limit`` (a
  slew limit) nor a relay bridge's transfer time at each reversal (``probe6_rig``'s
  note): a dead time that only a dwell of the command at rest arms, its length set by a
  timer (b: by the dwell itself).
* ``grease_viscoelastic_drag`` (motor.mechanical; speed and time): the gear grease is
  viscoelastic: its shear stress relaxes toward the viscous stress with a relaxation
  time (a Maxwell fluid), so its drag lags the speed: it builds up over a stroke,
  outlasts it and pulls the rotor back after a stop. ``lambda dtau/dt = c g(omega) -
  tau``, ``tau`` [N m] (zero at the start), ``c`` [N m s/rad] the strength (the
  grease's viscous drag, on top of the rig's viscous ``v``), ``lambda`` drawn 0.05-0.3
  s. a: Newtonian, ``g = omega``; b: shear-thinning (Cross), ``g = omega / (1 + |omega|
  / omega_c)``, ``omega_c`` a drawn share (0.2-0.5) of the twin's fastest ``|omega|``
  [rad/s]. ``tau`` relaxes on the motor's sub-steps at the accepted states (exact for
  the speed held over a sub-step). The term is the load torque [N m]. Not
  ``quadratic_drag`` (instantaneous in the speed) nor ``grease_thixotropy`` (an
  instantaneous drag whose coefficient remembers the rotation and the rest), nor the
  model's viscous friction or inertia (``lambda`` is tens to hundreds of times the
  rotor's few milliseconds): a drag that lags the speed.
* ``drive_slip_clutch`` (drive; force, b also direction): an overload slip clutch (a
  friction torque limiter) between the gear and the spindle protects the drive: it
  slips whenever the drive would push the piston past the force it transmits, so the
  motor turns on while the piston stays, and the slip remains once it re-engages: ``x =
  gap(theta - phi)`` (the LVDT reads the piston, the bell sees it), the slip ``phi``
  [deg] growing so that ``bell(gap(theta - phi))`` does not pass the slip force. The
  slip force is ``F_s = (1 - s) F_pk`` with ``F_pk`` the twin's peak force and ``s``
  [-] the strength (how far under the highest apply the clutch is set). a: the clutch
  slides at its static force (the force held at ``F_s`` while the motor advances); b:
  it sticks up to ``F_s`` and slides at ``F_k = (1 - s (1 + d)) F_pk`` (``d`` drawn
  0.5-1.5): once it breaks away the force drops to ``F_k`` and stays there while the
  motor advances, and it sticks again where it is when the motor stops advancing. The
  rig's motor does not feel the clamp (no wedge load), so it does not feel the slipping
  either. The term is the x shift ``gap(theta - phi) - gap(theta)`` [m]. Not the
  catalog's current limit (the motor's current, not the drive's force), nor
  ``drive_compliance`` (elastic, given back), ``roller_creep`` (a creep with every
  travel under load) or ``encoder_slip`` (the angle reading slips, the piston follows
  the motor): the force saturates, and the drive keeps the slip.
* ``paste_squeeze_out`` (force.input; force and time): the anti-squeal paste (a brake
  grease on the pad's backplate, where the piston bears) is a film in the load path
  that the clamping force squeezes out (Reynolds' squeeze film between parallel discs,
  ``dh/dt ~ -h^3 F``), so the pad sits the nearer to the piston the longer it has been
  loaded, and the paste does not flow back within a record: ``F = bell(x - (h_0 -
  h))`` with the film ``h`` [m] starting at ``h_0`` [m], the strength. ``d(1/h^2)/dt =
  K max(F - F_y, 0)``, ``K = 3 / (h_0^2 (F_rt - F_y) t_half)`` (at ``F_rt`` the film
  halves in ``t_half``), exact over a sample with the force held. a: a Newtonian paste,
  ``F_y = 0``, ``t_half`` drawn 0.5-2 s; b: a Bingham paste that flows only above a
  yield, ``F_y`` a drawn share (0.3-0.6) of the twin's peak force, ``t_half`` drawn
  0.3-1.2 s. The term is the x shift the bell sees, ``-(h_0 - h)`` [m]; the LVDT reads
  the piston. Not ``pad_creep`` (viscoelastic, given back after a release),
  ``thermal_expansion`` (growing with the energy without bound, toward the disc) nor
  ``pad_set`` (set at once by the record force): a loss that accrues with the time
  under load, ever slower, and saturates at the film's thickness.
* ``plateau_flattening`` (friction; force, b also time): the friction layer's
  load-bearing plateaus are flattened plastically by the largest force they have
  carried and unload elastically, so at a lower force their real contact area is larger
  than that force alone would make it (Hertzian unloading of a flattened contact, ``A ~
  F^(2/3) M^(1/3)``); the adhesive share of the friction follows the area: ``mu (1 +
  eps ((M/F)^(1/3) - 1))`` with ``M`` [N] the plateaus' record force and ``eps`` [-]
  the strength (the adhesive share). ``F`` enters the ratio as at least ``0.02 F_rt``
  (the torque added, ``~ F^(2/3) M^(1/3) - F``, vanishes with the force anyway). a:
  ``M`` the largest clamping force so far; b: the sliding wears the flattened tops and
  rebuilds the plateaus, so ``M`` relaxes to the present force, ``dM/dt = -(M - F) /
  tau_p`` above it (``tau_p`` drawn 0.3-1.5 s), ``M = F`` at a new record. The force
  does not change; the torque follows mu. The term is the mu factor minus one [-]. Not
  ``mu_pressure`` (a static function of the force), ``mu_load_rate`` (the force's rate
  or high-pass: mu lower whenever the force rises), ``mu_buildup`` (the contact time)
  nor the catalog's friction fade (the energy): mu above its law only under the force
  the pads have carried, independent of the rate in a.
* ``flange_rotor_zero`` (sensor.torque_Nm; disc angle): the rotating torque flange
  between the disc and its drive reads a zero that turns with its rotor, ``T + A sin(k
  phi_d + phi0)`` with ``phi_d = omega_d t`` the disc angle, ``phi0`` drawn and ``A``
  [N m] the strength as a share of ``2 mu F_rt r_eff`` (the flange's range). a: the
  crosstalk of the bending moment that a misaligned shaft line puts on the rotor, fixed
  in space and so once per revolution in the rotor, ``k = 1``; b: the rotor's
  electronics fed inductively through a stator antenna in two halves, whose supply (and
  with it the amplifier's zero) ripples twice per revolution, ``k = 2``. It is there
  whatever the brake does (at rest as under load). The term is the reading minus the
  torque [N m]. Not ``disc_runout`` (the clamping force and the torque modulated, a
  product with the force), ``torque_current_crosstalk`` nor the catalog's sensor offset
  (the current, or a constant): an additive error periodic in the disc angle only.

Families that are not here and why: load-dependent stray losses (an iron loss growing
with ``i^2``) and a commutator's bar bridging (a resistance ripple times the current)
act only while the current flows, which on this rig (no wedge load) is milliseconds at
the strokes' starts: a closed loop shows them only at sizes beyond the motor's own
torque, where the stray loss made the loop run away; a rotor's unbalance under gravity
is ``cogging`` at a 360-degree period and of 1e-4 N m; a vented piston boot pumping air
pushes with a fraction of a newton, tens of times less than a trace shows at the motor;
a magnetic hysteresis torque of the rotor iron is a Coulomb friction turning over a few
degrees (the catalog's stiction); a polymer gear's tooth creep is ``drive_compliance``
with ``pad_creep``'s lag; a dual-range torque flange switching range at a torque with
hysteresis is ``squeal_friction_drop`` a in what the trace shows; a load cell's
automatic zero tracking learns only the bell's tail at rest (some 10-40 N, a few noise
levels); a friction with a temperature hysteresis is the catalog's friction fade in what
a trace shows.

Command line
------------
``python -m validation_rigs.probe7_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from validation_rigs.probe_rig import make_probe_case, run_cli
from validation_rigs.uncatalogued_rig import H_MAX, Case, bell, chain, gap_m, theta_for_force

FAMILIES: dict[str, dict] = {
    "driver_standby_wake": {
        "stage": "motor",
        "place": "motor.electrical",
        "depends_on": {
            "a": ["voltage", "voltage_history"],
            "b": ["voltage", "voltage_history", "time"],
        },
        "words": "driver shorts its outputs in standby after the command has dwelt in its "
        "zero band for T_idle and applies nothing for t_w after the wake-up: a t_w fixed, "
        "b t_w = t_w0 (1 - exp(-t_sleep/tau_s)) (bootstrap recharge)",
    },
    "grease_viscoelastic_drag": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["speed", "time"], "b": ["speed", "time"]},
        "words": "viscoelastic gear grease (Maxwell): the drag relaxes toward its viscous "
        "value, lambda dtau/dt = c g(omega) - tau; a g = omega, "
        "b shear-thinning g = omega/(1 + |omega|/omega_c)",
    },
    "drive_slip_clutch": {
        "stage": "gap",
        "place": "drive",
        "depends_on": {"a": ["force"], "b": ["force", "direction"]},
        "words": "overload slip clutch in the drive: x = gap(theta - phi), phi grows so "
        "that the force does not pass the slip force; a F_s (slips at F_s), "
        "b sticks up to F_s, slides at F_k < F_s until the motor stops advancing",
    },
    "paste_squeeze_out": {
        "stage": "force",
        "place": "force.input",
        "depends_on": {"a": ["force", "time"], "b": ["force", "time"]},
        "words": "anti-squeal paste between piston and pad squeezed out under load: "
        "F = bell(x - (h_0 - h)); a Newtonian dh/dt = -K F h^3/2, "
        "b Bingham dh/dt = -K max(F - F_y, 0) h^3/2",
    },
    "plateau_flattening": {
        "stage": "torque",
        "place": "friction",
        "depends_on": {"a": ["force"], "b": ["force", "time"]},
        "words": "contact plateaus flattened by the largest force keep their area: "
        "mu (1 + eps ((M/F)^(1/3) - 1)); a M the record of F, b M relaxes to F (tau_p)",
    },
    "flange_rotor_zero": {
        "stage": "torque",
        "place": "sensor.torque_Nm",
        "depends_on": {"a": ["disc_angle"], "b": ["disc_angle"]},
        "words": "rotating torque flange's zero varies with its rotor angle (shaft "
        "misalignment bending): a T + A sin(phi_d + phi0), b T + A sin(2 phi_d + phi0)",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

#: Families run through the motor integration.
_MOTOR = {"driver_standby_wake", "grease_viscoelastic_drag"}
#: Families whose cases always record the current (none here).
CURRENT_ALWAYS: frozenset[str] = frozenset()
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe7"
#: Time constant of the driver's filter on ``|V|`` for its standstill detection [s].
STANDBY_TAU_F = 0.01
#: Least force in ``plateau_flattening``'s ratio ``M / F``, as a share of ``F_rt``.
PLATEAU_F_MIN = 0.02

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("driver_standby_wake", "a"): {
        "open": (5e-5, 1.5e-4),
        "closed": (0.005, 0.015),
        "unit": "t_w [s]",
    },
    ("driver_standby_wake", "b"): {
        "open": (6e-5, 1.8e-4),
        "closed": (0.006, 0.018),
        "unit": "t_w0 [s]",
    },
    ("grease_viscoelastic_drag", "a"): {
        "open": (1e-5, 3e-5),
        "closed": (2.5e-4, 7e-4),
        "unit": "c [N m s/rad]",
    },
    ("grease_viscoelastic_drag", "b"): {
        "open": (1.5e-5, 4.5e-5),
        "closed": (3.5e-4, 1e-3),
        "unit": "c [N m s/rad]",
    },
    ("drive_slip_clutch", "a"): {
        "open": (0.01, 0.03),
        "closed": (0.01, 0.03),
        "unit": "1 - F_s/F_pk [-]",
    },
    ("drive_slip_clutch", "b"): {
        "open": (0.006, 0.018),
        "closed": (0.006, 0.018),
        "unit": "1 - F_s/F_pk [-]",
    },
    ("paste_squeeze_out", "a"): {"open": (1e-5, 3e-5), "closed": (1e-5, 3e-5), "unit": "h_0 [m]"},
    ("paste_squeeze_out", "b"): {"open": (1e-5, 3e-5), "closed": (1e-5, 3e-5), "unit": "h_0 [m]"},
    ("plateau_flattening", "a"): {"open": (0.12, 0.3), "closed": (0.12, 0.3), "unit": "eps [-]"},
    ("plateau_flattening", "b"): {"open": (0.15, 0.4), "closed": (0.15, 0.4), "unit": "eps [-]"},
    ("flange_rotor_zero", "a"): {
        "open": (4e-3, 1.2e-2),
        "closed": (4e-3, 1.2e-2),
        "unit": "A / (2 mu F_rt r_eff) [-]",
    },
    ("flange_rotor_zero", "b"): {
        "open": (4e-3, 1.2e-2),
        "closed": (4e-3, 1.2e-2),
        "unit": "A / (2 mu F_rt r_eff) [-]",
    },
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``).

    ``h`` is recorded by ``run_motor`` as ``aux`` at the samples: the share of the
    present sub-step the bridge is off (``driver_standby_wake``), or the grease's drag
    ``tau`` [N m] (``grease_viscoelastic_drag``). Both states advance on the accepted
    sub-steps only: the standby state machine in ``advance``; the drag at the evaluation
    ``run_motor`` makes at the accepted state, which ``advance`` marks as the one to keep
    (predictor evaluations leave it alone)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        if family == "driver_standby_wake":
            v_i, t_idle, t_w = prm["V_i"], prm["T_idle_s"], prm["t_w_s"]
            tau_s = prm.get("tau_s_s")
            self._v = 0.0
            self._vf = 0.0  # |V| filtered by the driver's standstill detection [V]
            self._asleep = True  # the rig has stood still before the record
            self._slept = math.inf  # time asleep [s]
            self._idle = 0.0  # time awake inside the zero band [s]
            self._rem = 0.0  # wake-up time left [s]
            self._hs = H_MAX  # last sub-step [s]

            def f(i, w, th, V):
                self._v = V
                off = 1.0 if self._asleep else min(self._rem / self._hs, 1.0)
                self.h = off
                return V * off, 0.0

            def adv(i, hstep):
                self._hs = hstep
                self._vf = abs(self._v) + (self._vf - abs(self._v)) * math.exp(
                    -hstep / STANDBY_TAU_F
                )
                if self._asleep:
                    if self._vf > v_i:  # wake-up: the bridge stays off for t_w
                        sl = self._slept
                        self._rem = t_w if tau_s is None else t_w * -math.expm1(-sl / tau_s)
                        self._asleep, self._idle = False, 0.0
                    else:
                        self._slept += hstep
                elif self._rem > 0.0:
                    self._rem = max(self._rem - hstep, 0.0)
                elif self._vf < v_i:
                    self._idle += hstep
                    if self._idle >= t_idle:
                        self._asleep, self._slept = True, 0.0
                else:
                    self._idle = 0.0

            self.f, self.advance = f, adv
        elif family == "grease_viscoelastic_drag":
            c, lam = prm["c"], prm["lambda_s"]
            inv_wc = 1.0 / prm["omega_c"] if form == "b" else 0.0
            self._keep, self._hs = False, 0.0

            def f(i, w, th, V):
                if self._keep:  # the accepted state: relax the drag over the sub-step
                    target = c * w / (1.0 + abs(w) * inv_wc)
                    self.h = target + (self.h - target) * math.exp(-self._hs / lam)
                    self._keep = False
                return 0.0, self.h

            def adv(i, hstep):
                self._keep, self._hs = True, hstep

            self.f, self.advance = f, adv
        else:
            raise ValueError(family)


def draw_extras(family: str, form: str, rng: np.random.Generator, twin: dict) -> dict:
    """Effect parameters other than the strength (``twin``: the no-effect motor run)."""
    ex: dict = {}
    if family == "driver_standby_wake":
        av = np.abs(twin["V"])
        quiet = av[av < 0.02]
        q = float(np.median(quiet)) if quiet.size else 0.0
        ex.update(
            V_i=min(max(3.0 * q, 5e-3), 1.9e-2),
            dither_median_V=q,
            T_idle_s=float(rng.uniform(0.03, 0.1)),
        )
        if form == "b":
            ex["tau_s_s"] = float(rng.uniform(0.2, 1.0))
    elif family == "grease_viscoelastic_drag":
        ex["lambda_s"] = float(rng.uniform(0.05, 0.3))
        if form == "b":
            share = float(rng.uniform(0.2, 0.5))
            ex.update(omega_c_share=share, omega_c=share * float(np.max(np.abs(twin["w"]))))
    elif family == "drive_slip_clutch" and form == "b":
        ex["kinetic_drop"] = float(rng.uniform(0.5, 1.5))
    elif family == "paste_squeeze_out":
        ex["t_half_s"] = float(rng.uniform(0.5, 2.0) if form == "a" else rng.uniform(0.3, 1.2))
        if form == "b":
            ex["F_y_share"] = float(rng.uniform(0.3, 0.6))
    elif family == "plateau_flattening" and form == "b":
        ex["tau_p_s"] = float(rng.uniform(0.3, 1.5))
    elif family == "flange_rotor_zero":
        ex.update(order=1 if form == "a" else 2, phi0=float(rng.uniform(0.0, 2.0 * np.pi)))
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``).
    ``probe_chain`` adds the references it takes from the twin's readings."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "driver_standby_wake":
        prm["t_w_s"] = s
    elif family == "grease_viscoelastic_drag":
        prm["c"] = s
    elif family == "drive_slip_clutch":
        prm["cut"] = s
    elif family == "paste_squeeze_out":
        prm["h_0_m"] = s
    elif family == "plateau_flattening":
        prm["eps"] = s
    elif family == "flange_rotor_zero":
        prm["A_Nm"] = s * 2.0 * p["mu"] * p["F_rt"] * p["r_eff"]
    return prm


def _slip(th: np.ndarray, p: dict, prm: dict, form: str) -> tuple[np.ndarray, ...]:
    """Slip ``phi`` [deg] and force [N] of ``drive_slip_clutch``: the clutch slips while
    the motor drives the piston past the force it transmits (``F_s``, or ``F_k`` once
    sliding in b), so ``phi`` keeps ``bell(gap(theta - phi))`` at that force; it
    re-engages (b: sticks) when the motor stops advancing, keeping the slip."""
    f_s, f_k = prm["F_s_N"], prm.get("F_k_N", prm["F_s_N"])
    th_s = theta_for_force(f_s / p["F_rt"], p)  # angle of F_s on the bell's rising flank
    th_k = theta_for_force(f_k / p["F_rt"], p)
    n = len(th)
    phi, sliding = 0.0, False
    out_phi, out_f = np.empty(n), np.empty(n)
    for k in range(n):
        t_k = float(th[k])
        advancing = k > 0 and t_k > float(th[k - 1])
        if sliding and not advancing:
            sliding = False  # sticks again where it is
        if sliding:
            phi = max(phi, t_k - th_k)
        elif advancing and float(bell(gap_m(t_k - phi, p), p)) > f_s:
            if form == "a":
                phi = t_k - th_s
            else:
                phi, sliding = t_k - th_k, True
        out_phi[k] = phi
        out_f[k] = float(bell(gap_m(t_k - phi, p), p))
    return out_phi, out_f


def _squeeze(x: np.ndarray, p: dict, prm: dict, f_y: float, dt: float) -> tuple[np.ndarray, ...]:
    """Force [N] and film thinning ``h_0 - h`` [m] of ``paste_squeeze_out``: Reynolds'
    squeeze film, ``d(1/h^2)/dt = K max(F - F_y, 0)``, exact over a sample with the
    force held, ``K = 3 / (h_0^2 (F_rt - F_y) t_half)`` (``h`` halves in ``t_half`` at
    ``F_rt``)."""
    h0, f_rt = prm["h_0_m"], p["F_rt"]
    kk = 3.0 / (h0 * h0 * (f_rt - f_y) * prm["t_half_s"])
    inv2 = 1.0 / (h0 * h0)
    n = len(x)
    fo, do = np.empty(n), np.empty(n)
    for k in range(n):
        d = h0 - 1.0 / math.sqrt(inv2)
        fk = float(bell(float(x[k]) - d, p))
        fo[k], do[k] = fk, d
        inv2 += kk * max(fk - f_y, 0.0) * dt
    return fo, do


def probe_chain(
    p: dict, mot: dict, dt: float, w_disc: float, family: str, form: str, prm: dict
) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Noise-free readings with the probe effect (motor effects are already in ``mot``)."""
    rec, _, _, _ = chain(p, mot, dt, w_disc)
    th = mot["th"]
    n = len(th)
    t = np.arange(n) * dt
    mu, r, f_rt = p["mu"], p["r_eff"], p["F_rt"]
    x = gap_m(th, p)
    if family == "driver_standby_wake":
        return rec, mot["dv"], mot["aux"], "bridge_off_share"
    if family == "grease_viscoelastic_drag":
        return rec, mot["tau"], mot["w"], "omega_rad_s"
    if family == "drive_slip_clutch":
        f_pk = float(np.max(rec["force_N"]))
        prm.update(F_pk_twin_N=f_pk, F_s_N=(1.0 - prm["cut"]) * f_pk)
        if form == "b":
            prm["F_k_N"] = (1.0 - prm["cut"] * (1.0 + prm["kinetic_drop"])) * f_pk
        phi, force = _slip(th, p, prm, form)
        xp = gap_m(th - phi, p)
        rec["x_m"], rec["force_N"], rec["torque_Nm"] = xp, force, 2.0 * mu * force * r
        return rec, xp - x, force, "force_N"
    if family == "paste_squeeze_out":
        f_y = 0.0
        if form == "b":
            f_y = prm["F_y_share"] * float(np.max(rec["force_N"]))
            prm["F_y_N"] = f_y
        force, d = _squeeze(x, p, prm, f_y, dt)
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, -d, force, "force_N"
    if family == "plateau_flattening":
        force = rec["force_N"]
        if form == "a":
            rec_f = np.maximum.accumulate(force)
        else:
            a = math.exp(-dt / prm["tau_p_s"])
            rec_f = np.empty(n)
            m = 0.0
            for k in range(n):
                m = max(float(force[k]), force[k] + (m - force[k]) * a)
                rec_f[k] = m
        f_c = np.maximum(force, PLATEAU_F_MIN * f_rt)
        term = prm["eps"] * (np.cbrt(np.maximum(rec_f, f_c) / f_c) - 1.0)
        rec["torque_Nm"] = rec["torque_Nm"] * (1.0 + term)
        return rec, term, rec_f, "force_record_N"
    if family == "flange_rotor_zero":
        phd = w_disc * t + prm["phi0"]
        term = prm["A_Nm"] * np.sin(prm["order"] * phd)
        rec["torque_Nm"] = rec["torque_Nm"] + term
        return rec, term, np.mod(phd, 2.0 * np.pi), "disc_angle_rad"
    raise ValueError(family)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One case, drawn as ``probe_rig.make_case`` draws its cases; keywords as there."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
