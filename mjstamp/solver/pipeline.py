"""Solve a task: STAMP on its log posterior, then decode, verify, repair and group the plans.

`solve(task, config)` builds the task's `Problem` once and runs, in order:
seeding (a forward-only screen in MuJoCo C, `mjstamp.seeding`), calibration of
the gradient model against the scene's own physics (`scenes.fidelity`), STAMP
(`svgd.run_stamp`), and the evaluation of the final particles.

Which plans are *returned*: the particles whose MJX rollout (the planner's own
model) satisfies the task's success predicate; each is then replayed in MuJoCo
C with the scene's own solver settings, and counts as *verified* when the
predicate holds there too. The task plan of a verified plan is read off its C
replay. A returned plan that fails in C is refined there (`verify.repair`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from mjstamp import checkpoint as checkpoint_mod
from mjstamp import parallel, results, seeding, svgd, verify
from mjstamp.config import SolveConfig
from mjstamp.errors import FidelityWarning, MjstampError
from mjstamp.progress import QUIET, Progress, ProgressLike
from mjstamp.scenes import fidelity
from mjstamp.solver.outcome import (
    MAX_SEED,
    Found,
    Outcome,
    SolveResult,
    loss_report,
    problem_jit,
)
from mjstamp.solver.selection import keep_screened, keep_visited, select_robust, take_or_give_back
from mjstamp.solver.summary import group
from mjstamp.tasks import Problem, Task, as_problem
from mjstamp.version import __version__


def _box_widths(problem: Problem) -> np.ndarray:
    """(d,) width of each coordinate's box (angles: their range)."""
    return (problem.high - problem.low).astype(np.float64)


def _scale_columns(widths: np.ndarray) -> optax.GradientTransformation:
    """Multiplies the updates of an (n, d) parameter by a (d,) vector."""

    def update(updates, state, params=None):
        del params
        return updates * jnp.asarray(widths, updates.dtype), state

    return optax.GradientTransformation(lambda _: optax.EmptyState(), update)


def box_optimizer(rate: float | None, step: float, widths: np.ndarray):
    """Adam with ε in θ units (`rate`) or `step` of each coordinate's box width."""
    if rate is not None:
        return optax.inject_hyperparams(optax.adam)(learning_rate=rate)
    # N.B. Adam normalises each coordinate's gradient, so its step is ε whatever
    # the gradient's scale; ε = step · width makes it the same share of every box.
    return optax.chain(
        optax.inject_hyperparams(optax.adam)(learning_rate=step), _scale_columns(widths)
    )


def calibrate(problem: Problem, theta: np.ndarray, cfg: SolveConfig, *, progress=False,
              reference: verify.Replay | None = None):
    """Calibrates the gradient model on particles θ; returns (problem, Calibration).

    `reference`: θ's MuJoCo C replay where the caller has it (the seeding
    screen's); None replays θ here. `progress` (`mjstamp.progress`) hears the verdict.

    Raises:
      MjstampError: no setting within budget is faithful and
        `cfg.calibration.allow_unfaithful` is False (one line with the divergence).
    """
    qpos0, qvel0, ctrl = problem.inputs(np.asarray(theta, np.float64), xp=np)
    calibration = fidelity.calibrate(
        problem.scene, qpos0, qvel0, np.asarray(ctrl, np.float64),
        tolerance=cfg.calibration.fidelity_tolerance,
        max_iterations=cfg.calibration.max_solver_iterations,
        reference=None if reference is None else reference.qpos,
    )
    if not calibration.faithful and not cfg.calibration.allow_unfaithful:
        raise MjstampError(
            f"{calibration.message()}; set calibration.allow_unfaithful=True (CLI: --set "
            "calibration.allow_unfaithful=true) to solve anyway, or a larger "
            "calibration.fidelity_tolerance or calibration.max_solver_iterations"
        )
    Progress.of(progress, "solve")(calibration.message())
    after = calibration.after
    scene = problem.scene.with_grad_options(**after.options())
    return problem.on_scene(scene), calibration


def mjx_divergence(problem: Problem, theta: np.ndarray, qpos_mjx: np.ndarray) -> np.ndarray:
    """(n,) divergence of MJX rollouts (n, T, nq) of θ from their C replays (own solver)."""
    qpos_c = verify.simulate_c(problem, theta).qpos
    m = problem.scene.m
    return fidelity.divergence(fidelity.tracked_points(m, qpos_mjx),
                               fidelity.tracked_points(m, qpos_c))


def _stamp_config(cfg: SolveConfig, problem: Problem, seed: int) -> svgd.StampConfig:
    """`cfg.stamp` with the solve's seed and motion_tol resolved (None: 1e-4 of the mean width).

    Its learning rates stay as given: None means the optimizers `_run_stamp`
    passes, scaled per coordinate by the box (`_optimizer`). Where the landing
    refines (residual costs, `landing.iterations` > 0), SGD stops after at most
    `landing.sgd_max_iters` iterations.
    """
    motion = cfg.stamp.motion_tol
    if motion is None:
        motion = 1e-4 * float(_box_widths(problem).mean())
    sgd = cfg.stamp.sgd_max_iters
    if _lands(problem, cfg) and cfg.landing.sgd_max_iters is not None:
        sgd = min(sgd, cfg.landing.sgd_max_iters)
    return dataclasses.replace(cfg.stamp, seed=seed, motion_tol=motion, sgd_max_iters=sgd)


