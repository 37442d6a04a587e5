"""The log-posterior of the chain's parameters (an equinox module, vectorised over
walkers), its segments per trace and stage, and the walkers' starts."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.metrics import INTERVAL_PROB
from ewb_ident.data.trace import InputError
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.memory import physical_memory
from ewb_ident.inference.priors import Prior, param_info
from ewb_ident.inference.problem import Problem
from ewb_ident.model.params import ParamInfo
from ewb_ident.runtime.programs import on_device, program

#: The parameters every summary reports (CONTRACTS.md).
CONTRACT_PARAMS: tuple[str, ...] = ("a", "b", "c", "mu")
NOISE_MODELS: tuple[str, ...] = ("auto", "white", "ar1")

OVERDISPERSION = 2.0  #: start spread, in Laplace standard deviations
BURN_TAUS = 3.0  #: burn-in, in autocorrelation times
TAU_RELIABLE = 50.0  #: steps after burn-in (in tau) for emcee's tau estimate to be trusted
RHAT_MAX = 1.01  #: between-ensemble R-hat above which the ensembles disagree
STUCK = 0.2  #: a walker accepting less than this fraction of its ensemble's median is stuck
CHUNK = 100  #: steps between progress reports (and the least between convergence checks)
#: Steps between convergence checks, as a share of the chains' length (rounded to a whole
#: number of :data:`CHUNK`): a check's cost grows with the chains, so a long run checks
#: every 10 % of its length rather than every :data:`CHUNK` steps (19,000 steps: 1,900).
CHECK_SHARE = 0.1
MAX_KEPT = 10_000  #: most draws kept for the summary, over all ensembles (thinned)
ADAPT_STEPS = 100  #: steps of each of the two adaptation rounds (discarded)
PROPOSAL_SHARE = 0.8  #: share of steps proposed from the fitted Student-t (else DEMove)
PROPOSAL_DOF = 10.0  #: degrees of freedom of the Student-t proposal
PROPOSAL_SCALE = 1.15  #: its scale over the adaptation draws' standard deviation
PROPOSAL_K_MAX = 0.5  #: Pareto k-hat (posterior / proposal) from which DEMove runs alone
PROPOSAL_CHECK_DRAWS = 2000  #: draws from the proposal for its Pareto k-hat
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


class SampleError(InputError):
    """A posterior that cannot be set up as asked (the message says what to change)."""


#: Coordinates a whole-chain posterior typically samples (the model's free parameters
#: and a start angle), for memory estimates made before the fit says how many.
TYPICAL_DIMENSION = 16


@dataclass(frozen=True)
class SamplerSettings:
    """How the ensembles run and what is summarised, for
    :func:`ewb_ident.inference.posterior.sample` and ``sample_corrected`` (their
    ``settings``; each field may also be given to them as a keyword argument).

    Attributes
    ----------
    noise_model
        ``"auto"``, ``"white"`` or ``"ar1"`` (:mod:`ewb_ident.inference.posterior`).
    n_walkers
        Walkers per ensemble (even; default ``max(32, 4 * dimension)``).
    n_steps
        Steps per ensemble planned for the kept run (after the 200 adaptation steps); it
        stops earlier once converged (checked every 100 steps).
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
        log-likelihood of ``PosteriorResult.to_inference_data``.
    seed
        Seed of everything random (starting walkers, emcee, noise draws): the same seed
        gives the same result.
    """

    noise_model: str = "auto"
    n_walkers: int | None = None
    n_steps: int = 2000
    max_steps: int | None = None
    n_ensembles: int = 2
    min_ess: float = 400.0
    hdi_prob: float = INTERVAL_PROB
    max_draws: int = 1000
    seed: int = 0

    @classmethod
    def of(
        cls, settings: SamplerSettings | None, options: Mapping[str, Any], caller: str
    ) -> SamplerSettings:
        """``settings`` (default: the defaults) with the fields given one by one in
        ``options`` in place of its own: the keyword arguments of ``caller``, which
        raises :class:`TypeError` for a name that is no field."""
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = [name for name in options if name not in fields]
        if unknown:
            raise TypeError(f"{caller}() got an unexpected keyword argument {unknown[0]!r}")
        return dataclasses.replace(settings or cls(), **options)

    @property
    def step_limit(self) -> int:
        """Most steps per ensemble: ``max_steps``, else ten times ``n_steps``."""
        return self.max_steps or 10 * self.n_steps

    def memory_bytes(self, n_samples: int) -> float:
        """An estimate of the memory the ensembles need on traces of ``n_samples``
        samples in all: one batch of half the walkers evaluated at once (some 80 bytes
        per walker and sample: residuals of every channel and their intermediates), and
        the kept chains (every ensemble's walkers by the step limit, by
        :data:`TYPICAL_DIMENSION` coordinates of 8 bytes)."""
        walkers = self.n_walkers or 4 * TYPICAL_DIMENSION
        batch = walkers / 2 * n_samples * 80.0
        chains = self.n_ensembles * walkers * self.step_limit * TYPICAL_DIMENSION * 8.0
        return batch + chains

    def check(self, names: Mapping[str, str] | None = None, n_samples: int | None = None) -> None:
        """Raise :class:`SampleError` naming the first setting that cannot be used.

        Parameters
        ----------
        names
            How the message spells each setting (e.g. ``{"min_ess": "--min-ess"}`` for
            the command line); by default the keyword argument's name.
        n_samples
            Samples of the traces in all, when known: the walkers, ensembles and steps
            are then refused when :meth:`memory_bytes` exceeds half the machine's memory.
        """
        s = self

        def name(field: str) -> str:
            return (names or {}).get(field, field)

        if s.noise_model not in NOISE_MODELS:
            raise SampleError(
                f"{name('noise_model')} must be one of {', '.join(NOISE_MODELS)}, "
                f"got {s.noise_model!r}"
            )
        if not isinstance(s.n_ensembles, int) or s.n_ensembles < 2:
            raise SampleError(
                f"{name('n_ensembles')} must be an integer >= 2, got {s.n_ensembles!r}: R-hat "
                "needs independent ensembles (the walkers of one ensemble are not independent "
                "chains)"
            )
        if not isinstance(s.n_steps, int) or s.n_steps < 10:
            raise SampleError(f"{name('n_steps')} must be an integer >= 10, got {s.n_steps!r}")
        if s.max_steps is not None and (
            not isinstance(s.max_steps, int) or s.max_steps < s.n_steps
        ):
            raise SampleError(
                f"{name('max_steps')} must be an integer >= {name('n_steps')} ({s.n_steps}), "
                f"got {s.max_steps!r}"
            )
        if s.n_walkers is not None and (
            not isinstance(s.n_walkers, int) or s.n_walkers % 2 or s.n_walkers < 4
        ):
            raise SampleError(
                f"{name('n_walkers')} must be an even integer >= 4, got {s.n_walkers!r}"
            )
        if not 0.0 < s.hdi_prob < 1.0:
            raise SampleError(
                f"{name('hdi_prob')} must lie strictly between 0 and 1, got {s.hdi_prob!r}"
            )
        if not (math.isfinite(s.min_ess) and s.min_ess > 0):
            raise SampleError(f"{name('min_ess')} must be a finite number > 0, got {s.min_ess!r}")
        if not isinstance(s.max_draws, int) or s.max_draws < s.n_ensembles:
            raise SampleError(
                f"{name('max_draws')} must be an integer >= {name('n_ensembles')} "
                f"({s.n_ensembles}), got {s.max_draws!r}"
            )
        if not isinstance(s.seed, int) or s.seed < 0:
            raise SampleError(f"{name('seed')} must be a non-negative integer, got {s.seed!r}")
        if n_samples is not None:
            need, have = s.memory_bytes(n_samples), physical_memory()
            if need > 0.5 * have:
                walkers = s.n_walkers or f"about {4 * TYPICAL_DIMENSION} (the default)"
                raise SampleError(
                    f"{walkers} walkers in {s.n_ensembles} ensembles for up to {s.step_limit}"
                    f" steps on {n_samples:,} samples need about {need / 1e9:.3g} GB, more than"
                    f" half this machine's {have / 1e9:.3g} GB; use fewer"
                    f" {name('n_walkers')}, {name('n_ensembles')} or {name('n_steps')}"
                )


# ----------------------------------------------------------------------------- model


def _ar1_q(r: jnp.ndarray, phi: jnp.ndarray) -> jnp.ndarray:
    """``(1 - phi^2) r0^2 + sum (r_t - phi r_{t-1})^2``: the AR(1) quadratic form."""
    e = r[1:] - phi * r[:-1]
    return (1.0 - phi * phi) * r[0] * r[0] + jnp.sum(e * e)


class _LogPost(eqx.Module):
    """Log posterior of the unconstrained vector ``u`` (noise levels marginalised)."""

    problems: tuple[Problem, ...]
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
            sig = prob.sigmas(u[i0:i1], data)
            for k, pred in enumerate(prob.predict(u[i0:i1], data)):
                tr = data["traces"][k]
                out += [(pred[ch], tr[ch], sig[k][ch]) for ch in prob.channels[k]]
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


@program
def v_logp_q(lp: _LogPost, X):
    return jax.vmap(lp.with_q)(X)


@program
def v_predictive(lp: _LogPost, X, S):
    return jax.vmap(lp.predictive)(X, S)


def batched(fn, X: np.ndarray, *extra: np.ndarray, size: int):
    """``fn(X, *extra)`` over the rows of X in batches of one size (one compilation);
    ``fn`` is a program with its other arguments bound (e.g. ``v_logp_q.bind(lp)``)."""
    n = X.shape[0]
    pad = (-n) % size
    arrays = [np.concatenate([a, np.repeat(a[:1], pad, 0)]) for a in (X, *extra)]
    outs = []
    for i in range(0, n + pad, size):
        res = fn(*(a[i : i + size] for a in arrays))
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


def build(fits: Sequence[FitResult], priors: Mapping[str, Prior], noise_model: str, time_s):
    names: list[str] = []
    slices, u0 = [], []
    for f in fits:
        slices.append((len(names), len(names) + len(f.corr_names)))
        names += list(f.corr_names)
        u0.append(np.asarray(f.u, float))
    bases = [key(n) for n in names]
    lp = _LogPost(
        problems=tuple(f.problem for f in fits),
        datas=tuple(f.data for f in fits),
        phi=on_device(np.zeros(sum(len(c) for f in fits for c in f.problem.channels))),
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
    lp = eqx.tree_at(lambda m: m.phi, lp, on_device(np.array([s.phi for s in segs])))
    return lp, tuple(names), u, tuple(segs)


def walker_starts(lp, fits, u0, n_walkers, rngs) -> list[np.ndarray]:
    """Overdispersed starting walkers around ``u0``: the least-squares fits' Laplace
    approximation (their correlation and standard errors, in u), its sd x OVERDISPERSION."""
    sd, blocks = [], []
    for f in fits:
        blocks.append(np.where(np.isfinite(f.corr), f.corr, 0.0) if f.corr.size else f.corr)
        for n, u in zip(f.corr_names, f.u, strict=True):
            se = f.stderr.get(n)
            slope = abs(float(info_of(n).dp_du(u)))
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
    logp_q = v_logp_q.bind(lp)
    for rng in rngs:
        p = u0 + OVERDISPERSION * rng.standard_normal((n_walkers, u0.size)) @ L.T
        for _ in range(30):
            bad = ~np.isfinite(batched(logp_q, p, size=n_walkers // 2)[0])
            if not bad.any():
                break
            p[bad] = (
                u0 + 0.5 * OVERDISPERSION * rng.standard_normal((int(bad.sum()), u0.size)) @ L.T
            )
        else:
            raise SampleError("no finite log-posterior near the least-squares optimum")
        starts.append(p)
    return starts


def key(name: str) -> str:
    """The parameter a sampled name belongs to: ``c`` of ``c[1]`` (per trace); a
    mechanism's ``"variant.param"`` as it is."""
    return name if "." in name else name.split("[")[0]


def info_of(name: str) -> ParamInfo:
    return param_info(key(name))


def hint_of(name: str) -> str:
    return HINTS.get(key(name), "a trace in which this mechanism acts strongly")


def to_physical_columns(names: Sequence[str], u: np.ndarray) -> np.ndarray:
    """Unconstrained -> physical values (NumPy), column by column."""
    u = np.asarray(u, float)
    cols = [info_of(n).to_physical(u[..., j]) for j, n in enumerate(names)]
    return np.stack([np.asarray(c, float) for c in cols], axis=-1)
