"""SIGTERM in the middle of a run, sent to a real process: exit 143, and no file of the
interrupted run left (issue 38). Each process says it has reached the point to interrupt
by a file it writes (or the first file of its output), not after a fixed time."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ewb_ident.cli import app

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "datasets"
#: Seconds a process may take to reach the point to interrupt (the import of JAX and
#: friends on a loaded machine): a limit on waiting, not a measured time.
PATIENCE_S = 300.0


def _start(*args: str, cwd: Path) -> subprocess.Popen:
    """``python -m ewb_ident ARGS`` of this checkout, in ``cwd``."""
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return subprocess.Popen(
        [sys.executable, "-m", "ewb_ident", *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=os.environ | {"PYTHONPATH": path},
    )


def _wait_for(proc: subprocess.Popen, ready) -> None:
    """Wait until ``ready()`` is true; fail if the process ends first."""
    deadline = time.monotonic() + PATIENCE_S
    while not ready():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"ended with {proc.returncode} before the point to interrupt: {err!r}")
        if time.monotonic() > deadline:
            proc.kill()
            proc.communicate()
            pytest.fail(f"did not reach the point to interrupt within {PATIENCE_S:.0f} s")
        time.sleep(0.02)


def _terminate(proc: subprocess.Popen) -> str:
    """Send SIGTERM; the process must end with 143 and say so; its stderr."""
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=PATIENCE_S)
    assert proc.returncode == 143, err
    text = err.decode()
    assert text.strip().splitlines()[-1] == "interrupted", text
    return text


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


#: A study script that writes a figure, says it is ready, and waits to be interrupted.
SLOW_SCRIPT = """\
import time
from pathlib import Path


def run(out, progress=None):
    (out / "figure8_bell.png").write_bytes(b"half a study")
    (out / "more").mkdir()
    (out / "more" / "cases.csv").write_text("case\\n1\\n")
    (Path(__file__).parent / "ready").write_text("ready")
    for _ in range(3000):
        time.sleep(0.1)
    raise RuntimeError("not interrupted")
"""

QUICK_SCRIPT = """\
import pandas as pd


def run(out, progress=None):
    (out / "figure8_bell.png").write_bytes(b"the earlier study")
    return pd.DataFrame({"case": [0]}), "# the earlier study\\n"
