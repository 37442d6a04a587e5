"""The ``ewb-ident`` command line: parse, validate, call the library, write files.

Every command reads traces, does its work in memory, and writes its files only at the
end, atomically. Bad input (a trace, a mapping, an option) prints one line naming the
file, column, row and what to do, and exits with code 2; nothing is written.
"""

from __future__ import annotations

import sys
from typing import Annotated

import typer

from ewb_ident.cli.options import app

# Importing the command modules registers their commands with ``app``, in this order
# (the order of ``ewb-ident --help``).
# isort: off
from ewb_ident.cli import fit, simulate, sample, study, report  # noqa: F401
from ewb_ident.cli import diagnose, compare, validate, batch  # noqa: F401
# isort: on


def _reflowed(doc: str) -> str:
    """A docstring as help text: each paragraph one line (Typer keeps the docstring's
    line breaks, which the terminal's width then breaks again mid-sentence)."""
    import inspect

    paragraphs = inspect.cleandoc(doc).split("\n\n")
    return "\n\n".join(" ".join(line.strip() for line in p.splitlines()) for p in paragraphs)


for _info in app.registered_commands:
    if _info.help is None and _info.callback is not None and _info.callback.__doc__:
        _info.help = _reflowed(_info.callback.__doc__)


@app.callback(invoke_without_command=True)
def _main(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
    verbose: Annotated[
        bool,
        typer.Option(
            "--verbose",
            help="At the end, print to stderr how many compiled programs were reused "
            "(from memory or the on-disk cache) and how many were compiled.",
        ),
    ] = False,
) -> None:
    if verbose:
        import atexit

        from ewb_ident.runtime.programs import describe_stats
        from ewb_ident.runtime.store import DISK_ERRORS

        def report() -> None:
            sys.stderr.write(describe_stats() + "\n")
            for err in DISK_ERRORS:
                sys.stderr.write(f"  cache: {err}\n")

        atexit.register(report)
    if version:
        from importlib.metadata import version as _v

        typer.echo(f"ewb-ident {_v('ewb-ident')}")
        raise typer.Exit(0)


def main() -> None:
    """Entry point of the ``ewb-ident`` script: :func:`ewb_ident.configure`, then the
    command."""
    from ewb_ident.cli import interrupts

    interrupts.install()  # SIGINT / SIGTERM end the run at once, leaving no file of it

    command = next((a for a in sys.argv[1:] if not a.startswith("-")), None)
    if command not in ("study", "batch"):
        # Only ``study --scheduler`` and ``batch --scheduler`` use dask. Where it is
        # installed, xarray and ArviZ import it, and dask.distributed, for every array
        # they make (0.4-0.5 s of ``sample``, for arrays that are all NumPy). A ``None``
        # in ``sys.modules`` makes ``import dask`` raise ImportError, which both take for
        # "no dask"; the files are the same (tests/test_posterior.py).
        sys.modules.setdefault("dask", None)
    # The process's set-up (:func:`ewb_ident.configure`): float64 on, and compiled programs
    # kept on disk, so a second run of a command neither traces nor compiles them (JAX's
    # own cache stays off: an executable it loaded does not serialise whole into ours).
    from ewb_ident.runtime.config import configure

    try:
        configure()  # checks $EWB_IDENT_THREADS before any work starts
    except ValueError as err:
        sys.stderr.write(f"error: {err}\n")
        raise SystemExit(2) from None
    try:
        app()
    except SystemExit as done:
        interrupts.hold_if_ending()
        _exit_now(done)
    except BaseException:
        interrupts.hold_if_ending()
        raise
    raise SystemExit(0)  # typer's app always exits; this keeps the contract if it did not


def _exit_now(done: SystemExit) -> None:
    """End the process with ``done``'s exit code once the command has finished: its
    files are written and closed, the output is flushed and the ``atexit`` callbacks
    (``--verbose``'s summary, logging) have run. The interpreter's own teardown of
    the modules (jax, scipy, matplotlib) is skipped: it took a noticeable share of a
    short diagnosis and does nothing the next run can see. A code that
    is not a number (a message) takes the ordinary way out."""
    import atexit
    import os

    code = 0 if done.code is None else done.code
    if not isinstance(code, int):
        raise done
    atexit._run_exitfuncs()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed or broken pipe: let Python report it
        raise done from None
    os._exit(code)
