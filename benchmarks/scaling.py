"""Where gradients pay (issue 29): families whose dimension or rarity grows, samplers in C.

    python -m benchmarks.scaling [--families arm pushing rarity pushing_goal arm_goal jaco]
        [--members k2 k4 ...]
        [--samples N] [--budget-s S|stamp] [--budget-from FILE]
        [--methods stamp portfolio screen+adam random cmaes] [--seed S] [--json FILE] [--tiny]
        [--figures DIR] [--report FILE]

Families of problems written as a user would write them with mjstamp's
public API; in each, one knob raises the dimension d of θ or the rarity of
success while the physics stays the same:

- `arm` (k2, k4, k8, k16): the scene suite's two-link arm (`arm_strike.xml`)
  strikes a ball into one of three goals, with K torque knots per motor
  (d = 2K: 4, 8, 16, 32); task plan = the rails the ball touches and the goal;
- `pushing` (k1 … k5): the registered pushing task with up to K pushes
  (`registry.load("pushing", max_pushes=K)`, d = 7K: 7 … 35), as Table III;
- `rarity` (r0.2 … r0.003): billiards' table and balls (d = 2), the target
  ball to end within r of a spot (0.6, 0.25) on the open table, declared as
  residuals (`Task.residuals`, tolerance r: what the landing descends on); the
  share of shots that succeed falls about as r². N.B. billiards' own `pocket_radius`
  is no such knob: its pockets are corners, where the target's centre comes
  no nearer than √2 · 0.04 m ≈ 0.057 m without pressing into the walls, and
  shrinking the radius from 0.1 to 0.058 m only halved the share (1.16% to
  0.58% of 20,000 shots);
- `pushing_goal` (g0.08 … g0.01): pushing at K = 2 (d = 14), its goal region
  shrunk from its own ± 8 cm to ± 1 cm (`goal_half_size`);
- `arm_goal` (r0.08 … r0.01): the arm strike at K = 2 (d = 4), the ball to
  pass within r of a goal's centre (the suite's r: 8 cm);
- `jaco` (r0.1 … r0.01): dm_control's Jaco (the registered task's scene and
  controls, d = 9) to push the brick to end within r of a point (JACO_SPOT),
  declared as residuals with tolerance r; the registered task's goal regions
  take 17% of uniform shots.

For each member: d and the share of uniform samples over θ's box that
succeed in MuJoCo C (`modes.monte_carlo`: the same replay and decode as a
solve's; `--samples N`, the issue's aim 10⁶; seed 0's shots whatever `--seed`:
the share is the member's), with the task plans those
samples met; where none succeeds, `success_share` is the rule-of-three upper
bound 3/N and `success_share_is_upper_bound` says so. Then each method of
`METHODS` runs on the member and its anytime record is written: distinct
verified task plans, the seconds at which each was first verified, the first
of them, the samples drawn, and per task plan the best cost (C, on the MuJoCo
C replay) and the best robustness (the share of 32 perturbed C replays that
succeed, `verify.robustness`, seed 0) of the plans the method returned.

`METHODS`, a function `fn(task, config, budget_s, seed) -> record` per name
(the record's keys: see `record`):
- "stamp": `mjstamp.solve` at the member's solve settings (`solve_config`:
  pushing's registered ones, `SolveConfig`'s defaults for the others), as a
  user runs it; it sets its own time. Its plans stream: each returned task
  plan is "found" when the solve first verified it in C (`SolveResult.found`:
  the screen's successes, the landings', STAMP's).
- "portfolio": STAMP given the member's budget as a portfolio (`run_portfolio`):
  half of it screening in C (`screen.seconds`), half of the iterations; not
  run by default (`--methods ... portfolio`).
- "screen+adam": the ablation, the same solve without the Stein phase
  (`stamp.svgd_max_iters` = 0): the C screen seeds the particles (its best
  candidates spread over task plans), Adam refines them at Γ, no repulsion.
- "random": uniform shots over θ's box in MuJoCo C (`baselines.sampling.random_search`).
- "cmaes": IPOP-CMA-ES in MuJoCo C (`mjstamp.baselines.evolution`), defaults.
Both solves are run once first, untimed, with 1 iteration per phase (the
compiles, then cached); compiles left in the timed run are subtracted from
its wall time (`compile_s`). Both C methods replay and decode one batch
untimed before their clock starts. With `--budget-s stamp` (the default)
every other method gets the wall time STAMP took on that member.

JSON (`--json FILE`): {"benchmark", "samples", "budget_s", "seed",
"families": {FAMILY: {MEMBER: {"dim", "success_share", "successes",
"samples", "sampled_task_plans", "budget_s", "methods": {METHOD: record},
"versus": {SOLVE METHOD: `versus`}}}}, "crossover": {FAMILY: {SOLVE METHOD:
member}}}: `versus` holds the issue's targets against the member's best
sampler (task plans ratio, first-plan time ratio, and for the task plans both
found the share where the solve's best cost is no higher and the median
robustness gain); `crossover` the first member from which on the solve finds
at least the best sampler's task plans. The run prints the README's markdown
table (`table`); `--figures DIR` draws a figure per family (`family_figure`:
task plans against seconds, a line per method); `--report FILE` does both
for an earlier run's JSON without measuring.
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
SPOT_RADII = (0.2, 0.1, 0.05, 0.025, 0.0125, 0.006, 0.003)
GOAL_HALF_SIZES = (0.08, 0.04, 0.02, 0.01)
"""pushing_goal: the goal region's half-size (m), from the shipped 8 cm to 1 cm."""
ARM_RADII = (0.08, 0.04, 0.02, 0.01)
"""arm_goal: how near the goal's centre the ball must pass (m), from the suite's 8 cm."""
JACO_SPOT = (0.5, 0.135)
"""Where the jaco family's brick must end (m): the registered task's post goal, 10.5 cm
pushed (the brick starts at y = 0.03, its centre stops at y = 0.15 against the post)."""
JACO_RADII = (0.1, 0.05, 0.02, 0.01)


