"""Least-squares fits of the chain, stage-wise or whole, to one or several traces.

What is fitted
--------------
``stage="motor"``  voltage -> theta (and current, when recorded)
``stage="gap"``    measured theta -> x          (teacher-forced)
``stage="force"``  measured x -> force          (teacher-forced)
``stage="torque"`` measured force -> torque     (teacher-forced)
``stage="chain"``  voltage -> every recorded channel at once

Weights. Each channel's residuals are divided by that channel's noise level, which is
estimated, not hand-set: first from the data (second differences, see
:func:`ewb_ident.data.metrics.noise_sigma`), then, after a first solve, from the residuals
themselves (the maximum-likelihood estimate for Gaussian noise), and the fit is solved
again from there.

Parameters are optimised in unconstrained O(1) coordinates (:mod:`ewb_ident.model.params`);
standard errors come from the Jacobian at the optimum (delta method back to SI units).
The solver is optimistix's Levenberg-Marquardt; its result code is always checked.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ewb_ident.data.metrics import (
    SEED_ACCEPTANCE_PCT,
    SEED_PERCENT_ERROR,
    channel_metrics,
    noise_floor,
    noise_sigma,
)
from ewb_ident.data.outputs import null_nonfinite
from ewb_ident.data.trace import CHANNELS, STAGE_COLUMNS, Trace, TraceError
from ewb_ident.inference.initial import bell_start, motor_lag, motor_start
from ewb_ident.inference.uncertainty import (
    identifiability_notes,
    parameter_uncertainty,
    saturation_notes,
)
from ewb_ident.model.integrate import EXPONENTIAL, Integrator, heun_amplification, seed_motor_states
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, STAGE_PARAMS, EWBParams
from ewb_ident.model.physics import brake_torque, clamp_force, gap

Stage = Literal["motor", "gap", "force", "torque", "chain"]
STAGES: tuple[str, ...] = ("motor", "gap", "force", "torque", "chain")

#: Parameters fitted per trace unless the user says otherwise: the start angle is a
#: property of each recording, not of the rig.
DEFAULT_PER_TRACE: tuple[str, ...] = ("theta0_deg",)


class FitError(ValueError):
    """A fit that cannot be set up as asked (unknown stage or parameter, no data)."""


def stage_channels(stage: str, trace: Trace) -> tuple[str, ...]:
    """The measured channels a stage's prediction is compared with, for one trace."""
    if stage == "motor":
        return ("theta_deg",) + (("current_A",) if trace.has("current_A") else ())
    if stage == "chain":
        return tuple(ch for ch in CHANNELS if trace.has(ch))
    return (STAGE_COLUMNS[stage][1],)


def stage_inputs(stage: str) -> tuple[str, ...]:
    """The columns a stage needs as input."""
    return ("voltage_V",) if stage in ("motor", "chain") else (STAGE_COLUMNS[stage][0],)


def default_free(stage: str, traces: Sequence[Trace]) -> tuple[str, ...]:
    """The parameters a fit varies when the user does not say: only what the recorded
    channels can determine (see :func:`structural_notes` for the words).

    Motor: with current, ``R``, ``L``, ``kb``, ``M``, ``v`` and the start angle. From
    voltage and angle alone only the gain and the two lags of the transfer function are
    identified (:func:`motor_combinations`), so ``L``, ``kb`` and ``M`` are fitted:
    ``R`` stays nominal and ``v`` is held at a small value
    (:func:`held_viscous_friction`), so ``kb`` carries the damping. ``kT`` always stays
    fixed: with no load-torque measurement only ratios to it are identified.
    Gap: ``p2, p1, p0``. Force: ``F_rt, a, b, c`` (a rig's rated force differs from the
    seed's 3500 N, and a wrong fixed F_rt biases a, b, c and mu).
    Torque: ``mu``. Chain: the gap polynomial when ``x_m`` is recorded (otherwise it
    trades off with ``c``); the bell when force or torque is; ``mu`` only when both
    force and torque are (torque alone fixes only the product ``mu F_rt``).
    """
    if stage == "motor":
        if all(t.has("current_A") for t in traces):
            return ("R", "L", "kb", "M", "v", "theta0_deg")
        return ("L", "kb", "M", "theta0_deg")
    if stage == "gap":
        return ("p2", "p1", "p0")
    if stage == "force":
        return ("F_rt", "a", "b", "c")
    if stage == "torque":
        return ("mu",)
    has = {ch: any(t.has(ch) for t in traces) for ch in ("x_m", "force_N", "torque_Nm")}
    free = list(default_free("motor", traces))
    if has["x_m"]:
        free += default_free("gap", traces)
    if has["force_N"] or has["torque_Nm"]:
        free += default_free("force", traces)
    if has["force_N"] and has["torque_Nm"]:
        free += default_free("torque", traces)
    return tuple(free)


def structural_notes(stage: str, traces: Sequence[Trace], free: Sequence[str]) -> list[str]:
    """What the recorded channels cannot determine, in words (for the fit's warnings)."""
    notes = []
    fixed = set(MODEL_PARAMS) - set(free)
    if stage in ("motor", "chain"):
        if not all(t.has("current_A") for t in traces) and {"R", "v"} & fixed:
            notes.append(
                "no current_A: from voltage and angle the motor identifies only its gain "
                "kT/(R v + kT kb) and its lags (reported under 'derived'); R and v are held "
                "fixed, so kb, M and L are effective values"
            )
    if stage in ("torque", "chain"):
        defaulted = [t.name for t in traces if t.r_eff_source == "default" and t.has("torque_Nm")]
        if defaulted:
            notes.append(
                f"r_eff = 0.15 m (the seed's default) for {', '.join(defaulted)}: no sidecar "
                "gives the pad radius, and mu scales with 1/r_eff; give it with --r-eff or "
                "the sidecar's r_eff_m"
            )
    if stage == "chain":
        names = [t.name for t in traces]
        if not any(t.has("torque_Nm") for t in traces):
            notes.append(
                f"no torque_Nm in {', '.join(names)}: mu is not determined by this trace "
                "and is held at its nominal value"
            )
        elif not any(t.has("force_N") for t in traces) and "mu" in fixed:
            notes.append(
                "no force_N: the torque fixes only the product mu F_rt; mu is held at its "
                "nominal value and F_rt is an effective value"
            )
        if not any(t.has("x_m") for t in traces):
            notes.append(
                "no x_m: the gap polynomial is held at its nominal value, so c and a are "
                "measured in the nominal polynomial's displacement"
            )
        if not any(t.has("force_N") or t.has("torque_Nm") for t in traces):
            notes.append("no force_N or torque_Nm: a, b, c and mu are not determined")
    return notes