def _lands(problem: Problem, cfg: SolveConfig) -> bool:
    """Whether the solve lands its particles in C (`_land`): residual costs, landing on."""
    return bool(cfg.landing.iterations and problem.residual_terms)


def polish_iterations(cfg: SolveConfig) -> int:
    """`polish.max_iters` resolved: None is 20 where JAX runs on an accelerator, 0 on a CPU.

    N.B. off on a CPU: where the outcome is rough at the scale of a goal (billiards'
    table: the exact derivative predicts nothing there), Levenberg–Marquardt in MJX
    lands fewer particles than the landing in C, at a higher cost a step (README,
    "Precision"); on an accelerator a batch of MJX rollouts costs about what one
    does, and the polish is cheap beside it.
    """
    if cfg.polish.max_iters is not None:
        return cfg.polish.max_iters
    return 20 if jax.default_backend() != "cpu" else 0


class _Evaluator:
    """The final evaluation of particles, compiled once per solve and reused."""

    def __init__(self, problem: Problem, example: np.ndarray):
        self.problem = problem

        def final(th):
            """Cost and MJX trajectory of particles at Γ(θ), from one rollout."""
            r, values = problem.evaluate(th, hard=True)
            return problem.cost_total(values), r.traj["qpos"]

        self.fn = problem_jit(problem)(final, "final", jnp.asarray(example, problem.scene.dtype))

    def mjx(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(cost (n,), qpos (n, T, nq)) of θ in MJX."""
        cost, qpos = jax.device_get(self.fn(jnp.asarray(theta, self.problem.scene.dtype)))
        return np.asarray(cost, np.float64), np.asarray(qpos)

    def __call__(self, theta: np.ndarray, replay: verify.Replay | None = None) -> Outcome:
        """θ's `Outcome`; `replay`: θ's MuJoCo C replay where it was made already."""
        cost, qpos = self.mjx(theta)
        mjx_replay = verify.Replay(self.problem, qpos, source="mjx")
        replay = verify.simulate_c(self.problem, theta) if replay is None else replay
        return Outcome(cost, mjx_replay, self.problem.decode(mjx_replay, theta), replay,
                       self.problem.decode(replay, theta))


BUDGET_SCREEN = 1 / 3
"""With `SolveConfig.budget`: the most of it the screen runs for, while it still yields."""

BUDGET_DRY = 2
"""With `SolveConfig.budget`: the screen stops after this many chunks without a new task plan."""

BUDGET_RESERVE = 0.2
"""With `SolveConfig.budget`: the share kept after STAMP for the polish, landing and checks."""


def _deadlines(cfg: SolveConfig, stamp: svgd.StampConfig,
               started: float) -> tuple[float | None, float | None]:
    """(SVGD's, SGD's) deadlines of a budgeted solve; (None, None) without a budget.

    What is left of the budget but its reserve, split in the ratio of the
    phases' iteration caps as the run applies them (`stamp`: `_stamp_config`'s,
    SGD's lowered where the landing refines).
    """
    if cfg.budget is None:
        return None, None
    now = time.perf_counter()
    left = max(0.0, started + cfg.budget * (1 - BUDGET_RESERVE) - now)
    caps = stamp.svgd_max_iters + stamp.sgd_max_iters
    share = stamp.svgd_max_iters / caps if caps else 1.0
    return now + left * share, now + left


def _initial_particles(problem: Problem, cfg: SolveConfig, seed: int, say):
    """(θ0 (n, d), screen report or None, the screen's successes by task plan, θ0's C replay).

    Seeded from a C screen, or drawn from the prior (no screen, no successes).
    θ0's MuJoCo C replay is made once here (the screen's own, where there is one)
    and handed to calibration, the check of MJX and the evaluation of θ0.
    """
    key = jax.random.key(seed)
    seconds, until_dry = cfg.screen.seconds, 0
    if cfg.budget is not None and cfg.screen.candidates > 1:
        # A portfolio: the screen runs on while its chunks still find new task plans.
        seconds, until_dry = max(seconds, cfg.budget * BUDGET_SCREEN), BUDGET_DRY
    if cfg.screen.candidates <= 1 and not seconds:
        theta0 = problem.init(key, cfg.particles)
        replay = verify.simulate_c(problem, np.asarray(theta0, np.float64))
        return theta0, None, {}, replay
    say(f"screening {cfg.screen.candidates * cfg.particles} candidates in MuJoCo C"
        + (f", then more for up to {seconds:g} s in all" if seconds else "")
        + (" while they find new task plans" if until_dry else ""))
    seeded = seeding.screen_particles(problem, key, cfg.particles, screen=cfg.screen.candidates,
                                      seconds=seconds, until_dry=until_dry)
    # N.B. the candidates are draws in the scene's precision: the cast is exact, and
    # the screen's replay is that of θ0.
    theta0 = jnp.asarray(seeded.particles, problem.scene.dtype)
    return theta0, seeded.screen, seeded.successes, seeded.replay


def _posterior(problem: Problem, cfg: SolveConfig, screen, seed: int, say) -> Problem:
    """The problem STAMP samples: its cost scale β (`cost_scale`) and robust planning set."""
    auto = cfg.screen.cost_scale == "auto"
    scale = seeding.auto_cost_scale(screen) if auto else float(cfg.screen.cost_scale)
    if scale != 1:
        problem = problem.with_cost_scale(scale)
        say(f"posterior log ρ = −β·C with cost_scale β = {scale:.3g}"
            + (" (auto: from the screen's costs)" if auto else ""))
    if cfg.robust.draws:
        problem = problem.with_robust(cfg.robust.draws, seed, cfg.robust.cvar)
        say(f"robust planning: every particle in {cfg.robust.draws} draws of the uncertain physics"
            + ("" if cfg.robust.cvar == 1 else f", CVaR at {cfg.robust.cvar:g}"))
    return problem


def _check_mjx(problem: Problem, evaluate: _Evaluator, theta0: np.ndarray, calibration,
               say, replay0: verify.Replay) -> dict:
    """MJX itself, not its C twin, on the calibration's particles (before STAMP starts).

    Where MJX parts from C beyond the tolerance and beyond C's own chaos
    (`fidelity.judge`), warns in one line (`FidelityWarning`) naming the geom
    pairs in contact where the rollouts part, and plans anyway: every plan is
    verified and repaired in MuJoCo C.
    """
    say("MJX rollouts of the initial particles against MuJoCo C")
    _, qpos = evaluate.mjx(theta0)
    verdict = _judge(problem, theta0, qpos, replay0.qpos, calibration.tolerance_m)
    m = problem.scene.m
    message = verdict.message(problem.scene.name, m, problem.horizon)
    if verdict.faithful:
        say(message)
    else:
        warnings.warn(f"{message}; planning anyway: every plan is verified and repaired in "
                      "MuJoCo C", FidelityWarning, stacklevel=4)
    return {"mjx_initial_divergence_median_m": verdict.median_m,
            "mjx_initial_divergence_p95_m": verdict.p95_m,
            "mjx_initial": verdict.as_dict(m)}


def _judge(problem: Problem, theta: np.ndarray, qpos_mjx: np.ndarray, qpos_c: np.ndarray,
           tolerance: float) -> fidelity.Verdict:
    """`fidelity.judge` on particles θ's inputs."""
    qpos0, qvel0, ctrl = problem.inputs(np.asarray(theta, np.float64), xp=np)
    return fidelity.judge(problem.scene, np.asarray(qpos0, np.float64), qvel0,
                          np.asarray(ctrl, np.float64), qpos_mjx, qpos_c, tolerance=tolerance,
                          horizon=problem.horizon)


