"""The diagnosis's working state for one trace: its thresholds, the baseline stage
fits (cached), the augmented fits and their evidence (BIC with AR(1)-effective N)."""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Mapping, Sequence
from concurrent.futures import Future
from typing import Any

import numpy as np
from scipy.special import chdtrc

from ewb_ident.data.metrics import RHO_MAX, channel_metrics, noise_sigma, sensor_noise, smooth
from ewb_ident.data.stages import (
    CHANNELS,
    STAGE,
    STAGE_COLUMNS,
    STAGE_OUTPUTS,
    TEACHER_FORCED,
)
from ewb_ident.data.trace import InputError, Trace
from ewb_ident.diagnosis.filters import denoised
from ewb_ident.diagnosis.heldout import RHO_CAP
from ewb_ident.diagnosis.locate import (
    FLOOR_SCALE,
    StageCheck,
    coarsely_rounded,
    phase_labels,
)
from ewb_ident.inference.augmented import fit_mechanisms, make_data
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.least_squares import fit_checked_traces as fit_stage
from ewb_ident.inference.least_squares import start_of_checked_trace as start_of
from ewb_ident.inference.problem import default_free
from ewb_ident.inference.residuals import FORCED_INPUT, carried_noise
from ewb_ident.mechanisms import AbstractMechanism
from ewb_ident.mechanisms.learned import LearnedTerm
from ewb_ident.model.integrate import motor_angle_rad
from ewb_ident.model.params import PARAMS, EWBParams
from ewb_ident.model.physics import clamp_force
from ewb_ident.runtime.programs import on_device
from ewb_ident.runtime.threads import made_once

#: A mechanism must lower the BIC by at least this much.
BIC_THRESHOLD = 10.0
#: ... and remove at least this fraction of the excess residual at its stages.
MIN_EXPLAINED = 0.5
#: ... unless it removes at least this share of what a discovered term removes.
CATALOG_SHARE = 0.8
#: Most catalog mechanisms selected for one trace.
MAX_MECHANISMS = 3
#: Averaging time of the displacement that drives a hysteresis state, s.
X_SMOOTH_S = 0.01
#: Most stages given a discovered term.
MAX_CORRECTIONS = 2

#: How to record a trace that separates two mechanisms a trace could not tell apart.
SEPARATE: defaultdict[frozenset[str], str] = defaultdict(
    str,
    {
        frozenset(("friction_speed", "friction_fade")): (
            "when the disc slows steadily while the pads heat up, speed and dissipated "
            "energy rise and fall together; disc-speed steps, or a cooled-down repeat, "
            "separate them"
        ),
    },
)

#: The motor's physical parameters (its stage's, less the start angle).
MOTOR_PARAMS: tuple[str, ...] = tuple(n for n in STAGE["motor"].params if n != "theta0_deg")


class DiagnoseError(InputError):
    """A trace that cannot be diagnosed (the message says why and what to do)."""


