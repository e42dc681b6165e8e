"""The trace cache returns the same function, reuses entries, survives corruption."""

import jax.numpy as jnp
import numpy as np

from mjstamp import tracecache


def _fn(x, y):
    return jnp.sin(x) @ y, jnp.cos(x).sum()


def test_cached_function_matches_and_entry_is_reused(tmp_path, monkeypatch):
    monkeypatch.setenv("MJSTAMP_TRACE_CACHE", str(tmp_path))
    x, y = np.linspace(0, 1, 6).reshape(2, 3), np.ones(3)
    first = tracecache.cached_jit(_fn, "test-fn", x, y)
    entries = list(tmp_path.glob("*.jaxexport"))
    assert len(entries) == 1
    stamp = entries[0].stat().st_mtime_ns
    second = tracecache.cached_jit(_fn, "test-fn", x, y)
    assert entries[0].stat().st_mtime_ns == stamp  # read back, not rewritten
    for got in (first(x, y), second(x, y)):
        for a, b in zip(got, _fn(x, y), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12)
    tracecache.cached_jit(_fn, "other-key", x, y)
    tracecache.cached_jit(_fn, "test-fn", x[:1], y)  # other shapes: other entry
    assert len(list(tmp_path.glob("*.jaxexport"))) == 3


def test_corrupt_entry_is_rebuilt_and_cache_can_be_disabled(tmp_path, monkeypatch):
    monkeypatch.setenv("MJSTAMP_TRACE_CACHE", str(tmp_path))
    x, y = np.ones((2, 3)), np.ones(3)
    tracecache.cached_jit(_fn, "test-fn", x, y)
    (entry,) = tmp_path.glob("*.jaxexport")
    entry.write_bytes(b"not an export")
    out = tracecache.cached_jit(_fn, "test-fn", x, y)(x, y)
    np.testing.assert_allclose(out[1], _fn(x, y)[1])
    assert entry.read_bytes() != b"not an export"
    monkeypatch.setenv("MJSTAMP_TRACE_CACHE", "0")
    assert tracecache.cache_dir() is None


def test_pytrees_and_prng_keys_round_trip(tmp_path, monkeypatch):
    """Step functions take (state NamedTuple, PRNG key) and return pytrees."""
    import jax
    import optax

    from mjstamp.svgd import init

    monkeypatch.setenv("MJSTAMP_TRACE_CACHE", str(tmp_path))
    opt = optax.inject_hyperparams(optax.adam)(learning_rate=0.1)
    state = init(jnp.ones((4, 2)), opt)
    key = jax.random.key(3)

    def step(state, key):
        noise = jax.random.normal(key, state.particles.shape)
        return state._replace(particles=state.particles + noise), {"mean": noise.mean()}

    expected = step(state, key)
    for _ in range(2):  # written, then read back
        got = tracecache.cached_jit(step, "test-step", state, key)(state, key)
        assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(expected)
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(expected),
                        strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12)
    assert len(list(tmp_path.glob("*.jaxexport"))) == 1
