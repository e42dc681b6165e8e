"""The `mjstamp` command line.

Bad input (an unknown scene, a malformed MJCF, a bad option) prints one line,
`mjstamp: error: ...`, and exits with status 2; no traceback.

One module per command (`check`, `solve`, `view`, `compare`, `tasks`), each with
`add_parser(subparsers)` and `run(args) -> int`: the shape of a command a task
contributes (`mjstamp.tasks.Command`, pushing's `skills`). What several share
(argument types, the one-line-error parser) is in `arguments`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings

from mjstamp.cli import check, compare, solve, tasks, view
from mjstamp.cli.arguments import Parser, add_task_options
from mjstamp.cli.compare import METHODS
from mjstamp.errors import MjstampError

__all__ = ["METHODS", "build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for tests and docs)."""
    parser = Parser(
        prog="mjstamp",
        description="Differentiable task and motion planning (STAMP) on MuJoCo MJX.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    check.add_parser(sub)
    solvers = [solve.add_parser(sub)]
    view.add_parser(sub)
    solvers.append(compare.add_parser(sub))
    add_task_options(*solvers)
    _add_task_commands(sub)
    tasks.add_parser(sub)
    return parser


def _add_task_commands(sub) -> None:
    """The commands registered tasks contribute (pushing's `skills`)."""
    from mjstamp import registry

    for entry in registry.entries().values():
        for command in entry.commands:
            parser = sub.add_parser(command.name, help=command.help)
            command.add_arguments(parser)
            parser.set_defaults(func=command.run)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `mjstamp` console script."""
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0), or argparse's one-line error (2)
        return e.code if isinstance(e.code, int) else 2
    args.argv = argv
    try:
        _configure(args)
        with _warnings_as_lines():
            return args.func(args)
    except MjstampError as e:
        print(f"mjstamp: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # N.B. a last resort: a path the checks above did not foresee
        where = f"{str(e.filename)[:200]!r}: " if e.filename else ""
        print(f"mjstamp: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        print(f"mjstamp: interrupted{f' ({e})' if str(e) else ''}", file=sys.stderr)
        return 130


def _configure(args) -> None:
    """`mjstamp.configure` from the command's flags: precision, host devices, processes."""
    import mjstamp
    from mjstamp import parallel

    processes = _processes(args)
    if processes:
        _stdout_for_python_only()
    devices = getattr(args, "devices", None)
    # N.B. --devices N is checked against this machine's cores; configure takes any N.
    count = parallel.host_device_count(devices, **_coordinator(processes))
    mjstamp.configure(precision=getattr(args, "precision", "float64"), devices=count,
                      strict_devices=devices != "auto", **(processes or {}))


def _coordinator(processes: dict | None) -> dict:
    """`host_device_count`'s view of the run: its coordinator and process count."""
    if not processes:
        return {}
    return {"coordinator": processes["coordinator"],
            "num_processes": processes["num_processes"]}


def _processes(args) -> dict | None:
    """`configure`'s coordinator settings from --coordinator/--num-processes/--process-id."""
    coordinator = getattr(args, "coordinator", None)
    num, pid = getattr(args, "num_processes", None), getattr(args, "process_id", None)
    if coordinator is None:
        if num is not None or pid is not None:
            raise MjstampError("--num-processes and --process-id need --coordinator HOST:PORT "
                               "(process 0's address)")
        return None
    if num is None or pid is None:
        raise MjstampError("--coordinator needs --num-processes N and --process-id I "
                           "(0 for the process that hosts the coordinator)")
    return {"coordinator": coordinator, "num_processes": num, "process_id": pid,
            "coordinator_timeout_s": args.coordinator_timeout}


def _stdout_for_python_only() -> None:
    """Sends what C++ writes to stdout (Gloo's connection lines) to stderr instead.

    N.B. a run over several processes makes Gloo print to file descriptor 1,
    which would break `--json`'s one object on stdout; Python's `print` keeps
    the real stdout.
    """
    sys.stdout.flush()
    real = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = os.fdopen(real, "w", buffering=1, closefd=True)


@contextlib.contextmanager
def _warnings_as_lines():
    """Shows mjstamp's own warnings as one 'mjstamp: warning: ...' line.

    Those are `FidelityWarning` and `SettingDeprecationWarning` (a flat solve
    setting such as `--set backtrack=false`: shown, as Python hides a
    DeprecationWarning raised outside __main__).
    """
    from mjstamp.config import SettingDeprecationWarning
    from mjstamp.errors import FidelityWarning

    ours = (FidelityWarning, SettingDeprecationWarning)
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, ours):
            print(f"mjstamp: warning: {message}", file=sys.stderr, flush=True)
        else:
            shown(message, category, filename, lineno, file, line)

    with warnings.catch_warnings():
        warnings.simplefilter("default", SettingDeprecationWarning)
        warnings.showwarning = show
        yield
