"""The memory a computation needs, estimated before it starts, so that a setting that
cannot fit is refused with its estimate instead of ending in an out-of-memory error."""

from __future__ import annotations

import os
from collections.abc import Sequence

from ewb_ident.data.trace import Trace
from ewb_ident.inference.problem import FitError

#: Bytes per sample of a least-squares fit's peak, by stage (the motor's integration and
#: its derivatives dominate), and the process's own (interpreter, JAX, compiled
#: programs). Peak resident memory of ``ewb-ident fit`` on a 1 kHz position trace: chain
#: 2.23, 4.16 and 8.11 GB at 150,000, 300,000 and 600,000 samples; force 1.32 and torque
#: 1.33 GB at 600,000 (docs/least-squares.md; tests/test_misuse_audit.py holds them).
FIT_BYTES_PER_SAMPLE = {"chain": 13.5e3, "motor": 13.5e3, "gap": 2e3, "force": 2e3, "torque": 2e3}
PROCESS_BYTES = 0.3e9


def physical_memory() -> float:
    """The machine's memory, bytes (16 GB where the system does not say)."""
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 16e9


def fit_memory_bytes(n_samples: int, stage: str) -> float:
    """An estimate of a least-squares fit's peak memory on ``n_samples`` samples in all
    (an unknown stage: as the whole chain)."""
    return (
        PROCESS_BYTES + FIT_BYTES_PER_SAMPLE.get(stage, FIT_BYTES_PER_SAMPLE["chain"]) * n_samples
    )


def check_fit_memory(traces: Sequence[Trace], stage: str) -> None:
    """Refuse (:class:`FitError`) a fit of ``traces`` whose estimated memory is more
    than the machine has, naming the estimate and what to do."""
    n = sum(t.n for t in traces)
    need, have = fit_memory_bytes(n, stage), physical_memory()
    if need <= have:
        return
    labels = ", ".join(dict.fromkeys(t.label for t in traces))
    force = fit_memory_bytes(n, "force")
    raise FitError(
        f"{labels}: a {stage} fit of {n:,} samples needs about {need / 1e9:.3g} GB, more than"
        f" this machine's {have / 1e9:.3g} GB; fit a shorter excerpt, or a teacher-forced"
        f" stage (--stage force needs about {force / 1e9:.3g} GB)"
    )
