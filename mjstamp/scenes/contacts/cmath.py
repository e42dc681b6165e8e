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
