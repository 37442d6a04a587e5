"""Simulation of the synthetic rig: the compiled integrator and :func:`simulate_rig`."""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, overload

import jax
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.trace import Trace
from ewb_ident.rig.effects import (
    Backlash,
    CurrentLimit,
    ForceHysteresis,
    FrictionFade,
    FrictionSpeed,
    RigEffect,
    SensorDelay,
    SensorOffset,
    Stiction,
    WedgeLoadTorque,
    resolve_effects,
)
from ewb_ident.rig.params import (
    DEG,
    DISC_SLIP_RAD_S,
    SENSOR_CHANNELS,
    STICK_RELAX_S,
    RigError,
    RigParams,
    SensorNoise,
    check_finite,
    check_positive,
)
from ewb_ident.rig.profiles import CLOSED_LOOP, drive_signal

# --------------------------------------------------------------------------------------
# The compiled simulator
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Static:
    """Settings that change the compiled program (the cache key)."""

    n_sub: int
    closed_loop: bool
    backlash: bool
    backlash_spring: bool
    wedge_load: bool
    hysteresis: bool
    friction_speed: str | None
    fade: bool
    current_limit: str | None
    stiction: bool
    stribeck: bool
    coast: bool
    delay_channel: str | None
    delay_buffer: int


# State vector indices.
_I, _W, _TH, _Z, _HEAT, _WD = range(6)


