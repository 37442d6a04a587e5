"""Findings in words: what a supported mechanism or a generic correction means, where
it acts, and its metrics before and after."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from ewb_ident.data.stages import MAIN_CHANNEL, STAGE_WORDS
from ewb_ident.diagnosis.correction import (
    FEATURES,
    GenericCorrection,
    available_features,
    forward_select,
    signals,
)
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
from ewb_ident.diagnosis.session import SEPARATE, Session, bic_evidence, stage_order, stall_torque
from ewb_ident.inference.augmented import (
    AugFit,
    AugProblem,
    clipped_to_u,
    jacobian,
    residuals,
)
from ewb_ident.mechanisms import AbstractMechanism
from ewb_ident.mechanisms.base import fmt_pm
from ewb_ident.model.params import PARAMS
from ewb_ident.model.predict import n_substeps

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


def mechanism_start(m: AbstractMechanism, prev: AugFit) -> AbstractMechanism:
    for pm in prev.mechanisms:
        if pm.variant == m.variant:
            return pm
    return m


def stderr_of(mech: AbstractMechanism, f: AugFit | None, ses: Session):
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


def _and(items: Sequence[str]) -> str:
    items = list(items)
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _metric_words(ch: str, before, after) -> str:
    b = before.get(ch, {}).get("nrmse_pct")
    a = after.get(ch, {}).get("nrmse_pct")
    if b is None or a is None:
        return ""
    name = ch.split("_")[0]
    return f"{name} NRMSE {b:.2f} % → {a:.2f} %"


def refitted_ctx(ses, fit_m: AugFit | None) -> dict[str, Any]:
    """The session's facts, with the motor's stall torque from the fit that holds the
    finding (the baseline motor may have bent to absorb the missing physics)."""
    ctx = dict(ses.ctx)
    if fit_m is None or not ses.trace.has("voltage_V"):
        return ctx
    kT, R = fit_m.values.get("kT", 0.0), fit_m.values.get("R", 0.0)
    if R > 0 and "R" in fit_m.stderr:
        ctx["stall_torque_Nm"] = stall_torque(ses.trace, kT, R)
    return ctx


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


def fit_generic(ses: Session, stage: str, selected, current, threshold):
    """Fit the sparse generic correction at ``stage``; ``None`` when no term helps."""
    sig = signals(ses.trace)
    feats = available_features(stage, sig)
    if not feats:
        return None
    T = closure((stage,), selected, ses)
    ms = [m for m in selected if set(ses.mechanism_stages(m)) & set(T)]
    f_cur = ses.fit(T, ms, explore=[False] * len(ms))
    full = GenericCorrection(stage_name=stage, features=feats)
    mechs = [*f_cur.mechanisms, full]
    problem = AugProblem(
        stages=T,
        free=ses.free_of(T),
        specs=tuple((type(m), m.static_config()) for m in mechs),
        channels=ses.channels_of(T),
        n_sub=n_substeps(float(ses.data["dt"]), mechs),
    )
    u = [float(PARAMS[n].to_unconstrained(f_cur.values[n])) for n in problem.free]
    for m in mechs:
        vals = m.values()
        u += [clipped_to_u(i, vals[i.name]) for i in m.param_info()]
    u = jnp.asarray(np.asarray(u))
    r = np.asarray(residuals(problem, u, ses.data))
    J = np.asarray(jacobian(problem, u, ses.data))
    m_terms = len(feats)
    sel = forward_select(r, J[:, :-m_terms], J[:, -m_terms:], feats, threshold=threshold)
    if not sel.features:
        return None
    gc = GenericCorrection(stage_name=stage, features=sel.features)
    f_gen = ses.fit(T, [*f_cur.mechanisms, gc], explore=[False] * (len(ms) + 1))
    ev = bic_evidence(f_gen, f_cur, ses.sigma_tf)
    if ev["delta_bic"] > -threshold:
        return None
    return f_gen, ev, sel


def generic_finding(ses, mech, f_gen, ev, sel, flagged, before, after) -> Finding:
    stage = mech.stage
    se = f_gen.mechanism_stderr(mech)
    vals = mech.values()
    words = FEATURES[stage]
    deps = []
    for f in mech.features:
        w = words[f]
        if w not in deps:
            deps.append(w)
    phases = _phases_of(stage, flagged, (stage,))
    where = f"{stage} stage" + (f", {_and(phases)}" if phases else "")
    ch = MAIN_CHANNEL[stage]
    mw = _metric_words(ch, before, after)
    terms = ", ".join(
        f"{f} {fmt_pm(vals[f'c_{f}'], se.get(f'c_{f}'))} {i.unit}"
        for f, i in zip(mech.features, mech.param_info(), strict=True)
    )
    kind = "load torque" if stage == "motor" else f"correction of {ch}"
    text = (
        f"the {STAGE_WORDS[stage]} misses something no catalog mechanism explains ({where}); "
        f"a generic {kind} depending on {'; '.join(deps)} improves the fit ({terms})"
        + (f"; {mw}" if mw else "")
        + f", ΔBIC {ev['delta_bic']:.0f}. Physics not in the catalog: inspect before "
        "modelling it."
    )
    return Finding(
        effect=f"unexplained_{stage}",
        variant=mech.variant,
        stage=stage,
        explanation=text,
        params=vals,
        stderr=se,
        units={i.name: i.unit for i in mech.param_info()},
        evidence=ev,
        metrics_before=before,
        metrics_after=after,
        phases=phases,
        depends_on=tuple(mech.features),
        catalog=False,
    )