# ----------------------------------------------------------------------------- problem


class StageProblem(eqx.Module):
    """Weighted residuals of one fit as a function of the unconstrained vector ``u``.

    All configuration is static (hashable), so solving the same problem on new data of
    the same shapes reuses the compiled code.
    """

    stage: str = eqx.field(static=True)
    shared: tuple[str, ...] = eqx.field(static=True)
    per_trace: tuple[str, ...] = eqx.field(static=True)
    channels: tuple[tuple[str, ...], ...] = eqx.field(static=True)
    n_sub: tuple[int, ...] = eqx.field(static=True)
    method: str = eqx.field(static=True)

    def values(self, u: jnp.ndarray, base: dict, k: int) -> dict[str, jnp.ndarray]:
        """Parameter values (SI) for trace ``k``: fixed ones from ``base``, free from u."""
        out = dict(base)
        for j, name in enumerate(self.shared):
            out[name] = PARAMS[name].to_physical(u[j])
        offset = len(self.shared) + k * len(self.per_trace)
        for j, name in enumerate(self.per_trace):
            out[name] = PARAMS[name].to_physical(u[offset + j])
        return out

    def predict(self, u: jnp.ndarray, data: dict) -> list[dict[str, jnp.ndarray]]:
        """The model's prediction of each fitted channel, per trace."""
        preds = []
        for k, tr in enumerate(data["traces"]):
            base = dict(data["fixed"]) | {"theta0_deg": tr["theta0_deg"]}
            vals = self.values(u, base, k)
            p = EWBParams(**{n: vals[n] for n in MODEL_PARAMS})
            preds.append(self._predict_one(p, vals["theta0_deg"], tr, self.n_sub[k]))
        return preds

    def _predict_one(self, p: EWBParams, theta0, tr: dict, n_sub: int) -> dict:
        if self.stage == "gap":
            return {"x_m": gap(tr["theta_deg"], p.p2, p.p1, p.p0)}
        if self.stage == "force":
            return {"force_N": clamp_force(tr["x_m"], p.F_rt, p.a, p.b, p.c)}
        if self.stage == "torque":
            return {"torque_Nm": brake_torque(tr["force_N"], p.mu, tr["r_eff_m"])}
        s = seed_motor_states(p, tr["voltage_V"], tr["dt"], theta0, n_sub, self.method, None)
        theta = s[:, 2] * (180.0 / jnp.pi)
        out = {"theta_deg": theta, "current_A": s[:, 0]}
        if self.stage == "chain":
            x = gap(theta, p.p2, p.p1, p.p0)
            F = clamp_force(x, p.F_rt, p.a, p.b, p.c)
            out |= {"x_m": x, "force_N": F, "torque_Nm": brake_torque(F, p.mu, tr["r_eff_m"])}
        return out

    def __call__(self, u: jnp.ndarray, data: dict) -> jnp.ndarray:
        res = []
        for k, pred in enumerate(self.predict(u, data)):
            tr = data["traces"][k]
            for ch in self.channels[k]:
                res.append((pred[ch] - tr[ch]) / tr["sigma"][ch])
        return jnp.concatenate(res)


@eqx.filter_jit
def _solve(problem: StageProblem, u0, data, rtol, atol, max_steps):
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    return optx.least_squares(problem, solver, u0, args=data, max_steps=max_steps, throw=False)


