"""Tasks of the scene suite, declared the way a user of mjstamp would write them.

Every scene in this folder is plain MJCF in the style MuJoCo users write
(MuJoCo's default contact parameters, friction on, gravity on), and every task
here uses only the public API (`Task`, `box`, `contact`, `cost`, `controls`,
`success`, `display`, `costs.*`) with the library's defaults: no
temperatures, sharpness, weights beyond 1, learning rates or iteration counts
chosen for the planner. Boxes of θ are ranges a user would pick from the
physics (launch speeds, motor ranges, reachable via points).

`SUITE = {name: make}`: `make()` returns a fresh `Task`, smallest scenes first.
`examples.py` holds θ found while authoring, one per main task plan, that
tests/test_scene_suite.py replays.

N.B. the controls functions are written with plain array operations (`*`,
`@`, `reshape`, `swapaxes`, the θ array on the left), so that one function
serves both JAX (planning) and numpy (MuJoCo C replay).
"""

from __future__ import annotations

import ast
import hashlib
from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from mjstamp import Scene, Task, costs

HERE = Path(__file__).resolve().parent


def scene_path(name: str) -> Path:
    """The MJCF file of a suite scene."""
    return HERE / f"{name}.xml"


def _scene(name: str) -> Scene:
    return Scene(scene_path(name), name=name)


def _steps(scene: Scene, seconds: float) -> int:
    return int(round(seconds / scene.m.opt.timestep))


# ---------------------------------------------------------------------------
# Small pieces a user would write once and reuse.


def _strike(scene: Scene, body: str, horizon: int, duration: float):
    """Controls of an idealised strike: velocity v (n, k) -> force m v / τ for τ seconds.

    For motors that push a free body's centre (gear along world axes): a
    constant force F for τ seconds gives it the impulse F τ = m v.
    """
    mass = float(scene.m.body_subtreemass[scene.body(body)])
    steps = max(1, _steps(scene, duration))
    pulse = np.zeros((1, horizon, 1))
    pulse[:, :steps] = 1.0
    scale = mass / (steps * scene.m.opt.timestep)

    def controls(v):
        return v[:, None, :] * (scale * pulse)

    return controls


def _torque_knots(name: str, motors: int, knots: int, horizon: int):
    """Controls of torque knots: θ (n, motors·knots) -> ctrl (n, T, motors).

    Each motor's control is the piecewise-linear interpolation of its `knots`
    values, spread evenly from the first step to the last. Plain array
    operations, so the same function serves JAX (planning) and numpy (replay).
    """
    t = np.linspace(0.0, 1.0, horizon)
    at = np.linspace(0.0, 1.0, knots)
    weights = np.stack([np.interp(t, at, row) for row in np.eye(knots)])  # (knots, T)

    def controls(params):
        x = params[name]
        return (x.reshape(x.shape[0], motors, knots) @ weights).swapaxes(1, 2)

    return controls


def _via_points(name: str, start, times, horizon: int):
    """Servo references through via points: θ (n, 2K) -> ctrl (n, T, 2).

    The reference leaves `start` (the pusher's rest position, world x and y)
    at t = 0, passes the K via points of θ at the fractions `times` of the
    horizon, and holds the last one. Position servos take joint coordinates,
    so the reference is offset by `start`.
    """
    t = np.linspace(0.0, 1.0, horizon)
    at = np.concatenate([[0.0], times, [1.0]])
    k = len(times)
    rows = np.eye(k + 1)[:, 1:]  # knot values of each via point (start is 0)
    rows = np.concatenate([rows, rows[-1:]])  # hold the last via point
    weights = np.stack([np.interp(t, at, rows[:, j]) for j in range(k)])  # (K, T)
    start = np.asarray(start, float)

    def controls(params):
        x = params[name]
        via = x.reshape(x.shape[0], k, 2) - start  # (n, K, 2), joint coordinates
        return (via.swapaxes(1, 2) @ weights).swapaxes(1, 2)

    return controls


def _each_ends_in(bodies: dict[str, str], zones: dict[str, str]):
    """Success: some body's centre ends inside a box site; label = which ends where.

    The label joins `body_zone` for every body that ends in a zone, in the
    order of `bodies` (e.g. "a_north+b_south").
    """
    checks = {name: costs.ends_in_any(body, zones) for name, body in bodies.items()}

    def predicate(replay):
        parts = []
        for name, check in checks.items():
            ok, zone = check(replay)
            parts.append(np.where(ok, np.char.add(f"{name}_", zone.astype(str)), ""))
        label = np.array(["+".join(p for p in row if p) for row in zip(*parts, strict=True)],
                        dtype=object)
        return label != "", label

    return predicate


