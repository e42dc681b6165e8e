"""`mjstamp check`: fidelity and gradient health of a scene or task against its own physics."""

from __future__ import annotations

import json
import os

from mjstamp.cli.arguments import parse_seed
from mjstamp.errors import MjstampError
from mjstamp.progress import Progress

#: Most solver iterations `check --iterations` takes (MuJoCo's own default is 100).
MAX_SOLVER_ITERATIONS = 10_000


def add_parser(subparsers):
    """Adds `check` to `subparsers`; returns its parser."""
    check = subparsers.add_parser(
        "check",
        help="fidelity and gradient health of a scene against its own physics (exit 1 if "
        "unhealthy)",
    )
    check.add_argument("scene", help="registered task (its own particles and horizon), "
                       "shipped scene or MJCF path (every joint's initial velocity varied)")
    check.add_argument("--particles", type=int, default=256, help="random particles")
    check.add_argument("--seed", type=parse_seed, default=0)
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
    check.set_defaults(func=run)
    return check


def run(args) -> int:
    """Checks the scene or task; prints the report. Exit status 0 if healthy, else 1."""
    import dataclasses

    from mjstamp import registry
    from mjstamp.scenes.check import CheckSpec, check_scene, check_task

    options = _gradient_options(args)
    say = Progress(False if args.quiet else True, "check")
    # N.B. an explicit model is judged as given; otherwise the one a solve would calibrate.
    common = dict(particles=args.particles, seed=args.seed, tolerance=args.tolerance,
                  progress=say, calibrate=not options)
    if args.scene in registry.names():
        # A registered task: its own θ, bounds and horizon.
        if args.horizon is not None:
            raise MjstampError(f"--horizon: task {args.scene!r} has its own horizon; set it "
                               "with the task's settings instead")
        task, _ = registry.load(args.scene)
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
    return _print_report(report, calibrated_by_flags=bool(options))


def _gradient_options(args) -> dict:
    """The gradient model --iterations/--gradient ask for ({}: calibrate), the rest checked."""
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
    return options


def _print_report(report: dict, *, calibrated_by_flags: bool) -> int:
    """The report as lines on stdout; returns the exit status (0 healthy, 1 not)."""
    from mjstamp.scenes.fidelity import describe

    print(f"scene            {report['scene']} ({report['precision']}, {report['solver']}, "
          f"{describe(report['gradient'], report['iterations'])}, "
          f"ls_iterations={report['ls_iterations']})")
    print(f"particles        {report['particles']} x {report['horizon']} steps, "
          f"{report['dim']} coordinates each")
    if "calibrated" in report and not calibrated_by_flags:
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
              f"model: median {report['model_rel_err_median']:.2e}; over the "
              f"{report['fd_smooth_particles']} of {report['particles']} particles smooth at "
              f"the step")
    print(f"value-and-grad   {report['us_per_particle_step']:.1f} us per particle-step "
          f"(compile {report['compile_s']:.1f} s)")
    if report["healthy"]:
        print("healthy")
        return 0
    for problem in report["problems"]:
        print(f"UNHEALTHY: {problem}")
    if "calibrated" in report and calibrated_by_flags:
        cal = report["calibrated"]
        flags = (f"--gradient implicit --iterations {cal['iterations']}"
                 if cal["gradient"] == "implicit" else f"--iterations {cal['iterations']}")
        print(f"calibration: {cal['message']} (solve calibrates by itself; check it with "
              f"{flags})")
    return 1


def _load_scene(name: str, **kwargs):
    """A shipped scene by name, or an MJCF file by path."""
    from mjstamp.scenes import Scene

    looks_like_path = name.endswith(".xml") or os.sep in name
    if looks_like_path:
        return Scene(name, **kwargs)
    return Scene.shipped(name, **kwargs)
