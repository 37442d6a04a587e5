"""Second blind probe of discovery: six more physics families outside the catalog and
outside ``validation_rigs/uncatalogued_rig.py``'s fourteen and ``probe_rig.py``'s six.

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package. The
cases are drawn exactly as ``probe_rig.make_case`` draws its own (its own seed stream).

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``gear_eccentricity`` (gap; angle): runout of the worm / pinion gear changes the
  piston position an angle gives. a: ``x = gap(theta + A sin(2 pi theta / 360 deg +
  phi))`` (A [deg], once per pinion revolution); b: ``x = gap(theta) + e sin(2 pi theta
  / 90 deg + phi)`` (a tooth-mesh ripple, e [m]). The displacement sensor reads the
  true x and the force and torque follow it; the angle reading is the pinion's.
* ``pad_wear`` (force.input; a distance, b energy): the pads wear while the disc
  slides, so the bell's centre moves, ``c + w D / D_end``: a with ``D`` the disc's
  sliding angle ``int |omega_d| dt``, b (Archard) with ``D`` the braking energy
  ``E = int T omega_d dt`` (a fixed point: the energy comes from the force it changes;
  ``E_end`` is the no-effect twin's). The term is the x shift the bell sees, ``-w D /
  D_end`` [m].
* ``current_leakage`` (sensor.current_A; voltage): the current sensor also measures a
  path that is not the motor (a snubber, the driver's own supply current): a ``i + V /
  R_p`` (strength ``G_p = 1 / R_p`` [A/V]), b ``i + k |V|``. It only shows on a trace
  that records the current, so this family always records ``current_A``: the drawn
  has-current flag and a ``has_current`` argument are overridden (truth
  ``has_current`` True).
* ``piezo_leak`` (sensor.force_N; force): a piezoelectric force washer. a: its charge
  leaks, the reading is the first-order high-pass of F, ``F - L(F)`` with ``tau_p dL/dt
  = F - L`` (starting in steady state); the strength is the leak rate ``1 / tau_p``
  [1/s], drawn for ``tau_p`` 25-40 s (below about 25 s the 3 s recordings lose more
  than 5 % of the force: not concealed). b: the charge amplifier drifts, ``F + d int F
  dt`` (strength ``d`` [1/s]).
* ``encoder_slip`` (sensor.theta_deg; a direction, b direction and current): the
  encoder's coupling slips. a: it loses ``delta`` deg at each reversal of the motor's
  direction, ``theta - delta n_rev(t)``; a reversal is counted when the angle has come
  back ``hyst_deg`` = 1 deg from its last extreme (a Schmitt trigger, so the dither of a
  closed loop at rest does not count). b: it slips while turning at a rate proportional
  to the current above a threshold, ``theta - k int max(|i| - i_s, 0) sign(omega) dt``
  with ``i_s`` a drawn share (0.5-1) of the twin's 90th percentile of ``|i|``. The
  position controller sees the true angle (the logged encoder is a separate readout),
  as for ``probe_rig``'s encoder family.
* ``thrust_bearing_friction`` (motor.mechanical; a force and direction, b force,
  direction and speed): the spindle's thrust bearing carries the clamping force, so a
  friction torque proportional to the force opposes the motion, ``F = bell(gap(theta))``
  from the motor angle inside the motor integration (the rig has no other load torque
  than its viscous one): a Coulomb ``k F sign(omega)``, the sign regularised as
  ``tanh(omega / omega_eps)`` with ``omega_eps = max(0.2 rad/s, 2 H_MAX k F_rt / M)``
  (sharp against the 10-100 rad/s of a stroke, stable on the 0.1 ms sub-steps); b soft
  ``k F tanh(omega / omega0)`` with ``omega0`` drawn in 3-10 rad/s.

Command line
------------
``python -m validation_rigs.probe2_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from validation_rigs.probe_rig import make_probe_case, run_cli
from validation_rigs.uncatalogued_rig import (
    DEG,
    H_MAX,
    Case,
    bell,
    chain,
    gap_m,
    lag_foh,
)

FAMILIES: dict[str, dict] = {
    "gear_eccentricity": {
        "stage": "gap",
        "place": "gap",
        "depends_on": {"a": ["angle"], "b": ["angle"]},
        "words": "gear runout: a x = gap(theta + A sin(2 pi theta/360 deg + phi)), "
        "b x = gap(theta) + e sin(2 pi theta/90 deg + phi) (tooth mesh)",
    },
    "pad_wear": {
        "stage": "force",
        "place": "force.input",
        "depends_on": {"a": ["distance"], "b": ["energy"]},
        "words": "pad wear moves the bell centre: a c + w s_d/s_end, s_d the disc's sliding "
        "angle; b (Archard) c + w E/E_end, E the braking energy",
    },
    "current_leakage": {
        "stage": "motor",
        "place": "sensor.current_A",
        "depends_on": {"a": ["voltage"], "b": ["voltage"]},
        "words": "current sensor also measures a path that is not the motor: a i + V/R_p, "
        "b i + k |V|",
    },
    "piezo_leak": {
        "stage": "force",
        "place": "sensor.force_N",
        "depends_on": {"a": ["force"], "b": ["force"]},
        "words": "piezo force washer: a charge leaks, reading the high-pass F - L(F), "
        "tau_p dL/dt = F - L; b charge-amplifier drift F + d int F dt",
    },
    "encoder_slip": {
        "stage": "motor",
        "place": "sensor.theta_deg",
        "depends_on": {"a": ["direction"], "b": ["direction", "current"]},
        "words": "encoder coupling slips: a theta - delta n_reversals, "
        "b theta - k int max(|i| - i_s, 0) sign(omega) dt",
    },
    "thrust_bearing_friction": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["force", "direction"], "b": ["force", "direction", "speed"]},
        "words": "thrust bearing friction carries the clamp force: a k F sign(omega), "
        "b k F tanh(omega/omega0)",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

_MOTOR = {"thrust_bearing_friction"}
#: Families whose cases always record the current: the effect is on that reading.
CURRENT_ALWAYS = frozenset({"current_leakage"})
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe2"

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("gear_eccentricity", "a"): {"open": (1.0, 3.0), "closed": (1.0, 3.0), "unit": "A [deg]"},
    ("gear_eccentricity", "b"): {"open": (4e-6, 1.2e-5), "closed": (4e-6, 1.2e-5), "unit": "e [m]"},
    ("pad_wear", "a"): {"open": (7e-6, 2e-5), "closed": (7e-6, 2e-5), "unit": "w [m]"},
    ("pad_wear", "b"): {"open": (7e-6, 2e-5), "closed": (7e-6, 2e-5), "unit": "w [m]"},
    ("current_leakage", "a"): {
        "open": (0.03, 0.09),
        "closed": (0.04, 0.1),
        "unit": "G_p = 1/R_p [A/V]",
    },
    ("current_leakage", "b"): {"open": (0.03, 0.09), "closed": (0.04, 0.1), "unit": "k [A/V]"},
    ("piezo_leak", "a"): {
        "open": (1 / 40, 1 / 25),
        "closed": (1 / 40, 1 / 25),
        "unit": "leak rate 1/tau_p [1/s]",
    },
    ("piezo_leak", "b"): {"open": (0.012, 0.025), "closed": (0.012, 0.025), "unit": "d [1/s]"},
    ("encoder_slip", "a"): {"open": (0.1, 0.3), "closed": (0.1, 0.3), "unit": "delta [deg]"},
    ("encoder_slip", "b"): {"open": (15.0, 60.0), "closed": (15.0, 60.0), "unit": "k [deg/(A s)]"},
    ("thrust_bearing_friction", "a"): {
        "open": (6e-8, 2e-7),
        "closed": (3e-6, 1e-5),
        "unit": "k [N m/N]",
    },
    ("thrust_bearing_friction", "b"): {
        "open": (4e-7, 1.5e-6),
        "closed": (3e-6, 1e-5),
        "unit": "k [N m/N]",
    },
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        if family != "thrust_bearing_friction":
            raise ValueError(family)
        k = prm["k"]
        p2, p1, p0 = p["p2"], p["p1"], p["p0"]
        cc, aa, nn, f_rt = p["c"], p["a"], 2.0 * p["b"], p["F_rt"]
        w0 = prm["omega_eps"] if form == "a" else prm["omega0"]

        def f(i, w, th, V):
            td = th / DEG
            u = abs((p2 * td * td + p1 * td + p0 - cc) / aa)
            return 0.0, k * f_rt / (1.0 + u**nn) * math.tanh(w / w0)

        self.f = f


def draw_extras(family: str, form: str, rng: np.random.Generator, twin: dict) -> dict:
    """Effect parameters other than the strength (``twin``: the no-effect motor run)."""
    ex: dict = {}
    if family == "gear_eccentricity":
        ex.update(P_deg=360.0 if form == "a" else 90.0, phi=float(rng.uniform(0, 2 * np.pi)))
    elif family == "encoder_slip":
        if form == "a":
            ex["hyst_deg"] = 1.0
        else:
            share = float(rng.uniform(0.5, 1.0))
            ex.update(i_s_share=share, i_s=share * float(np.percentile(np.abs(twin["i"]), 90)))
    elif family == "thrust_bearing_friction" and form == "b":
        ex["omega0"] = float(rng.uniform(3.0, 10.0))
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``)."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "gear_eccentricity":
        prm["A_deg" if form == "a" else "e_m"] = s
    elif family == "pad_wear":
        prm["w_m"] = s
    elif family == "current_leakage":
        prm.update({"G_p": s, "R_p": 1.0 / s} if form == "a" else {"k": s})
    elif family == "piezo_leak":
        prm.update({"leak_rate": s, "tau_p": 1.0 / s} if form == "a" else {"d": s})
    elif family == "encoder_slip":
        prm["delta_deg" if form == "a" else "k"] = s
    elif family == "thrust_bearing_friction":
        prm["k"] = s
        if form == "a":
            prm["omega_eps"] = max(0.2, 2.0 * H_MAX * s * p["F_rt"] / p["M"])
    return prm


def _reversals(th: np.ndarray, hyst: float) -> tuple[np.ndarray, np.ndarray]:
    """Direction (+1/-1, 0 before the first move) and reversal count per sample of an
    angle [deg], with a hysteresis of ``hyst`` [deg] from the last extreme."""
    n = len(th)
    dirn, count = np.zeros(n), np.zeros(n)
    d, c, ext = 0.0, 0, float(th[0])
    for k in range(n):
        v = float(th[k])
        if d == 0.0:
            if abs(v - ext) >= hyst:
                d, ext = math.copysign(1.0, v - ext), v
        elif (v - ext) * d > 0.0:
            ext = v
        elif (ext - v) * d >= hyst:
            d, c, ext = -d, c + 1, v
        dirn[k], count[k] = d, c
    return dirn, count


def _cumtrapz(y: np.ndarray, dt: float) -> np.ndarray:
    """Running trapezoidal integral of samples ``y`` at interval ``dt``, 0 at the start."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * dt)])