def pct_text(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def json_number(v: Any) -> Any:
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def metrics_json(m: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    return {ch: {k: json_number(v) for k, v in mm.items()} for ch, mm in m.items()}


# ----------------------------------------------------------------------------- session


def stage_order(stages) -> tuple[str, ...]:
    if tuple(stages) == ("chain",):
        return ("chain",)
    return tuple(s for s in TEACHER_FORCED if s in stages)


def _key(stages, mechs) -> tuple:
    return (stage_order(stages), tuple(m.variant + repr(m.static_config()) for m in mechs))


class Session:
    """The trace, its noise floors and data, and a cache of fits."""

    def __init__(self, trace: Trace):
        self.trace = trace
        self.cols = tuple(c for c in trace.columns if c != "time_s")
        self.stages = tuple(
            s for s in TEACHER_FORCED if all(trace.has(c) for c in STAGE_COLUMNS[s])
        )
        if not self.stages:
            raise DiagnoseError(
                f"{trace.label}: no stage of the chain can be checked: it needs at least "
                "one input-output pair (voltage_V and theta_deg, theta_deg and x_m, x_m and "
                "force_N, or force_N and torque_Nm); record these channels"
            )
        self.noise = {ch: sensor_noise(trace[ch]) for ch in CHANNELS if trace.has(ch)}
        #: Each stage's start values for its baseline fit, once :meth:`checked`.
        self.starts: dict[str, dict[str, float]] = {}
        #: Channels (inputs included) on a grid coarse against their noise.
        self.rounded = {ch for ch in self.cols if coarsely_rounded(trace[ch])}
        self.labels = phase_labels(trace)
        self.cache: dict[tuple, FitResult] = {}
        # Fits under way (a diagnosis tries its candidates side by side): a second
        # caller of the same fit waits for the first.
        self._pending: dict[tuple, Future] = {}
        self._lock = threading.Lock()
        self.ctx = self._facts()

    def _facts(self) -> dict[str, Any]:
        tr = self.trace
        ctx: dict[str, Any] = {"dt": tr.dt, "duration_s": tr.n * tr.dt}
        if tr.has("voltage_V"):
            ctx["voltage_noise_V"] = noise_sigma(tr["voltage_V"])
        if tr.has("force_N"):
            ctx["force_max_N"] = float(np.max(tr["force_N"]))
        if tr.has("current_A"):
            ctx["current_peak_A"] = float(np.max(np.abs(tr["current_A"])))
        if tr.has("disc_speed_rad_s"):
            w = tr["disc_speed_rad_s"]
            contact = self.labels != "gapping"
            wc = w[contact] if np.sum(contact) > 2 else w
            ref = float(np.mean(wc))
            ctx["omega_ref"] = ref if abs(ref) > 1e-6 else 1.0
            ctx["disc_speed_range"] = (float(np.min(wc)), float(np.max(wc)))
            ctx["disc_speed_span"] = (
                float(np.max(wc) - np.min(wc)) / abs(ctx["omega_ref"]) if ref else 0.0
            )
            if tr.has("torque_Nm"):
                ctx["energy_total_J"] = float(np.sum(np.abs(tr["torque_Nm"] * w)) * tr.dt)
        return ctx

    # -- baseline

    def checked(self) -> Session:
        """This session, once its trace's data give every stage's baseline fit a start
        inside the parameters' bounds (else the :class:`FitError` that fit would raise,
        see :func:`~ewb_ident.inference.least_squares.start_of_checked_trace`); the
        baseline fits then begin from those starts."""
        self.starts = {s: start_of(self.trace, stage=s) for s in self.stages}
        return self

    def baseline(self) -> None:
        tr = self.trace
        vals = EWBParams().as_dict()
        vals["theta0_deg"] = float(np.median(tr["theta_deg"][:5])) if tr.has("theta_deg") else 0.0
        #: The start angle as recorded (a motor refit's second start).
        self.theta0_measured = vals["theta0_deg"]
        self.free: dict[str, tuple[str, ...]] = {}
        self.base_messages: list[str] = []
        for s in self.stages:
            free = default_free(s, [tr])
            self.free[s] = tuple(free)
            res = _safe_fit(tr, s, self.base_messages, self.starts.get(s))
            if res is None:
                continue
            bad = []
            for name in free:
                v = float(res.values[name])
                info = PARAMS[name]
                if not np.isfinite(v) or (info.transform == "log" and v <= 1e-9 * info.ref):
                    bad.append(name)  # degenerate: start from the seed value instead
                    continue
                vals[name] = v
            if bad:
                self.base_messages.append(
                    f"the baseline {s}-stage fit returned degenerate values for "
                    f"{', '.join(bad)}; the diagnosis started them from the seed values"
                )
            if not res.converged:
                self.base_messages.append(f"the baseline {s}-stage fit: {res.message}")
        self.values = vals
        kT, R = vals["kT"], vals["R"]
        self.ctx |= {"kT": kT, "R": R}
        if tr.has("voltage_V") and R > 0:
            self.ctx["stall_torque_Nm"] = stall_torque(tr, kT, R)
            if tr.has("theta_deg"):
                self.ctx["current_demand_A"] = current_demand(tr, vals["kb"], R)
        self.sigma_tf = self._stage_sigma(vals)
        # The displacement that drives a hysteresis state: averaged over about 10 ms,
        # then through a play twice as wide as the averaged noise (sensor noise must not
        # drive a rate-independent friction state while the piston stands still).
        width = max(1, round(X_SMOOTH_S / tr.dt)) | 1
        xp = 2.0 * self.noise.get("x_m", 0.0) / np.sqrt(width)
        x_model = None
        if "motor" in self.stages and "gap" in self.stages:
            # Better still: the motor model's angle follows the logged voltage, so it
            # carries the actuator's small motions (controller dither in a hold) that
            # the displacement sensor's noise hides, and that a friction state feels.
            theta_model = self.base_fits_motor_theta(vals)
            x_model = vals["p2"] * theta_model**2 + vals["p1"] * theta_model + vals["p0"]
        # The fits weigh a teacher-forced stage's output by its sensor noise and its
        # input's carried at the values being fitted (effective variance, see
        # ``carried_noise``); ``sigma_tf`` (at the baseline values) is the checks' floor.
        forced = {ch: self.noise[ch] for ch in FORCED_INPUT if ch in self.sigma_tf}
        data = make_data(
            tr,
            self.sigma_tf | forced,
            vals,
            carry={ch: self.noise.get(FORCED_INPUT[ch], 0.0) for ch in forced},
            x_play_m=xp,
            omega_ref=self.ctx.get("omega_ref", 1.0),
            theta_noise=self.noise.get("theta_deg"),
            x_smooth=width,
            x_model=x_model,
        )
        self.data = data
        self.base_fits = {s: self.fit((s,), ()) for s in self.stages}
        for s, f in self.base_fits.items():
            for name in self.free[s]:
                self.values[name] = f.values[name]

    def base_fits_motor_theta(self, v: Mapping[str, float]) -> np.ndarray:
        """The motor stage's angle (degrees) from the logged voltage, baseline values."""
        # As arrays: a program's plain-float arguments are part of its key, so float
        # values compiled one program per trace (same angles, bit for bit).
        p = EWBParams(**{k: np.asarray(float(v[k])) for k in EWBParams().as_dict()})
        theta = motor_angle_rad(
            p, *on_device((self.trace["voltage_V"], self.trace.dt, float(v["theta0_deg"])))
        )
        return np.asarray(theta) * (180.0 / np.pi)

    def _stage_sigma(self, v: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Noise floor per sample of each teacher-forced stage's output: its sensor's
        noise and its measured input's carried through the stage at the values ``v``
        (:func:`~ewb_ident.inference.residuals.carried_noise`, as the fits weigh it)."""
        tr, nz = self.trace, self.noise
        n = tr.n
        out: dict[str, np.ndarray] = {}
        if "motor" in self.stages:
            out |= {ch: np.full(n, nz[ch]) for ch in ("theta_deg", "current_A") if tr.has(ch)}
        p = EWBParams(**{k: float(v[k]) for k in EWBParams().as_dict()})
        d = {"meas": {c: tr[c] for c in CHANNELS if tr.has(c)}, "dt": tr.dt, "r_eff": tr.r_eff_m}
        carry = {ch: nz.get(inp, 0.0) for ch, inp in FORCED_INPUT.items()}
        carried = carried_noise(p, v["theta0_deg"], (), d, carry, self.stages, 1, "exponential")
        out |= {ch: np.sqrt(nz[ch] ** 2 + np.asarray(c) ** 2) for ch, c in carried.items()}
        return {ch: np.broadcast_to(np.asarray(v, float), (n,)).copy() for ch, v in out.items()}

    # -- fits

    def free_of(self, stages: Sequence[str]) -> tuple[str, ...]:
        out: list[str] = []
        for s in stages:
            out += [n for n in self.free[s] if n not in out]
        return tuple(out)

    def channels_of(self, stages: Sequence[str]) -> tuple[str, ...]:
        return tuple(c for s in stages for c in STAGE_OUTPUTS[s] if c in self.sigma_tf)

    def fit(
        self,
        stages: Sequence[str],
        mechs: Sequence[AbstractMechanism],
        explore: Sequence[bool] | None = None,
    ) -> FitResult:
        """The fit of ``stages`` with ``mechs`` (:func:`fit_mechanisms`), made once per
        session; callers in other threads that ask for it meanwhile wait for it."""
        stages = stage_order(stages)
        key = _key(stages, mechs)

        def make() -> FitResult:
            f = self._fit(stages, mechs, explore)
            with self._lock:
                self.cache[key] = f
            return f

        return made_once(self._lock, self._pending, key, self.cache.get, make)[0]

    def nominal_starts(self, stages: Sequence[str]) -> list[dict[str, float]]:
        """Other starts for a fit with physics added at ``stages``: a baseline motor
        fitted without the missing physics has compensated for it (and a closed-loop
        trace lets such errors grow without bound), so also the nominal motor."""
        if "motor" not in stages:
            return []
        nominal = EWBParams().as_dict() | {"theta0_deg": self.theta0_measured}
        keep = (*MOTOR_PARAMS, "theta0_deg")
        return [{n: nominal[n] for n in self.free_of(stages) if n in nominal and n in keep}]

    def _fit(self, stages, mechs, explore) -> FitResult:
        free = self.free_of(stages)
        alt = self.nominal_starts(stages) if mechs else []
        return fit_mechanisms(
            self.data,
            stages,
            free,
            tuple(mechs),
            self.channels_of(stages),
            start={n: self.values[n] for n in free},
            ctx=self.ctx,
            explore=explore,
            alt_starts=alt,
        )

    def check(self, stage: str, f: FitResult) -> list[StageCheck]:
        inp = STAGE_COLUMNS[stage][0] if stage in STAGE_COLUMNS else None
        out = []
        for ch in STAGE_OUTPUTS[stage]:
            if ch in f.predictions[0] and ch in self.sigma_tf:
                y, pred = self.trace[ch], f.predictions[0][ch]
                rounded = inp in self.rounded or ch in self.rounded
                rounded = rounded or coarsely_rounded(y, y - np.asarray(pred))
                out.append(StageCheck(stage, ch, y, pred, self.sigma_tf[ch], rounded))
        return out

    def mechanism_stages(self, m: AbstractMechanism) -> tuple[str, ...]:
        return tuple(s for s in m.stages if s in self.stages)


def chain_baseline(ses: Session, messages: list[str]):
    """The whole chain from the voltage without mechanisms: its data, free parameters,
    per-channel noise levels and fit (started from the least-squares chain fit, or the
    stage values when that fails)."""
    trace = ses.trace
    base_chain = _safe_fit(trace, "chain", messages)
    start = ses.values if base_chain is None else base_chain.values
    free = tuple(default_free("chain", [trace]))
    sigma = {ch: ses.noise[ch] for ch in CHANNELS if trace.has(ch)}
    data = make_data(trace, sigma, start, omega_ref=ses.ctx.get("omega_ref", 1.0))
    return data, free, sigma, fit_mechanisms(data, ("chain",), free, (), tuple(sigma))


def chain_metrics(trace: Trace, f: FitResult) -> dict[str, dict[str, float | None]]:
    """Metrics of a fit's predictions for the channels the trace records."""
    preds = f.predictions[0]
    return {ch: channel_metrics(p, trace[ch]) for ch, p in preds.items() if trace.has(ch)}


def _safe_fit(trace: Trace, stage: str, messages: list[str], start=None):
    """The baseline fit of one stage by :func:`ewb_ident.inference.least_squares.fit`
    (from ``start``, its data's start values, if given), or ``None`` (and a message)
    when it fails numerically: the diagnosis then starts from the seed values."""
    try:
        return fit_stage(trace, stage=stage, start=start)
    except (np.linalg.LinAlgError, FloatingPointError, ArithmeticError) as err:
        messages.append(f"the baseline {stage} fit failed ({err}); started from seed values")
        return None


# ----------------------------------------------------------------------------- evidence


def bic_evidence(
    f1: FitResult,
    f0: FitResult,
    sigma: Mapping[str, np.ndarray],
    own: Sequence[str] | None = None,
    rho_max: float = RHO_MAX,
) -> dict[str, float]:
    """Evidence for the mechanisms ``f1`` adds to ``f0`` (same stages and weights).

    ``delta_bic`` counts the residuals as an AR(1) series of the lag-1 correlation of
    ``f1``'s residual, clipped to ``rho_max``: a learned term, which has passed held-out
    folds, is judged with the cap the folds use
    (:data:`~ewb_ident.diagnosis.heldout.RHO_CAP`), since a smooth remainder of a large
    mismatch would otherwise leave a handful of "independent" residuals whatever share
    of it the term removes.

    ``explained_fraction`` is the share of the excess of ``f0``'s residual over the
    noise that ``f1`` removes; the noise expectation of the weighted residual sum of
    squares is ``sum_ch n c_ch^2`` with ``c_ch`` the residual's own white-noise level per
    channel (:func:`ewb_ident.diagnosis.locate.floor_scale`), so a noise floor that is off by some
    per cent does not distort it.
    """
    n = f0.n
    dk = f1.k - f0.k
    rss0, rss1 = max(f0.rss, 1e-300), max(f1.rss, 1e-300)
    rho = min(_lag1(f1, sigma), rho_max)
    n_eff = n * (1.0 - rho) / (1.0 + rho)
    dbic = n_eff * float(np.log(rss1 / rss0)) + dk * float(np.log(n_eff))
    dchi2 = rss0 - rss1
    # The explained share is judged on the mechanism's own channels (``own``): a fit
    # that spans more stages (with an earlier finding) carries their residuals too.
    chans = [ch for ch in f0.residuals[0] if own is None or ch in own] or list(f0.residuals[0])
    expected = ex0 = ex1 = 0.0
    for ch in chans:
        e = f0.residuals[0][ch] / sigma[ch]
        expected += e.size * float(np.clip(noise_sigma(e), *FLOOR_SCALE)) ** 2
        ex0 += float(f0.channel_rss[ch])
        ex1 += float(f1.channel_rss[ch])
    excess = ex0 - expected
    explained = (ex0 - ex1) / excess if excess > 0 else 0.0
    p = float(chdtrc(max(dk, 1), max(dchi2, 0.0)))  # chi-square survival function
    return {
        "delta_bic": dbic,
        "delta_chi2": dchi2,
        "explained_fraction": explained,
        "lr_p_value": p,
        "score_before": float(np.sqrt(rss0 / n)),
        "score_after": float(np.sqrt(rss1 / n)),
        "n_residuals": float(n),
        "n_effective": float(n_eff),
        "residual_lag1_after": rho,
        "n_params_added": float(dk),
    }


def rho_cap_of(mechanisms: Sequence[AbstractMechanism]) -> float:
    """The cap on the residual's lag-1 correlation in the evidence for adding
    ``mechanisms`` (:func:`bic_evidence`): learned terms alone, which passed held-out
    folds, are judged with the folds' (:data:`~ewb_ident.diagnosis.heldout.RHO_CAP`);
    anything with a catalog mechanism, which has no held-out folds, with ``RHO_MAX``."""
    learned = bool(mechanisms) and all(isinstance(m, LearnedTerm) for m in mechanisms)
    return RHO_CAP if learned else RHO_MAX


def _lag1(f: FitResult, sigma: Mapping[str, np.ndarray]) -> float:
    """Pooled lag-1 autocorrelation of ``f``'s weighted residuals, clipped to
    ``[0, RHO_MAX]``."""
    num = den = 0.0
    for ch, r in f.residuals[0].items():
        e = r / sigma[ch]
        e = e - np.mean(e)
        num += float(np.dot(e[1:], e[:-1]))
        den += float(np.dot(e, e))
    return float(np.clip(num / den, 0.0, RHO_MAX)) if den > 0 else 0.0


def chain_prefixed(ev: Mapping[str, float] | None) -> dict[str, float]:
    """The whole chain's evidence, keys prefixed ``chain_``."""
    keys = ("delta_bic", "delta_chi2", "lr_p_value")
    return {f"chain_{k}": ev[k] for k in keys} if ev else {}


def fitted_mechanism(f: FitResult, variant: str) -> AbstractMechanism:
    return next(m for m in f.mechanisms if m.variant == variant)


def current_demand(trace: Trace, kb: float, R: float) -> float:
    """The largest current the voltage asks for at the recorded speed, A.

    ``(V - kb omega) / R`` with the armature's inductance neglected, its speed from the
    angle smoothed over about 10 ms; the 99.5th percentile of its size, so that a few
    noisy samples do not set it. A trace without a current sensor has no other measure
    of the current a driver may have limited.
    """
    width = max(3, round(X_SMOOTH_S / trace.dt)) | 1
    omega = np.gradient(smooth(trace["theta_deg"], width), trace.dt) * (np.pi / 180.0)
    demand = (trace["voltage_V"] - kb * omega) / R
    return float(np.percentile(np.abs(demand), 99.5))


def stall_torque(trace: Trace, kT: float, R: float) -> float:
    """The motor's stall torque at the trace's largest voltage, N*m."""
    return kT * float(np.max(np.abs(trace["voltage_V"]))) / R


def model_channels(ses, fit) -> dict[str, np.ndarray]:
    """Model series for the inputs of a term fitted with ``fit``: its stages' own
    outputs as it predicts them and the channels that follow from them along the chain
    (the gap curve, the bell, the brake torque of the fit's values), and the motor's
    current where the trace records none. Recorded, these channels would carry the
    mismatch itself: a term could explain the force by the recorded force, or (a
    sensor's term, fitted at the stage it feeds too) by the torque computed from it."""
    from ewb_ident.model.physics import brake_torque, gap

    v = dict(ses.values) | dict(fit.values)
    tr = ses.trace
    law = {  # each static stage's output from its input
        "gap": lambda y: gap(y, v["p2"], v["p1"], v["p0"]),
        "force": lambda y: clamp_force(y, v["F_rt"], v["a"], v["b"], v["c"]),
        "torque": lambda y: brake_torque(y, v["mu"], tr.r_eff_m),
    }
    static = [STAGE[s] for s in TEACHER_FORCED if s in law]
    out: dict[str, np.ndarray] = {}
    if "motor" in fit.stages:
        for ch in STAGE_OUTPUTS["motor"]:
            if ch in fit.predictions[0]:
                out[ch] = np.asarray(fit.predictions[0][ch], float)
    # A teacher-forced stage's prediction carries its measured input's noise, which is
    # in the residual too: the stage is evaluated at the input's level without its noise
    # at each sample, or at the model's where an earlier stage of the fit predicts it.
    for st in static:
        if st.name in fit.stages:
            y = out[st.input] if st.input in out else denoised(tr[st.input], tr.dt)
            out[st.outputs[0]] = np.asarray(law[st.name](y))
    for st in static:  # and what follows along the chain from the model's channels
        if st.input in out and st.outputs[0] not in out:
            out[st.outputs[0]] = np.asarray(law[st.name](out[st.input]))
    mot = ses.base_fits.get("motor")
    if not tr.has("current_A") and "current_A" not in out:
        if mot is not None and "current_A" in mot.predictions[0]:
            out["current_A"] = np.asarray(mot.predictions[0]["current_A"], float)
    return out
