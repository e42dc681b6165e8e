"""Batched MJX rollouts (differentiable) and their MuJoCo C replay (verification)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import mujoco
import mujoco.rollout
import numpy as np

from mjstamp._mjx import mjx
from mjstamp.errors import MjstampError, valid_list
from mjstamp.kinematics import poses
from mjstamp.parallel import local_device
from mjstamp.scenes import gradsafe

# Fields a rollout can return, each of shape (n, T, ...) for steps 1..T.
STATE_FIELDS = ("qpos", "qvel", "ctrl")
POSE_FIELDS = ("xpos", "xquat", "xmat", "geom_xpos", "geom_xmat", "site_xpos")
FIELDS = STATE_FIELDS + POSE_FIELDS

Trajectory = dict[str, jax.Array]


def cast_floats(tree, dtype):
    """Casts the floating-point array leaves of a pytree (an MJX Model or Data) to dtype."""

    def f(x):
        if isinstance(x, (jax.Array, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.floating):
            return jnp.asarray(x, dtype)
        return x

    return jax.tree_util.tree_map(f, tree)


def set_columns(a, idx, values):
    """Returns a with a[:, idx] = values: a copy for numpy arrays, `.at[].set` for JAX."""
    if isinstance(a, np.ndarray):
        a = a.copy()
        a[:, idx] = values
        return a
    return a.at[:, idx].set(values)


def _check_fields(fields: Sequence[str]) -> tuple[str, ...]:
    fields = tuple(fields)
    for f in fields:
        if f not in FIELDS:
            raise MjstampError(f"unknown rollout field {f!r}; valid: {valid_list(FIELDS)}")
    if not fields:
        raise MjstampError(f"rollout needs at least one field; valid: {valid_list(FIELDS)}")
    return fields


def _chunk_length(horizon: int, checkpoint) -> int | None:
    """Steps per rematerialised chunk, or None for no checkpointing."""
    if checkpoint is None or checkpoint is False:
        return None
    if checkpoint == "auto":
        if horizon < 64:
            return None
        # The divisor of the horizon nearest sqrt(T): O(sqrt T) residual memory
        # for one extra forward pass in the backward sweep.
        divisors = [c for c in range(1, horizon + 1) if horizon % c == 0]
        return min(divisors, key=lambda c: abs(c - math.sqrt(horizon)))
    chunk = int(checkpoint)
    if chunk < 1 or horizon % chunk:
        raise MjstampError(
            f"checkpoint={checkpoint!r} must divide the horizon {horizon}; valid: "
            "None, 'auto' or a divisor of the horizon"
        )
    return chunk


def build_rollout(
    scene,
    horizon: int,
    *,
    fields: Sequence[str] = ("qpos", "qvel"),
    checkpoint: str | int | None = "auto",
    model_fields: Sequence[str] = (),
) -> Callable[..., Trajectory]:
    """Builds a batched, differentiable MJX rollout of `scene` over `horizon` steps.

    The returned function is `rollout(qpos0, qvel0, ctrl=None) -> {field: array}`
    with `qpos0: (n, nq)`, `qvel0: (n, nv)`, `ctrl: (n, horizon, nu)` (may be
    omitted when the scene has no actuators) and every field of shape
    `(n, horizon, ...)`, holding the state after steps 1..horizon. With
    `model_fields`, it is `rollout(qpos0, qvel0, ctrl, model)`: `model` maps
    each of those `mjx.Model` fields to (n, ...) values, one model per row
    (domain randomisation; `scenes.uncertainty.mjx_fields`). Poses
    (`xpos`, `geom_xpos`, ...) are those of that same state: MJX's step computes
    kinematics before integrating, so they are recomputed after it.

    It is `jax.jit`-compiled: one executable per batch size, reused; inside a
    caller's `jit` or `grad` it inlines. Use `Scene.rollout_fn` to share it.

    Args:
      scene: a `Scene`; its `mx` (gradient-safe options) is stepped.
      horizon: number of steps T >= 1.
      fields: which trajectories to return (see `FIELDS`).
      checkpoint: `"auto"` rematerialises chunks of about sqrt(T) steps when
        T >= 64, so reverse-mode memory grows as sqrt(T) instead of T, for one
        extra forward pass; None stores every step; an int is the chunk length.
      model_fields: names of `mjx.Model` fields given per row (see above).

    Returns:
      The rollout function.
    """
    horizon, fields, chunk, model_fields = _checked_settings(
        scene, horizon, fields, checkpoint, model_fields)
    single = _single_rollout(scene, horizon, fields, chunk, _initial_data(scene))
    batched = jax.jit(jax.vmap(single))
    mx, dtype = scene.mx, scene.dtype

    def rollout(qpos0, qvel0, ctrl=None, model=None) -> Trajectory:
        qpos0, qvel0, ctrl = _checked_inputs(scene, horizon, qpos0, qvel0, ctrl)
        return batched(qpos0, qvel0, ctrl, _checked_model(model_fields, model, qpos0.shape[0],
                                                          mx, dtype))

    rollout.horizon = horizon
    rollout.fields = fields
    rollout.chunk = chunk
    rollout.model_fields = model_fields
    return rollout


def _checked_settings(scene, horizon, fields, checkpoint, model_fields):
    """(horizon T, fields, chunk length or None, model_fields) of `build_rollout`, checked.

    Raises:
      MjstampError: T < 1, an unknown or no field, a checkpoint that does not
        divide T, or a model field `mjx.Model` lacks.
    """
    horizon = int(horizon)
    if horizon < 1:
        raise MjstampError(f"horizon={horizon} must be >= 1")
    fields = _check_fields(fields)
    chunk = _chunk_length(horizon, checkpoint)
    model_fields = tuple(model_fields)
    for f in model_fields:
        if not hasattr(scene.mx, f):
            raise MjstampError(f"model field {f!r} is not a field of mjx.Model")
    return horizon, fields, chunk, model_fields


def _initial_data(scene):
    """The `mjx.Data` every rollout starts from, in the scene's dtype, on the local device.

    N.B. built eagerly even when first asked for inside a trace (a task's log
    posterior under jit): a traced d0 memoised in the scene would leak.
    """
    with jax.ensure_compile_time_eval():
        return cast_floats(mjx.make_data(scene.mx, device=local_device()), scene.dtype)


def _single_rollout(scene, horizon: int, fields: tuple[str, ...], chunk: int | None, d0):
    """single(qpos0 (nq,), qvel0 (nv,), ctrl (T, nu), model) -> {field: (T, ...)}: one row.

    The steps run under `jax.lax.scan`, in rematerialised chunks of `chunk`
    steps when it is not None; `model` replaces fields of the scene's `mx`.
    """
    mx, nu, mode = scene.mx, scene.m.nu, scene.grad_options.gradient

    def single(qpos0, qvel0, ctrl, model):
        step = _step_fn(mx.replace(**model) if model else mx, mode, fields)
        dx = d0.replace(qpos=qpos0, qvel=qvel0)
        if chunk is None:
            return jax.lax.scan(step, dx, ctrl)[1]

        @jax.checkpoint
        def run_chunk(dx, ctrl_chunk):
            return jax.lax.scan(step, dx, ctrl_chunk)

        ctrl = ctrl.reshape(horizon // chunk, chunk, nu)
        out = jax.lax.scan(run_chunk, dx, ctrl)[1]
        return jax.tree_util.tree_map(lambda x: x.reshape(horizon, *x.shape[2:]), out)

    return single


def _step_fn(mxk, mode: str, fields: tuple[str, ...]):
    """step(dx, u) -> (dx after one MJX step of `mxk` with controls u, {field: its value})."""
    need_kinematics = any(f in POSE_FIELDS for f in fields)

    def step(dx, u):
        # N.B. read while tracing: how MJX's solver is differentiated (gradsafe).
        with gradsafe.gradient_mode(mode):
            dx = mjx.step(mxk, dx.replace(ctrl=u))
        src = mjx.kinematics(mxk, dx) if need_kinematics else dx
        return dx, {f: getattr(src, f) for f in fields}

    return step


def _checked_model(model_fields: tuple[str, ...], model, n: int, mx, dtype) -> dict:
    """Per-row model fields as arrays of the scene's dtype, or a one-line error."""
    if not model_fields:
        if model:
            raise MjstampError("this rollout takes no model fields; build it with model_fields=")
        return {}
    model = dict(model or {})
    if set(model) != set(model_fields):
        raise MjstampError(f"model fields {sorted(model)} given; valid: {sorted(model_fields)}")
    out = {}
    for f in model_fields:
        x = jnp.asarray(model[f])
        want = (n, *getattr(mx, f).shape)
        if x.shape != want:
            raise MjstampError(f"model field {f!r} has shape {x.shape}; valid: {want}")
        out[f] = x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
    return out


