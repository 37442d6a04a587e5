"""The command line's shared pieces: the Typer app, exit codes, option types, and
the checks every command makes before it starts work."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help=(
        "Fit the EWB rig model (DC motor -> worm pinion -> wedge -> caliper) to rig traces, "
        "say how certain the parameters are, and find the physics the model leaves out.\n\n"
        "Traces are CSV/Parquet/MATLAB tables in the trace format v1 (time_s, voltage_V, "
        "theta_deg, x_m, force_N, torque_Nm, current_A) with an optional JSON sidecar."
    ),
    pretty_exceptions_enable=False,
)

# Typer shows every option's type in its help, a flag's as "<bool>": a flag takes no
# value, so its type column is left empty.
_display_type = typer.core.TyperOption.display_type_rich
typer.core.TyperOption.display_type_rich = lambda self, ctx: (  # type: ignore[method-assign]
    "" if self.is_flag else _display_type(self, ctx)
)

EXIT_BAD_INPUT = 2
#: Done and written, but not trustworthy: not converged, or outside the stated acceptance.
EXIT_UNTRUSTWORTHY = 3

Traces = Annotated[list[Path], typer.Argument(help="Trace files (.csv, .parquet, .mat).")]


class _EmptyOut(type(Path())):
    """``--out ""`` as given (a plain Path of "" is the current folder)."""


def _out_path(text: str) -> Path:
    """``--out`` as given; an empty one is marked for :func:`check_out` to refuse."""
    return _EmptyOut() if not text.strip() else Path(text)


OutDir = Annotated[
    Path,
    typer.Option("--out", "-o", help="Output folder (created if absent).", parser=_out_path),
]
Mapping = Annotated[
    Path | None,
    typer.Option("--map", help="Column mapping (JSON/TOML): source name -> column and unit."),
]
FillGaps = Annotated[
    bool, typer.Option("--fill-gaps", help="Interpolate interior gaps of up to 5 samples.")
]
NoUnitCheck = Annotated[
    bool, typer.Option("--no-unit-check", help="Skip the plausibility checks of units.")
]
REff = Annotated[
    float | None,
    typer.Option(
        "--r-eff",
        help="Effective pad radius, m, for every trace (overrides the sidecar; default: "
        "the sidecar's r_eff_m, else 0.15 m with a warning).",
    ),
]
WithOption = Annotated[
    str | None,
    typer.Option(
        "--with",
        help="Catalog mechanisms to add to the chain, e.g. 'backlash' or "
        "'force_hysteresis,sensor_delay[force_N]', a flexible form after a colon, e.g. "
        "'backlash:spring' (whole chain, one trace).",
    ),
]
WithDiagnosisOption = Annotated[
    Path | None,
    typer.Option("--with-diagnosis", help="Folder of an earlier `diagnose`: add what it found."),
]
FixOption = Annotated[
    str | None, typer.Option(help="Fixed values in SI units, e.g. 'R=1.1,L=0.002'.")
]
IntegratorOption = Annotated[
    str, typer.Option(help="exponential (default) or heun (the seed's, at 0.01 s).")
]


def fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def check_out(out: Path, *, folder: bool = True) -> None:
    """Refuse an output location that cannot be written, before any work starts."""
    import os

    if isinstance(out, _EmptyOut):
        fail("--out is empty (it would write into the current folder); name the output folder")
    name = f"--out {out}" if folder else str(out)
    try:
        limit = os.pathconf(_existing(out), "PC_NAME_MAX")
    except (AttributeError, OSError, ValueError):  # no pathconf (Windows) or no answer
        limit = 255
    long_part = next((p for p in out.parts if len(os.fsencode(p)) > limit), None)
    if long_part is not None:
        fail(f"--out: the name {long_part[:40]}... is longer than {limit} bytes; use a shorter one")
    if len(os.fsencode(os.path.abspath(out))) >= 4096:
        fail(f"--out {str(out)[:40]}...: the path is longer than 4096 bytes; use a shorter one")
    if out.is_symlink() and not out.exists():
        fail(
            f"{name}: a symbolic link to {os.readlink(out)}, which does not exist; remove the"
            " link or name another location"
        )
    if folder and out.exists() and not out.is_dir():
        fail(f"--out {out}: exists and is not a folder; name a folder (it is created)")
    if not folder and out.is_dir():
        fail(f"{out}: is a folder; name a file to write")
    probe = out if folder and out.exists() else out.parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        fail(f"{out}: cannot write there ({probe} is not a writable folder); choose another")
    # Permissions do not tell everything (an immutable or read-only mounted folder, or
    # root): try to create a file there, and remove it.
    import tempfile

    try:
        fd, name = tempfile.mkstemp(dir=probe, prefix=".ewb-ident-probe-")
        os.close(fd)
        os.unlink(name)
    except OSError as err:
        fail(f"{out}: cannot write there ({probe}: {err.strerror}); choose another")


def _existing(path: Path) -> Path:
    """The nearest folder of ``path`` that exists (for file-system limits)."""
    import os

    probe = os.path.abspath(path)
    while not os.path.isdir(probe) and probe != os.path.dirname(probe):
        probe = os.path.dirname(probe)  # (isdir is False for a name too long, not an error)
    return Path(probe)


@contextlib.contextmanager
def writing(out: Path, *, folder: bool = True):
    """The results' writing: a file system that refuses it (a full disk, a quota, a
    folder made read-only meanwhile) is one line and exit 2, and leaves nothing: the
    atomic writes remove their temporary files, and a folder this run made is removed
    again if it stayed empty."""
    from ewb_ident.data.trace import TraceError

    where = out if folder else out.parent
    made = not where.exists()
    try:
        yield
    except (OSError, TraceError) as err:  # (write_trace says which file, as TraceError)
        if made:
            with contextlib.suppress(OSError):
                where.rmdir()  # only if empty
        if isinstance(err, TraceError):
            fail(str(err))
        fail(
            f"{out}: cannot write the results ({err.strerror or err}); free space or choose"
            " another location"
        )


class Status:
    """A one-line status on a terminal's stderr (``diagnose``, ``report``): what the
    long computation is doing now and for how long; when stderr is not a terminal (a
    batch log), one line per step."""

    def __init__(self, what: str):
        self.what = what
        self.live = None

    def __enter__(self):
        import time

        self.t0 = time.perf_counter()
        if not sys.stderr.isatty():

            def line(text: str) -> None:
                typer.echo(f"{self.what}: {text} ({time.perf_counter() - self.t0:.0f} s)", err=True)

            return line
        from rich.console import Console

        self.live = Console(stderr=True).status(self.what)
        self.live.start()

        def say(text: str) -> None:
            self.live.update(f"{self.what}: {text} ({time.perf_counter() - self.t0:.0f} s)")

        return say

    def __exit__(self, *exc) -> None:
        if self.live is not None:
            self.live.stop()


def progress_bar(no_progress: bool = False):
    """A progress bar on a terminal's stderr (elsewhere a line at every tenth of the
    steps, for a batch log), and the callback that moves it."""
    if no_progress:
        return None, None
    if not sys.stderr.isatty():
        import time

        t0, said = time.perf_counter(), [-1]

        def lines(done: int, total: int) -> None:
            tenth = 10 * done // max(total, 1)
            if tenth > said[0]:
                said[0] = tenth
                typer.echo(
                    f"sampling: {done}/{total} steps ({time.perf_counter() - t0:.0f} s)", err=True
                )

        return None, lines
    from rich.console import Console
    from rich.progress import Progress

    bar = Progress(console=Console(stderr=True), transient=True)
    task = None

    def progress(done: int, total: int) -> None:
        nonlocal task
        if task is None:
            task = bar.add_task("sampling", total=total)
        bar.update(task, completed=done, total=total)

    return bar, progress


def name_list(text: str | None) -> list[str] | None:
    if text is None:
        return None
    return [n.strip() for n in text.split(",") if n.strip()]


def assignments(text: str | None, option: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in name_list(text) or []:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            fail(f"{option} takes NAME=VALUE pairs separated by commas, got {item!r}")
    return out


def integrator_option(name: str):
    """The :class:`~ewb_ident.model.integrate.Integrator` ``--integrator`` names
    (``exponential`` or ``heun``); any other name is refused."""
    from ewb_ident.model.integrate import EXPONENTIAL, SEED_HEUN

    if name not in ("exponential", "heun"):
        fail(f"--integrator must be exponential or heun, got {name!r}")
    return SEED_HEUN if name == "heun" else EXPONENTIAL


def sampler_settings(**values):
    """The :class:`~ewb_ident.inference.log_posterior.SamplerSettings` of these values,
    checked before the traces are read: a setting that cannot be used is one line in the
    options' own spelling (:data:`SAMPLER_OPTIONS`), exit 2."""
    from ewb_ident.inference.log_posterior import SampleError, SamplerSettings

    settings = SamplerSettings(**values)
    try:
        settings.check(names=SAMPLER_OPTIONS)
    except SampleError as err:
        fail(str(err))
    return settings


