"""Held-out evidence for a learned term: folds of a trace (:func:`folds`) and the
linearised problem at one place solved on some folds and scored on the others
(:class:`Design`); the stage's parameters after a linearised step (:func:`estimates`).
Used by :mod:`ewb_ident.diagnosis.discovery`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ewb_ident.data.metrics import RHO_MAX
from ewb_ident.model.params import PARAMS, EWBParams

#: A learned term must lower the held-out residual by this much (a dBIC-like score of
#: the held-out residual sums, with the effective number of residuals, no penalty).
HELDOUT_BIC = 10.0
#: Held-out scores closer than this are ones the data cannot tell apart.
TIE = HELDOUT_BIC / 2
#: Largest lag-1 correlation used for that effective number: a smooth remainder (a
#: motor's angle integrates any misfit) would otherwise leave a handful of "independent"
#: residuals; the held-out folds, not this count, guard against a term fitting noise.
RHO_CAP = 0.9
#: Ridge penalties tried (relative to the mean diagonal of the term's Gram matrix).
RIDGES = (1e-4, 1e-2, 1.0)


# ----------------------------------------------------------------------------- folds


#: Largest share of the samples one apply's fold may hold: leaving it out must leave the
#: others enough of the trace to fit on (else blocks in time are used).
FOLD_MAX_SHARE = 0.5


def folds(labels: np.ndarray) -> tuple[np.ndarray, str]:
    """Fold index of each sample, and the method in words: leave one apply out when the
    trace holds three or more applies (each from the open pads before it to those
    after) and none holds more than :data:`FOLD_MAX_SHARE` of it, otherwise four
    contiguous blocks in time (a reading that drifts can make the open pads flicker into
    many "applies" of a few samples beside one that holds nearly the whole trace)."""
    n = labels.size
    open_ = labels == "gapping"
    starts = [i for i in range(1, n) if open_[i - 1] and not open_[i]]
    if len(starts) >= 3:
        cuts = [0]
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            gaps = np.flatnonzero(open_[a:b])
            cuts.append(a + int(gaps[len(gaps) // 2]) if gaps.size else b)
        cuts.append(n)
        if np.max(np.diff(cuts)) <= FOLD_MAX_SHARE * n:
            idx = np.zeros(n, int)
            for k in range(len(cuts) - 1):
                idx[cuts[k] : cuts[k + 1]] = k
            return idx, f"leave-one-apply-out over {len(cuts) - 1} applies"
    return np.minimum((np.arange(n) * 4) // n, 3), "4-fold blocked cross-validation in time"


# ----------------------------------------------------------------------------- solver


@dataclass
class Design:
    """The linearised problem at one place: residual ``r`` of the current fit, Jacobian
    ``J`` of the stage's own parameters, the effect of each basis column, fold per row;
    Gram matrices per fold for fast subset solves."""

    r: np.ndarray
    J: np.ndarray
    fold: np.ndarray
    G: np.ndarray
    noise_rows: float
    rho: float
    norms: np.ndarray
    #: Rows of the located stage's channels (a sensor's term also shows downstream).
    stage_rows: np.ndarray | None = None
    _grams: list[np.ndarray] = field(default_factory=list, repr=False)

    @property
    def n_folds(self) -> int:
        return int(self.fold.max()) + 1

    def __post_init__(self):
        A = self._A = np.concatenate([self.J, self.G], axis=1)
        own = np.ones(self.r.size, bool) if self.stage_rows is None else self.stage_rows
        grams, stage = [], []
        for k in range(self.n_folds):
            te = self.fold == k
            tr = ~te & (self.fold >= 0)
            At, rt = A[tr], self.r[tr]
            Ae, re = A[te], self.r[te]
            grams.append((At.T @ At, At.T @ rt, Ae.T @ Ae, Ae.T @ re, re @ re))
            As, rs = A[te & own], self.r[te & own]
            stage.append((As.T @ As, As.T @ rs, rs @ rs))
        # Stacked over the folds (the first axis), for one batched solve per subset.
        self._grams = [np.asarray(v, float) for v in zip(*grams, strict=True)]
        self._stage_grams = [np.asarray(v, float) for v in zip(*stage, strict=True)]
        self._full = (A.T @ A, A.T @ self.r, float(self.r @ self.r))

    @property
    def kb(self) -> int:
        return self.J.shape[1]

    def _index(self, terms: Sequence[int]) -> np.ndarray:
        """Columns of the stage's parameters and of the term columns ``terms``."""
        return np.r_[np.arange(self.kb), self.kb + np.asarray(terms, int)].astype(int)

    def _penalty(self, d: np.ndarray, lams: np.ndarray) -> np.ndarray:
        """Ridge penalties on the diagonal, shape ``lams.shape + d.shape``, for the
        diagonals ``d`` (``(..., m)``) of a subset's Gram matrices: a vanishing one on the
        stage's parameters, ``lam`` times the mean diagonal on the term's columns."""
        kb = self.kb
        pen = np.broadcast_to(1e-9 * (d + 1e-300), lams.shape + d.shape).copy()
        if d.shape[-1] > kb:
            dt = d[..., kb:]
            scale = np.where(np.any(dt != 0, axis=-1), np.mean(dt, axis=-1), 1.0)
            pen[..., kb:] = lams.reshape(lams.shape + (1,) * d.ndim) * scale[..., None]
        return pen

    def _solve(self, M, b, idx, lam):
        """Coefficients on the subset ``idx``: ``M`` of shape ``(..., p, p)`` and ``b``
        ``(..., p)`` (a stack of folds solved at once), ``lam`` a scalar or 1-d array of
        ridge penalties (a leading axis of the result)."""
        lams = np.atleast_1d(np.asarray(lam, float))
        Mi = M[..., idx[:, None], idx[None, :]]
        d = np.diagonal(Mi, axis1=-2, axis2=-1)
        pen = self._penalty(d, lams)
        lhs = Mi[None] + pen[..., :, None] * np.eye(len(idx))
        rhs = np.broadcast_to(-b[..., idx], lhs.shape[:-1])
        try:
            x = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            x = np.empty(rhs.shape)
            for j in np.ndindex(rhs.shape[:-1]):
                x[j] = np.linalg.lstsq(lhs[j], rhs[j], rcond=None)[0]
        return x if np.ndim(lam) else x[0]

    def heldout(self, terms: Sequence[int], lam: float, stage: bool = False) -> float:
        """Held-out residual sum of squares with the term columns ``terms`` (``stage``:
        on the located stage's rows only)."""
        return float(np.sum(self.heldout_folds(terms, lam, stage)))

    def heldout_folds(self, terms: Sequence[int], lam, stage: bool = False) -> np.ndarray:
        """:meth:`heldout` fold by fold (a leading axis per penalty when ``lam`` is an
        array)."""
        idx = self._index(terms)
        Mt, bt, Me, be, ee = self._grams
        if stage:
            Me, be, ee = self._stage_grams
        x = self._solve(Mt, bt, idx, lam)
        Mi = Me[:, idx[:, None], idx[None, :]]
        return (
            ee + 2 * np.sum(x * be[:, idx], axis=-1) + np.einsum("...ki,kij,...kj->...k", x, Mi, x)
        )

    def best_heldout(self, terms: Sequence[int]) -> tuple[float, float]:
        """The lowest held-out RSS over the ridge penalties, and its penalty."""
        if not len(terms):
            return self.heldout([], 0.0), 0.0
        got = np.sum(self.heldout_folds(terms, np.asarray(RIDGES)), axis=-1)
        k = int(np.argmin(got))
        return float(got[k]), RIDGES[k]

    def insample(self, terms: Sequence[int], lam: float) -> tuple[float, np.ndarray]:
        """In-sample RSS and the coefficients (stage parameters first) on all rows."""
        M, b, ee = self._full
        idx = self._index(terms)
        x = self._solve(M, b, idx, lam)
        return float(ee + 2 * x @ b[idx] + x @ M[np.ix_(idx, idx)] @ x), x

    def consistent(self, terms: Sequence[int], lam: float) -> int:
        """The folds where the term behaves as physics that generalises, counted: a fold
        whose residual exceeds the noise (by three standard deviations of a chi-square)
        is lowered, and a fold at the noise is not raised beyond that; when four or more
        folds show a mismatch, one of them may be spared. The count equals the number of
        folds when the term is consistent."""
        before = self.heldout_folds([], 0.0)
        after = self.heldout_folds(terms, lam)
        rows = np.array([np.count_nonzero(self.fold == k) for k in range(self.n_folds)])
        noise = self.noise_rows * rows / max(rows.sum(), 1)
        tol = 3.0 * np.sqrt(2.0 * np.maximum(noise, 1.0))
        mismatch = before > noise + tol
        ok = np.where(mismatch, after < before, after <= before + tol)
        spare = 1 if np.count_nonzero(mismatch) >= 4 else 0
        return int(min(np.count_nonzero(ok) + spare, self.n_folds))

    def rho_after(self, terms: Sequence[int], lam: float) -> float:
        """Lag-1 autocorrelation of the residual with the term columns ``terms`` fitted
        (clipped to [0, RHO_MAX]): what remains serially correlated after the term."""
        _, x = self.insample(terms, lam)
        return lag1((self.r + self._A[:, self._index(terms)] @ x)[self.fold >= 0])

    def score(self, before: float, after: float, rho: float | None = None) -> float:
        """dBIC-like score of a held-out change (negative: better), with the effective
        number of residuals of an AR(1) residual of lag-1 correlation ``rho`` (that of
        the residual with the term; default the residual without it)."""
        rho = min(self.rho if rho is None else rho, RHO_CAP)
        n = float(np.count_nonzero(self.fold >= 0)) * (1 - rho) / (1 + rho)
        return n * float(np.log(max(after, 1e-300) / max(before, 1e-300)))


