"""mjc_ccd and mjc_penetration: a geom pair's contacts from GJK, EPA and multicontact.

`ccd` runs GJK (`gjk.gjk`), EPA (`gjk.epa`) where the geoms overlap, and
MuJoCo C's multi-contact rule (`gjk_multi.multicontact`), with AD through
every iteration; `ccd_converged` runs the same search without derivatives
until C's tests stop it (`gjk.until_converged`) and differentiates one rebuild
of the converged simplex (pairs of `CONVERGED_KINDS`). Both return C's
contacts in fixed slots (`CCDResult`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from mjstamp.colliders import gjk_multi
from mjstamp.colliders.gjk import (
    BOX,
    CAPSULE,
    CCD_ITERATIONS,
    CCD_TOLERANCE,
    MESH,
    SPHERE,
    Kind,
    Obj,
    Vert,
    cross3,
    dot3,
    epa,
    gjk,
    lincomb4,
    mul,
    normalize3,
    project_origin_plane,
    safe_sqrt,
    start_polytope,
    subdistance,
    support_raw,
    tree_where,
    tri_affine_coord,
    until_converged,
    where3,
)


class CCDResult(NamedTuple):
    """The contacts mjc_penetration builds from mjc_ccd's status (fixed slots)."""

    ncon: jax.Array  # () int number of contacts (0 when mjc_ccd's distance is not < 0)
    dist: jax.Array  # (K,) status->dist[i] (before adding the margin)
    x1: jax.Array  # (K, 3)
    x2: jax.Array  # (K, 3)
    overflow: jax.Array  # () bool: a fixed buffer was too small (result may differ from C)


def _inflate(x1, x2, dist, m1, m2):
    """inflate() of the 3.17 binary for one witness pair (normal from x1 to x2)."""
    n, _ = normalize3(x2 - x1)
    x1n = jnp.where(m1 != 0, x1 + mul(m1, n), x1)
    x2n = jnp.where(m2 != 0, x2 + mul(-m2, n), x2)
    both0 = (m1 == 0) & (m2 == 0)
    return (where3(both0, x1, x1n), where3(both0, x2, x2n),
            jnp.where(both0, dist, dist - (m1 + m2)))


def discrete(k: Kind, o: Obj):
    """The test of discreteGeoms for one object with its margin."""
    return jnp.asarray(k.discrete) & (o.margin == 0)


class Single(NamedTuple):
    """mjc_ccd's single contact and the objects' simplex that multiple contacts start from."""

    contact: jax.Array  # () bool: mjc_ccd's distance is < 0
    shallow: jax.Array  # () bool: the shrunk-geom GJK decided (no EPA)
    dist: jax.Array  # () status->dist[0]
    x1: jax.Array  # (3,)
    x2: jax.Array  # (3,)
    simplex: Vert  # (4,) shallow: GJK's simplex of the shrunk geoms; else rows 0-2: EPA's face
    nsimplex: jax.Array  # () its size
    overflow: jax.Array  # () bool