def _run_stamp(problem: Problem, cfg: SolveConfig, theta0, seed: int, progress: Progress, *,
               devices: int = 1, checkpointer=None, resume=None, successes=None,
               deadlines=(None, None)):
    widths = _box_widths(problem)
    discrete = {}
    if problem.has_actions:
        # Discrete SVGD (eq. 4): the surrogate ρ relaxes actions with Γ̃, the target
        # p(Γ(θ)) and the SGD refinement take them at Γ. Γ has no gradient, so SGD
        # leaves the logits alone: App. E fixes them during SGD the same way.
        discrete = {"log_target_fn": parallel.shard_particles(problem.log_target, devices),
                    "sgd_logdensity_fn": parallel.shard_particles(problem.sgd_logdensity,
                                                                  devices)}
    jit = problem_jit(problem)
    logdensity = parallel.shard_particles(problem.logdensity, devices)
    result = svgd.run_stamp(
        logdensity, theta0, problem.kernel, _stamp_config(cfg, problem, seed),
        svgd_optimizer=box_optimizer(cfg.stamp.svgd_learning_rate, cfg.stamp.svgd_step, widths),
        sgd_optimizer=box_optimizer(cfg.stamp.sgd_learning_rate, cfg.stamp.sgd_step, widths),
        progress=progress,
        jit=lambda fn, name, *example: jit(
            parallel.replicate_outputs(fn, devices),
            f"stamp-{name} {cfg} on {devices}", *example),
        redraw=seeding.Redraw(problem, successes or {}, near=cfg.screen.rescue_near,
                              jitter=cfg.stamp.svgd_step),
        checkpoint=checkpointer, resume=resume, deadlines=deadlines,
        **discrete,
    )
    jax.block_until_ready(result.particles)
    return result


def _polish(problem: Problem, cfg: SolveConfig, theta: np.ndarray, say,
            devices: int = 1) -> svgd.PolishResult | None:
    """STAMP's particles polished by Levenberg–Marquardt on the task's residual costs.

    None where it does not run: `polish.max_iters` 0, a task without residual
    costs, or robust planning (the polish descends on the nominal model, and
    would undo what the draws' expected cost chose).
    """
    iterations = polish_iterations(cfg)
    if not iterations or not problem.residual_terms or problem.robust is not None:
        if iterations and problem.robust is not None:
            say("polish: off under robust planning (it descends on the nominal model)")
        return None
    terms = problem.residual_terms
    say(f"polishing {len(theta)} particles by Levenberg–Marquardt on "
        f"{', '.join(t.name for t in terms)} (at most {iterations} iterations)")
    jit = problem_jit(problem)
    config = dataclasses.replace(cfg.polish, max_iters=iterations)
    result = svgd.run_polish(
        parallel.shard_particles(problem.residuals, devices),
        jnp.asarray(theta, problem.scene.dtype), problem.low, problem.high, config,
        tolerances=problem.residual_tolerances(),
        jit=lambda fn, name, *example: jit(parallel.replicate_outputs(fn, devices),
                                           f"{name} {config} on {devices}", *example),
        progress=say)
    landed = "" if all(t is None for t in problem.residual_tolerances()) else (
        f"{int(result.landed.sum())} of {len(theta)} within their goals' tolerance, ")
    say(f"polish: {landed}median {np.median(result.iterations):g} iterations, "
        f"{result.seconds:.1f} s")
    return result


