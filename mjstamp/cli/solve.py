"""`mjstamp solve`: diverse task and motion plans for a registered task."""

from __future__ import annotations

import json
import os
import sys

from mjstamp.cli.arguments import (
    parse_count,
    parse_devices,
    parse_seconds,
    parse_seed,
    task_options,
)
from mjstamp.errors import MjstampError

ROBUST_SELECT = 64
"""`--robust` sets `robust.select`: screen successes per task plan scored for robustness."""


def add_parser(subparsers):
    """Adds `solve` to `subparsers`; returns its parser."""
    solve = subparsers.add_parser("solve", help="find diverse task and motion plans for a task")
    solve.add_argument("task", help="registered task name (see `mjstamp tasks`)")
    solve.add_argument("--particles", type=int, default=None, help="particles (plans) to move")
    solve.add_argument("--seed", type=parse_seed, default=0)
    solve.add_argument("--budget", type=parse_seconds("--budget"), metavar="S", default=None,
                       help="about this wall time for the solve, as a portfolio: the C screen "
                       "runs on "
                       "while it finds new task plans, STAMP's phases end at their share "
                       "(plans then depend on the machine's speed)")
    solve.add_argument("--out", metavar="DIR", help="write plans.json and .npz files here "
                       "(and, while STAMP runs, checkpoint.npz)")
    solve.add_argument("--resume", metavar="DIR", help="continue the unfinished solve whose "
                       "checkpoint is in DIR (same task, settings and seed); results go there")
    solve.add_argument("--checkpoint-every", type=float, metavar="S", default=None,
                       help="seconds between checkpoints with --out (default 30; 0: every "
                       "iteration); SIGINT/SIGTERM also write one")
    solve.add_argument("--json", action="store_true", help="print one JSON object")
    solve.add_argument("--set", action="append", metavar="KEY=VALUE",
                       help="override a task setting (repeatable)")
    solve.add_argument("--devices", type=parse_devices, default="auto", metavar="N",
                       help="shard the particles over N devices: CPU host devices (one per "
                       "core) or local GPUs; 'auto' (default): every one (CPU: one per core, "
                       "at most 8)")
    solve.add_argument("--coordinator", metavar="HOST:PORT",
                       help="run one solve over several processes (machines, or processes "
                       "of one machine): process 0 listens at HOST:PORT, the others join it; "
                       "each runs the same command with its own --process-id, --devices "
                       "counts its own; process 0 prints and writes")
    solve.add_argument("--num-processes", type=parse_count(1, "process count"), metavar="N",
                       help="processes in the run (with --coordinator)")
    solve.add_argument("--process-id", type=parse_count(0, "process id"), metavar="I",
                       help="this process's index, 0..N-1 (with --coordinator)")
    solve.add_argument("--coordinator-timeout", type=parse_seconds("coordinator timeout"),
                       default=60.0, metavar="S",
                       help="seconds to wait for the coordinator (default 60)")
    solve.add_argument("--robust", type=parse_count(0, "--robust"), nargs="?", const=8,
                       default=None, metavar="K", help="plan for the task's uncertain physics: "
                       "roll every particle out in K draws of it (default 8; about K times the "
                       "work) and minimise the expected cost; then give each task plan the "
                       f"most robust of its plans and {ROBUST_SELECT} of the screen's "
                       "(robust.select)")
    solve.add_argument("--robust-cvar", type=float, metavar="A", default=None,
                       help="with --robust, minimise the mean cost of the worst share A of "
                       "the draws (CVaR, 0 < A <= 1) instead of the mean of all")
    solve.add_argument("--no-coverage", action="store_true",
                       help="skip the ground-truth sweep behind the coverage figure")
    solve.add_argument("--quiet", action="store_true", help="no progress bars")
    solve.set_defaults(func=run)
    return solve


