"""The task API on a tiny scene, billiards decoding and verification, result files."""

import json

import numpy as np
import pytest

from mjstamp import registry, results, seeding, verify
from mjstamp.cli import main
from mjstamp.errors import MjstampError
from mjstamp.scenes import Scene
from mjstamp.tasks import Task, costs
from mjstamp.tracecache import cached_jit


def test_declaration_errors_name_the_culprit(tiny_xml):
    xml = tiny_xml()
    task = Task("tiny", Scene(xml, name="tiny"), horizon=10)
    with pytest.raises(MjstampError, match="unknown geom 'nope'.*valid: floor, wall, puck"):
        task.contact("c", "puck", "nope")
    with pytest.raises(MjstampError, match="'plane'.*'floor'.*'plane'|plane.*plane"):
        Task("t", Scene(xml.replace('type="box"', 'type="plane"')), horizon=5).contact(
            "c", "floor", "wall")
    with pytest.raises(MjstampError, match=r"low < high.*low=\[1.0\], high=\[0.0\]"):
        task.box("b", low=[1], high=[0])
    with pytest.raises(MjstampError, match="2 coordinates but initial_qvel names 1"):
        task.box("b", low=[0, 0], high=[1, 1], initial_qvel=("px",))
    with pytest.raises(MjstampError, match="unknown joint 'pz'"):
        task.box("b", low=[0], high=[1], initial_qvel=("pz",))
    task.box("v", low=[0], high=[1])
    with pytest.raises(MjstampError, match="'v' is already declared"):
        task.box("v", low=[0], high=[1])
    with pytest.raises(MjstampError, match="weight=-1"):
        task.cost("c", costs.reach("puck", ["goal"]), weight=-1)
    with pytest.raises(MjstampError, match="declares no costs"):
        task.check()


def test_cost_names_are_looked_up_where_the_cost_is_declared(tiny_xml):
    """A misspelt body or site fails at `Task.cost` / `Task.success`, not at solve time."""
    task = Task("tiny", Scene(tiny_xml(), name="tiny"), horizon=10)
    with pytest.raises(MjstampError) as e:
        task.cost("c", costs.reach("pukc", ["goal"]))
    msg = str(e.value)
    assert "task 'tiny': cost 'c': unknown body 'pukc'" in msg and "puck" in msg
    assert "\n" not in msg and not task.costs
    with pytest.raises(MjstampError, match="success: unknown site 'gaol'.*valid: goal"):
        task.success(costs.reaches("puck", {"g": "gaol"}, radius=0.1))
    with pytest.raises(MjstampError, match="cost 'a': unknown geom 'cue'"):
        task.cost("a", costs.aim("cue", "puck"))
    task.cost("c", costs.reach("puck", ["goal"]))
    assert callable(task.costs[0].fn) and not isinstance(task.costs[0].fn, costs.Bound)


def test_registry_errors():
    assert "billiards" in registry.names()
    with pytest.raises(MjstampError, match="unknown task 'nope'; valid: billiards"):
        registry.load("nope")
    with pytest.raises(MjstampError, match="no setting 'bogus'"):
        registry.load("billiards", bogus=1)


def test_a_task_setting_named_like_a_solve_setting_is_refused(monkeypatch):
    """An override could not say which of the two it meant (billiards' β did once)."""
    from mjstamp.config import SolveConfig

    registry.names()  # the built-in tasks registered before the registry is copied
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    registry.register("clash", lambda: {"particles": 3, "speed": 1.0})(lambda settings: None)
    with pytest.raises(MjstampError) as e:
        registry.load("clash")
    msg = str(e.value)
    assert "'clash'" in msg and "'particles'" in msg and "solve setting" in msg
    assert "\n" not in msg
    for name in registry.names():
        if name != "clash":
            assert not set(registry.default_config(name)) & set(SolveConfig.fields()), name


@pytest.fixture(scope="module")
def billiards_task():
    return registry.load("billiards")[0]


