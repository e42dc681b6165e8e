"""Pushing skills: scripted demonstrations, one DMP skill per side, servo references.

One skill per discrete action (push the block's north, east, south or west
side; STAMP §IV-C). A skill is two goal-conditioned DMPs fitted from
demonstrations recorded in the pushing scene itself (`record_demonstrations`):

- *approach*: lift the pusher over the block, move to a point `gap` behind the
  chosen side of the block's current pose, and lower it (a 3-D motion whose
  10-odd cm lift is kept whatever the start and goal: the DMP's planar-similarity
  frame scales and turns the planar part only);
- *push*: move from there to the same side of the block's *goal* pose, pressing
  the block along.

`references` turns a plan θ = (one-hots of the sides, goal poses g¹..g^K) into
the pusher's reference trajectory x̂(t), v̂(t); the scene's position and velocity
servos track it (u = kp (x̂ − x) + kv (v̂ − v), see models/pushing.xml), so
the controls come out of a differentiable tracking controller and θ holds only
the goals and the action logits. With relaxed one-hots Γ̃(s) the four skills'
references are blended by their weights.

References:
  STAMP §IV-C (learning action abstractions), §V-A2, App. C; eq. (5), (9).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.progress import Progress, ProgressLike
from mjstamp.skills import bank as bank_mod
from mjstamp.skills import dmp

SIDES = ("north", "east", "south", "west")  # the paper's 1-4
# Outward normal of each side in the block's frame; the pusher stands on that
# side and pushes the block along minus the normal.
NORMALS = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]])
DEFAULT_BANK = Path.home() / ".cache" / "mjstamp" / "skills" / "pushing.npz"


#: Most steps of one part of a push (approach, push, settle): a minute at 5 ms.
MAX_PART_STEPS = 12_000


@dataclasses.dataclass(frozen=True)
class PushSetup:
    """Geometry and timing of pushes in the pushing scene.

    Attributes:
      half: half side of the block (m).
      radius: pusher radius (m).
      gap: standoff behind a side where a push starts (m).
      lift: height the pusher lifts to when it changes sides (m); the block's
        top is at `half`, so this must exceed half + radius.
      approach_steps: steps of the approach part of a phase.
      push_steps: steps of the push part of a phase.
      settle_steps: steps after the last push, pusher held still.
      dt: scene timestep (s).
      block0: (3,) initial block pose (x, y, yaw).
      pusher0: (3,) initial pusher position (world).
      pusher_origin: (3,) world position of the pusher's joints' zero.
    """

    half: float
    radius: float
    gap: float
    lift: float
    approach_steps: int
    push_steps: int
    settle_steps: int
    dt: float
    block0: tuple[float, float, float]
    pusher0: tuple[float, float, float]
    pusher_origin: tuple[float, float, float]

    @classmethod
    def from_scene(
        cls,
        scene,
        *,
        approach_steps: int = 40,
        push_steps: int = 60,
        settle_steps: int = 20,
        gap: float = 0.04,
        lift: float = 0.12,
    ) -> PushSetup:
        """Reads sizes and initial poses from the pushing scene."""
        m = scene.m
        half = float(m.geom_size[scene.geom("block"), 0])
        radius = float(m.geom_size[scene.geom("pusher"), 0])
        if not lift > half + radius:
            raise MjstampError(
                f"lift={lift} m must exceed the block's top plus the pusher "
                f"radius, {half + radius:.3f} m"
            )
        # N.B. each part's DMP is fitted from its steps + 1 samples: 2 per basis function.
        fewest = 2 * dmp_config().n_basis - 1
        for name, value in (("approach_steps", approach_steps), ("push_steps", push_steps)):
            if int(value) > MAX_PART_STEPS:
                raise MjstampError(f"{name}={value} must be <= {MAX_PART_STEPS} steps")
            if int(value) < fewest:
                raise MjstampError(
                    f"{name}={value} must be >= {fewest} steps: its DMP skill "
                    f"({dmp_config().n_basis} basis functions) is fitted from steps + 1 samples, "
                    "two per basis function"
                )
        if not 0 <= int(settle_steps) <= MAX_PART_STEPS:
            raise MjstampError(f"settle_steps={settle_steps} must be in 0..{MAX_PART_STEPS}")
        origin = m.body_pos[scene.body("pusher")].copy()
        q0 = m.qpos0
        block0 = (
            float(m.body_pos[scene.body("block"), 0] + q0[scene.qpos_adr("block_x")]),
            float(m.body_pos[scene.body("block"), 1] + q0[scene.qpos_adr("block_y")]),
            float(q0[scene.qpos_adr("block_yaw")]),
        )
        pusher0 = tuple(
            float(origin[i] + q0[scene.qpos_adr(j)])
            for i, j in enumerate(("pusher_x", "pusher_y", "pusher_z"))
        )
        return cls(
            half,
            radius,
            float(gap),
            float(lift),
            int(approach_steps),
            int(push_steps),
            int(settle_steps),
            float(m.opt.timestep),
            block0,
            pusher0,
            tuple(float(v) for v in origin),
        )

    def horizon(self, pushes: int) -> int:
        """Steps of a plan with `pushes` phases."""
        return pushes * (self.approach_steps + self.push_steps) + self.settle_steps

    def phase_windows(self, pushes: int) -> list[tuple[int, int]]:
        """[(first, last + 1) step of each push part]; steps count from 0."""
        per = self.approach_steps + self.push_steps
        return [(k * per + self.approach_steps, (k + 1) * per) for k in range(pushes)]


def side_points(setup: PushSetup, pose, offset: float, xp=jnp):
    """Points `offset` beyond the centre of each side of a block pose.

    Args:
      setup: `PushSetup`.
      pose: (..., 3) block poses (x, y, yaw).
      offset: distance from the block's centre along each side's normal.
      xp: jnp or np.

    Returns:
      (..., 4, 2) planar points, sides in `SIDES` order.
    """
    c, s = xp.cos(pose[..., 2]), xp.sin(pose[..., 2])
    n = xp.asarray(NORMALS)
    rotated = xp.stack(
        [
            c[..., None] * n[:, 0] - s[..., None] * n[:, 1],
            s[..., None] * n[:, 0] + c[..., None] * n[:, 1],
        ],
        axis=-1,
    )
    return pose[..., None, :2] + offset * rotated


# ---------------------------------------------------------------------------
# Demonstrations.


def _min_jerk(u):
    """Minimum-jerk profile and its derivative on u in [0, 1]."""
    u = np.clip(u, 0.0, 1.0)
    return 10 * u**3 - 15 * u**4 + 6 * u**5, 30 * u**2 - 60 * u**3 + 30 * u**4


def _scripted_reference(setup: PushSetup, start, pre, end):
    """The scripted pusher reference of one demonstration: lift-move-lower, then push.

    Returns (x̂ (T, 3), v̂ (T, 3)) for steps 1..T, T = approach + push steps.
    """
    dt = setup.dt
    ta, tp = setup.approach_steps * dt, setup.push_steps * dt
    t = np.arange(1, setup.approach_steps + 1) * dt / ta
    # Planar move in the middle of the approach, while the pusher is up.
    move, dmove = _min_jerk((t - 0.25) / 0.5)
    up, dup = _min_jerk(t / 0.3)
    down, ddown = _min_jerk((t - 0.7) / 0.3)
    xa = np.zeros((len(t), 3))
    va = np.zeros((len(t), 3))
    xa[:, :2] = start[:2] + move[:, None] * (pre - start[:2])
    va[:, :2] = dmove[:, None] / (0.5 * ta) * (pre - start[:2])
    xa[:, 2] = setup.lift * (up - down)
    va[:, 2] = setup.lift * (dup / (0.3 * ta) - ddown / (0.3 * ta))
    u = np.arange(1, setup.push_steps + 1) * dt / tp
    p, dp = _min_jerk(u)
    xp_ = np.zeros((len(u), 3))
    vp = np.zeros((len(u), 3))
    xp_[:, :2] = pre + p[:, None] * (end - pre)
    vp[:, :2] = dp[:, None] / tp * (end - pre)
    return np.concatenate([xa, xp_]), np.concatenate([va, vp])


def demonstration_cases(setup: PushSetup, side: int, distances=(0.1, 0.2, 0.3)):
    """(start (3,), pre (2,), end (2,)) of the scripted demonstrations of one side.

    The block sits at the origin; the pusher starts touching each of the other
    three sides (as after an earlier push), goes to `gap` behind `side`, and
    pushes the block by each distance along minus the side's normal.
    """
    origin = np.zeros(3)
    touching = side_points(setup, origin, setup.half + setup.radius, xp=np)
    pre = side_points(setup, origin, setup.half + setup.radius + setup.gap, xp=np)[side]
    cases = []
    for other in range(4):
        if other == side:
            continue
        start = np.array([*touching[other], 0.0])
        for d in distances:
            end = touching[side] - d * NORMALS[side]
            cases.append((start, pre, end))
    return cases


def record_demonstrations(scene, setup: PushSetup, side: int, **kwargs) -> dict[str, np.ndarray]:
    """Runs the scripted pushes of one side in MuJoCo C and records the pusher.

    Args:
      scene: the pushing `Scene` (its own solver settings are used).
      setup: `PushSetup`.
      side: index into `SIDES`.
      **kwargs: passed to `demonstration_cases`.

    Returns:
      {"approach": (m, approach_steps + 1, 3), "push": (m, push_steps + 1, 3)}:
      the pusher's recorded world positions, t = 0 included, per demonstration.
    """
    m = scene.m
    d = mujoco.MjData(m)
    adr = [scene.qpos_adr(j) for j in ("pusher_x", "pusher_y", "pusher_z")]
    block = [scene.qpos_adr(j) for j in ("block_x", "block_y", "block_yaw")]
    origin = np.asarray(setup.pusher_origin)
    approach, push = [], []
    for start, pre, end in demonstration_cases(setup, side, **kwargs):
        mujoco.mj_resetData(m, d)
        d.qpos[block] = 0.0
        d.qpos[adr] = start - origin
        mujoco.mj_forward(m, d)
        x_ref, v_ref = _scripted_reference(setup, start, pre, end)
        path = [start.copy()]
        for x, v in zip(x_ref, v_ref, strict=True):
            d.ctrl[:] = np.concatenate([x - origin, v])
            mujoco.mj_step(m, d)
            path.append(d.qpos[adr] + origin)
        path = np.asarray(path)
        approach.append(path[: setup.approach_steps + 1])
        push.append(path[setup.approach_steps :])
    return {"approach": np.asarray(approach), "push": np.asarray(push)}


# ---------------------------------------------------------------------------
# The skill bank.


def dmp_config() -> dmp.DMPConfig:
    """DMP settings of the pushing skills (planar-similarity frame)."""
    return dmp.DMPConfig(frame="planar_similarity")


def fingerprint(scene, setup: PushSetup) -> str:
    """Identifies what a fitted bank depends on: this module, the DMP code, the scene, setup.

    The goal region's site is left out (a task moves and resizes it; it holds no sensor,
    tendon or actuator), and so is the model's visual extent, which sites count in.
    """
    h = hashlib.sha256()
    for module in (__file__, dmp.__file__):
        h.update(Path(module).read_bytes())
    # N.B. a task that moves or resizes its goal region reads the same bank.
    m = copy.copy(scene.m)
    goal = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "goal")
    if goal >= 0:
        m.site_pos[goal], m.site_size[goal] = 0.0, 0.0
    m.stat.center[:], m.stat.extent = 0.0, 0.0
    buffer = np.empty(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buffer)
    h.update(buffer.tobytes())
    h.update(repr(dataclasses.astuple(setup)).encode())
    h.update(repr(dmp_config()).encode())
    return h.hexdigest()[:16]


def record_all(scene, setup: PushSetup) -> dict[str, dict[str, np.ndarray]]:
    """{side: `record_demonstrations` of that side}, for every side."""
    return {side: record_demonstrations(scene, setup, i) for i, side in enumerate(SIDES)}


def fit_bank(
    scene,
    setup: PushSetup,
    *,
    demos: dict[str, dict[str, np.ndarray]] | None = None,
    progress: ProgressLike = False,
):
    """Fits each side's two DMPs to its demonstrations (recorded here unless given).

    Args:
      scene: the pushing `Scene`.
      setup: `PushSetup`.
      demos: `record_all`'s output, to fit (and later check) the same recordings.
      progress: a line per side (`mjstamp.progress`; False, the default: none).
    """
    say = Progress.of(progress or False, "skills")
    skills = {}
    for i, side in enumerate(SIDES):
        verb = "fitting" if demos is not None else "recording and fitting"
        say(f"{verb} the '{side}' push skill")
        side_demos = (demos[side] if demos is not None
                      else record_demonstrations(scene, setup, i))
        skills[f"{side}/approach"] = dmp.fit(
            side_demos["approach"], setup.approach_steps * setup.dt, dmp_config()
        )
        skills[f"{side}/push"] = dmp.fit(
            side_demos["push"], setup.push_steps * setup.dt, dmp_config()
        )
    meta = {
        "scene": scene.name,
        "setup": dataclasses.asdict(setup),
        "demonstrations_per_side": int(len(demonstration_cases(setup, 0))),
    }
    return bank_mod.SkillBank(skills=skills, meta=meta, fingerprint=fingerprint(scene, setup))


def load_bank(scene, setup: PushSetup, path: str | os.PathLike | None = None, *, say=None):
    """The pushing skill bank: loaded from `path`, fitted and saved when needed.

    With `path` None the bank lives in the user's cache
    (~/.cache/mjstamp/skills/pushing.npz) and is refitted (a few seconds) when
    missing or stale. An explicit `path` must hold a valid, current bank:
    a missing, unreadable or stale file is an error (`mjstamp skills fit
    --out PATH` writes one), so a user's file is never silently replaced.
    """
    fp = fingerprint(scene, setup)
    if path is None:
        return bank_mod.load_or_fit(DEFAULT_BANK, fp, lambda: fit_bank(scene, setup), say=say)
    refit = f"write a current one with `mjstamp skills --out {path}`"
    try:
        return bank_mod.load(path, fingerprint=fp)
    except bank_mod.MissingSkillBank:
        raise MjstampError(f"skill bank {str(path)!r} not found; {refit}") from None
    except bank_mod.StaleSkillBank as e:
        del e
        raise MjstampError(f"skill bank {str(path)!r} is stale (fitted for other "
                           f"demonstrations, scene or code); {refit}") from None


# ---------------------------------------------------------------------------
# References for the servos.


def references(bank, setup: PushSetup, onehot, goals):
    """The pusher's reference trajectory for a batch of plans.

    Args:
      bank: the fitted `SkillBank` (skills "<side>/approach", "<side>/push").
      setup: `PushSetup`.
      onehot: (n, K, 4) weights of the sides per phase (Γ̃ or Γ).
      goals: (n, K, 3) goal poses (x, y, yaw) of the block after each push.

    Returns:
      x_ref (n, T, 3), v_ref (n, T, 3): world reference position and velocity
      of the pusher at the end of steps 1..T, T = setup.horizon(K).
    """
    n, K, _ = onehot.shape
    dtype = goals.dtype
    ta, tp = setup.approach_steps, setup.push_steps
    # The four sides' skills stacked on a leading axis (one config): vmap over sides.
    approach = jax.tree.map(lambda *w: jnp.stack(w), *[bank.skills[f"{s}/approach"] for s in SIDES])
    push = jax.tree.map(lambda *w: jnp.stack(w), *[bank.skills[f"{s}/push"] for s in SIDES])
    touch = setup.half + setup.radius

    def play(skills, x0, g, steps):
        """(4 sides) x (n plans) DMP rollouts -> positions, velocities (n, 4, steps, 3)."""

        def one(skill, a, b):
            return dmp.rollout(skill, a, b, steps=steps, duration=steps * setup.dt)

        per_plan = jax.vmap(one, in_axes=(None, 0, 0))  # over plans
        x, v = jax.vmap(per_plan, in_axes=(0, 1, 1), out_axes=1)(skills, x0, g)
        return x[:, :, 1:], v[:, :, 1:]

    def at_table(p2):
        return jnp.concatenate([p2, jnp.zeros(p2.shape[:-1] + (1,), dtype)], axis=-1)

    pose = jnp.broadcast_to(jnp.asarray(setup.block0, dtype), (n, 3))
    pusher = jnp.broadcast_to(jnp.asarray(setup.pusher0, dtype), (n, 3))
    xs, vs = [], []
    for k in range(K):
        pre = at_table(side_points(setup, pose, touch + setup.gap))  # (n, 4, 3)
        end = at_table(side_points(setup, goals[:, k], touch))
        start = jnp.broadcast_to(pusher[:, None], (n, 4, 3))
        w = onehot[:, k, :, None, None]  # (n, 4, 1, 1)
        x1, v1 = play(approach, start, pre, ta)
        x2, v2 = play(push, pre, end, tp)
        xs += [jnp.sum(w * x1, axis=1), jnp.sum(w * x2, axis=1)]
        vs += [jnp.sum(w * v1, axis=1), jnp.sum(w * v2, axis=1)]
        pusher = xs[-1][:, -1]
        pose = goals[:, k]
    if setup.settle_steps:
        xs.append(jnp.repeat(pusher[:, None], setup.settle_steps, axis=1))
        vs.append(jnp.zeros((n, setup.settle_steps, 3), dtype))
    return jnp.concatenate(xs, axis=1), jnp.concatenate(vs, axis=1)


def controls(setup: PushSetup, x_ref, v_ref):
    """Servo controls (n, T, 6): reference joint positions, then velocities."""
    origin = jnp.asarray(setup.pusher_origin, x_ref.dtype)
    return jnp.concatenate([x_ref - origin, v_ref], axis=-1)


def fit_errors(scene, setup: PushSetup, bank, *, demos=None) -> dict[str, dict[str, float]]:
    """How well each skill reproduces its own demonstrations.

    Args:
      scene: the pushing `Scene`.
      setup: `PushSetup`.
      bank: the fitted `SkillBank`.
      demos: `record_all`'s output; recorded here when None.

    Returns:
      {skill name: {"rms_rel": RMS error / extent, "end_rel": worst end-point
      error / extent}}, the extent being the largest range of the
      demonstrations along any axis.
    """
    demos = record_all(scene, setup) if demos is None else demos
    out = {}
    for side in SIDES:
        for part, steps in (("approach", setup.approach_steps), ("push", setup.push_steps)):
            d = demos[side][part]
            skill = bank.skills[f"{side}/{part}"]

            def play(a, b, skill=skill, steps=steps):
                return dmp.rollout(skill, a, b, steps=steps, duration=steps * setup.dt)[0]

            x = np.asarray(jax.vmap(play)(jnp.asarray(d[:, 0]), jnp.asarray(d[:, -1])))
            extent = float(np.ptp(d, axis=1).max())
            out[f"{side}/{part}"] = {
                "rms_rel": float(np.sqrt(np.mean(np.sum((x - d) ** 2, -1))) / extent),
                "end_rel": float(np.linalg.norm(x[:, -1] - d[:, -1], axis=-1).max() / extent),
            }
    return out