def read_traces(paths: list[Path], stages, mapping, fill_gaps, no_unit_check, r_eff=None):
    import dataclasses

    from ewb_ident.data.campaign import with_pad_radius
    from ewb_ident.data.readers import read_trace
    from ewb_ident.data.validation import (
        R_EFF_RANGE_M,
        UNITS_UNCHECKED,
        check_traces,
        r_eff_ok,
    )

    if r_eff is not None and not r_eff_ok(r_eff):
        lo, hi = R_EFF_RANGE_M
        fail(f"--r-eff must be a pad radius from {lo} to {hi} m, got {r_eff!r}")
    out = []
    for p in paths:
        tr = read_trace(
            p,
            mapping=mapping,
            stages=stages,
            nan_policy="interpolate" if fill_gaps else "raise",
            # With --r-eff the units (the friction torque and force imply) are checked
            # below, with the pad radius given.
            check_units=not no_unit_check and r_eff is None,
        )
        if tr.sidecar.get("_csv_dialect"):
            typer.echo(f"{p}: read as {tr.sidecar['_csv_dialect']}", err=True)
        tr = with_pad_radius(tr, r_eff)
        if r_eff is not None and not no_unit_check:  # checked now, with the pad radius
            side = {k: v for k, v in tr.sidecar.items() if k != UNITS_UNCHECKED}
            tr = dataclasses.replace(tr, sidecar=side)
        out.append(tr)
    return list(check_traces(out))


