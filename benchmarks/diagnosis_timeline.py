"""Timeline of one diagnosis: which candidate fits ran when, on which thread, and how
busy the cores were.

    python -m benchmarks.diagnosis_timeline TRACE [--cache DIR]

Runs :func:`ewb_ident.diagnosis.diagnose.diagnose` on ``TRACE`` in this process (with
the program cache in ``DIR``: an empty folder gives a cold run, a second run with the
same folder a filled one; without ``--cache`` nothing is stored) and prints the
diagnosis's step times, the CPU time of its search step over its wall time (2.0: both
cores busy throughout), and every candidate's fit (``_try``) with its thread and its
start and end in seconds since the diagnosis started. A flexible form tried by
``_refine`` shows with round ``form``. Where a core waits, the lines of one thread stop
while the other's go on.
"""

from __future__ import annotations

import argparse
import os
import threading
import time

import jax

jax.config.update("jax_enable_x64", True)

from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.diagnosis import diagnose as module  # noqa: E402
from ewb_ident.runtime import store  # noqa: E402
from ewb_ident.runtime import threads as workers  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trace")
    parser.add_argument("--cache", default=None, help="program cache folder")
    args = parser.parse_args()
    store.set_cache_folder(args.cache)
    trace = read_trace(args.trace)

    lines: list[tuple[float, float, str, str, str]] = []
    threads: dict[int, str] = {}
    t0 = [0.0]
    real_try, real_explain = module._try, module._explain

    def spy_try(ses, tmpl, *rest, **kwargs):
        start = time.perf_counter() - t0[0]
        got = real_try(ses, tmpl, *rest, **kwargs)
        name = threads.setdefault(threading.get_ident(), f"thread {len(threads)}")
        kind = f"round {kwargs['rnd']}" if "rnd" in kwargs else "form"
        lines.append((start, time.perf_counter() - t0[0], name, kind, tmpl.variant))
        return got

    def spy_explain(*a, **k):
        c0, w0 = os.times(), time.perf_counter()
        out = real_explain(*a, **k)
        c1, w1 = os.times(), time.perf_counter()
        cpu = (c1.user - c0.user) + (c1.system - c0.system)
        print(f"search step: {w1 - w0:.2f} s wall, {cpu:.2f} s CPU ({cpu / (w1 - w0):.2f} cores)")
        return out

    module._try, module._explain = spy_try, spy_explain
    try:
        t0[0] = time.perf_counter()
        result = module.diagnose(trace)
    finally:
        module._try, module._explain = real_try, real_explain
    steps = ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items())
    print(f"threads: {workers.threads()}; steps: {steps}")
    for start, end, name, kind, variant in sorted(lines):
        if end - start >= 0.005:  # candidates not tried at this trace's stages return at once
            span = f"{start:6.2f} -> {end:6.2f} s ({end - start:5.2f})"
            print(f"{span}  {name:9s} {kind:8s} {variant}")


if __name__ == "__main__":
    main()
