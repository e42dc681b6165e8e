"""Playback: MJCF -> meshcat loader, contact-force arrows, plan timeline, HTML, live server, CLI.

Everything runs on a small scene and a results directory built here (no solve):
a sphere pushed by a motor into a sliding block, beside static geoms of every
MuJoCo type.
"""

import base64
import json
import math
import re
import shutil
import socket
import subprocess
import urllib.request
from pathlib import Path

import mujoco
import numpy as np
import pytest
import umsgpack
from meshcat.commands import SetAnimation, SetObject, SetProperty, SetTransform

from mjstamp import results, viz
from mjstamp.cli import main
from mjstamp.errors import MjstampError
from mjstamp.viz import scene as viz_scene
from mjstamp.viz.playback import ARROW_CAP, ARROW_FRACTION

TOY_XML = """
<mujoco model="toy">
  <option timestep="0.01" gravity="0 0 0"/>
  <asset>
    <mesh name="tet" vertex="0 0 0  0.1 0 0  0 0.1 0  0 0 0.1"/>
    <hfield name="bumps" nrow="3" ncol="4" size="0.2 0.1 0.05 0.01"
            elevation="0 1 0 1  1 0 1 0  0 0 1 1"/>
    <material name="steel" rgba="0.55 0.6 0.7 1"/>
  </asset>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="1 0.5 0.01" pos="0 0 -0.1" rgba="0.1 0.6 0.2 1"/>
    <geom name="wall" type="box" size="0.05 0.3 0.1" pos="0.7 0 0" rgba="0.9 0.1 0.1 1"/>
    <geom name="post" type="cylinder" size="0.03 0.08" pos="-0.6 0.3 0" euler="30 0 0"
          rgba="0.3 0.3 0.3 1"/>
    <geom name="pill" type="capsule" size="0.02 0.05" pos="-0.6 -0.3 0" euler="0 40 10"
          material="steel"/>
    <geom name="egg" type="ellipsoid" size="0.03 0.04 0.05" pos="-0.3 0.35 0" euler="0 0 45"
          rgba="0.9 0.9 0.9 1"/>
    <geom name="tet" type="mesh" mesh="tet" pos="-0.3 -0.35 0" rgba="0.5 0.2 0.6 1"/>
    <geom name="bumps" type="hfield" hfield="bumps" pos="0.3 0.35 -0.09" rgba="0.6 0.5 0.4 1"/>
    <geom name="collider" type="sphere" size="0.02" pos="0.3 -0.35 0" group="3"/>
    <site name="goal" type="box" pos="0.45 -0.3 -0.09" size="0.08 0.08 0.005"
          rgba="0.1 0.8 0.1 0.8"/>
    <body name="block" pos="0.2 0 0">
      <joint name="block_x" type="slide" axis="1 0 0" damping="5"/>
      <geom name="block" type="box" size="0.05 0.05 0.05" mass="0.5" rgba="0.8 0.1 0.1 1"
            contype="1" conaffinity="1"/>
    </body>
    <body name="pusher" pos="0 0 0">
      <joint name="pusher_x" type="slide" axis="1 0 0"/>
      <geom name="pusher" type="sphere" size="0.03" mass="0.5" rgba="0.2 0.2 0.9 1"
            contype="1" conaffinity="1"/>
      <geom name="handle" type="cylinder" size="0.005 0.04" pos="-0.02 0 0.05" euler="0 60 0"
            rgba="0.2 0.2 0.9 1"/>
    </body>
  </worldbody>
  <actuator><motor name="push" joint="pusher_x"/></actuator>
</mujoco>
"""
T = 60  # steps per plan: the pusher reaches the block after ~25 (0.12 m gap at 4 m/s^2)
# particle: (motor force N, verified task plan, verified, cost)
PLANS = {
    0: (2.0, "push-far", True, 1.0),
    3: (3.0, "push-near", True, 1.5),
    5: (1.0, "push-near", False, 0.5),
    7: (2.5, "push-far", True, 2.0),
}


@pytest.fixture(scope="module")
def toy_model():
    return mujoco.MjModel.from_xml_string(TOY_XML)


