"""Relaxations of discrete task variables: Γ, its surrogate Γ̃ and the base p₀.

A task plan 𝒜_{1:K} is K one-hot vectors of m entries each. STAMP lifts it to
x ∈ ℝ^{mK}: Γ(x) takes the argmax of each block of m entries and Γ̃(x) the
softmax of each block. With the uniform base p₀ on [-u, u]^{mK}, Γ splits p₀
into m^K parts of equal mass, which is what discrete SVGD needs.

References:
  STAMP §IV-A (Γ, Γ̃ and eq. (6)); App. A (uniform base and even partitioning);
  eq. (2) (the even-partition condition).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = [
    "hard_onehot",
    "soft_onehot",
    "block_labels",
    "uniform_base_sample",
]


def _blocks(x: jax.Array, m: int, name: str = "x") -> jax.Array:
    """Reshapes (..., m*K) to (..., K, m), checking that m divides the last axis."""
    if not isinstance(m, int) or m < 1:
        raise ValueError(f"m (entries per block) must be an integer >= 1; got {m!r}")
    x = jnp.asarray(x)
    if x.ndim < 1 or x.shape[-1] % m != 0:
        raise ValueError(
            f"{name} must have a last axis of m*K entries with m={m}; "
            f"got shape {x.shape}"
        )
    return x.reshape(*x.shape[:-1], x.shape[-1] // m, m)


def block_labels(x: jax.Array, m: int) -> jax.Array:
    """The index of the largest entry of each block: the symbol Γ(x) encodes.

    Args:
      x: (..., m*K) array of relaxed task variables.
      m: number of symbols per block (|𝒵|).

    Returns:
      (..., K) int array with values in [0, m). Ties go to the lowest index.

    References:
      STAMP §IV-A, footnote 2.
    """
    return jnp.argmax(_blocks(x, m), axis=-1)


def hard_onehot(x: jax.Array, m: int) -> jax.Array:
    """Γ: a one-hot vector per block of m entries.

    Γ is piecewise constant: its gradient is zero almost everywhere, so it only
    decodes plans and evaluates the discrete target p(Γ(x)); Γ̃ carries gradients.

    Args:
      x: (..., m*K) array of relaxed task variables.
      m: number of symbols per block (|𝒵|).

    Returns:
      (..., m*K) array of 0s and 1s, exactly one 1 per block, dtype of x.

    References:
      STAMP §IV-A and App. A (the map Γ : ℝ^{mK} → 𝒵^K).
    """
    xb = _blocks(x, m)
    onehot = jax.nn.one_hot(jnp.argmax(xb, axis=-1), m, dtype=xb.dtype)
    return onehot.reshape(jnp.shape(x))


def soft_onehot(x: jax.Array, m: int, temperature: float = 1.0) -> jax.Array:
    """Γ̃: a softmax per block of m entries, softmax(x_block / temperature).

    Sums to 1 over each block, and tends to Γ(x) as temperature → 0 (for x with
    no ties within a block).

    Args:
      x: (..., m*K) array of relaxed task variables.
      m: number of symbols per block (|𝒵|).
      temperature: softmax temperature, > 0. STAMP uses 1.

    Returns:
      (..., m*K) array with entries in (0, 1), each block summing to 1.

    References:
      STAMP §IV-A and App. A (the surrogate Γ̃).
    """
    if not isinstance(temperature, jax.Array) and not temperature > 0:
        raise ValueError(f"temperature must be > 0; got {temperature!r}")
    xb = _blocks(x, m)
    return jax.nn.softmax(xb / temperature, axis=-1).reshape(jnp.shape(x))


def uniform_base_sample(
    key: jax.Array, n: int, dim: int, u: float = 1.0, dtype=jnp.float32
) -> jax.Array:
    """Draws n samples of the base distribution p₀ = unif([-u, u]^dim).

    With dim = m*K, Γ maps each of the m^K one-hot codes to a 1/m^K share of
    these samples (App. A); this is the random initialisation of the discrete
    part of θ.

    Args:
      key: PRNG key.
      n: number of samples, >= 1.
      dim: dimension of each sample (m*K for task variables), >= 1.
      u: half-width of the box, > 0.
      dtype: floating dtype of the result.

    Returns:
      (n, dim) array with entries in [-u, u).

    References:
      STAMP App. A-A (the base distribution p₀).
    """
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an integer >= 1; got {n!r}")
    if not isinstance(dim, int) or dim < 1:
        raise ValueError(f"dim must be an integer >= 1; got {dim!r}")
    if not u > 0:
        raise ValueError(f"u (half-width of the base box) must be > 0; got {u!r}")
    return jax.random.uniform(key, (n, dim), dtype=dtype, minval=-u, maxval=u)