def _single(k1: Kind, k2: Kind, o1: Obj, o2: Obj, *, tolerance, kmax) -> Single:
    """mjc_ccd up to its single contact (GJK on shrunk geoms, else GJK and EPA on full ones)."""
    dtype = o1.pos.dtype
    itype = jnp.int32
    vi0 = jnp.array(-1, itype)
    x1c, x2c = o1.pos, o2.pos
    # ---- shrunk geoms: spheres/capsules to points/segments, margins removed
    always = k1.gtype in (SPHERE, CAPSULE) or k2.gtype in (SPHERE, CAPSULE)
    use_shrink = jnp.asarray(always) | (o1.margin > 0) | (o2.margin > 0)
    fm1, fm2 = _radii(k1, k2, o1, o2)
    # N.B. both GJK runs (shrunk and full geoms) go through one traced body: the
    # vertindex (mesh warm start) carries from the first to the second.
    zero = jnp.zeros((), dtype)

    def phase(carry, xs):
        vi1, vi2 = carry
        shrink, m1, m2, cutoff, reset = xs
        vi1 = jnp.where(reset, vi0, vi1)
        vi2 = jnp.where(reset, vi0, vi2)
        r = gjk(k1, k2, o1._replace(margin=m1), o2._replace(margin=m2), x1c, x2c, vi1, vi2,
                shrink=shrink, get_dist=shrink, dist_cutoff=cutoff, tolerance=tolerance,
                kmax=kmax)
        return (r.vi1, r.vi2), r

    xs = (jnp.array([True, False]), jnp.stack([zero, o1.margin]), jnp.stack([zero, o2.margin]),
          jnp.stack([0.0 + (fm1 + fm2), zero]), jnp.stack([jnp.array(False), ~use_shrink]))
    _, R = lax.scan(phase, (vi0, vi0), xs)
    A = jax.tree_util.tree_map(lambda x: x[0], R)
    B = jax.tree_util.tree_map(lambda x: x[1], R)
    shallow = use_shrink & (A.dist > tolerance)
    ax1, ax2, adist = _inflate(A.x1, A.x2, A.dist, fm1, fm2)
    a_contact = shallow & (adist < 0)
    # ---- full geoms: EPA
    epa_go = (B.dist <= tolerance) & (B.nsimplex >= 2) & ~B.separated
    P, ret, pvi1, pvi2 = start_polytope(k1, k2, o1, o2, B.simplex, B.nsimplex, B.vi1, B.vi2,
                                        kmax)
    E = epa(k1, k2, o1, o2, P, pvi1, pvi2, discrete=discrete(k1, o1) & discrete(k2, o2),
            tolerance=tolerance, kmax=kmax)
    face = epa_go & (ret == 0) & E.face_ok
    b_contact = ~shallow & face & (E.dist < 0)
    face4 = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[3:]]), E.face, A.simplex)
    return Single(
        contact=a_contact | b_contact, shallow=shallow,
        dist=jnp.where(shallow, adist, E.dist),
        x1=where3(shallow, ax1, E.x1), x2=where3(shallow, ax2, E.x2),
        simplex=tree_where(shallow, A.simplex, face4),
        nsimplex=jnp.where(shallow, A.nsimplex, 3),
        overflow=~shallow & epa_go & (ret == 0) & E.overflow)


def _multi(k1: Kind, k2: Kind, o1: Obj, o2: Obj, s: Single, max_contacts: int) -> CCDResult:
    """mjc_penetration's contacts from mjc_ccd's single one (`multicontact` when allowed)."""
    itype = jnp.int32
    if max_contacts < 2:
        return CCDResult(s.contact.astype(itype), s.dist[None], s.x1[None], s.x2[None],
                         s.overflow)
    nslot = 4
    sm = s.simplex
    nx, mdist, mx1, mx2, mover = gjk_multi.multicontact(
        k1, k2, o1, o2, sm.v1[:3], sm.i1[:3], sm.v2[:3], sm.i2[:3], s.nsimplex, s.x1, s.x2,
        s.dist, max_contacts)
    nx = jnp.where(s.contact, nx, 1)
    # mjc_ccd returns the least distance; mjc_penetration keeps all nx witnesses when < 0
    valid = jnp.arange(nslot) < nx
    mind = jnp.min(jnp.where(valid, lax.stop_gradient(mdist), jnp.inf))
    ncon = jnp.where(s.contact & (mind < 0), nx, 0)
    return CCDResult(ncon.astype(itype), mdist, mx1, mx2, s.overflow | (s.contact & mover))


def ccd(k1: Kind, k2: Kind, o1: Obj, o2: Obj, *, max_contacts: int,
        tolerance=CCD_TOLERANCE, kmax=CCD_ITERATIONS) -> CCDResult:
    """mjc_ccd followed by mjc_penetration's test (the 3.17 binary, native CCD).

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source. Reverse-mode AD goes through
    every one of C's iterations (fixed trip counts); `ccd_converged` gives the
    same contacts at a fraction of the cost.

    Args:
      k1: static description of geom 1 (type 1 <= type 2 as mjc_Convex receives them).
      k2: static description of geom 2.
      o1: pose and size of geom 1; its margin is the pair's margin (mjc_initCCDObj).
      o2: the same of geom 2.
      max_contacts: static, maxContacts() of mjc_Convex (1, 2 or 4).
      tolerance: ccd_tolerance.
      kmax: ccd_iterations (static).

    Returns:
      `CCDResult` with max(max_contacts, 4) slots when max_contacts > 1, else 1.
    """
    s = _single(k1, k2, o1, o2, tolerance=tolerance, kmax=kmax)
    return _multi(k1, k2, o1, o2, s, max_contacts)


def _straight(value, rebuilt):
    """`value` exactly, with the derivatives of `rebuilt` (which equals it to rounding)."""
    return jax.tree_util.tree_map(
        lambda v, r: lax.stop_gradient(v) + (r - lax.stop_gradient(r)), value, rebuilt)


def _rigid(o: Obj, points):
    """Points fixed in a geom's frame, as functions of its pose: (..., 3) -> (..., 3).

    Their values come from the converged search (no derivative); their
    derivatives are those of material points of the geom.
    """
    pos, mat = lax.stop_gradient(o.pos), lax.stop_gradient(o.mat)
    local = jnp.einsum("ji,...j->...i", mat, lax.stop_gradient(points) - pos)
    return jnp.einsum("ij,...j->...i", o.mat, local) + o.pos


# Geom types whose pairs `ccd_converged` differentiates as `ccd` does.
CONVERGED_KINDS = frozenset({SPHERE, CAPSULE, BOX, MESH})


def ccd_converged(k1: Kind, k2: Kind, o1: Obj, o2: Obj, *, max_contacts: int,
                  tolerance=CCD_TOLERANCE, kmax=CCD_ITERATIONS) -> CCDResult:
    """`ccd`'s contacts, its search run to convergence only, then differentiated once.

    GJK and EPA run without derivatives and stop when C's tests stop them
    (`until_converged`). Their result is then rebuilt as a function of the
    poses from the simplex they converged to: its points are material points
    of the two geoms (a box corner, a mesh vertex, a capsule's end) or, for one
    point of a sphere's surface, its support in the converged direction; the
    single contact is the closest point of that simplex (GJK) or the
    projection of the origin on EPA's final face, and the multiple contacts
    follow from those as in `ccd`. Values are `ccd`'s to the bit (`_straight`).

    Derivatives: those of `ccd` (central differences of distance, position
    and normal within 1e-6 on random poses) for pairs of boxes, meshes,
    spheres and capsules (`CONVERGED_KINDS`). Not for cylinders and
    ellipsoids: there the contact slides over a surface curved in two ways
    as the normal turns, which material points and one support leave out;
    their pairs keep `ccd`.

    Args: as `ccd`.

    Returns:
      `CCDResult`, as `ccd`.
    """
    sg = lax.stop_gradient
    with until_converged():
        s = _single(k1, k2, sg(o1), sg(o2), tolerance=tolerance, kmax=kmax)
    s = jax.tree_util.tree_map(sg, s)
    sm, n = s.simplex, s.nsimplex
    valid = jnp.arange(4) < n
    # 1. the simplex as material points of the geoms
    v1 = _straight(sm.v1, _rigid(o1, sm.v1))
    v2 = _straight(sm.v2, _rigid(o2, sm.v2))
    vert = v1 - v2
    # 2. where a full sphere's or capsule's simplex points are one point of its surface sampled
    # at nearby directions, its support in the converged direction instead (it slides over
    # the surface as the normal turns): EPA's face normal, or towards GJK's closest point
    _, fv = project_origin_plane(vert[2], vert[1], vert[0])
    gx = lincomb4(subdistance(n, vert), n, vert)
    toward, _ = normalize3(where3(s.shallow, -gx, fv))
    shrunk = s.shallow  # the shallow GJK ran on spheres and capsules shrunk to their cores
    c1, p1 = _curved(k1, o1, sm.v1, valid, toward, sm.i1[0], shrunk)
    c2, p2 = _curved(k2, o2, sm.v2, valid, -toward, sm.i2[0], shrunk)
    w1 = where3(p1[..., None], jnp.broadcast_to(c1, (4, 3)), v1)
    w2 = where3(p2[..., None], jnp.broadcast_to(c2, (4, 3)), v2)
    wv = sg(w1 - w2)
    area = cross3(wv[1] - wv[0], wv[2] - wv[0])
    flat = ~s.shallow & (dot3(area, area) < 1e-24)  # the replaced face degenerates
    one = p1 & p2  # both sides one point each: the pair of supports
    keep = flat & ~one
    v1 = where3(keep, v1, w1)
    v2 = where3(keep, v2, w2)
    vert = v1 - v2
    n_eff = jnp.where(one, 1, n)
    # shallow: the closest point of GJK's simplex, inflated by the shrunk radii
    lam = subdistance(n_eff, vert)
    g1 = lincomb4(lam, n_eff, v1)
    g2 = lincomb4(lam, n_eff, v2)
    gd = safe_sqrt(dot3(g1 - g2, g1 - g2))
    a1, a2, ad = _inflate(g1, g2, gd, *_radii(k1, k2, o1, o2))
    # deep: the origin's projection on EPA's face (depth: the face of material points)
    vf = where3(one, jnp.stack([vert[0], vert[0] + _E1, vert[0] + _E2, vert[0]]), vert)  # no 0/0
    _, fvw = project_origin_plane(vf[2], vf[1], vf[0])
    tl = tri_affine_coord(vf[0], vf[1], vf[2], fvw)
    tl = jnp.where(one, jnp.array([1.0, 0.0, 0.0], tl.dtype), tl)
    e1 = (mul(tl[0], v1[0]) + mul(tl[1], v1[1])) + mul(tl[2], v1[2])
    e2 = (mul(tl[0], v2[0]) + mul(tl[1], v2[1])) + mul(tl[2], v2[2])
    ed = -safe_sqrt(dot3(fv, fv))
    x1 = _straight(s.x1, where3(s.shallow, a1, e1))
    x2 = _straight(s.x2, where3(s.shallow, a2, e2))
    dist = _straight(s.dist, jnp.where(s.shallow, ad, ed))
    s = s._replace(x1=x1, x2=x2, dist=dist, simplex=sm._replace(v1=v1, v2=v2, vert=vert))
    return _multi(k1, k2, o1, o2, s, max_contacts)


