"""The evaluator's insertion points: every place where physics can enter the chain is
reached, by each hook named there, by a mechanism or learned term that acts there, and
changes the chain from that place on, not before it."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from ewb_ident import rig
from ewb_ident.inference.augmented import make_data
from ewb_ident.mechanisms import HOOKS, variants
from ewb_ident.mechanisms.learned import PLACES, LearnedTerm, with_bases
from ewb_ident.model.params import EWBParams
from ewb_ident.model.predict import INSERTION_POINTS, insertion_points, n_substeps, predict

P = rig.RigParams()
BASE = EWBParams(**{k: getattr(P, k) for k in EWBParams().as_dict()})
#: The channels in the order of the chain, and the first each place changes.
ORDER = ("current_A", "theta_deg", "x_m", "force_N", "torque_Nm")
FIRST = {
    "motor.electrical": "current_A",
    "motor.mechanical": "current_A",
    "gap": "x_m",
    "drive": "x_m",
    "force.input": "force_N",
    "force.output": "force_N",
    "friction": "torque_Nm",
    "torque.output": "torque_Nm",
}
#: A learned term's size at each place's unit (a visible effect).
SIZE = {"V": 0.5, "N*m": 2e-3, "m": 5e-5, "deg": 5.0, "N": 100.0, "1": 0.2, "A": 0.1}
#: Catalog variants whose default values have no effect, at values that have one.
VISIBLE = {
    "friction_speed": {"kappa": 0.2},
    "sensor_offset[force_N]": {"offset": 50.0},
    "sensor_offset[torque_Nm]": {"offset": 5.0},
}


@pytest.fixture(scope="module")
def data():
    _, _, run = rig.simulate_rig(
        sample_rate_hz=200.0, noise=rig.SensorNoise.none(), return_clean=True
    )
    tr = run.trace
    sigma = {c: 1.0 for c in ORDER if tr.has(c)}
    d = make_data(tr, sigma, BASE.as_dict() | {"theta0_deg": 0.0})
    ones = np.ones((tr.n, 1))
    return tr, with_bases(d, {place: ones for place in PLACES})


def _learned(place: str) -> LearnedTerm:
    size = 5.0 if place in ("torque.output", "sensor.torque_Nm") else SIZE[PLACES[place].unit]
    return LearnedTerm(place=place, names=("1",), scales=(1.0,), coef=jnp.asarray([size]))


def _acting(place: str, spec: str) -> list:
    """The catalog variants and learned terms that act at ``place`` through ``spec``."""
    hook, _, stage = spec.partition(":")
    catalog = [m.with_values(VISIBLE.get(m.variant, {})) for m in variants()]
    cands = [*catalog, *(_learned(p) for p in PLACES)]
    return [
        m
        for m in cands
        if m.uses(hook)
        and (not stage or m.stage == stage)
        and any(q == place or q.startswith(f"{place}.") for q in insertion_points(m))
    ]


def test_every_hook_has_one_insertion_point_and_every_learned_place_is_one():
    named = [spec.partition(":")[0] for specs in INSERTION_POINTS.values() for spec in specs]
    assert set(named) == set(HOOKS)
    for place in PLACES:
        assert insertion_points(_learned(place)) == (place,), place
    for m in variants():
        assert len(insertion_points(m)) >= 1, m.variant


CASES = [(place, spec) for place, specs in INSERTION_POINTS.items() for spec in specs]


@pytest.mark.parametrize(("place", "spec"), CASES, ids=[f"{p}:{s}" for p, s in CASES])
def test_each_hook_is_reached_where_it_acts(data, place, spec):
    tr, d = data
    mechanisms = _acting(place, spec)
    assert mechanisms, f"no mechanism acts at {place} through {spec}"
    plain = predict("chain", BASE, jnp.asarray(0.0), (), d, 1)
    n = tr.n
    for m in mechanisms:
        where = next(q for q in insertion_points(m) if q == place or q.startswith(place))
        first = where.split(".", 1)[1] if where.startswith("sensor.") else FIRST[where]
        out = predict("chain", BASE, jnp.asarray(0.0), (m,), d, n_substeps(tr.dt, (m,)))
        change = {
            ch: float(np.max(np.abs(np.asarray(out[ch])[:n] - np.asarray(plain[ch])[:n])))
            for ch in ORDER
        }
        scale = {ch: float(np.max(np.abs(np.asarray(plain[ch])[:n]))) for ch in ORDER}
        assert change[first] > 1e-4 * scale[first], (m.variant, change)
        before = ORDER[: ORDER.index(first)]
        if where.startswith("sensor.") or where.startswith("motor."):
            before = ()  # a sensor changes only its channel; the motor is the start
        for ch in before:
            assert change[ch] == 0.0, (m.variant, ch, change)
        if where.startswith("sensor."):
            others = [ch for ch in ORDER if ch != first]
            assert all(change[ch] == 0.0 for ch in others), (m.variant, change)
