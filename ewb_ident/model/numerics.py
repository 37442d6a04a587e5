"""The package's numerics policy, applied at every public entry point: float64, and one
thread for NumPy's linear algebra.

Float64. JAX's default is float32, whose 7 digits cannot resolve a 3 ms armature against
a seconds-long trace or a bell flank's curvature; a user who forgets
``jax.config.update("jax_enable_x64", True)`` would get silently worse fits. So each
public function that runs JAX code is wrapped by :func:`numerics`, which turns 64-bit
mode on for the call (a no-op when it is on already, as the CLI and the tests set it).
JAX's switch is per thread: code that runs JAX in worker threads (the MCMC ensembles)
turns it on there too. The synthetic rig does the same with its own switch, as it
imports nothing from the model.

One BLAS thread. The solvers factorise small matrices (a few thousand residuals by 15
parameters) thousands of times. OpenBLAS runs them on every core and its threads
spin-wait for each other: the SVD of a 3000 x 14 Jacobian took a couple of hundred
times longer while another process kept the second core busy than alone or with one
thread, which made a test suite or a study running two processes many times slower.
:func:`numerics` holds BLAS to one thread for the call (``threadpoolctl``; JAX's own
CPU threads are not BLAS's and are left alone).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import jax

_P = ParamSpec("_P")
_R = TypeVar("_R")


def numerics(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """Run ``fn`` with JAX's 64-bit mode on and NumPy's BLAS on one thread."""

    @functools.wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with jax.enable_x64(True), one_blas_thread():
            return fn(*args, **kwargs)

    return wrapper


def one_blas_thread() -> contextlib.AbstractContextManager:
    """A context in which the BLAS libraries NumPy and SciPy loaded use one thread."""
    controller = _controller()
    if controller is None:
        return contextlib.nullcontext()
    return controller.limit(limits=1, user_api="blas")


@functools.cache
def _controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()
