"""Fidelity of the gradient model against the scene's own physics, and plan repair.

The scene here is written the way MuJoCo users write MJCF: default contact
parameters, friction, gravity. A box slides on the floor (four frictional
contacts under load) into a wall; one Newton iteration does not converge there.
"""

import numpy as np
import pytest

from mjstamp import solve, verify
from mjstamp.errors import MjstampError
from mjstamp.scenes import Scene, fidelity
from mjstamp.scenes.check import CheckSpec, check_scene
from mjstamp.solver import SolveConfig
from mjstamp.tasks import Task, costs

SLIDE = """
<mujoco model="slide">
  <option timestep="0.01"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <geom name="wall" type="box" pos="0.6 0 0.1" size="0.05 1 0.1"/>
    <site name="goal" pos="0.2 0.4 0" size="0.05"/>
    <body name="puck" pos="0 0 0.05">
      <joint name="px" type="slide" axis="1 0 0"/>
      <joint name="py" type="slide" axis="0 1 0"/>
      <joint name="pz" type="slide" axis="0 0 1"/>
      <geom name="puck" type="box" size="0.05 0.05 0.05" mass="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""
HORIZON = 60
SPEC = CheckSpec(horizon=HORIZON, qvel_joints=("px", "py"), qvel_range=3.0)


def shots(scene, n=16, seed=0):
    rng = np.random.default_rng(seed)
    qpos0 = np.tile(scene.m.qpos0, (n, 1))
    qvel0 = np.zeros((n, scene.m.nv))
    qvel0[:, :2] = rng.uniform(-3, 3, (n, 2))
    return qpos0, qvel0


def test_calibration_converges_the_solver_on_a_frictional_scene():
    scene = Scene(SLIDE)
    cal = fidelity.calibrate(scene, *shots(scene), horizon=HORIZON, cache=False)
    # One iteration drifts by centimetres (0.1 m seen), far over the 2 mm tolerance.
    assert cal.before.iterations == 1 and cal.before.p95_m > 10 * cal.tolerance_m
    assert cal.faithful and cal.after.gradient == "implicit"
    assert cal.after.iterations == scene.m.opt.iterations  # the MJCF's own cap
    assert cal.after.p95_m <= 1e-9  # converged: the scene's own solver, to rounding
    assert cal.tolerance_m == pytest.approx(1e-3 * scene.length_scale)
    # Unrolled iterations get there too, with two or more.
    unrolled = fidelity.calibrate(scene, *shots(scene), horizon=HORIZON, cache=False,
                                  candidates=fidelity.UNROLLED)
    assert unrolled.faithful and unrolled.after.iterations >= 2


def test_calibration_keeps_one_iteration_where_it_is_exact(billiards):
    qpos0, qvel0 = shots(billiards)
    cal = fidelity.calibrate(billiards, qpos0, qvel0, horizon=150, cache=False)
    assert cal.faithful and cal.after.iterations == 1 and len(cal.tried) == 1


def test_calibration_out_of_budget_is_reported_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(fidelity, "CACHE", tmp_path)
    scene = Scene(SLIDE)
    cal = fidelity.calibrate(scene, *shots(scene), horizon=HORIZON, max_iterations=1)
    assert not cal.faithful
    msg = cal.message()
    assert "\n" not in msg and "cannot be made faithful" in msg and "'slide'" in msg
    assert f"{cal.tolerance_m:.2g} m" in msg and f"{cal.after.p95_m:.2g} m" in msg
    # Cached by the model and the inputs: the second call reads the file.
    again = fidelity.calibrate(scene, *shots(scene), horizon=HORIZON, max_iterations=1)
    assert again.cached and again.after == cal.after and len(list(tmp_path.iterdir())) == 1


def slide_task():
    task = Task("slide", Scene(SLIDE), horizon=HORIZON)
    task.box("v", low=[-3, -3], high=[3, 3], initial_qvel=("px", "py"))
    task.contact("wall", "puck", "wall")
    task.cost("goal", costs.reach("puck", ["goal"]))
    task.success(costs.reaches("puck", {"goal": "goal"}, radius=0.1))
    return task


def test_solve_refuses_an_unfaithful_scene_before_it_starts():
    with pytest.raises(MjstampError) as e:
        solve(slide_task(), {"particles": 8, "calibration.max_solver_iterations": 1},
              progress=False)
    msg = str(e.value)
    assert "\n" not in msg and "cannot be made faithful" in msg and "allow_unfaithful" in msg


def test_solve_config_names_unknown_and_bad_settings():
    with pytest.raises(MjstampError) as e:
        SolveConfig.from_dict({"svgd_iters": 3})
    msg = str(e.value)
    assert "'svgd_iters'" in msg and "did you mean 'stamp.svgd_max_iters'" in msg
    assert "valid:" in msg and "particles" in msg and "\n" not in msg
    assert SolveConfig.from_dict({"horizon": 5}, ignore={"horizon": 5}) == SolveConfig()
    for bad in ({"particles": 1}, {"stamp.svgd_step": 0}, {"verify.repair": "yes"},
                {"stamp.jacobian": "x"}, {"stamp.svgd_max_iters": 2.5},
                {"calibration.fidelity_tolerance": -1.0}, {"screen.rescue_near": 1.5},
                {"screen.rescue_near": float("nan")}, {"screen.rescue_near": True},
                {"screen.cost_scale": 0}, {"screen.cost_scale": "hot"},
                {"screen.cost_scale": True}, {"screen.cost_scale": float("inf")}):
        with pytest.raises(MjstampError, match=next(iter(bad)).replace(".", r"\.")):
            SolveConfig.from_dict(bad)
    assert SolveConfig(screen={"cost_scale": 2.5}).screen.cost_scale == 2.5
    assert SolveConfig().screen.cost_scale == "auto"
    # Caps a user would accept, not 1000 + 1000.
    assert SolveConfig().stamp.svgd_max_iters + SolveConfig().stamp.sgd_max_iters <= 200


@pytest.mark.slow
def test_check_fails_for_one_iteration_on_a_frictional_scene():
    """The check must not call a one-iteration model healthy where it drifts."""
    report = check_scene(Scene(SLIDE), particles=8, spec=SPEC, calibrate=False)
    assert not report["healthy"] and not report["faithful"]
    assert any("diverges from the scene's own physics" in p for p in report["problems"])
    assert report["calibrated"]["faithful"] and report["calibrated"]["gradient"] == "implicit"


@pytest.mark.slow
@pytest.mark.parametrize("gradient,iterations", [("unrolled", 4), ("implicit", 100)])
def test_gradients_through_the_solver_match_the_scene_physics(gradient, iterations):
    """Reverse mode through 4 unrolled iterations, or implicit, against differences in C.

    The reference is MuJoCo C with the MJCF's own solver (100 iterations, warm
    start), not the gradient model. Tolerance 1e-5 on the median: float64 central
    differences with eps = 1e-6 are good to ~1e-9 on smooth stretches (1e-9 seen),
    and a few particles straddle a contact event, where both are only piecewise.
    """
    scene = Scene(SLIDE, gradient=gradient, iterations=iterations)
    report = check_scene(scene, particles=8, spec=SPEC, calibrate=False)
    assert report["healthy"], report["problems"]
    assert report["nonfinite"] == 0
    assert report["physics_divergence_p95_m"] <= report["tolerance_m"]
    assert report["rel_err_median"] < 1e-5


@pytest.mark.slow
def test_repair_turns_a_perturbed_plan_into_one_that_verifies():
    task = slide_task().build()
    task = task.on_scene(task.scene.with_grad_options(gradient="implicit", iterations=100))
    # A shot that slides into the goal, from a MuJoCo C sweep of the box.
    axis = np.linspace(-3, 3, 41)
    grid = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2)
    ok = verify.decode(task, verify.simulate_c(task, grid), grid).ok
    assert ok.any()
    good = grid[np.flatnonzero(ok)[ok.sum() // 2]]
    # Turned until it misses.
    for angle in np.linspace(0.1, 1.0, 10):
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        bad = (turn @ good)[None]
        if not verify.decode(task, verify.simulate_c(task, bad), bad).ok[0]:
            break
    else:
        raise AssertionError("no turn of the shot misses the goal")
    fix = verify.repair(task, bad, np.array(["0-goal"]), rounds=8, samples=32, seed=0)
    assert fix.repaired[0]
    assert verify.decode(task, verify.simulate_c(task, fix.theta), fix.theta).ok[0]
    assert fix.rollouts <= 1 + 8 * 32


@pytest.mark.slow
def test_implicit_forward_values_are_the_converged_solvers():
    """The implicit model steps exactly as MJX's own solver loop: same trips, same values."""
    scene = Scene(SLIDE)
    qpos0, qvel0 = shots(scene, n=4)
    runs = [
        np.asarray(scene.with_grad_options(gradient=g, iterations=100)
                   .rollout_fn(HORIZON, fields=("qpos",))(qpos0, qvel0)["qpos"])
        for g in ("implicit", "unrolled")
    ]
    np.testing.assert_array_equal(runs[0], runs[1])
    with pytest.raises(MjstampError, match="needs solver='newton'"):
        Scene(SLIDE, gradient="implicit", solver="cg")
    with pytest.raises(MjstampError, match="gradient='exact' is not valid; valid: unrolled"):
        Scene(SLIDE, gradient="exact")


