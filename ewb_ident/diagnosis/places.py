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
from ewb_ident.diagnosis.filters import average_ranks, denoised, fft_convolve_columns
from ewb_ident.diagnosis.inputs import Signal, periodic, sensor_signal
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


# ----------------------------------------------------------------------------- response


def linearised(ses, fit, place):
    """The residual ``r`` and Jacobian ``J`` of the fit ``fit`` at the current values,
    its channels, their row weights (lowered where a teacher-forced stage carries its
    measured input's noise), and ``G(U)``: the weighted change of every
    residual row a term at ``place`` with basis columns ``U`` (n, K) makes (``None``
    when the term shows in none of the fit's channels)."""
    from ewb_ident.inference.augmented import residuals_and_jacobian

    n = ses.trace.n
    r, J, pred = residuals_and_jacobian(fit.problem, fit.u, ses.data)
    r, J = np.asarray(r, float), np.asarray(J, float)
    chans = fit.problem.channels[0]
    n_pad = r.size // len(chans)
    effect = place_effect(place, fit.values, ses.trace)
    if not set(effect) & set(chans) or not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        # No channel of the fit shows the place, or the fit cannot be linearised there (a
        # switching mechanism's Jacobian that is not finite): no term is learned at it.
        return r, J, chans, {}, None
    weights = {}  # as the fit applied them: each residual over its raw difference
    for k, ch in enumerate(chans):
        w, d = np.array(ses.data["w"][ch], float), np.asarray(pred[ch] - ses.data["meas"][ch])
        weights[ch] = np.divide(r[k * n_pad : (k + 1) * n_pad], d, out=w, where=d != 0)[:n_pad]

    def G_of(U: np.ndarray) -> np.ndarray:
        blocks = []
        for ch in chans:
            B = np.zeros((n_pad, U.shape[1]))
            if ch in effect:
                B[:n] = effect[ch](U) * weights[ch][:n, None]
            blocks.append(B)
        return np.concatenate(blocks, axis=0)

    return r, J, chans, weights, G_of


