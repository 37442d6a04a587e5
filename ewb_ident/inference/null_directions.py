"""Directions the data cannot determine: found from the scaled Jacobian's SVD, held at
documented values with words, never left to the solver."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ewb_ident.inference.problem import build_setup, to_u, usable
from ewb_ident.inference.residuals import evaluate
from ewb_ident.model.params import PARAMS


def hold_one(setup, u, data, st, held, notes, where: str, threshold: float | None = None) -> bool:
    """If the scaled Jacobian at ``u`` has a null direction (a condition number above
    ``threshold``, default :data:`NULL_CONDITION`), hold its dominant parameter at its
    start value (or the base one, if that is unusable), adding it to ``held`` and the
    words to ``notes``; whether one was held."""
    J = np.asarray(evaluate(setup.problem, u, data, predictions=False)[2])
    found = _null_direction(J, setup.problem.shared, threshold or NULL_CONDITION)
    if found is None:
        return False
    name, partners, cond = found
    if "b" in partners and set(partners) <= BELL_SHAPE:
        # The force never shows the bell's top (the piston stops on its flank): hold the
        # exponent at the seed value, the remedy the flank note gives, rather than an
        # edge or centre at a start value that may be far off.
        name, value = "b", float(setup.base.b)
        why = f"b is held at the seed model's {value:.4g}"
    else:
        value = float(st.get(name, getattr(setup.base, name)))
        info = PARAMS[name]
        if not (usable(name, value) and (info.transform == "affine" or info.inside(value))):
            value = float(getattr(setup.base, name))
        why = f"{name} is held at {value:.4g} {info.unit}"
    held[name] = value
    notes.append(
        f"the data cannot tell {', '.join(partners)} apart (condition number {cond:.2g} "
        f"{where}): {why}"
    )
    return True


def hold_flank_exponent(setup, u, data, held, notes) -> bool:
    """After a solve that did not converge: if the piston never passes the bell's centre
    c in any trace at ``u`` and b is free, hold b at the seed value (adding it to
    ``held`` and the words to ``notes``); whether it was held.

    On the rising flank alone a, b and c trade off along a curved valley whose condition
    number can stay under :data:`NULL_CONDITION` while the solver still wanders along it
    (a 100 Hz staircase stopped at its step limit with correlations a-b, a-c, b-c of
    +1.00). Which coordinate to hold is then set by the physics, not by the spectrum.
    """
    if "b" not in setup.problem.shared or setup.stage not in ("chain", "force"):
        return False
    preds = evaluate(setup.problem, u, data)[1]
    reach = []
    for k, (t, pred) in enumerate(zip(setup.traces, preds, strict=True)):
        x = t["x_m"] if t.has("x_m") else pred.get("x_m")
        if x is None:
            return False
        c = float(setup.problem.values(u, data["fixed"] | {"theta0_deg": 0.0}, k)["c"])
        if not float(np.max(np.asarray(x))) < c:
            return False
        reach.append(f"max x = {float(np.max(np.asarray(x))) * 1e3:.3f} mm < c = {c * 1e3:.3f} mm")
    held["b"] = float(setup.base.b)
    notes.append(
        "the solver did not converge and the piston never passes the bell's centre "
        f"({'; '.join(reach)}): the rising flank alone cannot set a, b and c, so b is held "
        f"at the seed model's {setup.base.b:.4g}"
    )
    return True


#: The bell's parameters: a null direction among only these means the force data do not
#: pin the bell's shape (typically an apply that never passes c).
BELL_SHAPE = frozenset({"F_rt", "a", "b", "c"})


def hold_null_directions(setup, st, per_trace, fixed, held, notes, integrator):
    """Hold, one at a time, the dominant parameter of each null direction of the scaled
    Jacobian at the start (adding to ``held`` and ``notes``); the final set-up, start
    vector, data and first weights. Parameters already in ``held`` are held first."""
    for _ in range(len(setup.free) + 1):
        if set(held) & set(setup.free):
            setup = build_setup(
                setup.traces,
                setup.stage,
                [n for n in setup.free if n not in held],
                per_trace,
                fixed | held,
                integrator,
            )
        u0 = to_u(setup.problem, st, setup.base, setup.tdata)
        sigma = setup.sensor_sigma()
        data = setup.data(sigma)
        if not hold_one(setup, u0, data, st, held, notes, "at the start"):
            break
    return setup, u0, data, sigma


#: Above this condition number of the column-scaled Jacobian at the start, a direction
#: is taken as null (structurally unidentified), not merely poorly determined.
NULL_CONDITION = 1.0e4


def _null_direction(
    J: np.ndarray, shared: Sequence[str], threshold: float
) -> tuple[str, list[str], float] | None:
    """The shared parameter to hold when ``J`` (weighted residuals by ``u``) has a null
    direction: the one with the largest weight in the smallest singular vector, with the
    parameters that make up the direction and the condition number."""
    if J.shape[1] < 2 or not np.all(np.isfinite(J)):
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        scale = np.linalg.norm(J, axis=0)
    if not np.all(np.isfinite(scale)):  # a diverging model: nothing to learn here
        return None
    if np.any(scale == 0):  # a parameter the residuals do not depend on at all
        j = int(np.argmin(scale))
        return (shared[j], [shared[j]], float("inf")) if j < len(shared) else None
    _, sv, Vt = np.linalg.svd(np.linalg.qr(J / scale, mode="r"))
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if cond < threshold:
        return None
    w = np.abs(Vt[-1][: len(shared)])
    if w.size == 0 or w.max() == 0:
        return None
    partners = [shared[j] for j in np.argsort(-w) if w[j] > 0.1 * w.max()]
    return shared[int(np.argmax(w))], partners, cond
