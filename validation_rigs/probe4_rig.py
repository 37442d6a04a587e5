"""Fourth blind probe of discovery: six more physics families outside the catalog and
outside ``validation_rigs/uncatalogued_rig.py``'s fourteen, ``probe_rig.py``'s six,
``probe2_rig.py``'s six and ``probe3_rig.py``'s six, one at each place of the chain
(motor electrical, motor mechanical, drive, force law, friction, a sensor).

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package. The
cases are drawn exactly as ``probe_rig.make_case`` draws its own (its own seed stream).
References taken from "the twin" are from the same case's no-effect run.

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``commutation_reactance`` (motor.electrical; current and speed): in a brushed motor
  the coil shorted by a brush must reverse its current within the commutation interval,
  which shrinks as the speed grows; the coil's inductance opposes it with the reactance
  voltage ``L_c di/dt ~ L_c 2 i / t_c``, ``t_c ~ 1 / |omega|``, which the brushes take
  from the supply (under-commutation, a voltage drop proportional to the current and
  the speed). The term is a voltage removed ``dV`` [V]. a: ``dV = k_c i |omega|``
  (``k_c`` [V s/(A rad)]); b: the brushes commutate without loss up to a speed
  ``omega_s`` and arc above it, ``dV = k_c i max(|omega| - omega_s, 0)``, ``omega_s`` a
  drawn share (0.3-0.6) of the twin's fastest ``|omega|`` [rad/s].
* ``screw_binding`` (motor.mechanical; angle and direction): the worm / spindle binds
  at some angles (a bent shaft, a damaged thread or a chip in the mesh), a friction
  torque ``tau = T_b g(theta) tanh(omega / omega_eps)`` [N m] that opposes the motion
  and depends on where the shaft is (``T_b`` [N m] the strength; the sign regularised
  with ``omega_eps = max(0.5 rad/s, 2 H_MAX T_b / M)``, sharp against the 10-100 rad/s
  of a stroke and stable on the 0.1 ms sub-steps). a: a bent shaft binds once per
  turn, ``g = (1 + cos(theta - theta_b)) / 2``; b: a tight spot at one angle, ``g =
  exp(-(theta - theta_b)^2 / (2 w_b^2))``, ``theta_b`` drawn in the middle 60 % of the
  twin's angle range, ``w_b`` 10-30 deg. It is not cogging (that is conservative, this
  dissipates in both directions) nor a speed-dependent friction (constant in angle).
* ``roller_creep`` (drive; a force, b force and time: the piston's accumulated travel
  has no word in the study's truth vocabulary, whose ``distance`` is the disc's sliding
  angle): the rolling elements of the angle-to-piston drive (the wedge's rollers, a
  roller screw's planets) creep under load (Carter creep): each travel ``|dx|`` of the
  drive under the clamping force ``F`` walks the rollers back by ``kappa (F / F_rt)
  |dx|``, so the piston falls behind the drive geometry, ``x = gap(theta) - delta`` (the
  LVDT reads the piston, the bell sees it). ``kappa`` [-] is the creep ratio at ``F_rt``
  (the strength). a: the creep accumulates (a ratchet, ``delta_k = delta_k-1 + kappa F_k
  / F_rt |dx_k|``); b: a cage spring re-centres the rollers with a time constant
  ``tau_r`` (drawn 0.3-1.5 s), ``delta_k = delta_k-1 exp(-dt / tau_r) + kappa F_k / F_rt
  |dx_k|``. ``F_k`` is the force at the previous shift (an explicit step; the shift is
  tiny per sample). The term is the x shift ``-delta`` [m].
* ``pad_edge_contact`` (force.output; x): the pad's load path changes near full clamp,
  which the bell (one elastic law over the whole stroke) cannot follow. With ``u =
  (x - x_e) / (x_pk - x_e)``, ``x_pk`` the twin's largest x and ``x_e`` the x at which
  the twin's bell gives a drawn share ``q`` (0.45-0.75) of its peak force: a: a second,
  stiffer contact engages (a cupped pad's rim or the caliper fingers bearing on the
  backplate; Hertzian line contact), ``F = bell(x) + F_e max(u, 0)^(3/2)`` (``F_e`` [N],
  the force it adds at ``x_pk``); b: the pad's damping underlayer yields (a plateau),
  ``F = bell(x) (1 - eps max(u, 0)^2)`` (``eps`` [-], the share lost at ``x_pk``). The
  torque follows the clamping force. The term is the force added [N].
* ``mu_buildup`` (friction; force and time): the friction coefficient rises during an
  application as the pads' transfer film forms (the in-stop rise of a dynamometer's
  stop), ``mu (1 + eps m)`` with ``eps`` [-] the strength and ``m`` in [0, 1] the film
  state, contact being ``F > F_c = 0.05 F_rt``. a: the film forms with the time ``t_c``
  since the present contact began and is wiped at each release, ``m = 1 - exp(-t_c /
  tau_f)``; b: it forms during contact and decays after, without a reset, ``tau_f dm/dt =
  [F > F_c] - m``. ``tau_f`` drawn 0.2-0.8 s. Unlike the catalog's friction_fade (mu
  falling with the dissipated energy over the whole record) it rises, and per contact.
  The term is the mu factor minus one [-].
* ``hall_remanence`` (sensor.current_A; current): the current sensor is a Hall
  transducer on a magnetic core; a large current leaves the core magnetised, so the
  reading keeps an offset (the datasheets' "magnetic offset after overload") in the
  sense of the last large current until a large current of the other sign clears it.
  ``i_c`` = a drawn share (0.3-0.6) of the twin's largest sampled ``|i|`` [A]; the
  strength is the offset at saturation ``eps`` [A]. a: a relay (one Preisach hysteron),
  ``r = eps`` after ``i > i_c``, ``-eps`` after ``i < -i_c``, 0 before either (the core
  starts demagnetised); b: a continuous magnetisation, the play operator ``y_k =
  min(max(y_k-1, i_k - i_c), i_k + i_c)`` (``y_0 = 0``), ``r = eps clip(y / i_c, -1,
  1)`` (a pulse to ``i_p`` leaves ``eps min(max(i_p - i_c, 0), i_c) / i_c``; saturated
  from ``2 i_c``). Both act on the current at the logged samples (the spikes between
  samples of a slow log are not simulated). The reading is ``i + r``. It only shows on a
  trace that records the current, so this family always records ``current_A`` (the
  drawn has-current flag and a ``has_current`` argument are overridden; truth
  ``has_current`` True).

Families that are not here and why: a magnet temperature lowering kb and kT is
``armature_heating``'s heat state in what the trace shows; an inductance that
saturates is invisible at these rates (the electrical time constant is 2 ms); the
reflected inertia of the piston is 1e-4 of the rotor's; a brake squeal's aliased tone
in the torque is a time function no term of the traces could learn; a force sensor's
thermal zero shift is ``piezo_leak`` b in what the trace shows; a friction varying
once per disc revolution (brake torque variation) is ``disc_runout`` b on the torque.

Command line
------------
``python -m validation_rigs.probe4_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from validation_rigs.probe_rig import make_probe_case, run_cli
from validation_rigs.uncatalogued_rig import DEG, H_MAX, Case, bell, chain, gap_m

FAMILIES: dict[str, dict] = {
    "commutation_reactance": {
        "stage": "motor",
        "place": "motor.electrical",
        "depends_on": {"a": ["current", "speed"], "b": ["current", "speed"]},
        "words": "commutation reactance voltage of a brushed motor: a dV = k_c i |omega|, "
        "b arcing above omega_s, dV = k_c i max(|omega| - omega_s, 0)",
    },
    "screw_binding": {
        "stage": "motor",
        "place": "motor.mechanical",
        "depends_on": {"a": ["angle", "direction"], "b": ["angle", "direction"]},
        "words": "spindle binds at some angles: tau = T_b g(theta) tanh(omega/omega_eps); "
        "a bent shaft g = (1 + cos(theta - theta_b))/2, b tight spot "
        "g = exp(-(theta - theta_b)^2/(2 w_b^2))",
    },
    "roller_creep": {
        "stage": "gap",
        "place": "drive",
        "depends_on": {"a": ["force"], "b": ["force", "time"]},
        "words": "drive rollers creep under load: x = gap(theta) - delta, "
        "a delta += kappa F/F_rt |dx| (ratchet), b the same with re-centring "
        "delta *= exp(-dt/tau_r)",
    },
    "pad_edge_contact": {
        "stage": "force",
        "place": "force.output",
        "depends_on": {"a": ["x"], "b": ["x"]},
        "words": "pad load path changes near full clamp, u = (x - x_e)/(x_pk - x_e): "
        "a stiff edge contact F = bell + F_e max(u,0)^1.5, b underlayer yields "
        "F = bell (1 - eps max(u,0)^2)",
    },
    "mu_buildup": {
        "stage": "torque",
        "place": "friction",
        "depends_on": {"a": ["force", "time"], "b": ["force", "time"]},
        "words": "mu rises during contact (F > 0.05 F_rt) as a transfer film forms: "
        "mu (1 + eps m); a m = 1 - exp(-t_c/tau_f), reset at release; "
        "b tau_f dm/dt = [contact] - m",
    },
    "hall_remanence": {
        "stage": "motor",
        "place": "sensor.current_A",
        "depends_on": {"a": ["current"], "b": ["current"]},
        "words": "Hall current sensor's core stays magnetised after a large current: "
        "i + r; a relay r = +-eps after i beyond +-i_c, "
        "b r = eps clip(play(i; i_c)/i_c, -1, 1)",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

_MOTOR = {"commutation_reactance", "screw_binding"}
#: Families whose cases always record the current: the effect is on that reading.
CURRENT_ALWAYS = frozenset({"hall_remanence"})
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe4"
#: Contact threshold of ``mu_buildup`` as a share of ``F_rt``.
CONTACT_SHARE = 0.05

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("commutation_reactance", "a"): {
        "open": (2e-3, 6e-3),
        "closed": (4e-3, 1.2e-2),
        "unit": "k_c [V s/(A rad)]",
    },
    ("commutation_reactance", "b"): {
        "open": (4e-3, 1.2e-2),
        "closed": (1e-2, 3e-2),
        "unit": "k_c [V s/(A rad)]",
    },
    ("screw_binding", "a"): {"open": (7e-4, 2.5e-3), "closed": (3e-3, 1e-2), "unit": "T_b [N m]"},
    ("screw_binding", "b"): {"open": (5e-3, 1.5e-2), "closed": (5e-3, 1.5e-2), "unit": "T_b [N m]"},
    ("roller_creep", "a"): {"open": (3e-3, 1e-2), "closed": (3e-3, 1e-2), "unit": "kappa [-]"},
    ("roller_creep", "b"): {"open": (1e-2, 3e-2), "closed": (1e-2, 3e-2), "unit": "kappa [-]"},
    ("pad_edge_contact", "a"): {"open": (60.0, 180.0), "closed": (60.0, 180.0), "unit": "F_e [N]"},
    ("pad_edge_contact", "b"): {"open": (0.02, 0.06), "closed": (0.02, 0.06), "unit": "eps [-]"},
    ("mu_buildup", "a"): {"open": (0.02, 0.05), "closed": (0.02, 0.05), "unit": "eps [-]"},
    ("mu_buildup", "b"): {"open": (0.02, 0.05), "closed": (0.02, 0.05), "unit": "eps [-]"},
    ("hall_remanence", "a"): {"open": (0.04, 0.12), "closed": (0.04, 0.12), "unit": "eps [A]"},
    ("hall_remanence", "b"): {"open": (0.08, 0.25), "closed": (0.08, 0.25), "unit": "eps [A]"},
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``).
    Both families here are memoryless (``advance`` None)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        if family == "commutation_reactance":
            k = prm["k_c"]
            ws = prm.get("omega_s", 0.0)

            def f(i, w, th, V):
                return k * i * max(abs(w) - ws, 0.0), 0.0

            self.f = f
        elif family == "screw_binding":
            tb, weps, thb = prm["T_b"], prm["omega_eps"], prm["theta_b_deg"] * DEG
            if form == "a":

                def g(th):
                    return 0.5 * (1.0 + math.cos(th - thb))

            else:
                inv = 1.0 / (2.0 * (prm["w_b_deg"] * DEG) ** 2)

                def g(th):
                    return math.exp(-((th - thb) ** 2) * inv)

            def f(i, w, th, V):
                return 0.0, tb * g(th) * math.tanh(w / weps)

            self.f = f
        else:
            raise ValueError(family)


def draw_extras(family: str, form: str, rng: np.random.Generator, twin: dict) -> dict:
    """Effect parameters other than the strength (``twin``: the no-effect motor run)."""
    ex: dict = {}
    if family == "commutation_reactance" and form == "b":
        share = float(rng.uniform(0.3, 0.6))
        ex.update(omega_s_share=share, omega_s=share * float(np.max(np.abs(twin["w"]))))
    elif family == "screw_binding":
        lo, hi = float(np.min(twin["th"])), float(np.max(twin["th"]))
        if form == "a":
            ex["theta_b_deg"] = float(rng.uniform(0.0, 360.0))
        else:
            ex["theta_b_deg"] = float(rng.uniform(lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)))
            ex["w_b_deg"] = float(rng.uniform(10.0, 30.0))
    elif family == "roller_creep" and form == "b":
        ex["tau_r_s"] = float(rng.uniform(0.3, 1.5))
    elif family == "pad_edge_contact":
        ex["q"] = float(rng.uniform(0.45, 0.75))
    elif family == "mu_buildup":
        ex["tau_f_s"] = float(rng.uniform(0.2, 0.8))
    elif family == "hall_remanence":
        share = float(rng.uniform(0.3, 0.6))
        i_pk = float(np.max(np.abs(twin["i"])))
        ex.update(i_c_share=share, i_c_A=share * i_pk, i_pk_A=i_pk)
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``).
    ``probe_chain`` adds the references it takes from the twin's readings."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "commutation_reactance":
        prm["k_c"] = s
    elif family == "screw_binding":
        prm["T_b"] = s
        prm["omega_eps"] = max(0.5, 2.0 * H_MAX * s / p["M"])
    elif family == "roller_creep":
        prm["kappa"] = s
    elif family == "pad_edge_contact":
        prm["F_e" if form == "a" else "eps"] = s
    elif family in ("mu_buildup", "hall_remanence"):
        prm["eps"] = s
    return prm


def _film(force: np.ndarray, f_c: float, tau: float, dt: float, reset: bool) -> np.ndarray:
    """Film state ``m`` in [0, 1] of ``mu_buildup``: contact is ``force > f_c``; with
    ``reset`` ``m = 1 - exp(-t_c / tau)`` (``t_c`` the time in the present contact),
    otherwise ``tau dm/dt = [contact] - m`` (exact for a contact held over each step)."""
    n = len(force)
    m = np.zeros(n)
    a = math.exp(-dt / tau)
    y = 0.0
    for k in range(1, n):
        on = 1.0 if force[k] > f_c else 0.0
        if reset and not on:
            y = 0.0
        else:
            y = on + (y - on) * a
        m[k] = y
    return m


def probe_chain(
    p: dict, mot: dict, dt: float, w_disc: float, family: str, form: str, prm: dict
) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Noise-free readings with the probe effect (motor effects are already in ``mot``)."""
    rec, _, _, _ = chain(p, mot, dt, w_disc)
    th, cur = mot["th"], mot["i"]
    n = len(th)
    mu, r, f_rt = p["mu"], p["r_eff"], p["F_rt"]
    x = gap_m(th, p)
    if family == "commutation_reactance":
        return rec, mot["dv"], mot["w"], "omega_rad_s"
    if family == "screw_binding":
        return rec, mot["tau"], th, "theta_deg"
    if family == "roller_creep":
        kappa = prm["kappa"]
        decay = math.exp(-dt / prm["tau_r_s"]) if form == "b" else 1.0
        delta = np.zeros(n)
        d = 0.0
        for k in range(1, n):
            fk = float(bell(x[k] - d, p))  # the force at the previous shift
            d = d * decay + kappa * fk / f_rt * abs(float(x[k] - x[k - 1]))
            delta[k] = d
        xp = x - delta
        force = bell(xp, p)
        rec["x_m"], rec["force_N"], rec["torque_Nm"] = xp, force, 2.0 * mu * force * r
        dist = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(x)))])
        return rec, -delta, dist, "drive_travel_m"
    if family == "pad_edge_contact":
        x_pk = float(np.max(x))
        f_pk = float(bell(x_pk, p))
        frac = min(prm["q"] * f_pk / p["F_rt"], 1.0 - 1e-9)
        x_e = p["c"] - p["a"] * (1.0 / frac - 1.0) ** (0.5 / p["b"])
        prm.update(x_peak_m=x_pk, x_e_m=float(x_e))
        u = np.maximum((x - x_e) / max(x_pk - x_e, 1e-12), 0.0)
        fb = rec["force_N"]
        force = fb + prm["F_e"] * u**1.5 if form == "a" else fb * (1.0 - prm["eps"] * u * u)
        term = force - fb
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, term, x, "x_m"
    if family == "mu_buildup":
        force = rec["force_N"]
        m = _film(force, CONTACT_SHARE * f_rt, prm["tau_f_s"], dt, reset=form == "a")
        term = prm["eps"] * m
        prm["F_c_N"] = CONTACT_SHARE * f_rt
        rec["torque_Nm"] = rec["torque_Nm"] * (1.0 + term)
        return rec, term, m, "film_state"
    if family == "hall_remanence":
        i_c, eps = prm["i_c_A"], prm["eps"]
        term = np.zeros(n)
        if form == "a":
            y = 0.0
            for k in range(n):
                ik = float(cur[k])
                if ik > i_c:
                    y = eps
                elif ik < -i_c:
                    y = -eps
                term[k] = y
        else:
            y = 0.0
            for k in range(n):
                ik = float(cur[k])
                y = min(max(y, ik - i_c), ik + i_c)
                term[k] = eps * min(max(y / i_c, -1.0), 1.0)
        rec["current_A"] = cur + term
        return rec, term, cur, "current_A"
    raise ValueError(family)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One case, drawn as ``probe_rig.make_case`` draws its cases (``hall_remanence``
    always records the current); keywords as there."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