def run(args) -> int:
    """Solves; prints the results table (or one JSON object) and writes --out."""
    from mjstamp import modes, parallel, registry, results, solve

    overrides = _overrides(args)
    out, resume = _results_dir(args)
    if out and not resume and not parallel.is_lead():
        out = None  # N.B. process 0 writes --out; a resume reads the checkpoint everywhere
    if out:
        results.check_writable(out)
    task, config = registry.load(args.task, **overrides)
    progress = None if not args.quiet else False
    every = 30.0 if args.checkpoint_every is None else args.checkpoint_every
    result = solve(task, config, seed=args.seed, progress=progress, checkpoint_dir=out,
                   resume=resume, checkpoint_every_s=every,
                   resume_hint=resume_hint(args.argv, out) if out else "")
    if not parallel.is_lead():
        # N.B. one of several processes: process 0 prints and writes for all; this one
        # waits for it (JAX would give up on a process that exits 300 s before the rest).
        parallel.barrier("mjstamp-solve-done")
        return 0
    coverage = None
    if modes.supports_sweep(task) and not args.no_coverage:
        truth = modes.sweep(task, progress=progress)
        found = [p for p, ok in zip(result.verified.plan, result.verified_mask(), strict=True)
                 if ok]
        coverage = modes.coverage(found, truth)
    summary = result.summary(coverage)
    if out:
        written = result.save(out, coverage=coverage, progress=progress)
        if not args.json:
            print(f"wrote {', '.join(str(p) for p in written)}", file=sys.stderr)
    if args.json:
        brief = {k: v for k, v in summary.items() if k not in ("plans", "declaration")}
        print(json.dumps(brief))
    else:
        print_table(summary)
    parallel.barrier("mjstamp-solve-done")
    return 0


def _overrides(args) -> dict:
    """`registry.load`'s overrides: --set, the task's flags, --particles, --robust, --devices."""
    from mjstamp import parallel
    from mjstamp.cli import settings

    overrides = settings.parse_overrides(args.task, args.set or [])
    overrides.update(task_options(args, args.task))
    if args.particles is not None:
        if args.particles < 2:
            raise MjstampError(f"--particles={args.particles} must be >= 2")
        overrides["particles"] = args.particles
    if args.budget is not None:
        overrides["budget"] = args.budget
    if args.robust is not None:
        overrides["robust.draws"] = args.robust
        if args.robust and not any(k in ("robust.select", "robust") for k in overrides):
            overrides["robust.select"] = ROBUST_SELECT
    if args.robust_cvar is not None:
        if not 0 < args.robust_cvar <= 1:  # N.B. false for NaN too
            raise MjstampError(f"--robust-cvar={args.robust_cvar} must be in (0, 1]: the "
                               "share of the worst draws (1: the expected cost)")
        if not args.robust and not (overrides.get("robust.draws") or overrides.get("robust")):
            raise MjstampError(f"--robust-cvar={args.robust_cvar} needs --robust K with K >= 1")
        overrides["robust.cvar"] = args.robust_cvar
    if args.devices is not None:
        import jax

        # N.B. over several processes --devices is each one's count; the particles
        # are sharded over all of them.
        several = jax.process_count() > 1
        overrides["devices"] = parallel.shard_count("auto" if several else args.devices)
    return overrides


def print_table(summary: dict) -> None:
    """The table of task plans, and the coverage line where the summary has one."""
    from mjstamp.results import format_table

    print(format_table(summary))
    if "coverage" in summary:
        detail = summary["coverage_detail"]
        print(f"coverage: {summary['coverage']:.0%} of the {len(detail['feasible'])} task plans "
              f"occupying >= {detail['min_share']:.1%} of the box"
              + (f" (missed: {', '.join(detail['missed'])})" if detail["missed"] else "")
              + (f"; found {detail['swept_found']} of all the sweep's {detail['swept']}"
                 if "swept" in detail else ""))


def resume_hint(argv: list[str], out: str) -> str:
    """The command line that continues this solve: the same one with --resume OUT."""
    import shlex

    kept, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg in ("--out", "--resume"):
            skip = True
            continue
        if arg.startswith(("--out=", "--resume=")):
            continue
        kept.append(arg)
    return shlex.join(["mjstamp", *kept, "--resume", out])


def _results_dir(args) -> tuple[str | None, bool]:
    """(results directory, resume?) of --out / --resume, checked up front."""
    from mjstamp import checkpoint

    if args.checkpoint_every is not None and not args.checkpoint_every >= 0:
        raise MjstampError(f"--checkpoint-every={args.checkpoint_every} must be >= 0 (seconds)")
    if args.resume is not None:
        if args.out is not None and os.path.abspath(args.out) != os.path.abspath(args.resume):
            raise MjstampError(f"--out {args.out!r} and --resume {args.resume!r} differ: a "
                               "resumed solve writes its results where its checkpoint is")
        checkpoint.read_meta(args.resume)  # one line now if there is none
        return args.resume, True
    if args.out is not None and os.path.isfile(os.path.join(args.out, checkpoint.FILENAME)):
        meta = checkpoint.read_meta(args.out)
        raise MjstampError(
            f"{args.out!r} holds the checkpoint of an unfinished solve of task "
            f"{meta.get('task')!r} ({checkpoint.describe(meta)}): continue it with --resume "
            f"{args.out}, or delete {os.path.join(args.out, checkpoint.FILENAME)} to start afresh"
        )
    return args.out, False
