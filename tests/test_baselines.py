"""Baselines on the tiny task; compare's and the CLI's bad input; CMA-ES on a test function."""

import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp import baselines, verify
from mjstamp.baselines.common import constrained_logdensity, empty_spec
from mjstamp.baselines.compare import compare
from mjstamp.cli import main
from mjstamp.errors import MjstampError

ROOT = Path(__file__).resolve().parent.parent
SMALL = {"particles": 8, "stamp.sgd_max_iters": 40}
SETTINGS = {"enumerate": {"starts": 8}, "blocking": {"starts": 8}, "cem": {"population": 32},
            "cmaes": {"population": 8}}


@pytest.fixture(scope="module")
def tiny(tiny_task):
    return tiny_task()


@pytest.mark.parametrize("method", ["enumerate", "blocking", "cem", "cmaes"])
def test_each_baseline_finds_a_plan_that_verifies(tiny, method):
    r = baselines.run(method, tiny, target=1, cap_s=300, seed=0, config=SMALL,
                      **SETTINGS[method])
    assert r.reached and len(r.found) == 1 and r.time_to(1) <= r.wall_s
    # Replayed anew in MuJoCo C, the plan succeeds with the task plan reported.
    theta = np.asarray([r.found[0]["theta"]])
    decoded = verify.decode(tiny, verify.simulate_c(tiny, theta), theta)
    assert decoded.ok[0] and decoded.plan[0] == r.found[0]["task_plan"]
    assert r.summary()["distinct_verified_task_plans"] == 1


def test_blocking_finds_both_task_plans_and_blocks_what_it_found(tiny):
    from mjstamp.baselines.methods import Blocks

    r = baselines.run("blocking", tiny, target=2, cap_s=300, seed=1, config=SMALL, starts=8)
    assert r.reached
    assert sorted(r.task_plans) == ["0-goal", "1-goal"]
    # The next run's penalty holds exactly the task plans found, each once.
    problem = tiny.build()
    spec = Blocks(problem, np.float64).spec(r.found)
    assert spec["blocked_on"].sum() == 2
    blocked = sorted("".join(str(int(b)) for b in row)
                     for row, on in zip(spec["blocked"], spec["blocked_on"], strict=True) if on)
    assert blocked == sorted(f["code"] for f in r.found) == ["0", "1"]


# The tiny table with two motors: a discrete choice of which way to drive the puck
# ("left" or "right") for the first 5 steps, then a velocity box on top.
MOTORS = '<actuator><motor joint="px" gear="1"/><motor joint="py" gear="1"/></actuator>'


def _discrete_task(tiny_mjcf):
    from mjstamp.scenes import Scene
    from mjstamp.tasks import Task, costs

    xml = tiny_mjcf().replace("</mujoco>", MOTORS + "\n</mujoco>")
    task = Task("tiny-drive", Scene(xml, name="tiny-drive"), horizon=30)
    task.box("v", low=[-1, -1], high=[1, 1], initial_qvel=("px", "py"))
    task.discrete("drive", ("left", "right"), phases=1)
    push = jnp.asarray([[-2.0, 0.0], [2.0, 0.0]])

    def controls(params):
        force = jnp.einsum("npo,oj->nj", params["drive"], push)  # (n, 2)
        on = (jnp.arange(30) < 5).astype(force.dtype)
        return on[None, :, None] * force[:, None, :]

    task.controls(controls)
    task.cost("goal", costs.reach("puck", ["goal"]), weight=50.0)
    task.success(costs.reaches("puck", {"goal": "goal"}, radius=0.15))
    return task


@pytest.mark.parametrize("method", ["enumerate", "blocking", "cem", "cmaes"])
def test_baselines_handle_discrete_actions(tiny_xml, method):
    task = _discrete_task(tiny_xml)
    r = baselines.run(method, task, target=1, cap_s=300, seed=0, config=SMALL,
                      **SETTINGS[method])
    assert r.reached, r.summary()
    f = r.found[0]
    assert f["task_plan"].split("-")[0] in ("left", "right")
    assert f["action_ids"] in (((0,),), ((1,),))


