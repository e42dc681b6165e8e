"""Scenes: MJCF models, batched differentiable MJX rollouts, MuJoCo C replay."""

from mjstamp.scenes.rollout import FIELDS, build_rollout, replay
from mjstamp.scenes.scene import GradOptions, Scene, package_model_path, shipped_models

__all__ = [
    "FIELDS",
    "GradOptions",
    "Scene",
    "build_rollout",
    "package_model_path",
    "replay",
    "shipped_models",
]
