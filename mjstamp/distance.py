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
local z (a plane's size only affects rendering). A mesh is collided by its
convex hull (``mesh_graph``), as MuJoCo and MJX do; a height field by the
triangular prisms under its cells, down to its base.

Every geom pair MJX 3.17 collides is covered (`SUPPORTED_PAIRS`, 27 pairs).
Accuracy, per pair, in float64 against ``mujoco.mj_geomDistance`` on random
poses on both sides of contact (``tests/test_distance.py``; "seen" is the
largest difference there). Float32 adds rounding only (≤ 1.3e-7 seen).

* plane vs sphere, capsule, cylinder, box, ellipsoid, mesh: exact (the depth
  of the deepest point when penetrating); ≤ 4e-16 seen.
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
* sphere, capsule, box or mesh vs mesh: exact, by enumeration over the hull's
  features like box-box: overlapping, the separating-axis test over the face
  normals and edge-direction cross products; separated, a vertex over a
  triangle or two edges. ≤ 4e-13 seen against MuJoCo's CCD at
  ``ccd_tolerance`` 1e-12 (at its default 1e-6, EPA stops up to 2e-7 short
  for a sphere or capsule partner).
* sphere, capsule, ellipsoid or cylinder vs ellipsoid, cylinder vs cylinder:
  exact to rounding, by the support-function dual below (a direction search).
  MuJoCo's CCD is the less accurate side here: compared with the closer of its
  runs at ``ccd_tolerance`` 1e-6 (where EPA stops up to 1e-6 short) and 1e-12
  (where GJK on curved shapes fails at some poses, by up to 2.6e-4), ≤ 3e-7
  seen (ellipsoid-ellipsoid; 8e-9 for the others), median ≤ 5e-13. At every
  pose of a 6,000-pose sweep (random sizes from needles to flat disks) where
  both runs disagreed with ours by more than 1e-8, a brute-force maximization
  of the same dual agreed with ours to 1e-16.
* height field vs sphere, capsule, box, mesh: the minimum over the prisms of
  a window of cells around the other geom of the polytope distance above,
  MuJoCo's definition (its collider runs CCD per prism). Exact: ≤ 7e-13 seen
  against ``mj_geomDistance`` on the height field (within its distmax, 0.05),
  and ≤ 1.1e-8 against each prism as a mesh (MuJoCo rounds the recentred
  vertices to float32). The window covers the cells within 2·rbound of the
  geom's centre (the whole field when smaller), so the distance is exact while
  it is at most the geom's ``geom_rbound``; beyond, it may be larger (never
  smaller), and it stays continuous below that bound as the window slides.
  N.B. ``mj_geomDistance`` on a height field raises each prism's top by its
  distmax, so with a large distmax it misreports penetration (0.1 off seen).

Cost, per evaluation: closed forms are the cheapest, then sphere or capsule vs
mesh, then the direction search; box-mesh and mesh-mesh grow with the hull's
edges squared; a height field costs its partner's per-prism cost times the
2·rows·cols prisms of the window. N.B. a fine height field under a large geom
is costly: the window grows as (2·rbound / cell size)². Gradients cost about
as much as values. Timings: benchmarks/results/README.md, "Measurements
quoted from the code".

Gradients: every branch uses safe norms (the double-``where`` trick); the
direction search differentiates through witness points held fixed (envelope
theorem), and the polytope enumerations through their winning candidate only.
So gradients are finite everywhere, including at contact, deep in penetration
and when two centres coincide (there a subgradient, often 0, is returned), and
match central differences on both sides of contact (tests, all 27 pairs). Gradients
with respect to ``mat`` are meant along rotations, which is all a rollout's
``geom_xmat`` can vary by: off rotations, formulas that agree on them (a
vertex-to-box and an edge-to-edge distance sharing a closest point) differ.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

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
_MESH = int(_G.mjGEOM_MESH)
_HFIELD = int(_G.mjGEOM_HFIELD)

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


# ---------------------------------------------------------------------------
# Polytopes: mesh convex hulls, boxes seen as polytopes, height-field prisms.
#
# Distances between polytopes are enumerated, like box-box: overlapping, the
# separating-axis test over the face normals and edge-direction cross products
# (the face normals of P ⊕ -Q, so the exact depth); separated, the closest
# features: a vertex over a triangle's interior, or two edges (the full
# segment-segment distance, which also covers vertex-edge and vertex-vertex).
# Every candidate is a distance between actual points of the two sets, or a
# separating-axis bound, so the min/max is exact and differentiates as its
# active candidate.


class _Poly(NamedTuple):
    """A convex polytope, in local or world coordinates.

    Attributes:
      verts: (nv, 3) vertices.
      tris: (nt, 3, 3) triangles covering the surface (for vertex-face tests).
      normals: (nf, 3) unit face normals, up to sign.
      edge_c: (ne, 3) edge centres.
      edge_u: (ne, 3) unit edge directions.
      edge_h: (ne,) edge half-lengths.
      dirs: (nd, 3) unit edge directions without repeats, up to sign.
    """

    verts: Any
    tris: Any
    normals: Any
    edge_c: Any
    edge_u: Any
    edge_h: Any
    dirs: Any


def _place(poly: _Poly, pos: jax.Array, mat: jax.Array) -> _Poly:
    """A local polytope moved to a pose."""
    rot = lambda x: x @ mat.T  # noqa: E731 - rows are vectors
    return _Poly(
        verts=pos + rot(poly.verts),
        tris=pos + rot(poly.tris),
        normals=rot(poly.normals),
        edge_c=pos + rot(poly.edge_c),
        edge_u=rot(poly.edge_u),
        edge_h=poly.edge_h,
        dirs=rot(poly.dirs),
    )


def _cast(tree, dtype):
    """Float arrays of a data pytree in `dtype`; ints and Python scalars kept."""
    def cast(x):
        if isinstance(x, np.ndarray) and np.issubdtype(x.dtype, np.floating):
            return jnp.asarray(x, dtype)
        return x

    return jax.tree.map(cast, tree)


