"""Multiple contacts from a CCD result: MuJoCo C's `mjc_multicontact` in JAX.

Ports `mjc_multicontact` and `polygonClip` of the installed MuJoCo 3.17 binary
(engine_collision_gjk.c, newer than the C source in /work/csrc): from the
features of the objects' final simplex it recovers a face or an edge of each
geom (boxNormals, meshNormals, cylinder caps; boxEdgeNormals, meshEdgeNormals,
cylinderEdgeNormals, capsuleEdgeNormals), matches a face against a face or an
edge (alignedFaces now keeps the most anti-parallel pair, alignedFaceEdge tests
each face against the separating direction), clips one against the other, keeps
the clipped vertices within the margin, reduces them to the largest
quadrilateral (hull4) or to an edge's two farthest points, and computes each
witness pair on the clipping face; margins are added back by `inflate`.

N.B. the binary's version was decoded from its machine code and checked against
it through `mjc_ccd` (ctypes) on random poses of every pair.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from mjstamp.colliders.gjk import (
    BOX,
    CAPSULE,
    CYLINDER,
    MESH,
    MINVAL,
    Kind,
    Obj,
    cross3,
    dot3,
    mat_vec,
    matT_vec,
    mul,
    normalize3,
    safe_div,
    safe_sqrt,
    where3,
)

FACE_TOL = 0.996  # mjFACE_TOL (~5.1 degrees)
EDGE_TOL = 0.0888  # mjEDGE_TOL
COS16 = (1.0, 0.923879532511287, 0.707106781186548, 0.38268343236509, 0.0, -0.38268343236509,
         -0.707106781186547, -0.923879532511287, -1.0, -0.923879532511287, -0.707106781186548,
         -0.38268343236509, 0.0, 0.38268343236509, 0.707106781186547, 0.923879532511287)
SIN16 = (0.0, 0.38268343236509, 0.707106781186547, 0.923879532511287, 1.0, 0.923879532511287,
         0.707106781186548, 0.38268343236509, 0.0, -0.38268343236509, -0.707106781186547,
         -0.923879532511287, -1.0, -0.923879532511287, -0.707106781186548, -0.38268343236509)
_BOX_FACES = np.array([[(1, 1, 1), (1, 1, -1), (1, -1, -1), (1, -1, 1)],
                       [(-1, 1, -1), (-1, 1, 1), (-1, -1, 1), (-1, -1, -1)],
                       [(-1, 1, -1), (1, 1, -1), (1, 1, 1), (-1, 1, 1)],
                       [(-1, -1, 1), (1, -1, 1), (1, -1, -1), (-1, -1, -1)],
                       [(-1, 1, 1), (1, 1, 1), (1, -1, 1), (-1, -1, 1)],
                       [(1, 1, -1), (-1, 1, -1), (-1, -1, -1), (1, -1, -1)]], np.float64)
_UNIT6 = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)],
                  np.float64)


def globalcoord(o: Obj, local, with_pos=True):
    """C's globalcoord: mat @ local (+ pos)."""
    r = mat_vec(o.mat, local)
    return r + o.pos if with_pos else r


def _gc_batch(o: Obj, local, with_pos=True):
    return jax.vmap(lambda v: globalcoord(o, v, with_pos))(local)


def face_size(k: Kind) -> int:
    """Most vertices of a face of this geom (0: it has no faces)."""
    if k.gtype == CYLINDER:
        return 16
    if k.gtype == BOX:
        return 4
    if k.gtype == MESH:
        return int(k.mesh.polyvert.shape[1])
    return 0


def nnormals(k: Kind) -> int:
    """Most face normals the feature of a simplex can yield."""
    if k.gtype == CYLINDER:
        return 1
    if k.gtype == BOX:
        return 3
    if k.gtype == MESH:
        return max(2, int(k.mesh.vertpoly.shape[1]))
    return 0


def nedgenormals(k: Kind) -> int:
    """Static bound on the edge normals of a geom at a simplex feature."""
    if k.gtype in (CYLINDER, CAPSULE):
        return 1
    if k.gtype == BOX:
        return 3
    if k.gtype == MESH:
        return max(1, int(k.mesh.vertpoly.shape[1]))
    return 0


# ------------------------------------------------------------------------- face normals