def test_cmaes_finds_both_task_plans_of_the_tiny_task(tiny):
    """Restarts go on after the first plan, and the Tracker keeps every one it verifies."""
    r = baselines.run("cmaes", tiny, target=2, cap_s=300, seed=0, population=8)
    assert r.reached and sorted(r.task_plans) == ["0-goal", "1-goal"], r.summary()
    found_at = [f["found_at_s"] for f in r.found]
    assert found_at == sorted(found_at) and found_at[-1] <= r.wall_s
    for f in r.found:
        theta = np.asarray([f["theta"]])
        decoded = verify.decode(tiny, verify.simulate_c(tiny, theta), theta)
        assert decoded.ok[0] and decoded.plan[0] == f["task_plan"]


def test_cmaes_minimises_an_ill_conditioned_rotated_ellipsoid():
    """CMA-ES learns a rotated ellipsoid of condition 10^6 (Hansen 2016's test function).

    With its covariance frozen (learning rates 0) it stays above 1e-12 for 1500 generations.
    """
    from mjstamp.baselines.evolution import CMAES

    n = 8
    rng = np.random.default_rng(0)
    rotation, _ = np.linalg.qr(rng.standard_normal((n, n)))
    scales = 10.0 ** (6 * np.arange(n) / (n - 1))

    def f(x):
        return np.sum(scales * (x @ rotation.T) ** 2, axis=-1)

    es = CMAES(np.full(n, 3.0), 1.0, 12, rng)
    for _ in range(1500):
        es.tell(f(es.ask()))
        if f(es.mean) < 1e-12:
            break
    assert f(es.mean) < 1e-12, (es.generation, f(es.mean))
    assert es.condition > 1e4  # it learnt the ellipsoid's shape, not only a step size


def test_mirror_folds_the_line_into_the_unit_interval():
    from mjstamp.baselines.evolution import mirror

    inside = np.linspace(0, 1, 11)
    np.testing.assert_allclose(mirror(inside), inside)
    np.testing.assert_allclose(mirror(np.array([-0.2, 1.3, 2.25, -1.75, 3.5])),
                               [0.2, 0.7, 0.25, 0.25, 0.5], atol=1e-12)
    u = np.random.default_rng(1).normal(0, 10, 1000)
    v = mirror(u)
    assert np.all((v >= 0) & (v <= 1))
    np.testing.assert_allclose(mirror(u + 2.0), v, atol=1e-9)  # period 2
    np.testing.assert_allclose(mirror(-u), v, atol=1e-12)  # even


def test_blocking_penalty_is_the_soft_probability_of_the_blocked_plan(tiny):
    """−Δ log ρ = w · Π_k (s_k or 1 − s_k) for a blocked code, by hand from the symbols."""
    problem = tiny.build()
    theta = jnp.asarray([[1.5, 0.2], [-1.0, 1.0], [0.3, -0.4]])
    dtype = theta.dtype
    plain = constrained_logdensity(problem, symbol_weight=0.0, block_weight=0.0)
    blocked = constrained_logdensity(problem, symbol_weight=0.0, block_weight=7.0)
    spec = {k: jnp.asarray(v) for k, v in empty_spec(problem, 4, dtype).items()}
    spec["blocked"] = spec["blocked"].at[0].set(1.0).at[1].set(0.0)
    spec["blocked_on"] = spec["blocked_on"].at[0].set(1.0).at[1].set(1.0)
    r, _ = problem.evaluate(theta, hard=True)
    s = np.asarray(r.symbols["wall"])
    expected = 7.0 * (s + (1.0 - s))  # plan "1" and plan "0" both blocked: they sum to 1
    np.testing.assert_allclose(plain(theta, spec) - blocked(theta, spec), expected, rtol=1e-9,
                               atol=1e-9)
    spec["blocked_on"] = spec["blocked_on"].at[1].set(0.0)
    np.testing.assert_allclose(plain(theta, spec) - blocked(theta, spec), 7.0 * s, rtol=1e-9,
                               atol=1e-9)
    want = dict(spec, blocked_on=jnp.zeros(4), want=jnp.ones(1), want_on=jnp.ones(()))
    asked = constrained_logdensity(problem, symbol_weight=3.0, block_weight=0.0)
    np.testing.assert_allclose(plain(theta, want) - asked(theta, want), 3.0 * (s - 1.0) ** 2,
                               rtol=1e-9, atol=1e-9)


