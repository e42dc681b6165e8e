"""Stable fingerprints of declarations: functions by their code, constants and closures.

A task's costs are Python functions, often closures a user wrote in a script
or notebook. The trace cache (`mjstamp.tracecache`) may reuse a traced
function in a new process only if everything it computes with is the same, so
a function's fingerprint hashes its bytecode and constants (nested code
objects included), its default arguments, the values in its closure cells, and
the globals its code reads, recursively for functions among them. Values are
hashed by content: numbers, strings, arrays (bytes, dtype, shape), tuples,
lists, dicts, dataclasses and objects with a `fingerprint` attribute (a skill
bank). Modules are named, not hashed (mjstamp's own source is in the trace
cache's key). Anything else is hashed by its type and `repr` unless that repr
holds a memory address, in which case by its identity, which differs in every
process: such a task is traced anew rather than matched wrongly.
"""

from __future__ import annotations

import dataclasses
import hashlib
import types
from typing import Any

import numpy as np

_MAX_DEPTH = 12


def of(obj: Any) -> str:
    """A hex digest of `obj` by content; see the module docstring."""
    h = hashlib.sha256()
    _feed(h, obj, depth=0, seen=set())
    return h.hexdigest()[:32]


def model_digest(scene) -> bytes:
    """Digest of a scene's compiled MuJoCo model (mj_saveModel bytes)."""
    import mujoco  # noqa: PLC0415 - only when fingerprinting a scene

    buffer = np.empty(mujoco.mj_sizeModel(scene.m), np.uint8)
    mujoco.mj_saveModel(scene.m, None, buffer)
    return hashlib.sha256(buffer.tobytes()).digest()


def _feed(h, obj: Any, *, depth: int, seen: set[int]) -> None:
    if depth > _MAX_DEPTH:
        h.update(b"<deep>")
        return
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        h.update(f"{type(obj).__name__}:{obj!r}".encode())
        return
    if isinstance(obj, np.ndarray) or (
        hasattr(obj, "__array__") and hasattr(obj, "dtype") and hasattr(obj, "shape")
        and not callable(obj)
    ):
        a = np.asarray(obj)
        h.update(f"array:{a.dtype}:{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
        return
    if isinstance(obj, np.generic):
        h.update(f"np:{obj.dtype}:{obj!r}".encode())
        return
    if isinstance(obj, types.ModuleType):
        h.update(f"module:{obj.__name__}".encode())
        return
    if id(obj) in seen:
        h.update(b"<cycle>")
        return
    seen = seen | {id(obj)}
    if isinstance(obj, (types.FunctionType, types.MethodType)):
        _feed_function(h, obj, depth=depth, seen=seen)
        return
    if isinstance(obj, types.CodeType):
        _feed_code(h, obj, depth=depth, seen=seen)
        return
    if isinstance(obj, (tuple, list, set, frozenset)):
        items = sorted(obj, key=repr) if isinstance(obj, (set, frozenset)) else obj
        h.update(f"{type(obj).__name__}[{len(items)}]".encode())
        for item in items:
            _feed(h, item, depth=depth + 1, seen=seen)
        return
    if isinstance(obj, dict):
        h.update(f"dict[{len(obj)}]".encode())
        for key in sorted(obj, key=repr):
            _feed(h, key, depth=depth + 1, seen=seen)
            _feed(h, obj[key], depth=depth + 1, seen=seen)
        return
    if isinstance(getattr(obj, "fingerprint", None), str):
        h.update(f"{type(obj).__qualname__}:fingerprint:{obj.fingerprint}".encode())
        return
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        h.update(f"dataclass:{type(obj).__qualname__}".encode())
        for field in dataclasses.fields(obj):
            h.update(field.name.encode())
            _feed(h, getattr(obj, field.name), depth=depth + 1, seen=seen)
        return
    if isinstance(obj, type):
        h.update(f"type:{obj.__module__}.{obj.__qualname__}".encode())
        return
    text = repr(obj)
    if " at 0x" in text:
        # N.B. no content to hash: the identity makes a key no other process shares.
        h.update(f"id:{type(obj).__qualname__}:{id(obj)}".encode())
    else:
        h.update(f"repr:{type(obj).__qualname__}:{text}".encode())


def _feed_function(h, fn, *, depth: int, seen: set[int]) -> None:
    if isinstance(fn, types.MethodType):
        h.update(b"method")
        _feed(h, fn.__self__, depth=depth + 1, seen=seen)
        fn = fn.__func__
    h.update(f"fn:{fn.__module__}.{fn.__qualname__}".encode())
    _feed_code(h, fn.__code__, depth=depth, seen=seen)
    _feed(h, fn.__defaults__, depth=depth + 1, seen=seen)
    _feed(h, fn.__kwdefaults__, depth=depth + 1, seen=seen)
    cells = tuple(c.cell_contents if _filled(c) else "<empty>" for c in fn.__closure__ or ())
    _feed(h, cells, depth=depth + 1, seen=seen)
    # The globals the code reads (a helper function, a constant of the script).
    names = sorted(_global_names(fn.__code__))
    for name in names:
        if name in fn.__globals__:
            h.update(f"global:{name}".encode())
            _feed(h, fn.__globals__[name], depth=depth + 1, seen=seen)


def _feed_code(h, code: types.CodeType, *, depth: int, seen: set[int]) -> None:
    h.update(code.co_code)
    h.update(repr(code.co_names).encode())
    for const in code.co_consts:
        _feed(h, const, depth=depth + 1, seen=seen)


def _global_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _global_names(const)
    return names


def _filled(cell) -> bool:
    try:
        cell.cell_contents  # noqa: B018 - probing an empty cell raises
    except ValueError:
        return False
    return True
