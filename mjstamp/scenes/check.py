"""Gradient health of a scene: fidelity, non-finite gradients, AD vs finite differences, speed.

`mjstamp check SCENE` draws N random particles (initial velocities or controls)
and measures the gradient model a solve would use (by default: the scene's
`GradOptions` calibrated on these particles, `fidelity.calibrate`; with
`calibrate=False` / `--iterations` / `--gradient`, the configured one) against
the scene's *own* physics, MuJoCo C with the MJCF's solver settings, which is
what plans are verified with:

* physics divergence: the largest difference of a body COM or geom centre over
  the horizon between the MJX rollout itself and the C replay of the same
  inputs (`fidelity.judge`); faithful when 95% of the particles stay within
  the tolerance, or within the spread C shows against itself from initial
  positions moved by 1e-9 m (a chaotic scene); where neither, the report names
  the geom pairs in contact at the step where the rollouts part (`parting`)
  and the pairs MJX collides differently from C (`approximate_pairs`);
* gradients: reverse-mode AD of a fixed smooth function of the MJX rollout
  against central finite differences of the same function in float64 MuJoCo C
  with the scene's own solver (`rel_err_*`), and, to tell a wrong derivative
  from a wrong model, against differences of the gradient model's C twin
  `m_grad` (`model_rel_err_*`), over the particles where the physics is smooth
  at the difference step (C's differences at `fd_eps` and `FD_CHECK` times it
  agree: `fd_smooth_particles`).

The check fails (`healthy` false, exit status 1 on the CLI) when any gradient
is non-finite, the model is not faithful, no particle is smooth at the step,
or the median relative error against the scene's own physics exceeds
`MAX_REL_ERR`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.progress import Progress
from mjstamp.scenes import fidelity
from mjstamp.scenes.rollout import replay, set_columns
from mjstamp.scenes.scene import Scene

# Median relative error of AD against the scene's own physics above which the
# gradients are not those of the physics plans are verified in: far above a faithful
# model's (float64), far below one solver iteration's on a frictional scene.
MAX_REL_ERR = 1e-3
# Central differences are a derivative only where the physics is smooth at their step: a
# particle's AD is judged where C's differences at `fd_eps` and FD_CHECK times it agree
# within MAX_REL_ERR (C's plane-cylinder contacts, a puck at rest on a table, do not).
FD_CHECK = 10.0


@dataclasses.dataclass(frozen=True)
class CheckSpec:
    """What `check` randomises in a scene.

    Attributes:
      horizon: rollout steps.
      qvel_joints: joints whose initial velocity is a particle coordinate;
        empty with `ctrl_segments == 0` means every dof.
      qvel_range: half-width of the uniform box the initial velocities come from.
      ctrl_segments: piecewise-constant control segments per actuator (each one
        particle coordinate per actuator), drawn uniformly in the ctrlrange
        scaled by `ctrl_fraction`; 0 for no controls.
      ctrl_fraction: fraction of each actuator's ctrlrange to draw from.
      ctrl_box: (low, high) per actuator to draw from instead of the scaled
        ctrlrange, or None.
    """

    horizon: int = 100
    qvel_joints: tuple[str, ...] = ()
    qvel_range: float = 1.0
    ctrl_segments: int = 0
    ctrl_fraction: float = 0.5
    ctrl_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None


@dataclasses.dataclass(frozen=True)
class Particles:
    """What a check varies.

    Attributes:
      horizon: rollout steps.
      dim: coordinates of a particle θ.
      to_inputs: (θ (n, dim), xp) -> (qpos0, qvel0, ctrl), with xp numpy or jax.numpy.
      sample: (numpy Generator, n) -> θ (n, dim).
    """

    horizon: int
    dim: int
    to_inputs: Callable
    sample: Callable


def task_particles(problem) -> Particles:
    """A task's own particles: θ uniform in its bounds over its horizon, its inputs."""
    low, high = problem.low, problem.high

    def sample(rng, n):
        return low + rng.uniform(size=(n, problem.dim)) * (high - low)

    return Particles(problem.horizon, problem.dim,
                     lambda theta, xp: problem.inputs(theta, xp=xp), sample)