def _box_triangles() -> np.ndarray:
    """Two triangles per box face, (12, 3), as indices into _SIGNS.

    Vertex k of _SIGNS has bit 2 - i of k set where its coordinate i is +1.
    """
    tris = []
    for i in range(3):
        for side in (0, 1):
            q = [k for k in range(8) if (k >> (2 - i)) & 1 == side]  # the face's 4
            tris += [(q[0], q[1], q[3]), (q[0], q[3], q[2])]  # split along q0-q3
    return np.array(tris)


_BOX_TRIS = _box_triangles()


def _box_poly(size: jax.Array) -> _Poly:
    """A box of half-sizes `size` as a local polytope (differentiable in size)."""
    dtype = size.dtype
    verts = jnp.asarray(_SIGNS, dtype) * size
    eye = jnp.eye(3, dtype=dtype)
    return _Poly(
        verts=verts,
        tris=verts[jnp.asarray(_BOX_TRIS, jnp.int32)],
        normals=eye,
        edge_c=jnp.asarray(_EDGE_SIGNS, dtype) * size,
        edge_u=jnp.repeat(eye, 4, axis=0),
        edge_h=jnp.repeat(size, 4),
        dirs=eye,
    )


def _segment_ends(a: jax.Array, b: jax.Array):
    """Edges from endpoints (..., 3) twice: centres, unit directions, halves."""
    v = b - a
    length = _safe_norm(v)
    u = v / jnp.where(length > 0, length, 1.0)[..., None]
    return (a + b) / 2, u, length / 2


