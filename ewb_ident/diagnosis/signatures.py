"""How a learned term reads: a table of known signatures that turns where a term acts
and what it depends on into a physical hypothesis (never a catalog name), and the words
for a stage whose learned term does not generalise."""

from __future__ import annotations

from collections.abc import Sequence

from ewb_ident.diagnosis.inputs import Column, product_of, sensor_signal

#: Known signatures: (place prefix, input, words); an input ``name@``: a term periodic
#: in that position. The first match reads the term; every reading is a hypothesis to
#: inspect, never a catalog name.
SIGNATURES: tuple[tuple[str, str, str], ...] = (
    (
        "sensor.x_m",
        "x@",
        "the reading errs periodically with the displacement: a linear scale's "
        "interpolation (sub-divisional) error or pitch error",
    ),
    (
        "sensor.theta_deg",
        "angle@",
        "the reading errs periodically with the angle: an encoder's eccentricity or "
        "interpolation error",
    ),
    (
        "",
        "x@",
        "a term that repeats with the piston's displacement: a periodic geometry of a part "
        "that moves with the piston (a ramp's or a track's waviness, a screw's lead error)",
    ),
    (
        "",
        "angle@",
        "a term that repeats with the pinion angle: a periodic geometry of the gear train "
        "(tooth meshing, an eccentric gear) or the motor's cogging",
    ),
    (
        "motor.electrical",
        "current",
        "a voltage lost in proportion to (or with the sign of) the "
        "current: resistance of the supply, wiring or driver, or a brush / switch voltage drop",
    ),
    (
        "motor.electrical",
        "heat",
        "a voltage lost growing with the heat dissipated: the "
        "armature's resistance rising as it warms",
    ),
    (
        "motor.electrical",
        "time",
        "a voltage lost that drifts over the recording: heating of "
        "the armature or a sagging supply",
    ),
    (
        "motor.electrical",
        "voltage_rate",
        "the motor sees the logged voltage late or smoothed: a lag in the driver",
    ),
    (
        "motor.electrical",
        "speed_history",
        "a voltage that follows the speed late: a drag that builds over the motion and "
        "outlasts it, seen in the current it draws (a viscoelastic lubricant)",
    ),
    ("motor.electrical", "speed", "a back-EMF that is not proportional to speed"),
    (
        "motor.mechanical",
        "current",
        "a torque deficit that grows with the current: magnetic "
        "saturation of the motor (kT falls at high current)",
    ),
    (
        "motor.mechanical",
        "angle",
        "a torque that repeats with the pinion angle: cogging, gear "
        "tooth meshing or an eccentric gear",
    ),
    (
        "motor.mechanical",
        "speed_history",
        "a drag that builds over the motion and outlasts it: a viscoelastic "
        "lubricant or a fluid coupling",
    ),
    (
        "motor.mechanical",
        "speed",
        "a drag torque depending on speed beyond the viscous term: "
        "windage, lubricant churning or Coulomb friction",
    ),
    ("motor.mechanical", "force", "a load torque from the clamping force"),
    (
        "drive",
        "force",
        "the piston yields under the clamping force: compliance of the drive "
        "(worm, wedge or caliper)",
    ),
    ("gap", "force", "the piston yields under the clamping force: compliance of the drive"),
    ("force.output", "x_rate", "force rising with the piston's speed: damping in the caliper"),
    (
        "force.output",
        "force_history",
        "force relaxing after it changes: viscoelastic creep of the pads",
    ),
    (
        "force.output",
        "time",
        "force drifting over the recording at a given displacement: thermal growth or creep",
    ),
    ("force.input", "time", "the displacement the caliper feels drifts: thermal expansion"),
    (
        "force.input",
        "energy",
        "the displacement the caliper feels grows with the braking "
        "energy: thermal expansion of pads and piston",
    ),
    (
        "force.input",
        "heat",
        "the displacement the caliper feels drifts with heating: thermal expansion",
    ),
    ("friction", "force", "the friction coefficient depends on the pad pressure"),
    (
        "friction",
        "distance",
        "the friction coefficient changes with sliding distance: "
        "bedding-in or a transfer layer building up",
    ),
    ("friction", "time", "the friction coefficient drifts over the recording"),
    (
        "friction",
        "energy",
        "the friction coefficient changes with the braking energy: a thermal effect",
    ),
    (
        "friction",
        "disc_angle",
        "the friction torque varies once or twice per disc revolution: "
        "disc thickness variation or runout",
    ),
    (
        "torque.output",
        "disc_angle",
        "the torque varies once or twice per disc revolution: disc thickness variation or runout",
    ),
    (
        "sensor.force_N",
        "force_integral",
        "the reading drifts with the integral of the force: a piezoelectric washer's "
        "charge leaking, or its charge amplifier drifting",
    ),
    (
        "sensor.current_A",
        "voltage",
        "the reading includes a path driven by the voltage beside the motor: a snubber "
        "or the driver's own supply current",
    ),
    (
        "sensor.theta_deg",
        "reversals",
        "the reading loses a step at each reversal of the motion: the encoder or its "
        "coupling slipping",
    ),
    (
        "",
        "force_peak",
        "a change that grows only when the force sets a new record: a permanent set "
        "(pads bedding in, a plastic deformation, a seal seating)",
    ),
    (
        "",
        "current_travel",
        "a term that restarts when the current reverses: magnetic hysteresis (a Hall "
        "sensor's core remanence, the motor's iron)",
    ),
    (
        "",
        "force_travel",
        "a term that restarts when the force reverses: hysteresis in the force path (a load "
        "cell's, or the pads' and caliper's)",
    ),
    (
        "",
        "reversals",
        "a change that steps at each reversal of the motion: a slip, or a loss or wear per stroke",
    ),
    (
        "",
        "travel",
        "a term that restarts at each reversal of the motion: hysteresis (a play, "
        "pre-sliding friction, a contact that sticks before it slides)",
    ),
    (
        "sensor.",
        "_rate",
        "the sensor reading lags its own signal: a low-pass filter in its signal conditioning",
    ),
    (
        "sensor.",
        "own",
        "the sensor's reading is not proportional to its signal: a calibration nonlinearity",
    ),
)


