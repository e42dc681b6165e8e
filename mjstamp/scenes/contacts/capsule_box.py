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
where C multiplies by one), so that ties and thresholds fall the same way.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

from mjstamp.scenes.contacts import FAR, PORTED, collider, make_frame

__all__ = ["capsule_box", "segment_points", "sphere_box"]

# mjMINVAL of C's mjmodel.h.
_MINVAL = 1e-15


def _mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """The product a * b, rounded before any sum it enters, as C rounds it.

    N.B. XLA lets LLVM contract ``a * b + c`` into one fused multiply-add (on
    CPU and GPU alike), which rounds once where C (built without FMA) rounds
    twice: the last-bit differences flip C's ties and thresholds on
    axis-aligned poses. LLVM cannot contract through the select. Products
    that are exact (by 0.5, 2 or +-1) are left bare.
    """
    p = a * b
    return jnp.where(p == p, p, 0.0)


def _mul_mat_vec(mat: jax.Array, vec: jax.Array) -> jax.Array:
    """Product mat (3, 3) @ vec (3,), summed as C's `mji_mulMatVec3` (engine_inline.h)."""
    return _mul(mat[:, 0], vec[0]) + _mul(mat[:, 1], vec[1]) + _mul(mat[:, 2], vec[2])


def _mul_mat_t_vec(mat: jax.Array, vec: jax.Array) -> jax.Array:
    """Product mat.T (3, 3) @ vec (3,), summed as C's `mji_mulMatTVec3` (engine_inline.h)."""
    return _mul(mat[0], vec[0]) + _mul(mat[1], vec[1]) + _mul(mat[2], vec[2])


def _dot3(a: jax.Array, b: jax.Array) -> jax.Array:
    """The dot product a . b, summed as C's `mju_dot3` (engine_util_blas.c)."""
    return _mul(a[0], b[0]) + _mul(a[1], b[1]) + _mul(a[2], b[2])


def _div_or_inf(num: jax.Array, den: jax.Array) -> jax.Array:
    """The quotient num / den for den > 0, else +inf (C's x / 0 with x > 0), with finite gradients.

    N.B. every caller only uses the quotient in `q < bound` tests, where C's
    +inf (or NaN for 0 / 0) never passes, so +inf stands for both.
    """
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), jnp.inf)


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
    center = _mul_mat_t_vec(mat2, center - pos2)
    # N.B. mju_clampVec skips limits <= 0; a box's half-sizes are positive.
    clamped = jnp.clip(center, -size2, size2)
    tmp = clamped - center
    sq = _dot3(tmp, tmp)
    pos_sq = sq > 0
    dist = jnp.where(pos_sq, jnp.sqrt(jnp.where(pos_sq, sq, 1.0)), 0.0)
    # mju_normalize3: leaves (1, 0, 0) below mjMINVAL, where the inside branch is taken.
    big = dist >= _MINVAL
    tmp = jnp.where(big, tmp * (1 / jnp.where(big, dist, 1.0)), jnp.array([1.0, 0.0, 0.0]))
    emitted = ~(dist - radius > margin)

    # Sphere centre inside the box: push out through the nearest face (first of
    # -x, +x, -y, +y, -z, +z on ties).
    closest = (size2[0] + size2[1] + size2[2]) * 2
    k = 0
    for i in range(6):
        face = (1.0 if i % 2 else -1.0) * size2[i // 2]
        gap = jnp.abs(face - center[i // 2])
        better = closest > gap
        closest = jnp.where(better, gap, closest)
        k = jnp.where(better, i, k)
    sign = jnp.where(k % 2 == 1, -1.0, 1.0)
    nearest = jnp.where(jnp.arange(3) == k // 2, sign, 0.0)
    pos_in = center + nearest * ((radius - closest) / 2)
    normal_in = _mul_mat_vec(mat2, nearest)

    # Outside: midpoint of the box's closest point and the sphere's deepest one.
    deepest = center + _mul(tmp, radius)
    pos_out = clamped * 0.5 + deepest * 0.5
    normal_out = _mul_mat_vec(mat2, tmp)

    inside = dist <= _MINVAL
    pos = jnp.where(inside, pos_in, pos_out)
    normal = jnp.where(inside, normal_in, normal_out)
    dist = jnp.where(inside, -closest, dist)
    return emitted, dist - radius, _mul_mat_vec(mat2, pos) + pos2, normal


def _face_candidates(pos, halfaxis, size2, bestdist):
    """The face tests of `mjraw_CapsuleBox`: each segment end clamped onto the box.

    An end outside the box along two or more axes is skipped (an edge or corner
    is closer; the edge tests find it).

    Returns:
      dict of the running best: bestdist, bestsegmentpos, cltype (-3 or -1:
      the -1 or +1 end is closest; -4: none), clface (the clamped axis, -1
      when the end is inside the box).
    """
    best = {"bestdist": bestdist, "bestsegmentpos": jnp.zeros_like(bestdist),
            "cltype": jnp.int32(-4), "clface": jnp.int32(-1)}
    for i in (-1, 1):
        end = pos + halfaxis * float(i)
        clamped = end
        c1 = jnp.int32(0)
        c2 = jnp.int32(-1)
        for j in range(3):
            below = end[j] < -size2[j]
            above = end[j] > size2[j]
            out = below | above
            c1 = c1 + out.astype(jnp.int32)
            c2 = jnp.where(out, j, c2)
            clamped = clamped.at[j].set(
                jnp.where(below, -size2[j], jnp.where(above, size2[j], end[j])))
        diff = clamped - end
        dist = _dot3(diff, diff)
        better = (c1 <= 1) & (dist < best["bestdist"])
        new = {"bestdist": dist, "bestsegmentpos": jnp.asarray(float(i), dist.dtype),
               "cltype": jnp.int32(-2 + i), "clface": c2}
        best = {key: jnp.where(better, new[key], best[key]) for key in best}
    return best


def _edge_candidate(j, i, pos, halfaxis, size1, size2):
    """Closest points of the segment and the box edge along axis j from corner i.

    C's inline line-line distance of `mjraw_CapsuleBox`: parameters x1 on the
    edge and x2 on the segment, each in [-1, 1], clamped the way C clamps them
    (N.B. a clamp of x2 recomputes x1 but keeps s1 from the first clamp unless
    x1 is clamped again: C's bookkeeping, kept because it picks the branch).

    Returns:
      (ok, dist2, x1, x2, c1): ok false where C skips the edge (parallel to the
      segment, |det| < mjMINVAL); squared distance; the parameters; c1 =
      3 * s1 + s2 with s = 0, 1, 2 for the lower end, interior, upper end.
    """
    corner = jnp.stack([(1.0 if i & (1 << k) else -1.0) * size2[k] for k in range(3)])
    corner = corner.at[j].set(0.0)
    dif = corner - pos
    sj = size2[j]
    ma = sj * sj
    mb = _mul(-sj, halfaxis[j])
    mc = size1[1] * size1[1]
    u = _mul(-sj, dif[j])
    v = _dot3(halfaxis, dif)
    det = _mul(ma, mc) - _mul(mb, mb)
    ok = ~(jnp.abs(det) < _MINVAL)
    idet = 1 / jnp.where(ok, det, 1.0)
    x1 = _mul(_mul(mc, u) - _mul(mb, v), idet)
    x2 = _mul(_mul(ma, v) - _mul(mb, u), idet)

    # Clamp the edge parameter; then the segment's, re-solving the edge's.
    hi1 = x1 > 1
    lo1 = ~hi1 & (x1 < -1)
    s1 = jnp.where(hi1, 2, jnp.where(lo1, 0, 1))
    x2 = jnp.where(hi1, _mul(v - mb, 1 / mc), jnp.where(lo1, _mul(v + mb, 1 / mc), x2))
    x1 = jnp.where(hi1, 1.0, jnp.where(lo1, -1.0, x1))
    hi2 = x2 > 1
    lo2 = ~hi2 & (x2 < -1)
    x1r = jnp.where(hi2, _mul(u - mb, 1 / ma), _mul(u + mb, 1 / ma))
    hi1r = x1r > 1
    lo1r = ~hi1r & (x1r < -1)
    s1r = jnp.where(hi1r, 2, jnp.where(lo1r, 0, s1))
    x1r = jnp.where(hi1r, 1.0, jnp.where(lo1r, -1.0, x1r))
    clamp2 = hi2 | lo2
    s2 = jnp.where(hi2, 2, jnp.where(lo2, 0, 1))
    x2 = jnp.where(hi2, 1.0, jnp.where(lo2, -1.0, x2))
    x1 = jnp.where(clamp2, x1r, x1)
    s1 = jnp.where(clamp2, s1r, s1)

    dif = corner - pos
    dif = dif + _mul(halfaxis, -x2)
    dif = dif.at[j].add(_mul(sj, x1))
    return ok, _dot3(dif, dif), x1, x2, s1 * 3 + s2


def _second_corner(axis, halfaxis, size2, axisdir, clcorner, bsp):
    """Second point when a box corner is closest (cltype >= 0, cltype // 3 != 1).

    Returns:
      (take, secondpos): take false where C skips (the segment points to or
      away from the corner, axisdir ^ clcorner in {0, 7}).
    """
    c1 = jnp.bitwise_xor(axisdir, clcorner)
    take = (c1 != 0) & (c1 != 7)
    flip = (c1 == 3) | (c1 == 5) | (c1 == 6)
    mul = jnp.where(flip, -1.0, 1.0)
    de = jnp.where(flip, 1 + bsp, 1 - bsp)
    dp = jnp.where(flip, 1 - bsp, 1 + bsp)
    c1 = jnp.where(flip, 7 - c1, c1)
    ax = jnp.where(c1 == 1, 0, jnp.where(c1 == 2, 1, 2))
    ax1 = (ax + 1) % 3
    ax2 = (ax + 2) % 3

    # Along the box's edge (the segment within 45 degrees of it) ...
    e1 = _div_or_inf(2 * size2[ax], jnp.abs(halfaxis[ax]))
    along_edge = jnp.where(e1 < de, e1, de) * mul
    # ... or across a face, stopping where the segment leaves it.
    sp = dp
    e1 = _div_or_inf(2 * size2[ax1], jnp.abs(halfaxis[ax1]))
    sp = jnp.where(e1 < sp, e1, sp)
    e1 = _div_or_inf(2 * size2[ax2], jnp.abs(halfaxis[ax2]))
    sp = jnp.where(e1 < sp, e1, sp)
    along_face = sp * -mul
    return take, jnp.where(axis[ax] * axis[ax] > 0.5, along_edge, along_face)


def _second_edge(axis, halfaxis, size2, axisdir, clcorner, cledge, bsp, bestboxpos):
    """Second point when the inside of a box edge is closest (cltype // 3 == 1).

    Returns:
      (take, secondpos): take false where C skips (segment and edge in a T, not
      crossed in an X).
    """
    c1 = jnp.bitwise_xor(axisdir, clcorner) & (7 - jnp.left_shift(1, cledge))
    take = (c1 == 1) | (c1 == 2) | (c1 == 4)
    ax = cledge
    ax1 = (ax + 1) % 3
    ax2 = (ax + 2) % 3
    # The face the segment makes the smaller angle with.
    ax1 = jnp.where(jnp.abs(axis[ax1]) > jnp.abs(axis[ax2]), ax2, ax1)
    ax2 = 3 - ax - ax1
    bit = (jnp.right_shift(c1, ax2) & 1) != 0
    mul = jnp.where(bit, 1.0, -1.0)
    sp = jnp.where(bit, 1 - bsp, 1 + bsp)
    e1 = _div_or_inf(2 * size2[ax2], jnp.abs(halfaxis[ax2]))
    sp = jnp.where(e1 < sp, e1, sp)
    same = ((jnp.right_shift(axisdir, ax) & 1) != 0) == bit
    e2 = jnp.where(same, 1 - bestboxpos, 1 + bestboxpos)
    # N.B. e2 >= 0: C's quotient by |halfaxis| = 0 is +inf or NaN, never taken.
    e1 = _div_or_inf(size2[ax] * e2, jnp.abs(halfaxis[ax]))
    sp = jnp.where(e1 < sp, e1, sp)
    return take, sp * mul


def _second_face(pos, halfaxis, size2, cltype, clface):
    """Second point when a segment end is closest to a face (cltype -3 or -1).

    Follows the segment from that end to the other and stops where it leaves
    the slab of the box across any other axis.

    Returns:
      (take, secondpos): take false where C skips (the end inside the box).
    """
    take = clface != -1
    mul = jnp.where(cltype == -3, 1.0, -1.0)
    sp = jnp.asarray(2.0, pos.dtype)
    tmp1 = pos + halfaxis * -mul
    for i in range(3):
        h = halfaxis[i]
        # N.B. C divides by h = 0 too: +-inf or NaN, which never pass the tests below.
        ok = (i != clface) & (h != 0)
        hs = jnp.where(h != 0, h, 1.0)
        for bound in (size2[i], -size2[i]):
            e1 = (bound - tmp1[i]) / hs * mul
            sp = jnp.where(ok & (e1 > 0) & (e1 < sp), e1, sp)
    return take, sp * mul


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
    halfaxis = _mul(axis, size1[1])
    # The octant of the axis (bit k: halfaxis[k] > 0); 7 - axisdir is the same line.
    axisdir = ((halfaxis[0] > 0).astype(jnp.int32) + 2 * (halfaxis[1] > 0).astype(jnp.int32)
               + 4 * (halfaxis[2] > 0).astype(jnp.int32))
    bestdistmax = margin + 2 * (size1[0] + size1[1] + size2[0] + size2[1] + size2[2])

    best = _face_candidates(pos, halfaxis, size2, bestdistmax)
    best["bestboxpos"] = jnp.zeros_like(bestdistmax)
    best["clcorner"] = jnp.int32(0)
    best["cledge"] = jnp.int32(0)
    for j in range(3):
        for i in range(8):
            if i & (1 << j):
                continue
            ok, dist2, x1, x2, c1 = _edge_candidate(j, i, pos, halfaxis, size1, size2)
            # N.B. C's "- mjMINVAL" keeps a face (or earlier edge) on near-ties
            # when the axis is numerically parallel to the box.
            better = ok & (dist2 < best["bestdist"] - _MINVAL)
            new = {"bestdist": dist2, "bestsegmentpos": x2, "bestboxpos": x1,
                   "clcorner": jnp.int32(i) + (1 << j) * (c1 // 6),
                   "cledge": jnp.int32(j), "cltype": c1, "clface": best["clface"]}
            best = {key: jnp.where(better, new[key], best[key]) for key in best}
    # N.B. C's dead block after the edge tests (a 2-D search in the xy plane
    # whose results are never read) is left out.

    cltype = best["cltype"]
    bsp = best["bestsegmentpos"]
    take_c, sp_c = _second_corner(axis, halfaxis, size2, axisdir, best["clcorner"], bsp)
    take_e, sp_e = _second_edge(axis, halfaxis, size2, axisdir, best["clcorner"],
                                best["cledge"], bsp, best["bestboxpos"])
    take_f, sp_f = _second_face(pos, halfaxis, size2, cltype, best["clface"])
    on_edge = cltype >= 0
    mid_edge = on_edge & (cltype // 3 == 1)
    secondpos = jnp.where(
        on_edge & ~mid_edge & take_c, sp_c,
        jnp.where(mid_edge & take_e, sp_e,
                  jnp.where(~on_edge & take_f, sp_f, -4.0)))
    return cltype != -4, bsp, secondpos, best


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
    pos1, mat1, size1 = info1.pos, info1.mat, info1.size
    pos2, mat2, size2 = info2.pos, info2.mat, info2.size

    # Capsule in the box's frame.
    pos = _mul_mat_t_vec(mat2, pos1 - pos2)
    axis = _mul_mat_t_vec(mat2, mat1[:, 2])
    halfaxis = _mul(axis, size1[1])
    found, bsp, secondpos, _ = segment_points(pos, axis, size1, size2, margin)

    def sphere_at(t):
        # N.B. C goes back to the world frame and sphere-box comes back to the
        # box's: kept, for C's rounding.
        centre = _mul_mat_vec(mat2, pos + _mul(halfaxis, t)) + pos2
        return sphere_box(centre, size1[0], margin, pos2, mat2, size2)

    em1, d1, p1, n1 = sphere_at(bsp)
    em2, d2, p2, n2 = sphere_at(secondpos + bsp)
    em1 = em1 & found
    em2 = em2 & found & (secondpos > -3)
    dist = jnp.stack([jnp.where(em1, d1, FAR), jnp.where(em2, d2, FAR)])
    pos_out = jnp.stack([p1, p2])
    frame = jnp.stack([make_frame(n1), make_frame(n2)])
    return dist, pos_out, frame


PORTED[(int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_BOX))] = capsule_box
