"""Least-squares fits of the chain, or of teacher-forced stages, with mechanisms added.

The residual of every fitted channel is divided by a per-sample noise level given by the
caller (the sensor noise floor, with the input noise a teacher-forced stage propagates),
so that fits of the same stages with and without a mechanism have comparable costs.
Parameters are optimised in unconstrained O(1) coordinates: the base parameters as
declared in :data:`ewb_ident.params.PARAMS`, each mechanism's as it declares them.
The solver is optimistix's Levenberg-Marquardt from the best of a few starting points.

Arrays are padded to a multiple of :data:`PAD` samples (padding weighted zero) so that
traces of similar length share compiled code.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..params import MODEL_PARAMS, PARAMS, EWBParams
from ..traces import Trace
from .base import AbstractMechanism
from .model import STAGE_OUTPUTS, n_substeps, predict

#: Arrays are padded to a multiple of this many samples.
PAD = 256
#: Most starting points tried per fit.
MAX_STARTS = 24
#: Columns a fit may read.
COLUMNS = (
    "voltage_V",
    "theta_deg",
    "x_m",
    "force_N",
    "torque_Nm",
    "current_A",
    "disc_speed_rad_s",
)


def padded_length(n: int) -> int:
    """``n`` rounded up to a multiple of :data:`PAD`."""
    return int(-(-n // PAD) * PAD)


def _pad(y: np.ndarray, n_pad: int) -> np.ndarray:
    y = np.asarray(y, dtype=float)
    return np.concatenate([y, np.full(n_pad - y.size, y[-1])]) if n_pad > y.size else y


def make_data(
    trace: Trace,
    sigma: Mapping[str, np.ndarray | float],
    fixed: Mapping[str, float],
    *,
    x_play_m: float = 0.0,
    omega_ref: float = 1.0,
) -> dict[str, Any]:
    """The data pytree of a fit.

    Parameters
    ----------
    trace
        The trace.
    sigma
        Noise level per fitted channel, a number or one per sample, in the channel's unit.
    fixed
        Values (SI) of every base parameter and ``theta0_deg``.
    x_play_m
        Half width of the play filter on the measured displacement (force stage), m.
    omega_ref
        Reference disc speed of ``friction_speed``, rad/s.
    """
    n = trace.n
    n_pad = padded_length(n)
    mask = np.zeros(n_pad)
    mask[:n] = 1.0
    meas = {c: jnp.asarray(_pad(trace[c], n_pad)) for c in COLUMNS if trace.has(c)}
    w = {}
    for ch, s in sigma.items():
        s = np.broadcast_to(np.asarray(s, dtype=float), (n,))
        w[ch] = jnp.asarray(_pad(1.0 / s, n_pad) * mask)
    return {
        "meas": meas,
        "w": w,
        "fixed": {k: jnp.asarray(float(v)) for k, v in fixed.items()},
        "dt": jnp.asarray(trace.dt),
        "t": jnp.asarray(np.arange(n_pad) * trace.dt),
        "r_eff": jnp.asarray(trace.r_eff_m),
        "omega_ref": jnp.asarray(float(omega_ref)),
        "x_play": jnp.asarray(float(x_play_m)),
        # An array, not a Python int: filter_jit would make a plain int static and
        # recompile for every trace length.
        "n": jnp.asarray(n),
    }


class AugProblem(eqx.Module):
    """Weighted residuals of the stages (or chain) with mechanisms, as a function of u."""

    stages: tuple[str, ...] = eqx.field(static=True)
    free: tuple[str, ...] = eqx.field(static=True)
    specs: tuple[tuple[type, tuple], ...] = eqx.field(static=True)
    channels: tuple[str, ...] = eqx.field(static=True)
    n_sub: int = eqx.field(static=True)

    def templates(self) -> list[AbstractMechanism]:
        return [cls(**dict(cfg)) for cls, cfg in self.specs]

    def build(self, u: jnp.ndarray, data: Mapping[str, Any]):
        """Base parameters, start angle and mechanism instances for the vector ``u``."""
        vals = dict(data["fixed"])
        for j, name in enumerate(self.free):
            vals[name] = PARAMS[name].to_physical(u[j])
        j = len(self.free)
        mechs = []
        for tmpl in self.templates():
            infos = tmpl.param_info()
            mv = {info.name: info.to_physical(u[j + i]) for i, info in enumerate(infos)}
            j += len(infos)
            mechs.append(tmpl.with_values(mv))
        p = EWBParams(**{n: vals[n] for n in MODEL_PARAMS})
        return p, vals["theta0_deg"], tuple(mechs)

    def predict(self, u: jnp.ndarray, data: Mapping[str, Any]) -> dict[str, jnp.ndarray]:
        p, theta0, mechs = self.build(u, data)
        stage = "chain" if self.stages == ("chain",) else self.stages
        return predict(stage, p, theta0, mechs, data, self.n_sub)

    def __call__(self, u: jnp.ndarray, data: Mapping[str, Any]) -> jnp.ndarray:
        pred = self.predict(u, data)
        return jnp.concatenate(
            [(pred[ch] - data["meas"][ch]) * data["w"][ch] for ch in self.channels]
        )


@eqx.filter_jit
def _solve(problem: AugProblem, u0, data, max_steps):
    solver = optx.LevenbergMarquardt(rtol=1e-7, atol=1e-9)
    sol = optx.least_squares(problem, solver, u0, args=data, max_steps=max_steps, throw=False)
    r = problem(sol.value, data)
    return sol.value, sol.result, jnp.sum(r * r), sol.stats["num_steps"]


@eqx.filter_jit
def _costs(problem: AugProblem, us, data):
    return jax.vmap(lambda u: jnp.sum(problem(u, data) ** 2))(us)


@eqx.filter_jit
def _residuals(problem: AugProblem, u, data):
    return problem(u, data)


@eqx.filter_jit
def _jacobian(problem: AugProblem, u, data):
    return jax.jacfwd(problem)(u, data)


@eqx.filter_jit
def _predict(problem: AugProblem, u, data):
    return problem.predict(u, data)


@dataclass(frozen=True)
class AugFit:
    """The outcome of one fit with mechanisms (immutable).

    Attributes
    ----------
    stages
        The fitted teacher-forced stages, or ``("chain",)``.
    mechanisms
        The fitted mechanism instances (plain float values).
    values
        Base parameter values (SI) and ``theta0_deg``.
    stderr
        Standard errors (SI) of the free base parameters (by name) and of the
        mechanisms' parameters (``"variant.param"``); ``None`` where not identified.
    rss
        Sum of squared weighted residuals.
    n
        Number of residuals (samples times channels).
    k
        Number of fitted parameters.
    channel_rss
        ``rss`` split by channel.
    converged
        Whether the solver reported success.
    predictions
        The model's fitted channels (NumPy, trace length).
    """

    stages: tuple[str, ...]
    mechanisms: tuple[AbstractMechanism, ...]
    values: dict[str, float]
    stderr: dict[str, float | None]
    rss: float
    n: int
    k: int
    channel_rss: dict[str, float]
    converged: bool
    predictions: dict[str, np.ndarray] = field(repr=False)
    residuals: dict[str, np.ndarray] = field(repr=False)

    def mechanism_values(self) -> dict[str, dict[str, float]]:
        """Fitted values of each mechanism, keyed by its variant."""
        return {m.variant: m.values() for m in self.mechanisms}

    def mechanism_stderr(self, m: AbstractMechanism) -> dict[str, float | None]:
        """Standard errors of one fitted mechanism's parameters."""
        return {i.name: self.stderr.get(f"{m.variant}.{i.name}") for i in m.param_info()}