def arm(knots: int):
    """The suite's arm strike with `knots` torque knots per motor (d = 2 · knots)."""
    use_suite()
    from suite.tasks import arm_strike

    return arm_strike(knots)


def pushing(pushes: int):
    """The registered pushing task with up to `pushes` pushes (d = 7 · pushes)."""
    from mjstamp import registry

    return registry.load("pushing", max_pushes=pushes)[0]


def spot(radius: float):
    """Billiards' scene: strike the cue ball so that the target ends within `radius` of SPOT.

    θ = the cue ball's initial velocity in [-4, 4]² m/s, as billiards'. Task
    plan = the walls the cue ball touches before the target ball, and "spot".
    """
    import jax.numpy as jnp

    from mjstamp import Scene, Task, costs
    from mjstamp.tasks.billiards import WALLS

    scene = Scene.shipped("billiards")
    task = Task(f"spot_r{radius:g}", scene, horizon=150,
                description=f"leave the target ball within {radius:g} m of {SPOT}; "
                "task plan = walls the cue ball touches before the target ball")
    task.box("cue_velocity", low=[-4.0, -4.0], high=[4.0, 4.0], initial_qvel=("cue_x", "cue_y"))
    for wall in WALLS:
        task.contact(wall, "cue", wall, before=("cue", "target"))
    task.cost("aim", costs.aim("cue", "target"))
    task.residuals("spot", lambda r: r.body_pos("target")[:, -1, :2] - jnp.asarray(SPOT),
                   tolerance=radius)

    def ends_on_spot(replay):
        ok = np.linalg.norm(replay.body_pos("target")[:, -1, :2] - np.asarray(SPOT),
                            axis=-1) < radius
        return ok, np.where(ok, "spot", "").astype(object)

    task.success(ends_on_spot)
    return task


def arm_goal(radius: float):
    """The suite's arm strike at 2 knots per motor, the ball to pass within `radius` of a goal."""
    use_suite()
    from suite.tasks import arm_strike

    return arm_strike(2, radius=radius)


def pushing_goal(half_size: float):
    """The registered pushing task at 2 pushes, its goal region ± `half_size` (m)."""
    from mjstamp import registry

    return registry.load("pushing", max_pushes=2, goal_half_size=half_size)[0]


