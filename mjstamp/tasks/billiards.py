"""Billiards (STAMP §V-A1, App. B), written with the public task API.

θ = (vx, vy), the cue ball's initial velocity. The task plan is which walls the
cue ball touches before it first touches the target ball (bits for the top,
bottom, left and right walls, as in the paper's Fig. 3), plus the pocket the
target ball enters.

Choices (and why):
- velocity box [-4, 4]² m/s: fast enough for two or three cushions within the
  horizon, slow enough that no contact lasts less than about 4 steps;
- horizon 150 steps of 10 ms: in 1.5 s a MuJoCo C sweep of the box finds 8
  wall codes (16 task plans) that pocket the target; a longer horizon finds
  more codes but costs more per iteration;
- soft wall indicators with α = 100 /m, β = 0: an indicator is 1/2 at touching
  distance and saturates within about 5 cm, wider than one step of travel at
  4 m/s, so the indicator is smooth in θ;
- costs: β_aim · L_aim (softmin gap to the target ball up to first contact)
  + β_target · L_target (softmin over time of the squared distance of the
  target ball to the nearer pocket, so passing through a pocket counts, as the
  success predicate does);
- softmin temperatures 0.2 m (aim) and 0.02 m² (target): with App. B-D's
  sharper softmin, a shot that leaves the target behind has its smallest gap
  at t = 0, where the gap does not depend on θ, and its particle stalls (about
  half of them did at 0.02 m); 0.2 m lets later, closer passes pull;
- 128 particles, at most 40 SVGD then 80 SGD iterations (Adam, 0.05 then
  0.02): SVGD spreads the particles over the modes, and the long SGD phase
  lets the narrow modes (0.05-0.3% of the box each) converge; a shorter SGD
  phase or a sharper aim softmin verifies fewer wall codes.
"""

from __future__ import annotations

from mjstamp.registry import register
from mjstamp.scenes import Scene
from mjstamp.tasks import costs
from mjstamp.tasks.task import Task

WALLS = ("wall_top", "wall_bottom", "wall_left", "wall_right")  # paper's 1-4
POCKETS = {"top": "pocket_top", "bottom": "pocket_bottom"}


def default_config() -> dict:
    """Settings of the billiards task."""
    return {
        "horizon": 150,
        "velocity_bound": 4.0,
        "pocket_radius": 0.1,
        "alpha": 100.0,
        "beta": 0.0,
        "aim_weight": 20.0,
        "target_weight": 200.0,
        "aim_temperature": 0.2,
        "target_temperature": 0.02,
    }


def solve_config() -> dict:
    """Settings of its solve (the rest are `SolveConfig`'s defaults)."""
    return {
        "particles": 128,
        "stamp": {
            "svgd_learning_rate": 0.05,
            "sgd_learning_rate": 0.02,
            "svgd_max_iters": 40,
            "sgd_max_iters": 80,
            "min_iters": 20,
            "jacobian": "fwd",  # d = 2 tangents beat 1 + 4 pullbacks through the rollout
        },
    }


@register("billiards", default_config,
          "bank the cue ball off walls to pocket the target (Fig. 7)", solve_config=solve_config)
def make(config: dict) -> Task:
    """Builds the billiards task from its settings (see `default_config`)."""
    scene = Scene.shipped("billiards")
    task = Task(
        "billiards", scene, horizon=config["horizon"], settings=config,
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
    task.display(trace=("cue", "target"))
    return task
