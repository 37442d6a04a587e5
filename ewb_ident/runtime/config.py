"""How a process is set up for the package's work: :func:`configure`, and the one
setting made when the package is imported.

:func:`configure` (``ewb_ident.configure()``) is the explicit set-up. The ``ewb-ident``
command calls it at its entry, before any work; a script calls it to work as the
command does. It turns on JAX's 64-bit mode for the process, keeps compiled programs
on disk across runs, and checks ``$EWB_IDENT_THREADS``. None of it is needed for
correct results: every public function computes in float64 whatever the setting
(:mod:`ewb_ident.model.numerics`), and without a cache folder programs are kept in
memory.

The one exception, made at import: XLA's small-loop threshold
(:data:`SMALL_LOOP_BYTES`), set in ``XLA_FLAGS`` when this module is imported, which
``import ewb_ident`` does. Why then and not in :func:`configure`: XLA reads
``XLA_FLAGS`` once per process, when JAX starts its CPU backend, which is at the
process's first JAX computation (not at ``import jax``: the flag may follow that). That
first computation is often the caller's own (an array made with ``jax.numpy`` before
the first fit, a test's setup), so no call into the package, neither :func:`configure`
nor a fit, is reliably before it; a script that imports the package first and computes
afterwards has it in effect without calling anything. So import time is the only
reliable moment. What the import does is bounded: it edits one environment variable
(keeping the user's own ``XLA_FLAGS``, and a threshold the user set), imports no JAX,
starts no backend and sets nothing else; it warns where JAX's backend had started
already. ``tests/test_configure.py`` checks all of this.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

#: XLA's CPU compiler emits a ``while`` loop whose one iteration reads and writes fewer
#: bytes than this as one native loop; a larger one runs as a sequence of kernels
#: dispatched one by one on every iteration (XLA's default threshold: 1024 bytes). The
#: models' loops (the motor's sub-steps, with a Jacobian's tangents: a few kB an
#: iteration) are each some 50-200 kernels of a few numbers, so dispatch dominated them:
#: natively a mechanism's residuals and Jacobian run 1.1-7x faster and compile as fast
#: (``python -m benchmarks.bench_native_loops``), their results equal up to round-off
#: (under 1e-11 relative on the shipped concealed diagnoses). Set through ``XLA_FLAGS``,
#: which XLA reads once, when JAX starts its CPU backend: see :func:`native_small_loops`.
SMALL_LOOP_BYTES = 1 << 20
_LOOP_KEY = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options="


def native_small_loops() -> str:
    """Add :data:`SMALL_LOOP_BYTES` to ``XLA_FLAGS`` (into the user's
    ``--xla_backend_extra_options`` if they gave any) unless they set the threshold
    themselves, and return the threshold JAX's backend uses (part of the compiled
    programs' cache key). When JAX's backend was started before this package was
    imported, the flag cannot take effect: a warning says so, and XLA's default holds
    (the fits run slower; their results differ by round-off)."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    for f in flags:
        if f.startswith(_EXTRA) and f"{_LOOP_KEY}=" in f:
            return f.split(f"{_LOOP_KEY}=", 1)[1].split(",", 1)[0]  # the user's own
    bridge = sys.modules.get("jax._src.xla_bridge")
    started = getattr(bridge, "backends_are_initialized", lambda: False)
    if started():
        warnings.warn(
            "ewb_ident was imported after JAX had started its CPU backend, so its XLA "
            f"option ({_EXTRA}{_LOOP_KEY}={SMALL_LOOP_BYTES}) is off and fits and "
            "diagnoses run 2-5x slower; import ewb_ident before any JAX computation, or "
            "set that option in XLA_FLAGS yourself",
            RuntimeWarning,
            stacklevel=3,
        )
        return "default"
    ours = f"{_LOOP_KEY}={SMALL_LOOP_BYTES}"
    given = [i for i, f in enumerate(flags) if f.startswith(_EXTRA)]
    if given:
        flags[given[-1]] += f",{ours}"
    else:
        flags.append(_EXTRA + ours)
    os.environ["XLA_FLAGS"] = " ".join(flags)
    return str(SMALL_LOOP_BYTES)


#: The small-loop threshold in effect in this process (see :data:`SMALL_LOOP_BYTES`),
#: set here, at import: the module docstring says why.
XLA_SMALL_LOOP_BYTES = native_small_loops()


def default_cache_folder() -> Path | None:
    """Where compiled programs are kept across runs unless told otherwise:
    ``$EWB_IDENT_CACHE`` if set (empty: nowhere, ``None``), else
    ``$XDG_CACHE_HOME/ewb-ident/programs`` (``~/.cache/ewb-ident/programs``)."""
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    cache = os.environ.get("EWB_IDENT_CACHE", str(Path(xdg) / "ewb-ident" / "programs"))
    return Path(cache) if cache else None


def configure(cache: bool | str | os.PathLike = True) -> Path | None:
    """Set this process up as the ``ewb-ident`` command does before its work:

    - ``$EWB_IDENT_THREADS`` checked first (a ``ValueError`` says how to fix it, and
      nothing is set);
    - JAX's 64-bit mode on for the whole process (the package's functions turn it on
      for their own call anyway; this is for the caller's JAX code);
    - compiled programs kept on disk across runs (:mod:`ewb_ident.runtime.store`), in
      ``cache`` if it is a folder, in :func:`default_cache_folder` if ``True``, nowhere
      (in memory only) if ``False``.

    XLA's options are not set here: importing the package did (see the module
    docstring; :data:`XLA_SMALL_LOOP_BYTES` says whether it took effect). Calling it
    again sets the same again. Returns the cache folder (``None``: in memory only)."""
    import jax

    from ewb_ident.runtime.store import set_cache_folder
    from ewb_ident.runtime.threads import threads

    threads()
    jax.config.update("jax_enable_x64", True)
    if cache is True:
        folder = default_cache_folder()
    else:
        folder = Path(cache) if cache else None
    set_cache_folder(folder)
    return folder
