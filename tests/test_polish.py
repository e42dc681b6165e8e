"""The precision polish (Levenberg–Marquardt in the gradient model) and the landing in C."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp import solve, svgd, verify
from mjstamp.config import SolveConfig
from mjstamp.errors import MjstampError
from mjstamp.tasks import Task, costs
from mjstamp.tasks.declaration import SumOfSquares

BOX = (np.array([-2.0, -2.0]), np.array([2.0, 2.0]))


def rosenbrock(theta):
    """Residuals whose Σ r² is Rosenbrock's function: minimum 0 at (1, 1)."""
    x, y = theta[:, 0], theta[:, 1]
    return [jnp.stack([10 * (y - x**2), 1 - x], axis=1)]


@pytest.mark.parametrize("mode", ["fwd", "rev"])
def test_polish_lands_rosenbrock_in_a_few_steps(mode):
    theta0 = np.random.default_rng(0).uniform(-2, 2, (32, 2))
    config = svgd.PolishConfig(max_iters=60, patience=0)
    result = svgd.run_polish(rosenbrock, theta0, *BOX, config, tolerances=[1e-6], mode=mode)
    assert result.landed.all()
    np.testing.assert_allclose(result.particles, 1.0, atol=1e-5)
    assert np.median(result.iterations) <= 10  # Adam at a fixed step would circle for hundreds
    assert (result.objective_after <= result.objective_before).all()


def test_polish_lets_no_straggler_hold_the_batch():
    """With patience, the batch stops once few still descend and none lands for a while."""
    theta0 = np.random.default_rng(0).uniform(-2, 2, (32, 2))
    patient = svgd.run_polish(rosenbrock, theta0, *BOX, svgd.PolishConfig(max_iters=60),
                              tolerances=[1e-6])
    full = svgd.run_polish(rosenbrock, theta0, *BOX,
                           svgd.PolishConfig(max_iters=60, patience=0), tolerances=[1e-6])
    assert patient.steps < full.steps
    assert patient.landed.sum() >= 0.9 * len(theta0)


def test_polish_keeps_to_the_box():
    """The goal (1, 1) lies outside x <= 0.5: each particle ends on that face, at (0.5, 0.25)."""
    low, high = np.array([-2.0, -2.0]), np.array([0.5, 2.0])
    theta0 = np.random.default_rng(1).uniform(low, high, (16, 2))
    result = svgd.run_polish(rosenbrock, theta0, low, high,
                             svgd.PolishConfig(max_iters=60, patience=0), tolerances=[None])
    assert (result.particles >= low).all() and (result.particles <= high).all()
    np.testing.assert_allclose(result.particles, [[0.5, 0.25]] * 16, atol=1e-4)
    assert not result.landed.any()  # no tolerance declared: nothing counts as landed


def test_polish_stops_where_its_model_predicts_nothing():
    """On residuals rough at a fine scale the exact derivative is useless: μ passes mu_max."""

    def rough(theta):
        return [theta + 0.05 * jnp.sin(2000 * theta) - 1.0]

    theta0 = np.random.default_rng(2).uniform(-2, 0, (16, 2))
    result = svgd.run_polish(rough, theta0, *BOX, svgd.PolishConfig(max_iters=200),
                             tolerances=[1e-3])
    assert result.steps < 200  # every particle gave up before the cap
    assert not result.landed.all()


def test_polish_leaves_a_nonfinite_particle_alone():
    def fn(theta):
        return [jnp.where(theta[:, :1] > 1.5, jnp.nan, theta - 0.5)]

    theta0 = np.array([[1.8, 0.0], [0.0, 0.0]])
    result = svgd.run_polish(fn, theta0, *BOX, tolerances=[1e-6])
    np.testing.assert_array_equal(result.particles[0], theta0[0])
    assert result.iterations[0] == 0 and result.landed[1]


@pytest.mark.parametrize(("key", "value", "message"), [
    ("polish.max_iters", -1, "polish.max_iters=-1 must be an integer >= 0 or None"),
    ("landing.sgd_max_iters", -2, "landing.sgd_max_iters=-2 must be an integer >= 0 or None"),
    ("polish.patience", True, "polish.patience=True must be an integer >= 0"),
    ("polish.depth", 0, r"polish.depth=0 must be a finite number in \(0, 1\]"),
    ("polish.mu_max", float("inf"), r"polish.mu_max=inf must be a finite number in \(0, inf\)"),
    ("polish.mu0", 1e9, "polish.mu0=1000000000.0 must be below polish.mu_max"),
    ("landing.iterations", 1.5, "landing.iterations=1.5 must be an integer >= 0"),
    ("landing.radius", 2, r"landing.radius=2 must be a number in \(0, 1\]"),
    ("landing.early", "yes", "landing.early='yes' must be True or False"),
])
def test_polish_and_landing_settings_are_checked_in_one_line(key, value, message):
    with pytest.raises(MjstampError, match=message) as e:
        SolveConfig.from_dict({key: value})
    assert "\n" not in str(e.value)


