"""The guards' decisions applied to a step's state: particles and optimizer rows, on the host.

`mjstamp.svgd.guards` decides (pure numpy); this module writes the decisions
into the `SVGDState` once per iteration, each array keeping its sharding.
"""

from __future__ import annotations

import jax
import numpy as np
import optax

from mjstamp.svgd import guards
from mjstamp.svgd._host import fetch, put, set_rows
from mjstamp.svgd.steps import SVGDState


def _edited(after: SVGDState, host, backed: np.ndarray, drawn: list) -> SVGDState:
    """The step's state with the guards' decisions applied, the particles put back once.

    host: (n, d) particles after backtracking, or None where it changed none;
    backed: rows taken back (their optimizer's first moment zeroed); drawn:
    [(rows, fresh particles)] re-drawn, in order (every moment of theirs zeroed).
    """
    if host is None and not drawn:
        return after
    if host is None:
        host = np.array(fetch(after.particles))
    for idx, rows in drawn:
        host[idx] = rows  # N.B. `host` is this function's own copy
    opt_state = after.opt_state
    if backed.size:
        opt_state = _zero_rows(opt_state, backed, host.shape, first_moment_only=True)
    if drawn:
        # Adam's moments of a re-drawn particle start from zero.
        opt_state = _zero_rows(opt_state, np.concatenate([idx for idx, _ in drawn]), host.shape)
    return after._replace(particles=put(host, after.particles), opt_state=opt_state)


def _best(particles: jax.Array, guard: guards.BacktrackState | None) -> jax.Array:
    """`particles` with each one backtracking has a scored point for replaced by that point."""
    if guard is None:
        return particles
    rows, theta = guards.backtrack_best(guard)
    return set_rows(particles, rows, theta) if rows.size else particles


def _zero_rows(opt_state, idx: np.ndarray, shape: tuple, *, first_moment_only: bool = False):
    """The optimizer state with rows `idx` of every (n, d) leaf (Adam's moments) zeroed.

    first_moment_only: zero only Adam's μ rows and keep ν (a step taken back).
    N.B. Adam's step count is one scalar for all particles, so zeroing both
    moments at count c makes the next updates (1-β₁)/(1-β₁^c)/√((1-β₂)/(1-β₂^c))
    times the learning rate, up to ~3x for large c; with ν kept (it remembers
    the steep gradient the failed step met) the restart is gentler than the
    step taken back. An optimizer without an Adam state has every (n, d) row zeroed.
    """

    def reset(leaf):
        if hasattr(leaf, "shape") and leaf.shape == shape:
            return set_rows(leaf, idx, 0)
        return leaf

    if first_moment_only:
        adam = lambda x: isinstance(x, optax.ScaleByAdamState)  # noqa: E731
        if any(adam(x) for x in jax.tree.leaves(opt_state, is_leaf=adam)):
            return jax.tree.map(
                lambda x: x._replace(mu=jax.tree.map(reset, x.mu)) if adam(x) else x,
                opt_state, is_leaf=adam)
    return jax.tree.map(reset, opt_state)
