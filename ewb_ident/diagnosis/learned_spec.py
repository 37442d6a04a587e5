"""A learned term as data: where it acts, its distilled basis and its coefficients, to
refit it as part of a model on any trace (``fit --with-diagnosis``, ``sample``,
``validate``) and to write it into ``diagnosis.json``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ewb_ident.data.stages import CHANNELS
from ewb_ident.data.trace import InputError
from ewb_ident.diagnosis.discovery import (
    Discovery,
    TermColumns,
    equation_of,
    inputs_of,
)
from ewb_ident.diagnosis.inputs import (
    Column,
    Signal,
    form_fn,
    form_values,
    input_signals,
    product_of,
    stacked,
)
from ewb_ident.mechanisms.learned import PLACES, LearnedTerm
from ewb_ident.model.integrate import motor_fine
from ewb_ident.model.params import MODEL_PARAMS, EWBParams


class TermError(InputError):
    """A learned term that cannot be read or rebuilt on a trace."""


@dataclass(frozen=True)
class LearnedSpec(TermColumns):
    """A learned term as data, to refit it as part of a model on any trace: where it
    acts, its distilled basis (each column a form of named signals,
    :func:`ewb_ident.diagnosis.inputs.form_values`), the size each signal is normalised
    by, which channels its inputs take from the model, and its coefficients (in the
    place's unit per normalised column).

    On a trace, the inputs are rebuilt as the diagnosis built them: recorded channels
    through their leave-one-out average (the levels of those in ``raw`` as recorded),
    the channels in ``model`` (and those the trace does not record) from the seed chain
    simulated from the voltage at the model's parameters, and the motor's states within
    each sample for a term in the motor.
    """

    place: str
    terms: tuple[tuple[Column, ...], ...]
    refs: dict[str, float]
    model: tuple[str, ...]
    coef: tuple[float, ...]
    #: Per base parameter (SI), how far its estimate moves between the forms and places
    #: of the term the diagnosed trace could not tell apart (:func:`form_spread`).
    spread: dict[str, float] = field(default_factory=dict)
    #: Recorded channels whose levels enter at their own sample (not their neighbours'
    #: average, :func:`~ewb_ident.diagnosis.inputs.input_signals`).
    raw: tuple[str, ...] = ()

    @classmethod
    def of(cls, disc: Discovery, coef: Sequence[float]) -> LearnedSpec:
        refs = {n: disc.signals[n].ref for c in disc.columns for n in inputs_of(c)}
        terms = tuple(tuple(Column(c.label, c.signal, None, c.form) for c in t) for t in disc.terms)
        coef = tuple(float(c) for c in coef)
        return cls(disc.place, terms, refs, disc.model, coef, dict(disc.spread), disc.raw)

    def to_json(self) -> dict[str, Any]:
        return {
            "place": self.place,
            "terms": [
                [{"label": c.label, "signal": c.signal, "form": list(c.form)} for c in t]
                for t in self.terms
            ],
            "refs": dict(self.refs),
            "model_channels": list(self.model),
            "coef": list(self.coef),
            "spread": dict(self.spread),
            "raw_channels": list(self.raw),
        }

    @classmethod
    def from_json(cls, doc: Any, where: str) -> LearnedSpec:
        """Read :meth:`to_json`'s document; ``where`` names it in the error.

        Raises
        ------
        TermError
            A document that is not a learned term's basis.
        """
        try:
            terms = tuple(
                tuple(Column(str(c["label"]), str(c["signal"]), None, tuple(c["form"])) for c in t)
                for t in doc["terms"]
            )
            spec = cls(
                str(doc["place"]),
                terms,
                {str(k): float(v) for k, v in doc["refs"].items()},
                tuple(str(c) for c in doc["model_channels"]),
                tuple(float(c) for c in doc["coef"]),
                {str(k): float(v) for k, v in (doc.get("spread") or {}).items()},
                tuple(str(c) for c in doc.get("raw_channels", ())),
            )
            for c in spec.columns:
                if c.form[0] != "one":
                    form_fn(product_of(c.form) or c.form, 1.0)
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise TermError(
                f"{where}: not a learned term's basis ({type(err).__name__}: {err}); use the "
                "'basis' of a finding that diagnose wrote"
            ) from None
        if spec.place not in PLACES or len(spec.coef) != len(spec.columns):
            raise TermError(
                f"{where}: place {spec.place!r} or its {len(spec.coef)} coefficients do not "
                f"match its {len(spec.columns)} columns; use the 'basis' diagnose wrote"
            )
        unknown = [c for c in (*spec.model, *spec.raw) if c not in CHANNELS]
        if unknown:
            raise TermError(
                f"{where}: 'model_channels' or 'raw_channels' names {', '.join(unknown)}, "
                "which is no channel of the trace format; use the 'basis' diagnose wrote"
            )
        numbers = [*spec.coef, *spec.refs.values(), *spec.spread.values()]
        if not all(np.isfinite(numbers)):
            raise TermError(f"{where}: a coefficient or size is not a finite number")
        return spec

    def term(self, coef: Sequence[float] | None = None) -> LearnedTerm:
        """The term as a mechanism (its coefficients scaled by their own size)."""
        return learned_term(
            self.place, [c.label for c in self.columns], self.coef if coef is None else coef
        )

    def signals_on(self, trace, values: Mapping[str, float]) -> dict[str, Signal]:
        """The term's inputs on ``trace`` with the model at ``values`` (SI, with
        ``theta0_deg``), normalised by the sizes it was fitted with.

        Raises
        ------
        TermError
            The trace lacks an input the term depends on (e.g. the disc speed).
        """
        from ewb_ident.model.predict import simulate_chain

        p = EWBParams(**{k: float(values[k]) for k in MODEL_PARAMS})
        sim = simulate_chain(
            p, trace["voltage_V"], trace.dt, float(values["theta0_deg"]), trace.r_eff_m
        )
        model = {
            ch: np.asarray(sim[ch], float)
            for ch in CHANNELS
            if ch in self.model or not trace.has(ch)
        }
        fine = motor_fine(values, trace) if self.place.startswith("motor.") else None
        return self._signals(trace, model, fine)

    def _signals(self, trace, model, fine) -> dict[str, Signal]:
        sig = input_signals(trace, model, fine, self.raw)
        missing = [n for n in self.refs if n not in sig]
        if missing:
            raise TermError(
                f"{trace.label}: the learned term at {self.place} depends on "
                f"{', '.join(missing)}, which this trace does not supply (or which does not "
                "vary in it); refit on a trace that records it"
            )
        return {n: replace(s, ref=self.refs[n]) if n in self.refs else s for n, s in sig.items()}

    def basis(self, signals: Mapping[str, Signal]) -> np.ndarray:
        """The basis series (n, K) on the signals of :meth:`signals_on`."""
        n = next(iter(signals.values())).values.size
        return stacked([form_values(c.form, c.signal, signals, self.refs) for c in self.columns], n)

    def equation(self, signals: Mapping[str, Signal], coef: Sequence[float] | None = None) -> str:
        return equation_of(self.place, self.terms, self.coef if coef is None else coef, signals)


def learned_term(place: str, labels: Sequence[str], coef: Sequence[float]) -> LearnedTerm:
    """A :class:`LearnedTerm` whose optimiser coordinates are its coefficients over
    their own sizes."""
    return LearnedTerm(
        place=place,
        names=tuple(labels),
        scales=tuple(float(max(abs(c), 1e-12)) for c in coef),
        coef=np.asarray(coef, float),
    )
