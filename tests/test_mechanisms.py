"""Catalog mechanisms: each hook against the synthetic rig's independent physics.

The rig (:mod:`ewb_ident.rig`) writes every effect on its own (fine-step RK4, its own
play operator and Dahl state); here each mechanism, given the rig's noise-free inputs,
must reproduce the rig's noise-free outputs.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ewb_ident import rig
from ewb_ident.inference.augmented import fit_mechanisms, make_data
from ewb_ident.mechanisms import (
    CATALOG,
    Backlash,
    CurrentLimit,
    ForceHysteresis,
    FrictionFade,
    FrictionSpeed,
    SensorDelay,
    SensorOffset,
    Stiction,
    WedgeLoadTorque,
    variants,
)
from ewb_ident.mechanisms.base import fmt_pm
from ewb_ident.mechanisms.stiction import STICK_SPEED_RAD_S
from ewb_ident.model.params import EWBParams
from ewb_ident.model.physics import clamp_force
from ewb_ident.model.predict import motor_states, predict

P = rig.RigParams()
QUIET = rig.SensorNoise.none()
BASE = EWBParams(**{k: getattr(P, k) for k in EWBParams().as_dict()})
CONTRACT_IDS = {
    "backlash",
    "wedge_load_torque",
    "force_hysteresis",
    "sensor_delay",
    "friction_speed",
    "friction_fade",
    "sensor_offset",
    "current_limit",
    "stiction",
}


def clean(**kwargs):
    kwargs.setdefault("noise", QUIET)
    _, truth, run = rig.simulate_rig(return_clean=True, **kwargs)
    return truth, run


def data_for(trace, **kw):
    sigma = {c: 1.0 for c in ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A")}
    sigma = {c: s for c, s in sigma.items() if trace.has(c)}
    fixed = BASE.as_dict() | {"theta0_deg": 0.0}
    return make_data(trace, sigma, fixed, **kw)


# ------------------------------------------------------------------------- registry


def test_registry_holds_every_contract_id_with_declared_parameters():
    assert set(CATALOG) == CONTRACT_IDS
    for mid, cls in CATALOG.items():
        assert cls.id == mid
    for m in variants():
        infos = m.param_info()
        assert infos, m.variant
        for info in infos:
            assert info.unit and info.doc
            assert info.lower < info.upper
        assert m.stage in ("motor", "gap", "force", "torque")
        assert m.stage in m.stages
        assert m.hook in (
            "voltage",
            "motor_friction",
            "wedge_angle",
            "clamp_force",
            "friction_coefficient",
            "sensor",
        )
    # sensor mechanisms come once per channel they can act on
    names = [m.variant for m in variants()]
    assert "sensor_delay[force_N]" in names and "sensor_offset[torque_Nm]" in names
    assert len(names) == len(set(names))


def test_bad_mechanism_settings_are_refused():
    with pytest.raises(ValueError, match="channel must be one of"):
        SensorDelay(channel="voltage_V")
    with pytest.raises(ValueError, match="channel must be one of"):
        SensorOffset(channel="x_m")
    with pytest.raises(ValueError, match="unknown parameter"):
        Backlash().with_values({"gamma": 1.0})


def test_plausibility_needs_resolved_parameters_inside_bounds():
    why = Backlash().implausible_reason
    assert why({"beta_deg": 2.0, "side": 1.0}, {"beta_deg": 0.1, "side": None}) == ""
    assert "outside the plausible range" in why({"beta_deg": 90.0, "side": 1.0}, {"beta_deg": 0.1})
    assert "includes no effect" in why({"beta_deg": 0.15, "side": 1.0}, {"beta_deg": 0.1})
    assert "not resolved" in why({"beta_deg": 2.0, "side": 1.0}, {"beta_deg": None})


def test_value_with_uncertainty_is_rounded_to_the_error():
    assert fmt_pm(230.4, 15.2) == "230 ± 15"
    assert fmt_pm(0.03172, 0.00085) == "0.03172 ± 0.00085"
    assert fmt_pm(1.5, None) == "1.5"


# ---------------------------------------------------------------------- seed model


def test_without_mechanisms_the_model_is_the_seed_chain():
    _, run = clean(sample_rate_hz=200.0)
    tr = run.trace
    d = data_for(tr)
    pred = predict("chain", BASE, jnp.asarray(0.0), (), d, 1)
    for ch in ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A"):
        ref = run.states[ch]
        err = np.max(np.abs(np.asarray(pred[ch])[: tr.n] - ref))
        assert err <= 1e-6 * (np.max(np.abs(ref)) + 1e-12), ch


# ------------------------------------------------------------------ stage mechanisms


def test_backlash_play_reproduces_the_rig_wedge_angle():
    _, run = clean(sample_rate_hz=1000.0, effects=[rig.Backlash(beta_deg=3.0)])
    theta = jnp.asarray(run.states["theta_deg"])
    w = Backlash(beta_deg=3.0, side=1.0).wedge_angle(theta, {})
    np.testing.assert_allclose(np.asarray(w), run.states["theta_w_deg"], atol=1e-9)


def test_force_hysteresis_reproduces_the_rig_dahl_state():
    eff = rig.ForceHysteresis(h=0.03, delta_m=2e-5)
    _, run = clean(sample_rate_hz=1000.0, effects=[eff])
    x = jnp.asarray(run.states["x_m"])
    fb = clamp_force(x, P.F_rt, P.a, P.b, P.c)
    F = ForceHysteresis(h=0.03, delta_m=2e-5).clamp_force(x, fb, {})
    # The rig integrates dz/dt with RK4 between samples; the model is exact per sample
    # increment: they agree to a small fraction of the excess h F.
    err = np.max(np.abs(np.asarray(F) - run.states["force_N"]))
    assert err < 0.02 * 0.03 * P.F_rt


def test_sensor_delay_shifts_by_a_fractional_number_of_samples():
    y = jnp.asarray(np.sin(np.linspace(0, 3, 300)))
    m = SensorDelay(channel="force_N", delay_s=0.0125)
    ctx = {"dt": 0.005}
    out = np.asarray(m.read("force_N", y, ctx))
    k = np.arange(300) - 2.5
    np.testing.assert_allclose(out[5:], np.interp(k, np.arange(300), np.asarray(y))[5:])
    back = np.asarray(m.unread("force_N", m.read("force_N", y, ctx), ctx))
    np.testing.assert_allclose(back[10:-10], np.asarray(y)[10:-10], atol=2e-4)
    np.testing.assert_array_equal(np.asarray(m.read("x_m", y, ctx)), np.asarray(y))


def test_sensor_offset_adds_and_removes_a_constant():
    m = SensorOffset(channel="torque_Nm", offset=-2.0)
    y = jnp.linspace(0.0, 5.0, 11)
    np.testing.assert_allclose(np.asarray(m.read("torque_Nm", y, {})), np.asarray(y) - 2.0)
    np.testing.assert_allclose(np.asarray(m.unread("torque_Nm", y, {})), np.asarray(y) + 2.0)


def test_friction_speed_matches_the_rig_mu():
    params = dataclasses.replace(P, disc_speed_end_rad_s=30.0)
    _, run = clean(params=params, effects=[rig.FrictionSpeed(kappa=-0.15, omega_ref_rad_s=50.0)])
    w = run.states["disc_speed_rad_s"]
    f = FrictionSpeed(kappa=-0.15).mu_factor({"disc_speed": jnp.asarray(w), "omega_ref": 50.0})
    np.testing.assert_allclose(P.mu * np.asarray(f), run.states["mu"], rtol=1e-12)


def test_friction_fade_follows_the_dissipated_energy():
    eff = rig.FrictionFade(phi_per_K=4e-3, heat_capacity_J_per_K=1500.0, tau_thermal_s=1e9)
    _, run = clean(effects=[eff], sample_rate_hz=1000.0)
    tr = run.trace
    d = data_for(tr)
    m = FrictionFade(phi_per_J=4e-3 / 1500.0)
    pred = predict("torque", BASE, jnp.asarray(0.0), (m,), d, 1)
    ref = run.states["torque_Nm"]
    err = np.max(np.abs(np.asarray(pred["torque_Nm"])[: tr.n] - ref))
    assert err < 2e-3 * np.max(ref)  # rectangle rule for the energy against RK4


# ------------------------------------------------------------------ flexible forms


def test_each_flexible_form_gives_back_its_catalog_form_at_no_effect():
    """A refinement carries the fitted values and adds parameters that, at no effect,
    give back the catalog form: so the diagnosis's comparison of the two is nested."""
    y = jnp.asarray(np.sin(np.linspace(0, 6, 400)) * 5.0)
    ctx = {"dt": 0.005, "t": jnp.arange(400) * 0.005}
    off = SensorOffset(channel="force_N", offset=7.0)
    (drifting,) = off.refinements()
    assert drifting.values() == {"offset": 7.0, "drift_per_s": 0.0}
    np.testing.assert_array_equal(drifting.read("force_N", y, ctx), off.read("force_N", y, ctx))
    bl = Backlash(beta_deg=2.0, side=0.5)
    (sprung,) = bl.refinements()
    np.testing.assert_allclose(
        dataclasses.replace(sprung, relax_per_s=0.0).wedge_angle(y, ctx),
        bl.wedge_angle(y, ctx),
        atol=1e-12,
    )
    s = jnp.asarray([0.0, 40.0, 0.0])
    lim = CurrentLimit(i_max_A=1.0)
    (soft,) = lim.refinements()
    sharp = dataclasses.replace(soft, softness=1e-3)
    for V in (-12.0, -1.0, 0.3, 2.0, 12.0):
        assert abs(float(sharp.voltage(V, s, BASE)) - float(lim.voltage(V, s, BASE))) < 1e-3
    st = Stiction(tau_c_Nm=0.02)
    (stribeck,) = st.refinements()
    none = dataclasses.replace(stribeck, excess_Nm=0.0)
    for w in (0.0, 0.5, 50.0):
        sw = jnp.asarray([0.0, w, 0.0])
        level = float(st.motor_friction(sw, BASE, 0.0)[0])
        assert float(none.motor_friction(sw, BASE, 0.0, start=sw)[0]) == level
    pairs = ((off, drifting), (bl, sprung), (lim, soft), (st, stribeck))
    for catalog, flexible in pairs:
        added = {i.name for i in flexible.param_info()} - {i.name for i in catalog.param_info()}
        assert added and not flexible.refinements()  # one step wider, not a ladder


