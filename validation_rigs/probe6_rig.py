"""Sixth blind probe of discovery: six more physics families outside the catalog and
outside ``validation_rigs/uncatalogued_rig.py``'s fourteen and the six of each of
``probe_rig.py``, ``probe2_rig.py``, ``probe3_rig.py``, ``probe4_rig.py`` and
``probe5_rig.py``, one at each place of the chain (motor electrical, motor mechanical,
drive, force law, friction, a sensor), each with a different kind of dependence (a
product of the voltage and the energy drawn, a structure with the memory of the rotation
and of the rest, a power of the drive's speed, a jump at each release, a regime switched
by force thresholds, a sampled reading held between frames).

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package. The
cases are drawn exactly as ``probe_rig.make_case`` draws its own (its own seed stream).
References taken from "the twin" are from the same case's no-effect run.

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``bus_charge_droop`` (motor.electrical; voltage and current, b also time): the driver
  turns the voltage command ``V`` into a PWM duty of a DC bus it takes at its nominal
  voltage ``V_b0`` (no bus-voltage compensation), so it applies ``V_o = V V_b / V_b0``;
  the bus is a capacitor bank (the actuator's backup energy store, or a buffer behind a
  current-limited supply) that the energy ``E`` [J] the bridge delivers discharges,
  ``V_b / V_b0 = 1 - E / (C V_b0^2)`` to first order. ``V_o = V (1 - k E)`` with ``k =
  1 / (C V_b0^2)`` [1/J] the strength (``k E`` bounded to [-0.5, 0.9]); the energy is
  the bridge's DC power ``V_o i`` integrated on the motor's sub-steps (regenerated
  energy returns to the bank). a: no recharge within a record, ``dE/dt = V_o i``; b: a
  charger refills the bank through a resistance, ``dE/dt = V_o i - E / tau_ch``
  (``tau_ch`` drawn 0.3-1.5 s). The term is the voltage removed ``dV = V k E`` [V]. Not
  ``supply_sag`` (a source resistance: a drop with the present current, whatever the
  command, or a ceiling that sags with it): this is a product of the command and the
  bus state, which remembers the energy drawn since the start (a) or lately (b).
* ``grease_thixotropy`` (motor.mechanical; speed and travel, a also time): the gear
  grease is thixotropic: its soap structure, rebuilt at rest, gives a viscous drag that
  shearing breaks down (the no-load torque of a grease-lubricated gearbox is highest
  after a rest and falls as it runs in). ``tau = c lam omega`` [N m] with ``c`` [N m
  s/rad] the strength (the drag of fully structured grease, on top of the rig's
  viscous ``v``) and the structure ``lam`` in [0, 1], 1 at the start (the grease has
  rested), broken down per radian turned, ``dlam = -lam |dtheta| / Theta_b``,
  ``Theta_b`` a drawn share (a 0.1-0.3, b 0.15-0.4) of the twin's total rotation. a
  (Moore's thixotropy): it rebuilds at rest, ``dlam/dt = (1 - lam) / tau_r - lam
  |omega| / Theta_b`` (``tau_r`` drawn 0.3-1.5 s); b: the grease is channelled for
  good, ``lam = exp(-s / Theta_b)`` with ``s`` the rotation since the start. ``lam``
  advances on the motor's sub-steps at the accepted states. The term is the load
  torque [N m]. Not ``quadratic_drag`` (a drag instantaneous in the speed), nor the
  catalog's stiction (a breakaway at low speed) or friction_speed (the disc's sliding
  speed): a viscous drag whose coefficient remembers the shaft's rotation and rest.
* ``drive_film_lift`` (drive; x rate, b also force): the drive's lubricated contacts
  carry a film that the motion entrains and that vanishes at rest; it stands in the
  load path, so while the drive moves the piston is further out than its geometry
  gives, ``x = gap(theta) + h`` (the LVDT reads the piston, the bell sees it). The speed
  is the piston's ``|xdot|`` (the gap polynomial's slope times the motor speed),
  ``v_ref`` the twin's largest. a: rolling contacts (the wedge's rollers, a ball
  screw), elastohydrodynamic (the film grows with the entrainment speed to the 0.67 and
  hardly with the load), ``h = d (|xdot| / v_ref)^(2/3)``; b: a plain sliding contact
  (a greased wedge guide, a trapezoidal thread's flanks), the hydrodynamic slider law
  ``h ~ sqrt(eta U / W)``, ``h = d sqrt(|xdot| / v_ref F_0 / (F + F_0))`` with ``F`` the
  twin's bell force and ``F_0`` (a drawn share 0.02-0.06 of ``F_rt``, the guide's
  preload) bounding the film at no clamp. ``d`` [m] is the strength (the film at
  ``v_ref`` and no load). The film lives only during the strokes and the x noise is
  about 1 um, so the drawn films are some micrometres to a few tens unloaded (the upper
  end of a plain contact's film). The term is the x shift ``h`` [m]. Not
  ``drive_compliance`` nor ``roller_creep`` (the force, the travel), nor
  ``caliper_damping`` (a force added at the pad with the x rate): the drive's
  kinematics shifted by its own speed.
* ``pad_reseating`` (force.input; reversals, b also force): the pad sits in the
  caliper's abutments with a clearance; at each release it comes off and re-seats a
  little differently (rocking in the abutment, tilted by the drag it carried), so the
  point where the piston meets it moves from apply to apply: ``F = bell(x + delta_j)``
  during the ``j``-th apply after a release (the first apply as calibrated, ``delta_0 =
  0``). A release is counted when the bell force falls below 0.05 ``F_rt`` after it has
  exceeded 0.4 ``F_rt``. a: scatter, ``delta_j = s z_j`` with ``z_j`` drawn (with the
  case) of magnitude 0.4-1 and either sign; b: the pad is left tilted by the drag of the
  apply just released, ``delta_j = s F_pk,j / F_rt`` (``F_pk,j`` that apply's peak
  clamping force). ``s`` [m] is the strength. The LVDT reads the piston; the torque
  follows the clamping force. The term is the x shift the bell sees [m]. Not
  ``pad_set`` (permanent, growing during an apply with the record force), nor
  ``pad_wear`` or ``thermal_expansion`` (continuous in the distance or the energy), nor
  the catalog's force hysteresis (the direction of motion): a shift that jumps at the
  releases only, at random in a.
* ``squeal_friction_drop`` (friction; force, b also time): while the brake squeals the
  pads' normal vibration (kHz) lowers the mean friction (vibration-induced friction
  reduction), and whether it squeals depends on the clamping force. The torque is
  ``2 mu r_eff F (1 - eps q)`` with the squeal state ``q`` in [0, 1] and ``eps`` [-]
  the strength. a: a subcritical onset with hysteresis, ``q = 1`` from when ``F`` rises
  above ``F_on`` (a drawn share 0.3-0.6 of the twin's peak force) until it falls below
  ``F_off = r F_on`` (``r`` drawn 0.3-0.7); b: a window of forces ``[F_1, F_2]`` in
  which the squeal mode is unstable (above it the stiffer pad damps it): inside ``q``
  builds, ``tau_g dq/dt = 1 - q`` (``tau_g`` drawn 0.02-0.08 s), outside it decays
  three times faster; ``F_2`` is drawn 3-15 % above the lowest apply peak of the twin
  and ``F_1 = F_2 - w F_pk`` (``w`` drawn 0.3-0.45, ``F_pk`` the twin's peak). The
  torque sensor and the logging rate average the tone away; only the mean shows. The
  term is the mu factor minus one [-]. Not ``mu_pressure`` (a static function of the
  force), ``mu_load_rate`` (the force rate) nor ``mu_buildup`` (the contact time): a
  regime switched by force thresholds, with memory.
* ``fieldbus_sampling`` (sensor.torque_Nm; a force rate and time, b force and force
  rate): the torque flange sends its readings over a field bus (CANopen process data
  objects) and the logger holds the last frame until the next. a: cyclic frames every
  ``P`` [s] (the strength) on the sensor's own clock (phase drawn), asynchronous to the
  logger: the reading is the torque of the latest frame, aged 0 to ``P``, a saw-tooth
  delay that beats with the log rate (above a rate of ``1 / P`` the log repeats
  values); b: event-driven frames (CiA 404's analog input "interrupt delta"): the
  flange checks the torque every 1 ms and sends a frame when it has changed by
  ``Delta`` since the last one (``Delta`` the strength as a share of ``2 mu F_rt
  r_eff``). The torque between the samples is interpolated linearly. The term is the
  reading minus the torque [N m]. Not the catalog's sensor delay (one fixed delay) nor
  ``sensor_lowpass`` (a filter): a hold whose age varies from sample to sample (a) or
  that moves only in steps of ``Delta`` (b).

Families that are not here and why: a relay-reversed bridge's transfer time would be a
dead time at each reversal of the command, which the closed loop's dither at rest
fires tens of times a second (no rig runs a relay bridge so); a torsionally elastic
coupling between the motor and the worm rings above the logging rates when stiff and
adds the worm's inertia, a parameter, when soft; a bearing preload growing with the
motor's heat is a breakaway torque drifting with the heat, the catalog's stiction with
``worm_thermal_growth``'s input; a sensor excitation sagging with the motor current
shows only in the milliseconds of the current's peaks (``probe3_rig``'s note); a gear
mesh's stiffness varying with the tooth phase is a product of the force and a harmonic
of the angle (``cogging`` b's kind) of a micrometre; a caliper mount's resonance lies
above the logging rates; an encoder counter that misses counts above a speed is
``encoder_slip`` b with the speed for the current; a pad's bedding-in (mu rising stop
by stop) is the catalog's friction fade or ``mu_buildup`` in what a trace shows.

Command line
------------
``python -m validation_rigs.probe6_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from validation_rigs.probe_rig import make_probe_case, run_cli
from validation_rigs.uncatalogued_rig import DEG, Case, bell, chain, gap_m

FAMILIES: dict[str, dict] = {
    "bus_charge_droop": {
        "stage": "motor",
        "place": "motor.electrical",
        "depends_on": {"a": ["voltage", "current"], "b": ["voltage", "current", "time"]},
        "words": "driver's duty scales a bus that droops with the energy it has delivered: "
        "V_o = V (1 - k E); a capacitor bank dE/dt = V_o i, b recharged, "
        "dE/dt = V_o i - E/tau_ch",
    },
    "grease_thixotropy": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["speed", "travel", "time"], "b": ["speed", "travel"]},
        "words": "thixotropic gear grease: tau = c lam omega, structure lam broken down by "
        "the rotation; a rebuilds at rest, dlam/dt = (1 - lam)/tau_r - lam |omega|/Theta_b; "
        "b channels for good, lam = exp(-s/Theta_b)",
    },
    "drive_film_lift": {
        "stage": "gap",
        "place": "drive",
        "depends_on": {"a": ["x_rate"], "b": ["x_rate", "force"]},
        "words": "lubricant film in the drive lifts the piston while it moves: "
        "x = gap(theta) + h; a rolling (EHL) h = d (|xdot|/v_ref)^(2/3), "
        "b sliding (hydrodynamic) h = d sqrt(|xdot|/v_ref F_0/(F + F_0))",
    },
    "pad_reseating": {
        "stage": "force",
        "place": "force.input",
        "depends_on": {"a": ["reversals"], "b": ["force", "reversals"]},
        "words": "pad re-seats in its abutment at each release: F = bell(x + delta_j); "
        "a delta_j = s z_j (scatter, z_j drawn), b delta_j = s F_pk,j/F_rt "
        "(tilt left by the last apply's drag)",
    },
    "squeal_friction_drop": {
        "stage": "torque",
        "place": "friction",
        "depends_on": {"a": ["force"], "b": ["force", "time"]},
        "words": "squeal's normal vibration lowers the mean friction: mu (1 - eps q); "
        "a q relay, on above F_on, off below F_off; b q builds (tau_g) inside a force "
        "window [F_1, F_2], decays three times faster outside",
    },
    "fieldbus_sampling": {
        "stage": "torque",
        "place": "sensor.torque_Nm",
        "depends_on": {"a": ["force_rate", "time"], "b": ["force", "force_rate"]},
        "words": "torque flange read over a field bus, held between frames: a cyclic frames "
        "every P on the sensor's own clock; b a frame when the torque has changed by Delta",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

#: Families run through the motor integration.
_MOTOR = {"bus_charge_droop", "grease_thixotropy"}
#: Families whose cases always record the current (none here).
CURRENT_ALWAYS: frozenset[str] = frozenset()
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe6"
#: Apply / release thresholds of ``pad_reseating`` as shares of ``F_rt`` (an apply is
#: armed above the first, its release counted below the second).
APPLY_ARM, RELEASE_COUNT = 0.4, 0.05
#: Internal sampling interval of the delta-triggered torque flange [s].
FLANGE_DT = 1e-3

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("bus_charge_droop", "a"): {"open": (5e-3, 1.5e-2), "closed": (0.06, 0.2), "unit": "k [1/J]"},
    ("bus_charge_droop", "b"): {"open": (0.012, 0.035), "closed": (0.12, 0.35), "unit": "k [1/J]"},
    ("grease_thixotropy", "a"): {
        "open": (1e-5, 3e-5),
        "closed": (2.5e-4, 7e-4),
        "unit": "c [N m s/rad]",
    },
    ("grease_thixotropy", "b"): {
        "open": (1e-5, 3e-5),
        "closed": (2.5e-4, 7e-4),
        "unit": "c [N m s/rad]",
    },
    ("drive_film_lift", "a"): {"open": (8e-6, 2e-5), "closed": (8e-6, 2e-5), "unit": "d [m]"},
    ("drive_film_lift", "b"): {"open": (1e-5, 2.5e-5), "closed": (1e-5, 2.5e-5), "unit": "d [m]"},
    ("pad_reseating", "a"): {"open": (5e-6, 1.5e-5), "closed": (5e-6, 1.5e-5), "unit": "s [m]"},
    ("pad_reseating", "b"): {"open": (5e-6, 1.5e-5), "closed": (5e-6, 1.5e-5), "unit": "s [m]"},
    ("squeal_friction_drop", "a"): {
        "open": (0.01, 0.03),
        "closed": (0.01, 0.03),
        "unit": "eps [-]",
    },
    ("squeal_friction_drop", "b"): {
        "open": (0.015, 0.04),
        "closed": (0.015, 0.04),
        "unit": "eps [-]",
    },
    ("fieldbus_sampling", "a"): {"open": (3e-3, 1e-2), "closed": (3e-3, 1e-2), "unit": "P [s]"},
    ("fieldbus_sampling", "b"): {
        "open": (0.008, 0.02),
        "closed": (0.008, 0.02),
        "unit": "Delta / (2 mu F_rt r_eff) [-]",
    },
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``).

    ``h`` is recorded by ``run_motor`` as ``aux`` at the samples: the bus energy state
    ``E`` [J] of ``bus_charge_droop``, the grease structure ``lam`` [-] of
    ``grease_thixotropy``. The states advance on the accepted sub-steps only: the bus in
    ``advance``; the grease at the evaluation ``run_motor`` makes at the accepted state,
    which ``advance`` marks as the one to keep (predictor evaluations leave it alone)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        if family == "bus_charge_droop":
            k = prm["k"]
            tau = prm.get("tau_ch_s")
            self._v, self._i = 0.0, 0.0

            def share() -> float:  # bus droop [-], bounded (a pumped bus rises a little)
                return min(max(k * self.h, -0.5), 0.9)

            def f(i, w, th, V):
                self._v = V
                return V * share(), 0.0

            def adv(i, hstep):  # the bridge's DC power, trapezoidal over the sub-step
                q = self._v * (1.0 - share()) * 0.5 * (self._i + i) * hstep
                self._i = i
                if tau:
                    a = math.exp(-hstep / tau)
                    self.h = self.h * a + q * math.sqrt(a)
                else:
                    self.h += q

            self.f, self.advance = f, adv
        elif family == "grease_thixotropy":
            c, thb = prm["c"], prm["Theta_b_rad"]
            rb = 1.0 / prm["tau_r_s"] if form == "a" else 0.0
            self.h = 1.0  # rested grease: full structure
            self._th = None
            self._keep = True
            self._hs = 0.0

            def f(i, w, th, V):
                if self._th is None:
                    self._th = th
                if self._keep:  # the accepted state: advance the structure over the step
                    e = rb * self._hs + abs(th - self._th) / thb
                    if e > 0.0:
                        lam_inf = rb * self._hs / e
                        self.h = lam_inf + (self.h - lam_inf) * math.exp(-e)
                    self._th, self._hs, self._keep = th, 0.0, False
                return 0.0, c * self.h * w

            def adv(i, hstep):
                self._keep, self._hs = True, hstep

            self.f, self.advance = f, adv
        else:
            raise ValueError(family)


def draw_extras(family: str, form: str, rng: np.random.Generator, twin: dict) -> dict:
    """Effect parameters other than the strength (``twin``: the no-effect motor run)."""
    ex: dict = {}
    if family == "bus_charge_droop" and form == "b":
        ex["tau_ch_s"] = float(rng.uniform(0.3, 1.5))
    elif family == "grease_thixotropy":
        travel = float(np.sum(np.abs(np.diff(twin["th"])))) * DEG
        share = float(rng.uniform(0.1, 0.3) if form == "a" else rng.uniform(0.15, 0.4))
        ex.update(travel_rad=travel, Theta_b_share=share, Theta_b_rad=share * travel)
        if form == "a":
            ex["tau_r_s"] = float(rng.uniform(0.3, 1.5))
    elif family == "drive_film_lift" and form == "b":
        ex["F_0_share"] = float(rng.uniform(0.02, 0.06))
    elif family == "pad_reseating" and form == "a":
        z = rng.uniform(0.4, 1.0, 32) * rng.choice((-1.0, 1.0), 32)
        ex["z"] = [float(v) for v in z]
    elif family == "squeal_friction_drop":
        if form == "a":
            q_on, r = float(rng.uniform(0.3, 0.6)), float(rng.uniform(0.3, 0.7))
            ex.update(F_on_share=q_on, off_ratio=r)
        else:
            ex.update(
                F_2_above=float(rng.uniform(0.03, 0.15)),
                width_share=float(rng.uniform(0.3, 0.45)),
                tau_g_s=float(rng.uniform(0.02, 0.08)),
            )
    elif family == "fieldbus_sampling" and form == "a":
        ex["phase_share"] = float(rng.uniform(0.0, 1.0))
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``).
    ``probe_chain`` adds the references it takes from the twin's readings."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "bus_charge_droop":
        prm["k"] = s
    elif family == "grease_thixotropy":
        prm["c"] = s
    elif family == "drive_film_lift":
        prm["d_m"] = s
    elif family == "pad_reseating":
        prm["s_m"] = s
    elif family == "squeal_friction_drop":
        prm["eps"] = s
    elif family == "fieldbus_sampling":
        if form == "a":
            prm["P_s"] = s
        else:
            prm["Delta_Nm"] = s * 2.0 * p["mu"] * p["F_rt"] * p["r_eff"]
    return prm


def _reseat(x: np.ndarray, p: dict, prm: dict, form: str) -> tuple[np.ndarray, np.ndarray]:
    """x shift ``delta`` [m] the bell sees and releases counted, per sample, for
    ``pad_reseating``: ``delta`` changes at each release (the bell of ``x + delta``
    falling below ``RELEASE_COUNT F_rt`` after exceeding ``APPLY_ARM F_rt``)."""
    f_rt, s = p["F_rt"], prm["s_m"]
    n = len(x)
    shift, count = np.zeros(n), np.zeros(n)
    d, armed, pk, j = 0.0, False, 0.0, 0
    for k in range(n):
        fk = float(bell(x[k] + d, p))
        if not armed and fk > APPLY_ARM * f_rt:
            armed, pk = True, fk
        elif armed:
            pk = max(pk, fk)
            if fk < RELEASE_COUNT * f_rt:
                d = s * (prm["z"][j % len(prm["z"])] if form == "a" else pk / f_rt)
                armed, j = False, j + 1
        shift[k], count[k] = d, j
    return shift, count


def _apply_peaks(force: np.ndarray, f_rt: float) -> list[float]:
    """Peak force [N] of each apply (armed above ``APPLY_ARM F_rt``, ended by a release
    below ``RELEASE_COUNT F_rt`` or by the end of the record); the record's peak if none."""
    peaks, armed, pk = [], False, 0.0
    for fk in force:
        if not armed and fk > APPLY_ARM * f_rt:
            armed, pk = True, float(fk)
        elif armed:
            pk = max(pk, float(fk))
            if fk < RELEASE_COUNT * f_rt:
                peaks.append(pk)
                armed = False
    if armed:
        peaks.append(pk)
    return peaks or [float(np.max(force))]


