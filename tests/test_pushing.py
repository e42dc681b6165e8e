"""Pushing: demonstrations, DMP skills in the scene, references, decoding, bad input."""

import json
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp import registry, verify
from mjstamp.cli import main
from mjstamp.errors import MjstampError
from mjstamp.skills import bank as bank_mod
from mjstamp.skills import pushing as skills
from mjstamp.tasks.pushing import manhattan_detour

SIDE = {name: i for i, name in enumerate(skills.SIDES)}


@pytest.fixture(scope="module")
def task():
    task, _ = registry.load("pushing", max_pushes=2)
    return task


def plan_theta(task, pushes):
    """θ for hand-written plans [(side, (x, y)), ...] (yaw 0), Γ picking each side."""
    sl = task.build().slices()
    theta = np.zeros((len(pushes), task.dim))
    for i, plan in enumerate(pushes):
        logits = np.full((2, 4), -2.0)
        for k, (side, xy) in enumerate(plan):
            logits[k, SIDE[side]] = 2.0
            theta[i, sl["goal_xy"].start + 2 * k : sl["goal_xy"].start + 2 * k + 2] = xy
        theta[i, sl["side"]] = logits.ravel()
    return theta


def test_skills_reproduce_the_recorded_demonstrations(task):
    errors = skills.fit_errors(task.scene, task.extras["setup"], task.extras["bank"])
    assert set(errors) == {f"{s}/{p}" for s in skills.SIDES for p in ("approach", "push")}
    for name, e in errors.items():
        assert e["rms_rel"] <= 0.02, (name, e)
        assert e["end_rel"] <= 0.01, (name, e)


def test_demonstrations_lift_over_the_block_and_push_it(task):
    setup = task.extras["setup"]
    demos = skills.record_demonstrations(task.scene, setup, SIDE["west"])
    n_cases = len(skills.demonstration_cases(setup, SIDE["west"]))
    assert demos["approach"].shape == (n_cases, setup.approach_steps + 1, 3)
    assert demos["push"].shape == (n_cases, setup.push_steps + 1, 3)
    # Up over the block's top (half + radius) while changing sides.
    assert demos["approach"][..., 2].max(axis=1).min() > setup.half + setup.radius
    # A west push moves the pusher east.
    assert np.all(demos["push"][:, -1, 0] > demos["push"][:, 0, 0] + 0.05)


def test_references_go_from_the_pusher_to_the_goal_side(task):
    setup = task.extras["setup"]
    goals = jnp.asarray([[[0.3, 0.0, 0.0], [0.3, 0.3, 0.2]]])
    onehot = jnp.asarray([[np.eye(4)[SIDE["west"]], np.eye(4)[SIDE["south"]]]])
    x, v = skills.references(task.extras["bank"], setup, onehot, goals)
    assert x.shape == v.shape == (1, setup.horizon(2), 3)
    x = np.asarray(x)[0]
    touch = setup.half + setup.radius
    first_end = setup.approach_steps + setup.push_steps - 1
    np.testing.assert_allclose(x[first_end, :2], [0.3 - touch, 0.0], atol=3e-3)
    yaw = 0.2
    south = np.array([0.3 + touch * np.sin(yaw), 0.3 - touch * np.cos(yaw)])
    np.testing.assert_allclose(x[2 * first_end + 1, :2], south, atol=3e-3)
    np.testing.assert_allclose(x[-1], x[2 * first_end + 1], atol=1e-12)  # settles
    # The reference starts next to the pusher's start and lifts when changing sides.
    assert np.linalg.norm(x[0] - np.asarray(setup.pusher0)) < 0.02
    second = slice(first_end + 1, first_end + 1 + setup.approach_steps)
    assert x[second, 2].max() > setup.half + setup.radius


def test_hand_written_plans_decode_to_the_sides_pushed(task):
    theta = plan_theta(task, [
        [("west", (0.3, -0.02)), ("south", (0.48, 0.3))],
        [("south", (0.0, 0.3)), ("west", (0.5, 0.3))],
        [("west", (0.5, 0.3)), ("west", (0.5, 0.3))],  # the second push does nothing
        [("north", (0.0, -0.3)), ("north", (0.0, -0.3))],
        # The first "push" misses (its goal is behind the pusher), so the second
        # approach, aimed at the block's planned pose, lowers the pusher onto the
        # block's top, and it drags the block by friction: not a push of a side.
        [("north", (0.01, 0.11)), ("south", (0.49, 0.40))],
    ])
    replay = verify.simulate_c(task, theta)
    decoded = verify.decode(task, replay, theta)
    assert list(decoded.plan) == ["west,south", "south,west", "west", "north", "top"]
    assert decoded.ok.tolist() == [True, True, True, False, False]


def test_manhattan_detour_is_zero_for_monotone_pushes_only():
    goal = np.array([0.5, 0.3])
    monotone = jnp.asarray([[[0.3, 0.0], [0.5, 0.3]], [[0.0, 0.3], [0.5, 0.3]]])
    detour = jnp.asarray([[[-0.2, 0.0], [0.5, 0.3]], [[0.3, -0.2], [0.5, 0.3]]])
    assert np.allclose(manhattan_detour(monotone, np.zeros(2), goal), 0.0, atol=1e-3)
    np.testing.assert_allclose(manhattan_detour(detour, np.zeros(2), goal), [0.4, 0.4],
                               atol=1e-3)


