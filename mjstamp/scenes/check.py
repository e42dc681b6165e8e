"""Gradient health of a scene: non-finite gradients, AD vs finite differences, speed.

`mjstamp check SCENE` draws N random particles (initial velocities or controls),
differentiates a fixed smooth function of the MJX rollout with reverse-mode AD,
and compares it with central finite differences of the same function computed
in MuJoCo C, in float64, on the scene's gradient model `m_grad` (the C twin of
the MJX model: same solver options, agreeing to about 1e-11 in float64). The
reference is therefore independent of the JAX precision being checked.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.scenes.rollout import replay, set_columns
from mjstamp.scenes.scene import Scene


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


# Per shipped scene: what a planner varies there. Billiards: the cue ball's
# initial velocity over a 2 s shot (long enough for two or three cushions).
# Pushing: pusher servo set-points (joint coordinates: the pusher starts 0.15 m
# west of the block) in three segments, drawn so that the pusher stays at table
# height and ends up pressing into the block's west side in most draws.
SCENE_CHECKS = {
    "billiards": CheckSpec(horizon=200, qvel_joints=("cue_x", "cue_y"), qvel_range=3.0),
    "pushing": CheckSpec(
        horizon=150, ctrl_segments=3,
        ctrl_box=((0.0, -0.12, -0.01, -0.3, -0.3, -0.05), (0.35, 0.12, 0.01, 0.3, 0.3, 0.05)),
    ),
}


def _parameterisation(scene: Scene, spec: CheckSpec):
    """Returns (dim, to_inputs, sample) for the particles of `spec`."""
    m = scene.m
    qpos0, qvel0 = scene.initial_state()
    T = spec.horizon
    if spec.qvel_joints or not spec.ctrl_segments:
        joints = spec.qvel_joints or scene.names("joint")
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

    return dim, to_inputs, sample


def check_scene(
    scene: Scene,
    *,
    particles: int = 256,
    spec: CheckSpec | None = None,
    seed: int = 0,
    fd_eps: float = 1e-6,
    progress=None,
) -> dict:
    """Measures gradient health of `scene`; see the module docstring.

    The differentiated function is f(θ) = c₁·qpos_T + c₂·mean_t(qpos_t), with
    c₁, c₂ fixed random unit vectors: it touches every coordinate of the state
    at every step, so a NaN anywhere in the backward pass shows up.

    Args:
      scene: the scene.
      particles: N random particles.
      spec: what to randomise; defaults to `SCENE_CHECKS[scene.name]` or, for
        other scenes, every initial joint velocity in [-1, 1].
      seed: draws and the projection vectors.
      fd_eps: central-difference step (float64, MuJoCo C).
      progress: optional callable(str) for status lines.

    Returns:
      A JSON-ready dict: nonfinite_fraction, rel_err_median, rel_err_p95,
      us_per_particle_step (value-and-grad), and the settings.
    """
    if particles < 1:
        raise MjstampError(f"--particles={particles} must be >= 1")
    spec = spec or SCENE_CHECKS.get(scene.name, CheckSpec())
    say = progress or (lambda _: None)
    dim, to_inputs, sample = _parameterisation(scene, spec)
    if dim == 0:
        raise MjstampError(f"scene {scene.name!r} has no joints or actuators to vary")
    rng = np.random.default_rng(seed)
    c1, c2 = rng.normal(size=(2, scene.m.nq))
    c1, c2 = c1 / np.linalg.norm(c1), c2 / np.linalg.norm(c2)
    theta = sample(rng, particles)

    def objective_np(qpos):
        return qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2

    rollout = scene.rollout_fn(spec.horizon, fields=("qpos",))

    def objective(theta):
        qpos = rollout(*to_inputs(theta, jnp))["qpos"]
        return jnp.sum(qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2)

    # Summing over particles gives every particle's gradient in one reverse pass.
    value_and_grad = jax.jit(jax.value_and_grad(objective))
    theta_j = jnp.asarray(theta, scene.dtype)
    say(f"compiling value-and-grad rollout ({particles} x {spec.horizon} steps)")
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

    say(f"central differences in MuJoCo C ({2 * dim * particles} float64 rollouts)")
    plus = np.repeat(theta[:, None, :], dim, axis=1) + fd_eps * np.eye(dim)
    minus = np.repeat(theta[:, None, :], dim, axis=1) - fd_eps * np.eye(dim)
    both = np.concatenate([plus, minus]).reshape(-1, dim)
    qpos = replay(scene, *to_inputs(both, np), solver="grad")["qpos"]
    f = objective_np(qpos).reshape(2, particles, dim)
    fd = (f[0] - f[1]) / (2 * fd_eps)

    err = np.linalg.norm(grad - fd, axis=1)
    scale = np.maximum(np.linalg.norm(fd, axis=1), np.linalg.norm(grad, axis=1))
    rel = err[finite] / np.maximum(scale[finite], 1e-9)
    return {
        "scene": scene.name,
        "precision": scene.precision,
        "particles": particles,
        "dim": dim,
        "horizon": spec.horizon,
        "nonfinite": int((~finite).sum()),
        "nonfinite_fraction": float((~finite).mean()),
        "rel_err_median": float(np.median(rel)) if rel.size else None,
        "rel_err_p95": float(np.percentile(rel, 95)) if rel.size else None,
        "rel_err_max": float(rel.max()) if rel.size else None,
        "grad_norm_median": float(np.median(np.linalg.norm(grad[finite], axis=1)))
        if finite.any()
        else None,
        "us_per_particle_step": float(np.median(times) / (particles * spec.horizon) * 1e6),
        "compile_s": compile_s,
        "fd_eps": fd_eps,
        "solver": scene.grad_options.solver,
        "ls_iterations": scene.grad_options.ls_iterations,
    }
