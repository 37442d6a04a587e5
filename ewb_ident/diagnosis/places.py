"""Where a learned term can act in the model, and how a term there changes each
predicted channel: the model's exact linear response at the current fit (the motor's
impulse response for its equations, a slope for a static stage, the reading and the
stage it feeds for a sensor), and which stages and recorded channels that involves.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ewb_ident.data.stages import CHANNEL_INPUT_OF, CHANNEL_STAGE, STAGE_OUTPUTS
from ewb_ident.diagnosis.filters import denoised, fft_convolve_columns
from ewb_ident.mechanisms.learned import PLACES, LearnedTerm
from ewb_ident.model.integrate import zoh_exact
from ewb_ident.model.physics import DEG_PER_RAD, motor_matrices


def motor_response(values: Mapping[str, float], dt: float, n: int) -> np.ndarray:
    """Impulse responses of the motor (current A, angle deg) to a voltage (column 0) and
    to a load torque (column 1) held over one sample: ``h[k, out, inp]`` is the output
    at sample ``k`` after a unit input over sample 0 (the outputs lag by one sample)."""
    A, B_V, B_tau = motor_matrices(*(float(values[k]) for k in "R L kb kT M v".split()), np)
    Ad, Bd = zoh_exact(A, np.stack([B_V, B_tau], axis=1), dt)
    h = np.zeros((n, 2, 2))
    x = Bd.copy()
    for k in range(1, n):
        h[k, 0], h[k, 1] = x[0], x[2] * DEG_PER_RAD
        x = Ad @ x
        if k > 50 and np.max(np.abs(x[:2])) < 1e-14 * (1 + np.max(np.abs(h[k]))):
            h[k + 1 :, 1] = h[k, 1]  # the speed has died out: the angle stays
            break
    return h


def _bell_slope(x, values) -> np.ndarray:
    F_rt, a, b, c = (float(values[k]) for k in ("F_rt", "a", "b", "c"))
    u = np.abs((x - c) / a) + 1e-300
    q = u ** (2 * b)
    return F_rt * (2 * b * q / u) * np.sign(c - x) / a / (1 + q) ** 2


def place_effect(place: str, values: Mapping[str, float], trace) -> dict[str, Any]:
    """How a term at ``place`` changes each predicted channel, per stage.

    Returns ``{channel: op}`` where ``op(U)`` maps the term's basis columns ``U`` (n, K)
    to the change of that channel's prediction (n, K): the model's exact linear response
    at the current fit (``values``)."""
    n, dt = trace.n, trace.dt
    ch_sensor = place.split(".", 1)[1] if place.startswith("sensor.") else None
    if place in ("motor.electrical", "motor.mechanical"):
        h = motor_response(values, dt, n)
        j = 0 if place == "motor.electrical" else 1

        def conv(k_out):
            def op(U):
                return fft_convolve_columns(h[:, k_out, j], U)[:n]  # scipy.signal.fftconvolve

            return op

        return {"current_A": conv(0), "theta_deg": conv(1)}

    def scaled(g):
        g = np.asarray(g, float)[:n]
        return lambda U: g[:, None] * U

    # The slopes at the recorded levels without their noise at each sample: a term's
    # change scaled by the recorded force would carry that sample's force noise, which
    # the residual of a stage fitted on the recorded force carries too (a term would
    # fit that noise's attenuation of the fit, held-out data alike).
    level = {ch: denoised(trace[ch], dt) for ch in ("theta_deg", "x_m", "force_N") if trace.has(ch)}
    th, x, F = level.get("theta_deg"), level.get("x_m"), level.get("force_N")
    slope_th = None if th is None else 2 * values["p2"] * th + values["p1"]
    slope_x = None if x is None else _bell_slope(x, values)
    gain_F = 2 * values["mu"] * trace.r_eff_m
    one = lambda U: U  # noqa: E731
    if place == "drive":
        return {"x_m": one}
    if place == "gap":
        return {"x_m": scaled(slope_th)} if slope_th is not None else {}
    if place == "force.input":
        return {"force_N": scaled(slope_x)} if slope_x is not None else {}
    if place == "force.output":
        return {"force_N": one}
    if place == "friction":
        return {"torque_Nm": scaled(gain_F * F)} if F is not None else {}
    if place == "torque.output":
        return {"torque_Nm": one}
    if ch_sensor is not None:
        out = {ch_sensor: one}
        down = CHANNEL_INPUT_OF.get(ch_sensor)
        slope = {"gap": slope_th, "force": slope_x, "torque": np.full(n, gain_F)}.get(down)
        if down is not None and slope is not None:
            down_ch = STAGE_OUTPUTS[down][0]
            out[down_ch] = scaled(-slope)
        return out
    raise ValueError(f"unknown place {place!r}")


def places_of(stage: str, channels: Sequence[str]) -> list[str]:
    """The places whose term shows at ``stage`` (its own, and the sensors of its
    recorded output and input channels)."""
    own = [p for p, info in PLACES.items() if info.stage == stage and not p.startswith("sensor.")]
    sensors = []
    for ch in channels:
        if ch == "voltage_V":
            continue
        if CHANNEL_STAGE.get(ch) == stage or CHANNEL_INPUT_OF.get(ch) == stage:
            sensors.append(f"sensor.{ch}")
    return own + sensors


def own_sample_channels(trace, model, stages: Sequence[str]) -> tuple[str, ...]:
    """The recorded channels whose noise is not in the residuals of ``stages`` (those a
    term at the channel's sensor shows in: as an output or through an input), nor taken
    from the model: a term there may take them at their own sample."""
    return tuple(
        ch for ch in CHANNEL_STAGE
        if trace.has(ch) and ch not in model and not place_stages(f"sensor.{ch}", stages)
    )  # fmt: skip


def place_stages(place: str, stages: Sequence[str]) -> tuple[str, ...]:
    """The teacher-forced stages (of those checkable) whose residuals a term at ``place``
    changes."""
    return tuple(s for s in LearnedTerm(place=place).stages if s in stages)