def _take_polished(theta: np.ndarray, polished: svgd.PolishResult, evaluate, found: Found):
    """(θ, its `Outcome`, the unpolished (θ, `Outcome`), rows given back): the polish's θ.

    A particle verified before the polish keeps its task plan: where the
    polish moved it out of it (or to a failure in C) it gets its unpolished θ
    back, so the polish deepens a plan and never swaps it. The plans verified
    before it are streamed first (`found`).
    """
    before = evaluate(theta)
    found.add(before.verified.plan[before.good], theta[before.good], "STAMP")
    proposed = np.array(polished.particles, np.float64)
    changed = np.flatnonzero(before.good & np.any(proposed != theta, axis=1))
    source = np.full(len(theta), "final", dtype=object)
    kept, _, outcome = take_or_give_back(theta, source, proposed.copy(), source.copy(), changed,
                                          evaluate, plan=before.verified.plan)
    given_back = int(np.any(kept != proposed, axis=1).sum())
    found.add(outcome.verified.plan[outcome.good], kept[outcome.good], "polished")
    return kept, outcome, (theta, before), given_back


def _polish_report(polished: svgd.PolishResult | None, landing: dict | None,
                   early: dict | None, outcome: Outcome, source: np.ndarray,
                   given_back: int = 0) -> dict | None:
    """What the polish and the landings did (None: neither ran).

    {"gradient": the polish in the gradient model (`PolishResult.as_dict`, with
    `verified`: its particles that end verified as it left them,
    `verified_landed`: those of them it landed within their goals'
    tolerance, and `given_back`: verified particles it moved out of their task
    plan, which got their θ back), "landing": the landing in C after it
    (`_land`), "early": the landing of the screen's candidates (`_land_early`)}.
    """
    if polished is None and landing is None and early is None:
        return None
    out: dict = {"gradient": None, "landing": landing, "early": early}
    if polished is not None:
        grad = {**polished.as_dict(), "given_back": given_back}
        kept = source == "final"
        grad["verified"] = int((outcome.good & kept).sum())
        grad["verified_landed"] = int((outcome.good & kept & polished.landed).sum())
        out["gradient"] = grad
    return out


def _landing_dict(result: verify.Landing, taken: int) -> dict:
    return {"particles": taken, "ok": int(result.ok.sum()), "landed": int(result.landed.sum()),
            "iterations_median": float(np.median(result.iterations)) if taken else 0.0,
            "rollouts": result.rollouts, "seconds": round(result.seconds, 3)}


def _land(problem: Problem, cfg: SolveConfig, theta, source, outcome: Outcome, evaluate, say):
    """Particles landed on their residual goals in MuJoCo C (`verify.land`), where they succeed.

    Every particle is taken (those landed already stop at once); one whose
    landing found a success in C takes it (source "landed"), unless MJX does
    not predict it to succeed (`take_or_give_back`).

    Returns:
      (theta, source, outcome, report or None where it did not run).
    """
    if not _lands(problem, cfg):
        return theta, source, outcome, None
    say(f"landing {len(theta)} particles on their goals in MuJoCo C (Gauss–Newton on central "
        f"differences, at most {cfg.landing.iterations} iterations)")
    result = verify.land(problem, theta, iterations=cfg.landing.iterations,
                         depth=cfg.landing.depth, radius=cfg.landing.radius,
                         replay=outcome.replay)
    report = _landing_dict(result, len(theta))
    say(f"landing: {report['ok']} of {len(theta)} succeed in C, {report['landed']} within "
        f"their goals' tolerance ({result.rollouts} C rollouts, {result.seconds:.1f} s)")
    changed = np.flatnonzero(result.ok & np.any(result.theta != theta, axis=1))
    if not changed.size:
        return theta, source, outcome, report
    new, new_source = theta.copy(), source.copy()
    new[changed], new_source[changed] = result.theta[changed], "landed"
    theta, source, outcome = take_or_give_back(theta, source, new, new_source, changed,
                                                evaluate)
    return theta, source, outcome, report


def _land_early(problem: Problem, cfg: SolveConfig, theta0: np.ndarray, replay0, screen,
                successes: dict, say) -> dict | None:
    """Lands the screen's chosen candidates in C before STAMP; adds what verifies to `successes`.

    The candidates are θ0, the screen's best of each of its groups (successes
    and nearest misses, spread over task plans); each plan a landing verifies
    goes first in its task plan's pool of `successes` (in place), so the solve
    returns it where no particle ends in that task plan (`keep_screened`).

    Returns:
      The landing's report, with "task_plans" it verified, or None where it did not run.
    """
    if (screen is None or not cfg.landing.early or not cfg.landing.iterations
            or not problem.residual_terms):
        return None
    say(f"landing the screen's {len(theta0)} chosen candidates in MuJoCo C")
    # N.B. here a success is enough (a task plan verified early): the depth is the end's.
    result = verify.land(problem, theta0, iterations=cfg.landing.iterations,
                         depth=cfg.landing.depth, radius=cfg.landing.radius, replay=replay0,
                         until="success")
    report = _landing_dict(result, len(theta0))
    # N.B. only what the landing moved: a candidate that succeeded as screened is in its pool.
    new = result.ok & np.any(result.theta != theta0, axis=1)
    found, plans, landed = result.theta[new], result.plan[new], result.landed[new]
    for plan in sorted(set(plans)):
        mine = np.flatnonzero(plans == plan)
        mine = mine[np.argsort(~landed[mine], kind="stable")]  # landed first
        pool = np.asarray(successes.get(plan, np.zeros((0, theta0.shape[1]))), np.float64)
        successes[plan] = np.concatenate([found[mine], pool.reshape(-1, theta0.shape[1])])
    report["task_plans"] = len(set(result.plan[result.ok]))
    say(f"landing: {report['ok']} of {len(theta0)} candidates succeed in C "
        f"({report['task_plans']} task plans), {report['landed']} within their goals' "
        f"tolerance ({result.seconds:.1f} s)")
    return report