def _mesh_hull(m: mujoco.MjModel, mesh_id: int, label: str) -> _Poly:
    """The convex hull MuJoCo collides a mesh by, from `mesh_graph` (numpy).

    Coplanar triangles' shared edges (diagonals of flat faces) are dropped:
    they lie inside a face, which the vertex-face tests already cover.
    """
    adr = int(m.mesh_graphadr[mesh_id])
    if adr < 0:
        raise MjstampError(f"{label}: the mesh has no convex hull (mesh_graph)")
    graph = m.mesh_graph[adr:]
    nvert, nface = int(graph[0]), int(graph[1])
    hull_ids = graph[2 + nvert : 2 + 2 * nvert]
    start = 2 + 3 * nvert + 3 * nface
    faces = graph[start : start + 3 * nface].reshape(nface, 3)
    vadr = int(m.mesh_vertadr[mesh_id])
    vert = m.mesh_vert[vadr : vadr + int(m.mesh_vertnum[mesh_id])].astype(np.float64)
    centroid = vert[hull_ids].mean(axis=0)

    tris = vert[faces]  # (nface, 3, 3)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = np.linalg.norm(n, axis=1)
    keep = area > 1e-12 * np.max(area)  # slivers carry no normal (and no NaN)
    faces, tris, n = faces[keep], tris[keep], n[keep] / area[keep, None]
    n *= np.sign(np.sum(n * (tris[:, 0] - centroid), axis=1))[:, None]  # outward

    normals = _unique_directions(n, signed=True)
    faces_of_edge: dict[tuple[int, int], list[int]] = {}
    for f, (i, j, k) in enumerate(faces):
        for a, b in ((i, j), (j, k), (k, i)):
            faces_of_edge.setdefault((min(a, b), max(a, b)), []).append(f)
    edges = np.array([
        e for e, fs in faces_of_edge.items()
        if len(fs) != 2 or np.dot(n[fs[0]], n[fs[1]]) < 1 - 1e-9
    ]).reshape(-1, 2)  # fmt: skip
    a, b = vert[edges[:, 0]], vert[edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    u = (b - a) / length[:, None]
    return _Poly(
        verts=vert[hull_ids],
        tris=tris,
        normals=normals,
        edge_c=(a + b) / 2,
        edge_u=u,
        edge_h=length / 2,
        dirs=_unique_directions(u, signed=False),
    )


def _unique_directions(v: np.ndarray, *, signed: bool) -> np.ndarray:
    """Unit rows of v without repeats (up to sign unless `signed`)."""
    out: list[np.ndarray] = []
    for x in v:
        if not any(
            (np.dot(x, y) if signed else abs(np.dot(x, y))) > 1 - 1e-12 for y in out
        ):
            out.append(x)
    return np.array(out)


def _vertex_face_all(v: jax.Array, tris: jax.Array) -> jax.Array:
    """Vertex-to-triangle distances where the vertex projects inside, else inf.

    Args:
      v: (..., nv, 3) vertices.
      tris: (..., nt, 3, 3) triangles.

    Returns:
      (..., nv, nt) distances.
    """
    v = v[..., :, None, :]
    a, b, c = tris[..., None, :, 0, :], tris[..., None, :, 1, :], tris[..., None, :, 2, :]
    n = jnp.cross(b - a, c - a)
    inside = (
        (_dot(jnp.cross(b - a, v - a), n) >= 0)
        & (_dot(jnp.cross(c - b, v - b), n) >= 0)
        & (_dot(jnp.cross(a - c, v - c), n) >= 0)
    )
    area2 = _safe_norm(n)
    inside &= area2 > 0  # a degenerate (flat prism) side has no interior
    dist = jnp.abs(_dot(n, v - a)) / jnp.where(inside, area2, 1.0)
    return jnp.where(inside, dist, jnp.inf)


def _segseg(c1, u1, h1, c2, u2, h2) -> jax.Array:
    """Segment-segment distances, broadcasting (see _segment_segment)."""
    ends = jnp.minimum(
        jnp.minimum(
            _point_segment(c1 + h1[..., None] * u1, c2, u2, h2),
            _point_segment(c1 - h1[..., None] * u1, c2, u2, h2),
        ),
        jnp.minimum(
            _point_segment(c2 + h2[..., None] * u2, c1, u1, h1),
            _point_segment(c2 - h2[..., None] * u2, c1, u1, h1),
        ),
    )
    return jnp.minimum(ends, _segment_interior(c1, u1, h1, c2, u2, h2))


def _gaps(axes: jax.Array, vp: jax.Array, vq: jax.Array) -> jax.Array:
    """Gaps (na,) between the projections of two vertex sets on unit axes."""
    pp, pq = vp @ axes.T, vq @ axes.T  # (nv, na)
    return jnp.maximum(
        jnp.min(pq, axis=0) - jnp.max(pp, axis=0),
        jnp.min(pp, axis=0) - jnp.max(pq, axis=0),
    )


# N.B. the polytope distances below enumerate hundreds to thousands of
# candidates. Each min/max is found on stopped values and only its winner is
# evaluated again with gradients: the same value and (away from ties, where
# any candidate's gradient is a subgradient) the same gradient, at a fraction
# of the cost of differentiating through every candidate.


def _best(values: jax.Array, *, largest: bool = False):
    """Flat index of the smallest (largest) of stopped values."""
    values = jax.lax.stop_gradient(values).ravel()
    return jnp.argmax(values) if largest else jnp.argmin(values)


def _sat(axes: jax.Array, ok: jax.Array, vp: jax.Array, vq: jax.Array) -> jax.Array:
    """Separating-axis value of two vertex sets over unit axes (na, 3)."""
    st = jax.lax.stop_gradient
    k = _best(jnp.where(ok, _gaps(*st((axes, vp, vq))), -jnp.inf), largest=True)
    return _gaps(axes[k][None], vp, vq)[0]


def _vertex_face(v: jax.Array, tris: jax.Array) -> jax.Array:
    """The least vertex-face distance of vertices (nv, 3) over triangles (nt, 3, 3).

    Only pairs where the vertex projects inside the triangle count (inf if none).
    """
    st = jax.lax.stop_gradient
    i, t = jnp.divmod(_best(_vertex_face_all(st(v), st(tris))), tris.shape[0])
    return _vertex_face_all(v[i][None], tris[t][None])[0, 0]


def _edge_edge(p: _Poly, q: _Poly) -> jax.Array:
    """Min over edge pairs of two polytopes of the segment-segment distance."""
    st = jax.lax.stop_gradient
    ps, qs = st(p), st(q)
    all_pairs = _segseg(
        ps.edge_c[:, None], ps.edge_u[:, None], ps.edge_h[:, None],
        qs.edge_c[None], qs.edge_u[None], qs.edge_h[None],
    )  # fmt: skip
    i, j = jnp.divmod(_best(all_pairs), q.edge_h.shape[0])
    return _segseg(p.edge_c[i], p.edge_u[i], p.edge_h[i], q.edge_c[j], q.edge_u[j], q.edge_h[j])


def _point_poly(p: jax.Array, q: _Poly) -> jax.Array:
    """Signed distance from a point (3,) to a polytope."""
    ok = jnp.ones(q.normals.shape[0], bool)
    sat = _sat(q.normals, ok, p[None], q.verts)
    separated = jnp.minimum(
        _vertex_face(p[None], q.tris),
        jnp.min(_point_segment(p, q.edge_c, q.edge_u, q.edge_h)),
    )
    return jnp.where(sat > 0.0, separated, sat)


def _segment_poly(c: jax.Array, u: jax.Array, h: jax.Array, q: _Poly) -> jax.Array:
    """Signed distance from the segment c + t·u, |t| ≤ h, to a polytope.

    Overlapping: the faces of segment ⊕ -polytope are the polytope's faces and
    u × (its edges). Separated: an end over a face, or the segment and an edge.
    """
    cross, ok = _cross_axes(u[None], q.dirs)
    axes = jnp.concatenate([q.normals, cross])
    ok = jnp.concatenate([jnp.ones(q.normals.shape[0], bool), ok])
    ends = jnp.stack([c + h * u, c - h * u])
    sat = _sat(axes, ok, ends, q.verts)
    separated = jnp.minimum(
        _vertex_face(ends, q.tris),
        jnp.min(_segseg(c, u, h, q.edge_c, q.edge_u, q.edge_h)),
    )
    return jnp.where(sat > 0.0, separated, sat)


def _poly_poly(p: _Poly, q: _Poly) -> jax.Array:
    """Signed distance between two polytopes."""
    cross, ok = _cross_axes(p.dirs, q.dirs)
    axes = jnp.concatenate([p.normals, q.normals, cross])
    nf = p.normals.shape[0] + q.normals.shape[0]
    ok = jnp.concatenate([jnp.ones(nf, bool), ok])
    sat = _sat(axes, ok, p.verts, q.verts)
    separated = jnp.minimum(
        jnp.minimum(_vertex_face(p.verts, q.tris), _vertex_face(q.verts, p.tris)),
        _edge_edge(p, q),
    )
    return jnp.where(sat > 0.0, separated, sat)


def _plane_mesh(_sp, pp, mp, hull, p, m):
    return jnp.min((p + hull.verts @ m.T - pp) @ mp[:, 2])


def _sphere_mesh(s, ps, _ms, hull, p, m):
    return _point_poly(ps, _place(hull, p, m)) - s[0]


def _capsule_mesh(s, pc, mc, hull, p, m):
    return _segment_poly(pc, mc[:, 2], s[1], _place(hull, p, m)) - s[0]


def _box_mesh(s, pb, mb, hull, p, m):
    return _poly_poly(_place(_box_poly(s), pb, mb), _place(hull, p, m))


def _mesh_mesh(hull1, p1, m1, hull2, p2, m2):
    return _poly_poly(_place(hull1, p1, m1), _place(hull2, p2, m2))


# ---------------------------------------------------------------------------
# Height fields: the minimum over the prisms near the other geom.


class _HField(NamedTuple):
    """A height field and the static window of cells searched around a geom.

    Attributes:
      height: (nrow, ncol) elevations in metres (``hfield_data·size[2]``).
      size: (4,) ``hfield_size``: x and y half-extents, top, base depth.
      window: (rows, cols) cells searched, a Python tuple.
      reach: the half-width of the square around the geom's centre that the
        window covers, a Python float.
    """

    height: Any
    size: Any
    window: tuple[int, int]
    reach: float


def _hfield_data(m: mujoco.MjModel, hfield_id: int, other_rbound: float) -> _HField:
    """Height-field data and a window covering 2·rbound around the other geom."""
    nrow, ncol = int(m.hfield_nrow[hfield_id]), int(m.hfield_ncol[hfield_id])
    adr = int(m.hfield_adr[hfield_id])
    size = np.array(m.hfield_size[hfield_id], np.float64)
    data = m.hfield_data[adr : adr + nrow * ncol].astype(np.float64)
    reach = 2.0 * float(other_rbound)
    dx, dy = 2 * size[0] / (ncol - 1), 2 * size[1] / (nrow - 1)
    cols = min(ncol - 1, int(np.ceil(2 * reach / dx)) + 1)
    rows = min(nrow - 1, int(np.ceil(2 * reach / dy)) + 1)
    return _HField(data.reshape(nrow, ncol) * size[2], size, (rows, cols), reach)


def _prism(top: jax.Array, base: jax.Array) -> _Poly:
    """The prism under a triangle top (3, 3) down to z = -base, as a _Poly."""
    bottom = top.at[:, 2].set(-base)
    verts = jnp.concatenate([top, bottom])
    i, j = jnp.array([0, 1, 2], jnp.int32), jnp.array([1, 2, 0], jnp.int32)
    sides = jnp.concatenate([
        jnp.stack([top[i], top[j], bottom[j]], 1),
        jnp.stack([top[i], bottom[j], bottom[i]], 1),
    ])  # fmt: skip
    tris = jnp.concatenate([top[None], bottom[None], sides])  # (8, 3, 3)
    zed = jnp.zeros_like(top[0]).at[2].set(1.0)
    up = jnp.cross(top[1] - top[0], top[2] - top[0])
    side_n = jnp.cross(bottom[j] - bottom[i], zed)
    normals = jnp.concatenate([up[None], zed[None], side_n])
    normals = normals / _safe_norm(normals)[:, None]  # cells have area: never 0
    c, u, h = _segment_ends(
        jnp.concatenate([top, bottom, top]), jnp.concatenate([top[j], bottom[j], bottom])
    )
    dirs = jnp.concatenate([u[:6], zed[None]])
    return _Poly(verts, tris, normals, c, u, h, dirs)


def _hfield_prisms(hf: _HField, centre: jax.Array) -> _Poly:
    """The 2·rows·cols prisms of the window around a point (hfield frame).

    N.B. the cells split along the diagonal from (col, row) to (col+1, row+1),
    as MuJoCo's and MJX's colliders do.
    """
    dtype = hf.height.dtype
    nrow, ncol = hf.height.shape
    rows, cols = hf.window
    sx, sy, _, base = hf.size[0], hf.size[1], hf.size[2], hf.size[3]
    dx, dy = 2 * sx / (ncol - 1), 2 * sy / (nrow - 1)
    # The window's first cell: integers, so no gradient flows through it.
    x, y = jax.lax.stop_gradient(centre[0]), jax.lax.stop_gradient(centre[1])
    c0 = jnp.clip(jnp.floor((x - hf.reach + sx) / dx), 0, ncol - 1 - cols).astype(int)
    r0 = jnp.clip(jnp.floor((y - hf.reach + sy) / dy), 0, nrow - 1 - rows).astype(int)
    z = jax.lax.dynamic_slice(hf.height, (r0, c0), (rows + 1, cols + 1))
    xs = (c0 + jnp.arange(cols + 1)).astype(dtype) * dx - sx
    ys = (r0 + jnp.arange(rows + 1)).astype(dtype) * dy - sy
    grid = jnp.stack(jnp.broadcast_arrays(xs[None, :], ys[:, None], z), -1)
    p00, p10 = grid[:-1, :-1], grid[:-1, 1:]  # (rows, cols, 3): (col, row) corners
    p01, p11 = grid[1:, :-1], grid[1:, 1:]
    tops = jnp.concatenate([
        jnp.stack([p01, p00, p11], -2).reshape(-1, 3, 3),
        jnp.stack([p00, p11, p10], -2).reshape(-1, 3, 3),
    ])  # fmt: skip
    return jax.vmap(_prism, in_axes=(0, None))(tops, base)


def _hfield_pair(other_distance):
    """Pair function hfield-X from other_distance(size, pos, mat, prism)."""

    def fn(hf, ph, mh, s, p, m):
        # The other geom in the height field's frame, where the prisms are built.
        pos, mat = (p - ph) @ mh, mh.T @ m
        prisms = _hfield_prisms(hf, pos)
        return jnp.min(jax.vmap(other_distance, in_axes=(None, None, None, 0))(s, pos, mat, prisms))

    return fn


_hfield_sphere = _hfield_pair(lambda s, p, _m, q: _point_poly(p, q) - s[0])
_hfield_capsule = _hfield_pair(lambda s, p, m, q: _segment_poly(p, m[:, 2], s[1], q) - s[0])
_hfield_box = _hfield_pair(lambda s, p, m, q: _poly_poly(_place(_box_poly(s), p, m), q))
_hfield_mesh = _hfield_pair(lambda hull, p, m, q: _poly_poly(_place(hull, p, m), q))


# ---------------------------------------------------------------------------
# Curved convex pairs (ellipsoids and cylinders): the support-function dual.
#
# For centrally symmetric convex sets A, B with centres a, b and support
# functions h_A, h_B, the signed distance on both sides of contact is
#     d = max over unit n of  g(n) = |n·(b - a)| - h_A(n) - h_B(n),
# the widest gap of their projections on a line (the separating-axis value
# over all axes; negative, it is the penetration depth). Every n gives a
# lower bound. The maximizer is found on stopped gradients (a grid over the
# sphere, then local refinement), and d is differentiated through the witness
# points a* ∈ A, b* ∈ B with b* - a* = d·n*, held in each shape's local
# coordinates: by the envelope theorem that is the gradient of the max.
# N.B. the value alone (g at n*) would give a wrong gradient where a support
# is not unique (a capsule's side, a cylinder's side or cap): there the
# gradient depends on where along the face the contact lies.

# Cores: a sphere is a point, a capsule a segment, grown by their radius.
_POINT, _SEGMENT, _ELLIPSOID_CORE, _CYLINDER_CORE = range(4)

_GRID_SIZE = 128  # directions over a hemisphere (g is even): spacing ≈ 0.22 rad
_GRID_NEIGHBOURS = 6  # for picking the grid's local maxima
_STARTS = 4  # local maxima of the grid refined in 2-D (penetrating, g is multimodal)
_LEVELS_2D = 26  # refinement steps: δ from 0.12 rad to 2e-9, Newton does the rest
_RIDGE_GRID = 48  # angles over a great circle's half
_RIDGE_STARTS = 2
_LEVELS_1D = 30  # δ from π/48 to 6e-11: g is smooth along a ridge, so O(δ²)
_WITNESS_ITERS = 24  # alternating projections when both supports can be faces


def _fibonacci_hemisphere(k: int) -> np.ndarray:
    """Near-uniform unit vectors with z > 0, (k, 3): a Fibonacci lattice."""
    i = np.arange(k) + 0.5
    z = i / k
    phi = i * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


_GRID = _fibonacci_hemisphere(_GRID_SIZE)
# Neighbours on the projective plane: n and -n are the same direction.
_GRID_NBRS = np.argsort(-np.abs(_GRID @ _GRID.T), axis=1)[:, 1 : 1 + _GRID_NEIGHBOURS]
# 3×3 stencil (centre first, so ties keep it) and the least-squares (here
# exact) fit of a quadratic a + b·x + c·y + d·x² + e·xy + f·y² to it.
_STENCIL = np.array(
    [(0, 0)] + [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)], float
)
_QUAD_FIT = np.linalg.pinv(
    np.stack([np.ones(9), _STENCIL[:, 0], _STENCIL[:, 1], _STENCIL[:, 0] ** 2,
              _STENCIL[:, 0] * _STENCIL[:, 1], _STENCIL[:, 1] ** 2], -1)
)  # fmt: skip  (6, 9)
_STENCIL_1D = np.array([0.0, -2.0, -1.0, 1.0, 2.0])


