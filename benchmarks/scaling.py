"""Where gradients pay (issue 29): families whose dimension or rarity grows, samplers in C.

    python -m benchmarks.scaling [--families arm pushing rarity] [--members k2 k4 ...]
        [--samples N] [--budget-s S] [--methods random cmaes] [--seed S] [--json FILE] [--tiny]

Three families of problems written as a user would write them with mjstamp's
public API; in each, one knob raises the dimension d of θ or the rarity of
success while the physics stays the same:

- `arm` (k2, k4, k8, k16): the scene suite's two-link arm (`arm_strike.xml`)
  strikes a ball into one of three goals, with K torque knots per motor
  (d = 2K: 4, 8, 16, 32); task plan = the rails the ball touches and the goal;
- `pushing` (k1 … k5): the registered pushing task with up to K pushes
  (`tasks.load("pushing", max_pushes=K)`, d = 7K: 7 … 35), as Table III;
- `rarity` (r0.2 … r0.0125): billiards' table and balls (d = 2), the target
  ball to end within r of a spot (0.6, 0.25) on the open table; the share of
  shots that succeed falls about as r². N.B. billiards' own `pocket_radius`
  is no such knob: its pockets are corners, where the target's centre comes
  no nearer than √2 · 0.04 m ≈ 0.057 m without pressing into the walls, and
  shrinking the radius from 0.1 to 0.058 m only halved the share (1.16% to
  0.58% of 20,000 shots).

For each member: d and the share of uniform samples over θ's box that
succeed in MuJoCo C (`modes.monte_carlo`: the same replay and decode as a
solve's; `--samples N`, the issue's aim 10⁶), with the task plans those
samples met; where none succeeds, `success_share` is the rule-of-three upper
bound 3/N and `success_share_is_upper_bound` says so. Then each method of
`METHODS` runs on the member for the same wall time (`--budget-s`) and its
anytime record is written: distinct verified task plans, the seconds at
which each was first verified, the first of them, and the samples drawn.

`METHODS` is the hook for the methods to compare: a function
`fn(task, budget_s, seed) -> record` per name (the record's keys: see
`record`). "random" (uniform shots in C, `modes.random_search`) and "cmaes"
(IPOP-CMA-ES in C, `mjstamp.baselines.evolution`) are here; STAMP and
"screen+adam" are to be added the same way. Both C methods replay and decode
one batch untimed before their clock starts (JIT compiles are not theirs).

JSON (`--json FILE`): {"benchmark", "samples", "budget_s", "seed",
"families": {FAMILY: {MEMBER: {"dim", "success_share", "successes",
"samples", "sampled_task_plans", "methods": {METHOD: record}}}}}.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.common import save_json, use_suite  # noqa: E402

SPOT = (0.6, 0.25)
"""Where the rarity family's target ball must end (m): open table, 0.3 m past the target."""

ARM_KNOTS = (2, 4, 8, 16)
PUSHES = (1, 2, 3, 4, 5)
SPOT_RADII = (0.2, 0.1, 0.05, 0.025, 0.0125)


def arm(knots: int):
    """The suite's arm strike with `knots` torque knots per motor (d = 2 · knots)."""
    use_suite()
    from suite.tasks import arm_strike

    return arm_strike(knots)


def pushing(pushes: int):
    """The registered pushing task with up to `pushes` pushes (d = 7 · pushes)."""
    from mjstamp import tasks

    return tasks.load("pushing", max_pushes=pushes)[0]


def spot(radius: float):
    """Billiards' scene: strike the cue ball so that the target ends within `radius` of SPOT.

    θ = the cue ball's initial velocity in [-4, 4]² m/s, as billiards'. Task
    plan = the walls the cue ball touches before the target ball, and "spot".
    """
    import jax.numpy as jnp

    from mjstamp.scenes import Scene
    from mjstamp.tasks import Task, costs
    from mjstamp.tasks.billiards import WALLS

    scene = Scene.shipped("billiards")
    task = Task(f"spot_r{radius:g}", scene, horizon=150,
                description=f"leave the target ball within {radius:g} m of {SPOT}; "
                "task plan = walls the cue ball touches before the target ball")
    task.box("cue_velocity", low=[-4.0, -4.0], high=[4.0, 4.0], initial_qvel=("cue_x", "cue_y"))
    for wall in WALLS:
        task.contact(wall, "cue", wall, before=("cue", "target"))
    task.cost("aim", costs.aim("cue", "target"))
    task.cost("spot", lambda r: jnp.sum((r.body_pos("target")[:, -1, :2]
                                         - jnp.asarray(SPOT)) ** 2, axis=-1))

    def ends_on_spot(replay):
        ok = np.linalg.norm(replay.body_pos("target")[:, -1, :2] - np.asarray(SPOT),
                            axis=-1) < radius
        return ok, np.where(ok, "spot", "").astype(object)

    task.success(ends_on_spot)
    return task


FAMILIES: dict[str, dict[str, Callable]] = {
    "arm": {f"k{k}": (lambda k=k: arm(k)) for k in ARM_KNOTS},
    "pushing": {f"k{k}": (lambda k=k: pushing(k)) for k in PUSHES},
    "rarity": {f"r{r:g}": (lambda r=r: spot(r)) for r in SPOT_RADII},
}
"""{family: {member: () -> a fresh Task}}, smallest dimension (or commonest success) first."""

TINY = {"arm": ["k2"], "pushing": ["k1"], "rarity": ["r0.2"]}
"""--tiny: one member per family."""


