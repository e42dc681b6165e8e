"""The Kinova Jaco arm that ships with dm_control pushes a brick towards a post.

The scene is composed with `dm_control.mjcf` the way dm_control's manipulation
tasks compose theirs (`dm_control/manipulation/lift.py`): the suite's
`arenas.Standard` (its ground plane is the table top), `kinova.JacoArm` with
`kinova.JacoHand` attached at the wrist, a `props.primitive.Box` brick added
as a free entity, and a fixed box post. Everything comes from the installed
dm_control (meshes included); nothing needs the network.
`tutorials/04_robot_arm.ipynb` builds the same scene and task in user code.

θ = joint-velocity knots of the arm's three large joints (shoulder yaw, shoulder
and elbow pitch), three knots each over the horizon, interpolated linearly and
sent to the arm's own actuators. N.B. dm_control's Jaco has *velocity* servos
(kv = 500, |q̇| ≤ 36°/s on the large joints, 48°/s on the wrist), so the
command a user of this arm chooses is a joint-velocity profile, and the box of
θ is the actuators' ctrlrange (joint limits are the MJCF's, enforced by the
simulator). The wrist joints and the fingers are held (velocity 0): the
closed hand, pointing down, is the pusher.

The hand starts beside the brick; sweeping the shoulder (joint 1 turning
negative) pushes the brick along +y towards a fixed post. Two goal regions lie
on that line: "near" (the brick pushed 4-7 cm) and "post" (9-12 cm, up to
the post's face). The task plan is the contact symbols (the hand's fist proxy
touched the brick; the brick touched the post) and the goal region the brick
ends in: uniform shots over θ reach 10-near, 10-post and 11-post (a plan
that parks the brick against the post, or short of it).

Choices (and why):
- collisions as dm_control sets them, pruned for MJX: the arm's links collide
  with nothing (dm_control collides them with each other: contype 3 /
  conaffinity 2; here they stay ≥ 15 cm above the table), the palm neither (it
  stays ≥ 8 cm above the fingertips, over a 5 cm brick and a 6 cm post); the
  six finger meshes collide with the brick, the post and the table; the brick
  with the table and the post. MJX tests every candidate pair every step
  (there is no broad phase), so each pruned mesh pair is time saved;
- noslip off: dm_control's arena asks for 5 noslip iterations, which MJX does
  not run; the C replay must run the physics MJX plans with;
- the finger meshes' convex hulls capped at 24 vertices (`maxhullvert`; as
  shipped 156 and 213): MuJoCo C and MJX both collide a mesh by its hull; the
  cap makes the MJX step cheaper to compile and to run, while the three task
  plans still succeed in C;
- 5 ms steps (dm_control's: 2 ms), 240 of them (1.2 s): MJX's cost is per
  step, and MuJoCo C finds the same task plans in about the same shares at
  2 ms as at 5 ms; at 36°/s the fingertips sweep about 0.3 m/s, enough to
  push the brick 15-20 cm in 1.2 s;
- the shoulder and elbow pitch knots are bounded by ±0.2 rad/s, not their
  servos' ±0.63: faster pitching lifts the fist off the table (or presses it
  in) within the horizon, and pushes nothing;
- the goals lie along the sweep: with the servos' speed limits the brick's
  end point spreads ±4 cm across the sweep and 0-12 cm along it in 1.2 s;
- solve settings: 8 particles, at most 5 SVGD and 10 SGD iterations: the
  value and gradient run MJX's own solver to convergence with its line search
  every step, so an iteration costs far more than on the small scenes; the
  seeding screen (512 shots in C) already starts most of the 8 particles on
  successes of all three task plans, and the gradient steps refine them;
- calibration: a pushed brick sticks or slips depending on where the solver
  starts, so MJX's solver without warm start parts from the scene's physics
  beyond the fidelity tolerance; calibration's last candidate (the MJCF's own
  line search and warm start) follows it exactly;
- symbols and the aim cost read a sphere proxy round the closed fingers (a
  closed form), not a finger mesh against the brick: that needs the hull
  enumerated in the C replay's pose pass, which runs out of memory on it;
- XLA's CPU fusion emitters recompute the kinematic chain in every fused
  consumer, at a large cost on this arm: `mjstamp.configure` turns them off.

Measurements behind these choices: benchmarks/results/README.md,
"Measurements quoted from the code".
"""

from __future__ import annotations

import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.registry import register
from mjstamp.scenes import Scene
from mjstamp.scenes.compose import start_at
from mjstamp.tasks import costs
from mjstamp.tasks.task import Task

