"""Diagnosis: locate a mismatch between model and recording, name the missing physics,
add it to the model, refit, and show the fit improve.

Steps (:func:`diagnose`)
------------------------
1. **Baseline.** Each stage is fitted teacher-forced from its measured input
   (:func:`ewb_ident.inference.least_squares.fit`), and the whole chain from the voltage.
2. **Locate** (:mod:`ewb_ident.diagnosis.locate`). Each stage's residual is scored against its
   noise floor, phase by phase, with a whiteness test; a stage with a flagged cell is
   *located*. Nothing located: the verdict is ``none``.
3. **Explain.** Every catalog mechanism (:mod:`ewb_ident.mechanisms`) that acts on a
   located stage and that the trace's columns support is fitted teacher-forced at its
   stage(s), with that stage's own parameters refitted. Evidence is the change of the
   Bayesian information criterion against the same stages without it,
   ``dBIC = N_eff ln(RSS_1 / RSS_0) + dk ln N_eff`` (Gaussian likelihood with the noise
   scale profiled; ``RSS`` the sum of squared residuals over the noise floor). ``N_eff =
   N (1 - rho) / (1 + rho)`` is the effective number of the ``N`` residuals, with ``rho``
   the lag-1 autocorrelation of the residual *with* the mechanism (AR(1) errors): a
   mechanism that leaves the residual white gets the full evidence of ``N`` samples; one
   that only absorbs part of a smooth misfit (a fraction of a sample's delay, say) gets
   the evidence of the few independent stretches that misfit spans. Without this, a
   white-noise BIC over-counts correlated residuals and names noise-level structure.
   A mechanism is *supported* when

   - ``dBIC <= -BIC_THRESHOLD`` (10: "very strong" evidence on the scale of Kass and
     Raftery 1995, a Bayes factor above about 150),
   - every physical parameter lies inside its plausibility bounds and its 90 % interval
     excludes "no effect" (guard against reporting an unresolved value), and
   - it removes at least ``MIN_EXPLAINED`` (half) of the excess of the residual over the
     noise at its stages (guard against a catalog name absorbing part of some other
     physics), or at least ``CATALOG_SHARE`` of what the learned term of step 4
     removes there (the excess can hold what no smooth term removes, e.g. noise on a
     measured input bent by a nonlinear stage).

   Forward selection: the supported mechanism with the lowest ``dBIC`` is added, the
   remaining candidates are refitted on top of it, and so on while a stage is still
   located (at most :data:`MAX_MECHANISMS`).
4. **Unknown physics.** Catalog names at a stage are first checked against a learned
   term there on held-out data (:mod:`ewb_ident.diagnosis.arbitration`); a stage still
   located afterwards goes to discovery (:mod:`ewb_ident.diagnosis.discovery`): a
   learned term where it acts, kept only if it generalises, distilled to an equation,
   reported as ``learned_<place>``. A catalog name still needing a learned term on top
   must beat a learned term alone by the evidence threshold. With no catalog finding
   the verdict is ``unexplained``.
5. **Show it.** The whole chain is refitted with the selected mechanisms, one added at a
   time, for metrics before and after each; words for each finding.

Thresholds are statistical (noise-relative scores, significance, information criterion)
and were set on rig settings other than those the accuracy study measures on.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ewb_ident.data.metrics import channel_metrics
from ewb_ident.data.stages import STAGE_OUTPUTS
from ewb_ident.data.trace import Trace
from ewb_ident.data.validation import check_trace
from ewb_ident.diagnosis.arbitration import (
    best_search,
    fits_of,
    one_explanation,
    promote,
    second_opinion,
    set_aside_records,
)
from ewb_ident.diagnosis.artefacts import find_artefacts
from ewb_ident.diagnosis.corrected import (
    corrected_of,
    merged_spread,
    model_tables,
    spread_notes,
    stage_spread,
    stage_spread_note,
    unresolved_notes,
    with_spread,
)
from ewb_ident.diagnosis.discovery import Discovery, discover
from ewb_ident.diagnosis.findings import (
    closure,
    fit_learned,
    learned_data,
    learned_finding,
    located_stages,
    make_finding,
    mechanism_start,
    ranked_stages,
    refitted_ctx,
    status_evidence,
    stderr_of,
    with_summary,
)
from ewb_ident.diagnosis.locate import Mismatch, score_check
from ewb_ident.diagnosis.result import Candidate, DiagnosisResult, Finding
from ewb_ident.diagnosis.session import (
    BIC_THRESHOLD,
    CATALOG_SHARE,
    MAX_CORRECTIONS,
    MAX_MECHANISMS,
    MIN_EXPLAINED,
    DiagnoseError,
    Session,
    bic_evidence,
    chain_baseline,
    chain_metrics,
    chain_prefixed,
    fitted_mechanism,
    rho_cap_of,
)
from ewb_ident.diagnosis.signatures import not_generalised
from ewb_ident.inference.augmented import fit_mechanisms
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.mechanisms import AbstractMechanism, variants
from ewb_ident.mechanisms.learned import term_at
from ewb_ident.model.numerics import numerics
from ewb_ident.model.predict import MOTOR_HOOKS
from ewb_ident.runtime.store import prefetching
from ewb_ident.runtime.threads import parallel_map, threads

# ----------------------------------------------------------------------------- main

#: The catalog is searched again without the names the whole chain did not confirm
#: while fewer than this many are set aside (at most two searches more).
MAX_SET_ASIDE = 2


@numerics
def diagnose(
    trace: Trace,
    *,
    bic_threshold: float = BIC_THRESHOLD,
    max_mechanisms: int = MAX_MECHANISMS,
    catalog: Sequence[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> DiagnosisResult:
    """Locate, explain and correct the mismatch between the model and one trace.

    Parameters
    ----------
    trace
        One rig trace (needs at least one input-output pair of a stage; the whole chain
        needs ``voltage_V``).
    bic_threshold
        Evidence a mechanism needs: ``dBIC <= -bic_threshold`` (default 10).
    max_mechanisms
        Most catalog mechanisms selected.
    catalog
        Catalog ids to consider (default: all).
    progress
        Called with a short description of each step as it starts (the CLI shows it on
        a terminal); the library itself never prints.

    Returns
    -------
    DiagnosisResult
        Its :meth:`~DiagnosisResult.to_json` is the ``diagnosis.json`` contract.

    Raises
    ------
    DiagnoseError
        The trace lacks the columns any stage needs, or ``catalog`` names unknown ids.

    Notes
    -----
    Each call compiles models for its trace's shape and the mechanisms it tries: release
    them between traces of many shapes (:func:`ewb_ident.runtime.programs.release`, as
    ``studies/diagnosis_accuracy.py`` does), or they accumulate up to the kernel's limit
    on memory maps. With the on-disk program cache, the programs the last diagnosis of a
    trace of this length and these channels used are loaded ahead
    (:func:`~ewb_ident.runtime.store.prefetching`).
    """
    trace = check_trace(trace)
    # The channels name the work too: the first program (a fit's) takes them as data.
    work = f"diagnose {sorted(trace.channels)} {bic_threshold!r} {max_mechanisms!r} {catalog!r}"
    with prefetching(work):
        return _diagnose(trace, bic_threshold, max_mechanisms, catalog, progress)


def _diagnose(trace, bic_threshold, max_mechanisms, catalog, progress) -> DiagnosisResult:
    t_start = time.perf_counter()
    timings: dict[str, float] = {}

    def lap(step: str) -> None:  # (a step run again adds to its time)
        timings[step] = (
            timings.pop(step, 0.0) + time.perf_counter() - t_start - sum(timings.values())
        )

    pool = _catalog_pool(catalog)
    ses = Session(trace).checked()  # data no fit can start from: refused before any work
    say = progress or (lambda text: None)
    say("baseline fits of every stage")
    ses.baseline()
    lap("baseline_stages")
    checks_before, cells, flagged = _locate(ses, trace)
    lap("locate")
    # Structured sensor noise (a mains hum) is not brake physics: named, then removed.
    artefacts, cleaned = find_artefacts(checks_before, trace, ses.labels)
    if cleaned:
        say("removing periodic interference: " + ", ".join(sorted(cleaned)))
        trace = dataclasses.replace(trace, channels={**trace.channels, **cleaned})
        ses = Session(trace)
        ses.baseline()
        checks_before, cells, flagged = _locate(ses, trace)
        lap("artefacts")
    chain = _Chain.baseline(ses, trace)
    lap("baseline_chain")
    start, set_aside, passes = dict(ses.values), [], []
    while True:
        left = [m for m in pool if all(m.variant != x.variant for x, _ in set_aside)]
        work = _explain(ses, left, {m.stage for m in flagged}, bic_threshold, max_mechanisms, say)
        lap("explain")
        say("checking each catalog name against a learned term at its stage")
        second_opinion(ses, work, bic_threshold)
        lap("second_opinion")
        say("looking for physics outside the catalog")
        _unknown(ses, work, bool(flagged), bic_threshold)
        one_explanation(ses, work, bic_threshold)
        lap("unknown")
        say("confirming the findings on the whole chain")
        tried = dataclasses.replace(chain, fits=list(chain.fits))
        added, chain_ev, unconfirmed = _confirm(ses, tried, work, bic_threshold)
        lap("chain")
        passes.append((work, tried, added, chain_ev, [*set_aside, *unconfirmed], dict(ses.values)))
        # A catalog name the whole chain does not confirm absorbed an artefact of a
        # teacher-forced stage; it also held back the rivals of its round and set the
        # stage fits a learned term was fitted on. Set aside, the catalog is searched
        # again without it; of the searches, the whole chain's best fit is kept.
        new = [(m, ev) for m, ev in unconfirmed if any(m is x for x in work.selected)]
        if not chain.ok or not new or len(set_aside) >= MAX_SET_ASIDE:
            break
        set_aside += new
        ses.values = dict(start)
        say("searching the catalog again without " + ", ".join(m.variant for m, _ in new))
    k = best_search([p[1] for p in passes], chain)
    work, chain, added, chain_ev, unconfirmed, ses.values = passes[k]
    work.candidates[:0] = set_aside_records([p[0] for p in passes[:k]], unconfirmed, bic_threshold)
    located = flagged + _screened_cells(cells, added, flagged, work)
    checks_after = {
        (c.stage, c.channel): c for s in ses.stages for c in ses.check(s, work.current[s])
    }
    stage_before = _stage_metrics(ses, checks_before)
    stage_after = _stage_metrics(ses, checks_after)
    findings = _findings(
        ses, trace, chain, work, added, chain_ev, flagged, stage_before, stage_after
    )
    verdict, notes = _verdict(ses, work, findings, located, unconfirmed, bic_threshold)
    tables = model_tables(chain.fits, chain.ok)
    if tables:
        spread = _form_spread(work, added)
        tables["augmented_stderr"] = with_spread(tables["augmented_stderr"], spread)
        notes += spread_notes(spread, tables["augmented_stderr"])
        if added:  # and the corrected a, b, c, mu the trace does not pin down
            apart = stage_spread(work, tables["augmented_params"])
            st = tables["augmented_stderr"] = with_spread(tables["augmented_stderr"], apart)
            notes += stage_spread_note(apart, st) + unresolved_notes(tables["augmented_params"], st)
    timings["total"] = time.perf_counter() - t_start
    return DiagnosisResult(
        trace_name=trace.name,
        verdict=verdict,
        mismatches=tuple(located),
        cells=tuple(cells),
        findings=tuple(findings),
        candidates=tuple(work.candidates),
        baseline_metrics=chain_metrics(trace, chain.fits[0]) if chain.ok else {},
        augmented_metrics=chain_metrics(trace, chain.fits[-1]) if chain.ok else {},
        stage_metrics_before=stage_before,
        stage_metrics_after=stage_after,
        noise=dict(ses.noise),
        checks_before=checks_before,
        checks_after=checks_after,
        chain_before=dict(chain.fits[0].predictions[0]) if chain.ok else {},
        chain_after=dict(chain.fits[-1].predictions[0]) if chain.ok else {},
        labels=ses.labels,
        trace=trace,
        timings=timings,
        notes=tuple(notes),
        artefacts=tuple(artefacts),
        corrected=corrected_of(
            trace, chain.fits, chain.data, chain.sigma, [d for d, _, _, _ in work.discoveries]
        )
        if chain.ok and len(chain.fits) > 1
        else None,
        **tables,
    )


# ----------------------------------------------------------------------------- steps


def _catalog_pool(catalog: Sequence[str] | None) -> list[AbstractMechanism]:
    """The catalog's variants to try (all, or those of the ids named)."""
    pool = variants()
    if isinstance(catalog, str):
        raise TypeError(
            f"catalog: give a sequence of catalog ids, e.g. {catalog.split(',')!r}, not the"
            f" string {catalog!r}"
        )
    if catalog is not None:
        catalog = list(catalog)
        known = {m.id for m in pool}
        if not catalog:
            raise DiagnoseError(
                "catalog (--catalog) names no id; name catalog ids, e.g. backlash,stiction,"
                " or leave it out for the whole catalog"
            )
        bad = sorted(set(catalog) - known)
        if bad:
            raise DiagnoseError(f"unknown catalog id(s) {bad}; the catalog is {sorted(known)}")
        pool = [m for m in pool if m.id in set(catalog)]
    return pool