def _replay(m, u):
    d = mujoco.MjData(m)
    out = {k: [] for k in ("qpos", "qvel", "ctrl", "xpos")}
    qpos0, qvel0 = d.qpos.copy(), d.qvel.copy()
    for _ in range(T):
        d.ctrl[:] = u
        mujoco.mj_step(m, d)
        mujoco.mj_kinematics(m, d)  # mj_step leaves xpos at the state before the step
        for k in out:
            out[k].append(np.array(getattr(d, k)))
    return qpos0, qvel0, {k: np.array(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def toy_results(toy_model, tmp_path_factory):
    """A results directory as `mjstamp solve --out` writes it, for the toy scene."""
    out = tmp_path_factory.mktemp("toy_results")
    m = toy_model
    particles = sorted(PLANS)
    runs = [_replay(m, PLANS[p][0]) for p in particles]
    traj = {
        "particle": np.array(particles),
        "qpos0": np.array([r[0] for r in runs]),
        "qvel0": np.array([r[1] for r in runs]),
        **{k: np.array([r[2][k] for r in runs]) for k in ("qpos", "qvel", "ctrl", "xpos")},
        "timestep": np.array(m.opt.timestep),
    }
    entries = [
        {"particle": p, "task_plan": PLANS[p][1] if PLANS[p][2] else "push-far",
         "predicted_task_plan": PLANS[p][1], "verified": PLANS[p][2], "cost": PLANS[p][3],
         "motion_plan": {"force": [PLANS[p][0]]}}
        for p in particles
    ]
    rows = [
        {"task_plan": "push-far", "code": "", "plans": 2, "verified": 2, "verified_share": 1.0,
         "best_cost": 1.0},
        {"task_plan": "push-near", "code": "", "plans": 1, "verified": 1,
         "verified_share": 1.0, "best_cost": 1.5},
        {"task_plan": "push-near (failed)", "code": "", "plans": 1, "verified": 0,
         "verified_share": 0.0, "best_cost": None},
    ]
    summary = {
        "task": "toy", "task_plans": rows, "plans": entries, "config": {},
        "declaration": {"name": "toy", "display": {"trace": ["pusher"],
                                                   "force": [["pusher", "block"]]}},
    }
    n = max(particles) + 1
    particle_arrays = {"verified": np.zeros(n, bool), "returned": np.zeros(n, bool),
                       "task_plan": np.full(n, "", dtype="<U20")}
    results.save(out, summary, {"trajectories": traj, "particles": particle_arrays}, model=m)
    return out


def _by_path(cmds, kind):
    out = {}
    for c in cmds:
        if isinstance(c, kind):
            out.setdefault(c.path.lower(), []).append(c)
    return out


def _world(transforms, path: str) -> np.ndarray:
    """Pose of a meshcat path: the product of the transforms of its prefixes (root excluded)."""
    parts = path.strip("/").split("/")
    out = np.eye(4)
    for i in range(3, len(parts) + 1):  # skip /meshcat/mjstamp: it only recentres the view
        prefix = "/" + "/".join(parts[:i])
        if prefix in transforms:
            out = out @ transforms[prefix][-1].matrix
    return out


def _object_matrix(obj: dict) -> np.ndarray:
    return np.array(obj["object"]["matrix"], float).reshape(4, 4).T  # three.js: column-major


def _vertices(geometry: dict) -> np.ndarray:
    ext = geometry["data"]["attributes"]["position"]["array"]
    return np.frombuffer(ext.data, np.float32).reshape(-1, 3)


def _same_color(hex_color: int, rgba) -> bool:
    """Whether 0xRRGGBB is rgba (to the nearest 8-bit step: 0.9 * 255 rounds either way)."""
    channels = np.array([hex_color >> 16, (hex_color >> 8) & 255, hex_color & 255])
    return bool(np.abs(channels - np.asarray(rgba[:3], float) * 255).max() <= 1)


# ----------------------------------------------------------------------------
# Loader.


def test_every_geom_type_gets_its_shape_size_pose_and_color(toy_model):
    m = toy_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    cmds = viz_scene.scene_commands(m)
    objects = {p: c[-1].object.lower() for p, c in _by_path(cmds, SetObject).items()}
    transforms = _by_path(cmds, SetTransform)
    drawn = 0
    for g in range(m.ngeom):
        name = m.geom(g).name
        body = m.body(m.geom_bodyid[g]).name
        path = f"/meshcat/mjstamp/bodies/{body}/geoms/{name}"
        obj = objects[path]
        geometry, material = obj["geometries"][0], obj["materials"][0]
        # Pose: body in the world, geom in the body, shape in the geom frame.
        pose = _world(transforms, path)
        np.testing.assert_allclose(pose[:3, 3], d.geom_xpos[g], atol=1e-9, err_msg=name)
        np.testing.assert_allclose(pose[:3, :3], d.geom_xmat[g].reshape(3, 3), atol=1e-9,
                                   err_msg=name)
        full = pose @ _object_matrix(obj)
        expected_rgba = m.mat_rgba[m.geom_matid[g]] if name == "pill" else m.geom_rgba[g]
        assert _same_color(material["color"], expected_rgba), name
        size = m.geom_size[g]
        gtype = mujoco.mjtGeom(m.geom_type[g])
        if gtype == mujoco.mjtGeom.mjGEOM_PLANE:
            v = _vertices(geometry)
            np.testing.assert_allclose(v.min(0), [-size[0], -size[1], 0], atol=1e-6)
            np.testing.assert_allclose(v.max(0), [size[0], size[1], 0], atol=1e-6)
        elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
            assert geometry["type"] == "BoxGeometry"
            np.testing.assert_allclose(
                [geometry["width"], geometry["height"], geometry["depth"]], 2 * size)
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            assert geometry["type"] == "SphereGeometry" and geometry["radius"] == size[0]
        elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            assert geometry["type"] == "SphereGeometry" and geometry["radius"] == 1.0
            np.testing.assert_allclose(np.diag(_object_matrix(obj))[:3], size)
        elif gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
            assert geometry["type"] == "CylinderGeometry"
            assert geometry["radiusTop"] == geometry["radiusBottom"] == size[0]
            assert geometry["height"] == pytest.approx(2 * size[1])
            # three.js builds cylinders along y: the drawn axis must be MuJoCo's z.
            np.testing.assert_allclose(full[:3, 1], d.geom_xmat[g].reshape(3, 3)[:, 2],
                                       atol=1e-9, err_msg=name)
        elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            v = _vertices(geometry)
            assert v[:, 2].max() == pytest.approx(size[1] + size[0], rel=1e-5)
            assert v[:, 2].min() == pytest.approx(-size[1] - size[0], rel=1e-5)
            assert np.hypot(v[:, 0], v[:, 1]).max() == pytest.approx(size[0], rel=1e-5)
        elif gtype == mujoco.mjtGeom.mjGEOM_MESH:
            mesh = m.geom_dataid[g]
            v = _vertices(geometry)
            assert len(v) == m.mesh_vertnum[mesh]
            np.testing.assert_allclose(v, m.mesh_vert[m.mesh_vertadr[mesh]:][: len(v)],
                                       atol=1e-6)
            index = geometry["data"]["index"]["array"].data
            assert len(np.frombuffer(index, np.uint32)) == 3 * m.mesh_facenum[mesh]
        elif gtype == mujoco.mjtGeom.mjGEOM_HFIELD:
            h = m.geom_dataid[g]
            v = _vertices(geometry)
            assert len(v) == m.hfield_nrow[h] * m.hfield_ncol[h]
            np.testing.assert_allclose(v.max(0), m.hfield_size[h][:3], rtol=1e-6)
        else:
            pytest.fail(f"untested geom type {gtype}")
        drawn += 1
    assert drawn == m.ngeom
    tested = {mujoco.mjtGeom(t) for t in m.geom_type}
    assert len(tested) == 8  # plane, sphere, capsule, ellipsoid, cylinder, box, mesh, hfield


def test_hidden_groups_and_see_through_sites(toy_model):
    cmds = viz_scene.scene_commands(toy_model)
    hidden = {p for p, cs in _by_path(cmds, SetProperty).items()
              if any(c.key == "visible" and c.value is False for c in cs)}
    assert "/meshcat/mjstamp/bodies/world/geoms/collider" in hidden  # group 3, like MuJoCo
    assert "/meshcat/mjstamp/bodies/world/geoms/wall" not in hidden
    goal = _by_path(cmds, SetObject)["/meshcat/mjstamp/bodies/world/sites/goal"][0]
    material = goal.object.lower()["materials"][0]
    assert material["transparent"] is True
    assert material["opacity"] == pytest.approx(0.8 * viz_scene.SITE_OPACITY)
    assert _same_color(material["color"], [0.1, 0.8, 0.1])


def test_root_recentres_the_scene_and_camera_sees_it(toy_model):
    cmds = viz_scene.scene_commands(toy_model)
    d = mujoco.MjData(toy_model)
    mujoco.mj_kinematics(toy_model, d)
    center, radius = viz_scene.scene_bounds(toy_model, d)
    # What lies on the floor bounds the scene, not the floor (2 x 1 m): the post and the
    # pill at x = -0.6, the wall at x = 0.75, the egg, tet and bumps at |y| = 0.35-0.45.
    np.testing.assert_allclose(center[:2], [0.04, 0.03], atol=0.01)
    assert 0.75 < radius < 0.9
    root = _by_path(cmds, SetTransform)["/meshcat/mjstamp"][-1].matrix
    np.testing.assert_allclose(root[:3, 3], -center)
    cam = _by_path(cmds, SetProperty)["/Cameras/default/rotated/<object>"][-1].value
    assert 1.2 * radius < np.linalg.norm(cam) < 2.5 * radius


# ----------------------------------------------------------------------------
# Contact forces.

RESTING_XML = """
<mujoco>
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <geom name="table" type="box" size="0.2 0.2 0.05" pos="0.5 0 0.05"/>
    <body name="crate" pos="0 0 0.2">
      <freejoint/>
      <geom name="crate" type="box" size="0.05 0.05 0.05" mass="2"/>
    </body>
    <body name="ball" pos="0.5 0 0.2">
      <freejoint/>
      <geom name="ball" type="sphere" size="0.03" mass="0.7"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_contact_force_is_weight_on_the_support_with_either_geom_order():
    m = mujoco.MjModel.from_xml_string(RESTING_XML)
    d = mujoco.MjData(m)
    for _ in range(1500):  # 3 s: both have settled
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    geom = {n: m.geom(n).id for n in ("floor", "table", "crate", "ball")}
    g = 9.81
    # A box on a plane touches at 4 corners: their forces must be summed.
    assert sum(1 for c in d.contact[: d.ncon] if {*c.geom} == {geom["floor"], geom["crate"]}) > 1
    for (a, b), weight in {("crate", "floor"): 2 * g, ("ball", "table"): 0.7 * g}.items():
        on_support, point = viz.contact_force(m, d, geom[a], geom[b])
        np.testing.assert_allclose(on_support, [0, 0, -weight], rtol=1e-3, atol=1e-6)
        back, _ = viz.contact_force(m, d, geom[b], geom[a])
        np.testing.assert_allclose(back, -on_support)
        assert point[2] == pytest.approx(d.geom_xpos[geom[b]][2] + (
            0.05 if b == "table" else 0.0), abs=2e-3)  # on the support's top surface
    none, point = viz.contact_force(m, d, geom["crate"], geom["ball"])
    assert point is None and not none.any()


# ----------------------------------------------------------------------------
# Results directory, plan choice, timeline.


def test_load_results_rejects_bad_directories(toy_results, tmp_path):
    with pytest.raises(MjstampError, match="does not exist"):
        viz.load_results(tmp_path / "nope")
    with pytest.raises(MjstampError, match="holds plans of task 'toy', not 'billiards'"):
        viz.load_results(toy_results, task="billiards")
    old = tmp_path / "old"
    shutil.copytree(toy_results, old)
    data = json.loads((old / "plans.json").read_text())
    data["schema_version"] = 1
    (old / "plans.json").write_text(json.dumps(data))
    with pytest.raises(MjstampError, match=r"schema_version 1; this mjstamp reads 3 \(re-run "
                                           r"`mjstamp solve toy --out"):
        viz.load_results(old)
    other = tmp_path / "other"
    shutil.copytree(toy_results, other)
    m = mujoco.MjModel.from_xml_string(RESTING_XML)
    del data["schema_version"]
    results.save(other, data, {}, model=m)  # the scene of another task
    with pytest.raises(MjstampError, match=r"has qpos of shape \(4, 60, 2\) but scene.mjb "
                                           r"has nq=14"):
        viz.load_results(other)


def test_select_plans(toy_results):
    res = viz.load_results(toy_results, task="toy")
    particles = lambda **kw: [e["particle"] for e in viz.select_plans(res, **kw)]  # noqa: E731
    assert particles() == [0, 3]  # least-cost verified plan of each task plan, table order
    assert particles(task_plan="push-far") == [0, 7]
    assert particles(task_plan="push-near (failed)") == [5]
    assert particles(plan=[5, 3]) == [5, 3]
    assert particles(plan=7) == [7]
    with pytest.raises(MjstampError, match=r"plan 4 is not among .*; valid: 0, 3, 5, 7"):
        viz.select_plans(res, plan=4)
    with pytest.raises(MjstampError, match=r"task plan 'x' has no plans .*; valid: push-far, "
                                           r"push-near, push-near \(failed\)"):
        viz.select_plans(res, task_plan="x")


def test_timeline_replays_saved_states_and_draws_force_and_paths(toy_results):
    res = viz.load_results(toy_results)
    entries = viz.select_plans(res, plan=[0, 3])
    pb = viz.build_playback(res, entries, hold=0.5)
    m, dt = res.model, res.timestep
    # Two plans of T steps, each holding 0.5 s before the next.
    s0, s1 = pb.segments
    assert (s0.particle, s1.particle) == (0, 3)
    assert s0.start == 0 and s0.end == pytest.approx(T * dt)
    assert s1.start == pytest.approx(s0.end + 0.5 + 2 * dt)  # one 50 fps frame later
    [anim] = [c for c in pb.commands if isinstance(c, SetAnimation)]
    clips = {p.lower(): clip for p, clip in anim.animation.clips.items()}
    fps = clips["/meshcat/mjstamp/bodies/pusher"].fps
    stride = round(1 / (fps * dt))
    assert stride == 2
    # Body keyframes are the saved states (trajectories.npz xpos) of each plan.
    pos = clips["/meshcat/mjstamp/bodies/pusher"].tracks["position"]
    pusher, block = m.body("pusher").id, m.body("block").id
    for seg, row in ((s0, 0), (s1, 1)):
        first = round(seg.start * fps)
        for k in (1, 10, 30):
            got = pos.values[pos.frames.index(first + k)]
            np.testing.assert_allclose(got, res.trajectories["xpos"][row, stride * k - 1, pusher])
    # Every clip lasts the whole timeline, or looping would drift.
    ends = {max(t.frames) for clip in clips.values() for t in clip.tracks.values()}
    assert len(ends) == 1
    # Only the playing plan's paths show.
    vis = [clips[f"/meshcat/mjstamp/plans/0{k}"].tracks["visible"] for k in (0, 1)]
    assert vis[0].values[:2] == [True, False] and vis[1].values[:2] == [False, True]
    # Force arrow of the pusher on the block: none before contact, then along +x,
    # its tip on the contact point and its length |F| * force_scale.
    arrow = clips["/meshcat/mjstamp/forces/pusher_on_block"].tracks
    scale = np.array(arrow["scale"].values)[:, 0]
    assert scale[0] < 1e-5
    touching = np.flatnonzero(scale > 1e-3)
    assert 8 < touching[0] < 20  # contact after ~0.25-0.35 s at 50 frames per second
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    _, radius = viz_scene.scene_bounds(m, d)
    assert scale.max() <= ARROW_CAP * ARROW_FRACTION * radius + 1e-12
    k = touching[5]
    frame = arrow["scale"].frames[k]
    q = arrow["quaternion"].values[k]  # three.js (x, y, z, w)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.array([q[3], q[0], q[1], q[2]]))
    direction = rot.reshape(3, 3) @ [0, 1, 0]
    np.testing.assert_allclose(direction, [1, 0, 0], atol=1e-6)
    tip = np.array(arrow["position"].values[k]) + scale[k] * direction
    # The contact point lies between the pusher's and the block's saved positions.
    step = stride * (frame - round(s0.start * fps)) - 1
    x_pusher = res.trajectories["xpos"][0, step, pusher, 0]
    x_block = res.trajectories["xpos"][0, step, block, 0]
    assert x_pusher < tip[0] < x_block
    # Its length is the force at that saved state (velocity and the control of the next step).
    tr = res.trajectories
    d.qpos[:], d.qvel[:] = tr["qpos"][0, step], tr["qvel"][0, step]
    d.ctrl[:] = tr["ctrl"][0, step + 1]
    mujoco.mj_forward(m, d)
    force, _ = viz.contact_force(m, d, m.geom("pusher").id, m.geom("block").id)
    assert force[0] > 0
    assert scale[k] == pytest.approx(min(np.linalg.norm(force) * pb.force_scale,
                                         ARROW_CAP * ARROW_FRACTION * radius))
    # Trace lines: one per plan and traced body, through the saved positions.
    lines = _by_path(pb.commands, SetObject)
    line = lines["/meshcat/mjstamp/plans/01/trace/pusher"][0].object.lower()
    pts = np.frombuffer(line["geometries"][0]["data"]["attributes"]["position"]["array"].data,
                        np.float32).reshape(-1, 3)
    np.testing.assert_allclose(pts[-1], res.trajectories["xpos"][1, -1, pusher], atol=1e-6)


@pytest.fixture(scope="module")
def scored_results(toy_results, tmp_path_factory):
    """The toy results as a solve that scored its plans' robustness writes them."""
    out = tmp_path_factory.mktemp("scored") / "res"
    shutil.copytree(toy_results, out)
    data = json.loads((out / "plans.json").read_text())
    data["robustness"] = {
        "samples": 16, "seed": 3, "seconds": 0.1, "rollouts": 64, "declared": True,
        "scored_plans": 3, "median": 0.5,
        "uncertain": [
            {"kind": "mass", "names": ["pusher"], "spread": 0.3, "distribution": "uniform"},
            {"kind": "position", "names": ["block"], "spread": 0.01, "distribution": "normal"},
        ],
    }
    for e in data["plans"]:
        if e["verified"]:
            e["robustness"] = 0.5
    (out / "plans.json").write_text(json.dumps(data))
    return out


def test_perturbed_replays_play_as_translucent_copies(scored_results, toy_results):
    from mjstamp.scenes import uncertainty

    res = viz.load_results(scored_results)
    pb = viz.build_playback(res, viz.select_plans(res, plan=[0, 3]), perturbed=4)
    m, dt = res.model, res.timestep
    assert pb.perturbed == 4
    assert "robustness 0.50, 4 perturbed replays" in pb.segments[0].label()
    [anim] = [c for c in pb.commands if isinstance(c, SetAnimation)]
    clips = {p.lower(): clip for p, clip in anim.animation.clips.items()}
    objects = _by_path(pb.commands, SetObject)
    ghost = "/meshcat/mjstamp/plans/{:02d}/ghosts/{:02d}/{}"
    for k in (0, 1):
        for j in range(4):
            for body in ("pusher", "block"):
                assert ghost.format(k, j, body) in clips
            material = objects[ghost.format(k, j, "pusher") + "/pusher"][0].object.lower()
            assert material["materials"][0]["opacity"] == pytest.approx(0.25)
    assert ghost.format(0, 4, "pusher") not in clips
    ends = {max(t.frames) for clip in clips.values() for t in clip.tracks.values()}
    assert len(ends) == 1  # ghost clips last the whole timeline too
    # Replay j is the score's draw j: its pusher mass m_j (F = 2 N, free flight
    # before contact, semi-implicit Euler: x_t = x_0 + F / m_j dt^2 t (t + 1) / 2), and
    # the block starts offset by draw j's position noise.
    draws = uncertainty.sample(
        m, uncertainty.from_describe(m, res.summary["robustness"]["uncertain"], "x"), 16, 3)
    pusher, block = m.body("pusher").id, m.body("block").id
    fps = clips[ghost.format(0, 0, "pusher")].fps
    stride = round(1 / (fps * dt))
    xs = []
    for j in range(4):
        pos = clips[ghost.format(0, j, "pusher")].tracks["position"]
        t = stride * 5
        x = pos.values[pos.frames.index(5)][0]
        mass = draws.models[j].body_mass[pusher]
        assert mass != pytest.approx(m.body_mass[pusher], rel=1e-3)
        assert x == pytest.approx(2.0 / mass * dt**2 * t * (t + 1) / 2, rel=1e-9)
        xs.append(x)
        bpos = clips[ghost.format(0, j, "block")].tracks["position"]
        adr = m.jnt_qposadr[m.body_jntadr[block]]
        assert bpos.values[0][0] == pytest.approx(0.2 + draws.qpos_noise[j, adr], abs=1e-12)
    assert np.ptp(xs) > 1e-4
    note = viz.html_page(pb, title="t")
    assert "translucent copies: 4 perturbed replays" in note
    # Without scores, or more replays than were scored: one line each.
    plain = viz.load_results(toy_results)
    with pytest.raises(MjstampError, match="holds no robustness scores"):
        viz.build_playback(plain, viz.select_plans(plain), perturbed=2)
    with pytest.raises(MjstampError, match=r"scored on 16; valid: 1\.\.16"):
        viz.build_playback(res, viz.select_plans(res), perturbed=17)


# ----------------------------------------------------------------------------
# Standalone HTML in headless Chromium.

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="no chromium on PATH: install Debian's `chromium` package (.ci/run does) "
           "to run the standalone-HTML playback test",
)


def test_html_is_self_contained(toy_results, tmp_path):
    out = tmp_path / "toy.html"
    pb = viz.write_html(toy_results, out, task="toy")
    page = out.read_text()
    assert pb.html == out
    # Nothing is loaded from anywhere: no src or href attributes, no data fetched.
    assert re.search(r"<[a-z]+[^>]*\s(src|href)=", page) is None
    assert 'fetch("data:' not in page
    assert "MeshCat.Viewer" in page and len(page) > 800_000  # meshcat's viewer inlined
    # The commands, in order, as base64 msgpack: what a live server would have been sent.
    array = re.search(r"const MJSTAMP_COMMANDS = (\[.*?\]);", page, re.S).group(1)
    sent = [umsgpack.unpackb(base64.b64decode(c)) for c in json.loads(array)]
    assert [c["type"] for c in sent] == [c.lower()["type"] for c in pb.commands]
    assert sent[-1]["type"] == "set_animation" and sent[-1]["options"]["repetitions"] == math.inf
    assert "particle 0: push-far, cost 1" in page and "particle 3: push-near" in page
    with pytest.raises(MjstampError, match="directory .* does not exist"):
        viz.write_html(toy_results, tmp_path / "no" / "x.html")


def _chromium(url: str, tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    args = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
        # WebGL without a GPU: SwiftShader, Chromium's software renderer.
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--no-first-run", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--disable-quic", f"--user-data-dir={tmp_path / 'profile'}",
        # Offline: any host name fails to resolve, so the page must carry everything.
        "--host-resolver-rules=MAP * ~NOTFOUND",
        "--window-size=800,600", "--virtual-time-budget=2500", *extra, url,
    ]
    return subprocess.run(args, capture_output=True, text=True, timeout=120)


@needs_chromium
def test_html_plays_offline_in_headless_chromium(toy_results, tmp_path):
    out = tmp_path / "toy.html"
    pb = viz.write_html(toy_results, out)
    url = out.as_uri()

    def body(dom):
        assert dom.returncode == 0, dom.stderr[-2000:]
        tag = re.search(r"<body([^>]*)>", dom.stdout).group(1)
        return dict(re.findall(r'data-mjstamp-(\w+)="([^"]*)"', tag))

    # Every command applied, and the animation clock runs (virtual time: 2.5 s).
    state = body(_chromium(url, tmp_path, "--dump-dom"))
    assert int(state["loaded"]) == len(pb.commands)
    assert float(state["time"]) > 0.2
    # page.html#t=... freezes a moment; the legend marks the plan playing then.
    assert body(_chromium(f"{url}#t=1.5", tmp_path, "--dump-dom"))["segment"] == "1"
    # A frozen frame while the first plan's pusher pushes the block.
    png = tmp_path / "shot.png"
    state = body(_chromium(f"{url}#t=0.45", tmp_path, "--dump-dom", f"--screenshot={png}"))
    assert (state["time"], state["segment"]) == ("0.450", "0")
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB"), np.int16)
    assert img.shape == (600, 800, 3)
    assert img.std() > 20  # not a blank page
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    # Scene colors as shaded by the viewer's lights: the green floor covers a good part
    # of the view; the red wall and block, the blue pusher and the orange force arrow show.
    assert ((g > 110) & (r < 80) & (b < 90)).mean() > 0.05, "green floor not drawn"
    assert ((r > 150) & (g < 60) & (b < 60)).mean() > 0.003, "red wall/block not drawn"
    assert ((b > 120) & (r < 80) & (g < 80)).sum() > 20, "blue pusher not drawn"
    orange = (r > 180) & (b < 50) & (g > 0.45 * r) & (g < 0.7 * r)  # FORCE_COLOR, shaded
    assert orange.sum() > 20, "force arrow not drawn"


# ----------------------------------------------------------------------------
# Live meshcat server.


def test_live_server_serves_the_scene(toy_results):
    pb = viz.play(toy_results, plan=[3], open_browser=False)
    try:
        assert pb.url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(pb.url, timeout=10) as page:
            assert page.status == 200 and b"MeshCat" in page.read()
        scene = pb.visualizer.static_html()  # the server's copy of everything we sent
        objects = sum(isinstance(c, SetObject) for c in pb.commands)
        assert scene.count("fetch(") >= objects
        assert [s.particle for s in pb.segments] == [3]
    finally:
        server = pb._server
        pb.close()
    assert server.poll() is not None


@pytest.fixture
def busy_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def test_port_in_use_falls_back_to_html(toy_results, tmp_path, busy_port):
    results = tmp_path / "res"
    shutil.copytree(toy_results, results)
    with pytest.raises(viz.ServerUnavailable, match=f"port {busy_port}.*in use.*wrote "
                                                    f"{results / 'plans.html'} instead"):
        viz.play(results, port=busy_port)
    assert (results / "plans.html").stat().st_size > 800_000


# ----------------------------------------------------------------------------
# CLI.


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mjstamp: error: "), err
    return err[0].removeprefix("mjstamp: error: ")


def test_cli_view_bad_input(toy_results, tmp_path, capsys, busy_port):
    assert main(["view", str(tmp_path / "missing")]) == 2
    assert _one_error_line(capsys) == (
        f"results directory {str(tmp_path / 'missing')!r} does not exist")
    assert main(["view", str(toy_results), "--task", "pushing", "--html",
                 str(tmp_path / "x.html")]) == 2
    assert _one_error_line(capsys) == (
        f"{str(toy_results)!r} holds plans of task 'toy', not 'pushing'")
    old = tmp_path / "old"
    shutil.copytree(toy_results, old)
    data = json.loads((old / "plans.json").read_text())
    (old / "plans.json").write_text(json.dumps(data | {"schema_version": 1}))
    assert main(["view", str(old)]) == 2
    assert "schema_version 1; this mjstamp reads 3" in _one_error_line(capsys)
    assert main(["view", str(toy_results), "--plan", "9", "--html", str(tmp_path / "x.html")]) == 2
    assert _one_error_line(capsys).endswith("valid: 0, 3, 5, 7")
    assert main(["view", str(old), "--port", "70000"]) == 2
    assert _one_error_line(capsys) == "--port=70000 must be in 1..65535"
    assert main(["view", str(old), "--perturbed", "-1"]) == 2
    assert _one_error_line(capsys) == "--perturbed=-1 must be >= 0 (replays per plan)"
    assert main(["view", str(toy_results), "--perturbed", "--html", str(tmp_path / "x.html")]) == 2
    assert "holds no robustness scores" in _one_error_line(capsys)
    # A port in use: the page is written next to the results instead, said in one line.
    res = tmp_path / "res"
    shutil.copytree(toy_results, res)
    assert main(["view", str(res), "--port", str(busy_port), "--no-browser"]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"meshcat server could not start (cannot listen on port {busy_port}")
    assert line.endswith(f"wrote {res / 'plans.html'} instead")
    assert (res / "plans.html").is_file()


def test_cli_view_html(toy_results, tmp_path, capsys):
    out = tmp_path / "page.html"
    assert main(["view", str(toy_results), "--task-plan", "push-far", "--html", str(out)]) == 0
    assert capsys.readouterr().err.strip() == f"wrote {out} (2 plans)"
    assert "particle 7: push-far" in out.read_text()


# ----------------------------------------------------------------------------
# A real robot: dm_control's Kinova Jaco (issue 30), its meshes as shipped.

#: θ of two Jaco plans (velocity knots, rad/s) found while authoring the task
#: (tests/test_jaco.py KNOWN: 10-near and 10-post); playback only needs them to move.
JACO_THETA = {
    "10-near": [0.1721, -0.2893, -0.5768, -0.1934, 0.1253, 0.1651, 0.0427, 0.0918, 0.0174],
    "10-post": [-0.2059, -0.4395, -0.0624, 0.1185, -0.1077, -0.1792, -0.0382, -0.1206, -0.1637],
}
#: The task's settings these plans and the page's figures were measured at (2 ms steps,
#: dm_control's own; the task's default is now 5 ms, where a perturbed brick deflects
#: the servoed arm by more than the page's copy threshold).
JACO_SETTINGS = {"timestep": 0.002, "horizon": 600}


@pytest.fixture(scope="module")
def jaco_results(tmp_path_factory):
    """A Jaco results directory as `solve --out` writes it, from two plans replayed in C.

    No solve: the task's own inputs (θ -> controls), MuJoCo C steps, `results.save` with
    the task's scene, the path `SolveResult.save` takes (seconds, where a solve of the arm
    takes minutes).
    """
    pytest.importorskip("dm_control")
    from mjstamp.registry import load
    from mjstamp.tasks import jaco  # noqa: F401 - importing jaco registers the task

    problem = load("jaco", **JACO_SETTINGS)[0].build()
    m = problem.scene.m
    theta = np.array(list(JACO_THETA.values()))
    qpos0, qvel0, ctrl = problem.inputs(theta, xp=np)
    runs = []
    for i in range(len(theta)):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = qpos0[i], qvel0[i]
        out = {k: [] for k in ("qpos", "qvel", "ctrl", "xpos")}
        for t in range(ctrl.shape[1]):
            d.ctrl[:] = ctrl[i, t]
            mujoco.mj_step(m, d)
            mujoco.mj_kinematics(m, d)
            for k in out:
                out[k].append(np.array(getattr(d, k)))
        runs.append({k: np.array(v) for k, v in out.items()})
    traj = {"particle": np.arange(len(theta)), "qpos0": np.asarray(qpos0, float),
            "qvel0": np.asarray(qvel0, float),
            **{k: np.array([r[k] for r in runs]) for k in runs[0]},
            "timestep": np.float64(m.opt.timestep)}
    plans = list(JACO_THETA)
    summary = {
        "task": "jaco", "config": dict(JACO_SETTINGS), "declaration": problem.describe(),
        "plans": [{"particle": i, "task_plan": p, "predicted_task_plan": p, "verified": True,
                   "cost": float(i), "motion_plan": {"velocity": JACO_THETA[p]}}
                  for i, p in enumerate(plans)],
        "task_plans": [{"task_plan": p, "code": "", "plans": 1, "verified": 1,
                        "verified_share": 1.0, "best_cost": float(i)}
                       for i, p in enumerate(plans)],
    }
    particles = {"verified": np.ones(len(plans), bool), "returned": np.ones(len(plans), bool),
                 "task_plan": np.array(plans)}
    path = tmp_path_factory.mktemp("jaco") / "res"
    path.mkdir()
    results.save(path, summary, {"trajectories": traj, "particles": particles}, model=m)
    page = path / "jaco.html"
    return path, m, viz.write_html(path, page, task="jaco"), page


def test_jaco_page_holds_the_robot_meshes_as_shipped(jaco_results):
    path, m_task, pb, page = jaco_results
    m = viz.load_results(path, task="jaco").model  # scene.mjb loads, meshes and all
    assert (m.nmesh, int(m.mesh_vertnum.sum())) == (9, 4030)
    np.testing.assert_array_equal(m.mesh_vert, m_task.mesh_vert)
    objects = {p: c[-1].object.lower() for p, c in _by_path(pb.commands, SetObject).items()}
    drawn = set()
    for g in np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_MESH):
        mesh = int(m.geom_dataid[g])
        # dm_control's names hold '/' (jaco_arm/base), a meshcat path separator: '_'.
        body = viz_scene.body_name(m, int(m.geom_bodyid[g]))
        name = viz_scene.clean_name(m.geom(g).name, "")
        geometry = objects[f"/meshcat/mjstamp/bodies/{body}/geoms/{name}"]["geometries"][0]
        v0, nv = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
        # The visual mesh, every vertex: not the convex hull MuJoCo and MJX collide
        # (the fingers' are capped at 24 vertices by the task).
        np.testing.assert_allclose(_vertices(geometry), m.mesh_vert[v0 : v0 + nv], atol=1e-6)
        faces = np.frombuffer(geometry["data"]["index"]["array"].data, np.uint32)
        np.testing.assert_array_equal(faces.reshape(-1, 3), m.mesh_face[
            m.mesh_faceadr[mesh] : m.mesh_faceadr[mesh] + m.mesh_facenum[mesh]])
        drawn.add(mesh)
    assert drawn == set(range(9))
    # The camera frames the arm, the brick and the goals, not dm_control's 2 m floor.
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    center, radius = viz_scene.scene_bounds(m, d)
    assert 0.3 < radius < 0.6
    for point in (d.xpos[m.body("brick/").id], d.site_xpos[m.site("goal_post").id],
                  d.site_xpos[m.site("jaco_arm/jaco_hand/pinchsite").id]):
        assert np.linalg.norm(point - center) < radius
    # The arena's textured ground is drawn in its texture's colour (dark blue), not white.
    ground = objects["/meshcat/mjstamp/bodies/world/geoms/ground"]["materials"][0]["color"]
    assert ground >> 16 < 0x40 and ground & 0xFF > 0x40
    # Size: meshcat's viewer (~0.85 MB), the nine meshes and the keyframes of both plans.
    assert page.stat().st_size < 2_000_000