def test_a_drifting_sensor_zero_is_read_and_removed():
    m = SensorOffset(channel="torque_Nm", drift=True, offset=-2.0, drift_per_s=0.5)
    t = jnp.arange(11) * 0.1
    y = jnp.linspace(0.0, 5.0, 11)
    ctx = {"t": t}
    np.testing.assert_allclose(m.read("torque_Nm", y, ctx), np.asarray(y) - 2.0 + 0.5 * t)
    np.testing.assert_allclose(m.unread("torque_Nm", m.read("torque_Nm", y, ctx), ctx), y)


def test_sprung_play_reproduces_the_rig_wedge_angle():
    eff = rig.Backlash(beta_deg=3.0, spring_tau_s=0.05)
    _, run = clean(sample_rate_hz=1000.0, effects=[eff])
    theta = jnp.asarray(run.states["theta_deg"])
    m = Backlash(spring=True, beta_deg=3.0, side=1.0, relax_per_s=1.0 / 0.05)
    w = np.asarray(m.wedge_angle(theta, {"dt": 0.001}))
    rigid = np.asarray(Backlash(beta_deg=3.0, side=1.0).wedge_angle(theta, {"dt": 0.001}))
    ref = run.states["theta_w_deg"]
    assert np.max(np.abs(rigid - ref)) > 1.0  # the spring matters ...
    assert np.max(np.abs(w - ref)) < 0.005  # ... and the flexible form follows it


