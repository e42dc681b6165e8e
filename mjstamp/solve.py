"""Solve a task: STAMP on its log posterior, then decode, verify and group the plans.

Which plans are *returned*: the particles whose MJX rollout (the planner's own
model) satisfies the task's success predicate; each is then replayed in MuJoCo
C with the scene's own solver settings, and counts as *verified* when the
predicate holds there too. The task plan of a verified plan is read off its C
replay.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import sys
import time
from collections import Counter
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from mjstamp import plans as plans_mod
from mjstamp import seeding, svgd
from mjstamp.errors import MjstampError, valid_list
from mjstamp.scenes import fidelity
from mjstamp.tracecache import cached_jit

_ITERS_OF_STAMP = ("svgd_max_iters", "sgd_max_iters", "min_iters", "window", "rtol", "jacobian")


@dataclasses.dataclass(frozen=True)
class SolveConfig:
    """Settings of `solve`, validated on construction (unknown keys are an error).

    Defaults are meant to work on a task nobody tuned: step sizes follow each
    variable's box, iteration caps keep a solve to minutes, and the gradient
    model is calibrated against the scene's own physics before STAMP starts.

    Attributes:
      particles: n >= 2 particles (candidate plans).
      svgd_max_iters: cap on SVGD iterations (Algorithm 1 line 3-7).
      sgd_max_iters: cap on SGD iterations (line 8-10).
      min_iters: iterations each phase runs before the convergence test may end it.
      window: W of the convergence test (`svgd.has_converged`).
      rtol: its relative tolerance on the mean log posterior.
      motion_tol: its bound on the mean displacement per iteration, in units
        of θ; None: 1e-4 of the mean box width.
      svgd_learning_rate: Adam step of the SVGD phase in units of θ (one
        number for every coordinate); None: `svgd_step` of each coordinate's
        box width.
      sgd_learning_rate: likewise for the SGD phase; None: `sgd_step`.
      svgd_step: SVGD step as a fraction of each coordinate's box width (when
        `svgd_learning_rate` is None): 0.01, so 50 iterations can cross half
        the box.
      sgd_step: SGD step as a fraction of the box width: 0.003, finer, to
        settle into narrow modes.
      jacobian: 'auto', 'fwd' or 'rev' (see `svgd.StampConfig`).
      calibrate: pick the gradient solver's iterations so the MJX rollouts
        follow the scene's own physics (`scenes.fidelity.calibrate`).
      fidelity_tolerance: divergence allowed to 95% of the particles, metres;
        None: 1e-3 of the scene's size.
      max_solver_iterations: calibration budget (solver iterations); None:
        the MJCF's own `opt.iterations`.
      allow_unfaithful: solve even when no setting within budget is faithful
        (the result is then marked so).
      repair: refine returned plans whose MuJoCo C replay fails, in C.
      repair_rounds: rounds of the local search per plan.
      repair_samples: candidates per plan and round.
      screen: seed the particles from `screen · particles` candidates of the
        prior replayed in MuJoCo C, spread over the task plans they reach
        (`mjstamp.seeding`); 1 draws them from the prior directly.
      keep_visited: a particle whose final state is not a verified plan, or
        duplicates another's task plan, returns the plan it held at the end
        of SVGD or at the start if that one was (no plan found is lost).
    """

    particles: int = 128
    svgd_max_iters: int = 50
    sgd_max_iters: int = 100
    min_iters: int = 20
    window: int = 25
    rtol: float = 1e-3
    motion_tol: float | None = None
    svgd_learning_rate: float | None = None
    sgd_learning_rate: float | None = None
    svgd_step: float = 0.01
    sgd_step: float = 0.003
    jacobian: str = "auto"
    calibrate: bool = True
    fidelity_tolerance: float | None = None
    max_solver_iterations: int | None = None
    allow_unfaithful: bool = False
    repair: bool = True
    repair_rounds: int = 8
    repair_samples: int = 32
    screen: int = 16
    keep_visited: bool = True

    def __post_init__(self):
        ints = {"particles": 2, "svgd_max_iters": 0, "sgd_max_iters": 0, "min_iters": 0,
                "window": 1, "max_solver_iterations": 1, "repair_rounds": 0,
                "repair_samples": 1, "screen": 1}
        for name, low in ints.items():
            value = getattr(self, name)
            if value is None and name == "max_solver_iterations":
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                raise MjstampError(f"solve setting {name}={value!r} must be an integer >= {low}")
        positive = ("svgd_step", "sgd_step", "rtol")
        optional = ("motion_tol", "svgd_learning_rate", "sgd_learning_rate", "fidelity_tolerance")
        for name in positive + optional:
            value = getattr(self, name)
            if value is None and name in optional:
                continue
            ok = not isinstance(value, bool) and isinstance(value, numbers.Real)
            if not (ok and math.isfinite(value) and value > 0) and not (
                name in ("rtol", "motion_tol") and ok and value == 0
            ):
                what = "a number > 0" + (" or None" if name in optional else "")
                raise MjstampError(f"solve setting {name}={value!r} must be {what}")
        for name in ("calibrate", "allow_unfaithful", "repair", "keep_visited"):
            if not isinstance(getattr(self, name), bool):
                raise MjstampError(
                    f"solve setting {name}={getattr(self, name)!r} must be True or False"
                )
        if self.jacobian not in ("auto", "fwd", "rev"):
            raise MjstampError(
                f"solve setting jacobian={self.jacobian!r} is not valid; valid: auto, fwd, rev"
            )

    @classmethod
    def fields(cls) -> list[str]:
        """Names of the settings."""
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_dict(cls, config: Mapping[str, Any] | None, *, ignore=()) -> SolveConfig:
        """Builds a config from a dict; keys in `ignore` (a task's own settings) are skipped.

        Raises:
          MjstampError: a key that is neither a solve setting nor in `ignore`,
            naming it, the closest valid key and every valid one.
        """
        config = dict(config or {})
        valid = cls.fields()
        for key in config:
            if key in valid or key in ignore:
                continue
            close = difflib.get_close_matches(str(key), valid + list(ignore), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise MjstampError(
                f"unknown solve setting {key!r}{hint}; valid: {valid_list(valid + sorted(ignore))}"
            )
        return cls(**{k: v for k, v in config.items() if k in valid})

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready view."""
        return dataclasses.asdict(self)


def _box_widths(task) -> np.ndarray:
    """(d,) width of each coordinate's box (angles: their range)."""
    return np.concatenate([v.high - v.low for v in task.variables]).astype(np.float64)


def _scale_columns(widths: np.ndarray) -> optax.GradientTransformation:
    """Multiplies the updates of an (n, d) parameter by a (d,) vector."""

    def update(updates, state, params=None):
        del params
        return updates * jnp.asarray(widths, updates.dtype), state

    return optax.GradientTransformation(lambda _: optax.EmptyState(), update)


def _optimizer(rate: float | None, step: float, widths: np.ndarray):
    """Adam with ε in θ units (`rate`) or `step` of each coordinate's box width."""
    if rate is not None:
        return optax.inject_hyperparams(optax.adam)(learning_rate=rate)
    # N.B. Adam normalises each coordinate's gradient, so its step is ε whatever
    # the gradient's scale; ε = step · width makes it the same share of every box.
    return optax.chain(
        optax.inject_hyperparams(optax.adam)(learning_rate=step), _scale_columns(widths)
    )


@dataclasses.dataclass
class SolveResult:
    """Everything a solve produced (see `summary` for the JSON view).

    Attributes:
      task: the task as solved (on its calibrated gradient model).
      config: the solve settings, the task's own settings and the seed.
      theta: (n, d) final particles (repaired ones replaced by their repair).
      repaired: (n,) returned plans that failed in MuJoCo C and were repaired.
      fidelity: the calibration (`Calibration.as_dict`) plus the divergence of
        the MJX rollouts of the final particles from their C replays.
    """

    task: Any
    config: dict
    theta: np.ndarray
    svgd_theta: np.ndarray
    initial_theta: np.ndarray
    cost: np.ndarray
    returned: np.ndarray
    repaired: np.ndarray
    predicted: plans_mod.Decoded
    verified: plans_mod.Decoded
    replay: plans_mod.Replay
    diagnostics: svgd.StampDiagnostics
    stamp: svgd.StampResult
    rows: list[dict]
    timings: dict[str, float]
    fidelity: dict
    screen: dict | None = None
    source: np.ndarray | None = None

    @property
    def verified_fraction(self) -> float:
        """Share of returned plans whose MuJoCo C replay succeeds."""
        n = int(self.returned.sum())
        return float((self.verified.ok & self.returned).sum() / n) if n else 0.0

    def verified_mask(self) -> np.ndarray:
        """(n,) returned and verified in MuJoCo C."""
        return self.returned & self.verified.ok

    def summary(self, coverage: dict | None = None) -> dict:
        """JSON-ready summary (also the body of plans.json)."""
        ok = self.verified_mask()
        found = sorted({p for p, good in zip(self.verified.plan, ok, strict=True) if good})
        codes = sorted({c for c, good in zip(self.verified.code, ok, strict=True) if good})
        out = {
            "task": self.task.name,
            "particles": int(self.theta.shape[0]),
            "seed": int(self.config.get("seed", 0)),
            "wall_time_s": self.timings["total_s"],
            "timings": self.timings,
            "returned_plans": int(self.returned.sum()),
            "verified_plans": int(ok.sum()),
            "repaired_plans": int((self.repaired & ok).sum()),
            "verified_fraction": self.verified_fraction,
            "verified_particle_share": float(ok.sum() / len(ok)),
            "distinct_verified_task_plans": len(found),
            "distinct_verified_codes": len(codes),
            "verified_codes": codes,
            "fidelity": self.fidelity,
            "screen": self.screen,
            "kept_from_earlier": {
                name: int(((self.source == name) & ok).sum()) for name in ("svgd", "initial")
            } if self.source is not None else {},
            "task_plans": [
                {k: r[k] for k in ("task_plan", "code", "plans", "verified", "repaired",
                                   "verified_share", "best_cost")}
                for r in self.rows
            ],
            "plans": [
                {
                    "particle": int(i),
                    "task_plan": self.verified.plan[i],
                    "predicted_task_plan": self.predicted.plan[i],
                    "verified": bool(self.verified.ok[i]),
                    "repaired": bool(self.repaired[i]),
                    "source": "final" if self.source is None else str(self.source[i]),
                    "cost": float(self.cost[i]),
                    "motion_plan": {
                        name: np.asarray(val[i]).tolist()
                        for name, val in self.task.unpack(self.theta).items()
                    },
                }
                for i in np.flatnonzero(self.returned)
            ],
            "iteration_seconds": _iteration_seconds(self.diagnostics),
            "stamp": {
                "svgd_iters": self.stamp.svgd_iters,
                "sgd_iters": self.stamp.sgd_iters,
                "svgd_converged": self.stamp.svgd_converged,
                "sgd_converged": self.stamp.sgd_converged,
            },
            "config": self.config,
            "declaration": self.task.describe(),
        }
        if coverage is not None:
            out["coverage"] = coverage["coverage"]
            out["coverage_detail"] = coverage
        return out

    def arrays(self) -> dict[str, dict[str, np.ndarray]]:
        """Arrays for the result files: particles.npz and trajectories.npz."""
        d = self.diagnostics
        particles = {
            "theta": self.theta, "svgd_theta": self.svgd_theta,
            "initial_theta": self.initial_theta, "cost": self.cost,
            "returned": self.returned, "verified": self.verified.ok,
            "repaired": self.repaired,
            "source": np.asarray(
                self.source if self.source is not None else ["final"] * len(self.theta), dtype=str
            ),
            # Task plan of every particle's C replay (returned or not), for figures.
            "task_plan": np.asarray(self.verified.plan, dtype=str),
            "predicted_task_plan": np.asarray(self.predicted.plan, dtype=str),
            "logdensity_mean": d.logdensity_mean, "logdensity_max": d.logdensity_max,
            "phase": d.phase, "displacement": d.displacement, "step_seconds": d.step_seconds,
        }
        idx = np.flatnonzero(self.returned)
        qpos0, qvel0, _ = self.task.inputs(self.task.unpack(self.theta[idx]), xp=np)
        trajectories = {
            "particle": idx,
            "qpos0": np.asarray(qpos0, np.float64),
            "qvel0": np.asarray(qvel0, np.float64),
            "qpos": self.replay.qpos[idx],
            "qvel": self.replay.qvel[idx],
            "ctrl": self.replay.ctrl[idx],
            "xpos": self.replay.xpos[idx],
            "timestep": np.float64(self.task.scene.m.opt.timestep),
        }
        return {"particles": particles, "trajectories": trajectories}


def _iteration_seconds(d: svgd.StampDiagnostics) -> dict[str, float | None]:
    """Per phase: the first iteration (compile or cache load included) and the median."""
    out: dict[str, float | None] = {}
    for phase, name in ((svgd.PHASE_SVGD, "svgd"), (svgd.PHASE_SGD, "sgd")):
        t = d.step_seconds[d.phase == phase]
        out[f"{name}_first"] = float(t[0]) if len(t) else None
        out[f"{name}_median"] = float(np.median(t[1:])) if len(t) > 1 else None
    return out


def task_jit(task):
    """`jit(fn, name, *example) -> compiled fn` for this task: `_jit` bound to it.

    For `figures.save_figures(result, out, jit=task_jit(result.task))`, so a
    registered task's figures skip tracing on a re-run as its solve does.
    """
    return lambda fn, name, *example: _jit(fn, task, name, *example)


def _jit(fn, task, name: str, *example):
    """jax.jit, through the trace cache when the task has a `cache_key`.

    Only registered tasks have one (their code is mjstamp's, whose source the
    trace cache hashes, and their config is the key); a task declared in a
    user's script may change without its key changing, so it is traced anew.
    The key also holds the gradient model's options, which calibration sets.
    """
    key = getattr(task, "cache_key", None)
    if key is None:
        return jax.jit(fn)
    grad = dataclasses.asdict(task.scene.grad_options)
    return cached_jit(fn, f"{key} grad={grad} {name}", *example)


def _say(progress: bool | None):
    """Status lines on stderr unless progress is False (a terminal, a log or a pipe)."""
    show = True if progress is None else bool(progress)
    return (lambda msg: print(f"[solve] {msg}", file=sys.stderr, flush=True)) if show else (
        lambda _msg: None
    )


def calibrate(task, theta: np.ndarray, cfg: SolveConfig, *, say=None):
    """Calibrates the task's gradient model on particles θ; returns (task, Calibration).

    Raises:
      MjstampError: no setting within budget is faithful and
        `cfg.allow_unfaithful` is False (one line with the divergence).
    """
    qpos0, qvel0, ctrl = task.inputs(task.unpack(np.asarray(theta, np.float64)), xp=np)
    calibration = fidelity.calibrate(
        task.scene, qpos0, qvel0, np.asarray(ctrl, np.float64),
        tolerance=cfg.fidelity_tolerance, max_iterations=cfg.max_solver_iterations,
    )
    if not calibration.faithful and not cfg.allow_unfaithful:
        raise MjstampError(
            f"{calibration.message()}; set allow_unfaithful=True (CLI: --set "
            "allow_unfaithful=true) to solve anyway, or a larger fidelity_tolerance or "
            "max_solver_iterations"
        )
    if say is not None:
        say(calibration.message())
    after = calibration.after
    scene = task.scene.with_grad_options(
        gradient=after.gradient, iterations=after.iterations, ls_iterations=after.ls_iterations
    )
    return task.on_scene(scene), calibration


def _mjx_divergence(task, theta: np.ndarray, qpos_mjx: np.ndarray) -> np.ndarray:
    """(n,) divergence of MJX rollouts (n, T, nq) of θ from their C replays (own solver)."""
    qpos_c = plans_mod.simulate_c(task, theta).qpos
    m = task.scene.m
    return fidelity.divergence(fidelity.body_positions(m, qpos_mjx),
                               fidelity.body_positions(m, qpos_c))


def _stamp_config(cfg: SolveConfig, task, seed: int) -> svgd.StampConfig:
    widths = _box_widths(task)
    motion = cfg.motion_tol if cfg.motion_tol is not None else 1e-4 * float(widths.mean())
    return svgd.StampConfig(
        svgd_learning_rate=cfg.svgd_learning_rate or cfg.svgd_step,
        sgd_learning_rate=cfg.sgd_learning_rate or cfg.sgd_step,
        svgd_max_iters=cfg.svgd_max_iters, sgd_max_iters=cfg.sgd_max_iters,
        min_iters=cfg.min_iters, window=cfg.window, rtol=cfg.rtol, motion_tol=motion,
        seed=seed, jacobian=cfg.jacobian,
    )


def solve(
    task, config: Mapping[str, Any] | SolveConfig | None = None, *, seed: int = 0,
    progress: bool | None = None,
) -> SolveResult:
    """Runs STAMP on `task`, then decodes, verifies, repairs and groups the plans.

    Steps: draw the initial particles; calibrate the gradient model on them
    (the fewest solver iterations whose rollouts follow the scene's own
    physics); STAMP; decode every particle from its MJX rollout (returned:
    those that succeed there) and from its MuJoCo C replay with the scene's
    own solver (verified: those that succeed there too); repair returned plans
    that fail in C by a local search in C; group by task plan.

    Args:
      task: a `Task`.
      config: solve settings (`SolveConfig` or a dict of its fields; a
        registered task's own settings, `task.settings`, may be in it too and
        are recorded); None for the defaults.
      seed: makes the run reproducible.
      progress: True: tqdm bar and status lines on stderr; None: the bar on a
        terminal, status lines in any case; False: nothing.

    Returns:
      A `SolveResult`.

    Raises:
      MjstampError: an unknown or invalid setting, a declaration that is not
        complete, or a scene no setting within budget makes faithful.
    """
    task.check()
    settings = dict(getattr(task, "settings", {}) or {})
    cfg = config if isinstance(config, SolveConfig) else SolveConfig.from_dict(
        config, ignore=settings
    )
    say = _say(progress)
    t_start = time.perf_counter()
    n = cfg.particles
    screen = None
    if cfg.screen > 1:
        say(f"screening {cfg.screen * n} candidates in MuJoCo C")
        theta0, screen = seeding.seed_particles(task, jax.random.key(seed), n, screen=cfg.screen)
        theta0 = jnp.asarray(theta0, task.scene.dtype)
    else:
        theta0 = task.initial_particles(jax.random.key(seed), n)
    t_screen = time.perf_counter()
    calibration = None
    if cfg.calibrate:
        task, calibration = calibrate(task, np.asarray(theta0), cfg, say=say)

    def final(th):
        """Cost and MJX trajectory of particles at Γ(θ), from one rollout."""
        r, values = task.evaluate(th, hard=True)
        return task.cost_total(values), r.traj["qpos"]

    final = _jit(final, task, "final", jnp.asarray(theta0, task.scene.dtype))
    if calibration is not None:
        # MJX itself, not its C twin, on the particles calibrated on: the same
        # compiled evaluation the decode uses at the end.
        say("MJX rollouts of the initial particles against MuJoCo C")
        _, qpos = jax.device_get(final(jnp.asarray(theta0, task.scene.dtype)))
        div = _mjx_divergence(task, np.asarray(theta0, np.float64), np.asarray(qpos))
        mjx_p95 = float(np.percentile(div, 95))
        if mjx_p95 > calibration.tolerance_m and not cfg.allow_unfaithful:
            raise MjstampError(
                f"scene {task.scene.name!r}: MJX rollouts diverge from MuJoCo C with the "
                f"scene's own solver by p95 {mjx_p95:.2g} m > tolerance "
                f"{calibration.tolerance_m:.2g} m over {task.horizon} steps although its C "
                f"twin agrees ({calibration.after.p95_m:.2g} m): MJX collides or integrates "
                "something differently; set allow_unfaithful=True to solve anyway"
            )
        initial_mjx = {"mjx_initial_divergence_median_m": float(np.median(div)),
                       "mjx_initial_divergence_p95_m": mjx_p95}
    t_calibrate = time.perf_counter()
    widths = _box_widths(task)
    discrete = {}
    if task.has_actions:
        # Discrete SVGD (eq. 4): the surrogate ρ relaxes actions with Γ̃, the target
        # p(Γ(θ)) and the SGD refinement take them at Γ. Γ has no gradient, so SGD
        # leaves the logits alone: App. E fixes them during SGD the same way.
        discrete = {
            "log_target_fn": lambda th: task.log_posterior(th, hard=True)[0],
            "sgd_logdensity_fn": task.logdensity(hard=True),
        }
    result = svgd.run_stamp(
        task.logdensity(), theta0, task.kernel(), _stamp_config(cfg, task, seed),
        svgd_optimizer=_optimizer(cfg.svgd_learning_rate, cfg.svgd_step, widths),
        sgd_optimizer=_optimizer(cfg.sgd_learning_rate, cfg.sgd_step, widths),
        progress=progress,
        jit=lambda step, state, key, phase: _jit(step, task, f"stamp-{phase} {cfg}", state, key),
        **discrete,
    )
    jax.block_until_ready(result.particles)
    t_stamp = time.perf_counter()

    theta = np.asarray(result.particles, np.float64)

    def outcome(theta):
        cost, qpos = jax.device_get(final(jnp.asarray(theta, task.scene.dtype)))
        mjx_replay = plans_mod.Replay(task, np.asarray(qpos), source="mjx")
        replay = plans_mod.simulate_c(task, theta)
        return (np.asarray(cost, np.float64), mjx_replay, plans_mod.decode(task, mjx_replay, theta),
                replay, plans_mod.decode(task, replay, theta))

    say("decoding and verifying in MuJoCo C")
    cost, mjx_replay, predicted, replay, verified = outcome(theta)
    source = np.full(n, "final", dtype=object)
    if cfg.keep_visited:
        snapshots = {"svgd": np.asarray(result.svgd_particles, np.float64),
                     "initial": np.asarray(theta0, np.float64)}
        theta, source = _keep_visited(theta, (cost, predicted, verified), snapshots, outcome)
        if (source != "final").any():
            cost, mjx_replay, predicted, replay, verified = outcome(theta)
    returned = predicted.ok & np.isfinite(cost)
    t_verify = time.perf_counter()
    repaired = np.zeros(n, bool)
    failed = np.flatnonzero(returned & ~verified.ok)
    if cfg.repair and len(failed):
        say(f"repairing {len(failed)} returned plans that fail in MuJoCo C")
        fix = plans_mod.repair(task, theta[failed], predicted.plan[failed],
                               rounds=cfg.repair_rounds, samples=cfg.repair_samples, seed=seed)
        if fix.repaired.any():
            theta[failed[fix.repaired]] = fix.theta[fix.repaired]
            repaired[failed[fix.repaired]] = True
            cost, mjx_replay, predicted, replay, verified = outcome(theta)
    t_repair = time.perf_counter()
    divergence = fidelity.divergence(mjx_replay.xpos, replay.xpos)
    report = dict(calibration.as_dict() if calibration is not None else {"calibrated": False})
    if calibration is not None:
        report.update(initial_mjx)
    report.update(
        gradient=task.scene.grad_options.gradient,
        mjx_divergence_median_m=float(np.median(divergence)),
        mjx_divergence_p95_m=float(np.percentile(divergence, 95)),
        # N.B. the particles end where calibration may not have looked (contacts the
        # initial ones never made): their plans are verified in C whatever this says.
        faithful_at_end=bool(
            calibration is None or np.percentile(divergence, 95) <= calibration.tolerance_m
        ),
        iterations=task.scene.grad_options.iterations,
        ls_iterations=task.scene.grad_options.ls_iterations,
        us_per_particle_step=_us_per_particle_step(result.diagnostics, n, task.horizon),
    )
    rows = plans_mod.group(cost, returned, predicted, verified, repaired)
    timings = {
        "screen_s": t_screen - t_start,
        "calibrate_s": t_calibrate - t_screen,
        "stamp_s": t_stamp - t_calibrate,
        "verify_s": t_verify - t_stamp,
        "repair_s": t_repair - t_verify,
        "total_s": time.perf_counter() - t_start,
    }
    return SolveResult(
        task=task, config={**settings, **cfg.as_dict(), "seed": seed}, theta=theta,
        svgd_theta=np.asarray(result.svgd_particles, np.float64),
        initial_theta=np.asarray(theta0, np.float64), cost=cost, returned=returned,
        repaired=repaired, predicted=predicted, verified=verified, replay=replay,
        diagnostics=result.diagnostics, stamp=result, rows=rows, timings=timings,
        fidelity=report, screen=None if screen is None else screen.as_dict(), source=source,
    )


def _keep_visited(theta, final, snapshots, outcome):
    """Per particle, the best plan it visited: its final state or an earlier snapshot.

    A particle can pass through a plan that succeeds and leave it (SVGD's
    repulsion or an Adam step out of a narrow valley). No plan found is lost:
    a particle whose final state is not a returned, verified plan takes its
    latest snapshot that is one; then a particle whose final task plan other
    particles also hold takes a snapshot whose task plan none holds, if it has
    one. Deterministic (particles in index order, later snapshots first).

    Args:
      theta: (n, d) final particles.
      final: (cost, predicted, verified) of `theta`.
      snapshots: {name: (n, d)} earlier particles, latest first.
      outcome: θ -> (cost, mjx replay, predicted, C replay, verified).

    Returns:
      (theta (n, d) with chosen snapshots, source (n,) names: "final" or a key
      of `snapshots`).
    """
    def good(cost, predicted, verified):
        return predicted.ok & np.isfinite(cost) & verified.ok

    cost, predicted, verified = final
    ok = good(cost, predicted, verified)
    plan = np.asarray(verified.plan, dtype=object).copy()
    theta = theta.copy()
    source = np.full(len(theta), "final", dtype=object)
    counts = Counter(plan[ok])
    seen = {}
    for name, snap in snapshots.items():
        c, _, p, _, v = outcome(snap)
        seen[name] = (snap, good(c, p, v), np.asarray(v.plan, dtype=object))
    for i in np.flatnonzero(~ok):
        for name, (snap, good_s, plan_s) in seen.items():
            if good_s[i]:
                theta[i], source[i], plan[i], ok[i] = snap[i], name, plan_s[i], True
                counts[plan_s[i]] += 1
                break
    for i in np.flatnonzero(ok & (source == "final")):
        if counts[plan[i]] < 2:
            continue
        for name, (snap, good_s, plan_s) in seen.items():
            if good_s[i] and counts[plan_s[i]] == 0:
                counts[plan[i]] -= 1
                theta[i], source[i], plan[i] = snap[i], name, plan_s[i]
                counts[plan_s[i]] += 1
                break
    return theta, source


def _us_per_particle_step(d: svgd.StampDiagnostics, n: int, horizon: int) -> float | None:
    """Median STAMP iteration time (first of each phase left out) per particle-step, µs."""
    times = [d.step_seconds[d.phase == p][1:] for p in (svgd.PHASE_SVGD, svgd.PHASE_SGD)]
    times = np.concatenate(times)
    return float(np.median(times) / (n * horizon) * 1e6) if len(times) else None
