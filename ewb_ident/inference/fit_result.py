"""What a least-squares fit returns (:class:`FitResult`) and the motor combinations a
trace without current identifies."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ewb_ident.data.metrics import (
    SEED_PERCENT_ERROR,
)
from ewb_ident.data.outputs import null_nonfinite
from ewb_ident.inference.problem import Problem
from ewb_ident.mechanisms.base import AbstractMechanism
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, EWBParams

# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class FitResult:
    """The outcome of a least-squares fit (immutable): of the seed model (a stage or
    the chain, :func:`ewb_ident.inference.least_squares.fit`) or with catalog mechanisms
    or learned terms (:func:`ewb_ident.inference.augmented.fit_mechanisms`, the
    diagnosis's fits; one trace).

    Attributes
    ----------
    free, per_trace
        Names of the varied base parameters; ``per_trace`` ones were fitted per trace.
    params
        Fitted parameters for each trace (SI units).
    theta0_deg
        Start angle of each trace, degrees.
    stderr
        Standard error of each free shared parameter (SI units); for per-trace ones
        ``"name[k]"`` keys, for a term's ``"variant.param"``. ``None`` where the
        Jacobian gives none. The larger of the white-residual and the
        serial-correlation-robust one (:mod:`ewb_ident.inference.uncertainty`).
    corr
        Correlation matrix of the free coordinates, ordered as ``corr_names``.
    condition_number
        Condition number of the column-scaled Jacobian at the optimum.
    rss
        Sum of squared weighted residuals at the optimum (``cost`` is half of it).
    n
        Number of residuals (samples times channels) that count.
    converged
        Whether the solver reported success on every solve.
    message
        The solver's result, in words.
    n_steps
        Solver steps, summed over the solves.
    predictions
        The model's prediction of every fitted channel, per trace (NumPy arrays); a fit
        with terms gives every channel its stages predict.
    residuals
        Measured minus predicted, per trace and fitted channel (NumPy arrays).
    u
        The solution in unconstrained coordinates (shared parameters, then the
        per-trace ones trace by trace, then the terms'), as ``corr_names`` orders them.
    problem, data
        The residual function (:class:`~ewb_ident.inference.problem.Problem`) and, for a
        seed fit, its data (measured channels, weights ``sigma``, fixed values):
        ``problem(u, data)`` gives the weighted residuals and ``problem.predict(u, data)``
        the model's channels. The posterior starts here. A fit with terms keeps no
        data (its caller holds them; ``problem.predict_trace`` reads them).
    stderr_white
        The standard errors if the residuals were white (``s^2 (J^T J)^-1``), keyed as
        ``stderr``: never larger than ``stderr``.
    mechanisms
        The fitted terms (catalog mechanisms or learned terms, plain float values);
        empty for the seed model.
    channel_rss
        ``rss`` split by channel (fits with terms; empty for seed fits).

    The rest describe a seed fit for its report (empty, or ``acceptable`` True, for a
    fit with terms, which the diagnosis judges by its evidence):

    trace_names
        Names of the fitted traces, in order.
    metrics, trace_metrics
        Pooled and per-trace metrics per channel (see :mod:`ewb_ident.data.metrics`).
    noise, sigma
        Per trace and channel: the sensor-noise estimate from the data, and the noise
        level the final weights used (from the residuals), in the channel's unit.
    r_eff
        Per trace, the pad radius used (m) and where it came from (``--r-eff``,
        ``sidecar`` or ``default``).
    acceptable
        Whether the fit passes the acceptance this tool states: a bell that is not
        flat (``b`` >= :data:`FLAT_BELL_B`) and force and torque percent errors within
        the seed paper's 10 % (:data:`ewb_ident.data.metrics.SEED_ACCEPTANCE_PCT`). A channel
        missing its noise floor by more than :data:`MISFIT_RATIO` is a warning, not a
        rejection (the diagnosis explains it).
    warnings
        Plain-language warnings (identifiability, solver), for the user to read.
    misfits
        Those of ``warnings`` that name a channel missing its noise floor by more than
        :data:`MISFIT_RATIO` (physics the model leaves out, or a logger's noise): a
        posterior from this fit repeats them, as its intervals are then those of a model
        that does not reproduce the trace.
    """

    free: tuple[str, ...]
    per_trace: tuple[str, ...]
    params: tuple[EWBParams, ...]
    theta0_deg: tuple[float, ...]
    stderr: dict[str, float | None]
    corr: np.ndarray
    corr_names: tuple[str, ...]
    condition_number: float
    rss: float
    n: int
    converged: bool
    message: str
    n_steps: int
    predictions: tuple[dict[str, np.ndarray], ...] = field(repr=False)
    residuals: tuple[dict[str, np.ndarray], ...] = field(repr=False)
    u: np.ndarray = field(repr=False)
    problem: Problem = field(repr=False)
    stderr_white: dict[str, float | None] = field(default_factory=dict, repr=False)
    mechanisms: tuple[AbstractMechanism, ...] = ()
    channel_rss: dict[str, float] = field(default_factory=dict)
    trace_names: tuple[str, ...] = ()
    metrics: dict[str, dict[str, float | None]] = field(default_factory=dict)
    trace_metrics: tuple[dict[str, dict[str, float | None]], ...] = ()
    noise: tuple[dict[str, float], ...] = ()
    sigma: tuple[dict[str, float], ...] = ()
    acceptable: bool = True
    r_eff: tuple[tuple[float, str], ...] = ()
    warnings: tuple[str, ...] = ()
    data: dict = field(default_factory=dict, repr=False)
    misfits: tuple[str, ...] = field(default=(), repr=False)

    @property
    def stages(self) -> tuple[str, ...]:
        """The fitted teacher-forced stages, or ``("chain",)``."""
        return self.problem.stages

    @property
    def stage(self) -> str:
        """What was fitted: ``"chain"``, a stage, or stages joined by ``+``."""
        return "+".join(self.problem.stages)

    @property
    def k(self) -> int:
        """Number of fitted parameters."""
        return int(np.size(self.u))

    @property
    def cost(self) -> float:
        """Half the weighted residual sum of squares (``inf`` if not finite)."""
        return 0.5 * self.rss if np.isfinite(self.rss) else float("inf")

    def mechanism_stderr(self, m: AbstractMechanism) -> dict[str, float | None]:
        """White-residual standard errors of one fitted mechanism's parameters: what the
        diagnosis's tests (a finding's parameter resolved from no effect) were set on,
        and what its words quote; the reported tables use :attr:`stderr`."""
        return {i.name: self.stderr_white.get(f"{m.variant}.{i.name}") for i in m.param_info()}

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

        def keyed(errors: dict[str, float | None]) -> dict[str, float | None]:
            out = {n: errors.get(n) for n in values}
            if len(self.params) == 1:
                out |= {n: errors.get(f"{n}[0]") for n in self.per_trace if n in values}
            return out

        stderr = keyed(self.stderr)
        doc = {
            "params": values,
            "stderr": stderr,
            "stderr_white": keyed(self.stderr_white),
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
            "condition_number": finite_or_none(self.condition_number),
            "solver": {"message": self.message, "steps": self.n_steps, "cost": self.cost},
            "derived": motor_combinations(self.params[0]),
            "r_eff_m": {
                t["trace"]: {"value": v, "source": src}
                for t, (v, src) in zip(per_trace, self.r_eff, strict=True)
            },
            "seed_percent_error": SEED_PERCENT_ERROR,
            "warnings": list(self.warnings),
            "stderr_note": (
                "the larger of the white-residual standard error (stderr_white) and the "
                "serial-correlation-robust one; null: parameter fixed, or not identified by "
                "the data (singular Jacobian), or the model diverged (see warnings)"
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


def finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
