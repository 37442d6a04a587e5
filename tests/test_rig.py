"""Tests of the synthetic rig (the truth generator).

References are independent of the rig's code: scipy's Radau for the motor, the bell
curve and the torque law written out here in NumPy, and the signature each catalog
effect must leave in a trace.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ewb_ident import rig
from ewb_ident.rig import (
    Backlash,
    CurrentLimit,
    ForceHysteresis,
    FrictionFade,
    FrictionSpeed,
    RigError,
    RigParams,
    SensorDelay,
    SensorNoise,
    SensorOffset,
    Stiction,
    WedgeLoadTorque,
    simulate_rig,
)

P = RigParams()
QUIET = SensorNoise.none()
DEG = 180.0 / math.pi


def bell(x: np.ndarray, p: RigParams) -> np.ndarray:
    return p.F_rt / (1.0 + np.abs((x - p.c) / p.a) ** (2.0 * p.b))


def gap(theta_deg: np.ndarray, p: RigParams) -> np.ndarray:
    return p.p2 * theta_deg**2 + p.p1 * theta_deg + p.p0


def step_voltage(fs: float, duration: float, v: float = 4.0) -> np.ndarray:
    t = np.arange(int(round(duration * fs)) + 1) / fs
    volts = np.zeros_like(t)
    volts[(t >= 0.05) & (t < 0.2)] = v
    volts[(t >= 0.35) & (t < 0.45)] = -v
    return volts


def clean_run(**kwargs):
    kwargs.setdefault("noise", QUIET)
    _, truth, clean = simulate_rig(return_clean=True, **kwargs)
    return truth, clean


# --------------------------------------------------------------------------------------
# Integration accuracy
# --------------------------------------------------------------------------------------


def test_motor_matches_radau_reference():
    fs, volts = 200.0, step_voltage(200.0, 0.6)
    _, clean = clean_run(profile="voltage", voltage_V=volts, sample_rate_hz=fs)

    def motor(_t, y, v):
        i, w, _th = y
        return [(v - P.R * i - P.kb * w) / P.L, (P.kT * i - P.v * w) / P.M, w]

    y = np.zeros(3)
    theta_ref, current_ref = [0.0], [0.0]
    for k in range(volts.size - 1):  # restart at each zero-order-hold switch
        sol = solve_ivp(
            motor,
            (k / fs, (k + 1) / fs),
            y,
            method="Radau",
            rtol=1e-10,
            atol=1e-12,
            args=(volts[k],),
        )
        y = sol.y[:, -1]
        theta_ref.append(y[2] * DEG)
        current_ref.append(y[0])
    assert np.ptp(theta_ref) > 100.0  # the motor really moved
    np.testing.assert_allclose(clean.states["theta_deg"], theta_ref, rtol=0, atol=1e-4)
    np.testing.assert_allclose(clean.states["current_A"], current_ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    "effects",
    [(), ("wedge_load_torque", "force_hysteresis", "friction_fade", "current_limit")],
    ids=["plain", "smooth-effects"],
)
def test_halving_the_fine_step_changes_nothing(effects):
    volts = step_voltage(500.0, 0.6)
    runs = [
        clean_run(
            profile="voltage",
            voltage_V=volts,
            sample_rate_hz=500.0,
            effects=effects,
            fine_step_s=step,
        )[1].states
        for step in (2e-5, 1e-5)
    ]
    scale = np.max(np.abs(runs[0]["theta_deg"]))
    assert scale > 100.0
    assert np.max(np.abs(runs[0]["theta_deg"] - runs[1]["theta_deg"])) < 1e-6 * scale
    force_scale = np.max(runs[0]["force_N"])
    assert np.max(np.abs(runs[0]["force_N"] - runs[1]["force_N"])) < 1e-6 * force_scale


def test_fast_after_compilation():
    simulate_rig(sample_rate_hz=1000.0, profile="position", seed=1)
    start = time.perf_counter()
    trace, _ = simulate_rig(sample_rate_hz=1000.0, profile="position", seed=2)
    assert time.perf_counter() - start < 2.0
    assert trace.n == 3001


# --------------------------------------------------------------------------------------
# The clean chain, noise, determinism, truth
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["steps", "position", "staircase"])
def test_clean_trace_follows_the_chain(profile):
    truth, clean = clean_run(profile=profile)
    ch = clean.trace.channels
    np.testing.assert_allclose(ch["x_m"], gap(ch["theta_deg"], P), rtol=0, atol=1e-15)
    np.testing.assert_allclose(ch["force_N"], bell(ch["x_m"], P), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(
        ch["torque_Nm"], 2 * P.mu * ch["force_N"] * P.r_eff_m, rtol=1e-12, atol=1e-9
    )
    np.testing.assert_array_equal(ch["disc_speed_rad_s"], P.disc_speed_rad_s)
    # The apply reaches clamping near c without passing far beyond it.
    assert np.max(ch["force_N"]) > 0.9 * P.F_rt
    assert np.max(ch["x_m"]) < P.c
    assert truth["profile"]["kind"] == profile


def test_steps_profile_is_the_documented_schedule():
    trace, truth = simulate_rig(noise=QUIET)
    o = truth["profile"]
    v, t = trace["voltage_V"], trace.time_s
    assert set(np.unique(v)) == {-o["v_apply_V"], 0.0, o["v_apply_V"]}
    on = t[v > 0]
    assert on[0] == pytest.approx(o["t_start_s"])
    assert on[-1] + trace.dt == pytest.approx(o["t_start_s"] + o["t_apply_s"])
    assert trace["theta_deg"][-1] == pytest.approx(0.0, abs=1.0)  # back to the start


def test_same_seed_same_arrays_other_seed_other_noise():
    a, truth_a = simulate_rig(profile="position", seed=7)
    b, truth_b = simulate_rig(profile="position", seed=7)
    c, _ = simulate_rig(profile="position", seed=8)
    for col in a.channels:
        np.testing.assert_array_equal(a[col], b[col])
    assert truth_a == truth_b
    assert not np.array_equal(a["force_N"], c["force_N"])


def test_noise_has_the_requested_levels_and_quantisation():
    noise = SensorNoise(theta_deg=0.0, x_m=2e-6, force_N=10.0, torque_Nm=1.0, q_force_N=5.0)
    trace, _, clean = simulate_rig(
        profile="steps", sample_rate_hz=1000.0, noise=noise, seed=3, return_clean=True
    )
    for ch in ("x_m", "torque_Nm", "current_A"):
        resid = trace[ch] - clean.trace[ch]
        assert np.std(resid) == pytest.approx(noise.sigma(ch), rel=0.1)
    np.testing.assert_array_equal(trace["theta_deg"], clean.trace["theta_deg"])
    np.testing.assert_array_equal(trace["voltage_V"], clean.trace["voltage_V"])
    np.testing.assert_allclose(trace["force_N"] / 5.0, np.round(trace["force_N"] / 5.0))
    assert np.std(trace["force_N"] - clean.trace["force_N"]) == pytest.approx(
        math.hypot(10.0, 5.0 / math.sqrt(12.0)), rel=0.1
    )


def test_trace_truth_and_sidecar():
    trace, truth = simulate_rig(effects=["backlash", SensorOffset(offset=25.0)], name="t1")
    assert trace.name == "t1"
    assert set(trace.channels) == {
        "voltage_V",
        "current_A",
        "theta_deg",
        "x_m",
        "force_N",
        "torque_Nm",
        "disc_speed_rad_s",
    }
    for col in trace.channels.values():
        assert col.dtype == np.float64 and col.shape == trace.time_s.shape
    assert trace.sample_rate_hz == pytest.approx(200.0)
    assert trace.sidecar["r_eff_m"] == P.r_eff_m
    assert trace.sidecar["disc_mode"] == "drag"
    # The sidecar carries what a rig log would; the planted effects stay in the truth.
    assert "backlash" not in json.dumps(trace.sidecar)
    text = json.dumps(truth, allow_nan=False)
    back = json.loads(text)
    assert back["params"] == dataclasses.asdict(P)
    assert back["effects"] == {
        "backlash": {"beta_deg": 3.0, "initial_side": "release", "spring_tau_s": 0.0},
        "sensor_offset": {"channel": "force_N", "offset": 25.0, "drift_per_s": 0.0},
    }
    assert back["noise"]["force_N"] == 10.0
    assert back["seed"] == 0 and back["n_samples"] == trace.n


def test_vary_perturbs_like_hardware():
    a = rig.vary(P, np.random.default_rng(1), rel=0.05)
    b = rig.vary(P, np.random.default_rng(1), rel=0.05)
    assert a == b
    assert rig.vary(P, np.random.default_rng(1), rel=0.0) == P
    ratios = np.array([getattr(a, k) / getattr(P, k) for k in rig.VARIED_PARAMS])
    assert np.all(ratios > 0.75) and np.all(ratios < 1.3)
    assert np.sum(ratios != 1.0) == len(rig.VARIED_PARAMS)
    assert {"a", "b", "c"} <= set(rig.VARIED_PARAMS)
    assert a.r_eff_m == P.r_eff_m and a.disc_mode == P.disc_mode
    trace, truth = simulate_rig(a, noise=QUIET)
    assert truth["params"]["a"] == a.a


def test_theta_for_gap_inverts_the_polynomial():
    th = rig.theta_for_gap(P, P.c)
    assert gap(np.array(th), P) == pytest.approx(P.c, rel=1e-12)
    assert 510.0 < th < 525.0


# --------------------------------------------------------------------------------------
# Position control
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("fs", [100.0, 1000.0])
def test_position_profile_tracks_its_reference(fs):
    trace, truth, clean = simulate_rig(profile="position", sample_rate_hz=fs, return_clean=True)
    err = clean.states["theta_deg"] - clean.states["theta_ref_deg"]
    assert np.max(np.abs(err)) < 2.0
    target = truth["profile"]["target_deg"]
    x_target = gap(np.array(target), P)
    assert x_target == pytest.approx(P.c - 0.3 * P.a, rel=1e-9)
    assert np.max(clean.states["theta_deg"]) == pytest.approx(target, abs=2.0)
    assert np.max(np.abs(trace["voltage_V"])) <= 12.0


def test_staircase_visits_its_levels_and_saturates_the_command():
    trace, truth, clean = simulate_rig(
        profile="staircase", sample_rate_hz=500.0, return_clean=True, v_max_V=12.0
    )
    levels = truth["profile"]["levels_deg"]
    assert len(levels) == 4 and np.all(np.diff(levels) > 0)
    theta = clean.states["theta_deg"]
    for level in levels:
        assert np.any(np.abs(theta - level) < 0.5)
    err = theta - clean.states["theta_ref_deg"]
    assert np.sqrt(np.mean(err**2)) < 2.0
    small, _ = simulate_rig(profile="staircase", v_max_V=1.5, noise=QUIET)
    assert np.max(np.abs(small["voltage_V"])) == pytest.approx(1.5)


# --------------------------------------------------------------------------------------
# Signatures of the catalog effects
# --------------------------------------------------------------------------------------


def test_registry_holds_the_catalog_ids():
    assert set(rig.EFFECTS) == {
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
    for eff_id, cls in rig.EFFECTS.items():
        assert cls.id == eff_id
        cls()  # the defaults are valid


def test_backlash_holds_the_piston_after_a_reversal():
    beta = 3.0
    trace, _, clean = simulate_rig(
        sample_rate_hz=1000.0, effects=[Backlash(beta_deg=beta)], noise=QUIET, return_clean=True
    )
    theta, x = clean.states["theta_deg"], clean.trace["x_m"]
    release = int(np.argmax(trace["voltage_V"] < 0))  # the reversal starts here
    back = theta[release] - theta[release:]
    in_band = back < 2 * beta - 0.05
    assert 5 < np.sum(in_band) and np.max(back[in_band]) > beta
    np.testing.assert_array_equal(x[release:][in_band], x[release])  # the wedge stays put
    out = back > 2 * beta + 0.05
    np.testing.assert_allclose(x[release:][out], gap(theta[release:][out] + beta, P), rtol=1e-12)
    # The first apply crossed the band too; the angle sensor reads the pinion.
    assert clean.states["theta_w_deg"][0] == pytest.approx(beta)
    np.testing.assert_array_equal(clean.trace["theta_deg"], theta)
    # Without backlash the piston follows the same reversal at once.
    _, plain = clean_run(sample_rate_hz=1000.0)
    k = release + int(np.sum(in_band)) // 2
    assert plain.trace["x_m"][k] < plain.trace["x_m"][release] - 1e-6


def test_wedge_load_torque_slows_the_motor_as_force_builds():
    _, plain = clean_run(sample_rate_hz=500.0)
    _, loaded = clean_run(sample_rate_hz=500.0, effects=[WedgeLoadTorque()])
    th0, th1 = plain.states["theta_deg"], loaded.states["theta_deg"]
    apply = slice(0, int(np.argmax(th0)) + 1)
    assert np.all(th1[apply] <= th0[apply] + 1e-9)
    assert np.max(th1) < np.max(th0) - 10.0
    # The speed lost grows with the force: nothing lost while the force is small.
    low = plain.states["force_N"][apply] < 100.0
    np.testing.assert_allclose(th1[apply][low], th0[apply][low], atol=0.5)


def test_wedge_reaction_takes_holding_current_in_closed_loop_and_opens_an_idle_brake():
    # A wedge that is not self-locking (k_r) pushes the pinion back toward release: the
    # position controller holds the force with current, and at 0 V the brake opens.
    k_r = 1e-5
    _, plain = clean_run(profile="position")
    _, held = clean_run(profile="position", effects=[WedgeLoadTorque(k_w=0.0, k_r=k_r)])
    hold = plain.states["force_N"] > 0.95 * np.max(plain.states["force_N"])
    i_hold = float(np.median(held.states["current_A"][hold]))
    expected = k_r * float(np.median(held.states["force_N"][hold])) / P.kT
    assert i_hold == pytest.approx(expected, rel=0.15)
    assert abs(float(np.median(plain.states["current_A"][hold]))) < 0.1 * expected
    _, idle = clean_run(effects=[WedgeLoadTorque(k_w=0.0, k_r=k_r)])  # steps: 0 V hold
    _, locked = clean_run(effects=[WedgeLoadTorque(k_w=3e-5)])
    f_locked = locked.states["force_N"]
    holding = f_locked > 0.95 * np.max(f_locked)
    assert np.median(idle.states["force_N"][holding]) < 0.5 * np.median(f_locked[holding])


def test_force_hysteresis_higher_on_apply_than_on_release():
    h = 0.03
    _, clean = clean_run(profile="position", effects=[ForceHysteresis(h=h)])
    x, f = clean.trace["x_m"], clean.trace["force_N"]
    peak = int(np.argmax(x))
    grid = np.linspace(P.c - 1.4 * P.a, P.c - 0.5 * P.a, 20)
    rising = np.interp(grid, x[:peak], f[:peak])
    falling = np.interp(grid, x[peak:][::-1], f[peak:][::-1])
    np.testing.assert_allclose(rising / falling, (1 + h) / (1 - h), rtol=2e-3)
    assert clean.states["hysteresis_z"][0] == -1.0
    # Pointwise on a monotone open-loop apply and release: z saturates at +1 and -1.
    _, steps = clean_run(sample_rate_hz=1000.0, effects=[ForceHysteresis(h=h)])
    x, f = steps.trace["x_m"], steps.trace["force_N"]
    peak = int(np.argmax(x))
    excess = f / bell(x, P) - 1.0
    idx, dx = np.arange(x.size), np.gradient(x)
    applying = (dx > 1e-7) & (idx < peak) & (f > 300.0)
    releasing = (dx < -1e-7) & (idx > peak) & (x < x[peak] - 20 * 2e-5)
    assert np.sum(applying) > 20 and np.sum(releasing) > 20
    np.testing.assert_allclose(excess[applying], h, atol=1e-9)
    np.testing.assert_allclose(excess[releasing], -h, atol=1e-9)


def test_sensor_delay_reads_the_past_exactly():
    """A 13 ms delay at 200 Hz (2.6 samples) equals the undelayed 1 kHz run 13 samples back."""
    volts200 = step_voltage(200.0, 0.6)
    volts1k = np.repeat(volts200, 5)[: (volts200.size - 1) * 5 + 1]
    _, slow = clean_run(
        profile="voltage",
        voltage_V=volts200,
        sample_rate_hz=200.0,
        effects=[SensorDelay(channel="force_N", delay_s=0.013)],
    )
    _, fast = clean_run(profile="voltage", voltage_V=volts1k, sample_rate_hz=1000.0)
    idx = np.maximum(np.arange(volts200.size) * 5 - 13, 0)
    expected = fast.states["force_N"][idx]
    np.testing.assert_allclose(slow.trace["force_N"], expected, rtol=1e-7, atol=1e-6)
    np.testing.assert_array_equal(slow.states["force_N"][0], slow.trace["force_N"][0])


def test_sensor_delay_shows_as_a_cross_correlation_lag():
    trace, _, clean = simulate_rig(
        sample_rate_hz=1000.0, effects=[SensorDelay()], seed=4, return_clean=True
    )
    truth_force = clean.states["force_N"]
    lags = np.arange(0, 40)
    core = slice(50, trace.n - 50)
    cost = [
        np.mean((trace["force_N"][core] - np.roll(truth_force, lag)[core]) ** 2) for lag in lags
    ]
    assert lags[int(np.argmin(cost))] == 15
    # The other channels are on time.
    np.testing.assert_array_equal(clean.trace["x_m"], clean.states["x_m"])


def test_delayed_angle_is_what_the_controller_sees():
    delay = 0.01  # two samples at 200 Hz
    _, clean = clean_run(profile="position", effects=[SensorDelay("theta_deg", delay)])
    th, ref = clean.states["theta_deg"], clean.states["theta_ref_deg"]
    np.testing.assert_allclose(clean.trace["theta_deg"][2:], th[:-2], atol=1e-9)
    # The loop closes on the delayed reading, so that one tracks the reference ...
    assert np.max(np.abs(clean.trace["theta_deg"] - ref)) < 5.0
    # ... and the true angle leads it by about the delay times the reference speed.
    rate = np.gradient(ref, clean.trace.time_s)
    fast = np.abs(rate) > 500.0
    assert np.median((th - ref)[fast] / (rate[fast] * delay)) == pytest.approx(1.0, abs=0.25)


def test_sensor_offset_is_constant():
    _, clean = clean_run(effects=[SensorOffset()])
    np.testing.assert_allclose(clean.trace["force_N"] - clean.states["force_N"], 40.0)
    np.testing.assert_array_equal(clean.trace["torque_Nm"], clean.states["torque_Nm"])
    _, clean = clean_run(effects=[SensorOffset("torque_Nm", -2.0)])
    np.testing.assert_allclose(clean.trace["torque_Nm"] - clean.states["torque_Nm"], -2.0)


def test_current_limit_bounds_the_current_and_logs_the_command():
    trace, _, clean = simulate_rig(
        sample_rate_hz=1000.0, effects=[CurrentLimit(i_max_A=2.0)], return_clean=True
    )
    _, plain = clean_run(sample_rate_hz=1000.0)
    assert np.max(np.abs(plain.states["current_A"])) > 3.0
    assert np.max(np.abs(clean.states["current_A"])) <= 2.0 * (1 + 1e-9)
    assert np.max(np.abs(clean.states["current_A"])) > 1.99  # the limit is reached
    assert np.max(trace["voltage_V"]) == 4.0  # the command, not the clipped voltage


def test_stiction_dead_band_before_the_actuator_moves():
    fs = 1000.0
    volts = np.linspace(0.0, 1.0, 1001)
    tau_s = 0.03
    eff = [Stiction(tau_c_Nm=0.02, tau_s_Nm=tau_s)]
    _, clean = clean_run(profile="voltage", voltage_V=volts, sample_rate_hz=fs, effects=eff)
    theta, i = clean.states["theta_deg"], clean.states["current_A"]
    breakaway = int(np.argmax(P.kT * i >= tau_s))
    assert breakaway > 250
    np.testing.assert_array_equal(theta[:breakaway], 0.0)  # stuck while kT i < tau_s
    assert theta[breakaway + 5] > 0.0  # and free once the motor torque passes it
    assert theta[-1] > 10.0
    # Without stiction the same ramp moves the actuator at once.
    _, plain = clean_run(profile="voltage", voltage_V=volts, sample_rate_hz=fs)
    assert plain.states["theta_deg"][100] > 1.0
    # A voltage below breakaway never moves it.
    _, held = clean_run(profile="voltage", voltage_V=np.full(501, 0.25), effects=eff)
    np.testing.assert_array_equal(held.states["theta_deg"], 0.0)


def _mu_estimate(trace, min_force=3000.0):
    f, tq = trace["force_N"], trace["torque_Nm"]
    clamped = f > min_force
    return clamped, tq[clamped] / (2.0 * f[clamped] * trace.r_eff_m)


def test_friction_fade_lowers_mu_over_the_trace():
    trace, _, clean = simulate_rig(
        profile="position", effects=[FrictionFade()], seed=5, return_clean=True
    )
    clamped, mu_hat = _mu_estimate(trace)
    k = mu_hat.size // 4
    early, late = np.mean(mu_hat[:k]), np.mean(mu_hat[-k:])
    assert late < early * 0.97
    mu = clean.states["mu"]
    assert mu[-1] / mu[0] == pytest.approx(0.93, abs=0.03)  # the documented ~5-10 %
    assert np.all(np.diff(mu[clamped]) <= 0)
    heat = clean.states["pad_temperature_rise_K"]
    np.testing.assert_allclose(mu, P.mu * (1 - FrictionFade().phi_per_K * heat), rtol=1e-12)


def test_friction_speed_mu_follows_disc_speed():
    params = dataclasses.replace(P, disc_speed_rad_s=70.0, disc_speed_end_rad_s=30.0)
    kappa, w_ref = -0.15, 50.0
    trace, _, clean = simulate_rig(
        params,
        profile="position",
        effects=[FrictionSpeed(kappa, w_ref)],
        seed=6,
        return_clean=True,
    )
    clamped, mu_hat = _mu_estimate(trace)
    speed = trace["disc_speed_rad_s"][clamped]
    assert np.corrcoef(mu_hat, speed)[0, 1] < -0.9
    slope = np.polyfit(speed, mu_hat, 1)[0]
    assert slope * w_ref / P.mu == pytest.approx(kappa, rel=0.1)
    np.testing.assert_allclose(trace["disc_speed_rad_s"][[0, -1]], [70.0, 30.0], atol=1e-9)
    with pytest.raises(RigError, match="friction_speed.*disc_speed_end_rad_s"):
        simulate_rig(P, effects=["friction_speed"])


# --------------------------------------------------------------------------------------
# Second physical forms of the effects (the diagnosis forms study draws them)
# --------------------------------------------------------------------------------------


def test_play_with_a_spring_pulls_the_wedge_back_inside_the_band():
    beta, tau = 3.0, 0.05
    eff = [Backlash(beta_deg=beta, spring_tau_s=tau)]
    trace, _, clean = simulate_rig(sample_rate_hz=1000.0, effects=eff, noise=QUIET,
                                   return_clean=True)  # fmt: skip
    theta, thw = clean.states["theta_deg"], clean.states["theta_w_deg"]
    assert np.all(np.abs(thw - theta) <= beta * (1 + 1e-12))
    # Where the pinion rests, the gap to the wedge side decays as exp(-t / tau).
    still = np.flatnonzero(np.abs(np.diff(theta)) < 1e-9)
    k = still[-1] - 50
    ratio = (thw[k + 50] - theta[k + 50]) / (thw[k] - theta[k])
    assert ratio == pytest.approx(math.exp(-0.05 / tau), rel=1e-3)
    # The rigid play leaves the wedge side where the pinion left it.
    _, _, rigid = simulate_rig(sample_rate_hz=1000.0, effects=[Backlash(beta_deg=beta)],
                               noise=QUIET, return_clean=True)  # fmt: skip
    r = rigid.states["theta_w_deg"] - rigid.states["theta_deg"]
    assert abs(r[k + 50] - r[k]) < 1e-9 and abs(r[k]) > 0.5


def test_sensor_lag_is_a_first_order_filter():
    tau = 0.02
    eff = [SensorDelay("force_N", tau, kind="lag")]
    _, clean = clean_run(sample_rate_hz=1000.0, effects=eff)
    f_true, f_read = clean.states["force_N"], clean.trace["force_N"]
    # The reading obeys tau dy/dt = u - y (centred differences on the 1 kHz samples).
    dydt = np.gradient(f_read, 1e-3)
    resid = tau * dydt - (f_true - f_read)
    assert np.max(np.abs(resid[5:-5])) < 1e-3 * np.max(f_true)
    with pytest.raises(RigError, match="not simulated on theta_deg"):
        SensorDelay("theta_deg", tau, kind="lag")


def test_exponential_friction_speed_law():
    params = dataclasses.replace(P, disc_speed_rad_s=70.0, disc_speed_end_rad_s=30.0)
    eff = [FrictionSpeed(-0.2, 50.0, law="exponential")]
    _, _, clean = simulate_rig(params, profile="position", effects=eff, noise=QUIET,
                               return_clean=True)  # fmt: skip
    s = (clean.states["disc_speed_rad_s"] - 50.0) / 50.0
    np.testing.assert_allclose(clean.states["mu"], P.mu * (1 - 0.2 * (1 - np.exp(-s))), rtol=1e-12)


def test_drifting_sensor_zero():
    trace, clean = clean_run(effects=[SensorOffset("torque_Nm", 1.0, drift_per_s=2.0)])
    t = clean.trace.time_s
    np.testing.assert_allclose(clean.trace["torque_Nm"] - clean.states["torque_Nm"], 1.0 + 2.0 * t)


def test_soft_current_limit_stays_below_its_limit_and_acts_early():
    _, soft = clean_run(sample_rate_hz=1000.0, effects=[CurrentLimit(2.0, kind="soft")])
    _, hard = clean_run(sample_rate_hz=1000.0, effects=[CurrentLimit(2.0)])
    i_soft, i_hard = np.abs(soft.states["current_A"]), np.abs(hard.states["current_A"])
    assert 1.5 < np.max(i_soft) < 2.0 and np.max(i_hard) > 1.99
    # Below the limit the clip does nothing; the soft limit already holds the current back.
    _, plain = clean_run(sample_rate_hz=1000.0)
    below = np.abs(plain.states["current_A"]) < 1.0
    np.testing.assert_allclose(i_hard[below][:20], np.abs(plain.states["current_A"])[below][:20])
    assert np.max(np.abs(i_soft[below] - np.abs(plain.states["current_A"])[below])) > 1e-3


def test_stribeck_friction_slows_the_start_of_a_move():
    volts = np.linspace(0.0, 1.5, 1001)
    common = dict(profile="voltage", voltage_V=volts, sample_rate_hz=1000.0)
    _, coulomb = clean_run(effects=[Stiction(0.02, 0.04)], **common)
    _, stribeck = clean_run(effects=[Stiction(0.02, 0.04, stribeck_rad_s=2.0)], **common)
    th_c, th_s = coulomb.states["theta_deg"], stribeck.states["theta_deg"]
    start = int(np.argmax(th_c > 0))
    np.testing.assert_array_equal(th_s[:start], 0.0)  # the same breakaway
    assert 0 < th_s[-1] < th_c[-1]  # more friction while slow


def test_coasting_disc_decelerates_by_torque_over_inertia():
    params = dataclasses.replace(P, disc_mode="coast", disc_inertia_kg_m2=20.0)
    trace, _, clean = simulate_rig(params, profile="position", noise=QUIET, return_clean=True)
    w, torque = clean.states["disc_speed_rad_s"], clean.states["torque_Nm"]
    dt = trace.dt
    decel = -np.diff(w) / dt
    mid_torque = 0.5 * (torque[1:] + torque[:-1])
    np.testing.assert_allclose(decel, mid_torque / 20.0, atol=0.02 * np.max(decel))
    assert w[-1] < 0.6 * w[0]
    assert trace.sidecar["disc_mode"] == "coast" and trace.sidecar["disc_inertia_kg_m2"] == 20.0


def test_all_effects_together():
    params = dataclasses.replace(P, disc_speed_end_rad_s=40.0)
    trace, truth = simulate_rig(
        params, profile="position", effects=list(rig.EFFECTS), sample_rate_hz=500.0
    )
    assert set(truth["effects"]) == set(rig.EFFECTS)
    for col in trace.channels.values():
        assert np.all(np.isfinite(col))
    assert np.max(trace["force_N"]) > 0.9 * P.F_rt


# --------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: simulate_rig(effects=["rust"]), "unknown effect 'rust'"),
        (lambda: simulate_rig(effects=["backlash", Backlash()]), "given twice"),
        (lambda: simulate_rig(profile="ramp"), "unknown profile 'ramp'"),
        (lambda: simulate_rig(profile="steps", target_deg=400), r"unknown option\(s\)"),
        (lambda: simulate_rig(sample_rate_hz=5000.0), "100 to 1000 Hz"),
        (lambda: simulate_rig(seed=None), "seed must be a non-negative integer"),
        (lambda: simulate_rig(profile="voltage"), "needs voltage_V"),
        (
            lambda: simulate_rig(profile="voltage", voltage_V=np.zeros(11), duration_s=3.0),
            "leave duration_s out",
        ),
        (lambda: simulate_rig(duration_s=1.0), "after the trace ends"),
        (lambda: simulate_rig(effects=["stiction"], fine_step_s=1e-4), "fine_step_s <= 5e-05"),
        (lambda: SensorDelay(channel="voltage_V"), "channel must be one of"),
        (lambda: Stiction(tau_c_Nm=0.05, tau_s_Nm=0.03), "must be >= tau_c_Nm"),
        (lambda: RigParams(a=-1.0), "a must be > 0"),
        (lambda: RigParams(disc_mode="spin"), "disc_mode must be"),
        (lambda: SensorNoise(force_N=float("nan")), "force_N must be a finite number"),
    ],
)
def test_bad_settings_are_refused_with_a_clear_message(call, match):
    with pytest.raises(RigError, match=match):
        call()