def test_residual_costs_are_their_sums_of_squares(tiny_task):
    task = tiny_task()
    task.cost("final", costs.reach("puck", ["goal"], when="final"), weight=2.0)
    task.residuals("mine", lambda r: r.body_pos("puck")[:, -1, :2] - 0.1, weight=3.0,
                   tolerance=0.05)
    problem = task.build()
    terms = {t.name: t for t in problem.residual_terms}
    assert list(terms) == ["goal", "final", "mine"]
    # A reach without a tolerance takes the radius of the `reaches` success on its goals.
    assert terms["goal"].tolerance == 0.1 and terms["final"].tolerance == 0.1
    assert terms["mine"].tolerance == 0.05 and isinstance(terms["mine"].fn, SumOfSquares)
    theta = jnp.asarray(np.random.default_rng(3).uniform(-2, 2, (4, 2)))
    rollout, values = problem.evaluate(theta, hard=True)
    parts = problem.residuals(theta)
    np.testing.assert_allclose(jnp.sum(parts[1] ** 2, axis=1), 2.0 * values["final"],
                               rtol=1e-12)
    np.testing.assert_allclose(jnp.sum(parts[2] ** 2, axis=1), 3.0 * values["mine"],
                               rtol=1e-12)
    # The softmin reach's residual is the offset at the nearest pass: its hard minimum.
    d2 = jnp.sum((rollout.body_pos("puck")[..., :2] - rollout.site_pos("goal")[..., :2]) ** 2,
                 axis=-1)
    np.testing.assert_allclose(jnp.sum(parts[0] ** 2, axis=1), 50.0 * d2.min(axis=1),
                               rtol=1e-12)
    assert problem.residual_tolerances() == pytest.approx(
        [0.1 * np.sqrt(50), 0.1 * np.sqrt(2), 0.05 * np.sqrt(3)])


def test_residual_declarations_are_checked(tiny_task):
    task = tiny_task()
    with pytest.raises(MjstampError, match="residuals 'r' tolerance=-1 must be a number >= 0"):
        task.residuals("r", lambda r: r.body_pos("puck")[:, -1, :2], tolerance=-1)
    with pytest.raises(MjstampError, match="residuals 'goal' is already declared|'goal'"):
        task.residuals("goal", lambda r: r.body_pos("puck")[:, -1, :2])
    assert costs.box_target("puck", "goal").residuals is not None
    assert costs.aim("puck", "wall").residuals is None  # a gap, not a squared distance
    with pytest.raises(MjstampError, match="'aim': this cost of mjstamp.tasks.costs has no "
                                           "residuals"):
        task.residuals("aim", costs.aim("puck", "wall"))
    with pytest.raises(MjstampError, match="cost 'gap': tolerance= is for a cost with "
                                           "residuals"):
        task.cost("gap", costs.aim("puck", "wall"), tolerance=0.1)
    # A cost of `costs` given to residuals brings its own; one of the wrong shape, one line.
    task.residuals("final", costs.reach("puck", ["goal"], when="final"), tolerance=0.02)
    task.residuals("flat", lambda r: r.body_pos("puck")[:, -1, 0])
    problem = task.build()
    assert {t.name: t.tolerance for t in problem.residual_terms}["final"] == 0.02
    with pytest.raises(MjstampError, match="residuals 'flat' must return an \\(n, m\\) array"):
        problem.evaluate(jnp.zeros((2, 2)), hard=True)


def test_landing_in_c_lands_a_near_miss_that_nothing_else_moves(tiny_task):
    """The tiny puck ends 1 cm from the goal for a 2 mm radius: Gauss–Newton in C lands it."""
    task = tiny_task(radius=0.002)
    problem = task.build()
    hit = np.array([[-0.75, 0.78]])  # θ found by hand: the puck passes 1.04 cm from the goal
    residual = np.concatenate(verify.residuals_c(problem, verify.simulate_c(problem, hit), hit), 1)
    assert np.linalg.norm(residual) / np.sqrt(50) > 0.002  # a miss to start with
    idle = verify.land(problem, hit, iterations=0)
    assert not idle.ok.any() and idle.rollouts == 1
    landed = verify.land(problem, hit, iterations=20)
    assert landed.ok.all() and landed.landed.all()
    assert landed.objective[0] < 0.25**2 * 0.002**2 * 50 * (1 + 1e-9)
    assert landed.iterations[0] <= 10