def _settings(cfg: SolveConfig) -> dict[str, Any]:
    """The solve's settings as checkpoints hash them and results record them.

    The flat view of before the nesting (`SolveConfig.flat_dict`) and the
    groups that came after it by their dotted names ("polish.max_iters",
    "landing.early", ...): the early landing changes the screen's pools, which
    STAMP's rescues draw from, so a resume at other landing settings is refused.
    """
    groups = {f"{name}.{k}": v for name in ("polish", "landing")
              for k, v in dataclasses.asdict(getattr(cfg, name)).items()}
    return {**cfg.flat_dict(), **groups}


def _checkpointing(problem: Problem, cfg: SolveConfig, seed: int, directory, resume: bool,
                   every_s: float, resume_hint: str, say, devices: int = 1):
    """(Checkpointer or None, snapshot to resume from or None), checked before any work."""
    if directory is None:
        if resume:
            raise MjstampError("resume=True needs checkpoint_dir, the results directory "
                               "holding the checkpoint")
        return None, None
    if isinstance(every_s, bool) or not isinstance(every_s, (int, float)) or not every_s >= 0:
        raise MjstampError(f"checkpoint_every_s={every_s!r} must be a number >= 0 (seconds)")
    # N.B. the device count resolved: a resume on other devices would shard otherwise.
    # N.B. the SGD cap as the run applies it: the landing may lower it (`_stamp_config`).
    settings = {"task": dict(problem.settings), "solve": {
        **_settings(cfg), "devices": devices,
        "sgd_max_iters": _stamp_config(cfg, problem, seed).sgd_max_iters}}
    meta = {"task": problem.name, "version": __version__,
            "fingerprint": checkpoint_mod.fingerprint(problem.fingerprint, settings, seed),
            "seed": seed, "settings": settings}
    snap = None
    if resume:
        found, snap = checkpoint_mod.load(
            directory, expect={k: meta[k] for k in ("task", "version", "fingerprint")},
            settings=settings, seed=seed)
        say(f"resuming from the checkpoint of {checkpoint_mod.describe(found)}")
    results.check_writable(directory)
    checkpointer = checkpoint_mod.Checkpointer(directory, meta, every_s=every_s,
                                               resume_hint=resume_hint, progress=say)
    return checkpointer, snap


def solve(
    task: Task | Problem, config: Mapping[str, Any] | SolveConfig | None = None, *,
    seed: int = 0, progress: ProgressLike = None,
    checkpoint_dir: str | Path | None = None,
    resume: bool = False, checkpoint_every_s: float = 30.0, resume_hint: str = "",
) -> SolveResult:
    """Runs STAMP on a task, then decodes, verifies, repairs and groups the plans.

    Args:
      task: a `Task` (built here, `task.build()`) or its `Problem`.
      config: solve settings (`SolveConfig` or a dict of its fields); None for
        the defaults.
      seed: makes the run reproducible.
      progress: True: tqdm bar and status lines on stderr; None: the bar on a
        terminal, status lines in any case; False: nothing; or a callable
        taking the lines, or a `mjstamp.progress.Progress`.
      checkpoint_dir: a results directory to write `checkpoint.npz` into
        while STAMP runs (`mjstamp.checkpoint`): every `checkpoint_every_s`
        seconds (0: every iteration) and on SIGINT / SIGTERM, after which the
        solve raises `checkpoint.Interrupted`.
      resume: continue from the checkpoint in `checkpoint_dir`; the same task,
        settings and seed end with the same plans as a solve never stopped.
      checkpoint_every_s: seconds between checkpoints.
      resume_hint: the command that resumes, for the interrupt message.

    Returns:
      A `SolveResult`.

    Raises:
      MjstampError: an unknown or invalid setting, a declaration that is not
        complete, a scene no setting within budget makes faithful, or a
        checkpoint to resume that is missing, unreadable or of another solve.
      checkpoint.Interrupted: SIGINT or SIGTERM while checkpointing (the
        checkpoint is written).
    """
    with _Compiles() as compiles:
        result = _solve(task, config, seed=seed, progress=progress,
                        checkpoint_dir=checkpoint_dir, resume=resume,
                        checkpoint_every_s=checkpoint_every_s, resume_hint=resume_hint)
    result.compiles = compiles.report()
    return result


