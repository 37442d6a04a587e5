"""Least-squares fits of the chain, or of teacher-forced stages, with mechanisms added.

The residual of every fitted channel is divided by a per-sample noise level given by the
caller (the sensor noise floor, with the input noise a teacher-forced stage propagates),
so that fits of the same stages with and without a mechanism have comparable costs.
Parameters are optimised in unconstrained O(1) coordinates: the base parameters as
declared in :data:`ewb_ident.model.params.PARAMS`, each mechanism's as it declares them.
The solver is Levenberg-Marquardt (:func:`ewb_ident.inference.solvers.levenberg_marquardt`,
the step from the normal equations, converged on the relative decrease of the cost) from
the best of a few starting points.

Arrays are padded to a multiple of :data:`ewb_ident.runtime.programs.PAD` samples (padding
weighted zero) so that traces of similar length share compiled code.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.stages import CHANNELS, STAGE_OUTPUTS
from ewb_ident.data.trace import Trace
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.problem import Problem
from ewb_ident.inference.residuals import (
    FORCED_CHANNEL,
    FORCED_INPUT,
    PROGRAM_COLUMNS,
    Z_NAMES,
    carried_noise,
    effective_weight,
    fit_program,
)
from ewb_ident.inference.solvers import (
    NormalEquationsDescent,
    RelativeDecrease,
    Solution,
    Status,
    levenberg_marquardt,
)
from ewb_ident.inference.uncertainty import parameter_uncertainty
from ewb_ident.mechanisms.base import AbstractMechanism
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, EWBParams
from ewb_ident.model.predict import n_substeps
from ewb_ident.runtime.programs import FAST_COMPILE, on_device, pad_to, padded_length, program
from ewb_ident.runtime.threads import parallel_map

#: Most starting points tried per fit.
MAX_STARTS = 24
#: A fit has converged when its last steps lowered the cost (a chi-square: residuals in
#: units of their noise) by less than this together, with the optimum of its linearised
#: model within one standard error (:class:`ewb_ident.inference.solvers.RelativeDecrease`).
STALL = 0.1
#: Columns a fit may read: the program's (the voltage and the channels of
#: :data:`ewb_ident.data.stages.CHANNELS`) and the disc speed that speed-dependent
#: mechanisms read.
COLUMNS = (*PROGRAM_COLUMNS, "disc_speed_rad_s")


def slow_smooth(y: np.ndarray, sigma: float, width: int = 5, fast: int = 1) -> np.ndarray:
    """``y`` averaged over ``width`` samples where it moves by less than its noise per
    sample, and left as it is where it moves faster.

    A play operator driven by a noisy signal follows the noise's running extreme while
    the signal stands still (the extreme of n noise samples grows like
    ``sigma sqrt(2 ln n)``); averaging there removes most of that drift. Where the
    signal moves fast the noise cannot push the play, and averaging would bend the
    signal, so the reading averaged over only ``fast`` samples is kept.
    """
    y = np.asarray(y, dtype=float)
    yf = smooth(y, fast)
    if sigma <= 0 or y.size < width:
        return yf
    ys = smooth(y, width)
    step = np.abs(np.gradient(smooth(y, 2 * width + 1)))
    a = np.exp(-((step / sigma) ** 2))
    return a * ys + (1.0 - a) * yf


from ewb_ident.data.metrics import noise_sigma, smooth  # noqa: E402


def make_data(
    trace: Trace,
    sigma: Mapping[str, np.ndarray | float],
    fixed: Mapping[str, float],
    *,
    x_play_m: float = 0.0,
    omega_ref: float = 1.0,
    theta_noise: float | None = None,
    x_smooth: int = 1,
    x_model: np.ndarray | None = None,
    carry: Mapping[str, float] | None = None,
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
        Half width of the play filter on the measured displacement that drives a
        hysteresis state (force stage, teacher-forced), m.
    x_smooth
        Width (samples) of the moving average applied to that displacement first.
    x_model
        A noise-free displacement history (m) that drives a hysteresis state instead
        of the measured one (e.g. the gap polynomial of the motor model's angle, which
        follows the logged voltage, controller dither included).
    omega_ref
        Reference disc speed of ``friction_speed``, rad/s.
    theta_noise
        Noise of the measured angle, degrees: the angle that drives a play operator
        (``backlash``, teacher-forced) is averaged where it stands still
        (:func:`slow_smooth`).
    carry
        Per channel a teacher-forced stage predicts, its measured input's noise level
        (:func:`~ewb_ident.inference.residuals.input_noise`): a teacher-forced fit weighs
        that channel by its ``sigma`` and the input's noise carried through the stage
        at the fitted values (:func:`~ewb_ident.inference.residuals.carried_noise`).
        Default none: ``sigma`` alone.
    """
    n = trace.n
    n_pad = padded_length(n)
    mask = np.zeros(n_pad)
    mask[:n] = 1.0
    meas = {c: pad_to(trace[c], n_pad) for c in COLUMNS if trace.has(c)}
    drive = {}
    if x_model is not None:
        drive["x_model"] = pad_to(np.asarray(x_model, dtype=float), n_pad)
    elif trace.has("x_m") and x_play_m > 0:
        x_noise = noise_sigma(trace["x_m"])
        x_drive = slow_smooth(trace["x_m"], x_noise, width=5 * x_smooth, fast=x_smooth)
        drive["x_m"] = pad_to(x_drive, n_pad)
    if trace.has("theta_deg"):
        s_th = float(theta_noise) if theta_noise is not None else 0.0
        drive["theta_deg"] = pad_to(slow_smooth(trace["theta_deg"], s_th), n_pad)
    w = {}
    for ch, s in sigma.items():
        s = np.broadcast_to(np.asarray(s, dtype=float), (n,))
        w[ch] = pad_to(1.0 / s, n_pad) * mask
    return on_device(
        {
            "meas": meas,
            "drive": drive,
            "w": w,
            "carry": {c: float((carry or {}).get(c, 0.0)) for c in FORCED_INPUT},
            "fixed": {k: float(v) for k, v in fixed.items()},
            "dt": trace.dt,
            "t": np.arange(n_pad) * trace.dt,
            "r_eff": trace.r_eff_m,
            "omega_ref": float(omega_ref),
            "x_play": float(x_play_m),
            # An array, not a Python int: filter_jit would make a plain int static and
            # recompile for every trace length.
            "n": np.asarray(n),
        }
    )