@needs_chromium
def test_jaco_page_renders_in_headless_chromium(jaco_results, tmp_path):
    _, _, pb, page = jaco_results
    png = tmp_path / "jaco.png"
    at = pb.segments[1].start + 0.9  # the second plan, its fist at the brick
    dom = _chromium(f"{page.as_uri()}#t={at:.2f}", tmp_path, "--dump-dom", f"--screenshot={png}")
    assert dom.returncode == 0, dom.stderr[-2000:]
    tag = re.search(r"<body([^>]*)>", dom.stdout).group(1)
    state = dict(re.findall(r'data-mjstamp-(\w+)="([^"]*)"', tag))
    assert int(state["loaded"]) == len(pb.commands)
    assert state["segment"] == "1"
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB"), np.int16)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    assert img.std() > 20  # not a blank page
    # The arm's dark grey links (0.1 0.1 0.1, shaded) fill a good part of the view, on
    # the arena's blue-grey ground; the brick (0.8 0.3 0.2) shows beside the fist.
    assert ((r < 45) & (g < 45) & (b < 45)).mean() > 0.02, "arm meshes not drawn"
    assert ((b > r + 15) & (b < 130) & (r < 90)).mean() > 0.3, "ground not drawn"
    assert ((r > 150) & (r > g + 60) & (b < 90)).sum() > 30, "brick not drawn"


