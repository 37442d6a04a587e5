"""Benchmark: whole-chain least squares, ewb-ident against the SciPy peer.

    python -m benchmarks.bench_fit

The traces are issue 12's: clean, 4 s at 200 Hz, every channel, from an independent
rig simulator (``validation_rigs/other_rig.py``, units drawn with :data:`SEED`, fixed before any
measurement): one open-loop apply-hold-release (``steps``) and one position-controlled
apply closed at the logging rate (``position``), written to CSV with their sidecar.

Warm: ``ewb_ident.inference.least_squares.fit`` (everything: the start from the data,
the stage fits, two weighted solves, null-direction checks, standard errors, metrics)
after one call that compiled it, median of 5; against the peer (``scipy_peer.py``:
``solve_ivp`` LSODA + ``least_squares`` with finite differences) fitting the same free
parameters, in the same coordinates, with the weights ewb-ident ended with, from the
start ewb-ident computes from the data (the peer's own start, the seed values, left it
in the flat-bell basin for more than 20 minutes on these units). The peer is run once:
its fits take minutes on the closed-loop trace.
Cold: whole commands in fresh processes, imports and compilation included:
``ewb-ident fit`` with its on-disk cache of compiled programs empty, and again with it
filled by the previous run, against ``python scipy_peer.py TRACE PROBLEM.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from benchmarks import scipy_peer  # noqa: E402
from ewb_ident.data.readers import read_trace  # noqa: E402
from ewb_ident.data.writers import write_trace  # noqa: E402
from ewb_ident.inference.least_squares import _start_values, fit  # noqa: E402
from validation_rigs.other_rig import draw_rig, record  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

#: The seed of the rig units the benchmark's traces come from.
SEED = 12
PROFILES = ("steps", "position")


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, jax {jax.__version__}"
    )


class Report:
    """A benchmark's table: each row printed as it is measured, and the whole written,
    under the command that made it and the machine, to the file of ``--out`` (default
    ``reports/NAME.md``) by :meth:`write`."""

    def __init__(self, script: str, doc: str):
        name = Path(script).stem
        ap = argparse.ArgumentParser(description=doc.splitlines()[0])
        ap.add_argument("--out", type=Path, default=ROOT / "reports" / f"{name}.md")
        self.out = ap.parse_args().out
        self.title = f"# `python -m benchmarks.{name}`"
        self.lines = [f"machine: {machine()}", ""]

    def row(self, text: str) -> None:
        print(text, flush=True)
        self.lines.append(text)

    def write(self) -> None:
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.out.write_text(self.title + "\n\n" + "\n".join(self.lines) + "\n")
        print(f"wrote {self.out}")


def issue_traces(folder: Path) -> list[Path]:
    """Issue 12's traces, written to ``folder`` (CSV + sidecar); their paths."""
    paths = []
    for k, profile in enumerate(PROFILES):
        rig = draw_rig(np.random.default_rng([SEED, k]))
        trace, _ = record(
            rig, profile=profile, rate_hz=200.0, duration_s=4.0, seed=SEED + k, name=profile
        )
        path = folder / f"{profile}_200hz.csv"
        write_trace(trace, path)
        paths.append(path)
    return paths


def _median_time(f, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def run(cmd, env=None) -> float:
    """Wall time of a command in a fresh process, s."""
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, env=env, cwd=ROOT)
    return time.perf_counter() - t0


def peer_problem(path: Path, result) -> dict:
    """The peer's problem: ewb-ident's free parameters, start, fixed values, final
    weights and pad radius (JSON-able)."""
    trace = read_trace(path)
    from ewb_ident.inference.problem import build_setup
    from ewb_ident.model.integrate import EXPONENTIAL

    setup = build_setup(trace, "chain", None, None, {}, EXPONENTIAL)
    start = _start_values(setup.traces, "chain", setup.free, setup.per_trace, setup.base)
    return {
        "free": list(result.free),
        "start": {k.split("[")[0]: float(v) for k, v in start.items()},
        "fixed": setup.base.as_dict(),
        "sigma": {c: float(v) for c, v in result.sigma[0].items()},
        "r_eff": trace.r_eff_m,
    }


def warm(path: Path) -> dict:
    """Warm times (s) of ewb-ident and of the peer on ``path``, their final costs, and
    the peer's problem."""
    trace = read_trace(path)
    ours = fit(trace)  # compiles
    assert ours.converged, ours.message
    t_ours = _median_time(lambda: fit(trace), 5)
    prob = peer_problem(path, ours)
    measured = {c: trace[c] for c in ours.trace_metrics[0]}
    t0 = time.perf_counter()
    p, res = scipy_peer.fit(
        trace.time_s, trace["voltage_V"], measured, prob["sigma"], prob["free"],
        prob["start"], prob["r_eff"], prob["fixed"],
    )  # fmt: skip
    t_peer = time.perf_counter() - t0
    return {
        "ours": t_ours,
        "peer": t_peer,
        "cost_ours": float(np.sum(np.asarray(ours.problem(ours.u, ours.data)) ** 2) / 2),
        "cost_peer": float(res.cost),
        "peer_nfev": int(res.nfev),
        "problem": prob,
        "b": (ours.values["b"], p["b"]),
    }


def cold(path: Path, problem: dict) -> dict:
    """Cold command times (s): ewb-ident with an empty and a filled program cache, and
    the peer's command on the same problem."""
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        env = dict(os.environ, EWB_IDENT_CACHE=cache)
        cmd = [sys.executable, "-m", "ewb_ident", "fit", str(path), "--out", out]
        empty = run(cmd, env)
        filled = run(cmd, env)
        spec = Path(out) / "peer_problem.json"
        spec.write_text(json.dumps(problem))
        peer_script = str(Path(__file__).parent / "scipy_peer.py")
        peer = run([sys.executable, peer_script, str(path), str(spec)])
    return {"empty": empty, "filled": filled, "peer": peer}


def main() -> None:
    print(f"machine: {machine()}")
    with tempfile.TemporaryDirectory() as folder:
        for path in issue_traces(Path(folder)):
            w = warm(path)
            print(f"\n{path.name}: warm fit {w['ours']:.3f} s, peer {w['peer']:.2f} s "
                  f"({w['peer_nfev']} evaluations), {w['peer'] / w['ours']:.0f}x; final cost "
                  f"{w['cost_ours']:.1f} vs {w['cost_peer']:.1f}; b {w['b'][0]:.4g} vs "
                  f"{w['b'][1]:.4g}")  # fmt: skip
            c = cold(path, w["problem"])
            print(f"  cold command: empty cache {c['empty']:.2f} s "
                  f"({c['peer'] / c['empty']:.1f}x), filled {c['filled']:.2f} s "
                  f"({c['peer'] / c['filled']:.1f}x), peer {c['peer']:.1f} s")  # fmt: skip


if __name__ == "__main__":
    main()
