"""``ewb-ident simulate``: write a trace from the synthetic rig or from fitted
parameters."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ewb_ident.cli.options import app, check_out, fail, writing


# The signature is the command's options (Typer): alike in shape to the other commands'
# signatures, each option its own.
@app.command()
def simulate(
    out: Annotated[Path, typer.Argument(help="Trace file to write (.csv or .parquet).")],
    profile: Annotated[
        str,
        typer.Option(
            help="steps (open-loop, as the seed), position (to x = c - 0.3 a), through_c "
            "(to x = c + 0.3 a: through full clamping, which pins down a, b, c) or staircase."
        ),
    ] = "steps",
    rate: Annotated[float, typer.Option(help="Sample rate, Hz (100-1000).")] = 200.0,
    duration: Annotated[float, typer.Option(help="Length of the trace, s.")] = 3.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise and of --vary.")] = 0,
    vary: Annotated[
        float, typer.Option(help="Relative spread of rig parameters, like another unit.")
    ] = 0.0,
    noise_scale: Annotated[
        float, typer.Option(help="Multiplies every sensor's default noise level.")
    ] = 1.0,
    effect: Annotated[
        list[str] | None,
        typer.Option(help="Catalog effect to switch on (repeat for several), e.g. backlash."),
    ] = None,
    params: Annotated[
        Path | None,
        typer.Option("--params", help="fit.json whose fitted parameters the rig takes."),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="NAME=VALUE, SI units: one rig parameter on top of the defaults or --params "
            "(repeat for several), e.g. --set c=1.007e-3.",
        ),
    ] = None,
) -> None:
    """Synthetic rig trace with documented truth: writes OUT, its sidecar and OUT.truth.json."""
    import dataclasses

    import numpy as np

    from ewb_ident import rig
    from ewb_ident.data.outputs import json_writer
    from ewb_ident.data.writers import write_trace

    if out.suffix.lower() not in (".csv", ".parquet"):
        fail(f"{out}: write a .csv or .parquet trace")
    check_out(out, folder=False)
    import math

    if seed < 0:
        fail(f"--seed must be a non-negative whole number, got {seed}")
    if not (math.isfinite(duration) and 0 < duration <= 600):
        fail(f"--duration must be within (0, 600] s, got {duration!r}")
    if not (math.isfinite(vary) and 0 <= vary <= 0.5):
        fail(f"--vary is a relative spread within [0, 0.5] (0.05: another unit), got {vary!r}")
    if not (math.isfinite(noise_scale) and 0 <= noise_scale <= 100):
        fail(f"--noise-scale must be within [0, 100], got {noise_scale!r}")
    unknown = [e for e in effect or [] if e not in rig.EFFECTS]
    if unknown:
        fail(f"unknown effect {unknown[0]!r}; the catalog is {', '.join(rig.EFFECTS)}")
    fitted = {}
    if params is not None:
        from ewb_ident.inference.validate import ValidateError, load_params

        try:
            fitted = load_params(params).as_dict()
        except ValidateError as err:
            fail(str(err))
    fitted |= _settings(set_ or [])
    try:
        rig_params = rig.RigParams(**fitted)
        if vary > 0:
            rig_params = rig.vary(rig_params, np.random.default_rng([seed, 1]), rel=vary)
        base = rig.SensorNoise()
        noise = rig.SensorNoise(
            **{f.name: getattr(base, f.name) * noise_scale for f in dataclasses.fields(base)}
        )
        trace, truth = rig.simulate_rig(
            rig_params,
            profile=profile,
            sample_rate_hz=rate,
            duration_s=duration,
            effects=tuple(effect or ()),
            noise=noise,
            seed=seed,
            name=out.stem,
        )
    except rig.RigError as err:
        fail(str(err))
    truth_path = out.with_suffix(".truth.json")
    with writing(out, folder=False):
        out.parent.mkdir(parents=True, exist_ok=True)
        # The truth in the same set as the table and its sidecar: all three or none.
        write_trace(trace, out, extra=[(truth_path, json_writer(truth))])
    typer.echo(f"wrote {out} ({trace.n} samples at {trace.sample_rate_hz:g} Hz) and {truth_path}")


def _settings(items: list[str]) -> dict[str, float]:
    """``--set NAME=VALUE`` pairs: rig parameters, finite numbers inside the fit's bounds
    (the rig's own checks, :class:`ewb_ident.rig.RigParams`, follow)."""
    import math

    from ewb_ident.model.params import PARAMS
    from ewb_ident.rig import VARIED_PARAMS

    allowed = (*VARIED_PARAMS, "r_eff_m")
    out: dict[str, float] = {}
    for item in items:
        name, sep, text = (part.strip() for part in item.partition("="))
        if not sep or not name:
            fail(f"--set takes NAME=VALUE, e.g. --set c=1.0e-3; got {item!r}")
        if name not in allowed:
            fail(f"--set {item}: unknown parameter {name!r}; the rig's are {', '.join(allowed)}")
        try:
            value = float(text)
        except ValueError:
            fail(f"--set {item}: {text!r} is not a number; give the value in SI units")
        info = PARAMS.get(name)
        if not math.isfinite(value) or (info is not None and not info.inside(value)):
            unit = "" if info is None or info.unit == "1" else f" {info.unit}"
            bounds = f" within ({info.lower:g}, {info.upper:g}){unit}" if info else ""
            fail(f"--set {item}: {name} must be a finite number{bounds}, got {text}")
        out[name] = value
    return out