def _ends_in_box(body: str, sites: dict[str, str]):
    """Success: the body's centre ends inside one of several box sites (3-D); label = which."""

    def predicate(replay):
        x = replay.body_pos(body)[:, -1]
        ok = np.zeros(len(x), bool)
        label = np.full(len(x), "", dtype=object)
        for name, site in sites.items():
            s = replay.scene.site(site)
            c = replay.site_pos(site)[:, -1]
            inside = np.all(np.abs(x - c) <= replay.scene.m.site_size[s], axis=-1) & ~ok
            label[inside] = name
            ok |= inside
        return ok, label

    return predicate


def _rings(bells: dict[str, str], angle: float):
    """Success: a hinged bell swings more than `angle` rad; label = bells in ringing order."""

    def predicate(replay):
        n = replay.qpos.shape[0]
        first = {}
        for name, joint in bells.items():
            swung = np.abs(replay.qpos[:, :, replay.scene.qpos_adr(joint)]) > angle
            first[name] = np.where(swung.any(axis=1), swung.argmax(axis=1), -1)
        label = []
        for i in range(n):
            rung = sorted((t[i], name) for name, t in first.items() if t[i] >= 0)
            label.append("+".join(name for _, name in rung))
        label = np.array(label, dtype=object)
        return label != "", label

    return predicate


def _crosses(body: str, lines: dict[str, tuple[int, float]]):
    """Success: the body's centre crosses a line {label: (axis, value)} beyond a rail.

    The label is the first line crossed (axis 0: x > value, axis 1: y > value).
    """

    def predicate(replay):
        x = replay.body_pos(body)
        n, T = x.shape[:2]
        first = np.full((n, len(lines)), T)
        for k, (axis, value) in enumerate(lines.values()):
            beyond = x[:, :, axis] > value
            first[:, k] = np.where(beyond.any(axis=1), beyond.argmax(axis=1), T)
        ok = first.min(axis=1) < T
        label = np.where(ok, np.asarray(list(lines), dtype=object)[first.argmin(axis=1)], "")
        return ok, label

    return predicate


# ---------------------------------------------------------------------------
# Scenes.


def rolling_ball() -> Task:
    """3-D: strike a free-joint ball so that it comes to rest in a target zone.

    θ = strike velocity (vx, vy) in m/s, a 20 ms force from the two motors.
    Task plan = the posts and walls the ball touches, and the zone it stops in.
    """
    scene = _scene("rolling_ball")
    task = Task("rolling_ball", scene, horizon=_steps(scene, 2.5),
                description="roll the ball to rest in a zone; task plan = posts and walls touched")
    task.box("strike", low=[0.0, -3.0], high=[3.0, 3.0])
    strike = _strike(scene, "ball", task.horizon, 0.02)
    task.controls(lambda p: strike(p["strike"]))
    for geom in ("post_north", "post_south", "wall_north", "wall_south", "wall_east"):
        task.contact(geom, "ball", geom)
    zones = {"north": "zone_north", "south": "zone_south"}
    task.cost("zone", costs.reach("ball", list(zones.values()), when="final"))
    task.success(costs.ends_in_any("ball", zones))
    task.display(trace=["ball"])
    return task


def pachinko() -> Task:
    """Gravity on the dofs, cylinder pegs: drop a ball through pegs into a scoring bin.

    θ = the ball's launch point x₀ (m) and horizontal speed vₓ (m/s) at the top.
    Task plan = the pegs it touches and the bin it ends in (bins 2 and 3, the
    inner ones, score).
    """
    scene = _scene("pachinko")
    task = Task("pachinko", scene, horizon=_steps(scene, 1.2),
                description="drop the ball into an inner bin; task plan = pegs touched")
    task.box("drop_x", low=[-0.2], high=[0.2], initial_qpos=["x"])
    task.box("throw", low=[-1.0], high=[1.0], initial_qvel=["x"])
    for k in range(1, 7):
        task.contact(f"peg_{k}", "ball", f"peg_{k}")
    bins = {"bin2": "bin_2", "bin3": "bin_3"}
    task.cost("bin", costs.reach("ball", list(bins.values()), when="final"))
    task.success(_ends_in_box("ball", bins))
    task.display(trace=["ball"])
    return task