def _normalize(x: jax.Array) -> jax.Array:
    """The rows of x scaled to unit length (0 stays 0), for stopped values."""
    n = jnp.sqrt(jnp.sum(x * x, axis=-1, keepdims=True))
    return x / jnp.where(n > 0, n, 1.0)


def _tangents(n: jax.Array):
    """An orthonormal pair (..., 3) twice, perpendicular to unit n (..., 3)."""
    pick = jnp.abs(n[..., :1]) < 0.9
    a = jnp.where(pick, jnp.array([1.0, 0.0, 0.0], n.dtype), jnp.array([0.0, 1.0, 0.0], n.dtype))
    e1 = _normalize(a - _dot(a, n)[..., None] * n)
    return e1, jnp.cross(n, e1)


def _sgn(x: jax.Array) -> jax.Array:
    """Sign with sgn(0) = 1: picks one support point where there are many."""
    return jnp.where(x >= 0, 1.0, -1.0).astype(x.dtype)


def _core_scale(core: int, size: jax.Array) -> jax.Array:
    """Local scaling of a core: unit-shape coordinates σ̂ to local ones."""
    zero = jnp.zeros((), size.dtype)
    if core == _POINT:
        return jnp.stack([zero, zero, zero])
    if core == _SEGMENT:
        return jnp.stack([zero, zero, size[1]])
    if core == _ELLIPSOID_CORE:
        return size
    return jnp.stack([size[0], size[0], size[1]])