def test_cooling_fade_reproduces_the_rig_surface_temperature():
    eff = rig.FrictionFade(phi_per_K=4e-3, heat_capacity_J_per_K=400.0, tau_thermal_s=0.5)
    _, run = clean(effects=[eff], sample_rate_hz=1000.0)
    tr = run.trace
    d = data_for(tr)
    m = FrictionFade(cooling=True, phi_per_J=4e-3 / 400.0, cool_per_s=2.0)
    energy_form = FrictionFade(phi_per_J=4e-3 / 400.0)
    pred, pred_e = (
        np.asarray(predict("torque", BASE, jnp.asarray(0.0), (x,), d, 1)["torque_Nm"])[: tr.n]
        for x in (m, energy_form)
    )
    ref = run.states["torque_Nm"]
    assert np.max(np.abs(pred_e - ref)) > 0.02 * np.max(ref)  # cooling matters ...
    assert np.max(np.abs(pred - ref)) < 2e-3 * np.max(ref)  # ... and is reproduced


def test_soft_saturation_spans_a_clip_and_a_tanh_limiter():
    from ewb_ident.mechanisms.current_limit import soft_saturation

    u = jnp.linspace(-6.0, 6.0, 1201)
    assert np.max(np.abs(soft_saturation(u, 0.02) - np.clip(u, -1, 1))) < 0.015
    assert np.max(np.abs(soft_saturation(u, 0.36) - np.tanh(u))) < 0.025
    grad = jax.grad(lambda k: jnp.sum(soft_saturation(u, k)))(0.05)
    assert np.isfinite(grad)


