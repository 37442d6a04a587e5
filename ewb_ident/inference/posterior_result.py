"""What a posterior run returns (:class:`PosteriorResult`): intervals, diagnostics,
identifiability, the predictive bands, and their JSON form."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ewb_ident.data.metrics import ar1_filter
from ewb_ident.data.trace import Trace
from ewb_ident.inference.chains import (
    autocorr_time,
    convergence_warnings,
    hdi,
    import_arviz,
    split_rhat,
)
from ewb_ident.inference.fit_result import FitResult, finite_or_none
from ewb_ident.inference.log_posterior import (
    CONTRACT_PARAMS,
    HINTS,
    PRIOR_LIKE,
    RHAT_MAX,
    RIDGE,
    STUCK,
    TAU_RELIABLE,
    SamplerSettings,
    batched,
    hint_of,
    info_of,
    key,
    to_physical_columns,
    v_logp_q,
    v_predictive,
)
from ewb_ident.inference.priors import Prior
from ewb_ident.model.params import PARAMS

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
            "priors": {n: self.priors[key(n)].to_json() for n in self.names}
            | {n: self.priors[n].to_json() for n in CONTRACT_PARAMS},
            "least_squares": {
                n: finite_or_none(float(v))
                for f in self.fits
                for n, v in zip(f.corr_names, to_physical_columns(f.corr_names, f.u), strict=True)
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
        az = import_arviz()
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


# ----------------------------------------------------------------------------- assembly


def entry(x: np.ndarray, hdi_prob: float, **more: Any) -> dict[str, Any]:
    flat = x.reshape(-1)
    lo, hi = hdi(flat, hdi_prob)
    out = {"mean": float(np.mean(flat)), "sd": float(np.std(flat, ddof=1)), "hdi_low": lo}
    out |= {"hdi_high": hi}
    return out | {k: (finite_or_none(v) if isinstance(v, float) else v) for k, v in more.items()}


def assemble(
    fits, traces, stages, lp, names, segs, run, priors, settings: SamplerSettings, notes, fixed,
    held,
) -> PosteriorResult:  # fmt: skip
    """The result record from the chains of ``run`` (:func:`~ewb_ident.inference.chains.
    run_chains`): intervals, diagnostics, identifiability, predictive bands."""
    samplers, chains, diag, seq = run.samplers, run.chains, run.diag, run.seq
    hdi_prob = settings.hdi_prob
    E, (N, W, D), S = len(chains), chains[0].shape, len(segs)
    burn, thin = diag["burn"], diag["thin"]
    kept = [c[burn::thin] for c in chains]
    T = kept[0].shape[0]
    U = np.stack([k.reshape(T * W, D) for k in kept])  # (E, M, D), time-major
    P = to_physical_columns(names, U)
    draws = {n: P[:, :, j] for j, n in enumerate(names)}

    # Noise levels: exact conditional draws s^2 | u, y ~ Inv-Gamma(n/2, Q/2).
    Q = batched(v_logp_q.bind(lp), U.reshape(-1, D), size=W // 2)[1].reshape(E, T * W, S)
    rng = np.random.default_rng(seq[2 * E])
    n_seg = np.array([s.n for s in segs], float)
    s2 = Q / rng.chisquare(np.broadcast_to(n_seg, Q.shape))
    phi = np.array([s.phi for s in segs])
    sig_ls = np.array([s.sigma_ls for s in segs])
    noise = np.sqrt(s2 / (1.0 - phi**2)) * sig_ls
    for j, seg in enumerate(segs):
        draws[seg.name] = noise[:, :, j]

    stats = _parameter_stats(names, draws, diag, hdi_prob)
    stats |= _noise_stats(segs, draws, noise.reshape(E, T, W, S), thin, hdi_prob)
    prng = np.random.default_rng(seq[2 * E + 1])
    prior_sd = _prior_spread(names, stats, priors, prng)
    ident = _identifiability(names, draws, stats, traces, stages, fixed)
    _unsampled_stats(stats, stages, traces, priors, prng, prior_sd, fixed, held, hdi_prob)

    acc = [s.acceptance_fraction for s in samplers]
    stuck = [int(np.sum(a < STUCK * np.median(a))) for a in acc]
    converged = bool(diag["ok"] and not any(stuck))
    warns = list(notes) + convergence_warnings(diag, names, stuck, acc, N, W, E, settings.min_ess)
    diagnostics = _diagnostics(diag, names, acc, stuck, E, N, W, T, settings.min_ess)
    predictive = _predictive(
        lp, U, s2, segs, names, draws, samplers, burn, thin, settings.max_draws, seq
    )
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
        noise=tuple(_noise_record(s) for s in segs),
        priors=dict(priors),
        seed=int(settings.seed),
        fits=tuple(fits),
        timing={},
        predictive=predictive,
    )


def _parameter_stats(names, draws, diag, hdi_prob) -> dict[str, dict[str, Any]]:
    """Summary of each model parameter; ESS and R-hat from the whole chain after burn-in."""
    stats: dict[str, dict[str, Any]] = {}
    for j, n in enumerate(names):
        stats[n] = entry(
            draws[n], hdi_prob, ess=float(diag["ess"][j]), r_hat=float(diag["rhat"][j]),
            unit=info_of(n).unit, source="posterior",
            tau_steps=float(np.max(diag["tau"][:, j])),
        )  # fmt: skip
    return stats


def _noise_stats(segs, draws, nz, thin, hdi_prob) -> dict[str, dict[str, Any]]:
    """Summary of each noise level (``nz``: ensembles, steps, walkers, segments); ESS and
    R-hat from their thinned draws."""
    E, T, W, S = nz.shape
    with np.errstate(all="ignore"):
        if T > 1:
            tau_noise = np.stack([autocorr_time(nz[e]) for e in range(E)]) * thin
        else:
            tau_noise = np.ones((E, S))
    stats: dict[str, dict[str, Any]] = {}
    for j, seg in enumerate(segs):
        ess = float(np.sum(W * T * thin / tau_noise[:, j]))
        rhat = split_rhat([nz[e, :, :, j] for e in range(E)])
        stats[seg.name] = entry(
            draws[seg.name], hdi_prob, ess=ess, r_hat=rhat, unit=_unit(seg.channel),
            source="posterior",
        )  # fmt: skip
    return stats


def _prior_spread(names, stats, priors, prng) -> dict[str, float | None]:
    """Each prior's standard deviation (by sampling), and each parameter's posterior sd
    over it: where the traces add nothing, the ratio is near 1."""
    prior_sd: dict[str, float | None] = {}
    for b in dict.fromkeys([key(n) for n in names] + list(CONTRACT_PARAMS)):
        x = priors[b].sample(prng, 20000)
        prior_sd[b] = None if x is None else float(np.std(x))
    for n in names:
        psd = prior_sd[key(n)]
        stats[n]["prior_sd"] = psd
        stats[n]["sd_ratio"] = None if not psd else finite_or_none(stats[n]["sd"] / psd)
    return prior_sd


def _unsampled_stats(stats, stages, traces, priors, prng, prior_sd, fixed, held, hdi_prob):
    """A line for each contract parameter that was not sampled: its prior where the
    stages do not reach it, else its held value."""
    for n in CONTRACT_PARAMS:
        if n in stats:
            continue
        src = _unsampled_source(n, stages, traces)
        if src == "prior" and n not in (fixed or {}):
            x = priors[n].sample(prng, 20000)
            stats[n] = entry(x, hdi_prob, ess=None, r_hat=None, unit=PARAMS[n].unit)
            stats[n] |= {"source": "prior", "prior_sd": prior_sd[n], "sd_ratio": 1.0}
        else:
            v = float(held[n])
            stats[n] = {"mean": v, "sd": 0.0, "hdi_low": v, "hdi_high": v, "ess": None}
            stats[n] |= {"r_hat": None, "unit": PARAMS[n].unit, "source": "fixed"}


def _diagnostics(diag, names, acc, stuck, E, N, W, T, min_ess) -> dict[str, Any]:
    """The MCMC diagnostics of the contract (``diagnostics`` in ``summary.json``)."""
    return {
        "n_ensembles": E,
        "n_walkers": W,
        "n_steps": N,
        "burn": diag["burn"],
        "thin": diag["thin"],
        "steps_after_burn": diag["n_post"],
        "moves": diag.get("moves", "emcee DEMove"),
        "tau": {
            n: [finite_or_none(float(t)) for t in diag["tau"][:, j]] for j, n in enumerate(names)
        },
        "tau_max": finite_or_none(float(np.max(diag["tau"]))),
        "tau_reliable": diag["reliable"],
        "tau_rule": f"steps after burn-in >= {TAU_RELIABLE:g} tau",
        "acceptance": [float(np.mean(a)) for a in acc],
        "stuck_walkers": stuck,
        "ess_min": finite_or_none(float(np.min(diag["ess"]))),
        "ess_floor": float(min_ess),
        "r_hat_max": finite_or_none(float(np.max(diag["rhat"]))),
        "r_hat_threshold": RHAT_MAX,
        "draws_kept": int(E * T * W),
    }


def _noise_record(s) -> dict[str, Any]:
    """One noise segment as ``summary.json`` lists it."""
    return {
        "trace": s.trace_name,
        "trace_index": s.trace,
        "channel": s.channel,
        "n": s.n,
        "model": s.model,
        "phi": s.phi,
        "residual_lag1_autocorrelation": s.rho1,
        "white_noise_band": 3.0 / math.sqrt(s.n),
    }


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


def _identifiability(names, draws, stats, traces, stages, fixed) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for n in names:
        r = stats[n].get("sd_ratio")
        if r is not None and r > PRIOR_LIKE:
            out.append({
                "kind": "prior_dominated", "params": [n], "sd_ratio": r,
                "statement": f"{n} is not identified by these traces: its posterior is close to "
                f"its prior (posterior sd {100 * r:.0f} % of the prior's). It needs "
                f"{hint_of(n)}.",
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
    past_c = x_max is not None and "c" in stats and x_max >= stats["c"]["mean"]
    for m, k, c in pairs:
        hint, other = hint_of(m), hint_of(k)
        if past_c and {m, k} <= {"F_rt", "a", "b", "c"}:
            # The traces do pass c: asking for an apply past c would be wrong for them.
            hint = other = (
                f"applies that dwell on both flanks of the bell (the piston already passes c: "
                f"max x = {x_max * 1e3:.3f} mm > c = {stats['c']['mean'] * 1e3:.3f} mm), or "
                "less noise on x_m and force_N"
            )
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
    E, M, D = U.shape
    K = max(1, min(M, max_draws // E))
    idx = np.unique(np.linspace(0, M - 1, K).round().astype(int))
    K = idx.size
    X = U[:, idx].reshape(E * K, D)
    s = np.sqrt(s2[:, idx]).reshape(E * K, -1)
    pred, log_lik = batched(v_predictive.bind(lp), X, s, size=min(E * K, 128))
    rng = np.random.default_rng(seq[2 * E + 2])
    y_rep, i0 = np.empty_like(pred), 0
    for j, seg in enumerate(segs):
        innov = rng.standard_normal((E * K, seg.n)) * s[:, j : j + 1]
        innov[:, 0] /= math.sqrt(1.0 - seg.phi**2)
        eps = ar1_filter(innov, seg.phi)
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
