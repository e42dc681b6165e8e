"""A disk cache of traced-and-lowered JAX functions (`jax.export`), for fast starts.

JAX's persistent compilation cache skips XLA compilation in a second process,
but not tracing: tracing and differentiating a scan of `mjx.step` still takes
5-10 s on a 2-core CPU before the cache can even be consulted. This module
stores the lowered StableHLO of a jitted function (`jax.export`) keyed by
everything it depends on, so a later process deserialises it in milliseconds
and only the (persistently cached) compilation remains.

The key covers: the caller's key (scene model, options, horizon, ...), the
argument shapes and dtypes, the x64 flag, the jax/jaxlib/mujoco versions, and
a hash of mjstamp's own source files, so editing the code invalidates entries.
Entries are written atomically; a corrupt or stale entry is ignored and
rewritten. Set MJSTAMP_TRACE_CACHE=0 to disable.
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import jax

DEFAULT_DIR = Path.home() / ".cache" / "mjstamp" / "trace"


@functools.cache
def _source_hash() -> str:
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _versions() -> str:
    import jaxlib
    import mujoco

    return f"jax={jax.__version__} jaxlib={jaxlib.__version__} mujoco={mujoco.__version__}"


def cache_dir() -> Path | None:
    """The cache folder, or None when disabled (MJSTAMP_TRACE_CACHE=0)."""
    setting = os.environ.get("MJSTAMP_TRACE_CACHE", "")
    if setting == "0":
        return None
    return Path(setting) if setting not in ("", "1") else DEFAULT_DIR


def cached_jit(fn: Callable, key: str, *example_args) -> Callable:
    """Returns `jax.jit(fn)`, traced at most once across processes for these shapes.

    Args:
      fn: a function of arrays (pytrees of arrays) to arrays; every value it
        closes over must be captured by `key`.
      key: identifies what `fn` computes (model, options, sizes...).
      *example_args: arrays (or ShapeDtypeStructs) with the shapes and dtypes
        the returned function will be called with.

    Returns:
      A callable with the signature of `fn`, for those shapes only.
    """
    jitted = jax.jit(fn)
    folder = cache_dir()
    if folder is None:
        return jitted
    shapes = jax.tree_util.tree_map(lambda x: (tuple(x.shape), str(x.dtype)), example_args)
    h = hashlib.sha256()
    for part in (key, repr(shapes), str(jax.config.jax_enable_x64), _versions(), _source_hash(),
                 jax.default_backend()):
        h.update(part.encode())
        h.update(b"\0")
    path = folder / f"{h.hexdigest()[:32]}.jaxexport"
    exported = None
    if path.is_file():
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # noqa: BLE001 - a corrupt entry is rebuilt, never fatal
            exported = None
    if exported is None:
        exported = jax.export.export(jitted)(*example_args)
        _write_atomic(path, exported.serialize())
    return jax.jit(exported.call)


def _write_atomic(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache folder only costs speed