@functools.lru_cache(maxsize=64)
def _compiled(st: _Static):
    """Build and jit the simulator for one set of static settings.

    Longer than the package's ~80-line guide on purpose: its nested functions (the
    wedge's play, one fine step of the motor, wedge and disc, one logging interval with
    its sensors and controller) close over ``st``, so each compiled program holds only
    the effects present, and the rig's physics reads top to bottom in one place.
    """

    def wedge(y, thw_old, p):
        """Wedge-side angle (deg) and speed (rad/s) given the play state before the step."""
        th_deg = y[_TH] * DEG
        if not st.backlash:
            return th_deg, y[_W]
        beta = p["beta_deg"]
        thw = jnp.clip(thw_old, th_deg - beta, th_deg + beta)
        pushing = ((thw_old <= th_deg - beta) & (y[_W] > 0)) | (
            (thw_old >= th_deg + beta) & (y[_W] < 0)
        )
        free = (th_deg - thw) / (p["spring_tau"] * DEG) if st.backlash_spring else 0.0
        return thw, jnp.where(pushing, y[_W], free)

    def observe(y, thw_old, p):
        thw, ww = wedge(y, thw_old, p)
        x = p["p2"] * thw**2 + p["p1"] * thw + p["p0"]
        f_bell = p["F_rt"] / (1.0 + jnp.abs((x - p["c"]) / p["a"]) ** (2.0 * p["b"]))
        force = f_bell * (1.0 + p["hyst_h"] * y[_Z]) if st.hysteresis else f_bell
        mu = p["mu"]
        if st.friction_speed is not None:
            s_rel = (y[_WD] - p["omega_ref"]) / p["omega_ref"]
            if st.friction_speed == "exponential":
                s_rel = 1.0 - jnp.exp(-s_rel)
            mu = mu * (1.0 + p["kappa"] * s_rel)
        if st.fade:
            mu = mu * (1.0 - p["phi"] * y[_HEAT])
        sliding = jnp.clip(y[_WD] / DISC_SLIP_RAD_S, -1.0, 1.0)
        torque = 2.0 * mu * force * p["r_eff"] * sliding
        return {"thw": thw, "ww": ww, "x": x, "force": force, "mu": mu, "torque": torque}

    def rhs(y, volts, thw_old, p):
        o = observe(y, thw_old, p)
        i, w = y[_I], y[_W]
        if st.current_limit == "clip":
            lim = p["R"] * p["i_max"]
            volts = jnp.clip(volts, p["kb"] * w - lim, p["kb"] * w + lim)
        elif st.current_limit == "soft":
            lim = p["R"] * p["i_max"]
            volts = p["kb"] * w + lim * jnp.tanh((volts - p["kb"] * w) / lim)
        di = (volts - p["R"] * i - p["kb"] * w) / p["L"]
        tau_ext = p["kT"] * i
        if st.wedge_load:
            tau_ext = tau_ext - p["k_w"] * o["force"] * jnp.tanh(o["ww"] / p["omega0"])
            tau_ext = tau_ext - p["k_r"] * o["force"]
        if st.stiction:
            stick = jnp.clip(tau_ext + p["M"] * w / STICK_RELAX_S, -p["tau_s"], p["tau_s"])
            slide = p["tau_c"]
            if st.stribeck:
                slide = slide + (p["tau_s"] - p["tau_c"]) * jnp.exp(-((w / p["stribeck"]) ** 2))
            tau_f = jnp.where(jnp.abs(w) < p["band"], stick, slide * jnp.sign(w))
        else:
            tau_f = 0.0
        dw = (tau_ext - p["v"] * w - tau_f) / p["M"]
        if st.hysteresis:
            xdot = (2.0 * p["p2"] * o["thw"] + p["p1"]) * o["ww"] * DEG
            dz = (xdot - jnp.abs(xdot) * y[_Z]) / p["delta"]
        else:
            dz = 0.0
        if st.fade:
            dheat = o["torque"] * y[_WD] / p["heat_cap"] - y[_HEAT] / p["tau_th"]
        else:
            dheat = 0.0
        dwd = -o["torque"] / p["J"] if st.coast else p["disc_slope"]
        return jnp.stack([di, dw, w, jnp.asarray(dz, y.dtype), jnp.asarray(dheat, y.dtype), dwd])

    def advance(y, thw, volts, p):
        """One classical RK4 step of size h; then the play operator."""
        h = p["h"]
        k1 = rhs(y, volts, thw, p)
        k2 = rhs(y + 0.5 * h * k1, volts, thw, p)
        k3 = rhs(y + 0.5 * h * k2, volts, thw, p)
        k4 = rhs(y + h * k3, volts, thw, p)
        y = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        if st.backlash:
            th_deg = y[_TH] * DEG
            if st.backlash_spring:
                thw = thw + (th_deg - thw) * p["spring_gain"]
            thw = jnp.clip(thw, th_deg - p["beta_deg"], th_deg + p["beta_deg"])
        return y, thw

    def channel(y, thw, p, name):
        if name == "theta_deg":
            return y[_TH] * DEG
        if name == "current_A":
            return y[_I]
        o = observe(y, thw, p)
        return {"x_m": o["x"], "force_N": o["force"], "torque_Nm": o["torque"]}[name]

    nb = st.delay_buffer

    def run(p, y0, thw0, xs):
        buf0 = jnp.full((max(nb, 1),), channel(y0, thw0, p, st.delay_channel or "theta_deg"))
        carry0 = (y0, thw0, buf0, jnp.asarray(0, jnp.int64), jnp.zeros_like(y0[0]), y0[_TH] * DEG)

        def sample(carry, x):
            y, thw, buf, j, integ, meas_prev = carry
            o = observe(y, thw, p)
            th_true = y[_TH] * DEG
            out = {
                "theta_deg": th_true,
                "theta_w_deg": o["thw"],
                "x_m": o["x"],
                "force_N": o["force"],
                "torque_Nm": o["torque"],
                "current_A": y[_I],
                "disc_speed_rad_s": y[_WD],
                "mu": o["mu"],
                "hysteresis_z": y[_Z],
                "pad_temperature_rise_K": y[_HEAT],
            }
            th_sensor = th_true
            if st.delay_channel is not None:
                m, frac = p["delay_m"], p["delay_frac"]
                y_a = buf[jnp.mod(j - m, nb)]
                y_b = buf[jnp.mod(j - m - 1, nb)]
                delayed = (1.0 - frac) * y_a + frac * y_b
                out["delayed"] = delayed
                if st.delay_channel == "theta_deg":
                    th_sensor = delayed
            q = p["q_theta"]
            raw = th_sensor + p["sigma_theta"] * x["noise_theta"]
            meas = jnp.where(q > 0, q * jnp.round(raw / jnp.where(q > 0, q, 1.0)), raw)
            out["theta_meas_deg"] = meas
            if st.closed_loop:
                err = x["ref"] - meas
                deriv = -(meas - meas_prev) / p["dt"]
                base = (
                    p["kff"] * x["ref_rate"]
                    + p["kaff"] * x["ref_acc"]
                    + p["kp"] * err
                    + p["kd"] * deriv
                )
                integ_new = integ + err * p["dt"]
                trial = base + p["ki"] * integ_new
                # Anti-windup: stop integrating when saturated and the error pushes further.
                windup = (jnp.abs(trial) > p["v_max"]) & (jnp.sign(trial) == jnp.sign(err))
                integ = jnp.where(windup, integ, integ_new)
                volts = jnp.clip(base + p["ki"] * integ, -p["v_max"], p["v_max"])
            else:
                volts = x["volts"]
            out["voltage_V"] = volts

            def sub(_, c):
                y, thw, buf, j = c
                y, thw = advance(y, thw, volts, p)
                j = j + 1
                if st.delay_channel is not None:
                    buf = buf.at[jnp.mod(j, nb)].set(channel(y, thw, p, st.delay_channel))
                return y, thw, buf, j

            y, thw, buf, j = jax.lax.fori_loop(0, st.n_sub, sub, (y, thw, buf, j))
            return (y, thw, buf, j, integ, meas), out

        _, outs = jax.lax.scan(sample, carry0, xs)
        return outs

    return jax.jit(run)


