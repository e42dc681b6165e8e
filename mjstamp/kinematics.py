"""Poses and contacts of MuJoCo states by C kinematics: the loops over `mj_kinematics`.

The C replay (`scenes.rollout.replay_model`'s pose fields), the fidelity
measure (`scenes.fidelity.tracked_points`) and the drawing of a plan
(`geometry.replay_frames`) all read their poses from `poses`. The planner's
own poses of a replay (MJX kinematics in the scene's precision, what the
task's costs read) are `verify.replay.poses`. Which geoms touch, what decode
reads off every replay, is MuJoCo C's own answer: `touching`.

Imports only mujoco, numpy and `mjstamp.errors`, so that `scenes/` and
`geometry` can both use it.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from mjstamp.errors import MjstampError

__all__ = ["check_touch_pair", "pair_key", "poses", "touching"]

# Geom types MuJoCo C has no collider for between each other (the empty cells of
# `mjCOLLISIONFUNC`): plane-plane, plane-hfield, hfield-hfield.
_UNCOLLIDED = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD))


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


def _geom_label(m: mujoco.MjModel, g: int) -> str:
    """"geom 'cue' (sphere)"."""
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g)
    kind = mujoco.mjtGeom(int(m.geom_type[g])).name.removeprefix("mjGEOM_").lower()
    return f"geom {name!r} ({kind})" if name else f"geom #{g} ({kind})"


def pair_key(g1: int, g2: int) -> tuple[int, int]:
    """A geom pair's key, low id first: (min, max) of geom ids g1, g2."""
    return (min(g1, g2), max(g1, g2))


def check_touch_pair(m: mujoco.MjModel, g1: int, g2: int) -> None:
    """Checks that `touching` can answer for geoms g1, g2 (ids); else one line naming them.

    Raises:
      MjstampError: an id outside the model, the same geom twice, or two types
        MuJoCo C has no collider for (plane or height field against plane or
        height field).
    """
    for g in (g1, g2):
        if not 0 <= g < m.ngeom:
            raise MjstampError(f"geom id {g} is not in the model; valid: two different "
                               f"geoms, ids 0 to {m.ngeom - 1}")
    if g1 == g2:
        raise MjstampError(f"{_geom_label(m, g1)} cannot touch itself; valid: two "
                           "different geoms")
    if int(m.geom_type[g1]) in _UNCOLLIDED and int(m.geom_type[g2]) in _UNCOLLIDED:
        raise MjstampError(
            f"{_geom_label(m, g1)} and {_geom_label(m, g2)}: MuJoCo C has no collider "
            "for them, so they never touch; valid: any pair but plane-plane, plane-hfield "
            "and hfield-hfield")


def touching(m: mujoco.MjModel, qpos: np.ndarray, pairs, candidates=None) -> np.ndarray:
    """Whether geom pairs touch at configurations, by MuJoCo C's own colliders.

    Touch means penetration: at zero margin, the collider MuJoCo C runs for the
    two geoms' types (the function `mj_collision` calls, here through
    `mj_geomDistance`) reports a contact of distance < 0. That is C's contact
    list for geoms without margin (it holds the contacts of distance < margin)
    and the test a JAX signed distance is held to (`sd < 0`,
    `verify.Replay.symbol_disagreements`); MuJoCo C's depth is its colliders'
    (GJK/EPA to 1e-6 for curved pairs), so the two may differ at grazing states.
    Filters (contype, conaffinity, `<exclude>`, parent and child) and margins
    are not applied: a pair touches by geometry alone, whether or not the
    scene makes a constraint of it. States with a non-finite coordinate (a
    replay that blew up) touch nowhere.

    Args:
      m: the model.
      qpos: (..., nq) configurations.
      pairs: k geom id pairs (each is checked by `check_touch_pair`: N.B.
        `mj_geomDistance` does not check its ids, and reads out of bounds).
      candidates: (..., k) bool, where C is asked; False elsewhere, where a
        caller's bound shows the pair apart (`scenes.distance.make_distance_bound`).
        None: everywhere.

    Returns:
      (..., k) bool.

    Raises:
      MjstampError: qpos not nq wide, or a pair `check_touch_pair` rejects.
    """
    qpos = np.asarray(qpos, np.float64)
    if qpos.ndim == 0 or qpos.shape[-1] != m.nq:
        raise MjstampError(f"qpos of shape {qpos.shape} is not a batch of configurations; "
                           f"valid: (..., {m.nq}), the model's nq last")
    batch = qpos.shape[:-1]
    flat = qpos.reshape(-1, m.nq)
    pairs = [(int(a), int(b)) for a, b in pairs]
    for g1, g2 in pairs:
        check_touch_pair(m, g1, g2)
    out = np.zeros((len(flat), len(pairs)), bool)
    ask = np.isfinite(flat).all(axis=1)[:, None] & (
        True if candidates is None
        else np.asarray(candidates, bool).reshape(len(flat), len(pairs)))
    ask = np.broadcast_to(ask, out.shape)
    rows = np.flatnonzero(ask.any(axis=1))
    d = mujoco.MjData(m)
    # N.B. one kinematics per state for all its pairs, and plain Python lists in the
    # loop: the bindings' call overhead is most of the cost.
    for i, row in zip(rows.tolist(), ask[rows].tolist(), strict=True):
        d.qpos[:] = flat[i]
        mujoco.mj_kinematics(m, d)
        for j, (g1, g2) in enumerate(pairs):
            if row[j]:
                out[i, j] = mujoco.mj_geomDistance(m, d, g1, g2, 0.0, None) < 0.0
    return out.reshape(*batch, len(pairs))
