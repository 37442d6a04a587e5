"""Priors of the posterior sampler: physical, weakly informative, read from a TOML file.

The defaults live in ``ewb_ident/inference/priors.toml`` (shipped with the package; each entry
says why it is what it is). :func:`load_priors` reads them, and a user's file on top:
a table in the user's file replaces the default table of that parameter.

Every prior is on the parameter's physical value (SI units). The sampler works in the
unconstrained coordinates of :mod:`ewb_ident.model.params` and adds the log-Jacobian of the
transform, so the prior a user writes here is the prior the posterior uses.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import jax.numpy as jnp
import numpy as np

from ewb_ident.data.trace import InputError
from ewb_ident.model.params import PARAMS, ParamInfo

Dist = Literal["normal", "lognormal", "beta", "uniform", "loguniform", "flat"]

#: The keys of each distribution, in the order they are stored in :attr:`Prior.args`.
DIST_KEYS: dict[str, tuple[str, ...]] = {
    "normal": ("mean", "sd"),
    "lognormal": ("median", "sigma_log"),
    "beta": ("alpha", "beta"),
    "uniform": (),
    "loguniform": (),
    "flat": (),
}
#: The support of each distribution before the user's bounds.
_SUPPORT: dict[str, tuple[float, float]] = {
    "normal": (-math.inf, math.inf),
    "lognormal": (0.0, math.inf),
    "beta": (0.0, 1.0),
    "uniform": (-math.inf, math.inf),
    "loguniform": (0.0, math.inf),
    "flat": (-math.inf, math.inf),
}
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


class PriorError(InputError):
    """A prior file or table that cannot be used (the message names file and key)."""


@dataclass(frozen=True)
class Prior:
    """The prior of one parameter, on its physical value (SI units).

    Parameters
    ----------
    name
        Parameter name (as in :data:`ewb_ident.model.params.PARAMS`).
    dist
        Distribution (see ``priors.toml``).
    args
        Its parameters, in the order of :data:`DIST_KEYS`.
    lower, upper
        Hard bounds: zero density outside (the support of ``dist`` included).
    why
        Where the numbers come from.
    """

    name: str
    dist: Dist
    args: tuple[float, ...]
    lower: float = -math.inf
    upper: float = math.inf
    why: str = ""

    def logpdf(self, p, xp=jnp):
        """Log density at ``p`` (up to the normalising constant of the truncation).

        ``xp`` is ``jax.numpy`` (default, traceable) or ``numpy``. ``-inf`` outside
        the bounds.
        """
        inside = (p > self.lower) & (p < self.upper)
        lo, hi = self.lower, self.upper
        mid = 0.5 * (lo + hi) if math.isfinite(lo) and math.isfinite(hi) else 0.5
        q = xp.where(inside, p, mid if self.dist in ("beta", "uniform") else max(lo, 0.0) + 1.0)
        if self.dist == "normal":
            m, s = self.args
            val = -0.5 * ((p - m) / s) ** 2 - math.log(s) - _HALF_LOG_2PI
        elif self.dist == "lognormal":
            m, s = self.args
            z = (xp.log(q) - math.log(m)) / s
            val = -0.5 * z * z - xp.log(q) - math.log(s) - _HALF_LOG_2PI
        elif self.dist == "beta":
            a, b = self.args
            norm = math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
            val = (a - 1.0) * xp.log(q) + (b - 1.0) * xp.log1p(-q) - norm
        elif self.dist == "uniform":
            val = xp.zeros_like(p) - math.log(hi - lo)
        elif self.dist == "loguniform":
            val = -xp.log(q) - math.log(math.log(hi / lo))
        else:
            val = xp.zeros_like(p)
        return xp.where(inside, val, -xp.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray | None:
        """``n`` draws (NumPy), truncated to the bounds; ``None`` for an improper prior."""
        if self.dist == "flat":
            return None
        if self.dist == "uniform":
            return rng.uniform(self.lower, self.upper, n)
        if self.dist == "loguniform":
            return np.exp(rng.uniform(math.log(self.lower), math.log(self.upper), n))
        out: list[np.ndarray] = []
        got = 0
        for _ in range(200):
            if self.dist == "normal":
                x = rng.normal(self.args[0], self.args[1], n)
            elif self.dist == "lognormal":
                x = self.args[0] * np.exp(self.args[1] * rng.standard_normal(n))
            else:
                x = rng.beta(self.args[0], self.args[1], n)
            x = x[(x > self.lower) & (x < self.upper)]
            out.append(x)
            got += x.size
            if got >= n:
                return np.concatenate(out)[:n]
        raise PriorError(f"prior of {self.name!r}: its bounds exclude almost all of its mass")

    def describe(self) -> str:
        """One line, e.g. ``lognormal(median=0.00063, sigma_log=1) on (1e-06, 0.01)``."""
        args = ", ".join(
            f"{k}={v:.4g}" for k, v in zip(DIST_KEYS[self.dist], self.args, strict=True)
        )
        bounds = (
            ""
            if self.lower == -math.inf and self.upper == math.inf
            else (f" on ({self.lower:.4g}, {self.upper:.4g})")
        )
        return f"{self.dist}({args}){bounds}"

    def to_json(self) -> dict[str, Any]:
        """The prior as plain JSON (infinite bounds as ``null``)."""
        doc: dict[str, Any] = {"dist": self.dist}
        doc |= dict(zip(DIST_KEYS[self.dist], self.args, strict=True))
        doc["lower"] = self.lower if math.isfinite(self.lower) else None
        doc["upper"] = self.upper if math.isfinite(self.upper) else None
        doc["why"] = self.why
        return doc


def _number(table: Mapping[str, Any], key: str, where: str) -> float:
    value = table.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PriorError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def parse_prior(name: str, table: Mapping[str, Any], where: str = "priors") -> Prior:
    """Build and check one prior from its TOML table.

    Raises
    ------
    PriorError
        Unknown parameter or distribution, a missing or bad number, empty bounds.
    """
    where = f"{where}: [{name}]"
    try:
        info = param_info(name)
    except KeyError:
        raise PriorError(
            f"{where}: unknown parameter; the parameters are {', '.join(PARAMS)} and the "
            'catalog mechanisms\' as "variant.param" (e.g. "backlash.beta_deg")'
        ) from None
    if not isinstance(table, Mapping):
        raise PriorError(f"{where}: must be a table with 'dist' and its numbers")
    dist = table.get("dist")
    if dist not in DIST_KEYS:
        raise PriorError(f"{where}: 'dist' must be one of {', '.join(DIST_KEYS)}, got {dist!r}")
    known = set(DIST_KEYS[dist]) | {"dist", "lower", "upper", "why"}
    extra = sorted(set(table) - known)
    if extra:
        raise PriorError(
            f"{where}: unknown key(s) {extra} for dist {dist!r}; it takes {sorted(known)}"
        )
    args = tuple(_number(table, k, where) for k in DIST_KEYS[dist])
    lo, hi = _SUPPORT[dist]
    if "lower" in table:
        lo = max(lo, _number(table, "lower", where))
    elif dist in ("uniform", "loguniform"):
        raise PriorError(f"{where}: {dist} needs 'lower' and 'upper'")
    if "upper" in table:
        hi = min(hi, _number(table, "upper", where))
    elif dist in ("uniform", "loguniform"):
        raise PriorError(f"{where}: {dist} needs 'lower' and 'upper'")
    if not lo < hi:
        raise PriorError(f"{where}: the bounds are empty (lower {lo!r} >= upper {hi!r})")
    if dist in ("normal", "lognormal") and args[1] <= 0:
        raise PriorError(f"{where}: '{DIST_KEYS[dist][1]}' must be > 0, got {args[1]!r}")
    if dist == "lognormal" and args[0] <= 0:
        raise PriorError(f"{where}: 'median' must be > 0, got {args[0]!r}")
    if dist == "beta" and min(args) <= 0:
        raise PriorError(f"{where}: 'alpha' and 'beta' must be > 0, got {args}")
    if dist == "loguniform" and lo <= 0:
        raise PriorError(f"{where}: loguniform needs lower > 0, got {lo!r}")
    if info.transform == "log" and lo < 0:
        lo = 0.0  # a log-transformed parameter is positive whatever the table says
    if info.transform == "logit":
        lo, hi = max(lo, info.lower), min(hi, info.upper)
    why = table.get("why", "")
    if not isinstance(why, str):
        raise PriorError(f"{where}: 'why' must be text")
    return Prior(name=name, dist=dist, args=args, lower=lo, upper=hi, why=why)


def param_info(name: str) -> ParamInfo:
    """The declaration of a model parameter or of a mechanism's (``"variant.param"``).

    Raises
    ------
    KeyError
        Neither.
    """
    if name in PARAMS:
        return PARAMS[name]
    from ewb_ident.mechanisms import mechanism_param

    return mechanism_param(name)


#: A learned term's coefficient: normal about zero, this many times its distilled size.
LEARNED_PRIOR_SDS = 10.0


def mechanism_prior(name: str) -> Prior:
    """The default prior of a mechanism parameter: uniform over its declared range
    (log-uniform for a positive, log-scaled one), the range the diagnosis fits it in.
    A learned term's coefficient has no physical range; it is sampled in units of its
    distilled size (:func:`ewb_ident.mechanisms.mechanism_param`): a normal about zero
    with sd :data:`LEARNED_PRIOR_SDS`, so it hardly constrains what the data determine."""
    info = param_info(name)
    if info.transform == "affine" and not np.isfinite(info.lower):
        why = f"a learned coefficient: normal, {LEARNED_PRIOR_SDS:g}x its distilled size"
        table = {"dist": "normal", "mean": 0.0, "sd": LEARNED_PRIOR_SDS * info.scale, "why": why}
        return parse_prior(name, table, "learned term")
    dist = "loguniform" if info.transform == "log" else "uniform"
    table = {"dist": dist, "lower": float(info.lower), "upper": float(info.upper)}
    table["why"] = f"the catalog's range of {info.doc or name}"
    return parse_prior(name, table, "mechanism defaults")


def _read_toml(text: str, where: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise PriorError(
            f"{where}: not valid TOML ({err}); see ewb_ident/inference/priors.toml"
        ) from err


def default_prior_text() -> str:
    """The text of the default prior file (to copy and edit)."""
    folder = resources.files("ewb_ident.inference")
    return folder.joinpath("priors.toml").read_text(encoding="utf-8")


def load_priors(path: str | Path | Mapping[str, Any] | None = None) -> dict[str, Prior]:
    """The priors of every parameter: the defaults, with the user's tables on top.

    Parameters
    ----------
    path
        A TOML file, or a mapping ``{name: table}`` already parsed, or ``None`` for the
        defaults only.

    Raises
    ------
    PriorError
        The file is missing, not TOML, or a table is wrong (the message says which).
    """
    tables = _read_toml(default_prior_text(), "ewb_ident/inference/priors.toml")
    out = {n: parse_prior(n, t, "ewb_ident/inference/priors.toml") for n, t in tables.items()}
    if path is None:
        return out
    if isinstance(path, Mapping):
        user, where = dict(path), "priors"
    else:
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as err:
            raise PriorError(f"{p}: cannot read the prior file ({err.strerror})") from err
        user, where = _read_toml(text, str(p)), str(p)
    for name, table in user.items():
        out[name] = parse_prior(name, table, where)
    return out
