"""Contact forces between two geoms, read from MuJoCo C, for drawing (paper Fig. 6)."""

from __future__ import annotations

import mujoco
import numpy as np


def contact_force(m: mujoco.MjModel, d: mujoco.MjData, a: int, b: int):
    """Total contact force of geom `a` on geom `b`, in the world frame.

    Sums every active contact between the two geoms (a box and a sphere can
    touch at several points). Needs `d` after `mj_forward` (or a step).

    N.B. MuJoCo's contact normal points from `contact.geom[0]` to
    `contact.geom[1]` and `mj_contactForce` gives the force in the contact
    frame with a positive (repulsive) normal part, so it is the force of
    geom[0] on geom[1]; pairs stored as (b, a) flip its sign.

    Args:
      m: the model.
      d: its data after `mj_forward`.
      a: id of the geom that exerts the force.
      b: id of the geom the force acts on.

    Returns:
      force: (3,) world-frame force on `b`, zero where they do not touch.
      point: (3,) application point: the contact positions weighted by the
        normal force (their plain mean where all normal forces are zero), or
        None where they do not touch.
    """
    force = np.zeros(3)
    points, weights = [], []
    f6 = np.zeros(6)
    for i in range(d.ncon):
        c = d.contact[i]
        g1, g2 = int(c.geom[0]), int(c.geom[1])
        if {g1, g2} != {a, b} or c.efc_address < 0:  # efc_address < 0: excluded contact
            continue
        mujoco.mj_contactForce(m, d, i, f6)
        world = c.frame.reshape(3, 3).T @ f6[:3]
        force += world if g1 == a else -world
        points.append(np.array(c.pos))
        weights.append(abs(f6[0]))
    if not points:
        return force, None
    w = np.asarray(weights)
    w = w / w.sum() if w.sum() > 0 else np.full(len(points), 1.0 / len(points))
    return force, w @ np.asarray(points)