@pytest.mark.parametrize(
    ("rig_effect", "mechanism", "catalog"),
    [
        (
            rig.Stiction(tau_c_Nm=0.02, tau_s_Nm=0.04, stribeck_rad_s=2.0),
            Stiction(stribeck=True, tau_c_Nm=0.02, excess_Nm=0.02, stribeck_rad_s=2.0),
            Stiction(tau_c_Nm=0.02),
        ),
        (
            rig.CurrentLimit(i_max_A=2.0, kind="soft"),
            CurrentLimit(soft=True, i_max_A=2.0, softness=0.36),
            CurrentLimit(i_max_A=2.0),
        ),
    ],
    ids=["stribeck", "soft_current_limit"],
)
def test_flexible_motor_forms_follow_the_rig_motor_closer_than_the_catalog_form(
    rig_effect, mechanism, catalog
):
    _, run = clean(sample_rate_hz=500.0, effects=[rig_effect], fine_step_s=2e-5)
    tr = run.trace
    V = jnp.asarray(tr["voltage_V"])

    def err(m):
        s = motor_states(BASE, V, tr.dt, 0.0, (m,), 4)
        i = np.asarray(s[:, 0])
        return np.sqrt(np.mean((i - run.states["current_A"]) ** 2))

    assert err(mechanism) < 0.5 * err(catalog)


# ------------------------------------------------------------------ motor mechanisms


@pytest.mark.parametrize(
    ("rig_effect", "mechanism", "tol_deg"),
    [
        (rig.WedgeLoadTorque(k_w=3e-5, omega0_rad_s=0.05), WedgeLoadTorque(k_w=3e-5), 1.0),
        (
            rig.WedgeLoadTorque(k_w=0.0, k_r=1e-5),
            WedgeLoadTorque(k_w=1e-8, k_r=1e-5),
            0.2,
        ),
        (rig.CurrentLimit(i_max_A=2.0), CurrentLimit(i_max_A=2.0), 1.0),
        (rig.Stiction(tau_c_Nm=0.02, tau_s_Nm=0.02), Stiction(tau_c_Nm=0.02), 1.0),
    ],
    ids=["wedge_load_torque", "wedge_reaction", "current_limit", "stiction"],
)
def test_motor_mechanisms_reproduce_the_rig_motor(rig_effect, mechanism, tol_deg):
    _, run = clean(sample_rate_hz=500.0, effects=[rig_effect], fine_step_s=2e-5)
    _, plain = clean(sample_rate_hz=500.0)
    tr = run.trace
    V = jnp.asarray(tr["voltage_V"])
    s = motor_states(BASE, V, tr.dt, 0.0, (mechanism,), 4)
    theta = np.asarray(s[:, 2]) * 180 / math.pi
    effect = np.max(np.abs(run.states["theta_deg"] - plain.states["theta_deg"]))
    err = np.max(np.abs(theta - run.states["theta_deg"]))
    assert effect > 10 * tol_deg  # the effect is large ...
    assert err < tol_deg  # ... and the mechanism reproduces it


