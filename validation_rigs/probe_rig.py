"""Blind probe of discovery: six more physics families outside the catalog *and* outside
``validation_rigs/uncatalogued_rig.py``'s fourteen.

The simulator is the uncatalogued rig's (motor ETD2 integration, gap polynomial, bell,
drive profiles, noise, visibility and the strength rescale rule); only the planted
effects are new. Like that rig it shares no code with the identification package.

Families (two forms each; ``place`` and ``depends_on`` in the truth vocabulary)
-------------------------------------------------------------------------------
* ``torque_current_crosstalk`` (sensor.torque_Nm; current): the torque bridge picks
  up the motor current (shared ground / magnetic pickup): reading ``T + k i`` (a) or
  ``T + k |i|`` (b, a rectified pickup).
* ``disc_runout`` (force; disc angle): disc thickness variation once per disc
  revolution. a: the bell sees ``x + e sin(phi_d + phi0)`` (force.input); b: the force
  is modulated, ``F (1 + eps sin(phi_d + phi0))`` (force.output, a product of the force
  and a harmonic of the disc angle). ``phi_d = omega_d t``.
* ``driver_lag`` (motor.electrical; voltage): the power stage does not apply the logged
  voltage. a: its output filter lags it, ``tau_d dV_eff/dt = V - V_eff`` (a voltage
  history); b: a dead band of the H-bridge (dead time), ``V_eff = sign(V)
  max(|V| - V_d, 0)``.
* ``torque_ripple`` (motor; angle and current): commutation ripple of the motor
  constant with the rotor angle, period ``P`` = 60 deg. a: torque only,
  ``kT i (1 + eps sin(2 pi theta / P + phi))`` (a load torque ``-eps kT i sin(...)``:
  the current times a harmonic of the angle); b: torque and back-EMF both (the same
  flux ripple in ``kT`` and ``kb``: a term at motor.mechanical *and* motor.electrical).
* ``pad_stiffness_heating`` (force; x and energy): the pad softens as it heats: the
  bell's width ``a`` grows, ``a (1 + s E / E_end)`` with ``E`` the braking energy (a)
  or ``a (1 + s Q / Q_max)`` with ``Q`` the braking power low-passed over 1 s (b, a
  temperature that cools). A parameter of the force law changing with a history: in
  the chain a function of the displacement *times* a function of the energy.
* ``encoder_eccentricity`` (sensor.theta_deg; angle): the angle encoder's disc is
  mounted off-centre: reading ``theta + A sin(2 pi theta / P + phi)``, P = 360 deg
  (a, once per revolution) or 120 deg (b).

Command line
------------
``python -m validation_rigs.probe_rig --seed S --per-form N --out DIR``
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from validation_rigs import uncatalogued_rig as ur
from validation_rigs.uncatalogued_rig import (
    DEG,
    PROFILES,
    RATES_HZ,
    Case,
    _code,
    _draw_rig,
    _released,
    _table,
    bell,
    chain,
    gap_m,
    lag_foh,
    plan_profile,
    rescale,
    run_motor,
    visibility,
    write_case,
)

FAMILIES: dict[str, dict] = {
    "torque_current_crosstalk": {
        "stage": "torque",
        "place": "sensor.torque_Nm",
        "depends_on": {"a": ["current"], "b": ["current"]},
        "words": "torque reading picks up the motor current: a T + k i, b T + k |i|",
    },
    "disc_runout": {
        "stage": "force",
        "place": {"a": "force.input", "b": "force.output"},
        "depends_on": {"a": ["disc_angle"], "b": ["disc_angle", "force"]},
        "words": "disc thickness variation once per revolution: a bell(x + e sin(phi_d+phi0)), "
        "b F (1 + eps sin(phi_d + phi0))",
    },
    "driver_lag": {
        "stage": "motor",
        "place": "motor.electrical",
        "depends_on": {"a": ["voltage", "voltage_history"], "b": ["voltage"]},
        "words": "power stage: a output filter tau_d dV_eff/dt = V - V_eff, "
        "b dead band V_eff = sign(V) max(|V| - V_d, 0)",
    },
    "torque_ripple": {
        "stage": "motor",
        "place": {"a": "motor.mechanical", "b": "motor.mechanical+motor.electrical"},
        "depends_on": {"a": ["angle", "current"], "b": ["angle", "current", "speed"]},
        "words": "commutation ripple, period 60 deg: a kT i (1 + eps sin(2 pi th/P + phi)), "
        "b the same ripple in kT and kb",
    },
    "pad_stiffness_heating": {
        "stage": "force",
        "place": "force.input",
        "depends_on": {"a": ["x", "energy"], "b": ["x", "energy_history"]},
        "words": "bell width grows as the pad heats: a a (1 + s E/E_end), "
        "b a (1 + s Q/Q_max), Q braking power low-passed over 1 s",
    },
    "encoder_eccentricity": {
        "stage": "motor",
        "place": "sensor.theta_deg",
        "depends_on": {"a": ["angle"], "b": ["angle"]},
        "words": "encoder reading theta + A sin(2 pi theta / P + phi): a P 360 deg, b P 120 deg",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

_MOTOR = {"driver_lag", "torque_ripple"}
#: Families whose cases always record the current (none here).
CURRENT_ALWAYS: frozenset[str] = frozenset()
#: The rig's name (its cases' seeds and descriptions).
NAME = "probe"

#: Starting strength ranges (lo, hi), open loop / closed loop; the rescale rule of the
#: uncatalogued rig then makes each case visible and concealed.
_SIZE: dict[tuple[str, str], dict] = {
    ("torque_current_crosstalk", "a"): {
        "open": (1.0, 3.0),
        "closed": (1.0, 3.0),
        "unit": "k [N m/A]",
    },
    ("torque_current_crosstalk", "b"): {
        "open": (1.0, 3.0),
        "closed": (1.0, 3.0),
        "unit": "k [N m/A]",
    },
    ("disc_runout", "a"): {"open": (1e-6, 3e-6), "closed": (1e-6, 3e-6), "unit": "e [m]"},
    ("disc_runout", "b"): {"open": (0.005, 0.015), "closed": (0.005, 0.015), "unit": "eps [-]"},
    ("driver_lag", "a"): {"open": (0.001, 0.003), "closed": (0.001, 0.003), "unit": "tau_d [s]"},
    ("driver_lag", "b"): {"open": (0.01, 0.03), "closed": (0.05, 0.15), "unit": "V_d [V]"},
    ("torque_ripple", "a"): {"open": (0.01, 0.03), "closed": (0.02, 0.06), "unit": "eps [-]"},
    ("torque_ripple", "b"): {"open": (0.01, 0.03), "closed": (0.02, 0.06), "unit": "eps [-]"},
    ("pad_stiffness_heating", "a"): {
        "open": (0.01, 0.03),
        "closed": (0.01, 0.03),
        "unit": "relative growth of a at E_end [-]",
    },
    ("pad_stiffness_heating", "b"): {
        "open": (0.01, 0.03),
        "closed": (0.01, 0.03),
        "unit": "relative growth of a at Q_max [-]",
    },
    ("encoder_eccentricity", "a"): {"open": (0.1, 0.3), "closed": (0.1, 0.3), "unit": "A [deg]"},
    ("encoder_eccentricity", "b"): {"open": (0.1, 0.3), "closed": (0.1, 0.3), "unit": "A [deg]"},
}


class MotorEffect:
    """Motor term ``f(i, w, th, V) -> (voltage removed [V], load torque [N m])`` with the
    hooks ``run_motor`` of the uncatalogued rig uses (``h``, ``advance``, ``stiff``)."""

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0
        self.advance = None
        self.stiff = False
        kT, kb = p["kT"], p["kb"]
        if family == "driver_lag" and form == "a":
            tau = prm["tau_d"]
            self._v = 0.0

            def f(i, w, th, V):
                self._v = V
                return V - self.h, 0.0

            def adv(i, hstep):  # V_eff (kept in h) follows the held V through the filter
                self.h = self._v + (self.h - self._v) * math.exp(-hstep / tau)

            self.f, self.advance = f, adv
        elif family == "driver_lag":
            vd = prm["V_d"]
            self.f = lambda i, w, th, V: (math.copysign(min(abs(V), vd), V), 0.0)
        elif family == "torque_ripple":
            eps, kk, ph = prm["eps"], 2 * math.pi / prm["P_deg"] / DEG, prm["phi"]
            both = form == "b"

            def f(i, w, th, V):
                r = eps * math.sin(kk * th + ph)
                return (kb * w * r if both else 0.0), -kT * i * r

            self.f = f
        else:
            raise ValueError(family)


def draw_extras(family: str, form: str, rng: np.random.Generator, twin=None) -> dict:
    ex: dict = {}
    if family == "disc_runout":
        ex["phi0"] = float(rng.uniform(0, 2 * np.pi))
    elif family == "torque_ripple":
        ex.update(P_deg=60.0, phi=float(rng.uniform(0, 2 * np.pi)))
    elif family == "encoder_eccentricity":
        ex.update(P_deg=360.0 if form == "a" else 120.0, phi=float(rng.uniform(0, 2 * np.pi)))
    elif family == "pad_stiffness_heating" and form == "b":
        ex["tau_q"] = 1.0
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p=None) -> dict:
    prm = dict(ex)
    prm["strength"] = s
    key = {
        "torque_current_crosstalk": "k",
        "disc_runout": "e_m" if form == "a" else "eps",
        "driver_lag": "tau_d" if form == "a" else "V_d",
        "torque_ripple": "eps",
        "pad_stiffness_heating": "growth",
        "encoder_eccentricity": "A_deg",
    }[family]
    prm[key] = s
    return prm


def probe_chain(
    p: dict, mot: dict, dt: float, w_disc: float, family: str, form: str, prm: dict
) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Noise-free readings with the probe effect (motor effects are already in ``mot``)."""
    rec, _, _, _ = chain(p, mot, dt, w_disc)
    th, cur = mot["th"], mot["i"]
    n = len(th)
    t = np.arange(n) * dt
    mu, r = p["mu"], p["r_eff"]
    x = gap_m(th, p)
    if family == "torque_current_crosstalk":
        term = prm["k"] * (cur if form == "a" else np.abs(cur))
        rec["torque_Nm"] = rec["torque_Nm"] + term
        return rec, term, cur, "current_A"
    if family == "disc_runout":
        phd = w_disc * t + prm["phi0"]
        if form == "a":
            term = prm["e_m"] * np.sin(phd)
            force = bell(x + term, p)
        else:
            fb = bell(x, p)
            force = fb * (1.0 + prm["eps"] * np.sin(phd))
            term = force - fb
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, term, np.mod(phd, 2 * np.pi), "disc_angle_rad"
    if family == "pad_stiffness_heating":
        f0 = bell(x, p)
        p_w = 2.0 * mu * r * f0 * w_disc
        if form == "a":
            ref = float(np.sum(0.5 * (p_w[1:] + p_w[:-1])) * dt)  # E_end of the twin
        else:
            ref = float(np.max(lag_foh(p_w, prm["tau_q"], dt)))  # Q_max of the twin
        force = f0
        for _ in range(6):  # fixed point: the heat comes from the braking it changes
            p_w = 2.0 * mu * r * force * w_disc
            if form == "a":
                hsig = np.concatenate([[0.0], np.cumsum(0.5 * (p_w[1:] + p_w[:-1]) * dt)])
            else:
                hsig = lag_foh(p_w, prm["tau_q"], dt)
                hsig = hsig - hsig[0]
            growth = prm["growth"] * hsig / ref
            force = bell(x, p | {"a": p["a"] * (1.0 + growth)})
        rec["force_N"], rec["torque_Nm"] = force, 2.0 * mu * force * r
        return rec, growth, hsig, "energy_J" if form == "a" else "power_lowpassed_W"
    if family == "encoder_eccentricity":
        term = prm["A_deg"] * np.sin(2 * np.pi * th / prm["P_deg"] + prm["phi"])
        rec["theta_deg"] = th + term
        return rec, term, th, "theta_deg"
    if family == "driver_lag":
        return rec, mot["dv"], mot["V"], "voltage_V"
    if family == "torque_ripple":
        return rec, mot["tau"], th, "theta_deg"
    raise ValueError(family)