@eqx.filter_jit
def _evaluate(problem: StageProblem, u, data):
    """Weighted residuals, predictions and the Jacobian at ``u``, in one compiled call."""
    return problem(u, data), problem.predict(u, data), jax.jacfwd(problem)(u, data)


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class FitResult:
    """The outcome of a least-squares fit (immutable).

    Attributes
    ----------
    stage
        What was fitted (see module docstring).
    trace_names
        Names of the fitted traces, in order.
    free, per_trace
        Names of the varied parameters; ``per_trace`` ones were fitted per trace.
    params
        Fitted parameters for each trace (SI units).
    theta0_deg
        Start angle of each trace, degrees.
    stderr
        Standard error of each free shared parameter (SI units); for per-trace ones
        ``"name[k]"`` keys. ``None`` where the Jacobian gives none.
    corr
        Correlation matrix of the free coordinates, ordered as ``corr_names``.
    condition_number
        Condition number of the column-scaled Jacobian at the optimum.
    metrics, trace_metrics
        Pooled and per-trace metrics per channel (see :mod:`ewb_ident.data.metrics`).
    noise, sigma
        Per trace and channel: the sensor-noise estimate from the data, and the noise
        level the final weights used (from the residuals), in the channel's unit.
    converged
        Whether the solver reported success on every solve.
    r_eff
        Per trace, the pad radius used (m) and where it came from (``--r-eff``,
        ``sidecar`` or ``default``).
    acceptable
        Whether the fit passes the acceptance this tool states: a bell that is not
        flat (``b`` >= :data:`FLAT_BELL_B`) and force and torque percent errors within
        the seed paper's 10 % (:data:`ewb_ident.data.metrics.SEED_ACCEPTANCE_PCT`). A channel
        missing its noise floor by more than :data:`MISFIT_RATIO` is a warning, not a
        rejection (the diagnosis explains it).
    message
        The solver's result, in words.
    n_steps
        Solver steps, summed over the solves.
    warnings
        Plain-language warnings (identifiability, solver), for the user to read.
    predictions
        The model's prediction of every fitted channel, per trace (NumPy arrays).
    u
        The solution in unconstrained coordinates (shared parameters, then the
        per-trace ones trace by trace), as ``corr_names`` orders them.
    problem, data
        The residual function and its data (measured channels, weights ``sigma``,
        fixed values): ``problem(u, data)`` gives the weighted residuals and
        ``problem.predict(u, data)`` the model's channels. The posterior starts here.
    """

    stage: str
    trace_names: tuple[str, ...]
    free: tuple[str, ...]
    per_trace: tuple[str, ...]
    params: tuple[EWBParams, ...]
    theta0_deg: tuple[float, ...]
    stderr: dict[str, float | None]
    corr: np.ndarray
    corr_names: tuple[str, ...]
    condition_number: float
    metrics: dict[str, dict[str, float | None]]
    trace_metrics: tuple[dict[str, dict[str, float | None]], ...]
    noise: tuple[dict[str, float], ...]
    sigma: tuple[dict[str, float], ...]
    converged: bool
    acceptable: bool
    r_eff: tuple[tuple[float, str], ...]
    message: str
    n_steps: int
    cost: float
    warnings: tuple[str, ...]
    predictions: tuple[dict[str, np.ndarray], ...] = field(repr=False)
    u: np.ndarray = field(repr=False)
    problem: StageProblem = field(repr=False)
    data: dict = field(repr=False)

    @property
    def status(self) -> str:
        """``ok``, ``not_converged`` or ``poor_fit`` (the CLI exits 3 unless ``ok``)."""
        if not self.converged:
            return "not_converged"
        return "ok" if self.acceptable else "poor_fit"

    @property
    def values(self) -> dict[str, float]:
        """All parameter values (SI) of the first trace, plus ``theta0_deg``."""
        return self.params[0].as_dict() | {"theta0_deg": self.theta0_deg[0]}

    def to_json(self) -> dict[str, Any]:
        """The contract ``fit.json`` document (plain JSON types, no NaN)."""
        shared = [n for n in self.free if n not in self.per_trace]
        values = self.params[0].as_dict()
        if len(self.params) > 1:  # per-trace parameters: report the mean, each below
            for name in self.per_trace:
                if name in values:
                    values[name] = float(np.mean([p.as_dict()[name] for p in self.params]))
        per_trace = []
        for k, name in enumerate(self.trace_names):
            vals = {n: self.params[k].as_dict()[n] for n in self.per_trace if n in MODEL_PARAMS}
            if "theta0_deg" in self.per_trace:
                vals["theta0_deg"] = self.theta0_deg[k]
            per_trace.append(
                {
                    "trace": name,
                    "params": vals,
                    "stderr": {n: self.stderr.get(f"{n}[{k}]") for n in self.per_trace},
                    "metrics": self.trace_metrics[k],
                    "noise_sigma": self.noise[k],
                    "residual_sigma": self.sigma[k],
                }
            )
        stderr = {n: self.stderr.get(n) for n in values}
        if len(self.params) == 1:
            stderr |= {n: self.stderr.get(f"{n}[0]") for n in self.per_trace if n in values}
        doc = {
            "params": values,
            "stderr": stderr,
            "metrics": self.metrics,
            "converged": self.converged,
            "acceptable": self.acceptable,
            "status": self.status,
            "stage": self.stage,
            "free": list(self.free),
            "shared": shared,
            "per_trace_params": list(self.per_trace),
            "fixed": sorted(n for n in MODEL_PARAMS if n not in self.free),
            "per_trace": per_trace,
            "units": {n: PARAMS[n].unit for n in values},
            "correlation": {
                "names": list(self.corr_names),
                "matrix": _finite(self.corr).tolist(),
            },
            "condition_number": _finite_or_none(self.condition_number),
            "solver": {"message": self.message, "steps": self.n_steps, "cost": self.cost},
            "derived": motor_combinations(self.params[0]),
            "r_eff_m": {
                t["trace"]: {"value": v, "source": src}
                for t, (v, src) in zip(per_trace, self.r_eff, strict=True)
            },
            "seed_percent_error": SEED_PERCENT_ERROR,
            "warnings": list(self.warnings),
            "stderr_note": (
                "null: parameter fixed, or not identified by the data (singular Jacobian), "
                "or the model diverged (see warnings)"
            ),
        }
        return null_nonfinite(doc)


def motor_combinations(p: EWBParams) -> dict[str, float]:
    """The motor's combinations that voltage and angle alone identify (SI).

    Voltage to speed is ``K / (c2 s^2 + c1 s + 1)`` with ``D = R v + kT kb``:

    ``motor_gain_rad_per_V_s``: ``K = kT / D``, the no-load speed per volt;
    ``motor_lag_s``: ``c1 = (L v + R M) / D``, the total lag (mechanical time constant
    ``M R / D`` plus a small electrical share);
    ``motor_lag2_s2``: ``c2 = L M / D``, weakly determined by the angle alone;
    ``motor_time_constant_s``: ``M R / D``; ``electrical_time_constant_s``: ``L / R``.
    """
    values = {n: float(getattr(p, n)) for n in ("R", "L", "kb", "kT", "M", "v")}
    return {k: float(v) for k, v in motor_combination_values(**values).items()}


def motor_combination_values(R, L, kb, kT, M, v) -> dict[str, Any]:
    """:func:`motor_combinations` of explicit motor parameters (SI; floats or JAX
    arrays, so it can be differentiated)."""
    damping = R * v + kT * kb
    return {
        "motor_gain_rad_per_V_s": kT / damping,
        "motor_lag_s": (L * v + R * M) / damping,
        "motor_lag2_s2": L * M / damping,
        "motor_time_constant_s": M * R / damping,
        "electrical_time_constant_s": L / R,
    }


def _finite(a: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(a), a, 0.0)


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


# ----------------------------------------------------------------------------- set-up


def _trace_data(trace: Trace, stage: str, channels: tuple[str, ...]) -> dict:
    needed = set(channels) | set(stage_inputs(stage)) | {"theta_deg"} & set(trace.channels)
    d: dict[str, Any] = {c: jnp.asarray(trace[c]) for c in needed if trace.has(c)}
    d["dt"] = jnp.asarray(trace.dt)
    d["r_eff_m"] = jnp.asarray(trace.r_eff_m)
    theta0 = float(np.median(trace["theta_deg"][:5])) if trace.has("theta_deg") else 0.0
    d["theta0_deg"] = jnp.asarray(theta0)
    return d


