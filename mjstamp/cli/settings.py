"""`--set KEY=VALUE`: texts typed like the settings they set, for `registry.load`."""

from __future__ import annotations

from collections.abc import Sequence

from mjstamp.config import FLAT_NAMES, SolveConfig
from mjstamp.errors import MjstampError
from mjstamp.registry import default_config


def parse_overrides(task_name: str, pairs: Sequence[str]) -> dict:
    """`KEY=VALUE` texts (the CLI's `--set`) as `load`'s overrides, each typed like its default.

    A key is a setting of the task or a solve setting by its dotted key
    (`stamp.backtrack`, `SolveConfig.fields()`; a flat name of before the
    nesting, such as `backtrack`, is typed like its new key and warned about
    once by `load`); a value takes its default's type
    (true/false/1/0/yes/no/on/off for a bool; "none" for a setting whose
    default is None; a number or a word such as "auto" for `screen.cost_scale`).

    Raises:
      MjstampError: an unknown task, a pair without "=", an unknown key
        (listing the valid ones) or a value of the wrong type; one line each.
    """
    solve = SolveConfig.leaves()
    defaults = {**solve, **{old: solve[new] for old, new in FLAT_NAMES.items()}}
    task_defaults = {k: (v, type(v).__name__) for k, v in default_config(task_name).items()}
    defaults.update(task_defaults)
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise MjstampError(f"--set {pair!r}: expected KEY=VALUE")
        if key not in defaults:
            raise MjstampError(
                f"--set {key!r}: task {task_name!r} has no such setting; valid: "
                + ", ".join(sorted(task_defaults) + list(solve))
            )
        out[key] = _parse_value(key, value, *defaults[key])
    return out


def _parse_value(key: str, text: str, default, annotation: str):
    """One --set value, typed like its default (or, for a None default, its annotation)."""
    kind = type(default) if default is not None else (
        float if "float" in annotation else int if "int" in annotation else str
    )
    if kind is bool:
        lowered = text.strip().lower()
        if lowered in ("true", "1", "yes", "on"):
            return True
        if lowered in ("false", "0", "no", "off"):
            return False
        raise MjstampError(f"--set {key}={text!r}: expected true or false")
    if default is None and text.strip().lower() == "none":
        return None
    if isinstance(default, str) and "float" in annotation:  # a number, or a word ("auto")
        try:
            return float(text)
        except ValueError:
            return text  # N.B. SolveConfig names the valid words
    try:
        return kind(text)
    except ValueError:
        raise MjstampError(f"--set {key}={text!r}: expected {kind.__name__}") from None


__all__ = ["parse_overrides"]