def test_the_landing_deepens_a_task_plan_and_never_swaps_it(monkeypatch):
    """A landing deepens a verified task plan, never swaps it.

    1-D: r = θ, success for |θ| < 1, task plan "A" above 0.05 and "B" below it. A particle
    verified in "A" descends towards 0 but keeps its best point in "A"; one that failed
    takes the best success it meets, whatever its plan.
    """
    from types import SimpleNamespace

    from mjstamp.verify import landing

    def evaluate(problem, theta, tolerances, depth, replay=None):
        x = theta[:, 0]
        ok = np.abs(x) < 1.0
        plan = np.where(x > 0.05, "A", "B").astype(object)
        return x**2, x[:, None], ok, ok & (np.abs(x) <= depth * 0.01), plan

    problem = SimpleNamespace(residual_tolerances=lambda: [0.01])
    monkeypatch.setattr(landing, "as_problem", lambda task: problem)
    monkeypatch.setattr(landing, "_evaluate", evaluate)
    monkeypatch.setattr(landing, "_box", lambda p: (np.array([-2.0]), np.array([2.0]),
                                                   np.array([True]), np.array([True])))
    result = landing.land(problem, np.array([[0.5], [1.5]]), iterations=30, radius=0.05)
    assert result.plan.tolist() == ["A", "B"] and result.ok.all()
    assert 0.05 < result.theta[0, 0] < 0.5  # deeper in "A", not crossed into "B"
    assert abs(result.theta[1, 0]) < 0.05 and result.landed[1]


def test_solve_polishes_and_lands_and_reports_it(tiny_task):
    """A tiny solve with a 5 mm goal: the polish and the landings land what STAMP leaves near."""
    task = tiny_task(radius=0.005)
    base = {"particles": 8, "screen": {"candidates": 4},
            "stamp": {"svgd_max_iters": 2, "sgd_max_iters": 2, "min_iters": 0},
            "verify": {"robustness_samples": 0}, "polish": {"max_iters": 20}}
    off = solve(task, {**base, "polish": {"max_iters": 0}, "landing": {"iterations": 0}},
                progress=False)
    on = solve(task, base, progress=False)
    assert off.polish is None
    report = on.summary()["polish"]
    assert set(report) == {"gradient", "landing", "early"}
    assert report["gradient"]["particles"] == 8 and report["landing"]["particles"] == 8
    assert on.verified_mask().sum() > off.verified_mask().sum()
    assert "landing_s" in on.timings and "polish_s" in on.timings
    # Plans stream: each task plan is recorded when first verified, the screen's first.
    summary = on.summary()
    assert set(on.verified.plan[on.verified_mask()]) <= set(summary["found"])
    times = [f["seconds"] for f in on.found.values()]
    assert times == sorted(times) and summary["first_plan_s"] == times[0]
    assert times[0] <= on.timings["screen_s"] + on.timings["early_s"] + 1.0


def test_the_polish_never_swaps_a_verified_plan_for_another():
    """The polish deepens a verified plan and never swaps it.

    A verified particle it moves out of its task plan (or to a failure) gets its θ back; one
    that stays in it, or failed before, keeps the polish's; every plan is streamed.
    """
    from types import SimpleNamespace

    from mjstamp.solver import pipeline as solve_mod

    def evaluate(theta, replay=None):  # succeeds where x > 0; task plan "a" where y > 0
        plan = np.where(theta[:, 1] > 0, "a", "b").astype(object)
        return SimpleNamespace(good=theta[:, 0] > 0, verified=SimpleNamespace(plan=plan))

    theta = np.array([[1.0, 1.0], [1.0, 1.0], [-1.0, -1.0], [1.0, 1.0]])
    polished = SimpleNamespace(particles=np.array(
        [[1.0, -1.0],   # verified "a" moved to "b": back
         [2.0, 2.0],    # verified "a", deeper in it: kept
         [1.0, -1.0],   # failed before, now "b": kept
         [-1.0, 1.0]]))  # verified "a" moved to a failure: back
    said = []
    found = solve_mod.Found(said.append, 0.0)
    kept, outcome, (before_theta, _), given_back = solve_mod._take_polished(
        theta, polished, evaluate, found)
    np.testing.assert_array_equal(kept, [[1, 1], [2, 2], [1, -1], [1, 1]])
    assert given_back == 2 and outcome.good.all() and before_theta is theta
    assert {p: f["source"] for p, f in found.plans.items()} == {"a": "STAMP", "b": "polished"}


