"""MuJoCo C's native convex collision detection (GJK, EPA) in JAX, for one geom pair.

Ports `mjc_ccd` of the installed MuJoCo 3.17 binary (`engine_collision_gjk.c`,
`engine_collision_convex.c`): GJK with its termination tests and `gjkIntersect`
fallback, the EPA start polytopes (`polytope2/3/4`), face expansion over the
horizon found by C's recursive search, witness points, the shrinking of spheres
and capsules (and of geoms with margins) to a point, segment or bare shape, and
the shape support functions with margins as `mjc_initCCDObj` sets them.
Multiple contacts (`mjc_multicontact`) are in `gjk_multi`; `ccd` puts the three
together as `mjc_ccd` and `mjc_penetration` do.

N.B. the 3.17 binary is newer than the C source in /work/csrc: the simplex lives
in the geoms' CCD objects, a geom with a margin is first collided bare and
inflated (as spheres and capsules are), point and segment supports count as
discrete, and `mjc_multicontact` also runs after the shallow (GJK-only) path.
These functions follow the binary, decoded instruction by instruction and
checked against it through `mjc_ccd` (ctypes) on random poses.

JAX form: every loop has a fixed trip count (`lax.fori_loop`/`scan` with masks,
a stopped lane's body the identity), so reverse-mode AD can go through it
(`ccd.ccd`); within `until_converged` the same loops are `while_loop`s that end when
C's tests stop them, and `ccd.ccd_converged` differentiates only a rebuild of the
converged simplex (what the colliders use). The polytope lives in fixed-size
arrays sized for `ccd_iterations`, data-dependent branches compute both sides
and select. Floating-point expressions keep C's evaluation order so that the
discrete decisions (which face, which vertex) are C's.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from mjstamp.colliders import cmath

# mjtGeom
PLANE, HFIELD, SPHERE, CAPSULE, ELLIPSOID, CYLINDER, BOX, MESH = range(8)

MINVAL = 1e-15
MINVAL2 = MINVAL * MINVAL
MAXVAL2 = 1e10 * 1e10
MAX_LIMIT = float(np.finfo(np.float64).max)
FLT_MAX = float(np.finfo(np.float32).max)
MINDIST = MINVAL2  # mjMINDIST2/3/4 in double precision
MINEPATOL = MINVAL

# mjOption defaults (MJX's Option has neither field).
CCD_ITERATIONS = 35
CCD_TOLERANCE = 1e-6

# Fixed sizes of the EPA buffers. C's horizon holds 24 edges; the depth-first
# search over deleted faces takes 2 * (deleted faces) + 1 steps (C never deletes
# more than ~12 faces on the shapes here: 23 steps at most over 14,000 draws).
NHORIZON = 24
NDFS = 32


# ------------------------------------------------------------------------------------- helpers

# N.B. XLA's CPU backend contracts a*b + c into fused multiply-adds (single rounding), which C
# does not: results then differ from C in the last bit, enough to flip the discrete decisions of
# GJK/EPA on degenerate poses. Multiplying each product by a runtime 1 (XLA cannot fold it) keeps
# the product rounded before the addition: fma(a*b, 1, c) == (a*b) + c. `exact()` sets that 1
# for the duration of a trace.
_CTX = threading.local()


@contextlib.contextmanager
def exact(ref: jax.Array):
    """Within this context, `mul` rounds products as C does (see above).

    Args:
      ref: any traced array; a runtime 1 is derived from its first element.
    """
    prev = getattr(_CTX, "one", None)
    _CTX.one = lax.stop_gradient(jnp.sign(jnp.abs(jnp.ravel(ref)[0]) + 1.0))
    try:
        yield
    finally:
        _CTX.one = prev


def mul(a, b):
    """The product a * b, rounded before any addition that follows (see `exact`)."""
    one = getattr(_CTX, "one", None)
    p = a * b
    return p if one is None else p * one


@contextlib.contextmanager
def until_converged():
    """Within this context, GJK's, EPA's and the horizon's loops stop when they are done.

    Their fixed trip counts (`lax.fori_loop`) become `lax.while_loop`s that end
    when every lane has stopped, with the same results: a stopped lane's body is
    the identity. Reverse-mode AD does not go through them: `ccd_converged`
    differentiates a rebuild of the converged simplex instead.
    """
    prev = getattr(_CTX, "early", False)
    _CTX.early = True
    try:
        yield
    finally:
        _CTX.early = prev


def _loop(n: int, body, carry, done):
    """lax.fori_loop(0, n, body, carry), or, within `until_converged`, until `done(carry)`."""
    if not getattr(_CTX, "early", False):
        return lax.fori_loop(0, n, body, carry)

    def cond(c):
        i, x = c
        return (i < n) & ~done(x)

    def step(c):
        i, x = c
        return i + 1, body(i, x)

    return lax.while_loop(cond, step, (jnp.array(0), carry))[1]



def dot3(a, b):
    """The dot product a . b in C's order ((a0 b0 + a1 b1) + a2 b2)."""
    return mul(a[..., 0], b[..., 0]) + mul(a[..., 1], b[..., 1]) + mul(a[..., 2], b[..., 2])


def cross3(a, b):
    """The cross product a x b as C's cross3."""
    return jnp.stack([mul(a[..., 1], b[..., 2]) - mul(a[..., 2], b[..., 1]),
                      mul(a[..., 2], b[..., 0]) - mul(a[..., 0], b[..., 2]),
                      mul(a[..., 0], b[..., 1]) - mul(a[..., 1], b[..., 0])], axis=-1)


def det3(v1, v2, v3):
    """v1 . (v2 x v3) as C's det3."""
    return (mul(v1[..., 0], mul(v2[..., 1], v3[..., 2]) - mul(v2[..., 2], v3[..., 1]))
            + mul(v1[..., 1], mul(v2[..., 2], v3[..., 0]) - mul(v2[..., 0], v3[..., 2]))
            + mul(v1[..., 2], mul(v2[..., 0], v3[..., 1]) - mul(v2[..., 1], v3[..., 0])))


def safe_div(a, b):
    """The quotient a / b with b = 0 replaced by 1 (N.B. only where C's result is not selected)."""
    return a / jnp.where(b == 0, 1.0, b)


def div3(v, s):
    """The quotient v / s per component.

    N.B. XLA rewrites v / broadcast(s) as v * (1/s), which C does not.
    """
    return jnp.stack([v[..., 0] / s, v[..., 1] / s, v[..., 2] / s], axis=-1)


# sqrt(x), 0 with a zero gradient at x <= 0: the ports' shared one.
safe_sqrt = cmath.sqrt


def normalize3(v):
    """mju_normalize3: v / |v|, (1, 0, 0) when |v| < mjMINVAL. Returns (unit, norm)."""
    n = safe_sqrt(dot3(v, v))
    small = n < MINVAL
    inv = 1.0 / jnp.where(small, 1.0, n)
    unit = jnp.where(small[..., None], jnp.array([1.0, 0.0, 0.0], v.dtype), v * inv[..., None])
    return unit, n


def mat_vec(mat, v):
    """The product mat @ v, rows in C's order."""
    return jnp.stack([mul(mat[0, 0], v[0]) + mul(mat[0, 1], v[1]) + mul(mat[0, 2], v[2]),
                      mul(mat[1, 0], v[0]) + mul(mat[1, 1], v[1]) + mul(mat[1, 2], v[2]),
                      mul(mat[2, 0], v[0]) + mul(mat[2, 1], v[1]) + mul(mat[2, 2], v[2])])


def matT_vec(mat, v):
    """mat^T @ v as C's mulMatTVec3."""
    return jnp.stack([mul(mat[0, 0], v[0]) + mul(mat[1, 0], v[1]) + mul(mat[2, 0], v[2]),
                      mul(mat[0, 1], v[0]) + mul(mat[1, 1], v[1]) + mul(mat[2, 1], v[2]),
                      mul(mat[0, 2], v[0]) + mul(mat[1, 2], v[1]) + mul(mat[2, 2], v[2])])


def local_to_global(mat, v, pos):
    """The point mat @ v + pos as C's localToGlobal / globalcoord."""
    return mat_vec(mat, v) + pos


