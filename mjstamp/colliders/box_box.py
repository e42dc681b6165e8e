"""MuJoCo C's box-box collider (`mjc_BoxBox`, engine_collision_box.c) in JAX.

C finds the axis of largest separation among the 15 candidates (3 face normals
per box, 9 edge cross products), then either clips the incident face of one box
against the side planes of the other's reference face (up to 8 contacts) or
joins the two supporting edges (1 contact). The port keeps C's formulas, their
order of evaluation, thresholds and tie-breaking; C's early returns and
variable-length polygons become masks over fixed-size arrays, and both the
edge and the face branch are computed and one is selected.

C's index arithmetic on the winning axis (component i of box 1, j of box 2,
face axis a, incident axis binc) becomes static index tables: one-hot vectors
picked by the axis code, or index permutations that bring (ax, ay, a) to
(0, 1, 2). Picking and permuting copy values exactly, so every floating-point
operation is C's, in C's order, and compiled graphs stay small.

N.B. MJX's own `box_box` (collision_convex.py) is a different algorithm (a
4-point manifold); nothing of it is reused here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp.colliders import FAR, PORTED, collider, make_frame

# engine_collision_box.c, double precision.
_SEPEPS = 1e-13    # mjBOXBOX_SEPEPS: slack on the separation tests, times the box scale
_PAREPS = 1e-16    # mjBOXBOX_PAREPS: sin^2 below which an edge-cross axis is noise
_SGNEPS = 1e-9     # mjBOXBOX_SGNEPS: axis component below which a support corner is ambiguous
_DUPEPS = 1e-14    # mjBOXBOX_DUPEPS: squared relative radius for clip-vertex deduplication
_EDGEBIAS = 1e-6   # mjBOXBOX_EDGEBIAS: relative penalty of edge axes on near-ties
_MAXVERT = 12      # mjBOXBOX_MAXVERT: capacity of the clipping buffers
_MINVAL = 1e-15    # mjMINVAL
_MAXVAL = 1e10     # mjMAXVAL

# C's maximum for the pair (mj_maxContact, engine_collision_driver.c): a 4-gon
# clipped by the 4 side planes of a rectangle has at most 8 vertices.
NCON = 8

# Edge pair e = 3 i + j (SAT code 6 + e): i of box 1, j of box 2, and the next two of each.
_EI = np.repeat(np.arange(3), 3)
_EJ = np.tile(np.arange(3), 3)
_EI1, _EI2 = (_EI + 1) % 3, (_EI + 2) % 3
_EJ1, _EJ2 = (_EJ + 1) % 3, (_EJ + 2) % 3
_ONEHOT = np.eye(3)

# Cyclic orders: _CYCLE[k] = (k, k + 1, k + 2) mod 3; for a face axis a, C's in-plane
# coordinates (ax, ay) and the normal a are _CYCLE[a][[1, 2, 0]], undone by _UNPERM[a].
_CYCLE = np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1]])
_PERM = _CYCLE[:, [1, 2, 0]]
_UNPERM = np.argsort(_PERM, axis=1)

# Corners of the incident face in C's cyclic winding (corner_sign).
_CORNER_SU = np.array([1.0, -1.0, -1.0, 1.0])
_CORNER_SV = np.array([1.0, 1.0, -1.0, -1.0])


def _dot3(a: jax.Array, b: jax.Array) -> jax.Array:
    """mju_dot3 over the last axis, summed left to right as C does."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _mat_vec(mat: jax.Array, vec: jax.Array) -> jax.Array:
    """mji_mulMatVec3 for (..., 3) vectors: mat (3, 3) @ vec, in C's summation order."""
    return (vec[..., 0:1] * mat[:, 0] + vec[..., 1:2] * mat[:, 1]) + vec[..., 2:3] * mat[:, 2]


def _mat_t_vec(mat: jax.Array, vec: jax.Array) -> jax.Array:
    """mji_mulMatTVec3 for (..., 3) vectors: mat.T (3, 3) @ vec, in C's summation order."""
    return (vec[..., 0:1] * mat[0] + vec[..., 1:2] * mat[1]) + vec[..., 2:3] * mat[2]