def probe_chain(
    p: dict, mot: dict, dt: float, w_disc: float, family: str, form: str, prm: dict
) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Noise-free readings with the probe effect (motor effects are already in ``mot``)."""
    rec, _, _, _ = chain(p, mot, dt, w_disc)
    th, cur = mot["th"], mot["i"]
    n = len(th)
    mu, r = p["mu"], p["r_eff"]
    x = gap_m(th, p)
    if family == "gear_eccentricity":
        arg = 2 * np.pi * th / prm["P_deg"] + prm["phi"]
        if form == "a":
            x_true = gap_m(th + prm["A_deg"] * np.sin(arg), p)
        else:
            x_true = x + prm["e_m"] * np.sin(arg)
        force = bell(x_true, p)
        rec["x_m"], rec["force_N"], rec["torque_Nm"] = x_true, force, 2.0 * mu * force * r
        return rec, x_true - x, th, "theta_deg"
    if family == "pad_wear":
        if form == "a":
            dist = np.abs(w_disc) * np.arange(n) * dt  # int |omega_d| dt, constant drag speed
            shift = -prm["w_m"] * dist / dist[-1]
            force = bell(x + shift, p)
            tin, name = dist, "disc_sliding_angle_rad"
        else:
            ref = float(_cumtrapz(2.0 * mu * r * bell(x, p) * w_disc, dt)[-1])  # E_end, twin
            force = bell(x, p)
            for _ in range(6):  # fixed point: the energy comes from the force it changes
                tin = _cumtrapz(2.0 * mu * r * force * w_disc, dt)
                shift = -prm["w_m"] * tin / ref
                force = bell(x + shift, p)
            name = "energy_J"
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, shift, tin, name
    if family == "current_leakage":
        volt = mot["V"]
        term = prm["G_p"] * volt if form == "a" else prm["k"] * np.abs(volt)
        rec["current_A"] = cur + term
        return rec, term, volt, "voltage_V"
    if family == "piezo_leak":
        force = rec["force_N"]
        if form == "a":
            term = -lag_foh(force, prm["tau_p"], dt)
        else:
            term = prm["d"] * _cumtrapz(force, dt)
        rec["force_N"] = force + term
        return rec, term, force, "force_N"
    if family == "encoder_slip":
        if form == "a":
            dirn, count = _reversals(th, prm["hyst_deg"])
            term, tin, name = -prm["delta_deg"] * count, dirn, "direction"
        else:
            rate = np.maximum(np.abs(cur) - prm["i_s"], 0.0) * np.sign(mot["w"])
            term, tin, name = -prm["k"] * _cumtrapz(rate, dt), cur, "current_A"
        rec["theta_deg"] = th + term
        return rec, term, tin, name
    if family == "thrust_bearing_friction":
        return rec, mot["tau"], bell(x, p), "force_N"
    raise ValueError(family)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One case, drawn as ``probe_rig.make_case`` draws its cases (``current_leakage``
    always records the current); keywords as there."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