def _core_support(core: int, scale: jax.Array, nl: jax.Array) -> jax.Array:
    """A support point σ̂ (..., 3) of the unit core along local directions nl."""
    if core == _POINT:
        return jnp.zeros_like(nl)
    if core == _SEGMENT:
        return jnp.zeros_like(nl).at[..., 2].set(_sgn(nl[..., 2]))
    if core == _ELLIPSOID_CORE:
        return _normalize(scale * nl)  # x = S²n/|Sn| = S·(Sn/|Sn|)
    rim = nl[..., :2]
    rho = jnp.sqrt(jnp.sum(rim * rim, axis=-1, keepdims=True))
    rim = jnp.where(rho > 0, rim / jnp.where(rho > 0, rho, 1.0), jnp.array([1.0, 0.0], nl.dtype))
    return jnp.concatenate([rim, _sgn(nl[..., 2:])], -1)


def _face_project(core: int, scale: jax.Array, nl: jax.Array, q: jax.Array):
    """σ̂ of the point nearest local q (3,) on the support face along unit nl.

    The face is a point, a segment (a capsule's axis, a cylinder's side) or a
    disk (a cylinder's cap); a direction within sqrt(eps) of a face's normal
    counts as on it, which the ridge search below hits to rounding.

    Returns:
      σ̂ (3,) and whether the face is a segment (then along local z).
    """
    tol = np.sqrt(np.finfo(nl.dtype).eps)
    h = jnp.where(scale[2] > 0, scale[2], 1.0)
    along = jnp.clip(q[2] / h, -1.0, 1.0)
    end = _sgn(nl[2])
    side = jnp.abs(nl[2]) <= tol
    if core == _SEGMENT:
        return jnp.zeros_like(q).at[2].set(jnp.where(side, along, end)), side
    rim = _core_support(core, scale, nl)[:2]
    disk = q[:2] / scale[0]
    rho = jnp.sqrt(jnp.sum(disk * disk))
    disk = disk / jnp.maximum(rho, 1.0)
    cap = jnp.sqrt(nl[0] * nl[0] + nl[1] * nl[1]) <= tol
    xy = jnp.where(cap, disk, rim)
    return jnp.concatenate([xy, jnp.where(side & ~cap, along, end)[None]]), side & ~cap


