"""MuJoCo C's contacts in MJX: collision functions ported from the C engine.

MJX 3.17 collides boxes, cylinders, ellipsoids and meshes with its own
routines, "implemented differently than in MuJoCo" (MJX docs): a 4-point SAT
manifold for box-box, corners within 1 mm of the deepest for plane-box, a
10-step signed-distance descent for every pair with a cylinder or ellipsoid.
Rollouts then part from MuJoCo C at the first such contact, and plans found on
them are verified against another physics.

This package holds JAX ports of MuJoCo C's own collision routines
(`engine_collision_primitive.c`, `engine_collision_box.c`,
`engine_collision_convex.c`, `engine_collision_gjk.c`), each producing the
contacts C produces (count, distance, position, frame) with a fixed number of
slots and unused slots inactive, and `patch_collisions()` installs them in
MJX's collision table (`collision_driver._COLLISION_FUNC`) the way
`gradsafe.patch_mjx` patches its solver. `compare` checks any installed
function against C on random poses.

A collider here has MJX's signature plus the pair's contact parameters:
``fn(m, d, key, contact) -> (dist (k,), pos (k, 3), frame (k, 3, 3))`` with
``fn.ncon`` slots per pair and ``fn.takes_contact = True``: C's routines take
the pair's margin (which MJX's do not), to emit contacts within it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco

from mjstamp.scenes import _mjx  # noqa: F401 - imports mujoco.mjx without its stdout chatter

__all__ = ["PORTED", "collider", "is_patched", "patch_collisions", "table_version", "FAR"]

# Distance of an unused slot: far beyond any margin, finite so that MJX's
# `(dist - includemargin) * active` stays 0 (inf * 0 is NaN).
FAR = 1e10

_PATCHED = False
_VERSION = 0

# (type1, type2) in mjtGeom order -> collider, filled by the modules below.
PORTED: dict[tuple[int, int], Callable] = {}


def collider(ncon: int):
    """Wraps a per-pair function into an MJX collision function with margins.

    The wrapped function takes ``(info1, info2, margin)`` of one geom pair
    (MJX `GeomInfo` or `ConvexInfo`, and the pair's margin, a scalar) and
    returns ``(dist (ncon,), pos (ncon, 3), frame (ncon, 3, 3))`` with unused
    slots at `FAR`. The result is vmapped over the pairs of a group, as MJX's
    own `collider` does.
    """

    def wrapper(func):
        def collide(m, d, key, contact):
            from mujoco.mjx._src.collision_types import GeomInfo  # pylint: disable=g-import-not-at-top

            g1, g2 = contact.geom.T
            info1 = GeomInfo(d.geom_xpos[g1], d.geom_xmat[g1], m.geom_size[g1])
            info2 = GeomInfo(d.geom_xpos[g2], d.geom_xmat[g2], m.geom_size[g2])
            dist, pos, frame = jax.vmap(func)(info1, info2, contact.includemargin)
            return (dist.reshape(-1), pos.reshape(-1, 3), frame.reshape(-1, 3, 3))

        collide.ncon = ncon
        collide.takes_contact = True
        collide.__name__ = func.__name__
        collide.__doc__ = func.__doc__
        collide.pair_fn = func
        return collide

    return wrapper


def _call(func, m, d, key, contact):
    """The patched driver's call of a collision function (ours take the contact)."""
    if getattr(func, "takes_contact", False):
        return func(m, d, key, contact)
    return func(m, d, key, contact.geom)


def table_version() -> int:
    """Changes whenever the installed collision table does (a cache key)."""
    return _VERSION


def _register() -> None:
    """Imports the ported routines, which add themselves to `PORTED`."""
    # pylint: disable=g-import-not-at-top,unused-import
    from mjstamp.scenes.contacts import box_box, capsule_box, convex, primitive  # noqa: F401


def patch_collisions() -> None:
    """Installs the ported C routines in MJX's collision table. Idempotent.

    Must run before the first trace of `mjx.collision` (compiled functions keep
    the table they were traced with). The driver's call of a collision function
    is rewritten (as `gradsafe` rewrites the solver: the expression must be
    found exactly once) to hand ported routines the pair's contact parameters.

    Raises:
      RuntimeError: if the installed MJX no longer contains the expression.
    """
    global _PATCHED, _VERSION
    if _PATCHED:
        return
    from mujoco.mjx._src import collision_driver  # pylint: disable=g-import-not-at-top

    from mjstamp.scenes import gradsafe  # pylint: disable=g-import-not-at-top

    _register()
    collide = gradsafe.rewrite(
        collision_driver, "collision",
        [("dist, pos, frame = func(m, d, key, contact.geom)",
          "dist, pos, frame = _mjs_call(func, m, d, key, contact)")],
        extra={"_mjs_call": _call},
    )
    for pair, fn in PORTED.items():
        collision_driver._COLLISION_FUNC[pair] = fn  # pylint: disable=protected-access
    collision_driver.collision = collide
    _patch_mjx_collision(collide)
    _PATCHED = True
    _VERSION += 1


def _patch_mjx_collision(collide) -> None:
    """Points every module that imported `collision` by name at the patched one."""
    import sys  # pylint: disable=g-import-not-at-top

    for name, module in list(sys.modules.items()):
        if not name.startswith("mujoco.mjx") or module is None:
            continue
        if getattr(module, "collision", None) is not None and getattr(
            module.collision, "__module__", ""
        ) == "mujoco.mjx._src.collision_driver":
            module.collision = collide


def is_patched() -> bool:
    """Whether `patch_collisions` has run in this process."""
    return _PATCHED


def safe_norm(x: jax.Array, axis: int = -1) -> jax.Array:
    """|x| with a zero (not NaN) gradient at x = 0."""
    sq = jnp.sum(x * x, axis=axis)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def make_frame(normal: jax.Array) -> jax.Array:
    """(3, 3) contact frame of a unit normal, as C's `mju_makeFrame` with no tangent."""
    y = jnp.where((normal[1] < 0.5) & (normal[1] > -0.5), jnp.array([0.0, 1.0, 0.0]),
                  jnp.array([0.0, 0.0, 1.0])).astype(normal.dtype)
    b = y - normal * jnp.dot(normal, y)
    b = b / safe_norm(b)
    return jnp.stack([normal, b, jnp.cross(normal, b)])


def frame_with_tangent(normal: jax.Array, tangent: jax.Array) -> jax.Array:
    """As C's `mju_makeFrame` when the collider set a tangent (|tangent|² >= 0.25)."""
    use = jnp.dot(tangent, tangent) >= 0.25
    y = jnp.where((normal[1] < 0.5) & (normal[1] > -0.5), jnp.array([0.0, 1.0, 0.0]),
                  jnp.array([0.0, 0.0, 1.0])).astype(normal.dtype)
    t = jnp.where(use, tangent, y)
    b = t - normal * jnp.dot(normal, t)
    b = b / safe_norm(b)
    return jnp.stack([normal, b, jnp.cross(normal, b)])


_ = mujoco  # the mjtGeom enums are read by the submodules
