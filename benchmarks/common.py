"""What several benchmarks repeat: the paper's tasks, two arguments, the scene suite, JSON files.

Imported as `benchmarks.common`. A benchmark run by its path (`python
benchmarks/perf/c_values.py`) first puts the repository root on sys.path, where
`benchmarks` is found; run as a module (`python -m benchmarks.perf.c_values`) it
needs nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
"""Where the benchmarks' figures are kept (`benchmarks/results/README.md` says what made each)."""

TASKS: dict[str, dict] = {"billiards": {}, "pushing": {"max_pushes": 2}}
"""The paper's two tasks and their settings in Table I and the studies (pushing: K = 2)."""


def add_tasks_argument(parser: argparse.ArgumentParser) -> None:
    """`--tasks [NAME ...]`: some of TASKS (default: both)."""
    parser.add_argument("--tasks", nargs="*", choices=sorted(TASKS), default=list(TASKS))


def add_devices_argument(parser: argparse.ArgumentParser) -> None:
    """`--devices K`: host devices to shard over (None: one per core, at most 8)."""
    parser.add_argument("--devices", type=int, default=None,
                        help="host devices (default: one per core, at most 8)")


def use_suite() -> None:
    """Makes the scene suite (`examples/suite/`) importable as `suite`, as its tools import it."""
    examples = str(ROOT / "examples")
    if examples not in sys.path:
        sys.path.insert(0, examples)


def load_task(name: str):
    """A registered task (with its default settings) or a scene suite task, not built.

    Args:
      name: a name of `mjstamp.tasks.names()` or of the suite's `SUITE`.

    Returns:
      a fresh `Task`.
    """
    from mjstamp import registry

    if name in registry.names():
        return registry.load(name)[0]
    use_suite()
    from suite.tasks import SUITE

    return SUITE[name]()


def save_json(path: str | Path, payload, *, indent: int | None = None,
              newline: bool = False) -> None:
    """Writes `json.dumps(payload, indent=indent)` to `path` atomically, making its folder.

    N.B. a long run calls this after every row, so that it keeps what it measured.

    Args:
      path: the file to write.
      payload: anything `json.dumps` takes.
      indent: as `json.dumps`'s.
      newline: end the file with a newline.
    """
    from mjstamp.fileio import write_atomic

    path = Path(path)
    data = (json.dumps(payload, indent=indent) + ("\n" if newline else "")).encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, lambda f: f.write(data))