def _refine_2d(g, n: jax.Array, delta0: float) -> jax.Array:
    """Local maxima of g near the unit rows of n (k, 3).

    Each step evaluates a 3×3 stencil of spacing δ in the tangent plane and the
    Newton point of the quadratic through it (at most 2δ away), moves to the
    best, and halves δ unless the Newton point was better and beyond the
    stencil. Smooth maxima converge quadratically whatever their anisotropy;
    the stencil alone keeps the step safe where g is not smooth.
    """
    dtype = n.dtype
    stencil, fit = jnp.asarray(_STENCIL, dtype), jnp.asarray(_QUAD_FIT, dtype)
    k = n.shape[0]

    def at(n, delta, offs):  # unit directions at tangent offsets (k, m, 2)·δ
        e1, e2 = _tangents(n)
        x, y = delta[:, None, None] * offs[..., :1], delta[:, None, None] * offs[..., 1:]
        return _normalize(n[:, None] + x * e1[:, None] + y * e2[:, None])

    def step(_, carry):
        n, delta = carry
        offs = jnp.broadcast_to(stencil, (k, 9, 2))
        vals = g(at(n, delta, offs))  # (k, 9)
        _, b, c, d, e, f = (vals @ fit.T).T
        det = 4 * d * f - e * e
        concave = (det > 0) & (d < 0)
        safe = jnp.where(concave, det, 1.0)
        x = jnp.where(concave, (e * c - 2 * f * b) / safe, 0.0)
        y = jnp.where(concave, (e * b - 2 * d * c) / safe, 0.0)
        shrink = 2.0 / jnp.maximum(2.0, jnp.maximum(jnp.abs(x), jnp.abs(y)))
        newton = jnp.stack([x * shrink, y * shrink], -1)[:, None]  # (k, 1, 2)
        offs = jnp.concatenate([offs, newton], 1)
        cand = jnp.concatenate([at(n, delta, offs[:, :9]), at(n, delta, newton)], 1)
        vals = jnp.concatenate([vals, g(cand[:, 9:])], 1)
        best = jnp.argmax(vals, axis=1)
        take = lambda a: jnp.take_along_axis(a, best[:, None, None], 1)[:, 0]  # noqa: E731
        inner = jnp.max(jnp.abs(take(offs)), axis=-1) <= 1.0
        return take(cand), jnp.where(inner, delta / 2, delta)

    delta = jnp.full((k,), delta0, dtype)
    return jax.lax.fori_loop(0, _LEVELS_2D, step, (n, delta))[0]


def _refine_ridge(g, w: jax.Array) -> jax.Array:
    """Local maxima of g on the great circle perpendicular to w: (starts, 3).

    A support that is a face (a segment's side, a cylinder's side) puts a kink
    in g along this circle; there the maximum often lies exactly on it, where a
    2-D search crawls. On the circle a 1-D zoom is exact for unimodal pieces.
    """
    dtype = w.dtype
    e1, e2 = _tangents(_normalize(w))
    circle = lambda t: jnp.cos(t)[..., None] * e1 + jnp.sin(t)[..., None] * e2  # noqa: E731
    theta = jnp.arange(_RIDGE_GRID, dtype=dtype) * (np.pi / _RIDGE_GRID)
    v = g(circle(theta))
    local = (v >= jnp.roll(v, 1)) & (v >= jnp.roll(v, -1))
    _, idx = jax.lax.top_k(jnp.where(local, v, -jnp.inf), _RIDGE_STARTS)
    stencil = jnp.asarray(_STENCIL_1D, dtype)

    def step(_, carry):
        t, delta = carry
        cand = t[:, None] + delta * stencil[None]
        best = jnp.argmax(g(circle(cand)), axis=1)
        # A unimodal maximum lies within δ of the best stencil point.
        return jnp.take_along_axis(cand, best[:, None], 1)[:, 0], delta / 2

    delta = jnp.asarray(np.pi / _RIDGE_GRID, dtype)
    t, _ = jax.lax.fori_loop(0, _LEVELS_1D, step, (theta[idx], delta))
    return circle(t)