def residuals(problem: Problem, u, data):
    """Weighted residuals at ``u``: from the compiled residuals-and-Jacobian program (a
    program of the residuals alone would be a second compilation per mechanism set, a
    quarter of a diagnosis's compile time, for a saving of well under a millisecond
    per call)."""
    return residuals_and_jacobian(problem, u, data)[0]


def residuals_and_jacobian(problem: Problem, u, data):
    """Residuals, their Jacobian (forward mode) and the predictions, in one pass.

    Without mechanisms the problem is the seed model's, and the seed fits' one program
    (:func:`ewb_ident.inference.residuals.fit_program`, the stages' inputs chosen by
    data) evaluates it: a diagnosis fits the seed model on seven combinations of stages,
    each of which would otherwise be compiled on its own."""
    if not problem.specs:
        return _seed_residuals_and_jacobian(problem, u, data)
    return _mechanism_program(problem, data, u)


def residuals_and_jacobian_at(problem: Problem, data) -> Callable:
    """``u -> residuals_and_jacobian(problem, u, data)`` for the many ``u`` of one fit
    (``u`` a float array). With mechanisms, the program is bound to ``problem`` and
    ``data`` (:func:`~ewb_ident.runtime.programs.program`'s ``bind``) and looked up once,
    not at each of the solver's steps (some 0.25 ms each, 1,700 steps in a diagnosis);
    the same program, so the same numbers."""
    if not problem.specs:
        return lambda u: residuals_and_jacobian(problem, u, data)
    return _mechanism_program.bind(problem, data)


def _seed_residuals_and_jacobian(problem: Problem, u, data):
    u = np.asarray(u, float)
    cols = [Z_NAMES.index(n) for n in problem.shared]
    z = np.zeros(len(Z_NAMES))
    z[cols] = u
    meas = data["meas"]
    n_pad = int(np.asarray(next(iter(meas.values()))).shape[0])
    zeros = np.zeros(n_pad)
    forced = () if problem.stages == ("chain",) else problem.stages
    pdata = on_device(
        {
            "meas": {c: meas.get(c, zeros) for c in PROGRAM_COLUMNS},
            "w": {c: data["w"][c] if c in problem.channels[0] else zeros for c in CHANNELS},
            "forced": {c: float(s in forced) for s, c in FORCED_CHANNEL.items()},
            "carry": {c: data["carry"][c] for c in FORCED_INPUT},
            "dt": data["dt"],
            "r_eff": data["r_eff"],
            "fixed": np.array([float(data["fixed"][n]) for n in Z_NAMES]),
            "free": np.array([float(n in problem.shared) for n in Z_NAMES]),
        }
    )
    ((r, J, pred),) = fit_program(problem.n_sub, problem.method, z[None, :], [pdata])
    rows = [CHANNELS.index(ch) for ch in problem.channels[0]]
    r, J = np.asarray(r)[rows], np.asarray(J)[rows][..., cols]
    outputs = CHANNELS if problem.stages == ("chain",) else [
        ch for s in problem.stages for ch in STAGE_OUTPUTS[s]
    ]  # fmt: skip
    return r.reshape(-1), J.reshape(-1, len(cols)), {ch: pred[ch] for ch in outputs}