def jaco_spot(radius: float):
    """The Jaco's scene and controls: push the brick to end within `radius` of JACO_SPOT.

    As the registered `jaco` task (θ = velocity knots of the three large
    joints, task plan = whether the hand touched the brick and the brick the
    post) but its goal a point: the brick's final (x, y) declared as
    residuals with tolerance `radius`, and "spot" where it ends within it.
    """
    import jax.numpy as jnp

    from mjstamp.tasks import Task, jaco

    config = jaco.default_config()
    task = Task(f"jaco_spot_r{radius:g}", jaco.scene(config), horizon=int(config["horizon"]),
                description=f"push the brick to end within {radius:g} m of {JACO_SPOT}")
    brick = jaco.declare_arm(task, config)
    task.residuals("spot", lambda r: r.body_pos(brick)[:, -1, :2] - jnp.asarray(JACO_SPOT),
                   weight=config["goal_weight"], tolerance=radius)

    def ends_on_spot(replay):
        ok = np.linalg.norm(replay.body_pos(brick)[:, -1, :2] - np.asarray(JACO_SPOT),
                            axis=-1) < radius
        return ok, np.where(ok, "spot", "").astype(object)

    task.success(ends_on_spot)
    task.display(trace=(brick,))
    return task


FAMILIES: dict[str, dict[str, Callable]] = {
    "arm": {f"k{k}": (lambda k=k: arm(k)) for k in ARM_KNOTS},
    "pushing": {f"k{k}": (lambda k=k: pushing(k)) for k in PUSHES},
    "rarity": {f"r{r:g}": (lambda r=r: spot(r)) for r in SPOT_RADII},
    "pushing_goal": {f"g{h:g}": (lambda h=h: pushing_goal(h)) for h in GOAL_HALF_SIZES},
    "arm_goal": {f"r{r:g}": (lambda r=r: arm_goal(r)) for r in ARM_RADII},
    "jaco": {f"r{r:g}": (lambda r=r: jaco_spot(r)) for r in JACO_RADII},
}
"""{family: {member: () -> a fresh Task}}, smallest dimension (or commonest success) first."""

TINY = {"arm": ["k2"], "pushing": ["k1"], "rarity": ["r0.2"], "pushing_goal": ["g0.08"],
        "arm_goal": ["r0.08"], "jaco": ["r0.1"]}
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


def solve_config(family: str, member: str) -> dict | None:
    """The solve settings a user runs a member at: its registered task's, else the defaults."""
    from mjstamp import registry

    if family == "pushing":
        return registry.load("pushing", max_pushes=int(member.removeprefix("k")))[1].as_dict()
    if family == "pushing_goal":
        return registry.load("pushing", max_pushes=2)[1].as_dict()
    if family == "jaco":
        return registry.load("jaco")[1].as_dict()
    return None


ROBUSTNESS_SAMPLES = 32
"""M perturbed C replays per plan for its robustness score (as `studies/robustness.py`)."""

PLANS_KEPT = 8
"""Most plans of one task plan scored for quality (the first, or the best by cost, kept)."""


def record(found_at_s, wall_s: float, samples: int, plans: dict | None = None,
           **extra) -> dict:
    """A method's anytime record: what every entry of `METHODS` returns.

    Args:
      found_at_s: seconds at which each distinct verified task plan was first verified.
      wall_s: seconds the method used.
      samples: rollouts or shots it spent.
      plans: {task plan: (m, d) verified θ the method returns for it}, scored by
        `quality` into the record's "quality" (and dropped from it).
      **extra: the method's own keys (its settings, ...).
    """
    found = sorted(float(t) for t in found_at_s)
    return {"task_plans": len(found), "first_plan_s": found[0] if found else None,
            "wall_s": float(wall_s), "found_at_s": found, "samples": int(samples),
            "plans": plans or {}, **extra}


