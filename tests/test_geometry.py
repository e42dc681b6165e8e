"""mjstamp.geometry: one set of poses, colours and contact forces for figures and playback.

A pusher (a box turned 8° about z, driven by a motor on a ramped control) pushes
a block whose margin and gap make MuJoCo list *excluded* contacts (outside the
constraint problem, efc_address < 0) next to active ones. Beside them: a geom
coloured by its rgba although it has a material, one coloured by its material,
and a translucent site. The same replay is drawn by `mjstamp.figures` and played
by `mjstamp.viz`; both must show the same colours, poses and forces.
"""

import mujoco
import numpy as np
import pytest
from matplotlib import colors as mcolors
from matplotlib.quiver import Quiver
from meshcat.commands import SetAnimation, SetObject

from mjstamp import figures, geometry, results, viz
from mjstamp.viz.playback import ARROW_CAP, ARROW_FRACTION

XML = """
<mujoco model="pushbox">
  <option timestep="0.01" gravity="0 0 0"/>
  <asset>
    <material name="steel" rgba="0.55 0.6 0.7 1"/>
    <material name="brass" rgba="0.8 0.6 0.2 1"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.01" pos="0 0 -0.06" rgba="0.1 0.6 0.2 1"
          contype="0" conaffinity="0"/>
    <geom name="wall" type="box" size="0.05 0.3 0.05" pos="0.7 0 0" material="steel"
          rgba="0.9 0.1 0.1 1" contype="0" conaffinity="0"/>
    <geom name="post" type="cylinder" size="0.03 0.05" pos="-0.4 0.3 0" material="brass"
          contype="0" conaffinity="0"/>
    <site name="goal" type="box" pos="0.45 -0.3 -0.05" size="0.08 0.08 0.005"
          rgba="0.1 0.8 0.1 0.8"/>
    <body name="block" pos="0.2 0 0">
      <joint name="block_x" type="slide" axis="1 0 0" damping="5"/>
      <geom name="block" type="box" size="0.05 0.05 0.05" mass="0.5" margin="0.01" gap="0.01"
            rgba="0.8 0.1 0.1 1"/>
    </body>
    <body name="pusher" pos="0 0 0" euler="0 0 8">
      <joint name="pusher_x" type="slide" axis="1 0 0"/>
      <geom name="pusher" type="box" size="0.03 0.05 0.05" mass="0.5" rgba="0.2 0.2 0.9 1"/>
    </body>
  </worldbody>
  <actuator><motor name="push" joint="pusher_x"/></actuator>
</mujoco>
"""
T = 80


@pytest.fixture(scope="module")
def replay():
    """The C replay as verify.Replay holds one, and the force each step applied.

    Returns:
      (m, qpos0, qvel0, qpos (T, nq), qvel (T, nv), ctrl (T, nu), stepped (T, 3)):
      stepped[t] is the force of the pusher on the block in the step from
      state t (read right after mj_step, whose contacts and constraint forces
      are those of state t).
    """
    m = mujoco.MjModel.from_xml_string(XML)
    d = mujoco.MjData(m)
    qpos0, qvel0 = d.qpos.copy(), d.qvel.copy()
    pair = (m.geom("pusher").id, m.geom("block").id)
    out = {k: [] for k in ("qpos", "qvel", "ctrl")}
    stepped = []
    for t in range(T):
        d.ctrl[:] = 1.0 + 0.05 * t  # ramped: the force depends on which step's control
        mujoco.mj_step(m, d)
        stepped.append(geometry.contact_force(m, d, *pair)[0])
        for k in out:
            out[k].append(np.array(getattr(d, k)))
    return (m, qpos0, qvel0, *(np.array(out[k]) for k in ("qpos", "qvel", "ctrl")),
            np.array(stepped))


@pytest.fixture(scope="module")
def frames(replay):
    m, qpos0, qvel0, qpos, qvel, ctrl, _ = replay
    pair = (m.geom("pusher").id, m.geom("block").id)
    return geometry.replay_frames(m, qpos0, qpos, qvel0=qvel0, qvel=qvel, ctrl=ctrl,
                                  pairs=[pair])


