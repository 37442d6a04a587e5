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
  threshold (:data:`ewb_ident.SMALL_LOOP_BYTES`); and
- a digest of this package's source files (a changed model never loads old code).

On a hit nothing is traced, lowered or compiled. JAX's own on-disk cache stores only
XLA's compilation, after the tracing and lowering that dominate a diagnosis's programs
(measured: 18.5 of 21 s of a diagnosis whose XLA code was all cached); this cache stores
the executable (``jax.experimental.serialize_executable``) and skips all three.

Where: in memory (the last :data:`MAX_IN_MEMORY` programs), and on disk in the folder
given to :func:`set_cache_folder` (the CLI gives ``$XDG_CACHE_HOME/ewb-ident/programs``,
or ``$EWB_IDENT_CACHE``; see the README), capped at :data:`MAX_DISK_BYTES` (least
recently used files go first). :data:`STATS` counts hits and compilations (shown by
``ewb-ident --verbose``). A stored program is checked on its first run in a process and
compiled afresh if it fails. JAX's own on-disk cache must not hold these programs: an
executable it loaded from there serialises without its compiled kernels.

Loading ahead: within :func:`prefetching` (a diagnosis), the programs the last run of
the same work used are loaded from disk in a background thread while the work computes;
each run records its programs in a small ``.keys`` file beside them.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pickle
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import equinox as eqx
import jax

#: Programs kept in memory (least recently used dropped first).
MAX_IN_MEMORY = 256
#: Largest total size of the on-disk programs, bytes.
MAX_DISK_BYTES = 2 * 1024**3
#: Hits in memory, hits on disk, compilations, and failed disk reads or writes.
STATS: dict[str, int] = {"memory": 0, "disk": 0, "compiled": 0, "disk_errors": 0}
#: Per program (function name): how many were compiled and the seconds it took (tracing,
#: lowering and XLA's compilation), shown by ``--verbose``.
COMPILE_TIME: dict[str, tuple[int, float]] = {}

#: The on-disk folder's size is checked after every this many programs written.
TRIM_EVERY = 32

_MEMORY: OrderedDict[str, Any] = OrderedDict()
#: Programs being loaded or compiled by one thread, which others wait for.
_PENDING: dict[str, Future] = {}
_LOCK = threading.Lock()
_STORES = [0]


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
        scope = _SCOPE[0]
        if scope is not None:
            scope.asked(key)

        def compiled():
            # A flat list in, so the stored program's input structure holds no module
            # (a module's structure does not rebuild from placeholders).
            def traced(flat):
                return fun(*eqx.combine(jax.tree_util.tree_unflatten(treedef, flat), static))

            t0 = time.perf_counter()
            exe = _compile(jax.jit(traced).lower(leaves), extra)
            with _LOCK:
                STATS["compiled"] += 1
                n, secs = COMPILE_TIME.get(name, (0, 0.0))
                COMPILE_TIME[name] = (n + 1, secs + time.perf_counter() - t0)
            _store(key, exe)
            return exe

        def in_memory(k):
            exe = _MEMORY.get(k)
            if exe is not None:
                _MEMORY.move_to_end(k)
            return exe

        first = []  # the maker's first run, checked when the program was loaded

        def load_or_compile():
            exe = _load(key)
            if exe is not None:
                # A stored program is checked on its first run, call and result: one that
                # fails (a file from another build of jaxlib, or one compiled from JAX's
                # own cache without its kernels) is compiled afresh.
                try:
                    first.append(jax.block_until_ready(exe(leaves)))
                    with _LOCK:
                        STATS["disk"] += 1
                except Exception as err:
                    _disk_error(f"{name}: stored program failed on its first run: {err}")
                    _forget(key)
                    exe = None
            if exe is None:
                exe = compiled()
                first.append(exe(leaves))
            _remember(key, exe)
            return exe

        # One caller makes a program that is not in memory (loads or compiles it); others
        # that ask for it meanwhile (a diagnosis fits from several threads) wait for it.
        exe, made = made_once(_LOCK, _PENDING, key, in_memory, load_or_compile)
        if made:
            return first[0]
        with _LOCK:
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
                with _LOCK:
                    exe = _MEMORY.get(_key(name, static, treedef, leaves))
                if exe is not None:
                    found[sig] = exe
                return out
            with _LOCK:
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
#: (:data:`ewb_ident.SMALL_LOOP_BYTES`); a by-hand A/B since then still found the
#: stiction diagnosis faster with the preset, cold and filled.
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
                with _LOCK:
                    _REFUSED.add(key)
    return lowered.compile()


#: The last few disk errors, in words (shown by ``--verbose``).
DISK_ERRORS: list[str] = []


def _disk_error(text: str) -> None:
    STATS["disk_errors"] += 1
    DISK_ERRORS.append(text.splitlines()[0][:300])
    del DISK_ERRORS[:-5]


def _remember(key: str, exe) -> None:
    with _LOCK:
        _MEMORY[key] = exe
        while len(_MEMORY) > MAX_IN_MEMORY:
            _MEMORY.popitem(last=False)


