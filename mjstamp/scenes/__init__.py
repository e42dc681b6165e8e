"""Scenes: MJCF models, batched differentiable MJX rollouts, MuJoCo C replay.

What it is for: everything about one MJCF scene and its physics: `Scene` (the
MjModel, its gradient model and MJX twin, names resolved once), batched
rollouts and their C replay, the gradient-safe patch of MJX's solver
(`gradsafe`: finite, faithful gradients, unrolled or implicit), signed
distances of geom pairs, what MJX cannot collide (`collisions`), the fidelity
of the gradient model (`fidelity`) and the check of a scene (`check`).

What it may import: mujoco, mujoco.mjx, jax, numpy, the optional
`mujoco_menagerie` (inside `Scene.menagerie` only), and of mjstamp only
`errors`, `fileio` and `kinematics`; never tasks, solvers or figures.
"""

from mjstamp._mjx import mjx
from mjstamp.scenes.rollout import FIELDS, build_rollout, replay
from mjstamp.scenes.scene import (
    GradOptions,
    Scene,
    menagerie_model_path,
    package_model_path,
    shipped_models,
)

__all__ = [
    "FIELDS",
    "GradOptions",
    "Scene",
    "build_rollout",
    "menagerie_model_path",
    "mjx",
    "package_model_path",
    "replay",
    "shipped_models",
]