def column_span(J: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns of ``J`` (its numerically nonzero directions)."""
    Uj, sj, _ = np.linalg.svd(J, full_matrices=False)
    return Uj[:, sj > 1e-10 * max(float(sj[0]), 1e-300)]


# ----------------------------------------------------------------------------- periods


#: The positions a term may be periodic in, and the range of periods looked for in each
#: (its own unit), with the places a term periodic in it may act at (``None``: all).
#: The pinion angle, deg: a cogging torque repeats 360/LCM(slots, poles) degrees of the
#: rotor (15-30 for common small motors), a gear's tooth or eccentricity once per tooth
#: or turn. The piston displacement, m: a linear scale's pole or grating pitch and its
#: interpolation error (a fraction of a pitch), a ramp's or a screw's machining waviness;
#: only where x is felt (the gap curve, the force law, the displacement sensor).
PERIODIC: dict[str, tuple[tuple[float, float], tuple[str, ...] | None]] = {
    "angle": ((10.0, 360.0), None),
    "x": ((10e-6, 10e-3), ("gap", "force.input", "force.output", "sensor.x_m")),
}
#: Periods of the coarse scan; neighbours differ in frequency by at most half a cycle
#: over the position's span where that takes no more than this many.
SCAN_PERIODS = 160


def position_periods(
    ses, fit, place: str, signals: Mapping[str, Signal], most: int = 2
) -> dict[str, list[float]]:
    """The periods of a term periodic in a position (:data:`PERIODIC`: the pinion angle,
    deg; the piston displacement, m) that best explain the residual at ``place``, per
    position, estimated from the residual itself (a periodogram in the position, through
    the model's response at the place and orthogonal to what the stage's parameters make;
    a harmonic times a carrier is not scanned: a current times a slow harmonic took the
    place of a resistance that heats), not taken from a list: a coarse scan over every
    period the trace covers (1.5 cycles or more) and resolves (4 samples a cycle or
    more), then each of the ``most`` best peaks refined. The held-out selection then
    judges them as any other input (and a period in x against one in the angle: over an
    apply the gap curve stretches one against the other)."""
    scans = {}
    for name, ((p_lo, p_hi), places) in PERIODIC.items():
        s = signals.get(name)
        if s is None or (places is not None and place not in places):
            continue
        vals = s.values if s.fine is None else s.fine.reshape(-1)
        step = float(np.percentile(np.abs(np.diff(vals)), 95)) if vals.size > 1 else 0.0
        span = float(np.ptp(s.values))
        lo, hi = max(p_lo, 4.0 * step), min(p_hi, span / 1.5)
        if lo < hi:
            scans[name] = (s, lo, hi, span)
    if not scans:
        return {}
    r, J, _, _, G_of = linearised(ses, fit, place)
    if G_of is None:
        return {}
    Uj = column_span(J) if J.shape[1] else np.zeros((r.size, 0))
    r_perp = r - Uj @ (Uj.T @ r)

    def gains(s: Signal, periods) -> np.ndarray:
        """The residual each period's sine and cosine of ``s`` would remove."""
        res = []
        for i in range(0, len(periods), 16):  # in chunks: memory bounded on long traces
            chunk = periods[i : i + 16]
            U = np.stack([c.values for P in chunk for c in periodic(s, P, signals)], axis=1)
            G = G_of(U)
            G = G - Uj @ (Uj.T @ G)
            for k in range(len(chunk)):
                Q, R = np.linalg.qr(G[:, 2 * k : 2 * k + 2])
                Q = Q[:, np.abs(np.diag(R)) > 1e-12 * max(float(np.abs(R).max()), 1e-300)]
                res.append(float(np.sum((Q.T @ r_perp) ** 2)))
        return np.asarray(res)

    out = {}
    for name, (s, lo, hi, span) in scans.items():
        # Frequencies (cycles per unit): spaced by half a cycle over the span, or
        # geometrically when that would take more than SCAN_PERIODS.
        f_lo, f_hi, df = 1.0 / hi, 1.0 / lo, 0.5 / span
        if (f_hi - f_lo) / df + 1 <= SCAN_PERIODS:
            freqs = np.arange(f_lo, f_hi + 0.5 * df, df)
        else:
            freqs = np.geomspace(f_lo, f_hi, SCAN_PERIODS)
        g = gains(s, 1.0 / freqs)
        # Local maxima inside the scan: one at either end is a trend (the gain still
        # rises past the periods the trace covers or resolves), not a period.
        inner = np.arange(1, g.size - 1)
        peaks = inner[(g[inner] >= g[inner - 1]) & (g[inner] >= g[inner + 1])]
        found = []
        for k in sorted(peaks, key=lambda k: -g[k])[:most]:
            fine = np.linspace(freqs[max(k - 1, 0)], freqs[min(k + 1, freqs.size - 1)], 9)
            found.append(float(1.0 / fine[int(np.argmax(gains(s, 1.0 / fine)))]))
        if found:
            out[name] = found
    return out


#: Signals local to a place (its states and their histories; a rate only where listed):
#: preferred among near-equal inputs. Not the logged voltage: the drive, recorded
#: exactly, edges out a state the model computes about a biased fit (a drag's speed).
LOCAL: dict[str, tuple[str, ...]] = {
    "motor.electrical": ("current", "heat", "speed"),
    "motor.mechanical": ("speed", "current", "angle"),
    "drive": ("force", "angle"),
    "gap": ("force", "angle"),
    "force.input": ("x", "time", "energy", "heat"),
    "force.output": ("force", "x_rate", "force_rate", "force_history"),
    "friction": ("force", "disc_speed", "energy", "distance", "disc_angle"),
    "torque.output": ("force", "torque", "disc_angle"),
}


def local_signals(place: str) -> tuple[str, ...]:
    """The signals local to ``place`` (a sensor's: what it reads, and its rate)."""
    own = sensor_signal(place)
    return (own, f"{own}_rate") if own else LOCAL.get(place, ())


def is_local(group: str, local: Sequence[str]) -> bool:
    """Whether an input group (``"force_history_0.5s"``, ``"angle@60"``) is one of
    ``local`` or a history of one (a rate only where listed)."""
    name = group.partition("@")[0]
    if name.endswith("_rate"):
        return name in local
    return any(name == s or name.startswith(s + "_") for s in local if s)


#: Spearman's rank correlation from which two signals are one monotone function of the
#: other over the trace (the pinion angle and the piston's displacement along the gap
#: curve, below the bell's centre the force too).
MONOTONE = 0.999


def monotone_twin(signals: Mapping[str, Signal], name: str, local: Sequence[str]) -> str | None:
    """The first signal of ``local`` that is a monotone function of the signal ``name``
    over the trace (:data:`MONOTONE`, ties ranked alike), if ``name`` is not local
    itself nor a history of a local signal (:func:`is_local`): a learned function of
    one is a function of the other, and the trace cannot tell which it is; the signal
    local to the place is the reading. ``None`` for a signal that only grows with time
    (an energy, a distance): clocks are all in the same order, and the trace tells them
    apart by their shapes."""

    def ranks(v: np.ndarray) -> np.ndarray | None:
        if not (np.all(np.isfinite(v)) and np.ptp(v) > 0):
            return None
        r = average_ranks(v) - (v.size + 1) / 2.0
        return r / float(np.linalg.norm(r))

    own = ranks(signals[name].values) if name in signals and not is_local(name, local) else None
    if own is None or abs(own @ ranks(np.arange(float(own.size)))) >= MONOTONE:
        return None
    twins = (lo for lo in local if lo in signals and (r := ranks(signals[lo].values)) is not None
             and abs(r @ own) >= MONOTONE)  # fmt: skip
    return next(twins, None)