def arm_strike(knots: int = 3, radius: float = 0.08) -> Task:
    """Hinge motors: a two-link arm strikes a ball into one of three goals.

    θ = `knots` torque knots per motor (shoulder, then elbow; the suite's: 3),
    in N·m within the motors' range, interpolated over the horizon. Task plan =
    the rails the ball touches and the goal it reaches (east, north or west):
    the ball's centre comes within `radius` (m; the suite's: 0.08) of the
    goal's. `benchmarks/scaling.py`'s arm family turns `knots`, its
    arm_goal family `radius`.
    """
    scene = _scene("arm_strike")
    task = Task("arm_strike", scene, horizon=_steps(scene, 1.5),
                description="strike the ball into a goal; task plan = rails touched")
    task.box("torque", low=[-1.0] * (2 * knots), high=[1.0] * (2 * knots))
    task.controls(_torque_knots("torque", motors=2, knots=knots, horizon=task.horizon))
    for rail in ("rail_north", "rail_east", "rail_west", "rail_south"):
        task.contact(rail, "ball", rail)
    goals = {"east": "goal_east", "north": "goal_north", "west": "goal_west"}
    task.cost("aim", costs.aim("forearm", "ball"))
    task.cost("goal", costs.reach("ball", list(goals.values())))
    task.success(costs.reaches("ball", goals, radius=radius))
    task.display(trace=["ball"])
    return task


def pendulum_bells() -> Task:
    """Hinge motor against gravity: swing a pendulum up to ring a bell.

    θ = six torque knots of the pendulum's motor (N·m, within its range),
    interpolated over 2 s. Task plan = which of bob and rod touch which bell,
    and the bells that ring, in order.
    """
    scene = _scene("pendulum_bells")
    task = Task("pendulum_bells", scene, horizon=_steps(scene, 2.0),
                description="ring a bell; task plan = bells struck by bob and rod")
    task.box("torque", low=[-3.0] * 6, high=[3.0] * 6)
    task.controls(_torque_knots("torque", motors=1, knots=6, horizon=task.horizon))
    for part in ("bob", "rod"):
        for bell in ("bell_left", "bell_right"):
            task.contact(f"{part}_{bell.removeprefix('bell_')}", part, bell)
    aims = [costs.aim("bob", bell) for bell in ("bell_left", "bell_right")]
    task.cost("bell", lambda r: jnp.minimum(*(aim(r) for aim in aims)))  # either bell
    task.success(_rings({"left": "bell_left", "right": "bell_right"}, angle=0.1))
    task.display(trace=["pendulum"])
    return task


def pusher() -> Task:
    """An actuated pusher pushes a free crate round a pipe into a zone.

    θ = two via points (x, y in m) of the pusher's servo reference, reached at
    40% and 80% of the horizon. Task plan = whether the crate and the
    pusher touch the pipe, and the zone the crate ends in.
    """
    scene = _scene("pusher")
    task = Task("pusher", scene, horizon=_steps(scene, 2.0),
                description="push the crate into a zone; task plan = pipe touched")
    task.box("via", low=[-0.3, -0.45] * 2, high=[0.6, 0.45] * 2)
    start = scene.m.body_pos[scene.body("pusher")][:2]
    task.controls(_via_points("via", start, times=[0.4, 0.8], horizon=task.horizon))
    task.contact("crate_pipe", "crate", "pipe")
    task.contact("pusher_pipe", "pusher", "pipe")
    zones = {"north": "zone_north", "south": "zone_south"}
    task.cost("aim", costs.aim("pusher", "crate"))
    task.cost("zone", costs.reach("crate", list(zones.values()), when="final"))
    task.success(costs.ends_in_any("crate", zones))
    task.display(trace=["crate", "pusher"], force=[("pusher", "crate")])
    return task


def bank_shot() -> Task:
    """Two balls on a frictional table: knock the target ball out through a gap.

    θ = the cue ball's initial velocity (vx, vy) in m/s. Task plan = the rails
    and the block the cue ball touches before it first touches the target
    ball, and the gap the target ball leaves through (right or top).
    """
    scene = _scene("bank_shot")
    task = Task("bank_shot", scene, horizon=_steps(scene, 2.0),
                description="knock the target ball out through a gap; task plan = what the "
                "cue ball touches first")
    task.box("cue_velocity", low=[-4.0, -4.0], high=[4.0, 4.0], initial_qvel=["cue_x", "cue_y"])
    for geom in ("rail_top", "rail_bottom", "rail_left", "block"):
        task.contact(geom, "cue", geom, before=("cue", "target"))
    task.cost("aim", costs.aim("cue", "target"))
    task.cost("gap", costs.reach("target", ["gap_right", "gap_top"]))
    task.success(_crosses("target", {"right": (0, 1.05), "top": (1, 0.55)}))
    task.display(trace=["cue", "target"])
    return task


