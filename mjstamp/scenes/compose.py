"""Helpers for scenes composed with `dm_control.mjcf`.

`start_at(root, angles)`: rollouts start at the model's qpos0, which for a
hinge is its `ref`. An arm composed from a model library stands upright at
qpos0; a task wants it at a working pose.
"""

from __future__ import annotations

from collections.abc import Mapping

import mujoco
import numpy as np

from mjstamp.errors import MjstampError, valid_list


def start_at(root, angles: Mapping[str, float]) -> None:
    """Makes hinge angles the model's qpos0, the state every rollout starts from.

    Setting a hinge's `ref = q` alone would relabel the pose it has at 0 as q;
    turning the joint's body by q about the joint's axis as well gives the
    same model (limits, actuators and kinematics unchanged: the body at qpos is
    at its old frame turned by qpos), whose qpos0 is the wanted pose.

    Args:
      root: a `dm_control.mjcf.RootElement`, changed in place (before `Scene`).
      angles: {joint name as `root.find` takes it (namespaced: "arm/joint_1"):
        angle in radians}.

    Raises:
      MjstampError: a name that is no joint of `root`, a joint that is not a
        hinge, one off its body's origin (its body would move, not turn), or a
        body oriented other than by a quat.
    """
    joints = {j.full_identifier: j for j in root.find_all("joint")}
    for name, q in angles.items():
        joint = root.find("joint", name)
        if joint is None:
            raise MjstampError(f"start_at: {name!r} is no joint of the scene; valid: "
                               f"{valid_list(joints)}")
        kind = "free" if joint.tag == "freejoint" else joint.type
        if kind not in (None, "hinge"):
            raise MjstampError(f"start_at: joint {name!r} is a {kind} joint; only "
                               "hinges can be turned to their start")
        if joint.pos is not None and np.any(joint.pos):
            raise MjstampError(f"start_at: joint {name!r} is off its body's origin")
        body = joint.parent
        if any(getattr(body, a) is not None for a in ("axisangle", "euler", "xyaxes", "zaxis")):
            raise MjstampError(f"start_at: the body of joint {name!r} gives its orientation "
                               "other than as a quat; write it as a quat")
        axis = np.asarray(joint.axis if joint.axis is not None else (0.0, 0.0, 1.0), float)
        turn = np.zeros(4)
        mujoco.mju_axisAngle2Quat(turn, axis / np.linalg.norm(axis), float(q))
        base = np.asarray(body.quat if body.quat is not None else (1.0, 0.0, 0.0, 0.0), float)
        quat = np.zeros(4)
        mujoco.mju_mulQuat(quat, base, turn)
        body.quat = quat
        joint.ref = float(q)