def _box_normals2(o: Obj, n):
    """boxNormals2: the box face within mjFACE_TOL of direction n, if any."""
    ln = matT_vec(o.mat, n)
    ln = ln * (1.0 / safe_sqrt(dot3(ln, ln)))
    dots = jax.vmap(lambda e: dot3(ln, e))(jnp.asarray(_UNIT6, n.dtype))
    hit = dots > FACE_TOL
    i = jnp.argmax(hit)
    return globalcoord(o, jnp.asarray(_UNIT6, n.dtype)[i], False), i, hit.any()


def box_normals(o: Obj, dim, vi, d):
    """C's boxNormals: face normals at a simplex feature of a box.

    Returns (N (3, 3), idx (3,), count).
    """
    dtype = o.pos.dtype
    v1, v2, v3 = vi[0], vi[1], vi[2]

    def axis3(bit):
        all_ = ((v1 & bit) != 0) & ((v2 & bit) != 0) & ((v3 & bit) != 0)
        none = ((v1 & bit) == 0) & ((v2 & bit) == 0) & ((v3 & bit) == 0)
        return all_.astype(jnp.int32) - none.astype(jnp.int32)

    def axis2(bit):
        all_ = ((v1 & bit) != 0) & ((v2 & bit) != 0)
        none = ((v1 & bit) == 0) & ((v2 & bit) == 0)
        return all_.astype(jnp.int32) - none.astype(jnp.int32)

    n2, i2, h2 = _box_normals2(o, d)
    z3 = jnp.zeros((3, 3), dtype)
    zi = jnp.zeros(3, jnp.int32)
    # dim 3
    x, y, z = axis3(1), axis3(2), axis3(4)
    nrm3 = globalcoord(o, jnp.stack([x, y, z]).astype(dtype), False)
    c3 = (x != 0).astype(jnp.int32) + (y != 0) + (z != 0)
    first = jnp.where(x != 0, 0, jnp.where(y != 0, 2, 4))
    first = jnp.where(x + y + z == -1, first + 1, first).astype(jnp.int32)
    N3 = jnp.where(c3 == 1, z3.at[0].set(nrm3), z3.at[0].set(n2))
    I3 = jnp.where(c3 == 1, zi.at[0].set(first), zi.at[0].set(jnp.asarray(i2, jnp.int32)))
    k3 = jnp.where(c3 == 1, 1, h2.astype(jnp.int32))
    # dim 2
    x, y, z = axis2(1), axis2(2), axis2(4)
    e = jnp.eye(3, dtype=dtype)
    nx_ = globalcoord(o, e[0] * x, False)
    ny_ = globalcoord(o, e[1] * y, False)
    nz_ = globalcoord(o, e[2] * z, False)
    ix = jnp.where(x > 0, 0, 1)
    iy = jnp.where(y > 0, 2, 3)
    iz = jnp.where(z > 0, 4, 5)
    c2 = (x != 0).astype(jnp.int32) + (y != 0) + (z != 0)
    a0 = where3(x != 0, nx_, ny_)
    a1 = where3((x != 0) & (y != 0), ny_, nz_)
    j0 = jnp.where(x != 0, ix, iy)
    j1 = jnp.where((x != 0) & (y != 0), iy, iz)
    N2 = jnp.where(c2 == 2, jnp.stack([a0, a1, jnp.zeros(3, dtype)]), z3.at[0].set(n2))
    I2 = jnp.where(c2 == 2, jnp.stack([j0, j1, 0]), zi.at[0].set(jnp.asarray(i2, jnp.int32)))
    k2 = jnp.where(c2 == 2, 2, h2.astype(jnp.int32))
    # dim 1
    sx = jnp.where((v1 & 1) != 0, 1.0, -1.0)
    sy = jnp.where((v1 & 2) != 0, 1.0, -1.0)
    sz = jnp.where((v1 & 4) != 0, 1.0, -1.0)
    N1 = jnp.stack([globalcoord(o, e[0] * sx, False), globalcoord(o, e[1] * sy, False),
                    globalcoord(o, e[2] * sz, False)])
    I1 = jnp.stack([jnp.where(sx > 0, 0, 1), jnp.where(sy > 0, 2, 3), jnp.where(sz > 0, 4, 5)])
    N = jnp.where(dim == 3, N3, jnp.where(dim == 2, N2, N1))
    ind = jnp.where(dim == 3, I3, jnp.where(dim == 2, I2, I1)).astype(jnp.int32)
    cnt = jnp.where(dim == 3, k3, jnp.where(dim == 2, k2, jnp.where(dim == 1, 3, 0)))
    return N, ind, cnt


