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
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from mjstamp.svgd._checks import check_particles
from mjstamp.svgd._jacobian import JacobianMode, check_mode
from mjstamp.svgd.kernels import Kernel
from mjstamp.svgd.steps import (
    LogDensityFn,
    build_dsvgd_step,
    build_sgd_step,
    build_svgd_step,
    init,
)

__all__ = [
    "PHASE_SGD",
    "PHASE_SVGD",
    "StampConfig",
    "StampDiagnostics",
    "StampResult",
    "has_converged",
    "run_stamp",
]

PHASE_SVGD = 0
PHASE_SGD = 1

Schedule = Callable[[jax.Array], jax.Array]


def _positive(value, name: str, *, allow_schedule: bool = False) -> None:
    if allow_schedule and callable(value):
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not (value > 0 and math.isfinite(value))
    ):
        what = "a float > 0 or an optax schedule" if allow_schedule else "> 0"
        raise ValueError(f"{name} must be {what}; got {value!r}")


def _count(value, name: str, minimum: int) -> None:
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Integral)
        or value < minimum
    ):
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")


@dataclasses.dataclass(frozen=True)
class StampConfig:
    """Settings of `run_stamp`; every field is validated on construction.

    Attributes:
      svgd_learning_rate: step size ε of the SVGD phase (float > 0 or an optax
        schedule); used by the default optimizer, Adam.
      sgd_learning_rate: step size ε of the SGD phase, likewise.
      svgd_max_iters: cap on SVGD iterations (>= 0); the fallback if the
        convergence test never fires.
      sgd_max_iters: cap on SGD iterations (>= 0; 0 skips refinement).
      min_iters: iterations each phase runs before the test may fire.
      window: W, the number of iterations the test looks back over (>= 1).
      rtol: bound on the relative change of the mean log posterior over W
        iterations, |L̄_t − L̄_{t−W}| / max(|L̄_{t−W}|, 1).
      motion_tol: bound on the mean particle displacement per iteration,
        averaged over the last W iterations, in units of θ.
      seed: seeds the PRNG keys handed to the steps and to a callable
        `initial_particles`; the same seed gives the same run.
      jacobian: 'auto', 'fwd' or 'rev': how the SVGD step differentiates a log
        density that also returns kernel features.
    """

    svgd_learning_rate: float | Schedule = 1e-2
    sgd_learning_rate: float | Schedule = 1e-2
    svgd_max_iters: int = 1000
    sgd_max_iters: int = 1000
    min_iters: int = 50
    window: int = 25
    rtol: float = 1e-3
    motion_tol: float = 1e-3
    seed: int = 0
    jacobian: JacobianMode = "auto"

    def __post_init__(self):
        """Validates every field (ValueError naming the field and its range)."""
        _positive(
            self.svgd_learning_rate,
            "svgd_learning_rate (step size)",
            allow_schedule=True,
        )
        _positive(
            self.sgd_learning_rate, "sgd_learning_rate (step size)", allow_schedule=True
        )
        _count(self.svgd_max_iters, "svgd_max_iters", 0)
        _count(self.sgd_max_iters, "sgd_max_iters", 0)
        _count(self.min_iters, "min_iters", 0)
        _count(self.window, "window", 1)
        for name in ("rtol", "motion_tol"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, numbers.Real)
                or not value >= 0
            ):
                raise ValueError(f"{name} must be a float >= 0; got {value!r}")
        _count(self.seed, "seed", 0)
        check_mode(self.jacobian, "jacobian")


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
      n_nonfinite: (T,) particles with a NaN/inf log ρ or gradient.
      step_seconds: (T,) wall time of each iteration; the first of each phase
        includes compiling its step (or loading it from the caches).
    """

    logdensity_mean: np.ndarray
    logdensity_max: np.ndarray
    bandwidth: np.ndarray
    phase: np.ndarray
    learning_rate: np.ndarray
    displacement: np.ndarray
    n_nonfinite: np.ndarray
    step_seconds: np.ndarray


class StampResult(NamedTuple):
    """What `run_stamp` returns.

    Attributes:
      particles: (n, d) final particles (after SGD).
      svgd_particles: (n, d) particles at the end of the SVGD phase.
      diagnostics: `StampDiagnostics`.
      svgd_iters: SVGD iterations run.
      sgd_iters: SGD iterations run.
      svgd_converged: True if the SVGD phase ended by the convergence test.
      sgd_converged: True if the SGD phase ended by the convergence test.
    """

    particles: jax.Array
    svgd_particles: jax.Array
    diagnostics: StampDiagnostics
    svgd_iters: int
    sgd_iters: int
    svgd_converged: bool
    sgd_converged: bool


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


def run_stamp(
    logdensity_fn: LogDensityFn,
    initial_particles: jax.Array | Callable[[jax.Array], jax.Array],
    kernel: Kernel | None = None,
    config: StampConfig = StampConfig(),
    *,
    log_target_fn: Callable[[jax.Array], jax.Array] | None = None,
    sgd_logdensity_fn: LogDensityFn | None = None,
    svgd_optimizer: optax.GradientTransformation | None = None,
    sgd_optimizer: optax.GradientTransformation | None = None,
    progress: bool | None = None,
    jit: Callable[[Callable, Any, jax.Array, str], Callable] | None = None,
) -> StampResult:
    """Runs STAMP: (discrete) SVGD until converged, then SGD until converged.

    Args:
      logdensity_fn: batched log posterior log ρ(θ | O = 1), (n, d) -> (n,), or
        (n, d) -> (logp (n,), features (n, f)) for a `feature_kernel()` that
        reads the features of the same rollout (see `mjstamp.svgd.steps`).
      initial_particles: (n, d) array with n >= 2, or a function of a PRNG key
        returning one (called with a key derived from config.seed).
      kernel: SVGD kernel; None for `rbf()` with the median heuristic.
      config: `StampConfig`.
      log_target_fn: batched log p(Γ(θ)), the target at the hard decode; when
        given the SVGD phase is discrete SVGD, eq. (4).
      sgd_logdensity_fn: the log density the SGD phase ascends; default
        logdensity_fn. A discrete task passes the target at the hard decode
        here, so refinement optimises the plan that will be executed.
      svgd_optimizer: optax transformation of the SVGD phase; default
        Adam(config.svgd_learning_rate).
      sgd_optimizer: optax transformation of the SGD phase; default
        Adam(config.sgd_learning_rate).
      progress: show a tqdm bar; None shows it when stderr is a terminal.
      jit: how each phase's step is compiled, jit(step, example_state,
        example_key, phase_name) -> compiled step; default `jax.jit`. A task
        passes `mjstamp.tracecache.cached_jit` here so a re-run skips tracing.

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
    key = jax.random.key(config.seed)
    if callable(initial_particles):
        key, sub = jax.random.split(key)
        initial_particles = initial_particles(sub)
    particles = jnp.asarray(initial_particles)
    check_particles(particles)
    n = particles.shape[0]

    svgd_optimizer = svgd_optimizer or _default_optimizer(config.svgd_learning_rate)
    sgd_optimizer = sgd_optimizer or _default_optimizer(config.sgd_learning_rate)
    if log_target_fn is None:
        svgd_step = build_svgd_step(
            logdensity_fn, kernel, svgd_optimizer, jacobian=config.jacobian
        )
    else:
        svgd_step = build_dsvgd_step(
            logdensity_fn,
            log_target_fn,
            kernel,
            svgd_optimizer,
            jacobian=config.jacobian,
        )
    sgd_step = build_sgd_step(sgd_logdensity_fn or logdensity_fn, sgd_optimizer)

    show = sys.stderr.isatty() if progress is None else bool(progress)
    bar = tqdm(
        total=config.svgd_max_iters + config.sgd_max_iters,
        desc="STAMP",
        unit="it",
        disable=not show,
    )
    records: list[tuple] = []
    phases: list[int] = []
    converged = {PHASE_SVGD: False, PHASE_SGD: False}
    iters = {PHASE_SVGD: 0, PHASE_SGD: 0}

    def run_phase(phase, step, state, max_iters):
        nonlocal key
        if max_iters == 0:  # nothing to run: compile nothing either
            return state
        if jit is None:
            step = jax.jit(step)
        else:
            step = jit(step, state, key, "svgd" if phase == PHASE_SVGD else "sgd")
        means, moves = [], []
        for _ in range(max_iters):
            started = time.perf_counter()
            key, sub = jax.random.split(key)
            state, info = step(state, sub)
            rec = jax.device_get(
                (
                    info.logdensity_mean,
                    info.logdensity_max,
                    info.bandwidth,
                    info.learning_rate,
                    info.displacement,
                    info.n_nonfinite,
                )
            ) + (time.perf_counter() - started,)
            if not records and int(rec[5]) == n:
                raise ValueError(
                    f"logdensity_fn returned NaN/inf (or a NaN gradient) for all {n} "
                    "initial particles; it must be finite for at least one"
                )
            records.append(rec)
            phases.append(phase)
            means.append(float(rec[0]))
            moves.append(float(rec[4]))
            iters[phase] += 1
            bar.update(1)
            if iters[phase] % 10 == 1:
                bar.set_postfix(
                    phase="SVGD" if phase == PHASE_SVGD else "SGD",
                    logp=f"{means[-1]:.4g}",
                )
            if has_converged(
                means,
                moves,
                window=config.window,
                rtol=config.rtol,
                motion_tol=config.motion_tol,
                min_iters=config.min_iters,
            ):
                converged[phase] = True
                break
        return state

    try:
        state = run_phase(
            PHASE_SVGD,
            svgd_step,
            init(particles, svgd_optimizer),
            config.svgd_max_iters,
        )
        svgd_particles = state.particles
        bar.total = iters[PHASE_SVGD] + config.sgd_max_iters
        bar.refresh()
        state = run_phase(
            PHASE_SGD,
            sgd_step,
            init(svgd_particles, sgd_optimizer),
            config.sgd_max_iters,
        )
    finally:
        bar.close()

    return StampResult(
        particles=state.particles,
        svgd_particles=svgd_particles,
        diagnostics=_assemble(records, phases),
        svgd_iters=iters[PHASE_SVGD],
        sgd_iters=iters[PHASE_SGD],
        svgd_converged=converged[PHASE_SVGD],
        sgd_converged=converged[PHASE_SGD],
    )


def _assemble(records: list[tuple], phases: list[int]) -> StampDiagnostics:
    g = max((np.size(r[2]) for r in records), default=0)

    def bandwidth(r):
        b = np.asarray(r[2], dtype=float).ravel()
        return b if b.size == g else np.full(g, np.nan)

    def column(k, dtype=float):
        return np.array([r[k] for r in records], dtype=dtype)

    return StampDiagnostics(
        logdensity_mean=column(0),
        logdensity_max=column(1),
        bandwidth=np.array([bandwidth(r) for r in records]).reshape(len(records), g),
        phase=np.array(phases, dtype=np.int8),
        learning_rate=column(3),
        displacement=column(4),
        n_nonfinite=column(5, int),
        step_seconds=column(6),
    )
