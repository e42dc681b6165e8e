"""Ports of MuJoCo C's primitive colliders (engine_collision_primitive.c, engine_collision_box.c).

MJX 3.17 has its own versions of these pairs, close to C's but not equal: its
plane-box keeps the corners within 1 mm of the deepest, its plane-cylinder has
three slots where C has four, its capsule-capsule one where C has two for
parallel capsules, its sphere-cylinder is a signed-distance descent where C is
analytic, and its plane-capsule frame does not take C's tangent. The functions
here follow C branch for branch (same formulas in the same order, the same
thresholds, the same choice of which candidate contacts survive), with C's
data-dependent branches as selects of both sides, so they are jit-able,
vmappable and differentiable.

Registered at import in `PORTED`:

==================  =========================================  =====
pair                C function                                 slots
==================  =========================================  =====
plane-capsule       mjc_PlaneCapsule                           2
plane-cylinder      mjc_PlaneCylinder                          4
plane-box           mjc_PlaneBox                               4
sphere-capsule      mjc_SphereCapsule (mjraw_SphereCapsule)    1
sphere-cylinder     mjc_SphereCylinder                         1
sphere-box          mjc_SphereBox (engine_collision_box.c)     1
capsule-capsule     mjc_CapsuleCapsule (binary: segWeights)    2
==================  =========================================  =====

Plane-sphere, sphere-sphere and plane-ellipsoid are left to MJX, whose
functions give C's contacts already (tests/test_contacts_primitive.py checks it).

N.B. every intermediate of both sides of a select must stay finite, with a
finite derivative, on every pose (a NaN on the side not taken still poisons
the reverse pass through `jnp.where`): divisions and square roots are guarded
by the double-where trick.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco

from mjstamp.colliders import FAR, PORTED, collider
from mjstamp.colliders.cmath import cross as _cross
from mjstamp.colliders.cmath import dot as _dot
from mjstamp.colliders.cmath import frame as _frame
from mjstamp.colliders.cmath import mat_t_vec as _matTvec
from mjstamp.colliders.cmath import matvec as _matvec
from mjstamp.colliders.cmath import normalize as _normalize
from mjstamp.colliders.cmath import sqrt as _sqrt

__all__ = [
    "capsule_capsule",
    "plane_box",
    "plane_capsule",
    "plane_cylinder",
    "sphere_box",
    "sphere_capsule",
    "sphere_cylinder",
]

# C's mjMINVAL (mjmodel.h): below it a length counts as zero.
MINVAL = 1e-15

_T = mujoco.mjtGeom


class _Con(NamedTuple):
    """One candidate contact, C's `mjPreContact` plus whether C emits it.

    Attributes:
      dist: () signed distance.
      pos: (3,) contact point.
      normal: (3,) unit normal, from geom1 to geom2.
      tangent: (3,) C's `tangent` (zero: none set).
      ok: () bool, whether C's routine emits this contact.
    """

    dist: jax.Array
    pos: jax.Array
    normal: jax.Array
    tangent: jax.Array
    ok: jax.Array


# ----------------------------------------------------------------------------- C's small helpers


def _clip01(x: jax.Array) -> jax.Array:
    """Clips x to [0, 1] as the binary does: `x < 0 ? 0 : min(1, x)`."""
    return jnp.where(x < 0, 0.0, jnp.where(1.0 < x, 1.0, x))


def _div(num: jax.Array, den: jax.Array, ok: jax.Array) -> jax.Array:
    """Divides where `ok` (den nonzero there), 0 elsewhere, with finite derivatives."""
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _zero3(like: jax.Array) -> jax.Array:
    return jnp.zeros(3, like.dtype)


def _select(cond: jax.Array, a: _Con, b: _Con) -> _Con:
    """Contact `a` where cond, else `b` (C's if/else between two candidates)."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(cond, x, y), a, b)


def _emit(cons: list[_Con]) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Slots of the candidates: C's contacts where `ok`, `FAR` elsewhere.

    Args:
      cons: the candidate contacts, one per slot.

    Returns:
      dist (k,), pos (k, 3), frame (k, 3, 3).
    """
    dist = jnp.stack([jnp.where(c.ok, c.dist, FAR) for c in cons])
    pos = jnp.stack([jnp.where(c.ok, c.pos, 0.0) for c in cons])
    frame = jnp.stack([_frame(c.normal, c.tangent) for c in cons])
    return dist, pos, frame


def _first(cons: list[_Con], k: int) -> list[_Con]:
    """The first `k` emitted candidates, in order (C fills its buffer in that order).

    Args:
      cons: candidates in C's order.
      k: slots.

    Returns:
      k contacts; slot j holds the (j+1)-th candidate with `ok`, or none (`ok` false).
    """
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cons)
    rank = jnp.cumsum(stacked.ok.astype(jnp.int32))
    out = []
    for j in range(k):
        hit = stacked.ok & (rank == j + 1)  # one-hot (or none) over the candidates

        def pick(x, hit=hit):
            h = hit.reshape(hit.shape + (1,) * (x.ndim - 1))
            return jnp.sum(jnp.where(h, x, jnp.zeros_like(x)), axis=0)

        out.append(_Con(pick(stacked.dist), pick(stacked.pos), pick(stacked.normal),
                        pick(stacked.tangent), jnp.any(hit)))
    return out


# ----------------------------------------------------------------------------- C's raw colliders


def _raw_plane_sphere(margin, pos1, normal, pos2, radius2) -> _Con:
    """C's `mjraw_PlaneSphere` (engine_collision_primitive.c).

    Args:
      margin: () the pair's margin.
      pos1: (3,) a point of the plane.
      normal: (3,) the plane's normal (its frame's z axis).
      pos2: (3,) the sphere's centre.
      radius2: () its radius.

    Returns:
      the contact (`ok` false where C returns 0).
    """
    cdist = _dot(pos2 - pos1, normal)
    ok = ~(cdist > margin + radius2)
    dist = cdist - radius2
    pos = pos2 + normal * (-dist / 2 - radius2)
    return _Con(dist, pos, normal, _zero3(pos1), ok)


def _raw_sphere_sphere(margin, pos1, mat1, radius1, pos2, mat2, radius2) -> _Con:
    """C's `mjraw_SphereSphere` (engine_collision_primitive.c).

    Args:
      margin: () the pair's margin.
      pos1: (3,) sphere 1's centre.
      mat1: (3, 3) its frame (the z axes give the normal of concentric spheres).
      radius1: () its radius.
      pos2: (3,) sphere 2's centre.
      mat2: (3, 3) its frame.
      radius2: () its radius.

    Returns:
      the contact (`ok` false where C returns 0).
    """
    dif = pos1 - pos2
    cdist_sqr = _dot(dif, dif)
    min_dist = margin + radius1 + radius2
    ok = ~(cdist_sqr > min_dist * min_dist)
    dist = _sqrt(cdist_sqr) - radius1 - radius2
    normal, length = _normalize(pos2 - pos1)
    # concentric: the normal is the cross product of the z axes ((1, 0, 0) if parallel)
    across, _ = _normalize(_cross(mat1[:, 2], mat2[:, 2]))
    normal = jnp.where(length < MINVAL, across, normal)
    pos = normal * (radius1 + dist / 2) + pos1
    return _Con(dist, pos, normal, _zero3(pos1), ok)


def _raw_sphere_capsule(margin, pos1, mat1, size1, pos2, mat2, size2) -> _Con:
    """C's `mjraw_SphereCapsule` (engine_collision_primitive.c).

    Args:
      margin: () the pair's margin.
      pos1: (3,) the sphere's centre.
      mat1: (3, 3) its frame.
      size1: (3,) its size (radius first).
      pos2: (3,) the capsule's centre.
      mat2: (3, 3) its frame (z: the axis).
      size2: (3,) its size (radius, half-length).

    Returns:
      the contact.
    """
    length = size2[1]
    axis = mat2[:, 2]
    x = jnp.clip(_dot(axis, pos1 - pos2), -length, length)
    near = axis * x + pos2
    return _raw_sphere_sphere(margin, pos1, mat1, size1[0], near, mat2, size2[0])


# ----------------------------------------------------------------------------- plane pairs


@collider(ncon=2)
def plane_capsule(plane, cap, margin):
    """Plane-capsule contacts: C's `mjc_PlaneCapsule` (engine_collision_primitive.c).

    One plane-sphere test per end of the capsule's segment, each contact's
    frame aligned with the capsule's axis (C's tangent).

    Args:
      plane: `GeomInfo` of the plane (pos (3,), mat (3, 3), size (3,)).
      cap: `GeomInfo` of the capsule.
      margin: () the pair's margin.

    Returns:
      dist (2,), pos (2, 3), frame (2, 3, 3); unused slots at `FAR`.
    """
    normal = plane.mat[:, 2]
    axis = cap.mat[:, 2]
    segment = cap.size[1] * axis
    cons = [_raw_plane_sphere(margin, plane.pos, normal, cap.pos + s, cap.size[0])
            for s in (segment, -segment)]
    return _emit([c._replace(tangent=axis) for c in cons])


@collider(ncon=4)
def plane_cylinder(plane, cyl, margin):
    """Plane-cylinder contacts: C's `mjc_PlaneCylinder` (engine_collision_primitive.c).

    The rim point nearest the plane, the same point of the other disk, and two
    points of the near disk at ±120° from the first (C's "triangle"), each where
    its distance is within the margin; none at all when the nearest point is not.

    Args:
      plane: `GeomInfo` of the plane.
      cyl: `GeomInfo` of the cylinder (size: radius, half-height).
      margin: () the pair's margin.

    Returns:
      dist (4,), pos (4, 3), frame (4, 3, 3); unused slots at `FAR`.
    """
    normal = plane.mat[:, 2]
    axis = cyl.mat[:, 2]
    radius, height = cyl.size[0], cyl.size[1]

    # make the axis point towards the plane
    prjaxis = _dot(normal, axis)
    flip = prjaxis > 0
    axis = jnp.where(flip, axis * -1, axis)
    prjaxis = jnp.where(flip, -prjaxis, prjaxis)

    dist0 = _dot(cyl.pos - plane.pos, normal)

    # the component of -normal across the axis, scaled to the radius
    vec = axis * prjaxis - normal
    len_sqr = _dot(vec, vec)
    general = len_sqr >= MINVAL * MINVAL
    scl = radius / _sqrt(jnp.where(general, len_sqr, 1.0))
    # disk parallel to the plane: the cylinder's x axis
    vec = jnp.where(general, vec * scl, cyl.mat[:, 0] * radius)

    prjvec = _dot(vec, normal)
    axis = axis * height
    prjaxis = prjaxis * height
    zero = _zero3(normal)

    d1 = dist0 + prjaxis + prjvec
    first = d1 <= margin  # C returns no contact at all otherwise
    c1 = _Con(d1, cyl.pos + vec + axis + normal * (-d1 * 0.5), normal, zero, first)

    d2 = dist0 - prjaxis + prjvec
    c2 = _Con(d2, cyl.pos + vec - axis + normal * (-d2 * 0.5), normal, zero,
              first & (d2 <= margin))

    prjvec1 = -prjvec * 0.5
    d3 = dist0 + prjaxis + prjvec1
    side = first & (d3 <= margin)
    vec1, _ = _normalize(_cross(vec, axis))
    vec1 = vec1 * (radius * jnp.sqrt(3.0) / 2)
    base = axis + vec * -0.5 + normal * (-d3 * 0.5)
    ca = _Con(d3, cyl.pos + vec1 + base, normal, zero, side)
    cb = _Con(d3, cyl.pos - vec1 + base, normal, zero, side)
    return _emit([c1, c2, ca, cb])


@collider(ncon=4)
def plane_box(plane, box, margin):
    """Plane-box contacts: C's `mjc_PlaneBox` (engine_collision_primitive.c).

    The first four corners (in C's order: bit 0 of the index flips x, bit 1 y,
    bit 2 z) that lie within the margin of the plane and on the plane's side
    of the box's centre.

    Args:
      plane: `GeomInfo` of the plane.
      box: `GeomInfo` of the box (size: half-extents).
      margin: () the pair's margin.

    Returns:
      dist (4,), pos (4, 3), frame (4, 3, 3); unused slots at `FAR`.
    """
    normal = plane.mat[:, 2]
    dist = _dot(box.pos - plane.pos, normal)
    zero = _zero3(normal)
    cons = []
    for i in range(8):
        vec = jnp.stack([box.size[0] if i & 1 else -box.size[0],
                         box.size[1] if i & 2 else -box.size[1],
                         box.size[2] if i & 4 else -box.size[2]])
        corner = _matvec(box.mat, vec)
        ldist = _dot(normal, corner)
        ok = ~((dist + ldist > margin) | (ldist > 0))
        d = dist + ldist
        cons.append(_Con(d, corner + box.pos + normal * (-d / 2), normal, zero, ok))
    return _emit(_first(cons, 4))


# ----------------------------------------------------------------------------- sphere pairs


@collider(ncon=1)
def sphere_capsule(sphere, cap, margin):
    """Sphere-capsule contact: C's `mjc_SphereCapsule` (engine_collision_primitive.c).

    Sphere-sphere against the capsule's segment point nearest the sphere's centre.

    Args:
      sphere: `GeomInfo` of the sphere.
      cap: `GeomInfo` of the capsule.
      margin: () the pair's margin.

    Returns:
      dist (1,), pos (1, 3), frame (1, 3, 3); an unused slot at `FAR`.
    """
    return _emit([_raw_sphere_capsule(margin, sphere.pos, sphere.mat, sphere.size,
                                      cap.pos, cap.mat, cap.size)])


@collider(ncon=1)
def sphere_cylinder(sphere, cyl, margin):
    """Sphere-cylinder contact: C's `mjc_SphereCylinder` (engine_collision_primitive.c).

    Against the side (sphere-sphere with the axis point level with the
    centre), a cap (plane-sphere with the cap's plane) or the rim (sphere-sphere
    with a point sphere on the rim), chosen by where the centre projects; a
    centre inside the cylinder goes to the nearer of side and cap.

    Args:
      sphere: `GeomInfo` of the sphere.
      cyl: `GeomInfo` of the cylinder (size: radius, half-height).
      margin: () the pair's margin.

    Returns:
      dist (1,), pos (1, 3), frame (1, 3, 3); an unused slot at `FAR`.
    """
    pos1, mat1, size1 = sphere.pos, sphere.mat, sphere.size
    pos2, mat2, size2 = cyl.pos, cyl.mat, cyl.size
    radius, height = size2[0], size2[1]
    axis = mat2[:, 2]

    vec = pos1 - pos2
    x = _dot(axis, vec)
    a_proj = axis * x
    p_proj = vec - a_proj
    p_proj_sqr = _dot(p_proj, p_proj)

    collide_side = jnp.abs(x) < height
    collide_cap = p_proj_sqr < radius * radius
    # centre inside: keep the shallower of the two
    inside = collide_side & collide_cap
    cap_first = height - jnp.abs(x) < radius - _sqrt(p_proj_sqr)
    collide_side = jnp.where(inside, ~cap_first, collide_side)
    collide_cap = jnp.where(inside, cap_first, collide_cap)

    side = _raw_sphere_sphere(margin, pos1, mat1, size1[0], a_proj + pos2, mat2, radius)

    # N.B. the bottom cap's frame is C's flipmat: its z axis is -axis
    top = x > 0
    pos_cap = jnp.where(top, pos2 + axis * height, pos2 + axis * -height)
    n_cap = jnp.where(top, axis, -axis)
    cap = _raw_plane_sphere(margin, pos_cap, n_cap, pos1, size1[0])
    # plane < sphere < cylinder in mjtGeom: turn the normal to point sphere -> cylinder
    cap = cap._replace(normal=cap.normal * -1)

    # rim: C's denominator cannot be 0 here (the centre is outside the radius)
    rim_ok = p_proj_sqr > 0
    p_rim = p_proj * (radius / _sqrt(jnp.where(rim_ok, p_proj_sqr, 1.0)))
    rim_pt = axis * jnp.where(top, height, -height) + p_rim + pos2
    rim = _raw_sphere_sphere(margin, pos1, mat1, size1[0], rim_pt, mat2, 0.0)

    con = _select(collide_side, side, _select(collide_cap, cap, rim))
    return _emit([con])


@collider(ncon=1)
def sphere_sphere(s1, s2, margin):
    """Sphere-sphere contact: C's `mjc_SphereSphere` (engine_collision_primitive.c).

    N.B. MJX's own function agrees with C except for concentric spheres, where
    C takes the normal from the cross product of the two z axes and MJX
    always (1, 0, 0): 2.0 apart in the normal seen.

    Args:
      s1: `GeomInfo` of the first sphere.
      s2: `GeomInfo` of the second.
      margin: () the pair's margin.

    Returns:
      dist (1,), pos (1, 3), frame (1, 3, 3); an unused slot at `FAR`.
    """
    return _emit([_raw_sphere_sphere(margin, s1.pos, s1.mat, s1.size[0], s2.pos, s2.mat,
                                     s2.size[0])])


@collider(ncon=1)
def sphere_box(sphere, box, margin):
    """Sphere-box contact: C's `mjc_SphereBox` / `mjraw_SphereBox` (engine_collision_box.c).

    From the box point nearest the sphere's centre; a centre inside the box
    goes to the nearest face (the first of equals in C's order -x, +x, -y, +y,
    -z, +z).

    Args:
      sphere: `GeomInfo` of the sphere.
      box: `GeomInfo` of the box (size: half-extents).
      margin: () the pair's margin.

    Returns:
      dist (1,), pos (1, 3), frame (1, 3, 3); an unused slot at `FAR`.
    """
    pos1, size1 = sphere.pos, sphere.size
    pos2, mat2, size2 = box.pos, box.mat, box.size
    r = size1[0]

    center = _matTvec(mat2, pos1 - pos2)
    # mju_clampVec: only positive limits clamp (a box's are)
    clamped = jnp.where(size2 > 0, jnp.clip(center, -size2, size2), center)
    tmp, dist = _normalize(clamped - center)
    ok = ~(dist - r > margin)

    # centre inside the box: the nearest face, first of equals in C's loop order
    closest = (size2[0] + size2[1] + size2[2]) * 2
    k = jnp.zeros((), jnp.int32)
    for i in range(6):
        face = jnp.abs((1.0 if i % 2 else -1.0) * size2[i // 2] - center[i // 2])
        better = closest > face
        closest = jnp.where(better, face, closest)
        k = jnp.where(better, i, k)
    # N.B. C leaves k unset if no face is nearer than twice the sizes' sum: impossible inside
    nearest = jnp.where(jnp.arange(3) == k // 2, jnp.where(k % 2 == 1, -1.0, 1.0), 0.0)
    nearest = nearest.astype(center.dtype)
    pos_in = center + nearest * ((r - closest) / 2)
    normal_in = _matvec(mat2, nearest)

    deepest = center + tmp * r
    pos_out = jnp.zeros(3, center.dtype) + clamped * 0.5 + deepest * 0.5
    normal_out = _matvec(mat2, tmp)

    inside = dist <= MINVAL
    pos = jnp.where(inside, pos_in, pos_out)
    normal = jnp.where(inside, normal_in, normal_out)
    dist = jnp.where(inside, -closest, dist)
    con = _Con(dist - r, _matvec(mat2, pos) + pos2, normal, _zero3(pos1), ok)
    return _emit([con])


# ----------------------------------------------------------------------------- capsule pairs


def _seg_weights(a0, a1, b0, b1) -> tuple[jax.Array, jax.Array]:
    """The installed binary's `mjc_segWeights`: nearest points of two segments as weights.

    N.B. not in the C source of /work/csrc (where mjraw_CapsuleCapsule solves
    its own 2x2 system and tries four end points for parallel axes): this is
    the routine the installed libmujoco 3.17.0 calls, read from its machine code
    (a static function at 0x1de2d0, constants mjMINVAL and 1e-8), including its
    order of operations.

    Args:
      a0: (3,) segment 1's first end.
      a1: (3,) its second end.
      b0: (3,) segment 2's first end.
      b1: (3,) its second end.

    Returns:
      (2, 2) weights (s, t), the points a0 + s (a1 - a0) and b0 + t (b1 - b0),
      and () the number of rows used: 1, or 2 for parallel segments (one row
      per end of segment 1).
    """
    d1 = a1 - a0
    d2 = b1 - b0
    a = _dot(d1, d1)
    e = _dot(d2, d2)
    r = a0 - b0
    f = _dot(r, d2)
    c = _dot(d1, r)
    b = _dot(d1, d2)
    a_pos, e_pos = a > MINVAL, e > MINVAL

    s_b0 = _clip01(_div(-c, a, a_pos))  # segment 1's point nearest b0
    s_b1 = _clip01(_div(b - c, a, a_pos))  # ... nearest b1
    zero, one = jnp.zeros_like(a), jnp.ones_like(a)

    def clamp_t(s, t):
        """(s, t) for t in [0, 1], else the end of segment 2 and its nearest point."""
        return jnp.where(t < 0, jnp.stack([s_b0, zero]),
                         jnp.where(t > 1, jnp.stack([s_b1, one]), jnp.stack([s, t])))

    # segment 1 a point: segment 2's point nearest a0
    w_a = jnp.stack([zero, _clip01(_div(f, e, e_pos))])
    # segment 2 a point: segment 1's point nearest b0
    w_e = jnp.stack([s_b0, zero])

    # general: the unconstrained nearest s, clipped, then t, clamped (s recomputed if t is)
    cr = jnp.stack([d1[1] * d2[2] - d1[2] * d2[1],
                    d1[2] * d2[0] - d1[0] * d2[2],
                    d1[0] * d2[1] - d1[1] * d2[0]])
    g = jnp.stack([r[2] * d2[1] - r[1] * d2[2],
                   r[0] * d2[2] - r[2] * d2[0],
                   r[1] * d2[0] - r[0] * d2[1]])
    cr2 = _dot(cr, cr)
    crossing = cr2 > a * 1e-8 * e
    s = _clip01(_div(_dot(cr, g), cr2, crossing))
    w_g = clamp_t(s, _div(b * s + f, e, e_pos))

    # parallel: each end of segment 1 against its nearest point of segment 2
    w_p0 = clamp_t(zero, _div(f, e, e_pos))
    w_p1 = clamp_t(one, _div(f + b, e, e_pos))

    first = jnp.where(~a_pos & ~e_pos, jnp.stack([zero, zero]),
                      jnp.where(~a_pos, w_a,
                                jnp.where(~e_pos, w_e,
                                          jnp.where(crossing, w_g, w_p0))))
    two = a_pos & e_pos & ~crossing
    return jnp.stack([first, w_p1]), jnp.where(two, 2, 1)


@collider(ncon=2)
def capsule_capsule(cap1, cap2, margin):
    """Capsule-capsule contacts: the installed binary's `mjc_CapsuleCapsule`.

    N.B. the installed libmujoco 3.17.0 does not run the `mjraw_CapsuleCapsule`
    of /work/csrc/engine_collision_primitive.c (a 2x2 solve, and for parallel
    axes up to four end-point tests): its machine code builds the segments'
    ends, takes their nearest points from `mjc_segWeights` (`_seg_weights`) and
    runs C's `mjraw_SphereSphere` on each pair of points. That is ported here.
    For parallel axes (|d1 x d2|² <= 1e-8 |d1|² |d2|²) that gives two
    contacts, one per end of capsule 1 (or of capsule 2 where capsule 1's end
    falls outside it).

    Args:
      cap1: `GeomInfo` of the first capsule.
      cap2: `GeomInfo` of the second.
      margin: () the pair's margin.

    Returns:
      dist (2,), pos (2, 3), frame (2, 3, 3); unused slots at `FAR`.
    """
    half1 = cap1.size[1] * cap1.mat[:, 2]
    half2 = cap2.size[1] * cap2.mat[:, 2]
    a0, a1 = cap1.pos - half1, half1 + cap1.pos
    b0, b1 = cap2.pos - half2, half2 + cap2.pos
    w, count = _seg_weights(a0, a1, b0, b1)
    d1, d2 = a1 - a0, b1 - b0
    cons = []
    for i in range(2):
        con = _raw_sphere_sphere(margin, w[i, 0] * d1 + a0, cap1.mat, cap1.size[0],
                                 w[i, 1] * d2 + b0, cap2.mat, cap2.size[0])
        cons.append(con._replace(ok=con.ok & (i < count)))
    return _emit(cons)


PORTED[(int(_T.mjGEOM_PLANE), int(_T.mjGEOM_CAPSULE))] = plane_capsule
PORTED[(int(_T.mjGEOM_PLANE), int(_T.mjGEOM_CYLINDER))] = plane_cylinder
PORTED[(int(_T.mjGEOM_PLANE), int(_T.mjGEOM_BOX))] = plane_box
PORTED[(int(_T.mjGEOM_SPHERE), int(_T.mjGEOM_SPHERE))] = sphere_sphere
PORTED[(int(_T.mjGEOM_SPHERE), int(_T.mjGEOM_CAPSULE))] = sphere_capsule
PORTED[(int(_T.mjGEOM_SPHERE), int(_T.mjGEOM_CYLINDER))] = sphere_cylinder
PORTED[(int(_T.mjGEOM_SPHERE), int(_T.mjGEOM_BOX))] = sphere_box
PORTED[(int(_T.mjGEOM_CAPSULE), int(_T.mjGEOM_CAPSULE))] = capsule_capsule