def _setup(task, config, seed, progress):
    """Checks the seed and devices; returns (problem, cfg, devices, say)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise MjstampError(f"seed={seed!r} must be an integer in 0..{MAX_SEED}")
    if progress is None and not parallel.is_lead():
        progress = QUIET  # N.B. one of several processes: process 0 speaks for all
    problem = as_problem(task)
    problem.check_relaxed()  # N.B. before the screen: STAMP relaxes every symbol
    cfg = config if isinstance(config, SolveConfig) else SolveConfig.from_dict(config)
    devices = parallel.shard_count(cfg.devices)
    if jax.process_count() > 1 and devices != jax.device_count():
        raise MjstampError(f"devices={devices}: a solve over {jax.process_count()} processes "
                           f"shards over all their {jax.device_count()} devices (devices=None)")
    return problem, cfg, devices, Progress.of(progress, "solve")


class _Start(NamedTuple):
    """The particles STAMP starts from, and what the screen found on the way."""

    theta0: Any  # (n, d) as `_initial_particles` returns them (STAMP's input)
    theta0_np: np.ndarray  # (n, d) float64
    screen: Any  # the screen's report, or None
    successes: dict[str, np.ndarray]  # {task plan: (m, d) verified in C, best first}
    replay0: verify.Replay  # θ0's C replay, made once per solve
    early: Any  # the early landing's report


def _start(problem: Problem, cfg: SolveConfig, seed: int, say, found: Found,
           clock: dict) -> _Start:
    """The screen, its task plans recorded as found, and the early landing."""
    theta0, screen, successes, replay0 = _initial_particles(problem, cfg, seed, say)
    theta0_np = np.asarray(theta0, np.float64)
    if screen is not None:  # each at the end of the chunk that verified it
        began = time.perf_counter() - screen.seconds - clock["start"]
        found.add_pools(successes, "screen",
                        {p: began + t for p, t in screen.first_seen_s.items()})
    clock["screen"] = time.perf_counter()
    early = _land_early(problem, cfg, theta0_np, replay0, screen, successes, say)
    found.add_pools(successes, "landed early")
    clock["early"] = time.perf_counter()
    return _Start(theta0, theta0_np, screen, successes, replay0, early)


def _calibrated(problem: Problem, cfg: SolveConfig, start: _Start, seed: int, say):
    """The gradient model calibrated on θ0 and checked, and the problem's posterior set.

    Returns:
      (problem, calibration or None, the fidelity report, the final `_Evaluator`).
    """
    calibration, report = None, {"calibrated": False}
    if cfg.calibration.enabled:
        problem, calibration = calibrate(problem, start.theta0_np, cfg, progress=say,
                                         reference=start.replay0)
        report = calibration.as_dict()
    evaluate = _Evaluator(problem, start.theta0_np)
    if calibration is not None:
        report.update(_check_mjx(problem, evaluate, start.theta0_np, calibration, say,
                                 start.replay0))
    problem = _posterior(problem, cfg, start.screen, seed, say)
    return problem, calibration, report, evaluate


def _stamp_phase(problem: Problem, cfg: SolveConfig, start: _Start, seed: int, say, devices,
                 checkpointer, snap, checkpoint_dir, found: Found, clock: dict):
    """STAMP from θ0, checkpointed; an interrupted solve saves what it verified first."""
    cpu = time.process_time()
    try:
        with checkpointer.catch_signals() if checkpointer else contextlib.nullcontext():
            stamp = _run_stamp(problem, cfg, start.theta0, seed, say, devices=devices,
                               checkpointer=checkpointer, resume=snap,
                               successes=start.successes,
                               deadlines=_deadlines(cfg, _stamp_config(cfg, problem, seed),
                                                    clock["start"]))
    except checkpoint_mod.Interrupted:
        found.save(checkpoint_dir)  # N.B. no plan verified is lost with the interrupted solve
        raise
    clock["stamp"] = time.perf_counter()
    clock["stamp_cpu"] = time.process_time() - cpu
    return stamp


class _Final(NamedTuple):
    """The particles a solve keeps before repair, and how it chose them."""

    theta: np.ndarray  # (n, d)
    source: np.ndarray  # (n,) where each particle's plan came from ("final", "landed", ...)
    outcome: Outcome
    visited: dict  # {name: (θ snapshot, its Outcome)}: "unpolished", "svgd", "initial"
    svgd_theta: np.ndarray  # (n, d) at the end of the SVGD phase
    loss: dict
    polished: Any  # the polish's result, or None
    landing: Any  # the landing's report
    given_back: int  # polished particles given their unpolished state back


def _final(problem: Problem, cfg: SolveConfig, stamp, start: _Start, evaluate: _Evaluator,
           seed: int, say, devices, found: Found, clock: dict) -> _Final:
    """Polish, evaluate and land STAMP's particles; keep the plans visited and screened."""
    theta = np.asarray(stamp.particles, np.float64)
    polished = _polish(problem, cfg, theta, say, devices)
    clock["polish"] = time.perf_counter()
    say("decoding and verifying in MuJoCo C")
    visited, given_back = {}, 0
    source = np.full(len(theta), "final", dtype=object)
    if polished is None:
        outcome = evaluate(theta)
        found.add(outcome.verified.plan[outcome.good], theta[outcome.good], "STAMP")
    else:
        theta, outcome, visited["unpolished"], given_back = _take_polished(theta, polished,
                                                                           evaluate, found)
    theta, source, outcome, landing = _land(problem, cfg, theta, source, outcome, evaluate, say)
    found.add(outcome.verified.plan[outcome.good], theta[outcome.good], "landed")
    clock["landing"] = time.perf_counter()
    svgd_theta = np.asarray(stamp.svgd_particles, np.float64)
    # N.B. θ0's C replay is the one made before STAMP: replayed once per solve.
    visited.update({"svgd": (svgd_theta, evaluate(svgd_theta)),
                    "initial": (start.theta0_np, evaluate(start.theta0_np, start.replay0))})
    loss = loss_report({"initial": visited["initial"][1].cost,
                         "svgd": visited["svgd"][1].cost, "final": outcome.cost})
    if cfg.verify.keep_visited:
        theta, kept = keep_visited(theta, outcome, visited)
        if (kept != "final").any():
            outcome = evaluate(theta)
        source = np.where(kept == "final", source, kept)
        theta, source, outcome = keep_screened(theta, source, outcome, start.successes,
                                               evaluate)
    if cfg.robust.select:
        theta, source, outcome = select_robust(problem, cfg, theta, source, outcome,
                                                start.successes, evaluate, seed, say)
    found.add(outcome.verified.plan[outcome.good], theta[outcome.good], "kept")
    clock["verify"] = time.perf_counter()
    return _Final(theta, source, outcome, visited, svgd_theta, loss, polished, landing,
                  given_back)