def _first_common(a, na, b, nb, limit):
    """intersect(): up to `limit` entries of a[:na] (in order) also in b[:nb]."""
    ia = jnp.arange(a.shape[0])
    ib = jnp.arange(b.shape[0])
    member = ((a[:, None] == b[None, :]) & (ib[None, :] < nb)).any(1) & (ia < na)
    rank = jnp.cumsum(member) - 1
    out = jnp.zeros(limit, a.dtype)
    for r in range(limit):
        sel = member & (rank == r)
        out = out.at[r].set(jnp.where(sel.any(), a[jnp.argmax(sel)], 0))
    return out, jnp.minimum(member.sum(), limit)


def mesh_normals(k: Kind, o: Obj, dim, vi):
    """meshNormals: polygon normals at a simplex feature of a mesh."""
    m = k.mesh
    K = nnormals(k)
    vp = jnp.asarray(m.vertpoly)
    vn = jnp.asarray(m.vertpolynum)
    pn = jnp.asarray(m.polynormal, o.pos.dtype)
    p0, n0 = vp[vi[0]], vn[vi[0]]
    p1, n1 = vp[vi[1]], vn[vi[1]]
    p2, n2 = vp[vi[2]], vn[vi[2]]
    edge, ne = _first_common(p0, n0, p1, n1, 2)
    face, nf = _first_common(edge, ne, p2, n2, 1)
    pad = lambda x: jnp.zeros(K, jnp.int32).at[:x.shape[0]].set(x[:K])  # noqa: E731
    idx1 = pad(p0)
    idx2 = pad(edge)
    idx3 = pad(face)
    ind = jnp.where(dim == 3, idx3, jnp.where(dim == 2, idx2, idx1))
    cnt = jnp.where(dim == 3, jnp.where((ne > 0) & (nf > 0), 1, 0),
                    jnp.where(dim == 2, ne, jnp.where(dim == 1, n0, 0)))
    N = _gc_batch(o, pn[ind], False)
    return N, ind, cnt


def face_normals(k: Kind, o: Obj, dim, vi, d):
    """Face normals of a geom at its simplex feature: (N (K, 3), idx (K,), count)."""
    if k.gtype == CYLINDER:
        s = jnp.where(vi[0] == 0, 1.0, -1.0).astype(o.pos.dtype)
        n = globalcoord(o, jnp.stack([jnp.zeros_like(s), jnp.zeros_like(s), s]), False)
        return n[None], vi[:1], jnp.where(dim == 1, 1, 0)
    if k.gtype == BOX:
        return box_normals(o, dim, vi, d)
    if k.gtype == MESH:
        return mesh_normals(k, o, dim, vi)
    return jnp.zeros((0, 3), o.pos.dtype), jnp.zeros(0, jnp.int32), jnp.array(0)


# ------------------------------------------------------------------------- edge normals