# --------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CleanRun:
    """The noise-free side of a simulated trace (for tests and studies).

    Parameters
    ----------
    trace
        What the sensors would read without noise and quantisation (sensor effects
        such as ``sensor_delay`` and ``sensor_offset`` included), same columns as the
        noisy trace.
    states
        True physical quantities at the sample times, float64 arrays:
        ``theta_deg`` (pinion), ``theta_w_deg`` (wedge side), ``x_m``, ``force_N``,
        ``torque_Nm``, ``current_A``, ``disc_speed_rad_s``, ``mu``, ``hysteresis_z``,
        ``pad_temperature_rise_K`` and ``theta_ref_deg`` (closed-loop profiles only).
    """

    trace: Trace
    states: Mapping[str, np.ndarray]


@overload  # twice, the signature repeated as typing.overload needs; return_clean differs
def simulate_rig(
    params: RigParams = ...,
    *,
    profile: str = ...,
    sample_rate_hz: float = ...,
    duration_s: float | None = ...,
    theta0_deg: float = ...,
    effects: Iterable[RigEffect | str] = ...,
    noise: SensorNoise = ...,
    seed: int = ...,
    name: str = ...,
    fine_step_s: float = ...,
    return_clean: Literal[False] = ...,
    **profile_options: Any,
) -> tuple[Trace, dict[str, Any]]: ...


@overload
def simulate_rig(
    params: RigParams = ...,
    *,
    profile: str = ...,
    sample_rate_hz: float = ...,
    duration_s: float | None = ...,
    theta0_deg: float = ...,
    effects: Iterable[RigEffect | str] = ...,
    noise: SensorNoise = ...,
    seed: int = ...,
    name: str = ...,
    fine_step_s: float = ...,
    return_clean: Literal[True],
    **profile_options: Any,
) -> tuple[Trace, dict[str, Any], CleanRun]: ...


