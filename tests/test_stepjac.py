"""C values with MJX step Jacobians (`benchmarks/perf/stepjac.py`) against C's differences.

The scene: a ball on a free joint (quaternion in qpos: nq = 7, nv = 6) resting on
a frictional floor, pushed by two motors; its initial velocity (linear and
angular) and two control segments per motor are θ. It rolls, so the objective
reads quaternions that change along the trajectory.
"""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp.errors import MjstampError
from mjstamp.scenes import Scene
from mjstamp.scenes.check import finite_differences, relative_errors

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks.perf import stepjac  # noqa: E402 - measured, not chosen: it lives with its benchmark

BALL = """
<mujoco model="ball">
  <option timestep="0.01"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="ball" pos="0 0 0.05">
      <freejoint name="ball"/>
      <geom name="ball" type="sphere" size="0.05" mass="0.2"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="fx" joint="ball" gear="1 0 0 0 0 0" ctrlrange="-2 2"/>
    <motor name="fy" joint="ball" gear="0 1 0 0 0 0" ctrlrange="-2 2"/>
  </actuator>
</mujoco>
"""
T = 30
N = 6
SEGMENTS = 2


@pytest.fixture(scope="module")
def case():
    # The implicit solver gradient, as calibration picks on frictional contact.
    scene = Scene(BALL).with_grad_options(gradient="implicit", iterations=100)
    m = scene.m

    def to_inputs(theta, xp):
        n = theta.shape[0]
        qpos = xp.broadcast_to(xp.asarray(m.qpos0), (n, m.nq))
        ctrl = xp.repeat(theta[:, 6:].reshape(n, SEGMENTS, m.nu), T // SEGMENTS, axis=1)
        return qpos, theta[:, :6], ctrl

    rng = np.random.default_rng(0)
    theta = np.concatenate([rng.uniform(-0.5, 0.5, (N, 6)),
                            rng.uniform(-1.0, 1.0, (N, SEGMENTS * m.nu))], axis=1)
    c1, c2 = rng.normal(size=(2, m.nq))
    traj = stepjac.c_trajectory(scene, *to_inputs(theta, np))
    objective = stepjac.check_objective(c1, c2)
    grads = {}
    for chaining, solution in [*((c, "mjx") for c in stepjac.CHAININGS), ("sweep", "c")]:
        gq, gv, gu, value = stepjac.input_gradients(scene, traj, objective, chaining=chaining,
                                                    solution=solution)
        grads[chaining if solution == "mjx" else f"{chaining}[c]"] = np.asarray(
            stepjac.pullback(lambda th: to_inputs(th, jnp), theta, gq, gv, gu))
    return {"scene": scene, "to_inputs": to_inputs, "theta": theta, "c1": c1, "c2": c2,
            "traj": traj, "objective": objective, "grads": grads, "value": np.asarray(value)}


def test_gradient_matches_central_differences_of_c(case):
    scene, theta = case["scene"], case["theta"]
    fd = finite_differences(scene, case["to_inputs"], theta, case["c1"], case["c2"], 1e-6,
                             "scene")
    for key in ("sweep", "sweep[c]"):  # MJX's solution at C's states, and C's own
        rel = relative_errors(case["grads"][key], fd, np.ones(N, bool))
        # Measured 6e-10 median, 1e-9 max: the differences' own floor at eps 1e-6
        # (float64). The bound leaves three orders for other CPUs' rounding.
        assert np.median(rel) < 1e-6 and rel.max() < 1e-5, key
    # The ball rolled: the quaternion moved, so the tangent-space handling counted.
    assert np.abs(case["traj"].qpos[:, -1, 3:] - case["traj"].qpos[:, 0, 3:]).max() > 0.1


def test_value_is_cs_own(case):
    traj = case["traj"]
    qpos = traj.qpos[:, 1:]
    want = qpos[:, -1] @ case["c1"] + qpos.mean(axis=1) @ case["c2"]
    # C's trajectory itself; only the summation order (XLA's against numpy's) differs.
    np.testing.assert_allclose(case["value"], want, rtol=1e-14, atol=1e-14)


def test_chainings_agree(case):
    g = case["grads"]
    scale = np.abs(g["sweep"]).max()
    assert scale > 0
    for other in ("scan", "vjp"):
        assert np.abs(g[other] - g["sweep"]).max() <= 1e-10 * scale


def test_mjx_steps_as_c_does_at_cs_states(case):
    scene, traj = case["scene"], case["traj"]
    for solution in stepjac.SOLUTIONS:
        jac = stepjac._builders(scene, solution, 64)[0](traj)  # the fixture's, compiled
        assert jac.A.shape == (N, T, 12, 12) and jac.B.shape == (N, T, 12, 2)
        # Sphere-plane is collided as C does, and the constraint solution is
        # the converged one (MJX's own, or C's): one step from C's state lands
        # on C's next state to rounding.
        assert stepjac.one_step_defect(scene, traj, jac).max() < 1e-10, solution


def test_jacobians_at_other_states_are_caught(case):
    # The check must be able to fail: Jacobians read one step late (states
    # 1..T, not 0..T-1) give a gradient far from the differences of C.
    scene, traj = case["scene"], case["traj"]
    late = stepjac.Trajectory(np.concatenate([traj.qpos[:, 1:], traj.qpos[:, -1:]], axis=1),
                              np.concatenate([traj.qvel[:, 1:], traj.qvel[:, -1:]], axis=1),
                              traj.ctrl)
    gq, gv, gu, _ = stepjac.input_gradients(scene, late, case["objective"])
    g = np.asarray(stepjac.pullback(lambda th: case["to_inputs"](th, jnp), case["theta"],
                                    gq, gv, gu))
    rel = relative_errors(g, case["grads"]["sweep"], np.ones(N, bool))
    assert np.median(rel) > 1e-3


def test_tangent_maps_are_inverse_to_first_order():
    # mj_integratePos's convention: a quaternion turns in its local frame.
    m = Scene(BALL).m
    layout = stepjac._layout(m)
    rng = np.random.default_rng(1)
    q = rng.normal(size=4)
    qpos = jnp.asarray(np.concatenate([[0.1, -0.2, 0.3], q / np.linalg.norm(q)]))
    J = jax.jacfwd(lambda dq: stepjac.local(layout, qpos, stepjac.retract(layout, qpos, dq),
                                            m.nv))(jnp.zeros(m.nv))
    np.testing.assert_allclose(J, np.eye(m.nv), atol=1e-14)
    # Against MuJoCo C's own mj_integratePos and mj_differentiatePos.
    import mujoco

    dq = 1e-7 * rng.normal(size=m.nv)
    moved = np.asarray(qpos).copy()
    mujoco.mj_integratePos(m, moved, dq, 1.0)
    np.testing.assert_allclose(stepjac.retract(layout, qpos, jnp.asarray(dq)), moved, atol=1e-13)
    back = np.zeros(m.nv)
    mujoco.mj_differentiatePos(m, back, 1.0, np.asarray(qpos), moved)
    np.testing.assert_allclose(stepjac.local(layout, qpos, jnp.asarray(moved), m.nv), back,
                               atol=1e-13)


def test_bad_arguments_are_refused_in_one_line(case):
    scene, traj = case["scene"], case["traj"]
    with pytest.raises(MjstampError, match="chaining='forward' is not valid; valid: "):
        stepjac.input_gradients(scene, traj, case["objective"], chaining="forward")
    with pytest.raises(MjstampError, match="solution='own' is not valid; valid: "):
        stepjac.input_gradients(scene, traj, case["objective"], solution="own")
    with pytest.raises(MjstampError, match="solution='c' needs the Newton solver"):
        stepjac.build_step_jacobians(
            scene.with_grad_options(solver="cg", gradient="unrolled"), solution="c")
    short = stepjac.Trajectory(traj.qpos, traj.qvel, traj.ctrl[:, 1:])
    with pytest.raises(MjstampError, match="trajectory ctrl has shape"):
        stepjac.build_step_jacobians(scene)(short)