def _row(table: np.ndarray, k: jax.Array) -> jax.Array:
    """table[k] of a static table for a traced index k."""
    return jnp.asarray(table)[k]


def _pick(vec: jax.Array, onehot: jax.Array) -> jax.Array:
    """vec[k] for onehot = e_k (exactly; zero gradient to the other components)."""
    return jnp.sum(jnp.where(onehot > 0, vec, 0.0), axis=-1)


def _normalize3(vec: jax.Array) -> jax.Array:
    """mju_normalize3 (engine_util_blas.c): vec / |vec|, or (1, 0, 0) below mjMINVAL.

    Args:
      vec: (3,) vector.

    Returns:
      (3,) unit vector; its gradient is finite (zero) in the degenerate case.
    """
    norm2 = _dot3(vec, vec)
    norm = jnp.where(norm2 > 0, jnp.sqrt(jnp.where(norm2 > 0, norm2, 1.0)), 0.0)
    small = norm < _MINVAL
    # N.B. C multiplies by the inverse (one more rounding than a division).
    inv = 1.0 / jnp.where(small, 1.0, norm)
    return jnp.where(small, jnp.array([1.0, 0.0, 0.0], vec.dtype), vec * inv)


def _edge_axes_raw(rot: jax.Array) -> jax.Array:
    """The unnormalized edge axes e_i x rot[:, j] of the 9 edge pairs, in box 1 frame.

    Args:
      rot: (3, 3) box2 axes in box1 frame (columns).

    Returns:
      (9, 3) axes: axis[i] = 0, axis[i1] = -rot[i2, j], axis[i2] = rot[i1, j].
    """
    comp1 = -rot[_EI2, _EJ]
    comp2 = rot[_EI1, _EJ]
    return (jnp.where(_ONEHOT[_EI1] > 0, comp1[:, None], 0.0)
            + jnp.where(_ONEHOT[_EI2] > 0, comp2[:, None], 0.0))


