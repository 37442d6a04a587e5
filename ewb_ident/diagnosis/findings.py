"""Findings in words: what a supported mechanism or a discovered term means, where it
acts, and its metrics before and after."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ewb_ident.data.stages import MAIN_CHANNEL, STAGE_WORDS
from ewb_ident.diagnosis.discovery import (
    Discovery,
    basis_matrix,
    group_signals,
)
from ewb_ident.diagnosis.inputs import OWN_SIGNAL, physical
from ewb_ident.diagnosis.learned_spec import LearnedSpec, learned_term
from ewb_ident.diagnosis.locate import (
    PHASES,
    Mismatch,
    describe_signature,
    score_check,
    signature,
    stage_excess,
    summary_text,
)
from ewb_ident.diagnosis.result import Finding
from ewb_ident.diagnosis.session import (
    SEPARATE,
    Session,
    bic_evidence,
    rho_cap_of,
    stage_order,
    stall_torque,
)
from ewb_ident.diagnosis.signatures import reading
from ewb_ident.inference.augmented import fit_mechanisms
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.mechanisms import AbstractMechanism
from ewb_ident.mechanisms.base import RESOLVED_Z, fmt_pm
from ewb_ident.mechanisms.learned import PLACES, term_at, with_bases

# ----------------------------------------------------------------------------- helpers


def closure(stages, selected, ses) -> tuple[str, ...]:
    """``stages`` plus those of every selected mechanism that shares one with them."""
    T = set(stages)
    grew = True
    while grew:
        grew = False
        for m in selected:
            ms = set(ses.mechanism_stages(m))
            if ms & T and not ms <= T:
                T |= ms
                grew = True
    return stage_order(T)


def located_stages(ses: Session, current, *, structured: bool) -> set[str]:
    """Stages whose current fit still shows a mismatch."""
    out = set()
    for s in ses.stages:
        for c in ses.check(s, current[s]):
            cells = score_check(c, ses.labels, ses.trace.time_s, structured=structured)
            if any(m.flagged for m in cells):
                out.add(s)
    return out


def ranked_stages(ses: Session, current, still) -> list[str]:
    excess = {}
    for s in still:
        excess[s] = sum(stage_excess(c) for c in ses.check(s, current[s]))
    return sorted(excess, key=lambda s: -excess[s])


def mechanism_start(m: AbstractMechanism, prev: FitResult) -> AbstractMechanism:
    for pm in prev.mechanisms:
        if pm.variant == m.variant:
            return pm
    return m


def stderr_of(mech: AbstractMechanism, f: FitResult | None, ses: Session):
    for fit_ in [f, *ses.cache.values()]:
        if fit_ is None:
            continue
        for m in fit_.mechanisms:
            if m.variant == mech.variant and np.allclose(
                list(m.values().values()), list(mech.values().values())
            ):
                return fit_.mechanism_stderr(m)
    return {i.name: None for i in mech.param_info()}


def with_summary(m: Mismatch, checks, trace, labels) -> Mismatch:
    if not m.flagged:
        return m
    c = checks[(m.stage, m.channel)]
    sig = signature(c, trace, labels)
    notes = describe_signature(c, sig, m.phase)
    return Mismatch(**{**m.__dict__, "summary": summary_text(m, notes), "signature": sig})


def _phases_of(stage: str, flagged: Sequence[Mismatch], stages: Sequence[str]) -> tuple[str, ...]:
    ph = {m.phase for m in flagged if m.stage in stages}
    return tuple(p for p in PHASES if p in ph)


def _and(items: Sequence[str], word: str = "and") -> str:
    items = list(items)
    if len(items) < 2:
        return "".join(items)
    return ", ".join(items[:-1]) + f" {word} " + items[-1]


def _metric_words(ch: str, before, after) -> str:
    b = before.get(ch, {}).get("nrmse_pct")
    a = after.get(ch, {}).get("nrmse_pct")
    if b is None or a is None:
        return ""
    name = ch.split("_")[0]
    return f"{name} NRMSE {b:.2f} % → {a:.2f} %"


def refitted_ctx(ses, fit_m: FitResult | None) -> dict[str, Any]:
    """The session's facts, with the motor's stall torque from the fit that holds the
    finding (the baseline motor may have bent to absorb the missing physics)."""
    ctx = dict(ses.ctx)
    if fit_m is None or not ses.trace.has("voltage_V"):
        return ctx
    kT, R = fit_m.values.get("kT", 0.0), fit_m.values.get("R", 0.0)
    if R > 0 and "R" in fit_m.stderr:
        ctx["stall_torque_Nm"] = stall_torque(ses.trace, kT, R)
    return ctx


def status_evidence(f_with: FitResult, f_without: FitResult) -> dict[str, float]:
    """Whether the fits with and without a term converged: ``converged`` (1.0 when both
    did), ``converged_with`` and ``converged_without``."""
    w, wo = float(f_with.converged), float(f_without.converged)
    return {"converged": min(w, wo), "converged_with": w, "converged_without": wo}


def status_words(ev: Mapping[str, float]) -> str:
    """A sentence when a finding's fits did not converge: its evidence is then what the
    solver reached, not an optimum."""
    if ev.get("converged", 1.0):
        return ""
    which = [w for w in ("with", "without") if not ev.get(f"converged_{w}", 1.0)]
    return (
        f"the fit {' and '.join(which)} it stopped before converging: its ΔBIC is what the "
        "solver reached, not an optimum"
    )


def make_finding(ses, mech, se, ev, flagged, before, after, alternatives=(), ctx=None) -> Finding:
    ctx = ses.ctx if ctx is None else ctx
    vals = mech.values()
    stages = ses.mechanism_stages(mech)
    phases = _phases_of(mech.stage, flagged, stages)
    where = f"{mech.stage} stage" + (f", {_and(phases)}" if phases else "")
    ch = mech.channels[0] if mech.hook == "sensor" else MAIN_CHANNEL[mech.stage]
    words = _metric_words(ch, before, after)
    text = (
        f"{mech.observation(vals, ctx)} ({where}): {mech.describe(vals, se, ctx)}"
        + (f"; {words}" if words else "")
        + f", ΔBIC {ev['delta_bic']:.0f}"
    )
    if alternatives:
        rivals = _and([f"{e} (ΔBIC {d:.0f})" for e, d in alternatives])
        text += f". But {rivals} explains it about as well: this trace cannot tell them apart"
        hints = [SEPARATE[frozenset((mech.id, e))] for e, _ in alternatives]
        text += "".join(f"; {h}" for h in hints if h)
    if stopped := status_words(ev):
        text += f". But {stopped}"
    return Finding(
        effect=mech.id,
        variant=mech.variant,
        stage=mech.stage,
        explanation=text,
        params=vals,
        stderr=se,
        units={i.name: i.unit for i in mech.param_info()},
        evidence=ev,
        metrics_before=before,
        metrics_after=after,
        phases=phases,
        alternatives=tuple(alternatives),
        form=mech.form,
    )


def fit_learned(ses: Session, disc: Discovery, selected, threshold: float):
    """Fit the distilled term of ``disc`` through the model (nonlinear least squares, the
    stages' own parameters and any selected mechanism there refitted alongside).

    Returns ``(fit, evidence, term)``, or ``None`` when the term does not lower the BIC
    of its stages by ``threshold`` (the in-sample guard beside the held-out one)."""
    T = closure(disc.stages, selected, ses)
    ms = [m for m in selected if set(ses.mechanism_stages(m)) & set(T)]
    f_cur = ses.fit(T, ms, explore=[False] * len(ms))
    data = learned_data(ses.data, [disc])
    term = learned_term(disc.place, [c.label for c in disc.columns], disc.coef)
    f_new = fit_mechanisms(
        data,
        T,
        ses.free_of(T),
        (*f_cur.mechanisms, term),
        ses.channels_of(T),
        start={n: f_cur.values[n] for n in ses.free_of(T)},
        # The term from its distilled coefficients and from zero; the stage's parameters
        # also from where the linearised step with the term put them, and the nominal
        # motor's.
        explore=[False] * len(ms) + [True],
        alt_starts=([disc.start] if disc.start else []) + ses.nominal_starts(T),
    )
    term = term_at(f_new.mechanisms, disc.place)
    ev = bic_evidence(f_new, f_cur, ses.sigma_tf, rho_max=rho_cap_of([term]))
    ev |= status_evidence(f_new, f_cur)
    if ev["delta_bic"] > -threshold:
        return None
    return f_new, ev, term


def learned_data(data: dict[str, Any], discoveries) -> dict[str, Any]:
    """``data`` with the basis series of the discovered terms (by place)."""
    return with_bases(data, {d.place: basis_matrix(d) for d in discoveries})


def _words(disc: Discovery, name: str) -> str:
    return disc.signals[name].words if name in disc.signals else name


def learned_finding(ses, disc: Discovery, term, f_new, ev, flagged, before, after,
                    rivals=()) -> Finding:  # fmt: skip
    """A finding for a discovered term: where it acts, its equation with intervals, what
    it depends on, its held-out improvement and a physical reading (a hypothesis)."""
    stage = disc.stage
    se = f_new.mechanism_stderr(term)
    vals, coef = term.values(), term.coefficients
    equation = disc.equation(coef)
    info = PLACES[disc.place]
    phases = _phases_of(stage, flagged, disc.stages)
    where = f"{stage} stage" + (f", {_and(phases)}" if phases else "")
    deps = [_words(disc, d) for d in disc.depends_on]
    same = [_words(disc, d) for d in disc.equivalents]
    moves = "which moves" if len(same) == 1 else "which move"
    ch = MAIN_CHANNEL[stage]
    mw = _metric_words(ch, before, after)
    ho = disc.distilled
    hyp = reading(disc.place, disc.depends_on, disc.columns)
    terms = []
    for j, c in enumerate(disc.columns):
        expr, factor, unit = physical(c, disc.signals)
        s_ = se.get(f"c{j}")
        terms.append(
            {
                "expression": expr,
                "coef": float(coef[j]) * factor,
                "stderr": None if s_ is None else abs(s_ * factor),
                "unit": info.unit + (f"/({unit})" if unit else ""),
            }
        )
    for t in terms:
        s_ = t["stderr"]
        t["low_90"] = None if s_ is None else t["coef"] - RESOLVED_Z * s_
        t["high_90"] = None if s_ is None else t["coef"] + RESOLVED_Z * s_
    coefs = "; ".join(
        f"{t['expression']}: {fmt_pm(t['coef'], t['stderr'])} {t['unit']}" for t in terms
    )
    text = (
        f"the {STAGE_WORDS[stage]} misses something no catalog mechanism explains ({where}). "
        f"A term learned at {disc.place} ({info.words}) depending on "
        f"{_and(deps) or 'no signal (a constant)'}"
        + (
            f" (or on {_and(same, 'or')}, {moves} with it here: the trace cannot tell)"
            if same
            else ""
        )
        + " "
        f"generalises: on held-out data ({disc.method}) it lowers the residual by "
        f"{ho.improvement_pct:.0f} % ({100 * min(ho.share, 1.0):.0f} % of the excess over "
        f"the noise). Distilled: {equation} (coefficients: {coefs})"
        + (f"; {mw}" if mw else "")
        + f", ΔBIC {ev['delta_bic']:.0f}."
        + (f" A reading to inspect: {hyp}." if hyp else " No known signature matches it.")
    )
    if rivals:
        text += (
            " The nearest catalog name, "
            + _and([f"{e} (ΔBIC {d:.0f})" for e, d in rivals])
            + ", explains less of it on held-out data."
        )
    modelled = [d for d in disc.depends_on if _source(d) and not ses.trace.has(_source(d))]
    if modelled:
        text += (
            f" It depends on the model's {_and(modelled)} (the trace records no "
            f"{_and(sorted({_source(d) for d in modelled}))}): its shape is only as good as "
            "the model's."
        )
    close = [
        f"{p.place} (on {_and([_words(disc, n) for n in dict.fromkeys(group_signals(p.groups))])})"
        for p in disc.close_places
    ]
    if close:
        who = ("Terms at", "explain") if len(close) > 1 else ("A term at", "explains")
        text += f" {who[0]} {_and(close)} {who[1]} it about as well: the trace cannot tell."
    if stopped := status_words(ev):
        text += f" But {stopped}."
    heldout = {
        "improvement_pct": ho.improvement_pct,
        "method": disc.method,
        "excess_share": min(max(ho.share, 0.0), 1.0),
        "learned_improvement_pct": disc.learned.improvement_pct,
        "insample_improvement_pct": 100.0
        * (ho.insample_before - ho.insample_after)
        / max(ho.insample_before, 1e-300),
        "delta_bic_heldout": ho.score,
    }
    return Finding(
        effect="learned_" + disc.place.replace(".", "_").lower(),
        variant=term.variant,
        stage=stage,
        explanation=text,
        params=vals,
        stderr=se,
        units={k: info.unit for k in vals},
        evidence=ev,
        metrics_before=before,
        metrics_after=after,
        phases=phases,
        depends_on=disc.depends_on,
        equivalents=disc.equivalents,
        catalog=False,
        alternatives=tuple(rivals),
        place=disc.place,
        equation=equation,
        heldout=heldout,
        terms=tuple(terms),
        reading=hyp,
        basis=LearnedSpec.of(disc, coef).to_json(),
        term_series=basis_matrix(disc) @ np.asarray(coef, float),
        **_main_input(disc),
    )


def _source(signal: str) -> str:
    """The channel a signal is computed from (the heat and its histories: the current;
    the reversals and the travel since one: the angle; a signal's change since it last
    reversed: that signal)."""
    name = "current" if signal.startswith("heat") else signal.removesuffix("_rate")
    name = name.removesuffix("_travel")
    name = "angle" if name in ("reversals", "travel") else name
    return {v: k for k, v in OWN_SIGNAL.items()}.get(name, "")


def _main_input(disc: Discovery) -> dict[str, Any]:
    """The signal a discovered term depends on first, for its figure."""
    for name in disc.depends_on:
        sig = disc.signals.get(name)
        if sig is not None:
            return {"term_input": sig.values, "term_input_label": f"{sig.words}, {sig.unit}"}
    return {}
