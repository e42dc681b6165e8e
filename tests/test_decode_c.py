"""Contact symbols read from MuJoCo C: the JAX decode's agreement, any pair C collides."""

import jax
import mujoco
import numpy as np
import pytest

from mjstamp import kinematics, solve, verify
from mjstamp.distance import make_distance_bound
from mjstamp.errors import MjstampError
from mjstamp.scenes import Scene
from mjstamp.tasks import Task, costs
from mjstamp.tasks.problem import Rollout

PUCKS = {
    "sphere": 'type="sphere" size="0.04"',
    "box": 'type="box" size="0.04 0.03 0.04"',
    "cylinder": 'type="cylinder" size="0.04 0.04"',
}


def _task(tiny_xml, puck: str, turn: float = 0.0, floor_z: float = -0.05) -> Task:
    """The tiny scene with its puck of another shape: θ its velocity, the wall a symbol."""
    xml = tiny_xml(turn=turn).replace('type="sphere" size="0.04"', PUCKS[puck])
    xml = xml.replace('pos="0 0 -0.05"', f'pos="0 0 {floor_z}"')
    task = Task("tiny", Scene(xml, name=f"tiny_{puck}_{floor_z}"), horizon=40)
    task.box("v", low=[-2, -2], high=[2, 2], initial_qvel=("px", "py"))
    task.contact("wall", "puck", "wall")
    task.cost("goal", costs.reach("puck", ["goal"]))
    return task


def _shots(n: int = 40) -> np.ndarray:
    """Straight at the wall, straight away from it, then n velocities at random (seed 0)."""
    rng = np.random.default_rng(0)
    return np.concatenate([[[2.0, 0.0], [-2.0, 0.0]], rng.uniform(-2, 2, size=(n, 2))])


@pytest.mark.parametrize(("puck", "turn"), [("sphere", 0.0), ("box", 0.4)])
def test_c_decode_agrees_with_the_jax_decode(tiny_xml, puck, turn):
    """Sphere-box and (turned) box-box: C's touch is the JAX sd < 0 at every state."""
    problem = _task(tiny_xml, puck, turn).build()
    theta = _shots()
    replay = verify.simulate_c(problem, theta)
    (pair,) = problem.contact_pairs()
    touch = replay.contact("puck", "wall")
    assert touch[0].any() and not touch[1].any()  # N.B. both answers occur: not vacuous
    np.testing.assert_array_equal(touch, replay.signed_distance("puck", "wall") < 0)
    np.testing.assert_array_equal(  # N.B. C asked at every state: the bound pruned nothing
        kinematics.touching(problem.scene.m, replay.qpos, [pair])[..., 0], touch)
    assert not replay.symbol_disagreements().any()
    decoded = verify.decode(problem, replay, theta)
    np.testing.assert_array_equal(decoded.bits[:, 0], touch.any(axis=1))


def test_disagreements_are_counted_per_plan(tiny_xml):
    """A C contact the JAX distances do not see makes its plan (and only it) disagree."""
    replay = verify.simulate_c(_task(tiny_xml, "sphere").build(), _shots(6))
    (pair,) = replay.touch
    quiet = np.flatnonzero(~replay.touch[pair].any(axis=1))[0]
    replay.touch = {pair: replay.touch[pair].copy()}
    replay.touch[pair][quiet, 5] = True
    assert np.flatnonzero(replay.symbol_disagreements()).tolist() == [quiet]


