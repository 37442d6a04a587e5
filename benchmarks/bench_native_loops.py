"""Benchmark: the models' loops as native loops (the package's XLA small-loop threshold,
1 MiB) against XLA's default (1 kB: a loop of more is a sequence of kernels dispatched
one by one on every iteration).

    python -m benchmarks.bench_native_loops [--out reports/bench_native_loops.md]

XLA reads the threshold once per process, when JAX starts its backend, so the two sides
cannot share a process: each runs in a fresh one (one thread, no on-disk program cache),
the package's own threshold or ``XLA_FLAGS=--xla_backend_extra_options=
xla_cpu_small_while_loop_byte_threshold=1024`` (the package keeps a threshold the user
set), alternately, :data:`ROUNDS` times each; the table gives the faster of the rounds.
Each process diagnoses ``datasets/concealed/stiction.csv`` twice (the first call
compiles its programs), fits and samples the posterior of ``datasets/steps_200hz.csv``
twice each (``min_ess=1000``), and compiles and runs (median of 9) each mechanism program
of the diagnosis (its residuals and Jacobian) with ``bench_mechanism_cost.py``'s
``capture`` and ``compare``. The last column says whether the two sides found the same
(the diagnosis's findings and candidates' dBIC, the fit's parameters and the posterior's
means, each to 1e-8 relative).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from benchmarks import bench_fit

ROOT = Path(__file__).resolve().parents[1]
ROUNDS = 2
DEFAULT = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024"

_ONE_SIDE = """
import json, sys, time
from benchmarks import bench_mechanism_cost as m  # one thread; imports the package (its XLA flag)
import ewb_ident
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.posterior import sample

out = {{"threshold": ewb_ident.XLA_SMALL_LOOP_BYTES}}


def twice(f):
    times, res = [], None
    for _ in range(2):
        t0 = time.perf_counter()
        res = f()
        times.append(time.perf_counter() - t0)
    return times, res


steps = m.read_trace({steps!r})
out["fit"], f = twice(lambda: fit(steps))
out["fit_values"] = [float(getattr(f.params[0], n)) for n in ("a", "b", "c", "mu")]
out["sample"], s = twice(lambda: sample(steps, min_ess=1000.0))
out["sample_values"] = [float(s.stats[n]["mean"]) for n in ("a", "b", "c", "mu")]
caps = m.capture()  # the diagnosis's first call: compiles its programs
t0 = time.perf_counter()
d = m.diagnose(m.read_trace(m.TRACE))
out["diagnose_warm"] = time.perf_counter() - t0
out["findings"] = [x.effect for x in d.findings]
out["dbic"] = [float(c.delta_bic) for c in d.candidates]
out["programs"] = []
for problem, u, data in caps:
    c = m.compare(problem, u, data)
    name = " + ".join(t.variant for t in problem.templates())
    out["programs"].append([f"{{name}} ({{', '.join(problem.stages)}})",
                            c["compile"]["jacobian"], c["run"]["jacobian"]])
print(json.dumps(out))
"""


def _side(default_loops: bool) -> dict:
    env = dict(os.environ, EWB_IDENT_THREADS="1", EWB_IDENT_CACHE="")
    env.pop("XLA_FLAGS", None)
    if default_loops:
        env["XLA_FLAGS"] = DEFAULT
    script = _ONE_SIDE.format(steps=str(ROOT / "datasets" / "steps_200hz.csv"))
    proc = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, cwd=ROOT
    )
    if proc.returncode:
        raise SystemExit(f"a side failed: {proc.stderr[-800:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _close(x: list[float], y: list[float], rtol: float = 1e-8) -> bool:
    return len(x) == len(y) and all(
        abs(a - b) <= rtol * max(abs(a), abs(b), 1e-300) for a, b in zip(x, y, strict=True)
    )


def main() -> None:
    report = bench_fit.Report(__file__, __doc__)
    row = report.row
    native, default = [], []
    for _ in range(ROUNDS):
        native.append(_side(False))
        default.append(_side(True))
    n, d = native[0], default[0]
    assert n["threshold"] != d["threshold"] == "1024", (n["threshold"], d["threshold"])

    def best(sides, f):
        return min(f(s) for s in sides)

    row(f"thresholds: {n['threshold']} bytes against {d['threshold']}; one thread, "
        f"no program cache; the faster of {ROUNDS} processes each, run alternately")  # fmt: skip
    row("")
    row("| step | native loops | XLA's default | ratio | same results |")
    row("|---|---|---|---|---|")
    same_fit = _close(n["fit_values"], d["fit_values"])
    same_post = _close(n["sample_values"], d["sample_values"])
    same_diag = n["findings"] == d["findings"] and _close(n["dbic"], d["dbic"])
    for label, f, same in (
        ("fit steps_200hz.csv, first call", lambda s: s["fit"][0], same_fit),
        ("the same, warm", lambda s: s["fit"][1], same_fit),
        ("posterior (ESS >= 1000), first call", lambda s: s["sample"][0], same_post),
        ("the same, warm", lambda s: s["sample"][1], same_post),
        ("diagnose concealed stiction, warm (one thread)", lambda s: s["diagnose_warm"],
         same_diag),
    ):  # fmt: skip
        a, b = best(native, f), best(default, f)
        row(f"| {label} | {a:.2f} s | {b:.2f} s | {b / a:.2f}x | {'yes' if same else 'no'} |")
    row("")
    row("Each mechanism program of the diagnosis (residuals and Jacobian): compile time and")
    row("one run (median of 9).")
    row("")
    row("| program | compile, native | compile, default | run, native | run, default | "
        "run ratio |")  # fmt: skip
    row("|---|---|---|---|---|---|")
    for k, (name, _, _) in enumerate(n["programs"]):
        cn = best(native, lambda s, k=k: s["programs"][k][1])
        cd = best(default, lambda s, k=k: s["programs"][k][1])
        rn = best(native, lambda s, k=k: s["programs"][k][2])
        rd = best(default, lambda s, k=k: s["programs"][k][2])
        row(f"| {name} | {cn:.2f} s | {cd:.2f} s | {rn * 1e3:.2f} ms | {rd * 1e3:.2f} ms | "
            f"{rd / rn:.1f}x |")  # fmt: skip
    tn = sum(best(native, lambda s, k=k: s["programs"][k][1]) for k in range(len(n["programs"])))
    td = sum(best(default, lambda s, k=k: s["programs"][k][1]) for k in range(len(d["programs"])))
    row("")
    row(f"compile time of the {len(n['programs'])} programs: {tn:.2f} s native, {td:.2f} s "
        "with XLA's default")  # fmt: skip
    report.write()


if __name__ == "__main__":
    main()
