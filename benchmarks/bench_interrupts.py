"""How long a signal waits while an ``ewb-ident`` command runs: to Python's handler in
the main thread, and to a thread waiting on the interpreter's wakeup socket (how
``ewb_ident.cli.interrupts`` ends a run on SIGINT / SIGTERM).

    python -m benchmarks.bench_interrupts [--seconds 120] [--rows 600000] -- fit {log} --out /tmp/o

The command runs in this process. An interval timer sends SIGALRM every 50 ms; for each
one, the wait is the time to the next run of the handler, and of the thread. ``{log}``
in the command is a ``.mat`` log of ``--rows`` samples at 1 kHz (the shipped 1 kHz
position trace, repeated), made in a temporary folder. After ``--seconds`` (or when the
command ends) the longest, 99th-percentile and median waits are printed.
"""

from __future__ import annotations

import argparse
import bisect
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PERIOD_S = 0.05


def make_log(folder: Path, rows: int) -> Path:
    """A ``rows``-sample, 1 kHz ``.mat`` log of the shipped position trace, repeated."""
    import numpy as np
    import pandas as pd
    import scipy.io

    one = pd.read_csv(ROOT / "datasets" / "position_1khz.csv")
    columns = {c: np.resize(one[c].to_numpy(), rows) for c in one.columns}
    columns["time_s"] = np.arange(rows) / 1000.0
    path = folder / "log.mat"
    scipy.io.savemat(path, columns)
    path.with_suffix(".json").write_text((ROOT / "datasets" / "position_1khz.json").read_text())
    return path


def waits(sent: list[float], runs: list[float], t0: float) -> str:
    runs = sorted(runs)
    out = []
    for s in sent:
        k = bisect.bisect_left(runs, s)
        out.append((runs[k] - s if k < len(runs) else float("inf"), s - t0))
    out.sort()
    worst, at = out[-1]
    return (
        f"longest {worst:.2f} s (signal at {at:.1f} s), 99th percentile "
        f"{out[int(0.99 * (len(out) - 1))][0]:.3f} s, median {out[len(out) // 2][0]:.3f} s"
    )


def main() -> None:
    argv = sys.argv[1:]
    command = argv[argv.index("--") + 1 :] if "--" in argv else []
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--rows", type=int, default=600_000)
    args = ap.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    if not command:
        ap.error("give the ewb-ident command after --")
    folder = Path(tempfile.mkdtemp(prefix="bench-interrupts-"))
    if any("{log}" in a for a in command):
        log = make_log(folder, args.rows)
        command = [a.replace("{log}", str(log)) for a in command]

    handler_runs: list[float] = []
    thread_runs: list[float] = []
    signal.signal(signal.SIGALRM, lambda signum, frame: handler_runs.append(time.perf_counter()))
    reader, writer = socket.socketpair()
    writer.setblocking(False)
    signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)

    def watch() -> None:
        while data := reader.recv(64):
            thread_runs.extend([time.perf_counter()] * len(data))

    threading.Thread(target=watch, daemon=True).start()
    t0 = time.perf_counter()

    def report() -> None:
        signal.setitimer(signal.ITIMER_REAL, 0, 0)
        end = time.perf_counter()
        # The last second's signals may not have been answered yet: left out.
        sent = [t0 + k * PERIOD_S for k in range(1, int((end - t0 - 1.0) / PERIOD_S))]
        print(f"ewb-ident {' '.join(command)}: {len(sent)} signals over {end - t0:.0f} s")
        print(f"  Python handler (main thread): {waits(sent, handler_runs, t0)}")
        print(f"  wakeup-socket thread:         {waits(sent, thread_runs, t0)}", flush=True)
        shutil.rmtree(folder, ignore_errors=True)
        os._exit(0)

    threading.Timer(args.seconds, report).start()
    from ewb_ident.cli import app
    from ewb_ident.runtime.config import configure

    configure()
    t0 = time.perf_counter()
    signal.setitimer(signal.ITIMER_REAL, PERIOD_S, PERIOD_S)
    try:
        app(command, standalone_mode=False)
    finally:
        report()


if __name__ == "__main__":
    main()
