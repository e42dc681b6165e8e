"""`mjstamp check` on small scenes, one per GJK/EPA pair family: AD of MJX rollouts against C.

Each scene is written as a user would: a body dropped or struck onto another
with MuJoCo's default contacts. Per scene, prints the check's verdict, the
median relative error of AD against MuJoCo C's central differences (over the
particles where C's own differences at the step and ten times it agree:
`fd_smooth_particles`), the cost per particle-step and the compile time.

Scenes:
  paddle_cylinder  a thrown box paddle strikes a cylinder puck (no table,
                   no gravity): cylinder-box;
  arm_cylinder     a two-link motor arm's box paddle strikes a cylinder puck
                   on a table (8 torque knots): cylinder-box, plane-cylinder;
  puck_cylinder    a cylinder puck sliding on a table: plane-cylinder (C's own
                   differences are not smooth there);
  puck_box         the same with a box puck;
  can_on_can       cylinder-cylinder;
  egg_on_box       ellipsoid-box;
  rock_on_box      mesh-box (exact meshes).

Usage: python benchmarks/perf/rollout_gradients.py [--scenes a,b] [--particles 8]
       [--save FILE]
N.B. a cylinder or ellipsoid scene compiles for minutes (AD through every
GJK/EPA iteration, `ccd.ccd`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import save_json  # noqa: E402

PADDLE = """
<mujoco model="paddle_cylinder">
  <option timestep="0.01" gravity="0 0 0"/>
  <worldbody>
    <geom name="bumper_top" type="box" pos="0 0.4 0" size="0.6 0.05 0.05"/>
    <geom name="bumper_bottom" type="box" pos="0 -0.4 0" size="0.6 0.05 0.05"/>
    <body name="paddle" pos="-0.35 0 0">
      <joint name="px" type="slide" axis="1 0 0" damping="0.5"/>
      <joint name="py" type="slide" axis="0 1 0" damping="0.5"/>
      <joint name="yaw" type="hinge" axis="0 0 1" damping="0.01"/>
      <geom name="paddle" type="box" size="0.03 0.12 0.04" mass="0.5"/>
    </body>
    <body name="puck" pos="-0.1 0 0">
      <joint name="x" type="slide" axis="1 0 0" damping="0.05"/>
      <joint name="y" type="slide" axis="0 1 0" damping="0.05"/>
      <geom name="puck" type="cylinder" size="0.04 0.04" mass="0.2"/>
    </body>
  </worldbody>
</mujoco>
"""

ARM = """
<mujoco model="arm_cylinder">
  <option timestep="0.005"/>
  <default><geom friction="0.5 0.005 0.0001"/></default>
  <worldbody>
    <geom name="table" type="plane" size="1 1 0.1"/>
    <geom name="bumper_left" type="box" pos="0.3 0.35 0.04" size="0.35 0.03 0.04"/>
    <geom name="bumper_right" type="box" pos="0.3 -0.35 0.04" size="0.35 0.03 0.04"/>
    <body name="upper" pos="-0.3 0 0.05">
      <joint name="shoulder" type="hinge" axis="0 0 1" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.02" contype="0" conaffinity="0"/>
      <body name="fore" pos="0.25 0 0">
        <joint name="elbow" type="hinge" axis="0 0 1" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" contype="0" conaffinity="0"/>
        <geom name="paddle" type="box" pos="0.22 0 0" size="0.02 0.06 0.03"/>
      </body>
    </body>
    <body name="puck" pos="0.12 0.1 0.02">
      <freejoint/>
      <geom name="puck" type="cylinder" size="0.04 0.02" mass="0.1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="elbow" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""

PUCK = """
<mujoco model="puck">
  <option timestep="0.005"/>
  <default><geom friction="0.5 0.005 0.0001"/></default>
  <worldbody>
    <geom name="table" type="plane" size="1 1 0.1"/>
    <body name="puck" pos="0 0 0.02"><freejoint/><geom name="puck" {shape} mass="0.1"/></body>
  </worldbody>
</mujoco>
"""

DROP = """
<mujoco model="drop">
  <option timestep="0.005"/>
  <asset>
    <mesh name="rock" vertex="0.04 0 0  -0.03 0.02 0  0 -0.035 0.01  0.01 0.01 0.04
                              0 0.005 -0.035  -0.02 -0.02 0.02"/>
  </asset>
  <worldbody>
    <geom name="base" {base} pos="0 0 0.05"/>
    <body name="body" pos="0.01 0.01 0.15" euler="20 10 0">
      <freejoint/><geom {shape}/>
    </body>
  </worldbody>
</mujoco>
"""


def scenes() -> dict:
    """{name: (xml, CheckSpec)}."""
    from mjstamp.scenes.check import CheckSpec

    drop = CheckSpec(horizon=40, qvel_range=0.3)
    return {
        "paddle_cylinder": (PADDLE, CheckSpec(horizon=100, qvel_joints=("px", "py", "yaw"),
                                              qvel_range=3.0)),
        "arm_cylinder": (ARM, CheckSpec(horizon=200, ctrl_segments=8, ctrl_fraction=1.0)),
        "puck_cylinder": (PUCK.format(shape='type="cylinder" size="0.04 0.02"'),
                          CheckSpec(horizon=100, qvel_range=0.3)),
        "puck_box": (PUCK.format(shape='type="box" size="0.04 0.04 0.02"'),
                     CheckSpec(horizon=100, qvel_range=0.3)),
        "can_on_can": (DROP.format(base='type="cylinder" size="0.06 0.05"',
                                   shape='type="cylinder" size="0.03 0.03"'), drop),
        "egg_on_box": (DROP.format(base='type="box" size="0.08 0.08 0.05"',
                                   shape='type="ellipsoid" size="0.04 0.025 0.03"'), drop),
        "rock_on_box": (DROP.format(base='type="box" size="0.08 0.08 0.05"',
                                    shape='type="mesh" mesh="rock"'), drop),
    }


KEYS = ("healthy", "faithful", "fd_smooth_particles", "rel_err_median", "rel_err_p95",
        "model_rel_err_median", "us_per_particle_step", "compile_s", "gradient", "iterations",
        "problems")


def measure(name: str, particles: int) -> dict:
    """One scene's row: the check's verdict and numbers."""
    from mjstamp import Scene, colliders
    from mjstamp.scenes.check import check_scene

    xml, spec = scenes()[name]
    colliders.exact_meshes()
    t0 = time.perf_counter()
    report = check_scene(Scene(xml, name=name), particles=particles, spec=spec)
    return {"scene": name, **{k: report[k] for k in KEYS},
            "wall_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    """Runs the scenes asked for and prints one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(scenes()), help="comma-separated names")
    parser.add_argument("--particles", type=int, default=8)
    parser.add_argument("--save", metavar="FILE", help="also write the JSON there")
    args = parser.parse_args(argv)
    names = [s for s in args.scenes.split(",") if s]
    unknown = [s for s in names if s not in scenes()]
    if unknown:
        parser.error(f"unknown scene {unknown[0]!r}; valid: {', '.join(scenes())}")
    import mjstamp

    mjstamp.configure()
    rows = [measure(name, args.particles) for name in names]
    out = {"particles": args.particles, "scenes": rows}
    print(json.dumps(out, indent=1))
    if args.save:
        save_json(Path(args.save), out, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