def edge_normals(k: Kind, o: Obj, dim, v, vi, x):
    """Edge directions at a simplex feature, with their far ends and the (recomputed) start.

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source.

    Ports capsuleEdgeNormals, cylinderEdgeNormals, boxEdgeNormals and
    meshEdgeNormals of the binary (the start vertex is recomputed from its
    index, which removes the margin offset of EPA's support points).

    Args:
      k: static description of the geom.
      o: its pose and size.
      dim: its simplex dimension (1 or 2).
      v: (3, 3) simplex vertices (v[0] is the edge's start).
      vi: (3,) their indices.
      x: (3,) the witness point on this geom.

    Returns:
      (start (3,), res (K, 3) unit directions, ends (K, 3), count).
    """
    dtype = o.pos.dtype
    mat = o.mat
    axis = jnp.stack([mat[0, 2], mat[1, 2], mat[2, 2]])
    if k.gtype == CAPSULE:
        dd = x - o.pos
        dot = mul(dd[0], axis[0]) + mul(axis[1], dd[1]) + mul(axis[2], dd[2])
        lo = -dot - o.size[1]
        hi = o.size[1] - dot
        return mul(lo, axis) + x, axis[None], (mul(hi, axis) + x)[None], jnp.array(1)
    if k.gtype == CYLINDER:
        sgn = jnp.where(vi[0] == 0, -1.0, 1.0).astype(dtype)
        res = sgn * axis
        dd = v[0] - o.pos
        loc = matT_vec(mat, dd)
        n2 = mul(loc[1], loc[1]) + mul(loc[0], loc[0])
        ok = n2 >= 1e-30
        scl = jnp.where(ok, o.size[0] / safe_sqrt(jnp.where(ok, n2, 1.0)), 0.0)
        proj = globalcoord(o, jnp.stack([loc[0] * scl, loc[1] * scl, -sgn * o.size[1]]))
        start = where3(o.margin > 0, proj, v[0])
        h = o.size[1] + o.size[1]
        return start, res[None], (mul(h, res) + start)[None], jnp.array(1)
    if k.gtype == BOX:
        s = o.size

        def corner(i, flip=(1.0, 1.0, 1.0)):
            loc = jnp.stack([jnp.where((i & 1) != 0, s[0], -s[0]) * flip[0],
                             jnp.where((i & 2) != 0, s[1], -s[1]) * flip[1],
                             jnp.where((i & 4) != 0, s[2], -s[2]) * flip[2]])
            return globalcoord(o, loc)

        start = corner(vi[0])
        end2 = corner(vi[1])
        r2, _ = normalize3(end2 - start)
        ends1 = jnp.stack([corner(vi[0], (-1.0, 1.0, 1.0)), corner(vi[0], (1.0, -1.0, 1.0)),
                           corner(vi[0], (1.0, 1.0, -1.0))])
        r1, _ = normalize3(ends1 - start)
        is2 = dim == 2
        res = jnp.where(is2, jnp.zeros((3, 3), dtype).at[0].set(r2), r1)
        ends = jnp.where(is2, jnp.zeros((3, 3), dtype).at[0].set(end2), ends1)
        return start, res, ends, jnp.where(is2, 1, 3)
    if k.gtype == MESH:
        m = k.mesh
        K = nedgenormals(k)
        verts = jnp.asarray(m.vert, dtype)
        start = globalcoord(o, verts[vi[0]])
        end2 = globalcoord(o, verts[vi[1]])
        r2, _ = normalize3(end2 - start)
        polys = jnp.asarray(m.vertpoly)[vi[0]]  # (D,)
        pv = jnp.asarray(m.polyvert)[polys]  # (D, P)
        nv = jnp.asarray(m.polyvertnum)[polys]  # (D,)
        P = pv.shape[1]
        cols = jnp.arange(P)
        hit = (pv == vi[0]) & (cols[None, :] < nv[:, None])
        found = hit.any(1)
        j = jnp.argmax(hit, axis=1)
        kk = jnp.where(j == 0, nv - 1, j - 1)
        prev = jnp.take_along_axis(pv, kk[:, None], 1)[:, 0]
        ends1 = jax.vmap(lambda i: globalcoord(o, verts[i]))(prev)
        r1, _ = normalize3(ends1 - start)
        # N.B. C leaves stale memory where the vertex is not on the polygon (never here)
        r1 = jnp.where(found[:, None], r1, jnp.nan)
        is2 = dim == 2
        res = jnp.where(is2, jnp.zeros((K, 3), dtype).at[0].set(r2), r1[:K])
        ends = jnp.where(is2, jnp.zeros((K, 3), dtype).at[0].set(end2), ends1[:K])
        return start, res, ends, jnp.where(is2, 1, jnp.asarray(m.vertpolynum)[vi[0]])
    return None


# -------------------------------------------------------------------------------- faces


def face_vertices(k: Kind, o: Obj, idx):
    """C's boxFace / meshFace / the cylinder's 16-gon cap: (P, 3) vertices and their count."""
    dtype = o.pos.dtype
    if k.gtype == CYLINDER:
        sgn = jnp.where(idx == 0, 1.0, -1.0).astype(dtype)
        s0, s1 = o.size[0], o.size[1]
        c = jnp.asarray(COS16, dtype)
        sn = jnp.asarray(SIN16, dtype)
        loc = jnp.stack([s0 * c, sgn * (s0 * -sn), jnp.broadcast_to(sgn * s1, c.shape)], -1)
        return _gc_batch(o, loc), jnp.array(16)
    if k.gtype == BOX:
        loc = jnp.asarray(_BOX_FACES, dtype)[idx] * o.size
        return _gc_batch(o, loc), jnp.array(4)
    if k.gtype == MESH:
        m = k.mesh
        P = m.polyvert.shape[1]
        nv = jnp.asarray(m.polyvertnum)[idx]
        ids = jnp.asarray(m.polyvert)[idx]
        i = jnp.arange(P)
        rev = jnp.where(i < nv, nv - 1 - i, 0)
        verts = jnp.asarray(m.vert, dtype)[ids[rev]]
        return _gc_batch(o, verts), nv
    return None


