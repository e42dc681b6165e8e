"""A disk cache of traced-and-lowered JAX functions (`jax.export`), for fast starts.

JAX's persistent compilation cache skips XLA compilation in a second process,
but not tracing: tracing and differentiating a scan of `mjx.step` still takes
seconds before the cache can even be consulted. This module
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
import pickle
from collections.abc import Callable
from pathlib import Path

import jax

from mjstamp.fileio import write_atomic
from mjstamp.parallel import local_device

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


def cached_jit(fn: Callable, key: str, *example_args, label: str | None = None) -> Callable:
    """Returns `jax.jit(fn)`, traced at most once across processes for these shapes.

    Arguments and results may be pytrees (NamedTuples, optax states, dicts) and
    may hold PRNG key arrays: the exported function works on their flattened
    leaves (keys as their raw data), and the result's tree structure is stored
    beside it.

    Args:
      fn: a function of arrays (pytrees of arrays) to arrays; every value it
        closes over must be captured by `key`.
      key: identifies what `fn` computes (model, options, sizes...).
      *example_args: arrays (or pytrees of arrays) with the shapes and dtypes
        the returned function will be called with.
      label: the name XLA's compile reports give the function (`jit(label)`;
        `solve`'s `compiles` reads them); default fn's own name.

    Returns:
      A callable with the signature of `fn`, for those shapes only.
    """
    folder = cache_dir()
    if folder is None:
        jitted = jax.jit(fn) if label is None else jax.jit(_named(fn, label))

        def uncached(*args):  # committed, strongly typed arguments: one compile (`_strong`)
            leaves, tree = jax.tree_util.tree_flatten(args)
            leaves = [x if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else _strong(x)
                      for x in leaves]
            return jitted(*jax.tree_util.tree_unflatten(tree, leaves))

        return uncached
    leaves, in_tree = jax.tree_util.tree_flatten(example_args)
    is_key = [jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) for x in leaves]
    raw = [jax.random.key_data(x) if k else x for x, k in zip(leaves, is_key, strict=True)]
    shapes = [(tuple(x.shape), str(x.dtype)) for x in leaves]
    h = hashlib.sha256()
    for part in (key, repr(shapes), str(in_tree), str(jax.config.jax_enable_x64), _versions(),
                 _source_hash(), jax.default_backend()):
        h.update(part.encode())
        h.update(b"\0")
    path = folder / f"{h.hexdigest()[:32]}.jaxexport"
    out_tree_box: list = []

    def flat_fn(*xs):
        xs = [jax.random.wrap_key_data(x) if k else x for x, k in zip(xs, is_key, strict=True)]
        out = fn(*jax.tree_util.tree_unflatten(in_tree, xs))
        out_leaves, out_tree = jax.tree_util.tree_flatten(out)
        out_tree_box.append(out_tree)
        return out_leaves

    entry = _read(path)
    if entry is None:
        exported = jax.export.export(jax.jit(flat_fn))(*raw)
        entry = (exported, out_tree_box[-1])
        payload = pickle.dumps({"export": bytes(exported.serialize()), "out_tree": entry[1]})
        _write_atomic(path, payload)
    exported, out_tree = entry
    call = jax.jit(_named(exported.call, label or getattr(fn, "__name__", "call")))
    # N.B. a function sharded over k devices (`mjstamp.parallel`) is exported for k
    # and must be called with its arguments on those k devices.
    place = None
    if exported.nr_devices > 1:
        from mjstamp import parallel  # noqa: PLC0415

        place = parallel.replicated(parallel.particle_mesh(exported.nr_devices))

    def cached(*args):
        xs = jax.tree_util.tree_leaves(args)
        xs = [jax.random.key_data(x) if k else x for x, k in zip(xs, is_key, strict=True)]
        xs = [_strong(x, place) for x in xs]
        return jax.tree_util.tree_unflatten(out_tree, call(*xs))

    return cached


def _named(fn: Callable, label: str) -> Callable:
    """The function fn under another name (XLA names it so in its compile reports)."""
    @functools.wraps(fn)
    def named(*args):
        return fn(*args)

    named.__name__ = named.__qualname__ = label
    return named


def _strong(x, place=None):
    """X as a committed, strongly typed array (on the sharding `place` when given).

    N.B. `jax.jit` keys its cache on weak types (a Python-scalar-born array,
    e.g. optax's injected ε) and on whether an argument is committed to a
    device: a loop feeding a step its own outputs (committed, strongly typed)
    would otherwise trace and compile it a second time at its second call.
    """
    if getattr(x, "weak_type", False):
        x = jax.numpy.asarray(x, dtype=x.dtype)
    if place is not None:
        if getattr(x, "sharding", None) != place:
            x = jax.device_put(x, place)
    elif not getattr(x, "committed", False):
        x = jax.device_put(x, local_device())
    return x


def _read(path: Path):
    """(Exported, output treedef) from a cache entry, or None if absent or bad."""
    if not path.is_file():
        return None
    try:
        # N.B. pickle only for the result's tree structure; the entry lives in
        # the user's own cache folder, written by this module.
        entry = pickle.loads(path.read_bytes())
        return jax.export.deserialize(bytearray(entry["export"])), entry["out_tree"]
    except Exception:  # noqa: BLE001 - a corrupt or stale entry is rebuilt, never fatal
        return None


def _write_atomic(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, lambda f: f.write(data))
    except OSError:
        pass  # a read-only cache folder only costs speed
