"""Hardware-change refit recovers a planted change, with direction and size."""

import dataclasses

import pytest

from ewb_ident import rig
from ewb_ident.inference.compare import compare


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
        # One recording pair: a 90 % interval misses one time in ten, so the size is
        # checked against the 99 % interval here; the 90 % rate is checked over 20 fresh
        # pairs in test_intervals_of_a_change_hold_the_true_change (slow).
        assert abs(change.delta - true) < 2.576 * change.stderr, (name, change)
        assert change.low90 < change.delta < change.high90
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


def test_the_summary_reads_like_a_result(planted):
    """A headline names what changed, strongest evidence first; a and c in mm; one kind
    of interval, said once; no line calls a change both unclear and probable; each side
    of compare.json lists its own traces and the method used."""
    _, _, result = planted
    text = result.summary()
    head = text.splitlines()[0]
    assert head.startswith("Changed: ")
    parts = head.removeprefix("Changed: ").split(". ")[0].rstrip(".").split("; P = ")
    names = [parts[0].split(" ")[0]] + [p.split("; ", 1)[1].split(" ")[0] for p in parts[1:-1]]
    assert {"c", "R"} <= set(names), head
    assert " mm " in head.split("c ", 1)[1].split(";")[0]  # c in mm
    ps = [float(p.split(")")[0]) for p in parts[1:]]
    assert ps == sorted(ps, reverse=True)  # strongest evidence first
    assert text.count("Every interval is 90 %") == 1 and "no clear change" not in text
    for line in text.splitlines()[2:]:
        if line.startswith("  unchanged"):
            assert float(line.rsplit("P = ", 1)[1].rstrip(")")) < 0.5, line
    doc = result.to_json()
    assert doc["old"]["traces"] == ["old"] and doc["new"]["traces"] == ["new"]
    assert doc["method"].startswith("a joint least-squares fit")


@pytest.mark.slow
def test_intervals_of_a_change_hold_the_true_change():
    """Issue 11.4: the 90 % intervals of the change of b and c held the truth far less
    often than 90 % (a shared a forced b to absorb a change of c). Over fresh pairs of
    recordings with a planted pad change (c) and bell change (b), the intervals hold the
    true change at about their nominal rate (>= 75 % of 20; binomial sd ~7 %)."""
    import numpy as np

    held = {"b": 0, "c": 0}
    n = 20
    for k in range(n):
        rng = np.random.default_rng([11, k])
        base = rig.vary(rig.RigParams(), rng, 0.05)
        new = dataclasses.replace(
            base,
            c=base.c + rng.uniform(20e-6, 60e-6),
            b=base.b * float(np.exp(rng.uniform(-0.08, 0.08))),
        )
        old_t = [rig.simulate_rig(base, profile="staircase", seed=2 * k, name="old")[0]]
        new_t = [rig.simulate_rig(new, profile="staircase", seed=2 * k + 1, name="new")[0]]
        result = compare(old_t, new_t)
        by = {c.name: c for c in result.changes}
        for name in held:
            true = getattr(new, name) - getattr(base, name)
            held[name] += by[name].low90 <= true <= by[name].high90
    assert all(v >= 0.75 * n for v in held.values()), held


def test_without_current_the_motor_change_is_given_for_what_is_identified():
    """A warm motor (R +15 %) recorded without current on the independent rig: L, kb and
    M are effective values there (R held), so their 'changes' would be R's in disguise.
    The comparison gives the gain and lag instead, and their intervals hold the truth."""
    import numpy as np

    from ewb_ident.inference.fit_result import motor_combination_values
    from validation_rigs.other_rig import draw_rig, record

    rng = np.random.default_rng([5, 1])
    old = draw_rig(rng)
    new = dataclasses.replace(old, R=old.R * 1.15, c=old.c + 40e-6)
    kw = dict(profile="steps", rate_hz=200.0, drop=("current_A",))
    t_old, _ = record(old, seed=1, name="old", **kw)
    t_new, _ = record(new, seed=2, name="new", **kw)
    result = compare([t_old], [t_new])
    by = {c.name: c for c in result.changes}
    assert not {"L", "kb", "M"} & set(by)
    motor = ("R", "L", "kb", "kT", "M", "v")
    for name in ("motor_gain_rad_per_V_s", "motor_lag_s"):
        true = (
            motor_combination_values(**{n: getattr(new, n) for n in motor})[name]
            - motor_combination_values(**{n: getattr(old, n) for n in motor})[name]
        )
        assert by[name].low90 <= true <= by[name].high90, (name, true, by[name])
    assert by["motor_lag_s"].changed  # a warm motor lags more (M R / D grows with R)
    assert "effective values" in result.summary()
    doc = result.to_json()
    assert doc["changes"]["motor_lag_s"]["stderr"] > 0


def test_a_small_but_real_mu_change_is_not_shared_into_the_bell():
    """Case 9 of the coverage study's seed 20261238 (independent rig, no current,
    position control): mu changed by 0.8 % — under the 1 % practical tolerance, but by
    30 standard errors. The joint refit shared it, so F_rt absorbed it: a change of
    -34 N with a +-3 N interval, where F_rt did not change. Shared now only are
    parameters whose change is consistent with none."""
    from studies import compare_coverage

    rows = {r["param"]: r for r in compare_coverage.run_case(9, seed=20261238)}
    assert rows["F_rt"]["true_delta"] == 0.0
    for p in ("F_rt", "a", "b", "c", "mu"):
        assert rows[p]["held"], (p, rows[p])


def test_compare_says_each_step_as_it_starts():
    """The command line's progress lines come from the library's steps."""
    base = rig.RigParams()
    old_t = [rig.simulate_rig(base, sample_rate_hz=100.0, seed=1, name="old")[0]]
    new_t = [rig.simulate_rig(base, sample_rate_hz=100.0, seed=2, name="new")[0]]
    steps: list[str] = []
    compare(old_t, new_t, stage="torque", progress=steps.append)
    assert steps[:2] == ["fitting OLD", "fitting NEW"]
    assert all(s.startswith("fitting") for s in steps)


def test_the_same_recording_on_both_sides_is_refused_before_any_fit():
    from ewb_ident.data.trace import TraceError

    trace, _ = rig.simulate_rig(rig.RigParams(), sample_rate_hz=100.0, seed=1, name="one")
    with pytest.raises(TraceError, match="same samples as trace 1"):
        compare([trace], [trace], stage="torque", progress=pytest.fail)
