"""Robustness under uncertain physics (issue 16): declarations, scores, seeds."""

import numpy as np
import pytest

from mjstamp import verify
from mjstamp.errors import MjstampError


def _verified(task, n=600):
    """Verified plans of the tiny task, from uniform draws replayed in MuJoCo C."""
    theta = np.random.default_rng(0).uniform(-2, 2, (n, 2))
    dec = task.build().decode(verify.simulate_c(task, theta), theta)
    return theta[dec.ok], dec.plan[dec.ok]


def test_zero_uncertainty_scores_every_verified_plan_one(tiny_task):
    task = tiny_task()
    task.uncertain("friction", spread=0.0)
    theta, plan = _verified(task)
    assert len(theta) > 5
    rob = verify.robustness(task, theta, plan, samples=4)
    np.testing.assert_array_equal(rob.success, 1.0)
    np.testing.assert_array_equal(rob.same_plan, 1.0)


def test_edge_plan_scores_below_centred_and_seeds_reproduce(tiny_task):
    task = tiny_task()
    task.uncertain("position", ["puck"], spread=0.01)
    # A fan of shots at 1 m/s around the goal's direction: the one through the centre,
    # and the one whose path passes nearest 0.097 m from it (success radius 0.1 m).
    angles = np.deg2rad(135) + np.linspace(-0.3, 0.3, 241)
    fan = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    path = verify.simulate_c(task, fan).body_pos("puck")[..., :2]
    miss = np.linalg.norm(path - np.array([-0.3, 0.3]), axis=-1).min(axis=1)
    theta = fan[[int(np.argmin(miss)), int(np.argmin(np.abs(miss - 0.097)))]]
    one = verify.robustness(task, theta, samples=32, seed=3)
    two = verify.robustness(task, theta, samples=32, seed=3)
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


# Robust planning (part 3) ------------------------------------------------------------

def _shots(task, n=3):
    """Shots of 1 m/s fanned around the goal's direction, n of them."""
    angles = np.deg2rad(135) + np.linspace(-0.2, 0.2, n)
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def test_mjx_rollouts_in_drawn_models_match_mujoco_c_in_the_same_models(tiny_task):
    import jax.numpy as jnp

    from mjstamp.scenes import uncertainty
    from mjstamp.scenes.rollout import replay

    task = tiny_task()
    task.uncertain("friction", spread=0.5)
    task.uncertain("mass", spread=0.3)
    problem = task.build().with_robust(4, seed=1)
    draws, scene, k = problem.robust, problem.scene, 4
    assert {"geom_friction", "body_mass", "body_invweight0"} <= set(draws.fields)
    theta = _shots(task)
    n = len(theta)
    qpos0, qvel0, ctrl = (np.repeat(np.asarray(x, np.float64), k, axis=0)
                          for x in problem.inputs(jnp.asarray(theta, scene.dtype)))
    model = {f: np.tile(v, (n,) + (1,) * (v.ndim - 1)) for f, v in draws.fields.items()}
    rollout = scene.rollout_fn(problem.horizon, fields=("qpos",),
                               model_fields=tuple(sorted(model)))
    mjx_q = np.asarray(rollout(qpos0, qvel0, ctrl, model)["qpos"])
    models = uncertainty.sample(scene.m_grad, problem.uncertain, k, 1,
                                stream=uncertainty.PLAN_STREAM).models
    drawn = replay(scene, qpos0, qvel0, ctrl, solver="grad", models=models * n)["qpos"]
    nominal = replay(scene, qpos0, qvel0, ctrl, solver="grad")["qpos"]
    effect = np.abs(nominal - drawn).max(axis=(1, 2))
    error = np.abs(mjx_q - drawn).max(axis=(1, 2))
    assert effect.min() > 1e-3, effect  # the draws change the motion...
    assert (error < 0.05 * effect).all(), (error, effect)  # ...and MJX follows them


def test_robust_log_density_is_the_mean_cost_over_draws_and_cvar_the_worst(tiny_task):
    import jax
    import jax.numpy as jnp

    from mjstamp.scenes import uncertainty
    from mjstamp.scenes.rollout import replay

    task = tiny_task()
    task.uncertain("friction", spread=0.5)
    task.uncertain("position", ["puck"], spread=0.03)
    problem, k = task.build(), 4
    theta = jnp.asarray(_shots(task), problem.scene.dtype)
    mean = problem.with_robust(k, seed=2)
    worst = problem.with_robust(k, seed=2, cvar=1 / k)
    # By hand: each shot replayed in MuJoCo C in each of the same K drawn models.
    draws = uncertainty.sample(problem.scene.m_grad, problem.uncertain, k, 2,
                               stream=uncertainty.PLAN_STREAM)
    th = np.repeat(np.asarray(theta, np.float64), k, axis=0)
    qpos0, qvel0, ctrl = problem.inputs(th, xp=np)
    qpos0 = qpos0 + np.tile(draws.qpos_noise, (len(theta), 1))
    states = replay(problem.scene, qpos0, qvel0, ctrl, solver="grad",
                    models=draws.models * len(theta))
    r = verify.Replay(problem, states["qpos"], source="mujoco", qvel=states["qvel"], ctrl=ctrl)
    c = verify.cost_c(problem, r, th)
    c = c.reshape(len(theta), k)
    assert np.ptp(c, axis=1).min() > 0.05  # the draws matter to the cost
    np.testing.assert_allclose(-np.asarray(mean.logdensity(theta)[0]), c.mean(axis=1),
                               rtol=0.02)
    np.testing.assert_allclose(-np.asarray(worst.logdensity(theta)[0]), c.max(axis=1),
                               rtol=0.02)
    # No uncertainty: K copies of the nominal model, the nominal log density.
    still = tiny_task()
    still.uncertain("friction", spread=0.0)
    nominal = still.build()
    np.testing.assert_allclose(nominal.with_robust(k, seed=2).logdensity(theta)[0],
                               nominal.logdensity(theta)[0], rtol=1e-5)
    grad = jax.grad(lambda t: mean.logdensity(t)[0].sum())(theta)
    assert np.isfinite(np.asarray(grad)).all() and np.abs(np.asarray(grad)).max() > 0


