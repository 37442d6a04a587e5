"""The whole-chain fit on somebody else's rig: every channel subset, profile and rate.

Traces come from ``validation_rigs/other_rig.py``, a simulator written separately from the model
and from ``ewb_ident/rig/``, whose units are drawn over wide ranges (not near the
seed's values), with closed-loop position control at the logging rate, actuator
saturation and quantised sensors. Each cell draws its own rig unit (a fresh seed per
cell, never used to tune anything).

The no-current cells run by default (the commonest real variation); the others are
marked slow (``pytest -m slow``).
"""

import math

import numpy as np
import pytest

from ewb_ident.inference.least_squares import fit
from validation_rigs.other_rig import Sensors, draw_rig, record

SUBSETS = {
    "all": (),
    "no_current": ("current_A",),
    "no_current_no_disc": ("current_A", "disc_speed_rad_s"),
    "no_torque": ("torque_Nm",),
}
PROFILES = ("steps", "position", "staircase")
RATES = (100.0, 500.0)


def _cells():
    for k, (subset, profile, rate) in enumerate(
        (s, p, r) for s in SUBSETS for p in PROFILES for r in RATES
    ):
        marks = () if subset.startswith("no_current") else (pytest.mark.slow,)
        yield pytest.param(
            subset, profile, rate, 1000 + k, marks=marks, id=f"{subset}-{profile}-{rate:g}Hz"
        )


@pytest.mark.parametrize(("subset", "profile", "rate", "seed"), list(_cells()))
def test_whole_chain_fit_converges_on_another_rig(subset, profile, rate, seed):
    rig = draw_rig(np.random.default_rng(seed))
    trace, _ = record(rig, profile=profile, rate_hz=rate, seed=seed, drop=SUBSETS[subset])
    result = fit(trace)
    assert result.converged, result.message
    assert result.status == "ok", result.warnings
    # The force is fitted to its sensor noise (white noise plus 1 N quantisation).
    s = Sensors()
    floor = math.hypot(s.force_N, s.q_force_N / math.sqrt(12.0))
    assert result.metrics["force_N"]["rmse"] < 1.5 * floor
    v = result.values
    if trace.has("torque_Nm"):
        assert abs(v["mu"] / rig.mu - 1) < 0.03
    else:
        assert any("mu is not determined" in w for w in result.warnings)
    if not trace.has("current_A"):
        assert set(result.free) & {"R", "v"} == set()
        assert any("no current_A" in w for w in result.warnings)
        # What voltage and angle identify is recovered, whatever R and v were held at:
        # the gain and the total lag of voltage -> speed.
        d = rig.R * rig.v + rig.kT * rig.kb
        derived = result.to_json()["derived"]
        assert abs(derived["motor_gain_rad_per_V_s"] / (rig.kT / d) - 1) < 0.01
        lag = (rig.L * rig.v + rig.R * rig.M) / d
        assert abs(derived["motor_lag_s"] / lag - 1) < 0.03
    # The bell: the truth within 4 standard errors (the bell is identified up to its noise).
    for name in ("a", "b", "c"):
        se = result.stderr[name]
        assert se is not None and abs(v[name] - getattr(rig, name)) < 4 * se + 1e-3 * abs(
            getattr(rig, name)
        ), (name, v[name], getattr(rig, name), se)


def _diagnose_cells():
    for cell in _cells():
        yield pytest.param(*cell.values, marks=(pytest.mark.slow,), id=cell.id)


@pytest.mark.parametrize(("subset", "profile", "rate", "seed"), list(_diagnose_cells()))
def test_diagnose_finds_nothing_on_a_clean_trace_of_another_rig(subset, profile, rate, seed):
    """The same cells, diagnosed: a clean trace of another rig (its own integrator,
    controller, quantised sensors and any channel subset) has no missing physics, so the
    verdict is ``none``, with no mismatch located and no finding. Slow: a diagnosis per
    cell (``pytest -m slow``)."""
    from ewb_ident.diagnosis.diagnose import diagnose

    rig = draw_rig(np.random.default_rng(seed))
    trace, _ = record(rig, profile=profile, rate_hz=rate, seed=seed, drop=SUBSETS[subset])
    result = diagnose(trace)
    assert result.verdict == "none", result.summary()
    assert result.findings == () and result.mismatches == ()