def _check_fixed(fixed: Mapping[str, float], free: Iterable[str] | None) -> None:
    """Every fixed value names a model parameter, is finite and inside its bounds, and is
    not also asked to vary."""
    for name, value in fixed.items():
        if name not in MODEL_PARAMS:
            close = [n for n in MODEL_PARAMS if n.lower() == name.lower()]
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise FitError(
                f"--fix: unknown parameter {name!r}{hint}; the model's parameters are "
                f"{', '.join(MODEL_PARAMS)}"
            )
        info = PARAMS[name]
        v = float(value)
        if not np.isfinite(v) or (info.transform != "affine" and not info.inside(v)):
            raise FitError(
                f"--fix: {name}={value!r} is outside its bounds ({info.lower:g} < {name} < "
                f"{info.upper:g} {info.unit}); give a finite value inside them"
            )
    both = sorted(set(fixed) & set(free or ()))
    if both:
        raise FitError(
            f"{', '.join(both)} cannot be both fixed (--fix) and free (--free); drop one"
        )


def _check_request(
    traces: Sequence[Trace], stage: str, free: Sequence[str], per_trace: Sequence[str]
) -> None:
    if stage not in STAGES:
        raise FitError(f"unknown stage {stage!r}; choose one of {', '.join(STAGES)}")
    if not traces:
        raise FitError("no traces to fit")
    allowed = STAGE_PARAMS[stage]
    for name in free:
        if name not in allowed:
            raise FitError(
                f"parameter {name!r} is not fitted by stage {stage!r}; "
                f"its parameters are {', '.join(allowed)}"
            )
    for name in per_trace:
        if name not in free:
            raise FitError(f"per-trace parameter {name!r} must also be free")
    for tr in traces:
        for col in stage_inputs(stage) + stage_channels(stage, tr)[:1]:
            if not tr.has(col):
                raise TraceError(
                    f"{tr.label}: column '{col}', row -: the {stage} stage needs it and the "
                    "trace has none; fit another stage or record this channel"
                )


def held_viscous_friction(traces: Sequence[Trace], base: EWBParams) -> float:
    """The viscous friction held fixed when the motor is fitted without current (SI).

    The nominal ``v``, or 20 % of the measured total damping ``(R v + kT kb)/R =
    kT/(K R)`` if that is lower (``K``: no-load speed per volt from
    :func:`ewb_ident.inference.initial.motor_lag`), so that ``kb`` stays positive for any motor.
    """
    gains = [abs(motor_lag(t["voltage_V"], t["theta_deg"], t.dt)["K"]) for t in traces]
    damping = float(base.kT) / (max(float(np.median(gains)), 1e-6) * float(base.R))
    return float(min(float(base.v), 0.2 * damping))


def _start_values(
    traces: Sequence[Trace],
    stage: str,
    free: Sequence[str],
    per_trace: Sequence[str],
    base: EWBParams,
) -> dict[str, float]:
    """A start in the optimum's valley, from the data (see :mod:`ewb_ident.inference.initial`).

    Closed forms where a stage is linear in its parameters (gap polynomial, mu); a
    lag-plus-integrator grid for the motor; a straight-line grid for the bell. For the
    whole chain, the motor and the bell are then refined by teacher-forced least-squares
    fits from their measured inputs, so the chain's solver starts with every link in its
    own valley (away from the flat-bell basin). Keys ``"name[k]"`` hold per-trace values.
    """
    start: dict[str, float] = {}
    want = set(free)
    if want & {"p2", "p1", "p0"} and all(t.has("theta_deg") and t.has("x_m") for t in traces):
        th = np.concatenate([t["theta_deg"] for t in traces])
        x = np.concatenate([t["x_m"] for t in traces])
        coef = np.linalg.lstsq(np.stack([th * th, th, np.ones_like(th)], 1), x, rcond=None)[0]
        start |= dict(zip(("p2", "p1", "p0"), map(float, coef), strict=True))
    if "mu" in want and all(t.has("force_N") and t.has("torque_Nm") for t in traces):
        F = np.concatenate([t["force_N"] * 2 * t.r_eff_m for t in traces])
        T = np.concatenate([t["torque_Nm"] for t in traces])
        start["mu"] = float(np.clip(F @ T / (F @ F), 0.01, 0.99))
    motor = [n for n in free if n in STAGE_PARAMS["motor"]]
    if stage in ("motor", "chain") and motor and all(t.has("theta_deg") for t in traces):
        start |= _motor_start(traces, motor, per_trace, base)
    bell = [n for n in STAGE_PARAMS["force"] if n in want]
    pseudo = []
    if bell and stage in ("force", "chain"):
        pseudo = [_bell_trace(t, start, base) for t in traces]
        if all(p is not None for p in pseudo):
            x = np.concatenate([p["x_m"] for p in pseudo])
            F = np.concatenate([p["force_N"] for p in pseudo])
            try:
                guess = bell_start(x, F)
            except ValueError:
                guess = {}
            start |= {n: v for n, v in guess.items() if n in bell}
    if stage != "chain":
        return start
    fixed = base.as_dict() | {k: v for k, v in start.items() if "[" not in k}
    subs = [("motor", traces, motor)]
    if bell and all(p is not None for p in pseudo):
        subs.append(("force", pseudo, bell))
    for sub, trs, names in subs:
        names = [n for n in names if n in free]
        if not names or not all(t.has(c) for t in trs for c in stage_inputs(sub)):
            continue
        res = fit(
            trs,
            stage=sub,
            free=names,
            per_trace=[n for n in per_trace if n in names],
            fixed={k: v for k, v in fixed.items() if k not in names},
            start={k: v for k, v in start.items() if k.split("[")[0] in names},
        )
        if not np.isfinite(res.cost) or not all(
            _usable(n, v) for p in res.params for n, v in p.as_dict().items() if n in names
        ):
            continue  # a stage fit that ran off to a bound: keep the data-driven start
        for k, p in enumerate(res.params):
            vals = p.as_dict() | {"theta0_deg": res.theta0_deg[k]}
            for n in names:
                start[f"{n}[{k}]" if n in per_trace else n] = vals[n]
    return start