def parameterisation(scene: Scene, spec: CheckSpec) -> Particles:
    """The particles of `spec` on a bare scene."""
    m = scene.m
    qpos0, qvel0 = scene.initial_state()
    T = spec.horizon
    if spec.qvel_joints or not spec.ctrl_segments:
        # N.B. by id: a hand-written scene often leaves its joints unnamed.
        joints = spec.qvel_joints or range(m.njnt)
        dofs = np.array([scene.dof_adr(j) for j in joints], dtype=int)
    else:
        dofs = np.zeros(0, dtype=int)
    nseg = spec.ctrl_segments if m.nu else 0
    if nseg and T % nseg:
        raise MjstampError(f"ctrl_segments={nseg} must divide horizon={T}")
    lo = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 0], -1.0)
    hi = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 1], 1.0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * spec.ctrl_fraction
    if spec.ctrl_box is not None:
        box_lo, box_hi = (np.asarray(b, float) for b in spec.ctrl_box)
        if box_lo.shape != (m.nu,) or box_hi.shape != (m.nu,):
            raise MjstampError(f"CheckSpec.ctrl_box needs {m.nu} values per bound")
        mid, half = (box_lo + box_hi) / 2, (box_hi - box_lo) / 2
    dim = len(dofs) + nseg * m.nu

    def to_inputs(theta, xp):
        """Theta (n, dim) -> qpos0 (n, nq), qvel0 (n, nv), ctrl (n, T, nu)."""
        n = theta.shape[0]
        qpos = xp.broadcast_to(xp.asarray(qpos0), (n, m.nq))
        qvel = xp.zeros((n, m.nv), theta.dtype)
        if len(dofs):
            qvel = set_columns(qvel, dofs, theta[:, : len(dofs)])
        if nseg:
            seg = theta[:, len(dofs) :].reshape(n, nseg, m.nu)
            ctrl = xp.repeat(seg, T // nseg, axis=1)
        else:
            ctrl = xp.zeros((n, T, m.nu), theta.dtype)
        return qpos, qvel, ctrl

    def sample(rng: np.random.Generator, n: int) -> np.ndarray:
        parts = [rng.uniform(-spec.qvel_range, spec.qvel_range, (n, len(dofs)))]
        if nseg:
            u = rng.uniform(-1, 1, (n, nseg, m.nu)) * half + mid
            parts.append(u.reshape(n, -1))
        return np.concatenate(parts, axis=1)

    return Particles(T, dim, to_inputs, sample)


def check_scene(
    scene: Scene,
    *,
    particles: int = 256,
    spec: CheckSpec | None = None,
    seed: int = 0,
    fd_eps: float = 1e-6,
    tolerance: float | None = None,
    progress=False,
    calibrate: bool = True,
) -> dict:
    """Measures the fidelity and gradient health of a bare scene; see the module docstring.

    Args:
      scene: the scene.
      particles: N random particles.
      spec: what to randomise; default `CheckSpec()`: every joint's initial
        velocity in [-1, 1] over 100 steps (a task varies its own θ: `check_task`).
      seed: draws and the projection vectors.
      fd_eps: central-difference step (float64, MuJoCo C).
      tolerance: physics divergence allowed to 95% of the particles, metres;
        default `fidelity.default_tolerance(scene)`.
      progress: status lines (`mjstamp.progress`: a callable, a `Progress`, True;
        False: none).
      calibrate: judge the gradient model a solve would use (`fidelity.calibrate`
        on these particles) rather than the scene's configured one.

    Returns:
      The report of `check`.
    """
    draws = parameterisation(scene, spec or CheckSpec())
    return check(scene, draws, particles=particles, seed=seed, fd_eps=fd_eps,
                 tolerance=tolerance, progress=progress, calibrate=calibrate)


def check_task(problem, *, particles: int = 256, **kwargs) -> dict:
    """`check` on a task's own particles (θ in its bounds, its horizon and inputs).

    Args:
      problem: the task's `Problem`, or the `Task` (built here).
      particles: N random particles.
      **kwargs: as `check_scene` (seed, fd_eps, tolerance, progress, calibrate).
    """
    if hasattr(problem, "build"):  # N.B. a Task: scenes/ cannot import tasks/, so duck-typed
        problem = problem.build()
    return check(problem.scene, task_particles(problem), particles=particles, **kwargs)


def check(
    scene: Scene,
    draws: Particles,
    *,
    particles: int = 256,
    seed: int = 0,
    fd_eps: float = 1e-6,
    tolerance: float | None = None,
    progress=False,
    calibrate: bool = True,
) -> dict:
    """Measures fidelity and gradient health on the particles `draws` describes.

    With `calibrate` (the default), first picks the gradient model a solve would
    use on these particles (`fidelity.calibrate`, on the model's MuJoCo C twin),
    then judges MJX itself with it; without, judges the scene's configured model
    and, where that is unfaithful, reports what calibration would pick. MJX is
    judged against C by `fidelity.judge`: within the tolerance, or within C's
    own chaos; where neither, the report names the geom pairs in contact at
    the step where the rollouts part.

    The differentiated function is f(θ) = c₁·qpos_T + c₂·mean_t(qpos_t), with
    c₁, c₂ fixed random unit vectors: it touches every coordinate of the state
    at every step, so a NaN anywhere in the backward pass shows up.

    Returns:
      A JSON-ready dict: healthy, problems, physics_divergence_median_m,
      physics_divergence_p95_m, judged_by, parting, nonfinite_fraction,
      rel_err_median, rel_err_p95, model_rel_err_median, us_per_particle_step,
      calibrated, and the settings.
    """
    if particles < 1:
        raise MjstampError(f"particles={particles} must be >= 1")
    say = Progress.of(progress or False, "check")  # N.B. None: silent, as before
    tolerance = fidelity.default_tolerance(scene) if tolerance is None else float(tolerance)
    if draws.dim == 0:
        raise MjstampError(f"scene {scene.name!r} has no joints or actuators to vary")
    rng = np.random.default_rng(seed)
    c1, c2 = rng.normal(size=(2, scene.m.nq))
    c1, c2 = c1 / np.linalg.norm(c1), c2 / np.linalg.norm(c2)
    theta = draws.sample(rng, particles)
    inputs = tuple(np.asarray(a, np.float64) for a in draws.to_inputs(theta, np))
    calibrated = None
    if calibrate:
        say("calibrating the gradient model on these particles, as solve does")
        calibration = fidelity.calibrate(scene, *inputs, tolerance=tolerance, progress=say)
        calibrated = _calibrated(calibration)
        a = calibration.after
        scene = scene.with_grad_options(**a.options())
    say(f"MJX rollout vs MuJoCo C with the scene's own solver ({particles} x "
        f"{draws.horizon} steps)")
    rollout = scene.rollout_fn(draws.horizon, fields=("qpos",))
    verdict = fidelity.judge(
        scene, *inputs, np.asarray(rollout(*inputs)["qpos"], np.float64),
        replay(scene, *inputs, fields=("qpos",), solver="scene")["qpos"],
        tolerance=tolerance,
    )
    grads = _gradients(scene, draws, rollout, theta, c1, c2, say)
    rel, smooth = {}, {}
    for solver in ("scene", "grad"):
        say(f"central differences in MuJoCo C, {solver} solver, steps {fd_eps:g} and "
            f"{FD_CHECK * fd_eps:g} ({4 * draws.dim * particles} float64 rollouts)")
        fd = finite_differences(scene, draws.to_inputs, theta, c1, c2, fd_eps, solver)
        wide = finite_differences(scene, draws.to_inputs, theta, c1, c2, FD_CHECK * fd_eps,
                                  solver)
        smooth[solver] = relative_errors(wide, fd, np.ones(particles, bool)) <= MAX_REL_ERR
        rel[solver] = relative_errors(grads["grad"], fd, grads["finite"] & smooth[solver])
    report = _report(scene, draws, particles, verdict, grads, rel, fd_eps,
                     int(smooth["scene"].sum()))
    if calibrated is None and not report["faithful"]:
        say("calibrating: the cheapest faithful solver setting")
        calibrated = _calibrated(
            fidelity.calibrate(scene, *inputs, tolerance=tolerance, progress=say))
    if calibrated is not None:
        report["calibrated"] = calibrated
    return report


def _calibrated(calibration: fidelity.Calibration) -> dict:
    return {
        "faithful": calibration.faithful,
        "gradient": calibration.after.gradient,
        "iterations": calibration.after.iterations,
        "ls_iterations": calibration.after.ls_iterations,
        "warmstart": calibration.after.warmstart,
        "divergence_p95_m": calibration.after.p95_m,
        "message": calibration.message(),
    }


def _report(scene, draws, particles, verdict, grads, rel, fd_eps, fd_smooth) -> dict:
    report = {
        "scene": scene.name,
        "precision": scene.precision,
        "particles": particles,
        "dim": draws.dim,
        "horizon": draws.horizon,
        "physics_divergence_median_m": verdict.median_m,
        "physics_divergence_p95_m": verdict.p95_m,
        "tolerance_m": verdict.tolerance_m,
        "faithful": verdict.faithful,
        "judged_by": verdict.judged_by,
        "chaos_p95_m": verdict.chaos_p95_m,
        "fidelity_message": verdict.message(scene.name, scene.m, draws.horizon),
        "parting": None if verdict.parting is None else verdict.parting.as_dict(scene.m),
        "approximate_pairs": verdict.as_dict(scene.m)["approximate_pairs"],
        "nonfinite": int((~grads["finite"]).sum()),
        "nonfinite_fraction": float((~grads["finite"]).mean()),
        **_error_stats("rel_err", rel["scene"]),
        **_error_stats("model_rel_err", rel["grad"]),
        "grad_norm_median": grads["norm_median"],
        "us_per_particle_step": grads["seconds"] / (particles * draws.horizon) * 1e6,
        "compile_s": grads["compile_s"],
        "fd_eps": fd_eps,
        "fd_smooth_particles": fd_smooth,
        "solver": scene.grad_options.solver,
        "gradient": scene.grad_options.gradient,
        "iterations": scene.grad_options.iterations,
        "ls_iterations": scene.grad_options.ls_iterations,
        "warmstart": scene.grad_options.warmstart,
    }
    report["problems"] = _problems(report)
    report["healthy"] = not report["problems"]
    return report


def _gradients(scene, draws: Particles, rollout, theta, c1, c2, say) -> dict:
    """Reverse-mode AD of the objective on every particle, timed."""
    particles = len(theta)

    def objective(theta):
        qpos = rollout(*draws.to_inputs(theta, jnp))["qpos"]
        return jnp.sum(qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2)

    # Summing over particles gives every particle's gradient in one reverse pass.
    value_and_grad = jax.jit(jax.value_and_grad(objective))
    theta_j = jnp.asarray(theta, scene.dtype)
    say(f"compiling value-and-grad rollout ({particles} x {draws.horizon} steps)")
    t0 = time.perf_counter()
    jax.block_until_ready(value_and_grad(theta_j))
    compile_s = time.perf_counter() - t0
    say("timing")
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        _, grad = jax.block_until_ready(value_and_grad(theta_j))
        times.append(time.perf_counter() - t0)
    grad = np.asarray(grad, np.float64)
    finite = np.isfinite(grad).all(axis=1)
    norm = float(np.median(np.linalg.norm(grad[finite], axis=1))) if finite.any() else None
    return {"grad": grad, "finite": finite, "norm_median": norm,
            "seconds": float(np.median(times)), "compile_s": compile_s}


def finite_differences(scene, to_inputs, theta, c1, c2, eps, solver) -> np.ndarray:
    """(n, dim) central differences of the objective in float64 MuJoCo C."""
    particles, dim = theta.shape
    plus = np.repeat(theta[:, None, :], dim, axis=1) + eps * np.eye(dim)
    minus = np.repeat(theta[:, None, :], dim, axis=1) - eps * np.eye(dim)
    both = np.concatenate([plus, minus]).reshape(-1, dim)
    qpos = replay(scene, *(np.asarray(a, np.float64) for a in to_inputs(both, np)),
                  solver=solver)["qpos"]
    f = (qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2).reshape(2, particles, dim)
    return (f[0] - f[1]) / (2 * eps)


def relative_errors(grad, fd, finite) -> np.ndarray:
    """|AD − FD| / max(|FD|, |AD|) per particle (rows), over the finite rows only."""
    err = np.linalg.norm(grad - fd, axis=1)
    scale = np.maximum(np.linalg.norm(fd, axis=1), np.linalg.norm(grad, axis=1))
    return err[finite] / np.maximum(scale[finite], 1e-9)


def _error_stats(prefix: str, rel: np.ndarray) -> dict:
    if not rel.size:
        return {f"{prefix}_median": None, f"{prefix}_p95": None, f"{prefix}_max": None}
    return {f"{prefix}_median": float(np.median(rel)),
            f"{prefix}_p95": float(np.percentile(rel, 95)),
            f"{prefix}_max": float(rel.max())}


def _problems(r: dict) -> list[str]:
    """One line per failed criterion of a check report."""
    out = []
    if r["nonfinite"]:
        out.append(f"{r['nonfinite']} of {r['particles']} gradients are not finite")
    if not r["faithful"]:
        out.append(
            f"the gradient model ({fidelity.describe(r['gradient'], r['iterations'])}) diverges "
            f"from the scene's own physics: {r['fidelity_message']}"
        )
    if r["fd_smooth_particles"] == 0 and not r["nonfinite"]:
        out.append(
            f"the scene's own physics is not smooth at the step {r['fd_eps']:g} on any of the "
            f"{r['particles']} particles (MuJoCo C's central differences at {r['fd_eps']:g} and "
            f"{FD_CHECK * r['fd_eps']:g} differ by more than {MAX_REL_ERR:g}), so no gradient "
            f"can be judged against them"
        )
    if r["rel_err_median"] is not None and r["rel_err_median"] > MAX_REL_ERR:
        out.append(
            f"AD gradients differ from finite differences of the scene's own physics: median "
            f"relative error {r['rel_err_median']:.2g} > {MAX_REL_ERR:g}"
        )
    return out