def simulate_rig(
    params: RigParams = RigParams(),  # noqa: B008 - frozen, immutable default
    *,
    profile: str = "steps",
    sample_rate_hz: float = 200.0,
    duration_s: float | None = None,
    theta0_deg: float = 0.0,
    effects: Iterable[RigEffect | str] = (),
    noise: SensorNoise = SensorNoise(),  # noqa: B008 - frozen, immutable default
    seed: int = 0,
    name: str = "synthetic",
    fine_step_s: float = 2e-5,
    return_clean: bool = False,
    **profile_options: Any,
):
    """Simulate one recording of the synthetic rig.

    Parameters
    ----------
    params
        Rig parameters (truth).
    profile
        ``"steps"`` (open-loop voltage steps; options ``v_apply_V``, ``t_start_s``,
        ``t_apply_s``, ``t_hold_s``, ``t_release_s``), ``"position"`` (PI position
        control of an apply-hold-release reference; options ``target_deg`` (default: the
        angle where ``x = c - 0.3 a``), ``t_start_s``, ``ramp_s``, ``hold_s``),
        ``"through_c"`` (the same, by default to ``x = c + 0.3 a``: through full clamping,
        which pins down a, b and c),
        ``"staircase"`` (the same controller through increasing levels and back;
        options ``levels_deg``, ``t_start_s``, ``dwell_s``, ``peak_rate_deg_s``,
        ``min_ramp_s``) or ``"voltage"`` (``voltage_V=array``, one value per sample).
        The controller options are ``kp_V_per_deg``, ``ki_V_per_deg_s``,
        ``kd_V_s_per_deg``, ``kff_V_s_per_deg`` (velocity feedforward, tuned to the
        nominal motor) and ``v_max_V`` (saturation, 12 V); it runs at the logging rate on
        the measured (noisy) angle, and ``voltage_V`` logs its command.
    sample_rate_hz
        Logging rate, Hz (100 to 1000).
    duration_s
        Trace length, s (default 3 s; for ``"voltage"`` it follows from the array).
    theta0_deg
        Initial pinion angle, degrees.
    effects
        Catalog effects: :class:`RigEffect` instances or catalog ids (defaults).
    noise
        Sensor noise; :meth:`SensorNoise.none` for none.
    seed
        Seed of ``numpy.random.default_rng`` for the sensor noise.
    name
        Name of the trace.
    fine_step_s
        Largest RK4 step, s; the step is ``1 / (sample_rate_hz * n)`` for the smallest
        integer ``n`` that keeps it at or below this.
    return_clean
        Also return a :class:`CleanRun` with the noise-free readings and true states.
    **profile_options
        Options of the profile (above).

    Returns
    -------
    trace
        The noisy trace (columns ``time_s``, ``voltage_V``, ``current_A``,
        ``theta_deg``, ``x_m``, ``force_N``, ``torque_Nm``, ``disc_speed_rad_s``).
    truth
        JSON-serialisable truth: rig parameters, effects and their parameters, noise,
        resolved profile settings, seed, sampling and integration settings.
    clean
        Only with ``return_clean=True``.
    """
    _check_request(params, noise, sample_rate_hz, theta0_deg, fine_step_s, seed)
    eff = resolve_effects(effects)
    dt = 1.0 / sample_rate_hz
    n = _sample_count(profile, profile_options, duration_s, dt, sample_rate_hz)
    t = np.arange(n) * dt
    duration = float(t[-1])

    signal, resolved = drive_signal(profile, params, t, theta0_deg, dict(profile_options))
    closed_loop = profile in CLOSED_LOOP

    if FrictionSpeed.id in eff and not params.disc_varies:
        raise RigError(
            "effect 'friction_speed' needs a disc speed that varies: set "
            "RigParams(disc_speed_end_rad_s=...) for a drag ramp or disc_mode='coast'"
        )

    n_sub = max(1, math.ceil(dt / fine_step_s * (1.0 - 1e-12)))
    h = dt / n_sub
    if Stiction.id in eff and h > STICK_RELAX_S / 2:
        raise RigError(
            f"effect 'stiction' needs fine_step_s <= {STICK_RELAX_S / 2:g} s, got a step of {h:g} s"
        )

    # Sensor noise: one fixed draw order, independent of which sigmas are zero.
    rng = np.random.default_rng(seed)
    unit_noise = {ch: rng.standard_normal(n) for ch in SENSOR_CHANNELS}

    p, thw0, z0, delay_channel, delay_buffer = _step_params(
        params, noise, eff, h, dt, duration, theta0_deg, resolved if closed_loop else None
    )
    static = _Static(
        n_sub=n_sub,
        closed_loop=closed_loop,
        backlash=Backlash.id in eff,
        backlash_spring=Backlash.id in eff and eff[Backlash.id].spring_tau_s > 0,
        wedge_load=WedgeLoadTorque.id in eff,
        hysteresis=ForceHysteresis.id in eff,
        friction_speed=eff[FrictionSpeed.id].law if FrictionSpeed.id in eff else None,
        fade=FrictionFade.id in eff,
        current_limit=eff[CurrentLimit.id].kind if CurrentLimit.id in eff else None,
        stiction=Stiction.id in eff,
        stribeck=Stiction.id in eff and eff[Stiction.id].stribeck_rad_s > 0,
        coast=params.disc_mode == "coast",
        delay_channel=delay_channel,
        delay_buffer=delay_buffer,
    )
    xs = _inputs(closed_loop, signal, unit_noise["theta_deg"], dt)
    y0 = np.array([0.0, 0.0, theta0_deg / DEG, z0, 0.0, params.disc_speed_rad_s])
    outs = _integrate(static, p, y0, thw0, xs)
    clean, measured = _readings(outs, eff, noise, unit_noise, delay_channel, t)

    sidecar: dict[str, Any] = {
        "r_eff_m": params.r_eff_m,
        "sample_rate_hz": float(sample_rate_hz),
        "disc_mode": params.disc_mode,
        "hardware": "synthetic EWB rig (ewb_ident.rig)",
        "description": f"synthetic trace, {profile} profile, seed {seed}",
    }
    if params.disc_mode == "coast":
        sidecar["disc_inertia_kg_m2"] = params.disc_inertia_kg_m2
    trace = Trace(name=name, time_s=t.copy(), channels=measured, sidecar=dict(sidecar))

    truth: dict[str, Any] = {
        "generator": "ewb_ident.rig",
        "name": name,
        "params": dataclasses.asdict(params),
        "effects": {k: e.to_dict() for k, e in eff.items()},
        "noise": dataclasses.asdict(noise),
        "profile": resolved,
        "seed": int(seed),
        "sample_rate_hz": float(sample_rate_hz),
        "duration_s": duration,
        "n_samples": int(n),
        "theta0_deg": float(theta0_deg),
        "fine_step_s": h,
        "n_substeps": n_sub,
    }
    if not return_clean:
        return trace, truth
    states = _states(outs, signal if closed_loop else None)
    clean_trace = Trace(name=name, time_s=t.copy(), channels=clean, sidecar=dict(sidecar))
    return trace, truth, CleanRun(trace=clean_trace, states=states)


