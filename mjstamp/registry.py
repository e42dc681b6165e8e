"""The registry of tasks: what `mjstamp solve NAME` and `registry.load(NAME)` find.

A task module registers a factory with `register`: its task settings
(`default_config()`) and its solve settings (`solve_config()`, a
`mjstamp.config.SolveConfig`'s fields) are two configs, as mujoco_playground
separates an environment's config from its training config. `load(name,
**overrides)` builds the task; each override goes to whichever config has the
key, and an unknown key is an error naming both. A registry entry may also
contribute command-line options of `mjstamp solve` (pushing's `--max-pushes`)
and commands (`mjstamp skills`). The shipped tasks (`mjstamp.tasks.billiards`,
`pushing`, `jaco`) are found by name, as a plug-in would be.

May import: config and errors. A factory returns a `mjstamp.tasks.Task`; the
task modules import the registry to register, never the other way round.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable, Sequence
from typing import Any

from mjstamp.config import FLAT_NAMES, SolveConfig
from mjstamp.errors import MjstampError, valid_list

# N.B. a factory's result is a `mjstamp.tasks.Task`, typed here as Any: the registry
# sits below tasks/ (task modules import it to register).
_Task = Any


@dataclasses.dataclass(frozen=True)
class Option:
    """A `mjstamp solve` flag a task contributes: `--flag VALUE` sets task setting `key`."""

    flag: str
    key: str
    type: Callable[[str], Any]
    help: str
    metavar: str | None = None


@dataclasses.dataclass(frozen=True)
class Command:
    """A `mjstamp NAME` command a task contributes.

    Attributes:
      name: the command's name.
      help: one line.
      add_arguments: fn(argparse parser) adding its arguments.
      run: fn(parsed args) -> exit status.
    """

    name: str
    help: str
    add_arguments: Callable[[Any], None]
    run: Callable[[Any], int]


@dataclasses.dataclass(frozen=True)
class Entry:
    """A registered task: its two configs, its factory and what it adds to the CLI."""

    name: str
    default_config: Callable[[], dict]
    make: Callable[[dict], _Task]
    summary: str
    solve_config: Callable[[], dict]
    options: tuple[Option, ...]
    commands: tuple[Command, ...]


_REGISTRY: dict[str, Entry] = {}
_BUILTIN_MODULES = ("mjstamp.tasks.billiards", "mjstamp.tasks.pushing", "mjstamp.tasks.jaco")


def register(
    name: str,
    default_config: Callable[[], dict],
    summary: str = "",
    *,
    solve_config: Callable[[], dict] | None = None,
    options: Sequence[Option] = (),
    commands: Sequence[Command] = (),
):
    """Decorator registering `make(settings) -> Task` under `name`.

    Args:
      name: the task's name.
      default_config: () -> the task's own settings.
      summary: one line for `mjstamp tasks`.
      solve_config: () -> the task's solve settings (`SolveConfig.from_dict`'s
        keys, such as {"stamp": {"min_iters": 20}}, that differ from its
        defaults); validated when the task is loaded.
      options: `mjstamp solve` flags this task contributes.
      commands: `mjstamp` commands this task contributes.
    """

    def wrap(make: Callable[[dict], _Task]):
        _REGISTRY[name] = Entry(name, default_config, make, summary,
                                solve_config or dict, tuple(options), tuple(commands))
        return make

    return wrap


def _load_builtins() -> None:
    for module in _BUILTIN_MODULES:
        importlib.import_module(module)


def entries() -> dict[str, Entry]:
    """{name: registry entry} of every registered task."""
    _load_builtins()
    return dict(sorted(_REGISTRY.items()))


def names() -> list[str]:
    """Registered task names."""
    return list(entries())


def summaries() -> dict[str, str]:
    """{task name: one-line summary}."""
    return {name: e.summary for name, e in entries().items()}


def _entry(name: str) -> Entry:
    table = entries()
    if name not in table:
        raise MjstampError(f"unknown task {name!r}; valid: {valid_list(table)}")
    return table[name]


def default_config(name: str) -> dict:
    """The task settings of a registered task (its `default_config()`)."""
    return _entry(name).default_config()


def solve_config(name: str) -> SolveConfig:
    """The solve settings of a registered task: `SolveConfig` with its overrides."""
    return SolveConfig.from_dict(_entry(name).solve_config())


def load(name: str, **overrides) -> tuple[_Task, SolveConfig]:
    """Builds a registered task; returns (task, its solve settings).

    Each override is a task setting or a solve setting (`SolveConfig.from_dict`'s
    keys: "particles", a group's dict such as `stamp={...}`, or a dotted key,
    passed as `**{"stamp.backtrack": False}`), laid over the task's own solve
    settings.

    Raises:
      MjstampError: an unknown task or setting (naming both kinds of valid keys),
        or a task setting named like a solve setting (an override could not
        say which it meant).
    """
    entry = _entry(name)
    settings = entry.default_config()
    solve_keys = SolveConfig.fields()
    taken = set(solve_keys) | set(SolveConfig.groups()) | set(FLAT_NAMES)
    shadowed = sorted(set(settings) & taken)
    if shadowed:
        raise MjstampError(
            f"task {name!r}: its setting {shadowed[0]!r} has the name of a solve setting; "
            f"rename it (solve settings: {valid_list(solve_keys)})"
        )
    unknown = sorted(set(overrides) - set(settings) - taken)
    if unknown:
        raise MjstampError(
            f"task {name!r} has no setting {unknown[0]!r}; valid task settings: "
            f"{valid_list(sorted(settings))}; valid solve settings: {valid_list(solve_keys)}"
        )
    settings.update({k: v for k, v in overrides.items() if k in settings})
    config = SolveConfig.from_dict({k: v for k, v in overrides.items() if k not in settings},
                                   base=SolveConfig.from_dict(entry.solve_config()))
    task = entry.make(settings)
    task.settings = dict(settings)
    return task, config


__all__ = ["Command", "Entry", "Option", "default_config", "entries", "load", "names", "register",
           "solve_config", "summaries"]
