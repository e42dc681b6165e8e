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
the pair's margin (which MJX's do not), to emit contacts within it; the
contact's ``includemargin`` holds what C passes its colliders, margin + gap.

Which ports a Scene installs. Every port gives C's contacts (`benchmarks/perf/contacts.py`:
10,000 random poses per pair), but those through C's GJK/EPA (`convex`) cost
orders of magnitude more per pair-collision than MJX's routines: their loops
run a fixed number of trips so that reverse-mode AD goes through. Where MJX
has no function (cylinder-box, ellipsoid-box, cylinder- and ellipsoid-mesh)
or a wrong one (its 10-step signed-distance descent for cylinder and
ellipsoid pairs, whose contacts part from C's) the port is installed anyway.
For the four mesh pairs MJX collides with its own convex routines (sphere-,
capsule-, box- and mesh-mesh, off C on some poses), MJX's function stays by
default: those pairs are reported as approximate (`approximate_pairs`,
`mjstamp check`, the solve's fidelity check and warning), and
`exact_meshes()` installs C's for them, at the GJK/EPA ports' price. The
measurements: benchmarks/results/README.md, "Measurements quoted from the code".

May import: mujoco, mujoco.mjx, jax, numpy, and of mjstamp only `_mjx` and
`errors`: the colliders sit below `scenes/`, which installs them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco

from mjstamp import _mjx  # mujoco.mjx without its stdout chatter; rewriting its source

__all__ = [
    "FAR",
    "MJX_EXACT",
    "PORTED",
    "approximate_pairs",
    "collider",
    "describe_pair",
    "exact_meshes",
    "is_patched",
    "mjx_own",
    "pair_info",
    "patch_collisions",
    "table_version",
]

# Distance of an unused slot: far beyond any margin, finite so that MJX's
# `(dist - includemargin) * active` stays 0 (inf * 0 is NaN).
FAR = 1e10

_PATCHED = False
_VERSION = 0
_EXACT_MESHES = False
_ORIGINAL: dict[tuple[int, int], Callable | None] = {}

# (type1, type2) in mjtGeom order -> collider, filled by the modules below.
PORTED: dict[tuple[int, int], Callable] = {}

_G = mujoco.mjtGeom
# Pairs whose MJX 3.17 function gives C's contacts already (tests/test_contacts_primitive.py
# compares them with C on random poses): MJX's own function stays.
MJX_EXACT = frozenset({
    (int(_G.mjGEOM_PLANE), int(_G.mjGEOM_SPHERE)),
    (int(_G.mjGEOM_PLANE), int(_G.mjGEOM_ELLIPSOID)),
})


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
    """The patched driver's call of a collision function (ours take the contact).

    N.B. C calls its colliders with margin + gap (engine_collision_driver.c,
    mj_collideGeoms) and makes active only the contacts within the margin
    (mj_setContact's includemargin); MJX ignores gap, which leaves its active
    set the same, but a routine that picks contacts by the margin (a box's
    corners) needs the wider one. Ours get it as `includemargin`; the driver
    keeps MJX's own for the activation.
    """
    if not getattr(func, "takes_contact", False):
        return func(m, d, key, contact.geom)
    return func(m, d, key, contact.replace(includemargin=_collider_margin(m, contact.geom)))


def _collider_margin(m, geom: jax.Array) -> jax.Array:
    """(k,) margin + gap of each geom pair, from its <pair> where it has one (as C)."""
    g1, g2 = geom[:, 0], geom[:, 1]
    out = m.geom_margin[g1] + m.geom_margin[g2] + m.geom_gap[g1] + m.geom_gap[g2]
    if m.npair:
        p1, p2 = jnp.asarray(m.pair_geom1), jnp.asarray(m.pair_geom2)
        # N.B. by ids, not by position: a broad-phase cull (max_geom_pairs) reorders pairs.
        same = (((g1[:, None] == p1) & (g2[:, None] == p2))
                | ((g1[:, None] == p2) & (g2[:, None] == p1)))
        pair = m.pair_margin + m.pair_gap
        out = jnp.where(same.any(axis=1), pair[jnp.argmax(same, axis=1)], out)
    return out


def table_version() -> int:
    """Changes whenever the installed collision table does (a cache key)."""
    return _VERSION


def _register() -> None:
    """Imports the ported routines, which add themselves to `PORTED`."""
    # pylint: disable=g-import-not-at-top,unused-import
    from mjstamp.colliders import box_box, capsule_box, convex, primitive  # noqa: F401


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

    _register()
    collide = _mjx.rewrite(
        collision_driver, "collision",
        [("dist, pos, frame = func(m, d, key, contact.geom)",
          "dist, pos, frame = _mjs_call(func, m, d, key, contact)")],
        extra={"_mjs_call": _call},
    )
    table = collision_driver._COLLISION_FUNC  # pylint: disable=protected-access
    for pair, fn in PORTED.items():
        _ORIGINAL[pair] = table.get(pair)
        if _installs(pair, fn):
            table[pair] = fn
    collision_driver.collision = collide
    _patch_mjx_collision(collide)
    _PATCHED = True
    _VERSION += 1


def _installs(pair: tuple[int, int], fn: Callable) -> bool:
    """Whether `patch_collisions` puts this port in the table (see the module docstring)."""
    return _EXACT_MESHES or not (getattr(fn, "opt_in", False) and _ORIGINAL.get(pair))


def exact_meshes(on: bool = True) -> None:
    """Collides sphere-, capsule-, box- and mesh-mesh pairs with C's GJK/EPA ports (or not).

    By default MJX's own functions collide these pairs (fast, approximate,
    reported as such); with ``on`` the ports do, exactly as MuJoCo C and about
    a thousand times slower per pair-collision. Affects what is traced from
    now on (compiled rollouts keep their table; `table_version` changes).
    """
    global _EXACT_MESHES, _VERSION
    _EXACT_MESHES = bool(on)
    if not _PATCHED:
        return
    from mujoco.mjx._src import collision_driver  # pylint: disable=g-import-not-at-top

    table = collision_driver._COLLISION_FUNC  # pylint: disable=protected-access
    for pair, fn in PORTED.items():
        if not getattr(fn, "opt_in", False):
            continue
        if _installs(pair, fn):
            table[pair] = fn
        else:
            table[pair] = _ORIGINAL[pair]
    _VERSION = (abs(_VERSION) + 1) * (1 if _VERSION >= 0 else -1)


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


@contextlib.contextmanager
def mjx_own():
    """Within the block, MJX's own collision functions (for comparisons with the ports).

    N.B. read at trace time, like the table itself: compile inside the block.
    """
    global _VERSION
    patch_collisions()
    from mujoco.mjx._src import collision_driver  # pylint: disable=g-import-not-at-top

    table = collision_driver._COLLISION_FUNC  # pylint: disable=protected-access
    ported = {pair: table[pair] for pair in _ORIGINAL}
    for pair, fn in _ORIGINAL.items():
        if fn is None:
            table.pop(pair, None)
        else:
            table[pair] = fn
    _VERSION = -abs(_VERSION) - 1
    try:
        yield
    finally:
        table.update(ported)
        _VERSION = -_VERSION


def is_patched() -> bool:
    """Whether `patch_collisions` has run in this process."""
    return _PATCHED


def safe_norm(x: jax.Array, axis: int = -1) -> jax.Array:
    """|x| with a zero (not NaN) gradient at x = 0."""
    sq = jnp.sum(x * x, axis=axis)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def make_frame(normal: jax.Array) -> jax.Array:
    """(3, 3) contact frame of a normal, as C's `mju_makeFrame` with no tangent set."""
    from mjstamp.colliders import cmath  # pylint: disable=g-import-not-at-top

    return cmath.frame(normal, jnp.zeros_like(normal))


def frame_with_tangent(normal: jax.Array, tangent: jax.Array) -> jax.Array:
    """As C's `mju_makeFrame` when the collider set a tangent (used if |tangent|² >= 0.25)."""
    from mjstamp.colliders import cmath  # pylint: disable=g-import-not-at-top

    return cmath.frame(normal, tangent)


def _type_name(t: int) -> str:
    return mujoco.mjtGeom(int(t)).name.removeprefix("mjGEOM_").lower()


def _geom_name(m: mujoco.MjModel, g: int) -> str:
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g))
    return repr(name) if name else f"#{int(g)}"