def _check_request(params, noise, sample_rate_hz, theta0_deg, fine_step_s, seed) -> None:
    if not isinstance(params, RigParams):
        raise RigError(f"params must be a RigParams, got {type(params).__name__}")
    if not isinstance(noise, SensorNoise):
        raise RigError(f"noise must be a SensorNoise, got {type(noise).__name__}")
    check_finite("simulate_rig", sample_rate_hz=sample_rate_hz, theta0_deg=theta0_deg)
    if not 100.0 <= sample_rate_hz <= 1000.0:
        raise RigError(f"sample_rate_hz must be within 100 to 1000 Hz, got {sample_rate_hz!r}")
    check_positive("simulate_rig", fine_step_s=fine_step_s)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise RigError(f"seed must be a non-negative integer, got {seed!r}")


def _sample_count(profile, profile_options, duration_s, dt, sample_rate_hz) -> int:
    """Samples of the trace: those of a given voltage, or the duration's (3 s default)."""
    if profile == "voltage":
        volts_in = profile_options.get("voltage_V")
        if volts_in is None:
            raise RigError("profile 'voltage' needs voltage_V=array (one value per sample, V)")
        volts_in = np.asarray(volts_in, dtype=np.float64)
        if volts_in.ndim != 1 or volts_in.size < 2 or not np.all(np.isfinite(volts_in)):
            raise RigError(
                "voltage_V must be a 1-D array of at least 2 finite values, got shape "
                f"{volts_in.shape}"
            )
        n = volts_in.size
        if duration_s is not None and abs((n - 1) * dt - duration_s) > 0.5 * dt:
            raise RigError(
                f"voltage_V has {n} samples = {(n - 1) * dt:.6g} s at {sample_rate_hz} Hz, "
                f"but duration_s={duration_s!r}; leave duration_s out or make them agree"
            )
    else:
        duration_s = 3.0 if duration_s is None else duration_s
        check_positive("simulate_rig", duration_s=duration_s)
        n = int(round(duration_s * sample_rate_hz)) + 1
    return n


