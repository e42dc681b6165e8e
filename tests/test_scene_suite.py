"""The scene suite (examples/suite): user-style MJCF, tasks, C replays, ground-truth tools.

Fast checks run no MJX compile: MJCF compiles in MuJoCo C, each scene keeps
MuJoCo's defaults, each task declares, a handful of C replays decode (the
decoder's small kinematics function is the only JIT). The slow test runs
benchmarks/studies/scene_suite.py end to end on the smallest scene with tiny settings.
"""

import importlib.util
import json
import pathlib
import re
import subprocess
import sys

import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import collision_driver
from mujoco.mjx._src.types import GeomType

from mjstamp import modes, verify
from mjstamp.baselines import sampling
from mjstamp.errors import MjstampError

ROOT = pathlib.Path(__file__).parents[1]
SUITE_DIR = ROOT / "examples" / "suite"
XMLS = sorted(SUITE_DIR.glob("*.xml"))


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"suite_{name}", SUITE_DIR / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


suite = _load("tasks")
examples = _load("examples")


@pytest.fixture(scope="module")
def tasks():
    """Every suite task, built once (Scene construction puts the MJX model, no compile)."""
    return {name: make() for name, make in suite.SUITE.items()}


def _task(tasks, name):
    return tasks[name]


def test_suite_has_the_scenes_the_issue_asks_for(tasks):
    """>= 6 scenes: a free-joint ball on a plane, motor-driven hinges, a pusher, a cylinder."""
    assert len(XMLS) >= 6 and sorted(p.stem for p in XMLS) == sorted(suite.SUITE)
    G, J = mujoco.mjtGeom, mujoco.mjtJoint

    def kinds(task):
        m = task.scene.m
        symbol_types = {int(m.geom_type[g]) for c in task.contacts for g in (c.geom1, c.geom2)}
        hinge_motor = any(m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
                          and m.jnt_type[m.actuator_trnid[a, 0]] == J.mjJNT_HINGE
                          for a in range(m.nu))
        free_ball = any(m.jnt_type[j] == J.mjJNT_FREE and any(
            m.geom_type[g] == G.mjGEOM_SPHERE for g in range(m.ngeom)
            if m.geom_bodyid[g] == m.jnt_bodyid[j]) for j in range(m.njnt))
        actuated = {int(m.jnt_bodyid[m.actuator_trnid[a, 0]]) for a in range(m.nu)}
        free_bodies = {int(m.jnt_bodyid[j]) for j in range(m.njnt) if m.jnt_type[j] == J.mjJNT_FREE}
        return {
            "3-D ball": free_ball and G.mjGEOM_PLANE in m.geom_type,
            "hinge motors": hinge_motor and task.controls_fn is not None,
            "pusher": task.controls_fn is not None and bool(free_bodies - actuated),
            "cylinder or mesh symbol": bool(symbol_types & {G.mjGEOM_CYLINDER, G.mjGEOM_MESH}),
        }

    built = [t for t in tasks.values() if not isinstance(t, MjstampError)]
    found = {k for task in built for k, v in kinds(task).items() if v}
    assert found == {"3-D ball", "hinge motors", "pusher", "cylinder or mesh symbol"}


@pytest.mark.parametrize("path", XMLS, ids=lambda p: p.stem)
def test_scene_is_plain_user_style_mjcf(path):
    """Compiles in MuJoCo C with default contacts, gravity on, dt in [2, 10] ms, MJX pairs."""
    text = path.read_text()
    assert text.lstrip().startswith("<!--"), "every scene starts with a comment saying what it is"
    assert not re.search(r"\bsol(ref|imp)\s*=", text), "contact parameters: MuJoCo's defaults"
    assert not re.search(r"\bgravity\s*=", text), "gravity stays MuJoCo's default (on)"
    assert 'condim="1"' not in text, "friction stays on"
    m = mujoco.MjModel.from_xml_path(str(path))
    assert 0.002 <= m.opt.timestep <= 0.01
    np.testing.assert_allclose(m.opt.gravity, [0, 0, -9.81])
    for g1, g2, _ in collision_driver.geom_pairs(m):
        t1, t2 = GeomType(m.geom_type[g1]), GeomType(m.geom_type[g2])
        assert collision_driver.has_collision_fn(t1, t2), f"MJX cannot collide {t1.name}-{t2.name}"


@pytest.mark.parametrize("name", list(suite.SUITE))
def test_task_declares_with_the_public_api(tasks, name):
    """Each task declares: box θ, symbols, a cost, a success predicate, a 1-4 s horizon."""
    task = _task(tasks, name)
    task.check()
    seconds = task.horizon * task.scene.m.opt.timestep
    assert 1.0 <= seconds <= 4.0 + 1e-9
    assert all(v.kind == "box" for v in task.variables)
    assert task.contacts and task.success_fn is not None
    assert all(t.weight == 1.0 for t in task.costs), "no per-scene cost weights"


def test_tasks_leave_planner_settings_to_the_library():
    """No temperature, sharpness, weight, step size or iteration count in the suite's tasks."""
    code = (SUITE_DIR / "tasks.py").read_text()
    for word in ("alpha=", "beta=", "temperature=", "weight=", "learning_rate", "iters"):
        assert word not in code, word