def test_polish_runs_by_default_on_an_accelerator_only(monkeypatch):
    from mjstamp.solver import pipeline as solve_mod

    assert solve_mod.polish_iterations(SolveConfig()) == 0  # the test session's CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert solve_mod.polish_iterations(SolveConfig()) == 20
    assert solve_mod.polish_iterations(SolveConfig.from_dict({"polish.max_iters": 3})) == 3


def test_the_landing_shortens_sgd_where_it_refines(tiny_task):
    from mjstamp.solver import pipeline as solve_mod

    problem = tiny_task().build()
    cfg = SolveConfig()
    assert solve_mod._stamp_config(cfg, problem, 0).sgd_max_iters == 20
    off = SolveConfig.from_dict({"landing.sgd_max_iters": None})
    assert solve_mod._stamp_config(off, problem, 0).sgd_max_iters == cfg.stamp.sgd_max_iters


def test_polish_and_landing_need_residuals(tiny_task):
    """A task without residual costs is left as STAMP leaves it: no polish, no landing."""
    from mjstamp.solver import pipeline as solve_mod

    task = tiny_task()
    bare = Task("bare", task.scene, horizon=20)
    bare.box("v", low=[-2, -2], high=[2, 2], initial_qvel=("px", "py"))
    bare.cost("aim", costs.aim("puck", "wall"))
    problem = bare.build()
    assert not problem.residual_terms
    cfg, theta = SolveConfig.from_dict({"polish.max_iters": 20}), np.zeros((4, 2))
    assert solve_mod._polish(problem, cfg, theta, print) is None
    assert solve_mod._stamp_config(cfg, problem, 0).sgd_max_iters == cfg.stamp.sgd_max_iters
    said = []
    out = solve_mod._land(problem, cfg, theta, None, None, None, said.append)
    assert out == (theta, None, None, None) and not said


def test_jacobian_with_aux_matches_without():
    fn = jax.jit(lambda x: (jnp.stack([x[:, 0] * x[:, 1], jnp.sin(x[:, 0])], 1), x.sum(1)))
    x = jnp.asarray(np.random.default_rng(4).normal(size=(5, 3)))
    from mjstamp.svgd._jacobian import value_and_batched_jacobian

    for mode in ("fwd", "rev"):
        (out, aux), jac = value_and_batched_jacobian(fn, x, mode, has_aux=True)
        out2, jac2 = value_and_batched_jacobian(lambda z: fn(z)[0], x, mode)
        np.testing.assert_allclose(jac, jac2, rtol=1e-12)
        np.testing.assert_allclose(aux, x.sum(1))


def test_a_budget_splits_the_solve_and_screens_while_it_yields(tiny_task):
    import time

    from mjstamp import seeding
    from mjstamp.solver import pipeline as solve_mod

    with pytest.raises(MjstampError, match="budget=0 must be a number of seconds > 0 or None"):
        SolveConfig(budget=0)
    problem = tiny_task().build()
    plain = SolveConfig()
    assert solve_mod._deadlines(plain, plain.stamp, time.perf_counter()) == (None, None)
    cfg = SolveConfig.from_dict({"budget": 100})
    # The split follows the caps the run applies: SGD's is the landing's 20 where it lands.
    stamp = solve_mod._stamp_config(cfg, problem, 0)
    assert (stamp.svgd_max_iters, stamp.sgd_max_iters) == (50, 20)
    start = time.perf_counter()
    svgd_end, sgd_end = solve_mod._deadlines(cfg, stamp, start)
    assert start < svgd_end < sgd_end <= start + 80 + 1e-6  # a fifth kept for the checks
    assert (svgd_end - start) / (sgd_end - start) == pytest.approx(50 / 70, abs=0.01)
    # The screen stops once its chunks find no new task plan, long before its seconds.
    started = time.perf_counter()
    seeded = seeding.screen_particles(problem, jax.random.key(0), 8, screen=4, chunk=64,
                                      seconds=60, until_dry=2)
    assert time.perf_counter() - started < 30
    assert seeded.screen.candidates > 32  # it screened on past the first 8 · 4
