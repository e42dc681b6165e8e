"""The `mjstamp` command line.

Bad input (an unknown scene, a malformed MJCF, a bad option) prints one line,
`mjstamp: error: ...`, and exits with status 2; no traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import warnings

from mjstamp.errors import MjstampError


def configure_jax(*, precision: str = "float64", devices: int | None = None,
                  strict_devices: bool = True, processes: dict | None = None) -> None:
    """The CLI's JAX settings: `mjstamp.configure` (precision, cache, devices, processes)."""
    import mjstamp

    mjstamp.configure(precision=precision, devices=devices, strict_devices=strict_devices,
                      **(processes or {}))


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


def _devices(text: str) -> int | str:
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


def _host_devices(requested, processes: dict | None = None) -> int | None:
    """How many host devices to ask XLA for: N, or for 'auto' one per core (at most 8).

    N.B. processes on one machine (a loopback coordinator) share its cores.
    """
    if requested is None:
        return None
    cores = os.cpu_count() or 1
    if requested == "auto":
        share = 1
        if processes and processes["coordinator"].rpartition(":")[0] in _LOOPBACK:
            share = processes["num_processes"] if isinstance(processes["num_processes"],
                                                             int) else 1
        return max(1, min(cores, 8) // max(1, share))
    if requested > cores:
        # N.B. XLA makes as many host devices as asked; more than cores only slows.
        raise MjstampError(f"--devices {requested}: this machine has {cores} CPU cores "
                           f"(host devices: at most {cores})")
    return requested


_LOOPBACK = ("127.0.0.1", "localhost", "[::1]", "::1")


def _load_scene(name: str, **kwargs):
    from mjstamp.scenes import Scene

    looks_like_path = name.endswith(".xml") or os.sep in name
    if looks_like_path:
        return Scene(name, **kwargs)
    return Scene.shipped(name, **kwargs)


def _cmd_check(args) -> int:
    import dataclasses

    from mjstamp import tasks
    from mjstamp.scenes.check import CheckSpec, check_scene, check_task

    options = {} if args.iterations is None else {"iterations": args.iterations}
    if args.iterations is not None and not 1 <= args.iterations <= MAX_SOLVER_ITERATIONS:
        raise MjstampError(f"--iterations={args.iterations} must be in "
                           f"1..{MAX_SOLVER_ITERATIONS}")
    if args.gradient is not None:
        options["gradient"] = args.gradient
    if args.tolerance is not None and not args.tolerance > 0:
        raise MjstampError(f"--tolerance={args.tolerance} must be > 0 (metres)")
    from mjstamp.tasks.task import MAX_HORIZON

    if args.horizon is not None and not 1 <= args.horizon <= MAX_HORIZON:
        raise MjstampError(f"--horizon={args.horizon} must be in 1..{MAX_HORIZON}")
    from mjstamp.config import MAX_PARTICLES

    if not 1 <= args.particles <= MAX_PARTICLES:
        raise MjstampError(f"--particles={args.particles} must be in 1..{MAX_PARTICLES}")
    say = (lambda msg: print(f"[check] {msg}", file=sys.stderr)) if not args.quiet else None
    # N.B. an explicit model is judged as given; otherwise the one a solve would calibrate.
    common = dict(particles=args.particles, seed=args.seed, tolerance=args.tolerance,
                  progress=say, calibrate=not options)
    if args.scene in tasks.names():
        # A registered task: its own θ, bounds and horizon.
        if args.horizon is not None:
            raise MjstampError(f"--horizon: task {args.scene!r} has its own horizon; set it "
                               "with the task's settings instead")
        task, _ = tasks.load(args.scene)
        problem = task.build()
        problem = problem.on_scene(problem.scene.with_grad_options(**options))
        report = check_task(problem, **common)
    else:
        scene = _load_scene(args.scene, **options)
        spec = CheckSpec()
        if args.horizon is not None:
            spec = dataclasses.replace(spec, horizon=args.horizon)
        report = check_scene(scene, spec=spec, **common)
    if args.json:
        print(json.dumps(report))
        return 0 if report["healthy"] else 1
    from mjstamp.scenes.fidelity import describe

    print(f"scene            {report['scene']} ({report['precision']}, {report['solver']}, "
          f"{describe(report['gradient'], report['iterations'])}, "
          f"ls_iterations={report['ls_iterations']})")
    print(f"particles        {report['particles']} x {report['horizon']} steps, "
          f"{report['dim']} coordinates each")
    if "calibrated" in report and not options:
        print(f"calibrated       {report['calibrated']['message']}")
    judged = (f"; within C's own chaos, p95 {report['chaos_p95_m']:.2g} m"
              if report["judged_by"] == "chaos" else "")
    print(f"physics          MJX vs MuJoCo C (scene's own solver): divergence median "
          f"{report['physics_divergence_median_m']:.2g} m, p95 "
          f"{report['physics_divergence_p95_m']:.2g} m (tolerance {report['tolerance_m']:.2g} m"
          f"{judged})")
    print(f"non-finite grads {report['nonfinite']} ({report['nonfinite_fraction']:.1%})")
    if report["rel_err_median"] is not None:
        print(f"AD vs FD         scene's own physics: rel err median "
              f"{report['rel_err_median']:.2e}, p95 {report['rel_err_p95']:.2e}; gradient "
              f"model: median {report['model_rel_err_median']:.2e}")
    print(f"value-and-grad   {report['us_per_particle_step']:.1f} us per particle-step "
          f"(compile {report['compile_s']:.1f} s)")
    if report["healthy"]:
        print("healthy")
        return 0
    for problem in report["problems"]:
        print(f"UNHEALTHY: {problem}")
    if "calibrated" in report and options:
        cal = report["calibrated"]
        flags = (f"--gradient implicit --iterations {cal['iterations']}"
                 if cal["gradient"] == "implicit" else f"--iterations {cal['iterations']}")
        print(f"calibration: {cal['message']} (solve calibrates by itself; check it with "
              f"{flags})")
    return 1


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


def _parse_settings(task_name: str, pairs: list[str]) -> dict:
    """--set key=value pairs: the task's settings and every solve setting, typed."""
    import dataclasses

    from mjstamp import tasks
    from mjstamp.config import SolveConfig

    defaults = {f.name: (f.default, str(f.type)) for f in dataclasses.fields(SolveConfig)}
    defaults.update({k: (v, type(v).__name__) for k, v in tasks.default_config(task_name).items()})
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise MjstampError(f"--set {pair!r}: expected KEY=VALUE")
        if key not in defaults:
            raise MjstampError(
                f"--set {key!r}: task {task_name!r} has no such setting; valid: "
                + ", ".join(sorted(defaults))
            )
        out[key] = _parse_value(key, value, *defaults[key])
    return out


def _task_options(args, task_name: str) -> dict:
    """Settings from the flags tasks contribute (e.g. --max-pushes), for this task."""
    from mjstamp import tasks

    out = {}
    for name, entry in tasks.entries().items():
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


def _cmd_tasks(args) -> int:
    from mjstamp import tasks

    rows = tasks.summaries()
    if args.json:
        print(json.dumps(rows))
        return 0
    width = max(map(len, rows), default=0)
    for name, summary in rows.items():
        print(f"{name:<{width}}  {summary}")
    return 0


def _print_table(summary: dict) -> None:
    from mjstamp.results import format_table

    print(format_table(summary))
    if "coverage" in summary:
        detail = summary["coverage_detail"]
        print(f"coverage: {summary['coverage']:.0%} of the {len(detail['feasible'])} task plans "
              f"occupying >= {detail['min_share']:.1%} of the box"
              + (f" (missed: {', '.join(detail['missed'])})" if detail["missed"] else ""))


def _resume_hint(argv: list[str], out: str) -> str:
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


def _cmd_solve(args) -> int:
    from mjstamp import modes, results, tasks
    from mjstamp.solve import solve

    overrides = _parse_settings(args.task, args.set or [])
    overrides.update(_task_options(args, args.task))
    if args.particles is not None:
        if args.particles < 2:
            raise MjstampError(f"--particles={args.particles} must be >= 2")
        overrides["particles"] = args.particles
    if args.robust is not None:
        overrides["robust"] = args.robust
    if args.robust_cvar is not None:
        if not 0 < args.robust_cvar <= 1:  # N.B. false for NaN too
            raise MjstampError(f"--robust-cvar={args.robust_cvar} must be in (0, 1]: the "
                               "share of the worst draws (1: the expected cost)")
        if not args.robust and not overrides.get("robust"):
            raise MjstampError(f"--robust-cvar={args.robust_cvar} needs --robust K with K >= 1")
        overrides["robust_cvar"] = args.robust_cvar
    if args.devices is not None:
        import jax

        from mjstamp.parallel import check_devices

        # N.B. over several processes --devices is each one's count; the particles
        # are sharded over all of them.
        k = (len(jax.devices()) if args.devices == "auto" or jax.process_count() > 1
             else args.devices)
        check_devices(k)
        overrides["devices"] = k
    from mjstamp import parallel

    out, resume = _results_dir(args)
    if out and not resume and not parallel.is_lead():
        out = None  # N.B. process 0 writes --out; a resume reads the checkpoint everywhere
    if out:
        results.check_writable(out)
    task, config = tasks.load(args.task, **overrides)
    progress = None if not args.quiet else False
    every = 30.0 if args.checkpoint_every is None else args.checkpoint_every
    result = solve(task, config, seed=args.seed, progress=progress, checkpoint_dir=out,
                   resume=resume, checkpoint_every_s=every,
                   resume_hint=_resume_hint(args.argv, out) if out else "")
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
        _print_table(summary)
    parallel.barrier("mjstamp-solve-done")
    return 0


#: `mjstamp.baselines.compare.ALL`, spelt out: building the parser imports no JAX.
METHODS = ("stamp", "enumerate", "blocking", "cem")


def _methods() -> tuple[str, ...]:
    return METHODS


def _seconds(what: str):
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


def _cmd_compare(args) -> int:
    from mjstamp import tasks
    from mjstamp.baselines.compare import compare, format_table, parse_methods

    methods = parse_methods(args.methods)
    overrides = _parse_settings(args.task, args.set or [])
    overrides.update(_task_options(args, args.task))
    if args.devices is not None:
        import jax

        from mjstamp.parallel import check_devices

        k = len(jax.devices()) if args.devices == "auto" else args.devices
        check_devices(k)
        overrides["devices"] = k
    tasks.load(args.task, **overrides)  # N.B. a bad task or setting fails before any work
    say = None if args.quiet else (lambda msg: print(f"[compare] {msg}", file=sys.stderr,
                                                     flush=True))
    rows = compare(lambda: tasks.load(args.task, **overrides), methods=methods,
                   seeds=args.seeds, cap_s=args.cap, say=say)
    if args.json:
        print(json.dumps({args.task: rows}))
    else:
        print(format_table(args.task, rows))
    return 0


def _cmd_view(args) -> int:
    import signal
    import time

    from mjstamp import viz

    if args.port is not None and not 0 < args.port < 65536:
        raise MjstampError(f"--port={args.port} must be in 1..65535")
    if args.perturbed < 0:
        raise MjstampError(f"--perturbed={args.perturbed} must be >= 0 (replays per plan)")
    choice = dict(plan=args.plan, task_plan=args.task_plan, task=args.task,
                  perturbed=args.perturbed)
    if args.html:
        playback = viz.write_html(args.dir, args.html, **choice)
        print(f"wrote {playback.html} ({len(playback.segments)} plans)", file=sys.stderr)
        return 0
    # ServerUnavailable is an MjstampError: main prints its one line (where the
    # fallback page went) and exits with status 2.
    playback = viz.play(args.dir, port=args.port, open_browser=not args.no_browser, **choice)
    print(f"meshcat viewer: {playback.url} (Ctrl-C to stop)", flush=True)
    for segment in playback.segments:
        print(f"  {segment.label()}", flush=True)

    def stop(signum, frame):  # SIGTERM ends the viewer like Ctrl-C, server included
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0
    finally:
        playback.close()


def _add_task_contributions(sub, *solvers) -> None:
    """Flags of `solve` (and `compare`) and commands that registered tasks contribute."""
    from mjstamp import tasks

    for entry in tasks.entries().values():
        for option in entry.options:
            # N.B. parsed after argparse (in _task_options): argparse's own errors
            # take two lines (usage, then the error); ours take one.
            for parser in solvers:
                parser.add_argument(option.flag, dest=option.key, metavar=option.metavar,
                                    help=option.help)
        for command in entry.commands:
            parser = sub.add_parser(command.name, help=command.help)
            command.add_arguments(parser)
            parser.set_defaults(func=command.run)


#: Most solver iterations `check --iterations` takes (MuJoCo's own default is 100).
MAX_SOLVER_ITERATIONS = 10_000


def _seed(text: str) -> int:
    """A --seed value: an integer in 0 .. 2**63 - 1 (what JAX's and NumPy's PRNGs take)."""
    from mjstamp.solve import MAX_SEED

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid seed {text!r}: expected an integer") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"seed {value} must be in 0..{MAX_SEED}")
    return value


def _count(low: int, what: str):
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


_positive_int = _count(1, "process count")
_nonnegative_int = _count(0, "process id")


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (`mjstamp solve: error: ...`), exit status 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for tests and docs)."""
    parser = _Parser(
        prog="mjstamp",
        description="Differentiable task and motion planning (STAMP) on MuJoCo MJX.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser(
        "check",
        help="fidelity and gradient health of a scene against its own physics (exit 1 if "
        "unhealthy)",
    )
    check.add_argument("scene", help="registered task (its own particles and horizon), "
                       "shipped scene or MJCF path (every joint's initial velocity varied)")
    check.add_argument("--particles", type=int, default=256, help="random particles")
    check.add_argument("--seed", type=_seed, default=0)
    check.add_argument(
        "--precision",
        choices=("float64", "float32"),
        default="float64",
        help="MJX precision (float32 gradients through contacts can go NaN)",
    )
    check.add_argument("--horizon", type=int, help="rollout steps (default: the scene's check)")
    check.add_argument("--iterations", type=int,
                       help="solver iterations of the gradient model, judged as given "
                       "(default: the model solve calibrates on these particles)")
    check.add_argument("--gradient", choices=("unrolled", "implicit"),
                       help="how the solver is differentiated: each of --iterations "
                       "(unrolled), or one Newton step after MJX's own converged loop (implicit)")
    check.add_argument("--tolerance", type=float, metavar="M",
                       help="physics divergence allowed to 95%% of particles, in metres "
                       "(default: 1e-3 of the scene's size)")
    check.add_argument("--json", action="store_true", help="print one JSON object")
    check.add_argument("--quiet", action="store_true", help="no progress on stderr")
    check.set_defaults(func=_cmd_check)

    solve = sub.add_parser("solve", help="find diverse task and motion plans for a task")
    solve.add_argument("task", help="registered task name (see `mjstamp tasks`)")
    solve.add_argument("--particles", type=int, default=None, help="particles (plans) to move")
    solve.add_argument("--seed", type=_seed, default=0)
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
    solve.add_argument("--devices", type=_devices, default="auto", metavar="N",
                       help="shard the particles over N devices: CPU host devices (one per "
                       "core) or local GPUs; 'auto' (default): every one (CPU: one per core, "
                       "at most 8)")
    solve.add_argument("--coordinator", metavar="HOST:PORT",
                       help="run one solve over several processes (machines, or processes "
                       "of one machine): process 0 listens at HOST:PORT, the others join it; "
                       "each runs the same command with its own --process-id, --devices "
                       "counts its own; process 0 prints and writes")
    solve.add_argument("--num-processes", type=_positive_int, metavar="N",
                       help="processes in the run (with --coordinator)")
    solve.add_argument("--process-id", type=_nonnegative_int, metavar="I",
                       help="this process's index, 0..N-1 (with --coordinator)")
    solve.add_argument("--coordinator-timeout", type=_seconds("coordinator timeout"),
                       default=60.0, metavar="S",
                       help="seconds to wait for the coordinator (default 60)")
    solve.add_argument("--robust", type=_count(0, "--robust"), nargs="?", const=8, default=None,
                       metavar="K", help="plan for the task's uncertain physics: roll every "
                       "particle out in K draws of it (default 8; about K times the work) "
                       "and minimise the expected cost")
    solve.add_argument("--robust-cvar", type=float, metavar="A", default=None,
                       help="with --robust, minimise the mean cost of the worst share A of "
                       "the draws (CVaR, 0 < A <= 1) instead of the mean of all")
    solve.add_argument("--no-coverage", action="store_true",
                       help="skip the ground-truth sweep behind the coverage figure")
    solve.add_argument("--quiet", action="store_true", help="no progress bars")
    solve.set_defaults(func=_cmd_solve)

    view = sub.add_parser(
        "view", help="play the plans of a results directory in meshcat (live or HTML)"
    )
    view.add_argument("dir", help="results directory written by `mjstamp solve --out`")
    which = view.add_mutually_exclusive_group()
    which.add_argument("--plan", type=int, action="append", metavar="N",
                       help="play the returned plan of particle N (repeatable); "
                       "default: the best verified plan of each task plan")
    which.add_argument("--task-plan", metavar="NAME",
                       help="play every verified plan of this task plan (e.g. 0110-top)")
    view.add_argument("--task", metavar="NAME",
                      help="check that DIR holds plans of this task")
    view.add_argument("--html", metavar="OUT.html",
                      help="write a standalone page that plays offline, instead of a server")
    view.add_argument("--perturbed", type=int, nargs="?", const=8, default=0, metavar="N",
                      help="play N (default 8) of each plan's perturbed replays (the draws "
                      "of its robustness score) beside it, as translucent copies")
    view.add_argument("--port", type=int, default=None,
                      help="web port of the meshcat server (default: first free from 7000)")
    view.add_argument("--no-browser", action="store_true",
                      help="do not open the viewer in a browser")
    view.set_defaults(func=_cmd_view)

    compare = sub.add_parser(
        "compare", help="time STAMP and the baselines (enumerate, blocking, cem) to the "
        "distinct verified task plans STAMP's default run finds (Table I's layout)")
    compare.add_argument("task", help="registered task name (see `mjstamp tasks`)")
    compare.add_argument("--methods", default=",".join(_methods()), metavar="M,M",
                         help=f"comma-separated, of {', '.join(_methods())} (default: all)")
    compare.add_argument("--seeds", type=_count(1, "seed count"), default=3, metavar="S",
                         help="seeds 0..S-1 (default 3)")
    compare.add_argument("--cap", type=_seconds("cap"), default=600.0, metavar="SECONDS",
                         help="each baseline's wall-time cap per seed (default 600)")
    compare.add_argument("--set", action="append", metavar="KEY=VALUE",
                         help="override a task or solve setting (repeatable), as for solve")
    compare.add_argument("--devices", type=_devices, default="auto", metavar="N",
                         help="devices every method's batched rollouts are sharded over "
                         "(as for solve)")
    compare.add_argument("--json", action="store_true", help="print one JSON object")
    compare.add_argument("--quiet", action="store_true", help="no status lines on stderr")
    compare.set_defaults(func=_cmd_compare)

    _add_task_contributions(sub, solve, compare)

    tasks = sub.add_parser("tasks", help="list the registered tasks")
    tasks.add_argument("--json", action="store_true")
    tasks.set_defaults(func=_cmd_tasks)
    return parser




@contextlib.contextmanager
def _warnings_as_lines():
    """Shows mjstamp's own warnings (`FidelityWarning`) as one 'mjstamp: warning: ...' line."""
    from mjstamp.errors import FidelityWarning

    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, FidelityWarning):
            print(f"mjstamp: warning: {message}", file=sys.stderr, flush=True)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = shown


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
        processes = _processes(args)
        if processes:
            _stdout_for_python_only()
        configure_jax(precision=getattr(args, "precision", "float64"),
                      devices=_host_devices(getattr(args, "devices", None), processes),
                      strict_devices=getattr(args, "devices", None) != "auto",
                      processes=processes)
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


if __name__ == "__main__":
    sys.exit(main())