def _no_symbols(tiny_mjcf):
    from mjstamp.scenes import Scene
    from mjstamp.tasks import Task, costs

    task = Task("plain", Scene(tiny_mjcf(), name="tiny"), horizon=20)
    task.box("v", low=[-2, -2], high=[2, 2], initial_qvel=("px", "py"))
    task.cost("goal", costs.reach("puck", ["goal"]))
    return task


def test_enumerate_needs_symbols_or_actions(tiny_xml):
    task = _no_symbols(tiny_xml)
    with pytest.raises(MjstampError, match="no contact symbols and no discrete actions"):
        baselines.run("enumerate", task, target=1, cap_s=10)
    with pytest.raises(MjstampError, match="no contact symbols and no discrete actions"):
        compare(lambda: (task, None), methods=["stamp", "enumerate"], seeds=1, cap_s=10)


@pytest.mark.parametrize("call, needle", [
    (lambda t: baselines.run("astar", t), "unknown method 'astar'; valid: enumerate"),
    (lambda t: baselines.run("cem", t, target=0, cap_s=10), "target=0 must be an integer"),
    (lambda t: baselines.run("cem", t, target=1, cap_s=0), "cap_s=0 must be a number"),
    (lambda t: baselines.run("cem", t, target=1, cap_s=1, population=1), "population=1"),
    (lambda t: baselines.run("cmaes", t, target=0, cap_s=10), "target=0 must be an integer"),
    (lambda t: baselines.run("cmaes", t, target=1, cap_s=0), "cap_s=0 must be a number"),
    (lambda t: baselines.run("cmaes", t, target=1, cap_s=1, population=2), "population=2"),
    (lambda t: baselines.run("cmaes", t, target=1, cap_s=1, sigma0=1.5), "sigma0=1.5"),
    (lambda t: baselines.run("cmaes", t, target=1, cap_s=1, max_population=4),
     "max_population=4 must be an integer >= 32"),
    (lambda t: compare(lambda: (t, None), seeds=0), "seeds=0 must be an integer >= 1"),
    (lambda t: compare(lambda: (t, None), cap_s=-5), "cap=-5 must be a number"),
    (lambda t: compare(lambda: (t, None), methods="stamp,lgp"), "unknown method 'lgp'"),
])
def test_bad_baseline_input_is_one_line(tiny, call, needle):
    with pytest.raises(MjstampError) as e:
        call(tiny)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_cli_names_every_method():
    from mjstamp.baselines.compare import ALL
    from mjstamp.cli import METHODS

    assert METHODS == ALL


def test_every_package_is_installed():
    """A package missing from pyproject's list is absent from a non-editable install."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "packages"])
    found = {str(p.parent.relative_to(ROOT)).replace("/", ".")
             for p in (ROOT / "mjstamp").rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)


@pytest.mark.parametrize("argv, needle", [
    (["compare", "billiards", "--methods", "stamp,astar"], "unknown method 'astar'"),
    (["compare", "billiards", "--seeds", "0"], "seed count 0 must be >= 1"),
    (["compare", "billiards", "--cap", "0"], "cap 0 must be a finite number of seconds"),
    (["compare", "billiards", "--cap", "nan"], "must be a finite number"),
    (["compare", "nosuch"], "unknown task 'nosuch'"),
    (["compare", "billiards", "--set", "stamp.svgd_max_iters=x"], "expected int"),
])
def test_bad_compare_flags_are_one_line(argv, needle, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


@pytest.mark.slow
def test_table1_runs_on_a_tiny_setting():
    import json

    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.paper.table1", "--tasks", "billiards", "--seeds", "1",
         "--cap", "20", "--devices", "1", "--set", "particles=8", "--set", "stamp.svgd_max_iters=3",
         "--set", "stamp.sgd_max_iters=3", "--set", "screen.candidates=1", "--json"],
        capture_output=True, text=True, timeout=1500, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(proc.stdout.strip().splitlines()[-1])["billiards"]
    assert set(rows) == {"stamp", "enumerate", "blocking", "cem"}
    assert rows["stamp"]["factor"] == pytest.approx(1.0)
    target = rows["stamp"]["target"][0]
    for m, row in rows.items():
        for key in ("runtime_mean_s", "runtime_std_s", "factor", "factor_std",
                    "distinct_verified", "reached"):
            assert key in row, (m, key)
        assert row["target"] == [target]
        found, reached = row["distinct_verified"][0], row["reached"][0]
        assert (found == target) if reached else (found < target), (m, row)