def test_cylinder_box_symbol_decodes_from_c(tiny_xml):
    """A pair without a JAX distance is a symbol: C's contact list, step by step."""
    # plane-cylinder: a JAX distance, compared below; the floor 1 mm into the puck
    # (half-height 0.04), so that it touches at every state.
    task = _task(tiny_xml, "cylinder", floor_z=-0.039)
    task.contact("floor", "puck", "floor")
    problem = task.build()
    assert [problem.relaxes(c) for c in problem.contacts] == [False, True]
    theta = _shots(6)
    replay = verify.simulate_c(problem, theta)
    assert replay.contact("puck", "floor").all()
    np.testing.assert_array_equal(replay.signed_distance("puck", "floor") < 0, True)
    assert list(verify.decode(problem, replay, theta).code[:2]) == ["11", "01"]
    m = problem.scene.m
    d = mujoco.MjData(m)
    d.qvel[:2] = theta[0]
    puck, wall = problem.scene.geom("puck"), problem.scene.geom("wall")
    listed = []
    for _ in range(problem.horizon):
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)  # contacts of the state after the step
        listed.append(any({c.geom1, c.geom2} == {puck, wall} for c in d.contact[: d.ncon]))
    assert any(listed)
    np.testing.assert_array_equal(replay.contact("puck", "wall")[0], listed)
    # The screen and samplers cost it in C; STAMP, which relaxes symbols, says why not.
    assert np.isfinite(verify.cost_c(problem, replay, theta)).all()
    why = (r"task 'tiny': symbol 'wall' has no soft indicator.*'cylinder' geom 'puck' and "
           r"'box' geom 'wall' is not supported; supported pairs: plane-sphere.*STAMP")
    with pytest.raises(MjstampError, match=why):
        problem.check_relaxed()
    with pytest.raises(MjstampError, match=why):
        Rollout(problem, {}, {}).symbols["wall"]
    with pytest.raises(KeyError):  # relaxed, just not computed on this bare rollout
        Rollout(problem, {}, {}).symbols["floor"]
    with pytest.raises(MjstampError, match=why):
        solve(task, {"particles": 2}, progress=False)
    assert verify.simulate_c(problem, theta).symbol_disagreements().tolist() == [False] * 8


def test_bad_pairs_are_one_line(tiny_xml):
    xml = tiny_xml()
    plane_wall = Scene(xml.replace('type="box"', 'type="plane"'), name="planes")
    with pytest.raises(MjstampError, match="symbol 'c'.*'floor' \\(plane\\) and geom 'wall' "
                                           "\\(plane\\): MuJoCo C has no collider.*valid: "):
        Task("t", plane_wall, horizon=5).contact("c", "floor", "wall")
    with pytest.raises(MjstampError, match="geom 'puck' \\(sphere\\) cannot touch itself"):
        Task("t", Scene(xml, name="tiny"), horizon=5).contact("c", "puck", "puck")
    problem = _task(tiny_xml, "sphere").build()
    replay = verify.simulate_c(problem, _shots(1))
    with pytest.raises(MjstampError, match="'floor'-'puck' is not one; valid: 'wall'-'puck'$"):
        replay.contact("puck", "floor")


def test_touching_refuses_ids_and_widths_outside_the_model(tiny_xml):
    """mj_geomDistance does not check its ids: `touching` does, one line each."""
    m = Scene(tiny_xml(), name="tiny").m
    qpos = np.zeros((2, m.nq))
    with pytest.raises(MjstampError, match=f"geom id 5 is not in the model; valid: two "
                                           f"different geoms, ids 0 to {m.ngeom - 1}"):
        kinematics.touching(m, qpos, [(1, 5)])
    with pytest.raises(MjstampError, match="geom id 1000000 is not in the model"):
        kinematics.touching(m, qpos, [(1000000, 1)])
    with pytest.raises(MjstampError, match="cannot touch itself; valid: two different geoms"):
        kinematics.touching(m, qpos, [(1, 1)])
    with pytest.raises(MjstampError, match=f"qpos of shape \\(2, 3\\).*valid: \\(..., {m.nq}\\)"):
        kinematics.touching(m, np.zeros((2, 3)), [(1, 2)])