def quality(task, plans: dict, *, seed: int = 0) -> dict:
    """{task plan: {"cost": best C on the MuJoCo C replay, "robustness": best score, "scored"}}.

    Every plan is scored the same way whatever found it: its cost C on its
    MuJoCo C replay with the scene's own solver (`verify.cost_c`) and the share
    of `ROBUSTNESS_SAMPLES` perturbed C replays in which it succeeds
    (`verify.robustness`, the task's uncertainty or the defaults, `seed`).
    """
    from mjstamp import verify

    out = {}
    for plan, theta in sorted(plans.items()):
        theta = np.asarray(theta, np.float64).reshape(-1, task.dim)[:PLANS_KEPT]
        cost = verify.cost_c(task, verify.simulate_c(task, theta), theta)
        robust = verify.robustness(task, theta, samples=ROBUSTNESS_SAMPLES, seed=seed)
        out[plan] = {"cost": float(np.min(cost)), "robustness": float(np.max(robust.success)),
                     "scored": len(theta)}
    return out


def run_random(task, config, budget_s: float, seed: int) -> dict:
    """Uniform shots over θ's box in MuJoCo C for `budget_s` (`sampling.random_search`)."""
    from mjstamp.baselines import sampling

    r = sampling.random_search(task, budget_s, seed=seed, keep_best=PLANS_KEPT)
    return record(r["found_at_s"].values(), r["wall_s"], r["shots"], plans=r["best"],
                  successes=r["successes"], found=r["task_plans"])


def run_cmaes(task, config, budget_s: float, seed: int) -> dict:
    """IPOP-CMA-ES in MuJoCo C for `budget_s`, at its defaults (`baselines.evolution`)."""
    from mjstamp import baselines

    r = baselines.run("cmaes", task, cap_s=budget_s, seed=seed)
    return record([f["found_at_s"] for f in r.found], r.wall_s, r.rollouts,
                  plans={f["task_plan"]: [f["theta"]] for f in r.found},
                  generations=r.runs, settings=r.settings, found=r.task_plans)


def _solve_record(task, config, seed: int, **stamp) -> dict:
    """`mjstamp.solve` at `config` (with `stamp` overrides), warmed up first; its record."""
    from mjstamp import SolveConfig, solve

    cfg = SolveConfig.from_dict({"stamp": stamp}, base=SolveConfig.from_dict(config or {}))
    warm = SolveConfig.from_dict({"stamp": {"svgd_max_iters": min(1, cfg.stamp.svgd_max_iters),
                                            "sgd_max_iters": 1, "min_iters": 0}}, base=cfg)
    solve(task, warm, seed=seed, progress=False)
    started = time.perf_counter()
    result = solve(task, cfg, seed=seed, progress=False)
    wall = time.perf_counter() - started
    compile_s = float(result.compiles["all_seconds"])
    net = max(wall - compile_s, 0.0)
    ok = result.verified_mask()
    plans: dict[str, list] = {}
    for i in np.argsort(result.cost, kind="stable"):  # best MJX cost first
        if ok[i]:
            plans.setdefault(str(result.verified.plan[i]), []).append(result.theta[i])
    screen = result.screen or {}
    rollouts = result.stamp.diagnostics.step_seconds.size * len(result.theta)
    # Plans stream: each returned task plan at the time the solve first verified it (its
    # `found` record, compiles before it included: their times are not known apart).
    found = result.found or {}
    at = [min(found[p]["seconds"], net) if p in found else net for p in plans]
    return record(at, net, rollouts + (screen.get("candidates") or 0),
                  plans=plans, wall_with_compiles_s=wall,
                  compile_s=compile_s, particles=len(result.theta),
                  returned=int(result.returned.sum()), verified=int(ok.sum()),
                  screen_task_plans=len(screen.get("task_plans", {})),
                  screen_candidates=screen.get("candidates"), timings=result.timings,
                  polish=result.polish,
                  settings=cfg.flat_dict(), found=sorted(plans))


def run_stamp(task, config, budget_s: float, seed: int) -> dict:
    """`mjstamp.solve` at the member's settings; it sets its own time (`budget_s` unused)."""
    return _solve_record(task, config, seed)


def run_screen_adam(task, config, budget_s: float, seed: int) -> dict:
    """The ablation: the same solve without the Stein phase (C screen, then Adam at Γ)."""
    return _solve_record(task, config, seed, svgd_max_iters=0)


