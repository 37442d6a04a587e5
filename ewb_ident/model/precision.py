"""The package's one precision policy: every public entry point computes in float64.

JAX's default is float32, whose 7 digits cannot resolve a 3 ms armature against a
seconds-long trace or a bell flank's curvature; a user who forgets
``jax.config.update("jax_enable_x64", True)`` would get silently worse fits. So each
public function that runs JAX code is wrapped by :func:`float64`, which turns 64-bit mode
on for the call (a no-op when it is on already, as the CLI and the tests set it).
JAX's switch is per thread: code that runs JAX in worker threads (the MCMC ensembles)
turns it on there too. The synthetic rig does the same with its own switch, as it
imports nothing from the model.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import jax

_P = ParamSpec("_P")
_R = TypeVar("_R")


def float64(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """Run ``fn`` with JAX's 64-bit mode on."""

    @functools.wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapper
