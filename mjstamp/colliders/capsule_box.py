"""Port of MuJoCo C's capsule-box collider (engine_collision_box.c).

C's `mjraw_CapsuleBox` finds the point of the capsule's segment closest to the
box among two kinds of candidates, in this order: the segment's two ends
clamped onto the box (a face is closest), then the segment against each of the
box's 12 edges (an edge or a corner is closest). From the winner's type and the
capsule's orientation relative to the box it may pick a second point along the
segment, and collides a sphere of the capsule's radius at each point with the
box (`mjraw_SphereBox`). So it emits at most 2 contacts, although
`mj_maxContact` reserves 4 for the pair: 2 slots here.

Every branch of C is computed and the taken one selected (`jnp.where`), in C's
order and with C's arithmetic (the same sums in the same order, reciprocals
where C multiplies by one, products rounded before they are summed: `cmath.mul`),
so that ties and thresholds fall the same way.

N.B. written on scalars (a 3-vector is a tuple of three), so that the compiled
code is elementwise loops only, forward and reverse (`cmath`'s scalar forms).
The search runs without gradients: its only continuous results, the winning
edge's two line parameters, are recomputed once from the winner's inputs (the
same operations on the same values, so the same bits) for the derivatives.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

from mjstamp.colliders import FAR, PORTED, collider
from mjstamp.colliders.cmath import (
    dot_s,
    frame_s,
    mat_t_vec_s,
    mat_vec_s,
    mul,
    opaque_one,
    sqrt,
    stage,
    unpack,
)

__all__ = ["capsule_box", "segment_points", "sphere_box"]

# mjMINVAL of C's mjmodel.h.
_MINVAL = 1e-15

# The 12 edges in C's order: axis j, then the corners i (0..7) with bit j clear.
_EDGES = tuple((j, i) for j in range(3) for i in range(8) if not i & (1 << j))


def _pick(k, values):
    """values[k] for a traced index k in 0..len(values) - 1, by selects (copies the value)."""
    out = values[-1]
    for i in range(len(values) - 2, -1, -1):
        out = jnp.where(k == i, values[i], out)
    return out


def _div_or_inf(num: jax.Array, den: jax.Array) -> jax.Array:
    """The quotient num / den for den > 0, else +inf (C's x / 0 with x > 0), with finite gradients.

    N.B. every caller only uses the quotient in `q < bound` tests, where C's
    +inf (or NaN for 0 / 0) never passes, so +inf stands for both.
    """
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), jnp.inf)


def _sphere_box(center, radius, margin, pos2, mat2, size2, one):
    """C's `mjraw_SphereBox` on scalars: see `sphere_box`; vectors are triples of scalars.

    `one` is `stage`'s divisor.
    """
    center = stage(mat_t_vec_s(mat2, tuple(c - p for c, p in zip(center, pos2, strict=True))),
                   one)
    # N.B. mju_clampVec skips limits <= 0; a box's half-sizes are positive.
    clamped = tuple(jnp.clip(c, -s, s) for c, s in zip(center, size2, strict=True))
    tmp = tuple(a - c for a, c in zip(clamped, center, strict=True))
    dist = sqrt(dot_s(tmp, tmp))
    # mju_normalize3: leaves (1, 0, 0) below mjMINVAL, where the inside branch is taken.
    big = dist >= _MINVAL
    inv = 1 / jnp.where(big, dist, 1.0)
    tmp = tuple(jnp.where(big, t * inv, e) for t, e in zip(tmp, (1.0, 0.0, 0.0), strict=True))
    emitted = ~(dist - radius > margin)
    clamped, tmp, dist = stage((clamped, tmp, dist), one)

    # Sphere centre inside the box: push out through the nearest face (first of
    # -x, +x, -y, +y, -z, +z on ties).
    closest = (size2[0] + size2[1] + size2[2]) * 2
    k = jnp.int32(0)
    for i in range(6):
        face = size2[i // 2] if i % 2 else -size2[i // 2]
        gap = jnp.abs(face - center[i // 2])
        better = closest > gap
        closest = jnp.where(better, gap, closest)
        k = jnp.where(better, i, k)
    closest, k = stage((closest, k), one)
    # nearest = -/+ e_(k // 2): C's sums with its zero components are exact.
    sign = jnp.where((k & 1) == 1, -1.0, 1.0)
    axis = k >> 1
    half = (radius - closest) / 2
    pos_in = tuple(jnp.where(axis == i, center[i] + sign * half, center[i]) for i in range(3))
    normal_in = tuple(_pick(axis, row) * sign for row in mat2)

    # Outside: midpoint of the box's closest point and the sphere's deepest one.
    pos_out = tuple(a * 0.5 + (c + mul(t, radius)) * 0.5
                    for a, c, t in zip(clamped, center, tmp, strict=True))
    normal_out = mat_vec_s(mat2, tmp)

    inside = dist <= _MINVAL
    pos = tuple(jnp.where(inside, a, b) for a, b in zip(pos_in, pos_out, strict=True))
    normal = tuple(jnp.where(inside, a, b) for a, b in zip(normal_in, normal_out, strict=True))
    dist = jnp.where(inside, -closest, dist)
    world = tuple(w + p for w, p in zip(mat_vec_s(mat2, pos), pos2, strict=True))
    return emitted, dist - radius, world, normal


def sphere_box(center: jax.Array, radius: jax.Array, margin: jax.Array, pos2: jax.Array,
               mat2: jax.Array, size2: jax.Array):
    """One sphere against a box: C's `mjraw_SphereBox` (engine_collision_box.c).

    Args:
      center: (3,) sphere centre, world frame.
      radius: sphere radius (scalar).
      margin: the pair's margin (scalar).
      pos2: (3,) box centre.
      mat2: (3, 3) box orientation.
      size2: (3,) box half-sizes.

    Returns:
      (emitted, dist, pos (3,), normal (3,)): whether C returns the contact
      (distance within the margin), its distance, position and normal (from
      the sphere to the box).
    """
    one = opaque_one(center[0] + pos2[0])
    center, pos2, m, size2 = stage((unpack(center), unpack(pos2), unpack(mat2), unpack(size2)),
                                   one)
    emitted, dist, pos, normal = _sphere_box(center, radius, margin, pos2,
                                             (m[0:3], m[3:6], m[6:9]), size2, one)
    return emitted, dist, jnp.stack(pos), jnp.stack(normal)


def _face_candidates(pos, halfaxis, size2, bestdist):
    """The face tests of `mjraw_CapsuleBox`: each segment end clamped onto the box.

    An end outside the box along two or more axes is skipped (an edge or corner
    is closer; the edge tests find it).

    Returns:
      (bestdist, cltype, clface): the running best squared distance; -3 or -1
      (the -1 or +1 end is closest) or -4 (none); the clamped axis (-1 when the
      end is inside the box).
    """
    cltype, clface = jnp.int32(-4), jnp.int32(-1)
    for i in (-1, 1):
        end = tuple(p + h * float(i) for p, h in zip(pos, halfaxis, strict=True))
        c1 = jnp.int32(0)
        c2 = jnp.int32(-1)
        diff = []
        for j in range(3):
            below = end[j] < -size2[j]
            above = end[j] > size2[j]
            out = below | above
            c1 = c1 + out.astype(jnp.int32)
            c2 = jnp.where(out, j, c2)
            clamped = jnp.where(below, -size2[j], jnp.where(above, size2[j], end[j]))
            diff.append(clamped - end[j])
        dist = dot_s(diff, diff)
        better = (c1 <= 1) & (dist < bestdist)
        bestdist = jnp.where(better, dist, bestdist)
        cltype = jnp.where(better, -2 + i, cltype)
        clface = jnp.where(better, c2, clface)
    return bestdist, cltype, clface


def _edge_params(dif, halfaxis, sj, hj, difj, mc):
    """C's line-line parameters of the segment and one box edge (inline in `mjraw_CapsuleBox`).

    Args:
      dif: the edge's start minus the capsule centre (triple), box frame.
      halfaxis: the capsule's half-axis (triple).
      sj: the box's half-size along the edge's axis j.
      hj: halfaxis[j].
      difj: dif[j].
      mc: the squared half-length.

    Returns:
      (ok, x1, x2, s1, s2): ok false where C skips the edge (parallel to the
      segment, |det| < mjMINVAL); the parameters on the edge and on the
      segment, each in [-1, 1], clamped the way C clamps them; s = 0, 1, 2 for
      the lower end, interior, upper end (N.B. a clamp of x2 recomputes x1 but
      keeps s1 from the first clamp unless x1 is clamped again: C's
      bookkeeping, kept because it picks the branch).
    """
    ma = sj * sj
    mb = mul(-sj, hj)
    u = mul(-sj, difj)
    v = dot_s(halfaxis, dif)
    det = mul(ma, mc) - mul(mb, mb)
    ok = ~(jnp.abs(det) < _MINVAL)
    idet = 1 / jnp.where(ok, det, 1.0)
    x1 = mul(mul(mc, u) - mul(mb, v), idet)
    x2 = mul(mul(ma, v) - mul(mb, u), idet)

    # Clamp the edge parameter; then the segment's, re-solving the edge's.
    hi1 = x1 > 1
    lo1 = ~hi1 & (x1 < -1)
    s1 = jnp.where(hi1, 2, jnp.where(lo1, 0, 1))
    x2 = jnp.where(hi1, mul(v - mb, 1 / mc), jnp.where(lo1, mul(v + mb, 1 / mc), x2))
    x1 = jnp.where(hi1, 1.0, jnp.where(lo1, -1.0, x1))
    hi2 = x2 > 1
    lo2 = ~hi2 & (x2 < -1)
    x1r = jnp.where(hi2, mul(u - mb, 1 / ma), mul(u + mb, 1 / ma))
    hi1r = x1r > 1
    lo1r = ~hi1r & (x1r < -1)
    s1r = jnp.where(hi1r, 2, jnp.where(lo1r, 0, s1))
    x1r = jnp.where(hi1r, 1.0, jnp.where(lo1r, -1.0, x1r))
    clamp2 = hi2 | lo2
    s2 = jnp.where(hi2, 2, jnp.where(lo2, 0, 1))
    x2 = jnp.where(hi2, 1.0, jnp.where(lo2, -1.0, x2))
    x1 = jnp.where(clamp2, x1r, x1)
    s1 = jnp.where(clamp2, s1r, s1)
    return ok, x1, x2, s1, s2


def _corner(i, j, size2):
    """The edge's start: corner i of the box (bit k: + or - size2[k]) with axis j set to 0."""
    return tuple(0.0 * size2[k] if k == j else (size2[k] if i & (1 << k) else -size2[k])
                 for k in range(3))


def _edge_search(pos, halfaxis, size1, size2, bestdist):
    """The 12 edge tests of `mjraw_CapsuleBox`, in C's order, with its tie rule.

    Returns:
      (won, bestdist): the index in `_EDGES` of the closest edge (-1: none beats
      the faces); its squared distance.
    """
    mc = size1[1] * size1[1]
    won = jnp.int32(-1)
    for k, (j, i) in enumerate(_EDGES):
        corner = _corner(i, j, size2)
        dif = tuple(c - p for c, p in zip(corner, pos, strict=True))
        ok, x1, x2, _, _ = _edge_params(dif, halfaxis, size2[j], halfaxis[j], dif[j], mc)
        dif = tuple(d + mul(h, -x2) for d, h in zip(dif, halfaxis, strict=True))
        dif = tuple(d + mul(size2[j], x1) if m == j else d for m, d in enumerate(dif))
        dist2 = dot_s(dif, dif)
        # N.B. C's "- mjMINVAL" keeps a face (or earlier edge) on near-ties
        # when the axis is numerically parallel to the box.
        better = ok & (dist2 < bestdist - _MINVAL)
        bestdist = jnp.where(better, dist2, bestdist)
        won = jnp.where(better, k, won)
    return won, bestdist


def _winning_edge(won, pos, halfaxis, size1, size2):
    """The closest edge's parameters, recomputed from its inputs (for the derivatives).

    Returns:
      (x1, x2, cltype, clcorner, cledge) as C's edge test sets them (garbage
      where won == -1).
    """
    k = jnp.maximum(won, 0)
    j = k >> 2  # 4 edges per axis
    i = _pick(k, [jnp.int32(i) for _, i in _EDGES])
    corner = tuple(jnp.where(j == m, 0.0 * size2[m],
                             jnp.where((i & (1 << m)) != 0, size2[m], -size2[m]))
                   for m in range(3))
    dif = tuple(c - p for c, p in zip(corner, pos, strict=True))
    _, x1, x2, s1, s2 = _edge_params(dif, halfaxis, _pick(j, size2), _pick(j, halfaxis),
                                     _pick(j, dif), size1[1] * size1[1])
    c1 = s1 * 3 + s2
    clcorner = i + jnp.where(c1 >= 6, jnp.left_shift(1, j), 0)
    return x1, x2, c1, clcorner, j


def _next(ax):
    """(ax + 1) % 3 and (ax + 2) % 3."""
    return jnp.where(ax == 2, 0, ax + 1), jnp.where(ax == 0, 2, ax - 1)


def _second_corner(axis, q, axisdir, clcorner, bsp):
    """Second point when a box corner is closest (cltype >= 0, cltype // 3 != 1).

    Args:
      axis: the capsule's unit axis (triple), box frame.
      q: the triple 2 size2[k] / |halfaxis[k]| (+inf for 0).
      axisdir: the axis's octant (bit k: halfaxis[k] > 0).
      clcorner: the closest corner (bit k: + side along k).
      bsp: the closest point's parameter on the segment.

    Returns:
      (take, secondpos): take false where C skips (the segment points to or
      away from the corner, axisdir ^ clcorner in {0, 7}).
    """
    c1 = jnp.bitwise_xor(axisdir, clcorner)
    take = (c1 != 0) & (c1 != 7)
    flip = (c1 == 3) | (c1 == 5) | (c1 == 6)
    mul_ = jnp.where(flip, -1.0, 1.0)
    de = jnp.where(flip, 1 + bsp, 1 - bsp)
    dp = jnp.where(flip, 1 - bsp, 1 + bsp)
    c1 = jnp.where(flip, 7 - c1, c1)
    ax = jnp.where(c1 == 1, 0, jnp.where(c1 == 2, 1, 2))
    ax1, ax2 = _next(ax)

    # Along the box's edge (the segment within 45 degrees of it) ...
    e1 = _pick(ax, q)
    along_edge = jnp.where(e1 < de, e1, de) * mul_
    # ... or across a face, stopping where the segment leaves it.
    e1 = _pick(ax1, q)
    sp = jnp.where(e1 < dp, e1, dp)
    e1 = _pick(ax2, q)
    sp = jnp.where(e1 < sp, e1, sp)
    along_face = sp * -mul_
    a = _pick(ax, axis)
    return take, jnp.where(a * a > 0.5, along_edge, along_face)


def _second_edge(axis, halfaxis, size2, q, axisdir, clcorner, cledge, bsp, bestboxpos):
    """Second point when the inside of a box edge is closest (cltype // 3 == 1).

    Returns:
      (take, secondpos): take false where C skips (segment and edge in a T, not
      crossed in an X).
    """
    c1 = jnp.bitwise_xor(axisdir, clcorner) & (7 - jnp.left_shift(1, cledge))
    take = (c1 == 1) | (c1 == 2) | (c1 == 4)
    ax = cledge
    ax1, ax2 = _next(ax)
    # The face the segment makes the smaller angle with.
    ax1 = jnp.where(jnp.abs(_pick(ax1, axis)) > jnp.abs(_pick(ax2, axis)), ax2, ax1)
    ax2 = 3 - ax - ax1
    bit = (jnp.right_shift(c1, ax2) & 1) != 0
    sign = jnp.where(bit, 1.0, -1.0)
    sp = jnp.where(bit, 1 - bsp, 1 + bsp)
    e1 = _pick(ax2, q)
    sp = jnp.where(e1 < sp, e1, sp)
    same = ((jnp.right_shift(axisdir, ax) & 1) != 0) == bit
    e2 = jnp.where(same, 1 - bestboxpos, 1 + bestboxpos)
    # N.B. e2 >= 0: C's quotient by |halfaxis| = 0 is +inf or NaN, never taken.
    e1 = _div_or_inf(_pick(ax, size2) * e2, jnp.abs(_pick(ax, halfaxis)))
    sp = jnp.where(e1 < sp, e1, sp)
    return take, sp * sign


def _second_face(pos, halfaxis, size2, cltype, clface):
    """Second point when a segment end is closest to a face (cltype -3 or -1).

    Follows the segment from that end to the other and stops where it leaves
    the slab of the box across any other axis.

    Returns:
      (take, secondpos): take false where C skips (the end inside the box).
    """
    take = clface != -1
    sign = jnp.where(cltype == -3, 1.0, -1.0)
    sp = jnp.asarray(2.0, pos[0].dtype)
    for i in range(3):
        h = halfaxis[i]
        start = pos[i] + h * -sign
        # N.B. C divides by h = 0 too: +-inf or NaN, which never pass the tests below.
        ok = (clface != i) & (h != 0)
        hs = jnp.where(h != 0, h, 1.0)
        for bound in (size2[i], -size2[i]):
            e1 = (bound - start) / hs * sign
            sp = jnp.where(ok & (e1 > 0) & (e1 < sp), e1, sp)
    return take, sp * sign


def _segment_points(pos, axis, size1, size2, margin, one):
    """`segment_points` on scalar triples; see there (`one`: `stage`'s divisor)."""
    halfaxis = stage(tuple(mul(a, size1[1]) for a in axis), one)
    # The octant of the axis (bit k: halfaxis[k] > 0); 7 - axisdir is the same line.
    axisdir = ((halfaxis[0] > 0).astype(jnp.int32) + 2 * (halfaxis[1] > 0).astype(jnp.int32)
               + 4 * (halfaxis[2] > 0).astype(jnp.int32))
    bestdistmax = margin + 2 * (size1[0] + size1[1] + size2[0] + size2[1] + size2[2])

    # The search: discrete choices only (its distances are compared, never output).
    sg = jax.lax.stop_gradient
    pos_, half_, size1_, size2_ = (tuple(sg(c) for c in v) for v in (pos, halfaxis, size1, size2))
    bestdist, cltype_f, clface = _face_candidates(pos_, half_, size2_, sg(bestdistmax))
    won, bestdist = _edge_search(pos_, half_, size1_, size2_, bestdist)
    # N.B. C's dead block after the edge tests (a 2-D search in the xy plane
    # whose results are never read) is left out.
    won, bestdist, cltype_f, clface = stage((won, bestdist, cltype_f, clface), one)

    edge = won >= 0
    x1, x2, cltype_e, clcorner, cledge = stage(_winning_edge(won, pos, halfaxis, size1, size2),
                                               one)
    cltype = jnp.where(edge, cltype_e, cltype_f)
    clcorner = jnp.where(edge, clcorner, 0)
    cledge = jnp.where(edge, cledge, 0)
    bsp = jnp.where(edge, x2, jnp.where(cltype_f == -1, 1.0, jnp.where(cltype_f == -3, -1.0,
                                                                         0.0)))
    bestboxpos = jnp.where(edge, x1, 0.0)

    # 2 size2[k] / |halfaxis[k]|, shared by the corner and the edge rules.
    q = tuple(_div_or_inf(2 * s, jnp.abs(h)) for s, h in zip(size2, halfaxis, strict=True))
    take_c, sp_c = _second_corner(axis, q, axisdir, clcorner, bsp)
    take_e, sp_e = _second_edge(axis, halfaxis, size2, q, axisdir, clcorner, cledge, bsp,
                                bestboxpos)
    take_f, sp_f = _second_face(pos, halfaxis, size2, cltype, clface)
    on_edge = cltype >= 0
    mid_edge = (cltype >= 3) & (cltype <= 5)
    secondpos = jnp.where(
        on_edge & ~mid_edge & take_c, sp_c,
        jnp.where(mid_edge & take_e, sp_e,
                  jnp.where(~on_edge & take_f, sp_f, -4.0)))
    best = {"bestdist": bestdist, "cltype": cltype, "clface": clface, "clcorner": clcorner,
            "cledge": cledge, "bestboxpos": bestboxpos, "bestsegmentpos": bsp}
    found, bsp, secondpos = stage((cltype != -4, bsp, secondpos), one)
    return found, bsp, secondpos, halfaxis, best


def segment_points(pos, axis, size1, size2, margin):
    """Where C puts its spheres on the segment: the search of `mjraw_CapsuleBox`.

    engine_collision_box.c: the face tests, the 12 edge tests, then the second
    point chosen from the closest feature (corner, edge, face) and the axis's
    octant relative to it (`axisdir`).

    Args:
      pos: (3,) capsule centre in the box's frame.
      axis: (3,) capsule axis (unit) in the box's frame.
      size1: (3,) capsule size (radius, half-length).
      size2: (3,) box half-sizes.
      margin: the pair's margin (scalar).

    Returns:
      (found, bestsegmentpos, secondpos, best): found is false where C returns
      no contact (cltype == -4); the closest point's parameter on the segment
      (-1 .. 1); the second point's offset from it (C's secondpos, <= -3 for
      none); and the search's winner (dict: cltype, clface, clcorner, cledge,
      bestboxpos, bestdist), for tests.
    """
    one = opaque_one(pos[0])
    found, bsp, secondpos, _, best = _segment_points(
        *stage((unpack(pos), unpack(axis), unpack(size1), unpack(size2)), one), margin, one)
    return found, bsp, secondpos, best


def box_frame(pos1, mat1, pos2, mat2):
    """The capsule's centre and axis in the box's frame, as C computes them.

    Args:
      pos1: (3,) the capsule's position.
      mat1: (3, 3) the capsule's orientation.
      pos2: (3,) the box's position.
      mat2: (3, 3) the box's orientation.

    Returns:
      (pos (3,), axis (3,)).
    """
    m2 = unpack(mat2)
    m2 = (m2[0:3], m2[3:6], m2[6:9])
    m1 = unpack(mat1)
    p1, p2 = unpack(pos1), unpack(pos2)
    pos = mat_t_vec_s(m2, tuple(a - b for a, b in zip(p1, p2, strict=True)))
    axis = mat_t_vec_s(m2, (m1[2], m1[5], m1[8]))
    return jnp.stack(pos), jnp.stack(axis)


@collider(2)
def capsule_box(info1, info2, margin):
    """Capsule (geom1) against box (geom2): C's `mjc_CapsuleBox` / `mjraw_CapsuleBox`.

    Ports engine_collision_box.c branch for branch: the closest point of the
    segment to the box and C's choice of a second point (`segment_points`),
    then a sphere-box contact (`sphere_box`) at each.

    Args:
      info1: the capsule's `GeomInfo` (pos (3,), mat (3, 3), size (3,): radius,
        half-length).
      info2: the box's `GeomInfo` (size: half-sizes).
      margin: the pair's margin (scalar).

    Returns:
      dist (2,), pos (2, 3), frame (2, 3, 3); slots C does not fill have
      dist = `FAR`.
    """
    one = opaque_one(info1.pos[0] + info2.pos[0])
    pos1, size1, m1, pos2, size2, m2 = stage(
        tuple(unpack(x) for x in (info1.pos, info1.size, info1.mat, info2.pos, info2.size,
                                  info2.mat)), one)
    mat2 = (m2[0:3], m2[3:6], m2[6:9])

    # Capsule in the box's frame.
    pos = mat_t_vec_s(mat2, tuple(a - b for a, b in zip(pos1, pos2, strict=True)))
    axis = mat_t_vec_s(mat2, (m1[2], m1[5], m1[8]))
    pos, axis = stage((pos, axis), one)
    found, bsp, secondpos, halfaxis, _ = _segment_points(pos, axis, size1, size2, margin, one)

    def sphere_at(t):
        # N.B. C goes back to the world frame and sphere-box comes back to the
        # box's: kept, for C's rounding.
        local = tuple(p + mul(h, t) for p, h in zip(pos, halfaxis, strict=True))
        centre = tuple(c + p for c, p in zip(mat_vec_s(mat2, local), pos2, strict=True))
        return _sphere_box(centre, size1[0], margin, pos2, mat2, size2, one)

    em1, d1, p1, n1 = stage(sphere_at(bsp), one)
    em2, d2, p2, n2 = stage(sphere_at(secondpos + bsp), one)
    em1 = em1 & found
    em2 = em2 & found & (secondpos > -3)
    dist = jnp.stack([jnp.where(em1, d1, FAR), jnp.where(em2, d2, FAR)])
    pos_out = jnp.stack([jnp.stack(p1), jnp.stack(p2)])
    frame = jnp.stack([frame_s(n1), frame_s(n2)])
    return dist, pos_out, frame


PORTED[(int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_BOX))] = capsule_box
