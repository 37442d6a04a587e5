"""Regenerate the concealed-effect traces in ``datasets/concealed/`` (deterministic).

Run from the repository root: ``python datasets/make_concealed.py``. Each trace is
``concealed/NAME.csv`` with its sidecar ``NAME.json`` and its truth ``NAME.truth.json``
(rig parameters, the planted effects and their parameters, profile, noise, seed). One
trace per catalog id, two with two effects, two clean ones: 3 s on another unit of the
rig than the nominal one, at 200 Hz (one at 500 Hz), open-loop steps or closed-loop
position control. The effects are *concealed*: the baseline fit of the seed model passes
the seed's acceptance (percent error below 10 % on force and torque), which
``python -m studies.concealed_diagnoses`` checks and records in
``reports/diagnosis/README.md`` beside each diagnosis.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ewb_ident import rig
from ewb_ident.data.outputs import write_json
from ewb_ident.data.writers import write_trace

HERE = Path(__file__).parent / "concealed"


def cases() -> dict[str, dict]:
    """Name -> keyword arguments of :func:`ewb_ident.rig.simulate_rig`."""
    unit = rig.vary(rig.RigParams(), np.random.default_rng(2027), rel=0.05)
    slowing = dataclasses.replace(unit, disc_speed_end_rad_s=30.0)
    pos = dict(params=unit, profile="position", sample_rate_hz=200.0)
    steps = dict(params=unit, profile="steps", sample_rate_hz=200.0)
    return {
        "clean_position": dict(**pos, seed=101),
        "clean_steps": dict(**steps, seed=102),
        "backlash": dict(**pos, seed=103, effects=[rig.Backlash(beta_deg=2.0)]),
        "wedge_load_torque": dict(**steps, seed=104, effects=[rig.WedgeLoadTorque(k_w=3e-5)]),
        "force_hysteresis": dict(**pos, seed=105, effects=[rig.ForceHysteresis(h=0.03)]),
        "sensor_delay": dict(**pos, seed=106, effects=[rig.SensorDelay("torque_Nm", 0.015)]),
        "friction_speed": dict(
            **{**pos, "params": slowing}, seed=107, effects=[rig.FrictionSpeed(kappa=-0.2)]
        ),
        "friction_fade": dict(**pos, seed=108, effects=[rig.FrictionFade(phi_per_K=5e-3)]),
        "sensor_offset": dict(**steps, seed=109, effects=[rig.SensorOffset("force_N", 35.0)]),
        "current_limit": dict(**steps, seed=110, effects=[rig.CurrentLimit(i_max_A=2.5)]),
        "stiction": dict(
            **{**steps, "sample_rate_hz": 500.0},
            seed=111,
            effects=[rig.Stiction(tau_c_Nm=0.02, tau_s_Nm=0.03)],
        ),
        "two_backlash_force_hysteresis": dict(
            **pos, seed=112, effects=[rig.Backlash(beta_deg=2.0), rig.ForceHysteresis(h=0.03)]
        ),
        "two_stiction_sensor_offset": dict(
            **steps,
            seed=113,
            effects=[
                rig.Stiction(tau_c_Nm=0.02, tau_s_Nm=0.025),
                rig.SensorOffset("torque_Nm", 5.0),
            ],
        ),
    }


def main() -> None:
    HERE.mkdir(exist_ok=True)
    for name, kw in cases().items():
        trace, truth = rig.simulate_rig(name=name, duration_s=3.0, **kw)
        write_trace(trace, HERE / f"{name}.csv")
        write_json(HERE / f"{name}.truth.json", truth)
        print(f"wrote datasets/concealed/{name}.csv ({trace.n} samples)")


if __name__ == "__main__":
    main()
