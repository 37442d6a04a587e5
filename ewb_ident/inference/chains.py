"""Running emcee ensembles until the effective sample size is reached: burn-in, thinning,
restarts of stuck chains, and the convergence diagnostics (tau, R-hat)."""

from __future__ import annotations

import functools
import math
import sys
import time
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import emcee
import jax
import numpy as np
import scipy.linalg

from ewb_ident.data.stages import STAGE_COLUMNS, STAGE_PARAMS
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.log_posterior import (
    ADAPT_STEPS,
    BURN_TAUS,
    CHECK_SHARE,
    CHUNK,
    MAX_KEPT,
    POOR_FIT,
    PROPOSAL_CHECK_DRAWS,
    PROPOSAL_DOF,
    PROPOSAL_K_MAX,
    PROPOSAL_SCALE,
    PROPOSAL_SHARE,
    RHAT_MAX,
    TAU_RELIABLE,
    SampleError,
    SamplerSettings,
    batched,
    key,
    to_physical_columns,
    v_logp_q,
    walker_starts,
)
from ewb_ident.runtime.threads import parallel_map

# ----------------------------------------------------------------------------- diagnostics


def autocorr_time(x: np.ndarray, c: float = 5.0) -> np.ndarray:
    """emcee's integrated autocorrelation time per column of x (steps, walkers, params):
    ``emcee.autocorr.integrated_time(x, c=c, tol=0)``, every walker's autocorrelation
    function from one real FFT of all series instead of one complex FFT per walker and
    parameter (some 14,000 small transforms per posterior;
    ``benchmarks/bench_autocorr.py``). The same estimate, the walkers summed in emcee's
    order; the transforms' round-off differs, so the times agree with emcee's to about
    1e-15 relative (``tests/test_posterior.py`` checks 1e-12 on 60 chain shapes)."""
    x = np.asarray(x, dtype=float)
    n_t, n_w, n_d = x.shape
    n = emcee.autocorr.next_pow_two(n_t)
    series = np.ascontiguousarray(np.moveaxis(x, 0, -1))  # (walkers, params, steps)
    spec = np.fft.rfft(series - np.mean(series, axis=-1, keepdims=True), n=2 * n, axis=-1)
    acf = np.fft.irfft(spec.real**2 + spec.imag**2, n=2 * n, axis=-1)[..., :n_t]
    acf /= acf[..., :1]
    f = np.zeros((n_d, n_t))
    for k in range(n_w):  # emcee's order of summation
        f += acf[k]
    f /= n_w
    taus = 2.0 * np.cumsum(f, axis=-1) - 1.0
    tau = np.empty(n_d)
    for d in range(n_d):
        tau[d] = taus[d, emcee.autocorr.auto_window(taus[d], c)]
    return tau


def split_rhat(per_ensemble: Sequence[np.ndarray]) -> float:
    """Rank-normalised split R-hat between ensembles; each is (steps, walkers), pooled
    over walkers in time order so that arviz's split halves are early and late draws."""
    az = import_arviz()
    with np.errstate(all="ignore"):
        value = float(az.rhat(np.stack([x.reshape(-1) for x in per_ensemble])))
    return value if math.isfinite(value) else math.inf  # e.g. a parameter that never moved


