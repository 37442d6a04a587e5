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
The solver is Levenberg-Marquardt in NumPy around one compiled program that returns the
residuals and their Jacobian (:func:`ewb_ident.inference.residuals.evaluate`); its status
is always checked. (optimistix's solver, compiled whole, cost 2-3 s of compilation per
stage and free set, more than a whole warm fit; it remains the reference the tests
compare this solver with.)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from ewb_ident.data.metrics import (
    SEED_ACCEPTANCE_PCT,
    channel_metrics,
    noise_floor,
    noise_sigma,
)
from ewb_ident.data.stages import STAGE_COLUMNS, STAGE_OUTPUTS, STAGE_PARAMS, STAGES
from ewb_ident.data.trace import Trace
from ewb_ident.data.validation import check_traces
from ewb_ident.inference.fit_result import FitResult, motor_combinations
from ewb_ident.inference.initial import bell_start, motor_start
from ewb_ident.inference.memory import check_fit_memory
from ewb_ident.inference.null_directions import hold_flank_exponent, hold_null_directions, hold_one
from ewb_ident.inference.problem import (
    FitError,
    Setup,
    Stage,
    build_setup,
    check_parameter_options,
    stage_inputs,
    usable,
)
from ewb_ident.inference.residuals import evaluate
from ewb_ident.inference.solvers import (
    NULL_LIMIT,
    NearOptimum,
    Solution,
    Status,
    SVDDescent,
    levenberg_marquardt,
)
from ewb_ident.inference.uncertainty import (
    identifiability_notes,
    parameter_uncertainty,
    saturation_notes,
)
from ewb_ident.model.integrate import EXPONENTIAL, Integrator
from ewb_ident.model.numerics import numerics
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, EWBParams
from ewb_ident.model.physics import gap


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
    _check_start(start, traces)
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
        res = _fit(
            trs,
            sub,
            names,
            [n for n in per_trace if n in names],
            {k: v for k, v in fixed.items() if k not in names},
            {k: v for k, v in start.items() if k.split("[")[0] in names},
            EXPONENTIAL,
            300,
            1e-8,
        )
        if not np.isfinite(res.cost) or not all(
            usable(n, v) for p in res.params for n, v in p.as_dict().items() if n in names
        ):
            continue  # a stage fit that ran off to a bound: keep the data-driven start
        for k, p in enumerate(res.params):
            vals = p.as_dict() | {"theta0_deg": res.theta0_deg[k]}
            for n in names:
                start[f"{n}[{k}]" if n in per_trace else n] = vals[n]
    return start


def _check_start(start: Mapping[str, float], traces: Sequence[Trace]) -> None:
    """Refuse a start value the data put outside its parameter's bounds (a bell wider
    than a centimetre, a negative resistance): the data, not the model, are then wrong,
    and the message says which columns set that value."""
    for key, value in start.items():
        name = key.split("[")[0]
        info = PARAMS.get(name)
        if info is None or info.transform == "affine":
            continue
        if np.isfinite(value) and info.inside(value):
            continue
        stage = next(s for s, names in STAGE_PARAMS.items() if name in names)
        present = [c for t in traces for c in (*STAGE_COLUMNS[stage], *STAGE_OUTPUTS[stage])
                   if t.has(c)]  # fmt: skip
        columns = " and ".join(dict.fromkeys(present))
        labels = ", ".join(dict.fromkeys(t.label for t in traces))
        raise FitError(
            f"{labels}: the {stage} stage's data ({columns}) put the start value of {name} at"
            f" {value:.4g} {info.unit}, outside its bounds ({info.lower:g} < {name} <"
            f" {info.upper:g} {info.unit}): these columns do not look like an EWB rig's;"
            " check their units (a mapping's unit, or one --no-unit-check let through) and"
            " that time runs forward"
        )


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


