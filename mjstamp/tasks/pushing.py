"""Block pushing (STAMP §V-A2, App. C), written with the public task API.

θ = [s¹..s^K, g¹..g^K] as in eq. (9): four logits per push (which side of the
block to push: north, east, south, west) and the block's goal pose after each
push (x, y; yaw φ). θ orders the goal positions before the yaws, so a box
variable holds every (x, y) and an angle variable every φ. Controls are not
in θ: each push is played by that side's DMP skill (`mjstamp.skills.pushing`)
and tracked by the scene's servos, so K pushes take 7K coordinates.

The task plan is the sequence of sides the pusher actually pushed, read off the
replay (a phase counts when the pusher touched the block and the block moved
at least 1 cm); a plan is verified when its MuJoCo C replay ends with the
block's centre inside the goal region and the pusher never moved the block by
pressing on its top face (which a pusher lowered onto a block that is not
where the plan expected can do, dragging it by friction: that is decoded as
"top" and fails).

Choices (and why):
- log posterior = −β_target L_target − β_subgoal L_subgoal + β_traj log p(g):
  App. C-C's goal-region loss and Manhattan prior, plus a subgoal term
  (block after push k near g^k) that keeps the planned poses honest, since
  the next push's approach is aimed at g^k;
- the Manhattan prior reads App. C-C's p(g^k | g^{k−1}) as
  exp(−[D(g^{k−1}, g^k) + D(g^k, G) − D(g^{k−1}, G)]) with G the goal region's
  centre: zero for pushes that head monotonically towards G, and the detour
  length otherwise (the paper's second term, D(g^k, g^k), is read as a typo);
- a cost on touching the block from above (`pushed_from_above`) steers the
  planner away from such drags;
- the goal loss aims 3 cm inside the 8 cm half-size region, so that a plan the
  relaxation calls good stays good when replayed with the scene's own solver
  (`goal_margin`; a region shrunk by `goal_half_size` is aimed at no deeper
  than half-way to its centre);
- discrete SVGD (eq. 4) on Γ̃ with the target at Γ, then SGD on the goals
  with the sides fixed (App. E); the library's 50 SVGD + 100 SGD iterations
  (Adam 0.03, then 0.02): SVGD spreads the sides and goals and, since its
  backtracking holds each particle within d/2 nats of its peak at Γ, lowers
  the mean cost by a large share of the whole decrease (without that guard,
  longer SVGD would raise the mean cost at Γ: the blended references of Γ̃
  are poor plans); SGD at Γ is where plans converge;
- goal yaws start within ±0.3 rad: the block's four sides make yaw ambiguous
  beyond ±π/4 and the servos push at side centres.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.progress import Progress
from mjstamp.registry import Command, Option, register
from mjstamp.scenes import Scene
from mjstamp.scenes.scene import package_model_path
from mjstamp.skills import pushing as skills
from mjstamp.tasks import costs
from mjstamp.tasks.task import Task


def default_config() -> dict:
    """Defaults of the pushing task and of its solve."""
    return {
        "max_pushes": 2,
        "approach_steps": 40,
        "push_steps": 60,
        "settle_steps": 20,
        "x_min": -0.4,
        "x_max": 0.9,
        "y_min": -0.4,
        "y_max": 0.7,
        "goal_x": 0.5,
        "goal_y": 0.3,
        "goal_half_size": 0.08,  # the shipped region's (m); the goal is the square ± this
        "goal_margin": 0.03,  # the loss aims this far inside the region, at most half-way in
        "target_weight": 500.0,
        "subgoal_weight": 50.0,
        "trajectory_weight": 5.0,
        "above_weight": 100.0,
        "skill_bank": "",  # "" = ~/.cache/mjstamp/skills/pushing.npz, refitted when stale
    }


def solve_config() -> dict:
    """Settings of its solve (the rest are `SolveConfig`'s defaults)."""
    return {
        "particles": 64,
        "stamp": {
            "svgd_learning_rate": 0.03,
            "sgd_learning_rate": 0.02,
            "sgd_max_iters": 100,
            "min_iters": 20,
            "jacobian": "rev",
        },
    }


def _skills_arguments(parser) -> None:
    parser.add_argument("--out", metavar="FILE",
                        help="bank file to write (default: the cache the pushing task reads)")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--quiet", action="store_true")


def _skills_command(args) -> int:
    """`mjstamp skills`: record the demonstrations, fit and save the skill bank."""
    import json  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    from mjstamp.skills import bank as bank_mod  # noqa: PLC0415

    out = Path(args.out) if args.out else skills.DEFAULT_BANK
    scene = Scene.shipped("pushing")
    setup = skills.PushSetup.from_scene(scene)
    demos = skills.record_all(scene, setup)
    bank = skills.fit_bank(scene, setup, demos=demos, progress=Progress(not args.quiet, "skills"))
    path = bank_mod.save(bank, out)
    errors = skills.fit_errors(scene, setup, bank, demos=demos)
    if args.json:
        print(json.dumps({"path": str(path), "fingerprint": bank.fingerprint, "errors": errors}))
        return 0
    print(f"wrote {path} ({len(bank.skills)} skills, fingerprint {bank.fingerprint})")
    for name, e in errors.items():
        print(f"{name:<16} reproduces its demonstrations to {e['rms_rel']:.2%} RMS of their "
              f"extent; end error {e['end_rel']:.2%}")
    return 0


#: Most pushes a plan may have (4^K push sequences; the paper goes to 5).
MAX_PUSHES = 10


def _positive_pushes(text: str) -> int:
    k = int(text)
    if not 1 <= k <= MAX_PUSHES:
        raise MjstampError(f"--max-pushes={k} must be in 1..{MAX_PUSHES}")
    return k


OPTIONS = (Option("--max-pushes", "max_pushes", _positive_pushes,
                  "pushing: plan up to K pushes (same as --set max_pushes=K)", "K"),)
COMMANDS = (Command("skills", "record the pushing demonstrations and fit the DMP skill bank",
                    _skills_arguments, _skills_command),)


def _scene(goal_x: float, goal_y: float, half_size: float) -> Scene:
    """The shipped pushing scene, its goal region moved to (goal_x, goal_y), ± half_size."""
    path = package_model_path("pushing.xml")
    spec = mujoco.MjSpec.from_file(str(path))
    site = spec.site("goal")
    if tuple(site.pos[:2]) == (goal_x, goal_y) and tuple(site.size[:2]) == (half_size,) * 2:
        return Scene.shipped("pushing")
    site.pos = [goal_x, goal_y, site.pos[2]]
    site.size = [half_size, half_size, site.size[2]]
    return Scene(spec.to_xml(), name="pushing")


def manhattan_detour(goal_xy, start_xy, target_xy):
    """Σ_k D(g^{k−1}, g^k) + D(g^k, G) − D(g^{k−1}, G), D the (smoothed) Manhattan distance.

    Args:
      goal_xy: (n, K, 2) intermediate goals g¹..g^K.
      start_xy: (2,) g⁰, the block's start.
      target_xy: (2,) G, the goal region's centre.

    Returns:
      (n,) the detour: >= 0, 0 when every push heads monotonically towards G.

    References:
      STAMP App. C-C (trajectory loss).
    """

    def dist(a, b):
        return jnp.sum(jnp.sqrt((a - b) ** 2 + 1e-8), axis=-1)

    start = jnp.broadcast_to(jnp.asarray(start_xy, goal_xy.dtype), goal_xy[:, :1].shape)
    prev = jnp.concatenate([start, goal_xy[:, :-1]], axis=1)
    target = jnp.asarray(target_xy, goal_xy.dtype)
    return jnp.sum(dist(prev, goal_xy) + dist(goal_xy, target) - dist(prev, target), axis=1)


TOP = "top"


def pushed_from_above(setup: skills.PushSetup):
    """Cost: the share of steps the pusher presses on the block's top face.

    A pusher lowered onto the block (where a plan expected the block elsewhere)
    can drag it by friction; that is not a push of a side. Smooth in θ:
    mean_t σ((z_t − h) / 5 mm) σ(−sd_t / 2 mm), z the pusher's height, h the
    block's half side, sd their signed distance.
    """

    def cost(r):
        z = r.body_pos("pusher")[..., 2]
        sd = r.signed_distance("pusher", "block")
        above = jax.nn.sigmoid((z - setup.half) / 0.005)
        return jnp.mean(above * jax.nn.sigmoid(-sd / 0.002), axis=1)

    return cost


def ends_in_goal_pushing_sides(actions):
    """Success: the block ends in the goal region and no push was from above."""
    in_goal = costs.ends_in("block", "goal")

    def predicate(replay):
        ok, label = in_goal(replay)
        above = np.array([TOP in seq for seq in actions(replay)], dtype=bool)
        return ok & ~above, label

    return predicate


def executed_sides(setup: skills.PushSetup, scene, *, pushes: int, min_travel: float = 0.01):
    """fn(replay, planned) -> the sides each plan actually pushed, phase by phase.

    A phase counts when, during its push part, the pusher touched the block
    (signed distance < 0) and the block moved at least `min_travel`; the side
    is the one the pusher touched most often (pusher position in the block's
    frame, largest component along a side normal), or `TOP` when the pusher
    was mostly above the block's top face (not a push: see `no_top_contact`).
    """
    bq = [scene.qpos_adr(j) for j in ("block_x", "block_y", "block_yaw")]
    pq = [scene.qpos_adr(j) for j in ("pusher_x", "pusher_y", "pusher_z")]
    origin = np.asarray(setup.pusher_origin)
    block_origin = scene.m.body_pos[scene.body("block")]

    def fn(replay, planned=None):
        del planned
        K = pushes
        q = replay.qpos
        block = q[..., bq] + np.r_[block_origin[:2], 0.0]
        pusher = q[..., pq] + origin
        c, s = np.cos(block[..., 2]), np.sin(block[..., 2])
        d = pusher[..., :2] - block[..., :2]
        local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
        # Sphere-box signed distance in the block's frame (z: both centred at 0).
        box = np.array([setup.half, setup.half, setup.half])
        rel = np.concatenate([local, pusher[..., 2:]], axis=-1)
        out = np.abs(rel) - box
        sd = np.linalg.norm(np.maximum(out, 0.0), axis=-1) + np.minimum(out.max(-1), 0.0)
        touching = sd - setup.radius < 0.0
        side_of = np.argmax(local @ skills.NORMALS.T, axis=-1)  # (n, T)
        # Over the block's top face: a touch from above (pressing and dragging it).
        side_of = np.where(pusher[..., 2] > setup.half, len(skills.SIDES), side_of)
        names = (*skills.SIDES, TOP)
        result = []
        windows = setup.phase_windows(K)
        for i in range(q.shape[0]):
            seq = []
            for a, b in windows:
                lo = max(a - 1, 0)
                moved = np.linalg.norm(block[i, b - 1, :2] - block[i, lo, :2])
                hits = side_of[i, a:b][touching[i, a:b]]
                if len(hits) and moved >= min_travel:
                    seq.append(names[int(np.bincount(hits, minlength=5).argmax())])
            result.append(seq)
        return result

    return fn


@register("pushing", default_config,
          "push a block into the goal region with up to K pushes (Fig. 8; --max-pushes K)",
          solve_config=solve_config, options=OPTIONS, commands=COMMANDS)
def make(config: dict) -> Task:
    """Builds the pushing task from a config (see `default_config`)."""
    K = int(config["max_pushes"])
    if not 1 <= K <= MAX_PUSHES:
        raise MjstampError(f"task 'pushing': max_pushes={K} must be in 1..{MAX_PUSHES} (4^K "
                           "push sequences)")
    lo = np.array([config["x_min"], config["y_min"]], float)
    hi = np.array([config["x_max"], config["y_max"]], float)
    if not np.all(hi > lo):
        raise MjstampError(f"task 'pushing': workspace x in [{lo[0]}, {hi[0]}], y in "
                           f"[{lo[1]}, {hi[1]}] is empty")
    half_size = float(config["goal_half_size"])
    if not half_size > 0:
        raise MjstampError(f"task 'pushing': goal_half_size={half_size:g} must be > 0 (m)")
    scene = _scene(float(config["goal_x"]), float(config["goal_y"]), half_size)
    goal = scene.m.site_pos[scene.site("goal"), :2]
    half = scene.m.site_size[scene.site("goal"), :2]
    if np.any(goal - half < lo) or np.any(goal + half > hi):
        raise MjstampError(
            f"task 'pushing': goal region at ({goal[0]:g}, {goal[1]:g}) (half-size "
            f"{half[0]:g}) is outside the workspace box x in [{lo[0]:g}, {hi[0]:g}], "
            f"y in [{lo[1]:g}, {hi[1]:g}]"
        )
    setup = skills.PushSetup.from_scene(
        scene, approach_steps=config["approach_steps"], push_steps=config["push_steps"],
        settle_steps=config["settle_steps"])
    bank = skills.load_bank(scene, setup, config["skill_bank"] or None)

    task = Task(
        "pushing", scene, horizon=setup.horizon(K), settings=config,
        extras={"setup": setup, "bank": bank},
        description=f"push the block into the goal region with up to {K} pushes; "
        "task plan = the sides pushed, in order",
    )
    task.discrete("side", skills.SIDES, phases=K, bound=3.0)
    task.box("goal_xy", low=np.tile(lo, K), high=np.tile(hi, K))
    task.angle("goal_yaw", K, low=-0.3, high=0.3)

    def goal_poses(params):
        n = params["goal_xy"].shape[0]
        xy = jnp.reshape(params["goal_xy"], (n, K, 2))
        return jnp.concatenate([xy, jnp.reshape(params["goal_yaw"], (n, K, 1))], axis=-1)

    def controls(params):
        x_ref, v_ref = skills.references(bank, setup, jnp.asarray(params["side"]),
                                         goal_poses(params))
        return skills.controls(setup, x_ref, v_ref)

    windows = setup.phase_windows(K)

    def subgoals(r):
        """Mean squared distance of the block after each push to its planned g^k."""
        block = r.body_pos("block")[..., :2]
        ends = jnp.stack([block[:, b - 1] for _, b in windows], axis=1)  # (n, K, 2)
        planned = jnp.reshape(r.params["goal_xy"], ends.shape)
        return jnp.mean(jnp.sum((ends - planned) ** 2, axis=-1), axis=1)

    start = np.asarray(setup.block0[:2])

    def trajectory(params):
        n = params["goal_xy"].shape[0]
        return -manhattan_detour(jnp.reshape(params["goal_xy"], (n, K, 2)), start, goal)

    task.controls(controls)
    margin = min(float(config["goal_margin"]), 0.5 * half_size)  # a small region: aim at its middle
    task.cost("target", costs.box_target("block", "goal", margin=margin),
              weight=config["target_weight"])
    task.cost("subgoals", subgoals, weight=config["subgoal_weight"])
    task.prior("trajectory", trajectory, weight=config["trajectory_weight"])
    task.cost("from_above", pushed_from_above(setup), weight=config["above_weight"])
    sides = executed_sides(setup, scene, pushes=K)
    task.success(ends_in_goal_pushing_sides(sides))
    task.actions_from(sides)
    task.display(trace=("block", "pusher"), force=[("pusher", "block")])
    return task