def test_bad_settings_are_one_line_errors(tmp_path):
    with pytest.raises(MjstampError, match="max_pushes=0 must be in 1..10"):
        registry.load("pushing", max_pushes=0)
    with pytest.raises(MjstampError, match=r"goal region at \(1.5, 0.3\).*outside the workspace"):
        registry.load("pushing", goal_x=1.5)
    with pytest.raises(MjstampError, match=r"goal_half_size=0 must be > 0"):
        registry.load("pushing", goal_half_size=0.0)
    missing = tmp_path / "none.npz"
    with pytest.raises(MjstampError, match="not found"):
        registry.load("pushing", skill_bank=str(missing))
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a bank")
    with pytest.raises(MjstampError, match="junk.npz"):
        registry.load("pushing", skill_bank=str(junk))


class _EndsAt:
    """A rollout whose bodies all end at `xy` (and sites where the scene has them)."""

    def __init__(self, scene, xy):
        self.scene, self.xy = scene, np.asarray(xy, float)

    def body_pos(self, body):
        xyz = np.concatenate([self.xy, np.zeros((len(self.xy), 1))], axis=1)
        return jnp.asarray(xyz[:, None, :])

    def site_pos(self, site):
        pos = self.scene.m.site_pos[site]
        return jnp.asarray(np.tile(pos, (len(self.xy), 1, 1)))


def test_a_smaller_goal_region_is_the_site_and_the_aim_stays_inside_it():
    small, _ = registry.load("pushing", goal_half_size=0.01)
    site = small.scene.site("goal")
    np.testing.assert_allclose(small.scene.m.site_size[site, :2], [0.01, 0.01])
    np.testing.assert_allclose(small.scene.m.site_pos[site, :2], [0.5, 0.3])
    (target,) = [t for t in small.costs if t.name == "target"]
    # The margin (0.03) is capped at half the half-size: zero within 5 mm of the centre.
    r = np.asarray(target.residual(_EndsAt(small.scene, [[0.504, 0.3], [0.507, 0.3]])))
    np.testing.assert_allclose(r[:, 0], [0.0, 0.002], atol=1e-9)


def test_the_skill_bank_does_not_depend_on_the_goal_region(task):
    """Sites do not touch the demonstrations' physics: a moved or shrunk goal, the same bank."""
    moved, _ = registry.load("pushing", max_pushes=2, goal_x=0.4, goal_half_size=0.02)
    before = moved.scene.m.site_pos.copy()
    fp = skills.fingerprint(moved.scene, moved.extras["setup"])
    assert fp == skills.fingerprint(task.scene, task.extras["setup"])
    np.testing.assert_array_equal(moved.scene.m.site_pos, before)  # the scene is not touched
    heavier = moved.scene.m.__copy__()
    heavier.body_mass[moved.scene.body("block")] *= 2
    assert skills.fingerprint(SimpleNamespace(m=heavier), moved.extras["setup"]) != fp


def test_an_explicit_stale_bank_is_refused_not_replaced(task, tmp_path):
    path = tmp_path / "bank.npz"
    stale = bank_mod.SkillBank(skills=dict(task.extras["bank"].skills), fingerprint="0" * 16)
    bank_mod.save(stale, path)
    before = path.read_bytes()
    with pytest.raises(MjstampError, match="stale"):
        registry.load("pushing", skill_bank=str(path))
    assert path.read_bytes() == before


def test_cli_pushing_bad_input(capsys):
    cases = [
        (["solve", "pushing", "--max-pushes", "0"], "--max-pushes=0 must be in 1..10"),
        (["solve", "billiards", "--max-pushes", "2"], "task 'billiards' has no such option"),
        (["solve", "pushing", "--set", "skill_bank=/nonexistent/bank.npz"], "not found"),
    ]
    for argv, expected in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expected in err[0], (argv, err)


def test_cli_fits_a_skill_bank_file(tmp_path, capsys):
    out = tmp_path / "bank.npz"
    assert main(["skills", "--out", str(out), "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["path"] == str(out) and out.is_file()
    assert max(e["rms_rel"] for e in report["errors"].values()) <= 0.02
    task, _ = registry.load("pushing", skill_bank=str(out))  # a fresh file is current
    assert task.extras["bank"].fingerprint == report["fingerprint"]


def test_push_skills_reach_any_goal_in_the_workspace(task):
    """Each fitted skill ends within 1% of the workspace size of any goal in it."""
    import jax

    from mjstamp.skills import dmp

    config = registry.default_config("pushing")
    low = np.array([config["x_min"], config["y_min"], 0.0])
    high = np.array([config["x_max"], config["y_max"], 0.0])
    size = np.linalg.norm(high - low)
    rng = np.random.default_rng(0)
    starts = rng.uniform(low, high, (64, 3))
    goals = rng.uniform(low, high, (64, 3))
    setup = task.extras["setup"]
    for name, skill in task.extras["bank"].skills.items():
        steps = setup.approach_steps if name.endswith("approach") else setup.push_steps

        def end(a, b, skill=skill, steps=steps):
            return dmp.rollout(skill, a, b, steps=steps, duration=steps * setup.dt)[0][-1]

        reached = np.asarray(jax.vmap(end)(jnp.asarray(starts), jnp.asarray(goals)))
        worst = np.linalg.norm(reached - goals, axis=1).max()
        assert worst <= 0.01 * size, (name, worst, size)
