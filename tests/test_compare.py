"""Hardware-change refit recovers a planted change, with direction and size."""

import dataclasses

import pytest

from ewb_ident import rig
from ewb_ident.compare import compare


@pytest.fixture(scope="module")
def planted():
    base = rig.RigParams()
    new = dataclasses.replace(base, c=base.c + 50e-6, R=base.R * 1.2)  # pad change, hot motor
    old_t = [rig.simulate_rig(base, profile="staircase", seed=1, name="old")[0]]
    new_t = [rig.simulate_rig(new, profile="staircase", seed=2, name="new")[0]]
    return base, new, compare(old_t, new_t)


def test_planted_change_is_found_with_its_size_inside_the_interval(planted):
    base, new, result = planted
    by = {c.name: c for c in result.changes}
    for name in ("c", "R"):
        true = getattr(new, name) - getattr(base, name)
        change = by[name]
        assert change.changed, name
        assert change.low90 < true < change.high90, (name, change)
        assert change.delta * true > 0  # direction


def test_unchanged_parameters_are_not_reported_as_changed(planted):
    _, _, result = planted
    moved = {c.name for c in result.changes if c.changed}
    assert moved <= {"c", "R", "L"}, moved  # L may follow R through the armature pole


def test_torque_at_the_operating_point_and_the_json(planted):
    _, _, result = planted
    assert result.torque_new < result.torque_old  # more resistance and more gap: less torque
    doc = result.to_json()
    assert doc["changes"]["c"]["changed"] is True
    assert "Brake torque at the seed's operating point" in doc["summary"]