def fit_mechanisms(
    data: Mapping[str, Any],
    stages: Sequence[str],
    free: Sequence[str],
    mechanisms: Sequence[AbstractMechanism],
    channels: Sequence[str],
    start: Mapping[str, float] | None = None,
    *,
    ctx: Mapping[str, Any] | None = None,
    explore: Sequence[bool] | None = None,
    max_steps: int = 200,
    n_best: int = 2,
) -> AugFit:
    """Fit base parameters ``free`` and every mechanism parameter by least squares.

    Parameters
    ----------
    data
        From :func:`make_data` (``fixed`` holds every base value, the start of the free).
    stages
        ``("chain",)`` or teacher-forced stage names.
    free
        Base parameters to vary (names of :data:`ewb_ident.params.PARAMS`).
    mechanisms
        Mechanisms with their starting values.
    channels
        Channels compared (each needs a weight in ``data["w"]``).
    start
        Starting values of free base parameters (default: ``data["fixed"]``).
    ctx
        Facts about the trace for the mechanisms' starting points.
    explore
        Per mechanism, whether to try its own starting points besides its given values
        (default: all); a mechanism fitted before needs only its fitted values.
    max_steps
        Solver step limit per start.
    n_best
        Number of the best starting points the solver runs from.
    """
    stages = tuple(stages)
    mechs = tuple(mechanisms)
    dt = float(data["dt"])
    problem = AugProblem(
        stages=stages,
        free=tuple(free),
        specs=tuple((type(m), m.static_config()) for m in mechs),
        channels=tuple(channels),
        n_sub=n_substeps(dt, mechs),
    )
    base = {k: float(v) for k, v in data["fixed"].items()} | dict(start or {})
    u_base = [float(PARAMS[n].to_unconstrained(base[n])) for n in problem.free]

    # Starting points: the given values of each mechanism, and its own suggestions.
    ctx = dict(ctx or {}) | {"dt": dt}
    options = []
    explore = [True] * len(mechs) if explore is None else list(explore)
    for m, more in zip(mechs, explore, strict=True):
        own = [m.values()] + ([m.values() | s for s in m.starts(ctx)] if more else [])
        options.append(own)
    combos = list(itertools.islice(itertools.product(*options), MAX_STARTS))
    us = []
    for combo in combos:
        u = list(u_base)
        for m, vals in zip(mechs, combo, strict=True):
            u += [_to_u(i, vals[i.name]) for i in m.param_info()]
        us.append(u)
    us = jnp.asarray(np.array(us, dtype=float))
    costs = np.asarray(_costs(problem, us, data))
    costs = np.where(np.isfinite(costs), costs, np.inf)
    order = np.argsort(costs)[: max(1, n_best)]

    best = None
    for i in order:
        u, result, cost, _ = _solve(problem, us[i], data, max_steps)
        cost = float(cost)
        ok = result == optx.RESULTS.successful and np.isfinite(cost)
        if not np.isfinite(cost):
            continue
        if best is None or cost < best[2]:
            best = (u, ok, cost)
    if best is None:  # every start failed: keep the best start point
        i = int(order[0])
        best = (us[i], False, float(costs[i]))
    u, ok, cost = best
    return _result(problem, u, data, ok, mechs)


