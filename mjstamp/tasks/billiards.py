"""Billiards (STAMP §V-A1, App. B), written with the public task API.

θ = (vx, vy), the cue ball's initial velocity. The task plan is which walls the
cue ball touches before it first touches the target ball (bits for the top,
bottom, left and right walls, as in the paper's Fig. 3), plus the pocket the
target ball enters.

Choices (and why):
- velocity box [-4, 4]² m/s: fast enough for two or three cushions within the
  horizon, slow enough that no contact lasts less than about 4 steps;
- horizon 150 steps of 10 ms: 1.5 s covers every shot that pockets the target
  inside the box (a MuJoCo C sweep of the box finds none that needs longer);
- soft wall indicators with α = 100 /m, β = 0: an indicator is 1/2 at touching
  distance and saturates within about 5 cm, wider than one step of travel at
  4 m/s, so the indicator is smooth in θ;
- costs: β_aim · L_aim (softmin gap to the target ball up to first contact)
  + β_target · L_target (softmin over time of the squared distance of the
  target ball to the nearer pocket, so passing through a pocket counts, as the
  success predicate does);
- 128 particles: enough to seed every mode of the box at its feasible share;
  each costs 150 value-and-grad steps per iteration.
"""

from __future__ import annotations

from mjstamp.scenes import Scene
from mjstamp.tasks import costs, register
from mjstamp.tasks.task import Task

WALLS = ("wall_top", "wall_bottom", "wall_left", "wall_right")  # paper's 1-4
POCKETS = {"top": "pocket_top", "bottom": "pocket_bottom"}


def default_config() -> dict:
    """Defaults of the billiards task and of its solve."""
    return {
        "horizon": 150,
        "velocity_bound": 4.0,
        "pocket_radius": 0.1,
        "alpha": 100.0,
        "beta": 0.0,
        "aim_weight": 20.0,
        "target_weight": 200.0,
        "aim_temperature": 0.02,
        "target_temperature": 0.005,
        # solve
        "particles": 128,
        "svgd_learning_rate": 0.05,
        "sgd_learning_rate": 0.02,
        "svgd_max_iters": 60,
        "sgd_max_iters": 40,
        "min_iters": 20,
    }


@register("billiards", default_config, "bank the cue ball off walls to pocket the target (Fig. 7)")
def make(config: dict) -> Task:
    """Builds the billiards task from a config (see `default_config`)."""
    scene = Scene.shipped("billiards")
    task = Task(
        "billiards", scene, horizon=config["horizon"],
        description="hit the target ball into a right-hand pocket; "
        "task plan = walls the cue ball touches before the target ball",
    )
    v = config["velocity_bound"]
    task.box("cue_velocity", low=[-v, -v], high=[v, v], initial_qvel=("cue_x", "cue_y"))
    for wall in WALLS:
        task.contact(wall, "cue", wall, before=("cue", "target"),
                     alpha=config["alpha"], beta=config["beta"])
    task.cost("aim", costs.aim("cue", "target", temperature=config["aim_temperature"]),
              weight=config["aim_weight"])
    task.cost("target", costs.reach("target", list(POCKETS.values()),
                                    temperature=config["target_temperature"]),
              weight=config["target_weight"])
    task.success(costs.reaches("target", POCKETS, radius=config["pocket_radius"]))
    return task
