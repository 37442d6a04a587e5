"""Threads: how many the package may use, a map over them, and work made once for
several threads that ask for it at the same time."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import jax


def threads() -> int:
    """Threads :func:`parallel_map` may use: ``$EWB_IDENT_THREADS`` if set (1 runs
    everything in the calling thread; the tests set it, as pytest-xdist already runs one
    process per core), else the cores this process may run on."""
    text = os.environ.get("EWB_IDENT_THREADS", "").strip()
    if text:
        try:
            n = int(text)
        except ValueError:
            raise ValueError(
                f"EWB_IDENT_THREADS={text!r} is not a whole number; set it to the number "
                "of threads to use (1: none besides the calling thread), or unset it"
            ) from None
        if n < 1:
            raise ValueError(
                f"EWB_IDENT_THREADS={text!r}: at least 1 thread is needed (1: none besides "
                "the calling thread); set it to 1 or more, or unset it"
            )
        return n
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def parallel_map(fn: Callable, items) -> list:
    """``[fn(x) for x in items]``, run in up to one thread per core (the results in the
    order of ``items``; the first exception raised is raised).

    A compiled program releases Python's lock while it runs, and XLA's compiler while it
    compiles, so independent fits (several starts of one fit, several candidates of a
    diagnosis) run side by side on a multi-core machine. Each call's work must not
    depend on the others': the results are then those of the loop, whatever the
    threads' timing. The workers run with the caller's float precision (JAX's 64-bit
    switch is per thread).
    """
    items = list(items)
    workers = min(len(items), threads())
    if workers <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    x64 = bool(jax.config.jax_enable_x64)  # JAX's switch is per thread: the caller's

    def run(x):
        with jax.enable_x64(x64):
            return fn(x)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(run, items))


def made_once(lock, pending: dict, key, lookup: Callable, make: Callable) -> tuple[Any, bool]:
    """``lookup(key)`` (called under ``lock``) or, where it gives ``None``, ``make()``,
    run by one caller while the others that ask for ``key`` meanwhile wait for its
    result (``pending``: the keys being made, shared by the callers). ``make`` keeps
    what it made where ``lookup`` finds it. Returns the value and whether this caller
    made it; an exception of ``make`` reaches the waiting callers too."""
    with lock:
        value = lookup(key)
        waiting = pending.get(key) if value is None else None
        if value is None and waiting is None:
            pending[key] = mine = Future()
    if value is not None:
        return value, False
    if waiting is not None:
        return waiting.result(), False
    try:
        value = make()
    except BaseException as err:
        with lock:
            del pending[key]
        mine.set_exception(err)
        raise
    with lock:
        del pending[key]
    mine.set_result(value)
    return value, True
