"""The STAMP loop: (discrete) SVGD until converged, then SGD until converged.

Each phase compiles one step function (`jax.jit`, traced once) and drives it
from a Python loop, so a progress bar and the convergence test run between
steps. The switch from SVGD to SGD (Algorithm 1 line 7), and the end of SGD,
use the test of `has_converged`, with an iteration cap per phase as fallback.

`run_stamp` reads as its steps: `_setup` checks the arguments and draws the
particles, `_phase_steps` builds each phase's step, `_Loop` runs the phases
(what changes between iterations is a `_Carry`, `mjstamp.svgd.resume`) and
`_result` assembles the `StampResult`. The settings live in
`mjstamp.svgd.config`, the records in `mjstamp.svgd.diagnostics`, the
snapshots in `mjstamp.svgd.resume`; their public names are importable from
here as before.

References:
  STAMP Algorithm 1; §IV-A (inference by SVGD), §IV-B (refinement by SGD).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from mjstamp.errors import MjstampError
from mjstamp.progress import QUIET, Progress, ProgressLike
from mjstamp.svgd import guards
from mjstamp.svgd._checks import check_particles
from mjstamp.svgd._host import fetch
from mjstamp.svgd.config import StampConfig
from mjstamp.svgd.diagnostics import (
    StampDiagnostics,
    StampResult,
    _fetch,
    _stack_records,
    has_converged,
)
from mjstamp.svgd.edits import _best, _edited
from mjstamp.svgd.guards import PHASE_SGD, PHASE_SVGD
from mjstamp.svgd.kernels import Kernel
from mjstamp.svgd.resume import (
    LoopSnapshot,
    _Carry,
    _resumed,
    check_snapshot,
    restore,
    snapshot,
)
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
    "fetch",
    "has_converged",
    "run_stamp",
]


def _default_optimizer(learning_rate) -> optax.GradientTransformation:
    # inject_hyperparams exposes ε in the optimizer state, for the diagnostics.
    return optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)


def run_stamp(
    logdensity_fn: LogDensityFn,
    initial_particles: jax.Array | Callable[[jax.Array], jax.Array],
    kernel: Kernel | None = None,
    config: StampConfig = StampConfig(),  # noqa: B008 (frozen: immutable)
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
      MjstampError: when config leaves a learning rate (without the phase's
        optimizer) or motion_tol None, for the caller to resolve.

    References:
      STAMP Algorithm 1.
    """
    particles, key = _setup(config, initial_particles, redraw,
                            optimizers=(svgd_optimizer, sgd_optimizer))
    steps = _phase_steps(
        logdensity_fn, kernel, config, log_target_fn, sgd_logdensity_fn,
        svgd_optimizer, sgd_optimizer, particles.shape[1],
    )  # fmt: skip
    loop = _Loop(config, jit, n=particles.shape[0], progress=Progress.of(progress).under("stamp"),
                 redraw=redraw, checkpoint=checkpoint, deadlines=deadlines)
    carry = _Carry.init(key, particles.shape[0], backtrack=config.backtrack)
    if resume is not None:
        carry = loop.restore(resume, particles.shape, carry)
    with loop.bar:  # closed on the way out, also when a phase raises
        svgd, state, carry, sgd_converged = loop.run(steps, particles, carry, resume)
    return _result(svgd, state, carry, sgd_converged, particles.shape[1])


def _setup(config, initial_particles, redraw, *, optimizers) -> tuple[jax.Array, jax.Array]:
    """(particles (n, d), the loop's PRNG key): `run_stamp`'s arguments checked, particles drawn.

    Args:
      config: what `run_stamp` was given as its config.
      initial_particles: its (n, d) particles, or a function of a PRNG key
        returning them (called with a key split off the one of config.seed).
      redraw: its source of fresh particles, or None.
      optimizers: (SVGD's, SGD's) optimizer as given to `run_stamp` (None: the
        default, which needs the phase's learning rate).

    Raises:
      ValueError: config is not a `StampConfig`, the particles are malformed,
        or rescue is on without `redraw`.
      MjstampError: a setting the caller was to resolve (None) is still None.
    """
    if not isinstance(config, StampConfig):
        raise ValueError(f"config must be a StampConfig; got {config!r}")
    svgd_optimizer, sgd_optimizer = optimizers
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
    return particles, key


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


def _svgd_iters(carry: _Carry) -> int:
    """The SVGD iterations among the carry's records."""
    return sum(int(r.phase) == PHASE_SVGD for r in carry.rows)


def _result(svgd: SVGDState, state: SVGDState, carry: _Carry, sgd_converged: bool,
            dim: int) -> StampResult:
    """The `StampResult` of a finished run: SVGD's last state, the final one and the carry."""
    svgd_iters = _svgd_iters(carry)
    return StampResult(
        particles=state.particles, svgd_particles=svgd.particles,
        diagnostics=_stack_records(carry.rows, dim), svgd_iters=svgd_iters,
        sgd_iters=len(carry.rows) - svgd_iters,
        svgd_converged=carry.svgd_end[1], sgd_converged=sgd_converged,
        rescued=carry.rescue.rescued, nonfinite_redrawn=carry.rescue.nonfinite_redrawn,
    )  # fmt: skip


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

    def restore(self, snap: LoopSnapshot, shape: tuple[int, int], carry: _Carry) -> _Carry:
        """The carry of a snapshot: its key, records and counters (its state: `run_phase`)."""
        check_snapshot(snap, shape)
        self.bar.update(len(snap.rows))
        return restore(snap, shape, carry)

    def run(self, steps, particles: jax.Array, carry: _Carry, resume):
        """(SVGD's last state, the final state, carry, SGD converged): both phases.

        Args:
          steps: ((SVGD step, its optimizer), (SGD step, its optimizer)), `_phase_steps`.
          particles: (n, d) initial particles.
          carry: the carry to start from (a snapshot's, with `resume`).
          resume: None, or the `LoopSnapshot` to continue after.
        """
        (svgd_step, svgd_optimizer), (sgd_step, sgd_optimizer) = steps
        svgd, carry = self.run_svgd(svgd_step, init(particles, svgd_optimizer), carry, resume)
        svgd_iters = _svgd_iters(carry)
        state, carry, sgd_converged = self.run_phase(
            PHASE_SGD, sgd_step, init(svgd.particles, sgd_optimizer), carry,
            resume=resume if resume is not None and resume.phase == PHASE_SGD else None,
        )
        if len(carry.rows) > svgd_iters:
            state = state._replace(particles=_best(state.particles, carry.backtrack))
        return svgd, state, carry, sgd_converged

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
        self.bar.total = _svgd_iters(carry) + self.config.sgd_max_iters
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
        return self._iterations(phase, step, state, carry, done, max_iters)

    def _iterations(self, phase: int, step, state, carry: _Carry, done: list, max_iters: int):
        """(state, carry, converged): the compiled `step` from iteration len(done) + 1 on.

        Ends at the convergence test, the cap `max_iters` or the phase's
        deadline. done: this phase's records so far (a snapshot's; else empty).
        """
        name = "svgd" if phase == PHASE_SVGD else "sgd"
        means = [float(r.logdensity_mean) for r in done]
        moves = [float(r.displacement) for r in done]
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
                                snapshot(phase, t, state, carry))
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