def test_a_learned_motor_term_enters_the_integration_exactly():
    """A learned voltage or load torque per sample (zero-order hold) enters the motor's
    linear flow exactly: the change it makes is the discovery's linear response (the
    motor's impulse response convolved with the series), to round-off."""
    from ewb_ident.diagnosis.places import motor_response
    from ewb_ident.mechanisms.learned import LearnedTerm

    n, dt = 400, 0.005
    volts = jnp.asarray(np.where(np.arange(n) < 100, 4.0, 0.0))
    rng = np.random.default_rng(3)
    basis = np.stack([np.ones(n), np.sin(np.arange(n) / 17.0), rng.standard_normal(n)], 1)
    plain = np.asarray(motor_states(BASE, volts, dt, 0.0, (), 1))
    h = motor_response(BASE.as_dict(), dt, n)
    for j, (place, coef) in enumerate(
        (("motor.electrical", (0.3, -0.2, 0.05)), ("motor.mechanical", (2e-3, 1e-3, 5e-4)))
    ):
        term = LearnedTerm(place=place, names=("1", "s", "r"), scales=(1.0,) * 3, coef=coef)
        ctx = {"learned": {place: jnp.asarray(basis)}}
        series = basis @ np.asarray(coef)
        from ewb_ident.model.predict import _motor_series

        got = np.asarray(motor_states(BASE, volts, dt, 0.0, (term,), 1, series=_motor_series(
            (term,), ctx)))  # fmt: skip
        change = got - plain
        expect_theta = np.convolve(h[:, 1, j], series)[:n]
        expect_i = np.convolve(h[:, 0, j], series)[:n]
        scale = np.max(np.abs(expect_theta))
        assert scale > 1.0  # the term matters (degrees) ...
        assert np.max(np.abs(change[:, 2] * 180 / math.pi - expect_theta)) < 1e-8 * scale
        assert np.max(np.abs(change[:, 0] - expect_i)) < 1e-8 * max(np.max(np.abs(expect_i)), 1)


def test_wedge_load_torque_of_one_form_leaves_the_other_absent_not_implausible():
    m = WedgeLoadTorque()
    # A reaction-only trace (fresh widened case 23) drove k_w's log coordinate far below
    # its bound; that is "no friction form", and the reaction form stands on its own.
    reaction = {"k_w": 1e-63, "omega0_rad_s": 5.8e-29, "k_r": 1.9e-5}
    assert m.implausible_reason(reaction, {"k_w": None, "omega0_rad_s": None, "k_r": 1e-7}) == ""
    friction = {"k_w": 3e-5, "omega0_rad_s": 0.5, "k_r": -5e-8}
    assert m.implausible_reason(friction, {"k_w": 1e-7, "omega0_rad_s": 0.1, "k_r": 2e-8}) == ""
    neither = m.implausible_reason(reaction | {"k_r": 1e-8}, {"k_w": None, "k_r": 1e-7})
    assert neither.startswith("neither part is resolved")
    too_big = m.implausible_reason(friction | {"k_r": 2e-3}, {"k_w": 1e-7, "k_r": 1e-5})
    assert "outside the plausible range" in too_big


def test_stiction_holds_the_actuator_still():
    # 0.1 V gives a 0.1 A stall current: 0.01 N m of motor torque, under tau_c = 0.02 N m.
    # The friction switches smoothly over STICK_SPEED_RAD_S (so the fit has gradients):
    # a held actuator creeps at most at that speed, a free one turns many degrees.
    volts = jnp.full(200, 0.1)
    held = motor_states(BASE, volts, 0.005, 0.0, (Stiction(tau_c_Nm=0.02),), 10)
    free = motor_states(BASE, volts, 0.005, 0.0, (), 10)
    creep_deg = math.degrees(STICK_SPEED_RAD_S * 1.0)
    assert np.max(np.abs(np.asarray(held[:, 2]))) < creep_deg
    assert np.max(np.abs(np.asarray(free[:, 2]))) > 1000 * np.max(np.abs(np.asarray(held[:, 2])))


# ------------------------------------------------------------------------- fitting


def test_fit_recovers_a_mechanism_parameter_from_a_noise_free_stage():
    _, run = clean(sample_rate_hz=200.0, effects=[rig.Backlash(beta_deg=3.3)])
    tr = run.trace
    d = data_for(tr)
    start = Backlash()
    assert abs(start.values()["beta_deg"] - 3.3) > 0.5  # the fit must move to the truth
    f = fit_mechanisms(d, ("gap",), ("p2", "p1", "p0"), (start,), ("x_m",))
    assert f.mechanisms[0].values()["beta_deg"] == pytest.approx(3.3, rel=1e-4)
    assert f.rss < 1e-8 * f.n