def test_forces_are_those_each_step_applied_and_skip_excluded_contacts(replay, frames):
    m, qpos0, qvel0, qpos, qvel, ctrl, stepped = replay
    assert frames.force.shape == (T + 1, 1, 3) and list(frames.states) == list(range(T + 1))
    # The force at state t is the one the step from t applied (its control is ctrl[t]).
    np.testing.assert_allclose(frames.force[:T, 0], stepped, atol=1e-9 * np.abs(stepped).max())
    assert np.abs(stepped).max() > 1.0
    # The scene lists excluded contacts beside active ones: they carry no force and
    # do not move the point where the force acts.
    d = mujoco.MjData(m)
    a, b = frames.pairs[0]
    states_qpos, states_qvel = np.vstack([qpos0, qpos]), np.vstack([qvel0, qvel])
    mixed = 0
    for t in np.flatnonzero(np.isfinite(frames.point[:, 0, 0])):
        d.qpos[:], d.qvel[:] = states_qpos[t], states_qvel[t]
        d.ctrl[:] = ctrl[min(t, T - 1)]
        mujoco.mj_forward(m, d)
        touch = [c for c in d.contact[: d.ncon] if {*c.geom} == {a, b}]
        active = [c for c in touch if c.efc_address >= 0]
        if len(active) < len(touch):
            mixed += 1
            every = np.mean([c.pos for c in touch], axis=0)
            assert np.abs(frames.point[t, 0] - every).max() > 1e-3  # excluded ones left out
            assert frames.point[t, 0, 1] < every[1]  # active corners lie on the near (-y) side
    assert mixed >= 5
    # Without velocities there is no force to read.
    still = geometry.replay_frames(m, qpos0, qpos, pairs=frames.pairs)
    assert not still.force.any() and np.isnan(still.point).all()
    np.testing.assert_array_equal(still.xpos, frames.xpos)


def test_colours_follow_mujoco(replay):
    m = replay[0]
    rgba = {name: geometry.mujoco_rgba(m, "geom", m.geom(name).id) for name in ("wall", "post")}
    np.testing.assert_allclose(rgba["wall"], [0.9, 0.1, 0.1, 1])  # its rgba beats its material
    np.testing.assert_allclose(rgba["post"], [0.8, 0.6, 0.2, 1])  # default rgba: the material's
    goal = geometry.drawn_rgba(m, "site", m.site("goal").id)
    np.testing.assert_allclose(goal, [0.1, 0.8, 0.1, 0.8 * geometry.SITE_OPACITY], rtol=1e-6)


TEXTURED_XML = """
<mujoco>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.2 0.3 0.4" rgb2="0.6 0.7 0.8"
             width="64" height="64"/>
    <material name="ground" texture="grid" rgba="1 1 1 1"/>
    <material name="tinted" texture="grid" rgba="0.5 1 1 0.7"/>
  </asset>
  <worldbody>
    <geom name="ground" type="plane" size="1 1 0.1" material="ground"/>
    <geom name="tinted" type="box" size="0.1 0.1 0.1" material="tinted"/>
    <geom name="own" type="box" size="0.1 0.1 0.1" material="ground" rgba="0 1 0 1"/>
  </worldbody>
</mujoco>
"""


def test_textured_materials_are_their_mean_texel_times_rgba():
    """A flat colour for MuJoCo's texel × rgba: the texture's mean times rgba.

    A checker's mean is the mean of its two colours; without it dm_control's textured white
    ground would be drawn white.
    """
    m = mujoco.MjModel.from_xml_string(TEXTURED_XML)
    mean = (np.array([0.2, 0.3, 0.4]) + [0.6, 0.7, 0.8]) / 2
    rgba = {n: geometry.mujoco_rgba(m, "geom", m.geom(n).id) for n in ("ground", "tinted", "own")}
    np.testing.assert_allclose(rgba["ground"], [*mean, 1], atol=3e-3)  # texels are bytes
    np.testing.assert_allclose(rgba["tinted"], [0.5 * mean[0], *mean[1:], 0.7], atol=3e-3)
    np.testing.assert_allclose(rgba["own"], [0, mean[1], 0, 1], atol=3e-3)


def _playback(replay, tmp_path):
    """A results directory holding the replay, opened and played at every saved state."""
    m, qpos0, qvel0, qpos, qvel, ctrl, _ = replay
    traj = {"particle": np.array([0]), "qpos0": qpos0[None], "qvel0": qvel0[None],
            "qpos": qpos[None], "qvel": qvel[None], "ctrl": ctrl[None],
            "timestep": np.array(m.opt.timestep)}
    entry = {"particle": 0, "task_plan": "push", "predicted_task_plan": "push",
             "verified": True, "cost": 1.0, "motion_plan": {}}
    summary = {"task": "pushbox", "task_plans": [], "plans": [entry], "config": {},
               "declaration": {"name": "pushbox", "display": {"trace": ["pusher"],
                                                              "force": [["pusher", "block"]]}}}
    results.save(tmp_path, summary, {"trajectories": traj, "particles": {}}, model=m)
    res = viz.load_results(tmp_path)
    return viz.build_playback(res, [entry], max_fps=1.0 / m.opt.timestep)  # stride 1


