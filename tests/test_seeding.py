"""Seeding STAMP's particles from a forward-only screen in MuJoCo C."""

import math

import jax
import numpy as np
import pytest

from mjstamp import seeding, verify


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
    decoded = verify.decode(task, verify.simulate_c(task, theta), theta)
    assert {p for p, ok in zip(decoded.plan, decoded.ok, strict=True) if ok} == {
        "0-goal", "1-goal"}
    # A screen of 1 is the prior draw itself.
    prior, none = seeding.seed_particles(task, key, 8, screen=1)
    np.testing.assert_array_equal(prior, np.asarray(task.build().init(key, 8)))
    assert none.successes == 0


def test_the_screen_hands_back_the_c_replay_of_the_particles_it_chose(tiny_task):
    # Chunks of 16 of 256 candidates: the screen drops the states of candidates
    # it can no longer choose between chunks, and keeps those of the chosen.
    task = tiny_task(goal_pos="0.2 0.3 0", radius=0.06)
    seeded = seeding.screen_particles(task, jax.random.key(3), 8, screen=32, chunk=16)
    again = verify.simulate_c(task, seeded.particles)
    for field in ("qpos", "qvel", "ctrl", "xpos", "site_xpos"):
        got, want = getattr(seeded.replay, field), getattr(again, field)
        assert got.dtype == want.dtype and np.array_equal(got, want), field
    assert seeded.replay.distances.keys() == again.distances.keys()
    for pair, d in again.distances.items():
        np.testing.assert_array_equal(seeded.replay.distances[pair], d)
    # Without a screen nothing was replayed.
    assert seeding.screen_particles(task, jax.random.key(3), 8, screen=1).replay is None


class _Box:
    """A stand-in problem: a 2-D box [0, 10] x [0, 1] with a uniform prior."""

    low = np.array([0.0, 0.0])
    high = np.array([10.0, 1.0])

    def init(self, key, n):
        return self.low + jax.random.uniform(key, (n, 2)) * (self.high - self.low)


def test_redraw_near_successes_spreads_over_task_plans_and_falls_back_to_the_prior():
    box = _Box()
    key = jax.random.key(0)
    # No successes: the prior's own draw, whatever `near` says.
    prior = seeding.Redraw(box, {}, near=1.0)
    np.testing.assert_array_equal(prior(key, 5),
                                  np.asarray(box.init(jax.random.split(key)[0], 5)))
    # A common task plan (100 candidates at x = 2) and a rare one (1 at x = 8):
    # each fresh particle near a success picks its task plan uniformly, so the
    # rare one gets about half of them, not 1%.
    successes = {"common": np.tile([2.0, 0.5], (100, 1)), "rare": np.array([[8.0, 0.5]])}
    near = seeding.Redraw(box, successes, near=1.0, jitter=0.01)
    fresh = near(key, 400)
    np.testing.assert_array_equal(fresh, near(key, 400))  # a function of the key
    assert not np.array_equal(fresh, near(jax.random.key(1), 400))
    rare = np.abs(fresh[:, 0] - 8.0) < 0.5
    common = np.abs(fresh[:, 0] - 2.0) < 0.5
    assert np.all(rare | common) and 0.4 < rare.mean() < 0.6
    # Noise of 1% of each box width (0.1 in x, 0.01 in y), clipped to the box.
    assert 0.05 < np.std(fresh[common, 0]) < 0.15 and 0.005 < np.std(fresh[common, 1]) < 0.015
    edge = seeding.Redraw(box, {"corner": np.array([[10.0, 1.0]])}, near=1.0, jitter=0.1)
    out = edge(key, 200)
    assert np.all(out <= box.high) and np.all(out >= box.low)
    # near = 0.5: about half near a success, the rest from the prior.
    half = seeding.Redraw(box, successes, near=0.5, jitter=0.01)(key, 400)
    by_success = (np.abs(half[:, 0] - 2.0) < 0.3) | (np.abs(half[:, 0] - 8.0) < 0.3)
    assert 0.4 < by_success.mean() < 0.7  # the prior puts ~12% of its draws there too


def test_screen_particles_hands_back_its_successes_by_task_plan(tiny_task):
    task = tiny_task(goal_pos="0.2 0.3 0", radius=0.06)
    seeded = seeding.screen_particles(task, jax.random.key(3), 8, screen=32)
    theta, _ = seeding.seed_particles(task, jax.random.key(3), 8, screen=32)
    np.testing.assert_array_equal(seeded.particles, theta)
    assert set(seeded.successes) == set(seeded.screen.task_plans) == {"0-goal", "1-goal"}
    for plan, members in seeded.successes.items():
        assert len(members) == seeded.screen.task_plans[plan]
        decoded = verify.decode(task, verify.simulate_c(task, members), members)
        assert all(decoded.ok) and set(decoded.plan) == {plan}


