"""What several commands share: argument types, the one-line-error parser, task flags.

Building a parser imports no JAX: every heavy import waits for a command's `run`.
"""

from __future__ import annotations

import argparse
import sys

from mjstamp.errors import MjstampError


class Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (`mjstamp solve: error: ...`), exit status 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def parse_devices(text: str) -> int | str:
    """A --devices value: a count >= 1, or 'auto'."""
    if text == "auto":
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid device count {text!r}: expected an integer "
                                         ">= 1 or 'auto'") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"device count {value} must be >= 1")
    return value


def parse_seed(text: str) -> int:
    """A --seed value: an integer in 0 .. 2**63 - 1 (what JAX's and NumPy's PRNGs take)."""
    from mjstamp.solver import MAX_SEED

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid seed {text!r}: expected an integer") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"seed {value} must be in 0..{MAX_SEED}")
    return value


def parse_count(low: int, what: str):
    """An argument type: an integer >= low, its errors naming `what`."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {what} {text!r}: expected an integer "
                                             f">= {low}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{what} {value} must be >= {low}")
        return value

    return parse


def parse_seconds(what: str):
    """An argument type: a finite number of seconds > 0, its errors naming `what`."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {what} {text!r}: expected seconds > 0"
                                             ) from None
        if not 0 < value < float("inf"):
            raise argparse.ArgumentTypeError(f"{what} {text} must be a finite number of "
                                             "seconds > 0")
        return value

    return parse


def add_task_options(*parsers) -> None:
    """The flags registered tasks contribute (pushing's --max-pushes), on each of `parsers`."""
    from mjstamp import registry

    for entry in registry.entries().values():
        for option in entry.options:
            # N.B. parsed after argparse (in task_options): argparse's own errors
            # take two lines (usage, then the error); ours take one.
            for parser in parsers:
                parser.add_argument(option.flag, dest=option.key, metavar=option.metavar,
                                    help=option.help)


def task_options(args, task_name: str) -> dict:
    """Settings from the flags tasks contribute (e.g. --max-pushes), for this task."""
    from mjstamp import registry

    out = {}
    for name, entry in registry.entries().items():
        for option in entry.options:
            value = getattr(args, option.key, None)
            if value is None:
                continue
            if name != task_name:
                raise MjstampError(f"{option.flag}: task {task_name!r} has no such option "
                                   f"(it is task {name!r}'s)")
            try:
                out[option.key] = option.type(value)
            except MjstampError:
                raise
            except ValueError:
                raise MjstampError(f"{option.flag}={value!r} is not valid") from None
    return out
