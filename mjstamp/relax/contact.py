"""Soft, differentiable summaries of a rollout: contact indicators and softmins.

Both are a softmax-weighted sum over the time steps of a trajectory up to the
first contact t_c, so they share one masked helper. Time runs along the last
axis; leading axes (particles, walls) broadcast.

References:
  STAMP App. B-B (soft wall-hit indicators w_i) and App. B-D (aim loss).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = [
    "first_contact_mask",
    "soft_contact_indicator",
    "softmin_aggregate",
]


def first_contact_mask(contact: jax.Array) -> jax.Array:
    """Marks the steps t = 1..t_c, where t_c is the first step in contact.

    Args:
      contact: (..., T) bool array, True where the bodies touch.

    Returns:
      (..., T) bool array, True up to and including the first True of
      `contact`; all True where `contact` never holds (t_c = T).

    References:
      STAMP App. B-B and B-D (sums run over t = 1..t_c).
    """
    contact = jnp.asarray(contact, dtype=bool)
    # Contacts strictly before t: zero exactly on the steps up to t_c.
    before = jnp.cumsum(contact, axis=-1) - contact
    return before == 0


def _masked_softmax_sum(
    values: jax.Array, logits: jax.Array, mask: jax.Array | None
) -> jax.Array:
    """Σ_t σ_t values_t with σ = softmax(logits) over the steps where mask holds."""
    if mask is None:
        return jnp.sum(jax.nn.softmax(logits, axis=-1) * values, axis=-1)
    mask = jnp.broadcast_to(jnp.asarray(mask, dtype=bool), jnp.shape(logits))
    # N.B. masked entries go to -inf *before* the softmax and their values to 0,
    # so neither a masked value nor its gradient can leak a NaN into the sum.
    sigma = jax.nn.softmax(jnp.where(mask, logits, -jnp.inf), axis=-1)
    return jnp.sum(sigma * jnp.where(mask, values, 0.0), axis=-1)


def soft_contact_indicator(
    signed_distance: jax.Array,
    *,
    alpha: float,
    beta: float,
    mask: jax.Array | None = None,
) -> jax.Array:
    """Soft indicator that a body touched a surface during steps 1..t_c.

    d_t = −α·signed_distance_t + β,  σ = softmax(d) over t ≤ t_c,
    w = sigmoid(Σ_t σ_t d_t).

    w is near 1 when the body came within about β/α of the surface (or
    penetrated it) at some step, and near 0 when it stayed far; it is smooth in
    the trajectory, hence in θ through a differentiable rollout.

    Args:
      signed_distance: (..., T) signed distances body–surface over time,
        negative in penetration. E.g. (n, 4, T) for four walls.
      alpha: scale α > 0.
      beta: shift β.
      mask: optional bool array broadcastable to (..., T), True on the steps
        to include (t ≤ t_c), e.g. `first_contact_mask(...)[..., None, :]`.
        Each row needs at least one True step. None: all steps.

    Returns:
      (...) array of indicators in (0, 1).

    References:
      STAMP App. B-B (task variables w_{1:4} as functions of velocity).
    """
    if not isinstance(alpha, jax.Array) and not alpha > 0:
        raise ValueError(f"alpha must be > 0; got {alpha!r}")
    d = -alpha * jnp.asarray(signed_distance) + beta
    return jax.nn.sigmoid(_masked_softmax_sum(d, d, mask))


def softmin_aggregate(
    values: jax.Array,
    *,
    mask: jax.Array | None = None,
    temperature: float = 1.0,
) -> jax.Array:
    """Softmin-weighted sum Σ_t σ_t L_t with σ = softmax(−L / temperature).

    A smooth stand-in for min_t L_t (it tends to it as temperature → 0) whose
    gradient reaches every step, weighted towards the smallest values.

    Args:
      values: (..., T) per-step losses L_t, e.g. the time-stamped aim loss.
      mask: optional bool array broadcastable to (..., T), True on the steps
        to include (t ≤ t_c). Each row needs at least one True step.
      temperature: > 0; STAMP uses 1.

    Returns:
      (...) array.

    References:
      STAMP App. B-D (L_aim = Σ_{t≤t_c} σ_t L_aim^(t)).
    """
    if not isinstance(temperature, jax.Array) and not temperature > 0:
        raise ValueError(f"temperature must be > 0; got {temperature!r}")
    values = jnp.asarray(values)
    return _masked_softmax_sum(values, -values / temperature, mask)