@pytest.mark.parametrize("name", list(suite.SUITE))
def test_c_replays_decode_and_stay_stable(tasks, name):
    """A handful of uniform shots replay in MuJoCo C, stay finite and bounded, and decode."""
    task = _task(tasks, name)
    theta = modes.uniform_theta(task, 6, np.random.default_rng(0))
    replay = verify.simulate_c(task, theta)
    decoded = verify.decode(task, replay, theta)
    assert np.isfinite(replay.qpos).all() and np.isfinite(replay.qvel).all()
    speed = np.linalg.norm(np.diff(replay.xpos, axis=1), axis=-1) / task.scene.m.opt.timestep
    assert speed.max() < 20.0  # no blow-up: every body stays below 20 m/s
    assert decoded.bits.shape == (6, len(task.contacts)) and len(decoded.plan) == 6
    # Controls of the replay are what the task's controls function gives in numpy.
    assert replay.ctrl.shape == (6, task.horizon, task.scene.m.nu)


@pytest.mark.parametrize("name", list(suite.SUITE))
def test_examples_reach_the_task_plans_they_promise(tasks, name):
    """Hand-checked shots, one per main task plan, succeed in MuJoCo C with that plan."""
    task = _task(tasks, name)
    shots = examples.EXAMPLES[name]
    assert len({plan for _, plan in shots}) >= 2, "each scene has several modes"
    theta = np.array([t for t, _ in shots])
    decoded = verify.decode(task, verify.simulate_c(task, theta), theta)
    assert decoded.ok.all()
    assert list(decoded.plan) == [plan for _, plan in shots]


def test_monte_carlo_counts_and_is_seeded(tasks):
    """Shares add up to the success share; the same seed gives the same modes."""
    task = tasks["pendulum_bells"]
    a = modes.monte_carlo(task, shots=96, seed=3, chunk=40, cache=False, progress=False)
    b = modes.monte_carlo(task, shots=96, seed=3, chunk=96, cache=False, progress=False)
    assert a["method"] == "uniform" and a["shots"] == 96
    assert a["modes"] == b["modes"]  # draws depend on the seed, not the chunking
    assert sum(m["count"] for m in a["modes"]) == round(a["success_share"] * 96)
    assert sum(m["share"] for m in a["modes"]) == pytest.approx(a["success_share"])
    cov = modes.coverage([a["modes"][0]["task_plan"]], a, min_share=0.0)
    assert cov["coverage"] == pytest.approx(1 / len(a["modes"])) and cov["method"] == "uniform"


def test_ground_truth_prints_lines_without_a_terminal(tasks, capsys):
    """A sweep written to a log says how far it is (the default progress, no TTY)."""
    modes.monte_carlo(tasks["pendulum_bells"], shots=60, seed=0, chunk=20, cache=False)
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("[modes]")]
    assert len(lines) == 3 and "40/60 shots replayed" in lines[-1]


def test_random_search_stops_in_its_wall_time(tasks):
    """random_search counts only shots that finished within the budget."""
    task = tasks["pendulum_bells"]
    out = sampling.random_search(task, 3.0, seed=0, chunk=16)
    assert 0 < out["wall_s"] <= 3.0 and out["shots"] % 16 == 0 and out["shots"] > 0
    assert set(out["task_plans"]) == set(out["found_at_s"])
    assert all(0 <= t <= 3.0 for t in out["found_at_s"].values())
    with pytest.raises(Exception, match="wall_s"):
        sampling.random_search(task, 0.0)


@pytest.mark.slow
def test_scene_suite_runs_end_to_end(tmp_path):
    """benchmarks/studies/scene_suite.py on the smallest scene, tiny settings, prints its JSON."""
    cmd = [sys.executable, str(ROOT / "benchmarks" / "studies" / "scene_suite.py"), "--scenes",
           "pendulum_bells", "--particles", "4", "--shots", "200", "--json",
           "--set", "stamp.svgd_max_iters=2", "--set", "stamp.sgd_max_iters=2",
           "--set", "stamp.min_iters=1"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=True)
    report = json.loads(out.stdout)
    (row,) = report["scenes"]
    required = {"physics_divergence_before_m", "physics_divergence_after_m",
                "verified_particle_share", "returned", "verified", "repaired",
                "task_plans_found", "coverage_all", "coverage_min_share",
                "random_task_plans", "wall_s"}
    assert required <= set(row)
    assert row["scene"] == "pendulum_bells" and row["particles"] == 4
    assert 0 <= row["verified"] <= row["returned"] <= 4
    assert row["random_task_plans"] >= 0 and row["wall_s"] > 0
    # Sharded as `mjstamp solve` shards (one host device per core), with issue 11's targets.
    assert report["devices"] >= 1
    met = row["targets_particles"]
    assert set(met) == {"verified_particle_share", "at_least_random", "twice_random"}
    assert met["at_least_random"] == (row["task_plans_found"] >= row["random_task_plans"])
    # Issue 28: MJX itself against C at both ends, warnings and approximate pairs recorded.
    assert row["mjx_initial_judged_by"] in ("tolerance", "chaos", "none")
    assert row["mjx_final_p95_m"] >= 0 and isinstance(row["fidelity_warnings"], list)
    assert set(row["targets_contacts"]) == {"accepted_without_warning", "faithful_initial",
                                            "faithful_at_end", "ad_rel_err"}