def _locate(ses: Session, trace: Trace) -> tuple[dict, list[Mismatch], list[Mismatch]]:
    """Step 2: every stage's residual checked phase by phase; the flagged cells, most
    severe first."""
    checks = {(c.stage, c.channel): c for s in ses.stages for c in ses.check(s, ses.base_fits[s])}
    cells = [m for c in checks.values() for m in score_check(c, ses.labels, trace.time_s)]
    cells = [with_summary(m, checks, trace, ses.labels) for m in cells]
    flagged = sorted((m for m in cells if m.flagged), key=lambda m: -m.score)
    return checks, cells, flagged


@dataclass
class _Chain:
    """The whole chain from the voltage: its data and weights, the free parameters, and
    its fits (the baseline first, then one per confirmed finding)."""

    ok: bool
    data: Any = None
    free: tuple[str, ...] = ()
    sigma: Any = None
    fits: list[FitResult] = field(default_factory=list)

    @classmethod
    def baseline(cls, ses: Session, trace: Trace) -> _Chain:
        if not (trace.has("voltage_V") and trace.has("theta_deg")):
            return cls(ok=False)
        data, free, sigma, f0 = chain_baseline(ses, ses.base_messages)
        return cls(ok=True, data=data, free=free, sigma=sigma, fits=[f0])


