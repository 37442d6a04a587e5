"""The residuals of a fit: their weights, and the one compiled program of the seed
model's residuals and Jacobian.

A teacher-forced stage reads its input as measured, so its residual also carries the
input's noise through the stage; :func:`carried_noise` is that part, at the values being
fitted, and :func:`effective_weight` the weight it leaves a residual (effective variance,
see ``docs/least-squares.md``). :func:`fit_program` evaluates the seed model for the chain
and every teacher-forced stage alike, the choice made by data, so one compiled program
serves every seed fit of traces of the same padded lengths.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.metrics import noise_sigma
from ewb_ident.data.stages import CHANNELS, STAGE_COLUMNS
from ewb_ident.data.trace import Trace
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, EWBParams
from ewb_ident.model.predict import predict
from ewb_ident.runtime.programs import on_device, pad_to, padded_length, program

if TYPE_CHECKING:
    from ewb_ident.inference.problem import Problem

#: The coordinates of the compiled fit program, per trace: every model parameter and
#: the start angle (unconstrained, as in :data:`ewb_ident.model.params.PARAMS`).
Z_NAMES: tuple[str, ...] = (*MODEL_PARAMS, "theta0_deg")
#: Columns the program reads (an absent one is zeros, weighted zero).
PROGRAM_COLUMNS: tuple[str, ...] = ("voltage_V", *CHANNELS)
#: The channel each teacher-forced stage predicts from its measured input.
FORCED_CHANNEL: dict[str, str] = {"gap": "x_m", "force": "force_N", "torque": "torque_Nm"}
#: The measured input of the teacher-forced stage that predicts each channel.
FORCED_INPUT: dict[str, str] = {STAGE_COLUMNS[s][1]: STAGE_COLUMNS[s][0] for s in FORCED_CHANNEL}


def input_noise(trace: Trace, ch: str) -> float:
    """The white-noise level of the measured input of the teacher-forced stage that
    predicts ``ch`` (:func:`~ewb_ident.data.metrics.noise_sigma`, in the input's unit; 0
    when the trace does not record it)."""
    inp = FORCED_INPUT[ch]
    return float(noise_sigma(trace[inp])) if trace.has(inp) else 0.0


def carried_noise(
    p: EWBParams,
    theta0_deg: Any,
    terms: Sequence[Any],
    d: Mapping[str, Any],
    carry: Mapping[str, Any],
    stages: Sequence[str],
    n_sub: int,
    method: str,
) -> dict[str, jnp.ndarray]:
    """Noise of each teacher-forced stage's measured input carried to its output, per
    sample: half the change of the stage's prediction when its input moves by
    ``± sigma_in`` (``|df/din| sigma_in``, the terms acting there included).

    A least-squares fit that weighs the residual of ``y = f(x_meas)`` by the output's
    noise alone is biased towards flatter laws wherever the input is noisy: flattening
    ``f`` shrinks the carried noise ``f' sigma_x`` in the residual (errors in
    variables). Weighing by ``sqrt(sigma_y^2 + (f' sigma_x)^2)`` with ``f'`` at the
    values being fitted (effective variance) removes that pull. (Found on clean
    widened-study traces with 1.4x the usual noise: the force stage's fit put ``F_rt``
    at 2270 N for a true 3430 N and left a structured residual that located a
    mismatch.) A difference, not a derivative: the derivative of the bell's slope is
    not finite where the displacement equals ``c``.

    Parameters
    ----------
    p, theta0_deg, terms
        Base parameters (SI), start angle (degrees) and terms (mechanism instances).
    d
        Data as :func:`ewb_ident.model.predict.predict` reads them.
    carry
        Per predicted channel (:data:`FORCED_INPUT`), its input's noise level, in the
        input's unit (0: nothing carried).
    stages
        The stages fitted: only the teacher-forced among them carry noise.
    n_sub, method
        As for :func:`ewb_ident.model.predict.predict`.
    """
    forced = tuple(s for s in stages if s in FORCED_CHANNEL)
    if not forced:
        return {}
    meas = d["meas"]

    def moved(sign: float) -> dict[str, jnp.ndarray]:
        shift = dict(meas)
        for s in forced:
            out = FORCED_CHANNEL[s]
            if FORCED_INPUT[out] in meas:
                shift[FORCED_INPUT[out]] = meas[FORCED_INPUT[out]] + sign * carry[out]
        return predict(forced, p, theta0_deg, terms, dict(d) | {"meas": shift}, n_sub, method)

    up, down = moved(1.0), moved(-1.0)
    return {ch: 0.5 * jnp.abs(up[ch] - down[ch]) for ch in up if ch in carry}


def effective_weight(w, carried=None):
    """The weight ``w = 1 / sigma`` of a residual, lowered to ``1 / sqrt(sigma^2 +
    carried^2)`` where a measured input's noise is ``carried`` (:func:`carried_noise`);
    0 where ``w`` is 0 (a channel not fitted, a padded sample)."""
    if carried is None:
        return w
    return jnp.where(w > 0, w / jnp.sqrt(1.0 + (w * carried) ** 2), 0.0)


def seed_predictions(p: EWBParams, theta0_deg, d: dict, n_sub: int, method: str) -> dict:
    """Every channel of the seed model from the voltage (the whole chain), except that a
    stage whose ``d["forced"][output]`` is 1 reads its measured input instead
    (teacher-forced): the gap the measured angle, the bell the measured displacement,
    the torque the measured force.

    One function for every stage, so that a single compiled program serves the chain,
    the stage fits of its start, and the stage commands: the one evaluator,
    :func:`ewb_ident.model.predict.predict` of ``"chain"`` without mechanisms, the
    choice of input made by data (``tests/test_fit.py`` checks that it agrees with the
    teacher-forced stages).
    """
    return predict("chain", p, theta0_deg, (), d, n_sub, method)


@program
def fit_program(n_sub: tuple[int, ...], method: str, Z, traces):
    """Per trace ``k``: weighted residuals of every channel, shape (channels, samples),
    their Jacobian with respect to ``Z[k]`` (forward mode), and the predictions.

    ``Z[k]`` holds the :data:`Z_NAMES` coordinates; where ``traces[k]["free"]`` is 0 the
    parameter takes its value from ``traces[k]["fixed"]`` (SI) instead. Which
    parameters are free, which channels are fitted (a weight of 0 drops a channel or a
    padded sample) and which stages are teacher-forced are all data, so one program
    serves every fit of traces of these padded lengths.
    """
    out = []
    for k, d in enumerate(traces):

        def residuals(z, d=d, k=k):
            vals = {
                n: jnp.where(d["free"][j] > 0, PARAMS[n].to_physical(z[j]), d["fixed"][j])
                for j, n in enumerate(Z_NAMES)
            }
            p = EWBParams(**{n: vals[n] for n in MODEL_PARAMS})
            pred = seed_predictions(p, vals["theta0_deg"], d, n_sub[k], method)
            carry = {ch: d["carry"][ch] * d["forced"][ch] for ch in FORCED_INPUT}
            carried = carried_noise(
                p, vals["theta0_deg"], (), d, carry, tuple(FORCED_CHANNEL), n_sub[k], method
            )
            r = jnp.stack(
                [
                    jnp.where(
                        d["w"][ch] > 0,
                        (pred[ch] - d["meas"][ch]) * effective_weight(d["w"][ch], carried.get(ch)),
                        0.0,
                    )
                    for ch in CHANNELS
                ]
            )
            return r, (r, pred)

        J, (r, pred) = jax.jacfwd(residuals, has_aux=True)(Z[k])
        out.append((r, J, pred))
    return out


def program_data(problem: Problem, tdata: Sequence[dict], sigma, base: dict) -> list[dict]:
    """What :func:`fit_program` reads of each trace, padded to
    :func:`~ewb_ident.runtime.programs.padded_length`: the columns, the weights of the
    fitted channels, the teacher-forcing flags, the fixed values and the free mask."""
    out = []
    forced_ch = FORCED_CHANNEL.get(problem.stages[0])
    for k, (d, s) in enumerate(zip(tdata, sigma, strict=True)):
        n = _length(d)
        n_pad = padded_length(n)
        meas = {
            c: pad_to(np.asarray(d[c], float), n_pad) if c in d else np.zeros(n_pad)
            for c in PROGRAM_COLUMNS
        }
        w = {}
        for ch in CHANNELS:
            wk = np.zeros(n_pad)
            if ch in problem.channels[k]:
                wk[:n] = 1.0 / float(s[ch])
            w[ch] = wk
        free = set(problem.shared) | set(problem.per_trace)
        fixed = dict(base) | {"theta0_deg": float(d["theta0_deg"])}
        carry = d.get("carry", {})
        out.append(
            {
                "meas": meas,
                "w": w,
                "forced": {c: np.asarray(float(c == forced_ch)) for c in FORCED_CHANNEL.values()},
                "carry": {c: np.asarray(float(carry.get(c, 0.0))) for c in FORCED_INPUT},
                "dt": np.asarray(float(d["dt"])),
                "r_eff": np.asarray(float(d["r_eff_m"])),
                "fixed": np.array([float(fixed[n]) for n in Z_NAMES]),
                "free": np.array([float(n in free) for n in Z_NAMES]),
            }
        )
    return on_device(out)  # once, not at every call of the program


def _length(d: dict) -> int:
    """Samples of a trace's data (the length of its first column)."""
    return next(int(np.asarray(v).shape[0]) for c, v in d.items() if c in PROGRAM_COLUMNS)


def _columns(problem: Problem, n_traces: int) -> np.ndarray:
    """For each trace and each :data:`Z_NAMES` coordinate, its index in ``u`` (-1:
    fixed), shape (traces, coordinates)."""
    cols = np.full((n_traces, len(Z_NAMES)), -1)
    for k in range(n_traces):
        for i, name in enumerate(problem.shared):
            cols[k, Z_NAMES.index(name)] = i
        offset = len(problem.shared) + k * len(problem.per_trace)
        for i, name in enumerate(problem.per_trace):
            cols[k, Z_NAMES.index(name)] = offset + i
    return cols


def evaluate(problem: Problem, u, data: dict, predictions: bool = True):
    """Weighted residuals (fitted channels, trace by trace), the predictions of every
    channel per trace (``None`` unless ``predictions``), and the Jacobian with respect
    to ``u``, at ``u``.

    One compiled program (:func:`fit_program`) per set of padded trace lengths serves
    every stage, free set and weighting: a fit, its start's stage fits and its
    null-direction checks compile nothing after the first.
    """
    u = np.asarray(u, float)
    pdata = data["program"]
    cols = _columns(problem, len(pdata))
    Z = np.where(cols >= 0, u[np.maximum(cols, 0)] if u.size else 0.0, 0.0)
    outs = fit_program(problem.n_sub, problem.method, Z, pdata)
    rs, Js, preds = [], [], []
    for k, (r, J, pred) in enumerate(outs):
        n = _length(data["traces"][k])
        rows = [CHANNELS.index(ch) for ch in problem.channels[k]]
        r = np.asarray(r)[rows, :n].reshape(-1)
        J = np.asarray(J)[rows, :n].reshape(-1, len(Z_NAMES))
        Ju = np.zeros((r.size, u.size))
        free = cols[k] >= 0
        Ju[:, cols[k][free]] = J[:, free]
        rs.append(r)
        Js.append(Ju)
        if predictions:
            preds.append({ch: np.asarray(v)[:n] for ch, v in pred.items()})
    return np.concatenate(rs), preds if predictions else None, np.concatenate(Js)