def _separating_axis(rot, pos21, pos12, size1, size2, septol):
    """Stage 1 of `mjc_BoxBox` (engine_collision_box.c): the separating-axis search.

    Args:
      rot: (3, 3) box2 axes in box1 frame (columns).
      pos21: (3,) box2 centre in box1 frame.
      pos12: (3,) box1 centre in box2 frame.
      size1: (3,) half-sizes of box 1.
      size2: (3,) half-sizes of box 2.
      septol: scalar, margin plus rounding slack.

    Returns:
      separated: bool, some candidate axis separates the boxes by more than septol
        (C returns 0 contacts).
      code: int, the winning axis after C's face substitution: 0..2 face of box1,
        3..5 face of box2, 6 + 3 i + j edge pair (i, j); -1 if none.
    """
    rotabs = jnp.abs(rot)
    # face axes of box 1 (rows of rot) and of box 2 (columns)
    radius2 = rotabs[:, 0] * size2[0] + rotabs[:, 1] * size2[1] + rotabs[:, 2] * size2[2]
    sep1 = jnp.abs(pos21) - size1 - radius2
    radius1 = rotabs[0] * size1[0] + rotabs[1] * size1[1] + rotabs[2] * size1[2]
    sep2 = jnp.abs(pos12) - size2 - radius1
    sep_faces = jnp.concatenate([sep1, sep2])

    # edge-cross axes e_i x rot[:, j]; C skips (`continue`) nearly parallel edges
    ax1 = -rot[_EI2, _EJ]
    ax2 = rot[_EI1, _EJ]
    norm2 = ax1 * ax1 + ax2 * ax2
    use = ~(norm2 < _PAREPS)
    inv = 1.0 / jnp.sqrt(jnp.where(use, norm2, 1.0))
    ax1 = ax1 * inv
    ax2 = ax2 * inv
    radius1 = size1[_EI1] * jnp.abs(ax1) + size1[_EI2] * jnp.abs(ax2)
    a2_1 = ax1 * rot[_EI1, _EJ1] + ax2 * rot[_EI2, _EJ1]
    a2_2 = ax1 * rot[_EI1, _EJ2] + ax2 * rot[_EI2, _EJ2]
    radius2 = size2[_EJ1] * jnp.abs(a2_1) + size2[_EJ2] * jnp.abs(a2_2)
    sep_edges = jnp.abs(ax1 * pos21[_EI1] + ax2 * pos21[_EI2]) - radius1 - radius2

    separated = jnp.any(sep_faces > septol) | jnp.any(use & (sep_edges > septol))

    # C's sequential search with strict '>' from -mjMAXVAL keeps the first of equal
    # separations: the first maximum (supports are bounded, so some face always wins)
    code_face = jnp.argmax(sep_faces).astype(jnp.int32)
    sep_face = jnp.max(sep_faces)
    sep_best, code = sep_face, code_face
    for e in range(9):
        sep = sep_edges[e]
        # an edge must beat the best axis by a relative bias, and the best face outright
        wins = use[e] & (sep - _EDGEBIAS * jnp.abs(sep) > sep_best) & (sep > sep_face)
        sep_best = jnp.where(wins, sep, sep_best)
        code = jnp.where(wins, 6 + e, code)

    # an edge axis within ~8 degrees of the best face axis, and not 5% deeper, gives way to it
    axis = _normalize3(_edge_axes_raw(rot)[jnp.clip(code - 6, 0, 8)])
    face1 = _pick(axis, _row(_ONEHOT, jnp.clip(code_face, 0, 2)))
    col = _row(_ONEHOT, jnp.clip(code_face - 3, 0, 2))
    face2 = _dot3(axis, jnp.sum(jnp.where(col > 0, rot, 0.0), axis=1))
    face_dot = jnp.abs(jnp.where(code_face < 3, face1, face2))
    substitute = ((code >= 6) & (face_dot > 0.99)
                  & (sep_best < sep_face + 0.05 * jnp.abs(sep_face) + _MINVAL))
    code = jnp.where(substitute, code_face, code)
    return separated, code