def _forget(key: str) -> None:
    with _LOCK:
        _MEMORY.pop(key, None)
    folder = cache_folder()
    if folder is not None:
        with contextlib.suppress(OSError):
            (folder / f"{key}.bin").unlink()


def clear_memory() -> None:
    """Drop the programs kept in memory (with ``jax.clear_caches()``, to release their
    code: a long study compiles thousands)."""
    with _LOCK:
        _MEMORY.clear()


_FOLDER: list[Path | None] = [None]


def set_cache_folder(folder: str | os.PathLike | None) -> None:
    """Keep compiled programs in ``folder`` across runs (``None``: in memory only)."""
    _FOLDER[0] = Path(folder) if folder else None


def release() -> None:
    """Release compiled code held in this process: JAX's caches and the programs kept in
    memory (a long study compiles thousands and would exhaust the process's memory
    maps). Programs on disk stay."""
    jax.clear_caches()
    clear_memory()


def cache_folder() -> Path | None:
    """The folder of on-disk programs, or ``None`` (memory only)."""
    return _FOLDER[0]


def describe_stats() -> str:
    """The cache's hits and compilations so far, in words (for ``--verbose``)."""
    s = STATS
    total = s["memory"] + s["disk"] + s["compiled"]
    if not total:
        return "compiled programs: none used"
    hits = s["memory"] + s["disk"]
    where = cache_folder()
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

    from ewb_ident import XLA_SMALL_LOOP_BYTES

    return "|".join(
        (
            jax.__version__,
            jaxlib.__version__,
            str(jax.config.jax_enable_x64),
            jax.default_backend(),
            XLA_SMALL_LOOP_BYTES,
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


# ----------------------------------------------------------------------------- disk


def _load(key: str):
    """The stored program of ``key``: loaded ahead by :func:`prefetching`'s thread (waited
    for if it is loading it now), else read from disk here; ``None`` if there is none."""
    with _LOCK:
        ahead = _AHEAD.pop(key, None)  # queued (None): not loaded yet, so read here
    if ahead is not None:
        exe = ahead.result()
        if exe is not None:
            return exe
    return _read(key)


def _read(key: str):
    folder = cache_folder()
    if folder is None:
        return None
    path = folder / f"{key}.bin"
    if not path.is_file():
        return None
    from jax.experimental import serialize_executable

    try:
        stored = pickle.loads(path.read_bytes())
        blob, in_tree, out_tree = stored[:3]
        if len(stored) < 4 or stored[3]:  # calls LAPACK (files before the flag: perhaps)
            _prime_linalg()
        exe = serialize_executable.deserialize_and_load(blob, in_tree, out_tree)
        os.utime(path)  # recently used
        return exe
    except Exception as err:  # a damaged or foreign file: compile instead
        _disk_error(f"loading {path.name}: {err}")
        with contextlib.suppress(OSError):
            path.unlink()
        return None


_LINALG_LOCK = threading.Lock()


def _prime_linalg() -> None:
    """:func:`_set_up_linalg` once per process, whichever thread loads a program first."""
    with _LINALG_LOCK:
        _set_up_linalg()


@functools.cache
def _set_up_linalg() -> None:
    """Set up jaxlib's LAPACK kernels before a stored program is loaded: jaxlib does it
    when it first compiles a LAPACK call, and a stored program that calls one crashes
    the process (a segmentation fault) if loaded before. jax's own deserialisation of
    exported programs calls the same initialiser; where a jax release lacks it, one
    small program of each routine the solvers use is compiled instead (0.6 s)."""
    try:
        from jax._src.lax.linalg import initialize_lapack
    except ImportError:
        initialize_lapack = None
    if initialize_lapack is not None:
        initialize_lapack()
        return
    import jax.numpy as jnp

    def f(a, b):
        q, r = jnp.linalg.qr(a)
        return (
            jnp.linalg.solve(a, b), q, r, jnp.linalg.cholesky(a), jnp.linalg.svd(a),
            jnp.linalg.eigh(a), jax.scipy.linalg.lu_factor(a), jnp.linalg.lstsq(a, b)
        )  # fmt: skip

    a = jnp.eye(2) * 2.0
    jax.jit(f).lower(a, jnp.ones(2)).compile()


def _store(key: str, exe) -> None:
    folder = cache_folder()
    if folder is None:
        return
    from jax.experimental import serialize_executable

    from ewb_ident.data.outputs import atomic_write

    try:
        uses_lapack = "lapack" in exe.as_text()
        data = pickle.dumps((*serialize_executable.serialize(exe), uses_lapack))
        folder.mkdir(parents=True, exist_ok=True)
        # Written whole, then renamed: a concurrent reader never sees half a file.
        atomic_write([(folder / f"{key}.bin", lambda tmp: tmp.write_bytes(data))])
        _STORES[0] += 1
        if _STORES[0] % TRIM_EVERY == 0:
            _trim(folder)
    except Exception as err:  # a full disk or an executable that does not serialise
        _disk_error(f"storing a program: {err}")


def _trim(folder: Path) -> None:
    paths = [*folder.glob("*.bin"), *folder.glob("*.keys")]
    files = [(p.stat().st_mtime, p.stat().st_size, p) for p in paths]
    total = sum(size for _, size, _ in files)
    for _, size, path in sorted(files):
        if total <= MAX_DISK_BYTES:
            break
        with contextlib.suppress(OSError):
            path.unlink()
            total -= size


# ----------------------------------------------------------------------------- ahead

#: The active :func:`prefetching` scope, or ``None``.
_SCOPE: list[_Scope | None] = [None]
#: Stored programs the scope's thread is to load ahead: ``None`` while queued (a caller
#: that asks for it first takes it off the queue and loads it itself), then a
#: ``Future`` of the program (``None`` where the file is missing or damaged).
_AHEAD: dict[str, Future | None] = {}


class _Scope:
    """The programs one :func:`prefetching` scope asks for, in order, and its loader."""

    def __init__(self, label: str, folder: Path):
        self.label, self.folder = label, folder
        self.keys: list[str] = []
        self.seen: set[str] = set()
        self.known: list[str] = []
        self.stop = threading.Event()
        self.thread: threading.Thread | None = None

    def record(self) -> Path:
        """The file that lists the programs asked for after the first, last time."""
        text = f"{self.label}\n{self.keys[0]}"
        return self.folder / f"{hashlib.sha256(text.encode()).hexdigest()[:40]}.keys"

    def asked(self, key: str) -> None:
        with _LOCK:
            if key in self.seen:
                return
            self.seen.add(key)
            self.keys.append(key)
            if len(self.keys) > 1:
                return
        try:
            self.known = self.record().read_text(encoding="ascii").split()
        except (OSError, ValueError):
            return  # nothing recorded yet (or unreadable): nothing to load ahead
        with _LOCK:
            queue = [k for k in self.known if k != key and k not in _MEMORY]
            for k in queue:
                _AHEAD.setdefault(k, None)
        if not queue:
            return  # all in memory already: no loader
        x64 = bool(jax.config.jax_enable_x64)
        self.thread = threading.Thread(
            target=self._load_ahead, args=(queue, x64), name="ewb-ident programs ahead",
            daemon=True,
        )  # fmt: skip
        self.thread.start()

    def _load_ahead(self, queue: list[str], x64: bool) -> None:
        with jax.enable_x64(x64):
            for k in queue:
                with _LOCK:
                    if self.stop.is_set():
                        return
                    if k not in _AHEAD or _AHEAD[k] is not None:
                        continue  # a caller took it off the queue
                    _AHEAD[k] = mine = Future()
                try:
                    mine.set_result(_read(k))
                except Exception as err:  # the caller reads it again
                    _disk_error(f"loading ahead: {err}")
                    mine.set_result(None)

    def close(self) -> None:
        """Stop the loader (after the program it is loading, if any), drop what it
        loaded that nothing asked for, and record this scope's programs."""
        self.stop.set()
        if self.thread is not None:
            self.thread.join()
        with _LOCK:
            _AHEAD.clear()
        if len(self.keys) > 1 and self.keys[1:] != self.known:
            from ewb_ident.data.outputs import atomic_write

            text = "\n".join(self.keys[1:]) + "\n"
            try:
                atomic_write([(self.record(), lambda tmp: tmp.write_text(text, "ascii"))])
            except OSError as err:
                _disk_error(f"recording the programs of {self.label}: {err}")


@contextlib.contextmanager
def prefetching(label: str):
    """Within this context, stored programs are loaded from disk ahead of their first
    call, in one background thread, while the caller computes.

    Which: those the last run of the same work asked for. The work is known by
    ``label`` and the first program it asks for, whose key holds the shapes of its
    arguments (a trace's padded length); ``label`` must name the rest that decides which
    programs follow (e.g. a trace's channels, which a fit's program takes as data).
    Once that first program is asked for,
    the thread loads the ones that run asked for after it, in their order. A program
    asked for before the thread reaches it is loaded by the caller, as without this;
    one the thread is loading is waited for. On leaving, the programs asked for are
    recorded for the next run: a small ``.keys`` file among the stored programs.

    A record is only a hint: a wrong or stale one costs loads nobody uses, never a
    result (a loaded program is still checked on its first run). Loading a program
    (jaxlib's ``deserialize_and_load``, some 50-100 ms) releases Python's lock, so
    the loads overlap the caller's computing on another core. Nothing is done without
    a cache folder (:func:`set_cache_folder`), with a single thread
    (:func:`threads`), or inside another such scope (the outer one records).
    """
    folder = cache_folder()
    if folder is None or _SCOPE[0] is not None or threads() < 2:
        yield
        return
    scope = _SCOPE[0] = _Scope(label, folder)
    try:
        yield
    finally:
        _SCOPE[0] = None
        scope.close()


# ----------------------------------------------------------------------------- threads


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
