"""Catalog names against learned terms at one stage: never a confident wrong name.

A catalog mechanism names physics with parameters a researcher knows; a learned term
(:mod:`ewb_ident.diagnosis.discovery`) represents whatever acts at a place. Where both
explain a stage, the catalog name is kept only when the data ask for it:

* :func:`second_opinion`: the catalog mechanisms selected at a stage must remove at
  least as much of the excess residual there as the best learned term does on held-out
  data (less :data:`~ewb_ident.diagnosis.discovery.CATALOG_MARGIN`), and the learned
  term fitted through the model in their place must not fit the stage better by the
  evidence threshold, its ΔBIC charged for the choice of its expression
  (:func:`search_penalty`), unless the catalog mechanisms explain more of the excess
  than the learned term does on held-out data;
* :func:`one_explanation`: when a learned term is still needed on top of a catalog
  mechanism at its stage, the mechanism must also earn its place on top of a learned
  term fitted without it: the stage's fit with both must beat the learned term alone by
  the evidence threshold (``dBIC <= -threshold``, the rule every finding passes), and
  predict held-out data better than it (the pair's catalog parameters are fitted on
  every fold, which can only favour the pair). Otherwise one explanation (the learned
  term: the discovery's own, or another of its expressions and places) does what two
  claim to. Where the term alone acts at other stages than the pair (a motor load torque
  against an angle sensor's term), both are fitted on the stages of either and compared
  in BIC alone (held-out residuals of terms at different places are not comparable).

Both compare fits of the same stages and weights; a dropped catalog name becomes a rival
the finding lists. :func:`promote` selects a held-back catalog rival in place of a
learned term that explains little more; :func:`best_search` chooses among catalog
searches run again with the names the whole chain did not confirm set aside.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Any

from ewb_ident.data.stages import STAGE_OUTPUTS
from ewb_ident.diagnosis.discovery import CATALOG_MARGIN, discover
from ewb_ident.diagnosis.findings import closure, fit_learned, learned_data
from ewb_ident.diagnosis.result import Candidate
from ewb_ident.diagnosis.session import Session, bic_evidence, stage_order
from ewb_ident.inference.augmented import fit_mechanisms


def fits_of(ses: Session, selected):
    """The current fit of a set of stages, with the selected mechanisms acting there."""

    def fit(stages):
        T = closure(stages, selected, ses)
        ms = [m for m in selected if set(ses.mechanism_stages(m)) & set(T)]
        return ses.fit(T, ms, explore=[False] * len(ms))

    return fit


def _drop(work: Any, stage: str, at: Sequence[Any], why: str) -> None:
    """Unselect the catalog mechanisms ``at`` (their candidates say why) and make them
    the rivals of a learned term at ``stage``."""
    for mech in at:
        work.selected.remove(mech)
        ev = work.evidence.pop(mech.variant)
        k = next(
            i for i, c in enumerate(work.candidates) if c.selected and c.variant == mech.variant
        )
        cand = work.candidates[k]
        work.candidates[k] = Candidate(**{**cand.__dict__, "selected": False, "rejected": why})
        work.rivals.setdefault(stage, []).append((mech.id, float(ev["delta_bic"])))
        work.notes.append(f"{mech.variant}: not reported: {why}")


def second_opinion(ses: Session, work: Any, threshold: float) -> None:
    """The catalog mechanisms selected at a stage stay only if together they remove at
    least as much of the excess there as the best learned term does on held-out data
    (less :data:`CATALOG_MARGIN`), and the learned term fitted through the model in
    their place does not fit the stage better by ``threshold`` in BIC (the share is
    judged on the stage's channels together, where one channel's large mismatch can
    hide another's that the mechanism leaves). Otherwise they are dropped, the stage
    goes to discovery, and the catalog names become the learned term's rivals."""
    for stage in dict.fromkeys(m.stage for m in work.selected):
        at = [m for m in work.selected if m.stage == stage]
        others = [m for m in work.selected if m.stage != stage]
        disc = discover(ses, stage, fits_of(ses, others))
        if disc is None or not disc.learned.generalises:
            continue
        T = closure((stage,), work.selected, ses)
        without = fits_of(ses, others)(T)
        with_all = fits_of(ses, work.selected)(T)
        own = [c for st in ses.mechanism_stages(at[0]) for c in STAGE_OUTPUTS[st]]
        explained = bic_evidence(with_all, without, ses.sigma_tf, own)["explained_fraction"]
        learned = min(disc.learned.share, 1.0)
        names = ", ".join(m.variant for m in at)
        if learned > explained + CATALOG_MARGIN:
            why = (
                f"a learned term at {disc.place} removes {100 * learned:.0f} % of the excess "
                f"on held-out data against {100 * explained:.0f} % by {names}"
            )
        else:
            res = fit_learned(ses, disc, others, threshold) if disc.distilled.generalises else None
            if res is None or res[0].stages != with_all.stages:
                continue
            gain = bic_evidence(res[0], with_all, ses.sigma_tf)["delta_bic"]
            if gain > -threshold:
                continue
            search = search_penalty(disc)
            kept = f"{names}: kept: a learned term at {disc.place} fits its stages better "
            if gain + search > -threshold:
                work.notes.append(
                    kept + f"(dBIC {gain:+.1f}), but not by the evidence threshold once "
                    f"choosing its expression among {disc.distilled.searched} forms is "
                    f"charged ({search:+.1f})"
                )
                continue
            if learned < explained:  # a better fit to this trace, worse on held-out data
                work.notes.append(
                    kept + f"(dBIC {gain:+.1f}) but removes less of the excess on held-out "
                    f"data ({100 * learned:.1f} %) than {names} does ({100 * explained:.1f} %)"
                )
                continue
            why = (
                f"a learned term at {disc.place} in its place fits its stages better than "
                f"{names} (dBIC {gain:+.1f}, {search:+.1f} for its expression chosen among "
                f"{disc.distilled.searched} forms, threshold -{threshold:g})"
            )
        _drop(work, stage, at, why)
        for st in T:
            work.current[st] = fits_of(ses, work.selected)((st,))


def search_penalty(disc) -> float:
    """What choosing the distilled expression's ``k`` terms among the library's ``M``
    forms adds to its BIC against a catalog law fixed beforehand: ``2 ln C(M, k)`` (the
    extended BIC of Chen and Chen, 2008). Without it an expression picked for its fit
    to this trace is compared as if it had been written down before seeing it."""
    m, k = disc.distilled.searched, len(disc.terms)
    if not 0 < k <= m:
        return 0.0
    return 2.0 * (math.lgamma(m + 1) - math.lgamma(k + 1) - math.lgamma(m - k + 1))


def _on(ses: Session, T: Sequence[str], fitted, disc, others) -> Any:
    """A fit of the stages ``T`` from ``fitted`` (a fit of some of them with a learned
    term at ``disc``'s place, whose basis it takes), with the mechanisms ``others`` of
    the stages ``fitted`` did not cover; ``fitted`` itself when it covers them all."""
    if set(fitted.stages) == set(T):
        return fitted
    extra = [m for m in others if set(ses.mechanism_stages(m)) & (set(T) - set(fitted.stages))]
    mechs = (*fitted.mechanisms, *extra)
    free = ses.free_of(T)
    return fit_mechanisms(
        learned_data(ses.data, [disc]), T, free, mechs, ses.channels_of(T),
        start={n: fitted.values.get(n, ses.values[n]) for n in free},
        explore=[False] * len(mechs),
    )  # fmt: skip


def one_explanation(ses: Session, work: Any, threshold: float) -> None:
    """A catalog mechanism under a learned term at its stages must beat, together with
    that term, a learned term fitted without it by ``threshold`` in BIC and on held-out
    data (the learned terms' held-out residuals); otherwise it is dropped and the
    learned term fitted without it takes the discovery's place. The term without it is
    the discovery's own, else the first of its other expressions and places that the
    pair does not beat (:func:`alone_terms`)."""
    for k, (disc, f_both, _, _) in enumerate(list(work.discoveries)):
        at = [m for m in work.selected if set(ses.mechanism_stages(m)) & set(f_both.stages)]
        if not at:
            continue
        others = [m for m in work.selected if m not in at]
        found = discover(ses, disc.stage, fits_of(ses, others))
        terms = [] if found is None else alone_terms(ses, found, others, f_both, threshold)
        names = ", ".join(m.variant for m in at)
        first = dropped = None
        for alone, res in terms:
            why, gain, same = _against(ses, disc, f_both, alone, res, others, threshold, names)
            first = first or (alone, gain, same)
            if why:
                dropped = (alone, res, why)
                break
        if dropped is None:
            if first is not None:  # the name stands, and says what it was weighed against
                alone, gain, same = first
                where = (" (on the stages of either)", " and predict held-out data better")
                work.notes.append(
                    f"{names}: kept beside the learned term at {disc.place}: together they "
                    f"fit better than a learned term at {alone.place} alone (dBIC "
                    f"{gain:+.1f}){where[same]}"
                )
            continue
        alone, res, why = dropped
        _drop(work, disc.stage, at, why)
        work.discoveries[k] = (alone, *res)
        for st in res[0].stages:
            work.current[st] = res[0]


def _against(ses: Session, disc, f_both, alone, res, others, threshold: float, names: str):
    """The pair (``disc``'s term on top of the catalog mechanisms ``names``, fitted as
    ``f_both``) weighed against the learned term ``alone`` (fitted as ``res``): ``(why
    the name goes or "", dBIC of the pair, same stages)``."""
    # Where the term alone acts at other stages, both on the stages of either (the
    # held-out residuals of terms at different places are not comparable).
    same = res[0].stages == f_both.stages
    T = stage_order(set(res[0].stages) | set(f_both.stages))
    pair_T, one_T = _on(ses, T, f_both, disc, others), _on(ses, T, res[0], alone, others)
    gain = bic_evidence(pair_T, one_T, ses.sigma_tf)["delta_bic"]
    pair, one = disc.learned.heldout_after, alone.learned.heldout_after
    why = ""
    if gain > -threshold:
        why = (
            f"a learned term at {alone.place} alone fits its stages as well as "
            f"{names} with a learned term on top "
            f"(dBIC {gain:+.1f} for the pair, threshold -{threshold:g})"
            + ("" if same else " (on the stages of either)")
        )
    elif same and one <= pair:
        why = (
            f"a learned term at {alone.place} alone predicts held-out data as well as "
            f"{names} with a learned term on top (held-out residual "
            f"{one / pair:.2f} of the pair's)"
        )
    return why, gain, same


def alone_terms(ses: Session, disc, others, f_both, threshold: float) -> Iterator[tuple]:
    """The learned terms without the catalog mechanism, in the order the pair is weighed
    against them: of ``disc``'s distilled term and its alternatives (other expressions,
    other places about as good) that generalise and lower their stages' BIC by
    ``threshold``, those on the stages of the pair's fit ``f_both`` if any acts there
    (else the first), the discovery's own first and the others by BIC. Each is
    ``(discovery, fit_learned result)``, fitted through the model only when the pair is
    weighed against it or needs it for the order (the first that the pair does not beat
    ends the weighing). The pair must beat every learned term alone, not only the
    first: without a current sensor the motor's two places explain a load alike, and
    the first can be the one whose distilled form fits the motor worse."""
    tried = (d for d in (disc, *disc.alternatives()) if d.learned.groups)
    fits = ((d, r) for d in tried if d.distilled.generalises
            and (r := fit_learned(ses, d, others, threshold)) is not None)  # fmt: skip
    first = None
    for x in fits:
        if x[1][0].stages == f_both.stages:
            yield x
            break
        first = first or x
    else:  # none acts on the pair's stages: the first alone
        if first is not None:
            yield first
        return
    rest = [x for x in fits if x[1][0].stages == f_both.stages]
    yield from sorted(rest, key=lambda x: x[1][1]["delta_bic"])


def promote(work, rival: tuple, generic_ev: dict[str, float]) -> None:
    """Select a held-back catalog rival in place of a discovered term."""
    cand, f1, ev1, mech = rival
    note = (
        f"explains {100 * cand.explained:.0f} % of the excess residual, "
        f"{100 * cand.delta_chi2 / generic_ev['delta_chi2']:.0f} % of what a learned term "
        "at its stage removes"
    )
    k = next(i for i, c in enumerate(work.candidates) if c is cand)
    work.candidates[k] = Candidate(**{**cand.__dict__, "selected": True, "rejected": ""})
    # One rival per stage set: a second located stage with the same stages must not
    # promote it again nor add another rival for the mismatch it explains.
    work.last_round = [r for r in work.last_round if r[1].stages != f1.stages]
    work.selected.append(mech)
    work.evidence[mech.variant] = ev1 | {"generic_delta_chi2": generic_ev["delta_chi2"]}
    work.notes.append(f"{mech.variant}: {note}")
    for st in f1.stages:
        work.current[st] = f1


def best_search(chains: Sequence[Any], chain: Any) -> int:
    """Of the catalog searches (each with the names the whole chain did not confirm set
    aside), the one whose findings fit the whole chain best (dBIC against the chain's
    baseline ``chain.fits[0]``); the first when they tie or there is no chain."""
    if not chain.ok or len(chains) == 1:
        return 0
    dbic = [bic_evidence(c.fits[-1], chain.fits[0], chain.sigma)["delta_bic"] for c in chains]
    return min(range(len(chains)), key=lambda k: (dbic[k], k))


def set_aside_records(earlier: Sequence[Any], unconfirmed, bic_threshold: float) -> list:
    """The candidate records of the names the searches before the one kept (``earlier``)
    selected and the whole chain did not confirm (``unconfirmed``: (mechanism, chain
    evidence) pairs), marked as set aside."""
    aside = {m.variant: ev for m, ev in unconfirmed}
    why = "not confirmed by the whole chain from the voltage (dBIC {:.1f} > -{:g})"
    return [
        Candidate(**{**c.__dict__, "selected": False,
                     "rejected": why.format(aside[c.variant]["delta_bic"], bic_threshold)})
        for w in earlier for c in w.candidates if c.selected and c.variant in aside
    ]  # fmt: skip