def _edge_contact(code, rot, pos21, size1, size2):
    """Stage 2a of `mjc_BoxBox` (engine_collision_box.c): the edge-edge contact.

    Args:
      code: int, the winning edge code 6 + 3 i + j (others give a meaningless result).
      rot: (3, 3) box2 axes in box1 frame.
      pos21: (3,) box2 centre in box1 frame.
      size1: (3,) half-sizes of box 1.
      size2: (3,) half-sizes of box 2.

    Returns:
      dist: scalar, signed distance along the axis.
      mid: (3,) contact position in box1 frame.
      axis: (3,) unit normal in box1 frame, from box1 toward box2.
    """
    e = jnp.clip(code - 6, 0, 8)
    oi, oi1, oi2 = (_row(_ONEHOT[k], e) for k in (_EI, _EI1, _EI2))
    oj, oj1, oj2 = (_row(_ONEHOT[k], e) for k in (_EJ, _EJ1, _EJ2))

    axis = _normalize3(_edge_axes_raw(rot)[e])
    axis = jnp.where(_dot3(axis, pos21) < 0, -axis, axis)

    # axis in box 2 coordinates; a near-zero component (the first of the two, per box)
    # makes its support corner ambiguous: both signs are tried
    a2 = _mat_t_vec(rot, axis)
    amb_i1 = jnp.abs(_pick(axis, oi1)) < _SGNEPS
    amb_i2 = ~amb_i1 & (jnp.abs(_pick(axis, oi2)) < _SGNEPS)
    flip1 = jnp.where(amb_i1, oi1, jnp.where(amb_i2, oi2, 0.0)) > 0
    amb_j1 = jnp.abs(_pick(a2, oj1)) < _SGNEPS
    amb_j2 = ~amb_j1 & (jnp.abs(_pick(a2, oj2)) < _SGNEPS)
    flip2 = jnp.where(amb_j1, oj1, jnp.where(amb_j2, oj2, 0.0)) > 0

    d2 = jnp.sum(jnp.where(oj > 0, rot, 0.0), axis=1)
    b = _pick(d2, oi)
    denom = 1 - b * b
    half1 = _pick(size1, oi)
    half2 = _pick(size2, oj)

    # the (v1, v2) variants in C's loop order; a flip exists only for an ambiguous component
    v1 = np.array([0, 0, 1, 1], bool)[:, None]
    v2 = np.array([0, 1, 0, 1], bool)[:, None]
    valid = (~v1[:, 0] | jnp.any(flip1)) & (~v2[:, 0] | jnp.any(flip2))
    c1 = jnp.where(oi > 0, 0.0, jnp.where(axis >= 0, size1, -size1))
    c1 = jnp.where(v1 & flip1, -c1, c1)                                 # (4, 3)
    cc = jnp.where(oj > 0, 0.0, jnp.where(a2 >= 0, -size2, size2))
    cc = jnp.where(v2 & flip2, -cc, cc)
    c2 = _mat_vec(rot, cc) + pos21

    # closest points of the two edge segments (unit directions e_i and d2), clamped
    # into the segments, each clamp re-solving the other parameter
    ev = c2 - c1
    d1e = _pick(ev, oi)
    d2e = _dot3(d2, ev)
    far = denom < _MINVAL
    # N.B. one division per variant: XLA rewrites a division by a broadcast scalar as a
    # product with its reciprocal, one rounding off C's quotient
    safe = jnp.where(far, 1.0, denom)
    s = jnp.stack([(d1e[k] - b * d2e[k]) / safe for k in range(4)])
    s = jnp.where(far, 0.0, s)
    s = jnp.clip(s, -half1, half1)
    t = jnp.clip(b * s - d2e, -half2, half2)
    s = jnp.clip(d1e + b * t, -half1, half1)
    p1 = jnp.where(oi > 0, s[:, None], c1)     # c1[i] = 0: p1[i] = 0 + s
    p2 = c2 + d2 * t[:, None]
    gap = p2 - p1
    gap2 = _dot3(gap, gap)

    best_d2 = jnp.asarray(_MAXVAL, pos21.dtype)
    w1 = w2 = jnp.zeros((3,), pos21.dtype)
    for k in range(4):
        take = valid[k] & (gap2[k] < best_d2)
        best_d2 = jnp.where(take, gap2[k], best_d2)
        w1 = jnp.where(take, p1[k], w1)
        w2 = jnp.where(take, p2[k], w2)

    dist = _dot3(w2 - w1, axis)
    mid = 0.5 * (w1 + w2)
    return dist, mid, axis


def _clip_half_plane(poly, n, coord, sign, limit):
    """Port of clipHalfPlane (engine_collision_box.c): clips a polygon to sign * v[coord] <= limit.

    Args:
      poly: (MAXVERT, 3) vertices, the first n valid.
      n: int, vertex count.
      coord: 0 or 1 (static), the clipped coordinate.
      sign: +1.0 or -1.0 (static).
      limit: scalar.

    Returns:
      (poly, n) of the clipped polygon, in C's vertex order; unchanged when every
      vertex is inside (as C, which then leaves its buffers alone).
    """
    idx = jnp.arange(_MAXVERT)
    valid = idx < n
    d = sign * poly[:, coord] - limit
    all_inside = jnp.all(jnp.where(valid, d <= 0, True))
    # the edge from vertex k goes to k + 1, and from the last back to the first
    last = idx + 1 == n
    dq = jnp.where(last, d[0], jnp.roll(d, -1))
    q = jnp.where(last[:, None], poly[0], jnp.roll(poly, -1, axis=0))
    emit_p = valid & (d <= 0)
    cross = valid & (((d < 0) & (dq > 0)) | ((d > 0) & (dq < 0)))
    t = d / jnp.where(cross, d - dq, 1.0)
    x = poly + t[:, None] * (q - poly)

    # C appends p (if inside) then the crossing (if any) per edge, up to MAXVERT
    cand = jnp.stack([poly, x], axis=1).reshape(2 * _MAXVERT, 3)
    flags = jnp.stack([emit_p, cross], axis=1).reshape(2 * _MAXVERT)
    slot = jnp.cumsum(flags) - 1
    sel = flags[:, None] & (slot[:, None] == idx[None, :])   # (2 MAXVERT, MAXVERT)
    out = jnp.sum(jnp.where(sel[:, :, None], cand[:, None, :], 0.0), axis=0)
    nout = jnp.minimum(jnp.sum(flags), _MAXVERT)
    return jnp.where(all_inside, poly, out), jnp.where(all_inside, n, nout)


