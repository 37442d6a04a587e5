"""Posterior of the EWB model's parameters: emcee, started from the least-squares fit.

What is sampled
---------------
The free coordinates ``u`` of the least-squares problem(s) (:mod:`ewb_ident.model.params`:
O(1), unconstrained), for the whole chain or for teacher-forced stages (several stages
at once are independent blocks of one log-probability). The log-Jacobian of each
transform is added, so the priors (:mod:`ewb_ident.inference.priors`) are on the physical values.

Likelihood
----------
For every trace and fitted channel the residual ``r = prediction - measurement`` is
Gaussian noise, white or AR(1): ``r[t] = phi r[t-1] + e[t]``, ``e ~ N(0, s^2)``, with the
stationary start ``r[0] ~ N(0, s^2 / (1 - phi^2))``. Each channel of each trace has its
own noise level ``s`` with the scale-invariant prior ``p(s) ~ 1/s``; it is marginalised
analytically, ``p(y | u) ~ Q(u)^(-n/2)`` with ``Q = (1 - phi^2) r[0]^2 + sum (r[t] -
phi r[t-1])^2``, so the sampler does not carry it. For every kept draw it is drawn from
its exact conditional posterior ``s^2 | u, y ~ Inv-Gamma(n/2, Q/2)`` and reported as
``sigma_<channel>[k]`` (the marginal noise sd ``s / sqrt(1 - phi^2)``, channel units).

``phi`` is 0 (``noise_model="white"``), or the lag-1 autocorrelation of the
least-squares residuals (``"ar1"``), or (``"auto"``, default) the latter only for the
channels whose residual autocorrelation exceeds ``3 / sqrt(n)`` (a 3-sigma test of
white noise). It is a plug-in estimate, not sampled.

Sampler and diagnostics
-----------------------
``emcee.EnsembleSampler(vectorize=True)`` on the log-probability jit-compiled and
``vmap``-ed over walkers; differential-evolution moves (``DEMove``: about 2.5x shorter
autocorrelation times than the default stretch move on this model; not
``DESnookerMove``, which in emcee <= 3.1.6 samples a Gaussian with 40 % too little
variance, fixed upstream in dfm/emcee#531; the calibration study found it). At least two
independent ensembles (own seeds, own overdispersed starts: twice the Laplace sd at the
least-squares optimum) run side by side.

Each ensemble first adapts (discarded): 100 DEMove steps, then 100 steps of which 80 %
propose from a multivariate Student-t (10 degrees of freedom, 1.15x the spread) fitted
to the later half of the ensemble's own DEMove draws, and that proposal refitted to the
later half of these. The kept run uses the last proposal, frozen, in the same 80/20
mixture with DEMove (``emcee.moves.MHMove`` with the independence sampler's Hastings
ratio): a fixed, valid Metropolis-Hastings kernel, whose proposals are independent of
the walker's position. Each fitted proposal is first checked: the Pareto k-hat (PSIS)
of the importance weights posterior / proposal on 2,000 draws from it must be below 0.5
(bounded weights are what an independence sampler needs; with heavier posterior tails a
walker that reaches them stays stuck), else that ensemble runs DEMove alone, as before;
``diagnostics.moves`` says which kernel ran and its k-hat. On this model's near-Gaussian
posteriors the mixture cuts the autocorrelation time about 9-fold (steps_200hz, 14
parameters: tau 6 steps instead of 54, the same means and intervals).

Per ensemble the integrated autocorrelation
time ``tau`` (emcee's estimator, averaged over walkers) sets burn-in (3 tau) and
thinning (tau/2, or more to keep at most 10,000 draws); ESS = walkers x steps after
burn-in / tau, summed over ensembles. The run stops at the first check (every 100 steps)
at which every criterion below holds.
R-hat is the rank-normalised split R-hat *between ensembles* (each ensemble's walkers
pooled, split in time): R-hat over the walkers of one ensemble is not valid, they are
not independent chains. ``converged`` needs all of: steps after burn-in >= 50 tau (the
length emcee needs to trust tau), ESS >= ``min_ess`` and R-hat < 1.01 for every
sampled parameter, and no stuck walkers.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.stages import STAGE_COLUMNS, STAGE_PARAMS, STAGES, TEACHER_FORCED
from ewb_ident.data.trace import Trace
from ewb_ident.data.validation import check_traces
from ewb_ident.inference.chains import poor, restart_chain, run_chains
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.log_posterior import SampleError, SamplerSettings, build
from ewb_ident.inference.posterior_result import PosteriorResult, assemble
from ewb_ident.inference.priors import load_priors, mechanism_prior
from ewb_ident.inference.problem import FitError, check_parameter_options, structural_notes
from ewb_ident.mechanisms.learned import LearnedTerm
from ewb_ident.model.integrate import EXPONENTIAL, Integrator
from ewb_ident.model.numerics import numerics


def _stage_list(stage: str | Sequence[str], traces: Sequence[Trace]) -> tuple[str, ...]:
    if isinstance(stage, str) and stage == "stages":
        stages = tuple(
            s
            for s in TEACHER_FORCED
            if all(t.has(c) for t in traces for c in (STAGE_COLUMNS[s][0], STAGE_COLUMNS[s][1]))
            or (s == "motor" and all(t.has("voltage_V") and t.has("theta_deg") for t in traces))
        )
        if not stages:
            raise SampleError("no stage can be fitted teacher-forced: the traces lack the columns")
        return stages
    stages = (stage,) if isinstance(stage, str) else tuple(stage)
    for s in stages:
        if s not in STAGES:
            raise SampleError(
                f"unknown stage {s!r}; choose chain, stages, or teacher-forced stages from "
                f"{', '.join(TEACHER_FORCED)} (several separated by commas)"
            )
    if len(stages) != len(set(stages)) or ("chain" in stages and len(stages) > 1):
        raise SampleError(
            f"stages {', '.join(stages)}: give each stage once, and chain alone (it already "
            "holds every stage's parameters)"
        )
    return stages


# ----------------------------------------------------------------------------- sample


@numerics
def sample(
    traces: Trace | Sequence[Trace],
    *,
    stage: str | Sequence[str] = "chain",
    free: Iterable[str] | None = None,
    per_trace: Iterable[str] | None = None,
    fixed: Mapping[str, float] | None = None,
    priors: str | Path | Mapping[str, Any] | None = None,
    settings: SamplerSettings | None = None,
    integrator: Integrator = EXPONENTIAL,
    progress: Callable[[int, int], None] | None = None,
    **options: Any,
) -> PosteriorResult:
    """Sample the posterior of the EWB model's parameters, starting from least squares.

    Parameters
    ----------
    traces
        One trace or several (they share every parameter except ``per_trace`` ones).
    stage
        ``"chain"`` (from voltage; every recorded channel), one teacher-forced stage
        (``"motor"``, ``"gap"``, ``"force"``, ``"torque"``), several (a sequence, e.g.
        ``("force", "torque")``: independent blocks of one posterior), or ``"stages"``
        (every teacher-forced stage the traces can serve).
    free, per_trace, fixed, integrator
        As for :func:`ewb_ident.inference.least_squares` (``free`` names may span the given stages).
    priors
        A TOML file (or parsed tables) overriding ``ewb_ident/inference/priors.toml``.
    settings
        How the ensembles run and what is summarised
        (:class:`~ewb_ident.inference.log_posterior.SamplerSettings`, which documents
        each field: ``noise_model``, ``n_walkers``, ``n_steps``, ``max_steps``,
        ``n_ensembles``, ``min_ess``, ``hdi_prob``, ``max_draws``, ``seed``); default:
        its defaults.
    progress
        Called as ``progress(steps_done, steps_planned)`` (per ensemble) during the run.
    **options
        Fields of :class:`~ewb_ident.inference.log_posterior.SamplerSettings` given one
        by one, in place of those of ``settings`` (e.g. ``sample(trace, seed=1)``).

    Returns
    -------
    PosteriorResult
        Never raises for chains that did not converge: ``converged`` is False and the
        warnings say what to do.

    Raises
    ------
    SampleError, PriorError, FitError, TraceError
        Settings, priors or traces that cannot be used.
    """
    traces = check_traces(traces)
    if not traces:
        raise SampleError("no traces to sample")
    free, per_trace, fixed, _ = check_parameter_options(free, per_trace, fixed, None)
    settings = SamplerSettings.of(settings, options, "sample")
    settings.check(n_samples=sum(t.n for t in traces))
    stages = _stage_list(stage, traces)
    prior_table = load_priors(priors)
    return _sample(
        traces, stages, free, per_trace, fixed, prior_table, settings, integrator, progress
    )


def _sample(
    traces, stages, free, per_trace, fixed, priors, settings: SamplerSettings, integrator,
    progress,
) -> PosteriorResult:  # fmt: skip
    t_start = time.perf_counter()
    free_l = None if free is None else list(free)
    if free_l is not None and stages != ("chain",):
        allowed = {n for s in stages for n in STAGE_PARAMS[s]}
        bad = [n for n in free_l if n not in allowed]
        if bad:
            raise FitError(
                f"parameter(s) {', '.join(bad)} belong to none of the stages "
                f"{', '.join(stages)}; their parameters are {', '.join(sorted(allowed))}"
            )
    fits, notes = [], []
    for s in stages:
        f_s = None if free_l is None else [n for n in free_l if n in STAGE_PARAMS[s]]
        if f_s == []:
            continue
        kw = dict(free=f_s, per_trace=per_trace, fixed=fixed, integrator=integrator)
        f = fit(traces, stage=s, **kw)
        if s == "chain" and poor(f):
            f = restart_chain(traces, f, kw, notes)
        fits.append(f)
    if not fits or not any(f.corr_names for f in fits):
        raise SampleError("nothing to sample: no free parameter in the given stages")
    # A fit that did not converge says everything; one that did, where it misses the
    # noise (the intervals are then a model's that does not reproduce the trace).
    notes += [
        f"least-squares start ({f.stage}): {w}"
        for f in fits
        for w in (f.misfits if f.converged else f.warnings)
    ]
    # What the channels cannot determine holds for the intervals too (a, c measured in
    # the nominal polynomial's displacement without x_m, mu held without torque_Nm); a
    # fit that did not converge gave them above, among all its warnings.
    for f in (f for f in fits if f.converged):
        notes += [w for w in structural_notes(f.stage, traces, tuple(f.free)) if w not in notes]
    for s in ("gap", "force"):
        if s in stages:
            notes.append(
                f"the {s} stage is teacher-forced: its measured input "
                f"({STAGE_COLUMNS[s][0]}) drives it, and that sensor's noise is weighed as carried "
                "through the stage to first order (studies/calibration.py, force and torque "
                "stages: the 90 % HDI of F_rt, a, b, c, mu held the truth in 89-91 % of 100 "
                "repeats); where the input's noise is large against the law's curvature, sample "
                "the whole chain, which reads only the logged voltage"
            )
    t_fit = time.perf_counter()

    lp, names, u0, segs = build(fits, priors, settings.noise_model, [t.time_s for t in traces])
    run = run_chains(lp, fits, names, u0, priors, settings, progress)
    held = fits[0].params[0].as_dict()
    result = assemble(
        fits, traces, stages, lp, names, segs, run, priors, settings, notes, fixed, held
    )
    return dataclasses.replace(result, timing=run.timing(t_start, t_fit))


@numerics
def sample_corrected(
    trace: Trace,
    corrected: Any,
    *,
    priors: str | Path | Mapping[str, Any] | None = None,
    settings: SamplerSettings | None = None,
    progress: Callable[[int, int], None] | None = None,
    **options: Any,
) -> PosteriorResult:
    """Sample the posterior of the whole chain corrected by catalog mechanisms.

    The start is a corrected fit of the trace,
    :func:`ewb_ident.diagnosis.corrected.fit_corrected` (the seed chain with the
    mechanisms, fitted from the voltage) or the diagnosis's
    (:attr:`ewb_ident.diagnosis.result.DiagnosisResult.corrected`); the sampled
    parameters are its free ones: the base parameters the channels determine and every
    mechanism parameter
    (``"variant.param"``). A mechanism parameter's prior is uniform (log-uniform when
    positive and log-scaled) over the catalog's range unless the prior file has a table
    of that name, e.g. ``["backlash.beta_deg"]``.

    Parameters
    ----------
    trace
        One trace with ``voltage_V`` and ``theta_deg``.
    corrected
        The corrected fit of ``trace`` (a
        :class:`ewb_ident.diagnosis.corrected.CorrectedFit`) whose free parameters are
        sampled.
    priors, settings, progress, **options
        As for :func:`sample`.

    Returns
    -------
    PosteriorResult
        Its ``mechanisms`` names the mechanisms; never raises for chains that did not
        converge (``converged`` is False and the warnings say why).

    Raises
    ------
    SampleError, PriorError
        Settings, priors or mechanisms that cannot be used with this trace.
    """
    settings = SamplerSettings.of(settings, options, "sample_corrected")
    settings.check(n_samples=trace.n)
    prior_table = load_priors(priors)
    t_start = time.perf_counter()
    start = _corrected_start(trace, corrected)
    table = {n: mechanism_prior(n) for n in start.corr_names if "." in n} | prior_table
    t_fit = time.perf_counter()
    lp, names, u0, segs = build([start], table, settings.noise_model, [trace.time_s])
    run = run_chains(lp, [start], names, u0, table, settings, progress)
    notes = [f"least-squares start (corrected chain): {w}" for w in corrected.warnings]
    result = assemble(
        [start], (trace,), ("chain",), lp, names, segs, run, table, settings, notes, None,
        corrected.params,
    )  # fmt: skip
    return dataclasses.replace(
        result, timing=run.timing(t_start, t_fit), mechanisms=tuple(corrected.mechanisms)
    )


class _AugChain(eqx.Module):
    """The corrected chain as the log posterior reads a model: one trace's predicted
    channels, trace length (the solver's data are padded)."""

    problem: Any
    n: int = eqx.field(static=True)
    channels: tuple[tuple[str, ...], ...] = eqx.field(static=True)

    def predict(self, u: jnp.ndarray, data: Mapping[str, Any]) -> list[dict[str, jnp.ndarray]]:
        pred = self.problem.predict_trace(u, data["aug"])
        return [{ch: pred[ch][: self.n] for ch in self.channels[0]}]

    def sigmas(self, u: jnp.ndarray, data: Mapping[str, Any]) -> list[dict[str, Any]]:
        """The channels' noise levels (a chain: nothing carried from a measured input)."""
        return [data["traces"][0]["sigma"]]


@dataclass(frozen=True)
class _CorrectedStart:
    """The corrected least-squares fit as the start of a posterior: what :func:`build`
    and :func:`walker_starts` read from a :class:`~ewb_ident.inference.fit_result.FitResult`."""

    trace_names: tuple[str, ...]
    corr_names: tuple[str, ...]
    u: np.ndarray
    corr: np.ndarray
    stderr: dict[str, float | None]
    problem: _AugChain
    data: dict[str, Any] = field(repr=False)
    predictions: list[dict[str, np.ndarray]] = field(repr=False)


def _sampled_stderr(f, names) -> dict[str, float | None]:
    """Standard errors in the units the posterior samples: a learned coefficient's over
    its size (:func:`ewb_ident.mechanisms.mechanism_param`)."""
    size = {
        f"{m.variant}.{i.name}": i.scale
        for m in f.problem.templates()
        if isinstance(m, LearnedTerm)
        for i in m.param_info()
    }
    out = {}
    for n in names:
        se = f.stderr.get(n)
        out[n] = se / size[n] if se is not None and n in size else se
    return out


def _corrected_start(trace: Trace, cf) -> _CorrectedStart:
    from ewb_ident.inference.augmented import residuals_and_jacobian

    f, aug, n = cf.fit, cf.data, trace.n
    names = list(f.problem.shared) + [
        f"{m.variant}.{i.name}" for m in f.problem.templates() for i in m.param_info()
    ]
    chans = f.problem.channels[0]
    J = np.asarray(residuals_and_jacobian(f.problem, jnp.asarray(f.u), aug)[1])
    cov = np.linalg.pinv(J.T @ J)
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    data = {
        "aug": aug,
        "traces": [
            {ch: jnp.asarray(trace[ch]) for ch in chans}
            | {"sigma": {ch: jnp.asarray(1.0 / float(aug["w"][ch][0])) for ch in chans}}
        ],
    }
    return _CorrectedStart(
        trace_names=(trace.name,),
        corr_names=tuple(names),
        u=np.asarray(f.u, float),
        corr=cov / np.outer(sd, sd),
        stderr=_sampled_stderr(f, names),
        problem=_AugChain(f.problem, n, (chans,)),
        data=data,
        predictions=[{ch: np.asarray(f.predictions[0][ch]) for ch in chans}],
    )