# N.B. over 80 lines: one numerical routine (direction search, witness points, the
# gradient path) whose steps share a dozen locals; split, they would travel as arguments.
def _convex_pair(core_a: int, core_b: int):
    """Pair function for two curved (or point/segment) cores, by the dual.

    Long: the dual's derivation reads as one piece (supports, Newton steps, the
    face cases); split, its steps would pass a dozen arrays between them.
    """
    faces = (_SEGMENT, _CYLINDER_CORE)  # supports that can be a whole face

    def fn(sa, pa, ma, sb, pb, mb):
        """Signed distance of the two cores at their poses (long: see `_convex_pair`)."""
        dtype = pa.dtype
        scale_a, scale_b = _core_scale(core_a, sa), _core_scale(core_b, sb)
        radii = (sa[0] if core_a in (_POINT, _SEGMENT) else 0.0) + (
            sb[0] if core_b in (_POINT, _SEGMENT) else 0.0
        )
        st = jax.lax.stop_gradient
        (pa0, ma0, scale_a0), (pb0, mb0, scale_b0) = st((pa, ma, scale_a)), st((pb, mb, scale_b))
        c = pb0 - pa0

        def support(n):  # h_A(n) + h_B(n), n (..., 3) world
            na, nb = n @ ma0, n @ mb0
            return (_dot(na, scale_a0 * _core_support(core_a, scale_a0, na))
                    + _dot(nb, scale_b0 * _core_support(core_b, scale_b0, nb)))  # fmt: skip

        def g(n):
            return jnp.abs(_dot(n, c)) - support(n)

        # Candidates: the grid's best local maxima refined in 2-D; the circles
        # where a support is a side; the directions where it is a cap, or
        # where two sides meet.
        ridges = [m0[:, 2] for core, m0 in ((core_a, ma0), (core_b, mb0)) if core in faces]
        points = [m0[:, 2] for core, m0 in ((core_a, ma0), (core_b, mb0))
                  if core == _CYLINDER_CORE]  # fmt: skip
        if len(ridges) == 2:
            points.append(_normalize(jnp.cross(ridges[0], ridges[1])))
        grid = jnp.asarray(_GRID, dtype)
        v = g(grid)
        # N.B. int32 index constants: numpy's int64 ones trip JAX once
        # enable_x64 toggled in the process (as for the float ones above).
        local = v >= jnp.max(v[jnp.asarray(_GRID_NBRS, jnp.int32)], axis=1)
        _, idx = jax.lax.top_k(jnp.where(local, v, -jnp.inf), _STARTS)
        cands = [_refine_2d(g, grid[idx], 0.12)]
        cands += [_refine_ridge(g, w) for w in ridges]
        if points:
            cands.append(_normalize(jnp.stack(points)))
        cands = jnp.concatenate(cands)
        vals = g(cands)
        n = cands[jnp.argmax(vals)]
        n = n * _sgn(_dot(n, c))  # from A towards B
        core_gap = jnp.max(vals)  # n·(b* - a*) at the optimum, radii aside

        # Witnesses: supports along ±n, then, where a support is a face, the
        # point of it facing the other witness (alternating when both are).
        na, nb = n @ ma0, -n @ mb0
        ua = _core_support(core_a, scale_a0, na)
        ub = _core_support(core_b, scale_b0, nb)
        world = lambda p0, m0, s0, u: p0 + m0 @ (s0 * u)  # noqa: E731
        both = core_a in faces and core_b in faces

        def project(carry, _):
            ua, ub, _, _ = carry
            seg_a = seg_b = jnp.array(False)
            if core_a in faces:
                q = (world(pb0, mb0, scale_b0, ub) - core_gap * n - pa0) @ ma0
                ua, seg_a = _face_project(core_a, scale_a0, na, q)
            if core_b in faces:
                q = (world(pa0, ma0, scale_a0, ua) + core_gap * n - pb0) @ mb0
                ub, seg_b = _face_project(core_b, scale_b0, nb, q)
            return (ua, ub, seg_a, seg_b), None

        no = jnp.array(False)
        (ua, ub, seg_a, seg_b), _ = jax.lax.scan(
            project, (ua, ub, no, no), None, length=_WITNESS_ITERS if both else 1
        )
        if both:
            # Two side segments: alternating projections between crossing
            # lines converge slowly, so take the lines' closest points.
            ca = world(pa0, ma0, scale_a0, ua.at[2].set(0.0))
            cb = world(pb0, mb0, scale_b0, ub.at[2].set(0.0)) - core_gap * n
            u, v, w = ma0[:, 2], mb0[:, 2], ca - cb
            b, d, e = jnp.dot(u, v), jnp.dot(u, w), jnp.dot(v, w)
            denom = 1.0 - b * b
            ok = seg_a & seg_b & (denom > 1e-12)
            safe = jnp.where(ok, denom, 1.0)
            ha = jnp.where(scale_a0[2] > 0, scale_a0[2], 1.0)
            hb = jnp.where(scale_b0[2] > 0, scale_b0[2], 1.0)
            ta = jnp.clip((b * e - d) / safe / ha, -1.0, 1.0)
            tb = jnp.clip((e - b * d) / safe / hb, -1.0, 1.0)
            ua = jnp.where(ok, ua.at[2].set(ta), ua)
            ub = jnp.where(ok, ub.at[2].set(tb), ub)
        n, ua, ub = st((n, ua, ub))
        # The value is g(n*), a lower bound, exact to rounding at the optimum;
        # the witnesses carry the gradient.
        gap = jnp.dot(n, world(pb, mb, scale_b, ub) - world(pa, ma, scale_a, ua))
        return gap + st(core_gap - gap) - radii

    return fn


_sphere_ellipsoid = _convex_pair(_POINT, _ELLIPSOID_CORE)
_capsule_ellipsoid = _convex_pair(_SEGMENT, _ELLIPSOID_CORE)
_ellipsoid_ellipsoid = _convex_pair(_ELLIPSOID_CORE, _ELLIPSOID_CORE)
_ellipsoid_cylinder = _convex_pair(_ELLIPSOID_CORE, _CYLINDER_CORE)
_cylinder_cylinder = _convex_pair(_CYLINDER_CORE, _CYLINDER_CORE)


_PAIRS: dict[tuple[int, int], Callable[..., jax.Array]] = {
    (_PLANE, _SPHERE): _plane_sphere,
    (_PLANE, _CAPSULE): _plane_capsule,
    (_PLANE, _ELLIPSOID): _plane_ellipsoid,
    (_PLANE, _CYLINDER): _plane_cylinder,
    (_PLANE, _BOX): _plane_box,
    (_PLANE, _MESH): _plane_mesh,
    (_HFIELD, _SPHERE): _hfield_sphere,
    (_HFIELD, _CAPSULE): _hfield_capsule,
    (_HFIELD, _BOX): _hfield_box,
    (_HFIELD, _MESH): _hfield_mesh,
    (_SPHERE, _SPHERE): _sphere_sphere,
    (_SPHERE, _CAPSULE): _sphere_capsule,
    (_SPHERE, _ELLIPSOID): _sphere_ellipsoid,
    (_SPHERE, _CYLINDER): _sphere_cylinder,
    (_SPHERE, _BOX): _sphere_box,
    (_SPHERE, _MESH): _sphere_mesh,
    (_CAPSULE, _CAPSULE): _capsule_capsule,
    (_CAPSULE, _ELLIPSOID): _capsule_ellipsoid,
    (_CAPSULE, _CYLINDER): _capsule_cylinder,
    (_CAPSULE, _BOX): _capsule_box,
    (_CAPSULE, _MESH): _capsule_mesh,
    (_ELLIPSOID, _ELLIPSOID): _ellipsoid_ellipsoid,
    (_ELLIPSOID, _CYLINDER): _ellipsoid_cylinder,
    (_CYLINDER, _CYLINDER): _cylinder_cylinder,
    (_BOX, _BOX): _box_box,
    (_BOX, _MESH): _box_mesh,
    (_MESH, _MESH): _mesh_mesh,
}

SUPPORTED_PAIRS: tuple[tuple[str, str], ...] = tuple(
    (_type_name(a), _type_name(b)) for a, b in _PAIRS
)
"""The supported (type, type) pairs by name; either order works."""