def test_jaco_perturbed_replays_copy_only_what_they_move(jaco_results, tmp_path):
    """Only what the perturbed replays move gets see-through copies.

    The brick's position noise moves the brick by centimetres and the servoed arm by
    under half a millimetre; copying the arm would put every link's mesh into the page
    once per plan and replay.
    """
    path, m, _, plain = jaco_results
    scored = tmp_path / "scored"
    shutil.copytree(path, scored)
    data = json.loads((scored / "plans.json").read_text())
    data["robustness"] = {
        "samples": 8, "seed": 0, "seconds": 0.1, "rollouts": 16, "declared": True,
        "scored_plans": 2, "median": 0.5,
        "uncertain": [{"kind": "position", "names": ["brick/"], "spread": 0.005,
                       "distribution": "normal"}],
    }
    (scored / "plans.json").write_text(json.dumps(data))
    page = tmp_path / "ghosts.html"
    pb = viz.write_html(scored, page, perturbed=8)
    [anim] = [c for c in pb.commands if isinstance(c, SetAnimation)]
    ghosts = [p.lower().split("/plans/")[1] for p in anim.animation.clips if "/ghosts/" in
              p.lower()]  # "00/ghosts/03/brick_": plan, replay, body
    moving = {viz_scene.body_name(m, b) for b in range(1, m.nbody) if m.body_weldid[b]}
    copied = {g.rsplit("/", 1)[1] for g in ghosts}
    assert copied == {"brick_"} and len(ghosts) == 2 * 8  # two plans, eight replays
    assert "jaco_arm_b_1" in moving  # the shoulder moves, but as its servo says in every draw
    # The brick's copies and their keyframes: 0.15 MB over the page without them (1.49 MB);
    # copying every moving body, as before, added 7.0 MB (the arm's meshes, 16 times).
    assert page.stat().st_size - plain.stat().st_size < 300_000