def test_auto_cost_scale_sharpens_a_flat_posterior_and_leaves_a_steep_one():
    def screen(low, median, candidates=8192):
        return seeding.Screen(candidates, 0, {}, 1, 0.0, cost_min=low, cost_median=median)

    # Costs in metres: the median candidate 1 above the best -> ln M nats apart.
    assert seeding.auto_cost_scale(screen(0.2, 1.2)) == pytest.approx(math.log(8192))
    assert seeding.auto_cost_scale(screen(5.0, 153.0)) == 1.0  # steep already: as declared
    for flat in (screen(1.0, 1.0), screen(None, None), None):  # no spread, no screen
        assert seeding.auto_cost_scale(flat) == 1.0


def test_auto_cost_scale_makes_the_posterior_independent_of_the_cost_units(tiny_task):
    """β·C is the same posterior whether the goal cost is weighted 0.01 or 0.02."""
    key = jax.random.key(3)
    betas, spreads = {}, {}
    for weight in (0.01, 0.02):
        report = seeding.screen_particles(tiny_task(weight=weight), key, 8, screen=32).screen
        betas[weight] = seeding.auto_cost_scale(report)
        spreads[weight] = report.cost_median - report.cost_min
    assert betas[0.01] > 1 and betas[0.01] == pytest.approx(2 * betas[0.02], rel=1e-6)
    assert betas[0.01] * spreads[0.01] == pytest.approx(math.log(256), rel=1e-9)


class _Outcome:
    """The two fields of `solve.Outcome` that `_keep_screened` reads."""

    def __init__(self, good, plans):
        self.good = np.asarray(good, bool)
        self.verified = type("Decoded", (), {"plan": np.asarray(plans, dtype=object)})()


def _evaluate(theta):
    """Rows 20, 30, 40 are screen candidates of "c", "d", "e"; MJX rejects "e"."""
    by_first = {20.0: ("c", True), 30.0: ("d", True), 40.0: ("e", False)}
    start = {0.0: ("a", True), 2.0: ("a", True), 4.0: ("b", True), 6.0: ("", False)}
    rows = [by_first.get(row[0]) or start[row[0]] for row in theta]
    return _Outcome([g for _, g in rows], [p for p, _ in rows])


@pytest.mark.parametrize("order, placed", [
    (("b", "c", "d", "e"), {3: "c", 1: "d"}),  # more plans than spare particles: best first
    (("e", "c"), {1: "c"}),  # MJX rejects "e": its particle gets its own plan back
])
def test_solve_returns_screen_plans_no_particle_holds(order, placed):
    from mjstamp.solver.selection import keep_screened as _keep_screened

    theta = np.arange(8.0).reshape(4, 2)  # particles 0, 1 hold "a", 2 holds "b", 3 fails
    pools = {"b": [[9.0, 9.0]], "c": [[20.0, 20.0], [21.0, 21.0]], "d": [[30.0, 30.0]],
             "e": [[40.0, 40.0]]}
    successes = {p: np.asarray(pools[p]) for p in order}
    source = np.full(4, "final", dtype=object)
    new, new_source, outcome = _keep_screened(theta, source, _evaluate(theta), successes,
                                              _evaluate)
    for i in range(4):
        if i in placed:
            assert new_source[i] == "screen" and outcome.verified.plan[i] == placed[i]
        else:
            assert new_source[i] == "final"
            np.testing.assert_array_equal(new[i], theta[i])
    assert set(outcome.verified.plan[outcome.good]) >= {"a", "b", *placed.values()}


def test_screen_seconds_screens_on_in_chunks_and_keeps_its_best(tiny_task):
    """screen.seconds: more candidates than n · screen, the particles still its best spread."""
    task = tiny_task(goal_pos="0.2 0.3 0", radius=0.06)
    key = jax.random.key(3)
    short = seeding.screen_particles(task, key, 8, screen=4, chunk=16)
    long = seeding.screen_particles(task, key, 8, screen=4, chunk=16, seconds=1.0)
    assert short.screen.candidates == 32
    assert long.screen.candidates > 32 and (long.screen.candidates - 32) % 16 == 0
    assert long.screen.seconds >= 1.0
    # more candidates: at least the short screen's successes, and no fewer task plans
    assert long.screen.successes >= short.screen.successes
    assert set(long.screen.task_plans) >= set(short.screen.task_plans)
    for plan, pool in long.successes.items():
        assert 1 <= len(pool) <= max(seeding.POOL, 8)
        decoded = verify.decode(task, verify.simulate_c(task, pool), pool)
        assert decoded.ok.all() and set(decoded.plan) == {plan}