def _usable(name: str, value: float) -> bool:
    """Whether a fitted value can start another fit: finite, and for a log-scaled
    parameter within 1e-6 to 1e6 of its reference (not run off towards 0 or infinity)."""
    info = PARAMS[name]
    if not np.isfinite(value):
        return False
    if info.transform == "log":
        return 1e-6 * info.ref < value < 1e6 * info.ref
    if info.transform == "logit":
        return info.inside(value)
    return True


def _motor_start(
    traces: Sequence[Trace], names: Sequence[str], per_trace: Sequence[str], base: EWBParams
) -> dict[str, float]:
    """Motor start values from each trace's voltage, angle and current (median over
    traces for shared parameters)."""
    per = []
    for t in traces:
        guess = motor_start(
            t["voltage_V"],
            t["theta_deg"],
            t.dt,
            base.as_dict(),
            t["current_A"] if "R" in names and t.has("current_A") else None,
        )
        per.append(guess)
    out: dict[str, float] = {}
    for n in names:
        if n not in per[0]:
            continue
        if n in per_trace:
            out |= {f"{n}[{k}]": g[n] for k, g in enumerate(per)}
        else:
            out[n] = float(np.median([g[n] for g in per]))
    return out


def _bell_trace(trace: Trace, start: Mapping[str, float], base: EWBParams) -> Trace | None:
    """The bell's input and output for a teacher-forced start: measured ``x_m`` (or the
    gap polynomial of the measured angle) and measured force (or torque / (2 mu r_eff))."""
    if trace.has("x_m"):
        x = trace["x_m"]
    elif trace.has("theta_deg"):
        p = {n: start.get(n, float(getattr(base, n))) for n in ("p2", "p1", "p0")}
        x = np.asarray(gap(trace["theta_deg"], p["p2"], p["p1"], p["p0"]))
    else:
        return None
    if trace.has("force_N"):
        F = trace["force_N"]
    elif trace.has("torque_Nm"):
        mu = start.get("mu", float(base.mu))
        F = trace["torque_Nm"] / (2.0 * mu * trace.r_eff_m)
    else:
        return None
    return Trace(
        name=trace.name,
        time_s=trace.time_s,
        channels={"x_m": np.asarray(x, float), "force_N": np.asarray(F, float)},
        sidecar=dict(trace.sidecar),
    )


# ----------------------------------------------------------------------------- fit


@dataclass(frozen=True)
class _Setup:
    """Everything about a fit that is fixed before the solver runs."""

    traces: tuple[Trace, ...]
    stage: str
    free: tuple[str, ...]
    per_trace: tuple[str, ...]
    base: EWBParams
    channels: tuple[tuple[str, ...], ...]
    problem: StageProblem
    tdata: list[dict]
    noise: tuple[dict[str, float], ...]
    notes: tuple[str, ...]

    def data(self, sigma: Sequence[Mapping[str, float]]) -> dict:
        """The solver's data pytree with the given per-trace, per-channel noise levels."""
        trs = [
            d | {"sigma": {c: jnp.asarray(v) for c, v in s.items()}}
            for d, s in zip(self.tdata, sigma, strict=True)
        ]
        return {"traces": trs, "fixed": {n: jnp.asarray(v) for n, v in self.base.as_dict().items()}}

    def sensor_sigma(self) -> list[dict[str, float]]:
        """Noise levels from the data alone (floored), the first weights."""
        return [
            {ch: max(s, noise_floor(t[ch])) for ch, s in nz.items()}
            for t, nz in zip(self.traces, self.noise, strict=True)
        ]


def _setup(traces, stage, free, per_trace, fixed, integrator) -> _Setup:
    traces = (traces,) if isinstance(traces, Trace) else tuple(traces)
    fixed = dict(fixed or {})
    _check_fixed(fixed, free)
    if free is None:
        free_t = tuple(n for n in default_free(stage, traces) if n not in fixed)
    else:
        free_t = tuple(free)
    # The start angle is a property of each recording: always per trace when free.
    pt = tuple(dict.fromkeys(DEFAULT_PER_TRACE + tuple(per_trace or ())))
    _check_request(traces, stage, free_t, tuple(n for n in pt if n not in DEFAULT_PER_TRACE))
    pt = tuple(n for n in free_t if n in pt)  # in the order of free
    base = EWBParams().replace(**{k: v for k, v in fixed.items() if k in MODEL_PARAMS})
    if stage in ("motor", "chain") and "kb" in free_t and "v" not in free_t and "v" not in fixed:
        base = base.replace(v=held_viscous_friction(traces, base))
    notes = structural_notes(stage, traces, free_t)
    if integrator.method == "heun":
        rho = heun_amplification(base, min(t.dt for t in traces))
        if rho > 1:
            notes.append(
                f"Heun's method at the seed's step is unstable for this motor (amplification "
                f"{rho:.3g} > 1): the simulation diverges; use the exponential integrator"
            )
    channels = tuple(stage_channels(stage, t) for t in traces)
    problem = StageProblem(
        stage=stage,
        shared=tuple(n for n in free_t if n not in pt),
        per_trace=pt,
        channels=channels,
        n_sub=tuple(integrator.substeps(t.dt, False) for t in traces),
        method=integrator.method,
    )
    return _Setup(
        traces=traces,
        stage=stage,
        free=free_t,
        per_trace=pt,
        base=base,
        channels=channels,
        problem=problem,
        tdata=[_trace_data(t, stage, ch) for t, ch in zip(traces, channels, strict=True)],
        noise=tuple(
            {ch: noise_sigma(t[ch]) for ch in chs} for t, chs in zip(traces, channels, strict=True)
        ),
        notes=tuple(notes),
    )


