"""Test-session settings: the CLI's precision policy and the compilation cache.

N.B. `import mjstamp` sets nothing (STYLE.md); like the CLI, the test session
turns on float64 (see mjstamp.scenes.gradsafe) and JAX's persistent compilation
cache, so MJX functions compiled once (20-45 s each on 2 cores) are reused by
later runs and by CLI subprocesses.
"""

import pytest

import mjstamp

mjstamp.configure(precision="float64")


# The longest xdist groups (cold, 2-core CPU), started first so that neither worker is left
# with a long one at the end; every other group follows in collection order.
LONGEST_FIRST = ["04_robot_arm.ipynb", "03_skills_and_pushing.ipynb", "01_quickstart.ipynb",
                 "convex-cylinder-box", "convex-box-mesh", "convex-capsule-cylinder",
                 "convex-capsule-mesh", "convex-ellipsoid-ellipsoid", "convex-vs-c-cylinder-box",
                 "convex-vs-c-box-mesh", "convex-vs-c-capsule-cylinder",
                 "convex-vs-c-ellipsoid-ellipsoid", "02_new_task.ipynb"]


def _group(item) -> str:
    return next(iter(m.args[0] for m in item.iter_markers("xdist_group")), "")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items):
    """Under xdist (`--dist loadgroup`), each module's tests run in one worker.

    A module's compiled fixtures (module- or session-scoped scenes, rollouts,
    solves) are then built once, not once per worker. A test marked
    `xdist_group(NAME)` itself keeps that group (a long parametrised module can
    spread over both workers that way). The groups in LONGEST_FIRST go first.
    """
    for item in items:
        if not _group(item):
            item.add_marker(pytest.mark.xdist_group(item.path.name))
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(_group(item), len(rank)))  # stable: the rest in order


# A puck on a plane table with one wall and a goal site: small enough that its
# rollouts compile in seconds. Tests vary the wall's turn, the goal's place and
# size and the success radius through `tiny_task` (the MJCF alone: `tiny_xml`).
TINY = """
<mujoco model="tiny">
  <option timestep="0.02" gravity="0 0 0"/>
  <default><geom condim="1" solref="-5000 -5"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1" pos="0 0 -0.05" contype="0" conaffinity="0"/>
    <geom name="wall" type="box" pos="0.5 0 0" size="0.05 1 0.05" euler="0 0 {turn}"/>
    <site name="goal" pos="{goal_pos}" size="{goal_size}" rgba="0 0.8 0 1"/>
    <body name="puck">
      <joint name="px" type="slide" axis="1 0 0" damping="0.05"/>
      <joint name="py" type="slide" axis="0 1 0" damping="0.05"/>
      <geom name="puck" type="sphere" size="0.04" mass="0.2"/>
    </body>
  </worldbody>
</mujoco>
"""


def tiny_mjcf(*, turn=0.0, goal_size=0.02, goal_pos="-0.3 0.3 0") -> str:
    """The tiny scene's MJCF."""
    return TINY.format(turn=turn, goal_size=goal_size, goal_pos=goal_pos)


def make_tiny_task(*, horizon=40, turn=0.0, goal_size=0.02, goal_pos="-0.3 0.3 0", radius=0.1,
                   weight=50.0):
    """The tiny task: θ = the puck's velocity; symbol: the wall; goal: the site."""
    from mjstamp.scenes import Scene
    from mjstamp.tasks import Task, costs

    scene = Scene(tiny_mjcf(turn=turn, goal_size=goal_size, goal_pos=goal_pos), name="tiny")
    task = Task("tiny", scene, horizon=horizon)
    task.box("v", low=[-2, -2], high=[2, 2], initial_qvel=("px", "py"))
    task.contact("wall", "puck", "wall")
    task.cost("goal", costs.reach("puck", ["goal"]), weight=weight)
    task.success(costs.reaches("puck", {"goal": "goal"}, radius=radius))
    return task


def assert_same_plans(one: dict, two: dict, *, atol: float = 1e-12) -> None:
    """Two solves' summaries hold the same plans; costs and motion plans within `atol`."""
    import numpy as np

    assert one["verified"] == two["verified"]

    def rows(summary):  # each task plan's row; its best cost compared within atol below
        return [{k: v for k, v in r.items() if k != "best_cost"} for r in summary["task_plans"]]

    assert rows(one) == rows(two)
    for r, s in zip(one["task_plans"], two["task_plans"], strict=True):
        assert (r["best_cost"] is None) == (s["best_cost"] is None)
        assert r["best_cost"] is None or abs(r["best_cost"] - s["best_cost"]) <= atol
    assert [(p["particle"], p["task_plan"], p["verified"]) for p in one["plans"]] == [
        (p["particle"], p["task_plan"], p["verified"]) for p in two["plans"]]
    for p, q in zip(one["plans"], two["plans"], strict=True):
        assert abs(p["cost"] - q["cost"]) <= atol
        for name, value in p["motion_plan"].items():
            np.testing.assert_allclose(value, q["motion_plan"][name], rtol=0, atol=atol)


@pytest.fixture(scope="session")
def same_plans():
    """`assert_same_plans`, for tests."""
    return assert_same_plans


@pytest.fixture(scope="session")
def tiny_xml():
    """`tiny_mjcf`, the tiny scene's MJCF (a factory)."""
    return tiny_mjcf


@pytest.fixture(scope="session")
def tiny_task():
    """`make_tiny_task`, for tests (a factory: each call declares a fresh task)."""
    return make_tiny_task


@pytest.fixture(scope="session")
def billiards():
    """The shipped billiards scene, shared so its compiled rollouts are reused."""
    from mjstamp.scenes import Scene

    return Scene.shipped("billiards")


@pytest.fixture(scope="session")
def pushing():
    """The shipped pushing scene, shared so its compiled rollouts are reused."""
    from mjstamp.scenes import Scene

    return Scene.shipped("pushing")