def _checked_inputs(scene, horizon: int, qpos0, qvel0, ctrl):
    """(qpos0, qvel0, ctrl) as arrays of the scene's dtype, or a one-line shape error."""
    m, dtype = scene.m, scene.dtype
    nq, nv, nu = m.nq, m.nv, m.nu
    qpos0 = jnp.asarray(qpos0, dtype)
    qvel0 = jnp.asarray(qvel0, dtype)
    if qpos0.ndim != 2 or qpos0.shape[1] != nq:
        raise MjstampError(f"qpos0 has shape {qpos0.shape}; valid: (n, {nq})")
    n = qpos0.shape[0]
    if qvel0.shape != (n, nv):
        raise MjstampError(f"qvel0 has shape {qvel0.shape}; valid: ({n}, {nv})")
    if ctrl is None:
        if nu:
            raise MjstampError(
                f"ctrl is missing; scene {scene.name!r} has {nu} actuators: "
                f"pass ctrl of shape ({n}, {horizon}, {nu})"
            )
        ctrl = jnp.zeros((n, horizon, 0), dtype)
    ctrl = jnp.asarray(ctrl, dtype)
    if ctrl.shape != (n, horizon, nu):
        raise MjstampError(f"ctrl has shape {ctrl.shape}; valid: ({n}, {horizon}, {nu})")
    return qpos0, qvel0, ctrl


