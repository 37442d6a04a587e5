"""Compiled programs kept in memory and on disk, loaded ahead, and made once for several
threads (:mod:`ewb_ident.runtime`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ewb_ident.runtime import programs, store
from ewb_ident.runtime import threads as workers


class _Scaled(eqx.Module):
    factor: float = eqx.field(static=True)
    offset: jnp.ndarray


@programs.program
def _apply(m: _Scaled, x, power):
    return {"y": m.factor * jnp.sin(x) ** power + m.offset, "s": [jnp.sum(x)]}


def _plain(m, x, power):
    return {"y": m.factor * np.sin(x) ** power + np.asarray(m.offset), "s": [np.sum(x)]}


@pytest.fixture
def folder(tmp_path):
    before = store.cache_folder()
    store.set_cache_folder(tmp_path)
    programs.clear_memory()
    yield tmp_path
    programs.clear_memory()
    store.set_cache_folder(before)


def _counts():
    return dict(programs.STATS)


def test_a_program_is_compiled_once_then_reused_from_memory_and_from_disk(folder):
    x = jnp.linspace(0.0, 1.0, 7)
    m = _Scaled(2.0, jnp.asarray(0.5))
    c0 = _counts()
    first = _apply(m, x, 2)
    np.testing.assert_allclose(first["y"], _plain(m, x, 2)["y"], rtol=1e-14)
    again = _apply(m, x + 1.0, 2)  # new values, same program
    np.testing.assert_allclose(again["y"], _plain(m, x + 1.0, 2)["y"], rtol=1e-14)
    c1 = _counts()
    assert c1["compiled"] - c0["compiled"] == 1 and c1["memory"] - c0["memory"] == 1
    assert len(list(folder.glob("*.bin"))) == 1
    programs.clear_memory()  # as a new process would start
    loaded = _apply(m, x, 2)
    c2 = _counts()
    assert c2["disk"] - c1["disk"] == 1 and c2["compiled"] == c1["compiled"]
    np.testing.assert_array_equal(loaded["y"], first["y"])
    np.testing.assert_array_equal(loaded["s"][0], first["s"][0])


def test_other_fixed_values_or_shapes_are_other_programs(folder):
    x = jnp.linspace(0.0, 1.0, 7)
    c0 = _counts()
    a = _apply(_Scaled(2.0, jnp.asarray(0.0)), x, 2)
    b = _apply(_Scaled(3.0, jnp.asarray(0.0)), x, 2)  # a static field differs
    c = _apply(_Scaled(2.0, jnp.asarray(0.0)), x, 3)  # a Python argument differs
    d = _apply(_Scaled(2.0, jnp.asarray(0.0)), jnp.linspace(0.0, 1.0, 9), 2)  # a shape
    assert _counts()["compiled"] - c0["compiled"] == 4
    np.testing.assert_allclose(b["y"], 1.5 * a["y"], rtol=1e-14)
    np.testing.assert_allclose(c["y"], 2.0 * np.sin(np.asarray(x)) ** 3, rtol=1e-14)
    assert d["y"].shape == (9,)


def test_a_damaged_file_is_compiled_afresh(folder):
    x = jnp.linspace(0.0, 1.0, 5)
    m = _Scaled(2.0, jnp.asarray(0.5))
    ref = _apply(m, x, 2)
    (path,) = folder.glob("*.bin")
    path.write_bytes(b"not a program")
    programs.clear_memory()
    c0 = _counts()
    out = _apply(m, x, 2)
    c1 = _counts()
    assert c1["disk_errors"] - c0["disk_errors"] == 1 and c1["compiled"] - c0["compiled"] == 1
    np.testing.assert_array_equal(out["y"], ref["y"])
    assert path.stat().st_size > 100  # written again, whole


def test_inside_another_program_it_is_traced_into_it(folder):
    m = _Scaled(2.0, jnp.asarray(0.5))
    outer = jax.jit(lambda x: _apply(m, x, 2)["y"].sum())
    x = jnp.linspace(0.0, 1.0, 5)
    assert float(outer(x)) == pytest.approx(float(np.sum(_plain(m, x, 2)["y"])), rel=1e-14)
    g = jax.grad(lambda x: _apply(m, x, 2)["y"].sum())(x)
    np.testing.assert_allclose(g, 2.0 * 2.0 * np.sin(x) * np.cos(x), rtol=1e-12)


def test_without_a_folder_programs_stay_in_memory(tmp_path):
    before = store.cache_folder()
    store.set_cache_folder(None)
    try:
        programs.clear_memory()
        out = _apply(_Scaled(1.0, jnp.asarray(0.0)), jnp.ones(3), 1)
        np.testing.assert_allclose(out["y"], np.sin(1.0) * np.ones(3), rtol=1e-14)
        assert store.cache_folder() is None
        assert not list(tmp_path.iterdir())
    finally:
        store.set_cache_folder(before)


def test_callers_in_several_threads_compile_a_new_program_once(folder):
    import threading
    from concurrent.futures import ThreadPoolExecutor

    x = jnp.linspace(0.0, 1.0, 11)
    m = _Scaled(5.0, jnp.asarray(0.25))
    together = threading.Barrier(4)

    def call(k):
        together.wait()
        return _apply(m, x + k, 2)

    c0 = _counts()
    with ThreadPoolExecutor(4) as pool:
        outs = list(pool.map(call, range(4)))
    c1 = _counts()
    assert c1["compiled"] - c0["compiled"] == 1 and c1["memory"] - c0["memory"] == 3
    for k, out in enumerate(outs):
        np.testing.assert_allclose(out["y"], _plain(m, x + k, 2)["y"], rtol=1e-14)


def test_parallel_map_keeps_order_and_the_callers_precision(monkeypatch):
    monkeypatch.setenv("EWB_IDENT_THREADS", "3")
    assert workers.threads() == 3
    assert workers.parallel_map(lambda k: k * k, range(5)) == [0, 1, 4, 9, 16]
    for x64, dtype in ((True, jnp.float64), (False, jnp.float32)):
        with jax.enable_x64(x64):
            got = workers.parallel_map(lambda _: jnp.zeros(1).dtype, range(3))
        assert got == [dtype] * 3


def test_a_thread_count_that_is_not_a_number_is_refused(monkeypatch):
    monkeypatch.setenv("EWB_IDENT_THREADS", "two")
    with pytest.raises(ValueError, match="EWB_IDENT_THREADS='two' is not a whole number"):
        workers.parallel_map(abs, [1, 2])


def test_a_compiler_option_jaxlib_lacks_is_dropped_not_fatal(folder, monkeypatch):
    monkeypatch.setattr(programs, "COMPILER_OPTIONS", {"xla_no_such_option_here": False})
    monkeypatch.setattr(programs, "_REFUSED", set())
    x = jnp.linspace(0.0, 1.0, 13)
    m = _Scaled(7.0, jnp.asarray(0.125))
    out = _apply(m, x, 2)
    np.testing.assert_allclose(out["y"], _plain(m, x, 2)["y"], rtol=1e-14)
    assert programs._REFUSED == {(("xla_no_such_option_here", False),)}


def test_a_programs_own_option_jaxlib_refuses_falls_back_to_the_common_ones(monkeypatch):
    """An option value this jaxlib does not know (here a preset that does not exist) is
    dropped, and the program compiles with the options every program has."""
    monkeypatch.setattr(programs, "_REFUSED", set())
    seen = []
    lowered = jax.jit(lambda x: jnp.tanh(x) * 2.0).lower(jnp.ones(5))
    real = type(lowered).compile

    def spy(self, compiler_options=None):
        seen.append(dict(compiler_options or {}))
        return real(self, compiler_options=compiler_options)

    monkeypatch.setattr(type(lowered), "compile", spy)
    exe = programs._compile(lowered, {"xla_cpu_opt_preset": "CPU_OPT_PRESET_NO_SUCH"})
    np.testing.assert_allclose(exe(jnp.ones(5)), 2.0 * np.tanh(np.ones(5)), rtol=1e-15)
    assert seen == [
        programs.COMPILER_OPTIONS | {"xla_cpu_opt_preset": "CPU_OPT_PRESET_NO_SUCH"},
        programs.COMPILER_OPTIONS,
    ]


def test_the_compiler_options_change_no_residual(folder):
    """The options the programs compile with (XLA's fusion emitters off; the fast-compile
    preset of the mechanism programs) give the same numbers as XLA's defaults, on a
    loop of small kernels like the motor's sub-steps."""
    x = jnp.linspace(-2.0, 3.0, 301)
    lowered = jax.jit(lambda x: jnp.tanh(x) ** 3 * jnp.exp(-x * x) + jnp.abs(x) ** 2.82).lower(x)
    np.testing.assert_allclose(
        programs._compile(lowered)(x), lowered.compile()(x), rtol=1e-15, atol=0
    )

    def loop(p):
        def step(s, v):
            w = s[1] + 1e-3 * (v - p[0] * s[0] - jnp.tanh(s[1] / p[1]))
            return jnp.stack([s[0] + 1e-3 * w, w]), s[0] ** p[2]

        return jax.lax.scan(step, jnp.array([0.1, 0.0]), jnp.sin(x))[1]

    lowered = jax.jit(jax.jacfwd(loop)).lower(jnp.array([2.0, 0.05, 1.5]))
    p = jnp.array([2.0, 0.05, 1.5])
    np.testing.assert_allclose(
        programs._compile(lowered, programs.FAST_COMPILE)(p), lowered.compile()(p),
        rtol=1e-13, atol=0,
    )  # fmt: skip


