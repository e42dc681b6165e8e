"""Differentiable signed distances between MuJoCo geoms, in pure JAX.

MJX reports a sentinel distance for geom pairs that are not touching, so no
gradient flows before contact. Soft contact indicators (STAMP's sigmoid of
-α·d + β over a trajectory) need a signed distance d that is finite and smooth
on both sides of contact; this module computes it from the geom poses of a
rollout (``geom_xpos``, ``geom_xmat``).

Conventions follow MuJoCo: ``size`` is the geom's ``geom_size`` row, ``mat``
rotates geom-local coordinates into the world (its columns are the geom's axes),
capsules and cylinders lie along their local z with half-length ``size[1]``,
and planes are infinite half-spaces ``{x : n·(x - pos) ≤ 0}`` with ``n`` their
local z (a plane's size only affects rendering).

Accuracy, per pair, in float64 against ``mujoco.mj_geomDistance`` on random
poses on both sides of contact (``tests/test_distance.py``; "seen" is the
largest difference there). Float32 adds rounding only (≤ 1e-7 seen).

* plane vs sphere, capsule, cylinder, box, ellipsoid: exact (the depth of the
  deepest point when penetrating); ≤ 4e-16 seen.
* sphere vs sphere, capsule, cylinder, box: exact (the point-to-shape signed
  distance minus the radius); ≤ 2e-16 seen.
* capsule vs capsule: the distance between the axes minus both radii, as
  MuJoCo computes it (≤ 2e-16 seen): exact unless the axes cross, where it
  reports -(r1 + r2) (the true penetration depth is larger there). Exact for
  nearly parallel axes too, where MuJoCo's own collider is off by up to 2e-6.
* box vs box: exact. Separated, the closest features (vertex-to-box and
  edge-to-edge); overlapping, the separating-axis test over the 15 candidate
  axes. ≤ 2e-16 seen on both sides. N.B. edge pairs within 1e-5 rad of
  parallel give no axis (the face normals cover exactly parallel ones), which
  can leave a depth error of order 1e-5·(box size) in that sliver.
* capsule vs box: exact. Separated, the minimum over the capsule's axis of the
  point-to-box distance, minus the radius, by a golden-section search (the
  signed distance to a convex set is convex along a line) that pins the
  minimizer to 2·h·0.618**_GOLDEN_ITERS ≈ 4e-8·h for half-length h; the
  distance, smooth at a separated minimum, is off by far less (≤ 4e-16 seen).
  Overlapping, the separating-axis test. N.B. MuJoCo's capsule-box collider
  reports a shallower depth once the capsule's axis enters the box (by up to
  0.2 seen); its general convex path (the box as a mesh, EPA) agrees with this
  one to its 1e-6 tolerance.
* capsule vs cylinder: the same golden-section minimum over the axis: exact
  while the capsule's axis stays outside the cylinder (≤ 4e-12 seen, MuJoCo's
  GJK tolerance); once the axis enters it, minus the depth of the deepest axis
  point minus r, shallower than the true penetration depth (by up to 0.016
  seen) as there is no separating-axis shortcut for a curved solid.

Gradients: every branch uses safe norms (the double-``where`` trick), so
gradients are finite everywhere, including at contact, deep in penetration and
when two centres coincide (there the subgradient 0 is returned). Gradients
with respect to ``mat`` are meant along rotations, which is all a rollout's
``geom_xmat`` can vary by: off rotations, formulas that agree on them (a
vertex-to-box and an edge-to-edge distance sharing a closest point) differ.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp.errors import MjstampError

_G = mujoco.mjtGeom
_PLANE = int(_G.mjGEOM_PLANE)
_SPHERE = int(_G.mjGEOM_SPHERE)
_CAPSULE = int(_G.mjGEOM_CAPSULE)
_ELLIPSOID = int(_G.mjGEOM_ELLIPSOID)
_CYLINDER = int(_G.mjGEOM_CYLINDER)
_BOX = int(_G.mjGEOM_BOX)

# Golden-section iterations for capsule vs box/cylinder: the bracket shrinks by
# 0.618 per step, so 37 steps leave 2h·1.9e-8, below float32 resolution.
_GOLDEN_ITERS = 37
_INV_PHI = (np.sqrt(5.0) - 1.0) / 2.0


def _type_name(geom_type: int) -> str:
    """'sphere' for mjGEOM_SPHERE, etc."""
    try:
        return _G(geom_type).name.removeprefix("mjGEOM_").lower()
    except ValueError:
        return f"type {geom_type}"


# ---------------------------------------------------------------------------
# Safe primitives.


def _safe_norm(x: jax.Array, axis: int = -1) -> jax.Array:
    """Euclidean norm with a finite gradient (0) at x = 0.

    N.B. the double ``where``: the inner one keeps ``sqrt`` away from 0, where
    its derivative is infinite and would turn the masked branch's 0 into NaN.
    """
    sq = jnp.sum(x * x, axis=axis)
    ok = sq > jnp.finfo(sq.dtype).tiny
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def _dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """a·b over the last axis, broadcasting over the others."""
    return jnp.sum(a * b, axis=-1)


# N.B. the point and segment helpers below broadcast over leading axes instead
# of being vmapped: box-box calls them on all 16 vertices and 144 edge pairs at
# once, and written elementwise (no batched dot_general) XLA fuses them, which
# keeps the gradient's compile time in check.


def _point_box(p: jax.Array, half: jax.Array, pos: jax.Array, mat: jax.Array):
    """Signed distance from points p (..., 3) to a box (negative inside)."""
    q = jnp.sum(mat * (p - pos)[..., :, None], axis=-2)  # matᵀ(p - pos)
    d = jnp.abs(q) - half
    return _safe_norm(jnp.maximum(d, 0.0)) + jnp.minimum(jnp.max(d, axis=-1), 0.0)


def _point_cylinder(p: jax.Array, size: jax.Array, pos: jax.Array, mat: jax.Array):
    """Signed distance from points p (..., 3) to a cylinder along local z."""
    q = jnp.sum(mat * (p - pos)[..., :, None], axis=-2)
    d = jnp.stack([_safe_norm(q[..., :2]) - size[0], jnp.abs(q[..., 2]) - size[1]], -1)
    return _safe_norm(jnp.maximum(d, 0.0)) + jnp.minimum(jnp.max(d, axis=-1), 0.0)


def _point_segment(p: jax.Array, c: jax.Array, u: jax.Array, h: jax.Array):
    """Distance from p (..., 3) to the segment c + t·u, t ∈ [-h, h], |u| = 1."""
    t = jnp.clip(_dot(p - c, u), -h, h)
    return _safe_norm(p - c - t[..., None] * u)


def _segment_interior(c1, u1, h1, c2, u2, h2):
    """Distance between two segments if their closest points are interior.

    Segments cᵢ + tᵢ·uᵢ, tᵢ ∈ [-hᵢ, hᵢ], |uᵢ| = 1; returns inf when the
    closest points of the two lines fall outside either segment. Broadcasts.
    """
    w = c1 - c2
    # N.B. the closest parameters t₁, t₂ carry no gradient: at an interior
    # minimum ∂distance/∂t = 0 (envelope theorem), and near-parallel segments
    # would otherwise feed their 1/sin²θ sensitivity into the gradient. For
    # the same reason no parallel threshold is needed beyond avoiding 0/0:
    # whatever t₁, t₂ come out, if inside they are points on both segments,
    # so the candidate can only be an upper bound, never below the distance.
    u1s, u2s, ws = jax.lax.stop_gradient((u1, u2, w))
    b = _dot(u1s, u2s)
    d = _dot(u1s, ws)
    e = _dot(u2s, ws)
    denom = 1.0 - b * b
    ok = denom > jnp.finfo(denom.dtype).tiny  # exactly parallel: the ends do
    safe = jnp.where(ok, denom, 1.0)
    t1 = (b * e - d) / safe
    t2 = (e - b * d) / safe
    inside = ok & (jnp.abs(t1) <= h1) & (jnp.abs(t2) <= h2)
    # Masked to 0 outside, so an overflowing t never reaches the gradient.
    t1, t2 = jnp.where(inside, t1, 0.0), jnp.where(inside, t2, 0.0)
    interior = _safe_norm(w + t1[..., None] * u1 - t2[..., None] * u2)
    return jnp.where(inside, interior, jnp.inf)


def _segment_segment(c1, u1, h1, c2, u2, h2):
    """Distance between segments cᵢ + tᵢ·uᵢ, tᵢ ∈ [-hᵢ, hᵢ], |uᵢ| = 1.

    The minimum of a convex quadratic over a rectangle is either its
    unconstrained minimum (if inside) or on an edge of the rectangle, i.e. an
    endpoint-to-segment distance. Taking the minimum over these five
    candidates needs no special case for parallel segments: their
    unconstrained minimum is a line, which meets the rectangle's boundary.
    """
    ends = _point_segment(
        jnp.stack([c1 + h1 * u1, c1 - h1 * u1, c2 + h2 * u2, c2 - h2 * u2]),
        jnp.stack([c2, c2, c1, c1]),
        jnp.stack([u2, u2, u1, u1]),
        jnp.stack([h2, h2, h1, h1]),
    )
    return jnp.minimum(jnp.min(ends), _segment_interior(c1, u1, h1, c2, u2, h2))


def _cross_axes(a: jax.Array, b: jax.Array):
    """Unit axes aᵢ × bⱼ for rows a (n, 3), b (k, 3): (n·k, 3) and a validity mask.

    N.B. parallel directions give no axis (masked out); in every use here the
    face normals cover that case.
    """
    cross = jnp.cross(a[:, None, :], b[None, :, :]).reshape(-1, 3)
    sq = jnp.sum(cross * cross, axis=-1)
    ok = sq > 1e-10
    return cross / jnp.sqrt(jnp.where(ok, sq, 1.0))[:, None], ok


def _max_gap(axes, ok, delta, half_widths):
    """Separating-axis value: max over valid unit axes L of |L·delta| - w(L).

    For any unit L this is ≤ the signed distance between the two convex sets
    whose centres differ by delta and whose projections on L have half-widths
    w(L); when they overlap the maximum over their face normals equals it.
    """
    return jnp.max(jnp.where(ok, jnp.abs(axes @ delta) - half_widths, -jnp.inf))


def _segment_min(point_sdf, shape, c, u, h) -> jax.Array:
    """The minimum over t ∈ [-h, h] of point_sdf(c + t·u, *shape), shape convex.

    The signed distance to a convex set is convex along a line, so a
    golden-section search finds the minimizer t*. It runs on stopped
    gradients, and the distance is differentiated at t* held fixed: that is
    the gradient of the minimum (envelope theorem: ∂f/∂t = 0 at an interior
    minimizer, and t* is pinned at an end otherwise).
    """
    f = lambda t: point_sdf(c + t[..., None] * u, *shape)  # noqa: E731
    c0, u0, h0, shape0 = jax.lax.stop_gradient((c, u, h, shape))
    fs = lambda t: point_sdf(c0 + t * u0, *shape0)  # noqa: E731

    def body(_, state):
        a, b, x1, x2, f1, f2 = state
        left = f1 <= f2  # convexity: the minimizer lies in [a, x2], else [x1, b]
        a, b = jnp.where(left, a, x1), jnp.where(left, x2, b)
        # One new evaluation per step: the surviving interior point is reused.
        xn = jnp.where(left, b - _INV_PHI * (b - a), a + _INV_PHI * (b - a))
        fn = fs(xn)
        return (
            a,
            b,
            jnp.where(left, xn, x2),
            jnp.where(left, x1, xn),
            jnp.where(left, fn, f2),
            jnp.where(left, f1, fn),
        )

    a, b = -h0, h0
    x1 = b - _INV_PHI * (b - a)
    x2 = a + _INV_PHI * (b - a)
    state = (a, b, x1, x2, fs(x1), fs(x2))
    _, _, x1, x2, f1, f2 = jax.lax.fori_loop(0, _GOLDEN_ITERS, body, state)
    t_star = jax.lax.stop_gradient(jnp.where(f1 <= f2, x1, x2))
    # The ends are checked exactly, so a minimum at an end has no search error.
    return jnp.min(f(jnp.stack([t_star, -h, h])))


# ---------------------------------------------------------------------------
# Pair functions: f(size_a, pos_a, mat_a, size_b, pos_b, mat_b) with
# type_a <= type_b in mjtGeom order.


def _plane_height(pos, mat, x):
    """Height of x above a plane (along its local z)."""
    return jnp.dot(mat[:, 2], x - pos)


def _plane_sphere(_sp, pp, mp, s, p, _m):
    return _plane_height(pp, mp, p) - s[0]


def _plane_capsule(_sp, pp, mp, s, p, m):
    n = mp[:, 2]
    return _plane_height(pp, mp, p) - s[1] * jnp.abs(jnp.dot(n, m[:, 2])) - s[0]


def _plane_cylinder(_sp, pp, mp, s, p, m):
    n, a = mp[:, 2], m[:, 2]
    na = jnp.dot(n, a)
    # |n - (n·a)a| = sin∠(n, a), written as a norm so its gradient stays finite
    # when the cylinder stands upright (sqrt(1 - (n·a)²) has an infinite one).
    rim = _safe_norm(n - na * a)
    return _plane_height(pp, mp, p) - s[1] * jnp.abs(na) - s[0] * rim


def _plane_box(_sp, pp, mp, s, p, m):
    return _plane_height(pp, mp, p) - jnp.sum(s * jnp.abs(m.T @ mp[:, 2]))


def _plane_ellipsoid(_sp, pp, mp, s, p, m):
    # Support of an ellipsoid along -n: |diag(s)·Rᵀn| (never 0: |n| = 1, s > 0).
    return _plane_height(pp, mp, p) - _safe_norm(s * (m.T @ mp[:, 2]))


def _sphere_sphere(s1, p1, _m1, s2, p2, _m2):
    return _safe_norm(p1 - p2) - s1[0] - s2[0]


def _sphere_capsule(s1, p1, _m1, s2, p2, m2):
    return _point_segment(p1, p2, m2[:, 2], s2[1]) - s1[0] - s2[0]


def _sphere_cylinder(s1, p1, _m1, s2, p2, m2):
    return _point_cylinder(p1, s2, p2, m2) - s1[0]


def _sphere_box(s1, p1, _m1, s2, p2, m2):
    return _point_box(p1, s2, p2, m2) - s1[0]


def _capsule_capsule(s1, p1, m1, s2, p2, m2):
    axis = _segment_segment(p1, m1[:, 2], s1[1], p2, m2[:, 2], s2[1])
    return axis - s1[0] - s2[0]


def _capsule_cylinder(s1, p1, m1, s2, p2, m2):
    return _segment_min(_point_cylinder, (s2, p2, m2), p1, m1[:, 2], s1[1]) - s1[0]


def _capsule_box(s1, p1, m1, s2, p2, m2):
    # A capsule is its axis segment grown by r, so d = d(segment, box) - r.
    # Overlapping: box ⊕ -segment is a polytope whose face normals are the box
    # axes and (capsule axis) × (box axes), so the separating-axis test over
    # those 6 gives the exact penetration depth. Separated: the minimum over
    # the segment of the point-to-box distance.
    u = m1[:, 2]
    cross, ok = _cross_axes(u[None], m2.T)
    axes = jnp.concatenate([m2.T, cross])  # (6, 3)
    ok = jnp.concatenate([jnp.ones(3, bool), ok])
    widths = s1[1] * jnp.abs(axes @ u) + jnp.abs(axes @ m2) @ s2
    sat = _max_gap(axes, ok, p2 - p1, widths)
    separated = _segment_min(_point_box, (s2, p2, m2), p1, u, s1[1])
    return jnp.where(sat > 0.0, separated, sat) - s1[0]


_SIGNS = np.array(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float
)  # (8, 3) box vertices in half-size units


# The 12 box edges, 4 along each axis in turn: edge k's centre is offset by
# _EDGE_SIGNS[k] (0 along its own axis) in half-size units.
_EDGE_SIGNS = np.array(
    [np.insert(np.array([sj, sk], float), i, 0.0) for i in range(3)
     for sj in (-1, 1) for sk in (-1, 1)]
)  # fmt: skip


def _box_edges(half, pos, mat):
    """The 12 edges of a box: centres (12, 3), unit dirs (12, 3), halves (12,)."""
    centres = pos + (jnp.asarray(_EDGE_SIGNS, half.dtype) * half) @ mat.T
    return centres, jnp.repeat(mat.T, 4, axis=0), jnp.repeat(half, 4)


def _box_box(s1, p1, m1, s2, p2, m2):
    # Overlapping: the separating-axis test over the face normals and the
    # edge-edge cross products (the face normals of box ⊕ -box) gives the
    # exact penetration depth.
    cross, ok = _cross_axes(m1.T, m2.T)
    axes = jnp.concatenate([m1.T, m2.T, cross])  # (15, 3)
    ok = jnp.concatenate([jnp.ones(6, bool), ok])
    widths = jnp.abs(axes @ m1) @ s1 + jnp.abs(axes @ m2) @ s2
    sat = _max_gap(axes, ok, p2 - p1, widths)

    # Separated: the closest points are a vertex and the other box, or two
    # edges' interiors (a vertex-to-edge pair is a vertex-to-box one).
    # N.B. numpy constants are cast explicitly: a float64 one met a float32
    # trace after jax.enable_x64 toggled within one process.
    signs = jnp.asarray(_SIGNS, s1.dtype)
    v1 = p1 + (signs * s1) @ m1.T
    v2 = p2 + (signs * s2) @ m2.T
    half, pos, mat = (
        jnp.repeat(jnp.stack([a, b]), 8, axis=0)
        for a, b in ((s2, s1), (p2, p1), (m2, m1))
    )
    vertex = jnp.min(_point_box(jnp.concatenate([v1, v2]), half, pos, mat))
    c1, u1, h1 = _box_edges(s1, p1, m1)
    c2, u2, h2 = _box_edges(s2, p2, m2)
    edge = _segment_interior(
        c1[:, None], u1[:, None], h1[:, None], c2[None], u2[None], h2[None]
    )  # (12, 12)
    separated = jnp.minimum(vertex, jnp.min(edge))
    return jnp.where(sat > 0.0, separated, sat)


_PAIRS: dict[tuple[int, int], Callable[..., jax.Array]] = {
    (_PLANE, _SPHERE): _plane_sphere,
    (_PLANE, _CAPSULE): _plane_capsule,
    (_PLANE, _ELLIPSOID): _plane_ellipsoid,
    (_PLANE, _CYLINDER): _plane_cylinder,
    (_PLANE, _BOX): _plane_box,
    (_SPHERE, _SPHERE): _sphere_sphere,
    (_SPHERE, _CAPSULE): _sphere_capsule,
    (_SPHERE, _CYLINDER): _sphere_cylinder,
    (_SPHERE, _BOX): _sphere_box,
    (_CAPSULE, _CAPSULE): _capsule_capsule,
    (_CAPSULE, _CYLINDER): _capsule_cylinder,
    (_CAPSULE, _BOX): _capsule_box,
    (_BOX, _BOX): _box_box,
}

SUPPORTED_PAIRS: tuple[tuple[str, str], ...] = tuple(
    (_type_name(a), _type_name(b)) for a, b in _PAIRS
)
"""The supported (type, type) pairs by name; either order works."""


def _supported_list() -> str:
    return ", ".join(f"{a}-{b}" for a, b in SUPPORTED_PAIRS)


def _pair_fn(type1: int, type2: int, what1: str, what2: str):
    """(pair function, swapped?) for two geom types, or a one-line ValueError."""
    swap = type1 > type2
    key = (type2, type1) if swap else (type1, type2)
    if key not in _PAIRS:
        raise MjstampError(
            f"signed distance between {what1} and {what2} is not supported; "
            f"supported pairs: {_supported_list()}"
        )
    return _PAIRS[key], swap


def signed_distance(
    type1: int,
    size1: jax.Array,
    pos1: jax.Array,
    mat1: jax.Array,
    type2: int,
    size2: jax.Array,
    pos2: jax.Array,
    mat2: jax.Array,
) -> jax.Array:
    """Signed distance between two geoms; negative when they penetrate.

    Symmetric: swapping the two geoms gives the same value.

    Args:
      type1: static ``mujoco.mjtGeom`` type of the first geom (a Python int).
      size1: (3,) ``geom_size`` row of the first geom.
      pos1: (3,) world position of the first geom.
      mat1: (3, 3) rotation of the first geom (local to world).
      type2: static ``mujoco.mjtGeom`` type of the second geom.
      size2: (3,) ``geom_size`` row of the second geom.
      pos2: (3,) world position of the second geom.
      mat2: (3, 3) rotation of the second geom.

    Returns:
      () signed distance: the gap when separated, minus the penetration depth
      when overlapping (see the module docstring for each pair's accuracy).

    Raises:
      ValueError: the pair of types is not supported.
    """
    type1, type2 = int(type1), int(type2)
    fn, swap = _pair_fn(
        type1, type2, f"'{_type_name(type1)}'", f"'{_type_name(type2)}'"
    )
    a = (jnp.asarray(size1), jnp.asarray(pos1), jnp.asarray(mat1).reshape(3, 3))
    b = (jnp.asarray(size2), jnp.asarray(pos2), jnp.asarray(mat2).reshape(3, 3))
    if swap:
        a, b = b, a
    return fn(*a, *b)


def _geom_id(m: mujoco.MjModel, geom: str | int) -> int:
    """Resolves a geom name or id, with a one-line error listing valid names."""
    names = [m.geom(i).name for i in range(m.ngeom)]
    if isinstance(geom, str):
        if geom in names:
            return names.index(geom)
        valid = ", ".join(repr(n) for n in names if n) or "(no named geoms)"
        raise MjstampError(f"unknown geom {geom!r}; valid geom names: {valid}")
    gid = int(geom)
    if not 0 <= gid < m.ngeom:
        raise MjstampError(f"geom id {gid} out of range; the model has {m.ngeom} geoms")
    return gid


def _describe(m: mujoco.MjModel, gid: int) -> str:
    name = m.geom(gid).name
    return f"'{_type_name(int(m.geom_type[gid]))}' geom " + (
        f"'{name}'" if name else f"#{gid}"
    )


def make_distance_fn(
    m: mujoco.MjModel, geom1: str | int, geom2: str | int
) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """Builds d(geom_xpos, geom_xmat), the signed distance between two geoms.

    Names, types and sizes are resolved once, here; the returned function is
    pure and jit/vmap/grad-able. Batch it over particles and time with
    ``jax.vmap``.

    Args:
      m: the model.
      geom1: name or id of the first geom.
      geom2: name or id of the second geom.

    Returns:
      A function of ``geom_xpos`` (ngeom, 3) and ``geom_xmat`` (ngeom, 3, 3) or
      (ngeom, 9) (as in ``mjx.Data`` and ``mujoco.MjData``) returning the ()
      signed distance, negative when the geoms penetrate.

    Raises:
      ValueError: an unknown name or id, the same geom twice, or an unsupported
        pair of geom types (the message names both).
    """
    g1, g2 = _geom_id(m, geom1), _geom_id(m, geom2)
    if g1 == g2:
        raise MjstampError(f"signed distance of {_describe(m, g1)} with itself")
    t1, t2 = int(m.geom_type[g1]), int(m.geom_type[g2])
    fn, swap = _pair_fn(t1, t2, _describe(m, g1), _describe(m, g2))
    if swap:
        g1, g2 = g2, g1
    size1, size2 = np.array(m.geom_size[g1]), np.array(m.geom_size[g2])

    def distance(geom_xpos: jax.Array, geom_xmat: jax.Array) -> jax.Array:
        dtype = geom_xpos.dtype
        return fn(
            jnp.asarray(size1, dtype),
            geom_xpos[g1],
            geom_xmat[g1].reshape(3, 3),
            jnp.asarray(size2, dtype),
            geom_xpos[g2],
            geom_xmat[g2].reshape(3, 3),
        )

    return distance