def weights(problem: Problem, u, data) -> dict[str, Any]:
    """The weight of each fitted channel's residual at ``u``: ``data["w"]``, lowered in
    a teacher-forced fit where the stage carries its measured input's noise
    (:func:`~ewb_ident.inference.residuals.carried_noise` at ``u``)."""
    w = data["w"]
    if problem.stages == ("chain",):
        return {ch: w[ch] for ch in problem.channels[0]}
    p, theta0, terms = problem.build(u, data["fixed"])
    carried = carried_noise(
        p, theta0, terms, data, data["carry"], problem.stages, problem.n_sub[0], problem.method
    )
    return {ch: effective_weight(w[ch], carried.get(ch)) for ch in problem.channels[0]}


@program(options=FAST_COMPILE)
def _mechanism_program(problem: Problem, data, u):
    def f(v):
        pred = problem.predict_trace(v, data)
        wt = weights(problem, v, data)
        r = jnp.concatenate([(pred[ch] - data["meas"][ch]) * wt[ch] for ch in problem.channels[0]])
        return r, (r, pred)

    J, (r, pred) = jax.jacfwd(f, has_aux=True)(u)
    return r, J, pred


def jacobian(problem: Problem, u, data):
    return residuals_and_jacobian(problem, u, data)[1]


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
    alt_starts: Sequence[Mapping[str, float]] = (),
    max_steps: int = 200,
    n_best: int = 2,
) -> FitResult:
    """Fit base parameters ``free`` and every mechanism parameter by least squares.

    Parameters
    ----------
    data
        From :func:`make_data` (``fixed`` holds every base value, the start of the free).
    stages
        ``("chain",)`` or teacher-forced stage names.
    free
        Base parameters to vary (names of :data:`ewb_ident.model.params.PARAMS`).
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
    alt_starts
        Other starting values of (some) free base parameters: the solver also runs from
        the best starting points built on each (e.g. nominal motor values, when the
        baseline's have compensated for the missing physics and sit in another valley),
        unless a fit from the best starting points overall has converged to the noise
        (weighted cost at most the number of residuals).
    max_steps
        Solver step limit per start.
    n_best
        Number of the best starting points (over all, and of each alternative) the
        solver runs from.
    """
    stages = tuple(stages)
    mechs = tuple(mechanisms)
    dt = float(data["dt"])
    problem = Problem(
        stages=stages,
        shared=tuple(free),
        per_trace=(),
        channels=(tuple(channels),),
        n_sub=(n_substeps(dt, mechs),),
        specs=tuple((type(m), m.static_config()) for m in mechs),
    )
    base = {k: float(v) for k, v in data["fixed"].items()} | dict(start or {})
    bases = [base] + [base | dict(a) for a in alt_starts]

    # Starting points: the given values of each mechanism, and its own suggestions.
    ctx = dict(ctx or {}) | {"dt": dt}
    options = []
    explore = [True] * len(mechs) if explore is None else list(explore)
    for m, more in zip(mechs, explore, strict=True):
        own = [m.values()] + ([m.values() | s for s in m.starts(ctx)] if more else [])
        options.append(own)
    combos = list(itertools.islice(itertools.product(*options), MAX_STARTS))
    us, group = [], []
    for g, b in enumerate(bases):
        u_base = [clipped_to_u(PARAMS[n], b[n]) for n in problem.shared]
        for combo in combos:
            u = list(u_base)
            for m, vals in zip(mechs, combo, strict=True):
                u += [clipped_to_u(i, vals[i.name]) for i in m.param_info()]
            us.append(u)
            group.append(g)
    us = np.array(us, dtype=float)
    # Each start's residuals and Jacobian: the cost ranks the starts, and the solver's
    # first evaluation from a start is the one made here.
    evaluate = residuals_and_jacobian_at(problem, data)
    screened = {}
    if len(us) > 1:
        evals = parallel_map(evaluate, us)
        screened = dict(enumerate(evals))
        with np.errstate(over="ignore", invalid="ignore"):
            costs = np.array([float(np.sum(np.asarray(screened[i][0]) ** 2)) for i in screened])
    else:
        costs = np.zeros(1)
    costs = np.where(np.isfinite(costs), costs, np.inf)
    ranked = [int(i) for i in np.argsort(costs)]
    # The solver runs from the best starts overall, then from the best of each
    # alternative (``groups``); a start that coincides with one before it runs once.
    group = np.asarray(group)
    first = ranked[: max(1, n_best)]
    groups, seen = [], set()
    for ids in [first] + [
        [i for i in ranked if group[i] == g and i not in first][: max(1, n_best)]
        for g in range(1, len(bases))
    ]:
        groups.append([])
        for i in ids:
            if us[i].tobytes() not in seen:
                seen.add(us[i].tobytes())
                groups[-1].append(i)
    order = [i for ids in groups for i in ids]
    # Residuals that count (nonzero weight): a converged fit with a cost no larger (reduced
    # chi-square at most 1 under the fit's noise weights) explains the data to the noise,
    # and the alternatives' starts, there for a fit caught in another valley, are not run.
    n_res = sum(int(np.count_nonzero(np.asarray(data["w"][ch]))) for ch in problem.channels[0])
    screened = {i: screened[i] for i in order if i in screened}

    def solve(i):
        made = [screened[i]] if i in screened else []

        def fun_and_jac(u):
            return made.pop() if made else evaluate(u)

        return levenberg_marquardt(
            fun_and_jac,
            us[i],
            descent=NormalEquationsDescent(),
            stop=RelativeDecrease(stall=STALL),
            max_steps=max_steps,
        )

    def at_noise() -> bool:
        return best is not None and best.converged and best.cost <= n_res

    # Each group's starts run side by side; their fits are taken in the group's order
    # (the loop's outcome, whatever the threads' timing), and no later start counts once
    # a fit has converged to the noise.
    best = None
    for k, ids in enumerate(groups):
        if k and at_noise():
            break
        for sol in parallel_map(solve, ids):
            if k and at_noise():
                break  # run alongside one whose fit reached the noise: not needed
            if np.isfinite(sol.cost) and (best is None or sol.cost < best.cost):
                best = sol
    if best is None:  # every start failed: keep the best start point
        i = int(order[0])
        best = Solution(us[i], float(costs[i]), Status.FAILED, 0)
    return _result(problem, data, best)


