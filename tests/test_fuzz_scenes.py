"""Fuzzed scenes (tests/stress/fuzz.py): a random valid MJCF builds a Scene or is refused in a line.

Plus one regression test per crash the fuzzer found, each on the smallest
scene that shows it.
"""

import json
import pathlib
import subprocess
import sys
import tempfile

import mujoco
import pytest
from hypothesis import HealthCheck, given, settings

# The generator lives in tests/stress/ (not in the engine): import it from the repository root.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from mjstamp.errors import MjstampError  # noqa: E402
from mjstamp.scenes import Scene  # noqa: E402
from mjstamp.scenes.check import CheckSpec, parameterisation  # noqa: E402
from tests.stress.fuzz import (  # noqa: E402 - after the path set-up above
    CHECK_ARGS,
    build_scene,
    classify_check,
    generic_task,
    mjcf_scenes,
    random_mjcf,
    scene_mjcf,
    solve_in_process,
)

SEED = 0  # the fixed seed of the slow CLI and solve tests


def _scene(option: str = "", joints: str = '<joint type="slide"/>') -> str:
    return f"""
<mujoco>
  <option {option}/>
  <worldbody>
    <body pos="0 0 0.2">{joints}<geom type="sphere" size="0.1"/></body>
  </worldbody>
</mujoco>"""


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mjcf_scenes())
def test_random_scene_builds_or_is_refused_in_one_line(xml):
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "scene.xml"
        path.write_text(xml)
        try:
            Scene(path)
        except MjstampError as e:
            message = str(e)
            assert message.strip() and "\n" not in message, repr(message)
            assert message.startswith(str(path)), message  # names the file first


def test_generator_is_deterministic_and_varied():
    import numpy as np

    assert scene_mjcf(3, 7) == scene_mjcf(3, 7)
    assert random_mjcf(np.random.default_rng(1)) != random_mjcf(np.random.default_rng(2))
    text = "".join(scene_mjcf(0, i) for i in range(60))
    for needle in ('type="free"', 'type="ball"', 'type="slide"', 'type="hinge"',
                   'type="plane"', 'type="sphere"', 'type="capsule"', 'type="ellipsoid"',
                   'type="cylinder"', 'type="box"', 'type="mesh"', 'type="hfield"',
                   "<mesh ", "<motor ", "<position ", "<pair ", "solimp=", "condim="):
        assert needle in text, needle


def test_classify_check_rejects_what_it_must():
    status = "[check] compiling\nWARNING: Inertia matrix is too close to singular\n"
    assert classify_check(2, "", status + "mjstamp: error: a.xml: bad\n")[0] == "rejected"
    assert classify_check(2, "", "mjstamp: error: a.xml: bad\nmore\n")[0] == "crash"
    assert classify_check(2, "", "usage: mjstamp\n")[0] == "crash"
    tb = "Traceback (most recent call last):\n  File x\nValueError: boom\n"
    assert classify_check(1, "{}", tb) == ("crash", "traceback on stderr: ValueError: boom", True)
    assert classify_check(0, '{"healthy": true}', status)[0] == "ok"
    assert classify_check(1, '{"problems": ["p"]}', status)[:2] == ("unhealthy", "p")
    assert classify_check(0, "not json", "")[0] == "crash"
    assert classify_check(-9, "", "")[0] == "crash"


# Regression tests, one per crash found by `python -m tests.stress.fuzz`.


def test_discrete_integrator_is_refused_in_one_line():
    # Found by the fuzzer: mjx.put_model accepts integrator="discrete" (an
    # mjx IntegratorType), but mjx.step raised NotImplementedError at the first
    # rollout step, a traceback out of `mjstamp check`.
    with pytest.raises(MjstampError) as e:
        Scene(_scene('integrator="discrete"'))
    assert str(e.value) == (
        "MJCF string: <option integrator='discrete'> is not supported by MJX 3.17; valid: "
        "Euler, RK4, implicitfast"
    )
    for ok in ("Euler", "RK4", "implicitfast"):
        Scene(_scene(f'integrator="{ok}"'))


