"""Third blind probe of discovery: six more physics families outside the catalog and
outside ``validation_rigs/uncatalogued_rig.py``'s fourteen, ``probe_rig.py``'s six and
``probe2_rig.py``'s six.

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package. The
cases are drawn exactly as ``probe_rig.make_case`` draws its own (its own seed stream).
References taken from "the twin" are from the same case's no-effect run.

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``return_spring`` (motor.mechanical; a x and angle, b angle): a preloaded spring
  that opens the brake loads the motor over the whole stroke, with no clamping force
  needed (a conservative load, zero friction). a: a coil spring on the piston,
  reflected through the drive by virtual work, ``tau = k_s (x(theta) - x_f) dx/dtheta``
  (``k_s`` [N/m], ``dx/dtheta`` [m/rad] from the gap polynomial, free length ``x_f =
  gap(theta_min) - l_p``, ``theta_min`` the twin's lowest angle, pre-compression
  ``l_p`` drawn 0.5-2 mm); b: a fail-safe torsion spring on the pinion, ``tau = k_th
  (theta - theta_f)`` (``k_th`` [N m/rad], ``theta_f = theta_min - theta_p``, pre-wind
  ``theta_p`` drawn 180-720 deg). ``tau`` [N m] is a load torque (it opposes opening
  the gap). The gear is not self-locking (the rig's motor has none), so in open loop
  the spring also backs the pinion off during the holds.
* ``piston_seal`` (motor.mechanical; travel and direction): the piston's elastomer
  seal grips the bore and deflects before it slides (seal roll-back), so its force
  ``z`` [N] on the piston builds over a travel ``s_0`` after each reversal and saturates
  at the sliding force ``F_s`` (the strength, [N]); the motor sees ``tau = z
  dx/dtheta`` [N m]. a (Dahl): ``dz = (F_s sign(dx) - z) |dx| / s_0``; b
  (elastic-perfectly plastic): ``z = clip(z + (F_s / s_0) dx, -F_s, F_s)``. ``x`` is the
  piston position ``gap(theta)`` [m], ``s_0`` drawn 0.05-0.2 mm (tens of pinion degrees,
  a few % of a stroke, unlike a Coulomb friction), ``z = 0`` at the start.
* ``pwm_ripple_alias`` (sensor.current_A; voltage and time): the motor current
  carries the PWM ripple of the power stage and the logger samples it without an
  anti-alias filter, its clock off the PWM's by tens of ppm: the nominal PWM frequency
  is a multiple of the logging rate, so the sampled ripple phase advances at the beat
  ``f_a`` [Hz] (drawn 0.3-3 Hz): ``psi_k = frac(f_a t_k + psi_0)``. Reading ``i + r(V)
  tri(psi_k; d)`` with ``tri`` the zero-mean triangle of unit peak-to-peak that rises
  over the on-share ``d`` of the period; supply ``V_s`` = 24 V, strength ``dI_0 = V_s /
  (L f_pwm)`` [A] (3 A is a 4 kHz PWM on the 2 mH motor). a: sign-magnitude PWM, ``D =
  |V| / V_s``, ``r = sign(V) dI_0 D (1 - D)``, ``d = D`` (no ripple at rest); b:
  locked anti-phase PWM, ``D_b = V / V_s``, ``r = dI_0 (1 - D_b^2) / 2``, ``d = (1 +
  D_b) / 2`` (largest at rest). Continuous conduction assumed. It only shows on a
  trace that records the current, so this family always records ``current_A`` (the
  drawn has-current flag and a ``has_current`` argument are overridden; truth
  ``has_current`` True).
* ``caliper_pin_friction`` (torque.output; force and direction): a floating caliper's
  guide pins stick, so the outer pad's force ``F_o`` is not the piston's ``F``: the pins
  hold the caliper while ``|F_o - F|`` is below their friction ``F_f``, a play operator
  ``F_o,k = min(max(F_o,k-1, F_k - F_f), F_k + F_f)`` (``F_o,0 = F_0``); the torque is
  ``mu r_eff (F + F_o)`` (the force sensor reads the piston's ``F``; the added term is
  ``mu r_eff (F_o - F)`` [N m]). a: ``F_f`` constant [N] (after a release the outer pad
  still drags with ``F_f``); b: the pins carry the pads' friction drag, ``F_f = kappa
  F`` (``kappa`` [-]; the torque's apparent mu is lower after an apply than after a
  release).
* ``probe_liftoff`` (sensor.x_m; a x rate and direction, b x rate, direction and x): the
  displacement sensor is a spring-return LVDT gauging probe pressed by the piston; on a
  fast retraction its plunger cannot follow and lifts off. Reading ``x_r``: ``x_r,k =
  max(x_k, R(x_r,k-1))``, with ``R`` the plunger's own return over one sample. a: a
  damped plunger with a constant return speed ``v_r``, ``R(y) = y - v_r dt``; b: a
  spring-dominated return toward its stop ``x_st`` (``l_s`` drawn 0.5-1.5 mm below the
  twin's lowest x), ``R(y) = x_st + (y - x_st) exp(-dt / tau_p)``. The strength is
  relative, zero at the edge of lift-off: a ``s = v_pk / v_r - 1`` with ``v_pk`` the
  twin's fastest retraction [m/s]; b ``s = tau_p / tau_c - 1`` with ``tau_c`` the
  largest ``tau_p`` that keeps contact on the twin (min of ``(x - x_st) / (-dx/dt)``
  over the retraction) [s]. The force and torque are those of the true piston.
* ``pad_set`` (force.input; force): green pads compact permanently (the permanent set
  ISO 6310 runs its preload cycles for): the pad thins whenever the clamping force
  sets a new record, and never recovers, so the bell sees ``x - delta g(M)`` with ``M``
  the running maximum of the clamping force (a fixed point per sample: a new record's
  force is the one its own set allows) and ``delta`` [m] the strength. a: ``g = M /
  F_rt``; b: set only above a yield force, ``g = max(M - F_y, 0) / (F_rt - F_y)`` with
  ``F_y`` a drawn share (0.3-0.6) of the twin's peak force. The term is the x shift the
  bell sees, ``-delta g(M)`` [m]; the LVDT reads the piston.

Families that are not here and why: a friction coefficient falling with a braking
temperature, and a torque-sensor gain drifting with it, are the catalog's
``friction_fade`` in what the trace shows; PWM dead time is ``brush_drop`` /
``driver_lag`` b; a strain-gauge excitation that sags with the motor current hardly
shows on this rig (its current is large only for milliseconds); an encoder's counts are
the clean traces' quantisation nuisance; a disc thickness variation is ``disc_runout``.

Command line
------------
``python -m validation_rigs.probe3_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from validation_rigs.probe_rig import make_probe_case, run_cli
from validation_rigs.uncatalogued_rig import DEG, Case, bell, chain, gap_m

FAMILIES: dict[str, dict] = {
    "return_spring": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["x", "angle"], "b": ["angle"]},
        "words": "preloaded brake-opening spring loads the motor: a coil spring on the piston "
        "tau = k_s (x - x_f) dx/dtheta, b torsion spring on the pinion "
        "tau = k_th (theta - theta_f)",
    },
    "piston_seal": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["travel", "direction"], "b": ["travel", "direction"]},
        "words": "piston seal deflects then slides (roll-back), tau = z dx/dtheta: "
        "a Dahl dz = (F_s sign(dx) - z)|dx|/s_0, b elastic-plastic "
        "z = clip(z + F_s dx/s_0, -F_s, F_s)",
    },
    "pwm_ripple_alias": {
        "stage": "motor",
        "place": "sensor.current_A",
        "depends_on": {"a": ["voltage", "time"], "b": ["voltage", "time"]},
        "words": "PWM current ripple sampled without anti-aliasing, beat f_a: i + r(V) "
        "tri(f_a t + psi_0; d); a sign-magnitude r = dI_0 D(1-D), b locked anti-phase "
        "r = dI_0 (1 - D_b^2)/2",
    },
    "caliper_pin_friction": {
        "stage": "torque",
        "place": "torque.output",
        "depends_on": {"a": ["force", "direction"], "b": ["force", "direction"]},
        "words": "floating caliper's guide pins stick: outer pad force F_o = play of F "
        "(half-width F_f), T = mu r (F + F_o); a F_f constant, b F_f = kappa F",
    },
    "probe_liftoff": {
        "stage": "gap",
        "place": "sensor.x_m",
        "depends_on": {"a": ["x_rate", "direction"], "b": ["x_rate", "direction", "x"]},
        "words": "spring-return LVDT probe lifts off on fast retraction: x_r = max(x, R(x_r)); "
        "a return speed v_r, b exponential return to its stop with tau_p",
    },
    "pad_set": {
        "stage": "force",
        "place": "force.input",
        "depends_on": {"a": ["force"], "b": ["force"]},
        "words": "pads compact permanently at each new force record: bell(x - delta g(M)), "
        "M running max of F; a g = M/F_rt, b g = max(M - F_y, 0)/(F_rt - F_y)",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

_MOTOR = {"return_spring", "piston_seal"}
#: Families whose cases always record the current: the effect is on that reading.
CURRENT_ALWAYS = frozenset({"pwm_ripple_alias"})
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe3"
#: Supply voltage of the PWM power stage [V] (above the closed loop's 12 V saturation).
V_SUPPLY = 24.0

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("return_spring", "a"): {"open": (80.0, 300.0), "closed": (5e3, 2e4), "unit": "k_s [N/m]"},
    ("return_spring", "b"): {
        "open": (2e-6, 8e-6),
        "closed": (3e-4, 1.5e-3),
        "unit": "k_th [N m/rad]",
    },
    ("piston_seal", "a"): {"open": (0.5, 2.0), "closed": (8.0, 40.0), "unit": "F_s [N]"},
    ("piston_seal", "b"): {"open": (0.5, 2.0), "closed": (8.0, 40.0), "unit": "F_s [N]"},
    ("pwm_ripple_alias", "a"): {"open": (3.0, 8.0), "closed": (4.0, 10.0), "unit": "dI_0 [A]"},
    ("pwm_ripple_alias", "b"): {"open": (0.6, 2.0), "closed": (0.6, 2.0), "unit": "dI_0 [A]"},
    ("caliper_pin_friction", "a"): {
        "open": (30.0, 90.0),
        "closed": (30.0, 90.0),
        "unit": "F_f [N]",
    },
    ("caliper_pin_friction", "b"): {
        "open": (0.02, 0.06),
        "closed": (0.02, 0.06),
        "unit": "kappa [-]",
    },
    ("probe_liftoff", "a"): {
        "open": (0.25, 0.5),
        "closed": (0.12, 0.3),
        "unit": "s = v_pk/v_r - 1 [-]",
    },
    ("probe_liftoff", "b"): {
        "open": (0.1, 0.25),
        "closed": (0.15, 0.4),
        "unit": "s = tau_p/tau_c - 1 [-]",
    },
    ("pad_set", "a"): {"open": (6e-6, 1.8e-5), "closed": (6e-6, 1.8e-5), "unit": "delta [m]"},
    ("pad_set", "b"): {"open": (1e-5, 3e-5), "closed": (1e-5, 3e-5), "unit": "delta [m]"},
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``).

    The seal's state advances only on accepted sub-steps: ``advance`` (called after each
    accepted step) marks the next evaluation, which ``run_motor`` makes at the accepted
    state, as the one to keep; predictor evaluations leave it alone. ``h`` holds the
    seal force [N] (``run_motor`` records it as ``aux``)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        p2, p1, p0 = p["p2"], p["p1"], p["p0"]
        if family == "return_spring":
            if form == "a":
                k, xf = prm["k_s"], prm["x_f"]

                def f(i, w, th, V):
                    td = th / DEG
                    x = p2 * td * td + p1 * td + p0
                    return 0.0, k * (x - xf) * (2.0 * p2 * td + p1) / DEG

            else:
                k, thf = prm["k_th"], prm["theta_f_deg"] * DEG

                def f(i, w, th, V):
                    return 0.0, k * (th - thf)

            self.f = f
        elif family == "piston_seal":
            fs, s0 = prm["F_s"], prm["s0_m"]
            dahl = form == "a"
            self._x = None  # piston position of the kept state [m]
            self._keep = True

            def f(i, w, th, V):
                td = th / DEG
                x = p2 * td * td + p1 * td + p0
                if self._x is None:
                    self._x = x
                dx = x - self._x
                z = self.h
                if dx != 0.0:
                    if dahl:
                        sg = math.copysign(fs, dx)
                        z = sg + (z - sg) * math.exp(-abs(dx) / s0)
                    else:
                        z = min(max(z + fs / s0 * dx, -fs), fs)
                if self._keep:
                    self.h, self._x, self._keep = z, x, False
                return 0.0, z * (2.0 * p2 * td + p1) / DEG

            def adv(i, hstep):
                self._keep = True

            self.f, self.advance = f, adv
        else:
            raise ValueError(family)


def draw_extras(family: str, form: str, rng: np.random.Generator, twin: dict) -> dict:
    """Effect parameters other than the strength (``twin``: the no-effect motor run)."""
    ex: dict = {}
    if family == "return_spring":
        ex["theta_min_deg"] = float(np.min(twin["th"]))
        if form == "a":
            ex["l_p_m"] = float(rng.uniform(0.5e-3, 2e-3))
        else:
            ex["theta_p_deg"] = float(rng.uniform(180.0, 720.0))
    elif family == "piston_seal":
        ex["s0_m"] = float(np.exp(rng.uniform(np.log(0.05e-3), np.log(0.2e-3))))
    elif family == "pwm_ripple_alias":
        ex.update(
            V_s=V_SUPPLY,
            f_a_hz=float(np.exp(rng.uniform(np.log(0.3), np.log(3.0)))),
            psi0=float(rng.uniform(0.0, 1.0)),
        )
    elif family == "probe_liftoff" and form == "b":
        ex["l_s_m"] = float(rng.uniform(0.5e-3, 1.5e-3))
    elif family == "pad_set" and form == "b":
        ex["F_y_share"] = float(rng.uniform(0.3, 0.6))
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``).
    ``probe_chain`` adds the references it takes from the twin's readings."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "return_spring":
        if form == "a":
            prm["k_s"] = s
            prm["x_f"] = float(gap_m(ex["theta_min_deg"], p)) - ex["l_p_m"]
        else:
            prm["k_th"] = s
            prm["theta_f_deg"] = ex["theta_min_deg"] - ex["theta_p_deg"]
    elif family == "piston_seal":
        prm["F_s"] = s
    elif family == "pwm_ripple_alias":
        prm["dI_0"] = s
        prm["f_pwm_equivalent_hz"] = ex["V_s"] / (p["L"] * s)
    elif family == "caliper_pin_friction":
        prm["F_f" if form == "a" else "kappa"] = s
    elif family == "probe_liftoff":
        prm["s"] = s
    elif family == "pad_set":
        prm["delta_m"] = s
    return prm


def _tri(psi: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Zero-mean triangle of unit peak-to-peak at the phase ``psi`` in [0, 1): rising
    from -1/2 over the share ``d`` of the period, then falling back."""
    d = np.clip(d, 1e-9, 1.0 - 1e-9)
    return np.where(psi < d, psi / d - 0.5, 0.5 - (psi - d) / (1.0 - d))


