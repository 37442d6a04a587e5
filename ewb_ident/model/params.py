"""Model parameters: the immutable parameter pytree, and how each parameter is fitted.

:class:`EWBParams` holds the physical parameters of the whole chain in SI units
(angles of the gap polynomial in degrees). :data:`PARAMS` declares, for every parameter
a fit may vary, its unit, bounds and the transform that maps it to an unconstrained,
O(1) coordinate ``u`` used by the optimiser and the sampler:

- ``log``:   ``p = ref * exp(u)``             (positive parameters)
- ``logit``: ``p = lo + (hi - lo) * sigmoid(u)`` (bounded parameters, e.g. mu in (0, 1))
- ``affine``: ``p = ref + scale * u``          (signed parameters, e.g. the gap polynomial)

The seed paper's Table 2 prints the bell exponent as ``b = 2.820e-4 m``. ``b`` is a
dimensionless exponent; with 2.820e-4 the bell is flat at F_rt/2 = 1750 N for every
displacement, which contradicts the paper's own force traces. We use ``b = 2.82``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

Transform = Literal["log", "logit", "affine"]


class EWBParams(eqx.Module):
    """Physical parameters of the EWB rig model (an immutable pytree).

    ``EWBParams(R=..., a=..., ...)`` takes each as a keyword; the defaults are
    :data:`SEED`'s.

    Attributes
    ----------
    R
        Armature resistance, ohm.
    L
        Armature inductance, H.
    kb
        Back-EMF constant, V*s/rad.
    kT
        Torque constant, N*m/A.
    M
        Rotor + pinion inertia, kg*m^2.
    v
        Viscous friction coefficient, N*m*s/rad.
    p2, p1, p0
        Gap polynomial ``x = p2*theta^2 + p1*theta + p0``; theta in degrees, x in m
        (so p2 in m/deg^2, p1 in m/deg, p0 in m).
    F_rt
        Rated (maximum) clamping force of the bell curve, N.
    a
        Bell half-width, m.
    b
        Bell slope exponent, dimensionless (seed: 2.82; see module docstring).
    c
        Bell centre: the piston displacement of full clamping, m.
    mu
        Pad friction coefficient, dimensionless.
    """

    R: ArrayLike = 1.0
    L: ArrayLike = 2.0e-3
    kb: ArrayLike = 0.1
    kT: ArrayLike = 0.1
    M: ArrayLike = 2.0e-4
    v: ArrayLike = 2.0e-3
    p2: ArrayLike = 3.8e-9
    p1: ArrayLike = 1.5e-6
    p0: ArrayLike = -8.4e-4
    F_rt: ArrayLike = 3500.0
    a: ArrayLike = 6.295e-4
    b: ArrayLike = 2.82
    c: ArrayLike = 9.57e-4
    mu: ArrayLike = 0.35

    def replace(self, **values: ArrayLike) -> EWBParams:
        """A copy with some parameters replaced (SI units)."""
        return dataclasses.replace(self, **values)

    def as_dict(self) -> dict[str, float]:
        """The parameters as plain floats, keyed by name."""
        return {f.name: float(getattr(self, f.name)) for f in dataclasses.fields(self)}


#: Names of the physical parameters, in :class:`EWBParams` order.
MODEL_PARAMS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(EWBParams))

#: The seed paper's values (Table 2, with b read as dimensionless; motor values are this
#: tool's nominal rig, the brief gives none).
SEED = EWBParams()


@dataclass(frozen=True)
class ParamInfo:
    """How one parameter is declared, bounded and scaled for fitting.

    Parameters
    ----------
    name
        Parameter name (as in :class:`EWBParams`, or ``theta0_deg``).
    unit
        SI unit, as text.
    transform
        ``log``, ``logit`` or ``affine`` (see module docstring).
    ref
        Reference value: ``u = 0`` maps to it (log, affine).
    scale
        Affine scale: one unit of ``u`` in the parameter's unit.
    lower, upper
        Physical bounds; hard bounds for ``logit``, plausibility bounds otherwise.
    doc
        One line saying what the parameter is.
    """

    name: str
    unit: str
    transform: Transform
    ref: float
    scale: float = 1.0
    lower: float = -jnp.inf
    upper: float = jnp.inf
    doc: str = ""

    def to_physical(self, u: ArrayLike) -> jnp.ndarray:
        """Map the unconstrained coordinate ``u`` to the parameter value (SI)."""
        xp = jnp if isinstance(u, jax.Array) else np  # plain numbers stay in NumPy
        if self.transform == "log":
            return self.ref * xp.exp(u)
        if self.transform == "logit":
            return self.lower + (self.upper - self.lower) / (1.0 + xp.exp(-u))
        return self.ref + self.scale * u

    def to_unconstrained(self, p: ArrayLike) -> jnp.ndarray:
        """Map a parameter value (SI) to ``u``; the inverse of :meth:`to_physical`."""
        xp = jnp if isinstance(p, jax.Array) else np  # plain numbers stay in NumPy
        p = xp.asarray(p, dtype=float)
        if self.transform == "log":
            return xp.log(p / self.ref)
        if self.transform == "logit":
            s = (p - self.lower) / (self.upper - self.lower)
            return xp.log(s) - xp.log1p(-s)
        return (p - self.ref) / self.scale

    def dp_du(self, u: ArrayLike) -> jnp.ndarray:
        """Derivative of the parameter value with respect to ``u`` (for the delta method)."""
        xp = jnp if isinstance(u, jax.Array) else np
        if self.transform == "log":
            return self.ref * xp.exp(u)
        if self.transform == "logit":
            s = 1.0 / (1.0 + xp.exp(-u))
            return (self.upper - self.lower) * s * (1.0 - s)
        return xp.asarray(self.scale)

    def inside(self, p: float) -> bool:
        """Whether ``p`` lies strictly inside the parameter's bounds."""
        return bool(self.lower < p < self.upper)