@numerics
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
    tol: float = 1e-8,
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
        Solver step limit per solve (for each of its two dampings: uniform, then
        Marquardt's if the first reaches it).
    tol
        Convergence: the optimum lies within ``sqrt(tol)`` standard errors of the
        solution, in the metric of the weighted Jacobian (the Gauss-Newton step's
        predicted decrease of the weighted cost is below ``tol`` times the residual
        variance; see :class:`~ewb_ident.inference.solvers.NearOptimum`).

    Returns
    -------
    FitResult
        Never raises for a fit that fails to converge: ``converged`` is False and
        ``message`` and ``warnings`` say why.

    Raises
    ------
    FitError
        Unknown stage or parameter; start values the data put outside their bounds;
        traces longer than the machine's memory can fit (its estimate).
    TraceError
        A trace that fails :func:`~ewb_ident.data.validation.check_traces` (the
        command line's checks), or lacks a column the stage needs.
    TypeError
        ``traces`` not traces (a path: read it first), ``free`` or ``per_trace`` a
        string, ``fixed`` or ``start`` values that are not numbers.
    """
    traces = check_traces(traces, stages=(stage,) if stage in STAGES else None)
    free, per_trace, fixed, start = check_parameter_options(free, per_trace, fixed, start)
    check_fit_memory(traces, stage)
    return _fit(traces, stage, free, per_trace, fixed, start, integrator, max_steps, tol)


@numerics
def fit_checked_traces(
    trace: Trace, *, stage: Stage, start: dict[str, float] | None = None
) -> FitResult:
    """:func:`fit` of one stage, with its defaults, of a trace its caller has checked
    (the diagnosis's baseline fits of every stage the trace's columns serve, whether or
    not its force clamps), from ``start`` if given (of :func:`start_of_checked_trace`)."""
    return _fit((trace,), stage, None, None, None, None, EXPONENTIAL, 300, 1e-8, start)


def start_of_checked_trace(trace: Trace, *, stage: Stage) -> dict[str, float]:
    """The start values :func:`fit_checked_traces` would begin from, or at once the
    :class:`FitError` it would raise for data that put one outside its bounds (x logged
    in mm let through by --no-unit-check, a channel reversed in time)."""
    setup = build_setup((trace,), stage, None, None, None, EXPONENTIAL)
    return _start_values(setup.traces, stage, setup.free, setup.per_trace, setup.base)


def _fit(
    traces, stage, free, per_trace, fixed, start, integrator, max_steps, tol, computed=None
) -> FitResult:
    """:func:`fit` of checked traces and options (the sub-fits of its start call this);
    ``computed``: the data's start values, if already computed."""
    setup = build_setup(traces, stage, free, per_trace, fixed, integrator)
    st = computed
    if st is None:
        st = _start_values(setup.traces, stage, setup.free, setup.per_trace, setup.base)
    st = {k: v for k, v in st.items() if usable(k.split("[")[0], v)}
    st |= dict(start or {})
    # No null direction reaches the solver: at the start, a combination of free
    # parameters the data cannot see (scaled Jacobian numerically singular) has its
    # dominant parameter held at its start value, and the fit says so. A solve that did
    # not converge is checked the same way where it stopped (a valley floor the start
    # did not show, e.g. a current channel too small against its noise to separate R,
    # kb and M), and a converged one for the directions its convergence test leaves out
    # (condition number above NULL_LIMIT); the parameter is then held at its start value
    # and the fit solved again from the start. A solve that did not converge on a trace
    # whose piston never passes c has b held at the seed value.
    held: dict[str, float] = {}
    held_notes: list[str] = []
    while True:
        setup, u0, data, sigma = hold_null_directions(
            setup, st, per_trace, dict(fixed or {}), held, held_notes, integrator
        )
        sol, sigma, data, results, steps = _solve_twice(setup, u0, data, sigma, tol, max_steps)
        if len(setup.problem.shared) < 2:
            break
        # Every solve counts, as in ``_finish``: a first solve that ran out of steps in a
        # flat valley can be followed by a re-weighted one that stops at a point the
        # first did not reach.
        converged = all(s.converged for s in results)
        # A converged solve controlled every direction its convergence test could see;
        # the rest (condition number above 1e6) are held like any null direction.
        limit = NULL_LIMIT if converged else None
        if hold_one(setup, sol.u, data, st, held, held_notes, "where the solver stopped", limit):
            continue
        if converged or not hold_flank_exponent(setup, sol.u, data, held, held_notes):
            break
    if held_notes:
        setup = dataclasses.replace(setup, notes=setup.notes + tuple(held_notes))
    return _finish(setup, sol.u, data, sigma, results, steps, max_steps)


def _solve_twice(setup, u0, data, sigma, tol, max_steps):
    """Solve, re-estimate the noise levels from the residuals, solve again; a solve that
    ran out of steps while still descending gets one more allowance."""
    problem = setup.problem
    sol = _solve(problem, u0, data, tol, max_steps)
    results, steps = [sol], sol.steps
    r = np.asarray(evaluate(problem, sol.u, data, predictions=False)[0])
    if np.all(np.isfinite(r)):
        sigma = _residual_sigma(r, setup.channels, setup.traces, sigma)
        data = setup.data(sigma)
        sol = _solve(problem, sol.u, data, tol, max_steps)
        results.append(sol)
        steps += sol.steps
        if sol.status is Status.MAX_STEPS:
            sol = _solve(problem, sol.u, data, tol, max_steps)
            results[-1] = sol
            steps += sol.steps
    return sol, sigma, data, results, steps


def _solve(problem, u0, data, tol: float, max_steps: int) -> Solution:
    """Levenberg-Marquardt on the compiled residuals and Jacobian of :func:`evaluate`,
    the step from their SVD, converged within ``sqrt(tol)`` standard errors of the
    optimum: identity damping in ``u``, and if that reaches the step limit, Marquardt's
    damping from the same start (each crawls where the other does not; see
    :class:`~ewb_ident.inference.solvers.SVDDescent`). The converged one, else the lower
    cost."""

    def fun_and_jac(u):
        r, _, J = evaluate(problem, u, data, predictions=False)
        return r, J

    u0 = np.asarray(u0)
    stop = NearOptimum(tol)
    sol = levenberg_marquardt(fun_and_jac, u0, descent=SVDDescent(), stop=stop, max_steps=max_steps)
    if sol.status is not Status.MAX_STEPS:
        return sol
    alt = levenberg_marquardt(
        fun_and_jac, u0, descent=SVDDescent(marquardt=True), stop=stop, max_steps=max_steps
    )
    steps = sol.steps + alt.steps
    if alt.converged or (alt.cost is not None and alt.cost < sol.cost):
        return dataclasses.replace(alt, steps=steps)
    return dataclasses.replace(sol, steps=steps)


def _finish(setup: Setup, u, data, sigma, results, steps, max_steps) -> FitResult:
    """Uncertainty, predictions, metrics and notes at the solution ``u``."""
    problem, traces, channels = setup.problem, setup.traces, setup.channels
    r, predicted, J = evaluate(problem, u, data)
    r, J, u = np.asarray(r), np.asarray(J), np.asarray(u)
    finite = bool(np.all(np.isfinite(r)) and np.all(np.isfinite(J)))
    ok = all(s.converged for s in results) and bool(np.all(np.isfinite(r)))
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
    segments = [
        (len(chs), int(np.asarray(d[chs[0]]).shape[0]))
        for d, chs in zip(data["traces"], problem.channels, strict=True)
        if chs
    ]
    unc = parameter_uncertainty(J, r, u, infos, segments)
    stderr = dict(zip(names, unc.stderr, strict=True))
    if finite:
        notes += identifiability_notes(names, unc, stderr)
    else:
        notes.append(
            "the model's prediction or its Jacobian is not finite where the solver stopped: "
            "no standard errors"
        )

    preds = [
        {k: np.asarray(v) for k, v in p.items() if k in chs}
        for p, chs in zip(predicted, channels, strict=True)
    ]
    params, theta0 = [], []
    for k, d in enumerate(setup.tdata):
        vals = problem.values(u, setup.base.as_dict() | {"theta0_deg": float(d["theta0_deg"])}, k)
        params.append(EWBParams(**{n: float(vals[n]) for n in MODEL_PARAMS}))
        theta0.append(float(vals["theta0_deg"]))
    if finite and setup.stage in ("force", "chain") and any(n in setup.free for n in "abc"):
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
    acceptable, judged, misfits = _judge(setup, params, trace_metrics, pooled)
    notes += judged
    return FitResult(
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
        rss=float(np.sum(r * r)) if np.all(np.isfinite(r)) else float("inf"),
        n=int(r.size),
        warnings=tuple(notes),
        misfits=tuple(misfits),
        predictions=tuple(preds),
        residuals=tuple({c: t[c] - p[c] for c in p} for t, p in zip(traces, preds, strict=True)),
        u=u,
        problem=problem,
        data={k: v for k, v in data.items() if k != "program"},
        stderr_white=dict(zip(names, unc.stderr_white, strict=True)),
    )


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


#: A bell exponent below this is the degenerate flat bell (force stuck near F_rt/2).
FLAT_BELL_B = 0.5
#: A channel whose residual RMS exceeds this many times its sensor noise is a misfit.
MISFIT_RATIO = 3.0


def _judge(setup: Setup, params, trace_metrics, pooled) -> tuple[bool, list[str], list[str]]:
    """Judge the fit against what this tool states as acceptable (see ``FitResult``):
    whether it is, the notes on it, and those of the notes that name a channel missing
    its noise floor (a warning, not a rejection)."""
    notes: list[str] = []
    misfits: list[str] = []
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
                misfits.append(
                    f"{t.name}: {ch} misses its noise floor: residual RMS {m['rmse']:.3g} is "
                    f"{ratio:.1f}x the sensor noise ({floor:.3g}); the model leaves "
                    "something out here (ewb-ident diagnose locates it)"
                )
                notes.append(misfits[-1])
    return acceptable, notes, misfits


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


def _message(results: list[Solution], r, max_steps) -> str:
    if not np.all(np.isfinite(r)):
        return "the model produced non-finite values at the solution"
    for sol in results:
        if sol.status is Status.MAX_STEPS:
            return f"step limit ({max_steps}) reached before the tolerances were met"
        if sol.status is not Status.SUCCESSFUL:
            return sol.detail
    return "unknown failure"