def test_rows_slice_the_replay(tiny_xml):
    """`Replay.rows` is the replay of those plans alone, as a fresh replay computes it."""
    problem = _task(tiny_xml, "sphere").build()
    theta = _shots(6)
    replay = verify.simulate_c(problem, theta)
    idx = [3, 0]
    part, fresh = replay.rows(idx), verify.simulate_c(problem, theta[idx])
    for field in fresh.traj:
        np.testing.assert_allclose(part.traj[field], fresh.traj[field], rtol=0, atol=1e-12)
    for pair in fresh.touch:
        np.testing.assert_array_equal(part.touch[pair], fresh.touch[pair])
    np.testing.assert_array_equal(part._near, fresh._near)
    assert part.symbol_disagreements().tolist() == [False, False]


# Every geom type MuJoCo C collides, each on its own free body, over a plane and a
# height field: random poses in a small cube, so that about half the pairs touch.
MENAGERIE = """
<mujoco>
  <option gravity="0 0 0"/>
  <asset>
    <hfield name="bumps" nrow="3" ncol="3" size="0.3 0.3 0.05 0.05"
            elevation="0 1 0 1 0 1 0 1 0"/>
    <mesh name="wedge" vertex="-.06 -.04 -.03  .06 -.04 -.03  -.06 .04 -.03  .06 .04 -.03
                               -.06 -.01 .03  .06 -.01 .03  -.06 .01 .03  .06 .01 .03"/>
  </asset>
  <worldbody>
    <geom name="plane" type="plane" size="1 1 0.1" pos="0 0 -0.12" euler="0.2 0 0"/>
    <geom name="field" type="hfield" hfield="bumps" pos="0 0 -0.2"/>
    <body><freejoint/><geom name="sphere" type="sphere" size="0.05"/></body>
    <body><freejoint/><geom name="capsule" type="capsule" size="0.03 0.06"/></body>
    <body><freejoint/><geom name="ellipsoid" type="ellipsoid" size="0.06 0.04 0.03"/></body>
    <body><freejoint/><geom name="cylinder" type="cylinder" size="0.04 0.06"/></body>
    <body><freejoint/><geom name="box" type="box" size="0.07 0.04 0.03" pos="0.02 0 0"/></body>
    <body><freejoint/><geom name="mesh" type="mesh" mesh="wedge"/></body>
  </worldbody>
</mujoco>
"""


def test_the_bound_never_hides_a_contact_c_sees():
    """Wherever C says a pair touches, its distance bound is <= 0; elsewhere it prunes."""
    m = mujoco.MjModel.from_xml_string(MENAGERIE)
    rng = np.random.default_rng(0)
    n = 3000
    qpos = np.tile(m.qpos0, (n, 1))
    for b in range(6):
        quat = rng.normal(size=(n, 4))
        qpos[:, 7 * b : 7 * b + 3] = rng.uniform(-0.15, 0.15, size=(n, 3))
        qpos[:, 7 * b + 3 : 7 * b + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    pairs = [(a, b) for a in range(m.ngeom) for b in range(a + 1, m.ngeom) if b >= 2]
    touch = kinematics.touching(m, qpos, pairs)
    poses = kinematics.poses(m, qpos, ("geom_xpos", "geom_xmat"))
    fns = [make_distance_bound(m, *p) for p in pairs]
    bounds = np.asarray(jax.jit(jax.vmap(lambda x, r: jax.numpy.stack([f(x, r) for f in fns])))(
        poses["geom_xpos"], poses["geom_xmat"]))
    assert 0.1 < touch.mean() < 0.9
    assert (bounds[touch] <= 1e-12).all()
    assert (bounds > 0).mean() > 0.2  # it prunes: C is not asked there
    np.testing.assert_array_equal(kinematics.touching(m, qpos, pairs, bounds <= 0), touch)


def test_a_state_that_blew_up_touches_nothing():
    m = mujoco.MjModel.from_xml_string(MENAGERIE)
    qpos = np.tile(m.qpos0, (2, 1))  # every body at the origin: all touch
    qpos[1, 0] = np.nan
    touch = kinematics.touching(m, qpos, [(2, 3), (5, 6)])
    assert touch[0].all() and not touch[1].any()