def _solve(task, config, *, seed, progress, checkpoint_dir, resume, checkpoint_every_s,
           resume_hint) -> SolveResult:
    """`solve`'s body: the stages in order, each timed on `clock`."""
    problem, cfg, devices, say = _setup(task, config, seed, progress)
    clock = {"start": time.perf_counter()}
    checkpointer, snap = _checkpointing(problem, cfg, seed, checkpoint_dir, resume,
                                        checkpoint_every_s, resume_hint, say, devices)
    found = Found(say, clock["start"])
    start = _start(problem, cfg, seed, say, found, clock)
    problem, calibration, report, evaluate = _calibrated(problem, cfg, start, seed, say)
    clock["calibrate"] = time.perf_counter()
    stamp = _stamp_phase(problem, cfg, start, seed, say, devices, checkpointer, snap,
                         checkpoint_dir, found, clock)
    final = _final(problem, cfg, stamp, start, evaluate, seed, say, devices, found, clock)
    returned = final.outcome.predicted.ok & np.isfinite(final.outcome.cost)
    theta, repaired, outcome = _repair(problem, cfg, final.theta, returned, final.outcome,
                                       evaluate, seed, say)
    found.add(outcome.verified.plan[outcome.good], theta[outcome.good], "repaired")
    clock["repair"] = time.perf_counter()
    robust = _robustness(problem, cfg, theta, returned & outcome.verified.ok,
                         outcome.verified.plan, seed, say)
    clock["robustness"] = time.perf_counter()
    # N.B. on the returned plans alone: a slice of the replay, with the JAX distances
    # (compiled once per declaration) only at their near states.
    disagreements = int(outcome.replay.rows(np.flatnonzero(returned))
                        .symbol_disagreements().sum())
    clock["symbols"] = time.perf_counter()
    initial_faithful = (report.get("mjx_initial") or {}).get("faithful", True)
    report.update(_final_fidelity(problem, outcome, calibration, stamp, len(theta), theta,
                                  initial_faithful=initial_faithful))
    return SolveResult(
        problem=problem, config={"seed": seed, "task": dict(problem.settings),
                                 "solve": _settings(cfg)},
        theta=theta, svgd_theta=final.svgd_theta,
        initial_theta=start.theta0_np, cost=outcome.cost, returned=returned, repaired=repaired,
        predicted=outcome.predicted, verified=outcome.verified, replay=outcome.replay,
        diagnostics=stamp.diagnostics, stamp=stamp,
        rows=group(outcome.cost, returned, outcome.predicted, outcome.verified,
                   repaired, None if robust is None else robust["success"]),
        timings=_timings(clock), fidelity=report,
        screen=None if start.screen is None else start.screen.as_dict(), source=final.source,
        rescue=_rescue_report(problem, cfg, stamp, final.visited["initial"][1], outcome),
        devices=devices, loss=final.loss, robustness=robust,
        polish=_polish_report(final.polished, final.landing, start.early, outcome,
                              final.source, final.given_back),
        found=found.as_dict(),
        symbol_disagreements=disagreements,
    )


class _Compiles:
    """XLA compiles of this process while active: (function, seconds) each (jax.monitoring)."""

    _listening = False
    _active: list = []

    def __enter__(self):
        if not _Compiles._listening:
            from jax._src import dispatch, monitoring  # noqa: PLC0415 - the event's name

            def listen(event, seconds, **kwargs):
                if event == dispatch.BACKEND_COMPILE_EVENT:
                    for log in _Compiles._active:
                        log.append((str(kwargs.get("fun_name", "?")), float(seconds)))

            monitoring.register_event_duration_secs_listener(listen)
            _Compiles._listening = True
        self.log: list[tuple[str, float]] = []
        _Compiles._active.append(self.log)
        return self

    def __exit__(self, *exc):
        _Compiles._active.remove(self.log)

    def report(self, min_s: float = 0.5) -> dict:
        """Compiles of at least `min_s` (the rollouts' and steps'; a cache hit takes less)."""
        big = [(name, round(t, 2)) for name, t in self.log if t >= min_s]
        # The functions that roll the scene out (the rest: kernels, optimizers, helpers).
        rollouts = sorted({name for name, _ in self.log if name.endswith(_ROLLOUT_LABELS)})
        return {"count": len(big), "seconds": round(sum(t for _, t in big), 2),
                "all_count": len(self.log), "all_seconds": round(sum(t for _, t in self.log), 2),
                "largest": sorted(big, key=lambda e: -e[1])[:8], "min_s": min_s,
                "rollouts": rollouts}


# Names (`problem_jit` labels) of the compiled functions that contain a rollout.
_ROLLOUT_LABELS = ("-evaluate)", "(final)", "(polish-step)")