def _diagnose(chains: list[np.ndarray], phys, min_ess: float, final: bool = True) -> dict[str, Any]:
    """Burn-in, thinning, tau, ESS and R-hat from the chains (steps, walkers, params);
    not ``final``: R-hat only when the other criteria hold (NaN otherwise)."""
    N, W, _ = chains[0].shape
    with np.errstate(all="ignore"):
        tau0 = np.nan_to_num(np.max([autocorr_time(phys(c[N // 2 :])) for c in chains]), nan=N)
        burn = int(min(math.ceil(BURN_TAUS * tau0), N // 2))
        post = [phys(c[burn:]) for c in chains]
        tau = np.nan_to_num(np.stack([autocorr_time(p) for p in post]), nan=np.inf)  # (E, D)
    n_post = N - burn
    ess = np.sum(W * n_post / tau, axis=0)
    reliable = bool(n_post >= TAU_RELIABLE * np.max(tau))
    # R-hat (the costly criterion) only when it can decide, or for the final summary.
    rhat = np.full(tau.shape[1], np.nan)
    if final or (reliable and np.min(ess) >= min_ess):
        import_arviz()  # here, not in the threads
        # Each a sort of every draw (18 ms), side by side: NumPy sorts without Python's lock.
        rhat = np.array(
            parallel_map(lambda j: split_rhat([p[:, :, j] for p in post]), range(tau.shape[1]))
        )
    # Thinning: half a tau, and no more kept draws than MAX_KEPT over the ensembles.
    thin = max(1, int(0.5 * min(np.min(tau), N)), math.ceil(len(chains) * W * n_post / MAX_KEPT))
    return {
        "burn": burn,
        "thin": thin,
        "tau": tau,
        "ess": ess,
        "rhat": rhat,
        "n_post": n_post,
        "reliable": reliable,
        "ok": bool(reliable and np.min(ess) >= min_ess and np.max(rhat) < RHAT_MAX),
    }


def import_arviz():
    """ArviZ, imported without its refactoring notice (a ``FutureWarning``). Once it is
    imported the warning filters are left alone: changing them is not safe in threads,
    and :func:`split_rhat` runs in several."""
    done = sys.modules.get("arviz")
    if done is not None and not getattr(done.__spec__, "_initializing", False):
        return done
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # arviz's refactoring notice
        import arviz

    return arviz


def hdi(x: np.ndarray, prob: float) -> tuple[float, float]:
    """Highest-density interval of a 1-D sample (the narrowest interval holding prob)."""
    s = np.sort(x)
    k = max(1, int(math.floor(prob * s.size)))
    widths = s[k:] - s[: s.size - k]
    i = int(np.argmin(widths))
    return float(s[i]), float(s[i + k])


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


class StudentProposal:
    """An independence proposal for :class:`emcee.moves.MHMove`: a multivariate Student-t
    whose centre and scale come from earlier draws of the same ensemble (frozen before
    the draws it proposes for are kept, so the chain is an ordinary Metropolis-Hastings
    chain with a fixed kernel).

    Parameters
    ----------
    draws
        Earlier draws of the ensemble, shape (n, dimension), unconstrained coordinates.
    """

    def __init__(self, draws: np.ndarray):
        D = draws.shape[1]
        self.mean = np.mean(draws, axis=0)
        C = np.atleast_2d(np.cov(draws.T)) * PROPOSAL_SCALE**2
        # A ridge for an ensemble that has not spread in some direction (never singular).
        C += np.eye(D) * 1e-10 * max(float(np.trace(C)) / D, 1e-300)
        self.chol = np.linalg.cholesky(C)
        self.dim = D

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """Log density up to a constant at the rows of ``x``."""
        y = scipy.linalg.solve_triangular(self.chol, (x - self.mean).T, lower=True)
        return -0.5 * (PROPOSAL_DOF + self.dim) * np.log1p(np.sum(y * y, axis=0) / PROPOSAL_DOF)

    def draw(self, n: int, random) -> np.ndarray:
        """``n`` draws, shape (n, dimension), from ``random`` (a NumPy RandomState)."""
        z = random.standard_normal((n, self.dim))
        g = random.chisquare(PROPOSAL_DOF, n) / PROPOSAL_DOF
        return self.mean + (z @ self.chol.T) / np.sqrt(g)[:, None]

    def __call__(self, coords: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        """New positions for every walker, and ``log q(x) - log q(x')`` (emcee's order)."""
        x = self.draw(coords.shape[0], random)
        return x, self.log_density(coords) - self.log_density(x)


def _checked(s: emcee.EnsembleSampler, logp) -> tuple[StudentProposal | None, float]:
    """The Student-t proposal fitted to the later half of ``s``'s draws (``None`` when
    its tails are too light for the posterior: the Pareto k-hat of the importance
    weights posterior / proposal on :data:`PROPOSAL_CHECK_DRAWS` draws from it (PSIS,
    Vehtari et al.) at or above :data:`PROPOSAL_K_MAX`. An independence sampler is
    only reliable while those weights stay bounded: with heavier posterior tails (a
    curved ridge, a parameter at a bound) a walker that reaches them stays stuck), and
    the k-hat."""
    prop = StudentProposal(_later_half(s))
    rs = np.random.RandomState()
    rs.set_state(s.random_state)  # a copy: the sampler's own stream is not advanced
    x = prop.draw(PROPOSAL_CHECK_DRAWS, rs)
    lw = logp(x) - prop.log_density(x)
    finite = np.isfinite(lw)
    if not finite.any():
        return None, math.inf
    lw = np.where(finite, lw, np.min(lw[finite]) - 50.0)  # outside the prior: ~zero weight
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        k_hat = float(import_arviz().psislw(lw - np.max(lw))[1])
    return (prop if k_hat < PROPOSAL_K_MAX else None), k_hat


def _kernel_name(proposal: StudentProposal | None, k_hat: float) -> str:
    if proposal is None:
        return f"emcee DEMove (Student-t proposal refused: Pareto k {k_hat:.2f})"
    return (
        f"emcee DEMove {100 * (1 - PROPOSAL_SHARE):.0f} % + Student-t independence MHMove "
        f"{100 * PROPOSAL_SHARE:.0f} % (Pareto k {k_hat:.2f})"
    )


def _moves(proposal: StudentProposal | None):
    if proposal is None:
        return emcee.moves.DEMove()
    return [
        (emcee.moves.DEMove(), 1.0 - PROPOSAL_SHARE),
        (emcee.moves.MHMove(proposal), PROPOSAL_SHARE),
    ]


def _sampler(W, D, logp, proposal, random_state) -> emcee.EnsembleSampler:
    smp = emcee.EnsembleSampler(W, D, logp, vectorize=True, moves=_moves(proposal))
    smp.random_state = random_state
    if not np.array_equal(smp.random_state[1], random_state[1]):
        raise RuntimeError("emcee did not accept the seed of its random state")
    return smp


def _adapt(pool, samplers, states, W, D, logp, report) -> tuple[list, list, list[str]]:
    """The adaptation: :data:`ADAPT_STEPS` of differential evolution, then as many with
    the Student-t proposal fitted to each ensemble's later half of them (when it passes
    :func:`_checked`), refitted to the later half of those and checked again. Returns
    fresh samplers with the final kernel, the states they start from and each kernel's
    name; every adaptation draw is discarded."""
    for _round in range(2):
        states = list(pool.map(functools.partial(_advance, ADAPT_STEPS), samplers, states))
        report(ADAPT_STEPS)
        checked = [_checked(s, logp) for s in samplers]
        samplers = [
            _sampler(W, D, logp, p, s.random_state)
            for (p, _), s in zip(checked, samplers, strict=True)
        ]
    return samplers, states, [_kernel_name(p, k) for p, k in checked]


def _later_half(s: emcee.EnsembleSampler) -> np.ndarray:
    c = s.get_chain()
    return c[c.shape[0] // 2 :].reshape(-1, c.shape[2])


def run_chains(
    lp, fits, names, u0, priors, settings: SamplerSettings,
    progress,
) -> _Run:  # fmt: skip
    """Independent emcee ensembles from the least-squares optimum: an adaptation
    (:func:`_adapt`, discarded), then the kept run, stopped once every convergence
    criterion holds (checked every :data:`CHUNK` steps, or every :data:`CHECK_SHARE`
    of the chains' length once that is more, and wherever the run was planned to end)
    or extended until they do, up to ``max_steps``."""
    s = settings
    n_walkers, n_steps, max_steps = s.n_walkers, s.n_steps, s.step_limit
    n_ensembles, min_ess, seed = s.n_ensembles, s.min_ess, s.seed
    excluded = [
        n
        for n, v in zip(names, to_physical_columns(names, u0), strict=True)
        if not np.isfinite(float(priors[key(n)].logpdf(v, np)))
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
    starts = walker_starts(lp, fits, u0, W, [np.random.default_rng(s) for s in seq[:n_ensembles]])
    t_compile = time.perf_counter()

    logp_q = v_logp_q.bind(lp)

    def logp(X: np.ndarray) -> np.ndarray:
        return batched(logp_q, X, size=W // 2)[0]

    samplers = [
        _sampler(
            W, D, logp, None,
            np.random.RandomState(int(seq[n_ensembles + e].generate_state(1)[0])).get_state(),
        )
        for e in range(n_ensembles)
    ]  # fmt: skip
    phys = functools.partial(to_physical_columns, names)
    adapt = 2 * ADAPT_STEPS
    done, target, states = 0, n_steps, list(starts)
    check = CHUNK  # the step of the next convergence check
    adapted = 0

    def report(k: int) -> None:
        nonlocal adapted
        adapted += k
        if progress is not None:
            progress(adapted + done, adapt + target)

    with ThreadPoolExecutor(max_workers=n_ensembles) as pool:
        samplers, states, kernels = _adapt(pool, samplers, states, W, D, logp, report)
        while True:
            k = min(CHUNK, target - done)
            states = list(pool.map(functools.partial(_advance, k), samplers, states))
            done += k
            report(0)
            if done < min(check, target):  # target <= max_steps
                continue
            check = next_check(done)
            chains = [s.get_chain() for s in samplers]
            diag = _diagnose(chains, phys, min_ess, final=False)
            if diag["ok"] or done >= max_steps:
                if np.isnan(diag["rhat"]).any():
                    diag = _diagnose(chains, phys, min_ess)
                break
            if done < target:
                continue
            tau = float(np.max(np.where(np.isfinite(diag["tau"]), diag["tau"], done)))
            need = diag["burn"] + max(TAU_RELIABLE * tau, min_ess * tau / (n_ensembles * W))
            target = int(min(max_steps, max(1.2 * need, done + CHUNK)))
    diag["moves"] = (
        kernels[0]
        if len(set(kernels)) == 1
        else "; ".join(f"ensemble {e}: {k}" for e, k in enumerate(kernels))
    )
    return _Run(samplers, chains, diag, seq, t_compile, time.perf_counter())


def next_check(done: int) -> int:
    """The step of the convergence check after one at step ``done``: :data:`CHUNK` steps
    later, or :data:`CHECK_SHARE` of ``done`` rounded to whole chunks once that is more
    (a check's autocorrelation times cost in proportion to the chains' length)."""
    return done + CHUNK * max(1, round(CHECK_SHARE * done / CHUNK))


def poor(f: FitResult) -> bool:
    """A fit whose residuals are far above the sensor noise on some channel: a local
    minimum of the least squares (or physics the model leaves out)."""
    return any(
        f.sigma[k][ch] > POOR_FIT * max(f.noise[k][ch], 1e-300)
        for k in range(len(f.sigma))
        for ch in f.sigma[k]
    )


def restart_chain(traces, first: FitResult, kw: dict, notes: list[str]) -> FitResult:
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


def convergence_warnings(diag, names, stuck, acc, N, W, E, min_ess) -> list[str]:
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