ARM_JOINTS = tuple(f"joint_{k}" for k in range(1, 7))
FINGERS = ("finger_1", "finger_2", "finger_3")
#: Finger geoms (proximal and distal meshes of each finger): the pusher.
FINGER_GEOMS = tuple(f"finger_{part}_{k}" for k in (1, 2, 3) for part in ("knuckle", "tip"))
#: Joints θ drives (velocity knots): shoulder yaw, shoulder pitch, elbow pitch.
DRIVEN = ("joint_1", "joint_2", "joint_3")
#: Arm pose at t = 0: the closed hand pointing down, its pinch site at
#: (0.5, -0.1, 0.022) m, fingertips 1 cm above the table (solved once by damped
#: least squares on the pinch site).
HOME_ARM = (0.005, 2.1571, 4.6673, 2.9519, 0.7334, -2.092)
HOME_FINGERS = 1.0  # rad: closed into a fist (range 0.15-1.35)
#: The fist proxy: centre in the hand's frame and radius enclosing the finger
#: meshes below 6 cm at home (measured from the meshes' vertices).
FIST_POS = (-0.0056, -0.0045, -0.1789)
FIST_RADIUS = 0.055
FIST = "jaco_arm/jaco_hand/fist"

# Collision bits: 1 = static world and the brick, 2 = the fingers.
_WORLD, _FINGER = 1, 2


def default_config() -> dict:
    """Settings of the Jaco task."""
    return {
        "horizon": 240,  # steps of `timestep`: 1.2 s
        "timestep": 0.005,  # s (dm_control's: 0.002)
        "knots": 3,
        "pitch_speed": 0.2,  # rad/s: bound of the shoulder and elbow pitch knots
        "hull_vertices": 24,  # per finger mesh's convex hull; 0: as shipped (156 and 213)
        "brick_x": 0.5,
        "brick_y": 0.03,
        "brick_half": 0.025,
        "brick_mass": 0.2,
        "post_x": 0.5,
        "post_y": 0.2,
        "post_half": 0.025,
        "goal_x": 0.5,
        "goal_near_y": 0.085,
        "goal_post_y": 0.135,
        "goal_half_x": 0.05,
        "goal_half_y": 0.02,
        "aim_weight": 10.0,
        "goal_weight": 200.0,
    }


def solve_config() -> dict:
    """Settings of its solve (the rest are `SolveConfig`'s defaults)."""
    return {"particles": 8,
            "stamp": {"jacobian": "rev", "svgd_max_iters": 5, "sgd_max_iters": 10,
                      "min_iters": 5}}


def compose(config: dict | None = None):
    """The scene as a `dm_control.mjcf.RootElement` (see the module docstring).

    Args:
      config: task settings (`default_config()` where None); reads the brick,
        post and goal entries.

    Returns:
      the arena's RootElement with the arm, hand, brick, post and goal sites;
      its `get_assets()` holds the meshes.
    """
    # N.B. imported here: dm_control pulls in its composer (and glfw) at import.
    from dm_control.entities.manipulators import kinova  # noqa: PLC0415
    from dm_control.manipulation.props import primitive  # noqa: PLC0415
    from dm_control.manipulation.shared import arenas  # noqa: PLC0415

    c = {**default_config(), **(config or {})}
    arena = arenas.Standard(name="arena")
    root = arena.mjcf_model
    root.option.noslip_iterations = 0  # MJX runs no noslip; C must replay what MJX plans
    root.option.timestep = float(c["timestep"])
    ground = root.find("geom", "ground")
    ground.contype, ground.conaffinity = _WORLD, _WORLD | _FINGER

    arm = kinova.JacoArm(name="jaco_arm")
    hand = kinova.JacoHand(name="jaco_hand", use_pinch_site_as_tcp=True)
    arm.attach(hand)
    for mesh in ("finger_proximal", "finger_distal") if int(c["hull_vertices"]) else ():
        hand.mjcf_model.find("mesh", mesh).maxhullvert = int(c["hull_vertices"])
    for geom in arm.mjcf_model.find_all("geom") + hand.mjcf_model.find_all("geom"):
        finger = geom.name in FINGER_GEOMS
        geom.contype = _FINGER if finger else 0
        geom.conaffinity = 0
    # A contact proxy (collides with nothing): the sphere round the fingers' lower
    # halves. Symbols and the aim cost read its signed distance to the brick, a
    # closed form, where a finger mesh against the brick needs the hull enumerated
    # (the C replay's pose pass runs out of memory on it).
    hand.mjcf_model.find("body", "hand").add(
        "geom", name="fist", type="sphere", size=(FIST_RADIUS,), pos=FIST_POS, mass=0,
        contype=0, conaffinity=0, group=3, rgba=(1, 1, 1, 0.15))
    arena.attach(arm)

    h = float(c["brick_half"])
    brick = primitive.Box(half_lengths=[h, h, h], mass=float(c["brick_mass"]), name="brick")
    brick.geom.name = "brick"
    brick.geom.rgba = (0.8, 0.3, 0.2, 1.0)
    brick.geom.friction = (0.4, 0.005, 0.0001)  # the arena's table friction
    brick.geom.contype, brick.geom.conaffinity = _WORLD, _WORLD | _FINGER
    frame = arena.add_free_entity(brick)
    frame.pos = (c["brick_x"], c["brick_y"], h)

    p = float(c["post_half"])
    root.worldbody.add("geom", name="post", type="box", size=(p, p, 0.03),
                       pos=(c["post_x"], c["post_y"], 0.03), rgba=(0.5, 0.5, 0.55, 1),
                       contype=_WORLD, conaffinity=_WORLD | _FINGER)
    for name, y in (("goal_near", c["goal_near_y"]), ("goal_post", c["goal_post_y"])):
        root.worldbody.add("site", name=name, type="box",
                           size=(c["goal_half_x"], c["goal_half_y"], 0.001),
                           pos=(c["goal_x"], y, 0.001), rgba=(0.2, 0.7, 0.3, 0.4))
    return root