def _travel(x: np.ndarray) -> np.ndarray:
    """Signed travel [m] since the last reversal of ``x`` (sign: the present direction)."""
    out = np.zeros(len(x))
    d, s = 0.0, 0.0
    for k in range(1, len(x)):
        dx = float(x[k] - x[k - 1])
        if dx != 0.0:
            sg = math.copysign(1.0, dx)
            if sg != d:
                d, s = sg, 0.0
            s += abs(dx)
        out[k] = d * s
    return out


def probe_chain(
    p: dict, mot: dict, dt: float, w_disc: float, family: str, form: str, prm: dict
) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Noise-free readings with the probe effect (motor effects are already in ``mot``)."""
    rec, _, _, _ = chain(p, mot, dt, w_disc)
    th, cur = mot["th"], mot["i"]
    n = len(th)
    mu, r = p["mu"], p["r_eff"]
    x = gap_m(th, p)
    if family == "return_spring":
        if form == "a":
            return rec, mot["tau"], x, "x_m"
        return rec, mot["tau"], th, "theta_deg"
    if family == "piston_seal":
        return rec, mot["tau"], _travel(x), "travel_since_reversal_m"
    if family == "pwm_ripple_alias":
        volt = mot["V"]
        psi = np.mod(prm["f_a_hz"] * np.arange(n) * dt + prm["psi0"], 1.0)
        if form == "a":
            dd = np.minimum(np.abs(volt) / prm["V_s"], 1.0)
            term = np.sign(volt) * prm["dI_0"] * dd * (1.0 - dd) * _tri(psi, dd)
        else:
            db = np.clip(volt / prm["V_s"], -1.0, 1.0)
            term = prm["dI_0"] * (1.0 - db * db) / 2.0 * _tri(psi, (1.0 + db) / 2.0)
        rec["current_A"] = cur + term
        return rec, term, volt, "voltage_V"
    if family == "caliper_pin_friction":
        force = rec["force_N"]
        half = np.full(n, prm["F_f"]) if form == "a" else prm["kappa"] * force
        outer = np.empty(n)
        y = float(force[0])
        for k in range(n):
            y = min(max(y, force[k] - half[k]), force[k] + half[k])
            outer[k] = y
        term = mu * r * (outer - force)
        rec["torque_Nm"] = rec["torque_Nm"] + term
        return rec, term, force, "force_N"
    if family == "probe_liftoff":
        xdot = np.gradient(x, dt)
        if form == "a":
            v_pk = float(max(np.max(-np.diff(x)) / dt, 1e-9))
            v_r = v_pk / (1.0 + prm["s"])
            prm.update(v_peak_m_s=v_pk, v_r_m_s=v_r)
            step = v_r * dt
        else:
            x_st = float(np.min(x)) - prm["l_s_m"]
            back = np.diff(x) < 0.0  # retracting sample intervals
            dxs = -np.diff(x)[back] / dt
            tau_c = float(np.min((x[1:][back] - x_st) / dxs)) if back.any() else 1.0
            tau_p = tau_c * (1.0 + prm["s"])
            prm.update(x_stop_m=x_st, tau_c_s=tau_c, tau_p_s=tau_p)
            decay = math.exp(-dt / tau_p)
        xr = np.empty(n)
        y = float(x[0])
        for k in range(n):
            ret = y - step if form == "a" else x_st + (y - x_st) * decay
            y = max(float(x[k]), ret)
            xr[k] = y
        rec["x_m"] = xr
        return rec, xr - x, xdot, "x_rate_m_s"
    if family == "pad_set":
        f_rt, delta = p["F_rt"], prm["delta_m"]
        if form == "a":
            f_y = 0.0
        else:
            f_y = prm["F_y_share"] * float(np.max(rec["force_N"]))
            prm["F_y_N"] = f_y
        span = f_rt - f_y

        def shift(m):
            return delta * max(m - f_y, 0.0) / span

        force, sft, peak = np.empty(n), np.empty(n), np.empty(n)
        m = 0.0
        for k in range(n):
            xk = float(x[k])
            fk = float(bell(xk - shift(m), p))
            if fk > m:  # a new record: the force its own set allows (a contraction)
                for _ in range(30):
                    f_new = float(bell(xk - shift(fk), p))
                    if abs(f_new - fk) < 1e-9 * f_rt:
                        fk = f_new
                        break
                    fk = f_new
                m = max(m, fk)
            force[k], sft[k], peak[k] = fk, -shift(m), m
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, sft, peak, "force_running_max_N"
    raise ValueError(family)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One case, drawn as ``probe_rig.make_case`` draws its cases (``pwm_ripple_alias``
    always records the current); keywords as there."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