class UnsupportedPairError(MjstampError):
    """A pair of geom types without a JAX signed distance (not in `SUPPORTED_PAIRS`)."""


def _supported_list() -> str:
    return ", ".join(f"{a}-{b}" for a, b in SUPPORTED_PAIRS)


def _pair_fn(type1: int, type2: int, what1: str, what2: str):
    """(pair function, swapped?) for two geom types, or a one-line ValueError."""
    swap = type1 > type2
    key = (type2, type1) if swap else (type1, type2)
    if key not in _PAIRS:
        raise UnsupportedPairError(
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
      ValueError: the pair of types is not supported, or needs model data (a
        mesh's vertices, a height field's elevations: see make_distance_fn).
    """
    type1, type2 = int(type1), int(type2)
    what1, what2 = f"'{_type_name(type1)}'", f"'{_type_name(type2)}'"
    fn, swap = _pair_fn(type1, type2, what1, what2)
    for t, what in ((type1, what1), (type2, what2)):
        if t in _MODEL_DATA_TYPES:
            raise MjstampError(
                f"signed distance between {what1} and {what2} needs the model's "
                f"{what} data; use make_distance_fn(m, geom1, geom2)"
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


_MODEL_DATA_TYPES = (_MESH, _HFIELD)


def _geom_data(m: mujoco.MjModel, g: int, other: int):
    """What a pair function takes for geom g: its size, hull or height field."""
    t = int(m.geom_type[g])
    if t == _MESH:
        return _mesh_hull(m, int(m.geom_dataid[g]), _describe(m, g))
    if t == _HFIELD:
        return _hfield_data(m, int(m.geom_dataid[g]), float(m.geom_rbound[other]))
    return np.array(m.geom_size[g])


def make_distance_fn(
    m: mujoco.MjModel, geom1: str | int, geom2: str | int
) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """Builds d(geom_xpos, geom_xmat), the signed distance between two geoms.

    Names, types, sizes, mesh hulls and height fields are resolved once, here;
    the returned function is pure and jit/vmap/grad-able. Batch it over particles and time with
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
    data1, data2 = _geom_data(m, g1, g2), _geom_data(m, g2, g1)

    def distance(geom_xpos: jax.Array, geom_xmat: jax.Array) -> jax.Array:
        dtype = geom_xpos.dtype
        return fn(
            _cast(data1, dtype),
            geom_xpos[g1],
            geom_xmat[g1].reshape(3, 3),
            _cast(data2, dtype),
            geom_xpos[g2],
            geom_xmat[g2].reshape(3, 3),
        )

    return distance


def make_distance_bound(
    m: mujoco.MjModel, geom1: str | int, geom2: str | int
) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """Builds ℓ(geom_xpos, geom_xmat): a cheap bound that is > 0 only if two geoms are apart.

    From MuJoCo's own bounding volumes, for any pair of geom types: each geom
    lies in its bounding sphere (``geom_rbound`` about its frame's origin) and
    in its box (``geom_aabb``, in its frame); a plane is its half-space. ℓ is
    the larger of the gap between the two spheres and the gap between the
    smaller geom's sphere and the larger geom's box (a plane: the height of the
    other geom's sphere above it). Where ℓ > 0 the geoms are at least ℓ apart, so no
    collider can report a contact at zero margin; `verify.Replay` asks MuJoCo C
    (`mjstamp.kinematics.touching`) only at the other states. A few flops
    per pair, far fewer than the signed distance of a curved pair.

    Args:
      m: the model.
      geom1: name or id of the first geom.
      geom2: name or id of the second geom.

    Returns:
      A pure function of ``geom_xpos`` (ngeom, 3) and ``geom_xmat`` (ngeom, 3, 3)
      or (ngeom, 9) returning the () bound; -inf (nothing to skip) for a plane
      against a plane or height field, which nothing collides.
    """
    g1, g2 = _geom_id(m, geom1), _geom_id(m, geom2)
    t1, t2 = int(m.geom_type[g1]), int(m.geom_type[g2])

    def nothing_to_skip(geom_xpos: jax.Array, geom_xmat: jax.Array) -> jax.Array:
        return jnp.full((), -jnp.inf, geom_xpos.dtype)

    if _PLANE in (t1, t2):
        plane, other = (g1, g2) if t1 == _PLANE else (g2, g1)
        if int(m.geom_type[other]) in (_PLANE, _HFIELD):
            return nothing_to_skip
        radius = float(m.geom_rbound[other])

        def above_plane(geom_xpos: jax.Array, geom_xmat: jax.Array) -> jax.Array:
            normal = geom_xmat[plane].reshape(3, 3)[:, 2]
            return _dot(normal, geom_xpos[other] - geom_xpos[plane]) - radius

        return above_plane
    # N.B. one box, the larger: against the smaller geom's sphere it is the tighter
    # term (a ball against a long wall), and a second costs as much again.
    if np.prod(m.geom_aabb[g1, 3:]) < np.prod(m.geom_aabb[g2, 3:]):
        g1, g2 = g2, g1
    r1, r2 = float(m.geom_rbound[g1]), float(m.geom_rbound[g2])
    if not (r1 > 0 and r2 > 0):
        return nothing_to_skip  # N.B. no bounding sphere (only planes have none): ask C
    centre, half = np.array(m.geom_aabb[g1, :3]), np.array(m.geom_aabb[g1, 3:])

    def bound(geom_xpos: jax.Array, geom_xmat: jax.Array) -> jax.Array:
        delta = geom_xpos[g2] - geom_xpos[g1]
        # N.B. elementwise (matᵀ·delta as a sum of products): XLA fuses it with the rest.
        local = jnp.sum(geom_xmat[g1].reshape(3, 3) * delta[:, None], axis=0) - centre
        to_box = _safe_norm(jnp.maximum(jnp.abs(local) - half, 0.0))
        return jnp.maximum(_safe_norm(delta) - r1, to_box) - r2

    return bound