def fit(
    traces: Trace | Sequence[Trace],
    *,
    stage: Stage = "chain",
    free: Iterable[str] | None = None,
    per_trace: Iterable[str] | None = None,
    fixed: Mapping[str, float] | None = None,
    start: Mapping[str, float] | None = None,
    integrator: Integrator = EXPONENTIAL,
    max_steps: int = 300,
    rtol: float = 1e-6,
    atol: float = 1e-8,
) -> FitResult:
    """Fit the EWB model to one or several traces by weighted least squares.

    Parameters
    ----------
    traces
        One :class:`~ewb_ident.data.trace.Trace` or several; several share every free
        parameter except those in ``per_trace``.
    stage
        ``"chain"`` (from voltage alone, every recorded channel), or one stage
        teacher-forced from its measured input: ``"motor"``, ``"gap"``, ``"force"``,
        ``"torque"``.
    free
        Parameters to vary (default: :func:`default_free`).
    per_trace
        Free parameters fitted separately for each trace (default: the start angle),
        e.g. ``("c", "p0")`` for the contact point after a pad change.
    fixed
        Values (SI) of parameters held fixed, overriding the seed values.
    start
        Starting values (SI) of free parameters, overriding the automatic start.
    integrator
        How the motor is integrated (motor and chain stages).
    max_steps
        Solver step limit per solve.
    rtol, atol
        Solver tolerances on the unconstrained O(1) coordinates (1e-6 is far below any
        parameter's statistical uncertainty).

    Returns
    -------
    FitResult
        Never raises for a fit that fails to converge: ``converged`` is False and
        ``message`` and ``warnings`` say why.

    Raises
    ------
    FitError
        Unknown stage or parameter.
    TraceError
        A trace lacks a column the stage needs.
    """
    setup = _setup(traces, stage, free, per_trace, fixed, integrator)
    st = _start_values(setup.traces, stage, setup.free, setup.per_trace, setup.base)
    st = {k: v for k, v in st.items() if _usable(k.split("[")[0], v)}
    st |= dict(start or {})
    # No null direction reaches the solver: at the start, a combination of free
    # parameters the data cannot see (scaled Jacobian numerically singular) has its
    # dominant parameter held at its start value, and the fit says so. A solve that
    # still ran out of steps is checked the same way at the point it reached (the
    # solver wandering along a valley floor the start did not show, e.g. a current
    # channel too small against its noise to separate R, kb and M); the parameter is
    # then held at its start value and the fit solved again from the start.
    held: dict[str, float] = {}
    held_notes: list[str] = []
    while True:
        setup, u0, data, sigma = _hold_null_directions(
            setup, st, per_trace, dict(fixed or {}), held, held_notes, integrator
        )
        sol, sigma, data, results, steps = _solve_twice(
            setup, u0, data, sigma, rtol, atol, max_steps
        )
        # Every solve counts, as in ``_finish``: a first solve that ran out of steps in a
        # flat valley can be followed by a re-weighted one that stops "successfully"
        # because its steps became tiny, not because it reached an optimum.
        done = all(_is(res, optx.RESULTS.successful) for res in results)
        if done or len(setup.problem.shared) < 2:
            break
        if not (
            _hold_one(setup, sol.value, data, st, held, held_notes, "where the solver stopped")
            or _hold_flank_exponent(setup, sol.value, data, held, held_notes)
        ):
            break
    if held_notes:
        setup = dataclasses.replace(setup, notes=setup.notes + tuple(held_notes))
    return _finish(setup, sol.value, data, sigma, results, steps, max_steps)


def _hold_one(setup, u, data, st, held, notes, where: str) -> bool:
    """If the scaled Jacobian at ``u`` has a null direction, hold its dominant parameter
    at its start value (or the base one, if that is unusable), adding it to ``held``
    and the words to ``notes``; whether one was held."""
    J = np.asarray(_evaluate(setup.problem, u, data)[2])
    found = _null_direction(J, setup.problem.shared)
    if found is None:
        return False
    name, partners, cond = found
    if "b" in partners and set(partners) <= BELL_SHAPE:
        # The force never shows the bell's top (the piston stops on its flank): hold the
        # exponent at the seed value, the remedy the flank note gives, rather than an
        # edge or centre at a start value that may be far off.
        name, value = "b", float(setup.base.b)
        why = f"b is held at the seed model's {value:.4g}"
    else:
        value = float(st.get(name, getattr(setup.base, name)))
        info = PARAMS[name]
        if not (_usable(name, value) and (info.transform == "affine" or info.inside(value))):
            value = float(getattr(setup.base, name))
        why = f"{name} is held at {value:.4g} {info.unit}"
    held[name] = value
    notes.append(
        f"the data cannot tell {', '.join(partners)} apart (condition number {cond:.2g} "
        f"{where}): {why}"
    )
    return True


def _hold_flank_exponent(setup, u, data, held, notes) -> bool:
    """After a solve that did not converge: if the piston never passes the bell's centre
    c in any trace at ``u`` and b is free, hold b at the seed value (adding it to
    ``held`` and the words to ``notes``); whether it was held.

    On the rising flank alone a, b and c trade off along a curved valley whose condition
    number can stay under :data:`NULL_CONDITION` while the solver still wanders along it
    (a 100 Hz staircase stopped at its step limit with correlations a-b, a-c, b-c of
    +1.00). Which coordinate to hold is then set by the physics, not by the spectrum.
    """
    if "b" not in setup.problem.shared or setup.stage not in ("chain", "force"):
        return False
    preds = _evaluate(setup.problem, u, data)[1]
    reach = []
    for k, (t, pred) in enumerate(zip(setup.traces, preds, strict=True)):
        x = t["x_m"] if t.has("x_m") else pred.get("x_m")
        if x is None:
            return False
        c = float(setup.problem.values(u, data["fixed"] | {"theta0_deg": 0.0}, k)["c"])
        if not float(np.max(np.asarray(x))) < c:
            return False
        reach.append(f"max x = {float(np.max(np.asarray(x))) * 1e3:.3f} mm < c = {c * 1e3:.3f} mm")
    held["b"] = float(setup.base.b)
    notes.append(
        "the solver did not converge and the piston never passes the bell's centre "
        f"({'; '.join(reach)}): the rising flank alone cannot set a, b and c, so b is held "
        f"at the seed model's {setup.base.b:.4g}"
    )
    return True


#: The bell's parameters: a null direction among only these means the force data do not
#: pin the bell's shape (typically an apply that never passes c).
BELL_SHAPE = frozenset({"F_rt", "a", "b", "c"})


