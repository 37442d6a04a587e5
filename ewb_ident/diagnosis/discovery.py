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
   distance, force history), elapsed time, and angles taken modulo candidate periods.
   A stage's own outputs enter as the model's noise-free predictions (a channel's noise
   must not predict itself).
3. **The learned function** is an additive model: for each input, a flexible basis
   (piecewise-linear hinges for levels; odd powers and a smooth sign for signed
   signals; harmonics for angles), so any smooth or switching dependence on one input
   and sums over inputs are representable. It is fitted through the model: the term's
   effect on the stage's residuals is the model's exact linear response at the place
   (diagonal for a static place, the motor's impulse response for the motor's
   equations, both the output and the downstream input for a sensor), computed at the
   current fit together with the Jacobian of the stage's own parameters, which are
   refitted alongside (one Gauss-Newton step of a universal differential equation).
   A ridge penalty chosen by cross-validation regularises it.
4. **Held out.** Inputs enter one at a time while they improve the *held-out* residual
   (leave-one-apply-out with three or more applies, else four blocks in time): a term
   that only fits the data it saw is not kept. Places are ranked by held-out residual.
5. **Distilled.** On the best place, sparse regression over a generated library of
   the chosen inputs (powers, saturations, signs, hinges, harmonics at the period the
   learned term chose, products) keeps the smallest expression that keeps 90 % of the
   learned term's held-out improvement.

The distilled term is then fitted by nonlinear least squares through the JAX model (as
a :class:`~ewb_ident.mechanisms.learned.LearnedTerm`, with the stage's parameters), and
its words come from a table of known signatures (:func:`reading`), as a hypothesis.

Thresholds were set before any study of uncatalogued physics was run.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import expm
from scipy.signal import fftconvolve

from ewb_ident.data.metrics import smooth
from ewb_ident.data.stages import CHANNEL_INPUT_OF, CHANNEL_STAGE, STAGE_OUTPUTS
from ewb_ident.mechanisms.learned import PLACES, LearnedTerm
from ewb_ident.model.physics import DEG_PER_RAD

#: A learned term must lower the held-out residual by this much (a dBIC-like score of
#: the held-out residual sums, with the effective number of residuals, no penalty).
HELDOUT_BIC = 10.0
#: Largest lag-1 correlation used for that effective number: a smooth remainder (a
#: motor's angle integrates any misfit) would otherwise leave a handful of "independent"
#: residuals; the held-out folds, not this count, guard against a term fitting noise.
RHO_CAP = 0.9
#: ... and remove at least this share of the held-out excess over the noise.
MIN_HELDOUT_SHARE = 0.25
#: An input enters the learned function only if it adds this share of the excess.
MIN_STEP_SHARE = 0.03
#: Most inputs of a learned function, and most terms of a distilled equation.
MAX_INPUTS = 3
MAX_TERMS = 4
#: The distilled equation keeps at least this share of the learned term's gain.
KEEP_SHARE = 0.9
#: Ridge penalties tried (relative to the mean diagonal of the term's Gram matrix).
RIDGES = (1e-4, 1e-2, 1.0)
#: Candidate periods of a term periodic in the pinion angle, degrees.
PERIODS_DEG = (360.0, 180.0, 120.0, 90.0, 72.0, 60.0, 45.0, 40.0, 36.0, 30.0, 24.0, 20.0)
#: Time constants of the low-passed histories, s.
HISTORY_S = (0.1, 0.5, 2.0)
#: A basis column whose part outside the span of the stage's own parameters' Jacobian
#: is smaller than this share of it is left out (the parameters make it already).
MIN_NEW_SHARE = 0.05
#: Places in order of specificity: among places whose term removes at least
#: :data:`PLACE_TIE` of the best place's held-out gain, the first is chosen (a term
#: inside the physics before a sensor's, a sensor's before an added output).
PLACE_ORDER = (
    "motor.",
    "gap",
    "drive",
    "force.input",
    "friction",
    "sensor.",
    "force.output",
    "torque.output",
)
PLACE_TIE = 0.95
#: A catalog mechanism yields to a learned term at its stage when the learned term
#: removes this much more of the excess on held-out data.
CATALOG_MARGIN = 0.05


# ----------------------------------------------------------------------------- signals


@dataclass(frozen=True)
class Signal:
    """One input a learned term may depend on.

    ``kind``: ``signed`` (speed, current, rates), ``level`` (force, time, heat ...),
    ``angle`` (the pinion angle, degrees: a level and periodic candidates) or ``phase``
    (the disc angle, rad). ``ref``: its size (the largest magnitude), in ``unit``.
    """

    name: str
    values: np.ndarray = field(repr=False)
    unit: str
    kind: str
    words: str
    symbol: str
    ref: float
    #: Values within each sample interval, shape (n, m + 1) (a model state inside the
    #: motor's integration), or ``None``.
    fine: np.ndarray | None = field(default=None, repr=False)


def _rate(y: np.ndarray, dt: float, width: int) -> np.ndarray:
    return np.gradient(smooth(y, width), dt)


def _lowpass(y: np.ndarray, dt: float, tau: float) -> np.ndarray:
    a = float(np.exp(-dt / tau))
    from scipy.signal import lfilter

    return lfilter([1.0 - a], [1.0, -a], y, zi=[a * y[0]])[0]


def _integral(y: np.ndarray, dt: float) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]))]) * dt


def leave_one_out(y: np.ndarray, half: int) -> np.ndarray:
    """Centred moving average over ``2 half`` neighbours, the sample itself left out
    (ends: the neighbours there are). A recorded channel's noise at a sample is then
    not in the input at that sample, so a term cannot fit the residual's noise through
    its input; the central differences of the result hold no noise of their own sample
    either (it enters both neighbours equally)."""
    y = np.asarray(y, float)
    n = y.size
    c = np.concatenate([[0.0], np.cumsum(y)])
    k = np.arange(n)
    lo, hi = np.maximum(k - half, 0), np.minimum(k + half + 1, n)
    count = hi - lo - 1
    return (c[hi] - c[lo] - y) / np.maximum(count, 1)


#: Longest sub-step of the motor states resolved within each sample interval, s.
FINE_STEP_S = 2.5e-4


