"""The inputs of a learned term, and its bases: every signal the trace and the model
supply (:func:`input_signals`), the flexible basis of the learned function
(:func:`learned_groups`), the library an equation is distilled from (:func:`library`),
and the physical form of each term (:func:`physical`). Used by
:mod:`ewb_ident.diagnosis.discovery`.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ewb_ident.diagnosis.filters import denoised, first_order_lowpass, leave_one_out, reversals
from ewb_ident.diagnosis.locate import disc_angle
from ewb_ident.model.physics import DEG_PER_RAD

#: Time constants of the low-passed histories, s.
HISTORY_S = (0.1, 0.5, 2.0)
#: A reversal of the motion: the angle back from its last extreme by this share of its range.
REVERSAL_SHARE = 0.01

#: The signal named after each channel (a sensor's own signal).
OWN_SIGNAL = {
    "force_N": "force",
    "torque_Nm": "torque",
    "x_m": "x",
    "theta_deg": "angle",
    "current_A": "current",
}


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


def _lowpass(y: np.ndarray, dt: float, tau: float) -> np.ndarray:
    a = float(np.exp(-dt / tau))
    return first_order_lowpass(y, 1.0 - a, a, a * y[0])  # scipy.signal.lfilter's, exactly


def _integral(y: np.ndarray, dt: float) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]))]) * dt


def input_signals(
    trace,
    model: Mapping[str, np.ndarray],
    fine: Mapping[str, np.ndarray] | None = None,
    raw: Collection[str] = (),
) -> dict[str, Signal]:
    """Every signal a learned term may depend on, from the trace and the model.

    Recorded channels enter without their noise at a sample (a term cannot fit the
    residual's noise through its input): levels through :func:`denoised`, rates and
    histories from the 5 ms :func:`leave_one_out` average; the channels in ``model``
    enter as the model gives them.

    Parameters
    ----------
    trace
        The trace.
    model
        Model series that replace recorded channels
        (:func:`~ewb_ident.diagnosis.session.model_channels`: the outputs of the stages a
        term is fitted at and what follows from them, which as recorded would carry the
        very mismatch the term is to explain), and of channels the trace does not record,
        in the channel's unit.
    fine
        The motor's states within each sample interval (:func:`motor_fine`): a term
        inside the motor's integration depends on them there, so they replace the
        current, speed and angle (and the heat is integrated from them).
    raw
        Recorded channels whose noise is not in the residual the term explains: their
        level enters at its own sample (a fast transient), not as its neighbours' mean.
    """
    dt, n = trace.dt, trace.n
    half = max(1, round(0.005 / dt))
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

    def channel(ch, level=False):  # a level: as recorded in ``raw``, else :func:`denoised`
        if ch in model:
            return np.asarray(model[ch], float)[:n]
        if not trace.has(ch):
            return None
        if not level:  # (its rate and history: the 5 ms average's)
            return leave_one_out(trace[ch], half)
        return trace[ch] if ch in raw else denoised(trace[ch], dt)

    t = trace.time_s - trace.time_s[0]
    add("time", t, "s", "level", "elapsed time", "t")
    if trace.has("voltage_V"):
        V = trace["voltage_V"]
        add("voltage", V, "V", "signed", "the motor voltage", "V")
        # The logged voltage is held over each interval: its rate is its step at the
        # interval's start (a central difference would act before the step).
        rate = np.diff(V, prepend=V[0]) / dt
        add("voltage_rate", rate, "V/s", "signed", "the voltage's rate", "dV/dt")
    th = channel("theta_deg")
    if th is not None:
        omega = np.gradient(th, dt) / DEG_PER_RAD
        add("angle", channel("theta_deg", True), "deg", "angle", "the pinion angle", "θ")
        add("speed", omega, "rad/s", "signed", "the motor speed", "ω")
        for tau in HISTORY_S:  # a drag that builds over a stroke and outlasts it
            hist, lp = f"the motor speed low-passed over {tau:g} s", _lowpass(omega, dt, tau)
            add(f"speed_history_{tau:g}s", lp, "rad/s", "signed", hist, f"ω̄{tau:g}s")
        # What steps at each reversal (a slip, a loss per stroke); what restarts (hysteresis).
        count, travel = reversals(th, REVERSAL_SHARE)
        add("reversals", count, "1", "level", "the reversals of the motion so far", "n_rev")
        add("travel", travel, "deg", "signed", "the angle travelled since a reversal", "θ_rev")
    cur = channel("current_A")
    if fine is not None and "current" in fine:
        cur = np.asarray(fine["current"])[:, 0]
    if cur is not None:
        level = channel("current_A", True) if fine is None else cur
        add("current", level, "A", "signed", "the motor current", "i")
        if fine is not None and "current" in fine:
            per = interval_mean(np.asarray(fine["current"]) ** 2)
            heat = np.concatenate([[0.0], np.cumsum(per[:-1])]) * dt
        else:
            per = cur**2
            heat = _integral(per, dt)
        add("heat", heat, "A^2*s", "level", "heat dissipated, ∫i²dt", "∫i²dt")
        # A temperature rise that cools again: the Joule heating through a first-order
        # thermal lag (a winding, a driver stage, a shunt), one per time constant.
        for tau in HISTORY_S:
            words = f"the squared current low-passed over {tau:g} s (a temperature rise)"
            name, sym = f"heat_history_{tau:g}s", f"ī²{tau:g}s"
            add(name, _lowpass(per, dt, tau), "A^2", "level", words, sym)
    levels = (
        ("x_m", "x", "m", "the piston displacement", "x", "the piston speed"),
        ("force_N", "force", "N", "the clamping force", "F", "the rate of the force"),
        ("torque_Nm", "torque", "N*m", "the brake torque", "T", "the rate of the brake torque"),
    )
    for ch, name, unit, words, sym, rate_words in levels:
        y = channel(ch)
        if y is None:
            continue
        add(name, channel(ch, True), unit, "level", words, sym)
        add(f"{name}_rate", np.gradient(y, dt), f"{unit}/s", "signed", rate_words, f"d{sym}/dt")
        if name != "force":
            continue
        for tau in HISTORY_S:  # its recent history, and its whole (what accumulates with it)
            hist = f"the force low-passed over {tau:g} s (its recent history)"
            add(f"force_history_{tau:g}s", _lowpass(y, dt, tau), "N", "level", hist, f"F̄{tau:g}s")
        add("force_integral", _integral(y, dt), "N*s", "level", "the force's integral", "∫Fdt")
        peak = np.maximum.accumulate(out["force"].values) if "force" in out else np.zeros(n)
        add("force_peak", peak, "N", "level", "the largest force so far", "F̂")  # pads that set
    if trace.has("disc_speed_rad_s"):
        wd = trace["disc_speed_rad_s"]
        if np.ptp(wd) > 0.02 * max(float(np.max(np.abs(wd))), 1e-9):
            add("disc_speed", wd, "rad/s", "level", "the disc speed", "ω_d")
        slid = _integral(np.abs(wd), dt)
        add("distance", slid, "rad", "level", "the disc's sliding angle", "s_d")
        phi = np.mod(disc_angle(trace), 2 * np.pi)
        add("disc_angle", phi, "rad", "phase", "the disc angle", "φ_d")
        if "torque" in out:
            energy = _integral(np.abs(out["torque"].values * wd), dt)
            add("energy", energy, "J", "level", "the braking energy dissipated", "E")
    for name in [k for k in ("current", "force") if k in out]:  # a hysteresis of its own
        s, moved = out[name], reversals(out[name].values, REVERSAL_SHARE)[1]
        words = f"the {name}'s change since it last reversed"
        add(f"{name}_travel", moved, s.unit, "signed", words, f"Δ{s.symbol}_rev")
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


def interval_mean(f: np.ndarray) -> np.ndarray:
    """The mean over each sample interval of values within it, (n, m + 1) -> (n,)."""
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
    "gap": ("angle",),
    "force.input": ("x",),
    "force.output": ("force",),
    "torque.output": ("force",),
}


def sensor_signal(place: str) -> str:
    """The signal a sensor place reads (``"force"`` for ``sensor.force_N``), ``""`` for a
    place that is not a sensor's."""
    return OWN_SIGNAL.get(place.split(".", 1)[1], "") if place.startswith("sensor.") else ""


def carriers_of(place: str) -> tuple[str, ...]:
    """The carriers of a place (a sensor's: its own signal)."""
    own = sensor_signal(place)  # "" for a place that is not a sensor's
    return (own,) if own else CARRIERS.get(place, ())


TRIG = {"sin": np.sin, "cos": np.cos}
#: A product's function of its second input (its first, the carrier, is normalised, or
#: for an ``s`` kind its sign: a friction, or a drop, whose size another signal sets).
PRODUCT = {"prod": ("pow", 1), "prod2": ("pow", 2), "prodabs": ("abs",)}
PRODUCT |= {f"s{k}": v for k, v in PRODUCT.items()}
SIGN = ("tanh", 0.05)


def product_of(form: tuple) -> tuple | None:
    """The form of the function of its second input a product column has (a carrier
    times a power, or ``prodtrig``: times a harmonic of a phase or a position's period),
    or ``None`` for a column that is not a product."""
    if form[0] in PRODUCT:
        return PRODUCT[form[0]]
    return tuple(form[3:]) if form[0] in ("prodtrig", "sprodtrig") else None


def carrier_form(form: tuple) -> tuple:
    """The function of its carrier a product column has: the carrier or its sign."""
    return SIGN if form[0].startswith("sprod") else ("pow", 1)


def form_fn(form: tuple, r: float):
    """The function of a signal's raw values a one-input form is (normalised by ``r``)."""
    kind = form[0]
    if kind == "pow":
        return lambda v, p=form[1]: (v / r) ** p
    if kind == "spow":
        return lambda v: v * np.abs(v) / r**2
    if kind == "abs":
        return lambda v: np.abs(v) / r
    if kind == "tanh":
        return lambda v, w=form[1]: np.tanh(v / r / w)
    if kind == "sqrt":
        return lambda v: np.sqrt(np.abs(v) / r)
    if kind == "sat":
        return lambda v, w=form[1]: 1 - np.exp(-np.abs(v) / r / w)
    if kind == "hinge":
        return lambda v, k=form[1]: np.maximum(v / r - k, 0.0)
    if kind == "nhinge":
        return lambda v, k=form[1]: np.maximum(-v / r - k, 0.0)
    if kind == "ohinge":
        return lambda v, k=form[1]: np.sign(v) * np.maximum(np.abs(v) / r - k, 0.0)
    if kind == "harm":
        return lambda v, k=form[1], g=TRIG[form[2]]: g(k * v)
    if kind == "period":
        return lambda v, P=form[1], g=TRIG[form[2]]: g(2 * np.pi * v / P)
    raise ValueError(f"unknown basis form {form!r}")


def form_values(
    form: tuple,
    signal: str,
    signals: Mapping[str, Signal],
    refs: Mapping[str, float] | None = None,
) -> np.ndarray | None:
    """A basis column's values per sample from its form (``None``: the constant).

    Parameters
    ----------
    form
        ``(kind, *args)``: ``pow``, ``spow``, ``abs``, ``tanh``, ``sqrt``, ``sat``,
        ``hinge``, ``nhinge`` (the hinge of the negated signal), ``ohinge`` (the odd
        hinge of the magnitude), ``harm``, ``period`` of ``signal``; ``prod``, ``prod2``,
        ``prodabs``, ``prodtrig`` of the carrier ``form[1]`` (``sprod...``: its sign)
        times a function of ``form[2]`` (:func:`product_of`); ``one``.
    signal
        The input it depends on (a product's: ``"carrier*other"``).
    signals
        The signals (:func:`input_signals`).
    refs
        The size each signal is normalised by; default each signal's own ``ref`` (a
        term rebuilt on another trace keeps the sizes it was fitted with, so its
        coefficients keep their meaning).
    """
    kind = form[0]
    if kind == "one":
        return None

    def ref(name: str) -> float:
        return float(refs[name]) if refs is not None else signals[name].ref

    second = product_of(form)
    if second is not None:
        c, s = signals[form[1]], signals[form[2]]
        fn, fc = form_fn(second, ref(form[2])), form_fn(carrier_form(form), ref(form[1]))
        if c.fine is not None and s.fine is not None:
            return interval_mean(fc(c.fine) * fn(s.fine))
        return ev(c, fc) * ev(s, fn)
    return ev(signals[signal], form_fn(form, ref(signal)))


def stacked(values: Sequence[np.ndarray | None], n: int) -> np.ndarray:
    """Basis columns side by side, (n, K) (``None``: the constant)."""
    return np.stack([np.ones(n) if v is None else v for v in values], axis=1)


def _col(label: str, signal: str, form: tuple, signals: Mapping[str, Signal]) -> Column:
    return Column(label, signal, form_values(form, signal, signals), form)


def _products(c: Signal, s: Signal, signals: Mapping[str, Signal]) -> list[Column]:
    """The carrier ``c`` times ``s``, ``s²`` (and ``|s|`` for a signed ``s``), and for a
    signed carrier its sign times each (a friction whose size another signal sets)."""
    kinds = ["prod", "prod2"] + (["prodabs"] if s.kind == "signed" else [])
    kinds += [f"s{k}" for k in kinds] if c.kind == "signed" else []
    cols = [_col("", f"{c.name}*{s.name}", (k, c.name, s.name), signals) for k in kinds]
    return [replace(col, label=physical(col, signals)[0]) for col in cols]


def trig_products(c: Signal, s: Signal, arg: tuple, signals) -> list[Column]:
    """The carrier ``c`` (and a signed one's sign) times a sine and cosine of the phase
    or position ``s`` (``arg``: ``("harm", k)`` or ``("period", P)``): a coefficient that
    varies around a turn (a friction that binds at some angles)."""
    trig = periodic(s, arg[1], signals) if arg[0] == "period" else _harmonic(s, arg[1], signals)
    heads = {"prodtrig": c.symbol, "sprodtrig": f"sign({c.symbol})"}
    g = f"{c.name}*{s.name}"
    return [_col(f"{heads[k]}·{col.label}", g, (k, c.name, s.name, *col.form), signals)
            for k in list(heads)[: 1 + (c.kind == "signed")] for col in trig]  # fmt: skip


def periodic(s: Signal, period: float, signals) -> list[Column]:
    """A sine and cosine of the position ``s`` with ``period`` (in its unit, mm for x)."""
    arg = f"2π{s.symbol}/" + {"deg": f"{period:.4g}°", "m": f"{period * 1e3:.4g} mm"}[s.unit]
    return [_col(f"{f}({arg})", s.name, ("period", period, f), signals) for f in TRIG]


def _harmonic(s: Signal, k: int, signals) -> list[Column]:
    """A sine and cosine of ``k`` times the phase ``s``."""
    k_ = "" if k == 1 else str(k)
    return [_col(f"{f}({k_}{s.symbol})", s.name, ("harm", k, f), signals) for f in TRIG]


def _signed(s: Signal, signals) -> list[Column]:
    """The odd functions of a signed input, with the odd hinges of its magnitude beyond
    a knot (a clipping or a dead zone; its even part and one-sided forms are the
    distillation library's: :func:`library`)."""
    return [
        _col(s.symbol, s.name, ("pow", 1), signals),
        _col(f"{s.symbol}|{s.symbol}|", s.name, ("spow", 2), signals),
        _col(f"{s.symbol}³", s.name, ("pow", 3), signals),
        _col(f"sign({s.symbol})", s.name, ("tanh", 0.05), signals),
        *_odd_hinges(s, signals),
    ]


def _odd_hinges(s: Signal, signals) -> list[Column]:
    """``sign(s) max(0, |s| - k)``, knots at :data:`SIDE_KNOTS` of its size."""
    cols = [_col("", s.name, ("ohinge", q), signals) for q in SIDE_KNOTS]
    return [replace(c, label=physical(c, signals)[0]) for c in cols]


#: Knots of a signed input's hinges in the library, as shares of its largest excursion
#: on each side.
SIDE_KNOTS = (1 / 3, 2 / 3)


def _side_hinges(s: Signal, shares: Sequence[float], signals) -> list[Column]:
    """Hinges of a signed input on each side it reaches, ``max(0, s - k)`` and
    ``max(0, -s - k)``, knots at ``shares`` of its largest excursion there (a share of
    0: the side itself, ``max(0, s)``)."""
    z = s.values / s.ref
    out = []
    for kind, top in (("hinge", float(np.max(z))), ("nhinge", float(np.max(-z)))):
        if top < 0.05:
            continue  # a side the signal does not reach
        out += [_col("", s.name, (kind, q * top), signals) for q in shares]
    return [replace(c, label=physical(c, signals)[0]) for c in out]


def _hinges(s: Signal, shares: Sequence[float], signals) -> list[Column]:
    return [
        _col(f"max(0, {s.symbol} − {k * s.ref:.3g})", s.name, ("hinge", k), signals)
        for k in _hinge_knots(s.values / s.ref, shares)
    ]


def learned_groups(
    signals: Mapping[str, Signal],
    carriers: Sequence[str] = (),
    periods: Mapping[str, Sequence[float]] | None = None,
) -> dict[str, list[Column]]:
    """The flexible basis of the learned function, one group of columns per input (and
    per period of a position in ``periods``, ``{signal: periods}`` in its unit), and per
    carrier times each other input."""
    periods = periods or {}
    groups: dict[str, list[Column]] = {"constant": [Column("1", "constant", None, ("one",))]}
    for cname in carriers:
        c = signals.get(cname)
        if c is None:
            continue
        for s in signals.values():
            if s.name != cname and s.kind in ("level", "signed"):
                groups[f"{cname}*{s.name}"] = _products(c, s, signals)
            elif s.kind == "phase":
                groups[f"{cname}*{s.name}"] = [
                    col for k in (1, 2) for col in trig_products(c, s, ("harm", k), signals)
                ]
            for P in periods.get(s.name, ()) if s.name != cname else ():
                groups[f"{cname}*{s.name}@{P:.4g}"] = trig_products(c, s, ("period", P), signals)
    for s in signals.values():
        if s.kind == "signed":
            groups[s.name] = _signed(s, signals)
        elif s.kind == "phase":
            groups[s.name] = [c for k in (1, 2) for c in _harmonic(s, k, signals)]
        else:
            groups[s.name] = [_col(s.symbol, s.name, ("pow", 1), signals)] + _hinges(
                s, KNOTS, signals
            )
        for P in periods.get(s.name, ()):
            groups[f"{s.name}@{P:.4g}"] = periodic(s, P, signals)
    return groups


def library(signals: Mapping[str, Signal], chosen: Sequence[str], knots=(0.5,)) -> list:
    """The distillation library of the chosen groups: each item one term (a harmonic is
    its sine and cosine together); a level's hinges at ``knots`` (shares of its range)."""
    items: list[list[Column]] = []
    names = []
    for g in chosen:
        if g == "constant":
            items.append([Column("1", "constant", None, ("one",))])
            continue
        if "*" in g:  # a carrier times another input
            cname, _, other = g.partition("*")
            c, (oname, _, per) = signals[cname], other.partition("@")
            if per:
                args = [("period", float(per) / h) for h in (1, 2)]
            elif signals[oname].kind == "phase":
                args = [("harm", k) for k in (1, 2)]
            else:
                items += [[col] for col in _products(c, signals[oname], signals)]
                continue
            items += [trig_products(c, signals[oname], a, signals) for a in args]
            continue
        name, _, per = g.partition("@")
        s = signals[name]
        if per:
            items += [periodic(s, float(per) / h, signals) for h in (1, 2)]
            continue
        names.append(name)
        if s.kind == "phase":
            items += [_harmonic(s, k, signals) for k in (1, 2)]
            continue
        sym = s.symbol
        cand = [
            _col(sym, name, ("pow", 1), signals),
            _col(f"{sym}²", name, ("pow", 2), signals),
            _col(f"{sym}³", name, ("pow", 3), signals),
        ]
        if s.kind == "signed":
            cand += [
                _col(f"{sym}|{sym}|", name, ("spow", 2), signals),
                _col(f"|{sym}|", name, ("abs",), signals),
                _col(f"sign({sym})", name, ("tanh", 0.05), signals),
                _col(f"tanh({sym}/{0.3 * s.ref:.3g})", name, ("tanh", 0.3), signals),
                *_side_hinges(s, (0.0, *SIDE_KNOTS), signals),
                *_odd_hinges(s, signals),
            ]
        else:
            cand += [
                _col(f"√{sym}", name, ("sqrt",), signals),
                _col(f"1 − exp(−{sym}/{0.3 * s.ref:.3g})", name, ("sat", 0.3), signals),
                *_hinges(s, knots, signals),
            ]
        items += [[c] for c in cand]
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            sa, sb = signals[a], signals[b]
            label = f"{sa.symbol}·{sb.symbol}"
            items.append([_col(label, f"{a}*{b}", ("prod", a, b), signals)])
    return items


def physical(col: Column, signals: Mapping[str, Signal]) -> tuple[str, float, str]:
    """The expression of a basis column in physical units, the factor that turns its
    coefficient into the expression's, and the expression's unit (``""``: none).

    A column is ``f(z)`` of a normalised signal ``z = s / ref``; its coefficient times
    ``factor`` is the coefficient of the expression in the signal's own unit."""
    kind = col.form[0]
    if kind == "one":
        return "1", 1.0, ""
    if kind in PRODUCT:  # the carrier (or its sign) times the other's one-input form
        a = signals[col.form[1]]
        expr, factor, unit = physical(Column("", col.form[2], None, PRODUCT[kind]), signals)
        if carrier_form(col.form) == SIGN:
            return f"sign({a.symbol})·{expr}", factor, unit
        return f"{a.symbol}·{expr}", factor / a.ref, f"{a.unit}*{unit}"
    if kind in ("prodtrig", "sprodtrig"):
        a = signals[col.form[1]]
        return (col.label, 1.0 / a.ref, a.unit) if kind == "prodtrig" else (col.label, 1.0, "")
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
    if kind in ("hinge", "nhinge"):
        sym = s.symbol if kind == "hinge" else f"−{s.symbol}"
        knot = col.form[1] * s.ref
        expr = f"max(0, {sym})" if knot == 0 else f"max(0, {sym} − {knot:.4g} {s.unit})"
        return expr, 1.0 / s.ref, s.unit
    if kind == "ohinge":
        knot = col.form[1] * s.ref
        return f"sign({s.symbol})·max(0, |{s.symbol}| − {knot:.4g} {s.unit})", 1.0 / s.ref, s.unit
    return col.label, 1.0, ""


def render(col: Column, coef: float, signals: Mapping[str, Signal]) -> str:
    """One term of the equation in SI units: the physical coefficient times the
    expression (see :func:`physical`)."""
    expr, factor, _ = physical(col, signals)
    return f"{coef * factor:+.4g}" if expr == "1" else f"{coef * factor:+.4g}·{expr}"


def render_pair(cols: Sequence[Column], coefs: Sequence[float], signals) -> str:
    """A sine and cosine pair as one harmonic, ``A·sin(... + phase)`` (a carrier's
    product: ``A·c·sin(... + phase)``)."""
    factor = physical(cols[0], signals)[1]
    cs, cc = (float(c) * factor for c in coefs)
    amp, phase = float(np.hypot(cs, cc)), float(np.arctan2(cc, cs))
    head, _, arg = cols[0].label.partition("sin(")
    return f"{amp:+.4g}·{head}sin({arg[:-1]} {phase:+.2f})"