def clipped_to_u(info, value: float) -> float:
    """A start value in ``u``, moved inside the bounds where the transform has none: a
    log parameter is kept at or above ``ref * LOG_FLOOR`` (a fit that drove it to 0 in
    floating point would otherwise start at ``u = -inf``, and one near it where the
    parameter has no slope)."""
    if info.transform == "logit":
        lo, hi = info.lower, info.upper
        value = min(max(value, lo + 1e-6 * (hi - lo)), hi - 1e-6 * (hi - lo))
    if info.transform == "log":
        value = max(value, info.ref * LOG_FLOOR)
    return float(info.to_unconstrained(value))


#: Smallest start of a log parameter, relative to its reference value.
LOG_FLOOR = 1e-12


def _result(problem: Problem, data, best: Solution) -> FitResult:
    """The fit at ``best.u``, from the residuals, Jacobian and predictions there if the
    solver kept them (``best.at``)."""
    u, n = best.u, int(data["n"])
    at = best.at
    if at is None:
        at = residuals_and_jacobian(problem, np.asarray(u, float), data)
    r, J, pred_all = at
    r, J = np.asarray(r), np.asarray(J)
    rss = float(np.sum(r * r))
    channels = problem.channels[0]
    nch = len(channels)
    n_res = n * nch
    chan_rss = {}
    for j, ch in enumerate(channels):
        seg = r[j * r.size // nch : (j + 1) * r.size // nch]
        chan_rss[ch] = float(np.sum(seg * seg))
    u_np = np.asarray(u)
    infos = [PARAMS[n_] for n_ in problem.shared]
    names = list(problem.shared)
    for tmpl in problem.templates():
        for info in tmpl.param_info():
            infos.append(info)
            names.append(f"{tmpl.variant}.{info.name}")
    unc = parameter_uncertainty(J, r, u_np, infos, [(nch, r.size // nch)], n=n_res)
    p, theta0, mechs = problem.build(np.asarray(u, float), data["fixed"])
    pred = {ch: np.asarray(v)[:n] for ch, v in pred_all.items()}
    plain = tuple(m.with_values(m.values()) for m in mechs)
    resid = {ch: np.asarray(data["meas"][ch])[:n] - pred[ch] for ch in channels}
    return FitResult(
        free=problem.shared,
        per_trace=(),
        params=(EWBParams(**{name: float(getattr(p, name)) for name in MODEL_PARAMS}),),
        theta0_deg=(float(theta0),),
        stderr=dict(zip(names, unc.stderr, strict=True)),
        stderr_white=dict(zip(names, unc.stderr_white, strict=True)),
        corr=unc.corr,
        corr_names=tuple(names),
        condition_number=unc.condition_number,
        rss=rss,
        n=n_res,
        converged=best.converged,
        message="successful" if best.converged else best.detail or best.status.name.lower(),
        n_steps=best.steps,
        predictions=(pred,),
        residuals=(resid,),
        u=u_np,
        problem=problem,
        mechanisms=plain,
        channel_rss=chan_rss,
    )
