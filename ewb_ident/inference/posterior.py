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
least-squares optimum) run side by side. Per ensemble the integrated autocorrelation
time ``tau`` (emcee's estimator, averaged over walkers) sets burn-in (3 tau) and
thinning (tau/2); ESS = walkers x steps after burn-in / tau, summed over ensembles.
R-hat is the rank-normalised split R-hat *between ensembles* (each ensemble's walkers
pooled, split in time): R-hat over the walkers of one ensemble is not valid, they are
not independent chains. ``converged`` needs all of: steps after burn-in >= 50 tau (the
length emcee needs to trust tau), ESS >= ``min_ess`` and R-hat < 1.01 for every
sampled parameter, and no stuck walkers.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import emcee
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.trace import STAGE_COLUMNS, Trace
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.priors import Prior, load_priors, mechanism_prior, param_info
from ewb_ident.inference.problem import STAGES, FitError, StageProblem
from ewb_ident.model.integrate import EXPONENTIAL, Integrator
from ewb_ident.model.params import PARAMS, STAGE_PARAMS, ParamInfo

#: The parameters every summary reports (CONTRACTS.md).
CONTRACT_PARAMS: tuple[str, ...] = ("a", "b", "c", "mu")
NOISE_MODELS: tuple[str, ...] = ("auto", "white", "ar1")
TEACHER_FORCED: tuple[str, ...] = ("motor", "gap", "force", "torque")

OVERDISPERSION = 2.0  #: start spread, in Laplace standard deviations
BURN_TAUS = 3.0  #: burn-in, in autocorrelation times
TAU_RELIABLE = 50.0  #: steps after burn-in (in tau) for emcee's tau estimate to be trusted
RHAT_MAX = 1.01  #: between-ensemble R-hat above which the ensembles disagree
STUCK = 0.2  #: a walker accepting less than this fraction of its ensemble's median is stuck
CHUNK = 100  #: steps between progress reports and convergence checks
PRIOR_LIKE = 0.5  #: posterior sd / prior sd above which a parameter is "not identified"
RIDGE = 0.95  #: |posterior correlation| above which two parameters are named as a ridge
POOR_FIT = 3.0  #: residual sd / sensor noise above which the least-squares start is retried

#: What measurement or input profile identifies each parameter (for the statements).
HINTS: dict[str, str] = {
    "a": "an apply that drives the piston through full clamping (x past c) with x_m and "
    "force_N recorded, e.g. rig profile 'position' or 'staircase' to high force",
    "b": "an apply through the whole rise of the force, past full clamping (x past c)",
    "c": "an apply that drives the piston past full clamping (x past c)",
    "F_rt": "an apply to saturation (x at c), where the force levels off at F_rt",
    "mu": "a recorded disc torque (torque_Nm) together with the clamping force",
    "R": "voltage steps of several sizes and lengths with current_A recorded (the "
    "steady-state current fixes R, the acceleration M)",
    "L": "current_A logged at 1 kHz or more (the armature pole R/L is 200-1000 1/s)",
    "kb": "voltage steps of several sizes with theta_deg recorded (profile 'steps')",
    "kT": "a known load torque, or current with speed and acceleration",
    "M": "fast voltage steps (the acceleration phase) with theta_deg and current_A recorded",
    "v": "long voltage steps that reach a steady speed, with theta_deg recorded",
    "p2": "x_m recorded over the whole stroke, from rest to full clamping",
    "p1": "x_m recorded over the whole stroke, from rest to full clamping",
    "p0": "x_m recorded from rest (the air gap)",
    "theta0_deg": "theta_deg recorded from the first sample",
}


class SampleError(ValueError):
    """A posterior that cannot be set up as asked (the message says what to change)."""


# ----------------------------------------------------------------------------- model


def _ar1_q(r: jnp.ndarray, phi: jnp.ndarray) -> jnp.ndarray:
    """``(1 - phi^2) r0^2 + sum (r_t - phi r_{t-1})^2``: the AR(1) quadratic form."""
    e = r[1:] - phi * r[:-1]
    return (1.0 - phi * phi) * r[0] * r[0] + jnp.sum(e * e)


class _LogPost(eqx.Module):
    """Log posterior of the unconstrained vector ``u`` (noise levels marginalised)."""

    problems: tuple[StageProblem, ...]
    datas: tuple[dict, ...]
    phi: jnp.ndarray
    slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    n: tuple[int, ...] = eqx.field(static=True)
    infos: tuple[ParamInfo, ...] = eqx.field(static=True)
    priors: tuple[Prior, ...] = eqx.field(static=True)

    def segments(self, u: jnp.ndarray) -> list[tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]]:
        """(prediction, measurement, least-squares sigma) per trace and channel."""
        out = []
        for prob, data, (i0, i1) in zip(self.problems, self.datas, self.slices, strict=True):
            for k, pred in enumerate(prob.predict(u[i0:i1], data)):
                tr = data["traces"][k]
                out += [(pred[ch], tr[ch], tr["sigma"][ch]) for ch in prob.channels[k]]
        return out

    def residuals(self, u: jnp.ndarray) -> list[jnp.ndarray]:
        """Residuals per segment, in units of the least-squares noise level."""
        return [(p - m) / s for p, m, s in self.segments(u)]

    def q(self, u: jnp.ndarray) -> jnp.ndarray:
        """The AR(1) quadratic form of each segment, shape (segments,)."""
        return jnp.stack([_ar1_q(r, self.phi[j]) for j, r in enumerate(self.residuals(u))])

    def log_prior(self, u: jnp.ndarray) -> jnp.ndarray:
        """Prior on the physical values plus the log-Jacobian of the transforms."""
        lp = jnp.zeros((), u.dtype)
        for j, (info, prior) in enumerate(zip(self.infos, self.priors, strict=True)):
            lp = lp + prior.logpdf(info.to_physical(u[j])) + jnp.log(jnp.abs(info.dp_du(u[j])))
        return lp

    def with_q(self, u: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        """The log posterior and the quadratic forms it was computed from."""
        q = self.q(u)
        ll = -0.5 * jnp.sum(jnp.asarray(self.n, u.dtype) * jnp.log(jnp.maximum(q, 1e-300)))
        lp = self.log_prior(u) + ll
        return jnp.where(jnp.isnan(lp) | (lp == jnp.inf), -jnp.inf, lp), q

    def __call__(self, u: jnp.ndarray) -> jnp.ndarray:
        return self.with_q(u)[0]

    def predictive(self, u: jnp.ndarray, s: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Predictions and pointwise log-likelihood (channel units) given innovation sds
        ``s`` (per segment, least-squares units); both concatenated over segments."""
        preds, lls = [], []
        for j, (p, m, sig) in enumerate(self.segments(u)):
            r, phi = (p - m) / sig, self.phi[j]
            e = jnp.concatenate([r[:1] * jnp.sqrt(1.0 - phi * phi), r[1:] - phi * r[:-1]])
            ll = -0.5 * (e / s[j]) ** 2 - jnp.log(s[j] * sig) - 0.5 * jnp.log(2.0 * jnp.pi)
            lls.append(ll.at[0].add(0.5 * jnp.log(1.0 - phi * phi)))
            preds.append(p)
        return jnp.concatenate(preds), jnp.concatenate(lls)


@jax.jit
def _v_logp_q(lp: _LogPost, X):
    return jax.vmap(lp.with_q)(X)


@jax.jit
def _v_predictive(lp: _LogPost, X, S):
    return jax.vmap(lp.predictive)(X, S)


def _batched(fn, lp, X: np.ndarray, *extra: np.ndarray, size: int):
    """``fn(lp, X, *extra)`` over the rows of X in batches of one size (one compilation)."""
    n = X.shape[0]
    pad = (-n) % size
    arrays = [np.concatenate([a, np.repeat(a[:1], pad, 0)]) for a in (X, *extra)]
    outs = []
    for i in range(0, n + pad, size):
        res = fn(lp, *(a[i : i + size] for a in arrays))
        outs.append(jax.tree_util.tree_map(np.asarray, res))
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs)[:n], *outs)


# ----------------------------------------------------------------------------- set-up


@dataclass(frozen=True)
class _Segment:
    trace: int
    trace_name: str
    channel: str
    n: int
    sigma_ls: float
    rho1: float
    phi: float
    time_s: np.ndarray = field(repr=False)
    measured: np.ndarray = field(repr=False)

    @property
    def name(self) -> str:
        return f"sigma_{self.channel}[{self.trace}]"

    @property
    def model(self) -> str:
        return "ar1" if self.phi != 0.0 else "white"


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


def _check_options(
    noise_model, n_walkers, n_steps, max_steps, n_ensembles, hdi_prob, min_ess, max_draws, seed
):
    if noise_model not in NOISE_MODELS:
        raise SampleError(
            f"noise model must be one of {', '.join(NOISE_MODELS)}, got {noise_model!r}"
        )
    if not isinstance(n_ensembles, int) or n_ensembles < 2:
        raise SampleError(
            f"n_ensembles must be an integer >= 2, got {n_ensembles!r}: R-hat needs independent "
            "ensembles (the walkers of one ensemble are not independent chains)"
        )
    if not isinstance(n_steps, int) or n_steps < 10:
        raise SampleError(f"n_steps must be an integer >= 10, got {n_steps!r}")
    if max_steps is not None and (not isinstance(max_steps, int) or max_steps < n_steps):
        raise SampleError(f"max_steps must be an integer >= n_steps ({n_steps}), got {max_steps!r}")
    if n_walkers is not None and (not isinstance(n_walkers, int) or n_walkers % 2 or n_walkers < 4):
        raise SampleError(f"n_walkers must be an even integer >= 4, got {n_walkers!r}")
    if not 0.0 < hdi_prob < 1.0:
        raise SampleError(f"hdi_prob must lie strictly between 0 and 1, got {hdi_prob!r}")
    if not min_ess > 0:
        raise SampleError(f"min_ess must be > 0, got {min_ess!r}")
    if not isinstance(max_draws, int) or max_draws < n_ensembles:
        raise SampleError(f"max_draws must be an integer >= n_ensembles, got {max_draws!r}")
    if not isinstance(seed, int) or seed < 0:
        raise SampleError(f"seed must be a non-negative integer, got {seed!r}")


def _build(fits: Sequence[FitResult], priors: Mapping[str, Prior], noise_model: str, time_s):
    names: list[str] = []
    slices, u0 = [], []
    for f in fits:
        slices.append((len(names), len(names) + len(f.corr_names)))
        names += list(f.corr_names)
        u0.append(np.asarray(f.u, float))
    bases = [_key(n) for n in names]
    lp = _LogPost(
        problems=tuple(f.problem for f in fits),
        datas=tuple(f.data for f in fits),
        phi=jnp.zeros(sum(len(c) for f in fits for c in f.problem.channels)),
        slices=tuple(slices),
        n=tuple(
            int(f.data["traces"][k][ch].shape[0])
            for f in fits
            for k, chs in enumerate(f.problem.channels)
            for ch in chs
        ),
        infos=tuple(param_info(b) for b in bases),
        priors=tuple(priors[b] for b in bases),
    )
    u = np.concatenate(u0) if u0 else np.zeros(0)
    # Residual autocorrelation at the least-squares optimum decides the noise model.
    segs: list[_Segment] = []
    for f in fits:
        for k, chs in enumerate(f.problem.channels):
            tr = f.data["traces"][k]
            for ch in chs:
                meas = np.asarray(tr[ch])
                r = (f.predictions[k][ch] - meas) / float(tr["sigma"][ch])
                rho1 = float(np.sum(r[1:] * r[:-1]) / max(float(np.sum(r * r)), 1e-300))
                white = noise_model == "white" or (
                    noise_model == "auto" and abs(rho1) <= 3 / math.sqrt(r.size)
                )
                segs.append(
                    _Segment(
                        trace=k,
                        trace_name=f.trace_names[k],
                        channel=ch,
                        n=r.size,
                        sigma_ls=float(tr["sigma"][ch]),
                        rho1=rho1,
                        phi=0.0 if white else float(np.clip(rho1, -0.99, 0.99)),
                        time_s=np.asarray(time_s[k]),
                        measured=meas,
                    )
                )
    lp = eqx.tree_at(lambda m: m.phi, lp, jnp.asarray([s.phi for s in segs]))
    return lp, tuple(names), u, tuple(segs)


def _starts(lp, fits, u0, n_walkers, rngs) -> list[np.ndarray]:
    """Overdispersed starting walkers around ``u0``: the least-squares fits' Laplace
    approximation (their correlation and standard errors, in u), its sd x OVERDISPERSION."""
    sd, blocks = [], []
    for f in fits:
        blocks.append(np.where(np.isfinite(f.corr), f.corr, 0.0) if f.corr.size else f.corr)
        for n, u in zip(f.corr_names, f.u, strict=True):
            se = f.stderr.get(n)
            slope = abs(float(_info(n).dp_du(u)))
            sd.append(se / slope if se is not None and slope > 0 and np.isfinite(se) else 1.0)
    C = np.zeros((u0.size, u0.size))
    i = 0
    for B in blocks:
        C[i : i + len(B), i : i + len(B)] = B
        i += len(B)
    sd_u = np.minimum(np.asarray(sd), 1.0)
    cov = C * np.outer(sd_u, sd_u)
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    # Never wider than one unit of the O(1) u; never flat (emcee needs a full-rank start).
    L = V * np.sqrt(np.clip(lam, 1e-8 * max(float(np.max(lam)), 1e-12), 1.0))
    starts = []
    for rng in rngs:
        p = u0 + OVERDISPERSION * rng.standard_normal((n_walkers, u0.size)) @ L.T
        for _ in range(30):
            bad = ~np.isfinite(_batched(_v_logp_q, lp, p, size=n_walkers // 2)[0])
            if not bad.any():
                break
            p[bad] = (
                u0 + 0.5 * OVERDISPERSION * rng.standard_normal((int(bad.sum()), u0.size)) @ L.T
            )
        else:
            raise SampleError("no finite log-posterior near the least-squares optimum")
        starts.append(p)
    return starts


# ----------------------------------------------------------------------------- diagnostics


def _tau(x: np.ndarray) -> np.ndarray:
    """emcee's integrated autocorrelation time per column of x (steps, walkers, params)."""
    return emcee.autocorr.integrated_time(x, tol=0)


def _rhat(per_ensemble: Sequence[np.ndarray]) -> float:
    """Rank-normalised split R-hat between ensembles; each is (steps, walkers), pooled
    over walkers in time order so that arviz's split halves are early and late draws."""
    az = _arviz()
    with np.errstate(all="ignore"):
        value = float(az.rhat(np.stack([x.reshape(-1) for x in per_ensemble])))
    return value if math.isfinite(value) else math.inf  # e.g. a parameter that never moved


def _diagnose(chains: list[np.ndarray], phys, min_ess: float) -> dict[str, Any]:
    """Burn-in, thinning, tau, ESS and R-hat from the chains (steps, walkers, params)."""
    N, W, _ = chains[0].shape
    with np.errstate(all="ignore"):
        tau0 = np.nan_to_num(np.max([_tau(phys(c[N // 2 :])) for c in chains]), nan=N)
        burn = int(min(math.ceil(BURN_TAUS * tau0), N // 2))
        post = [phys(c[burn:]) for c in chains]
        tau = np.nan_to_num(np.stack([_tau(p) for p in post]), nan=np.inf)  # (E, D)
    n_post = N - burn
    ess = np.sum(W * n_post / tau, axis=0)
    rhat = np.array([_rhat([p[:, :, j] for p in post]) for j in range(tau.shape[1])])
    return {
        "burn": burn,
        "thin": max(1, int(0.5 * min(np.min(tau), N))),
        "tau": tau,
        "ess": ess,
        "rhat": rhat,
        "n_post": n_post,
        "reliable": bool(n_post >= TAU_RELIABLE * np.max(tau)),
        "ok": bool(
            n_post >= TAU_RELIABLE * np.max(tau)
            and np.min(ess) >= min_ess
            and np.max(rhat) < RHAT_MAX
        ),
    }


def _arviz():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # arviz's refactoring notice
        import arviz

    return arviz


def _hdi(x: np.ndarray, prob: float) -> tuple[float, float]:
    """Highest-density interval of a 1-D sample (the narrowest interval holding prob)."""
    s = np.sort(x)
    k = max(1, int(math.floor(prob * s.size)))
    widths = s[k:] - s[: s.size - k]
    i = int(np.argmin(widths))
    return float(s[i]), float(s[i + k])


# ----------------------------------------------------------------------------- result


@dataclass(frozen=True)
class PosteriorResult:
    """The outcome of :func:`sample` (immutable).

    Attributes
    ----------
    stages, trace_names
        What was sampled: ``("chain",)`` or teacher-forced stages; the traces.
    names
        Sampled model parameters (per-trace ones as ``"theta0_deg[k]"``).
    noise_names
        The noise levels drawn for every kept draw, ``"sigma_<channel>[k]"``.
    draws
        Name -> kept draws, physical units, shape (ensembles, draws): burn-in removed,
        thinned by tau/2, each ensemble's walkers pooled in time order.
    stats
        Name -> mean, sd, hdi_low, hdi_high, ess, r_hat, unit, source (``posterior``,
        ``prior`` when the traces hold no information on it, ``fixed``) and more.
    converged
        Whether every convergence criterion holds (module docstring); if not,
        ``warnings`` say why and what to do.
    identifiability
        Plain statements about what the traces do not pin down, and what would.
    diagnostics
        Walkers, steps, burn-in, thinning, tau per ensemble, acceptance, criteria.
    noise
        Per trace and channel: noise model, AR(1) coefficient, residual autocorrelation.
    fits
        The least-squares fits the sampler started from.
    timing
        Seconds spent fitting, compiling and sampling (not in the summary: the summary
        of a seed must not change between runs).
    predictive
        Stored draws with predictions, pointwise log-likelihood and replicated data.
    mechanisms
        Catalog mechanisms added to the seed chain (:func:`sample_corrected`), else empty.
    """

    stages: tuple[str, ...]
    trace_names: tuple[str, ...]
    names: tuple[str, ...]
    noise_names: tuple[str, ...]
    draws: dict[str, np.ndarray] = field(repr=False)
    stats: dict[str, dict[str, Any]]
    hdi_prob: float
    converged: bool
    warnings: tuple[str, ...]
    identifiability: tuple[dict[str, Any], ...]
    diagnostics: dict[str, Any]
    noise: tuple[dict[str, Any], ...]
    priors: dict[str, Prior] = field(repr=False)
    seed: int
    fits: tuple[FitResult, ...] = field(repr=False)
    timing: dict[str, float]
    predictive: dict[str, Any] = field(repr=False)
    mechanisms: tuple[str, ...] = ()

    def correlation(self, names: Iterable[str] | None = None) -> tuple[list[str], np.ndarray]:
        """Posterior correlation matrix of sampled parameters (default: a, b, c, mu)."""
        return _corr([n for n in (names or CONTRACT_PARAMS) if n in self.draws], self.draws)

    def to_summary_json(self) -> dict[str, Any]:
        """The contract ``summary.json`` document (plain JSON; null where no value)."""
        corr_names, corr = self.correlation()
        all_names, corr_all = self.correlation(self.names)
        return {
            "hdi_prob": self.hdi_prob,
            "params": self.stats,
            "converged": self.converged,
            "warnings": list(self.warnings),
            "identifiability": list(self.identifiability),
            "correlation": {"names": corr_names, "matrix": corr.tolist()},
            "correlation_all": {"names": all_names, "matrix": corr_all.tolist()},
            "stages": list(self.stages),
            "traces": list(self.trace_names),
            "sampled": list(self.names),
            "noise_model": {
                "prior": "Jeffreys p(s) ~ 1/s per trace and channel, marginalised analytically",
                "channels": list(self.noise),
            },
            "diagnostics": self.diagnostics,
            "priors": {n: self.priors[_key(n)].to_json() for n in self.names}
            | {n: self.priors[n].to_json() for n in CONTRACT_PARAMS},
            "least_squares": {
                n: _finite(float(v))
                for f in self.fits
                for n, v in zip(f.corr_names, _physical(f.corr_names, f.u), strict=True)
            },
            "seed": self.seed,
            "mechanisms": list(self.mechanisms),
            "ess_note": (
                "ESS = walkers x steps after burn-in / tau (emcee's integrated "
                "autocorrelation time), summed over ensembles; r_hat: rank-normalised split "
                "R-hat between independent ensembles; null where the value is not sampled"
            ),
        }

    def to_inference_data(self):
        """ArviZ InferenceData: posterior (chain = ensemble), observed data, posterior
        predictive and pointwise log-likelihood (``y``, all traces and channels
        concatenated along ``obs``; ``az.loo`` works on it), and sample stats."""
        az = _arviz()
        pr = self.predictive
        post = {n: pr["draws"][n] for n in self.names + self.noise_names}
        obs = pr["observed"]
        idata = az.from_dict(
            posterior=post,
            posterior_predictive={"y": pr["y_rep"]},
            log_likelihood={"y": pr["log_lik"]},
            observed_data={"y": obs},
            sample_stats={"lp": pr["lp"]},
            dims={"y": ["obs"]},
            coords={"obs": np.arange(obs.size)},
            attrs={"stages": ",".join(self.stages), "hdi_prob": self.hdi_prob},
        )
        coords = {
            "obs_trace": ("obs", pr["obs_trace"]),
            "obs_channel": ("obs", pr["obs_channel"]),
            "obs_time_s": ("obs", pr["obs_time_s"]),
        }
        for group in ("observed_data", "posterior_predictive", "log_likelihood"):
            setattr(idata, group, getattr(idata, group).assign_coords(coords))
        return idata

    def pair_plot(
        self, names: Iterable[str] | None = None, truth: Mapping[str, float] | None = None
    ):
        """A matplotlib Figure: pairwise scatter and marginal histograms (default a, b,
        c, mu, those sampled), the HDIs dashed, ``truth`` (if given) in red."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.ticker import MaxNLocator

        names = [n for n in (names or CONTRACT_PARAMS) if n in self.draws] or list(self.names[:4])
        k = len(names)
        fig = Figure(figsize=(2.4 * k + 0.6, 2.4 * k + 0.6))
        FigureCanvasAgg(fig)
        flat = {n: self.draws[n].reshape(-1) for n in names}
        pick = np.linspace(0, flat[names[0]].size - 1, min(3000, flat[names[0]].size)).astype(int)
        for i, ni in enumerate(names):
            for j, nj in enumerate(names[: i + 1]):
                ax = fig.add_subplot(k, k, i * k + j + 1)
                if i == j:
                    ax.hist(flat[ni], bins=40, color="0.45")
                    for v in (self.stats[ni]["hdi_low"], self.stats[ni]["hdi_high"]):
                        ax.axvline(v, ls="--", color="k", lw=0.8)
                    if truth and ni in truth:
                        ax.axvline(truth[ni], color="r")
                    ax.set_yticks([])
                else:
                    ax.plot(flat[nj][pick], flat[ni][pick], ".", ms=1.5, alpha=0.3, color="0.2")
                    if truth and ni in truth and nj in truth:
                        ax.plot(truth[nj], truth[ni], "r+", ms=10)
                if i == k - 1:
                    ax.set_xlabel(f"{nj} [{_info(nj).unit}]")
                if j == 0 and i > 0:
                    ax.set_ylabel(f"{ni} [{_info(ni).unit}]")
                ax.tick_params(labelsize=7)
                for axis in (ax.xaxis, ax.yaxis):
                    axis.set_major_locator(MaxNLocator(3))
                    axis.get_major_formatter().set_powerlimits((-3, 4))
        fig.suptitle(f"posterior of {', '.join(self.trace_names)} ({'+'.join(self.stages)})")
        fig.tight_layout()
        return fig


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _key(name: str) -> str:
    """The parameter a sampled name belongs to: ``c`` of ``c[1]`` (per trace); a
    mechanism's ``"variant.param"`` as it is."""
    return name if "." in name else name.split("[")[0]


def _info(name: str) -> ParamInfo:
    return param_info(_key(name))


def _hint(name: str) -> str:
    return HINTS.get(_key(name), "a trace in which this mechanism acts strongly")


def _physical(names: Sequence[str], u: np.ndarray) -> np.ndarray:
    """Unconstrained -> physical values (NumPy), column by column."""
    u = np.asarray(u, float)
    cols = [_info(n).to_physical(u[..., j]) for j, n in enumerate(names)]
    return np.stack([np.asarray(c, float) for c in cols], axis=-1)


# ----------------------------------------------------------------------------- sample


def sample(
    traces: Trace | Sequence[Trace],
    *,
    stage: str | Sequence[str] = "chain",
    free: Iterable[str] | None = None,
    per_trace: Iterable[str] | None = None,
    fixed: Mapping[str, float] | None = None,
    priors: str | Path | Mapping[str, Any] | None = None,
    noise_model: str = "auto",
    n_walkers: int | None = None,
    n_steps: int = 2000,
    max_steps: int | None = None,
    n_ensembles: int = 2,
    min_ess: float = 400.0,
    hdi_prob: float = 0.9,
    max_draws: int = 1000,
    seed: int = 0,
    integrator: Integrator = EXPONENTIAL,
    progress: Callable[[int, int], None] | None = None,
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
    noise_model
        ``"auto"``, ``"white"`` or ``"ar1"`` (module docstring).
    n_walkers
        Walkers per ensemble (even; default ``max(32, 4 * dimension)``).
    n_steps
        Steps per ensemble.
    max_steps
        The run is extended (deterministically) until it has converged or has this many
        steps (default ``10 * n_steps``; ``n_steps`` switches extension off).
    n_ensembles
        Independent ensembles (>= 2).
    min_ess
        Effective sample size every sampled parameter needs for ``converged``.
    hdi_prob
        Probability of the highest-density intervals.
    max_draws
        Draws kept (over all ensembles) for the posterior predictive and the pointwise
        log-likelihood of :meth:`PosteriorResult.to_inference_data`.
    seed
        Seed of everything random (starting walkers, emcee, noise draws): the same seed
        gives the same result.
    progress
        Called as ``progress(steps_done, steps_planned)`` (per ensemble) during the run.

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
    traces = (traces,) if isinstance(traces, Trace) else tuple(traces)
    if not traces:
        raise SampleError("no traces to sample")
    _check_options(
        noise_model, n_walkers, n_steps, max_steps, n_ensembles, hdi_prob, min_ess, max_draws, seed
    )
    stages = _stage_list(stage, traces)
    prior_table = load_priors(priors)
    with jax.enable_x64(True):
        return _sample(
            traces, stages, free, per_trace, fixed, prior_table, noise_model, n_walkers,
            n_steps, max_steps or 10 * n_steps, n_ensembles, min_ess, hdi_prob, max_draws, seed,
            integrator, progress,
        )  # fmt: skip


def _sample(
    traces, stages, free, per_trace, fixed, priors, noise_model, n_walkers, n_steps,
    max_steps, n_ensembles, min_ess, hdi_prob, max_draws, seed, integrator, progress,
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
        if s == "chain" and _poor(f):
            f = _restart_chain(traces, f, kw, notes)
        fits.append(f)
    if not fits or not any(f.corr_names for f in fits):
        raise SampleError("nothing to sample: no free parameter in the given stages")
    notes += [
        f"least-squares start ({f.stage}): {w}" for f in fits if not f.converged for w in f.warnings
    ]
    for s in ("gap", "force"):
        if s in stages:
            notes.append(
                f"the {s} stage is teacher-forced: its measured input "
                f"({STAGE_COLUMNS[s][0]}) is taken as exact, and that sensor's noise is read as "
                "information, so its intervals are too narrow (studies/calibration.py: the 90 % "
                "HDI of a, b, c, F_rt held the truth in ~73 % of repeats); sample the whole chain "
                "for calibrated intervals"
            )
    t_fit = time.perf_counter()

    lp, names, u0, segs = _build(fits, priors, noise_model, [t.time_s for t in traces])
    run = _run_chains(
        lp, fits, names, u0, priors, n_walkers, n_steps, max_steps, n_ensembles, min_ess, seed,
        progress,
    )  # fmt: skip
    result = _assemble(
        fits, traces, stages, lp, names, segs, run.samplers, run.chains, run.diag, priors,
        hdi_prob, min_ess, max_draws, seed, run.seq, notes, fixed, fits[0].params[0].as_dict(),
    )  # fmt: skip
    return dataclasses.replace(result, timing=run.timing(t_start, t_fit))


def sample_corrected(
    trace: Trace,
    corrected: Any,
    *,
    priors: str | Path | Mapping[str, Any] | None = None,
    noise_model: str = "auto",
    n_walkers: int | None = None,
    n_steps: int = 2000,
    max_steps: int | None = None,
    n_ensembles: int = 2,
    min_ess: float = 400.0,
    hdi_prob: float = 0.9,
    max_draws: int = 1000,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
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
    priors, noise_model, n_walkers, n_steps, max_steps, n_ensembles, min_ess, hdi_prob,
    max_draws, seed, progress
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
    _check_options(
        noise_model, n_walkers, n_steps, max_steps, n_ensembles, hdi_prob, min_ess, max_draws, seed
    )
    prior_table = load_priors(priors)
    with jax.enable_x64(True):
        t_start = time.perf_counter()
        cf = corrected
        start = _corrected_start(trace, corrected)
        table = {n: mechanism_prior(n) for n in start.corr_names if "." in n} | prior_table
        t_fit = time.perf_counter()
        lp, names, u0, segs = _build([start], table, noise_model, [trace.time_s])
        run = _run_chains(
            lp, [start], names, u0, table, n_walkers, n_steps, max_steps or 10 * n_steps,
            n_ensembles, min_ess, seed, progress,
        )  # fmt: skip
        notes = [f"least-squares start (corrected chain): {w}" for w in cf.warnings]
        result = _assemble(
            [start], (trace,), ("chain",), lp, names, segs, run.samplers, run.chains, run.diag,
            table, hdi_prob, min_ess, max_draws, seed, run.seq, notes, None, cf.params,
        )  # fmt: skip
    return dataclasses.replace(
        result, timing=run.timing(t_start, t_fit), mechanisms=tuple(cf.mechanisms)
    )


class _AugChain(eqx.Module):
    """The corrected chain as the log posterior reads a model: one trace's predicted
    channels, trace length (the solver's data are padded)."""

    problem: Any
    n: int = eqx.field(static=True)
    channels: tuple[tuple[str, ...], ...] = eqx.field(static=True)

    def predict(self, u: jnp.ndarray, data: Mapping[str, Any]) -> list[dict[str, jnp.ndarray]]:
        pred = self.problem.predict(u, data["aug"])
        return [{ch: pred[ch][: self.n] for ch in self.channels[0]}]


@dataclass(frozen=True)
class _CorrectedStart:
    """The corrected least-squares fit as the start of a posterior: what :func:`_build`
    and :func:`_starts` read from a :class:`~ewb_ident.inference.least_squares.FitResult`."""

    trace_names: tuple[str, ...]
    corr_names: tuple[str, ...]
    u: np.ndarray
    corr: np.ndarray
    stderr: dict[str, float | None]
    problem: _AugChain
    data: dict[str, Any] = field(repr=False)
    predictions: list[dict[str, np.ndarray]] = field(repr=False)


def _corrected_start(trace: Trace, cf) -> _CorrectedStart:
    from ewb_ident.inference.augmented import residuals_and_jacobian

    f, aug, n = cf.fit, cf.data, trace.n
    names = list(f.problem.free) + [
        f"{m.variant}.{i.name}" for m in f.problem.templates() for i in m.param_info()
    ]
    chans = tuple(f.problem.channels)
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
        stderr={n_: f.stderr.get(n_) for n_ in names},
        problem=_AugChain(f.problem, n, (chans,)),
        data=data,
        predictions=[{ch: np.asarray(f.predictions[ch]) for ch in chans}],
    )


@dataclass(frozen=True)
class _Run:
    samplers: list
    chains: list[np.ndarray]
    diag: dict[str, Any]
    seq: list
    t_compile: float
    t_sample: float

    def timing(self, t_start: float, t_fit: float) -> dict[str, float]:
        return {
            "fit_s": t_fit - t_start,
            "compile_and_start_s": self.t_compile - t_fit,
            "sampling_s": self.t_sample - self.t_compile,
            "summary_s": time.perf_counter() - self.t_sample,
        }


def _run_chains(
    lp, fits, names, u0, priors, n_walkers, n_steps, max_steps, n_ensembles, min_ess, seed,
    progress,
) -> _Run:  # fmt: skip
    """Independent emcee ensembles from the least-squares optimum, extended until every
    convergence criterion holds or ``max_steps`` is reached."""
    excluded = [
        n
        for n, v in zip(names, _physical(names, u0), strict=True)
        if not np.isfinite(float(priors[_key(n)].logpdf(v, np)))
    ]
    if excluded:
        raise SampleError(
            "the least-squares optimum lies outside the prior bounds of "
            f"{', '.join(excluded)}: widen them in the prior file, or check the fit"
        )
    D = len(names)
    W = max(32, 4 * D) if n_walkers is None else int(n_walkers)
    if W < 2 * D or W % 2:
        raise SampleError(
            f"n_walkers must be even and at least twice the dimension ({2 * D}), got {W}"
        )
    seq = np.random.SeedSequence(seed).spawn(2 * n_ensembles + 3)
    starts = _starts(lp, fits, u0, W, [np.random.default_rng(s) for s in seq[:n_ensembles]])
    t_compile = time.perf_counter()

    def logp(X: np.ndarray) -> np.ndarray:
        return _batched(_v_logp_q, lp, X, size=W // 2)[0]

    samplers = []
    for e in range(n_ensembles):
        moves = emcee.moves.DEMove()
        smp = emcee.EnsembleSampler(W, D, logp, vectorize=True, moves=moves)
        state = np.random.RandomState(int(seq[n_ensembles + e].generate_state(1)[0]))
        smp.random_state = state.get_state()
        if not np.array_equal(smp.random_state[1], state.get_state()[1]):
            raise RuntimeError("emcee did not accept the seed of its random state")
        samplers.append(smp)
    phys = functools.partial(_physical, names)
    done, target, states = 0, n_steps, list(starts)
    with ThreadPoolExecutor(max_workers=n_ensembles) as pool:
        while True:
            while done < target:
                k = min(CHUNK, target - done)
                states = list(pool.map(functools.partial(_advance, k), samplers, states))
                done += k
                if progress is not None:
                    progress(done, target)
            chains = [s.get_chain() for s in samplers]
            diag = _diagnose(chains, phys, min_ess)
            if diag["ok"] or done >= max_steps:
                break
            tau = float(np.max(np.where(np.isfinite(diag["tau"]), diag["tau"], done)))
            need = diag["burn"] + max(TAU_RELIABLE * tau, min_ess * tau / (n_ensembles * W))
            target = int(min(max_steps, max(1.2 * need, done + max(CHUNK, done // 2))))
    return _Run(samplers, chains, diag, seq, t_compile, time.perf_counter())


def _poor(f: FitResult) -> bool:
    """A fit whose residuals are far above the sensor noise on some channel: a local
    minimum of the least squares (or physics the model leaves out)."""
    return any(
        f.sigma[k][ch] > POOR_FIT * max(f.noise[k][ch], 1e-300)
        for k in range(len(f.sigma))
        for ch in f.sigma[k]
    )


def _restart_chain(traces, first: FitResult, kw: dict, notes: list[str]) -> FitResult:
    """The whole chain again, from the teacher-forced fits of the gap, force and torque
    stages; the better of the two fits (lower cost) is kept."""
    start: dict[str, float] = {}
    for s in ("gap", "force", "torque"):
        names = [n for n in first.free if n in STAGE_PARAMS[s] and n not in first.per_trace]
        if names and all(t.has(c) for t in traces for c in STAGE_COLUMNS[s]):
            g = fit(traces, stage=s, **(kw | {"free": names, "per_trace": ()}))
            if g.converged:
                start |= {n: g.params[0].as_dict()[n] for n in names}
    if not start:
        return first
    second = fit(traces, stage="chain", start=start, **kw)
    before, after = _profile_nll(first), _profile_nll(second)
    if not after < before:
        return first
    notes.append(
        "the least-squares fit of the whole chain from its default start left residuals far "
        "above the sensor noise (a local minimum); it was restarted from the teacher-forced "
        f"fits of the stages, which raised its log-likelihood by {before - after:.4g}"
    )
    return second


def _profile_nll(f: FitResult) -> float:
    """Minus the log-likelihood at the fit with each channel's noise at its ML value
    (up to a constant): sum of n log(sigma) over traces and channels."""
    return sum(
        f.data["traces"][k][ch].shape[0] * math.log(max(sig, 1e-300))
        for k in range(len(f.sigma))
        for ch, sig in f.sigma[k].items()
    )


def _advance(k: int, sampler: emcee.EnsembleSampler, state):
    """``k`` steps of one ensemble (in a worker thread: float64 is set per thread)."""
    with jax.enable_x64(True):
        return sampler.run_mcmc(state, k)


# ----------------------------------------------------------------------------- assembly


def _entry(x: np.ndarray, hdi_prob: float, **more: Any) -> dict[str, Any]:
    flat = x.reshape(-1)
    lo, hi = _hdi(flat, hdi_prob)
    out = {"mean": float(np.mean(flat)), "sd": float(np.std(flat, ddof=1)), "hdi_low": lo}
    out |= {"hdi_high": hi}
    return out | {k: (_finite(v) if isinstance(v, float) else v) for k, v in more.items()}


def _assemble(
    fits, traces, stages, lp, names, segs, samplers, chains, diag, priors, hdi_prob, min_ess,
    max_draws, seed, seq, notes, fixed, held,
) -> PosteriorResult:  # fmt: skip
    E, (N, W, D), S = len(chains), chains[0].shape, len(segs)
    burn, thin = diag["burn"], diag["thin"]
    kept = [c[burn::thin] for c in chains]
    T = kept[0].shape[0]
    U = np.stack([k.reshape(T * W, D) for k in kept])  # (E, M, D), time-major
    P = _physical(names, U)
    draws = {n: P[:, :, j] for j, n in enumerate(names)}

    # Noise levels: exact conditional draws s^2 | u, y ~ Inv-Gamma(n/2, Q/2).
    Q = _batched(_v_logp_q, lp, U.reshape(-1, D), size=W // 2)[1].reshape(E, T * W, S)
    rng = np.random.default_rng(seq[2 * E])
    n_seg = np.array([s.n for s in segs], float)
    s2 = Q / rng.chisquare(np.broadcast_to(n_seg, Q.shape))
    phi = np.array([s.phi for s in segs])
    sig_ls = np.array([s.sigma_ls for s in segs])
    noise = np.sqrt(s2 / (1.0 - phi**2)) * sig_ls
    for j, seg in enumerate(segs):
        draws[seg.name] = noise[:, :, j]

    # Statistics: ESS and R-hat of model parameters from the whole chain after burn-in;
    # of the noise levels from their thinned draws.
    tau = {n: diag["tau"][:, j] for j, n in enumerate(names)}
    stats: dict[str, dict[str, Any]] = {}
    for j, n in enumerate(names):
        stats[n] = _entry(
            draws[n], hdi_prob, ess=float(diag["ess"][j]), r_hat=float(diag["rhat"][j]),
            unit=_info(n).unit, source="posterior",
            tau_steps=float(np.max(tau[n])),
        )  # fmt: skip
    nz = noise.reshape(E, T, W, S)
    with np.errstate(all="ignore"):
        tau_noise = np.stack([_tau(nz[e]) for e in range(E)]) * thin if T > 1 else np.ones((E, S))
    for j, seg in enumerate(segs):
        ess = float(np.sum(W * T * thin / tau_noise[:, j]))
        rhat = _rhat([nz[e, :, :, j] for e in range(E)])
        stats[seg.name] = _entry(
            draws[seg.name], hdi_prob, ess=ess, r_hat=rhat, unit=_unit(seg.channel),
            source="posterior",
        )  # fmt: skip

    # Priors: their spread, to say where the traces add nothing.
    prng = np.random.default_rng(seq[2 * E + 1])
    prior_sd: dict[str, float | None] = {}
    for b in dict.fromkeys([_key(n) for n in names] + list(CONTRACT_PARAMS)):
        x = priors[b].sample(prng, 20000)
        prior_sd[b] = None if x is None else float(np.std(x))
    for n in names:
        psd = prior_sd[_key(n)]
        stats[n]["prior_sd"] = psd
        stats[n]["sd_ratio"] = None if not psd else _finite(stats[n]["sd"] / psd)
    ident = _identifiability(names, draws, stats, traces, stages, fixed)
    for n in CONTRACT_PARAMS:
        if n in stats:
            continue
        src = _unsampled_source(n, stages, traces)
        if src == "prior" and n not in (fixed or {}):
            x = priors[n].sample(prng, 20000)
            stats[n] = _entry(x, hdi_prob, ess=None, r_hat=None, unit=PARAMS[n].unit)
            stats[n] |= {"source": "prior", "prior_sd": prior_sd[n], "sd_ratio": 1.0}
        else:
            v = float(held[n])
            stats[n] = {"mean": v, "sd": 0.0, "hdi_low": v, "hdi_high": v, "ess": None}
            stats[n] |= {"r_hat": None, "unit": PARAMS[n].unit, "source": "fixed"}

    # Convergence and what to do about it.
    acc = [s.acceptance_fraction for s in samplers]
    stuck = [int(np.sum(a < STUCK * np.median(a))) for a in acc]
    converged = bool(diag["ok"] and not any(stuck))
    warns = list(notes) + _convergence_warnings(diag, names, stuck, acc, N, W, E, min_ess)
    diagnostics = {
        "n_ensembles": E,
        "n_walkers": W,
        "n_steps": N,
        "burn": burn,
        "thin": thin,
        "steps_after_burn": diag["n_post"],
        "moves": "emcee DEMove",
        "tau": {n: [_finite(float(t)) for t in tau[n]] for n in names},
        "tau_max": _finite(float(np.max(diag["tau"]))),
        "tau_reliable": diag["reliable"],
        "tau_rule": f"steps after burn-in >= {TAU_RELIABLE:g} tau",
        "acceptance": [float(np.mean(a)) for a in acc],
        "stuck_walkers": stuck,
        "ess_min": _finite(float(np.min(diag["ess"]))),
        "ess_floor": float(min_ess),
        "r_hat_max": _finite(float(np.max(diag["rhat"]))),
        "r_hat_threshold": RHAT_MAX,
        "draws_kept": int(E * T * W),
    }
    predictive = _predictive(lp, U, s2, segs, names, draws, samplers, burn, thin, max_draws, seq)
    diagnostics["draws_stored"] = int(predictive["lp"].size)
    return PosteriorResult(
        stages=tuple(stages),
        trace_names=tuple(t.name for t in traces),
        names=tuple(names),
        noise_names=tuple(s.name for s in segs),
        draws=draws,
        stats=stats,
        hdi_prob=float(hdi_prob),
        converged=converged,
        warnings=tuple(warns),
        identifiability=tuple(ident),
        diagnostics=diagnostics,
        noise=tuple(
            {
                "trace": s.trace_name,
                "trace_index": s.trace,
                "channel": s.channel,
                "n": s.n,
                "model": s.model,
                "phi": s.phi,
                "residual_lag1_autocorrelation": s.rho1,
                "white_noise_band": 3.0 / math.sqrt(s.n),
            }
            for s in segs
        ),  # fmt: skip
        priors=dict(priors),
        seed=int(seed),
        fits=tuple(fits),
        timing={},
        predictive=predictive,
    )


def _unit(channel: str) -> str:
    return {"theta_deg": "deg", "x_m": "m", "force_N": "N", "torque_Nm": "N*m"}.get(channel, "A")


def _unsampled_source(name: str, stages: Sequence[str], traces: Sequence[Trace]) -> str:
    """``prior`` when the traces carry no information on an unsampled contract parameter
    (none of the channels it drives is fitted), else ``fixed``."""
    if stages == ("chain",):
        drives = ("torque_Nm",) if name == "mu" else ("force_N", "torque_Nm")
        return "fixed" if any(t.has(c) for t in traces for c in drives) else "prior"
    owner = "torque" if name == "mu" else "force"
    return "fixed" if owner in stages else "prior"


def _convergence_warnings(diag, names, stuck, acc, N, W, E, min_ess) -> list[str]:
    out = []
    tau = float(np.max(np.where(np.isfinite(diag["tau"]), diag["tau"], N)))
    need = int(math.ceil(diag["burn"] + max(TAU_RELIABLE * tau, min_ess * tau / (E * W))))
    advice = f"run at least {max(need, N + 1)} steps (--steps {max(need, N + 1)}, or --max-steps)"
    if not diag["reliable"]:
        out.append(
            f"the chains are too short: {diag['n_post']} steps after burn-in are "
            f"{diag['n_post'] / tau:.1f} autocorrelation times (tau up to {tau:.0f} steps); "
            f"emcee's tau, ESS and R-hat need at least {TAU_RELIABLE:g} tau; {advice}"
        )
    low = [n for n, e in zip(names, diag["ess"], strict=True) if e < min_ess]
    if low:
        out.append(
            f"effective sample size below {min_ess:g} for {', '.join(low)} (minimum "
            f"{np.min(diag['ess']):.0f}); {advice}"
        )
    high = [n for n, r in zip(names, diag["rhat"], strict=True) if r >= RHAT_MAX]
    if high:
        out.append(
            f"R-hat between the {E} ensembles is {np.max(diag['rhat']):.3f} (>= {RHAT_MAX}) "
            f"for {', '.join(high)}: the ensembles disagree; {advice}, and check the pair "
            "plot for several modes"
        )
    for e, k in enumerate(stuck):
        if k:
            out.append(
                f"ensemble {e}: {k} walker(s) accept far fewer proposals than the rest "
                "(stuck in a low-probability region): discard this run, fit again, run longer"
            )
    if min(float(np.mean(a)) for a in acc) < 0.1:
        out.append(
            "acceptance below 10 %: the posterior is narrow or curved for the moves; "
            "expect long autocorrelation times"
        )
    return out


def _identifiability(names, draws, stats, traces, stages, fixed) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for n in names:
        r = stats[n].get("sd_ratio")
        if r is not None and r > PRIOR_LIKE:
            out.append({
                "kind": "prior_dominated", "params": [n], "sd_ratio": r,
                "statement": f"{n} is not identified by these traces: its posterior is close to "
                f"its prior (posterior sd {100 * r:.0f} % of the prior's). It needs "
                f"{_hint(n)}.",
            })  # fmt: skip
    for n in CONTRACT_PARAMS:
        if n in names or n in (fixed or {}):
            continue
        if _unsampled_source(n, stages, traces) == "prior":
            what = "torque_Nm" if n == "mu" else "force_N or torque_Nm"
            text = (
                f"{n} is not identified: the traces record no {what} in the fitted stages, so "
                f"they say nothing about it; its posterior is its prior. It needs {HINTS[n]}."
            )
        else:
            text = f"{n} was held at its seed value, not sampled; free it to sample it"
        out.append({"kind": "not_sampled", "params": [n], "statement": text})
    corr_names, C = _corr(names, draws)
    pairs = [
        (corr_names[i], corr_names[j], float(C[i, j]))
        for i in range(len(corr_names))
        for j in range(i + 1, len(corr_names))
        if abs(C[i, j]) > RIDGE
    ]
    bell = [n for n in ("a", "b", "c") if n in names]
    x_max = max((float(np.max(t["x_m"])) for t in traces if t.has("x_m")), default=None)
    if len(bell) == 3 and x_max is not None and x_max < stats["c"]["mean"]:
        if "F_rt" in names and any(
            abs(c) > RIDGE for m, k, c in pairs if "F_rt" in (m, k) and {m, k} & set(bell)
        ):
            bell.insert(0, "F_rt")
        rho = ", ".join(f"{m}-{k} {c:+.2f}" for m, k, c in pairs if {m, k} <= set(bell))
        out.append({
            "kind": "ridge", "params": bell,
            "statement": f"{', '.join(bell[:-1])} and {bell[-1]} trade off along a ridge: the "
            f"piston never passes the bell's centre c (max x = {x_max * 1e3:.3f} mm < c = "
            f"{stats['c']['mean'] * 1e3:.3f} mm), so only the rising flank of the force is "
            f"seen" + (f" (posterior correlations {rho})" if rho else "") + ". It needs "
            f"{HINTS['c']}; or fix b.",
        })  # fmt: skip
        pairs = [p for p in pairs if not {p[0], p[1]} <= set(bell)]
    for m, k, c in pairs:
        hint, other = _hint(m), _hint(k)
        out.append({
            "kind": "ridge", "params": [m, k], "correlation": c,
            "statement": f"{m} and {k} trade off (posterior correlation {c:+.3f}): the traces "
            f"pin down a combination of them, not each one. Separating them needs {hint}"
            + ("" if other == hint else f", and {other}") + ".",
        })  # fmt: skip
    return out


def _corr(names, draws) -> tuple[list[str], np.ndarray]:
    names = [n for n in names if np.std(draws[n]) > 0]
    if not names:
        return [], np.zeros((0, 0))
    C = np.atleast_2d(np.corrcoef(np.stack([draws[n].reshape(-1) for n in names])))
    return names, np.where(np.isfinite(C), C, 0.0)


def _predictive(lp, U, s2, segs, names, draws, samplers, burn, thin, max_draws, seq):
    """Stored draws with predictions, pointwise log-likelihood and replicated data."""
    from scipy.signal import lfilter

    E, M, D = U.shape
    K = max(1, min(M, max_draws // E))
    idx = np.unique(np.linspace(0, M - 1, K).round().astype(int))
    K = idx.size
    X = U[:, idx].reshape(E * K, D)
    s = np.sqrt(s2[:, idx]).reshape(E * K, -1)
    pred, log_lik = _batched(_v_predictive, lp, X, s, size=min(E * K, 128))
    rng = np.random.default_rng(seq[2 * E + 2])
    y_rep, i0 = np.empty_like(pred), 0
    for j, seg in enumerate(segs):
        innov = rng.standard_normal((E * K, seg.n)) * s[:, j : j + 1]
        innov[:, 0] /= math.sqrt(1.0 - seg.phi**2)
        eps = lfilter([1.0], [1.0, -seg.phi], innov, axis=1)
        y_rep[:, i0 : i0 + seg.n] = pred[:, i0 : i0 + seg.n] + seg.sigma_ls * eps
        i0 += seg.n
    lps = [sm.get_log_prob()[burn::thin].reshape(-1)[idx] for sm in samplers]
    return {
        "draws": {n: v[:, idx] for n, v in draws.items()},
        "lp": np.stack(lps),
        "log_lik": log_lik.reshape(E, K, -1),
        "y_rep": y_rep.reshape(E, K, -1).astype(np.float32),
        "observed": np.concatenate([seg.measured for seg in segs]),
        "obs_trace": np.concatenate([np.full(seg.n, seg.trace_name) for seg in segs]),
        "obs_channel": np.concatenate([np.full(seg.n, seg.channel) for seg in segs]),
        "obs_time_s": np.concatenate([seg.time_s for seg in segs]),
    }