def _hold_null_directions(setup, st, per_trace, fixed, held, notes, integrator):
    """Hold, one at a time, the dominant parameter of each null direction of the scaled
    Jacobian at the start (adding to ``held`` and ``notes``); the final set-up, start
    vector, data and first weights. Parameters already in ``held`` are held first."""
    for _ in range(len(setup.free) + 1):
        if set(held) & set(setup.free):
            setup = _setup(
                setup.traces,
                setup.stage,
                [n for n in setup.free if n not in held],
                per_trace,
                fixed | held,
                integrator,
            )
        u0 = _to_u(setup.problem, st, setup.base, setup.tdata)
        sigma = setup.sensor_sigma()
        data = setup.data(sigma)
        if not _hold_one(setup, u0, data, st, held, notes, "at the start"):
            break
    return setup, u0, data, sigma


def _solve_twice(setup, u0, data, sigma, rtol, atol, max_steps):
    """Solve, re-estimate the noise levels from the residuals, solve again; a solve that
    ran out of steps while still descending gets one more allowance."""
    problem = setup.problem
    sol = _solve(problem, u0, data, rtol, atol, max_steps)
    results, steps = [sol.result], int(sol.stats["num_steps"])
    r = np.asarray(_evaluate(problem, sol.value, data)[0])
    if np.all(np.isfinite(r)):
        sigma = _residual_sigma(r, setup.channels, setup.traces, sigma)
        data = setup.data(sigma)
        sol = _solve(problem, sol.value, data, rtol, atol, max_steps)
        results.append(sol.result)
        steps += int(sol.stats["num_steps"])
        if _is(sol.result, optx.RESULTS.nonlinear_max_steps_reached):
            sol = _solve(problem, sol.value, data, rtol, atol, max_steps)
            results[-1] = sol.result
            steps += int(sol.stats["num_steps"])
    return sol, sigma, data, results, steps


def _finish(setup: _Setup, u, data, sigma, results, steps, max_steps) -> FitResult:
    """Uncertainty, predictions, metrics and notes at the solution ``u``."""
    problem, traces, channels = setup.problem, setup.traces, setup.channels
    r, predicted, J = _evaluate(problem, u, data)
    r, J, u = np.asarray(r), np.asarray(J), np.asarray(u)
    ok = all(_is(res, optx.RESULTS.successful) for res in results) and bool(np.all(np.isfinite(r)))
    message = "successful" if ok else _message(results, r, max_steps)
    notes = list(setup.notes)
    if not ok:
        notes.append(f"the solver did not converge: {message}")

    names = problem.shared + tuple(
        f"{n}[{k}]" for k in range(len(traces)) for n in problem.per_trace
    )
    infos = [PARAMS[n] for n in problem.shared] + [
        PARAMS[n] for _ in traces for n in problem.per_trace
    ]
    unc = parameter_uncertainty(J, r, u, infos)
    stderr = dict(zip(names, unc.stderr, strict=True))
    notes += identifiability_notes(names, unc, stderr)

    preds = [
        {k: np.asarray(v) for k, v in p.items() if k in chs}
        for p, chs in zip(predicted, channels, strict=True)
    ]
    params, theta0 = [], []
    for k, d in enumerate(setup.tdata):
        vals = problem.values(u, setup.base.as_dict() | {"theta0_deg": float(d["theta0_deg"])}, k)
        params.append(EWBParams(**{n: float(vals[n]) for n in MODEL_PARAMS}))
        theta0.append(float(vals["theta0_deg"]))
    if setup.stage in ("force", "chain") and any(n in setup.free for n in ("a", "b", "c")):
        notes += saturation_notes(traces, preds, params, unc.corr, names)
    trace_metrics = tuple(
        {ch: channel_metrics(p[ch], t[ch]) for ch in chs}
        for p, t, chs in zip(preds, traces, channels, strict=True)
    )
    pooled = {}
    for ch in dict.fromkeys(c for chs in channels for c in chs):
        sim = np.concatenate([p[ch] for p in preds if ch in p])
        meas = np.concatenate([t[ch] for t, chs in zip(traces, channels, strict=True) if ch in chs])
        pooled[ch] = channel_metrics(sim, meas)
    acceptable, judged = _judge(setup, params, trace_metrics, pooled)
    notes += judged
    return FitResult(
        stage=setup.stage,
        trace_names=tuple(t.name for t in traces),
        free=setup.free,
        per_trace=setup.per_trace,
        params=tuple(params),
        theta0_deg=tuple(theta0),
        stderr=stderr,
        corr=unc.corr,
        corr_names=names,
        condition_number=unc.condition_number,
        metrics=pooled,
        trace_metrics=trace_metrics,
        noise=setup.noise,
        sigma=tuple(sigma),
        converged=ok,
        acceptable=acceptable,
        r_eff=tuple((t.r_eff_m, t.r_eff_source) for t in traces),
        message=message,
        n_steps=steps,
        cost=float(0.5 * np.sum(r * r)) if np.all(np.isfinite(r)) else float("inf"),
        warnings=tuple(notes),
        predictions=tuple(preds),
        u=u,
        problem=problem,
        data=data,
    )


def _to_u(
    problem: StageProblem, values: Mapping[str, float], base: EWBParams, tdata
) -> jnp.ndarray:
    """The unconstrained vector for start ``values`` (SI; ``"name[k]"`` per trace)."""
    defaults = base.as_dict()
    u = [PARAMS[n].to_unconstrained(values.get(n, defaults.get(n))) for n in problem.shared]
    for k, d in enumerate(tdata):
        for n in problem.per_trace:
            v = float(d["theta0_deg"]) if n == "theta0_deg" else defaults[n]
            u.append(PARAMS[n].to_unconstrained(values.get(f"{n}[{k}]", values.get(n, v))))
    return jnp.asarray(np.array(u, dtype=float))


#: Above this condition number of the column-scaled Jacobian at the start, a direction
#: is taken as null (structurally unidentified), not merely poorly determined.
NULL_CONDITION = 1.0e4