def _hex(rgba) -> int:
    r, g, b = (round(float(c) * 255) for c in rgba[:3])
    return (r << 16) | (g << 8) | b


def test_a_figure_and_the_playback_show_the_same_colours_poses_and_forces(
        replay, frames, tmp_path):
    m = replay[0]
    pusher = m.body("pusher").id
    drawing = figures.plan_drawing(m, frames, trace=[pusher])
    fig = figures.draw_topdown(m, [drawing], ["push"], title="pushbox")
    ax = fig.axes[0]
    patches = {p.get_gid(): p for p in ax.patches}
    pb = _playback(replay, tmp_path)
    objects = {c.path.lower(): c.object.lower()["materials"][0]
               for c in pb.commands if isinstance(c, SetObject)}

    # Colours: every non-plane geom and every site drawn in the PNG has the colour and
    # opacity of its meshcat object (the floor is paled on purpose in the PNG).
    checked = set()
    for gid, patch in patches.items():
        kind, name = gid.split("/")[-2:]
        if name == "floor":
            continue
        face = mcolors.to_rgba(patch.get_facecolor())
        if gid.startswith("start/"):  # the faint ghost of a moving geom at the start
            face = (*face[:3], face[3] / 0.25)
        [material] = [v for path, v in objects.items() if path.endswith(f"/{kind}s/{name}")]
        assert material["color"] == _hex(face), gid
        assert material.get("opacity", 1.0) == pytest.approx(face[3], rel=1e-6), gid
        checked.add(name)
    assert checked == {"wall", "post", "goal", "block", "pusher"}
    wall = objects["/meshcat/mjstamp/bodies/world/geoms/wall"]
    # Its rgba, not its material's (which the PNG used to draw).
    assert wall["color"] == _hex(np.float32([0.9, 0.1, 0.1])) != _hex(np.float32([0.55, 0.6, 0.7]))

    # Poses: the PNG's path of the pusher is the playback's keyframes of its body.
    [anim] = [c for c in pb.commands if isinstance(c, SetAnimation)]
    clips = {p.lower(): clip for p, clip in anim.animation.clips.items()}
    pos = np.array(clips["/meshcat/mjstamp/bodies/pusher"].tracks["position"].values)
    np.testing.assert_allclose(ax.get_lines()[0].get_xydata(), pos[: T + 1, :2])

    # Forces: each PNG arrow starts where the playback's arrow tip is at that state and
    # points along it, with its length in newtons.
    [quiver] = [c for c in ax.collections if isinstance(c, Quiver)]
    [arrows] = drawing.forces
    assert 3 <= len(arrows.states) <= figures.FORCE_FRAMES
    np.testing.assert_allclose(quiver.get_offsets(), arrows.point)
    tracks = clips["/meshcat/mjstamp/forces/pusher_on_block"].tracks
    _, radius = viz.scene.scene_bounds(m, frames.pose(0))
    longest = ARROW_CAP * ARROW_FRACTION * radius  # the playback caps its arrows there
    uncapped = 0
    for s, force, point in zip(arrows.states, arrows.force, arrows.point, strict=True):
        k = tracks["scale"].frames.index(s)
        length = tracks["scale"].values[k][0]
        x, y, z, w = tracks["quaternion"].values[k]
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, np.array([w, x, y, z]))
        direction = rot.reshape(3, 3) @ [0, 1, 0]
        tip = np.array(tracks["position"].values[k]) + length * direction
        np.testing.assert_allclose(tip[:2], point, atol=1e-9)
        assert abs(direction[2]) < 1e-9  # the forces lie in the plane of the push
        np.testing.assert_allclose(direction[:2], force / np.linalg.norm(force), atol=1e-9)
        if length < longest * (1 - 1e-9):
            newtons = length / pb.force_scale
            np.testing.assert_allclose(newtons, np.linalg.norm(force), rtol=1e-9)
            uncapped += 1
    assert uncapped >= 2
