"""`mjstamp compare`: STAMP and the baselines timed to the task plans STAMP finds (Table I)."""

from __future__ import annotations

import json

from mjstamp.cli.arguments import parse_count, parse_devices, parse_seconds, task_options

#: `mjstamp.baselines.compare.ALL`, spelt out: building the parser imports no JAX.
METHODS = ("stamp", "enumerate", "blocking", "cem", "cmaes")


def add_parser(subparsers):
    """Adds `compare` to `subparsers`; returns its parser."""
    compare = subparsers.add_parser(
        "compare", help="time STAMP and the baselines (enumerate, blocking, cem, cmaes) to the "
        "distinct verified task plans STAMP's default run finds (Table I's layout)")
    compare.add_argument("task", help="registered task name (see `mjstamp tasks`)")
    compare.add_argument("--methods", default=",".join(METHODS), metavar="M,M",
                         help=f"comma-separated, of {', '.join(METHODS)} (default: all)")
    compare.add_argument("--seeds", type=parse_count(1, "seed count"), default=3, metavar="S",
                         help="seeds 0..S-1 (default 3)")
    compare.add_argument("--cap", type=parse_seconds("cap"), default=600.0, metavar="SECONDS",
                         help="each baseline's wall-time cap per seed (default 600)")
    compare.add_argument("--set", action="append", metavar="KEY=VALUE",
                         help="override a task or solve setting (repeatable), as for solve")
    compare.add_argument("--devices", type=parse_devices, default="auto", metavar="N",
                         help="devices every method's batched rollouts are sharded over "
                         "(as for solve)")
    compare.add_argument("--json", action="store_true", help="print one JSON object")
    compare.add_argument("--quiet", action="store_true", help="no status lines on stderr")
    compare.set_defaults(func=run)
    return compare


def run(args) -> int:
    """Runs every method on seeds 0..S-1; prints the table (or one JSON object)."""
    from mjstamp import parallel, registry
    from mjstamp.baselines.compare import compare, format_table, parse_methods
    from mjstamp.cli import settings

    methods = parse_methods(args.methods)
    overrides = settings.parse_overrides(args.task, args.set or [])
    overrides.update(task_options(args, args.task))
    if args.devices is not None:
        overrides["devices"] = parallel.shard_count(args.devices)
    registry.load(args.task, **overrides)  # N.B. a bad task or setting fails before any work
    rows = compare(lambda: registry.load(args.task, **overrides), methods=methods,
                   seeds=args.seeds, cap_s=args.cap, progress=not args.quiet)
    if args.json:
        print(json.dumps({args.task: rows}))
    else:
        print(format_table(args.task, rows))
    return 0
