"""Old import paths that still work for one release, with one deprecation line.

A module that moved leaves a stub at its old path that calls `alias`: the old
name then *is* the new module (and each of its submodules), so that state held
in a module (a registry, a patched table) exists once, whichever path a user
imported.
"""

from __future__ import annotations

import importlib
import sys
import warnings


def alias(old: str, new: str, *, submodules: tuple[str, ...] = (), stacklevel: int = 3):
    """Makes module `old` the module `new` (and `old.sub` the module `new.sub`).

    Args:
      old: the old dotted path; its stub module calls this at import.
      new: where the code lives now.
      submodules: names under `new` that were importable under `old`.
      stacklevel: where the warning points (the importer of the stub).

    Returns:
      The module `new`.
    """
    warnings.warn(f"{old} moved to {new}; the old path works until the next release",
                  DeprecationWarning, stacklevel=stacklevel)
    module = importlib.import_module(new)
    sys.modules[old] = module
    for name in submodules:
        sys.modules[f"{old}.{name}"] = importlib.import_module(f"{new}.{name}")
    return module


def moved_attribute(module: str, name: str, new: str):
    """The object `name` now at module `new`, with one deprecation line.

    For a module-level `__getattr__` at the old place: `module.name` still works.
    """
    warnings.warn(f"{module}.{name} moved to {new}.{name}; the old path works until the next "
                  "release", DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(new), name)