# ------------------------------------------------------------------------------ clipping


def _plane_normal(v1, v2, n):
    """planeNormal: unit normal of the plane through edge v1 v2 perpendicular to the face."""
    res = cross3(v2 - v1, (v1 + n) - v1)
    res, _ = normalize3(res)
    return res, dot3(res, v1)


def area4(a, b, c, d):
    """Area of the quadrilateral a, b, c, d (half the norm of its diagonals' cross product)."""
    g = cross3(a - c, b - d)
    return 0.5 * safe_sqrt(dot3(g, g))


def hull4(poly, npoly, nsteps):
    """The largest-area quadrilateral of a polygon (hull4 in polygonClip).

    A fixed-step replay of C's nested while loops (advance d, then c, then b while
    the area grows). Returns ((4,) indices, finished).
    """
    n = jnp.maximum(npoly, 1)
    area = lambda i: area4(poly[i[0]], poly[i[1]], poly[i[2]], poly[i[3]])  # noqa: E731
    idx0 = jnp.array([0, 1, 2, 3])
    carry = (idx0, lax.stop_gradient(area(idx0)), idx0, jnp.array(0))  # (a,b,c,d), m, res, phase

    def step(_, c):
        abcd, m, res, phase = c
        a, b, cc, d = abcd[0], abcd[1], abcd[2], abcd[3]
        cand = jnp.where(phase == 0, jnp.stack([a, b, cc, (d + 1) % n]),
                         jnp.where(phase == 1, jnp.stack([a, b, (cc + 1) % n, d]),
                                   jnp.stack([a, (b + 1) % n, cc, d])))
        mn = lax.stop_gradient(area(cand))
        up = (phase < 3) & (mn > m)
        # D fails: adjust b, c, d if they caught up with a, advance a
        b2 = jnp.where(b == a, (b + 1) % n, b)
        c2 = jnp.where((b == a) & (cc == b2), (cc + 1) % n, cc)
        d2 = jnp.where((b == a) & (cc == b2) & (d == c2), (d + 1) % n, d)
        a2 = a + 1
        nxt_d = jnp.where(a2 < npoly, 0, 3)
        new_abcd = jnp.where(up, cand, jnp.where(phase == 0, jnp.stack([a2, b2, c2, d2]), abcd))
        new_phase = jnp.where(phase == 3, 3, jnp.where(
            up, jnp.where(phase == 0, 1, phase), jnp.where(phase == 0, nxt_d, jnp.where(
                phase == 1, 2, 0))))
        return new_abcd, jnp.where(up, mn, m), jnp.where(up, cand, res), new_phase

    _, _, res, phase = lax.fori_loop(0, nsteps, step, carry)
    return res, phase == 3


def _witness(v, a, n, d):
    """Witness pair of a clipped vertex: its projection on face 1's plane, then along d."""
    d1 = dot3(v - a, n)
    w1 = v - mul(d1, n)
    dd = dot3(w1 - v, d)
    return w1, w1 - mul(dd, d), dd