def scene(config: dict | None = None) -> Scene:
    """The Jaco scene as a `Scene` (composed by `compose`)."""
    root = compose(config)
    start_at(root, home_angles())
    return Scene(root, name="jaco")


def home_angles() -> dict[str, float]:
    """{joint: angle}: the arm at HOME_ARM, the fingers closed (`scenes.compose.start_at`)."""
    homes = {f"jaco_arm/{j}": q for j, q in zip(ARM_JOINTS, HOME_ARM, strict=True)}
    homes.update({f"jaco_arm/jaco_hand/{f}": HOME_FINGERS for f in FINGERS})
    return homes


BRICK = "brick/brick"  # the prop's geom, namespaced by its entity


def brick_body(scene: Scene) -> str:
    """Name of the brick's body (the free entity's attachment frame)."""
    return scene.m.body(int(scene.m.geom_bodyid[scene.geom(BRICK)])).name
GOALS = {"near": "goal_near", "post": "goal_post"}


def velocity_knots(name: str, scene: Scene, knots: int, horizon: int):
    """Controls: θ (n, J·knots) -> ctrl (n, T, nu), J = len(DRIVEN) velocity profiles.

    Each driven joint's velocity command is the piecewise-linear interpolation of
    its `knots` values spread evenly from the first step to the last; every
    other actuator (wrist, fingers) is commanded 0, which its velocity servo
    holds. Plain array operations (θ on the left), so the same function serves
    JAX (planning) and numpy (the MuJoCo C replay).
    """
    t = np.linspace(0.0, 1.0, horizon)
    at = np.linspace(0.0, 1.0, knots)
    weights = np.stack([np.interp(t, at, row) for row in np.eye(knots)])  # (knots, T)
    select = np.zeros((len(DRIVEN), scene.m.nu))  # driven joint -> its actuator
    for i, j in enumerate(DRIVEN):
        select[i, scene.actuator(f"jaco_arm/{j}")] = 1.0

    def controls(params):
        x = params[name]
        v = (x.reshape(x.shape[0], len(DRIVEN), knots) @ weights).swapaxes(1, 2)  # (n, T, J)
        return v @ select

    return controls




def declare_arm(task: Task, config: dict) -> str:
    """Declares the Jaco task's θ, controls, contact symbols and aim; the brick's body name.

    What a task of another goal on the same scene (`task.scene`, `scene(config)`)
    shares with this one: `benchmarks/scaling.py`'s jaco family.
    """
    knots = int(config["knots"])
    if knots < 2:
        raise MjstampError(f"task {task.name!r}: knots={knots} must be >= 2")
    sc = task.scene
    limits = np.array([sc.m.actuator_ctrlrange[sc.actuator(f"jaco_arm/{j}")] for j in DRIVEN])
    pitch = float(config["pitch_speed"])
    limits[1:] = np.clip(limits[1:], -pitch, pitch)
    low, high = np.repeat(limits[:, 0], knots), np.repeat(limits[:, 1], knots)
    task.box("velocity", low=low, high=high)
    task.controls(velocity_knots("velocity", sc, knots, task.horizon))
    task.contact("hand_brick", FIST, BRICK)
    task.contact("brick_post", BRICK, "post")
    task.cost("aim", costs.aim(FIST, BRICK), weight=config["aim_weight"])
    return brick_body(sc)


@register("jaco", default_config,
          "the Kinova Jaco arm (dm_control) pushes a brick round a post into a goal",
          solve_config=solve_config)
def make(config: dict) -> Task:
    """Builds the Jaco task from its settings (see `default_config`)."""
    if int(config["knots"]) < 2:  # N.B. before the scene is composed
        raise MjstampError(f"task 'jaco': knots={int(config['knots'])} must be >= 2")
    sc = scene(config)
    task = Task("jaco", sc, horizon=int(config["horizon"]), settings=config,
                description="push the brick into a goal region; task plan = whether the "
                "brick touched the post, and the goal")
    brick = declare_arm(task, config)
    task.cost("goal", costs.reach(brick, list(GOALS.values()), when="final"),
              weight=config["goal_weight"])
    task.success(costs.ends_in_any(brick, GOALS))
    task.display(trace=(brick,), force=[("jaco_arm/jaco_hand/finger_tip_2", BRICK)])
    return task
