"""Old import paths that still work for one release, with one deprecation line.

A module that moved leaves a stub at its old path that calls `alias`: the old
name then *is* the new module (and each of its submodules), so that state held
in a module (a registry, a patched table) exists once, whichever path a user
imported.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings

_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn_at_user(text: str, category: type[Warning] = DeprecationWarning) -> None:
    """Warns where the user wrote the old form: the first frame outside mjstamp.

    N.B. Python shows a DeprecationWarning only where it is attributed to
    `__main__` (a script, a notebook); one attributed to a frame inside mjstamp
    would never be seen. The import machinery's frames do not count (`warnings`
    skips them).
    """
    frame, level = sys._getframe(0), 1
    while frame is not None:
        name = frame.f_code.co_filename
        internal = "importlib" in name and "_bootstrap" in name
        if not internal:
            if not name.startswith(_PACKAGE):
                break
            level += 1
        frame = frame.f_back
    warnings.warn(text, category, stacklevel=level)


def alias(old: str, new: str, *, submodules: tuple[str, ...] = ()):
    """Makes module `old` the module `new` (and `old.sub` the module `new.sub`).

    Args:
      old: the old dotted path; its stub module calls this at import.
      new: where the code lives now.
      submodules: names under `new` that were importable under `old`.

    Returns:
      The module `new`.
    """
    warn_at_user(f"{old} moved to {new}; the old path works until the next release")
    module = importlib.import_module(new)
    sys.modules[old] = module
    for name in submodules:
        sys.modules[f"{old}.{name}"] = importlib.import_module(f"{new}.{name}")
    return module


def moved_attribute(module: str, name: str, new: str):
    """The object `name` now at module `new`, with one deprecation line.

    For a module-level `__getattr__` at the old place: `module.name` still works.
    """
    warn_at_user(f"{module}.{name} moved to {new}.{name}; the old path works until the next "
                 "release")
    value = getattr(importlib.import_module(new), name)
    setattr(sys.modules[module], name, value)  # N.B. one line: `from m import name` asks twice
    return value


def moved_names(module: str, moved: dict[str, str]):
    """A module-level `__getattr__` for names that moved out of `module`.

    Args:
      module: the module that held them (`__name__`).
      moved: {name: the module that holds it now}.

    Returns:
      `__getattr__(name)`: a moved name with one deprecation line
      (`moved_attribute`); any other name an AttributeError.
    """

    def __getattr__(name: str):
        if name in moved:
            return moved_attribute(module, name, moved[name])
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