# Hand-made shots from the cue ball at (-0.5, -0.2) towards the target at (0.3, 0):
# straight at it, and at its mirror image behind the top wall (ball centres
# bounce at y = 0.5 - R = 0.46, so the image is at y = 0.92).
STRAIGHT = np.array([0.8, 0.2]) / np.hypot(0.8, 0.2) * 2.0
OFF_TOP = np.array([0.8, 1.12]) / np.hypot(0.8, 1.12) * 2.0
# Shots found by a MuJoCo C sweep of the box that pocket the target ball.
POCKETING = {
    "0000-top": [2.71356784, 0.62311558],
    "0000-bottom": [3.1959799, 0.94472362],
    "1000-bottom": [1.70854271, 2.75376884],
    "0100-top": [2.59296482, -2.99497487],
}


@pytest.mark.slow
def test_billiards_decodes_hand_made_shots(billiards_task):
    shots = np.array([STRAIGHT, OFF_TOP, *POCKETING.values()])
    for simulate in (verify.simulate_c, verify.simulate_mjx):
        decoded = verify.decode(billiards_task, simulate(billiards_task, shots), shots)
        assert decoded.code[0] == "0000" and decoded.code[1] == "1000"
        assert not decoded.ok[:2].any()  # neither pockets the target
        assert list(decoded.plan[2:]) == list(POCKETING)
        assert decoded.ok[2:].all()


@pytest.mark.slow
def test_billiards_contacts_match_mujoco_contact_list(billiards_task):
    """Contacts read off poses equal MuJoCo's own contact list, step by step."""
    import mujoco

    m = billiards_task.scene.m
    shot = np.array([POCKETING["1000-bottom"]])
    replay = verify.simulate_c(billiards_task, shot)
    d = mujoco.MjData(m)
    d.qvel[:2] = shot[0]
    cue, top = billiards_task.scene.geom("cue"), billiards_task.scene.geom("wall_top")
    touching = []
    for _ in range(billiards_task.horizon):
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)  # contacts of the state after the step
        touching.append(any({c.geom1, c.geom2} == {cue, top} for c in d.contact[: d.ncon]))
    assert any(touching)
    np.testing.assert_array_equal(replay.contact("cue", "wall_top")[0], touching)


@pytest.mark.slow
def test_tiny_task_solves_and_results_round_trip(tmp_path, tiny_task, monkeypatch):
    from mjstamp import solve
    from mjstamp.solver import outcome as solve_mod

    labels = []  # what the solve compiles, by the label its compile reports carry

    def spy(fn, key, *example, label=None):
        labels.append(label)
        return cached_jit(fn, key, *example, label=label)

    monkeypatch.setattr(solve_mod, "cached_jit", spy)
    task = tiny_task()
    config = {"particles": 8, "stamp": {"svgd_max_iters": 15, "sgd_max_iters": 15, "min_iters": 5,
                                        "svgd_learning_rate": 0.05, "sgd_learning_rate": 0.05,
                                        "rescue_window": 3}}
    result = solve(task, config, seed=0, progress=False)
    # Two functions roll the scene out (issue 12): the evaluation both STAMP phases share
    # (θ is 2-D: both differentiate forward mode) and the final evaluation; on a CPU the
    # polish in MJX is off by default (`solve.polish_iterations`), its step not compiled.
    assert sorted(labels) == ["final", "stamp-sgd-update", "stamp-svgd-evaluate",
                              "stamp-svgd-update"]
    summary = result.summary()
    assert set(summary["compiles"]["rollouts"]) <= {"jit(stamp-svgd-evaluate)", "jit(final)"}
    assert summary["particles"] == 8 and summary["task"] == "tiny"
    assert summary["symbol_disagreements"] == 0  # C decodes the wall as the JAX sd < 0 does
    # β "auto" from the screen's costs, and the log posterior STAMP sampled used it.
    assert summary["cost_scale"] == seeding.auto_cost_scale(seeding.Screen(**summary["screen"]))
    assert result.problem.cost_scale == summary["cost_scale"]
    rescue = summary["rescue"]  # the stall rescue's report: re-draws, task plans before/after
    assert rescue["redraws"] == int(result.stamp.rescued.sum())
    assert [sum(c.values()) for c in rescue["task_plan_counts"].values()] == [8, 8]
    loss = summary["loss"]  # the cost at the start, after SVGD and at the end (MJX, at Γ)
    assert loss["particles"] == 8 and loss["mean"]["final"] < loss["mean"]["initial"]
    assert result.theta.shape == (8, 2)
    # Reaching the goal pays: the mean cost fell over the run (`loss` above). N.B. the last
    # iterate's log density need not be higher: SGD returns each particle's best point.
    written = result.save(tmp_path, figures=False)
    assert {p.name for p in written} == {
        "plans.json", "particles.npz", "trajectories.npz", "scene.mjb"}
    assert results.load_model(tmp_path).ngeom == result.task.scene.m.ngeom
    loaded, arrays = results.load(tmp_path)
    assert loaded == json.loads(json.dumps({"schema_version": results.SCHEMA_VERSION, **summary}))
    for name, data in result.arrays().items():
        for key, value in data.items():
            np.testing.assert_array_equal(arrays[name][key], value, err_msg=f"{name}.{key}")
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