def _step_params(params, noise, eff, h, dt, duration, theta0_deg, controller):
    """The compiled simulator's parameters (a flat dict of numbers), the wedge's start
    angle and hysteresis state, and the delayed channel with its buffer length."""
    p: dict[str, float] = {
        key: float(getattr(params, key))
        for key in ("R", "L", "kb", "kT", "M", "v", "p2", "p1", "p0", "F_rt", "a", "c", "b", "mu")
    }
    p.update(
        r_eff=params.r_eff_m,
        J=params.disc_inertia_kg_m2,
        h=h,
        dt=dt,
        sigma_theta=noise.theta_deg,
        q_theta=noise.q_theta_deg,
        disc_slope=0.0,
    )
    if params.disc_mode == "drag" and params.disc_speed_end_rad_s is not None:
        p["disc_slope"] = (params.disc_speed_end_rad_s - params.disc_speed_rad_s) / duration
    thw0 = theta0_deg
    z0 = 0.0
    delay_channel, delay_buffer = None, 0
    if Backlash.id in eff:
        bl = eff[Backlash.id]
        p["beta_deg"] = bl.beta_deg
        if bl.spring_tau_s > 0:
            p.update(spring_tau=bl.spring_tau_s, spring_gain=-math.expm1(-h / bl.spring_tau_s))
        thw0 = theta0_deg + {"release": 1.0, "apply": -1.0, "centre": 0.0}[bl.initial_side] * (
            bl.beta_deg
        )
    if WedgeLoadTorque.id in eff:
        e = eff[WedgeLoadTorque.id]
        p.update(k_w=e.k_w, omega0=e.omega0_rad_s, k_r=e.k_r)
    if ForceHysteresis.id in eff:
        e = eff[ForceHysteresis.id]
        p.update(hyst_h=e.h, delta=e.delta_m)
        z0 = -1.0
    if SensorDelay.id in eff and eff[SensorDelay.id].kind == "transport":
        e = eff[SensorDelay.id]
        steps = e.delay_s / h
        m = int(math.floor(steps + 1e-9))
        p.update(delay_m=m, delay_frac=max(0.0, steps - m))
        delay_channel = e.channel
        delay_buffer = 1 << max(1, (m + 2 - 1).bit_length())  # power of two >= m + 2
    if FrictionSpeed.id in eff:
        e = eff[FrictionSpeed.id]
        p.update(kappa=e.kappa, omega_ref=e.omega_ref_rad_s)
    if FrictionFade.id in eff:
        e = eff[FrictionFade.id]
        p.update(phi=e.phi_per_K, heat_cap=e.heat_capacity_J_per_K, tau_th=e.tau_thermal_s)
    if CurrentLimit.id in eff:
        p["i_max"] = eff[CurrentLimit.id].i_max_A
    if Stiction.id in eff:
        e = eff[Stiction.id]
        p.update(tau_c=e.tau_c_Nm, tau_s=e.tau_s_Nm, band=e.band_rad_s)
        if e.stribeck_rad_s > 0:
            p["stribeck"] = e.stribeck_rad_s
    if controller is not None:
        resolved = controller
        p.update(
            kp=resolved["kp_V_per_deg"],
            ki=resolved["ki_V_per_deg_s"],
            kd=resolved["kd_V_s_per_deg"],
            kff=resolved["kff_V_s_per_deg"],
            kaff=resolved["kaff_V_s2_per_deg"],
            v_max=resolved["v_max_V"],
        )

    return p, thw0, z0, delay_channel, delay_buffer


