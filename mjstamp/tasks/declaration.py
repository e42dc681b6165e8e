"""What a task declaration is made of: typed variables, contact symbols, weighted terms.

Plain frozen data, shared by the `Task` builder and the `Problem` it builds.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable

import mujoco
import numpy as np

from mjstamp.distance import UnsupportedPairError, make_distance_fn
from mjstamp.errors import MjstampError


class Kind(enum.StrEnum):
    """The kind of a block of θ.

    BOX: bounded reals (velocities, positions, goals).
    ANGLE: angles in radians, wrapping around (von Mises kernel).
    DISCRETE: a discrete choice of one of `options` in each of `phases` phases,
      relaxed to logits with a softmax one-hot per phase (STAMP §IV-A, App. A).
    """

    BOX = "box"
    ANGLE = "angle"
    DISCRETE = "discrete"


@dataclasses.dataclass(frozen=True)
class Variable:
    """A named block of θ.

    Attributes:
      name: unique name.
      kind: its `Kind`.
      size: number of coordinates of θ it takes (a discrete variable: options × phases).
      low, high: (size,) bounds; particles start uniform inside them.
      qvel, qpos: addresses in qvel / qpos the variable sets at t = 0, or None.
      options: names of the options of a discrete variable.
      phases: K phases of a discrete variable.
    """

    name: str
    kind: Kind
    size: int
    low: np.ndarray
    high: np.ndarray
    qvel: tuple[int, ...] | None = None
    qpos: tuple[int, ...] | None = None
    options: tuple[str, ...] = ()
    phases: int = 1


@dataclasses.dataclass(frozen=True)
class Contact:
    """A symbol: "geom1 touches geom2" (up to the first contact of `before`).

    Relaxed to the soft indicator of App. B-B,
    w = sigmoid(Σ_t σ_t d_t), d_t = −α·sd_t + β, σ = softmax(d) over t ≤ t_c,
    with sd_t the signed distance of the two geoms at step t.
    """

    name: str
    geom1: int
    geom2: int
    before: tuple[int, int] | None
    alpha: float
    beta: float


@dataclasses.dataclass(frozen=True)
class Term:
    """A weighted cost or log-prior term.

    Attributes:
      name: unique among the task's terms.
      fn: the term's (n,) value: fn(rollout) for a cost, fn(params) for a prior.
      weight: its weight in C (or log p).
      residual: for a cost that is a sum of squares, fn(rollout) -> r (n, m)
        with `fn` = Σ r² (what the polish descends on); None otherwise.
      tolerance: with `residual`, the norm ‖r‖ within which the term's goal
        is met (a goal's radius), or None where unknown.
    """

    name: str
    fn: Callable
    weight: float
    residual: Callable | None = None
    tolerance: float | None = None


@dataclasses.dataclass(frozen=True)
class SumOfSquares:
    """The cost Σ r² of a residual function r(rollout) -> (n, m) (`Task.residuals`)."""

    residual: Callable
    where: str = "residuals"

    def __call__(self, rollout):
        """(n,) Σ_j r_j²; a residual of another shape is one line naming `where`."""
        r = self.residual(rollout)
        if getattr(r, "ndim", None) != 2:
            raise MjstampError(f"{self.where} must return an (n, m) array (m residuals per "
                               f"particle), got shape {getattr(r, 'shape', type(r).__name__)}")
        return (r**2).sum(axis=-1)


def joint_width(joint_type: int, kind: str) -> int:
    """Coordinates of a joint type in qvel or qpos."""
    free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
    if joint_type == free:
        return 6 if kind == "qvel" else 7
    if joint_type == ball:
        return 3 if kind == "qvel" else 4
    return 1


def distance_fn(m: mujoco.MjModel, task: str, g1: int, g2: int) -> Callable:
    """The signed distance function of a geom pair, or one line naming the task and pair.

    Raises:
      UnsupportedPairError: a pair of geom types without a JAX distance.
      MjstampError: any other reason (an unknown geom, a mesh without a hull).
    """
    try:
        return make_distance_fn(m, g1, g2)
    except (ValueError, KeyError) as e:
        kind = UnsupportedPairError if isinstance(e, UnsupportedPairError) else MjstampError
        raise kind(f"task {task!r}: {' '.join(str(e).split())}") from None
