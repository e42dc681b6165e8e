"""MuJoCo C's general convex collisions in MJX: mjc_Convex and mjc_PlaneConvex.

MuJoCo C collides cylinders, ellipsoids and meshes (except with planes and the
primitive pairs) through `mjc_Convex` (engine_collision_convex.c): native GJK/EPA
(`ccd.ccd`) with, in the installed 3.17 binary, no perturbation passes for geom
pairs but `mjc_multicontact` (`gjk_multi`) for cylinder, box and mesh pairs (up
to 4 contacts) and for a capsule against those (2). MJX 3.17 instead runs a
10-step signed-distance descent (cylinders, ellipsoids) or its own SAT manifold
(meshes), and has no cylinder-box collider at all. This module installs C's
algorithm for these pairs:

  capsule-cylinder, cylinder-cylinder, cylinder-box;
  sphere-, capsule-, cylinder-, box-, ellipsoid-ellipsoid;
  sphere-, capsule-, ellipsoid-, cylinder-, box-, mesh-mesh;
  plane-mesh (mjc_PlaneConvex, up to 4 contacts).

N.B. the 3.17 binary differs from the C source next to it (/work/csrc): its
mjc_Convex skips the multi-CCD rotations for geom pairs, maxContacts ignores
margins, and mj_maxContact gives 2 for capsule pairs and 4 for plane-mesh. The
ports follow the binary (the comparison harness measures against it).

Mesh pairs need C's mesh polygons (`mesh_polyvert`, `mesh_polymap`...), which
`mjx.Model` does not carry: `register_model` records them, and importing this
module wraps `mjx.put_model` to register every model put on device.
"""

from __future__ import annotations

import functools
import hashlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp import colliders
from mjstamp.colliders import ccd, gjk
from mjstamp.colliders.gjk import (
    BOX,
    CAPSULE,
    CYLINDER,
    ELLIPSOID,
    MESH,
    PLANE,
    SPHERE,
    Kind,
    Obj,
    mul,
)

__all__ = ["kind_of", "max_contacts", "plane_mesh", "register_model", "pair_contacts"]

_MULTICCD = int(mujoco.mjtDisableBit.mjDSBL_MULTICCD)
_NATIVECCD = int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)

# Mesh data by content (vertex bytes): C's polygons of every registered mesh.
_MESHES: dict[str, gjk.MeshData] = {}


# ------------------------------------------------------------------------------- meshes


def _mesh_key(vert: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(vert, np.float32).tobytes()).hexdigest()


def _mesh_data(m: mujoco.MjModel, mid: int) -> gjk.MeshData:
    """C's vertices and polygons of mesh `mid` (mjc_initCCDObj's view of it)."""
    va, nv = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
    pa, npoly = int(m.mesh_polyadr[mid]), int(m.mesh_polynum[mid])
    vert = np.asarray(m.mesh_vert[va:va + nv], np.float64)
    pvn = np.asarray(m.mesh_polyvertnum[pa:pa + npoly], np.int32)
    pmax = max(int(pvn.max()) if npoly else 1, 3)
    polyvert = np.zeros((max(npoly, 1), pmax), np.int32)
    for k in range(npoly):
        adr = int(m.mesh_polyvertadr[pa + k])
        polyvert[k, :pvn[k]] = m.mesh_polyvert[adr:adr + pvn[k]]
    vpn = np.asarray(m.mesh_polymapnum[va:va + nv], np.int32)
    dmax = max(int(vpn.max()) if nv else 1, 1)
    vertpoly = np.zeros((nv, dmax), np.int32)
    for v in range(nv):
        adr = int(m.mesh_polymapadr[va + v])
        vertpoly[v, :vpn[v]] = m.mesh_polymap[adr:adr + vpn[v]]
    normals = np.asarray(m.mesh_polynormal[pa:pa + npoly], np.float64).reshape(-1, 3)
    if not npoly:
        normals = np.zeros((1, 3))
        pvn = np.zeros(0, np.int32)
    return gjk.MeshData(vert, normals, polyvert, pvn, vertpoly, vpn)


def register_model(m: mujoco.MjModel) -> None:
    """Records C's mesh polygons of `m` for the mesh colliders (by mesh content)."""
    for mid in range(m.nmesh):
        va, nv = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
        _MESHES.setdefault(_mesh_key(m.mesh_vert[va:va + nv]), _mesh_data(m, mid))


