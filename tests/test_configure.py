"""The process's set-up: the one setting made at import (XLA's small-loop threshold in
``XLA_FLAGS``; :mod:`ewb_ident.runtime.config` says why then) and :func:`ewb_ident.configure`,
which the CLI calls at its entry."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from ewb_ident.runtime import config, store

#: Run in a fresh process: what importing the package changes, then what configure()
#: does.
_IMPORT_THEN_CONFIGURE = """
import json, os, sys
before = dict(os.environ)
import ewb_ident
changed = sorted(k for k in set(before) | set(os.environ) if before.get(k) != os.environ.get(k))
out = {"changed": changed, "flags": os.environ.get("XLA_FLAGS"),
       "jax_imported": "jax" in sys.modules, "in_effect": ewb_ident.XLA_SMALL_LOOP_BYTES}
import jax
from jax._src import xla_bridge
from ewb_ident.runtime import store
out["x64"] = jax.config.jax_enable_x64
out["folder"] = store.cache_folder()
folder = ewb_ident.configure()
out["after"] = [jax.config.jax_enable_x64, str(folder), str(store.cache_folder())]
out["started"] = xla_bridge.backends_are_initialized()
print(json.dumps(out))
"""


def test_importing_the_package_sets_xla_flags_only_and_configure_the_rest(tmp_path):
    """``import ewb_ident`` edits ``XLA_FLAGS`` and nothing else: no JAX imported, no
    backend started, 64-bit mode off, no cache folder; :func:`ewb_ident.configure` then
    turns 64-bit mode on and keeps programs in ``$EWB_IDENT_CACHE``, still without
    starting JAX's backend (so it may come before or after the first computation)."""
    import json

    drop = ("XLA_FLAGS", "JAX_ENABLE_X64", "EWB_IDENT_THREADS")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["EWB_IDENT_CACHE"] = str(tmp_path / "cache")
    done = subprocess.run(
        [sys.executable, "-c", _IMPORT_THEN_CONFIGURE], env=env, capture_output=True,
        text=True, check=True,
    )  # fmt: skip
    out = json.loads(done.stdout.strip().splitlines()[-1])
    key = "xla_cpu_small_while_loop_byte_threshold"
    assert out["changed"] == ["XLA_FLAGS"]
    assert out["flags"] == f"--xla_backend_extra_options={key}={config.SMALL_LOOP_BYTES}"
    assert out["in_effect"] == str(config.SMALL_LOOP_BYTES)
    assert not out["jax_imported"] and out["x64"] is False and out["folder"] is None
    assert out["after"] == [True, str(tmp_path / "cache"), str(tmp_path / "cache")]
    assert out["started"] is False


def test_configure_takes_the_cache_folder_from_its_argument_or_the_environment(
    tmp_path, monkeypatch
):
    before = store.cache_folder()
    try:
        monkeypatch.setenv("EWB_IDENT_CACHE", str(tmp_path / "env"))
        assert config.configure() == tmp_path / "env" == store.cache_folder()
        assert config.configure(tmp_path / "given") == tmp_path / "given"
        assert config.configure(cache=False) is None and store.cache_folder() is None
        monkeypatch.setenv("EWB_IDENT_CACHE", "")  # empty: memory only
        assert config.configure() is None
        monkeypatch.delenv("EWB_IDENT_CACHE")
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        assert config.configure() == tmp_path / "xdg" / "ewb-ident" / "programs"
        monkeypatch.setenv("EWB_IDENT_THREADS", "none")  # refused before anything is set
        with pytest.raises(ValueError, match="EWB_IDENT_THREADS='none' is not a whole"):
            config.configure(tmp_path / "other")
        assert store.cache_folder() == tmp_path / "xdg" / "ewb-ident" / "programs"
    finally:
        store.set_cache_folder(before)


# A loop whose iteration reads and writes some 3 kB (over XLA's default 1 kB), and its
# Jacobian compiled (run here, and in a process without the package).
_WIDE_LOOP = """
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)

def loop(p):
    def step(s, v):
        return jnp.tanh(s * p[0]) + v * p[1], s[0] * s[-1]

    return jax.lax.scan(step, jnp.linspace(0.0, 1.0, 200), jnp.sin(jnp.arange(300.0)))[1]

p = jnp.array([1.3, 0.7])
compiled = jax.jit(jax.jacfwd(loop)).lower(p).compile()
native, out = "xla_cpu_small_call" in compiled.as_text(), compiled(p)
"""


def test_the_models_loops_compile_as_native_loops_with_the_same_numbers():
    """Importing the package sets XLA's small-loop threshold before JAX starts (so this
    process has it, although its conftest imported JAX first), and a loop of a few kB an
    iteration is then one native loop (XLA's ``xla_cpu_small_call``), not kernels
    dispatched one by one; a process without the package compiles it as kernels and gets
    the same numbers to round-off."""
    import json

    import ewb_ident

    assert ewb_ident.XLA_SMALL_LOOP_BYTES == str(ewb_ident.SMALL_LOOP_BYTES)
    here: dict = {}
    exec(_WIDE_LOOP, here)
    assert here["native"]
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    script = _WIDE_LOOP + "import json; print(json.dumps([native, out.tolist()]))"
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
    )
    native, plain = json.loads(done.stdout.strip().splitlines()[-1])
    assert not native  # XLA's default: kernels
    np.testing.assert_allclose(here["out"], np.array(plain), rtol=1e-12, atol=1e-300)


def test_a_users_xla_flags_are_kept_and_a_late_import_says_the_option_is_off(monkeypatch):
    """The threshold joins the user's own backend options; a threshold of the user's is
    theirs; imported after JAX started its backend, the package warns and reports XLA's
    default (the programs' cache key holds it)."""
    import sys
    import types

    key = "xla_cpu_small_while_loop_byte_threshold"
    fresh = types.SimpleNamespace(backends_are_initialized=lambda: False)
    monkeypatch.setitem(sys.modules, "jax._src.xla_bridge", fresh)
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=a=1 --xla_dump_to=/x")
    assert config.native_small_loops() == str(config.SMALL_LOOP_BYTES)
    assert os.environ["XLA_FLAGS"] == (
        f"--xla_backend_extra_options=a=1,{key}={config.SMALL_LOOP_BYTES} --xla_dump_to=/x"
    )
    monkeypatch.setenv("XLA_FLAGS", f"--xla_backend_extra_options={key}=4096,b=2")
    assert config.native_small_loops() == "4096"
    assert os.environ["XLA_FLAGS"] == f"--xla_backend_extra_options={key}=4096,b=2"
    started = types.SimpleNamespace(backends_are_initialized=lambda: True)
    monkeypatch.setitem(sys.modules, "jax._src.xla_bridge", started)
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/x")
    with pytest.warns(RuntimeWarning, match="import ewb_ident before any JAX computation"):
        assert config.native_small_loops() == "default"
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/x"