def test_check_varies_unnamed_joints():
    # Found by the fuzzer: `check` of a scene whose joints have no names (as a
    # hand-written scene often has) refused it, "has no joints or actuators to vary".
    scene = Scene(_scene(joints='<joint type="slide"/><joint type="hinge" axis="0 1 0"/>'))
    draws = parameterisation(scene, CheckSpec(horizon=5))
    assert draws.dim == 2


@pytest.mark.slow
def test_cli_check_on_generated_scenes_exits_cleanly():
    """`mjstamp check --particles 4` (console script) on the first 2 scenes of SEED that build."""
    script = pathlib.Path(sys.executable).with_name("mjstamp")
    checked = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(100):
            path = pathlib.Path(tmp) / f"scene_{i}.xml"
            path.write_text(scene_mjcf(SEED, i))
            if build_scene(path)[0] != "ok":
                continue
            proc = subprocess.run([str(script), "check", str(path), *CHECK_ARGS],
                                  capture_output=True, text=True, timeout=1200)
            assert proc.returncode in (0, 1, 2), (i, proc.returncode, proc.stderr[-2000:])
            assert "Traceback" not in proc.stderr, (i, proc.stderr[-2000:])
            if proc.returncode == 2:
                errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("mjstamp:")]
                assert len(errors) == 1 and errors[0].startswith("mjstamp: error: "), errors
            else:
                assert json.loads(proc.stdout)["particles"] == 4
            checked.append(i)
            if len(checked) == 2:
                break
    assert len(checked) == 2


def test_task_declares_unnamed_joints_by_id():
    # Found by the fuzzer's tiny solve: a task on a scene whose joints have no names
    # could not name them; `initial_qvel=(0,)` raised TypeError ('int' object is not
    # subscriptable) and (0, 1) was read as one (joint, k) pair.
    from mjstamp.tasks import Task

    scene = Scene(_scene(joints='<joint type="slide"/><joint type="hinge" axis="0 1 0"/>'))
    task = Task("t", scene, horizon=5)
    task.box("a", low=[-1, -1], high=[1, 1], initial_qvel=(0, 1))
    task.box("b", low=[-1], high=[1], initial_qvel=(1,))
    task.box("c", low=[-1], high=[1], initial_qvel=1)
    task.box("d", low=[-1], high=[1], initial_qpos=[(0, 0)])
    assert [v.qvel or v.qpos for v in task.variables] == [(0, 1), (1,), (1,), (0,)]
    for bad, match in (((1.5,), "entry 1.5 is not a joint; valid: a joint name or id"),
                       ((None,), "entry None is not a joint"),
                       ((True,), "entry True is not a joint"),
                       (1.5, "initial_qvel=1.5 is not a sequence of joints"),
                       ((2,), "unknown joint 2 .*valid: an id in 0..1$"),
                       (("x",), "unknown joint 'x' .*valid: an id in 0..1$")):
        with pytest.raises(MjstampError, match=match) as e:
            Task("t", scene, horizon=5).box("v", low=[-1], high=[1], initial_qvel=bad)
        assert "\n" not in str(e.value)
    # A free joint's coordinates by id, and the one-pair shorthand of a single one.
    free = Scene(_scene(joints="<freejoint/>"))
    task = Task("t", free, horizon=5)
    task.box("v", low=[-1] * 3, high=[1] * 3, initial_qvel=[(0, 0), (0, 1), (0, 5)])
    task.box("w", low=[-1], high=[1], initial_qvel=(0, 4))
    assert [v.qvel for v in task.variables] == [(0, 1, 5), (4,)]


def test_generic_task_declares_on_any_joints():
    # The fuzzer's tiny-solve task: unnamed joints by id, a free joint's vx and vy.
    scene = Scene(_scene(joints='<joint type="slide"/><joint type="hinge" axis="0 1 0"/>'))
    task = generic_task(scene)
    assert task.dim == 2 and task.variables[0].qvel == (0, 1) and task.horizon == 20
    assert generic_task(Scene(_scene(joints="<freejoint/>"))).variables[0].qvel == (0, 1)
    assert generic_task(Scene(_scene(joints=""))) is None


