"""Compiled programs, kept in memory and on disk, so a program is traced, lowered and
compiled once per machine and not once per call, trace or run.

:func:`program` wraps a pure function as ``equinox.filter_jit`` does: its array
arguments (JAX or NumPy) are traced, everything else (Python numbers, strings, the
static fields of modules such as a residual function's configuration) is fixed in the
program. Each compiled program is kept under a key made of

- the function's name;
- the structure and values of the fixed arguments (``repr``);
- the structure, shapes and dtypes of the traced arguments;
- the JAX and jaxlib versions, the float precision, the backend, XLA's small-loop
  threshold (:data:`ewb_ident.runtime.config.XLA_SMALL_LOOP_BYTES`); and
- a digest of this package's source files (a changed model never loads old code).

On a hit nothing is traced, lowered or compiled. JAX's own on-disk cache stores only
XLA's compilation, after the tracing and lowering that dominate a diagnosis's programs
(measured: 18.5 of 21 s of a diagnosis whose XLA code was all cached); this cache stores
the executable (``jax.experimental.serialize_executable``) and skips all three.

Where: in memory (the last :data:`MAX_IN_MEMORY` programs), and on disk
(:mod:`ewb_ident.runtime.store`: the folder, its size cap, loading ahead).
:data:`STATS` counts hits and compilations (shown by ``ewb-ident --verbose``). A stored
program is checked on its first run in a process and compiled afresh if it fails. JAX's
own on-disk cache must not hold these programs: an executable it loaded from there
serialises without its compiled kernels.
"""

from __future__ import annotations

import functools
import hashlib
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import equinox as eqx
import jax

from ewb_ident.runtime import config, store
from ewb_ident.runtime.store import LOCK, STATS
from ewb_ident.runtime.threads import made_once

#: Programs kept in memory (least recently used dropped first).
MAX_IN_MEMORY = 256
#: Per program (function name): how many were compiled and the seconds it took (tracing,
#: lowering and XLA's compilation), shown by ``--verbose``.
COMPILE_TIME: dict[str, tuple[int, float]] = {}

_MEMORY: OrderedDict[str, Any] = OrderedDict()
#: Programs being loaded or compiled by one thread, which others wait for.
_PENDING: dict[str, Future] = {}