def _face_contacts(code, rot, pos21, pos12, info1, info2, margin):
    """Stage 2b of `mjc_BoxBox` (engine_collision_box.c): the face-clipping manifold.

    Long: a line-for-line port of MuJoCo C's code, kept in C's order so each
    line can be checked against the C source.

    Args:
      code: int, the winning face code 0..5 (others give a meaningless result).
      rot: (3, 3) box2 axes in box1 frame.
      pos21: (3,) box2 centre in box1 frame.
      pos12: (3,) box1 centre in box2 frame.
      info1: box 1 (pos (3,), mat (3, 3), size (3,)).
      info2: box 2, likewise.
      margin: scalar.

    Returns:
      dist: (NCON,) C's contact distances in C's order, FAR past the count.
      pos: (NCON, 3) world contact positions.
      normal: (3,) world normal from geom1 to geom2.
    """
    ref1 = code < 3
    a = jnp.clip(jnp.where(ref1, code, code - 3), 0, 2)
    sizeref = jnp.where(ref1, info1.size, info2.size)
    sizeinc = jnp.where(ref1, info2.size, info1.size)
    posref = jnp.where(ref1, info1.pos, info2.pos)
    matref = jnp.where(ref1, info1.mat, info2.mat)
    posoi = jnp.where(ref1, pos21, pos12)
    rinc = jnp.where(ref1, rot, rot.T)

    # reference coordinates reordered to C's projected (x, y, z) = (ax, ay, a)
    perm = _row(_PERM, a)
    sref = sizeref[perm]
    pinc = posoi[perm]
    rrow = rinc[perm]                  # rrow[r, k] = rinc(c_r, k)
    sgn = jnp.where(pinc[2] >= 0, 1.0, -1.0)

    # incident face: the first of the incident axes most aligned with the reference normal
    binc = jnp.array(0, jnp.int32)
    absn = jnp.abs(rrow[2])
    for k in range(1, 3):
        binc = jnp.where(absn[k] > _pick(absn, _row(_ONEHOT, binc)), k, binc)
    cyc = _row(_CYCLE, binc)    # (binc, bu, bv)
    r3 = rrow[:, cyc]
    sinc = sizeinc[cyc]
    tinc = jnp.where(sgn * r3[2, 0] > 0, -1.0, 1.0)

    # face centre and half-edge offsets; z is the height above the reference face
    cx = pinc + tinc * sinc[0] * r3[:, 0]
    du = sinc[1] * r3[:, 1]
    dv = sinc[2] * r3[:, 2]
    cx = cx.at[2].set(sgn * cx[2] - sref[2])
    du = du.at[2].set(du[2] * sgn)
    dv = dv.at[2].set(dv[2] * sgn)
    corners = (cx + _CORNER_SU[:, None] * du) + _CORNER_SV[:, None] * dv
    poly = jnp.concatenate([corners, jnp.zeros((_MAXVERT - 4, 3), corners.dtype)])
    n = jnp.array(4, jnp.int32)

    poly, n = _clip_half_plane(poly, n, 0, 1.0, sref[0])
    poly, n = _clip_half_plane(poly, n, 0, -1.0, sref[0])
    poly, n = _clip_half_plane(poly, n, 1, 1.0, sref[1])
    poly, n = _clip_half_plane(poly, n, 1, -1.0, sref[1])

    # accept vertices in the margin band unless near an earlier accepted one
    dupe2 = _DUPEPS * (sref[0] * sref[0] + sref[1] * sref[1])
    idx = jnp.arange(_MAXVERT)
    inband = (idx < n) & ~(poly[:, 2] > margin)
    dx = poly[:, None, 0] - poly[None, :, 0]
    dy = poly[:, None, 1] - poly[None, :, 1]
    close = dx * dx + dy * dy < dupe2
    accepted = jnp.zeros((_MAXVERT,), bool)
    for k in range(_MAXVERT):
        accepted = jnp.where(idx == k, inband[k] & ~jnp.any(accepted & close[:, k]), accepted)

    # positions on the clipped polygon, midway between the reference plane and the
    # incident surface, back in the reference box's own axis order
    posc = jnp.stack([poly[:, 0], poly[:, 1], sgn * (sref[2] + 0.5 * poly[:, 2])], axis=1)
    posc = posc[:, _row(_UNPERM, a)]
    pos_all = _mat_vec(matref, posc) + posref

    slot = jnp.cumsum(accepted) - 1
    sel = accepted[:, None] & (slot[:, None] == jnp.arange(NCON)[None, :])  # (MAXVERT, NCON)
    dist = jnp.where(jnp.any(sel, axis=0),
                     jnp.sum(jnp.where(sel, poly[:, 2:3], 0.0), axis=0), FAR)
    pos = jnp.sum(jnp.where(sel[:, :, None], pos_all[:, None, :], 0.0), axis=0)

    nsign = jnp.where(ref1, sgn, -sgn)
    normal = nsign * jnp.sum(jnp.where(_row(_ONEHOT, a) > 0, matref, 0.0), axis=1)
    return dist, pos, normal