def test_results_directory_errors(tmp_path):
    with pytest.raises(MjstampError, match="no plans.json"):
        results.load(tmp_path)
    (tmp_path / "plans.json").write_text(json.dumps({"schema_version": 0}))
    with pytest.raises(MjstampError, match="schema_version 0; this mjstamp reads 3"):
        results.load(tmp_path)


def test_solve_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    cases = [
        (["solve", "nope"], "unknown task 'nope'; valid: billiards"),
        (["solve", "billiards", "--set", "horizon=abc"], "--set horizon='abc': expected int"),
        (["solve", "billiards", "--set", "nokey=1"], "--set 'nokey': task 'billiards' has no"),
        (["solve", "billiards", "--particles", "1"], "--particles=1 must be >= 2"),
        (["solve", "billiards", "--out", str(blocker / "sub")], "is not writable"),
    ]
    for argv, expected in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expected in err[0], (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_format_table_text_and_markdown():
    summary = {
        "task": "t", "particles": 8, "wall_time_s": 1.25, "returned_plans": 3,
        "verified_fraction": 2 / 3, "distinct_verified_task_plans": 1,
        "distinct_verified_codes": 1, "declaration": {"symbols": ["a"]},
        "task_plans": [
            {"task_plan": "1-goal", "plans": 2, "verified": 2, "repaired": 1, "best_cost": 0.5,
             "verified_share": 1.0},
            {"task_plan": "0 (failed)", "plans": 1, "verified": 0, "best_cost": None,
             "verified_share": 0.0},
        ],
    }
    text = results.format_table(summary).splitlines()
    assert text[0] == ("task t: 8 particles, 1.2 s; 3 plans returned, 67% verified in "
                       "MuJoCo C")
    assert text[1].split() == ["task", "plan", "plans", "found", "verified", "repaired", "best",
                               "cost", "verified", "share"]
    assert text[3].split() == ["1-goal", "2", "2", "1", "0.5", "100%"]
    # Results files written before repair existed have no "repaired" counts.
    assert text[4].split() == ["0", "(failed)", "1", "0", "0", "-", "0%"]
    assert text[5] == "distinct verified task plans: 1 (symbol codes: 1)"
    md = results.format_table(summary, markdown=True)
    assert "| `1-goal` | 2 | 2 | 1 | 0.5 | 100% |" in md.splitlines()
    summary["declaration"]["symbols"] = []
    assert results.format_table(summary).endswith("distinct verified task plans: 1")
    summary.update(repaired_plans=1, fidelity={
        "iterations": 2, "mjx_divergence_p95_m": 1e-9, "tolerance_m": 2e-3, "faithful": True})
    assert results.format_table(summary).splitlines()[-2:] == [
        "distinct verified task plans: 1; 1 plans verified only after repair in MuJoCo C",
        "gradient model: unrolled (2 solver iterations); MJX vs MuJoCo C divergence p95 "
        "1e-09 m (tolerance 0.002 m)",
    ]
    # A solve's summary also says how the particles fared and what SVGD did for the cost.
    summary.update(verified_particle_share=0.25, rescue={"redraws": 3}, loss={
        "mean": {"initial": 10.0, "svgd": 6.0, "final": 2.0}, "svgd_share": 0.5})
    assert results.format_table(summary).splitlines()[-1] == (
        "particles: 25% end as verified plans; mean cost 10 at the start, 6 after SVGD, 2 at "
        "the end (SVGD: 50% of the decrease); 3 stalled particles re-drawn")


def test_loss_report_by_hand():
    from mjstamp.solver import loss_report

    nan = float("nan")
    costs = {"initial": np.array([10.0, 8.0, nan, 6.0]), "svgd": np.array([7.0, 5.0, 1.0, 3.0]),
             "final": np.array([1.0, 2.0, 0.0, 3.0])}
    out = loss_report(costs)  # particle 2 is left out: not finite at the start
    assert out["particles"] == 3
    assert out["mean"] == {"initial": 8.0, "svgd": 5.0, "final": 2.0}
    assert out["median"] == {"initial": 8.0, "svgd": 5.0, "final": 2.0}
    assert out["svgd_share"] == 0.5  # (8 - 5) / (8 - 2)
    costs["final"] = np.array([9.0, 9.0, 0.0, 9.0])  # the mean rose: no share to speak of
    assert loss_report(costs)["svgd_share"] is None
    assert loss_report({k: np.full(2, nan) for k in costs})["mean"]["final"] is None


def test_free_joint_coordinates_and_spatial_goals():
    xml = """<mujoco><worldbody><site name="goal" pos="0 0 1" size="0.05"/>
      <body name="ball" pos="0 0 0.1"><freejoint name="free"/>
      <geom name="ball" type="sphere" size="0.05"/></body></worldbody></mujoco>"""
    task = Task("free", Scene(xml), horizon=5)
    task.box("v", low=[-1, -1, 0], high=[1, 1, 2],
             initial_qvel=(("free", 0), ("free", 1), ("free", 2)))
    task.box("spin", low=[-1], high=[1], initial_qvel=[("free", 5)])
    assert task.variables[0].qvel == (0, 1, 2) and task.variables[1].qvel == (5,)
    with pytest.raises(MjstampError, match="joint 'free' has 6 qvel coordinates; index 6"):
        task.box("bad", low=[0], high=[1], initial_qvel=[("free", 6)])
    task.cost("up", costs.reach("ball", ["goal"], axes=(0, 1, 2)))
    task.success(costs.reaches("ball", {"goal": "goal"}, radius=0.1, axes=(0, 1, 2)))
    theta = np.array([[0.0, 0.0, 0.0, 0.0]])
    replay = verify.simulate_c(task, theta)
    ok, _ = task.success_fn(replay)
    assert not ok[0]  # 0.9 m below the goal, though right under it in x-y


@pytest.mark.slow
def test_composed_log_posterior_gradient_matches_finite_differences(tiny_task):
    """The gradient of the whole log ρ (rollout, symbols, costs, bounds) vs differences.

    Both on the same MJX model in float64. Tolerance 1e-5 relative: differences
    with eps = 1e-6 are good to ~1e-9 on smooth stretches, and the soft
    indicator and softmin are smooth; particles are drawn away from contact.
    """
    import jax
    import jax.numpy as jnp

    problem = tiny_task(horizon=30).build()
    theta = jnp.asarray([[-1.2, 0.9], [0.4, -0.8], [1.5, 0.3]])

    def total(th):
        return jnp.sum(problem.logdensity(th)[0])

    grad = np.asarray(jax.jit(jax.grad(total))(theta))
    logp = jax.jit(lambda th: problem.logdensity(th)[0])
    eps = 1e-6
    fd = np.zeros_like(grad)
    for j in range(2):
        step = jnp.zeros_like(theta).at[:, j].set(eps)
        fd[:, j] = (np.asarray(logp(theta + step)) - np.asarray(logp(theta - step))) / (2 * eps)
    assert np.all(np.isfinite(grad)) and np.abs(grad).max() > 1e-3
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-7)