@pytest.mark.slow
def test_tiny_solve_on_a_generated_scene():
    """The fuzzer's tiny solve on the first scene of SEED that builds and has a joint."""
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(100):
            path = pathlib.Path(tmp) / f"scene_{i}.xml"
            path.write_text(scene_mjcf(SEED, i))
            if build_scene(path)[0] == "ok" and Scene(path).m.njnt:
                break
        outcome, message, had_traceback = solve_in_process(path)
    # N.B. a one-line MjstampError is a legitimate refusal (solve_in_process
    # classifies a several-line one as a crash); anything else is a bug.
    assert outcome in ("ok", "rejected"), (i, message)
    assert not had_traceback


def test_ground_is_not_told_to_become_a_body_geom():
    # Found by the fuzzer: an hfield-cylinder pair was told "make geom 'ground' a
    # sphere, capsule, ellipsoid or cylinder"; the terrain is not what to change.
    xml = """
<mujoco>
  <asset><hfield name="h" nrow="2" ncol="2" size="1 1 0.1 0.1" elevation="0 0 0 0"/></asset>
  <worldbody>
    <geom name="ground" type="hfield" hfield="h"/>
    <body pos="0 0 0.3"><freejoint/><geom name="can" type="cylinder" size="0.1 0.1"/></body>
  </worldbody>
</mujoco>"""
    with pytest.raises(MjstampError) as e:
        Scene(xml)
    message = str(e.value)
    assert "hfield-cylinder is not collided" in message
    assert "make geom 'can' a sphere, capsule, box or mesh" in message
    assert "make geom 'ground'" not in message


def test_impedance_past_the_solimp_width_has_finite_gradients():
    # Found by the fuzzer: 3 of the first 6 random scenes that `check` compiled had
    # NaN gradients from a solimp with a fractional power ("... 1.287"): MJX's
    # impedance forms (1 - x) ** power for rows deeper than the width (x > 1),
    # then discards it; gradsafe clamps that base at 0 (culprit 5).
    import jax
    import jax.numpy as jnp
    import numpy as np
    from mujoco.mjx._src import constraint

    scene = Scene(_scene())  # applies gradsafe.patch_mjx()
    solref = jnp.array([0.02, 1.0])
    dmax, width = 0.95, 0.001
    for power in (1.287, 2.0, 1.0):
        solimp = jnp.array([0.9, dmax, width, 0.5, power])

        def imp(pos, solimp=solimp):
            return constraint._kbi(scene.mx, solref, solimp, pos)[2]

        for pos in (-0.01, -0.0007, -0.0003, 0.0, 0.0004, 0.002):
            value, grad = jax.value_and_grad(imp)(jnp.asarray(pos))
            assert np.isfinite(grad), (power, pos, grad)
            x = abs(pos) / width
            if x > 1:
                assert value == dmax and grad == 0
            else:  # MuJoCo's impedance curve (modeling.html#solver-parameters)
                y = x**power / 0.5 ** (power - 1) if x < 0.5 else (
                    1 - (1 - x) ** power / 0.5 ** (power - 1))
                np.testing.assert_allclose(value, 0.9 + y * (dmax - 0.9), rtol=1e-12)


def test_c_twin_drops_what_mjx_ignores():
    # Found by the fuzzer: on a scene with noslip_iterations="1", `check` measured
    # MJX 0.99 m from the scene's physics but calibrated on the C twin m_grad,
    # which ran the noslip solver MJX lacks (0.07 m). Sleeping is the same.
    xml = _scene('noslip_iterations="3"').replace(
        '<option noslip_iterations="3"/>',
        '<option noslip_iterations="3"><flag sleep="enable"/></option>')
    scene = Scene(xml)
    sleep = int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    assert scene.m.opt.noslip_iterations == 3 and scene.m.opt.enableflags & sleep
    assert scene.m_grad.opt.noslip_iterations == 0
    assert not scene.m_grad.opt.enableflags & sleep
    other = scene.with_grad_options(iterations=2)
    assert other.m_grad.opt.noslip_iterations == 0
