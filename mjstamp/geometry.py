"""What a MuJoCo C replay looks like: poses, colours and contact forces, for drawing.

One set of rules for everything that draws a plan: the PNG figures
(`mjstamp.figures`) and the meshcat playback (`mjstamp.viz`) both read their
poses, colours and contact forces from here, so the two cannot disagree.

    frames = replay_frames(m, qpos0, qpos, qvel0=qvel0, qvel=qvel, ctrl=ctrl,
                           pairs=[(pusher, block)])
    frames.xpos[k]            # (nbody, 3) body positions at frame k
    frames.force[k, 0]        # (3,) force of the pusher on the block there
    drawn_rgba(m, "geom", g)  # (4,) colour of geom g as drawn

A replay is the initial state s_0 = (qpos0, qvel0) and the states s_1..s_T
after each step, with ctrl[t] the control applied over the step from s_t to
s_{t+1} (as `verify.Replay` and results directories hold them). Each frame is
posed by `mj_kinematics` (`kinematics.poses`); its forces, where asked for, come
from one `mj_forward`.

Imports only mujoco, numpy and `mjstamp.kinematics` (no JAX, no matplotlib, no meshcat).

References:
  STAMP Fig. 3 and 7 (plan paths), Fig. 6 (contact-force arrows).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from mjstamp.kinematics import poses

__all__ = [
    "DEFAULT_RGBA",
    "Frames",
    "Pose",
    "SITE_OPACITY",
    "contact_force",
    "drawn_rgba",
    "mujoco_rgba",
    "pose",
    "replay_frames",
    "shown",
]

DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], np.float32)  # MuJoCo's geom and site default
SITE_OPACITY = 0.5  # sites mark regions (pockets, goals), not matter: drawn see-through


# ----------------------------------------------------------------------------
# Appearance.


def mujoco_rgba(m: mujoco.MjModel, kind: str, i: int) -> np.ndarray:
    """(4,) colour of geom or site `i` as MuJoCo's renderer gives it.

    A material's rgba wins only where the element keeps the default rgba
    (MuJoCo's rule in mjv_addGeoms); an explicit rgba beats the material. A
    material with a colour texture (dm_control's checkered ground, a textured
    mesh) is drawn by MuJoCo as texel × rgba: here its mean texel stands in
    for the texture (the PNGs and meshcat draw flat colours), or a textured
    ground drawn with its plain white rgba would be white.

    Args:
      m: the model.
      kind: "geom" or "site".
      i: its id.
    """
    rgba = np.array(getattr(m, f"{kind}_rgba")[i], np.float32)
    matid = getattr(m, f"{kind}_matid")[i]
    if matid >= 0 and np.allclose(rgba, DEFAULT_RGBA):
        rgba = np.array(m.mat_rgba[matid], np.float32)
    if matid >= 0:
        rgba[:3] *= _mean_texel(m, int(matid))
    return rgba


def _mean_texel(m: mujoco.MjModel, matid: int) -> np.ndarray:
    """(3,) mean colour in [0, 1] of material `matid`'s colour texture; ones without one."""
    texid = np.atleast_1d(m.mat_texid[matid])
    tex = int(texid[int(mujoco.mjtTextureRole.mjTEXROLE_RGB)] if len(texid) > 1 else texid[0])
    if tex < 0:
        return np.ones(3, np.float32)
    c = int(m.tex_nchannel[tex])
    n = int(m.tex_width[tex]) * int(m.tex_height[tex]) * c
    adr = int(m.tex_adr[tex])
    texels = np.asarray(m.tex_data[adr : adr + n], np.float32).reshape(-1, c)
    if c < 3:  # a grey (luminance) texture
        return np.full(3, texels[:, 0].mean() / 255.0, np.float32)
    return texels[:, :3].mean(axis=0) / 255.0


def drawn_rgba(m: mujoco.MjModel, kind: str, i: int) -> np.ndarray:
    """(4,) colour and opacity of geom or site `i` in the figures and the playback.

    MuJoCo's colour (`mujoco_rgba`), with sites at `SITE_OPACITY` of their
    opacity so that what lies under a pocket or a goal region shows.
    """
    rgba = mujoco_rgba(m, kind, i)
    if kind == "site":
        rgba[3] *= SITE_OPACITY
    return rgba


def shown(m: mujoco.MjModel, kind: str, i: int) -> bool:
    """Whether geom or site `i` is shown by default: its group is one MuJoCo's viewer shows.

    (Groups 0-2; 3-5 usually hold collision duplicates and helpers.)
    """
    option = mujoco.MjvOption()
    groups = option.geomgroup if kind == "geom" else option.sitegroup
    group = int(getattr(m, f"{kind}_group")[i])
    return bool(0 <= group < len(groups) and groups[group])


# ----------------------------------------------------------------------------
# Contact forces.


def contact_force(m: mujoco.MjModel, d: mujoco.MjData, a: int, b: int):
    """Total contact force of geom `a` on geom `b`, in the world frame.

    Sums every active contact between the two geoms (a box and a sphere can
    touch at several points); excluded contacts (inside the gap, or otherwise
    not in the constraint problem: `efc_address < 0`) carry no force and do
    not count. Needs `d` after `mj_forward` (or a step).

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
        if {g1, g2} != {a, b} or c.efc_address < 0:
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


# ----------------------------------------------------------------------------
# Poses and forces of a replay.


class Pose(NamedTuple):
    """World poses at one state; the same names as `mujoco.MjData`'s, so either will do.

    Attributes:
      xpos: (nbody, 3) body positions.
      xquat: (nbody, 4) body orientations, wxyz.
      geom_xpos: (ngeom, 3) geom positions.
      geom_xmat: (ngeom, 9) geom orientations, row-major.
      site_xpos: (nsite, 3) site positions.
      site_xmat: (nsite, 9) site orientations, row-major.
    """

    xpos: np.ndarray
    xquat: np.ndarray
    geom_xpos: np.ndarray
    geom_xmat: np.ndarray
    site_xpos: np.ndarray
    site_xmat: np.ndarray


class Frames(NamedTuple):
    """Poses and contact forces at F states of one replay (numpy, float64).

    Attributes:
      states: (F,) index of each frame's state (0: the initial state s_0).
      xpos, xquat, geom_xpos, geom_xmat, site_xpos, site_xmat: the `Pose`
        fields, each with a leading axis of length F.
      pairs: the geom pairs (a, b) whose forces were read.
      force: (F, len(pairs), 3) world-frame force of a on b (zero where they
        do not touch).
      point: (F, len(pairs), 3) where it acts; NaN where they do not touch.
    """

    states: np.ndarray
    xpos: np.ndarray
    xquat: np.ndarray
    geom_xpos: np.ndarray
    geom_xmat: np.ndarray
    site_xpos: np.ndarray
    site_xmat: np.ndarray
    pairs: tuple[tuple[int, int], ...]
    force: np.ndarray
    point: np.ndarray

    def pose(self, k: int) -> Pose:
        """The `Pose` of frame k (negative k counts from the end)."""
        return Pose(*(getattr(self, name)[k] for name in Pose._fields))


def pose(m: mujoco.MjModel, qpos: np.ndarray) -> Pose:
    """The `Pose` of one configuration qpos (nq,), by `mj_kinematics`."""
    k = poses(m, qpos, Pose._fields)
    return Pose(*(k[name] for name in Pose._fields))


def replay_frames(
    m: mujoco.MjModel,
    qpos0: np.ndarray,
    qpos: np.ndarray,
    *,
    qvel0: np.ndarray | None = None,
    qvel: np.ndarray | None = None,
    ctrl: np.ndarray | None = None,
    pairs: Sequence[tuple[int, int]] = (),
    states: Sequence[int] | None = None,
) -> Frames:
    """Poses, and the contact forces of `pairs`, at states of one MuJoCo C replay.

    The force at state s_t is the one of the constraint problem that the step
    from s_t solves, so `mj_forward` gets s_t's velocities and ctrl[t] (the
    last state, which no step leaves, reuses the last control). Without
    velocities there is no such problem to read: every force is then zero and
    every point NaN.

    Args:
      m: the model the replay ran on.
      qpos0: (nq,) initial positions s_0.
      qpos: (T, nq) positions after steps 1..T.
      qvel0: (nv,) initial velocities (needed for forces, with qvel).
      qvel: (T, nv) velocities after steps 1..T.
      ctrl: (T, nu) controls of steps 1..T; None (or nu = 0) leaves them 0.
      pairs: geom id pairs (a, b): read the force of a on b.
      states: state indices in 0..T to compute (default all T + 1).

    Returns:
      `Frames` of the chosen states, in the order given.
    """
    qpos = np.concatenate([np.asarray(qpos0, np.float64)[None], np.asarray(qpos, np.float64)])
    forces = bool(pairs) and qvel0 is not None and qvel is not None
    if forces:
        qvel = np.concatenate([np.asarray(qvel0, np.float64)[None], np.asarray(qvel, np.float64)])
    if ctrl is not None and (m.nu == 0 or np.size(ctrl) == 0):
        ctrl = None
    idx = np.arange(len(qpos)) if states is None else np.asarray(states, int)
    pairs = tuple((int(a), int(b)) for a, b in pairs)
    force = np.zeros((len(idx), len(pairs), 3))
    point = np.full((len(idx), len(pairs), 3), np.nan)
    if forces:
        d = mujoco.MjData(m)
        for f, t in enumerate(idx):
            d.qpos[:], d.qvel[:] = qpos[t], qvel[t]
            if ctrl is not None:
                d.ctrl[:] = ctrl[min(t, len(ctrl) - 1)]
            mujoco.mj_forward(m, d)
            for k, (a, b) in enumerate(pairs):
                force[f, k], p = contact_force(m, d, a, b)
                if p is not None:
                    point[f, k] = p
    # N.B. the poses `mj_forward` computes are those of `mj_kinematics`: its first stage.
    return Frames(states=idx, pairs=pairs, force=force, point=point,
                  **poses(m, qpos[idx], Pose._fields))