def motor_fine(values: Mapping[str, float], trace) -> dict[str, np.ndarray]:
    """The motor model's states within each sample interval from the logged voltage
    (the fit's parameters ``values``; exact zero-order-hold flow at sub-steps of at most
    :data:`FINE_STEP_S`): ``current`` (A), ``speed`` (rad/s), ``angle`` (deg), each of
    shape (n, m + 1), the interval's start and end included. At the sample times they
    are the motor stage's own prediction."""
    dt, n = trace.dt, trace.n
    m = max(1, int(np.ceil(dt / FINE_STEP_S - 1e-9)))
    R, L, kb, kT, M, v = (float(values[k]) for k in ("R", "L", "kb", "kT", "M", "v"))
    A = np.array([[-R / L, -kb / L, 0.0], [kT / M, -v / M, 0.0], [0.0, 1.0, 0.0]])
    aug = np.zeros((4, 4))
    aug[:3, :3], aug[0, 3] = A * (dt / m), dt / m / L
    E = expm(aug)
    Ad, bd = E[:3, :3], E[:3, 3]
    V = trace["voltage_V"]
    # The flow over a whole sample, then each sub-step from the sample's start state.
    Am = np.linalg.matrix_power(Ad, m)
    bm = sum(np.linalg.matrix_power(Ad, j) @ bd for j in range(m))
    starts = np.empty((n, 3))
    x = np.array([0.0, 0.0, float(values.get("theta0_deg", 0.0)) / DEG_PER_RAD])
    for k in range(n):
        starts[k] = x
        x = Am @ x + bm * V[k]
    out = np.empty((n, m + 1, 3))
    S = starts
    out[:, 0] = S
    for j in range(1, m + 1):
        S = S @ Ad.T + bd[None, :] * V[:, None]
        out[:, j] = S
    return {"current": out[..., 0], "speed": out[..., 1], "angle": out[..., 2] * DEG_PER_RAD}


def input_signals(
    trace, model: Mapping[str, np.ndarray], fine: Mapping[str, np.ndarray] | None = None
) -> dict[str, Signal]:
    """Every signal a learned term may depend on, from the trace and the model.

    Recorded channels enter through :func:`leave_one_out` (their noise at a sample is
    not in the input there), rates as central differences of that; the channels in
    ``model`` enter as the model gives them.

    Parameters
    ----------
    trace
        The trace.
    model
        Model series that replace recorded channels (:func:`model_channels`: the
        outputs of the stages a term is fitted at and what follows from them, which as
        recorded would carry the very mismatch the term is to explain), and of channels
        the trace does not record, in the channel's unit.
    fine
        The motor's states within each sample interval (:func:`motor_fine`): a term
        inside the motor's integration depends on them there, so they replace the
        current, speed and angle (and the heat is integrated from them).
    """
    dt, n = trace.dt, trace.n
    half = max(1, round(0.005 / dt))
    width = 1
    out: dict[str, Signal] = {}

    def add(name, values, unit, kind, words, symbol):
        v = np.asarray(values, float)[:n]
        within = None if fine is None else fine.get(name)
        if within is not None:
            within = np.asarray(within, float)
            v = interval_mean(within)
        ref = float(np.max(np.abs(v))) if v.size else 0.0
        if not np.all(np.isfinite(v)) or ref <= 0 or np.ptp(v) <= 1e-9 * ref:
            return
        if within is not None:
            ref = max(ref, float(np.max(np.abs(within))))
        out[name] = Signal(name, v, unit, kind, words, symbol, ref, within)

    def channel(ch):
        if ch in model:
            return np.asarray(model[ch], float)[:n], True
        if trace.has(ch):
            return leave_one_out(trace[ch], half), False
        return None, False

    t = trace.time_s - trace.time_s[0]
    add("time", t, "s", "level", "elapsed time", "t")
    if trace.has("voltage_V"):
        V = trace["voltage_V"]
        add("voltage", V, "V", "signed", "the motor voltage", "V")
        add("voltage_rate", np.gradient(V, dt), "V/s", "signed", "the voltage's rate", "dV/dt")
    th, th_model = channel("theta_deg")
    if th is not None:
        omega = _rate(th, dt, width) / DEG_PER_RAD
        add("angle", th, "deg", "angle", "the pinion angle", "θ")
        add("speed", omega, "rad/s", "signed", "the motor speed", "ω")
    cur, _ = channel("current_A")
    if fine is not None and "current" in fine:
        cur = np.asarray(fine["current"])[:, 0]
    if cur is not None:
        add("current", cur, "A", "signed", "the motor current", "i")
        if fine is not None and "current" in fine:
            f2 = np.asarray(fine["current"]) ** 2
            per = interval_mean(f2)
            heat = np.concatenate([[0.0], np.cumsum(per[:-1])]) * dt
        else:
            heat = _integral(cur**2, dt)
        add("heat", heat, "A^2*s", "level", "heat dissipated, ∫i²dt", "∫i²dt")
    levels = (
        ("x_m", "x", "m", "the piston displacement", "x", "the piston speed"),
        ("force_N", "force", "N", "the clamping force", "F", "the rate of the force"),
        ("torque_Nm", "torque", "N*m", "the brake torque", "T", "the rate of the brake torque"),
    )
    for ch, name, unit, words, sym, rate_words in levels:
        y, modelled = channel(ch)
        if y is None:
            continue
        add(name, y, unit, "level", words, sym)
        rate = _rate(y, dt, 1 if modelled else width)
        add(f"{name}_rate", rate, f"{unit}/s", "signed", rate_words, f"d{sym}/dt")
        if name != "force":
            continue
        for tau in HISTORY_S:
            hist = f"the force low-passed over {tau:g} s (its recent history)"
            add(f"force_history_{tau:g}s", _lowpass(y, dt, tau), "N", "level", hist, f"F̄{tau:g}s")
    if trace.has("disc_speed_rad_s"):
        wd = trace["disc_speed_rad_s"]
        if np.ptp(wd) > 0.02 * max(float(np.max(np.abs(wd))), 1e-9):
            add("disc_speed", wd, "rad/s", "level", "the disc speed", "ω_d")
        add(
            "distance", _integral(np.abs(wd), dt), "rad", "level", "the disc's sliding angle", "s_d"
        )
        add(
            "disc_angle",
            np.mod(_integral(wd, dt), 2 * np.pi),
            "rad",
            "phase",
            "the disc angle",
            "φ_d",
        )
        if "torque" in out:
            add(
                "energy",
                _integral(np.abs(out["torque"].values * wd), dt),
                "J",
                "level",
                "the braking energy dissipated",
                "E",
            )
    return out


# ----------------------------------------------------------------------------- basis


@dataclass(frozen=True)
class Column:
    """One basis series: its name (an expression), the input it depends on, values."""

    label: str
    signal: str
    values: np.ndarray = field(repr=False)
    #: For the equation: ``(kind, *args)`` (see :func:`render`).
    form: tuple = ()


#: Knots of the piecewise-linear basis of a level, as shares of its range.
KNOTS = (1 / 7, 2 / 7, 3 / 7, 4 / 7, 5 / 7, 6 / 7)


def _hinge_knots(z: np.ndarray, shares: Sequence[float] = KNOTS) -> list[float]:
    lo, hi = float(np.min(z)), float(np.max(z))
    return [lo + q * (hi - lo) for q in shares]


def _times(k: int) -> str:
    return "" if k == 1 else str(k)


