"""Poses of MuJoCo states by C kinematics: the one loop over `mj_kinematics`.

The C replay (`scenes.rollout.replay_model`'s pose fields), the fidelity
measure (`scenes.fidelity.tracked_points`) and the drawing of a plan
(`geometry.replay_frames`) all read their poses from `poses`. The planner's
own poses of a replay (MJX kinematics in the scene's precision, what decode and
the task's costs read) are `verify.replay.poses`.

Imports only mujoco and numpy, so that `scenes/` and `geometry` can both use it.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

__all__ = ["poses"]


def poses(m: mujoco.MjModel, qpos: np.ndarray, fields: Sequence[str]) -> dict[str, np.ndarray]:
    """`mujoco.MjData` fields after `mj_kinematics` at each configuration, float64.

    Args:
      m: the model.
      qpos: (..., nq) configurations.
      fields: names of `MjData` fields that kinematics sets (xpos, xipos,
        xquat, xmat, geom_xpos, geom_xmat, site_xpos, site_xmat, ...).

    Returns:
      {field: (..., *shape)} with `shape` that of the `MjData` field
      (`xmat`: (nbody, 9), as MuJoCo stores it).
    """
    qpos = np.asarray(qpos, np.float64)
    batch = qpos.shape[:-1]
    flat = qpos.reshape(-1, m.nq)
    d = mujoco.MjData(m)
    out = {f: np.empty((len(flat), *getattr(d, f).shape)) for f in fields}
    for k, q in enumerate(flat):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        for f, values in out.items():
            values[k] = getattr(d, f)
    return {f: values.reshape(*batch, *values.shape[1:]) for f, values in out.items()}
