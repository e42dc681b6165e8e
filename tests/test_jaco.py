"""The Jaco task: dm_control's Kinova arm composed offline, and plans found while authoring."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from mjstamp.registry import load
from mjstamp.tasks import jaco

#: θ (velocity knots, rad/s: joint 1 ×3, joint 2 ×3, joint 3 ×3) found by uniform
#: shots replayed in MuJoCo C (seed 0), one per task plan they reached.
KNOWN = {
    "10-near": [0.1721, -0.2893, -0.5768, -0.1934, 0.1253, 0.1651, 0.0427, 0.0918, 0.0174],
    "10-post": [-0.2059, -0.4395, -0.0624, 0.1185, -0.1077, -0.1792, -0.0382, -0.1206, -0.1637],
    "11-post": [-0.4486, -0.6111, -0.0831, 0.1049, 0.0457, -0.0703, 0.0869, -0.0062, 0.1998],
}


@pytest.fixture(scope="module")
def task():
    return load("jaco")[0]


def test_scene_composes_offline_from_dm_control():
    root = jaco.compose()
    assets = root.get_assets()
    assert any(name.endswith(".stl") for name in assets)  # the meshes ship with dm_control
    scene = jaco.scene()
    m = scene.m
    # Arm 6 + fingers 3 hinges, the brick's free joint; one velocity servo per hinge.
    assert (m.nq, m.nv, m.nu, m.nmesh) == (16, 15, 9, 9)
    assert np.all(m.actuator_biastype == mujoco.mjtBias.mjBIAS_AFFINE)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)  # qpos0 is the home pose
    pinch = d.site_xpos[scene.site("jaco_arm/jaco_hand/pinchsite")]
    np.testing.assert_allclose(pinch, [0.5, -0.1, 0.022], atol=2e-3)
    arm = [g for g in range(m.ngeom) if scene.m.geom(g).name.startswith("jaco_arm/link")]
    assert arm and not np.any(m.geom_contype[arm] | m.geom_conaffinity[arm])


def test_home_pose_is_the_same_arm():
    """Turning each body by its home angle and setting ref to it changes no kinematics."""
    root = jaco.compose()
    m0 = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    m1 = jaco.scene().m
    q = m1.qpos0.copy()
    q[:6] += [0.3, -0.2, 0.4, 0.1, -0.5, 0.2]
    d0, d1 = mujoco.MjData(m0), mujoco.MjData(m1)
    d0.qpos[:], d1.qpos[:] = q, q
    mujoco.mj_kinematics(m0, d0)
    mujoco.mj_kinematics(m1, d1)
    np.testing.assert_allclose(d1.geom_xpos, d0.geom_xpos, atol=1e-9)
    np.testing.assert_allclose(m1.jnt_range, m0.jnt_range)


def _c_replay_ends(task, theta):
    """The brick's final centre after a plain MuJoCo C replay of θ (n, d)."""
    problem = task.build()
    m = problem.scene.m
    qpos0, qvel0, ctrl = problem.inputs(np.asarray(theta, float), xp=np)
    adr = problem.scene.qpos_adr("brick/")
    ends = []
    for i in range(len(theta)):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = qpos0[i], qvel0[i]
        for t in range(ctrl.shape[1]):
            d.ctrl[:] = ctrl[i, t]
            mujoco.mj_step(m, d)
        ends.append(d.qpos[adr : adr + 3].copy())
    return np.array(ends)


def test_known_plans_reach_their_goals_in_c(task):
    ends = _c_replay_ends(task, np.array(list(KNOWN.values())))
    m = task.scene.m
    for (plan, _), end in zip(KNOWN.items(), ends, strict=True):
        site = task.scene.site(jaco.GOALS[plan.split("-")[1]])
        assert np.all(np.abs(end[:2] - m.site_pos[site, :2]) <= m.site_size[site, :2]), plan


@pytest.mark.slow
def test_known_plans_decode_and_verify(task):
    from mjstamp.verify import decode, simulate_c

    theta = np.array(list(KNOWN.values()))
    decoded = decode(task, simulate_c(task, theta), theta)
    assert decoded.ok.all()
    assert list(decoded.plan) == list(KNOWN)


def test_start_at_refuses_what_it_cannot_turn_in_one_line():
    from mjstamp.errors import MjstampError
    from mjstamp.scenes.compose import start_at

    root = jaco.compose()
    with pytest.raises(MjstampError, match=r"'jaco_arm/joint_9' is no joint of the scene; "
                                           r"valid: .*jaco_arm/joint_1") as e:
        start_at(root, {"jaco_arm/joint_9": 0.1})
    assert "\n" not in str(e.value)
    from dm_control import mjcf

    slider = mjcf.from_xml_string('<mujoco><worldbody><body><joint name="s" type="slide"/>'
                                  '<geom size="0.1"/></body></worldbody></mujoco>')
    with pytest.raises(MjstampError, match="'s' is a slide joint; only hinges"):
        start_at(slider, {"s": 0.1})
