"""Compiled programs on disk: the folder, reading and writing them, and loading ahead.

Where: the folder given to :func:`set_cache_folder` (:func:`ewb_ident.configure` and the
CLI give ``$XDG_CACHE_HOME/ewb-ident/programs``, or ``$EWB_IDENT_CACHE``; see the
README), capped at :data:`MAX_DISK_BYTES` (least recently used files go first). A
program is stored as its serialised executable (``jax.experimental.serialize_executable``)
in ``<key>.bin``, the key made by :mod:`ewb_ident.runtime.programs`.

Loading ahead: within :func:`prefetching` (a diagnosis), the programs the last run of
the same work used are loaded from disk in a background thread while the work computes;
each run records its programs in a small ``.keys`` file beside them.

:data:`LOCK` guards the state the runtime shares between threads: here the programs
loaded ahead and the counts, in :mod:`~ewb_ident.runtime.programs` the programs in
memory and those being made.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pickle
import threading
from collections.abc import Container
from concurrent.futures import Future
from pathlib import Path

import jax

from ewb_ident.runtime.threads import threads

#: Largest total size of the on-disk programs, bytes.
MAX_DISK_BYTES = 2 * 1024**3
#: The on-disk folder's size is checked after every this many programs written.
TRIM_EVERY = 32
#: Hits in memory, hits on disk, compilations, and failed disk reads or writes.
STATS: dict[str, int] = {"memory": 0, "disk": 0, "compiled": 0, "disk_errors": 0}
#: The last few disk errors, in words (shown by ``--verbose``).
DISK_ERRORS: list[str] = []
#: The one lock over the runtime's shared state (see the module docstring).
LOCK = threading.Lock()

_STORES = [0]
_FOLDER: list[Path | None] = [None]


def set_cache_folder(folder: str | os.PathLike | None) -> None:
    """Keep compiled programs in ``folder`` across runs (``None``: in memory only)."""
    _FOLDER[0] = Path(folder) if folder else None


def cache_folder() -> Path | None:
    """The folder of on-disk programs, or ``None`` (memory only)."""
    return _FOLDER[0]


def disk_error(text: str) -> None:
    """Count a failed disk read or write and keep its first line (for ``--verbose``)."""
    STATS["disk_errors"] += 1
    DISK_ERRORS.append(text.splitlines()[0][:300])
    del DISK_ERRORS[:-5]


def discard(key: str) -> None:
    """Remove the stored program of ``key``, if any."""
    folder = cache_folder()
    if folder is not None:
        with contextlib.suppress(OSError):
            (folder / f"{key}.bin").unlink()


def load(key: str):
    """The stored program of ``key``: loaded ahead by :func:`prefetching`'s thread (waited
    for if it is loading it now), else read from disk here; ``None`` if there is none."""
    with LOCK:
        ahead = _AHEAD.pop(key, None)  # queued (None): not loaded yet, so read here
    if ahead is not None:
        exe = ahead.result()
        if exe is not None:
            return exe
    return read(key)


def read(key: str):
    """The program stored under ``key``, read from disk; ``None`` where there is none (or
    it is damaged: then it is removed)."""
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
        disk_error(f"loading {path.name}: {err}")
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


def write(key: str, exe) -> None:
    """Store the compiled program ``exe`` under ``key`` (nothing without a folder; a
    failure is counted, not raised)."""
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
        disk_error(f"storing a program: {err}")


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


def asked(key: str, held: Container[str]) -> None:
    """Tell the active :func:`prefetching` scope, if any, that the program of ``key`` is
    asked for; ``held``: the keys of the programs in memory (not to be loaded ahead)."""
    scope = _SCOPE[0]
    if scope is not None:
        scope.asked(key, held)


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

    def asked(self, key: str, held: Container[str]) -> None:
        with LOCK:
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
        with LOCK:
            queue = [k for k in self.known if k != key and k not in held]
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
                with LOCK:
                    if self.stop.is_set():
                        return
                    if k not in _AHEAD or _AHEAD[k] is not None:
                        continue  # a caller took it off the queue
                    _AHEAD[k] = mine = Future()
                try:
                    mine.set_result(read(k))
                except Exception as err:  # the caller reads it again
                    disk_error(f"loading ahead: {err}")
                    mine.set_result(None)

    def close(self) -> None:
        """Stop the loader (after the program it is loading, if any), drop what it
        loaded that nothing asked for, and record this scope's programs."""
        self.stop.set()
        if self.thread is not None:
            self.thread.join()
        with LOCK:
            _AHEAD.clear()
        if len(self.keys) > 1 and self.keys[1:] != self.known:
            from ewb_ident.data.outputs import atomic_write

            text = "\n".join(self.keys[1:]) + "\n"
            try:
                atomic_write([(self.record(), lambda tmp: tmp.write_text(text, "ascii"))])
            except OSError as err:
                disk_error(f"recording the programs of {self.label}: {err}")


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
    (:func:`~ewb_ident.runtime.threads.threads`), or inside another such scope (the
    outer one records).
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
