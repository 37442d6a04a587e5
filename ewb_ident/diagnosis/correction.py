"""A generic, regularised correction for physics the catalog does not hold.

When a located mismatch is not explained by any catalog mechanism, the stage gets a
sparse correction built from a library of candidate terms (:data:`FEATURES`), as in
sparse regression of dynamics (SINDy): an additive correction of the stage's output
(gap, force, torque), or a load torque inside the motor integration (motor). Terms
enter one at a time, each the one that lowers the residual most, while it improves the
Bayesian information criterion by at least the selection threshold (a linearised
search around the current fit, with the stage's own parameters refitted alongside);
the chosen terms are then fitted by nonlinear least squares. What the correction
depends on is read off the chosen terms.

Every term is scaled to about unit size over the trace, so its coefficient is in the
output channel's unit (N*m of load torque for the motor).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ewb_ident.mechanisms.base import AbstractMechanism
from ewb_ident.model.params import ParamInfo

#: Library terms per stage: name -> words.
FEATURES: dict[str, dict[str, str]] = {
    "motor": {
        "coulomb": "a constant friction torque opposing motion",
        "viscous": "a torque proportional to motor speed",
        "force_friction": "a friction torque proportional to the clamping force",
        "force_push": "a torque proportional to the clamping force, pushing back",
        "constant": "a constant torque",
        "spring": "a torque proportional to the pinion angle (a return spring)",
        "pinion_sin": "a torque varying once per pinion revolution",
        "pinion_cos": "a torque varying once per pinion revolution",
    },
    "gap": {
        "theta_cubed": "a cubic term in the pinion angle (gap curve shape)",
        "direction": "the direction of motion",
        "rate": "the speed of motion (a lag)",
        "pinion_sin": "the pinion angle, once per revolution (gear eccentricity)",
        "pinion_cos": "the pinion angle, once per revolution (gear eccentricity)",
        "time": "elapsed time (drift)",
    },
    "force": {
        "offset": "a constant offset",
        "direction": "the direction of motion, in proportion to force",
        "rate": "the speed of motion, in proportion to force",
        "force_squared": "the square of the force (a nonlinear force sensor or stiffness)",
        "time": "elapsed time, in proportion to force (creep or drift)",
        "damping": "the speed of motion at any force (damping)",
    },
    "torque": {
        "offset": "a constant offset",
        "time": "elapsed time, in proportion to force",
        "energy": "dissipated energy, in proportion to force",
        "disc_speed": "disc speed, in proportion to force",
        "force_squared": "the square of the clamping force",
        "disc_sin": "the disc angle, once per revolution (runout or thickness variation)",
        "disc_cos": "the disc angle, once per revolution (runout or thickness variation)",
        "disc2_sin": "the disc angle, twice per revolution",
        "disc2_cos": "the disc angle, twice per revolution",
        "direction": "the direction of motion, in proportion to force",
    },
}
#: Coefficient scale (one unit of the optimiser's coordinate) per stage.
_SCALE = {"motor": 0.01, "gap": 1e-6, "force": 10.0, "torque": 1.0}
_UNIT = {"motor": "N*m", "gap": "m", "force": "N", "torque": "N*m"}


def signals(trace, labels=None) -> dict[str, np.ndarray]:
    """Data-derived signals the library terms use (unit size, NumPy arrays)."""
    from ewb_ident.diagnosis.locate import disc_angle, motion_rate

    n = trace.n
    t = trace.time_s - trace.time_s[0]
    v = motion_rate(trace)
    vmax = float(np.max(np.abs(v))) or 1.0
    out = {
        "time": t / max(float(t[-1]), 1e-9),
        "rate": v / vmax,
        "direction": np.tanh(v / (0.05 * vmax)),
    }
    phi = disc_angle(trace)
    if phi is not None:
        out |= {
            "disc_sin": np.sin(phi),
            "disc_cos": np.cos(phi),
            "disc2_sin": np.sin(2 * phi),
            "disc2_cos": np.cos(2 * phi),
        }
        w = trace["disc_speed_rad_s"]
        span = float(np.max(w) - np.min(w))
        out["disc_speed"] = (w - float(np.mean(w))) / (span if span > 0 else 1.0)
        if trace.has("torque_Nm"):
            e = np.concatenate([[0.0], np.cumsum(trace["torque_Nm"][:-1] * w[:-1])]) * trace.dt
            out["energy"] = e / (float(np.max(np.abs(e))) or 1.0)
    return {k: np.asarray(val, float)[:n] for k, val in out.items()}


def scales(trace) -> dict[str, float]:
    """Sizes that make the library terms unit-sized."""
    out = {}
    for ch in ("force_N", "theta_deg", "torque_Nm"):
        if trace.has(ch):
            out[ch] = float(np.max(np.abs(trace[ch]))) or 1.0
    if trace.has("theta_deg"):
        rate = np.gradient(trace["theta_deg"], trace.dt) / (180 / np.pi)
        out["omega"] = float(np.percentile(np.abs(rate), 99)) or 1.0
    return out


class GenericCorrection(AbstractMechanism):
    """Sparse correction of one stage: coefficients of the chosen library terms."""

    id: ClassVar[str] = "generic_correction"
    physics: ClassVar[str] = "physics not in the catalog"

    stage_name: str = eqx.field(static=True, default="force")
    features: tuple[str, ...] = eqx.field(static=True, default=())
    coef: Any = None

    def __check_init__(self):
        if self.stage_name not in FEATURES:
            raise ValueError(f"generic correction: unknown stage {self.stage_name!r}")
        bad = [f for f in self.features if f not in FEATURES[self.stage_name]]
        if bad:
            raise ValueError(f"generic correction: unknown terms {bad} for {self.stage_name}")

    @property
    def stage(self) -> str:
        return self.stage_name

    @property
    def hook(self) -> str:  # type: ignore[override]
        return "load_torque" if self.stage_name == "motor" else "output"

    @property
    def variant(self) -> str:
        return f"unexplained_{self.stage_name}"

    def param_info(self) -> tuple[ParamInfo, ...]:
        return tuple(
            ParamInfo(
                f"c_{f}", _UNIT[self.stage_name], "affine", 0.0, scale=_SCALE[self.stage_name]
            )
            for f in self.features
        )

    def _coef(self) -> jnp.ndarray:
        if self.coef is None:
            return jnp.zeros(len(self.features))
        return jnp.asarray(self.coef)

    def values(self) -> dict[str, float]:
        c = np.asarray(self._coef(), dtype=float)
        return {f"c_{f}": float(v) for f, v in zip(self.features, c, strict=True)}

    def with_values(self, values: Mapping[str, Any]) -> GenericCorrection:
        cur = dict(zip([f"c_{f}" for f in self.features], list(self._coef()), strict=True))
        cur |= dict(values)
        coef = (
            jnp.stack([jnp.asarray(cur[f"c_{f}"], dtype=float) for f in self.features])
            if (self.features)
            else jnp.zeros(0)
        )
        return GenericCorrection(stage_name=self.stage_name, features=self.features, coef=coef)

    def static_config(self) -> tuple[tuple[str, Any], ...]:
        return (("stage_name", self.stage_name), ("features", self.features))

    def starts(self, ctx) -> list[dict[str, float]]:
        return []

    # -- the terms

    def _terms(self, sig: Mapping[str, Any]) -> list[jnp.ndarray]:
        return [_term(self.stage_name, f, sig) for f in self.features]

    def load_torque(self, s, p, force):
        terms = [_motor_term(f, s, force) for f in self.features]
        if not terms:
            return jnp.zeros_like(s[1])
        return jnp.sum(self._coef() * jnp.stack(terms))

    def correction(self, sig):
        terms = self._terms(sig)
        if not terms:
            return jnp.zeros_like(sig["y"])
        return jnp.tensordot(self._coef(), jnp.stack(terms), axes=1)


#: Nominal sizes of the motor terms (speed, rad/s; force, N; angle, rad): the terms are
#: unit-sized on a rig like the seed's; the fit does not depend on them otherwise.
_MOTOR_SCALES = (30.0, 3500.0, 500.0 * np.pi / 180)


def _motor_term(name: str, s, force) -> jnp.ndarray:
    w = s[1]
    ws, fs, ts = _MOTOR_SCALES
    smooth_sign = jnp.tanh(w / (0.02 * ws))
    return {
        "coulomb": smooth_sign,
        "viscous": w / ws,
        "force_friction": force / fs * smooth_sign,
        "force_push": force / fs,
        "constant": jnp.ones_like(w),
        "spring": s[2] / ts,
        "pinion_sin": jnp.sin(s[2]),
        "pinion_cos": jnp.cos(s[2]),
    }[name]


def _term(stage: str, name: str, sig: Mapping[str, Any]) -> jnp.ndarray:
    d = sig["data_signals"]
    sc = sig["scales"]
    if stage == "gap":
        th = sig["theta"]
        if name == "theta_cubed":
            return (th / sc["theta_deg"]) ** 3
        if name in ("pinion_sin", "pinion_cos"):
            f = jnp.sin if name == "pinion_sin" else jnp.cos
            return f(th * np.pi / 180)
        return d[name]
    if stage == "force":
        fb = sig["f_bell"] / sc["force_N"]
        if name == "offset":
            return jnp.ones_like(fb)
        if name == "force_squared":
            return fb * fb
        if name == "damping":
            return d["rate"]
        return fb * d[name]
    fr = sig["force"] / sc["force_N"]
    if name == "offset":
        return jnp.ones_like(fr)
    if name == "force_squared":
        return fr * fr
    return fr * d[name]


def available_features(stage: str, sig: Mapping[str, np.ndarray]) -> tuple[str, ...]:
    """The library terms a trace's columns support at ``stage``."""
    out = []
    for f in FEATURES[stage]:
        if stage == "torque" and f not in ("offset", "force_squared") and f not in sig:
            continue
        if stage in ("gap", "force") and f in ("direction", "rate", "time") and f not in sig:
            continue
        out.append(f)
    return tuple(out)