def interval_mean(f: np.ndarray) -> np.ndarray:
    """The mean over each sample interval of values within it, shape (n, m + 1) ->
    (n,) (trapezoid rule)."""
    return (0.5 * (f[:, 0] + f[:, -1]) + f[:, 1:-1].sum(axis=1)) / (f.shape[1] - 1)


def ev(s: Signal, fn) -> np.ndarray:
    """``fn`` of a signal's raw values per sample: for a signal resolved within each
    sample interval (a model state inside the motor's integration, :attr:`Signal.fine`),
    the interval's mean of ``fn`` (trapezoid), as a term held over the interval sees it."""
    if s.fine is None:
        return fn(s.values)
    return interval_mean(fn(s.fine))


#: The signal each place's quantity is naturally proportional to: a resistance that
#: changes drops a voltage in proportion to the current, a torque constant that changes
#: gives a torque in proportion to it, a force law's or a sensor's gain that changes
#: adds in proportion to the force or the reading. A learned term there may be that
#: carrier times a function of any other input (``"current*heat"``).
CARRIERS: dict[str, tuple[str, ...]] = {
    "motor.electrical": ("current",),
    "motor.mechanical": ("current", "speed"),
    "drive": ("force",),
    "force.output": ("force",),
    "torque.output": ("force",),
}


def carriers_of(place: str) -> tuple[str, ...]:
    """The carriers of a place (a sensor's: its own channel)."""
    if place.startswith("sensor."):
        own = _OWN.get(place.split(".", 1)[1], "")
        return (own,) if own else ()
    return CARRIERS.get(place, ())


def _modulated(c: Signal, s: Signal, fn) -> np.ndarray:
    """The carrier ``c`` (normalised) times ``fn`` of ``s``'s raw values, per sample
    (within each interval where both are resolved there)."""
    if c.fine is not None and s.fine is not None:
        return interval_mean(c.fine / c.ref * fn(s.fine))
    return ev(c, lambda v: v / c.ref) * ev(s, fn)


def learned_groups(
    signals: Mapping[str, Signal], dt: float, carriers: Sequence[str] = ()
) -> dict[str, list[Column]]:
    """The flexible basis of the learned function, one group of columns per input (and
    per candidate period of the angle), and per carrier times each other input."""
    groups: dict[str, list[Column]] = {"constant": [Column("1", "constant", None, ("one",))]}
    for cname in carriers:
        c = signals.get(cname)
        if c is None:
            continue
        for s in signals.values():
            if s.name == cname or s.kind not in ("level", "signed"):
                continue
            r = s.ref
            cols = [
                Column(
                    f"{c.symbol}·{s.symbol}",
                    f"{cname}*{s.name}",
                    _modulated(c, s, lambda v, r=r: v / r),
                    ("prod", cname, s.name),
                ),
                Column(
                    f"{c.symbol}·{s.symbol}²",
                    f"{cname}*{s.name}",
                    _modulated(c, s, lambda v, r=r: (v / r) ** 2),
                    ("prod2", cname, s.name),
                ),
            ]
            if s.kind == "signed":
                cols.append(
                    Column(
                        f"{c.symbol}·|{s.symbol}|",
                        f"{cname}*{s.name}",
                        _modulated(c, s, lambda v, r=r: np.abs(v) / r),
                        ("prodabs", cname, s.name),
                    )
                )
            groups[f"{cname}*{s.name}"] = cols
    for s in signals.values():
        r = s.ref
        if s.kind == "signed":
            groups[s.name] = [
                Column(f"{s.symbol}", s.name, ev(s, lambda v, r=r: v / r), ("pow", 1)),
                Column(
                    f"{s.symbol}|{s.symbol}|",
                    s.name,
                    ev(s, lambda v, r=r: v * np.abs(v) / r**2),
                    ("spow", 2),
                ),
                Column(f"{s.symbol}³", s.name, ev(s, lambda v, r=r: (v / r) ** 3), ("pow", 3)),
                Column(
                    f"sign({s.symbol})",
                    s.name,
                    ev(s, lambda v, r=r: np.tanh(v / r / 0.05)),
                    ("tanh", 0.05),
                ),
            ]
        elif s.kind == "phase":
            groups[s.name] = [
                Column(
                    f"{f}({_times(k)}{s.symbol})",
                    s.name,
                    ev(s, lambda v, r=r, k=k, fn=fn: fn(k * v)),
                    ("harm", k, f),
                )
                for k in (1, 2)
                for f, fn in (("sin", np.sin), ("cos", np.cos))
            ]
        else:
            cols = [Column(s.symbol, s.name, ev(s, lambda v, r=r: v / r), ("pow", 1))]
            for k in _hinge_knots(s.values / r):
                cols.append(
                    Column(
                        f"max(0, {s.symbol} − {k * r:.3g})",
                        s.name,
                        ev(s, lambda v, r=r, k=k: np.maximum(v / r - k, 0.0)),
                        ("hinge", k),
                    )
                )
            groups[s.name] = cols
            if s.kind == "angle":
                vals = s.values if s.fine is None else s.fine.reshape(-1)
                step = float(np.percentile(np.abs(np.diff(vals)), 95)) if vals.size > 1 else 0
                span = float(np.ptp(s.values))
                for P in PERIODS_DEG:
                    if span < 1.5 * P or step > P / 4:
                        continue  # not a period this trace covers or resolves
                    groups[f"{s.name}@{P:g}"] = [
                        Column(
                            f"{f}(2π{s.symbol}/{P:g}°)",
                            s.name,
                            ev(s, lambda v, r=r, P=P, fn=fn: fn(2 * np.pi * v / P)),
                            ("period", P, f),
                        )
                        for f, fn in (("sin", np.sin), ("cos", np.cos))
                    ]
    return groups