def _null_direction(J: np.ndarray, shared: Sequence[str]) -> tuple[str, list[str], float] | None:
    """The shared parameter to hold when ``J`` (weighted residuals by ``u``) has a null
    direction: the one with the largest weight in the smallest singular vector, with the
    parameters that make up the direction and the condition number."""
    if J.shape[1] < 2 or not np.all(np.isfinite(J)):
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        scale = np.linalg.norm(J, axis=0)
    if not np.all(np.isfinite(scale)):  # a diverging model: nothing to learn here
        return None
    if np.any(scale == 0):  # a parameter the residuals do not depend on at all
        j = int(np.argmin(scale))
        return (shared[j], [shared[j]], float("inf")) if j < len(shared) else None
    _, sv, Vt = np.linalg.svd(np.linalg.qr(J / scale, mode="r"))
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if cond < NULL_CONDITION:
        return None
    w = np.abs(Vt[-1][: len(shared)])
    if w.size == 0 or w.max() == 0:
        return None
    partners = [shared[j] for j in np.argsort(-w) if w[j] > 0.1 * w.max()]
    return shared[int(np.argmax(w))], partners, cond


def _residual_sigma(r, channels, traces, old):
    """Per-trace, per-channel noise levels from the weighted residuals (ML estimate)."""
    out, i = [], 0
    for t, chs, sig in zip(traces, channels, old, strict=True):
        s = {}
        for ch in chs:
            rk = r[i : i + t.n] * sig[ch]
            with np.errstate(over="ignore", invalid="ignore"):
                s[ch] = max(float(np.sqrt(np.mean(rk * rk))), noise_floor(t[ch]))
            i += t.n
        out.append(s)
    return out


def _is(result, item) -> bool:
    """Whether a solver result code is ``item`` (compared by meaning: the enumeration's
    items do not compare equal across optimistix's and lineax's result classes)."""
    return optx.RESULTS[result] == optx.RESULTS[item]


#: A bell exponent below this is the degenerate flat bell (force stuck near F_rt/2).
FLAT_BELL_B = 0.5
#: A channel whose residual RMS exceeds this many times its sensor noise is a misfit.
MISFIT_RATIO = 3.0


def _judge(setup: _Setup, params, trace_metrics, pooled) -> tuple[bool, list[str]]:
    """Judge the fit against what this tool states as acceptable (see ``FitResult``)."""
    notes: list[str] = []
    acceptable = True
    if setup.stage in ("force", "chain") and "b" in setup.free:
        b = float(params[0].b)
        if b < FLAT_BELL_B:
            acceptable = False
            notes.append(
                f"the fitted bell is flat (b = {b:.3g} < {FLAT_BELL_B}): the force is held "
                "near F_rt/2 whatever the displacement, a degenerate fit, not the rig; "
                "check that the force channel rises with x_m"
            )
    for ch in ("force_N", "torque_Nm"):
        pe = (pooled.get(ch) or {}).get("percent_error")
        if pe is not None and pe > SEED_ACCEPTANCE_PCT:
            acceptable = False
            notes.append(
                f"{ch}: percent error {pe:.1f} % is outside the seed paper's acceptance "
                f"({SEED_ACCEPTANCE_PCT:g} %): the fitted model does not reproduce this trace"
            )
    for t, nz, tm, p in zip(setup.traces, setup.noise, trace_metrics, params, strict=True):
        if setup.stage in ("motor", "chain"):
            notes += _input_noise_note(t, p, tm, nz)
        for ch, m in tm.items():
            if m["rmse"] is None:
                acceptable = False
                notes.append(f"{t.name}: the simulated {ch} is not finite (the model diverged)")
                continue
            floor = max(nz.get(ch, 0.0), noise_floor(t[ch]))
            ratio = m["rmse"] / floor
            if ratio > MISFIT_RATIO:
                notes.append(
                    f"{t.name}: {ch} misses its noise floor: residual RMS {m['rmse']:.3g} is "
                    f"{ratio:.1f}x the sensor noise ({floor:.3g}); the model leaves "
                    "something out here (ewb-ident diagnose locates it)"
                )
    return acceptable, notes


#: A drift from the logged voltage's noise this large against the angle's excess misfit
#: is named as a possible cause of the misfit.
INPUT_NOISE_SHARE = 0.5


def _input_noise_note(trace: Trace, p: EWBParams, tm: Mapping, nz: Mapping) -> list[str]:
    """Words when the angle's misfit could be the logged voltage's own noise.

    The model is driven by the logged voltage. If that column carries measurement noise
    the motor never saw (a logger reading the driver's output, not its command), a
    simulation integrates it: the angle drifts as a random walk of step ``K sigma_V dt``
    (``K`` the motor's no-load speed per volt), whose RMS about its mean over ``n``
    samples is ``K sigma_V dt sqrt(n / 6)``. When that explains at least
    :data:`INPUT_NOISE_SHARE` of the angle's excess over its noise, the fit says so: the
    misfit may be the logger's, not missing physics.
    """
    m = tm.get("theta_deg")
    if not (trace.has("voltage_V") and m and m["rmse"] is not None):
        return []
    floor = max(nz.get("theta_deg", 0.0), noise_floor(trace["theta_deg"]))
    if m["rmse"] < 2.0 * floor:
        return []
    excess = float(np.sqrt(m["rmse"] ** 2 - floor**2))
    sigma_v = noise_sigma(trace["voltage_V"])
    gain_deg = abs(motor_combinations(p)["motor_gain_rad_per_V_s"]) * 180.0 / np.pi
    drift = gain_deg * sigma_v * trace.dt * np.sqrt(trace.n / 6.0)
    if not drift >= INPUT_NOISE_SHARE * excess:
        return []
    return [
        f"{trace.name}: the logged voltage carries white noise of about {sigma_v:.3g} V; if "
        f"that is the logger's and not the driver's, a simulation from it drifts by about "
        f"{drift:.2g} deg over the trace, which would account for the angle's misfit "
        f"({m['rmse']:.2g} deg against its noise {floor:.2g} deg): the mismatch may be the "
        "input's noise, not missing physics. A teacher-forced stage fit (--stage force) "
        "does not integrate the voltage and checks a, b, c"
    ]


def _message(results, r, max_steps) -> str:
    if not np.all(np.isfinite(r)):
        return "the model produced non-finite values at the solution"
    for res in results:
        if _is(res, optx.RESULTS.nonlinear_max_steps_reached):
            return f"step limit ({max_steps}) reached before the tolerances were met"
        if not _is(res, optx.RESULTS.successful):
            return str(optx.RESULTS[res])
    return "unknown failure"