def where3(c, a, b):
    """Selects (3,) rows a where c, else b."""
    return jnp.where(jnp.asarray(c)[..., None], a, b)


def tree_where(c, a, b):
    """Selects pytree a where c (a scalar bool) else b."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(c, x, y), a, b)


# --------------------------------------------------------------------------------- geoms


@dataclasses.dataclass(frozen=True, eq=False)
class MeshData:
    """A mesh's static data as `mjc_initCCDObj` and `mjc_multicontact` read it.

    Attributes:
      vert: (nv, 3) vertices (float32 values as float64).
      polynormal: (np, 3) polygon normals.
      polyvert: (np, P) local vertex ids of each polygon, padded with 0.
      polyvertnum: (np,) vertices per polygon.
      vertpoly: (nv, D) polygons at each vertex (mesh_polymap), padded with 0.
      vertpolynum: (nv,) polygons per vertex.
    """

    vert: np.ndarray
    polynormal: np.ndarray
    polyvert: np.ndarray
    polyvertnum: np.ndarray
    vertpoly: np.ndarray
    vertpolynum: np.ndarray

    @property
    def polynum(self) -> int:
        """Number of polygons."""
        return int(len(self.polyvertnum))


@dataclasses.dataclass(frozen=True)
class Kind:
    """Static description of a CCD object: geom type, support mode and mesh data.

    `mode` is 'full', or 'point'/'line' while a sphere/capsule is shrunk
    (`mjc_pointSupport`, `mjc_lineSupport`).
    """

    gtype: int
    mesh: MeshData | None = None
    mode: str = "full"

    def shrunk(self) -> Kind:
        """The kind mjc_ccd shrinks this one to (spheres to points, capsules to segments)."""
        mode = {SPHERE: "point", CAPSULE: "line"}.get(self.gtype, "full")
        return dataclasses.replace(self, mode=mode)

    @property
    def discrete(self) -> bool:
        """The test of discreteGeoms for one geom with zero margin (3.17: point/segment too)."""
        return self.mode in ("point", "line") or self.gtype in (HFIELD, BOX, MESH)


class Obj(NamedTuple):
    """Dynamic part of a CCD object (mjCCDObj): pose, size and margin."""

    pos: jax.Array  # (3,)
    mat: jax.Array  # (3, 3)
    size: jax.Array  # (3,)
    margin: jax.Array  # ()


def support_raw(kind: Kind, o: Obj, d: jax.Array, vi: jax.Array, shrink=None):
    """obj->support: the support point of a geom (no margin) and its vertex index.

    Ports mjc_sphereSupport, mjc_capsuleSupport, mjc_ellipsoidSupport,
    mjc_cylinderSupport, mjc_boxSupport, mjc_meshSupport (engine_collision_convex.c),
    mjc_pointSupport and mjc_lineSupport.

    Args:
      kind: static geom description.
      o: pose and size.
      d: (3,) direction (unit except in degenerate calls).
      vi: () int, the object's vertindex (mesh warm start).
      shrink: optional () bool: a sphere/capsule is shrunk to its point/segment.

    Returns:
      ((3,) point, () int vertindex after the call).
    """
    if shrink is not None and kind.gtype in (SPHERE, CAPSULE) and kind.mode == "full":
        p_full, _ = support_raw(kind, o, d, vi)
        p_small, _ = support_raw(kind.shrunk(), o, d, vi)
        return where3(shrink, p_small, p_full), vi
    mat, pos, size = o.mat, o.pos, o.size
    if kind.mode == "point":
        return pos, vi
    if kind.mode == "line":
        dot = mul(mat[0, 2], d[0]) + mul(mat[1, 2], d[1]) + mul(mat[2, 2], d[2])
        scl = jnp.where(dot >= 0, size[1], -size[1])
        return jnp.stack([mul(mat[0, 2], scl) + pos[0], mul(mat[1, 2], scl) + pos[1],
                          mul(mat[2, 2], scl) + pos[2]]), vi
    t = kind.gtype
    if t == SPHERE:
        return mul(size[0], d) + pos, vi
    ld = matT_vec(mat, d)
    if t == CAPSULE:
        ls = mul(ld, size[0])
        ls = ls.at[2].add(jnp.where(ld[2] >= 0, size[1], -size[1]))
        return local_to_global(mat, ls, pos), vi
    if t == ELLIPSOID:
        ls = ld * size
        n2 = dot3(ls, ls)
        small = n2 < MINVAL2
        inv = 1.0 / safe_sqrt(jnp.where(small, 1.0, n2))
        ls = ls * (inv * size)
        res = local_to_global(mat, ls, pos)
        alt = jnp.stack([mul(mat[0, 0], size[0]) + pos[0], mul(mat[1, 0], size[0]) + pos[1],
                         mul(mat[2, 0], size[0]) + pos[2]])
        return jnp.where(small, alt, res), vi
    if t == CYLINDER:
        n2 = mul(ld[0], ld[0]) + mul(ld[1], ld[1])
        ok = n2 >= MINVAL2
        scl = jnp.where(ok, size[0] / safe_sqrt(jnp.where(ok, n2, 1.0)), 0.0)
        ls = jnp.stack([scl * ld[0], scl * ld[1], jnp.where(ld[2] >= 0, size[1], -size[1])])
        return local_to_global(mat, ls, pos), jnp.where(ld[2] < 0, 1, 0).astype(vi.dtype)
    if t == BOX:
        ls = jnp.where(ld >= 0, size, -size)
        idx = ((ls[0] > 0).astype(vi.dtype) | (2 * (ls[1] > 0)).astype(vi.dtype)
               | (4 * (ls[2] > 0)).astype(vi.dtype))
        return local_to_global(mat, ls, pos), idx
    if t == MESH:
        verts = jnp.asarray(kind.mesh.vert, d.dtype)
        ld = lax.stop_gradient(ld)
        vd = mul(ld[0], verts[:, 0]) + mul(ld[1], verts[:, 1]) + mul(ld[2], verts[:, 2])
        warm = vi >= 0
        max0 = jnp.where(warm, vd[jnp.maximum(vi, 0)], -FLT_MAX)
        cand = vd > max0
        vdc = jnp.where(cand, vd, -jnp.inf)
        imax = jnp.where(cand.any(), jnp.argmax(vdc), jnp.where(warm, vi, 0)).astype(vi.dtype)
        return local_to_global(mat, verts[imax], pos), imax
    raise NotImplementedError(f"no support function for geom type {t}")


class Vert(NamedTuple):
    """Vertices of the Minkowski difference (C's Vertex), any leading shape."""

    vert: jax.Array  # (..., 3) v1 - v2
    v1: jax.Array  # (..., 3) point of geom 1
    v2: jax.Array  # (..., 3) point of geom 2
    i1: jax.Array  # (...,) vertex index in geom 1
    i2: jax.Array  # (...,) vertex index in geom 2


def support(k1: Kind, k2: Kind, o1: Obj, o2: Obj, d, dneg, vi1, vi2, shrink=None):
    """C's support (gjk.c): S_{A-B}(d) with each geom grown by half its margin.

    Returns:
      (Vert of one vertex, vi1, vi2).
    """
    p1, vi1 = support_raw(k1, o1, d, vi1, shrink)
    p1 = jnp.where(o1.margin > 0, p1 + mul(d, 0.5 * o1.margin), p1)
    p2, vi2 = support_raw(k2, o2, dneg, vi2, shrink)
    p2 = jnp.where(o2.margin > 0, p2 + mul(dneg, 0.5 * o2.margin), p2)
    return Vert(p1 - p2, p1, p2, vi1, vi2), vi1, vi2


def pick3(v, idx):
    """v[..., idx] for idx in {0, 1, 2} by selects (cheaper than a gather under vmap)."""
    return jnp.where(idx == 0, v[..., 0], jnp.where(idx == 1, v[..., 1], v[..., 2]))


def _small_take(x, idx):
    """x[idx] on a small leading axis by selects; idx: int array of any shape."""
    out = jnp.zeros(idx.shape + x.shape[1:], x.dtype)
    for j in range(x.shape[0]):
        out = jnp.where(jnp.reshape(idx == j, idx.shape + (1,) * (x.ndim - 1)), x[j], out)
    return out


def vert_take(v: Vert, idx) -> Vert:
    """v[idx] for a small (4-row) Vert."""
    return jax.tree_util.tree_map(lambda x: _small_take(x, idx), v)


def vert_put(v: Vert, i, w: Vert) -> Vert:
    """The vertices v with row i (dynamic) replaced by w, for a small Vert."""
    def put(x, y):
        rows = jnp.arange(x.shape[0]) == i
        return jnp.where(jnp.reshape(rows, (-1,) + (1,) * (x.ndim - 1)), y, x)
    return jax.tree_util.tree_map(put, v, w)


def vert_at(v: Vert, i) -> Vert:
    """Row(s) i of v."""
    return jax.tree_util.tree_map(lambda x: x[i], v)


def vert_set(v: Vert, i, w: Vert) -> Vert:
    """The vertices v with row i set to w (dropped when out of range)."""
    return jax.tree_util.tree_map(lambda x, y: x.at[i].set(y, mode="drop"), v, w)


# ----------------------------------------------------------------------- GJK subdistance


def project_origin_plane(v1, v2, v3):
    """projectOriginPlane: (ret, projection of the origin on the plane of v1 v2 v3)."""
    d21, d31, d32 = v2 - v1, v3 - v1, v3 - v2
    outs = []
    for n, vv in ((cross3(d32, d21), v2), (cross3(d21, d31), v1), (cross3(d31, d32), v3)):
        nv, nn = dot3(n, vv), dot3(n, n)
        outs.append((n * safe_div(nv, nn)[..., None], nv, nn))
    (r1, nv1, nn1), (r2, nv2, nn2), (r3, _, _) = outs
    ok1 = (nv1 != 0) & (nn1 > MINVAL)
    ok2 = (nv2 != 0) & (nn2 > MINVAL)
    ret = (nn1 == 0) | (~ok1 & (nn2 == 0))
    res = where3(ok1, r1, where3(ok2, r2, r3))
    return ret, res


def same_sign(a, b):
    """sameSign2(a, b) != 0."""
    return ((a > 0) & (b > 0)) | ((a < 0) & (b < 0))


def s1d(s1, s2):
    """S1D: barycentric coordinates of the point of segment s1 s2 nearest the origin."""
    diff = s2 - s1
    scl = -safe_div(dot3(s2, diff), dot3(diff, diff))
    p = s2 + mul(scl[..., None], diff)
    mu = s1 - s2
    a0, a1, a2 = jnp.abs(mu[..., 0]), jnp.abs(mu[..., 1]), jnp.abs(mu[..., 2])
    i1 = a1 >= a0
    m01 = jnp.where(i1, a1, a0)
    i2 = a2 >= m01
    idx = jnp.where(i2, 2, jnp.where(i1, 1, 0))
    mu_max = pick3(mu, idx)
    pi = pick3(p, idx)
    s1i = pick3(s1, idx)
    s2i = pick3(s2, idx)
    c1, c2 = pi - s2i, s1i - pi
    same = same_sign(mu_max, c1) & same_sign(mu_max, c2)
    return jnp.stack([jnp.where(same, safe_div(c1, mu_max), 0.0),
                      jnp.where(same, safe_div(c2, mu_max), 1.0)], axis=-1)


def _minors(s1, s2, s3):
    def m(a, b, i, j):
        return mul(a[..., i], b[..., j])
    m14 = (m(s2, s3, 1, 2) - m(s2, s3, 2, 1) - m(s1, s3, 1, 2) + m(s1, s3, 2, 1) + m(s1, s2, 1, 2)
           - m(s1, s2, 2, 1))
    m24 = (m(s2, s3, 0, 2) - m(s2, s3, 2, 0) - m(s1, s3, 0, 2) + m(s1, s3, 2, 0) + m(s1, s2, 0, 2)
           - m(s1, s2, 2, 0))
    m34 = (m(s2, s3, 0, 1) - m(s2, s3, 1, 0) - m(s1, s3, 0, 1) + m(s1, s3, 1, 0) + m(s1, s2, 0, 1)
           - m(s1, s2, 1, 0))
    mu1, mu2, mu3 = jnp.abs(m14), jnp.abs(m24), jnp.abs(m34)
    c1 = (mu1 >= mu2) & (mu1 >= mu3)
    c2 = ~c1 & (mu2 >= mu3)
    m_max = jnp.where(c1, m14, jnp.where(c2, m24, m34))
    x = jnp.where(c1, 1, 0)
    y = jnp.where(c1 | c2, 2, 1)
    return m_max, x, y


def _cofactors(s1, s2, s3, p, x, y):
    g = pick3
    ax, ay, bx, by, cx, cy, px, py = (g(s1, x), g(s1, y), g(s2, x), g(s2, y), g(s3, x),
                                      g(s3, y), g(p, x), g(p, y))
    c31 = mul(px, by) + mul(py, cx) + mul(bx, cy) - mul(px, cy) - mul(py, bx) - mul(cx, by)
    c32 = mul(px, cy) + mul(py, ax) + mul(cx, ay) - mul(px, ay) - mul(py, cx) - mul(ax, cy)
    c33 = mul(px, ay) + mul(py, bx) + mul(ax, by) - mul(px, by) - mul(py, ax) - mul(bx, ay)
    return c31, c32, c33


def _lincomb2(lam, a, b):
    return mul(lam[..., 0:1], a) + mul(lam[..., 1:2], b)


def _s2d(s1, s2, s3):
    """S2D, also returning its S1D(s1, s2) (the 1-simplex case of GJK's subdistance)."""
    ret, p_o = project_origin_plane(s1, s2, s3)
    m_max, x, y = _minors(s1, s2, s3)
    c31, c32, c33 = _cofactors(s1, s2, s3, p_o, x, y)
    k1, k2, k3 = same_sign(m_max, c31), same_sign(m_max, c32), same_sign(m_max, c33)
    inside = k1 & k2 & k3
    lin = jnp.stack([safe_div(c31, m_max), safe_div(c32, m_max), safe_div(c33, m_max)], -1)
    la, lb, lc = s1d(s2, s3), s1d(s1, s3), s1d(s1, s2)
    da, db, dc = (dot3(_lincomb2(la, s2, s3), _lincomb2(la, s2, s3)),
                  dot3(_lincomb2(lb, s1, s3), _lincomb2(lb, s1, s3)),
                  dot3(_lincomb2(lc, s1, s2), _lincomb2(lc, s1, s2)))
    z = jnp.zeros_like(da)
    lam = jnp.zeros(da.shape + (3,), s1.dtype)
    dmin = jnp.full(da.shape, MAX_LIMIT, s1.dtype)
    # !comp1 assigns unconditionally; the others only if nearer
    lam = where3(~k1, jnp.stack([z, la[..., 0], la[..., 1]], -1), lam)
    dmin = jnp.where(~k1, da, dmin)
    t = ~k2 & (db < dmin)
    lam = where3(t, jnp.stack([lb[..., 0], z, lb[..., 1]], -1), lam)
    dmin = jnp.where(t, db, dmin)
    t = ~k3 & (dc < dmin)
    lam = where3(t, jnp.stack([lc[..., 0], lc[..., 1], z], -1), lam)
    lam = where3(inside, lin, lam)
    # projectOriginPlane failed: S1D(s1, s2), which is lc
    return where3(ret, jnp.stack([lc[..., 0], lc[..., 1], z], -1), lam), lc


def s2d(s1, s2, s3):
    """S2D: barycentric coordinates of the point of triangle s1 s2 s3 nearest the origin."""
    return _s2d(s1, s2, s3)[0]


def _s3d(s1, s2, s3, s4):
    """S3D, also returning S2D(s1, s2, s3) and S1D(s1, s2) computed on the way."""
    c41, c42, c43, c44 = -det3(s2, s3, s4), det3(s1, s3, s4), -det3(s1, s2, s4), det3(s1, s2, s3)
    m_det = c41 + c42 + c43 + c44
    k = [same_sign(m_det, c) for c in (c41, c42, c43, c44)]
    inside = k[0] & k[1] & k[2] & k[3]
    lin = jnp.stack([safe_div(c, m_det) for c in (c41, c42, c43, c44)], -1)
    faces = (s2, s3, s4), (s1, s3, s4), (s1, s2, s4), (s1, s2, s3)
    # the four faces at once (a leading axis)
    fa = jnp.stack([f[0] for f in faces])
    fb = jnp.stack([f[1] for f in faces])
    fc = jnp.stack([f[2] for f in faces])
    lm, l1 = _s2d(fa, fb, fc)
    xx = mul(lm[..., 0:1], fa) + mul(lm[..., 1:2], fb) + mul(lm[..., 2:3], fc)
    ds = dot3(xx, xx)
    z = jnp.zeros_like(m_det)
    full = [jnp.stack([z, lm[0, ..., 0], lm[0, ..., 1], lm[0, ..., 2]], -1),
            jnp.stack([lm[1, ..., 0], z, lm[1, ..., 1], lm[1, ..., 2]], -1),
            jnp.stack([lm[2, ..., 0], lm[2, ..., 1], z, lm[2, ..., 2]], -1),
            jnp.stack([lm[3, ..., 0], lm[3, ..., 1], lm[3, ..., 2], z], -1)]
    lam = jnp.zeros(m_det.shape + (4,), s1.dtype)
    lam = where3(~k[0], full[0], lam)
    dmin = jnp.where(~k[0], ds[0], MAX_LIMIT)
    for j in (1, 2, 3):
        t = ~k[j] & (ds[j] < dmin)
        lam = where3(t, full[j], lam)
        dmin = jnp.where(t, ds[j], dmin)
    return where3(inside, lin, lam), lm[3], l1[3]


def s3d(s1, s2, s3, s4):
    """S3D: barycentric coordinates of the point of tetrahedron s1..s4 nearest the origin."""
    return _s3d(s1, s2, s3, s4)[0]


def subdistance(n, simplex):
    """C's subdistance for n = 1..4 (n traced): (4,) coordinates.

    N.B. S3D's last face is the 2-simplex case and that face's S1D(s1, s2) the
    1-simplex case, so one S3D evaluation serves all n.
    """
    s = simplex
    l4, l3, l2 = _s3d(s[0], s[1], s[2], s[3])
    z = jnp.zeros((), s.dtype)
    l3 = jnp.concatenate([l3, z[None]])
    l2 = jnp.concatenate([l2, jnp.zeros(2, s.dtype)])
    l1 = jnp.array([1.0, 0.0, 0.0, 0.0], s.dtype)
    return jnp.where(n == 4, l4, jnp.where(n == 3, l3, jnp.where(n == 2, l2, l1)))


def lincomb4(lam, n, v):
    """lincomb(res, coef, n, v...) for (4, 3) v with coefficients beyond n unused."""
    p = [mul(lam[i], v[i]) for i in range(4)]
    r1 = lam[0] * v[0]
    r2 = p[0] + p[1]
    r3 = p[0] + p[1] + p[2]
    r4 = p[0] + p[1] + p[2] + p[3]
    return jnp.where(n == 4, r4, jnp.where(n == 3, r3, jnp.where(n == 2, r2, jnp.where(
        n == 1, r1, jnp.zeros(3, v.dtype)))))


# ----------------------------------------------------------------------------------- GJK


class GJKResult(NamedTuple):
    """What gjk() leaves in mjCCDStatus and in the two objects."""

    separated: jax.Array  # () bool
    dist: jax.Array  # () status->dist[0]
    x1: jax.Array  # (3,) witness on geom 1
    x2: jax.Array  # (3,) witness on geom 2
    nsimplex: jax.Array  # () int (also obj->nsimplex of both objects)
    simplex: Vert  # (4,) the simplex (first nsimplex valid)
    vi1: jax.Array  # () int vertindex of geom 1
    vi2: jax.Array  # () int vertindex of geom 2


def _signed_distance(a, b, c):
    """signedDistance(normal, v1, v2, v3) on vertex positions: (dist, normal)."""
    n = cross3(c - a, b - a)
    n2 = dot3(n, n)
    ok = (n2 > MINVAL2) & (n2 < MAXVAL2)
    nn = n * (1.0 / safe_sqrt(jnp.where(ok, n2, 1.0)))[..., None]
    return jnp.where(ok, dot3(nn, a), MAX_LIMIT), where3(ok, nn, n)


def _discrete(k: Kind, o: Obj, shrink):
    """The test of discreteGeoms for one object (3.17: shrunk spheres and capsules count)."""
    d = jnp.asarray(k.gtype in (HFIELD, BOX, MESH))
    if k.gtype in (SPHERE, CAPSULE):
        d = jnp.asarray(shrink)
    return d & (o.margin == 0)


def gjk(k1: Kind, k2: Kind, o1: Obj, o2: Obj, x1, x2, vi1, vi2, *, shrink, get_dist,
        dist_cutoff, tolerance=CCD_TOLERANCE, kmax=CCD_ITERATIONS) -> GJKResult:
    """The gjk function (with gjkIntersect) of engine_collision_gjk.c, as the 3.17 binary runs it.

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source.

    Args:
      k1: static description of geom 1.
      k2: static description of geom 2.
      o1: pose, size and margin of geom 1 (margin already zeroed where mjc_ccd zeroes it).
      o2: the same of geom 2.
      x1: (3,) initial witness point on geom 1 (its center).
      x2: (3,) the same on geom 2.
      vi1: () int vertindex of object 1.
      vi2: () int vertindex of object 2.
      shrink: () bool, spheres/capsules shrunk to their point/segment.
      get_dist: () bool, status->dist_cutoff > 0 (geom distances wanted).
      dist_cutoff: () the cutoff (used when get_dist).
      tolerance: ccd_tolerance.
      kmax: ccd_iterations (static).

    Returns:
      `GJKResult`.
    """
    dtype = x1.dtype
    disc = _discrete(k1, o1, shrink) & _discrete(k2, o2, shrink)
    tol2 = tolerance * tolerance
    epsilon = jnp.where(disc, 0.0, 0.5 * tol2)
    min_norm = jnp.where(disc, MINVAL, tolerance)
    zero4 = Vert(jnp.zeros((4, 3), dtype), jnp.zeros((4, 3), dtype), jnp.zeros((4, 3), dtype),
                 jnp.zeros(4, vi1.dtype), jnp.zeros(4, vi1.dtype))
    x_k = x1 - x2
    x_norm = safe_sqrt(dot3(x_k, x_k))
    # mode: 0 gjk iteration, 1 gjkIntersect iteration, 2 rest of the gjk iteration after
    # an inconclusive gjkIntersect, 3 loop left (normal exit), 4 returned early
    state = dict(mode=jnp.array(0), k=jnp.array(0), n=jnp.array(0), simplex=zero4,
                 lam=jnp.zeros(4, dtype), x_k=x_k, x_norm=x_norm, x_norm_prev=jnp.zeros((), dtype),
                 backup=~jnp.asarray(get_dist), isimp=zero4, s=jnp.arange(4),
                 separated=jnp.array(False), dist=jnp.zeros((), dtype), nsimplex=jnp.array(0),
                 vi1=vi1, vi2=vi2)

    def step(_, st):
        """One pass of C's loop, its three modes in C's order (long: see `gjk`)."""
        mode, k, n = st["mode"], st["k"], st["n"]
        m0, m1, m2 = mode == 0, mode == 1, mode == 2
        # ---- mode 0: head of a gjk iteration
        x_k, x_norm = st["x_k"], st["x_norm"]
        stop0 = (k >= kmax) | (x_norm < min_norm) | (jnp.abs(st["x_norm_prev"] - x_norm) < MINVAL)
        inv = jnp.where(x_norm > 0, 1.0 / jnp.where(x_norm > 0, x_norm, 1.0), 0.0)
        dneg = x_k * inv
        d = dneg * -1.0
        # ---- mode 1: gjkIntersect iteration on its local simplex
        isimp, s = st["isimp"], st["s"]
        pv = _small_take(isimp.vert, s)
        dist_i, nrm_i = [], []
        for a, b, c in ((2, 1, 3), (0, 2, 3), (1, 0, 3), (0, 1, 2)):
            dd, nn = _signed_distance(pv[a], pv[b], pv[c])
            dist_i.append(dd)
            nrm_i.append(nn)
        dists = jnp.stack(dist_i)
        nrms = jnp.stack(nrm_i)
        dsg = lax.stop_gradient(dists)
        i = jnp.where(dsg[0] < dsg[1], 0, 1)
        j = jnp.where(dsg[2] < dsg[3], 2, 3)
        index = jnp.where(_small_take(dsg, i) < _small_take(dsg, j), i, j)
        on_hull = (dsg == 0).any()
        inside = _small_take(dsg, index) > 0
        nrm = _small_take(nrms, index)
        # one support call per step: gjk direction or intersect normal
        dir1 = where3(m1, nrm, d)
        dir2 = where3(m1, -nrm, dneg)
        w, vi1n, vi2n = support(k1, k2, o1, o2, dir1, dir2, st["vi1"], st["vi2"], shrink)
        # ---- mode 0 continued
        simplex0 = vert_put(st["simplex"], n, w)
        s_k = w.vert
        gap = lax.stop_gradient(dot3(x_k, x_k - s_k)) < epsilon
        lower = lax.stop_gradient(dot3(x_k, s_k))
        sep0 = jnp.where(get_dist, (lower > 0) & (lower >= dist_cutoff * x_norm), lower > 0)
        to_int = (n == 3) & st["backup"]
        # ---- mode 1 continued
        isimp_new = vert_put(isimp, _small_take(s, index), w)
        out1 = dot3(nrm, lax.stop_gradient(w.vert)) < 0
        ii, jj = (index + 1) & 3, (index + 2) & 3
        r4 = jnp.arange(4)
        s_sw = jnp.where(r4 == ii, _small_take(s, jj), jnp.where(r4 == jj, _small_take(s, ii), s))
        k1n = k + 1
        # ---- end of a gjk iteration (mode 0 without break, or mode 2): subdistance,
        # simplex reduction and the next x_k
        simplex_in = tree_where(m2, st["simplex"], simplex0)
        lam = subdistance(n + 1, simplex_in.vert)
        keep = lam != 0
        # compaction of the kept vertices (C's loop), by selects
        rank = jnp.cumsum(keep) - 1
        order = jnp.stack([jnp.argmax(keep & (rank == t)) for t in range(4)])
        simplex_p = vert_take(simplex_in, order)
        lam = _small_take(lam, order)
        n_p = keep.sum()
        x_k_p = lincomb4(lam, n_p, simplex_p.vert)
        x_norm_p = safe_sqrt(dot3(x_k_p, x_k_p))
        brk = n_p == 4
        bad = n_p < 1  # SHOULD NOT OCCUR in C: returns "separated"
        post_mode = jnp.where(bad, 4, jnp.where(brk, 3, 0))
        post_k = jnp.where(brk, k, k + 1)

        head_stop = m0 & stop0
        gap_stop = m0 & ~stop0 & gap
        sep_stop = m0 & ~stop0 & ~gap & sep0
        go_int = m0 & ~stop0 & ~gap & ~sep0 & to_int
        go_post = (m0 & ~stop0 & ~gap & ~sep0 & ~to_int) | m2
        int_hull = m1 & on_hull
        int_in = m1 & ~on_hull & inside
        int_out = m1 & ~on_hull & ~inside & out1
        int_next = m1 & ~on_hull & ~inside & ~out1
        int_exhaust = int_next & (k1n >= kmax)

        new = dict(st)
        simplex = tree_where(m0 & ~stop0, simplex0, st["simplex"])
        simplex = tree_where(go_post, simplex_p, simplex)
        new["simplex"] = tree_where(int_in, vert_take(isimp, s), simplex)
        new["lam"] = jnp.where(go_post, lam, st["lam"])
        new["n"] = jnp.where(go_post, n_p, n)
        new["x_k"] = where3(go_post, x_k_p, x_k)
        new["x_norm"] = jnp.where(go_post, x_norm_p, x_norm)
        new["x_norm_prev"] = jnp.where(go_post, x_norm, st["x_norm_prev"])
        kk = jnp.where(go_post, post_k, k)
        kk = jnp.where(int_next & ~int_exhaust, k1n, kk)
        new["k"] = jnp.where(int_exhaust, kmax, kk)
        md = mode
        md = jnp.where(head_stop | gap_stop, 3, md)
        md = jnp.where(sep_stop | int_in | int_out, 4, md)
        md = jnp.where(go_int, 1, md)
        md = jnp.where(go_post, post_mode, md)
        new["mode"] = jnp.where(int_hull | int_exhaust, 2, md)
        new["isimp"] = tree_where(go_int, simplex0, tree_where(int_next, isimp_new, isimp))
        new["s"] = jnp.where(go_int, jnp.arange(4), jnp.where(int_next, s_sw, s))
        new["backup"] = jnp.where(m2, False, st["backup"])
        called = (m0 & ~stop0) | (m1 & ~on_hull & ~inside)
        new["vi1"] = jnp.where(called, vi1n, st["vi1"])
        new["vi2"] = jnp.where(called, vi2n, st["vi2"])
        sep_any = sep_stop | int_out | (go_post & bad)
        new["separated"] = jnp.where(sep_any, True, jnp.where(int_in, False, st["separated"]))
        new["dist"] = jnp.where(sep_any, MAX_LIMIT, jnp.where(int_in, 0.0, st["dist"]))
        new["nsimplex"] = jnp.where(sep_any, 0, jnp.where(int_in, 4, st["nsimplex"]))
        return new

    st = _loop(kmax + 4, step, state, lambda st: st["mode"] >= 3)
    n = st["n"]
    returned = st["mode"] == 4
    simplex = st["simplex"]
    lam = st["lam"]
    wx1 = where3(n > 0, lincomb4(lam, n, simplex.v1), x1)
    wx2 = where3(n > 0, lincomb4(lam, n, simplex.v2), x2)
    # final separation check (one more support call)
    x_k, x_norm = st["x_k"], st["x_norm"]
    inv = jnp.where(x_norm > 0, 1.0 / jnp.where(x_norm > 0, x_norm, 1.0), 0.0)
    dneg = x_k * inv
    w, vi1n, vi2n = support(k1, k2, o1, o2, dneg * -1.0, dneg, st["vi1"], st["vi2"], shrink)
    sep = lax.stop_gradient(dot3(x_k, w.vert)) > 0
    dist = jnp.where((n == 4) & ~sep, 0.0, x_norm)
    return GJKResult(
        separated=jnp.where(returned, st["separated"], sep),
        dist=jnp.where(returned, st["dist"], dist),
        x1=where3(returned, x1, wx1), x2=where3(returned, x2, wx2),
        nsimplex=jnp.where(returned, st["nsimplex"], n),
        simplex=simplex,
        vi1=jnp.where(returned, st["vi1"], vi1n), vi2=jnp.where(returned, st["vi2"], vi2n))


# ----------------------------------------------------------------------------------- EPA


class Polytope(NamedTuple):
    """C's Polytope in fixed-size arrays (5 + N vertices, 6 N faces)."""

    verts: Vert  # (NV,)
    nverts: jax.Array
    fverts: jax.Array  # (NF, 3) int
    fadj: jax.Array  # (NF, 3) int
    fv: jax.Array  # (NF, 3) projection of the origin on the face
    fd2: jax.Array  # (NF,) its squared norm
    fidx: jax.Array  # (NF,) int position in the map; -1 not in it, -2 deleted
    nfaces: jax.Array
    fmap: jax.Array  # (NF,) int face ids
    nmap: jax.Array
    center: jax.Array  # (3,)


def _empty_polytope(kmax, dtype, itype) -> Polytope:
    # N.B. NHORIZON spare faces: new faces are written as one block of NHORIZON rows
    nv, nf = 5 + kmax, 6 * kmax + NHORIZON
    z = jnp.zeros((nv, 3), dtype)
    return Polytope(Vert(z, z, z, jnp.zeros(nv, itype), jnp.zeros(nv, itype)), jnp.array(0),
                    jnp.zeros((nf, 3), jnp.int32), jnp.zeros((nf, 3), jnp.int32),
                    jnp.zeros((nf, 3), dtype), jnp.zeros(nf, dtype),
                    jnp.full(nf, -1, jnp.int32), jnp.array(0), jnp.zeros(nf, jnp.int32),
                    jnp.array(0), jnp.zeros(3, dtype))


def _face_plane(P: Polytope, a, b, c):
    """The geometry of attachFace for face (a, b, c).

    Returns (ret, v, dist2), ret: the origin's projection failed.
    """
    va, vb, vc = P.verts.vert[a], P.verts.vert[b], P.verts.vert[c]
    ret, v = project_origin_plane(vc, vb, va)
    outward = va - P.center
    v = where3(dot3(v, outward) < 0, -v, v)
    return ret, v, dot3(v, v)


def _small_faces(vv, center, table):
    """The attachFace of C for a start polytope: faces `table` (F, 3) on vertices vv (n, 3).

    Returns (v (F, 3), dist2 (F,), attachFace's return value (F,)).
    """
    table = np.asarray(table)
    a, b, c = vv[table[:, 0]], vv[table[:, 1]], vv[table[:, 2]]
    ret, v = project_origin_plane(c, b, a)
    v = where3(dot3(v, a - center) < 0, -v, v)
    d2 = dot3(v, v)
    return v, d2, jnp.where(ret, 0.0, d2)


def _epa_support(k1, k2, o1, o2, d, dnorm, vi1, vi2):
    """The direction of epaSupport: d / dnorm, (1, 0, 0) when dnorm <= mjMINVAL."""
    ok = dnorm > MINVAL
    dd = div3(d, jnp.where(ok, dnorm, 1.0))
    dirn = where3(ok, dd, jnp.array([1.0, 0.0, 0.0], d.dtype))
    dneg = where3(ok, dd * -1.0, jnp.array([-1.0, 0.0, 0.0], d.dtype))
    return support(k1, k2, o1, o2, dirn, dneg, vi1, vi2)


def _same_side(p0, p1, p2, p3):
    n = cross3(p1 - p0, p2 - p0)
    dot1 = dot3(n, p3 - p0)
    dot2 = dot3(n, p0 * -1.0)
    return ((dot1 > 0) & (dot2 > 0)) | ((dot1 < 0) & (dot2 < 0))


def _test_tetra(p0, p1, p2, p3):
    return (_same_side(p0, p1, p2, p3) & _same_side(p1, p2, p3, p0) & _same_side(p2, p3, p0, p1)
            & _same_side(p3, p0, p1, p2))


def tri_affine_coord(v1, v2, v3, p):
    """triAffineCoord: affine coordinates of p on the triangle v1 v2 v3."""
    m_max, x, y = _minors(v1, v2, v3)
    c31, c32, c33 = _cofactors(v1, v2, v3, p, x, y)
    return jnp.stack([safe_div(c31, m_max), safe_div(c32, m_max), safe_div(c33, m_max)], -1)


def _tri_point_intersect(v1, v2, v3, p):
    lam = tri_affine_coord(v1, v2, v3, p)
    neg = (lam[0] < 0) | (lam[1] < 0) | (lam[2] < 0)
    pr = (mul(v1, lam[0]) + mul(v2, lam[1])) + mul(v3, lam[2])
    diff = pr - p
    return ~neg & (safe_sqrt(dot3(diff, diff)) < MINVAL)


def _rotmat(axis):
    n = safe_sqrt(dot3(axis, axis))
    u = div3(axis, jnp.where(n == 0, 1.0, n))
    u1, u2, u3 = u[0], u[1], u[2]
    sin, cos = 0.86602540378, -0.5
    r = [cos + mul(mul(u1, u1), 1 - cos), mul(mul(u1, u2), 1 - cos) - mul(u3, sin),
         mul(mul(u1, u3), 1 - cos) + mul(u2, sin), mul(mul(u2, u1), 1 - cos) + mul(u3, sin),
         cos + mul(mul(u2, u2), 1 - cos), mul(mul(u2, u3), 1 - cos) - mul(u1, sin),
         mul(mul(u1, u3), 1 - cos) - mul(u2, sin), mul(mul(u2, u3), 1 - cos) + mul(u1, sin),
         cos + mul(mul(u3, u3), 1 - cos)]
    return jnp.stack(r).reshape(3, 3)


def _ray_triangle(v1, v2, v3, v4, v5):
    d12, d13, d14, d15 = v2 - v1, v3 - v1, v4 - v1, v5 - v1
    vol1, vol2, vol3 = det3(d13, d14, d12), det3(d14, d15, d12), det3(d15, d13, d12)
    pos = (vol1 >= 0) & (vol2 >= 0) & (vol3 >= 0)
    neg = (vol1 <= 0) & (vol2 <= 0) & (vol3 <= 0)
    return pos | neg


_FACES2 = ((0, 2, 3), (0, 4, 2), (0, 3, 4), (1, 3, 2), (1, 2, 4), (1, 4, 3))
_FACES3 = ((4, 0, 1), (4, 2, 0), (4, 1, 2), (3, 1, 0), (3, 0, 2), (3, 2, 1))
_FACES4 = ((0, 1, 2), (0, 3, 1), (0, 2, 3), (3, 2, 1))
_ADJ6 = ((1, 3, 2), (2, 4, 0), (0, 5, 1), (5, 0, 4), (3, 1, 5), (4, 2, 3))
_ADJ4 = ((1, 3, 2), (2, 3, 0), (0, 3, 1), (2, 0, 1))


def start_polytope(k1, k2, o1, o2, simplex: Vert, nsimplex, vi1, vi2, kmax):
    """polytope2/3/4 (and replaceSimplex3) as mjc_ccd picks them by the GJK simplex size.

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source.

    The start polytopes are built in small arrays and the chosen one is written
    into the fixed-size polytope once.

    Returns (P, ret, vi1, vi2); ret 0 on success.
    """
    dtype, itype = simplex.vert.dtype, simplex.i1.dtype
    # ---- polytope2: three supports 120 degrees apart around the segment, six faces
    v1, v2 = simplex.vert[0], simplex.vert[1]
    diff = v2 - v1
    ad = jnp.abs(diff)
    index = jnp.array(0)
    value = jnp.asarray(MAX_LIMIT, dtype)
    for i in range(3):
        t = ad[i] < value
        index = jnp.where(t, i, index)
        value = jnp.where(t, ad[i], value)
    e = (jnp.arange(3) == index).astype(dtype)
    d1 = cross3(e, diff)
    R = _rotmat(diff)
    d2 = mat_vec(R, d1)
    d3 = mat_vec(R, d2)
    ws = []
    a1, a2 = vi1, vi2
    for dd in (d1, d2, d3):
        w, a1, a2 = _epa_support(k1, k2, o1, o2, dd, safe_sqrt(dot3(dd, dd)), a1, a2)
        ws.append(w)
    V2 = jax.tree_util.tree_map(lambda s, *w: jnp.concatenate([s[:2], jnp.stack(w)]),
                                simplex, *ws)
    c2 = mul(v1 + v2, 0.5)
    fv2, fd22, at2 = _small_faces(V2.vert, c2, _FACES2)
    bad2 = at2 < MINDIST
    first2 = jnp.argmax(bad2)
    ret2 = jnp.where(_ray_triangle(*[V2.vert[i] for i in range(5)]), 0, 2)
    # ---- polytope4: the tetrahedron
    sv = simplex.vert
    c4 = mul(((sv[0] + sv[1]) + sv[2]) + sv[3], 0.25)
    fv4, fd24, at4 = _small_faces(sv, c4, _FACES4)
    bad4 = at4 < MINDIST
    first4 = jnp.argmax(bad4)
    ret4 = jnp.where(_test_tetra(sv[0], sv[1], sv[2], sv[3]), 0, 9)
    # ---- polytope3, directly or on a face of the 1/3-simplex polytope (replaceSimplex3)
    use2 = (nsimplex == 2) & bad2.any()
    use4 = (nsimplex >= 4) & bad4.any()
    t2 = jnp.asarray(_FACES2)[first2]
    t4 = jnp.asarray(_FACES4)[first4]
    tri = tree_where(use2, vert_at(V2, t2), tree_where(use4, vert_at(simplex, t4),
                                                         vert_at(simplex, jnp.arange(3))))
    b1 = jnp.where(nsimplex == 2, a1, vi1)
    b2 = jnp.where(nsimplex == 2, a2, vi2)
    t1, t2_, t3 = tri.vert[0], tri.vert[1], tri.vert[2]
    c3 = mul((t1 + t2_) + t3, 1.0 / 3.0)
    n = cross3(t2_ - t1, t3 - t1)
    n_norm = safe_sqrt(dot3(n, n))
    w5, c1_, c2_ = _epa_support(k1, k2, o1, o2, n * -1.0, n_norm, b1, b2)
    w4, c1_, c2_ = _epa_support(k1, k2, o1, o2, n, n_norm, c1_, c2_)
    V3 = jax.tree_util.tree_map(lambda t, a, b: jnp.concatenate([t, a[None], b[None]]), tri, w5,
                                w4)
    fv3, fd23, at3 = _small_faces(V3.vert, c3, _FACES3)
    ret3 = jnp.where(n_norm < MINVAL, 4, jnp.where(
        _tri_point_intersect(t1, t2_, t3, w4.vert), 5, jnp.where(
            _tri_point_intersect(t1, t2_, t3, w5.vert), 6, jnp.where((at3 < MINDIST).any(), 8,
                                                                     0))))
    use3 = (nsimplex == 3) | use2 | use4
    is2 = ~use3 & (nsimplex == 2)
    # ---- the chosen start polytope into the fixed-size arrays
    V4 = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[:1]]), simplex)
    V = tree_where(use3, V3, tree_where(is2, V2, V4))
    fv = where3(use3, fv3, where3(is2, fv2, jnp.concatenate([fv4, fv4[:2]])))
    fd2 = jnp.where(use3, fd23, jnp.where(is2, fd22, jnp.concatenate([fd24, fd24[:2]])))
    fverts = jnp.where(use3, jnp.asarray(_FACES3), jnp.where(
        is2, jnp.asarray(_FACES2), jnp.asarray(_FACES4 + _FACES4[:2])))
    fadj = jnp.where(use3 | is2, jnp.asarray(_ADJ6), jnp.asarray(_ADJ4 + _ADJ4[:2]))
    nface = jnp.where(use3 | is2, 6, 4)
    nvert = jnp.where(use3 | is2, 5, 4)
    P = _empty_polytope(kmax, dtype, itype)
    ids = jnp.arange(P.fmap.shape[0])
    P = P._replace(
        verts=jax.tree_util.tree_map(lambda big, x: big.at[:5].set(x), P.verts, V),
        nverts=nvert, fverts=P.fverts.at[:6].set(fverts.astype(jnp.int32)),
        fadj=P.fadj.at[:6].set(fadj.astype(jnp.int32)), fv=P.fv.at[:6].set(fv),
        fd2=P.fd2.at[:6].set(fd2), fidx=jnp.where(ids < nface, ids, -1).astype(jnp.int32),
        nfaces=nface, fmap=jnp.where(ids < nface, ids, 0).astype(jnp.int32), nmap=nface,
        center=where3(use3, c3, where3(is2, c2, c4)))
    ret = jnp.where(use3, ret3, jnp.where(is2, ret2, ret4))
    vo1 = jnp.where(use3, c1_, jnp.where(is2, a1, vi1))
    vo2 = jnp.where(use3, c2_, jnp.where(is2, a2, vi2))
    return P, ret, vo1, vo2