def periodic_in(columns: Sequence[Column]) -> tuple[str, ...]:
    """The positions basis columns are periodic in (a harmonic of a period of the
    signal, alone or times a carrier: :func:`product_of`'s second form)."""
    forms = ((c.signal, c.form) if (second := product_of(c.form)) is None
             else (c.form[2], second) for c in columns)  # fmt: skip
    return tuple(dict.fromkeys(n for n, f in forms if f[0] == "period"))


def reading(place: str, depends_on: Sequence[str], columns: Sequence[Column] = ()) -> str:
    """A physical reading of a learned term from :data:`SIGNATURES` (a hypothesis), or
    ``""`` when no known signature matches. ``columns``: the term's basis columns (what
    it is periodic in)."""
    own = sensor_signal(place)
    periodic = periodic_in(columns)
    for pre, inp, words in SIGNATURES:
        if not place.startswith(pre):
            continue
        if inp.endswith("@"):
            if inp[:-1] in periodic:
                return words
            continue
        for dep in depends_on:
            if inp == "own" and own and dep == own:
                return words
            if inp == "_rate" and own and dep == f"{own}_rate":
                return words
            if (
                dep == inp
                or dep.startswith(inp + "_history")
                or dep.startswith(inp)
                and inp.endswith("_history")
            ):
                return words
    return ""


def not_generalised(disc) -> str:
    """Words for a stage whose learned term does not generalise."""
    pf = disc.learned
    if not pf.groups:
        return (
            f"{disc.stage} stage: no learned term at any of its places "
            f"({', '.join(p.place for p in disc.places)}) improves held-out data "
            f"({disc.method}): unexplained"
        )
    d = disc.distilled if disc.learned.generalises else pf
    what = "its distilled equation" if d is disc.distilled else "it"
    ins = 100.0 * (d.insample_before - d.insample_after) / max(d.insample_before, 1e-300)
    return (
        f"{disc.stage} stage: a term learned at {disc.place} depending on "
        f"{', '.join(disc.depends_on) or ', '.join(pf.groups)}: {what} lowers the residual "
        f"it was fitted to by {ins:.0f} % and held-out data ({disc.method}) by "
        f"{d.improvement_pct:.0f} %, but {d.why_not}: it is not a finding"
    )
