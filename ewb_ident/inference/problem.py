"""The least-squares problem of a stage or the whole chain: which channels and
parameters a stage has, the residual function of every least-squares fit (an equinox
module, :class:`Problem`, with or without mechanisms), and the solver call."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.metrics import (
    noise_floor,
    noise_sigma,
)
from ewb_ident.data.stages import CHANNELS, STAGE_COLUMNS, STAGE_PARAMS, STAGES
from ewb_ident.data.trace import InputError, Trace, TraceError
from ewb_ident.inference.initial import motor_lag
from ewb_ident.inference.residuals import (
    FORCED_CHANNEL,
    carried_noise,
    input_noise,
    program_data,
)
from ewb_ident.model.integrate import heun_amplification
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, EWBParams
from ewb_ident.model.predict import predict
from ewb_ident.runtime.programs import on_device

Stage = Literal["motor", "gap", "force", "torque", "chain"]

#: Parameters fitted per trace unless the user says otherwise: the start angle is a
#: property of each recording, not of the rig.
DEFAULT_PER_TRACE: tuple[str, ...] = ("theta0_deg",)


class FitError(InputError):
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


class Problem(eqx.Module):
    """Weighted residuals of one least-squares fit as a function of the unconstrained
    vector ``u``: the seed model's stage and chain fits, and the fits with catalog
    mechanisms or learned terms (``specs``; empty for the seed model).

    ``u`` holds the ``shared`` parameters, then the ``per_trace`` ones trace by trace,
    then each term's parameters as it declares them. All configuration is static
    (hashable), so solving the same problem on new data of the same shapes reuses the
    compiled code.

    Two layouts of data are read: :meth:`predict` and ``__call__`` the fit data of
    several traces (:meth:`Setup.data`: ``traces``, each with its measured columns, ``dt``,
    ``r_eff_m``, ``theta0_deg`` and ``sigma``, and ``fixed``); :meth:`predict_trace` one
    trace's data as :func:`ewb_ident.model.predict.predict` reads it, with ``fixed``
    (:func:`ewb_ident.inference.augmented.make_data`, padded, per-sample weights).
    """

    stages: tuple[str, ...] = eqx.field(static=True)
    shared: tuple[str, ...] = eqx.field(static=True)
    per_trace: tuple[str, ...] = eqx.field(static=True)
    channels: tuple[tuple[str, ...], ...] = eqx.field(static=True)
    n_sub: tuple[int, ...] = eqx.field(static=True)
    method: str = eqx.field(static=True, default="exponential")
    specs: tuple[tuple[type, tuple], ...] = eqx.field(static=True, default=())

    def templates(self) -> list:
        """The terms (mechanism instances at their class's values), in ``u``'s order."""
        return [cls(**dict(cfg)) for cls, cfg in self.specs]

    def values(self, u: jnp.ndarray, base: Mapping, k: int = 0) -> dict[str, jnp.ndarray]:
        """Parameter values (SI) for trace ``k``: fixed ones from ``base``, free from u."""
        out = dict(base)
        for j, name in enumerate(self.shared):
            out[name] = PARAMS[name].to_physical(u[j])
        offset = len(self.shared) + k * len(self.per_trace)
        for j, name in enumerate(self.per_trace):
            out[name] = PARAMS[name].to_physical(u[offset + j])
        return out

    def terms(self, u: jnp.ndarray) -> tuple:
        """The terms with their parameters from ``u``."""
        j = len(self.shared) + len(self.n_sub) * len(self.per_trace)
        out = []
        for tmpl in self.templates():
            infos = tmpl.param_info()
            vals = {info.name: info.to_physical(u[j + i]) for i, info in enumerate(infos)}
            out.append(tmpl.with_values(vals))
            j += len(infos)
        return tuple(out)

    def build(self, u: jnp.ndarray, fixed: Mapping, k: int = 0):
        """Base parameters, start angle and terms of trace ``k`` for the vector ``u``."""
        vals = self.values(u, fixed, k)
        p = EWBParams(**{n: vals[n] for n in MODEL_PARAMS})
        return p, vals["theta0_deg"], self.terms(u)

    def predict_trace(self, u: jnp.ndarray, d: Mapping, k: int = 0) -> dict[str, jnp.ndarray]:
        """The model's channels of trace ``k`` from its data ``d`` (with ``d["fixed"]``)."""
        p, theta0, terms = self.build(u, d["fixed"], k)
        stage = self.stages[0] if len(self.stages) == 1 else self.stages
        return predict(stage, p, theta0, terms, d, self.n_sub[k], self.method)

    def predict(self, u: jnp.ndarray, data: dict) -> list[dict[str, jnp.ndarray]]:
        """The model's prediction of each fitted channel, per trace."""
        preds = []
        for k, tr in enumerate(data["traces"]):
            fixed = dict(data["fixed"]) | {"theta0_deg": tr["theta0_deg"]}
            d = {"meas": tr, "dt": tr["dt"], "r_eff": tr["r_eff_m"], "fixed": fixed}
            preds.append(self.predict_trace(u, d, k))
        return preds

    def sigmas(self, u: jnp.ndarray, data: dict) -> list[dict[str, jnp.ndarray]]:
        """Per trace, the noise level of each fitted channel's residual at ``u``: its
        ``sigma``, and in a teacher-forced stage also its measured input's noise carried
        through the stage at ``u`` (:func:`carried_noise`)."""
        out = []
        forced = self.stages != ("chain",)
        for k, tr in enumerate(data["traces"]):
            carried = {}
            if forced:
                fixed = dict(data["fixed"]) | {"theta0_deg": tr["theta0_deg"]}
                d = {"meas": tr, "dt": tr["dt"], "r_eff": tr["r_eff_m"], "fixed": fixed}
                p, theta0, terms = self.build(u, fixed, k)
                carry = tr.get("carry", {})
                carried = carried_noise(
                    p, theta0, terms, d, carry, self.stages, self.n_sub[k], self.method
                )
            out.append(
                {
                    ch: jnp.sqrt(tr["sigma"][ch] ** 2 + carried[ch] ** 2)
                    if ch in carried
                    else tr["sigma"][ch]
                    for ch in self.channels[k]
                }
            )
        return out

    def __call__(self, u: jnp.ndarray, data: dict) -> jnp.ndarray:
        """Weighted residuals of the fitted channels, trace by trace (layout of :meth:`predict`)."""
        res = []
        sig = self.sigmas(u, data)
        for k, pred in enumerate(self.predict(u, data)):
            tr = data["traces"][k]
            for ch in self.channels[k]:
                res.append((pred[ch] - tr[ch]) / sig[k][ch])
        return jnp.concatenate(res)


# ----------------------------------------------------------------------------- set-up


def trace_data(trace: Trace, stage: str, channels: tuple[str, ...]) -> dict:
    needed = set(channels) | set(stage_inputs(stage)) | {"theta_deg"} & set(trace.channels)
    d: dict[str, Any] = {c: trace[c] for c in needed if trace.has(c)}
    d["dt"] = trace.dt
    d["r_eff_m"] = trace.r_eff_m
    d["theta0_deg"] = float(np.median(trace["theta_deg"][:5])) if trace.has("theta_deg") else 0.0
    if stage in FORCED_CHANNEL:
        d["carry"] = {FORCED_CHANNEL[stage]: input_noise(trace, FORCED_CHANNEL[stage])}
    return on_device(d)


def check_parameter_options(free, per_trace, fixed, start):
    """The Python API's parameter options, checked for type where they enter (``fit``,
    ``sample``): ``free`` and ``per_trace`` sequences of names, ``fixed`` and ``start``
    dicts of names to numbers. Returns them as tuples and dicts (``None`` kept).

    Raises
    ------
    TypeError
        Naming the argument and what to give instead.
    """
    out: list = []
    for arg, names in (("free", free), ("per_trace", per_trace)):
        if names is None:
            out.append(None)
            continue
        if isinstance(names, str):
            split = [n.strip() for n in names.split(",") if n.strip()]
            raise TypeError(
                f"{arg}: give a sequence of parameter names, e.g. {arg}={split!r}, not the"
                f" string {names!r}"
            )
        if isinstance(names, Mapping) or not isinstance(names, Iterable):
            raise TypeError(
                f"{arg}: give a sequence of parameter names, got a {type(names).__name__}"
            )
        names = tuple(names)
        for n in names:
            if not isinstance(n, str):
                raise TypeError(f"{arg}: parameter names are strings, got {n!r}")
        out.append(names)
    for arg, values in (("fixed", fixed), ("start", start)):
        if values is None:
            out.append(None)
            continue
        if not isinstance(values, Mapping):
            raise TypeError(
                f"{arg}: give a dict of parameter names to values in SI units, e.g."
                f" {arg}={{'R': 1.1}}, got a {type(values).__name__}"
            )
        for k, v in values.items():
            if not isinstance(k, str):
                raise TypeError(f"{arg}: parameter names are strings, got {k!r}")
            try:
                if isinstance(v, str | bytes | bool | np.bool_):
                    raise TypeError
                float(v)
            except (TypeError, ValueError):
                raise TypeError(
                    f"{arg}: {k}={v!r} is not a number; give its value in SI units, e.g."
                    f" {arg}={{{k!r}: {PARAMS[k].ref if k in PARAMS else 1.0}}}"
                ) from None
        out.append({k: float(v) for k, v in values.items()})
    return tuple(out)


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


def usable(name: str, value: float) -> bool:
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


# ----------------------------------------------------------------------------- fit


@dataclass(frozen=True)
class Setup:
    """Everything about a fit that is fixed before the solver runs."""

    traces: tuple[Trace, ...]
    stage: str
    free: tuple[str, ...]
    per_trace: tuple[str, ...]
    base: EWBParams
    channels: tuple[tuple[str, ...], ...]
    problem: Problem
    tdata: list[dict]
    noise: tuple[dict[str, float], ...]
    notes: tuple[str, ...]

    def data(self, sigma: Sequence[Mapping[str, float]]) -> dict:
        """The solver's data pytree with the given per-trace, per-channel noise levels."""
        trs = [
            d | {"sigma": on_device({c: float(v) for c, v in s.items()})}
            for d, s in zip(self.tdata, sigma, strict=True)
        ]
        return {
            "traces": trs,
            "fixed": on_device(self.base.as_dict()),
            "program": program_data(self.problem, self.tdata, sigma, self.base.as_dict()),
        }

    def sensor_sigma(self) -> list[dict[str, float]]:
        """Noise levels from the data alone (floored), the first weights."""
        return [
            {ch: max(s, noise_floor(t[ch])) for ch, s in nz.items()}
            for t, nz in zip(self.traces, self.noise, strict=True)
        ]


def build_setup(traces, stage, free, per_trace, fixed, integrator) -> Setup:
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
    problem = Problem(
        stages=(stage,),
        shared=tuple(n for n in free_t if n not in pt),
        per_trace=pt,
        channels=channels,
        n_sub=tuple(integrator.substeps(t.dt, False) for t in traces),
        method=integrator.method,
    )
    return Setup(
        traces=traces,
        stage=stage,
        free=free_t,
        per_trace=pt,
        base=base,
        channels=channels,
        problem=problem,
        tdata=[trace_data(t, stage, ch) for t, ch in zip(traces, channels, strict=True)],
        noise=tuple(
            {ch: noise_sigma(t[ch]) for ch in chs} for t, chs in zip(traces, channels, strict=True)
        ),
        notes=tuple(notes),
    )


def to_u(problem: Problem, values: Mapping[str, float], base: EWBParams, tdata) -> np.ndarray:
    """The unconstrained vector for start ``values`` (SI; ``"name[k]"`` per trace)."""
    defaults = base.as_dict()
    u = [PARAMS[n].to_unconstrained(values.get(n, defaults.get(n))) for n in problem.shared]
    for k, d in enumerate(tdata):
        for n in problem.per_trace:
            v = float(d["theta0_deg"]) if n == "theta0_deg" else defaults[n]
            u.append(PARAMS[n].to_unconstrained(values.get(f"{n}[{k}]", values.get(n, v))))
    return np.array(u, dtype=float)
