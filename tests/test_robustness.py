"""Robustness under uncertain physics (issue 16): declarations, scores, seeds."""

import numpy as np
import pytest

from mjstamp import plans
from mjstamp.errors import MjstampError


def _verified(task, n=600):
    """Verified plans of the tiny task, from uniform draws replayed in MuJoCo C."""
    theta = np.random.default_rng(0).uniform(-2, 2, (n, 2))
    dec = task.build().decode(plans.simulate_c(task, theta), theta)
    return theta[dec.ok], dec.plan[dec.ok]


def test_zero_uncertainty_scores_every_verified_plan_one(tiny_task):
    task = tiny_task()
    task.uncertain("friction", spread=0.0)
    theta, plan = _verified(task)
    assert len(theta) > 5
    rob = plans.robustness(task, theta, plan, samples=4)
    np.testing.assert_array_equal(rob.success, 1.0)
    np.testing.assert_array_equal(rob.same_plan, 1.0)


def test_edge_plan_scores_below_centred_and_seeds_reproduce(tiny_task):
    task = tiny_task()
    task.uncertain("position", ["puck"], spread=0.01)
    # A fan of shots at 1 m/s around the goal's direction: the one through the centre,
    # and the one whose path passes nearest 0.097 m from it (success radius 0.1 m).
    angles = np.deg2rad(135) + np.linspace(-0.3, 0.3, 241)
    fan = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    path = plans.simulate_c(task, fan).body_pos("puck")[..., :2]
    miss = np.linalg.norm(path - np.array([-0.3, 0.3]), axis=-1).min(axis=1)
    theta = fan[[int(np.argmin(miss)), int(np.argmin(np.abs(miss - 0.097)))]]
    one = plans.robustness(task, theta, samples=32, seed=3)
    two = plans.robustness(task, theta, samples=32, seed=3)
    np.testing.assert_array_equal(one.success, two.success)
    assert one.success[0] == 1.0
    assert one.success[1] < one.success[0]


@pytest.mark.parametrize(("args", "kwargs", "expect"), [
    (("viscosity",), {}, "valid: friction"),
    (("friction", ["nope"]), {}, "unknown geom 'nope'"),
    (("mass",), {"spread": 1.5}, "valid: 0 <= spread < 1"),
    (("position", ["world"]), {}, "no free or slide joint"),
    (("friction",), {"distribution": "cauchy"}, "valid: uniform, normal"),
    ((), {"spread": 0.1}, "without a kind declares the defaults"),
])
def test_bad_declarations_give_one_line(tiny_task, args, kwargs, expect):
    task = tiny_task()
    with pytest.raises(MjstampError) as e:
        task.uncertain(*args, **kwargs)
    assert expect in str(e.value) and "\n" not in str(e.value)