def _to_u(info, value: float) -> float:
    if info.transform == "logit":
        lo, hi = info.lower, info.upper
        value = min(max(value, lo + 1e-6 * (hi - lo)), hi - 1e-6 * (hi - lo))
    if info.transform == "log":
        value = max(value, 1e-300)
    return float(info.to_unconstrained(value))


def _result(problem: AugProblem, u, data, ok, templates) -> AugFit:
    n = int(data["n"])
    r = np.asarray(problem(u, data))
    rss = float(np.sum(r * r))
    nch = len(problem.channels)
    n_res = n * nch
    chan_rss = {}
    for j, ch in enumerate(problem.channels):
        seg = r[j * r.size // nch : (j + 1) * r.size // nch]
        chan_rss[ch] = float(np.sum(seg * seg))
    J = np.asarray(_jacobian(problem, u, data))
    k = J.shape[1]
    u_np = np.asarray(u)
    infos = [PARAMS[n_] for n_ in problem.free]
    names = list(problem.free)
    for tmpl in problem.templates():
        for info in tmpl.param_info():
            infos.append(info)
            names.append(f"{tmpl.variant}.{info.name}")
    stderr = _stderr(J, rss, n_res, u_np, infos)
    p, theta0, mechs = problem.build(u, data)
    pred = {ch: np.asarray(v)[:n] for ch, v in _predict(problem, u, data).items()}
    values = {name: float(getattr(p, name)) for name in MODEL_PARAMS}
    values["theta0_deg"] = float(theta0)
    plain = tuple(m.with_values(m.values()) for m in mechs)
    resid = {ch: np.asarray(data["meas"][ch])[:n] - pred[ch] for ch in problem.channels}
    return AugFit(
        stages=problem.stages,
        mechanisms=plain,
        values=values,
        stderr=dict(zip(names, stderr, strict=True)),
        rss=rss,
        n=n_res,
        k=k,
        channel_rss=chan_rss,
        converged=bool(ok),
        predictions=pred,
        residuals=resid,
    )


def _stderr(J: np.ndarray, rss: float, n: int, u: np.ndarray, infos) -> list[float | None]:
    """Standard errors (SI) from the Jacobian, with the residual scale profiled."""
    k = J.shape[1]
    if k == 0:
        return []
    scale = np.linalg.norm(J, axis=0)
    good = scale > 1e-12 * max(float(np.max(scale)), 1e-300)
    out: list[float | None] = [None] * k
    if not np.any(good):
        return out
    Js = J[:, good] / scale[good]
    _, s, Vt = np.linalg.svd(Js, full_matrices=False)
    if s[-1] <= s[0] * 1e-10:
        keep = s > s[0] * 1e-10
        inv = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
    else:
        inv = (Vt.T / s**2) @ Vt
    s2 = rss / max(n - k, 1)
    cov = inv / np.outer(scale[good], scale[good]) * s2
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    for j, idx in enumerate(np.flatnonzero(good)):
        se = float(abs(infos[idx].dp_du(u[idx])) * sd[j])
        out[idx] = se if np.isfinite(se) else None
    return out


def stage_channels(stages: Sequence[str], available: Sequence[str]) -> tuple[str, ...]:
    """Channels compared by a fit of these stages, given the trace's columns."""
    if tuple(stages) == ("chain",):
        chans = ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A")
    else:
        chans = tuple(c for s in stages for c in STAGE_OUTPUTS[s])
    return tuple(c for c in chans if c in available)