def polygon_clip(F, nf, Q, nq, n, d, margin, maxcon, nhull=None):
    """The polygonClip of the binary: clips polygon Q by face F, returns up to 4 witness pairs.

    Args:
      F: (PF, 3) clipping face (first nf valid), normal n.
      nf: () number of valid vertices of F.
      Q: (PQ, 3) polygon (first nq valid).
      nq: () number of valid vertices of Q.
      n: (3,) normal of F.
      d: (3,) direction for the second witness point.
      margin: () sum of the two half margins (vertices farther than it are dropped).
      maxcon: static max_contacts.
      nhull: static number of steps of the 4-point hull search (6 * (PQ + PF) if None).

    Returns:
      (count, w1 (4, 3), w2 (4, 3), dist (4,), overflow).
    """
    dtype = F.dtype
    PF, PQ = F.shape[0], Q.shape[0]
    B = PQ + PF
    ef = jnp.arange(PF)
    F2 = F[jnp.where(ef == nf - 1, 0, jnp.minimum(ef + 1, PF - 1))]
    pn, pd = jax.vmap(lambda a, b: _plane_normal(a, b, n))(F, F2)
    poly = jnp.zeros((B, 3), dtype).at[:PQ].set(Q)
    ib = jnp.arange(B)

    def clip(e, c):
        poly, npoly, over = c
        active = e < nf
        a = F[e]
        pne, pde = pn[e], pd[e]
        P = poly
        Qv = poly[jnp.where(ib < npoly - 1, ib + 1, 0)]
        valid = ib < npoly
        in1 = lax.stop_gradient(dot3(P - a, pne)) > -MINVAL
        in2 = lax.stop_gradient(dot3(Qv - a, pne)) > -MINVAL
        pq = Qv - P
        tmp = dot3(pne, pq)
        t = safe_div(pde - dot3(pne, P), tmp)
        X = P + mul(t[:, None], pq)
        ts = lax.stop_gradient(t)
        has_x = valid & (in1 != in2) & (lax.stop_gradient(tmp) != 0) & (ts >= 0) & (ts <= 1)
        has_q = valid & in2
        cand = jnp.stack([X, Qv], 1).reshape(2 * B, 3)
        keep = jnp.stack([has_x, has_q], 1).reshape(2 * B)
        pos = jnp.cumsum(keep) - 1
        new = jnp.zeros((B, 3), dtype).at[jnp.where(keep, pos, B)].set(cand, mode="drop")
        cnt = keep.sum()
        poly = jnp.where(active, new, poly)
        npoly = jnp.where(active, jnp.minimum(cnt, B), npoly).astype(jnp.int32)
        return poly, npoly, over | (active & (cnt > B))

    nq = jnp.asarray(nq, jnp.int32)
    poly, npoly, over = lax.fori_loop(0, PF, clip, (poly, nq, jnp.array(False)))
    # keep the vertices within the margin of face 1
    keep = (ib < npoly) & (lax.stop_gradient(dot3(poly - F[0], n)) <= margin)
    pos = jnp.cumsum(keep) - 1
    poly = jnp.zeros((B, 3), dtype).at[jnp.where(keep, pos, B)].set(poly, mode="drop")
    npoly = keep.sum()
    # choose the witnesses
    quad = (maxcon < 5) & (npoly >= 5)
    qidx, qdone = hull4(poly, npoly, nhull or 6 * B)
    pairs = poly[None, :, :] - poly[:, None, :]
    d2 = lax.stop_gradient(dot3(pairs, pairs))
    ok = (ib[:, None] < ib[None, :]) & (ib[None, :] < npoly)
    flat = jnp.where(ok, d2, -jnp.inf).reshape(-1)
    best = jnp.argmax(flat)
    far = flat[best] > 0
    b1 = jnp.where(far, best // B, 0)
    b2 = jnp.where(far, best % B, 1)
    dedupe = ~quad & (nq == 2) & (npoly >= 3)
    nall = jnp.minimum(npoly, maxcon)
    sel = jnp.where(quad, qidx, jnp.where(dedupe, jnp.array([0, 1, 2, 3]).at[0].set(b1).at[1].set(
        b2), jnp.arange(4)))
    cnt = jnp.where(quad, 4, jnp.where(dedupe, 2, nall))
    cnt = jnp.where(nf < 3, 0, jnp.where(npoly < 1, 0, cnt))
    w1, w2, dist = jax.vmap(lambda v: _witness(v, F[0], n, d))(poly[jnp.minimum(sel, B - 1)])
    return cnt, w1, w2, dist, over | (quad & ~qdone)


# ------------------------------------------------------------------------- multicontact


def _simplex_dim(vi, v):
    """simplexDim: dimension of the feature, moving the third vertex up when needed."""
    same01 = vi[0] == vi[1]
    same02 = vi[0] == vi[2]
    dim = jnp.where(same01, jnp.where(same02, 1, 2),
                    jnp.where((vi[2] == vi[0]) | (vi[2] == vi[1]), 2, 3))
    mv = same01 & ~same02
    vi = vi.at[1].set(jnp.where(mv, vi[2], vi[1]))
    v = v.at[1].set(where3(mv, v[2], v[1]))
    return dim, vi, v


def multicontact(k1: Kind, k2: Kind, o1: Obj, o2: Obj, sv1, si1, sv2, si2, nsimplex, x1, x2,
                 dist, max_contacts: int):
    """mjc_multicontact (3.17 binary): more witness pairs from the objects' simplex features.

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source.

    Args:
      k1: static description of geom 1.
      k2: static description of geom 2.
      o1: pose, size and margin of geom 1 (margins as mjc_ccd leaves them).
      o2: the same of geom 2.
      sv1: (3, 3) geom 1's simplex points.
      si1: (3,) their vertex indices.
      sv2: (3, 3) geom 2's simplex points.
      si2: (3,) their vertex indices.
      nsimplex: () size of the objects' simplex.
      x1: (3,) the single witness point on geom 1.
      x2: (3,) the one on geom 2.
      dist: () its distance.
      max_contacts: static.

    Returns:
      (nx, dist (4,), x1 (4, 3), x2 (4, 3), overflow); nx = 1 leaves the single pair.
    """
    dtype = x1.dtype
    single = (jnp.array(1), jnp.zeros(4, dtype).at[0].set(dist),
              jnp.zeros((4, 3), dtype).at[0].set(x1), jnp.zeros((4, 3), dtype).at[0].set(x2),
              jnp.array(False))
    for k in (k1, k2):
        if k.gtype == MESH and k.mesh.polynum == 0:
            return single
    has1 = nnormals(k1) > 0 or nedgenormals(k1) > 0
    has2 = nnormals(k2) > 0 or nedgenormals(k2) > 0
    if not (has1 and has2):
        return single
    n = nsimplex
    sel = jnp.stack([jnp.array(0), jnp.where(n != 1, 1, 0), jnp.where(n >= 3, 2, 0)])
    dim1, vi1, v1 = _simplex_dim(si1[sel], sv1[sel])
    dim2, vi2, v2 = _simplex_dim(si2[sel], sv2[sel])
    d = x2 - x1
    dneg = x1 - x2
    N1, I1, c1 = face_normals(k1, o1, dim1, vi1, dneg)
    N2, I2, c2 = face_normals(k2, o2, dim2, vi2, d)
    K1, K2 = N1.shape[0], N2.shape[0]
    dsg = lax.stop_gradient(d)
    # aligned faces: the most anti-parallel pair, each facing the other geom
    if K1 and K2:
        thr = EDGE_TOL * safe_sqrt(dot3(dsg, dsg))
        t1 = dot3(dsg, lax.stop_gradient(N1))
        t2 = dot3(dsg, lax.stop_gradient(N2))
        cc = jax.vmap(lambda a: jax.vmap(lambda b: dot3(a, b))(lax.stop_gradient(N2)))(
            lax.stop_gradient(N1))
        ok = ((jnp.arange(K1) < c1)[:, None] & (jnp.arange(K2) < c2)[None, :]
              & (t1 < -thr)[:, None] & (thr < t2)[None, :] & (cc < -FACE_TOL))
        flat = jnp.where(ok, cc, jnp.inf).reshape(-1)
        best = jnp.argmin(flat)
        found = ok.any()
        ff_i, ff_j = best // K2, best % K2
    else:
        found = jnp.array(False)
        ff_i = ff_j = jnp.array(0)
    e1_branch = ~found & (dim1 != 3) & (c2 > 0) & ((dim1 <= dim2) | (c1 == 0))
    e2_branch = ~found & ~e1_branch
    # edge of geom 1 against a face of geom 2
    E1 = edge_normals(k1, o1, dim1, v1, vi1, x1) if K2 else None
    if E1 is not None:
        st1, R1, ends1, ce1 = E1
        J = R1.shape[0]
        okf = (jnp.arange(K2) < c2) & (MINVAL < dot3(dsg, lax.stop_gradient(N2)))
        par = jax.vmap(lambda a: jax.vmap(lambda b: jnp.abs(dot3(a, b)))(
            lax.stop_gradient(R1)))(lax.stop_gradient(N2))
        hit = okf[:, None] & (jnp.arange(J) < ce1)[None, :] & (EDGE_TOL > par)
        e1_found = e1_branch & hit.any()
        f = jnp.argmax(hit.reshape(-1))
        e1_i, e1_j = f // J, f % J
    else:
        e1_found = jnp.array(False)
        e1_i = e1_j = jnp.array(0)
    # face of geom 1 against an edge of geom 2
    E2 = edge_normals(k2, o2, dim2, v2, vi2, x2) if K1 else None
    if E2 is not None:
        st2, R2, ends2, ce2 = E2
        J = R2.shape[0]
        okf = (jnp.arange(K1) < c1) & (MINVAL < dot3(lax.stop_gradient(dneg),
                                                     lax.stop_gradient(N1)))
        par = jax.vmap(lambda a: jax.vmap(lambda b: jnp.abs(dot3(a, b)))(
            lax.stop_gradient(R2)))(lax.stop_gradient(N1))
        hit = okf[:, None] & (jnp.arange(J) < ce2)[None, :] & (EDGE_TOL > par)
        e2_found = e2_branch & (dim2 != 3) & hit.any()
        f = jnp.argmax(hit.reshape(-1))
        e2_i, e2_j = f // J, f % J
    else:
        e2_found = jnp.array(False)
        e2_i = e2_j = jnp.array(0)
    mode_ff, mode_e1, mode_e2 = found, e1_found, e2_found
    any_mode = mode_ff | mode_e1 | mode_e2
    # faces and edges to clip
    P1, P2 = face_size(k1), face_size(k2)
    PF = max(P1, P2, 3)
    PQ = max(P1, P2, 2)

    def pad(x, rows):
        return jnp.zeros((rows, 3), dtype).at[:x.shape[0]].set(x[:rows])

    zeroF = jnp.zeros((PF, 3), dtype)
    zeroQ = jnp.zeros((PQ, 3), dtype)
    if P1:
        f1, nf1 = face_vertices(k1, o1, I1[jnp.where(mode_ff, ff_i, e2_i)])
    else:
        f1, nf1 = zeroF, jnp.array(0)
    if P2:
        f2, nf2 = face_vertices(k2, o2, I2[jnp.where(mode_ff, ff_j, e1_i)])
    else:
        f2, nf2 = zeroF, jnp.array(0)
    if E1 is not None:
        edge1 = jnp.stack([st1, ends1[e1_j]])
        n_e1 = N2[e1_i]
    else:
        edge1, n_e1 = jnp.zeros((2, 3), dtype), jnp.zeros(3, dtype)
    if E2 is not None:
        edge2 = jnp.stack([st2, ends2[e2_j]])
        n_e2 = N1[e2_i]
    else:
        edge2, n_e2 = jnp.zeros((2, 3), dtype), jnp.zeros(3, dtype)
    n_ff1 = N1[ff_i] if K1 else jnp.zeros(3, dtype)
    n_ff2 = N2[ff_j] if K2 else jnp.zeros(3, dtype)
    F = jnp.where(mode_e1, pad(f2, PF), pad(f1, PF))
    nF = jnp.where(mode_e1, nf2, nf1)
    Q = jnp.where(mode_ff, pad(f2, PQ), jnp.where(mode_e1, pad(edge1, PQ), pad(edge2, PQ)))
    nQ = jnp.where(mode_ff, nf2, 2)
    nrm = where3(mode_ff, n_ff1, where3(mode_e1, n_e1, n_e2))
    wdir = where3(mode_ff, n_ff2, -nrm)
    inf_n = where3(mode_ff, -n_ff2, where3(mode_e1, -n_e1, n_e2))
    del zeroQ
    m1 = 0.0 if k1.gtype == CAPSULE else 0.5 * o1.margin
    m2 = 0.0 if k2.gtype == CAPSULE else 0.5 * o2.margin
    cnt, w1, w2, dd, over = polygon_clip(F, nF, Q, nQ, nrm, wdir, m1 + m2, max_contacts)
    # geom 1's edge was clipped by geom 2's face: the witness pairs swap
    a1 = where3(mode_e1, w2, w1)
    a2 = where3(mode_e1, w1, w2)
    # inflate by the margins along the matched face normal
    m1 = jnp.asarray(m1, dtype)
    m2 = jnp.asarray(m2, dtype)
    a1 = jnp.where(m1 != 0, a1 + mul(m1, inf_n), a1)
    a2 = jnp.where(m2 != 0, a2 + mul(-m2, inf_n), a2)
    both0 = (m1 == 0) & (m2 == 0)
    dd = jnp.where(both0, dd, dd - (m1 + m2))
    use = any_mode & (cnt > 0) & (nsimplex > 0)
    nx = jnp.where(use, jnp.minimum(cnt, 4), 1)
    slots = jnp.arange(4) < nx
    out_d = jnp.where(use, jnp.where(slots, dd, 0.0), single[1])
    out_1 = jnp.where(use, jnp.where(slots[:, None], a1, 0.0), single[2])
    out_2 = jnp.where(use, jnp.where(slots[:, None], a2, 0.0), single[3])
    return nx, out_d, out_1, out_2, use & over