#: One tried mechanism: its candidate record, its fit, evidence and fitted instance.
_Tried = tuple[Candidate, FitResult, dict[str, float], AbstractMechanism]


@dataclass
class _Work:
    """What the explain and unknown steps decide, for the steps after them."""

    selected: list[AbstractMechanism] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    evidence: dict[str, dict[str, float]] = field(default_factory=dict)
    current: dict[str, FitResult] = field(default_factory=dict)  # stage -> latest fit of it
    last_round: list[_Tried] = field(default_factory=list)
    alternatives: dict[str, list[tuple[str, float]]] = field(default_factory=dict)
    #: Discovered terms: (discovery, its fit, evidence, the fitted term).
    discoveries: list[tuple[Discovery, FitResult, dict[str, float], Any]] = field(
        default_factory=list
    )
    #: Catalog names a discovered term at their stage outdid on held-out data.
    rivals: dict[str, list[tuple[str, float]]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _explain(ses, pool, located, bic_threshold, max_mechanisms, say) -> _Work:
    """Step 3: forward selection over the catalog while a stage is still located."""
    work = _Work(current=dict(ses.base_fits))
    still = set(located)
    for rnd in range(1, max_mechanisms + 1):
        # Nothing located: only the screened mechanisms are tried (see ``_try``).
        done = {m.variant for m in work.selected}
        todo = [tmpl for tmpl in pool if tmpl.variant not in done]
        say(f"round {rnd}: trying {', '.join(t.variant for t in todo)}")
        # The candidates are fitted side by side (one compiles while another fits);
        # each fit depends only on the round's start, so the results are the loop's.
        attempt = functools.partial(
            _try, ses, selected=work.selected, still=still, rnd=rnd, bic_threshold=bic_threshold
        )
        ahead = _RefineAhead(ses, work.selected, rnd, bic_threshold)
        tried = ahead.run(attempt, todo)
        results = [t for t in tried if t is not None]
        _, best = _best(results)
        # The chosen form's family: a flexible form in its place when the trace shows it
        # (with nothing supported, the forms of those held back for a partial share).
        for r in [best] if best is not None else _short(results):
            wider = ahead.refined(r)
            if wider is not None:
                results[next(i for i, x in enumerate(results) if x is r)] = wider
                why = f"its flexible form fits better (dBIC {wider[0].form_gain_bic:.1f})"
                results.append((Candidate(**{**r[0].__dict__, "rejected": why}), *r[1:]))
                work.notes.append(_refined_note(r, wider))
        ok, best = _best(results)
        work.last_round = results if best is None else []
        for r in results:
            sel = best is not None and r[0] is best[0]
            work.candidates.append(Candidate(**{**r[0].__dict__, "selected": sel}) if sel else r[0])
        if best is None:
            break
        cand, f1, ev, mech = best
        work.selected.append(mech)
        work.evidence[mech.variant] = ev
        # Rivals the trace cannot tell apart from the choice: also supported, and within
        # the evidence threshold of it (a Bayes factor under about 150).
        work.alternatives[mech.variant] = [
            (r[0].effect, r[0].delta_bic)
            for r in ok
            if r is not best
            and r[0].effect != cand.effect
            and r[0].delta_bic - cand.delta_bic < bic_threshold
        ]
        for s in f1.stages:
            work.current[s] = f1
        for n in ses.free_of(f1.stages):
            ses.values[n] = f1.values[n]
        # The next round tries the stages located at first and any located now: a
        # weaker second effect may hide under the first one's residual (the targeted
        # evidence test is more sensitive than the location test).
        still = set(located) | located_stages(ses, work.current, structured=True)
    return work


class _RefineAhead:
    """A round's candidates fitted side by side, the slow ones first, and the flexible
    forms of the best supported one so far tried by a worker that would otherwise wait
    for the round's last fit.

    The candidates' fit times differ by up to 20x: a motor candidate with a load torque
    can take half of a round while the other core idles, and the chosen form's
    refinement would then run after the round. So the candidates that need motor
    sub-steps start first, and once every candidate has started, a worker that
    finishes one refines the best supported candidate so far (a later one may still
    beat it: its refinement is then not used).
    Only with more than one thread. The fits and refinements depend on the round's
    start alone, so :meth:`run` and :meth:`refined` give what the loop and
    :func:`_refine` after it give."""

    def __init__(self, ses, selected, rnd: int, bic_threshold: float) -> None:
        self._args = (ses, selected, rnd, bic_threshold)
        self._lock = threading.Lock()
        self._done: dict[str, _Tried | None] = {}
        self._on = threads() > 1

    def run(self, attempt: Callable[[Any], _Tried | None], todo: list) -> list[_Tried | None]:
        """``[attempt(t) for t in todo]``, side by side."""
        order = sorted(range(len(todo)), key=lambda i: not _sub_stepped(todo[i]))
        started, lead, claimed = [0], [None], set()

        def one(tmpl):
            with self._lock:
                started[0] += 1
            got = attempt(tmpl)
            with self._lock:
                if got is not None and not got[0].rejected:
                    if lead[0] is None or got[0].delta_bic < lead[0][0].delta_bic:
                        lead[0] = got
                best = lead[0]
                ahead = (
                    self._on and started[0] == len(todo) and best is not None
                    and best[0].variant not in claimed and bool(best[3].refinements())
                )  # fmt: skip
                if ahead:
                    claimed.add(best[0].variant)
            if ahead:
                self._done[best[0].variant] = self._refine(best)
            return got

        done = parallel_map(one, [todo[i] for i in order])
        tried: list[_Tried | None] = [None] * len(todo)
        for k, i in enumerate(order):
            tried[i] = done[k]
        return tried

    def refined(self, tried: _Tried) -> _Tried | None:
        """:func:`_refine` of ``tried``, made ahead or now."""
        if tried[0].variant in self._done:
            return self._done[tried[0].variant]
        return self._refine(tried)

    def _refine(self, tried: _Tried) -> _Tried | None:
        ses, selected, rnd, bic_threshold = self._args
        return _refine(ses, tried, selected, rnd, bic_threshold)


def _sub_stepped(tmpl: AbstractMechanism) -> bool:
    """Whether the mechanism acts inside the motor's integration (the slowest fits)."""
    return any(tmpl.uses(h) for h in MOTOR_HOOKS)


def _try(ses, tmpl, selected, still, rnd, bic_threshold) -> _Tried | None:
    """Fit one catalog mechanism at its stages on top of those selected, and judge it;
    ``None`` when it does not act on a located stage (unless it is screened: tried on
    every trace, :attr:`~ewb_ident.mechanisms.base.AbstractMechanism.SCREENED`) or the
    trace cannot show it."""
    mst = ses.mechanism_stages(tmpl)
    if not mst or not (set(mst) & still or tmpl.SCREENED):
        return None
    if tmpl.unsupported_reason(ses.cols, ses.ctx):
        return None
    T = closure(mst, selected, ses)
    ms = [m for m in selected if set(ses.mechanism_stages(m)) & set(T)]
    f0 = ses.fit(T, ms, explore=[False] * len(ms))
    f1 = ses.fit(T, ms + [tmpl], explore=[False] * len(ms) + [True])
    own = [c for st in mst for c in STAGE_OUTPUTS[st]]
    ev = bic_evidence(f1, f0, ses.sigma_tf, own) | status_evidence(f1, f0)
    mech = fitted_mechanism(f1, tmpl.variant)
    se = f1.mechanism_stderr(mech)
    reason = mech.implausible_reason(mech.values(), se)
    if not reason and ev["delta_bic"] > -bic_threshold:
        reason = f"dBIC {ev['delta_bic']:.1f} > -{bic_threshold:g}"
    if not reason and ev["explained_fraction"] < MIN_EXPLAINED:
        reason = (
            f"explains only {100 * ev['explained_fraction']:.0f} % of the excess "
            "residual at its stages"
        )
    cand = Candidate(
        variant=tmpl.variant,
        effect=tmpl.id,
        stages=T,
        round=rnd,
        delta_bic=ev["delta_bic"],
        delta_chi2=ev["delta_chi2"],
        explained=ev["explained_fraction"],
        p_value=ev["lr_p_value"],
        params=mech.values(),
        stderr=se,
        rejected=reason,
    )
    return cand, f1, ev, mech


def _best(results: list[_Tried]) -> tuple[list[_Tried], _Tried | None]:
    """The supported candidates, and the one with the lowest dBIC (``None``: none)."""
    ok = [r for r in results if not r[0].rejected]
    return ok, (min(ok, key=lambda r: r[0].delta_bic) if ok else None)


def _short(results: list[_Tried]) -> list[_Tried]:
    """Candidates held back only because they explain part of the excess."""
    return [r for r in results if r[0].rejected.startswith("explains only")]


def _refine(ses, tried: _Tried, selected, rnd, bic_threshold) -> _Tried | None:
    """A flexible form of a tried mechanism
    (:meth:`~ewb_ident.mechanisms.base.AbstractMechanism.refinements`) that the trace
    supports over the form tried: judged as a mechanism on its own (against the stages
    without it) and better than the form tried by ``dBIC <= -bic_threshold``, its added
    parameters plausible and resolved. ``None`` when no form is."""
    cand, f1, _, mech = tried
    own = [c for st in ses.mechanism_stages(mech) for c in STAGE_OUTPUTS[st]]
    best, best_bic = None, -bic_threshold
    for form in mech.refinements():
        got = _try(ses, form, selected, set(ses.mechanism_stages(form)), rnd, bic_threshold)
        if got is None or got[0].rejected:
            continue
        gain = bic_evidence(got[1], f1, ses.sigma_tf, own)["delta_bic"]
        if gain <= best_bic:
            best, best_bic = got, gain
    if best is None:
        return None
    return (Candidate(**{**best[0].__dict__, "form_gain_bic": best_bic}), *best[1:])


def _refined_note(plain: _Tried, wider: _Tried) -> str:
    added = sorted(set(wider[0].params) - set(plain[0].params))
    return (
        f"{wider[0].variant}: the flexible form (with {', '.join(added)}) fits better than "
        f"the catalog's form (dBIC {wider[0].form_gain_bic:.1f} against it)"
    )


def _form_spread(work: _Work, added) -> dict[str, float]:
    """Per base parameter, the spread of its estimate over the forms and places of the
    learned terms kept that the trace cannot tell apart (the largest over the terms)."""
    kept = {m.variant for m in added}
    return merged_spread(d.spread for d, _, _, term in work.discoveries if term.variant in kept)


def _unknown(ses: Session, work: _Work, any_flagged: bool, bic_threshold: float) -> None:
    """Step 4: discovery (:mod:`ewb_ident.diagnosis.discovery`) at each stage still
    located (or whose catalog names went to a learned term: :func:`second_opinion`),
    unless a held back catalog rival removes as much as the discovered term does."""
    # Only a residual clearly above the noise (not merely serially correlated) calls for
    # physics beyond the catalog once a mechanism has been added: what remains at the
    # noise level then is the approximation of the added physics.
    still = set(work.rivals)
    if any_flagged:
        still |= located_stages(ses, work.current, structured=not work.selected)
    remaining = ranked_stages(ses, work.current, still)
    done: set[str] = set()
    for s in remaining[:MAX_CORRECTIONS]:
        if s in done:
            continue
        disc = discover(ses, s, fits_of(ses, work.selected))
        if disc is None:
            continue
        # The distilled term, else the other expressions and places about as good.
        tried = [d for d in (disc, *disc.alternatives()) if d.learned.groups]
        tried = [d for d in tried if d.distilled.generalises]
        if not tried:
            work.notes.append(not_generalised(disc))
            continue
        res = None
        for alt in tried:
            res = fit_learned(ses, alt, work.selected, bic_threshold)
            if res is not None:
                disc = alt
                break
        if res is None:
            work.notes.append(
                f"{s} stage: the term learned at {disc.place} generalises on held-out data "
                "but its distilled equation does not improve the fit of the whole stage "
                "(dBIC above the threshold): not reported"
            )
            continue
        f_new, ev, term = res
        rivals = [
            r
            for r in work.last_round
            if r[0].rejected.startswith("explains only")
            and r[1].stages == f_new.stages
            and r[2]["delta_chi2"] >= CATALOG_SHARE * ev["delta_chi2"]
        ]
        if rivals and s not in work.rivals:
            promote(work, min(rivals, key=lambda r: r[0].delta_bic), ev)
            continue
        work.discoveries.append((disc, f_new, ev, term))
        for st in f_new.stages:
            work.current[st] = f_new
            done.add(st)


def _confirm(ses: Session, chain: _Chain, work: _Work, bic_threshold: float):
    """Step 5: the whole chain with the findings added one at a time.

    The chain runs from the logged voltage, which carries no sensor noise into the
    model: a finding must also improve it (dBIC <= -threshold). That guards against
    explaining artefacts of a teacher-forced stage (noise on its measured input bends a
    nonlinear stage's output, a bias no mechanism should take the blame for). A catalog
    mechanism the chain did not confirm is tried again on top of those confirmed after
    it (two effects can each show in the chain only once the other is modelled: a
    backlash under a hysteresis loop), before the learned terms (:func:`rho_cap_of`).
    Returns the findings kept, the chain evidence of each, and those not confirmed."""
    catalog = list(work.selected)
    learned = [term for _, _, _, term in work.discoveries]
    chain_ev: dict[str, dict[str, float]] = {}
    if not chain.ok:
        return catalog + learned, chain_ev, []
    kept: list[AbstractMechanism] = []
    last: dict[str, tuple[AbstractMechanism, dict[str, float]]] = {}

    def confirmed(m: AbstractMechanism, fitted: FitResult | None = None) -> bool:
        prev = chain.fits[-1]
        mechs = [mechanism_start(x, prev) for x in [*kept, m]]
        # ... and from the teacher-forced fits with the mechanisms (on a second try of a
        # learned term: its stages' fit with it, ``fitted``, and its coefficients from
        # zero too, where the chain has bent other parameters to take up what it explains)
        alt = [{n: ses.values[n] for n in chain.free if n in ses.values}]
        if fitted is not None:
            alt.append({n: fitted.values[n] for n in chain.free if n in fitted.values})
        f = fit_mechanisms(
            chain.data,
            ("chain",),
            chain.free,
            mechs,
            tuple(chain.sigma),
            start={n: prev.values[n] for n in chain.free},
            explore=[False] * len(kept) + [fitted is not None],
            alt_starts=alt,
        )
        ev = bic_evidence(f, prev, chain.sigma, rho_max=rho_cap_of([m]))
        if ev["delta_bic"] > -bic_threshold:
            last[m.variant] = (m, ev)
            return False
        kept.append(m)
        chain.fits.append(f)
        chain_ev[m.variant] = ev
        last.pop(m.variant, None)
        return True

    pending = catalog
    while pending:
        failed = [m for m in pending if not confirmed(m)]
        if len(failed) == len(pending):
            break
        pending = failed
    if learned:
        # The learned terms' basis series, for the chain's model.
        chain.data = learned_data(chain.data, [d for d, _, _, _ in work.discoveries])
    for k, (disc, f_stage, _, term) in enumerate(list(work.discoveries)):
        if confirmed(term) or confirmed(term, f_stage):
            continue
        # Not confirmed by the chain: the other places about as good, then the other
        # expressions (a voltage that stands in for the speed on the motor stage alone).
        for alt in disc.alternatives(places_first=True):
            res = fit_learned(ses, alt, work.selected, bic_threshold)
            if res is None:
                continue
            chain.data = learned_data(chain.data, [alt])
            if confirmed(res[2], res[0]):
                work.discoveries[k] = (alt, *res)
                break
    return kept, chain_ev, list(last.values())


def _screened_cells(cells, added, flagged, work: _Work) -> list[Mismatch]:
    """The mismatch a confirmed screened mechanism located where the location test
    flagged nothing (or a learned term that explains it better in its place, the
    mechanism its rival): its stage's most severe cell, flagged, with the evidence in
    words (a diagnosis that names physics has located a mismatch: never ``none``)."""
    out: list[Mismatch] = []
    skip = {m.stage for m in flagged} | ({m.stage for m in added} - {c.stage for c in cells})
    for mech in added:
        screened = getattr(mech, "SCREENED", False)
        rival = next(iter(work.rivals.get(mech.stage, [])), None) if not screened else None
        if not (screened or rival) or mech.stage in skip:
            continue
        worst = max((c for c in cells if c.stage == mech.stage), key=lambda c: c.score)
        name, dbic = (mech.id, work.evidence[mech.variant]["delta_bic"]) if screened else rival
        summary = (
            f"{worst.summary} Under the location test's thresholds (the refitted friction "
            f"coefficient absorbs most of it); located by the targeted test of {name} "
            f"(ΔBIC {dbic:.0f}){'' if screened else ', which a learned term explains better'}."
        ).strip()
        out.append(Mismatch(**{**worst.__dict__, "flagged": True, "summary": summary}))
        skip.add(mech.stage)
    return out


def _stage_metrics(ses: Session, checks: dict) -> dict[str, dict[str, Any]]:
    """Metrics of each stage's channels from its checks."""
    return {
        s: {
            ch: channel_metrics(c.predicted, c.measured)
            for (st, ch), c in checks.items()
            if st == s
        }
        for s in ses.stages
    }


def _findings(
    ses, trace, chain, work, added, chain_ev, flagged, stage_before, stage_after
) -> list[Finding]:
    """A finding, with its words and its metrics before and after, per mechanism kept."""
    findings: list[Finding] = []
    by_variant = {term.variant: (d, f, ev, term) for d, f, ev, term in work.discoveries}
    for k, mech in enumerate(added):
        if chain.ok:
            before = chain_metrics(trace, chain.fits[k])
            after = chain_metrics(trace, chain.fits[k + 1])
        else:
            before = stage_before.get(mech.stage, {})
            after = stage_after.get(mech.stage, {})
        if mech.variant in by_variant:
            disc, f_new, ev, _ = by_variant[mech.variant]
            term = term_at(f_new.mechanisms, disc.place)
            ev = ev | chain_prefixed(chain_ev.get(mech.variant))
            rivals = tuple(work.rivals.get(disc.stage, ()))
            findings.append(
                learned_finding(ses, disc, term, f_new, ev, flagged, before, after, rivals)
            )
        else:
            fit_m = work.current[mech.stage] if mech.stage in work.current else None
            se = stderr_of(mech, fit_m, ses)
            ev = work.evidence[mech.variant] | chain_prefixed(chain_ev.get(mech.variant))
            alts = tuple(work.alternatives.get(mech.variant, ()))
            ctx = refitted_ctx(ses, fit_m)
            findings.append(make_finding(ses, mech, se, ev, flagged, before, after, alts, ctx))
    return findings


def _verdict(ses, work, findings, flagged, unconfirmed, bic_threshold) -> tuple[str, list[str]]:
    """The verdict (``none`` only when nothing is located) and the notes."""
    notes = list(ses.base_messages) + work.notes
    for m, ev in unconfirmed:
        notes.append(
            f"{m.variant} improved the {m.stage} stage fitted from its measured input, but "
            f"not the whole chain from the voltage (dBIC {ev['delta_bic']:.1f} > "
            f"-{bic_threshold:g}): not reported, as the mismatch it absorbed is within what "
            "noise on the stage's measured input produces"
        )
    if not flagged:
        verdict = "none"
    elif any(f.catalog for f in findings):
        verdict = "found"
    else:  # located, not explained by the catalog: never "none"
        verdict = "unexplained"
    if flagged and not findings:  # say where, when not even a correction helps
        notes.append(
            "a mismatch is located ("
            + ", ".join(f"{m.stage} stage, {m.phase}: {m.score:.1f}x" for m in flagged[:3])
            + " the noise), but neither a catalog mechanism nor a learned term that "
            "generalises to held-out data explains it beyond the noise in the whole chain: "
            "unexplained"
        )
    return verdict, notes