def library(signals: Mapping[str, Signal], chosen: Sequence[str]) -> list[list[Column]]:
    """The distillation library of the chosen groups: each item one term (a harmonic is
    its sine and cosine together)."""
    items: list[list[Column]] = []
    names = []
    for g in chosen:
        if g == "constant":
            items.append([Column("1", "constant", None, ("one",))])
            continue
        if "*" in g:  # a carrier times another input
            cname, _, other = g.partition("*")
            c, o = signals[cname], signals[other]
            r = o.ref
            forms = [
                (f"{c.symbol}·{o.symbol}", lambda v, r=r: v / r, ("prod", cname, other)),
                (f"{c.symbol}·{o.symbol}²", lambda v, r=r: (v / r) ** 2, ("prod2", cname, other)),
                (
                    f"{c.symbol}·|{o.symbol}|",
                    lambda v, r=r: np.abs(v) / r,
                    ("prodabs", cname, other),
                ),
            ]
            items += [[Column(lbl, g, _modulated(c, o, fn), form)] for lbl, fn, form in forms]
            continue
        name, _, per = g.partition("@")
        s = signals[name]
        r = s.ref
        if per:
            P = float(per)
            for h in (1, 2):
                items.append(
                    [
                        Column(
                            f"{f}(2π{s.symbol}/{P / h:g}°)",
                            name,
                            ev(s, lambda v, r=r, P=P, h=h, fn=fn: fn(2 * np.pi * h * v / P)),
                            ("period", P / h, f),
                        )
                        for f, fn in (("sin", np.sin), ("cos", np.cos))
                    ]
                )
            continue
        names.append(name)
        if s.kind == "phase":
            for k in (1, 2):
                items.append(
                    [
                        Column(
                            f"{f}({_times(k)}{s.symbol})",
                            name,
                            ev(s, lambda v, r=r, k=k, fn=fn: fn(k * v)),
                            ("harm", k, f),
                        )
                        for f, fn in (("sin", np.sin), ("cos", np.cos))
                    ]
                )
            continue
        cand = [
            (f"{s.symbol}", lambda v, r=r: v / r, ("pow", 1)),
            (f"{s.symbol}²", lambda v, r=r: (v / r) ** 2, ("pow", 2)),
            (f"{s.symbol}³", lambda v, r=r: (v / r) ** 3, ("pow", 3)),
        ]
        if s.kind == "signed":
            cand += [
                (f"{s.symbol}|{s.symbol}|", lambda v, r=r: v * np.abs(v) / r**2, ("spow", 2)),
                (f"|{s.symbol}|", lambda v, r=r: np.abs(v) / r, ("abs",)),
                (f"sign({s.symbol})", lambda v, r=r: np.tanh(v / r / 0.05), ("tanh", 0.05)),
                (
                    f"tanh({s.symbol}/{0.3 * r:.3g})",
                    lambda v, r=r: np.tanh(v / r / 0.3),
                    ("tanh", 0.3),
                ),
            ]
        else:
            cand += [
                (f"√{s.symbol}", lambda v, r=r: np.sqrt(np.abs(v) / r), ("sqrt",)),
                (
                    f"1 − exp(−{s.symbol}/{0.3 * r:.3g})",
                    lambda v, r=r: 1 - np.exp(-np.abs(v) / r / 0.3),
                    ("sat", 0.3),
                ),
            ]
            for k in _hinge_knots(s.values / r, (0.5,)):
                cand.append(
                    (
                        f"max(0, {s.symbol} − {k * r:.3g})",
                        lambda v, r=r, k=k: np.maximum(v / r - k, 0),
                        ("hinge", k),
                    )
                )
        items += [[Column(lbl, name, ev(s, fn), form)] for lbl, fn, form in cand]
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            sa, sb = signals[a], signals[b]
            items.append(
                [
                    Column(
                        f"{sa.symbol}·{sb.symbol}",
                        f"{a}*{b}",
                        ev(sa, lambda v, q=sa.ref: v / q) * ev(sb, lambda v, q=sb.ref: v / q),
                        ("prod", a, b),
                    )
                ]
            )
    return items


def physical(col: Column, signals: Mapping[str, Signal]) -> tuple[str, float, str]:
    """The expression of a basis column in physical units, the factor that turns its
    coefficient into the expression's, and the expression's unit (``""``: none).

    A column is ``f(z)`` of a normalised signal ``z = s / ref``; its coefficient times
    ``factor`` is the coefficient of the expression in the signal's own unit."""
    kind = col.form[0]
    if kind == "one":
        return "1", 1.0, ""
    if kind == "prod":
        a, b = signals[col.form[1]], signals[col.form[2]]
        return f"{a.symbol}·{b.symbol}", 1.0 / (a.ref * b.ref), f"{a.unit}*{b.unit}"
    if kind == "prod2":
        a, b = signals[col.form[1]], signals[col.form[2]]
        return f"{a.symbol}·{b.symbol}²", 1.0 / (a.ref * b.ref**2), f"{a.unit}*{b.unit}^2"
    if kind == "prodabs":
        a, b = signals[col.form[1]], signals[col.form[2]]
        return f"{a.symbol}·|{b.symbol}|", 1.0 / (a.ref * b.ref), f"{a.unit}*{b.unit}"
    s = signals[col.signal]
    if kind == "pow":
        p = col.form[1]
        sup = {1: "", 2: "²", 3: "³"}[p]
        return f"{s.symbol}{sup}", s.ref**-p, s.unit + ("" if p == 1 else f"^{p}")
    if kind == "spow":
        return f"{s.symbol}|{s.symbol}|", s.ref**-2, f"{s.unit}^2"
    if kind == "abs":
        return f"|{s.symbol}|", 1.0 / s.ref, s.unit
    if kind == "sqrt":
        return f"√{s.symbol}", s.ref**-0.5, f"{s.unit}^0.5"
    if kind == "tanh":
        scale = col.form[1] * s.ref
        if col.form[1] <= 0.05:
            return f"sign({s.symbol}) [tanh({s.symbol}/{scale:.3g} {s.unit})]", 1.0, ""
        return f"tanh({s.symbol}/{scale:.3g} {s.unit})", 1.0, ""
    if kind == "sat":
        return f"(1 − exp(−|{s.symbol}|/{col.form[1] * s.ref:.3g} {s.unit}))", 1.0, ""
    if kind == "hinge":
        return f"max(0, {s.symbol} − {col.form[1] * s.ref:.4g} {s.unit})", 1.0 / s.ref, s.unit
    return col.label, 1.0, ""


def render(col: Column, coef: float, signals: Mapping[str, Signal]) -> str:
    """One term of the equation in SI units: the physical coefficient times the
    expression (see :func:`physical`)."""
    expr, factor, _ = physical(col, signals)
    return f"{coef * factor:+.4g}" if expr == "1" else f"{coef * factor:+.4g}·{expr}"


def render_pair(cols: Sequence[Column], coefs: Sequence[float]) -> str:
    """A sine and cosine pair as one harmonic, ``A·sin(... + phase)``."""
    (cs, cc) = coefs
    amp, phase = float(np.hypot(cs, cc)), float(np.arctan2(cc, cs))
    arg = cols[0].label[4:-1]
    return f"{amp:+.4g}·sin({arg} {phase:+.2f})"


# ----------------------------------------------------------------------------- places


def motor_response(values: Mapping[str, float], dt: float, n: int) -> np.ndarray:
    """Impulse responses of the motor (current A, angle deg) to a voltage (column 0) and
    to a load torque (column 1) held over one sample: ``h[k, out, inp]`` is the output
    at sample ``k`` after a unit input over sample 0 (the outputs lag by one sample)."""
    R, L, kb, kT, M, v = (float(values[k]) for k in ("R", "L", "kb", "kT", "M", "v"))
    A = np.array([[-R / L, -kb / L, 0.0], [kT / M, -v / M, 0.0], [0.0, 1.0, 0.0]])
    B = np.array([[1.0 / L, 0.0], [0.0, -1.0 / M], [0.0, 0.0]])
    aug = np.zeros((5, 5))
    aug[:3, :3], aug[:3, 3:] = A * dt, B * dt
    E = expm(aug)
    Ad, Bd = E[:3, :3], E[:3, 3:]
    h = np.zeros((n, 2, 2))
    x = Bd.copy()
    for k in range(1, n):
        h[k, 0], h[k, 1] = x[0], x[2] * DEG_PER_RAD
        x = Ad @ x
        if k > 50 and np.max(np.abs(x[:2])) < 1e-14 * (1 + np.max(np.abs(h[k]))):
            h[k + 1 :, 1] = h[k, 1]  # the speed has died out: the angle stays
            break
    return h


