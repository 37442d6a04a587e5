"""The corrected model: the seed chain with the diagnosed (or named) catalog
mechanisms, refitted from the voltage, with every parameter's value and standard error."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import jax.numpy as jnp
import numpy as np

from ewb_ident.data.trace import Trace
from ewb_ident.diagnosis.learned_spec import LearnedSpec, TermError
from ewb_ident.diagnosis.session import (
    BIC_THRESHOLD,
    DiagnoseError,
    Session,
    bic_evidence,
    chain_baseline,
    chain_metrics,
    metrics_json,
    rho_cap_of,
    stage_order,
)
from ewb_ident.inference.augmented import fit_mechanisms
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.log_posterior import CONTRACT_PARAMS
from ewb_ident.inference.uncertainty import POORLY_DETERMINED
from ewb_ident.mechanisms import AbstractMechanism, variants
from ewb_ident.mechanisms.learned import LearnedTerm, term_at, with_bases
from ewb_ident.model.numerics import numerics


def corrected_of(trace: Trace, chain_fits, data, sigma, discoveries=()) -> CorrectedFit | None:
    """The diagnosis's corrected whole chain as a :class:`CorrectedFit`: its catalog
    mechanisms and learned terms (``discoveries``: the discoveries the terms were learned
    from, by place)."""
    catalog = {m.variant for m in variants()}
    by_place = {d.place: d for d in discoveries}
    f0, f1 = chain_fits[0], chain_fits[-1]
    docs = []
    for m in f1.mechanisms:
        if isinstance(m, LearnedTerm) and m.place in by_place:
            d = by_place[m.place]
            docs.append(learned_doc(LearnedSpec.of(d, m.coefficients), d.equation(m.coefficients)))
        elif m.variant not in catalog:
            return None
    if not f1.mechanisms:
        return None
    notes = () if f1.converged else ("the corrected whole-chain fit did not converge",)
    ev = bic_evidence(f1, f0, sigma, rho_max=rho_cap_of(f1.mechanisms))
    return corrected_record(trace, f0, f1, data, ev, notes, docs)


def corrected_record(trace: Trace, f0, f1, data, ev, notes, learned=()) -> CorrectedFit:
    """A :class:`CorrectedFit` from the baseline ``f0`` and corrected ``f1`` chain fits
    (``learned``: the refitted terms' documents)."""
    tables = model_tables([f0, f1], True)
    return CorrectedFit(
        trace_name=trace.name,
        mechanisms=tuple(m.variant for m in f1.mechanisms),
        params=tables["augmented_params"],
        stderr=tables["augmented_stderr"],
        metrics=chain_metrics(trace, f1),
        baseline_params=tables["baseline_params"],
        baseline_stderr=tables["baseline_stderr"],
        baseline_metrics=chain_metrics(trace, f0),
        stderr_white=tables["augmented_stderr_white"],
        baseline_stderr_white=tables["baseline_stderr_white"],
        converged=bool(f1.converged),
        delta_bic=float(ev["delta_bic"]),
        warnings=(*notes, *at_bounds(f1)),
        predictions={k: np.asarray(v) for k, v in f1.predictions[0].items()},
        fit=f1,
        data=data,
        learned=tuple(learned),
        context={"omega_ref": float(data["omega_ref"])},
    )


def at_bounds(f: FitResult) -> list[str]:
    """Words for each mechanism parameter with hard bounds that the fit left at one of
    them, where it has no slope and so no standard error."""
    out = []
    for m in f.mechanisms:
        for info in m.param_info():
            v = float(m.values()[info.name])
            if info.transform == "logit" and not (
                info.lower + 1e-6 * (info.upper - info.lower)
                < v
                < info.upper - 1e-6 * (info.upper - info.lower)
            ):
                side = "lower" if v - info.lower < info.upper - v else "upper"
                out.append(
                    f"{m.variant}.{info.name} = {v:.3g} {info.unit} sits at its {side} "
                    "bound, where the fit leaves it (no standard error)"
                )
    return out


def with_terms(data: dict[str, Any], trace: Trace, specs, values) -> dict[str, Any]:
    """``data`` with the basis series of learned terms (:class:`LearnedSpec`) rebuilt on
    ``trace`` with the model at ``values``."""
    return with_bases(data, {s.place: s.basis(s.signals_on(trace, values)) for s in specs})


def _refitted(spec: LearnedSpec, f: FitResult) -> LearnedSpec:
    return replace(spec, coef=term_at(f.mechanisms, spec.place).coefficients)


def learned_doc(spec: LearnedSpec, equation: str) -> dict[str, Any]:
    """A learned term as ``fit.json`` lists it: where it acts, its equation (SI), what it
    depends on and its basis."""
    return {
        "place": spec.place,
        "equation": equation,
        "depends_on": list(spec.depends_on),
        "basis": spec.to_json(),
    }


def merged_spread(spreads: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Per parameter, the largest form spread of several learned terms."""
    out: dict[str, float] = {}
    for spread in spreads:
        for k, v in spread.items():
            out[k] = max(out.get(k, 0.0), float(v))
    return out


def with_spread(stderr: Mapping[str, float | None], spread: Mapping[str, float]):
    """Standard errors with the spread of a learned term's form added in quadrature
    (a parameter that depends on what the trace cannot pin down is that uncertain)."""
    out = dict(stderr)
    for k, v in spread.items():
        if k in out and out[k] is not None and v > 0:
            out[k] = float(np.hypot(out[k], v))
    return out


def dominated(spread: Mapping[str, float], stderr) -> list[str]:
    """The headline parameters (a, b, c, mu) whose ``spread`` is more than half their
    standard error (which already includes it): a note names them."""
    return [
        k
        for k in CONTRACT_PARAMS
        if spread.get(k, 0.0) > 0 and stderr.get(k) and spread[k] > 0.5 * stderr[k]
    ]


def spread_notes(spread, stderr) -> list[str]:
    """A note naming the headline parameters whose error is mostly the form spread."""
    big = [f"{k} ±{spread[k]:.3g}" for k in dominated(spread, stderr)]
    if not big:
        return []
    one = len(big) == 1
    return [
        f"the corrected {', '.join(b.split(' ')[0] for b in big)} "
        + ("depends" if one else "depend")
        + " on the form and place of the learned term, which the trace cannot pin down "
        "(other forms or places fit held-out data about as well): "
        + ("its standard error includes" if one else "their standard errors include")
        + f" that spread ({', '.join(big)}, SI)"
    ]


def unresolved_notes(params: Mapping[str, float], stderr) -> list[str]:
    """A note naming the corrected chain's headline parameters (a, b, c, mu) that the
    trace does not pin down: a standard error beyond :data:`POORLY_DETERMINED` of the
    value (as the seed fit's identifiability notes judge its own), with the recording
    that would pin each down: a, b, c the bell's shape, mu the torque under clamp."""
    bad = [k for k in CONTRACT_PARAMS if k in params and (s := stderr.get(k)) is not None
           and not s <= POORLY_DETERMINED * abs(params[k])]  # fmt: skip
    if not bad:
        return []
    one = len(bad) == 1
    bell = [k for k in bad if k != "mu"]
    record = []
    if bell:
        record.append(f"for {', '.join(bell)}: one that moves the piston past the bell's centre")
    if "mu" in bad:
        record.append("for mu: one with the brake torque recorded while the pads clamp")
    return [
        f"the corrected {', '.join(bad)} {'is' if one else 'are'} not pinned down by this "
        f"trace (standard error beyond {POORLY_DETERMINED:.0%} of the value: "
        + ", ".join(f"{k} = {params[k]:.4g} ± {stderr[k]:.3g}" for k in bad)
        + f"); treat {'it' if one else 'them'} as unresolved, or record a trace "
        + " and, ".join(record)
    ]


def model_tables(chain_fits: Sequence[FitResult], ok: bool) -> dict[str, dict]:
    """Parameter values and standard errors of the baseline and the corrected chain."""
    if not ok or not chain_fits:
        return {}

    def table(f: FitResult):
        values = {k: float(v) for k, v in f.values.items()}
        for m in f.mechanisms:
            values |= {f"{m.variant}.{k}": float(v) for k, v in m.values().items()}
        stderr = {k: f.stderr.get(k) for k in values}
        white = {k: f.stderr_white.get(k) for k in values}
        return values, stderr, white

    bp, bs, bw = table(chain_fits[0])
    ap, as_, aw = table(chain_fits[-1])
    return {
        "baseline_params": bp,
        "baseline_stderr": bs,
        "augmented_params": ap,
        "augmented_stderr": as_,
        "baseline_stderr_white": bw,
        "augmented_stderr_white": aw,
    }


def stage_spread(work, chain_values) -> dict[str, float]:
    """Per headline parameter (a, b, c, mu), how far the corrected chain's estimate lies
    from that of its own stage fitted on the recorded input (the force law on the
    recorded piston, the friction on the recorded force), with the findings there.

    The chain runs from the voltage: what the findings leave of an upstream stage's
    mismatch reaches the force and the torque through the model's piston and force, and
    the bell's a, b, c (or mu) can take it up. Were the corrected model right, the two
    estimates would agree within their errors; their distance is how far the
    remaining misfit moves the parameter, which the trace cannot settle. Like the form
    spread, it is added to the standard error in quadrature."""
    out: dict[str, float] = {}
    for name in CONTRACT_PARAMS:
        fits = [f for st, f in work.current.items() if st != "chain" and name in f.problem.shared]
        if fits and name in chain_values:
            out[name] = abs(float(chain_values[name]) - float(fits[0].values[name]))
    return out


def stage_spread_note(apart: dict[str, float], stderr) -> list[str]:
    """A note naming the headline parameters whose error is mostly :func:`stage_spread`."""
    # Same shape as spread_notes, deliberately separate: another sentence, with its own
    # singular and plural forms.
    big = dominated(apart, stderr)
    if not big:
        return []
    one = len(big) == 1
    return [
        f"the corrected chain's {', '.join(big)} "
        + ("differs from its stage's fit" if one else "differ from their stages' fits")
        + " on the recorded inputs by "
        + ", ".join(f"{apart[k]:.3g}" for k in big)
        + " (SI): what the findings leave of the mismatch upstream moves "
        + (
            "it, and its standard error includes it"
            if one
            else "them, and their standard errors include it"
        )
    ]


# ----------------------------------------------------------------------------- corrected


@dataclass(frozen=True)
class CorrectedFit:
    """The whole chain fitted from the voltage with catalog mechanisms switched on.

    Attributes
    ----------
    trace_name
        The fitted trace.
    mechanisms
        The mechanism variants switched on (e.g. ``backlash``, ``sensor_delay[force_N]``).
    params, stderr
        Every fitted value (SI): the base parameters (a, b, c, mu, the motor, the gap
        polynomial, ``theta0_deg``) and each mechanism's as ``"variant.param"``; standard
        errors (``None`` where not identified), the larger of the white-residual and the
        serial-correlation-robust one (``stderr_white``, ``baseline_stderr_white``: the
        white ones).
    metrics, baseline_metrics
        Whole-chain metrics per recorded channel, corrected and baseline.
    baseline_params
        The baseline chain's values (no mechanism), for comparison.
    converged
        Whether the solver reported success.
    warnings
        Plain-language notes.
    fit, data
        The corrected least-squares fit and its data (the posterior starts from them).
    """

    trace_name: str
    mechanisms: tuple[str, ...]
    params: dict[str, float]
    stderr: dict[str, float | None]
    metrics: dict[str, dict[str, float | None]]
    baseline_params: dict[str, float]
    baseline_stderr: dict[str, float | None]
    baseline_metrics: dict[str, dict[str, float | None]]
    converged: bool
    delta_bic: float
    warnings: tuple[str, ...]
    predictions: dict[str, np.ndarray] = field(repr=False)
    fit: FitResult | None = field(default=None, repr=False)
    data: dict[str, Any] | None = field(default=None, repr=False)
    stderr_white: dict[str, float | None] = field(default_factory=dict)
    baseline_stderr_white: dict[str, float | None] = field(default_factory=dict)
    #: Each learned term refitted: ``place``, ``equation``, ``depends_on`` and its
    #: ``basis`` (:meth:`~ewb_ident.diagnosis.learned_spec.LearnedSpec.to_json`).
    learned: tuple[dict[str, Any], ...] = ()
    #: What the model's predictions need beside the parameters (``omega_ref``, rad/s).
    context: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """A ``fit.json`` document (contract keys) for the corrected model."""
        return {
            "params": self.params,
            "stderr": self.stderr,
            "stderr_white": self.stderr_white,
            "metrics": metrics_json(self.metrics),
            "converged": self.converged,
            "stage": "chain",
            "mechanisms": list(self.mechanisms),
            "baseline": {
                "params": self.baseline_params,
                "stderr": self.baseline_stderr,
                "stderr_white": self.baseline_stderr_white,
                "metrics": metrics_json(self.baseline_metrics),
            },
            "evidence": {"delta_bic": self.delta_bic},
            "warnings": list(self.warnings),
            "learned": list(self.learned),
            "context": dict(self.context),
        }


def mechanism_templates(names: Sequence[str]) -> list[AbstractMechanism]:
    """Mechanism instances for catalog ids or variants (``sensor_delay[force_N]``), each
    optionally in a flexible form after a colon (``backlash:spring``).

    Raises
    ------
    DiagnoseError
        An unknown name, or a sensor mechanism without its channel.
    """
    pool = {m.variant: m for m in variants()}
    out = []
    for name in names:
        name, _, form = name.strip().partition(":")
        if name in pool:
            try:
                out.append(pool[name].in_form(form))
            except ValueError as err:
                raise DiagnoseError(f"--with {name}:{form}: {err}") from None
            continue
        options = [v for v in pool if v.startswith(name + "[")]
        if options:
            raise DiagnoseError(
                f"--with {name}: say which channel it acts on, one of {', '.join(options)}"
            )
        raise DiagnoseError(
            f"--with {name}: not a catalog mechanism; choose from {', '.join(pool)}"
        )
    return out


@numerics
def fit_corrected(
    trace: Trace, mechanisms: Sequence[str], learned: Sequence[LearnedSpec] = ()
) -> CorrectedFit:
    """Fit the seed chain augmented by catalog mechanisms and learned terms, from the
    voltage.

    Each catalog mechanism is first fitted teacher-forced at its own stages (from its
    own starting points), then the whole chain is fitted from the logged voltage with
    every mechanism on, from the baseline chain and from the teacher-forced values. A
    learned term (a diagnosis's finding outside the catalog) starts from its
    coefficients; its inputs are rebuilt on ``trace`` from the baseline chain, then
    once more at the corrected parameters and the chain refitted, so the term's inputs
    and the parameters agree (as :func:`simulate_corrected` rebuilds them elsewhere).

    Parameters
    ----------
    trace
        One trace with ``voltage_V`` and ``theta_deg``.
    mechanisms
        Catalog ids or variants, e.g. ``["backlash", "sensor_delay[force_N]"]``.
    learned
        Learned terms (e.g. from ``diagnosis.json``'s findings, their ``basis``).

    Raises
    ------
    DiagnoseError
        A mechanism or term that cannot be fitted on this trace.
    """
    templates = mechanism_templates(mechanisms)
    if not (trace.has("voltage_V") and trace.has("theta_deg")):
        raise DiagnoseError(
            f"{trace.label}: the corrected whole-chain fit needs voltage_V and theta_deg"
        )
    if not templates and not learned:
        raise DiagnoseError("the corrected fit needs a catalog mechanism or a learned term")
    places = [s.place for s in learned]
    if len(set(places)) < len(places):
        raise DiagnoseError(f"two learned terms act at the same place ({', '.join(places)})")
    ses = Session(trace)
    ses.baseline()
    notes = list(ses.base_messages)
    for m in templates:
        if not ses.mechanism_stages(m):
            raise DiagnoseError(
                f"--with {m.variant}: its stages ({', '.join(m.stages)}) cannot be fitted "
                f"from the channels of {trace.label}"
            )
        reason = m.unsupported_reason(ses.cols, ses.ctx)
        if reason:
            raise DiagnoseError(f"--with {m.variant}: {reason}")
    tf: list[AbstractMechanism] = []
    if templates:
        stages = stage_order({s for m in templates for s in ses.mechanism_stages(m)})
        # A flexible form starts from its catalog form's fit, as in the diagnosis.
        f_tf = ses.fit(stages, [m.in_form("") for m in templates])
        if any(m.form for m in templates):
            flexible = [f.in_form(m.form) for f, m in zip(f_tf.mechanisms, templates, strict=True)]
            f_tf = ses.fit(stages, flexible, explore=[bool(m.form) for m in templates])
        tf = list(f_tf.mechanisms)
    data, chain_free, sigma, f0 = chain_baseline(ses, notes)
    try:
        if learned:
            data = with_terms(data, trace, learned, f0.values)
        mechs = [*tf, *(spec.term() for spec in learned)]

        def chain_fit(data, mechs, start, explore):
            return fit_mechanisms(
                data,
                ("chain",),
                chain_free,
                mechs,
                tuple(sigma),
                start={n: start[n] for n in chain_free},
                ctx=ses.ctx,
                explore=explore,
                alt_starts=[{n: ses.values[n] for n in chain_free if n in ses.values}],
            )

        f1 = chain_fit(data, mechs, f0.values, [True] * len(tf) + [False] * len(learned))
        if learned and f1.converged:
            specs = [_refitted(spec, f1) for spec in learned]
            data2 = with_terms(data, trace, specs, f1.values)
            f2 = chain_fit(data2, list(f1.mechanisms), f1.values, [False] * len(mechs))
            if f2.converged:
                f1, data = f2, data2
        final = [_refitted(spec, f1) for spec in learned]
        docs = [learned_doc(s, s.equation(s.signals_on(trace, f1.values))) for s in final]
    except TermError as err:
        raise DiagnoseError(str(err)) from None
    ev = bic_evidence(f1, f0, sigma, rho_max=rho_cap_of(f1.mechanisms))
    spread = merged_spread(s.spread for s in learned)
    if not f1.converged:
        notes.append("the corrected whole-chain fit did not converge")
    if ev["delta_bic"] > -BIC_THRESHOLD:
        notes.append(
            f"the mechanisms do not improve the whole chain (dBIC {ev['delta_bic']:.1f} > "
            f"-{BIC_THRESHOLD:g}): this trace gives no evidence for them"
        )
    out = corrected_record(trace, f0, f1, data, ev, notes, docs)
    if not spread:
        return out
    stderr = with_spread(out.stderr, spread)
    more = spread_notes(spread, stderr)
    return replace(out, stderr=stderr, warnings=out.warnings + tuple(more))


# ----------------------------------------------------------------------------- elsewhere


@dataclass(frozen=True)
class CorrectedModel:
    """A corrected fit's model as its ``fit.json`` holds it (catalog mechanisms with
    their values, learned terms), to simulate it on a trace it was not fitted to.

    Attributes
    ----------
    mechanisms
        The catalog mechanisms with their fitted values.
    learned
        The learned terms with their fitted coefficients.
    omega_ref
        The disc speed a speed-dependent friction coefficient refers to, rad/s.
    """

    mechanisms: tuple[AbstractMechanism, ...]
    learned: tuple[LearnedSpec, ...]
    omega_ref: float = 1.0

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m.variant for m in self.mechanisms) + tuple(
            f"learned[{s.place}]" for s in self.learned
        )

    @classmethod
    def from_json(cls, doc: Mapping[str, Any], where: str) -> CorrectedModel | None:
        """The corrected model of a ``fit.json`` document, ``None`` for a fit without
        mechanisms.

        Raises
        ------
        DiagnoseError
            Mechanisms or learned terms that cannot be read.
        """
        names = doc.get("mechanisms") or []
        if not names:
            return None
        params = doc.get("params") or {}
        learned_docs = doc.get("learned") or []
        try:
            specs = tuple(
                LearnedSpec.from_json(d.get("basis") if isinstance(d, dict) else None, where)
                for d in learned_docs
            )
        except TermError as err:
            raise DiagnoseError(str(err)) from None
        catalog = [n for n in names if not str(n).startswith("learned[")]
        if len(specs) != len(names) - len(catalog):
            raise DiagnoseError(
                f"{where}: 'mechanisms' lists learned terms but 'learned' does not hold "
                "their bases; give the fit.json that `fit --with-diagnosis` wrote"
            )
        mechs = []
        for variant in catalog:
            (m,) = mechanism_templates([str(variant)])
            have = {k.split(".", 1)[1]: v for k, v in params.items() if k.startswith(f"{variant}.")}
            form = next(
                (c for c in (m, *m.refinements()) if {i.name for i in c.param_info()} == set(have)),
                None,
            )
            if form is None or not all(isinstance(v, int | float) for v in have.values()):
                raise DiagnoseError(
                    f"{where}: the parameters of {variant} ({', '.join(sorted(have))}) are "
                    "not those of any of its forms; give the fit.json `fit --with` wrote"
                )
            mechs.append(form.with_values({k: float(v) for k, v in have.items()}))
        omega_ref = float((doc.get("context") or {}).get("omega_ref", 1.0))
        return cls(tuple(mechs), specs, omega_ref)

    def simulate(self, trace: Trace, values: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Every channel of the corrected chain on ``trace`` from its voltage, with the
        base parameters and start angle ``values`` (SI, ``theta0_deg``).

        Raises
        ------
        DiagnoseError
            A learned term whose inputs the trace does not supply.
        """
        from ewb_ident.inference.augmented import make_data
        from ewb_ident.model.params import MODEL_PARAMS, EWBParams
        from ewb_ident.model.predict import n_substeps, predict

        data = make_data(trace, {}, values, omega_ref=self.omega_ref)
        mechs = list(self.mechanisms)
        if self.learned:
            try:
                data = with_terms(data, trace, self.learned, values)
            except TermError as err:
                raise DiagnoseError(str(err)) from None
            mechs += [s.term() for s in self.learned]
        p = EWBParams(**{k: float(values[k]) for k in MODEL_PARAMS})
        theta0 = jnp.asarray(float(values["theta0_deg"]))
        out = predict("chain", p, theta0, tuple(mechs), data, n_substeps(trace.dt, mechs))
        return {k: np.asarray(v)[: trace.n] for k, v in out.items()}
