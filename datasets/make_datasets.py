"""Regenerate the shipped synthetic rig traces and their truth (deterministic).

Run from the repository root: ``python datasets/make_datasets.py``. Each trace is
written as ``NAME.csv`` with its sidecar ``NAME.json`` and its truth ``NAME.truth.json``
(the rig parameters, profile, noise and seed that made it). The traces come from
:mod:`ewb_ident.rig`, whose physics and integrator are independent of the fitted model.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ewb_ident import rig
from ewb_ident.data.outputs import write_json
from ewb_ident.data.writers import write_trace

HERE = Path(__file__).parent


def _cases():
    nominal = rig.RigParams()
    unit_b = rig.vary(nominal, np.random.default_rng(2024), rel=0.05)  # another rig unit
    through_c = rig.theta_for_gap(unit_b, unit_b.c + 0.3 * unit_b.a)
    return {
        # The seed's experiment: open-loop voltage steps, logged at 100 Hz.
        "seed_steps_100hz": dict(params=nominal, profile="steps", sample_rate_hz=100.0),
        # The main job's trace: the same steps on another unit of the rig, at 200 Hz.
        "steps_200hz": dict(params=unit_b, profile="steps", sample_rate_hz=200.0, seed=1),
        # Position-controlled apply-hold-release at 1 kHz (piston stays below c).
        "position_1khz": dict(params=unit_b, profile="position", sample_rate_hz=1000.0, seed=2),
        # An apply that drives the piston through c: identifies a, b, c separately.
        "through_c_500hz": dict(
            params=unit_b, profile="position", sample_rate_hz=500.0, seed=3, target_deg=through_c
        ),
        # A staircase of force levels at 200 Hz.
        "staircase_200hz": dict(params=unit_b, profile="staircase", sample_rate_hz=200.0, seed=4),
    }


def main() -> None:
    for name, kw in _cases().items():
        trace, truth = rig.simulate_rig(name=name, **kw)
        write_trace(trace, HERE / f"{name}.csv")
        write_json(HERE / f"{name}.truth.json", truth)
        print(f"wrote datasets/{name}.csv ({trace.n} samples, {trace.sample_rate_hz:g} Hz)")


if __name__ == "__main__":
    main()