def _bell_slope(x, values) -> np.ndarray:
    F_rt, a, b, c = (float(values[k]) for k in ("F_rt", "a", "b", "c"))
    u = np.abs((x - c) / a) + 1e-300
    q = u ** (2 * b)
    return F_rt * (2 * b * q / u) * np.sign(c - x) / a / (1 + q) ** 2


def place_effect(
    place: str, values: Mapping[str, float], trace, model: Mapping[str, np.ndarray]
) -> dict[str, Any]:
    """How a term at ``place`` changes each predicted channel, per stage.

    Returns ``{channel: op}`` where ``op(U)`` maps the term's basis columns ``U`` (n, K)
    to the change of that channel's prediction (n, K): the model's exact linear response
    at the current fit (``values``)."""
    n, dt = trace.n, trace.dt
    ch_sensor = place.split(".", 1)[1] if place.startswith("sensor.") else None
    if place in ("motor.electrical", "motor.mechanical"):
        h = motor_response(values, dt, n)
        j = 0 if place == "motor.electrical" else 1

        def conv(k_out):
            def op(U):
                return fftconvolve(h[:, k_out, j][:, None], U, axes=0)[:n]

            return op

        return {"current_A": conv(0), "theta_deg": conv(1)}

    def scaled(g):
        g = np.asarray(g, float)[:n]
        return lambda U: g[:, None] * U

    th = trace["theta_deg"] if trace.has("theta_deg") else None
    x = trace["x_m"] if trace.has("x_m") else None
    F = trace["force_N"] if trace.has("force_N") else None
    slope_th = None if th is None else 2 * values["p2"] * th + values["p1"]
    slope_x = None if x is None else _bell_slope(x, values)
    gain_F = 2 * values["mu"] * trace.r_eff_m
    one = lambda U: U  # noqa: E731
    if place == "drive":
        return {"x_m": one}
    if place == "gap":
        return {"x_m": scaled(slope_th)} if slope_th is not None else {}
    if place == "force.input":
        return {"force_N": scaled(slope_x)} if slope_x is not None else {}
    if place == "force.output":
        return {"force_N": one}
    if place == "friction":
        return {"torque_Nm": scaled(gain_F * F)} if F is not None else {}
    if place == "torque.output":
        return {"torque_Nm": one}
    if ch_sensor is not None:
        out = {ch_sensor: one}
        down = CHANNEL_INPUT_OF.get(ch_sensor)
        slope = {"gap": slope_th, "force": slope_x, "torque": np.full(n, gain_F)}.get(down)
        if down is not None and slope is not None:
            down_ch = STAGE_OUTPUTS[down][0]
            out[down_ch] = scaled(-slope)
        return out
    raise ValueError(f"unknown place {place!r}")


def places_of(stage: str, channels: Sequence[str]) -> list[str]:
    """The places whose term shows at ``stage`` (its own, and the sensors of its
    recorded output and input channels)."""
    own = [p for p, info in PLACES.items() if info.stage == stage and not p.startswith("sensor.")]
    sensors = []
    for ch in channels:
        if ch == "voltage_V":
            continue
        if CHANNEL_STAGE.get(ch) == stage or CHANNEL_INPUT_OF.get(ch) == stage:
            sensors.append(f"sensor.{ch}")
    return own + sensors


def place_stages(place: str, stages: Sequence[str]) -> tuple[str, ...]:
    """The teacher-forced stages (of those checkable) whose residuals a term at ``place``
    changes."""
    return tuple(s for s in LearnedTerm(place=place).stages if s in stages)


# ----------------------------------------------------------------------------- folds