def test_a_thread_count_under_one_is_refused(monkeypatch):
    monkeypatch.setenv("EWB_IDENT_THREADS", "0")
    with pytest.raises(ValueError, match="EWB_IDENT_THREADS='0': at least 1 thread is needed"):
        workers.threads()


def test_made_once_makes_a_key_once_and_hands_its_failure_to_the_waiters():
    import threading
    import time as _time

    lock, pending, kept, calls = threading.Lock(), {}, {}, []

    def make_slowly(value):
        def make():
            calls.append(value)
            _time.sleep(0.2)  # the other callers ask meanwhile
            if value is None:
                raise RuntimeError("could not make it")
            kept[value] = value
            return value

        return make

    def ask(key, value, out):
        try:
            out.append(workers.made_once(lock, pending, key, kept.get, make_slowly(value)))
        except RuntimeError as err:
            out.append(str(err))

    made, failed = [], []
    threads = [threading.Thread(target=ask, args=(7, 7, made)) for _ in range(3)]
    threads += [threading.Thread(target=ask, args=("bad", None, failed)) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(made) == [(7, False), (7, False), (7, True)]
    assert failed == ["could not make it"] * 3
    assert sorted(calls, key=str) == [7, None]
    assert pending == {}
    assert workers.made_once(lock, pending, 7, kept.get, make_slowly(8)) == (7, False)


@programs.program
def _shifted(m: _Scaled, x):
    return {"y": m.factor * jnp.sin(x) + m.offset}


def test_a_bound_program_gives_the_same_results_without_hashing_its_arguments_again(
    folder, monkeypatch
):
    m = _Scaled(2.0, jnp.asarray(0.5))
    f = _shifted.bind(m)
    x = np.linspace(0.0, 1.0, 7)
    c0 = _counts()
    np.testing.assert_array_equal(f(x)["y"], _shifted(m, x)["y"])  # compiled once
    keys = []
    real_key = programs._key
    monkeypatch.setattr(programs, "_key", lambda *a: keys.append(1) or real_key(*a))
    c1 = _counts()
    for k in range(3):
        np.testing.assert_array_equal(f(x + k)["y"], 2.0 * np.sin(x + k) + 0.5)
    assert not keys  # the program was found once, not per call
    c2 = _counts()
    assert c1["compiled"] - c0["compiled"] == 1 and c2["compiled"] == c1["compiled"]
    assert c2["memory"] - c1["memory"] == 3  # still counted as reuse (--verbose)
    y9 = f(np.linspace(0.0, 1.0, 9))["y"]  # another shape: another program
    assert y9.shape == (9,) and _counts()["compiled"] - c2["compiled"] == 1
    with pytest.raises(TypeError, match="after the bound ones must be arrays"):
        _apply.bind(m)(x, 2)


def _work(x) -> list:
    """Three programs in a fixed order, as a diagnosis asks for its fits' programs. (Each
    test gives its own length of ``x``: a program compiled again in one process comes
    from JAX's cache, which the tests switch on, and such a program does not serialise
    whole; see tests/conftest.py.)"""
    m = _Scaled(2.0, jnp.asarray(0.5))
    return [_apply(m, x, 2), _apply(m, x, 3), _shifted(m, x)]


@pytest.fixture
def reads(monkeypatch):
    """Which thread read each stored program from disk: (thread name, key), in order;
    two threads allowed."""
    import threading

    seen: list[tuple[str, str]] = []
    read = store.read

    def spy(key):
        seen.append((threading.current_thread().name, key))
        return read(key)

    monkeypatch.setattr(store, "read", spy)
    monkeypatch.setenv("EWB_IDENT_THREADS", "2")
    return seen


AHEAD = "ewb-ident programs ahead"


def test_the_programs_the_last_run_used_are_loaded_ahead_in_the_background(folder, reads):
    x = jnp.linspace(0.0, 1.0, 21)
    with store.prefetching("work"):
        first = _work(x)  # compiled, stored, and recorded in the order asked
    (record,) = folder.glob("*.keys")
    keys = [k for _, k in reads]  # each looked up on disk once, and not found
    assert record.read_text().split() == keys[1:]
    reads.clear()
    programs.clear_memory()  # as a new process would start
    c0 = _counts()
    with store.prefetching("work"):
        m = _Scaled(2.0, jnp.asarray(0.5))
        head = _apply(m, x, 2)  # the first program names the work: the thread starts
        store._SCOPE[0].thread.join()
        rest = [_apply(m, x, 3), _shifted(m, x)]
    assert sorted(reads) == sorted([("MainThread", keys[0]), *((AHEAD, k) for k in keys[1:])])
    assert _counts()["disk"] - c0["disk"] == 3 and _counts()["compiled"] == c0["compiled"]
    for got, want in zip([head, *rest], first, strict=True):
        jax.tree_util.tree_map(np.testing.assert_array_equal, got, want)
    assert store._AHEAD == {} and store._SCOPE[0] is None


def test_a_program_asked_for_before_the_loader_reaches_it_is_loaded_by_the_caller(
    folder, reads, monkeypatch
):
    import threading

    x = jnp.linspace(0.0, 1.0, 22)
    with store.prefetching("work"):
        first = _work(x)
    keys = [k for _, k in reads]
    reads.clear()
    programs.clear_memory()
    held, release = threading.Event(), threading.Event()
    spy = store.read

    def slow(key):  # the loader is held on its first program
        if threading.current_thread().name == AHEAD:
            held.set()
            release.wait(10)
        return spy(key)

    monkeypatch.setattr(store, "read", slow)
    c0 = _counts()
    with store.prefetching("work"):
        m = _Scaled(2.0, jnp.asarray(0.5))
        got = [_apply(m, x, 2)]
        assert held.wait(10)
        got.append(_shifted(m, x))  # still queued: this thread takes it and loads it
        release.set()
        got.insert(1, _apply(m, x, 3))  # being loaded by the thread: waited for
    assert sorted(reads) == sorted(
        [("MainThread", keys[0]), (AHEAD, keys[1]), ("MainThread", keys[2])]
    )
    assert _counts()["disk"] - c0["disk"] == 3 and _counts()["compiled"] == c0["compiled"]
    for a, b in zip(got, first, strict=True):
        jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)


