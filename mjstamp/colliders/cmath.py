"""C's small vector helpers in JAX, rounding as C rounds (the ports share them).

MuJoCo C sums dot products and matrix-vector products in index order and
multiplies by 1/|v| rather than dividing; the ports keep that, so that they
agree with C to the last bit where XLA does not fuse the arithmetic (to about
1e-16 where it does). Square roots and divisions are guarded so that reverse-
mode derivatives stay finite at 0 (the double-where trick).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

MINVAL = mujoco.mjMINVAL  # 1e-15: C's "treat as zero"


def dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """C's `mju_dot3`, summed in C's order."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def matvec(mat: jax.Array, v: jax.Array) -> jax.Array:
    """C's `mju_mulMatVec3`: mat (3, 3) @ v (3,), summed in C's order."""
    return mat[:, 0] * v[0] + mat[:, 1] * v[1] + mat[:, 2] * v[2]


def mat_t_vec(mat: jax.Array, v: jax.Array) -> jax.Array:
    """C's `mju_mulMatTVec3`: mat (3, 3)ᵀ @ v (3,), summed in C's order."""
    return mat[0] * v[0] + mat[1] * v[1] + mat[2] * v[2]


def cross(a: jax.Array, b: jax.Array) -> jax.Array:
    """C's `mju_cross`."""
    return jnp.stack([a[1] * b[2] - a[2] * b[1],
                      a[2] * b[0] - a[0] * b[2],
                      a[0] * b[1] - a[1] * b[0]])


def sqrt(x: jax.Array) -> jax.Array:
    """√x with a zero (not infinite) derivative at x = 0."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def normalize(v: jax.Array) -> tuple[jax.Array, jax.Array]:
    """C's `mju_normalize3` (engine_util_blas.c): (unit v, |v|), (1, 0, 0) when |v| < mjMINVAL.

    Args:
      v: (3,) vector.

    Returns:
      (3,) unit vector and () the norm of v.
    """
    norm = sqrt(dot(v, v))
    small = norm < MINVAL
    # N.B. C multiplies by 1/norm (not divides): kept for the last bit.
    inv = 1.0 / jnp.where(small, 1.0, norm)
    unit = jnp.where(small, jnp.array([1.0, 0.0, 0.0], v.dtype), v * inv)
    return unit, norm


def frame(normal: jax.Array, tangent: jax.Array) -> jax.Array:
    """C's `mju_makeFrame` (engine_util_spatial.c) of a contact's normal and tangent.

    `mj_setContact` (engine_collision_driver.c) copies the collider's normal and
    tangent into the frame's first two rows and completes it here.

    Args:
      normal: (3,) the contact normal.
      tangent: (3,) the collider's tangent; unused when |tangent|² < 0.25.

    Returns:
      (3, 3) frame: normal, first tangent, second tangent (rows).
    """
    x, _ = normalize(normal)
    mid = (x[1] < 0.5) & (x[1] > -0.5)
    default = jnp.where(mid, jnp.array([0.0, 1.0, 0.0]), jnp.array([0.0, 0.0, 1.0]))
    y = jnp.where(dot(tangent, tangent) < 0.25, default.astype(x.dtype), tangent)
    y, _ = normalize(y - x * dot(x, y))
    return jnp.stack([x, y, cross(x, y)])


# Scalar forms: a 3-vector as a tuple of three scalars (under vmap, three (n,)
# arrays). Code written on them compiles to elementwise operations only, which
# XLA fuses into a few loops; indexing a (3,) array instead costs a slice in
# the forward pass and a pad plus an add in the reverse one, each its own
# kernel. The products are rounded before any sum (`mul`), so that these agree
# with C to the last bit.


def mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """The product a * b, rounded on its own before any sum it enters, as C rounds it.

    N.B. XLA lets LLVM contract ``a * b + c`` into one fused multiply-add (on
    CPU and GPU alike), which rounds once where C (built without FMA) rounds
    twice: the last-bit differences flip C's ties and thresholds on
    axis-aligned poses. LLVM does not contract through the select.
    """
    p = a * b
    return jnp.where(p == p, p, 0.0)


def unpack(x: jax.Array) -> tuple[jax.Array, ...]:
    """The components of x (any shape, row-major) as scalars.

    N.B. one split, whose transpose is one concatenate (indexing x[i] would
    transpose to a pad per component). Pass the result through `stage`, so
    that XLA does not fuse the whole reverse pass into that concatenate.
    """
    flat = x.reshape(-1)
    return tuple(p.reshape(()) for p in jnp.split(flat, flat.shape[0]))


def opaque_one(x: jax.Array) -> jax.Array:
    """1.0, computed from x so that XLA cannot know it: `stage`'s divisor.

    N.B. x must be data XLA cannot fold (poses, not model constants that a
    compiled function may close over; a sum of both geoms' positions, so that
    one moving geom suffices): where XLA can fold it, the stages vanish (the
    results stay the same, but the compiled code grows manyfold, and its
    compilation with it). A NaN or infinite x makes everything staged NaN.
    """
    # N.B. a quotient, so that XLA computes it once (not once per stage)
    y = 1.0 + 0.0 * jax.lax.stop_gradient(x)
    return y / y


def stage(values, one: jax.Array):
    """The values (a pytree of arrays), unchanged, computed once: a boundary for XLA's fusion.

    N.B. XLA's CPU fusion copies a cheap elementwise producer into each of its
    consumers; on long elementwise graphs such as the scalar forms' that
    recomputes shared work many times over (40 times the work in one case).
    It does not copy an expensive operation (a division) that has several
    consumers: dividing by 1 (`opaque_one`, which XLA cannot fold away) is
    exact, and makes the values (and, in the reverse pass, their cotangents)
    computed once and read by every consumer. `jax.lax.optimization_barrier`
    does not serve: XLA removes it before fusion.

    Args:
      values: a pytree of float, int or bool arrays.
      one: `opaque_one(...)`, a () float array.

    Returns:
      values, the same bits.
    """
    leaves, tree = jax.tree_util.tree_flatten(values)
    leaves = [jnp.asarray(v) for v in leaves]
    if not leaves:
        return values
    # N.B. one division of all the values packed in one vector (ints and bools as
    # floats: exact), so one kernel: XLA's CPU backend runs each fusion as a
    # kernel of its own, and at small batches their launches dominate.
    packed = jnp.stack([v.astype(one.dtype) for v in leaves]) / one
    out = [p.reshape(()).astype(v.dtype) if v.dtype != one.dtype else p.reshape(())
           for p, v in zip(jnp.split(packed, len(leaves)), leaves, strict=True)]
    return jax.tree_util.tree_unflatten(tree, out)


def dot_s(a, b):
    """C's `mju_dot3` of scalar triples, summed in C's order, products rounded."""
    return mul(a[0], b[0]) + mul(a[1], b[1]) + mul(a[2], b[2])


def mat_vec_s(mat, v):
    """C's `mji_mulMatVec3` of scalar triples: mat (rows of scalars) @ v."""
    return tuple(mul(row[0], v[0]) + mul(row[1], v[1]) + mul(row[2], v[2]) for row in mat)