def test_a_coarsely_quantised_angle_is_weighted_by_its_rounding_error():
    """A 1 kHz trace whose angle sensor's step (0.9 deg) is far above its white noise
    (0.05 deg): consecutive samples mostly repeat, second differences are mostly zero,
    and a noise estimate from them alone says "no noise" and weights the angle ~1e4x too
    heavily, which bent the motor fit (R, kb held, theta 2 deg off; seen on the third
    rig's chirp traces). The noise is at least the rounding error, q / sqrt(12)."""
    seed = 4711
    rig = draw_rig(np.random.default_rng(seed))
    sensors = Sensors(theta_deg=0.05, q_theta_deg=0.9)
    trace, _ = record(rig, profile="position", rate_hz=1000.0, seed=seed, sensors=sensors)
    motor = fit(trace, stage="motor")
    assert motor.status == "ok", motor.warnings
    assert motor.noise[0]["theta_deg"] == pytest.approx(0.9 / math.sqrt(12.0), rel=0.1)
    assert not any("cannot tell" in w for w in motor.warnings), motor.warnings
    for name in ("R", "kb"):
        assert abs(motor.values[name] / getattr(rig, name) - 1) < 0.05, name
    # the angle is fitted to its rounding error, not to a fraction of a degree's bias
    assert motor.metrics["theta_deg"]["rmse"] < 1.2 * math.hypot(0.05, 0.9 / math.sqrt(12.0))


def test_a_reading_held_on_its_grid_may_be_off_by_half_a_step():
    """A 12-bit angle held at a few levels (a staircase in saturation): during each hold
    its rounding error is one offset of up to half a step, not white noise of
    q/sqrt(12); the phase's floor allows it, so a clean hold is no mismatch."""
    from ewb_ident.diagnosis.locate import StageCheck, phase_floor_scale

    q = 360.0 / 4096
    ramp = np.arange(0.0, 60 * q, q / 3)  # moving: a new grid value every few samples
    holds = np.repeat([(k + 0.45) * q for k in (120, 250, 400, 530)], 150)
    truth = np.concatenate([ramp + 0.01, holds])
    measured = np.round(truth / q) * q
    sigma = np.full(truth.size, q / np.sqrt(12))
    check = StageCheck("motor", "theta_deg", measured, truth, sigma, rounded=True)
    hold = np.arange(ramp.size, truth.size)
    rms = float(np.sqrt(np.mean(check.normalized[hold] ** 2)))
    assert rms > 1.5  # beyond the white rounding level the floor had before
    assert phase_floor_scale(check, hold) >= rms


@pytest.mark.parametrize(
    "rig_name",
    [
        "probe_rig",
        "probe2_rig",
        "probe3_rig",
        "probe4_rig",
        "probe5_rig",
        "probe6_rig",
        "probe7_rig",
    ],
)
def test_probe_rigs_draw_visible_concealed_reproducible_cases(rig_name):
    """Each family and form of a blind-probe rig is drawn visible (>= 3x the noise on
    some channel) and concealed (force and torque within 10 % of the same rig without
    it), the same case twice from the same seed; the rig imports nothing of the tool."""
    import importlib
    from pathlib import Path

    rig = importlib.import_module(f"validation_rigs.{rig_name}")
    assert "ewb_ident" not in Path(rig.__file__).read_text(encoding="utf-8")
    for fam in rig.FAMILIES:
        for form in ("a", "b"):
            case = rig.make_case(fam, form, 4242, 1)
            tr = case.truth
            assert tr["visibility"] >= 3.0, (fam, form)
            assert max(tr["concealed_force_pct"], tr["concealed_torque_pct"]) < 10.0
            if fam in rig.CURRENT_ALWAYS:
                assert tr["has_current"] and "current_A" in case.table
            again = rig.make_case(fam, form, 4242, 1)
            for k, v in case.table.items():
                np.testing.assert_array_equal(np.asarray(v), np.asarray(again.table[k]))