def replay(
    scene,
    qpos0,
    qvel0,
    ctrl=None,
    *,
    horizon: int | None = None,
    fields: Sequence[str] = ("qpos", "qvel"),
    solver: str = "scene",
    models: Sequence[mujoco.MjModel] | None = None,
) -> dict[str, np.ndarray]:
    """Replays initial states and controls in MuJoCo C (float64), for verification.

    Args:
      scene: a `Scene`.
      qpos0: (n, nq) initial positions.
      qvel0: (n, nv) initial velocities.
      ctrl: (n, T, nu) controls, or None for a scene without actuators.
      horizon: T, needed when `ctrl` is None.
      fields: as in `build_rollout`.
      solver: "scene" steps `scene.m`, the scene's own solver settings (how a
        plan is verified); "grad" steps `scene.m_grad`, the MuJoCo C twin of the
        MJX model (how MJX is tested).
      models: n models of the same size signature, one per state (perturbed
        copies of the scene's, `scenes.uncertainty.sample`), instead of one.

    Returns:
      {field: (n, T, ...) float64 array}, states after steps 1..T.
    """
    if solver not in ("scene", "grad"):
        raise MjstampError(f"solver={solver!r} is not valid; valid: scene, grad")
    m = scene.m if solver == "scene" else scene.m_grad
    return replay_model(m, qpos0, qvel0, ctrl, horizon=horizon, fields=fields, models=models)


def controls(ctrl, horizon: int | None, n: int, nu: int, *, who: str) -> np.ndarray:
    """(n, T, nu) float64 controls: `ctrl`, or zeros over `horizon` steps where it is None.

    Raises:
      MjstampError: neither is given (`who` names the caller in the line).
    """
    if ctrl is None:
        if horizon is None:
            raise MjstampError(f"{who} needs ctrl or horizon")
        return np.zeros((n, int(horizon), nu))
    return np.asarray(ctrl, np.float64)


def replay_model(
    m: mujoco.MjModel,
    qpos0,
    qvel0,
    ctrl=None,
    *,
    horizon: int | None = None,
    fields: Sequence[str] = ("qpos", "qvel"),
    models: Sequence[mujoco.MjModel] | None = None,
) -> dict[str, np.ndarray]:
    """`replay` on a bare MjModel (a results directory's scene.mjb), not a `Scene`."""
    fields = _check_fields(fields)
    qpos0 = np.asarray(qpos0, np.float64)
    qvel0 = np.asarray(qvel0, np.float64)
    n = qpos0.shape[0]
    if qpos0.shape != (n, m.nq) or qvel0.shape != (n, m.nv):
        raise MjstampError(
            f"replay needs qpos0 ({n}, {m.nq}) and qvel0 ({n}, {m.nv}); got "
            f"{qpos0.shape} and {qvel0.shape}"
        )
    ctrl = controls(ctrl, horizon, n, m.nu, who="replay")
    T = ctrl.shape[1]
    if models is not None and len(models) != n:
        raise MjstampError(f"replay got {len(models)} models for {n} states; valid: one each")

    d = mujoco.MjData(m)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state0 = np.empty((n, mujoco.mj_stateSize(m, spec)))
    for i in range(n):
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = qpos0[i], qvel0[i]
        mujoco.mj_getState(m, d, state0[i], spec)
    nthread = max(1, min(n, len(_affinity())))
    datas = [mujoco.MjData(m) for _ in range(nthread)]
    state, _ = mujoco.rollout.rollout(m if models is None else list(models), datas, state0,
                                      ctrl, nstep=T)

    out: dict[str, np.ndarray] = {}
    # FULLPHYSICS state: time, qpos, qvel, act, history, warmstart, ... in that order.
    qpos = state[..., 1 : 1 + m.nq]
    qvel = state[..., 1 + m.nq : 1 + m.nq + m.nv]
    if "qpos" in fields:
        out["qpos"] = qpos.copy()
    if "qvel" in fields:
        out["qvel"] = qvel.copy()
    if "ctrl" in fields:
        out["ctrl"] = ctrl.copy()
    slow = [f for f in fields if f not in ("qpos", "qvel", "ctrl")]
    if slow:
        # N.B. the C rollout stores states, not poses: kinematics gives them.
        out.update(poses(m, qpos, slow))
        for f in ("xmat", "geom_xmat"):
            if f in out:
                out[f] = out[f].reshape(n, T, -1, 3, 3)
    return out


def _affinity() -> set[int]:
    import os

    try:
        return os.sched_getaffinity(0)
    except AttributeError:  # pragma: no cover - macOS
        return set(range(os.cpu_count() or 1))