def _squeal(force: np.ndarray, dt: float, prm: dict, form: str) -> np.ndarray:
    """Squeal state ``q`` in [0, 1] of ``squeal_friction_drop`` from the clamping force."""
    n = len(force)
    q = np.zeros(n)
    if form == "a":
        on, f_on, f_off = False, prm["F_on_N"], prm["F_off_N"]
        for k in range(n):
            if not on and force[k] > f_on:
                on = True
            elif on and force[k] < f_off:
                on = False
            q[k] = 1.0 if on else 0.0
        return q
    f1, f2, tau = prm["F_1_N"], prm["F_2_N"], prm["tau_g_s"]
    grow, decay = math.exp(-dt / tau), math.exp(-3.0 * dt / tau)
    y = 0.0
    for k in range(n):
        y = 1.0 + (y - 1.0) * grow if f1 <= force[k] <= f2 else y * decay
        q[k] = y
    return q


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
    if family == "bus_charge_droop":
        return rec, mot["dv"], mot["aux"], "bus_energy_J" if form == "a" else "bus_deficit_J"
    if family == "grease_thixotropy":
        return rec, mot["tau"], mot["aux"], "grease_structure"
    if family == "drive_film_lift":
        xdot = (2.0 * p["p2"] * th + p["p1"]) * mot["w"] / DEG
        v_ref = float(max(np.max(np.abs(xdot)), 1e-12))
        prm["v_ref_m_s"] = v_ref
        u = np.abs(xdot) / v_ref
        if form == "a":
            h = prm["d_m"] * u ** (2.0 / 3.0)
        else:
            f0 = prm["F_0_share"] * f_rt
            prm["F_0_N"] = f0
            h = prm["d_m"] * np.sqrt(u * f0 / (rec["force_N"] + f0))
        xp = x + h
        force = bell(xp, p)
        rec["x_m"], rec["force_N"], rec["torque_Nm"] = xp, force, 2.0 * mu * force * r
        return rec, h, xdot, "x_rate_m_s"
    if family == "pad_reseating":
        shift, count = _reseat(x, p, prm, form)
        force = bell(x + shift, p)
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, shift, count, "releases"
    if family == "squeal_friction_drop":
        force = rec["force_N"]
        f_pk = float(np.max(force))
        if form == "a":
            prm.update(F_on_N=prm["F_on_share"] * f_pk)
            prm["F_off_N"] = prm["off_ratio"] * prm["F_on_N"]
        else:
            f_low = min(_apply_peaks(force, f_rt))
            f_2 = f_low * (1.0 + prm["F_2_above"])
            prm.update(F_low_peak_N=f_low, F_2_N=f_2, F_1_N=f_2 - prm["width_share"] * f_pk)
        term = -prm["eps"] * _squeal(force, dt, prm, form)
        rec["torque_Nm"] = rec["torque_Nm"] * (1.0 + term)
        return rec, term, force, "force_N"
    if family == "fieldbus_sampling":
        torque = rec["torque_Nm"]
        if form == "a":
            per = prm["P_s"]
            phi = prm["phase_share"] * per
            t_f = phi + per * np.floor((t - phi) / per)  # the latest frame at or before t
            reading = np.interp(t_f, t, torque)
            tin, name = np.gradient(torque, dt), "torque_rate_Nm_s"
        else:
            m = max(1, math.ceil(dt / FLANGE_DT - 1e-9))
            tg = np.arange(n * m) * (dt / m)
            tq = np.interp(tg, t, torque)
            delta = prm["Delta_Nm"]
            held = np.empty(n * m)
            last = float(tq[0])
            for g in range(n * m):
                if abs(tq[g] - last) >= delta:
                    last = float(tq[g])
                held[g] = last
            reading = held[::m]
            tin, name = torque, "torque_Nm"
        rec["torque_Nm"] = reading
        return rec, reading - torque, tin, name
    raise ValueError(family)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One case, drawn as ``probe_rig.make_case`` draws its cases; keywords as there."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