def _install_put_model_hook() -> None:
    """Wraps mjx.put_model so that every model put on device registers its meshes."""
    from mjstamp._mjx import mjx  # pylint: disable=g-import-not-at-top

    put = mjx.put_model
    if getattr(put, "_mjstamp_meshes", False):
        return

    @functools.wraps(put)
    def put_model(m, *args, **kwargs):
        if isinstance(m, mujoco.MjModel):
            register_model(m)
        return put(m, *args, **kwargs)

    put_model._mjstamp_meshes = True  # pylint: disable=protected-access
    mjx.put_model = put_model


def kind_of(m, g: int) -> Kind:
    """The static CCD description of geom g of an MjModel or mjx.Model (mesh data included)."""
    t = int(m.geom_type[g])
    if t == MESH:
        if isinstance(m, mujoco.MjModel):
            register_model(m)
        return Kind(t, _mesh_of(m, int(m.geom_dataid[g])))
    return Kind(t)


def _mesh_of(m, mid: int) -> gjk.MeshData:
    va, nv = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
    key = _mesh_key(np.asarray(m.mesh_vert)[va:va + nv])
    if key not in _MESHES:
        raise KeyError("mesh polygons unknown: call mjstamp.colliders.convex."
                       "register_model(mj_model) before collecting contacts of this model")
    return _MESHES[key]


# ------------------------------------------------------------------------------- pairs


def max_contacts(t1: int, t2: int, disableflags: int = 0) -> int:
    """maxContacts() of mjc_Convex in the 3.17 binary: contacts of one CCD pass."""
    if disableflags & _NATIVECCD:
        return 1
    if t1 == BOX and t2 == BOX:
        return 8
    if disableflags & _MULTICCD:
        return 1
    poly = (CYLINDER, BOX, MESH)
    if t1 in poly and t2 in poly:
        return 4
    if (t1 == CAPSULE and t2 in poly) or (t2 == CAPSULE and t1 in poly):
        return 2
    return 1


def ncon_of(t1: int, t2: int) -> int:
    """mj_maxContact (3.17 binary) with default flags: the slots of a pair."""
    if t1 == PLANE:
        return 4
    return max_contacts(t1, t2)


def pair_contacts(k1: Kind, k2: Kind, info1, info2, margin, *, ncon: int,
                  disableflags: int = 0):
    """mjc_Convex for one geom pair: (dist (ncon,), pos (ncon, 3), frame (ncon, 3, 3)).

    Args:
      k1: static description of geom 1 (type 1 <= type 2).
      k2: static description of geom 2.
      info1: MJX GeomInfo of geom 1 (pos (3,), mat (3, 3), size (3,)).
      info2: the same of geom 2.
      margin: () the pair's margin as C passes it (mjc_initCCDObj's margin of both).
      ncon: static number of slots.
      disableflags: static mjOption.disableflags.

    Returns:
      contacts in C's order, unused slots at `contacts.FAR`.

    Pairs of boxes, meshes, spheres and capsules take `ccd.ccd_converged` (the
    derivatives of `ccd.ccd` at a fraction of its cost); pairs with a cylinder
    or an ellipsoid differentiate through every iteration (`ccd.ccd`).
    """
    if disableflags & _NATIVECCD:
        raise NotImplementedError("libccd (nativeccd disabled) is not ported")
    margin = jnp.asarray(margin, info1.pos.dtype)
    o1 = Obj(info1.pos, info1.mat.reshape(3, 3), info1.size, margin)
    o2 = Obj(info2.pos, info2.mat.reshape(3, 3), info2.size, margin)
    maxc = max_contacts(k1.gtype, k2.gtype, disableflags)
    with gjk.exact(info1.pos):
        converged = {k1.gtype, k2.gtype} <= ccd.CONVERGED_KINDS
        run = ccd.ccd_converged if converged else ccd.ccd
        r = run(k1, k2, o1, o2, max_contacts=maxc)
        n = r.dist.shape[0]
        pos = mul(r.x1 + r.x2, 0.5)
        nrm, _ = gjk.normalize3(r.x1 - r.x2)
        dist = margin + r.dist
    frame = jax.vmap(colliders.make_frame)(nrm)
    valid = jnp.arange(n) < r.ncon
    dist = jnp.where(valid, dist, colliders.FAR)
    if n < ncon:
        pad = ncon - n
        dist = jnp.concatenate([dist, jnp.full(pad, colliders.FAR, dist.dtype)])
        pos = jnp.concatenate([pos, jnp.zeros((pad, 3), pos.dtype)])
        frame = jnp.concatenate([frame, jnp.tile(jnp.eye(3, dtype=pos.dtype), (pad, 1, 1))])
    return dist[:ncon], pos[:ncon], frame[:ncon]