def folds(labels: np.ndarray) -> tuple[np.ndarray, str]:
    """Fold index of each sample, and the method in words: leave one apply out when the
    trace holds three or more applies (each from the open pads before it to those
    after), otherwise four contiguous blocks in time."""
    n = labels.size
    open_ = labels == "gapping"
    starts = [i for i in range(1, n) if open_[i - 1] and not open_[i]]
    if len(starts) >= 3:
        cuts = [0]
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            gaps = np.flatnonzero(open_[a:b])
            cuts.append(a + int(gaps[len(gaps) // 2]) if gaps.size else b)
        cuts.append(n)
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
    cols: list[Column]
    G: np.ndarray
    noise_rows: float
    n_folds: int
    rho: float
    norms: np.ndarray
    #: Rows of the located stage's channels (a sensor's term also shows downstream).
    stage_rows: np.ndarray | None = None
    _grams: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]] = field(
        default_factory=list, repr=False
    )

    def __post_init__(self):
        A = np.concatenate([self.J, self.G], axis=1)
        own = np.ones(self.r.size, bool) if self.stage_rows is None else self.stage_rows
        self._stage_grams = []
        for k in range(self.n_folds):
            te = self.fold == k
            tr = ~te & (self.fold >= 0)
            At, rt = A[tr], self.r[tr]
            Ae, re = A[te], self.r[te]
            self._grams.append((At.T @ At, At.T @ rt, Ae.T @ Ae, Ae.T @ re, float(re @ re)))
            As, rs = A[te & own], self.r[te & own]
            self._stage_grams.append((As.T @ As, As.T @ rs, float(rs @ rs)))
        self._full = (A.T @ A, A.T @ self.r, float(self.r @ self.r))

    @property
    def kb(self) -> int:
        return self.J.shape[1]

    def _solve(self, M, b, idx, lam):
        Mi = M[np.ix_(idx, idx)]
        d = np.diag(Mi).copy()
        pen = np.where(np.arange(len(idx)) < self.kb, 1e-9 * (d + 1e-300), 0.0)
        if len(idx) > self.kb:
            term_scale = float(np.mean(d[self.kb :])) if np.any(d[self.kb :]) else 1.0
            pen[self.kb :] = lam * term_scale
        try:
            return np.linalg.solve(Mi + np.diag(pen), -b[idx])
        except np.linalg.LinAlgError:
            return np.linalg.lstsq(Mi + np.diag(pen), -b[idx], rcond=None)[0]

    def heldout(self, terms: Sequence[int], lam: float, stage: bool = False) -> float:
        """Held-out residual sum of squares with the term columns ``terms`` (``stage``:
        on the located stage's rows only)."""
        return float(np.sum(self.heldout_folds(terms, lam, stage)))

    def heldout_folds(self, terms: Sequence[int], lam: float, stage: bool = False) -> np.ndarray:
        """:meth:`heldout` fold by fold."""
        idx = np.r_[np.arange(self.kb), self.kb + np.asarray(terms, int)].astype(int)
        total = []
        for (Mt, bt, Me, be, ee), (Ms, bs, es) in zip(self._grams, self._stage_grams, strict=True):
            x = self._solve(Mt, bt, idx, lam)
            if stage:
                Me, be, ee = Ms, bs, es
            total.append(ee + 2 * x @ be[idx] + x @ Me[np.ix_(idx, idx)] @ x)
        return np.asarray(total, float)

    def best_heldout(self, terms: Sequence[int]) -> tuple[float, float]:
        """The lowest held-out RSS over the ridge penalties, and its penalty."""
        if not len(terms):
            return self.heldout([], 0.0), 0.0
        got = [(self.heldout(terms, lam), lam) for lam in RIDGES]
        return min(got)

    def insample(self, terms: Sequence[int], lam: float) -> tuple[float, np.ndarray]:
        """In-sample RSS and the coefficients (stage parameters first) on all rows."""
        M, b, ee = self._full
        idx = np.r_[np.arange(self.kb), self.kb + np.asarray(terms, int)].astype(int)
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
        (clipped to [0, 0.98]): what remains serially correlated after the term."""
        _, x = self.insample(terms, lam)
        idx = np.r_[np.arange(self.kb), self.kb + np.asarray(terms, int)].astype(int)
        A = np.concatenate([self.J, self.G], axis=1)[:, idx]
        e = (self.r + A @ x)[self.fold >= 0]
        e = e - np.mean(e)
        return float(np.clip(e[1:] @ e[:-1] / max(e @ e, 1e-300), 0.0, 0.98))

    def score(self, before: float, after: float, rho: float | None = None) -> float:
        """dBIC-like score of a held-out change (negative: better), with the effective
        number of residuals of an AR(1) residual of lag-1 correlation ``rho`` (that of
        the residual with the term; default the residual without it)."""
        rho = min(self.rho if rho is None else rho, RHO_CAP)
        n = float(np.count_nonzero(self.fold >= 0)) * (1 - rho) / (1 + rho)
        return n * float(np.log(max(after, 1e-300) / max(before, 1e-300)))


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

    @property
    def rank_gain(self) -> float:
        """What places are ranked by: the held-out gain at the located stage, no more
        than the gain over every stage the term shows in (a sensor's term must not
        worsen the other stage it feeds); the whole gain when the other stage gains
        clearly too (by ``2 HELDOUT_BIC`` and a tenth of the located stage's gain): a
        sensor's error shows downstream, a term of the physics does not."""
        total = self.heldout_before - self.heldout_after
        other = total - self.stage_gain
        if other > max(2 * HELDOUT_BIC, 0.1 * self.stage_gain):
            return total
        return min(total, self.stage_gain)

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
        """Held-out score and share beyond their thresholds, and consistent over the
        folds (:meth:`Design.consistent`)."""
        consistent = self.folds_improved >= self.n_folds
        return self.score <= -HELDOUT_BIC and self.share >= MIN_HELDOUT_SHARE and consistent


@dataclass(frozen=True)
class Discovery:
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

    @property
    def columns(self) -> list[Column]:
        return [c for t in self.terms for c in t]

    @property
    def depends_on(self) -> tuple[str, ...]:
        out: list[str] = []
        for c in self.columns:
            for s in c.signal.split("*"):
                if s != "constant" and s not in out:
                    out.append(s)
        return tuple(out)

    def equation(self, coef: Sequence[float] | None = None) -> str:
        """The distilled term in SI units, ``quantity = expression [unit]``."""
        coef = list(self.coef if coef is None else coef)
        info = PLACES[self.place]
        parts, k = [], 0
        for t in self.terms:
            cs = coef[k : k + len(t)]
            k += len(t)
            if len(t) == 2:
                parts.append(render_pair(t, cs))
            else:
                parts.append(render(t[0], cs[0], self.signals))
        expr = " ".join(parts).lstrip("+")
        return f"{info.quantity} = {expr} [{info.unit}]"


def _design(ses, fit, place, groups, fold, stage: str) -> Design | None:
    """The linearised problem of a term at ``place`` about the fit ``fit`` of ``stages``."""
    from ewb_ident.inference.augmented import residuals_and_jacobian

    n = ses.trace.n
    r, J, _ = residuals_and_jacobian(fit.problem, fit.u, ses.data)
    r, J = np.asarray(r, float), np.asarray(J, float)
    chans = fit.problem.channels
    n_pad = r.size // len(chans)
    model = model_channels(ses, fit)
    effect = place_effect(place, fit.values, ses.trace, model)
    if not set(effect) & set(chans):
        return None
    cols = [c for g in groups.values() for c in g]
    U = np.stack([np.ones(n) if c.values is None else c.values for c in cols], axis=1)
    blocks = []
    for ch in chans:
        w = np.asarray(ses.data["w"][ch], float)[:n_pad]
        B = np.zeros((n_pad, U.shape[1]))
        if ch in effect:
            B[:n] = effect[ch](U) * w[:n, None]
        blocks.append(B)
    G = np.concatenate(blocks, axis=0)
    keep = np.linalg.norm(G, axis=0) > 0
    norms = np.where(keep, np.linalg.norm(G, axis=0), 1.0)
    G = G / norms
    # A column the stage's own parameters already make (the torque itself at the torque's
    # output is a change of mu) is no new physics: left out.
    if J.shape[1]:
        Uj, sj, _ = np.linalg.svd(J, full_matrices=False)
        Uj = Uj[:, sj > 1e-10 * max(float(sj[0]), 1e-300)]
        orth = np.linalg.norm(G - Uj @ (Uj.T @ G), axis=0)
        G[:, orth < MIN_NEW_SHARE] = 0.0
    fold_rows = np.concatenate([np.r_[fold, -np.ones(n_pad - n, int)]] * len(chans))
    fold_rows = np.where(
        np.concatenate([np.asarray(ses.data["w"][c])[:n_pad] for c in chans]) > 0, fold_rows, -1
    )
    e = r[fold_rows >= 0]
    ee = e - np.mean(e)
    rho = float(np.clip(ee[1:] @ ee[:-1] / max(ee @ ee, 1e-300), 0.0, 0.98))
    noise_rows = float(np.count_nonzero(fold_rows >= 0)) * _white_level(r, fold_rows) ** 2
    own = np.concatenate([np.full(n_pad, ch in STAGE_OUTPUTS[stage]) for ch in chans])
    return Design(r, J, fold_rows, cols, G, noise_rows, int(fold.max()) + 1, rho, norms, own)


def _white_level(r: np.ndarray, fold_rows: np.ndarray) -> float:
    """The residual's white-noise level (differences of neighbours), clipped to the
    floor-scale band the location test uses."""
    from ewb_ident.diagnosis.locate import FLOOR_SCALE

    e = r[fold_rows >= 0]
    if e.size < 5:
        return 1.0
    d = np.diff(e)
    level = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2)
    return float(np.clip(level, *FLOOR_SCALE))


def model_channels(ses, fit) -> dict[str, np.ndarray]:
    """Model series for the inputs of a term fitted with ``fit``: its stages' own
    outputs as it predicts them and the channels that follow from them along the chain
    (the gap curve, the bell, the brake torque of the fit's values), and the motor's
    current where the trace records none. Recorded, these channels would carry the
    mismatch itself: a term could explain the force by the recorded force."""
    from ewb_ident.model.physics import brake_torque, clamp_force, gap

    v = dict(ses.values) | dict(fit.values)
    tr = ses.trace
    half = max(1, round(0.005 / tr.dt))
    out: dict[str, np.ndarray] = {}
    # A teacher-forced stage's prediction carries its measured input's noise, which is
    # in the residual too: the stage is evaluated at the input's leave-one-out average.
    for st in fit.stages:
        if st == "motor":
            for ch in STAGE_OUTPUTS[st]:
                if ch in fit.predictions:
                    out[ch] = np.asarray(fit.predictions[ch], float)
        elif st == "gap":
            th = leave_one_out(tr["theta_deg"], half)
            out["x_m"] = np.asarray(gap(th, v["p2"], v["p1"], v["p0"]))
        elif st == "force":
            x = leave_one_out(tr["x_m"], half)
            out["force_N"] = np.asarray(clamp_force(x, v["F_rt"], v["a"], v["b"], v["c"]))
        elif st == "torque":
            F = leave_one_out(tr["force_N"], half)
            out["torque_Nm"] = np.asarray(brake_torque(F, v["mu"], tr.r_eff_m))
    if "theta_deg" in out and "x_m" not in out:
        out["x_m"] = np.asarray(gap(out["theta_deg"], v["p2"], v["p1"], v["p0"]))
    if "x_m" in out and "force_N" not in out:
        out["force_N"] = np.asarray(clamp_force(out["x_m"], v["F_rt"], v["a"], v["b"], v["c"]))
    if "force_N" in out and "torque_Nm" not in out:
        out["torque_Nm"] = np.asarray(brake_torque(out["force_N"], v["mu"], ses.trace.r_eff_m))
    mot = ses.base_fits.get("motor")
    if not tr.has("current_A") and "current_A" not in out:
        if mot is not None and "current_A" in mot.predictions:
            out["current_A"] = np.asarray(mot.predictions["current_A"], float)
    return out


def _column_index(d: Design, groups: Mapping[str, list[Column]], names) -> list[int]:
    idx, k = [], 0
    for g, cols in groups.items():
        if g in names:
            idx += list(range(k, k + len(cols)))
        k += len(cols)
    return idx


#: Signals local to a place (its own quantities): preferred among near-equal inputs.
LOCAL: dict[str, tuple[str, ...]] = {
    "motor.electrical": ("current", "voltage", "heat", "speed"),
    "motor.mechanical": ("speed", "current", "angle"),
    "drive": ("force", "angle"),
    "gap": ("force", "angle"),
    "force.input": ("x", "time", "energy", "heat"),
    "force.output": ("force", "x_rate", "force_rate", "force_history"),
    "friction": ("force", "disc_speed", "energy", "distance", "disc_angle"),
    "torque.output": ("force", "torque", "disc_angle"),
}


def _is_local(group: str, local: Sequence[str]) -> bool:
    name = group.partition("@")[0]
    return any(name == s or name.startswith(s + "_") for s in local if s)


def learn_place(d: Design, groups: Mapping[str, list[Column]], place: str) -> PlaceFit:
    """Forward selection of input groups at one place by held-out residual."""
    base_ho, _ = d.best_heldout([])
    base_in, _ = d.insample([], 0.0)
    excess = max(base_ho - d.noise_rows, 0.0)
    chosen: list[str] = []
    cur = base_ho
    usable = [g for g in groups if _column_index(d, groups, {g})]
    local = LOCAL.get(place.split(".")[0] if place.startswith("sensor.") else place, ())
    if place.startswith("sensor."):
        own = _OWN.get(place.split(".", 1)[1], "")
        local = (own, f"{own}_rate")
    for _ in range(MAX_INPUTS):
        tried = []
        for g in usable:
            if g in chosen or ("@" in g and any("@" in c for c in chosen)):
                continue  # one period of the angle at most
            val, _ = d.best_heldout(_column_index(d, groups, {*chosen, g}))
            tried.append((val, g))
        if not tried:
            break
        best = min(tried)
        # Signals along the chain are monotone in one another over an apply (angle,
        # displacement, force, torque): a signal local to the place that does nearly
        # as well is the better reading.
        near = [
            t for t in tried if cur - t[0] >= PLACE_TIE * (cur - best[0]) and _is_local(t[1], local)
        ]
        if near and not _is_local(best[1], local):
            best = min(near)
        gain = cur - best[0]
        if gain < MIN_STEP_SHARE * max(excess, 1e-300):
            break
        trial = _column_index(d, groups, {*chosen, best[1]})
        rho = d.rho_after(trial, d.best_heldout(trial)[1])
        if d.score(cur, best[0], rho) > -HELDOUT_BIC / 2:
            break
        chosen.append(best[1])
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
    )