def mat_t_vec_s(mat, v):
    """C's `mji_mulMatTVec3` of scalar triples: matᵀ (rows of scalars) @ v."""
    return tuple(mul(mat[0][c], v[0]) + mul(mat[1][c], v[1]) + mul(mat[2][c], v[2])
                 for c in range(3))


def normalize_s(v):
    """C's `mju_normalize3` of a scalar triple: (unit v, |v|), (1, 0, 0) when |v| < mjMINVAL."""
    norm = sqrt(dot_s(v, v))
    small = norm < MINVAL
    inv = 1.0 / jnp.where(small, 1.0, norm)
    unit = tuple(jnp.where(small, e, c * inv) for c, e in zip(v, (1.0, 0.0, 0.0), strict=True))
    return unit, norm


def frame_s(normal) -> jax.Array:
    """C's `mju_makeFrame` of a normal with no tangent, from a scalar triple.

    As `frame(normal, 0)`, with every product rounded as C rounds it.

    Args:
      normal: the contact normal, a triple of scalars.

    Returns:
      (3, 3) frame: normal, first tangent, second tangent (rows).
    """
    x, _ = normalize_s(normal)
    mid = (x[1] < 0.5) & (x[1] > -0.5)
    # y = (0, 1, 0) or (0, 0, 1); C's x . y is x[1] or x[2] (products by 0 and 1 are exact)
    y = (jnp.zeros_like(x[0]), jnp.where(mid, 1.0, 0.0), jnp.where(mid, 0.0, 1.0))
    d = jnp.where(mid, x[1], x[2])
    y, _ = normalize_s(tuple(yk - mul(xk, d) for xk, yk in zip(x, y, strict=True)))
    z = (mul(x[1], y[2]) - mul(x[2], y[1]), mul(x[2], y[0]) - mul(x[0], y[2]),
         mul(x[0], y[1]) - mul(x[1], y[0]))
    return jnp.stack([jnp.stack(x), jnp.stack(y), jnp.stack(z)])
