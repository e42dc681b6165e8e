"""`mjstamp tasks`: the registered tasks, one line each."""

from __future__ import annotations

import json


def add_parser(subparsers):
    """Adds `tasks` to `subparsers`; returns its parser."""
    tasks = subparsers.add_parser("tasks", help="list the registered tasks")
    tasks.add_argument("--json", action="store_true")
    tasks.set_defaults(func=run)
    return tasks


def run(args) -> int:
    """Prints each task's name and summary (or one JSON object)."""
    from mjstamp import registry

    rows = registry.summaries()
    if args.json:
        print(json.dumps(rows))
        return 0
    width = max(map(len, rows), default=0)
    for name, summary in rows.items():
        print(f"{name:<{width}}  {summary}")
    return 0