_E1 = np.array([1.0, 0.0, 0.0])
_E2 = np.array([0.0, 1.0, 0.0])
# A sphere's or capsule's simplex points closer together than this share of its radius are one
# point of its surface (EPA samples it at nearby directions).
POINT_SHARE = 0.1


def _curved(k: Kind, o: Obj, points, valid, d, vi, shrunk):
    """A full sphere's or capsule's support in direction d, where its simplex points are one.

    EPA samples a sphere's surface (or a capsule's cap) at nearby directions;
    the contact is its support in the converged direction, which slides over
    the surface as that direction turns. A feature that spans the geom (a
    capsule's side line) and shrunk geoms (a point, a segment) keep material points.

    Returns:
      ((3,) support with its margin, as a function of the pose and d; () bool: use it).
    """
    if k.gtype not in (SPHERE, CAPSULE):
        return jnp.zeros(3, points.dtype), jnp.array(False)
    pts = lax.stop_gradient(points)
    gap = jnp.max(jnp.where(valid[:, None] & valid[None, :],
                            jnp.linalg.norm(pts[:, None] - pts[None, :], axis=-1), 0.0))
    use = (gap < POINT_SHARE * lax.stop_gradient(o.size[0])) & ~shrunk
    p, _ = support_raw(k, o, d, vi)
    p = jnp.where(o.margin > 0, p + mul(d, 0.5 * o.margin), p)
    return p, use


def _radii(k1: Kind, k2: Kind, o1: Obj, o2: Obj):
    """What shallow witnesses are inflated by: half the margin, plus a sphere's/capsule's radius."""
    fm1, fm2 = 0.5 * o1.margin, 0.5 * o2.margin
    if k1.gtype in (SPHERE, CAPSULE):
        fm1 = fm1 + o1.size[0]
    if k2.gtype in (SPHERE, CAPSULE):
        fm2 = fm2 + o2.size[0]
    return fm1, fm2