def describe_pair(m: mujoco.MjModel, g1: int, g2: int) -> str:
    """"box-box 'paddle'/'bumper'": the types, then the geoms (names, else #ids)."""
    t1, t2 = int(m.geom_type[g1]), int(m.geom_type[g2])
    if t1 > t2:
        g1, g2, t1, t2 = g2, g1, t2, t1
    return f"{_type_name(t1)}-{_type_name(t2)} {_geom_name(m, g1)}/{_geom_name(m, g2)}"


def pair_info(m: mujoco.MjModel, g1: int, g2: int) -> dict:
    """JSON view of a geom pair: names (None when unnamed), ids and types."""
    return {
        "geoms": [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in (g1, g2)],
        "ids": [int(g1), int(g2)],
        "types": [_type_name(m.geom_type[g]) for g in (g1, g2)],
    }


def is_exact(t1: int, t2: int) -> bool:
    """Whether the table in force collides this type pair as MuJoCo C does."""
    from mujoco.mjx._src import collision_driver  # pylint: disable=g-import-not-at-top

    pair = tuple(sorted((int(t1), int(t2))))
    fn = collision_driver._COLLISION_FUNC.get(pair)  # pylint: disable=protected-access
    if fn is not None and fn is PORTED.get(pair):
        return not getattr(fn, "approximate", False)
    return pair in MJX_EXACT


def approximate_pairs(m: mujoco.MjModel) -> list[tuple[int, int]]:
    """The model's colliding geom pairs (MJX's rule) whose contacts are not C's."""
    from mujoco.mjx._src import collision_driver  # pylint: disable=g-import-not-at-top

    out = []
    if m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return out
    for g1, g2, _ in collision_driver.geom_pairs(m):
        if not is_exact(m.geom_type[g1], m.geom_type[g2]):
            out.append((int(g1), int(g2)))
    return out
