"""mjstamp.skills: goal-conditioned DMP skills learnt from demonstrations, and their bank.

What it is for: `fit` turns demonstrations into a DMP (a linear regression),
`rollout` plays it from any start to any goal at any speed (pure JAX,
differentiable, vmappable), a `SkillBank` keeps fitted skills in a versioned
file that is refitted when the code that made its demonstrations changes, and
`skills.pushing` records and fits the pushing demonstrations.

What it may import: jax, numpy, mujoco (recording demonstrations), and of
mjstamp only `errors` and `fileio`.

References:
  STAMP §III-C eq. (5) and §IV-C.
"""

from mjstamp.skills.bank import (
    FORMAT,
    FORMAT_VERSION,
    MissingSkillBank,
    SkillBank,
    StaleSkillBank,
    load,
    load_or_fit,
    save,
)
from mjstamp.skills.dmp import DMP, FRAMES, MIN_RK4_STEPS, DMPConfig, fit, rollout

__all__ = [
    "DMP",
    "FORMAT",
    "FORMAT_VERSION",
    "FRAMES",
    "MIN_RK4_STEPS",
    "DMPConfig",
    "MissingSkillBank",
    "SkillBank",
    "StaleSkillBank",
    "fit",
    "load",
    "load_or_fit",
    "rollout",
    "save",
]
