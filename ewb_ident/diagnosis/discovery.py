"""Discovery beyond the catalog: learn the missing term where it acts, prove it on held-out
data, and distil it to an equation.

When a located stage is not explained by the catalog, the diagnosis asks where in the
model something is missing and what it depends on, without a list of candidate physics:

1. **Places.** Every place of the stage where physics can enter
   (:data:`ewb_ident.mechanisms.learned.PLACES`: the motor's electrical and mechanical
   equations, the drive and the gap curve, the force law's input and output, the
   friction coefficient, the brake torque, each sensor's reading) gets a learned term.
2. **Inputs.** The term is a function of every signal the trace and the model supply
   (:func:`input_signals`): recorded channels and model states, their rates, the
   directions of motion, integrals and low-passed histories (heat, energy, sliding
   distance, force history), elapsed time, and positions taken modulo candidate periods.
   A stage's own outputs enter as the model's noise-free predictions (a channel's noise
   must not predict itself).
3. **The learned function** is an additive model: for each input, a flexible basis
   (piecewise-linear hinges for levels; odd powers and a smooth sign for signed
   signals; harmonics for positions, at the periods the residual shows: a periodogram
   in the angle and in x, :func:`~ewb_ident.diagnosis.places.position_periods`, not a
   list), so any smooth or switching dependence on one input and sums over inputs are representable.
   It is fitted through the model: the term's effect on the stage's residuals is the
   model's exact linear response at the place (diagonal for a static place, the motor's
   impulse response for the motor's equations, both the output and the downstream input
   for a sensor), at the current fit together with the Jacobian of the stage's own
   parameters, which are refitted alongside (one Gauss-Newton step of a universal
   differential equation), with a ridge penalty chosen by cross-validation.
4. **Held out.** Inputs enter one at a time while they improve the *held-out* residual
   (leave-one-apply-out with three or more applies, else four blocks in time): a term
   that only fits the data it saw is not kept. Places are ranked by held-out residual;
   one whose distilled term fails held-out data yields to the next that generalises.
5. **Distilled.** Sparse regression over a generated library of the chosen inputs
   (powers, saturations, signs, hinges, one-sided and dead-zone forms, harmonics at the
   learned periods, products) keeps the smallest expression that keeps 90 % of the
   learned term's held-out improvement (greedily; a pair where no single form starts
   it, as a rise that levels off needs two); of places about as good, the one whose
   expression keeps the most.

The distilled term is then fitted by nonlinear least squares through the JAX model (a
:class:`~ewb_ident.mechanisms.learned.LearnedTerm`, with the stage's parameters); its
words come from :func:`ewb_ident.diagnosis.signatures.reading`, as a hypothesis.
Thresholds were set before any study of uncatalogued physics was run.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ewb_ident.data.stages import STAGE_OUTPUTS
from ewb_ident.diagnosis.heldout import (
    HELDOUT_BIC,
    RIDGES,
    TIE,
    Design,
    estimates,
    folds,
    form_spread,
    lag1,
    linearised_start,
    white_level,
)
from ewb_ident.diagnosis.inputs import (
    KNOTS,
    Column,
    Signal,
    carriers_of,
    input_signals,
    learned_groups,
    library,
    product_of,
    render,
    render_pair,
    stacked,
)
from ewb_ident.diagnosis.places import (
    column_span,
    is_local,
    linearised,
    local_signals,
    monotone_twin,
    own_sample_channels,
    place_stages,
    places_of,
    position_periods,
)
from ewb_ident.diagnosis.session import model_channels
from ewb_ident.mechanisms.learned import PLACES
from ewb_ident.model.integrate import motor_fine

#: ... a learned term must also remove at least this share of the held-out excess over
#: the noise (beside a held-out score of at most ``-HELDOUT_BIC``).
MIN_HELDOUT_SHARE = 0.25
#: An input enters the learned function only if it adds this share of the excess.
MIN_STEP_SHARE = 0.03
#: Most inputs of a learned function, and most terms of a distilled equation.
MAX_INPUTS = 3
MAX_TERMS = 4
#: The distilled equation keeps at least this share of the learned term's gain.
KEEP_SHARE = 0.9
#: A basis column whose part outside the span of the stage's own parameters' Jacobian
#: is smaller than this share of it is left out (the parameters make it already).
MIN_NEW_SHARE = 0.05
#: Places in order of specificity: among places whose term removes at least
#: :data:`PLACE_TIE` of the best place's held-out gain, one whose term also explains
#: another stage (:attr:`PlaceFit.spans`: one term for both) and then the first is chosen
#: (a term inside the physics before a sensor's, a sensor's before an added output),
#: unless a close place's distilled term keeps clearly more (:func:`discover`).
PLACE_ORDER = ("motor.", "gap", "drive", "force.input", "friction", "sensor.",
               "force.output", "torque.output")  # fmt: skip
PLACE_TIE = 0.95
#: A catalog mechanism yields to a learned term at its stage when the learned term
#: removes this much more of the excess on held-out data.
CATALOG_MARGIN = 0.05


# ----------------------------------------------------------------------------- search


@dataclass(frozen=True)
class PlaceFit:
    """The learned term at one place: its inputs and held-out residuals."""

    place: str
    groups: tuple[str, ...]
    heldout_before: float
    heldout_after: float
    insample_before: float
    insample_after: float
    excess: float
    score: float
    #: Held-out gain on the located stage's rows alone.
    stage_gain: float = 0.0
    #: Folds where the term is consistent (:meth:`Design.consistent`), of how many.
    folds_improved: int = 0
    n_folds: int = 0
    #: Input groups that, put in place of a chosen one, fit held-out data about as well
    #: (held-out score within half the evidence threshold): the trace cannot tell them.
    ties: tuple[str, ...] = ()
    #: Library items a distilled expression was chosen from (0: a learned term).
    searched: int = 0

    @property
    def rank_gain(self) -> float:
        """What places are ranked by: the held-out gain at the located stage, no more
        than the gain over every stage the term shows in (a sensor's term must not
        worsen the other stage it feeds); the whole gain when the other stage gains
        clearly too (by ``2 HELDOUT_BIC`` and a tenth of the located stage's gain): a
        sensor's error shows downstream, a term of the physics does not."""
        total = self.heldout_before - self.heldout_after
        if self.spans and total - self.stage_gain > 0.1 * self.stage_gain:
            return total
        return min(total, self.stage_gain)

    @property
    def spans(self) -> bool:
        """Whether the term also improves another stage's held-out data clearly (by
        ``2 HELDOUT_BIC``): one term for the mismatch of two stages."""
        return self.heldout_before - self.heldout_after - self.stage_gain > 2 * HELDOUT_BIC

    @property
    def share(self) -> float:
        """Share of the held-out excess over the noise the term removes."""
        gain = self.heldout_before - self.heldout_after
        return gain / self.excess if self.excess > 0 else 0.0

    @property
    def improvement_pct(self) -> float:
        return 100.0 * (self.heldout_before - self.heldout_after) / max(self.heldout_before, 1e-300)

    @property
    def generalises(self) -> bool:
        """Held-out score and share past their thresholds, consistent over the folds."""
        return not self.why_not

    @property
    def why_not(self) -> str:
        """Why the term does not generalise, in words (``""``: it does)."""
        if self.folds_improved < self.n_folds:
            return (
                f"it behaves as physics in only {self.folds_improved} of the {self.n_folds} held-"
                "out folds (lowering each fold that shows the mismatch, not raising the others)"
            )
        if self.share < MIN_HELDOUT_SHARE:
            return (
                f"it removes only {100 * max(self.share, 0.0):.0f} % of the held-out excess "
                f"over the noise (at least {100 * MIN_HELDOUT_SHARE:.0f} % is needed)"
            )
        if self.score > -HELDOUT_BIC:
            return f"its held-out evidence is weak (score {self.score:.1f} > -{HELDOUT_BIC:g})"
        return ""


def group_signals(groups: Sequence[str]) -> list[str]:
    """The signals of input groups (``"current*heat"``, ``"angle@60"``: i, heat, angle)."""
    return [n for g in groups for n in g.partition("@")[0].split("*") if n != "constant"]


def inputs_of(col: Column) -> tuple[str, ...]:
    """The signals a basis column depends on."""
    if col.form[0] == "one":
        return ()
    return tuple(col.form[1:3]) if product_of(col.form) is not None else (col.signal,)


class TermColumns:
    """The basis columns of a distilled term (``terms``: its items, each a tuple of
    columns) and the signals they depend on, in order of first use."""

    terms: tuple[tuple[Column, ...], ...]

    @property
    def columns(self) -> list[Column]:
        return [c for t in self.terms for c in t]

    @property
    def depends_on(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(n for c in self.columns for n in inputs_of(c)))


@dataclass(frozen=True)
class Discovery(TermColumns):
    """What discovery found at one stage: the best place, its learned and distilled
    terms, the other places tried, and the evidence."""

    stage: str
    place: str
    stages: tuple[str, ...]
    learned: PlaceFit
    distilled: PlaceFit
    terms: tuple[tuple[Column, ...], ...]
    coef: tuple[float, ...]
    method: str
    places: tuple[PlaceFit, ...]
    signals: dict[str, Signal] = field(repr=False)
    #: The channels its inputs took from the model rather than the recording.
    model: tuple[str, ...] = ()
    #: Per base parameter (SI): how far its estimate moves between the terms the trace
    #: cannot tell apart (:func:`form_spread`).
    spread: dict[str, float] = field(default_factory=dict)
    #: The stage's free parameters (SI) after the linearised step with the term: a start
    #: for its fit through the model beside the current values.
    start: dict[str, float] = field(default_factory=dict)
    #: Other expressions of the distillation (:func:`distil`), each ``(terms, coef,
    #: distilled, start)``, for when this one does not improve the fit through the model.
    fallbacks: tuple = field(default=(), repr=False)
    #: The recorded channels whose levels its inputs took at their own sample
    #: (:func:`own_sample_channels`).
    raw: tuple[str, ...] = ()
    #: The distilled terms of the other places about as good (:attr:`close_places`)
    #: whose expression generalises, for when this one's fit through the model fails.
    elsewhere: tuple = field(default=(), repr=False)

    def alternatives(self, places_first: bool = False) -> list[Discovery]:
        """This discovery with each of its fallback expressions in place of its own, and
        the distilled terms of the other places that explain the mismatch about as well
        (:attr:`elsewhere`; first with ``places_first``: when the place is in doubt, not
        the expression)."""
        same = [
            replace(self, terms=t, coef=c, distilled=f, start=st, fallbacks=(), elsewhere=())
            for t, c, f, st in self.fallbacks
        ]
        return [*self.elsewhere, *same] if places_first else [*same, *self.elsewhere]

    @property
    def close_places(self) -> tuple[PlaceFit, ...]:
        """The other places whose learned term explains the mismatch about as well."""
        return tuple(p for p in self.places if p.place != self.place and alike(p, self.learned))

    @property
    def equivalents(self) -> tuple[str, ...]:
        """Signals the trace cannot tell from those the term depends on: put in place of
        one of its inputs, or as the inputs of a term at a place about as good
        (:attr:`close_places`), they fit held-out data about as well (they move together
        in this trace)."""
        groups = (*self.learned.ties, *(g for p in self.close_places for g in p.groups))
        return tuple(dict.fromkeys(n for n in group_signals(groups) if n not in self.depends_on))

    def equation(self, coef: Sequence[float] | None = None) -> str:
        """The distilled term in SI units, ``quantity = expression [unit]``."""
        return equation_of(
            self.place, self.terms, self.coef if coef is None else coef, self.signals
        )


def equation_of(
    place: str,
    terms: Sequence[Sequence[Column]],
    coef: Sequence[float],
    signals: Mapping[str, Signal],
) -> str:
    """A term's equation in SI units, ``quantity = expression [unit]`` (a sine and cosine
    pair as one harmonic; a term the refit set under 1e-9 of the largest left out)."""
    coef, info, parts, k = list(coef), PLACES[place], [], 0
    tiny = 1e-9 * max(map(abs, coef), default=0.0)
    for t in terms:
        cs = coef[k : k + len(t)]
        k += len(t)
        if max(map(abs, cs)) < tiny:
            continue
        parts.append(render_pair(t, cs, signals) if len(t) == 2 else render(t[0], cs[0], signals))
    return f"{info.quantity} = {' '.join(parts).lstrip('+')} [{info.unit}]"


def _design(ses, fit, place, groups, fold, stage: str) -> Design | None:
    """The linearised problem of a term at ``place`` about the fit ``fit`` of ``stages``."""
    n = ses.trace.n
    r, J, chans, weights, G_of = linearised(ses, fit, place)
    if G_of is None:
        return None
    n_pad = r.size // len(chans)
    cols = [c for g in groups.values() for c in g]
    G = G_of(np.stack([np.ones(n) if c.values is None else c.values for c in cols], axis=1))
    G[:, ~np.all(np.isfinite(G), axis=0)] = 0.0  # a column the model cannot carry: unused
    keep = np.linalg.norm(G, axis=0) > 0
    norms = np.where(keep, np.linalg.norm(G, axis=0), 1.0)
    G = G / norms
    # What the stage's parameters already make is no new physics (the torque at its output: mu).
    if J.shape[1]:
        Uj = column_span(J)
        orth = np.linalg.norm(G - Uj @ (Uj.T @ G), axis=0)
        G[:, orth < MIN_NEW_SHARE] = 0.0
    fold_rows = np.concatenate([np.r_[fold, -np.ones(n_pad - n, int)]] * len(chans))
    fold_rows = np.where(np.concatenate([weights[c] for c in chans]) > 0, fold_rows, -1)
    rho = lag1(r[fold_rows >= 0])
    noise_rows = float(np.count_nonzero(fold_rows >= 0)) * white_level(r, fold_rows) ** 2
    own = np.concatenate([np.full(n_pad, ch in STAGE_OUTPUTS[stage]) for ch in chans])
    return Design(r, J, fold_rows, G, noise_rows, rho, norms, own)


def _column_index(d: Design, groups: Mapping[str, list[Column]], names) -> list[int]:
    idx, k = [], 0
    for g, cols in groups.items():
        if g in names:
            idx += list(range(k, k + len(cols)))
        k += len(cols)
    return idx


#: Signals a place's term cannot depend on: the driver's voltage acts in the motor's
#: circuit (its electrical equation, and the current sensor, which reads any path beside
#: the motor); the rest sees it only through the current.
CIRCUIT = ("motor.electrical", "sensor.current_A")
NOT_INPUTS = {p: ("voltage", "voltage_rate") for p in PLACES if p not in CIRCUIT}


def learn_place(d: Design, groups: Mapping[str, list[Column]], place: str, sig=None) -> PlaceFit:
    """Forward selection of input groups at one place by held-out residual; an input that
    is a monotone function of a signal of ``sig`` (``{name: Signal}``) local to the place
    is read as that one (:func:`~ewb_ident.diagnosis.places.monotone_twin`)."""
    base_ho, _ = d.best_heldout([])
    base_in, _ = d.insample([], 0.0)
    excess = max(base_ho - d.noise_rows, 0.0)
    chosen, ties, cur = [], [], base_ho  # input groups chosen, groups tied with one; residual
    usable = [g for g in groups if _column_index(d, groups, {g})]
    local = local_signals(place)
    for _ in range(MAX_INPUTS):
        tried = []
        for g in usable:
            if g in chosen or ("@" in g and any("@" in c for c in chosen)):
                continue  # one period at most
            val, _ = d.best_heldout(_column_index(d, groups, {*chosen, g}))
            tried.append((val, g))
        if not tried:
            break
        best = min(tried)
        # Signals along the chain are monotone in one another over an apply (angle,
        # displacement, force, torque): a signal local to the place that does nearly
        # as well is the better reading.
        near = [
            t for t in tried if cur - t[0] >= PLACE_TIE * (cur - best[0]) and is_local(t[1], local)
        ]
        if near and not is_local(best[1], local):
            best = min(near)
        twin_of = monotone_twin(sig or {}, best[1], local)  # once, not per input tried
        if twin := [t for t in tried if t[1] == twin_of]:  # the same function, read locally
            ties, best = [*ties, best[1]], twin[0]
        gain = cur - best[0]
        if gain < MIN_STEP_SHARE * max(excess, 1e-300):
            break
        trial = _column_index(d, groups, {*chosen, best[1]})
        rho = d.rho_after(trial, d.best_heldout(trial)[1])
        if d.score(cur, best[0], rho) > -HELDOUT_BIC / 2:
            break
        chosen.append(best[1])
        ties += [g for v, g in tried if g != best[1] and d.score(best[0], v, rho) < HELDOUT_BIC / 2]
        cur = best[0]
    idx = _column_index(d, groups, set(chosen))
    _, lam = d.best_heldout(idx)
    ins, _ = d.insample(idx, lam)
    stage_gain = d.heldout([], 0.0, stage=True) - d.heldout(idx, lam, stage=True)
    return PlaceFit(
        place,
        tuple(chosen),
        base_ho,
        cur,
        base_in,
        ins,
        excess,
        d.score(base_ho, cur, d.rho_after(idx, lam)),
        stage_gain,
        d.consistent(idx, lam),
        d.n_folds,
        tuple(dict.fromkeys(g for g in ties if g not in chosen)),
    )


def _linear_in(item, other) -> bool:  # linear in the inputs of ``other`` (only those)
    ins = {n for c in other for n in inputs_of(c)}
    return all(c.form[:2] == ("pow", 1) and set(inputs_of(c)) <= ins for c in item)


def _forward(d: Design, items, learned: PlaceFit, chosen: list[int]) -> tuple[list[int], float]:
    """Forward selection over the library from the items ``chosen``: items enter by
    held-out residual until the expression keeps :data:`KEEP_SHARE` of the learned
    term's held-out gain (at most :data:`MAX_TERMS`); when no single item starts the
    expression, the best pair may (two forms that only together make the learned shape:
    a rise that levels off, a bump). Returns the items and the held-out residual."""
    target = learned.heldout_before - KEEP_SHARE * (learned.heldout_before - learned.heldout_after)
    cur = d.heldout(_item_cols(items, chosen), RIDGES[0]) if chosen else learned.heldout_before
    while len(chosen) < MAX_TERMS and not (chosen and cur <= target):
        vals = [
            (d.heldout(_item_cols(items, [*chosen, j]), RIDGES[0]), j)
            for j in range(len(items))
            if j not in chosen
        ]
        if not vals:
            break
        best = min(vals)
        # A law linear in the best's input where held-out data cannot tell them apart.
        same = [v for v in vals if _linear_in(items[v[1]], items[best[1]])]
        best = min([v for v in same if d.score(best[0], v[0]) < TIE] or [best])
        step = MIN_STEP_SHARE * max(learned.excess, 1e-300)
        if cur - best[0] < step:
            pair = None if chosen else _best_pair(d, items)
            if pair is None or cur - pair[0] < 2 * step:
                break
            chosen, cur = list(pair[1:]), pair[0]
            continue
        chosen = [*chosen, best[1]]
        cur = best[0]
    return chosen, cur


def _best_pair(d: Design, items) -> tuple[float, int, int] | None:
    """The pair of library items with the lowest held-out residual (or ``None``)."""
    pairs = itertools.combinations(range(len(items)), 2)
    return min(((d.heldout(_item_cols(items, p), RIDGES[0]), *p) for p in pairs), default=None)


def _distilled_fit(d: Design, items, learned: PlaceFit, place: str, chosen, cur):
    """The PlaceFit of the items ``chosen``, their coefficients (per normalised basis
    column) and the stage parameters' step."""
    cols = _item_cols(items, chosen)
    ins, x = d.insample(cols, RIDGES[0])
    fit = PlaceFit(
        place,
        tuple(str(j) for j in chosen),
        learned.heldout_before,
        cur,
        learned.insample_before,
        ins,
        learned.excess,
        d.score(learned.heldout_before, cur, d.rho_after(cols, RIDGES[0])),
        learned.stage_gain,
        d.consistent(cols, RIDGES[0]),
        d.n_folds,
        searched=len(items),
    )
    coef = x[d.kb :] / d.norms[cols] if cols else np.zeros(0)
    return fit, [items[j] for j in chosen], coef, x[: d.kb]


#: Other expressions a distillation offers, for when the chosen one does not improve
#: the fit through the model (:func:`distil`).
FALLBACKS = 2


def distil(d: Design, items: list[list[Column]], learned: PlaceFit, place: str):
    """Forward selection over the library (:func:`_forward`): the smallest expression
    that keeps :data:`KEEP_SHARE` of the learned term's held-out gain. Returns its
    PlaceFit (its ``groups`` the chosen items' indices), the chosen items, their
    least-squares coefficients (per normalised basis column of the design), the stage
    parameters' step, and the steps of the forms held-out data cannot tell from it."""
    chosen, cur = _forward(d, items, learned, [])
    fit, chosen_items, coef, step = _distilled_fit(d, items, learned, place, chosen, cur)
    # Forms the held-out data cannot tell from the chosen one: one item swapped for
    # another whose held-out score differs by less than half the evidence threshold.
    alts = []
    for pos in range(len(chosen)):
        for j in range(len(items)):
            if j in chosen:
                continue
            swap = [*chosen[:pos], j, *chosen[pos + 1 :]]
            c_alt = _item_cols(items, swap)
            val = d.heldout(c_alt, RIDGES[0])
            if d.score(cur, val, d.rho_after(c_alt, RIDGES[0])) < TIE:
                alts.append(d.insample(c_alt, RIDGES[0])[1][: d.kb])
    return fit, chosen_items, coef, step, alts


def fallback_expressions(d: Design, items, learned: PlaceFit, distilled: PlaceFit, fit) -> list:
    """Up to :data:`FALLBACKS` other expressions (as :attr:`Discovery.fallbacks` holds
    them; ``fit``: the fit the design is linearised about), each a forward selection
    from the best first item on other signals than the distilled expression's first: on
    a large mismatch the linearised design can rank signals that all move with it nearly
    alike, and the fit through the model decides (an angle harmonic a hair above the
    current that drives a magnetic saturation)."""
    chosen = [int(g) for g in distilled.groups]
    if not chosen:
        return []
    used = {inputs_of(c) for c in items[chosen[0]]}
    singles = (j for j in range(len(items)) if j not in chosen)
    first = sorted((d.heldout(_item_cols(items, [j]), RIDGES[0]), j) for j in singles)
    out = []
    for _, j in first:
        ins = {inputs_of(c) for c in items[j]}
        if len(out) == FALLBACKS:
            break
        if ins <= used or not all(ins):
            continue
        used |= ins
        c2, cur2 = _forward(d, items, learned, [j])
        f_fit, f_items, f_coef, f_step = _distilled_fit(
            d, items, learned, distilled.place, c2, cur2
        )
        if f_fit.generalises:
            terms = tuple(tuple(t) for t in f_items)
            out.append((terms, tuple(map(float, f_coef)), f_fit, linearised_start(fit, f_step)))
    return out


def _item_cols(items, chosen) -> list[int]:
    offs = np.cumsum([0] + [len(it) for it in items])
    return [int(offs[j]) + i for j in chosen for i in range(len(items[j]))]


def discover(ses, stage: str, fits_of) -> Discovery | None:
    """Learn the missing term at every place of ``stage``, keep the best on held-out data,
    and distil it.

    Parameters
    ----------
    ses
        The diagnosis session (trace, data, baseline fits).
    stage
        The located stage.
    fits_of
        ``fits_of(stages) -> FitResult``: the current fit of a set of stages (with the
        catalog mechanisms selected there).

    Returns
    -------
    Discovery or None
        ``None`` when no place's term can be built for this trace.
    """
    trace = ses.trace
    fold, method = folds(ses.labels)
    results = []
    for place in places_of(stage, ses.cols):
        stages = place_stages(place, ses.stages)
        if stage not in stages:
            continue
        fit = fits_of(stages)
        fine = motor_fine(fit.values, trace) if place.startswith("motor.") else None
        model = model_channels(ses, fit)
        raw = own_sample_channels(trace, model, stages)
        sig = input_signals(trace, model, fine, raw)
        sig = {k: v for k, v in sig.items() if k not in NOT_INPUTS.get(place, ())}
        groups = learned_groups(sig, carriers_of(place), position_periods(ses, fit, place, sig))
        d = _design(ses, fit, place, groups, fold, stage)
        if d is None:
            continue
        pf = learn_place(d, groups, place, sig)
        results.append((pf, d, groups, sig, stages, (tuple(model), raw)))
    if not results:
        return None
    # The place whose term removes the most held-out residual (in units of the noise:
    # a sensor's term is judged on both stages it shows in).
    results.sort(key=lambda x: -x[0].rank_gain)
    best_gain = results[0][0].rank_gain
    close = keep_generalising(
        [x for x in results if x[0].groups and x[0].rank_gain >= PLACE_TIE * best_gain]
    )
    if close:
        first = min(close, key=lambda x: (not x[0].spans, _specificity(x[0].place)))
        results.insert(0, results.pop(results.index(first)))
    pf, d, groups, sig, stages, (model, raw) = results[0]
    if not pf.groups:
        places = tuple(r[0] for r in results)
        return Discovery(stage, pf.place, stages, pf, pf, (), (), method, places, sig, model,
                         raw=raw)  # fmt: skip

    def distilled(pf, sig, stages, knots=(0.5,)):
        items = library(sig, pf.groups, knots)
        groups_l = {f"item{j}": list(it) for j, it in enumerate(items)}
        fit = fits_of(stages)
        dl = _design(ses, fit, pf.place, groups_l, fold, stage)
        assert dl is not None  # the same place built a design above
        dfit, chosen, x, step, alts = distil(dl, items, pf, pf.place)
        if not chosen and len(knots) < len(KNOTS):
            # The library's smooth forms are what the stage's own parameters already
            # make (a gap polynomial takes up any smooth function of the angle over one
            # apply): hinges at every knot of the learned basis, for a term that sets
            # in part of the way (a compliance past contact).
            return distilled(pf, sig, stages, KNOTS)
        return dfit, chosen, x, fit, step, [estimates(fit, a) for a in alts], (dl, items)

    done: dict[str, tuple] = {}

    def distilled_at(r):  # each place's once
        if r[0].place not in done:
            done[r[0].place] = distilled(r[0], r[3], r[4])
        return done[r[0].place]

    # Of the places that explain the mismatch about as well, the first whose distilled
    # term keeps about as much held-out gain as the best distilled one: a learned term
    # the library cannot express (in the learned basis, not the library) yields to one.
    def close_to(pf):  # the other places whose learned term explains about as much
        return [r for r in results[1:] if alike(r[0], pf)]

    cands = keep_generalising([results[0], *close_to(pf)])
    kept_gain = [f.heldout_before - f.heldout_after for f, *_ in map(distilled_at, cands)]
    kept = cands[next(i for i, g in enumerate(kept_gain) if g >= PLACE_TIE * max(kept_gain))]
    if not distilled_at(kept)[0].generalises:
        # A larger gain that fails held-out data does not hide a place whose terms pass.
        passing = (r for r in results if r[0].generalises and distilled_at(r)[0].generalises)
        kept = next(passing, kept)
    if kept is not results[0]:
        results.insert(0, results.pop(results.index(kept)))
        pf, d, groups, sig, stages, (model, raw) = kept
    dfit, chosen, x, fit, step, others, (dl, items) = distilled_at(kept)
    others = list(others)  # (a copy: ``done`` keeps the original)
    fallbacks = fallback_expressions(dl, items, pf, dfit, fit)
    best = estimates(fit, step, free_only=False)
    # Other estimates of the stage's parameters: the distilled forms, and the distilled
    # terms of other places, about as good on held-out data ("the trace cannot tell").
    elsewhere = []
    for r in close_to(pf):
        dfit_o, chosen_o, x_o, fit_o, step_o, _, _ = distilled_at(r)
        others.append(estimates(fit_o, step_o))
        if chosen_o and dfit_o.generalises:  # (kept for a fit through the model that fails)
            elsewhere.append((r, dfit_o, chosen_o, x_o, fit_o, step_o))
    spread = form_spread(best, others)
    places = tuple(r[0] for r in results)

    def found_at(r, dfit, chosen, x, fit, step, fallbacks=()) -> Discovery:
        pf, _, _, sig, stages, (model, raw) = r
        terms = tuple(tuple(t) for t in chosen)
        coef, start = tuple(float(c) for c in x), linearised_start(fit, step)
        return Discovery(stage, pf.place, stages, pf, dfit, terms, coef, method, places, sig,
                         model, spread, start, tuple(fallbacks), raw)  # fmt: skip

    main = found_at(kept, dfit, chosen, x, fit, step, fallbacks)
    return replace(main, elsewhere=tuple(found_at(*e) for e in elsewhere))


def keep_generalising(cands: list) -> list:
    """Of places that explain the mismatch about as well, those whose term generalises
    (:attr:`PlaceFit.why_not`), if any does: a term that fails the held-out folds at
    one place does not hide one that passes them at another."""
    good = [r for r in cands if r[0].generalises]
    return good or cands


#: Places whose held-out gain is at least this share of the best's explain the
#: mismatch about as well: the trace cannot tell them apart.
CLOSE = 0.9


def alike(other: PlaceFit, to: PlaceFit) -> bool:
    """Whether ``other`` explains the mismatch about as well as ``to`` (:data:`CLOSE`) and
    passes the held-out folds where ``to`` does (a term that fails them is no twin)."""
    good = other.generalises or not to.generalises
    return bool(other.groups) and other.rank_gain >= CLOSE * to.rank_gain and good


def _specificity(place: str) -> int:
    return next(i for i, p in enumerate(PLACE_ORDER) if place.startswith(p))


def basis_matrix(disc: Discovery) -> np.ndarray:
    """The distilled term's basis series on the diagnosed trace, (n, K)."""
    n = disc.signals[next(iter(disc.signals))].values.size
    return stacked([c.values for c in disc.columns], n)