"""


def _study(folder: Path, name: str, script: str) -> Path:
    (folder / f"{name}.py").write_text(script)
    path = folder / f"{name}.toml"
    path.write_text(f'[study]\nname = "{name}"\nscript = "{name}.py"\n')
    return path


@pytest.mark.parametrize("earlier", [False, True], ids=["new folder", "earlier run"])
def test_sigterm_during_a_script_study_leaves_no_file_of_it(tmp_path, earlier):
    """Was: the figure the script had written (figure8_bell.png) left behind. The
    script writes into a staging folder that is moved into OUT only when it returns:
    an interrupted run leaves OUT as it was (absent, or an earlier run's files)."""
    out = tmp_path / "results" / "out"
    before: dict[str, bytes] = {}
    if earlier:
        quick = _study(tmp_path, "quick", QUICK_SCRIPT)
        done = CliRunner().invoke(app, ["study", str(quick), "--out", str(out)])
        assert done.exit_code == 0, done.output
        before = _files(out)
        assert "figure8_bell.png" in before and "results.csv" in before
    study = _study(tmp_path, "slow", SLOW_SCRIPT)
    proc = _start("study", str(study), "--out", str(out), cwd=tmp_path)
    _wait_for(proc, (tmp_path / "ready").exists)
    _terminate(proc)
    if earlier:
        assert _files(out) == before  # the staging folder and the new figure gone
        assert sorted(p.name for p in out.iterdir()) == sorted(
            [".ewb-ident-run.json", "figure8_bell.png", "report.md", "results.csv"]
        )
    else:
        assert not (tmp_path / "results").exists()


def test_a_script_study_that_returns_moves_its_files_in_as_one_set(tmp_path):
    """What the script wrote (a figure, a file in a subfolder) lands beside results.csv
    and report.md and in the run's list, so the next run into OUT replaces it."""
    script = QUICK_SCRIPT.replace(
        '    (out / "figure8_bell.png")',
        '    (out / "sub").mkdir()\n    (out / "sub" / "x.txt").write_text("x")\n'
        '    (out / "figure8_bell.png")',
    )
    out = tmp_path / "out"
    done = CliRunner().invoke(app, ["study", str(_study(tmp_path, "q", script)), "--out", str(out)])
    assert done.exit_code == 0, done.output
    files = _files(out)
    assert sorted(files) == [
        ".ewb-ident-run.json", "figure8_bell.png", "report.md", "results.csv", "sub/x.txt",
    ]  # fmt: skip
    done = CliRunner().invoke(
        app, ["study", str(_study(tmp_path, "p", QUICK_SCRIPT)), "--out", str(out)]
    )
    assert done.exit_code == 0, done.output
    assert not (out / "sub" / "x.txt").exists()


def test_a_rerun_of_the_same_script_starts_from_its_earlier_files(tmp_path):
    """A script that resumes (calibration, diagnosis_accuracy) finds the files its last
    complete run wrote into OUT; another script does not."""
    counting = """\
import pandas as pd


def run(out, progress=None):
    done = int((out / "count.txt").read_text()) if (out / "count.txt").exists() else 0
    (out / "count.txt").write_text(str(done + 1))
    return pd.DataFrame({"runs": [done + 1]}), "# counted\\n"
"""
    out = tmp_path / "out"
    for expected in (1, 2):
        study = _study(tmp_path, "count", counting)
        assert CliRunner().invoke(app, ["study", str(study), "--out", str(out)]).exit_code == 0
        assert (out / "count.txt").read_text() == str(expected)
    sub = tmp_path / "other"
    sub.mkdir()
    other = _study(sub, "count", counting)  # another script of the same name
    assert CliRunner().invoke(app, ["study", str(other), "--out", str(out)]).exit_code == 0
    assert (out / "count.txt").read_text() == "1"


def test_a_script_that_raises_leaves_the_earlier_run_as_it_was(tmp_path):
    out = tmp_path / "out"
    quick = _study(tmp_path, "quick", QUICK_SCRIPT)
    assert CliRunner().invoke(app, ["study", str(quick), "--out", str(out)]).exit_code == 0
    before = _files(out)
    raises = _study(
        tmp_path,
        "raises",
        "def run(out, progress=None):\n"
        "    (out / 'figure8_bell.png').write_bytes(b'half')\n"
        "    raise KeyError('lost')\n",
    )
    result = CliRunner().invoke(app, ["study", str(raises), "--out", str(out)])
    assert result.exit_code == 3 and "raises.py:3: KeyError: 'lost'" in result.output
    assert _files(out) == before


def test_sigterm_while_a_long_log_is_split_leaves_no_cycle(tmp_path):
    """``batch LOG --cycles`` of a 30-minute, 1 kHz log as .mat: SIGTERM once the first
    cycle file is written. Was: the cycles written so far left under OUT/cycles/."""
    import pandas as pd
    import scipy.io

    one = pd.read_csv(DATA / "position_1khz.csv")  # one apply in 3 s
    n = 1_800_000
    columns = {c: np.resize(one[c].to_numpy(), n) for c in one.columns}
    columns["time_s"] = np.arange(n) / 1000.0
    log = tmp_path / "log.mat"
    scipy.io.savemat(log, columns)
    log.with_suffix(".json").write_text((DATA / "position_1khz.json").read_text())
    out = tmp_path / "out"
    proc = _start("batch", str(log), "--cycles", "--out", str(out), cwd=tmp_path)
    _wait_for(proc, lambda: any((out / "cycles").rglob("*.parquet")))
    _terminate(proc)
    assert not out.exists()


def test_sigterm_ends_the_process_while_the_main_thread_is_busy(tmp_path):
    """The interpreter also writes the signal's number to a socket a thread of ours
    waits on, so the process ends while the main thread is in a long C call, before
    Python's handler could run there. Here the handler is made to do nothing: only
    that thread can end the process, with 143, removing the folder a run was filling."""
    code = f"""
import signal, time
from pathlib import Path
from ewb_ident.cli import interrupts
from ewb_ident.data.outputs import removed_if_interrupted

interrupts.install()
signal.signal(signal.SIGTERM, lambda signum, frame: None)  # the thread only
tree = Path({str(tmp_path / "filling")!r})
with removed_if_interrupted(tree):
    tree.mkdir()
    (tree / "part").write_text("half")
    Path({str(tmp_path / "ready")!r}).write_text("ready")
    for _ in range(3000):
        time.sleep(0.1)
raise SystemExit("not interrupted")
"""
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=os.environ | {"PYTHONPATH": path},
    )
    _wait_for(proc, (tmp_path / "ready").exists)
    _terminate(proc)
    assert not (tmp_path / "filling").exists()
