"""A scene MJX used to part on (box-box) solves by default, its MJX rollouts on C's path.

A box paddle on the table is thrown (θ = its initial velocity: x, y and spin)
so that it knocks a puck towards a goal, banking off box bumpers on the way
or not. MuJoCo's default contacts. With MJX's own box-box function the
rollouts part from C at the first paddle-bumper contact (0.07 m at p95, seen
in tests/test_contacts_fidelity.py's way); with C's routine ported they agree
to rounding, and the default solve takes the scene without a warning.
"""

import warnings

import numpy as np
import pytest

from mjstamp import solve
from mjstamp.errors import FidelityWarning
from mjstamp.scenes import Scene
from mjstamp.scenes.check import CheckSpec, check_scene
from mjstamp.tasks import Task, costs

PADDLE = """
<mujoco model="paddle">
  <option timestep="0.01" gravity="0 0 0"/>
  <worldbody>
    <geom name="bumper_top" type="box" pos="0 0.4 0" size="0.6 0.05 0.05"/>
    <geom name="bumper_bottom" type="box" pos="0 -0.4 0" size="0.6 0.05 0.05"/>
    <site name="goal" pos="0.45 0 0" size="0.08"/>
    <body name="paddle" pos="-0.35 0 0">
      <joint name="px" type="slide" axis="1 0 0" damping="0.5"/>
      <joint name="py" type="slide" axis="0 1 0" damping="0.5"/>
      <joint name="yaw" type="hinge" axis="0 0 1" damping="0.01"/>
      <geom name="paddle" type="box" size="0.03 0.12 0.04" mass="0.5"/>
    </body>
    <body name="puck" pos="-0.1 0 0">
      <joint name="x" type="slide" axis="1 0 0" damping="0.05"/>
      <joint name="y" type="slide" axis="0 1 0" damping="0.05"/>
      <geom name="puck" type="sphere" size="0.04" mass="0.2"/>
    </body>
  </worldbody>
</mujoco>
"""


def paddle_task():
    scene = Scene(PADDLE, name="paddle")
    task = Task("paddle", scene, horizon=100)
    task.box("throw", low=[0.5, -3.0, -10.0], high=[2.0, 3.0, 10.0],
             initial_qvel=("px", "py", "yaw"))
    task.contact("top", "paddle", "bumper_top")
    task.contact("bottom", "paddle", "bumper_bottom")
    task.cost("goal", costs.reach("puck", ["goal"]))
    task.success(costs.reaches("puck", {"goal": "goal"}, radius=0.1))
    return task


@pytest.mark.slow
def test_box_box_gradients_are_those_of_c():
    """MJX within the tolerance of C; AD against C's own central differences to 1e-4."""
    scene = Scene(PADDLE, name="paddle")
    spec = CheckSpec(horizon=100, qvel_joints=("px", "py", "yaw"), qvel_range=3.0)
    report = check_scene(scene, particles=16, spec=spec)
    assert report["healthy"], report["problems"]
    assert report["judged_by"] == "tolerance" and report["approximate_pairs"] == []
    assert report["physics_divergence_p95_m"] < 1e-9  # 2e-14 m seen: rounding
    assert report["rel_err_median"] <= 1e-4


@pytest.mark.slow
def test_default_solve_takes_the_paddle_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", FidelityWarning)
        result = solve(paddle_task(), {"particles": 16, "stamp.svgd_max_iters": 10,
                                       "stamp.sgd_max_iters": 10, "stamp.min_iters": 5}, seed=0,
                       progress=False)
    fid = result.summary()["fidelity"]
    assert fid["mjx_initial"]["judged_by"] == "tolerance"
    assert fid["mjx_initial"]["p95_m"] < 1e-9
    assert fid["faithful_at_end"] and fid["mjx_final"]["approximate_pairs"] == []
    assert np.isfinite(result.cost).all()