def test_with_cost_scale_scales_the_log_posterior_and_its_trace_key(tiny_task, monkeypatch):
    import jax
    import jax.numpy as jnp

    from mjstamp.solver import outcome as solve_mod
    from mjstamp.solver import problem_jit

    problem = tiny_task(horizon=30).build()
    hot = problem.with_cost_scale(3.0)
    theta = jnp.asarray([[-1.2, 0.9], [0.4, -0.8], [1.5, 0.3]])
    base = np.asarray(jax.jit(lambda th: problem.logdensity(th)[0])(theta))
    scaled = np.asarray(jax.jit(lambda th: hot.logdensity(th)[0])(theta))
    assert np.all(base < 0)
    np.testing.assert_allclose(scaled, 3.0 * base, rtol=1e-12)
    assert problem.cost_scale == 1.0 and hot.with_cost_scale(1.0).cost_scale == 1.0
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="cost_scale"):
            problem.with_cost_scale(bad)
    keys = []
    monkeypatch.setattr(solve_mod, "cached_jit",
                        lambda fn, key, *example, label=None: keys.append(key))
    for p in (problem, hot, problem.with_cost_scale(1.0)):
        problem_jit(p)(lambda t: t, "probe", np.zeros(2))
    assert keys[0] == keys[2] != keys[1]  # β is a constant of the trace: part of its key