#: Declarations of every parameter a fit can vary, keyed by name.
PARAMS: dict[str, ParamInfo] = {
    p.name: p
    for p in (
        ParamInfo("R", "ohm", "log", 1.0, lower=0.0, doc="armature resistance"),
        ParamInfo("L", "H", "log", 2.0e-3, lower=0.0, doc="armature inductance"),
        ParamInfo("kb", "V*s/rad", "log", 0.1, lower=0.0, doc="back-EMF constant"),
        ParamInfo("kT", "N*m/A", "log", 0.1, lower=0.0, doc="torque constant"),
        ParamInfo("M", "kg*m^2", "log", 2.0e-4, lower=0.0, doc="rotor and pinion inertia"),
        ParamInfo("v", "N*m*s/rad", "log", 2.0e-3, lower=0.0, doc="viscous friction"),
        ParamInfo("p2", "m/deg^2", "affine", 3.8e-9, scale=1e-10, doc="gap polynomial, quadratic"),
        ParamInfo("p1", "m/deg", "affine", 1.5e-6, scale=1e-7, doc="gap polynomial, linear"),
        ParamInfo("p0", "m", "affine", -8.4e-4, scale=1e-5, doc="gap polynomial, offset"),
        ParamInfo("F_rt", "N", "log", 3500.0, lower=0.0, doc="rated clamping force"),
        ParamInfo("a", "m", "log", 6.295e-4, lower=0.0, upper=1e-2, doc="bell half-width"),
        ParamInfo("b", "1", "log", 2.82, lower=0.0, upper=50.0, doc="bell slope exponent"),
        ParamInfo("c", "m", "affine", 9.57e-4, scale=1e-4, doc="bell centre (full clamping)"),
        ParamInfo("mu", "1", "logit", 0.35, lower=0.0, upper=1.0, doc="pad friction coefficient"),
        ParamInfo("theta0_deg", "deg", "affine", 0.0, scale=1.0, doc="pinion angle at t0"),
    )
}