# ----------------------------------------------------------------------------- plane-mesh


def _hull_from(verts, pv, nv, k, nsteps):
    """The hull search of mjc_PlaneConvex: a fixed, b c d grow the quadrilateral's area."""
    def area(i):
        return gjk_multi_area(verts[pv[i[0]]], verts[pv[i[1]]], verts[pv[i[2]]], verts[pv[i[3]]])

    n = jnp.maximum(nv, 1)
    idx = jnp.stack([k, (k + 1) % n, (k + 2) % n, (k + 3) % n])
    carry = (idx, jax.lax.stop_gradient(area(idx)), jnp.array(0))  # phase: 0 d, 1 c, 2 b, 3 done

    def step(_, c):
        abcd, m, phase = c
        a, b, cc, d = abcd[0], abcd[1], abcd[2], abcd[3]
        cand = jnp.where(phase == 0, jnp.stack([a, b, cc, (d + 1) % n]),
                         jnp.where(phase == 1, jnp.stack([a, b, (cc + 1) % n, d]),
                                   jnp.stack([a, (b + 1) % n, cc, d])))
        mn = jax.lax.stop_gradient(area(cand))
        up = (phase < 3) & (m < mn)
        new_phase = jnp.where(phase == 3, 3, jnp.where(up, jnp.where(phase == 0, 1, phase),
                                                       jnp.where(phase == 0, 3, jnp.where(
                                                           phase == 1, 2, 0))))
        return jnp.where(up, cand, abcd), jnp.where(up, mn, m), new_phase

    idx, _, phase = jax.lax.fori_loop(0, nsteps, step, carry)
    return idx, phase == 3


def gjk_multi_area(a, b, c, d):
    from mjstamp.colliders import gjk_multi  # pylint: disable=g-import-not-at-top

    return gjk_multi.area4(a, b, c, d)


def plane_mesh(k2: Kind, info1, info2, margin):
    """mjc_PlaneConvex of the 3.17 binary for a mesh: up to 4 contacts.

    The deepest vertex along the plane normal, then up to three more vertices of
    the adjacent polygon whose normal is most opposed to the plane's (the
    largest-area quadrilateral through the first vertex when the polygon has
    more than four), each kept if within the margin and below the mesh center.

    Args:
      k2: the mesh (static).
      info1: the plane's GeomInfo.
      info2: the mesh's.
      margin: () the pair's margin.

    Returns:
      (dist (4,), pos (4, 3), frame (4, 3, 3)), unused slots at `contacts.FAR`.
    """
    dtype = info1.pos.dtype
    margin = jnp.asarray(margin, dtype)
    mat1 = info1.mat.reshape(3, 3)
    pos1 = info1.pos
    o2 = Obj(info2.pos, info2.mat.reshape(3, 3), info2.size, jnp.zeros((), dtype))
    mesh = k2.mesh
    with gjk.exact(pos1):
        normal = mat1[:, 2]
        s, vi = gjk.support_raw(k2, o2, normal * -1.0, jnp.array(-1, jnp.int32))
        dist0 = gjk.dot3(normal, s - pos1)
        pos0 = mul(normal, dist0 * -0.5) + s
        verts = jnp.asarray(mesh.vert, dtype)
        ln = gjk.matT_vec(o2.mat, normal)
        polys = jnp.asarray(mesh.vertpoly)[vi]
        npv = jnp.asarray(mesh.vertpolynum)[vi]
        dots = jax.vmap(lambda q: gjk.dot3(ln, jnp.asarray(mesh.polynormal, dtype)[q]))(polys)
        dots = jax.lax.stop_gradient(dots)
        okp = (jnp.arange(polys.shape[0]) < npv) & (dots < 1.0)
        # the first strict minimum below 1 in polymap order
        vals = jnp.where(okp, dots, jnp.inf)
        ib = jnp.argmin(vals)
        found = okp.any() & (mesh.polynum > 0)
        q = polys[ib]
        pv = jnp.asarray(mesh.polyvert)[q]
        nv = jnp.asarray(mesh.polyvertnum)[q] if mesh.polynum else jnp.array(0)
        P = pv.shape[0]
        hit = (pv == vi) & (jnp.arange(P) < nv)
        kk = jnp.where(hit.any(), jnp.argmax(hit), 0)
        hull_idx, _ = _hull_from(verts, pv, nv, kk, 6 * P + 8)
        big = nv >= 5
        cand = jnp.where(big, hull_idx[1:], jnp.stack([(kk + 1) % jnp.maximum(nv, 1),
                                                       (kk + 2) % jnp.maximum(nv, 1),
                                                       (kk + 3) % jnp.maximum(nv, 1)]))
        ncand = jnp.where(big, 3, jnp.minimum(3, nv - 1))
        ncand = jnp.where(found & (nv >= 2), ncand, 0)
        pnts = jax.vmap(lambda j: gjk.local_to_global(o2.mat, verts[pv[j]], o2.pos))(cand)
        dd = jax.vmap(lambda p: gjk.dot3(normal, p - pos1))(pnts)
        above = jax.vmap(lambda p: gjk.dot3(normal, p - o2.pos))(pnts)
        keep = ((jnp.arange(3) < ncand) & (jax.lax.stop_gradient(dd) <= margin)
                & (jax.lax.stop_gradient(above) <= 0))
        cpos = jax.vmap(lambda p, x: mul(normal, x * -0.5) + p)(pnts, dd)
    first = jax.lax.stop_gradient(dist0) <= margin
    keep = keep & first
    order = jnp.argsort(~keep, stable=True)
    dist = jnp.concatenate([dist0[None], jnp.where(keep[order], dd[order], colliders.FAR)])
    dist = dist.at[0].set(jnp.where(first, dist0, colliders.FAR))
    pos = jnp.concatenate([pos0[None], cpos[order]])
    frame = jnp.tile(colliders.make_frame(normal)[None], (4, 1, 1))
    return dist, pos, frame