def _inputs(closed_loop, signal, noise_theta, dt) -> dict[str, np.ndarray]:
    """Per-sample inputs: the voltage (open loop), or the reference with its rate and
    acceleration for the feed-forward (closed loop); the angle sensor's unit noise."""
    if closed_loop:
        # Feedforward from the reference's mean rate and acceleration over each interval.
        ref = signal
        rate = np.diff(ref, append=ref[-1]) / dt
        return {
            "noise_theta": noise_theta,
            "ref": ref,
            "ref_rate": rate,
            "ref_acc": np.diff(rate, prepend=0.0) / dt,
        }
    return {"noise_theta": noise_theta, "volts": signal}


def _integrate(static, p, y0, thw0, xs) -> dict[str, np.ndarray]:
    """Run the compiled simulator (float64) and return its outputs as NumPy arrays."""
    with jax.enable_x64(True):
        fn = _compiled(static)
        jp = {
            k: jnp.asarray(val, jnp.int64 if k == "delay_m" else jnp.float64)
            for k, val in p.items()
        }
        outs = fn(
            jp,
            jnp.asarray(y0, jnp.float64),
            jnp.asarray(thw0, jnp.float64),
            {k: jnp.asarray(val, jnp.float64) for k, val in xs.items()},
        )
    return {k: np.asarray(val, dtype=np.float64) for k, val in outs.items()}


def _first_order_lag(u: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``u`` through ``tau dy/dt = u - y`` (``y[0] = u[0]``), exact for a ``u`` linear
    between samples."""
    if tau <= 0:
        return u.copy()
    alpha = math.exp(-dt / tau)
    gain = 1.0 - tau / dt * (1.0 - alpha)
    y = np.empty_like(u)
    y[0] = u[0]
    for k in range(1, u.size):
        y[k] = alpha * y[k - 1] + (1.0 - alpha) * u[k - 1] + gain * (u[k] - u[k - 1])
    return y


def _readings(outs, eff, noise, unit_noise, delay_channel, t):
    """The sensor readings: clean (sensor effects included) and measured (noise and
    quantisation added; the angle as the controller saw it)."""
    # Sensor readings without noise (sensor effects included).
    clean = {
        "voltage_V": outs["voltage_V"],
        "current_A": outs["current_A"].copy(),
        "theta_deg": outs["theta_deg"].copy(),
        "x_m": outs["x_m"].copy(),
        "force_N": outs["force_N"].copy(),
        "torque_Nm": outs["torque_Nm"].copy(),
        "disc_speed_rad_s": outs["disc_speed_rad_s"].copy(),
    }
    if delay_channel is not None:
        clean[delay_channel] = outs["delayed"]
    if SensorDelay.id in eff and eff[SensorDelay.id].kind == "lag":
        e = eff[SensorDelay.id]
        clean[e.channel] = _first_order_lag(clean[e.channel], e.delay_s, float(t[1] - t[0]))
    if SensorOffset.id in eff:
        e = eff[SensorOffset.id]
        clean[e.channel] = clean[e.channel] + e.offset + e.drift_per_s * t

    measured = dict(clean)
    for ch in SENSOR_CHANNELS:
        if ch == "theta_deg":
            measured[ch] = outs["theta_meas_deg"]  # what the controller saw
            continue
        value = clean[ch] + noise.sigma(ch) * unit_noise[ch]
        q = noise.quantum(ch)
        measured[ch] = q * np.round(value / q) if q > 0 else value

    return clean, measured


def _states(outs, reference) -> dict[str, np.ndarray]:
    """The rig's internal states at the sample times (for :class:`CleanRun`)."""
    states = {
        k: outs[k]
        for k in (
            "theta_deg",
            "theta_w_deg",
            "x_m",
            "force_N",
            "torque_Nm",
            "current_A",
            "disc_speed_rad_s",
            "mu",
            "hysteresis_z",
            "pad_temperature_rise_K",
        )
    }
    if reference is not None:
        states["theta_ref_deg"] = reference.copy()
    return states