def test_divergence_sees_a_body_that_swings_about_its_own_origin():
    """A pendulum hinged at its body's origin: the origin stays put, its rod does not."""
    import mujoco

    m = mujoco.MjModel.from_xml_string("""
    <mujoco><worldbody><body name="arm" pos="0 0 1">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02"/>
    </body></worldbody></mujoco>""")
    rest, swung = np.zeros((1, 1, 1)), np.full((1, 1, 1), 0.5)
    div = fidelity.divergence(fidelity.tracked_points(m, swung), fidelity.tracked_points(m, rest))
    # The capsule's centre (and the COM), 0.25 m below the hinge, moves by
    # 0.25·(sin 0.5, 0, 1 − cos 0.5); the divergence is the largest coordinate.
    np.testing.assert_allclose(div, 0.25 * np.sin(0.5), rtol=1e-9)


def test_the_last_candidate_is_the_scenes_own_solver_warm_start_and_line_search_included():
    xml = SLIDE.replace('<option timestep="0.01"/>', '<option timestep="0.01" ls_iterations="17"/>')
    scene = Scene(xml)
    assert fidelity.CANDIDATES[-1] == ("implicit", None, None)
    cal = fidelity.calibrate(scene, *shots(scene), horizon=HORIZON, cache=False,
                             candidates=fidelity.CANDIDATES[-1:])
    own = cal.tried[-1]
    assert (own.gradient, own.iterations, own.ls_iterations, own.warmstart) == (
        "implicit", scene.m.opt.iterations, 17, True)
    assert own.p95_m == 0.0  # its C twin is the scene's own physics, bit for bit
    assert cal.as_dict()["warmstart"] is True
    # A scene without a warm start keeps it off in that candidate.
    cold = Scene(xml.replace('ls_iterations="17"/>',
                             'ls_iterations="17"><flag warmstart="disable"/></option>'))
    again = fidelity.calibrate(cold, *shots(cold), horizon=HORIZON, cache=False,
                               candidates=fidelity.CANDIDATES[-1:])
    assert again.tried[-1].warmstart is False and again.tried[-1].ls_iterations == 17
