"""How the motor's sub-step length moves a diagnosis's fitted parameters.

    python -m studies.substep_bias [TRACE] [--steps 2.5e-4,5e-4,1e-3]

Diagnoses ``TRACE`` (default: the shipped concealed stiction trace) once per longest
sub-step of the motor integration with mechanisms
(:data:`ewb_ident.model.integrate.MAX_SUBSTEP_S`, 0.5 ms in the package), and prints each
finding's parameters with their standard errors. The splitting of a sub-step (exact
linear flow, then implicit friction) is first order, so the parameters move in
proportion to the step: the difference between the package's step and half of it is
about the bias of the package's step.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trace", nargs="?", type=Path,
                    default=ROOT / "datasets" / "concealed" / "stiction.csv")  # fmt: skip
    ap.add_argument("--steps", default="2.5e-4,5e-4,1e-3", help="longest sub-steps, s")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    from ewb_ident.data.readers import read_trace
    from ewb_ident.diagnosis.diagnose import diagnose
    from ewb_ident.model import integrate

    trace = read_trace(args.trace)
    package_step = integrate.MAX_SUBSTEP_S
    try:
        for step in (float(s) for s in args.steps.split(",")):
            integrate.MAX_SUBSTEP_S = step
            result = diagnose(trace).to_json()
            found = "; ".join(
                f"{f['effect']}: "
                + ", ".join(
                    f"{k} = {v:.5g} ± {(f.get('stderr') or {}).get(k) or float('nan'):.2g}"
                    for k, v in f["params"].items()
                )
                for f in result["findings"]
            )
            print(f"sub-step {step * 1e3:g} ms: {result['verdict']}; {found}", flush=True)
    finally:
        integrate.MAX_SUBSTEP_S = package_step


if __name__ == "__main__":
    main()
