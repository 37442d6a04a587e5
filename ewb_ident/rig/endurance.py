"""A synthetic endurance log: many apply cycles of the rig in one long recording, with a
slow drift of its parameters (a planted fade) whose truth is known per cycle."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ewb_ident.data.trace import Trace
from ewb_ident.rig.params import RigError, RigParams, SensorNoise
from ewb_ident.rig.simulate import simulate_rig


def simulate_endurance(
    params: RigParams = RigParams(),  # noqa: B008 - frozen, immutable default
    *,
    duration_s: float = 3600.0,
    period_s: float = 10.0,
    sample_rate_hz: float = 1000.0,
    drift: Mapping[str, float] | None = None,
    profile: str = "through_c",
    apply_at_s: float = 1.0,
    noise: SensorNoise = SensorNoise(),  # noqa: B008 - frozen, immutable default
    seed: int = 0,
    name: str = "endurance",
) -> tuple[Trace, dict[str, Any]]:
    """Simulate an endurance log: one apply cycle every ``period_s``, concatenated.

    Each cycle is one :func:`~ewb_ident.rig.simulate_rig` run of ``period_s`` (the apply
    of ``profile`` starting ``apply_at_s`` into it, then rest), from rest to rest, with
    its own noise seed ``seed * 100_000 + k``; the runs are laid end to end on one time axis.
    Parameters drift linearly in time: cycle ``k``, starting at ``t_k = k period_s``,
    has ``value * (1 + drift[name] * t_k / duration_s)`` (``drift`` is the relative
    change over the whole log, e.g. ``{"mu": -0.1}``: the pad friction 10 % lower at
    the end, a slow fade). Within a cycle the parameters are constant.

    Parameters
    ----------
    params
        The rig at the start of the log.
    duration_s, period_s, sample_rate_hz
        Length of the log and of each cycle, s, and the sample rate, Hz.
    drift
        Relative change of rig parameters over ``duration_s`` (see above).
    profile, apply_at_s
        The drive of each cycle and when its apply starts, s into the cycle.
    noise, seed, name
        Sensor noise, seed of the per-cycle noise, and the trace's name.

    Returns
    -------
    trace, truth
        The log (``time_s`` from 0), and its truth: ``cycles`` (per cycle ``t_start_s``
        and the parameters it had), ``drift``, ``period_s``, ``params`` (at the start).
    """
    drift = dict(drift or {})
    unknown = [k for k in drift if k not in {f.name for f in dataclasses.fields(RigParams)}]
    if unknown:
        raise RigError(f"drift: {unknown[0]!r} is not a rig parameter")
    n_cycles = int(round(duration_s / period_s))
    if n_cycles < 1 or not math.isclose(n_cycles * period_s, duration_s, rel_tol=1e-9):
        raise RigError(f"duration_s {duration_s:g} is not a whole number of periods "
                       f"{period_s:g} s")
    per = int(round(period_s * sample_rate_hz))
    if not math.isclose(per / sample_rate_hz, period_s, rel_tol=1e-9):
        raise RigError(f"period_s {period_s:g} is not a whole number of samples at "
                       f"{sample_rate_hz:g} Hz")
    dt = 1.0 / sample_rate_hz
    time_s = np.arange(n_cycles * per) * dt
    columns: dict[str, np.ndarray] = {}
    cycles = []
    for k in range(n_cycles):
        t0 = k * period_s
        values = {p: getattr(params, p) * (1.0 + r * t0 / duration_s) for p, r in drift.items()}
        cycle_params = dataclasses.replace(params, **values)
        trace, _ = simulate_rig(cycle_params, profile=profile, sample_rate_hz=sample_rate_hz,
                                duration_s=period_s, noise=noise, seed=seed * 100_000 + k,
                                name=f"{name}_{k}", t_start_s=apply_at_s)
        for channel, series in trace.channels.items():
            if channel not in columns:
                columns[channel] = np.empty(n_cycles * per)
            columns[channel][k * per:(k + 1) * per] = series[:per]
        cycles.append({"cycle": k, "t_start_s": t0,
                       "params": {p: float(v) for p, v in values.items()}})
    sidecar = {"sample_rate_hz": sample_rate_hz, "r_eff_m": params.r_eff_m,
               "description": f"synthetic endurance log: {n_cycles} {profile} cycles every "
                              f"{period_s:g} s"}
    truth = {"params": dataclasses.asdict(params), "drift": drift, "period_s": period_s,
             "apply_at_s": apply_at_s, "profile": profile, "cycles": cycles}
    return Trace(name=name, time_s=time_s, channels=columns, sidecar=sidecar), truth
