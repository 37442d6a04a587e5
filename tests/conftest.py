"""Test configuration: float64 everywhere, as the CLI sets it at its entry point
(:func:`ewb_ident.configure`), and on-disk caches of compiled programs in a folder that
starts empty for each test run."""

import gc
import os

import jax
import pytest

from ewb_ident.runtime import programs, store

jax.config.update("jax_enable_x64", True)

if os.environ.get("PYTEST_XDIST_WORKER"):
    # pytest-xdist runs a process per core already: a diagnosis's fits run in the calling
    # thread (threads of their own would only contend with the other workers).
    os.environ.setdefault("EWB_IDENT_THREADS", "1")


@pytest.fixture(autouse=True, scope="session")
def _session_compilation_cache(tmp_path_factory):
    """Compiled programs are cached on disk for this session only, as the CLI caches them
    for a user: a module that needs a program an earlier module compiled loads it instead
    of compiling it again (each module drops its compiled code, below). The folder starts
    empty, so every session still compiles each program once and nothing carries over
    between sessions. With pytest-xdist the workers of one run share it (pytest's base
    temporary folder of the run; pytest removes old runs' folders)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the run's folder, above each worker's own
    folder = os.path.join(base, "compiled")
    # The package's programs (traced, lowered and compiled once per session), and JAX's
    # cache for the rest (its XLA code only). A program of the package's compiled from
    # JAX's cache (another key, the same code) does not serialise whole; it fails the
    # check on its first load and is compiled afresh (ewb_ident.runtime.programs).
    store.set_cache_folder(os.path.join(folder, "programs"))
    jax.config.update("jax_compilation_cache_dir", os.path.join(folder, "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    yield
    jax.config.update("jax_compilation_cache_dir", None)
    store.set_cache_folder(None)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop compiled XLA code after each test module: the diagnosis compiles a model per
    mechanism set and trace shape, and a whole suite's worth in one process would run
    into the kernel's limit on memory maps (``vm.max_map_count``)."""
    yield
    jax.clear_caches()
    programs.clear_memory()
    gc.collect()
