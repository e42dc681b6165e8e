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
