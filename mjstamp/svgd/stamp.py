"""The STAMP loop: (discrete) SVGD until converged, then SGD until converged.

Each phase compiles one step function (`jax.jit`, traced once) and drives it
from a Python loop, so a progress bar and the convergence test run between
steps. The switch from SVGD to SGD (Algorithm 1 line 7), and the end of SGD,
use the test of `has_converged`, with an iteration cap per phase as fallback.

References:
  STAMP Algorithm 1; §IV-A (inference by SVGD), §IV-B (refinement by SGD).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from mjstamp.errors import MjstampError
from mjstamp.progress import QUIET, Progress, ProgressLike
from mjstamp.svgd import guards
from mjstamp.svgd._checks import check_particles
from mjstamp.svgd._jacobian import JacobianMode, check_mode
from mjstamp.svgd.guards import PHASE_SGD, PHASE_SVGD
from mjstamp.svgd.kernels import Kernel
from mjstamp.svgd.steps import (
    LogDensityFn,
    StepInfo,
    SVGDState,
    build_dsvgd_step,
    build_sgd_step,
    build_svgd_step,
    init,
    near_zero_share,
    near_zero_threshold,
    sgd_mode,
)

__all__ = [
    "PHASE_SGD",
    "PHASE_SVGD",
    "LoopSnapshot",
    "StampConfig",
    "StampDiagnostics",
    "StampResult",
    "has_converged",
    "run_stamp",
]


Schedule = Callable[[jax.Array], jax.Array]


def _number(value, name: str, *, zero: bool = False, schedule: bool = False,
            none: bool = False) -> None:
    """A finite number > 0 (>= 0 with `zero`), or else an optax schedule or None if allowed."""
    if (schedule and callable(value)) or (none and value is None):
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not math.isfinite(value)
        or not (value >= 0 if zero else value > 0)
    ):
        what = f"a float {'>=' if zero else '>'} 0"
        what += " or an optax schedule" * schedule + " or None" * none
        raise MjstampError(f"{name} must be {what}; got {value!r}")


def _count(value, name: str, minimum: int) -> None:
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Integral)
        or value < minimum
    ):
        raise MjstampError(f"{name} must be an integer >= {minimum}; got {value!r}")


@dataclasses.dataclass(frozen=True)
class StampConfig:
    """Settings of the STAMP loop; every field is validated on construction.

    The one definition of these settings: `run_stamp` reads them, and
    `mjstamp.SolveConfig.stamp` holds them for a solve (with the solve's own
    defaults, see there).

    Attributes:
      svgd_learning_rate: step size ε of the SVGD phase, in units of θ (float
        > 0 or an optax schedule), used by the default optimizer, Adam; None:
        the caller scales the step per coordinate (`svgd_step`) and passes its
        own optimizer (`mjstamp.solve` does, by each coordinate's box width).
      sgd_learning_rate: step size ε of the SGD phase, likewise (`sgd_step`).
      svgd_step: with `svgd_learning_rate` None, the SVGD step as a fraction
        of each coordinate's scale, which the caller's optimizer applies
        (`run_stamp` itself does not read it): 0.01, so 50 iterations can
        cross half a box.
      sgd_step: likewise for SGD: 0.003, finer, to settle into narrow modes.
      svgd_max_iters: cap on SVGD iterations (>= 0; Algorithm 1 line 3-7); the
        fallback if the convergence test never fires.
      sgd_max_iters: cap on SGD iterations (>= 0, line 8-10; 0 skips refinement).
      min_iters: iterations each phase runs before the test may fire.
      window: W, the number of iterations the test looks back over (>= 1;
        `has_converged`).
      rtol: bound on the relative change of the mean log posterior over W
        iterations, |L̄_t − L̄_{t−W}| / max(|L̄_{t−W}|, 1).
      motion_tol: bound on the mean particle displacement per iteration,
        averaged over the last W iterations, in units of θ; None: the caller
        resolves it before `run_stamp` (`mjstamp.solve`: 1e-4 of the mean box
        width).
      seed: seeds the PRNG keys handed to the steps and to a callable
        `initial_particles`; the same seed gives the same run (a solve sets
        it from its own seed).
      jacobian: 'auto', 'fwd' or 'rev': how the SVGD step differentiates a log
        density that also returns kernel features, and how the SGD step
        differentiates its own (see `build_sgd_step`).
      rescue_window: 0 (off) or R >= 1: in the SVGD phase, a particle that has
        stalled for R consecutive iterations is re-drawn by `run_stamp`'s
        `redraw` (and its optimizer moments zeroed). Stalled: its score norm is
        at most the phase's near-zero threshold (`near_zero_threshold`: it
        feels no gradient) and its log density is at most the population's
        median (it is not resting in a good mode), or either is not finite.
      nonfinite_redraw: 0 (never) or M >= 1: a particle whose log density,
        score or features are not finite is frozen for the iteration (both
        phases) and left out of the kernel of the others; after M consecutive
        such iterations it is re-drawn by `redraw` when one is given (and its
        optimizer moments zeroed), else it stays frozen.
      backtrack: True: in SVGD, a step that leaves a particle's log density
        more than max(1, d/2) nats below its peak in the phase is taken back
        (in discrete SVGD the target at the decoded plan, log p(Γ(θ)), is the
        one guarded): at its next iteration the particle returns to its last
        accepted point, its step scale halves (down to 2^-10) and its
        optimizer moments are zeroed; an accepted step multiplies the scale by
        1.25, up to 1, and scales the particle's next optimizer update.
        Adam's per-coordinate normalisation makes its first step the full
        learning rate whatever the gradient, which throws particles out of
        valleys narrower than that step. In SGD
        the optimizer runs free and each particle ends at the best point it
        visited (taking steps back there shrank them until the convergence
        test ended SGD early: pushing K = 2 ended with 53% of particles
        verified, against 70%). False: every update as the optimizer gives it
        and the last iterate returned (Algorithm 1 as written).
    """

    svgd_learning_rate: float | Schedule | None = 1e-2
    sgd_learning_rate: float | Schedule | None = 1e-2
    svgd_step: float = 0.01
    sgd_step: float = 0.003
    svgd_max_iters: int = 1000
    sgd_max_iters: int = 1000
    min_iters: int = 50
    window: int = 25
    rtol: float = 1e-3
    motion_tol: float | None = 1e-3
    seed: int = 0
    jacobian: JacobianMode = "auto"
    rescue_window: int = 0
    nonfinite_redraw: int = 3
    backtrack: bool = True

    def __post_init__(self):
        """Validates every field (MjstampError naming the field and its range)."""
        for name in ("svgd_learning_rate", "sgd_learning_rate"):
            _number(getattr(self, name), name, schedule=True, none=True)
        for name in ("svgd_step", "sgd_step"):
            _number(getattr(self, name), name)
        _count(self.svgd_max_iters, "svgd_max_iters", 0)
        _count(self.sgd_max_iters, "sgd_max_iters", 0)
        _count(self.min_iters, "min_iters", 0)
        _count(self.window, "window", 1)
        _number(self.rtol, "rtol", zero=True)
        _number(self.motion_tol, "motion_tol", zero=True, none=True)
        _count(self.seed, "seed", 0)
        _count(self.rescue_window, "rescue_window", 0)
        _count(self.nonfinite_redraw, "nonfinite_redraw", 0)
        if not isinstance(self.backtrack, bool):
            raise MjstampError(f"backtrack must be True or False; got {self.backtrack!r}")
        try:
            check_mode(self.jacobian, "jacobian")
        except ValueError as e:
            raise MjstampError(str(e)) from None


class StampDiagnostics(NamedTuple):
    """Per-iteration diagnostics of a run, T = SVGD + SGD iterations (numpy).

    Attributes:
      logdensity_mean: (T,) mean log ρ over the particles with a finite value.
      logdensity_max: (T,) max log ρ.
      bandwidth: (T, g) kernel bandwidths (NaN in the SGD phase).
      phase: (T,) PHASE_SVGD (0) or PHASE_SGD (1).
      learning_rate: (T,) step size ε when the optimizer exposes it (the
        default ones do), NaN otherwise.
      displacement: (T,) mean ‖Δθ_i‖ of the iteration: the step actually taken.
      nonfinite_particles: (T,) particles with a NaN/inf log ρ, score or
        features: frozen that iteration and counted for no other particle.
      step_seconds: (T,) wall time of each iteration; the first of each phase
        includes compiling its step (or loading it from the caches).
      driving_norm_mean: (T,) mean over particles of ‖D_i‖, the driving term
        D_i = Σ_j a_j k(θ_j, θ_i) ∇log ρ(θ_j) of the Stein direction (a_j = 1/n,
        or the normalised importance weights of discrete SVGD); NaN in SGD.
      driving_norm_median: (T,) median of ‖D_i‖; NaN in SGD.
      repulsion_norm_mean: (T,) mean of ‖R_i‖, the repulsive term
        R_i = Σ_j a_j ∇_{θ_j} k(θ_j, θ_i); NaN in SGD.
      repulsion_norm_median: (T,) median of ‖R_i‖; NaN in SGD.
      score_norm_median: (T,) median of ‖∇log ρ(θ_i)‖ over finite particles
        (both phases: in SGD the score is the direction).
      direction_norm_mean: (T,) mean ‖φ_i‖ of the direction handed to the
        optimizer (D + R in SVGD, the score in SGD); displacement /
        (learning_rate · direction_norm_mean) is the optimizer's gain (1 for
        plain SGD; Adam's per-coordinate normalisation makes it large where
        gradients are small).
      displacement_per_coordinate: (T, d) mean over particles of |Δθ_ik|.
      near_zero_share: (T,) share of the particles whose score norm is at most
        near_zero_threshold, i.e. that feel almost no gradient.
      near_zero_threshold: (T,) τ = max(1e-3 · m, 1e-12), m the median of the
        nonzero score norms at the first iteration of the phase
        (`mjstamp.svgd.near_zero_threshold`); constant within a phase.
      self_weight_median: (T,) median over particles of a_i k_ii / Σ_j a_j k_ji,
        the share of a particle's own score in its driving term: near 1/n the
        kernel averages every particle's score, so a particle in a narrow valley
        follows the crowd rather than its valley; NaN in SGD.
      rescued: (T,) particles re-drawn after the iteration (`rescue_window`).
      nonfinite_redrawn: (T,) particles re-drawn after the iteration for
        being non-finite `nonfinite_redraw` iterations in a row.
      backtracked: (T,) particles whose previous step lowered their log
        density and was taken back at this iteration (`backtrack`; SVGD only).
      step_scale_median: (T,) median over particles of the step scale
        (`backtrack`; 1 when off).
    """

    logdensity_mean: np.ndarray
    logdensity_max: np.ndarray
    bandwidth: np.ndarray
    phase: np.ndarray
    learning_rate: np.ndarray
    displacement: np.ndarray
    nonfinite_particles: np.ndarray
    step_seconds: np.ndarray
    driving_norm_mean: np.ndarray
    driving_norm_median: np.ndarray
    repulsion_norm_mean: np.ndarray
    repulsion_norm_median: np.ndarray
    score_norm_median: np.ndarray
    direction_norm_mean: np.ndarray
    displacement_per_coordinate: np.ndarray
    near_zero_share: np.ndarray
    near_zero_threshold: np.ndarray
    self_weight_median: np.ndarray
    rescued: np.ndarray
    nonfinite_redrawn: np.ndarray
    backtracked: np.ndarray
    step_scale_median: np.ndarray


class StampResult(NamedTuple):
    """What `run_stamp` returns.

    Attributes:
      particles: (n, d) final particles (after SGD; with `backtrack`, the best
        point each particle visited in SGD).
      svgd_particles: (n, d) particles at the end of the SVGD phase (with
        `backtrack`, the last points it accepted).
      diagnostics: `StampDiagnostics`.
      svgd_iters: SVGD iterations run.
      sgd_iters: SGD iterations run.
      svgd_converged: True if the SVGD phase ended by the convergence test.
      sgd_converged: True if the SGD phase ended by the convergence test.
      rescued: (n,) times each particle was re-drawn (`rescue_window`).
      nonfinite_redrawn: (n,) times each particle was re-drawn for being
        non-finite (`nonfinite_redraw`).
    """

    particles: jax.Array
    svgd_particles: jax.Array
    diagnostics: StampDiagnostics
    svgd_iters: int
    sgd_iters: int
    svgd_converged: bool
    sgd_converged: bool
    rescued: np.ndarray
    nonfinite_redrawn: np.ndarray


def has_converged(
    logdensity_mean: Sequence[float],
    displacement: Sequence[float],
    *,
    window: int,
    rtol: float,
    motion_tol: float,
    min_iters: int = 0,
) -> bool:
    """The convergence test of a phase (Algorithm 1 line 7, and the end of SGD).

    With t iterations done, L̄ the mean log posterior and m the mean particle
    displacement per iteration, the phase has converged when t >= min_iters,
    t > W and both

      |L̄_t − L̄_{t−W}| ≤ rtol · max(|L̄_{t−W}|, 1)  and  (1/W) Σ_{s>t−W} m_s ≤ motion_tol.

    The max(·, 1) compares a mean log posterior near 0 in absolute terms.
    Non-finite values never count as converged.

    Args:
      logdensity_mean: L̄ for the iterations of this phase so far.
      displacement: m for the same iterations.
      window: W >= 1.
      rtol: relative tolerance on the change of L̄.
      motion_tol: tolerance on the mean displacement, in units of θ.
      min_iters: iterations before the test may pass.

    Returns:
      Whether the phase has converged.
    """
    t = len(logdensity_mean)
    if t < max(min_iters, window + 1):
        return False
    now, then = float(logdensity_mean[-1]), float(logdensity_mean[-1 - window])
    motion = float(np.mean(np.asarray(displacement[-window:], dtype=float)))
    if not (math.isfinite(now) and math.isfinite(then) and math.isfinite(motion)):
        return False
    return abs(now - then) <= rtol * max(abs(then), 1.0) and motion <= motion_tol


def _default_optimizer(learning_rate) -> optax.GradientTransformation:
    # inject_hyperparams exposes ε in the optimizer state, for the diagnostics.
    return optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)


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


# N.B. over 80 lines: 50 of them the docstring, 16 the signature; the loop itself is `_Loop`.
def run_stamp(
    logdensity_fn: LogDensityFn,
    initial_particles: jax.Array | Callable[[jax.Array], jax.Array],
    kernel: Kernel | None = None,
    config: StampConfig = StampConfig(),
    *,
    log_target_fn: LogDensityFn | None = None,
    sgd_logdensity_fn: LogDensityFn | None = None,
    svgd_optimizer: optax.GradientTransformation | None = None,
    sgd_optimizer: optax.GradientTransformation | None = None,
    progress: ProgressLike = None,
    jit: Callable[[Callable, Any, jax.Array, str], Callable] | None = None,
    redraw: Callable[[jax.Array, int], jax.Array] | None = None,
    checkpoint: Callable[[Callable[[], LoopSnapshot]], None] | None = None,
    resume: LoopSnapshot | None = None,
    deadlines: tuple[float | None, float | None] = (None, None),
) -> StampResult:
    """Runs STAMP: (discrete) SVGD until converged, then SGD until converged.

    Args:
      logdensity_fn: batched log posterior log ρ(θ | O = 1), (n, d) ->
        (logp (n,), aux (n, f)): aux the features of the same rollout for a
        `feature_kernel()` that reads them, else an (n, 0) array (see
        `mjstamp.svgd.steps`).
      initial_particles: (n, d) array with n >= 2, or a function of a PRNG key
        returning one (called with a key derived from config.seed).
      kernel: SVGD kernel; None for `rbf()` with the median heuristic.
      config: `StampConfig`.
      log_target_fn: batched (n, d) -> (log p(Γ(θ)) (n,), aux), the target at
        the hard decode; when given the SVGD phase is discrete SVGD, eq. (4).
      sgd_logdensity_fn: the log density the SGD phase ascends; default
        logdensity_fn. A discrete task passes the target at the hard decode
        here, so refinement optimises the plan that will be executed.
      svgd_optimizer: optax transformation of the SVGD phase; default
        Adam(config.svgd_learning_rate).
      sgd_optimizer: optax transformation of the SGD phase; default
        Adam(config.sgd_learning_rate).
      progress: show a tqdm bar; None shows it when stderr is a terminal and
        prints a status line per phase and every tenth of it otherwise (a log
        or a pipe); or a callable taking those lines, or a `Progress`
        (`mjstamp.progress`), whose lines read "[stamp] ...".
      jit: how the steps' halves are compiled, jit(fn, name, *example_args)
        -> compiled fn, with name "svgd-evaluate", "svgd-update",
        "sgd-evaluate" or "sgd-update" (the SGD phase reuses the SVGD phase's
        compiled evaluation when they share it); default `jax.jit`. A task
        passes `mjstamp.tracecache.cached_jit` here so a re-run skips tracing.
      redraw: redraw(key, k) -> (k, d) fresh particles for the stalled ones
        (`config.rescue_window`) and the persistently non-finite ones
        (`config.nonfinite_redraw`), e.g. draws from the prior; required when
        rescue is on.
      checkpoint: called after every iteration with a function that returns
        the `LoopSnapshot` of that moment; it decides whether to build and
        keep one (say every 30 s) and may raise to stop the run.
      resume: a `LoopSnapshot` of a run with the same arguments: the run
        continues after its iteration instead of starting afresh.
      deadlines: (SVGD's, SGD's) `time.perf_counter()` times after which the
        phase ends at its next iteration as at its cap (None: no deadline); a
        run with one depends on the machine's speed, so a resumed one may differ.

    Returns:
      `StampResult`.

    Raises:
      ValueError: on a bad config or malformed particles (before tracing), on
        kernel groups or log-density outputs of the wrong shape (while tracing
        the first step, before compiling it), or when log ρ is not finite at
        any initial particle (after the first step's evaluation).

    References:
      STAMP Algorithm 1.
    """
    if not isinstance(config, StampConfig):
        raise ValueError(f"config must be a StampConfig; got {config!r}")
    unresolved = [name for name, given in (("svgd_learning_rate", svgd_optimizer),
                                           ("sgd_learning_rate", sgd_optimizer),
                                           ("motion_tol", None))
                  if getattr(config, name) is None and given is None]
    if unresolved:  # N.B. None means "the caller resolves it" (StampConfig): it did not
        raise MjstampError(f"run_stamp needs config.{unresolved[0]} as a number (or, for a "
                           "learning rate, the phase's optimizer); got None")
    key = jax.random.key(config.seed)
    if callable(initial_particles):
        key, sub = jax.random.split(key)
        initial_particles = initial_particles(sub)
    particles = jnp.asarray(initial_particles)
    check_particles(particles)
    if config.rescue_window and redraw is None:
        raise ValueError("config.rescue_window > 0 needs redraw(key, k), the particles' source")

    (svgd_step, svgd_optimizer), (sgd_step, sgd_optimizer) = _phase_steps(
        logdensity_fn, kernel, config, log_target_fn, sgd_logdensity_fn,
        svgd_optimizer, sgd_optimizer, particles.shape[1],
    )  # fmt: skip
    loop = _Loop(config, jit, n=particles.shape[0], progress=Progress.of(progress).under("stamp"),
                 redraw=redraw, checkpoint=checkpoint, deadlines=deadlines)
    carry = _Carry.init(key, particles.shape[0], backtrack=config.backtrack)
    if resume is not None:
        carry = loop.restore(resume, particles.shape, carry)
    with loop.bar:  # closed on the way out, also when a phase raises
        svgd, carry = loop.run_svgd(svgd_step, init(particles, svgd_optimizer), carry, resume)
        svgd_iters = sum(int(r.phase) == PHASE_SVGD for r in carry.rows)
        state, carry, sgd_converged = loop.run_phase(
            PHASE_SGD, sgd_step, init(svgd.particles, sgd_optimizer), carry,
            resume=resume if resume is not None and resume.phase == PHASE_SGD else None,
        )
        if len(carry.rows) > svgd_iters:
            state = state._replace(particles=_best(state.particles, carry.backtrack))
    return StampResult(
        particles=state.particles, svgd_particles=svgd.particles,
        diagnostics=_stack_records(carry.rows, particles.shape[1]), svgd_iters=svgd_iters,
        sgd_iters=len(carry.rows) - svgd_iters,
        svgd_converged=carry.svgd_end[1], sgd_converged=sgd_converged,
        rescued=carry.rescue.rescued, nonfinite_redrawn=carry.rescue.nonfinite_redrawn,
    )  # fmt: skip


def _phase_steps(
    logdensity_fn, kernel, config, log_target_fn, sgd_logdensity_fn, svgd_optimizer, sgd_optimizer,
    dim: int,
):
    """((SVGD step, its optimizer), (SGD step, its optimizer)) of `run_stamp`'s arguments.

    When the SGD phase ascends the same log density and its scores come the
    way the SVGD step's do (forward mode with a feature kernel, or one pullback
    without), the SGD step reads the SVGD step's own evaluation
    (`step.evaluate`): one rollout compiled for both phases.
    """
    svgd_optimizer = svgd_optimizer or _default_optimizer(config.svgd_learning_rate)
    sgd_optimizer = sgd_optimizer or _default_optimizer(config.sgd_learning_rate)
    if log_target_fn is None:
        svgd_step = build_svgd_step(
            logdensity_fn, kernel, svgd_optimizer, jacobian=config.jacobian
        )
    else:
        svgd_step = build_dsvgd_step(
            logdensity_fn, log_target_fn, kernel, svgd_optimizer, jacobian=config.jacobian
        )
    sgd_fn = sgd_logdensity_fn or logdensity_fn
    features = kernel is not None and kernel.uses_density_features
    shared = (sgd_fn is logdensity_fn and log_target_fn is None
              and sgd_mode(config.jacobian, dim) == ("fwd" if features else "rev"))
    sgd_step = build_sgd_step(sgd_fn, sgd_optimizer, jacobian=config.jacobian,
                              evaluate=svgd_step.evaluate if shared else None)
    return (svgd_step, svgd_optimizer), (sgd_step, sgd_optimizer)


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


class _Loop:
    """The Python loop of `run_stamp`: what stays fixed over a run (settings, compiled steps).

    What changes from one iteration to the next is a `_Carry`, passed in and
    returned; the particles and optimizer state are the step's `SVGDState`.
    """

    def __init__(
        self, config: StampConfig, jit, *, n: int, progress: Progress,
        redraw=None, checkpoint=None, deadlines=(None, None),
    ):
        self.deadlines = deadlines
        self.checkpoint = checkpoint
        self.redraw = redraw
        # N.B. without a source of fresh particles a non-finite one just stays frozen.
        self.nonfinite_window = config.nonfinite_redraw if redraw is not None else 0
        self.config = config
        self.jit = jit
        self.n = n
        # N.B. without a terminal tqdm writes nothing a log can show: say lines instead.
        self.say = progress if progress.lines else QUIET
        self.bar = tqdm(
            total=config.svgd_max_iters + config.sgd_max_iters,
            desc="STAMP",
            unit="it",
            disable=not progress.bar,
        )
        self.evaluations: dict[int, tuple] = {}  # id(step.evaluate) -> (it, compiled)

    def _compile(self, step, fresh_state: SVGDState, name: str, key: jax.Array):
        """The phase's step, compiled as its two halves (`mjstamp.svgd.steps`).

        The evaluation (the rollouts) is compiled once per `step.evaluate` and
        shared by the phases built on it; the update (kernel, optimizer) per
        phase. The first evaluation, of the phase's initial particles, is the
        update's example and serves the phase's first iteration.
        """
        jit = self.jit or (lambda fn, _name, *_example: jax.jit(fn))
        x0 = fresh_state.particles
        ev_key = id(step.evaluate)
        if ev_key not in self.evaluations:  # N.B. the function is kept: its id stays its own
            self.evaluations[ev_key] = (step.evaluate,
                                        jit(step.evaluate, f"{name}-evaluate", x0))
        evaluate = self.evaluations[ev_key][1]
        first = {"particles": x0, "evaluation": evaluate(x0)}
        update = jit(step.update, f"{name}-update", fresh_state, first["evaluation"], key)

        def compiled(state: SVGDState, key: jax.Array):
            if first and state.particles is first.pop("particles"):
                ev = first.pop("evaluation")
            else:
                first.clear()
                ev = evaluate(state.particles)
            return update(state, ev, key)

        return compiled

    def snapshot(self, phase: int, t: int, state, carry: _Carry) -> LoopSnapshot:
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

    def restore(self, snap: LoopSnapshot, shape: tuple[int, int], carry: _Carry) -> _Carry:
        """The carry of a snapshot: its key, records and counters (its state: `run_phase`)."""
        if not isinstance(snap, LoopSnapshot):
            raise ValueError(f"resume must be a LoopSnapshot; got {type(snap).__name__}")
        if snap.phase not in (PHASE_SVGD, PHASE_SGD) or np.shape(snap.particles) != shape:
            raise ValueError(f"resume: a snapshot of phase {snap.phase} with particles "
                             f"{np.shape(snap.particles)} cannot continue a run of {shape}")
        self.bar.update(len(snap.rows))
        c = snap.counters
        rescue = guards.RescueState(
            *(np.array(c[k]) for k in ("stalled", "rescued", "failing", "nonfinite_redrawn")),
            fresh=np.array(c.get("fresh", guards.RescueState._field_defaults["fresh"]), int))
        backtrack = None if carry.backtrack is None else _backtrack_from(c, shape[0])
        return carry._replace(
            key=jax.random.wrap_key_data(jnp.asarray(snap.key_data)), rows=tuple(snap.rows),
            rescue=rescue, backtrack=backtrack)

    def run_svgd(self, step, state, carry: _Carry, resume) -> tuple[SVGDState, _Carry]:
        """(SVGD's last state, carry with `svgd_end` set): the SVGD phase, or a snapshot's."""
        if resume is not None and resume.phase == PHASE_SGD:
            svgd = SVGDState(jnp.asarray(resume.svgd_particles), None)
            converged = bool(resume.svgd_converged)
        else:
            svgd, carry, converged = self.run_phase(PHASE_SVGD, step, state, carry,
                                                    resume=resume)
            if carry.rows:
                # The last update was never scored: SVGD ends at the points it accepted.
                svgd = svgd._replace(particles=_best(svgd.particles, carry.backtrack))
        svgd_iters = sum(int(r.phase) == PHASE_SVGD for r in carry.rows)
        self.bar.total = svgd_iters + self.config.sgd_max_iters
        self.bar.refresh()
        return svgd, carry._replace(svgd_end=(np.asarray(svgd.particles), converged))

    def run_phase(self, phase: int, step, state, carry: _Carry, *, resume=None):
        """Runs `step` until the convergence test passes or the cap; (state, carry, converged).

        With `resume` (a `LoopSnapshot` of this phase), continues after its
        iteration from its particles and optimizer state.
        """
        max_iters = self.config.svgd_max_iters if phase == PHASE_SVGD else \
            self.config.sgd_max_iters
        if max_iters == 0:  # nothing to run: compile nothing either
            return state, carry, False
        name = "svgd" if phase == PHASE_SVGD else "sgd"
        done = [r for r in carry.rows if r.phase == phase] if resume is not None else []
        means = [float(r.logdensity_mean) for r in done]
        moves = [float(r.displacement) for r in done]
        fresh_state = state  # what the step is compiled for; a snapshot shares its shapes
        if resume is not None:
            state = _resumed(state, resume)
            self.say(f"{name.upper()}: resumed after iteration {resume.iteration}")
            if self._converged(means, moves):  # the order of the loop's own exits
                return state, carry, True
            if resume.iteration >= max_iters:
                return state, carry, False
        self.say(f"{name.upper()}: compiling its step (or loading it from the caches)")
        step = self._compile(step, fresh_state, name, carry.key)
        if carry.backtrack is not None and not done:
            # a new phase: a new objective, a new optimizer
            carry = carry._replace(backtrack=guards.backtrack_init(self.n))
        # Near-zero score norm, fixed at the phase's first iteration.
        threshold = float(done[0].near_zero_threshold) if done else None
        for t in range(len(done) + 1, max_iters + 1):
            state, carry, row = self._iterate(phase, t, step, state, carry, threshold)
            threshold = float(row.near_zero_threshold)
            means.append(float(row.logdensity_mean))
            moves.append(float(row.displacement))
            self._report(phase, t, max_iters, means[-1], row)
            if self.checkpoint is not None:
                self.checkpoint(lambda t=t, state=state, carry=carry:
                                self.snapshot(phase, t, state, carry))
            if self._converged(means, moves):
                return state, carry, True
            deadline = self.deadlines[0 if phase == PHASE_SVGD else 1]
            if deadline is not None and time.perf_counter() >= deadline:
                self.say(f"{name.upper()}: its share of the budget spent after {t} iterations")
                break
        return state, carry, False

    def _iterate(self, phase: int, t: int, step, state: SVGDState, carry: _Carry, threshold):
        """(state, carry, row) after one iteration: the step, then the guards around it."""
        started = time.perf_counter()
        carry, sub = carry.split()
        after, info = step(state, sub)
        row, score_norm = _fetch(info, phase)
        host, backed, carry, row = self._backtrack(phase, state, after, info, carry, row)
        row = row._replace(step_seconds=time.perf_counter() - started)
        if threshold is None:
            threshold = float(near_zero_threshold(score_norm, xp=np))
        row = row._replace(
            near_zero_share=float(near_zero_share(score_norm, threshold, xp=np)),
            near_zero_threshold=threshold,
        )
        drawn, carry, row = self._redraws(phase, t, info, score_norm, threshold, after, carry,
                                          row)
        if drawn and carry.backtrack is not None and phase == PHASE_SVGD:
            # N.B. in SGD the best point a particle visited stays its best: the
            # fresh particle's points compete with it.
            carry = carry._replace(backtrack=guards.backtrack_forget(
                np.concatenate([idx for idx, _ in drawn]), carry.backtrack))
        if not carry.rows and int(row.nonfinite_particles) == self.n:
            raise ValueError(
                f"logdensity_fn returned NaN/inf (or a NaN gradient) for all {self.n} "
                "initial particles; it must be finite for at least one"
            )
        after = _edited(after, host, backed, drawn)
        return after, carry._replace(rows=(*carry.rows, row)), row

    def _backtrack(self, phase, before: SVGDState, after: SVGDState, info: StepInfo,
                   carry: _Carry, row):
        """(particles after it on the host or None, rows taken back, carry, row): the guard."""
        if carry.backtrack is None:
            return None, _NO_ROWS, carry, row
        logp = np.asarray(fetch(info.guard_logdensity), dtype=float)
        theta_t = np.asarray(fetch(before.particles), dtype=float)
        decision, guard = guards.backtrack_update(theta_t, logp, phase, carry.backtrack)
        row = row._replace(backtracked=int(decision.back.size),
                           step_scale_median=float(np.median(guard.scale)))
        host = None
        if decision.edits:  # the steps taken, not the optimizer's updates
            host = guards.backtrack_apply(fetch(after.particles), theta_t, decision, guard)
            moved = host.astype(float) - theta_t
            row = row._replace(displacement=float(np.mean(np.linalg.norm(moved, axis=1))),
                               displacement_per_coordinate=np.mean(np.abs(moved), 0))
        return host, decision.back, carry._replace(backtrack=guard), row

    def _redraws(self, phase, t, info: StepInfo, score_norm, threshold, after, carry, row):
        """([(indices, fresh rows)], carry, row): the stall rescue, then the non-finite re-draw."""
        name, drawn = ("SVGD" if phase == PHASE_SVGD else "SGD"), []
        if phase == PHASE_SVGD and self.config.rescue_window:
            carry, sub = carry.split()
            logp = np.asarray(fetch(info.logdensity), dtype=float)
            idx, rescue = guards.stall_update(logp, score_norm, threshold,
                                              self.config.rescue_window, carry.rescue)
            carry, row = carry._replace(rescue=rescue), row._replace(rescued=int(idx.size))
            if idx.size:
                drawn.append((idx, self._draw(sub, idx.size, after.particles)))
                self.say(f"{name} {t}: {idx.size} stalled particles re-drawn")
        if self.nonfinite_window:
            idx, rescue = guards.nonfinite_update(score_norm, self.nonfinite_window,
                                                  carry.rescue)
            carry = carry._replace(rescue=rescue)
            row = row._replace(nonfinite_redrawn=int(idx.size))
            if idx.size:
                # N.B. a key only when some particle is re-drawn, so a run without
                # one draws the same PRNG keys as before this check existed.
                carry, sub = carry.split()
                drawn.append((idx, self._draw(sub, idx.size, after.particles)))
                self.say(f"{name} {t}: {idx.size} particles non-finite "
                         f"{self.nonfinite_window} iterations in a row re-drawn")
        return drawn, carry, row

    def _draw(self, key: jax.Array, k: int, like: jax.Array) -> np.ndarray:
        """(k, d) fresh particles from `redraw`, in the particles' dtype, on the host."""
        fresh = jnp.asarray(self.redraw(key, k), like.dtype)
        if fresh.shape != (k, like.shape[1]):
            raise ValueError(f"redraw(key, {k}) returned shape {fresh.shape}; "
                             f"expected ({k}, {like.shape[1]})")
        return np.asarray(fresh)

    def _report(self, phase: int, t: int, max_iters: int, mean: float, row) -> None:
        """The progress bar, and a status line at the first, every tenth and the last."""
        name = "SVGD" if phase == PHASE_SVGD else "SGD"
        self.bar.update(1)
        if t % 10 == 1:
            self.bar.set_postfix(phase=name, logp=f"{mean:.4g}")
        if t == 1 or t % max(1, max_iters // 10) == 0 or t == max_iters:
            self.say(f"{name} {t}/{max_iters}: mean log density {mean:.4g}, "
                     f"{row.step_seconds:.2f} s/it")

    def _converged(self, means, moves) -> bool:
        c = self.config
        return has_converged(means, moves, window=c.window, rtol=c.rtol,
                             motion_tol=c.motion_tol, min_iters=c.min_iters)


_NO_ROWS = np.zeros(0, dtype=int)


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
    return after._replace(particles=_put(host, after.particles), opt_state=opt_state)


def _best(particles: jax.Array, guard: guards.BacktrackState | None) -> jax.Array:
    """`particles` with each one backtracking has a scored point for replaced by that point."""
    if guard is None:
        return particles
    rows, theta = guards.backtrack_best(guard)
    return _set_rows(particles, rows, theta) if rows.size else particles


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


def _set_rows(array: jax.Array, idx: np.ndarray, rows) -> jax.Array:
    """`array` with rows `idx` set to `rows`, with the array's own sharding.

    N.B. written on the host and put back shard by shard: an array replicated
    over several processes' devices takes no eager `.at[].set` (it is not fully
    addressable), and the compiled step expects the sharding it was built for.
    """
    host = np.array(fetch(array))
    host[idx] = rows
    return _put(host, array)


def _put(host: np.ndarray, like: jax.Array) -> jax.Array:
    """A host array as a jax.Array with the sharding of `like` (over any processes)."""
    return jax.make_array_from_callback(host.shape, like.sharding, lambda i: host[i])


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
            return _set_rows(leaf, idx, 0)
        return leaf

    if first_moment_only:
        adam = lambda x: isinstance(x, optax.ScaleByAdamState)  # noqa: E731
        if any(adam(x) for x in jax.tree.leaves(opt_state, is_leaf=adam)):
            return jax.tree.map(
                lambda x: x._replace(mu=jax.tree.map(reset, x.mu)) if adam(x) else x,
                opt_state, is_leaf=adam)
    return jax.tree.map(reset, opt_state)


def fetch(tree):
    """`jax.device_get` that also reads arrays spread over several processes' devices.

    N.B. such an array is gathered by a collective, which every process must
    reach at the same point; the loop's arrays are replicated by the caller's
    `jit` when its mesh spans processes (`mjstamp.parallel.replicate_outputs`),
    so it never needs one.
    """
    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated:
            from jax.experimental import multihost_utils  # noqa: PLC0415

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return x

    return jax.device_get(jax.tree.map(one, tree))


_FROM_STEP = tuple(f for f in StampDiagnostics._fields if f in StepInfo._fields)


def _fetch(info: StepInfo, phase: int) -> tuple[StampDiagnostics, np.ndarray]:
    """The iteration's record and its (n,) score norms, on the host (waits for the step).

    The record's step_seconds and near-zero fields are left for the loop to fill.
    N.B. everything derived from the (n,) score norms is computed here in numpy: a
    jnp call outside the step would be one more dispatch per iteration.
    """
    # N.B. the fields a StepInfo carries are copied by name; the rest the loop fills.
    copied = {name: getattr(info, name) for name in _FROM_STEP}
    record, score_norm = fetch((
        StampDiagnostics(**{**dict.fromkeys(StampDiagnostics._fields), **copied})._replace(
            phase=phase, rescued=0, nonfinite_redrawn=0, backtracked=0,
            step_scale_median=1.0),
        info.score_norm,
    ))
    finite = score_norm[np.isfinite(score_norm)]
    median = float(np.median(finite)) if finite.size else math.nan
    return record._replace(score_norm_median=median), score_norm


# dtype of each StampDiagnostics column; bandwidth's width g may differ between phases
# (SGD has none): a row of another width is NaN.
_COLUMN_DTYPES = {"phase": np.int8, "nonfinite_particles": int, "rescued": int,
                  "nonfinite_redrawn": int, "backtracked": int}


def _stack_records(rows: Sequence[StampDiagnostics], dim: int) -> StampDiagnostics:
    """The run's `StampDiagnostics`: its per-iteration rows stacked leaf by leaf (T rows).

    Args:
      rows: one `StampDiagnostics` per iteration, each field that iteration's
        value (bandwidth (g,), displacement_per_coordinate (d,), the rest scalars).
      dim: d, the width of displacement_per_coordinate when there are no rows.
    """
    g = max((np.size(r.bandwidth) for r in rows), default=0)

    def bandwidth(b):
        b = np.asarray(b, dtype=float).ravel()
        return b if b.size == g else np.full(g, np.nan)

    if not rows:
        return StampDiagnostics(**{f: np.zeros(0, _COLUMN_DTYPES.get(f, float))
                                   for f in StampDiagnostics._fields})._replace(
            bandwidth=np.zeros((0, 0)), displacement_per_coordinate=np.zeros((0, dim)))
    rows = [r._replace(bandwidth=bandwidth(r.bandwidth)) for r in rows]
    stacked = jax.tree.map(lambda *column: np.array(column), *rows)
    return StampDiagnostics(**{f: np.asarray(v, dtype=_COLUMN_DTYPES.get(f, float))
                               for f, v in stacked._asdict().items()})._replace(
        bandwidth=np.asarray(stacked.bandwidth, dtype=float).reshape(len(rows), g))