def _delete_face(P: Polytope, g, act):
    """deleteFace(face g) when act: drops it from the map (swap with the last entry)."""
    idx = P.fidx[g]
    inmap = act & (idx >= 0)
    last = P.fmap[jnp.maximum(P.nmap - 1, 0)]
    nf = P.fmap.shape[0]
    fmap = P.fmap.at[jnp.where(inmap, idx, nf)].set(last, mode="drop")
    fidx = P.fidx.at[jnp.where(inmap, last, nf)].set(idx, mode="drop")
    fidx = fidx.at[jnp.where(act, g, nf)].set(-2, mode="drop")
    return P._replace(fmap=fmap, fidx=fidx, nmap=jnp.where(inmap, P.nmap - 1, P.nmap))


def horizon(P: Polytope, face, w, act, nsteps=NDFS, nhorizon=NHORIZON):
    """C's horizon and horizonRec: deletes the faces visible from w, returns the horizon edges.

    C's recursion is a depth-first search from `face`; here an explicit stack
    replays it one edge test per step, so the edges come out in C's order.

    Returns:
      (P, hz_idx (H,), hz_edge (H,), nedges, overflow) where overflow marks a
      search longer than `nsteps` (never seen on the shapes here).
    """
    P = _delete_face(P, face, act)
    fd2 = lax.stop_gradient(P.fd2)
    fv = lax.stop_gradient(P.fv)
    w = lax.stop_gradient(w)
    sf = jnp.zeros(nsteps + 1, jnp.int32).at[0].set(face)
    se = jnp.zeros(nsteps + 1, jnp.int32)
    sk = jnp.full(nsteps + 1, 3, jnp.int32).at[0].set(0)
    sp = jnp.where(act, 1, 0)
    hz_idx = jnp.zeros(nhorizon, jnp.int32)
    hz_edge = jnp.zeros(nhorizon, jnp.int32)
    carry = (P.fmap, P.fidx, P.nmap, sf, se, sk, sp, hz_idx, hz_edge, jnp.array(0))
    slots = jnp.arange(nsteps + 1)

    def body(_, c):
        fmap, fidx, nmap, sf, se, sk, sp, hz_idx, hz_edge, ne = c
        on = sp > 0
        top = jnp.maximum(sp - 1, 0)
        f, e, k = sf[top], se[top], sk[top]
        i = (e + k) % 3
        g = P.fadj[f, i]
        vtx = P.fverts[f, (i + 1) % 3]
        sk = sk.at[top].set(jnp.where(on, k + 1, k))
        live = fidx[g] > -2
        fg = P.fverts[g]
        ge = jnp.where(fg[0] == vtx, 0, jnp.where(fg[1] == vtx, 1, 2))
        vis = dot3(fv[g], w) - fd2[g] > MINVAL
        do = on & live
        push = do & vis
        add = do & ~vis
        # delete g
        P_ = P._replace(fmap=fmap, fidx=fidx, nmap=nmap)
        P_ = _delete_face(P_, g, push)
        fmap, fidx, nmap = P_.fmap, P_.fidx, P_.nmap
        pos = jnp.where(push, sp, nsteps + 1)
        sf = sf.at[pos].set(g, mode="drop")
        se = se.at[pos].set(ge, mode="drop")
        sk = sk.at[pos].set(1, mode="drop")
        sp = jnp.where(push, sp + 1, sp)
        hpos = jnp.where(add, ne, nhorizon)
        hz_idx = hz_idx.at[hpos].set(g, mode="drop")
        hz_edge = hz_edge.at[hpos].set(ge, mode="drop")
        ne = jnp.where(add, ne + 1, ne)
        # pop finished frames
        open_ = (slots < sp) & (sk < 3)
        sp = jnp.where(open_.any(), jnp.max(jnp.where(open_, slots, -1)) + 1, 0)
        return fmap, fidx, nmap, sf, se, sk, sp, hz_idx, hz_edge, ne

    fmap, fidx, nmap, _, _, _, sp, hz_idx, hz_edge, ne = _loop(nsteps, body, carry,
                                                              lambda c: c[6] == 0)
    return P._replace(fmap=fmap, fidx=fidx, nmap=nmap), hz_idx, hz_edge, ne, sp > 0