def make_probe_case(
    rig: Any,
    family: str,
    form: str,
    seed: int,
    index: int,
    *,
    rate_hz: float | None = None,
    profile: str | None = None,
    has_current: bool | None = None,
    duration_s: float | None = None,
) -> Case:
    """One case of a probe rig module ``rig`` (its ``NAME``, ``FAMILIES``, ``_SIZE``,
    ``_MOTOR``, ``MotorEffect``, ``draw_extras``, ``effect_params``, ``probe_chain`` and
    ``CURRENT_ALWAYS``), drawn as ``uncatalogued_rig.make_case`` draws its cases."""
    FAMILIES, _SIZE = rig.FAMILIES, rig._SIZE  # noqa: N806
    if family not in FAMILIES or form not in ("a", "b"):
        raise ValueError(f"unknown family/form {family}/{form}")
    ss = np.random.SeedSequence([seed, index, _code(family), _code(form), _code(rig.NAME)])
    r_rig, r_plan, r_noise, r_eff = (np.random.default_rng(c) for c in ss.spawn(4))
    p = _draw_rig(r_rig)
    rate = int(r_plan.choice(RATES_HZ))
    prof = str(r_plan.choice(PROFILES))
    cur_on = bool(r_plan.random() < 0.5)
    factor = float(np.exp(r_plan.uniform(np.log(0.5), np.log(2.0))))
    w_disc = float(r_plan.uniform(20.0, 50.0))
    theta0 = float(r_plan.uniform(5.0, 40.0))
    rate = int(rate_hz) if rate_hz is not None else rate
    prof = profile or prof
    dur = float(duration_s) if duration_s is not None else 3.0
    cur_on = cur_on if has_current is None else bool(has_current)
    cur_on = cur_on or family in rig.CURRENT_ALWAYS
    n_cyc = 2 if prof == "staircase" else int(r_plan.integers(2, 4))
    if dur > 4.5:
        n_cyc = max(2, round(dur / (1.6 if prof == "staircase" else 1.2)))
    dt = 1.0 / rate
    n = round(dur * rate)
    plan = plan_profile(prof, p, r_plan, dt, n, n_cyc, theta0)
    e = r_noise.standard_normal((6, n))
    sig = {c: v * factor for c, v in ur.NOISE_BASE.items()}
    sig["torque_Nm"] *= p["r_eff"] / 0.15
    ctrl = plan.get("ctrl")
    if ctrl is not None:
        ctrl["noise"] = sig["theta_deg"] * e[0]
    kw = {"volts": plan.get("volts"), "ctrl": ctrl}
    mot0 = run_motor(p, dt, n, theta0, **kw)
    rec0, _, _, _ = chain(p, mot0, dt, w_disc)
    t = np.arange(n) * dt
    info = FAMILIES[family]
    ex = rig.draw_extras(family, form, r_eff, mot0)
    size = _SIZE[(family, form)]
    lo, hi = size["open" if prof == "steps" else "closed"]
    s0 = float(np.exp(r_eff.uniform(np.log(lo), np.log(hi))))

    def attempt(s):
        prm = rig.effect_params(family, form, s, ex, p)
        mot = mot0
        if family in rig._MOTOR:
            mot = run_motor(p, dt, n, theta0, fx=rig.MotorEffect(family, form, prm, p), **kw)
        rec = rig.probe_chain(p, mot, dt, w_disc, family, form, prm)
        return (prm, mot, *rec), visibility(rec[0], rec0, sig, cur_on)

    (prm, mot, rec, term, tin, tname), hist = rescale(attempt, s0, 16)
    vis, pf, pt = hist[-1][1:]
    place = info["place"][form] if isinstance(info["place"], dict) else info["place"]
    truth: dict = {
        "family": family,
        "form": form,
        "nuisance": None,
        "nuisance_params": {},
        "stage": info["stage"],
        "place": place,
        "depends_on": list(info["depends_on"][form]),
        "words": info["words"],
        "strength_unit": size["unit"],
    }
    n_app, rel_ok, pk = _released(rec0["force_N"], p["F_rt"])
    table = _table(rec, mot["V"], t, e, sig, cur_on, w_disc, None, {}, p)
    truth.update(
        params={"effect": prm, "rig": p},
        profile=prof,
        rate=rate,
        duration_s=dur,
        n_samples=n,
        n_cycles=n_cyc,
        theta0_deg=theta0,
        disc_speed_rad_s=w_disc,
        noise_factor=factor,
        noise_sigma=sig,
        has_current=cur_on,
        visibility=vis,
        concealed_force_pct=pf,
        concealed_torque_pct=pt,
        strength_drawn=s0,
        strength=hist[-1][0],
        rescales=[
            dict(zip(("strength", "vis", "force_pct", "torque_pct"), h, strict=True)) for h in hist
        ],
        term_input_name=tname,
        profile_info=plan["info"],
        applies_seen=n_app,
        released_between=rel_ok,
        peak_force_frac=pk,
    )
    desc = f"{rig.NAME} rig: {family}/{form}, profile {prof}, {rate} Hz; synthetic, see truth file"
    sidecar = {
        "r_eff_m": p["r_eff"],
        "sample_rate_hz": rate,
        "disc_mode": "drag",
        "hardware": f"{rig.NAME} rig (independent simulator)",
        "description": desc,
    }
    return Case(table, sidecar, truth, np.asarray(term, float), np.asarray(tin, float), tname)