def test_a_robust_solve_records_its_draws_and_keys_its_traces_by_them(tiny_task, monkeypatch):
    from mjstamp import solve
    from mjstamp.solver import outcome as solve_mod
    from mjstamp.solver import problem_jit

    config = {"particles": 8, "stamp": {"svgd_max_iters": 4, "sgd_max_iters": 4, "min_iters": 100},
              "robust.draws": 2, "verify.robustness_samples": 4}
    result = solve(tiny_task(), config, seed=0, progress=False)
    summary = result.summary()
    assert summary["robust_planning"]["samples"] == 2
    assert "geom_friction" in summary["robust_planning"]["fields"]
    assert summary["config"]["solve"]["robust"] == 2  # plans.json keeps the flat view
    one, two = result.problem, result.problem.with_robust(2, seed=1)
    assert one.robust.key() != two.robust.key()
    assert one.robust.key() == result.problem.with_robust(2, seed=0).robust.key()
    keys = []
    monkeypatch.setattr(solve_mod, "cached_jit",
                        lambda fn, key, *example, label=None: keys.append(key))
    for p in (one, two, one.with_robust(0, seed=0)):
        problem_jit(p)(lambda t: t, "probe", np.zeros(2))
    assert len(set(keys)) == 3  # the draws are constants of the trace: part of its key


@pytest.mark.parametrize(("setting", "expect"), [
    ({"robust.draws": -1}, "robust.draws=-1 must be an integer >= 0"),
    ({"robust": {"draws": 4, "cvar": 0}}, "robust.cvar=0 must be a number in (0, 1]"),
    ({"robust.draws": 4, "robust.cvar": 1.5}, "robust.cvar=1.5 must be a number in (0, 1]"),
])
def test_bad_robust_settings_give_one_line(setting, expect):
    from mjstamp.config import SolveConfig

    with pytest.raises(MjstampError) as e:
        SolveConfig.from_dict(setting)
    assert expect in str(e.value) and "\n" not in str(e.value)


def test_robust_cvar_without_robust_is_one_line(capsys):
    from mjstamp.cli import main

    assert main(["solve", "billiards", "--robust-cvar", "0.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["mjstamp: error: --robust-cvar=0.5 needs --robust K with K >= 1"]
    assert main(["solve", "billiards", "--robust", "0", "--robust-cvar", "0.5"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "mjstamp: error: --robust-cvar=0.5 needs --robust K with K >= 1"]
    for bad in ("0", "1.5", "nan"):
        assert main(["solve", "billiards", "--robust", "--robust-cvar", bad]) == 2
        assert capsys.readouterr().err.strip().splitlines() == [
            f"mjstamp: error: --robust-cvar={float(bad)} must be in (0, 1]: the share of the "
            "worst draws (1: the expected cost)"]


def test_robust_select_gives_each_task_plan_its_most_robust_candidates(tiny_task):
    """robust.select: the same task plans, each at least as robust on the selection draws."""
    from mjstamp import solve
    from mjstamp.scenes import uncertainty

    # N.B. polish and landing off: they move particles to the goal's centre, which leaves
    # the screen no more robust candidate to offer on this tiny goal.
    config = {"particles": 8, "screen.candidates": 16, "verify.robustness_samples": 16,
              "stamp": {"svgd_max_iters": 2, "sgd_max_iters": 2, "min_iters": 0},
              "polish.max_iters": 0, "landing.iterations": 0}
    task = tiny_task(goal_pos="0.2 0.3 0", radius=0.06)
    plain = solve(task, config, seed=0, progress=False)
    chosen = solve(task, {**config, "robust.select": 16}, seed=0, progress=False)

    def by_plan(result):
        ok = result.verified_mask()
        plans = result.verified.plan[ok]
        score = verify.robustness(task, result.theta[ok], samples=32, seed=0,
                                  stream=uncertainty.SELECT_STREAM).success
        return {p: sorted(score[plans == p], reverse=True) for p in set(plans)}

    before, after = by_plan(plain), by_plan(chosen)
    assert set(after) == set(before) and before
    for p in before:  # as many plans each, and the k-th best no worse
        assert len(after[p]) == len(before[p])
        assert all(a >= b for a, b in zip(after[p], before[p], strict=True)), p
    assert (chosen.source == "screen").any()  # the screen had more robust ones
    moved = chosen.source == "screen"
    assert not np.array_equal(chosen.theta[moved], plain.theta[moved])
    np.testing.assert_array_equal(chosen.theta[~moved], plain.theta[~moved])


@pytest.mark.parametrize(("argv", "select"), [
    (["--robust"], 64), (["--robust", "4"], 64), (["--robust", "0"], None),
    (["--robust", "--set", "robust.select=3"], 3), ([], None),
])
def test_robust_flag_also_selects_unless_told_otherwise(argv, select):
    from mjstamp.cli import build_parser
    from mjstamp.cli.solve import ROBUST_SELECT, _overrides

    assert ROBUST_SELECT == 64
    overrides = _overrides(build_parser().parse_args(["solve", "billiards", *argv]))
    assert overrides.get("robust.select") == select
