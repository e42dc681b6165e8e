"""Per-particle Jacobians of a batched, particle-separable function in one pass.

A batched function f : (n, d) -> (n, m) is *particle-separable* when row i of
the output depends on row i of the input only (a vmapped rollout is). Its
Jacobian is then block diagonal, and all n blocks (m, d) come from one forward
pass plus either m batched pullbacks (reverse mode) or d batched pushforwards
(forward mode): the cost is that of O(min(m, d)) evaluations of f over the whole
batch, never n separate ones.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import jax
import jax.numpy as jnp

JacobianMode = Literal["auto", "fwd", "rev"]
_MODES = ("auto", "fwd", "rev")


def check_mode(mode: str, name: str = "jacobian") -> None:
    """Raises ValueError unless mode is one of 'auto', 'fwd', 'rev'."""
    if mode not in _MODES:
        raise ValueError(f"{name} must be one of {_MODES}; got {mode!r}")


def value_and_batched_jacobian(
    fn: Callable[[jax.Array], jax.Array],
    x: jax.Array,
    mode: JacobianMode = "auto",
    *,
    has_aux: bool = False,
):
    """Evaluates a particle-separable f and its per-particle Jacobians.

    Args:
      fn: batched function (n, d) -> (n, m), row i depending on x[i] only;
        with `has_aux`, (n, d) -> ((n, m), aux), aux not differentiated.
      x: (n, d) particles.
      mode: 'rev' (one forward pass, m pullbacks), 'fwd' (one forward pass
        carrying d tangents) or 'auto' (whichever of m and d is smaller; reads
        m with an abstract trace of fn, which compiles nothing but traces fn a
        second time: pass 'fwd' or 'rev' when tracing fn is expensive).
      has_aux: fn also returns a pytree computed from the same pass.

    Returns:
      (out, jac): (n, m) values and (n, m, d) Jacobians, jac[i] = ∂f(x)[i] / ∂x[i];
      with `has_aux`, ((out, aux), jac).
    """
    check_mode(mode)
    n, d = x.shape
    main = (lambda z: fn(z)[0]) if has_aux else fn
    if mode == "auto":
        m = jax.eval_shape(main, x).shape[-1]
        mode = "rev" if m <= d else "fwd"
    if mode == "rev":
        if has_aux:
            out, pullback, aux = jax.vjp(fn, x, has_aux=True)
        else:
            (out, pullback), aux = jax.vjp(fn, x), None
        m = out.shape[-1]
        # Cotangent k selects output k of every particle at once.
        cotangents = jnp.broadcast_to(
            jnp.eye(m, dtype=out.dtype)[:, None, :], (m, n, m)
        )
        (jac_t,) = jax.vmap(pullback)(cotangents)  # (m, n, d)
        jac = jnp.swapaxes(jac_t, 0, 1)
        return ((out, aux), jac) if has_aux else (out, jac)
    # vmap over the tangents only: the primal does not depend on them, so it is
    # computed once, unbatched, and only the tangent arithmetic is d-wide.
    tangents = jnp.broadcast_to(jnp.eye(d, dtype=x.dtype)[:, None, :], (d, n, d))
    if has_aux:
        # N.B. the aux's tangents are computed and dropped: no pass of its own.
        def push(t):
            (out, aux), (jac_t, _) = jax.jvp(fn, (x,), (t,))
            return (out, aux), jac_t

        (out, aux), jac_t = jax.vmap(push, out_axes=(None, 0))(tangents)
        return (out, aux), jnp.moveaxis(jac_t, 0, -1)
    out, jac_t = jax.vmap(lambda t: jax.jvp(fn, (x,), (t,)), out_axes=(None, 0))(
        tangents
    )
    return out, jnp.moveaxis(jac_t, 0, -1)  # (d, n, m) -> (n, m, d)