def program(fun: Callable | None = None, *, options: Mapping[str, Any] | None = None):
    """``fun`` compiled per fixed configuration and argument shapes, and kept (see the
    module docstring). The outputs must be arrays in lists, tuples and dicts. Called
    while another program is traced, ``fun`` is traced into it.

    ``options``: XLA options of this program on top of :data:`COMPILER_OPTIONS`
    (``@program(options=...)``); e.g. :data:`FAST_COMPILE`."""
    if fun is None:
        return functools.partial(program, options=options)
    extra = dict(options or {})
    name = f"{fun.__module__}.{fun.__qualname__}"

    @functools.wraps(fun)
    def call(*args):
        leaves, treedef, static = _split(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return fun(*args)  # called inside another program: part of it
        key = _key(name, static, treedef, leaves)
        store.asked(key, _MEMORY)

        def compiled():
            # A flat list in, so the stored program's input structure holds no module
            # (a module's structure does not rebuild from placeholders).
            def traced(flat):
                return fun(*eqx.combine(jax.tree_util.tree_unflatten(treedef, flat), static))

            t0 = time.perf_counter()
            exe = _compile(jax.jit(traced).lower(leaves), extra)
            with LOCK:
                STATS["compiled"] += 1
                n, secs = COMPILE_TIME.get(name, (0, 0.0))
                COMPILE_TIME[name] = (n + 1, secs + time.perf_counter() - t0)
            store.write(key, exe)
            return exe

        def in_memory(k):
            exe = _MEMORY.get(k)
            if exe is not None:
                _MEMORY.move_to_end(k)
            return exe

        first = []  # the maker's first run, checked when the program was loaded

        def load_or_compile():
            exe = store.load(key)
            if exe is not None:
                # A stored program is checked on its first run, call and result: one that
                # fails (a file from another build of jaxlib, or one compiled from JAX's
                # own cache without its kernels) is compiled afresh.
                try:
                    first.append(jax.block_until_ready(exe(leaves)))
                    with LOCK:
                        STATS["disk"] += 1
                except Exception as err:
                    store.disk_error(f"{name}: stored program failed on its first run: {err}")
                    _forget(key)
                    exe = None
            if exe is None:
                exe = compiled()
                first.append(exe(leaves))
            _remember(key, exe)
            return exe

        # One caller makes a program that is not in memory (loads or compiles it); others
        # that ask for it meanwhile (a diagnosis fits from several threads) wait for it.
        exe, made = made_once(LOCK, _PENDING, key, in_memory, load_or_compile)
        if made:
            return first[0]
        with LOCK:
            STATS["memory"] += 1
        return exe(leaves)

    def bind(*fixed):
        """``call`` with its leading arguments ``fixed``: a function of the remaining
        ones, all arrays, that looks its program up once per shape and dtype of them
        and then calls it directly, without splitting and hashing the fixed arguments
        again (0.3 of the 0.8 ms a call of the posterior's log density took, which
        emcee makes thousands of times). Same program, same inputs: same outputs."""
        f_leaves = [jax.device_put(x) for x in _split(fixed)[0]]
        found: dict[tuple, Any] = {}

        def bound(*rest):
            if not all(eqx.is_array(x) for x in rest):
                raise TypeError(f"{name}: the arguments after the bound ones must be arrays")
            sig = tuple((x.shape, x.dtype.str) for x in rest)
            exe = found.get(sig)
            if exe is None:
                out = call(*fixed, *rest)  # made, loaded or found: now in memory
                leaves, treedef, static = _split((*fixed, *rest))
                with LOCK:
                    exe = _MEMORY.get(_key(name, static, treedef, leaves))
                if exe is not None:
                    found[sig] = exe
                return out
            with LOCK:
                STATS["memory"] += 1
            return exe([*f_leaves, *rest])

        return bound

    call.__wrapped__ = fun
    call.bind = bind
    return call


def _split(args: tuple) -> tuple[list, Any, Any]:
    """A program's arguments as its traced leaves, their structure and the fixed rest."""
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    return leaves, treedef, static


#: XLA options of every program: XLA's CPU fusion emitters off (the elemental emitters
#: instead) about halves the compilation of a mechanism's program for the same speed of
#: the program; residuals equal bit for bit, Jacobians to 1e-13 relative. And the machine
#: code of a program generated in 4 parts side by side, not XLA's default split: it
#: compiles a little faster, the programs bit for bit the same
#: (``python -m benchmarks.bench_compiler_options`` measures both). A jaxlib that does not know an
#: option compiles without it.
COMPILER_OPTIONS: dict[str, Any] = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_parallel_codegen_split_count": 4,
}