@dataclass(frozen=True)
class Selection:
    """Terms chosen by the linearised forward search, with the RSS after each."""

    features: tuple[str, ...]
    rss_path: tuple[float, ...]
    delta_bic_path: tuple[float, ...]


def forward_select(
    r: np.ndarray,
    J_base: np.ndarray,
    J_terms: np.ndarray,
    names: Sequence[str],
    *,
    threshold: float,
    max_terms: int = 4,
) -> Selection:
    """Greedy forward selection of library terms on a linearised problem.

    ``r`` are the weighted residuals of the current fit, ``J_base`` the Jacobian of the
    stage's own parameters (always refitted), ``J_terms`` that of each term. A term
    enters while the profiled-variance BIC improves by at least ``threshold``.
    """
    n = r.size

    def rss(cols):
        A = np.concatenate([J_base, J_terms[:, cols]], axis=1) if cols else J_base
        if A.shape[1] == 0:
            return float(r @ r)
        coef, *_ = np.linalg.lstsq(A, r, rcond=None)
        res = r - A @ coef
        return float(res @ res)

    chosen: list[int] = []
    current = rss([])
    path, bics = [current], [0.0]
    for _ in range(max_terms):
        best = None
        for j in range(J_terms.shape[1]):
            if j in chosen:
                continue
            val = rss(chosen + [j])
            if best is None or val < best[1]:
                best = (j, val)
        if best is None:
            break
        dbic = n * np.log(max(best[1], 1e-300) / current) + np.log(n)
        if dbic > -threshold:
            break
        chosen.append(best[0])
        current = best[1]
        path.append(current)
        bics.append(float(dbic))
    return Selection(tuple(names[j] for j in chosen), tuple(path), tuple(bics))


def with_signals(data: Mapping[str, Any], trace) -> dict[str, Any]:
    """``data`` with the library's signals and scales added (padded like the data)."""
    from ewb_ident.model.programs import on_device, pad_to

    n_pad = int(np.asarray(data["t"]).shape[0])
    sig = on_device({k: pad_to(v, n_pad) for k, v in signals(trace).items()})
    sc = on_device(dict(scales(trace)))
    return dict(data) | {"signals": sig, "scales": sc}
