"""SIGINT / SIGTERM: end the run at once with 130 / 143, leaving no file of it.

Python runs a signal handler in the main thread between two bytecodes, so a handler
alone waits for the C call the main thread is in: a compiled program over a long trace,
a least-squares solve of a 600,000-row Jacobian, a file being read (seconds each). The
signal's number is therefore also written, by the interpreter's C-level handler, to a
socket (:func:`signal.set_wakeup_fd`) that a thread of ours waits on; that thread ends
the process as soon as it holds the interpreter, which such calls release. Whichever of
the two comes first removes what the run left (:func:`ewb_ident.data.outputs.remove_pending`:
temporary files of atomic writes, a study script's staging folder, a folder the run
made) and ends the process (an exception raised instead could land in a callback that
swallows it, e.g. JAX's garbage-collection hook).
"""

from __future__ import annotations

import os
import signal
import sys
import threading

#: Held by whichever of the handler and the watching thread ends the process.
_ENDING = threading.Lock()
#: The wakeup socket pair, kept open for the process's life (a socket closes when it is
#: collected, and the interpreter writes to its number).
_WAKEUP: list = []


def end(signum: int) -> None:
    """Remove what the run left and end the process with 128 + the signal's number
    (130 for SIGINT, 143 for SIGTERM). A second call while the first is ending
    returns at once."""
    if not _ENDING.acquire(blocking=False):
        return
    from ewb_ident.data.outputs import remove_pending

    try:
        # The run's main thread, still running, takes the interpreter back after each
        # of the removal's system calls for the default 5 ms: hand it over at once.
        sys.setswitchinterval(1e-6)
        # What the run's other thread says from now on (an error of a file removed
        # under it) is not the run's outcome: it goes nowhere.
        sys.stdout = sys.stderr = open(os.devnull, "w")  # noqa: SIM115
        remove_pending()
        os.write(2, b"interrupted\n")
    finally:
        os._exit(130 if signum == signal.SIGINT else 143)


def hold_if_ending() -> None:
    """Wait for ever if another thread is ending the process (:func:`end`): a command
    that finishes meanwhile must not exit with its own code."""
    if _ENDING.locked():
        threading.Event().wait()


def _handler(signum, frame) -> None:
    end(signum)


def _watch(reader) -> None:
    """Wait for a signal's number on ``reader`` (the interpreter's wakeup socket) and
    end the process on SIGINT or SIGTERM."""
    while True:
        try:
            data = reader.recv(64)
        except OSError:
            return
        if not data:
            return
        for signum in data:
            if signum in (signal.SIGINT, signal.SIGTERM):
                end(signum)


def install() -> None:
    """Handle SIGINT and SIGTERM as :func:`end` (call from the main thread, once)."""
    import socket

    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)
    try:
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
    except (OSError, ValueError):  # no socket pair here: the handler alone
        return
    _WAKEUP[:] = [reader, writer]
    threading.Thread(
        target=_watch, args=(reader,), name="ewb-ident-interrupts", daemon=True
    ).start()
