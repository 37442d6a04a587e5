"""The stages of the chain, in one table: what each reads and writes, which parameters it
has, and how it is named in words. Every other view of a stage (columns, outputs,
parameters, the channel a stage is judged on) is derived here from :data:`STAGE_TABLE`.

The table lives at the bottom of the package (beside the trace schema) because every
layer needs it: the trace's validation (which columns a stage needs), the model (what
a stage predicts), the fits (what a stage varies), the diagnosis and the figures.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StageSpec:
    """One stage of the chain.

    Attributes
    ----------
    name
        ``motor``, ``gap``, ``force`` or ``torque``.
    input
        The column the stage reads when it is fitted teacher-forced.
    outputs
        The measured channels it predicts; the first is its main channel.
    params
        The model parameters it has (names of :data:`ewb_ident.model.params.PARAMS`).
    words
        The stage in words, with its input and outputs.
    """

    name: str
    input: str
    outputs: tuple[str, ...]
    params: tuple[str, ...]
    words: str


STAGE_TABLE: tuple[StageSpec, ...] = (
    StageSpec(
        "motor",
        "voltage_V",
        ("theta_deg", "current_A"),
        ("R", "L", "kb", "kT", "M", "v", "theta0_deg"),
        "motor stage (voltage -> angle, current)",
    ),
    StageSpec(
        "gap", "theta_deg", ("x_m",), ("p2", "p1", "p0"), "gap stage (angle -> displacement)"
    ),
    StageSpec(
        "force", "x_m", ("force_N",), ("F_rt", "a", "b", "c"), "force stage (displacement -> force)"
    ),
    StageSpec("torque", "force_N", ("torque_Nm",), ("mu",), "torque stage (force -> torque)"),
)
#: Stage name -> its row of the table.
STAGE: dict[str, StageSpec] = {s.name: s for s in STAGE_TABLE}

#: The stages that can be fitted teacher-forced from a measured input, in chain order.
TEACHER_FORCED: tuple[str, ...] = tuple(STAGE)
#: Stage names a fit accepts: the teacher-forced stages and ``chain`` (from voltage alone).
STAGES: tuple[str, ...] = (*TEACHER_FORCED, "chain")

#: Measured channels a model output can be compared with: each stage's main channel in
#: chain order, then the others (the motor current).
CHANNELS: tuple[str, ...] = tuple(s.outputs[0] for s in STAGE_TABLE) + tuple(
    ch for s in STAGE_TABLE for ch in s.outputs[1:]
)
#: Input and main output column of each teacher-forced stage.
STAGE_COLUMNS: dict[str, tuple[str, str]] = {s.name: (s.input, s.outputs[0]) for s in STAGE_TABLE}
#: Output channels of each teacher-forced stage.
STAGE_OUTPUTS: dict[str, tuple[str, ...]] = {s.name: s.outputs for s in STAGE_TABLE}
#: The channel each stage is judged on first.
MAIN_CHANNEL: dict[str, str] = {s.name: s.outputs[0] for s in STAGE_TABLE}
#: (stage, channel) for every output, in chain order.
STAGE_CHANNELS: tuple[tuple[str, str], ...] = tuple(
    (s.name, ch) for s in STAGE_TABLE for ch in s.outputs
)
#: The stage whose output each channel is.
CHANNEL_STAGE: dict[str, str] = {ch: s.name for s in STAGE_TABLE for ch in s.outputs}
#: The stage whose (teacher-forced) input each measured channel is.
CHANNEL_INPUT_OF: dict[str, str] = {
    s.input: s.name for s in STAGE_TABLE if s.input in CHANNEL_STAGE
}
#: The parameters each stage can vary (``chain``: all of them, in chain order).
STAGE_PARAMS: dict[str, tuple[str, ...]] = {s.name: s.params for s in STAGE_TABLE} | {
    "chain": tuple(n for s in STAGE_TABLE for n in s.params)
}
#: Each stage in words (``chain``: the whole chain from the voltage).
STAGE_WORDS: dict[str, str] = {s.name: s.words for s in STAGE_TABLE} | {
    "chain": "whole chain (from voltage)"
}
