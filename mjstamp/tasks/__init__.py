"""Tasks: TAMP problems declared on scenes, and a registry the CLI finds them in.

A task module registers a factory with `register`; `load(name, **overrides)`
builds the task from its `default_config()` updated with the overrides
(mujoco_playground's `load(name, config_overrides=...)` pattern).
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Callable

from mjstamp.errors import MjstampError, valid_list
from mjstamp.tasks.task import Contact, Rollout, Task, Variable

# name -> (default_config() -> dict, make(config: dict) -> Task, one-line summary)
_REGISTRY: dict[str, tuple[Callable[[], dict], Callable[[dict], Task], str]] = {}
_BUILTIN_MODULES = ("mjstamp.tasks.billiards", "mjstamp.tasks.pushing")


def register(name: str, default_config: Callable[[], dict], summary: str = ""):
    """Decorator registering `make(config) -> Task` under `name`."""

    def wrap(make: Callable[[dict], Task]):
        _REGISTRY[name] = (default_config, make, summary)
        return make

    return wrap


def _load_builtins() -> None:
    for module in _BUILTIN_MODULES:
        importlib.import_module(module)


def names() -> list[str]:
    """Registered task names."""
    _load_builtins()
    return sorted(_REGISTRY)


def summaries() -> dict[str, str]:
    """{task name: one-line summary}."""
    _load_builtins()
    return {name: entry[2] for name, entry in sorted(_REGISTRY.items())}


def default_config(name: str) -> dict:
    """The default configuration of a registered task."""
    _load_builtins()
    if name not in _REGISTRY:
        raise MjstampError(f"unknown task {name!r}; valid: {valid_list(sorted(_REGISTRY))}")
    return _REGISTRY[name][0]()


def load(name: str, **overrides) -> tuple[Task, dict]:
    """Builds a registered task; returns (task, the config it was built with)."""
    config = default_config(name)
    unknown = sorted(set(overrides) - set(config))
    if unknown:
        raise MjstampError(
            f"task {name!r} has no setting {unknown[0]!r}; valid: {valid_list(sorted(config))}"
        )
    config.update(overrides)
    task = _REGISTRY[name][1](config)
    # Identifies what the task computes, for the trace cache (mjstamp.tracecache).
    task.cache_key = f"task={name} config={json.dumps(config, sort_keys=True)}"
    from mjstamp.solve import SolveConfig  # noqa: PLC0415 - solve imports the engine

    # The task's own settings; `solve` accepts them beside its own and records them.
    task.settings = {k: v for k, v in config.items() if k not in SolveConfig.fields()}
    return task, config


__all__ = [
    "Contact",
    "Rollout",
    "Task",
    "Variable",
    "default_config",
    "load",
    "names",
    "register",
    "summaries",
]
