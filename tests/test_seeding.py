"""Seeding STAMP's particles from a forward-only screen in MuJoCo C."""

import jax
import numpy as np

from mjstamp import plans, seeding
from mjstamp.scenes import Scene
from mjstamp.tasks import Task, costs

# A puck with a wall behind the goal: the goal is reached straight or off the wall.
SCENE = """
<mujoco model="bank">
  <option timestep="0.02" gravity="0 0 0"/>
  <default><geom condim="1" solref="-5000 -5"/></default>
  <worldbody>
    <geom name="wall" type="box" pos="0.5 0 0" size="0.05 1 0.05"/>
    <site name="goal" pos="0.2 0.3 0" size="0.02"/>
    <body name="puck">
      <joint name="px" type="slide" axis="1 0 0" damping="0.05"/>
      <joint name="py" type="slide" axis="0 1 0" damping="0.05"/>
      <geom name="puck" type="sphere" size="0.04" mass="0.2"/>
    </body>
  </worldbody>
</mujoco>
"""


def bank_task():
    task = Task("bank", Scene(SCENE), horizon=40)
    task.box("v", low=[-2, -2], high=[2, 2], initial_qvel=("px", "py"))
    task.contact("wall", "puck", "wall")
    task.cost("goal", costs.reach("puck", ["goal"]))
    task.success(costs.reaches("puck", {"goal": "goal"}, radius=0.06))
    return task


def test_seeding_is_reproducible_and_spread_over_task_plans():
    task = bank_task()
    key = jax.random.key(3)
    theta, report = seeding.seed_particles(task, key, 8, screen=32)
    again, _ = seeding.seed_particles(task, key, 8, screen=32)
    np.testing.assert_array_equal(theta, again)
    assert theta.shape == (8, 2) and report.candidates == 256
    # The screen found both task plans (straight, and off the wall), and the
    # particles start on each of them, not only on the most common one.
    assert set(report.task_plans) == {"0-goal", "1-goal"}
    decoded = plans.decode(task, plans.simulate_c(task, theta), theta)
    assert {p for p, ok in zip(decoded.plan, decoded.ok, strict=True) if ok} == {
        "0-goal", "1-goal"}
    # A screen of 1 is the prior draw itself.
    prior, none = seeding.seed_particles(task, key, 8, screen=1)
    np.testing.assert_array_equal(prior, np.asarray(task.build().init(key, 8)))
    assert none.successes == 0