def make_case(family: str, form: str, seed: int, index: int, **kw: Any) -> Case:
    """One probe case (:func:`make_probe_case` of this rig; keywords ``rate_hz``,
    ``profile``, ``has_current``, ``duration_s``)."""
    return make_probe_case(sys.modules[__name__], family, form, seed, index, **kw)


def run_cli(rig: Any, argv: list[str] | None = None) -> int:
    """The command line of a probe rig module: write its cases, one line each."""
    ap = argparse.ArgumentParser(description=rig.__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--per-form", type=int, default=2)
    ap.add_argument("--first-index", type=int, default=0)
    ap.add_argument("--families", default=",".join(rig.FAMILIES))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    for fam in args.families.split(","):
        for form in ("a", "b"):
            for i in range(args.first_index, args.first_index + args.per_form):
                c = rig.make_case(fam, form, args.seed, i)
                name = f"{fam}_{form}_{i:03d}"
                write_case(c, args.out, name)
                tr = c.truth
                ok = (
                    tr["visibility"] >= 3.0
                    and max(tr["concealed_force_pct"], tr["concealed_torque_pct"]) < 10.0
                )
                print(
                    f"{name:34s} {tr['profile']:9s} {tr['rate']:5d} Hz cur={tr['has_current']!s:5s}"
                    f" vis={tr['visibility']:6.2f} F%={tr['concealed_force_pct']:5.2f}"
                    f" T%={tr['concealed_torque_pct']:5.2f} s={tr['strength']:.3g}"
                    f" resc={len(tr['rescales'])} pk={tr['peak_force_frac']:.2f}"
                    f" {'ok' if ok else 'FAIL'}",
                    flush=True,
                )
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(sys.modules[__name__], argv)


if __name__ == "__main__":
    sys.exit(main())
