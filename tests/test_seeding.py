"""Seeding STAMP's particles from a forward-only screen in MuJoCo C."""

import jax
import numpy as np

from mjstamp import plans, seeding


def test_seeding_is_reproducible_and_spread_over_task_plans(tiny_task):
    # The goal in front of the wall: reached straight or off the wall.
    task = tiny_task(goal_pos="0.2 0.3 0", radius=0.06)
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
