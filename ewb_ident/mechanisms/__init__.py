"""The catalog of brake mechanisms the seed model leaves out.

One interface (:class:`~ewb_ident.mechanisms.base.AbstractMechanism`), one module per
mechanism, and this registry. :data:`CATALOG` maps each catalog id of
``shared/CONTRACTS.md`` to its class; :func:`variants` lists the instances a diagnosis
tries (a sensor mechanism once per channel it can act on).
"""

from __future__ import annotations

from ewb_ident.mechanisms.backlash import Backlash as Backlash
from ewb_ident.mechanisms.base import HOOKS as HOOKS
from ewb_ident.mechanisms.base import AbstractMechanism as AbstractMechanism
from ewb_ident.mechanisms.current_limit import CurrentLimit as CurrentLimit
from ewb_ident.mechanisms.force_hysteresis import ForceHysteresis as ForceHysteresis
from ewb_ident.mechanisms.friction_fade import FrictionFade as FrictionFade
from ewb_ident.mechanisms.friction_speed import FrictionSpeed as FrictionSpeed
from ewb_ident.mechanisms.learned import PLACES
from ewb_ident.mechanisms.sensor_delay import SensorDelay as SensorDelay
from ewb_ident.mechanisms.sensor_offset import SensorOffset as SensorOffset
from ewb_ident.mechanisms.stiction import Stiction as Stiction
from ewb_ident.mechanisms.wedge_load_torque import WedgeLoadTorque as WedgeLoadTorque
from ewb_ident.model.params import ParamInfo

#: Catalog id -> mechanism class.
CATALOG: dict[str, type[AbstractMechanism]] = {
    cls.id: cls
    for cls in (
        Backlash,
        WedgeLoadTorque,
        ForceHysteresis,
        SensorDelay,
        FrictionSpeed,
        FrictionFade,
        SensorOffset,
        CurrentLimit,
        Stiction,
    )
}

#: Channels each sensor mechanism can act on.
SENSOR_CHANNELS: dict[str, tuple[str, ...]] = {
    "sensor_delay": ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A"),
    "sensor_offset": ("force_N", "torque_Nm"),
}


def variants() -> list[AbstractMechanism]:
    """Every mechanism instance a diagnosis can try, with default parameter values."""
    out: list[AbstractMechanism] = []
    for mid, cls in CATALOG.items():
        if mid in SENSOR_CHANNELS:
            out += [cls(channel=ch) for ch in SENSOR_CHANNELS[mid]]
        else:
            out.append(cls())
    return out


def mechanism_param(name: str) -> ParamInfo:
    """The declaration of a mechanism parameter named ``"variant.param"`` (e.g.
    ``"backlash.beta_deg"``, ``"sensor_delay[force_N].delay_s"``), of its catalog form or
    of a flexible form (:meth:`~ewb_ident.mechanisms.base.AbstractMechanism.refinements`).

    A learned term's coefficient (``"learned[force.output].c0"``) is declared in units
    of its size when the term was distilled (1: the distilled term), which is how a
    posterior samples it (its size differs from one diagnosis to the next).

    Raises
    ------
    KeyError
        ``name`` names no parameter of a catalog mechanism variant or learned term.
    """
    variant, _, param = name.rpartition(".")
    if variant.startswith("learned[") and variant[8:-1] in PLACES and param[1:].isdigit():
        doc = "a learned term's coefficient over its size when distilled"
        return ParamInfo(param, "1", "affine", 0.0, scale=1.0, doc=doc)
    for m in variants():
        if m.variant == variant:
            for form in (m, *m.refinements()):
                for info in form.param_info():
                    if info.name == param:
                        return info
    raise KeyError(name)
