"""The runtime under the model: compiled programs and where they are kept, threads, and
the process's set-up.

- :mod:`~ewb_ident.runtime.programs`: :func:`~ewb_ident.runtime.programs.program`
  (compile once per configuration and shape, keep in memory), compiler options, the
  padding that lets traces share programs;
- :mod:`~ewb_ident.runtime.store`: compiled programs on disk, and loading them ahead;
- :mod:`~ewb_ident.runtime.threads`: how many threads, a map over them, work made once;
- :mod:`~ewb_ident.runtime.config`: :func:`~ewb_ident.runtime.config.configure`, and
  XLA's flag, set at the package's import (its docstring says why).

The model, inference and diagnosis layers ask this one for compiled programs and threads
and keep no such state of their own. It imports nothing of the package above it (only
:mod:`ewb_ident.data.outputs`' atomic writes, so that an interrupted command removes
half-written cache files too). This file imports nothing: the package's import loads
:mod:`~ewb_ident.runtime.config` alone, without JAX.
"""