def test_alternative_starts_run_only_while_no_fit_is_at_the_noise(monkeypatch):
    """The solver runs from an alternative's best start unless a fit from the best starts
    overall converged with a weighted cost at most the number of residuals; a start that
    coincides with one already run is never run twice."""
    from ewb_ident.inference import augmented

    starts = []
    solve = augmented.levenberg_marquardt

    def counted(fun_and_jac, u0, **kw):
        starts.append(np.array(u0))
        return solve(fun_and_jac, u0, **kw)

    monkeypatch.setattr(augmented, "levenberg_marquardt", counted)
    trace, _ = rig.simulate_rig(sample_rate_hz=200.0, effects=[rig.Backlash(beta_deg=3.3)])
    fixed = BASE.as_dict() | {"theta0_deg": 0.0}
    other = {"p1": 1.3 * fixed["p1"]}

    def fit(sigma_m, alt):
        starts.clear()
        d = make_data(trace, {"x_m": sigma_m}, fixed)
        free = ("p2", "p1", "p0")
        return fit_mechanisms(d, ("gap",), free, (Backlash(),), ("x_m",), alt_starts=alt)

    noise = float(np.std(np.diff(trace["x_m"]))) / math.sqrt(2.0)
    f = fit(2.0 * noise, [other])  # at the noise: the alternative is not needed
    assert f.converged and f.rss <= f.n and len(starts) == 2
    f = fit(0.1 * noise, [other])  # ten times the noise: it is run too
    assert f.rss > f.n and len(starts) == 4  # the alternative's two best starts
    assert all(s[1] != 0.0 for s in starts[2:]) and all(s[1] == 0.0 for s in starts[:2])
    fit(0.1 * noise, [{"p1": fixed["p1"]}])  # the base's own starts again
    assert len(starts) == len({s.tobytes() for s in starts}) < 4


def test_levenberg_marquardt_solves_a_linear_problem_in_one_step():
    _, run = clean(sample_rate_hz=200.0)
    d = data_for(run.trace)
    f0 = fit_mechanisms(d, ("gap",), ("p2", "p1", "p0"), (), ("x_m",))
    assert f0.converged and f0.rss < 1e-12


def test_a_dead_band_within_the_logged_voltages_noise_is_named_as_possibly_that_noise():
    """On a clean third-rig trace whose logged voltage carries noise the motor never saw,
    the diagnosis found stiction of 0.06 V at standstill beside 0.034 V of voltage noise:
    a dead band absorbs the drift of a motor driven by that noise. The words say so."""
    mech = Stiction(tau_c_Nm=0.00586)
    ctx = {"kT": 0.1, "R": 1.0}
    plain = mech.describe(mech.values(), {"tau_c_Nm": 2.6e-4}, ctx)
    assert "Caution" not in plain
    noisy = mech.describe(mech.values(), {"tau_c_Nm": 2.6e-4}, ctx | {"voltage_noise_V": 0.034})
    assert "within 3x the logged voltage's own noise (0.034 V)" in noisy
    wide = Stiction(tau_c_Nm=0.05).describe(
        {"tau_c_Nm": 0.05}, {}, ctx | {"voltage_noise_V": 0.034}
    )
    assert "Caution" not in wide


def test_levenberg_marquardt_is_not_stalled_by_heavy_weights():
    # Residuals weighted by a small noise level make J^T J large; a damping scaled by its
    # largest diagonal damped the first step to nothing and ended the solve, "converged",
    # at its start (a chain fit adding hysteresis to stiction stopped at 257k, 38 % above
    # the fit without hysteresis, where it reaches 31k).
    rng = np.random.default_rng(3)
    X = rng.standard_normal((300, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + 0.01 * rng.standard_normal(300)
    w = 1e7

    def fun(u):
        return w * (X @ np.asarray(u) - y)

    sol = _normal_lm(lambda u: (fun(u), w * X, None), np.zeros(3))
    assert sol.converged
    np.testing.assert_allclose(sol.u, np.linalg.lstsq(X, y, rcond=None)[0], rtol=1e-6)


def _normal_lm(fun_and_jac, u0, stall=None, max_steps=200):
    """The mechanism fits' Levenberg-Marquardt: normal equations, relative decrease."""
    from ewb_ident.inference.solvers import (
        NormalEquationsDescent,
        RelativeDecrease,
        levenberg_marquardt,
    )

    return levenberg_marquardt(
        fun_and_jac,
        u0,
        descent=NormalEquationsDescent(),
        stop=RelativeDecrease(stall=stall),
        max_steps=max_steps,
    )


def _valley(e: float):
    """Rosenbrock's valley in noise units: ``100 (u1 - u0^2)`` fixes a combination, and
    ``e (1 - u0)`` tells where along the valley the optimum (1, 1) is, to ``1/e``."""

    def fun_and_jac(u):
        r = np.array([100.0 * (u[1] - u[0] ** 2), e * (1.0 - u[0])])
        return r, np.array([[-200.0 * u[0], 100.0], [-e, 0.0]]), None

    return fun_and_jac


@pytest.mark.parametrize("e", [0.1, 0.3])
def test_levenberg_marquardt_ends_a_slide_worth_under_one_noise_unit(e):
    """Along a weakly determined valley each step gains little; with ``stall`` the solver
    stops once ten steps gained under ``stall`` and the optimum is within one standard
    error (cost within 1 of the optimum's 0), instead of sliding for hundreds of steps."""
    u0 = np.array([-1.2, 1.0])
    slide = _normal_lm(_valley(e), u0, max_steps=500)
    assert slide.converged and slide.steps > 100 and slide.cost < 1e-20
    stop = _normal_lm(_valley(e), u0, max_steps=500, stall=0.1)
    assert stop.converged and stop.steps < 20 and 0.0 < stop.cost < 1.0
    assert abs(stop.u[0] - 1.0) < 2.0 / e  # where along the valley: within its error


@pytest.mark.parametrize("e", [10.0, 30.0])
def test_levenberg_marquardt_with_stall_still_reaches_a_determined_optimum(e):
    sol = _normal_lm(_valley(e), np.array([-1.2, 1.0]), stall=0.1)
    assert sol.converged
    np.testing.assert_allclose(sol.u, [1.0, 1.0], atol=1e-9)


def test_levenberg_marquardt_refuses_a_step_where_jtj_overflows():
    # Was: "RuntimeWarning: overflow encountered in matmul" (J^T J of a Jacobian of 1e200
    # after a step that lowered the cost; a diagnosis of a 2 s closed-loop trace with a
    # wedge reaction took such a step), then a damped system of infinities. The step is
    # refused like one to where the model has no slope.
    def fun(u):
        return np.asarray(u) - 3.0

    def fun_and_jac(u):
        steep = 1e200 if float(u[0]) >= 2.5 else 1.0
        return fun(u), np.array([[steep]]), None

    sol = _normal_lm(fun_and_jac, np.zeros(1))
    assert np.all(np.isfinite(sol.u)) and float(sol.u[0]) < 2.5
    assert np.isfinite(sol.cost) and sol.cost < 9.0  # moved toward 3 without crossing


def _no_current_session(effect, seed: int, profile: str = "position", rate: float = 500.0):
    from ewb_ident.diagnosis.session import Session

    noise = rig.SensorNoise()
    trace, _ = rig.simulate_rig(
        profile=profile,
        sample_rate_hz=rate,
        duration_s=3.0,
        effects=[effect],
        seed=seed,
        noise=noise,
    )
    trace = dataclasses.replace(
        trace, channels={c: v for c, v in trace.channels.items() if c != "current_A"}
    )
    ses = Session(trace)
    ses.baseline()
    return ses


def test_a_current_limit_well_under_the_peak_is_fitted_without_a_current_sensor():
    # Without current_A the limit's starts came from a default 4 A peak, all above a
    # limit of ~0.5 A, where the limit does not act and its slope is zero.
    _, _, free = rig.simulate_rig(
        profile="position", sample_rate_hz=500.0, duration_s=3.0, seed=11, return_clean=True
    )
    i_max = 0.45 * float(np.max(np.abs(free.states["current_A"])))
    ses = _no_current_session(rig.CurrentLimit(i_max_A=i_max), seed=11)
    f = ses.fit(("motor",), [CurrentLimit()], explore=[True])
    assert f.mechanisms[0].values()["i_max_A"] == pytest.approx(i_max, rel=0.05)


def test_a_wedge_load_torque_of_both_forms_is_fitted_without_a_current_sensor():
    # No start held both a friction-like part and a reaction; the fit stopped worse than
    # the baseline.
    truth = rig.WedgeLoadTorque(k_w=3e-5, omega0_rad_s=0.5, k_r=2e-5)
    ses = _no_current_session(truth, seed=12, profile="steps", rate=1000.0)
    f0 = ses.fit(("motor",), [])
    f = ses.fit(("motor",), [WedgeLoadTorque()], explore=[True])
    vals = f.mechanisms[0].values()
    assert f.rss < 0.01 * f0.rss
    assert vals["k_w"] == pytest.approx(3e-5, rel=0.2)
    assert vals["k_r"] == pytest.approx(2e-5, rel=0.2)