def test_a_damaged_record_or_a_missing_program_only_costs_the_loads(folder, reads):
    x = jnp.linspace(0.0, 1.0, 23)
    with store.prefetching("work"):
        first = _work(x)
    (record,) = folder.glob("*.keys")
    keys = record.read_text().split()
    record.write_text("\n".join(["not a key", "0" * 64, *keys]) + "\n")
    (folder / f"{keys[-1]}.bin").unlink()
    programs.clear_memory()
    c0 = _counts()
    with store.prefetching("work"):
        again = _work(x)
    for a, b in zip(again, first, strict=True):
        jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)
    assert _counts()["compiled"] - c0["compiled"] == 1  # the one deleted
    assert _counts()["disk"] - c0["disk"] == 2
    assert record.read_text().split() == keys  # recorded afresh


def test_nothing_is_loaded_ahead_with_one_thread_or_without_a_folder(folder, monkeypatch):
    x = jnp.linspace(0.0, 1.0, 24)
    monkeypatch.setenv("EWB_IDENT_THREADS", "1")
    with store.prefetching("work"):
        _work(x)
        assert store._SCOPE[0] is None
    monkeypatch.setenv("EWB_IDENT_THREADS", "2")
    store.set_cache_folder(None)
    with store.prefetching("work"):
        _work(x)
        assert store._SCOPE[0] is None
    assert list(folder.glob("*.keys")) == []