def _timings(clock: dict[str, float]) -> dict[str, float]:
    order = ["start", "screen", "early", "calibrate", "stamp", "polish", "landing", "verify",
             "repair", "robustness", "symbols"]
    out = {f"{b}_s": clock[b] - clock[a] for a, b in zip(order, order[1:], strict=False)}
    # Process CPU seconds over wall seconds of STAMP: 2.0 keeps two cores busy.
    out["stamp_cpu_share"] = clock["stamp_cpu"] / max(out["stamp_s"], 1e-9)
    out["total_s"] = time.perf_counter() - clock["start"]
    return out


def _repair(problem, cfg, theta, returned, outcome, evaluate, seed, say):
    """Returned plans that fail in MuJoCo C, refined there; (θ, repaired (n,), outcome)."""
    repaired = np.zeros(len(theta), bool)
    failed = np.flatnonzero(returned & ~outcome.verified.ok)
    if not (cfg.verify.repair and len(failed)):
        return theta, repaired, outcome
    say(f"repairing {len(failed)} returned plans that fail in MuJoCo C")
    fix = verify.repair(problem, theta[failed], outcome.predicted.plan[failed],
                        rounds=cfg.verify.repair_rounds, samples=cfg.verify.repair_samples,
                        seed=seed)
    if fix.repaired.any():
        theta = theta.copy()
        theta[failed[fix.repaired]] = fix.theta[fix.repaired]
        repaired[failed[fix.repaired]] = True
        outcome = evaluate(theta)
    return theta, repaired, outcome


def _robustness(problem, cfg, theta, verified, plan, seed, say) -> dict | None:
    """Every verified plan's robustness score (`verify.robustness`), or None when off.

    Returns:
      {"samples", "seed", "seconds", "rollouts", "uncertain", "declared", "success",
      "same_plan", "cost_median", "cost_std"}: the last four (n,) arrays, NaN
      where a particle is not a verified plan.
    """
    if not cfg.verify.robustness_samples:
        return None
    idx = np.flatnonzero(verified)
    say(f"scoring {len(idx)} verified plans under uncertain physics "
        f"({cfg.verify.robustness_samples} perturbed MuJoCo C replays each)")
    rob = verify.robustness(problem, theta[idx], plan[idx],
                            samples=cfg.verify.robustness_samples, seed=seed)
    out = {"samples": rob.samples, "seed": rob.seed, "seconds": rob.seconds,
           "rollouts": rob.rollouts, "uncertain": rob.uncertain, "declared": rob.declared}
    for name in ("success", "same_plan", "cost_median", "cost_std"):
        full = np.full(len(theta), np.nan)
        full[idx] = getattr(rob, name)
        out[name] = full
    return out


def _plan_counts(decoded: verify.Decoded) -> dict[str, int]:
    counts: dict[str, int] = {}
    for ok, plan in zip(decoded.ok, decoded.plan, strict=True):
        key = plan if ok else "(no plan)"
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def _rescue_report(problem, cfg: SolveConfig, stamp, initial: Outcome,
                   outcome: Outcome) -> dict | None:
    """Re-draws of the stall rescue and the task plans (C) before and after; None when off."""
    if not cfg.stamp.rescue_window:
        return None
    initial = initial.verified
    return {"window": cfg.stamp.rescue_window, "redraws": int(stamp.rescued.sum()),
            "particles_redrawn": int((stamp.rescued > 0).sum()),
            "task_plan_counts": {"initial": _plan_counts(initial),
                                 "final": _plan_counts(outcome.verified)}}


def _final_fidelity(problem, outcome: Outcome, calibration, stamp, n: int, theta, *,
                    initial_faithful: bool) -> dict:
    """MJX against C at the final particles (`fidelity.judge`), and the model's cost.

    Warns (`FidelityWarning`) where MJX parts from C there though it did not at
    the initial particles (which warned already if it did).
    """
    out = {
        "gradient": problem.scene.grad_options.gradient,
        "iterations": problem.scene.grad_options.iterations,
        "ls_iterations": problem.scene.grad_options.ls_iterations,
        "warmstart": problem.scene.grad_options.warmstart,
        "us_per_particle_step": _us_per_particle_step(stamp.diagnostics, n, problem.horizon),
    }
    m = problem.scene.m
    tolerance = (calibration.tolerance_m if calibration is not None
                 else fidelity.default_tolerance(problem.scene))
    verdict = _judge(problem, theta, outcome.mjx_replay.qpos, outcome.replay.qpos, tolerance)
    if calibration is not None and not verdict.faithful and initial_faithful:
        # N.B. the particles found contacts the initial ones never made: say so once.
        message = verdict.message(problem.scene.name, m, problem.horizon)
        warnings.warn(f"at the final particles, {message}; their plans are verified and "
                      "repaired in MuJoCo C", FidelityWarning, stacklevel=4)
    out.update({
        "mjx_divergence_median_m": verdict.median_m,
        "mjx_divergence_p95_m": verdict.p95_m,
        # N.B. the particles end where calibration may not have looked (contacts the
        # initial ones never made): their plans are verified in C whatever this says.
        "faithful_at_end": bool(calibration is None or verdict.faithful),
        "mjx_final": verdict.as_dict(m),
    })
    return out


def _us_per_particle_step(d: svgd.StampDiagnostics, n: int, horizon: int) -> float | None:
    """Median STAMP iteration time (first of each phase left out) per particle-step, µs."""
    times = [d.step_seconds[d.phase == p][1:] for p in (svgd.PHASE_SVGD, svgd.PHASE_SGD)]
    times = np.concatenate(times)
    return float(np.median(times) / (n * horizon) * 1e6) if len(times) else None