# -------------------------------------------------------------------------- MJX colliders

_PAIRS = [(CAPSULE, CYLINDER), (CYLINDER, CYLINDER), (CYLINDER, BOX),
          (SPHERE, ELLIPSOID), (CAPSULE, ELLIPSOID), (ELLIPSOID, ELLIPSOID),
          (ELLIPSOID, CYLINDER), (ELLIPSOID, BOX),
          (SPHERE, MESH), (CAPSULE, MESH), (CYLINDER, MESH), (ELLIPSOID, MESH), (BOX, MESH),
          (MESH, MESH), (PLANE, MESH)]


_OPT_IN = {(SPHERE, MESH), (CAPSULE, MESH), (BOX, MESH), (MESH, MESH)}


def _make(t1: int, t2: int):
    ncon = ncon_of(t1, t2)
    has_mesh = MESH in (t1, t2)

    kind1, kind2 = Kind(t1), Kind(t2)

    def pair_fn(info1, info2, margin, *, k1=kind1, k2=kind2, flags=0):
        """One pair (non-mesh kinds by default); see `pair_contacts`."""
        if t1 == PLANE:
            return plane_mesh(k2, info1, info2, margin)
        return pair_contacts(k1, k2, info1, info2, margin, ncon=ncon, disableflags=flags)

    def collide(m, d, key, contact):
        from mujoco.mjx._src.collision_types import GeomInfo  # pylint: disable=g-import-not-at-top

        g1, g2 = contact.geom.T
        ids = getattr(key, "data_ids", (-1, -1))
        k1 = Kind(t1, _mesh_of(m, int(ids[0])) if t1 == MESH else None)
        k2 = Kind(t2, _mesh_of(m, int(ids[1])) if t2 == MESH else None)
        flags = int(m.opt.disableflags)
        info1 = GeomInfo(d.geom_xpos[g1], d.geom_xmat[g1], m.geom_size[g1])
        info2 = GeomInfo(d.geom_xpos[g2], d.geom_xmat[g2], m.geom_size[g2])
        fn = functools.partial(pair_fn, k1=k1, k2=k2, flags=flags)
        dist, pos, frame = jax.vmap(fn)(info1, info2, contact.includemargin)
        return dist.reshape(-1), pos.reshape(-1, 3), frame.reshape(-1, 3, 3)

    collide.ncon = ncon
    collide.takes_contact = True
    collide.pair_fn = pair_fn
    names = [mujoco.mjtGeom(t).name[7:].lower() for t in (t1, t2)]
    collide.__name__ = "_".join(names)
    cname = "PlaneConvex" if t1 == PLANE else "Convex"
    collide.__doc__ = f"mjc_{cname} (C 3.17) as an MJX collider."
    collide.needs_mesh = has_mesh
    # MJX's own function stays for these unless `contacts.exact_meshes()` (see contacts)
    collide.opt_in = (t1, t2) in _OPT_IN
    return collide


for _t1, _t2 in _PAIRS:
    colliders.PORTED[(_t1, _t2)] = _make(_t1, _t2)

_install_put_model_hook()
