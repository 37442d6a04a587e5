"""Test configuration: float64 everywhere, as the CLI sets it at its entry point."""

import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop compiled XLA code after each test module: the diagnosis compiles a model per
    mechanism set and trace shape, and a whole suite's worth in one process would run
    into the kernel's limit on memory maps (``vm.max_map_count``)."""
    yield
    jax.clear_caches()
    gc.collect()
