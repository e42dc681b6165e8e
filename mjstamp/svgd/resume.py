"""A run between two iterations: what the loop carries, and its snapshot to continue from.

`_Carry` is what changes from one iteration to the next besides the step's
`SVGDState` (the PRNG key, the records, the guards' states); a `LoopSnapshot`
is both on the host, for a checkpoint. `snapshot` builds one, `restore` and
`_resumed` turn one back into a carry and a state.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp.svgd import guards
from mjstamp.svgd._host import fetch
from mjstamp.svgd.guards import PHASE_SGD, PHASE_SVGD
from mjstamp.svgd.steps import SVGDState

__all__ = ["LoopSnapshot"]


class LoopSnapshot(NamedTuple):
    """Everything `run_stamp` needs to continue a run after an iteration (host values).

    A checkpoint holds one (`run_stamp(checkpoint=...)` hands them out,
    `run_stamp(resume=...)` continues from one); continuing gives the same
    iterations, bit for bit, as a run never stopped (the steps are
    deterministic and every PRNG key comes from `key_data`).

    Attributes:
      phase: PHASE_SVGD or PHASE_SGD, the phase of the last iteration done.
      iteration: iterations done in that phase (>= 1).
      particles: (n, d) particles after it.
      opt_leaves: the leaves of that phase's optimizer state
        (`jax.tree.leaves`), in order; the tree comes from `init`.
      key_data: `jax.random.key_data` of the loop's PRNG key.
      rows: the `StampDiagnostics` row of every iteration so far, both phases
        (each field that iteration's value).
      svgd_particles: (n, d) particles at the end of SVGD; None in SVGD.
      svgd_converged: whether SVGD ended by the convergence test; None in SVGD.
      counters: the re-draw counters ({"stalled", "rescued", "failing",
        "nonfinite_redrawn"}: (n,) ints each, and "fresh": the indices re-drawn
        by the last re-draw, absent in older snapshots) and the backtracking state
        ({"guard_theta": (n, d) last accepted particles, "guard_logp": (n,)
        their log densities (NaN: none yet), "guard_scale": (n,) step scales}).
    """

    phase: int
    iteration: int
    particles: np.ndarray
    opt_leaves: list
    key_data: np.ndarray
    rows: list
    svgd_particles: np.ndarray | None
    svgd_converged: bool | None
    counters: dict


class _Carry(NamedTuple):
    """What the loop carries from one iteration to the next, across both phases.

    Attributes:
      key: the loop's PRNG key (every key a step or a re-draw gets comes from it).
      rows: the `StampDiagnostics` row of every iteration so far, both phases.
      rescue: the re-draw counters (`guards.RescueState`).
      backtrack: `guards.BacktrackState` of the phase, or None (backtrack off).
      svgd_end: (particles (n, d) host array, converged) once SVGD is over.
    """

    key: jax.Array
    rows: tuple
    rescue: guards.RescueState
    backtrack: guards.BacktrackState | None
    svgd_end: tuple = (None, None)

    @classmethod
    def init(cls, key: jax.Array, n: int, *, backtrack: bool) -> _Carry:
        return cls(key, (), guards.rescue_init(n),
                   guards.backtrack_init(n) if backtrack else None)

    def split(self) -> tuple[_Carry, jax.Array]:
        """(carry with the key moved on, a fresh subkey)."""
        key, sub = jax.random.split(self.key)
        return self._replace(key=key), sub


def snapshot(phase: int, t: int, state: SVGDState, carry: _Carry) -> LoopSnapshot:
    """The `LoopSnapshot` after iteration t of `phase` (fetches the state to the host)."""
    particles, leaves, key_data = fetch(
        (state.particles, jax.tree.leaves(state.opt_state), jax.random.key_data(carry.key))
    )
    return LoopSnapshot(
        phase=phase, iteration=t, particles=np.asarray(particles),
        opt_leaves=[np.asarray(leaf) for leaf in leaves], key_data=np.asarray(key_data),
        rows=list(carry.rows), svgd_particles=carry.svgd_end[0],
        svgd_converged=carry.svgd_end[1], counters=_counters(carry),
    )


def check_snapshot(snap: LoopSnapshot, shape: tuple[int, int]) -> None:
    """Raises ValueError unless `snap` is a `LoopSnapshot` that can continue a run of `shape`."""
    if not isinstance(snap, LoopSnapshot):
        raise ValueError(f"resume must be a LoopSnapshot; got {type(snap).__name__}")
    if snap.phase not in (PHASE_SVGD, PHASE_SGD) or np.shape(snap.particles) != shape:
        raise ValueError(f"resume: a snapshot of phase {snap.phase} with particles "
                         f"{np.shape(snap.particles)} cannot continue a run of {shape}")


def restore(snap: LoopSnapshot, shape: tuple[int, int], carry: _Carry) -> _Carry:
    """The carry of a checked snapshot: its key, records and counters (its state: `_resumed`)."""
    c = snap.counters
    rescue = guards.RescueState(
        *(np.array(c[k]) for k in ("stalled", "rescued", "failing", "nonfinite_redrawn")),
        fresh=np.array(c.get("fresh", guards.RescueState._field_defaults["fresh"]), int))
    backtrack = None if carry.backtrack is None else _backtrack_from(c, shape[0])
    return carry._replace(
        key=jax.random.wrap_key_data(jnp.asarray(snap.key_data)), rows=tuple(snap.rows),
        rescue=rescue, backtrack=backtrack)


def _resumed(state: SVGDState, resume: LoopSnapshot) -> SVGDState:
    """`state` (a phase's fresh one) with a snapshot's particles and optimizer state."""
    leaves, tree = jax.tree.flatten(state.opt_state)
    if len(leaves) != len(resume.opt_leaves):
        raise ValueError(f"resume: {len(resume.opt_leaves)} optimizer-state leaves, "
                         f"this run's optimizer has {len(leaves)}")
    opt_state = jax.tree.unflatten(tree, [
        jnp.asarray(v, dtype=leaf.dtype)
        for v, leaf in zip(resume.opt_leaves, leaves, strict=True)])
    return state._replace(particles=jnp.asarray(resume.particles, state.particles.dtype),
                          opt_state=opt_state)


def _counters(carry: _Carry) -> dict:
    """A snapshot's counters: the re-draw counters and the backtracking state."""
    r = carry.rescue
    counters = {"stalled": r.stalled, "rescued": r.rescued, "failing": r.failing,
                "nonfinite_redrawn": r.nonfinite_redrawn, "fresh": r.fresh}
    g = carry.backtrack
    if g is not None:
        theta = np.full((r.stalled.size, 0), np.nan) if g.theta is None else g.theta
        counters.update(guard_theta=theta, guard_logp=g.logp, guard_peak=g.peak,
                        guard_scale=g.scale)
    # N.B. copies: a snapshot kept by the caller must not share arrays with the run
    return {k: np.array(v) for k, v in counters.items()}


def _backtrack_from(counters: dict, n: int) -> guards.BacktrackState:
    """The backtracking state of a snapshot's counters (a fresh one if it has none)."""
    if "guard_scale" not in counters:
        return guards.backtrack_init(n)
    theta = np.array(counters["guard_theta"], dtype=float)
    logp = np.array(counters["guard_logp"], dtype=float)
    return guards.BacktrackState(
        theta=theta if theta.size else None, logp=logp,
        peak=np.array(counters.get("guard_peak", logp), dtype=float),
        scale=np.array(counters["guard_scale"], dtype=float))