@collider(NCON)
def box_box(info1, info2, margin):
    """Port of `mjc_BoxBox` (engine_collision_box.c): box-box contacts, up to 8.

    Args:
      info1: box 1 (pos (3,), mat (3, 3), size (3,)).
      info2: box 2, likewise.
      margin: scalar, the pair's margin (C's margin + gap).

    Returns:
      dist: (8,) signed distances, C's contacts first in C's order, FAR after.
      pos: (8, 3) contact positions.
      frame: (8, 3, 3) contact frames, row 0 the normal from box 1 to box 2.
    """
    pos1, mat1, size1 = info1.pos, info1.mat, info1.size
    pos2, mat2, size2 = info2.pos, info2.mat, info2.size
    pos21 = _mat_t_vec(mat1, pos2 - pos1)
    pos12 = _mat_t_vec(mat2, pos1 - pos2)
    # mju_mulMatTMat3: rot[i, j] = sum_k mat1[k, i] mat2[k, j], k in order
    rot = (mat1[0][:, None] * mat2[0][None, :] + mat1[1][:, None] * mat2[1][None, :]
           + mat1[2][:, None] * mat2[2][None, :])

    septol = margin + _SEPEPS * (size1[0] + size1[1] + size1[2]
                                 + size2[0] + size2[1] + size2[2])
    separated, code = _separating_axis(rot, pos21, pos12, size1, size2, septol)
    contact = ~separated & (code >= 0)
    is_edge = code >= 6

    edist, emid, eaxis = _edge_contact(code, rot, pos21, size1, size2)
    edge_ok = contact & is_edge & ~(edist > septol)
    epos = _mat_vec(mat1, emid) + pos1
    enormal = _mat_vec(mat1, eaxis)

    fdist, fpos, fnormal = _face_contacts(code, rot, pos21, pos12, info1, info2, margin)
    face_ok = contact & ~is_edge

    first = jnp.arange(NCON) == 0
    dist = jnp.where(is_edge, jnp.where(first & edge_ok, edist, FAR),
                     jnp.where(face_ok, fdist, FAR))
    pos = jnp.where(is_edge, jnp.where(first[:, None], epos, 0.0), fpos)
    normal = jnp.where(is_edge, enormal, fnormal)
    frame = jnp.broadcast_to(make_frame(normal), (NCON, 3, 3))
    return dist, pos, frame


PORTED[(int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_BOX))] = box_box