def lag1(e: np.ndarray) -> float:
    """Lag-1 autocorrelation of a residual about its mean, clipped to
    ``[0, RHO_MAX]`` (:data:`ewb_ident.data.metrics.RHO_MAX`)."""
    e = e - np.mean(e)
    return float(np.clip(e[1:] @ e[:-1] / max(e @ e, 1e-300), 0.0, RHO_MAX))


def white_level(r: np.ndarray, fold_rows: np.ndarray) -> float:
    """The residual's white-noise level (differences of neighbours), clipped to the
    floor-scale band the location test uses."""
    from ewb_ident.diagnosis.locate import FLOOR_SCALE

    e = r[fold_rows >= 0]
    if e.size < 5:
        return 1.0
    d = np.diff(e)
    level = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2)
    return float(np.clip(level, *FLOOR_SCALE))


# ----------------------------------------------------------------------------- steps


def estimates(fit, step: np.ndarray, free_only: bool = True) -> dict[str, float]:
    """The fit's free base parameters (SI) after the linearised step ``step`` (in the
    fit's optimiser coordinates, its free parameters first); with ``free_only`` False,
    its held ones too, at their values."""
    out = {} if free_only else {k: float(v) for k, v in fit.values.items() if k in PARAMS}
    for j, name in enumerate(fit.problem.shared):
        if name in PARAMS and j < step.size:
            dp = float(PARAMS[name].dp_du(float(fit.u[j]))) * float(step[j])
            out[name] = float(fit.values[name]) + dp
    return out


def linearised_start(fit, step: np.ndarray) -> dict[str, float]:
    """A start for a term's fit through the model: :func:`estimates`, but a parameter the
    step takes out of its range (it has no slope there, so the linearisation says
    nothing about it: an armature's L pinned near zero) at its nominal value."""
    nominal, out = EWBParams().as_dict(), estimates(fit, step)
    with np.errstate(divide="ignore", invalid="ignore"):
        bad = [n for n, v in out.items() if not np.isfinite(PARAMS[n].to_unconstrained(v))]
    return out | {n: nominal.get(n, float(fit.values[n])) for n in bad}


def form_spread(best: Mapping[str, float], others: Sequence[Mapping[str, float]]):
    """Per base parameter, the largest distance of another term's estimate (of the
    parameters its fit frees) from the chosen term's (free or held at its stages' fit):
    how much the parameter depends on the term's form and place, which the trace cannot
    pin down."""
    return {k: max((abs(o[k] - v) for o in others if k in o), default=0.0) for k, v in best.items()}