def test_fingerprint_follows_the_declaration(tiny_task):
    """Same declaration, same key (a re-run); any change of code or constant, a new one."""
    a, b = tiny_task(), tiny_task()
    assert a.fingerprint() == b.fingerprint()
    assert tiny_task(weight=51.0).fingerprint() != a.fingerprint()
    assert tiny_task(radius=0.2).fingerprint() != a.fingerprint()  # a closure constant

    def declare(scale):
        task = tiny_task()
        task.cost("extra", lambda r: scale * r.body_pos("puck")[:, -1, 0])
        return task

    assert declare(1.0).fingerprint() == declare(1.0).fingerprint()
    assert declare(2.0).fingerprint() != declare(1.0).fingerprint()
    other = tiny_task()
    other.cost("extra", lambda r: 1.0 * r.body_pos("puck")[:, -1, 1])  # other code
    assert other.fingerprint() != declare(1.0).fingerprint()
    # Building is memoised while nothing changes, and is redone after a change.
    assert a.build() is a.build()
    first = a.build()
    a.prior("p", lambda params: -jnp_sum(params["v"]))
    assert a.build() is not first and a.build().fingerprint != first.fingerprint


def jnp_sum(x):
    import jax.numpy as jnp

    return jnp.sum(x**2, axis=1)


def test_problem_is_frozen_and_kernels_can_be_replaced(tiny_task):
    import dataclasses

    from mjstamp import svgd

    task = tiny_task()
    problem = task.build()
    with pytest.raises(dataclasses.FrozenInstanceError):
        problem.horizon = 3
    assert problem.symbols == ("wall",) and problem.dim == 2 and not problem.has_actions
    kernel = svgd.rbf()
    task.use_kernel(kernel)
    assert task.build().kernel is kernel
    task.use_kernel(lambda p: svgd.feature_kernel(svgd.rbf(), include_inputs=False))
    assert isinstance(task.build().kernel, svgd.FeatureKernel)
    with pytest.raises(MjstampError, match="kernel weight 'angle'.*valid: continuous"):
        task.use_kernel(weights={"angle": 2.0})