def run_portfolio(task, config, budget_s: float, seed: int) -> dict:
    """STAMP as a portfolio of `budget_s`: half of it screening in C, half of the iterations.

    `screen.seconds` = budget_s / 2 (the screen runs on in C until then, and
    the solve returns every task plan it verified); `stamp.svgd_max_iters`,
    `sgd_max_iters` and `min_iters` halved, so the gradient phases take about
    half of what they take at the member's settings.
    """
    from mjstamp import SolveConfig

    stamp = SolveConfig.from_dict(config or {}).stamp
    return _solve_record(task, {**(config or {}), "screen": {
        **(config or {}).get("screen", {}), "seconds": budget_s / 2}}, seed,
        svgd_max_iters=stamp.svgd_max_iters // 2, sgd_max_iters=stamp.sgd_max_iters // 2,
        min_iters=stamp.min_iters // 2)


METHODS: dict[str, Callable[[object, dict | None, float, int], dict]] = {
    "stamp": run_stamp,
    "portfolio": run_portfolio,
    "screen+adam": run_screen_adam,
    "random": run_random,
    "cmaes": run_cmaes,
}
"""{name: fn(task, solve config, budget_s, seed) -> `record`}: the methods compared."""

SAMPLERS = ("random", "cmaes")
"""The methods that run for a given wall time; the solves set their own ("portfolio" from it)."""


def tiny_config(family: str, member: str) -> dict:
    """--tiny's solve settings: the member's, with 8 particles and 2 iterations per phase."""
    config = solve_config(family, member) or {}
    return {**config, "particles": 8, "screen": {"candidates": 8},
            "stamp": {**config.get("stamp", {}), "svgd_max_iters": 2, "sgd_max_iters": 2,
                      "min_iters": 0}}


def measure(families: dict[str, list[str]], *, samples: int, budget_s: float | str,
            seed: int, methods: list[str], out: dict, save: Callable[[], None] = lambda: None,
            say: Callable[[str], None] = print,
            configs: Callable[[str, str], dict | None] = solve_config) -> dict:
    """Fills `out["families"]` member by member (saving after each method); returns `out`.

    `budget_s`: seconds for each sampler; "stamp": the wall time STAMP took on
    the member (then "stamp" runs first); or {family: {member: seconds}}.
    `configs(family, member)`: the solve settings of the solves.
    """
    out.setdefault("families", {})
    if budget_s == "stamp":
        methods = ["stamp", *[m for m in methods if m != "stamp"]]
    for family, members in families.items():
        for member in members:
            task = FAMILIES[family][member]()
            config = configs(family, member)
            started = time.perf_counter()
            # The share is the member's, whatever the methods' seed: its shots are seed 0's.
            row = {"dim": task.dim, **success_share(task, samples), "methods": {}}
            bound = "<= " if row["success_share_is_upper_bound"] else ""
            say(f"{family} {member}: d = {task.dim}, success share {bound}"
                f"{row['success_share']:.3g} ({row['successes']}/{samples}, "
                f"{len(row['sampled_task_plans'])} task plans; "
                f"{time.perf_counter() - started:.0f} s)")
            out["families"].setdefault(family, {})[member] = row
            budget = (None if budget_s == "stamp" else budget_s[family][member]
                      if isinstance(budget_s, dict) else float(budget_s))
            for name in methods:
                rec = METHODS[name](task, config, budget or 0.0, seed)
                if name == "stamp" and budget is None:
                    budget = rec["wall_s"]
                rec["quality"] = quality(task, rec.pop("plans"), seed=seed)
                row["methods"][name] = rec
                first = rec["first_plan_s"]
                say(f"{family} {member}: {name} {rec['task_plans']} task plans in "
                    f"{rec['wall_s']:.1f} s ({rec['samples']} samples; first at "
                    f"{'-' if first is None else f'{first:.2f} s'})")
                save()
            row["budget_s"] = budget
            save()
    return out


COLORS = {"stamp": "C0", "portfolio": "C4", "screen+adam": "C2", "random": "C1", "cmaes": "C3"}
"""One colour per method in every family's figure."""


def best_sampler(row: dict) -> str | None:
    """The sampler of `SAMPLERS` that found most task plans on a member (first first on ties)."""
    ran = [m for m in SAMPLERS if m in row["methods"]]
    return max(ran, key=lambda m: row["methods"][m]["task_plans"], default=None)


def versus(row: dict, method: str) -> dict | None:
    """How `method` fares against the member's best sampler (the issue's targets), or None.

    Returns:
      {"sampler", "plans_ratio": method's task plans / the sampler's (None if
      the sampler found none), "first_plan_ratio": method's first plan time /
      the sampler's, "common": task plans both found, "cost_le_share": share of
      those where the method's best C cost <= the sampler's, "robustness_gain":
      median over them of method's best robustness - the sampler's}.
    """
    sampler = best_sampler(row)
    if sampler is None or method not in row["methods"]:
        return None
    mine, theirs = row["methods"][method], row["methods"][sampler]
    common = sorted(set(mine["quality"]) & set(theirs["quality"]))
    a, b = mine["quality"], theirs["quality"]
    first = (mine["first_plan_s"] / theirs["first_plan_s"]
             if mine["first_plan_s"] is not None and theirs["first_plan_s"] else None)
    return {
        "sampler": sampler,
        "plans_ratio": mine["task_plans"] / theirs["task_plans"] if theirs["task_plans"] else None,
        "first_plan_ratio": first, "common": len(common),
        "cost_le_share": (float(np.mean([a[p]["cost"] <= b[p]["cost"] for p in common]))
                          if common else None),
        "robustness_gain": (float(np.median([a[p]["robustness"] - b[p]["robustness"]
                                             for p in common])) if common else None),
    }


def anytime(rec: dict) -> tuple[list[float], list[int]]:
    """(seconds, task plans found by then) of a record: a step curve from 0 to its wall time."""
    found = rec["found_at_s"]
    return [0.0, *found, rec["wall_s"]], [0, *range(1, len(found) + 1), len(found)]


def family_figure(family: str, rows: dict):
    """One panel per member: distinct verified task plans against seconds, a line per method."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3.0 * len(rows) + 0.6, 3.4), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(rows), squeeze=False)[0]
    for ax, (member, row) in zip(axes, rows.items(), strict=True):
        for name, rec in row["methods"].items():
            t, n = anytime(rec)
            ax.step(t, n, where="post", color=COLORS.get(name), label=name, lw=1.6)
        share = row["success_share"]
        bound = "≤ " if row.get("success_share_is_upper_bound") else ""
        ax.set_title(f"{member}: d = {row['dim']}, share {bound}{share:.1g}", fontsize=9)
        ax.set_xlabel("wall time (s)")
        ax.set_ylim(bottom=0)
    axes[0].set_ylabel("distinct verified task plans")
    axes[-1].legend(fontsize=8, loc="lower right")
    fig.suptitle(f"{family}: task plans found against wall time\n(equal budgets, same cores)",
                 fontsize=10)
    return fig


def table(out: dict) -> str:
    """The README's markdown table: per member d, share, budget, each method's plans (first s)."""
    rows = [row for family in out["families"].values() for row in family.values()]
    methods = [m for m in METHODS if any(m in row["methods"] for row in rows)]
    head = ["family", "member", "d", "success share", "budget s",
            *[f"{m}: plans (first s)" for m in methods],
            "stamp vs best sampler: cost ≤, robustness +"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for family, rows in out["families"].items():
        for member, row in rows.items():
            share = row["success_share"]
            cells = [family, member, str(row["dim"]),
                     f"{'≤ ' if row.get('success_share_is_upper_bound') else ''}{share:.2g}",
                     f"{row.get('budget_s') or 0:.0f}"]
            for m in methods:
                rec = row["methods"].get(m)
                first = None if rec is None else rec["first_plan_s"]
                cells.append("-" if rec is None else
                             f"{rec['task_plans']} ({'-' if first is None else f'{first:.1f}'})")
            v = versus(row, "stamp")
            cells.append("-" if not v or not v["common"] else
                         f"{v['cost_le_share']:.0%} of {v['common']}, {v['robustness_gain']:+.2f}")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def crossover(rows: dict, method: str = "stamp") -> str | None:
    """The first member from which on `method` finds at least the best sampler's task plans.

    Members in the family's order (dimension or rarity rising); None when the
    last member is not such a one (or the method did not run).
    """
    first = None
    for member, row in rows.items():
        v = versus(row, method)
        if v is None:
            return None
        mine, theirs = row["methods"][method]["task_plans"], row["methods"][v["sampler"]]
        if mine >= theirs["task_plans"]:
            first = first or member
        else:
            first = None
    return first


def report(out: dict, figures: Path | None = None) -> str:
    """Adds each member's `versus` and each family's `crossover` for the solves; figures; table."""
    for family, rows in out["families"].items():
        for row in rows.values():
            row["versus"] = {m: versus(row, m) for m in row["methods"] if m not in SAMPLERS}
        solves = {m for row in rows.values() for m in row["versus"]}
        out.setdefault("crossover", {})[family] = {m: crossover(rows, m) for m in sorted(solves)}
    if figures is not None:
        figures.mkdir(parents=True, exist_ok=True)
        for family, rows in out["families"].items():
            family_figure(family, rows).savefig(figures / f"scaling_{family}.png", dpi=120)
    return table(out)


def main(argv: list[str] | None = None) -> int:
    """Parses the arguments, measures, prints a line per step; writes JSON with --json."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="*", choices=sorted(FAMILIES),
                        default=list(FAMILIES))
    parser.add_argument("--members", nargs="*", default=None, metavar="MEMBER",
                        help="members to run, of every family chosen (default: all)")
    parser.add_argument("--samples", type=int, default=10_000,
                        help="uniform shots per member for its success share (issue: 10^6)")
    parser.add_argument("--budget-s", default="stamp", metavar="S|stamp",
                        help="wall time each sampler gets on each member: seconds, or 'stamp' "
                        "(default): the time STAMP took on it")
    parser.add_argument("--budget-from", metavar="FILE",
                        help="each member's budget from an earlier run's JSON (its STAMP time)")
    parser.add_argument("--methods", nargs="*", choices=sorted(METHODS),
                        default=[m for m in METHODS if m != "portfolio"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="FILE", help="write the results here")
    parser.add_argument("--figures", metavar="DIR", type=Path,
                        help="write a figure per family here (scaling_FAMILY.png)")
    parser.add_argument("--report", metavar="FILE", type=Path,
                        help="measure nothing: the table and figures of an earlier run's JSON")
    parser.add_argument("--tiny", action="store_true",
                        help="one member per family, 256 shots, 8 particles, 2 iterations "
                        "per phase, 3 s budgets (a smoke run)")
    args = parser.parse_args(argv)

    if args.report:
        import json

        try:
            out = json.loads(args.report.read_text())
        except (OSError, ValueError) as e:
            parser.error(f"--report {args.report}: not a JSON file of this benchmark ({e})")
        print(report(out, args.figures))
        return 0

    import mjstamp

    mjstamp.configure(precision="float64")
    if args.budget_s != "stamp":
        try:
            args.budget_s = float(args.budget_s)
        except ValueError:
            parser.error(f"--budget-s {args.budget_s!r} must be seconds or 'stamp'")
    if args.budget_from:
        import json

        earlier = json.loads(Path(args.budget_from).read_text())["families"]
        args.budget_s = {f: {m: row["budget_s"] for m, row in rows.items()}
                         for f, rows in earlier.items()}
    if args.tiny:
        chosen = {f: TINY[f] for f in args.families}
        args.samples, args.budget_s = 256, 3.0
    else:
        chosen = {f: [m for m in FAMILIES[f] if args.members is None or m in args.members]
                  for f in args.families}
    unknown = sorted(set(args.members or []) - {m for f in args.families for m in FAMILIES[f]})
    if unknown:
        parser.error(f"no member {unknown[0]!r} in {args.families}")
    if args.samples < 1 or (isinstance(args.budget_s, float) and not args.budget_s > 0):
        parser.error("--samples must be >= 1 and --budget-s > 0")
    out = {"benchmark": "scaling", "samples": args.samples, "budget_s": args.budget_s,
           "seed": args.seed, "methods": args.methods, "families": {}}

    def save():
        if args.json:
            save_json(args.json, out, indent=1, newline=True)

    measure(chosen, samples=args.samples, budget_s=args.budget_s, seed=args.seed,
            methods=args.methods, out=out, save=save, say=lambda s: print(s, flush=True),
            configs=tiny_config if args.tiny else solve_config)
    print(report(out, args.figures))
    save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