def distil(d: Design, items: list[list[Column]], learned: PlaceFit, place: str):
    """Forward selection over the library: the smallest expression that keeps
    :data:`KEEP_SHARE` of the learned term's held-out gain (at most :data:`MAX_TERMS`
    terms). Returns its PlaceFit, the chosen items and their least-squares coefficients
    (per normalised basis column of the design)."""
    # The library's columns are appended to the design as new columns.
    target = learned.heldout_before - KEEP_SHARE * (learned.heldout_before - learned.heldout_after)
    chosen: list[int] = []
    cur = learned.heldout_before
    while len(chosen) < MAX_TERMS:
        best = None
        for j in range(len(items)):
            if j in chosen:
                continue
            val = d.heldout(_item_cols(items, [*chosen, j]), RIDGES[0])
            if best is None or val < best[0]:
                best = (val, j)
        if best is None or cur - best[0] < MIN_STEP_SHARE * max(learned.excess, 1e-300):
            break
        chosen.append(best[1])
        cur = best[0]
        if cur <= target:
            break
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
    )
    coef = x[d.kb :] / d.norms[cols] if cols else np.zeros(0)
    return fit, [items[j] for j in chosen], coef


def _item_cols(items, chosen) -> list[int]:
    offs = np.cumsum([0] + [len(it) for it in items])
    return [int(offs[j]) + i for j in chosen for i in range(len(items[j]))]