def success_share(task, samples: int, *, seed: int = 0) -> dict:
    """The share of `samples` uniform shots over θ's box that succeed in MuJoCo C.

    Cached on disk by `modes.monte_carlo`, keyed by the task's fingerprint
    (its declaration and the code of its controls, costs and success).

    Returns:
      {"success_share": k/N, or 3/N where k = 0 (rule of three: a 95% upper
      bound), "success_share_is_upper_bound", "successes" k, "samples" N,
      "sampled_task_plans": {task plan: count}}.
    """
    from mjstamp import modes

    m = modes.monte_carlo(task, shots=samples, seed=seed, progress=False,
                          salt=task.fingerprint())
    k = sum(mode["count"] for mode in m["modes"])
    return {"success_share": k / samples if k else 3.0 / samples,
            "success_share_is_upper_bound": k == 0, "successes": k, "samples": samples,
            "sampled_task_plans": {mode["task_plan"]: mode["count"] for mode in m["modes"]},
            "sampling_s": m["compute_s"]}


def record(found_at_s, wall_s: float, samples: int, **extra) -> dict:
    """A method's anytime record: what every entry of `METHODS` returns.

    Args:
      found_at_s: seconds at which each distinct verified task plan was first verified.
      wall_s: seconds the method used (at most the budget).
      samples: rollouts or shots it spent.
      **extra: the method's own keys (its settings, ...).
    """
    found = sorted(float(t) for t in found_at_s)
    return {"task_plans": len(found), "first_plan_s": found[0] if found else None,
            "wall_s": float(wall_s), "found_at_s": found, "samples": int(samples), **extra}


def run_random(task, budget_s: float, seed: int) -> dict:
    """Uniform shots over θ's box in MuJoCo C for `budget_s` (`modes.random_search`)."""
    from mjstamp import modes

    r = modes.random_search(task, budget_s, seed=seed)
    return record(r["found_at_s"].values(), r["wall_s"], r["shots"],
                  successes=r["successes"], found=r["task_plans"])


def run_cmaes(task, budget_s: float, seed: int) -> dict:
    """IPOP-CMA-ES in MuJoCo C for `budget_s`, at its defaults (`baselines.evolution`)."""
    from mjstamp import baselines

    r = baselines.run("cmaes", task, cap_s=budget_s, seed=seed)
    return record([f["found_at_s"] for f in r.found], r.wall_s, r.rollouts,
                  generations=r.runs, settings=r.settings, found=r.task_plans)


METHODS: dict[str, Callable[[object, float, int], dict]] = {
    "random": run_random,
    "cmaes": run_cmaes,
}
"""{name: fn(task, budget_s, seed) -> `record`}: the methods compared, each given the same
wall time on the same cores. N.B. the hook where "stamp" and "screen+adam" go."""


def measure(families: dict[str, list[str]], *, samples: int, budget_s: float, seed: int,
            methods: list[str], out: dict, save: Callable[[], None] = lambda: None,
            say: Callable[[str], None] = print) -> dict:
    """Fills `out["families"]` member by member (saving after each); returns `out`."""
    out.setdefault("families", {})
    for family, members in families.items():
        for member in members:
            task = FAMILIES[family][member]()
            started = time.perf_counter()
            row = {"dim": task.dim, **success_share(task, samples, seed=seed), "methods": {}}
            bound = "<= " if row["success_share_is_upper_bound"] else ""
            say(f"{family} {member}: d = {task.dim}, success share {bound}"
                f"{row['success_share']:.3g} ({row['successes']}/{samples}, "
                f"{len(row['sampled_task_plans'])} task plans; "
                f"{time.perf_counter() - started:.0f} s)")
            out["families"].setdefault(family, {})[member] = row
            for name in methods:
                rec = METHODS[name](task, budget_s, seed)
                row["methods"][name] = rec
                first = rec["first_plan_s"]
                say(f"{family} {member}: {name} {rec['task_plans']} task plans in "
                    f"{rec['wall_s']:.1f} s ({rec['samples']} samples; first at "
                    f"{'-' if first is None else f'{first:.2f} s'})")
                save()
            save()
    return out


def main(argv: list[str] | None = None) -> int:
    """Parses the arguments, measures, prints a line per step; writes JSON with --json."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="*", choices=sorted(FAMILIES),
                        default=list(FAMILIES))
    parser.add_argument("--members", nargs="*", default=None, metavar="MEMBER",
                        help="members to run, of every family chosen (default: all)")
    parser.add_argument("--samples", type=int, default=10_000,
                        help="uniform shots per member for its success share (issue: 10^6)")
    parser.add_argument("--budget-s", type=float, default=60.0,
                        help="wall time each method gets on each member")
    parser.add_argument("--methods", nargs="*", choices=sorted(METHODS), default=list(METHODS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="FILE", help="write the results here")
    parser.add_argument("--tiny", action="store_true",
                        help="one member per family, 256 shots, 3 s budgets (a smoke run)")
    args = parser.parse_args(argv)

    import mjstamp

    mjstamp.configure(precision="float64")
    if args.tiny:
        chosen = {f: TINY[f] for f in args.families}
        args.samples, args.budget_s = 256, 3.0
    else:
        chosen = {f: [m for m in FAMILIES[f] if args.members is None or m in args.members]
                  for f in args.families}
    unknown = sorted(set(args.members or []) - {m for f in args.families for m in FAMILIES[f]})
    if unknown:
        parser.error(f"no member {unknown[0]!r} in {args.families}")
    if args.samples < 1 or not args.budget_s > 0:
        parser.error("--samples must be >= 1 and --budget-s > 0")
    out = {"benchmark": "scaling", "samples": args.samples, "budget_s": args.budget_s,
           "seed": args.seed, "methods": args.methods, "families": {}}

    def save():
        if args.json:
            save_json(args.json, out, indent=1, newline=True)

    measure(chosen, samples=args.samples, budget_s=args.budget_s, seed=args.seed,
            methods=args.methods, out=out, save=save, say=lambda s: print(s, flush=True))
    save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