def bad_input_errors() -> tuple[type[Exception], ...]:
    from ewb_ident.data.trace import TraceError
    from ewb_ident.inference.problem import FitError

    return (TraceError, FitError)


def corrected_options(traces, stage, free, per_trace, fix, integrator) -> None:
    """Refuse options the corrected model does not take (it is one trace, whole chain)."""
    if (
        len(traces) != 1
        or stage != "chain"
        or free
        or per_trace
        or fix
        or integrator != ("exponential")
    ):
        fail(
            "--with/--with-diagnosis take one trace, whole chain, default parameters and "
            "integrator: drop --stage, --free, --per-trace, --fix and --integrator, or give "
            "one trace"
        )


def mechanism_option(
    with_: str | None, with_diagnosis: Path | None
) -> tuple[list[str], list] | None:
    """Catalog mechanism variants from --with and/or an earlier diagnosis, and the
    diagnosis's learned terms (:class:`ewb_ident.diagnosis.learned_spec.LearnedSpec`);
    ``None``: neither option given."""
    if with_ is None and with_diagnosis is None:
        return None
    names = name_list(with_) or []
    specs: list = []
    if with_diagnosis is not None:
        import json

        from ewb_ident.diagnosis.learned_spec import LearnedSpec, TermError

        path = with_diagnosis / "diagnosis.json" if with_diagnosis.is_dir() else with_diagnosis
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            found = [
                f["mechanism"] + (f":{f['form']}" if f.get("form") else "")
                for f in doc["findings"]
                if f.get("catalog", True)
            ]
            learned = [f for f in doc["findings"] if not f.get("catalog", True)]
        except (OSError, ValueError, KeyError, TypeError) as err:
            fail(f"--with-diagnosis {with_diagnosis}: cannot read diagnosis.json ({err})")
        found = [m for m in found if not m.startswith("unexplained_")]
        try:
            specs = [
                LearnedSpec.from_json(f.get("basis"), f"{path}: finding {f.get('effect')}")
                for f in learned
            ]
        except TermError as err:
            fail(str(err))
        if not found and not specs:
            fail(
                f"--with-diagnosis {with_diagnosis}: the diagnosis found no catalog mechanism "
                "and no learned term (verdict none, or a mismatch nothing explains); fit "
                "without it"
            )
        names += [m for m in found if m not in names]
    if not names and not specs:
        fail("--with: name at least one catalog mechanism")
    return names, specs


def command_line() -> str:
    """The command line as typed when run as ``ewb-ident`` (or ``python -m ewb_ident``);
    from Python, the command and its parsed options."""
    import shlex
    import sys

    if Path(sys.argv[0]).name in ("ewb-ident", "__main__.py"):
        return shlex.join(["ewb-ident", *sys.argv[1:]])
    try:  # typer >= 0.2x runs its own copy of click; older ones run click itself
        from typer._click.globals import get_current_context
    except ImportError:
        from click import get_current_context
    ctx = get_current_context(silent=True)
    if ctx is None:
        return "ewb-ident (called from Python)"
    opts = [f"{k}={v!r}" for k, v in ctx.params.items()]
    return f"{ctx.command_path} ({', '.join(opts)})"


SAMPLER_OPTIONS = {
    "noise_model": "--noise",
    "n_walkers": "--walkers",
    "n_steps": "--steps",
    "max_steps": "--max-steps",
    "n_ensembles": "--ensembles",
    "min_ess": "--min-ess",
    "hdi_prob": "--hdi-prob",
    "max_draws": "--draws",
    "seed": "--seed",
}
"""The command-line option of each sampler setting (``SamplerSettings`` field), for
messages in the options' own spelling (sample, report, batch --posterior)."""