def wedges() -> Task:
    """Mesh symbols: shoot a puck into a corner pocket, turned by wedge-shaped meshes.

    θ = the puck's initial velocity (vx, vy) in m/s. Task plan = the wedges
    and walls the puck touches before it reaches a pocket, and the pocket.
    """
    scene = _scene("wedges")
    task = Task("wedges", scene, horizon=_steps(scene, 2.0),
                description="pocket the puck; task plan = wedges and walls touched")
    task.box("puck_velocity", low=[-3.0, -3.0], high=[3.0, 3.0],
             initial_qvel=["puck_x", "puck_y"])
    for geom in ("wedge_north", "wedge_south", "wall_north", "wall_south", "wall_east"):
        task.contact(geom, "puck", geom)
    pockets = {"north": "pocket_north", "south": "pocket_south"}
    task.cost("pocket", costs.reach("puck", list(pockets.values())))
    task.success(costs.reaches("puck", pockets, radius=0.1))
    task.display(trace=["puck"])
    return task


def crate_ledge() -> Task:
    """Box-box contacts: a pusher pushes a crate off a raised ledge into a landing zone.

    θ = two via points (x, y in m) of the pusher's servo reference, reached at
    40% and 80% of the horizon. Task plan = whether the crate touches the
    block and the fence (box-box), whether the pusher touches the block, and
    the zone the crate lands in (the edge it goes over: north, east or south).
    """
    scene = _scene("crate_ledge")
    task = Task("crate_ledge", scene, horizon=_steps(scene, 2.0),
                description="push the crate off the ledge into a zone; task plan = block "
                "and fence touched, edge")
    task.box("via", low=[-0.2, -0.35] * 2, high=[0.5, 0.35] * 2)
    start = scene.m.body_pos[scene.body("pusher")][:2]
    task.controls(_via_points("via", start, times=[0.4, 0.8], horizon=task.horizon))
    task.contact("crate_block", "crate", "block")
    task.contact("crate_fence", "crate", "fence")
    task.contact("pusher_block", "pusher", "block")
    zones = {"north": "zone_north", "east": "zone_east", "south": "zone_south"}
    task.cost("aim", costs.aim("pusher", "crate"))
    task.cost("zone", costs.reach("crate", list(zones.values()), when="final"))
    task.success(costs.ends_in_any("crate", zones))
    task.display(trace=["crate", "pusher"], force=[("pusher", "crate")])
    return task


def cans() -> Task:
    """Cylinder contacts: two cans roll down a ramp, between blocks, to rest in zones.

    θ = where each can is let go across the ramp (y of can a, then can b, in
    m; both start at rest). Task plan = whether the cans touch each other,
    and which can ends in which zone. N.B. the blocks cannot be symbols:
    mjstamp.distance has no cylinder-box signed distance.
    """
    scene = _scene("cans")
    task = Task("cans", scene, horizon=_steps(scene, 2.5),
                description="roll the cans to rest in the zones; task plan = cans touch, "
                "which can ends where")
    task.box("release", low=[-0.24, -0.24], high=[0.24, 0.24],
             initial_qpos=[("can_a", 1), ("can_b", 1)])
    task.contact("a_b", "can_a", "can_b")
    zones = {"north": "zone_north", "south": "zone_south"}
    reach = [costs.reach(can, list(zones.values()), when="final") for can in ("can_a", "can_b")]
    task.cost("zone", lambda r: jnp.minimum(*(f(r) for f in reach)))  # either can
    task.success(_each_ends_in({"a": "can_a", "b": "can_b"}, zones))
    task.display(trace=["can_a", "can_b"])
    return task


SUITE: dict[str, Callable[[], Task]] = {
    "rolling_ball": rolling_ball,
    "pachinko": pachinko,
    "arm_strike": arm_strike,
    "pendulum_bells": pendulum_bells,
    "pusher": pusher,
    "bank_shot": bank_shot,
    "wedges": wedges,
    "crate_ledge": crate_ledge,
    "cans": cans,
}

def source_salt(name: str) -> str:
    """A hash of one scene's task code: the salt of its ground-truth cache key.

    The cache key already holds the task's declaration and compiled model; this
    adds what they cannot show: the code of the scene's `make` function and of
    the helpers of this file it calls (controls, success predicates), with
    docstrings left out, so that editing prose or another scene keeps the cache.
    """
    tree = ast.parse(Path(__file__).read_text())
    functions = {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}
    todo, seen = [SUITE[name].__name__], set()
    while todo:
        fn = todo.pop()
        if fn in seen:
            continue
        seen.add(fn)
        todo += [n.id for n in ast.walk(functions[fn])
                 if isinstance(n, ast.Name) and n.id in functions]
    h = hashlib.sha256()
    for fn in sorted(seen):
        node = functions[fn]
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            body = body[1:]  # the docstring
        h.update(ast.dump(ast.Module(body=body, type_ignores=[])).encode())
    return h.hexdigest()[:16]