def discover(ses, stage: str, fits_of, *, margin_places: float = HELDOUT_BIC) -> Discovery | None:
    """Learn the missing term at every place of ``stage``, keep the best on held-out data,
    and distil it.

    Parameters
    ----------
    ses
        The diagnosis session (trace, data, baseline fits).
    stage
        The located stage.
    fits_of
        ``fits_of(stages) -> AugFit``: the current fit of a set of stages (with the
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
        sig = input_signals(trace, model_channels(ses, fit), fine)
        groups = learned_groups(sig, trace.dt, carriers_of(place))
        d = _design(ses, fit, place, groups, fold, stage)
        if d is None:
            continue
        pf = learn_place(d, groups, place)
        results.append((pf, d, groups, sig, stages))
    if not results:
        return None
    # The place whose term removes the most held-out residual (in units of the noise:
    # a sensor's term is judged on both stages it shows in).
    results.sort(key=lambda x: -x[0].rank_gain)
    best_gain = results[0][0].rank_gain
    close = [x for x in results if x[0].groups and x[0].rank_gain >= PLACE_TIE * best_gain]
    if close:
        results.remove(min(close, key=lambda x: _specificity(x[0].place)))
        results.insert(0, min(close, key=lambda x: _specificity(x[0].place)))
    pf, d, groups, sig, stages = results[0]
    if not pf.groups:
        return Discovery(
            stage, pf.place, stages, pf, pf, (), (), method, tuple(r[0] for r in results), sig
        )
    items = library(sig, pf.groups)
    groups_l = {f"item{j}": list(it) for j, it in enumerate(items)}
    dl = _design(ses, fits_of(stages), pf.place, groups_l, fold, stage)
    assert dl is not None  # the same place built a design above
    dfit, chosen, x = distil(dl, items, pf, pf.place)
    coef = tuple(float(c) for c in x)
    return Discovery(
        stage,
        pf.place,
        stages,
        pf,
        dfit,
        tuple(tuple(t) for t in chosen),
        coef,
        method,
        tuple(r[0] for r in results),
        sig,
    )


def _specificity(place: str) -> int:
    return next(i for i, p in enumerate(PLACE_ORDER) if place.startswith(p))


def basis_matrix(disc: Discovery, n_pad: int) -> np.ndarray:
    """The distilled term's basis series (n_pad, K), zero-padded, for the model's data."""
    n = disc.signals[next(iter(disc.signals))].values.size
    cols = [np.ones(n) if c.values is None else c.values for c in disc.columns]
    B = np.zeros((n_pad, len(cols)))
    B[:n] = np.stack(cols, axis=1)
    return B


# ----------------------------------------------------------------------------- words

#: Known signatures: (place prefix, input, words). The first match reads the term;
#: every reading is a hypothesis to inspect, never a catalog name.
SIGNATURES: tuple[tuple[str, str, str], ...] = (
    (
        "motor.electrical",
        "current",
        "a voltage lost in proportion to (or with the sign of) the "
        "current: resistance of the supply, wiring or driver, or a brush / switch voltage drop",
    ),
    (
        "motor.electrical",
        "heat",
        "a voltage lost growing with the heat dissipated: the "
        "armature's resistance rising as it warms",
    ),
    (
        "motor.electrical",
        "time",
        "a voltage lost that drifts over the recording: heating of "
        "the armature or a sagging supply",
    ),
    (
        "motor.electrical",
        "voltage_rate",
        "the motor sees the logged voltage late or smoothed: a lag in the driver",
    ),
    ("motor.electrical", "speed", "a back-EMF that is not proportional to speed"),
    (
        "motor.mechanical",
        "current",
        "a torque deficit that grows with the current: magnetic "
        "saturation of the motor (kT falls at high current)",
    ),
    (
        "motor.mechanical",
        "angle",
        "a torque that repeats with the pinion angle: cogging, gear "
        "tooth meshing or an eccentric gear",
    ),
    (
        "motor.mechanical",
        "speed",
        "a drag torque depending on speed beyond the viscous term: "
        "windage, lubricant churning or Coulomb friction",
    ),
    ("motor.mechanical", "force", "a load torque from the clamping force"),
    (
        "drive",
        "force",
        "the piston yields under the clamping force: compliance of the drive "
        "(worm, wedge or caliper)",
    ),
    ("gap", "force", "the piston yields under the clamping force: compliance of the drive"),
    ("force.output", "x_rate", "force rising with the piston's speed: damping in the caliper"),
    (
        "force.output",
        "force_history",
        "force relaxing after it changes: viscoelastic creep of the pads",
    ),
    (
        "force.output",
        "time",
        "force drifting over the recording at a given displacement: thermal growth or creep",
    ),
    ("force.input", "time", "the displacement the caliper feels drifts: thermal expansion"),
    (
        "force.input",
        "energy",
        "the displacement the caliper feels grows with the braking "
        "energy: thermal expansion of pads and piston",
    ),
    (
        "force.input",
        "heat",
        "the displacement the caliper feels drifts with heating: thermal expansion",
    ),
    ("friction", "force", "the friction coefficient depends on the pad pressure"),
    (
        "friction",
        "distance",
        "the friction coefficient changes with sliding distance: "
        "bedding-in or a transfer layer building up",
    ),
    ("friction", "time", "the friction coefficient drifts over the recording"),
    (
        "friction",
        "energy",
        "the friction coefficient changes with the braking energy: a thermal effect",
    ),
    (
        "friction",
        "disc_angle",
        "the friction torque varies once or twice per disc revolution: "
        "disc thickness variation or runout",
    ),
    (
        "torque.output",
        "disc_angle",
        "the torque varies once or twice per disc revolution: disc thickness variation or runout",
    ),
    (
        "sensor.",
        "_rate",
        "the sensor reading lags its own signal: a low-pass filter in its signal conditioning",
    ),
    (
        "sensor.",
        "own",
        "the sensor's reading is not proportional to its signal: a calibration nonlinearity",
    ),
)

_OWN = {
    "force_N": "force",
    "torque_Nm": "torque",
    "x_m": "x",
    "theta_deg": "angle",
    "current_A": "current",
}


def reading(place: str, depends_on: Sequence[str]) -> str:
    """A physical reading of a learned term from :data:`SIGNATURES` (a hypothesis), or
    ``""`` when no known signature matches."""
    own = _OWN.get(place.split(".", 1)[1], "") if place.startswith("sensor.") else ""
    for pre, inp, words in SIGNATURES:
        if not place.startswith(pre):
            continue
        for dep in depends_on:
            if inp == "own" and own and dep == own:
                return words
            if inp == "_rate" and own and dep == f"{own}_rate":
                return words
            if (
                dep == inp
                or dep.startswith(inp + "_history")
                or dep.startswith(inp)
                and (inp in ("force_history",))
            ):
                return words
    return ""