class EPAResult(NamedTuple):
    """What `epa` returns."""

    face_ok: jax.Array  # () bool: epa returned a face
    dist: jax.Array  # () status->dist[0]
    x1: jax.Array  # (3,)
    x2: jax.Array  # (3,)
    face: Vert  # (3,) the face's vertices (the objects' simplex after EPA)
    vi1: jax.Array
    vi2: jax.Array
    overflow: jax.Array  # () bool: a fixed-size buffer was too small (C would differ)


def epa(k1, k2, o1, o2, P: Polytope, vi1, vi2, *, discrete, tolerance=CCD_TOLERANCE,
        kmax=CCD_ITERATIONS, nhorizon=NHORIZON, ndfs=NDFS) -> EPAResult:
    """The EPA (epa in engine_collision_gjk.c): expands the polytope toward the penetration depth.

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source.

    Args:
      k1: static description of geom 1.
      k2: static description of geom 2.
      o1: pose, size and margin of geom 1.
      o2: the same of geom 2.
      P: start polytope from `start_polytope`.
      vi1: vertindex of object 1.
      vi2: vertindex of object 2.
      discrete: () bool, discreteGeoms(obj1, obj2).
      tolerance: ccd_tolerance.
      kmax: ccd_iterations (static).
      nhorizon: static size of the horizon buffer.
      ndfs: static number of steps of the horizon's depth-first search.

    Returns:
      `EPAResult`.
    """
    dtype = P.fv.dtype
    tol = jnp.where(discrete, MINEPATOL, tolerance)
    maxfaces = 6 * kmax
    nf = P.fv.shape[0]
    hidx = jnp.arange(nhorizon)

    def body(k, c):
        """One EPA iteration in C's order (long: see `epa`)."""
        P, face, upper, upper2, done, vi1, vi2, over = c
        act = ~done
        pface = face
        ids = jnp.arange(nf)
        d2m = lax.stop_gradient(P.fd2)[P.fmap]
        cand = (ids < P.nmap) & (d2m < MAX_LIMIT)
        vals = jnp.where(cand, d2m, jnp.inf)
        j = jnp.argmin(vals)
        found = cand.any()
        face_sel = jnp.where(found, P.fmap[j], face)
        lower2 = jnp.where(found, P.fd2[jnp.maximum(face_sel, 0)], MAX_LIMIT)
        lower2_sg = lax.stop_gradient(lower2)
        b1 = (lower2_sg > upper2) | (face_sel < 0)
        b2 = ~b1 & (lower2_sg <= 0)
        go = act & ~b1 & ~b2
        fvf = P.fv[jnp.maximum(face_sel, 0)]
        lower = safe_sqrt(lower2)
        w, n1, n2 = _epa_support(k1, k2, o1, o2, fvf, lower, vi1, vi2)
        wi = P.nverts
        upper_k = safe_div(dot3(fvf, w.vert), lower)
        better = lax.stop_gradient(upper_k) < upper
        upper_n = jnp.where(go & better, lax.stop_gradient(upper_k), upper)
        upper2_n = jnp.where(go & better, upper_n * upper_n, upper2)
        conv = lax.stop_gradient(upper_n - lower) < tol
        b3 = go & conv
        nullify3 = b3 & (k == 0) & (upper_n < lax.stop_gradient(lower) - 1e-10)
        go = go & ~conv
        rep = ((P.verts.i1 == w.i1) & (P.verts.i2 == w.i2) & (jnp.arange(P.verts.i1.shape[0])
                                                               < wi)).any()
        b4 = go & discrete & rep
        go = go & ~(discrete & rep)
        supported = act & ~b1 & ~b2
        old_row = vert_at(P.verts, wi)
        row = tree_where(supported, w, old_row)
        Pw = P._replace(
            verts=jax.tree_util.tree_map(
                lambda a, r: lax.dynamic_update_index_in_dim(a, r, wi, 0), P.verts, row),
            nverts=jnp.where(supported, wi + 1, wi))
        Ph, hz_idx, hz_edge, ne, hover = horizon(Pw, jnp.maximum(face_sel, 0), w.vert, go,
                                                 ndfs, nhorizon)
        b5 = go & (ne < 3)
        go = go & (ne >= 3)
        b6 = go & (ne > maxfaces - Ph.nfaces)
        go = go & ~(ne > maxfaces - Ph.nfaces)
        # attach the new faces along the horizon: one block of rows at nfaces
        valid = hidx < ne
        hi = hz_idx
        he = hz_edge
        hrow = Ph.fverts[hi]
        va = jnp.where(he == 0, hrow[:, 0], jnp.where(he == 1, hrow[:, 1], hrow[:, 2]))
        vb = jnp.where(he == 0, hrow[:, 1], jnp.where(he == 1, hrow[:, 2], hrow[:, 0]))
        nfa = Ph.nfaces
        cur = nfa + hidx
        prv = jnp.where(hidx == 0, nfa + ne - 1, cur - 1)
        nxt = nfa + (hidx + 1) % jnp.maximum(ne, 1)
        ret, fv_new, d2_new = jax.vmap(lambda a, b: _face_plane(Ph, wi, b, a))(va, vb)
        fail = valid & (ret | (d2_new == 0))
        b7 = go & fail.any()
        first_fail = jnp.where(fail.any(), jnp.argmax(fail), nhorizon)
        ok_face = valid & (hidx < first_fail)
        d2s = lax.stop_gradient(d2_new)
        ins = ok_face & (d2s >= lower2_sg) & (d2s <= upper2_n)
        rank = jnp.cumsum(ins) - 1
        pos = Ph.nmap + rank
        put = go & valid

        def block(arr, new, start):
            old = lax.dynamic_slice_in_dim(arr, start, nhorizon, 0)
            m = jnp.reshape(put, (-1,) + (1,) * (new.ndim - 1))
            return lax.dynamic_update_slice_in_dim(arr, jnp.where(m, new, old).astype(arr.dtype),
                                                   start, 0)

        fverts = block(Ph.fverts, jnp.stack([jnp.full_like(va, wi), vb, va], -1), nfa)
        fadj = block(Ph.fadj, jnp.stack([prv, hi, nxt], -1), nfa)
        fvv = block(Ph.fv, fv_new, nfa)
        fd2 = block(Ph.fd2, d2_new, nfa)
        fidx = block(Ph.fidx, jnp.where(ins, pos, -1), nfa)
        fadj = fadj.at[jnp.where(put, hi, nf), he].set(cur.astype(jnp.int32), mode="drop")
        nins = ins.sum()
        new_ids = jnp.zeros(nhorizon, jnp.int32).at[jnp.where(ins, rank, nhorizon)].set(
            cur.astype(jnp.int32), mode="drop")
        old_map = lax.dynamic_slice_in_dim(Ph.fmap, Ph.nmap, nhorizon, 0)
        fmap = lax.dynamic_update_slice_in_dim(
            Ph.fmap, jnp.where(go & (hidx < nins), new_ids, old_map).astype(jnp.int32), Ph.nmap,
            0)
        nmap = jnp.where(go, Ph.nmap + nins, Ph.nmap)
        Pn = Ph._replace(fverts=fverts, fadj=fadj, fv=fvv, fd2=fd2, fmap=fmap, fidx=fidx,
                         nmap=nmap, nfaces=jnp.where(go, nfa + ne, nfa))
        b8 = go & ~b7 & (nmap == 0)
        P = Pn
        vi1 = jnp.where(supported, n1, vi1)
        vi2 = jnp.where(supported, n2, vi2)
        newface = face_sel
        newface = jnp.where(act & b1, pface, newface)
        newface = jnp.where(nullify3 | b5 | b7, -1, newface)
        face = jnp.where(act, newface, face)
        stop = b1 | b2 | b3 | b4 | b5 | b6 | b7 | b8
        done = done | (act & stop)
        over = over | (go & (hover | (ne > nhorizon)))
        return P, face, upper_n, upper2_n, done, vi1, vi2, over

    carry = (P, jnp.array(-1), jnp.asarray(MAX_LIMIT, dtype), jnp.asarray(MAX_LIMIT, dtype),
             jnp.array(False), vi1, vi2, jnp.array(False))
    P, face, _, _, _, vi1, vi2, over = _loop(kmax, body, carry, lambda c: c[4])
    ok = face >= 0
    f = jnp.maximum(face, 0)
    tri = vert_at(P.verts, P.fverts[f])
    lam = tri_affine_coord(tri.vert[0], tri.vert[1], tri.vert[2], P.fv[f])
    x1 = (mul(lam[0], tri.v1[0]) + mul(lam[1], tri.v1[1])) + mul(lam[2], tri.v1[2])
    x2 = (mul(lam[0], tri.v2[0]) + mul(lam[1], tri.v2[1])) + mul(lam[2], tri.v2[2])
    dist = -safe_sqrt(P.fd2[f])
    return EPAResult(ok, jnp.where(ok, dist, 0.0), x1, x2, tri, vi1, vi2, over)