#: XLA's fast-compile preset, for programs built around a long loop of small scalar
#: kernels (the motor with mechanisms: each sub-step is some 40-70 kernels of a few
#: numbers). Such a program runs faster with it (``bench_compiler_options.py`` gives
#: the ratios, e.g. stiction with wedge load torque's residuals and Jacobian) and
#: compiles in about the same time, its outputs equal to 2e-14 relative; the seed
#: model's programs compile 20-25 % slower with it, so it is not every program's
#: (``python -m benchmarks.bench_compiler_options``). Those figures predate native loops
#: (:data:`ewb_ident.runtime.config.SMALL_LOOP_BYTES`); a by-hand A/B since then still
#: found the stiction diagnosis faster with the preset, cold and filled.
FAST_COMPILE: dict[str, Any] = {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"}
#: Option sets this jaxlib refused (one holds an option it does not know).
_REFUSED: set[tuple] = set()


def _compile(lowered, extra: Mapping[str, Any] | None = None):
    """``lowered.compile()`` with :data:`COMPILER_OPTIONS` and ``extra`` where jaxlib
    knows them: a set it refuses is retried without ``extra``, then without options."""
    if jax.default_backend() == "cpu":
        for opts in (COMPILER_OPTIONS | dict(extra or {}), COMPILER_OPTIONS):
            key = tuple(sorted(opts.items()))
            if not opts or key in _REFUSED:
                continue
            try:
                return lowered.compile(compiler_options=opts)
            except Exception as err:  # an option (or value) this jaxlib does not have
                if not any(m in str(err) for m in ("compile option", "setting option")):
                    raise
                with LOCK:
                    _REFUSED.add(key)
    return lowered.compile()


def _remember(key: str, exe) -> None:
    with LOCK:
        _MEMORY[key] = exe
        while len(_MEMORY) > MAX_IN_MEMORY:
            _MEMORY.popitem(last=False)


def _forget(key: str) -> None:
    with LOCK:
        _MEMORY.pop(key, None)
    store.discard(key)


def clear_memory() -> None:
    """Drop the programs kept in memory (with ``jax.clear_caches()``, to release their
    code: a long study compiles thousands)."""
    with LOCK:
        _MEMORY.clear()


def release() -> None:
    """Release compiled code held in this process: JAX's caches and the programs kept in
    memory (a long study compiles thousands and would exhaust the process's memory
    maps). Programs on disk stay."""
    jax.clear_caches()
    clear_memory()


def describe_stats() -> str:
    """The cache's hits and compilations so far, in words (for ``--verbose``)."""
    s = STATS
    total = s["memory"] + s["disk"] + s["compiled"]
    if not total:
        return "compiled programs: none used"
    hits = s["memory"] + s["disk"]
    where = store.cache_folder()
    text = (
        f"compiled programs: {total} calls, {hits} reused ({s['memory']} in memory, "
        f"{s['disk']} from {where or 'disk'}), {s['compiled']} compiled"
        + (f", {s['disk_errors']} disk errors" if s["disk_errors"] else "")
    )
    costs = sorted(COMPILE_TIME.items(), key=lambda kv: -kv[1][1])
    if costs:
        text += f" in {sum(t for _, t in COMPILE_TIME.values()):.1f} s: " + ", ".join(
            f"{name.rsplit('.', 1)[-1]} {n}x {t:.1f} s" for name, (n, t) in costs
        )
    return text


def on_device(tree):
    """``tree``'s numbers and arrays as device arrays (floats as float64), without the
    small program ``jnp.asarray`` compiles for every new shape (10-20 ms each; a
    diagnosis made some fifty of them in every run). Python floats become float64
    arrays, not weakly typed ones, so programs see the same argument types whoever
    prepared their data."""
    import numpy as np

    def leaf(x):
        if isinstance(x, jax.Array):
            return x
        arr = np.asarray(x)
        return jax.device_put(arr.astype(float) if arr.dtype.kind == "f" else arr)

    return jax.tree_util.tree_map(leaf, tree)


# ----------------------------------------------------------------------------- lengths

#: Traces are padded to a multiple of this many samples (the padding weighted zero), so
#: that traces of similar length share one compiled program.
PAD = 128


def padded_length(n: int) -> int:
    """``n`` rounded up to a multiple of :data:`PAD`."""
    return int(-(-n // PAD) * PAD)


def pad_to(y, n_pad: int):
    """``y`` (1-D) extended to ``n_pad`` samples by holding its last value."""
    import numpy as np

    y = np.asarray(y, dtype=float)
    return np.concatenate([y, np.full(n_pad - y.size, y[-1])]) if n_pad > y.size else y


# ----------------------------------------------------------------------------- keys


@functools.cache
def _source_digest() -> str:
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _environment() -> str:
    import jaxlib

    return "|".join(
        (
            jax.__version__,
            jaxlib.__version__,
            str(jax.config.jax_enable_x64),
            jax.default_backend(),
            config.XLA_SMALL_LOOP_BYTES,
            _source_digest(),
        )
    )


def _key(name: str, static: Any, treedef: Any, leaves: list) -> str:
    s_leaves, s_def = jax.tree_util.tree_flatten(static)
    # dtype.str ("<f8"), not str(dtype): numpy's name lookup costs 5 us a leaf per call.
    shapes = [(x.shape, x.dtype.str, bool(getattr(x, "weak_type", False))) for x in leaves]
    text = "\n".join(
        (name, repr(s_def), repr(s_leaves), repr(treedef), repr(shapes), _environment())
    )
    return hashlib.sha256(text.encode()).hexdigest()
