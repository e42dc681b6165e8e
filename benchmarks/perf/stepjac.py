"""Gradients of MuJoCo C's own trajectories from MJX step Jacobians taken at C's states.

An alternative gradient model (issue 28, item 5), measured by
`benchmarks/perf/c_values.py`. The trajectory is MuJoCo C's, with the scene's own
solver (`rollout.replay`, `mujoco.rollout` on every core): the value of any
cost is C's by construction. Only the local derivative of each step comes from
MJX: for every particle and step t,

    A_t = ∂x_{t+1}/∂x_t,   B_t = ∂x_{t+1}/∂u_t

of one `mjx.step` evaluated at C's state x_t and control u_t. Where the step's
constraint solution comes from (`solution`): "mjx", the scene's gradient model
solves it at C's state (`Scene.mx`, its `GradOptions.gradient`: unrolled or
implicit, `gradsafe.gradient_mode`); or "c", C's own solution (recovered from
C's next velocity) is taken and the implicit derivative read there, with no
solver loop (`_implicit_at_c`). These n·T Jacobians are independent of one
another, so they are computed in one batch (`build_step_jacobians`: vmap over
particles × steps, by forward mode), then chained by the adjoint recursion of a
cost F = Σ_t ℓ_t(x_t):

    λ_T = ∇ℓ_T,   λ_t = ∇ℓ_t + A_tᵀ λ_{t+1},   ∂F/∂u_t = B_tᵀ λ_{t+1},

either by a sequential backward sweep (`chain_sweep`, a `lax.scan` of
matrix-vector products) or by an associative scan over the affine maps
λ ↦ A_tᵀ λ + ∇ℓ_t (`chain_scan`, O(log T) depth: the fully parallel form).
`build_vjp_sweep` is a third chaining that materialises no Jacobian: the same
backward sweep, each step a VJP of `mjx.step` at C's state (sequential in T,
one MJX forward and backward per step, as reverse-mode AD of a rollout).

State and tangent space. x = (qpos, qvel); nq != nv where a free or ball
joint holds a quaternion. Every Jacobian is taken in tangent coordinates
z = (dq, dv) ∈ R^{2nv}, as `mj_integratePos` and mink perturb configurations:
the input state is qpos ⊕ dq (`retract`: slide and hinge coordinates add, a
quaternion turns by q ⊗ exp(dq/2) in its local frame, MuJoCo's convention for
free and ball joint velocities), qvel + dv; the output qpos is read as
qpos' ⊖ qpos'* (`local`: 2·vec(q*⁻¹ ⊗ q'), the linearised logarithm at MJX's
own output q'*, exact to first order). A cost's gradient with respect to raw
qpos coordinates is pulled into tangent space by the transpose of
∂(qpos ⊕ dq)/∂dq at C's state, and the gradient with respect to the initial
raw qpos by the transpose of ∂(q ⊖ qpos0)/∂q. The quaternions' radial direction
is not a degree of freedom: MuJoCo normalises it away, and so does `local`.

Usage::

    traj = stepjac.c_trajectory(scene, qpos0, qvel0, ctrl)
    g_qpos0, g_qvel0, g_ctrl, value = stepjac.input_gradients(
        scene, traj, objective)           # objective(qpos, qvel) -> (n,), JAX
    g_theta = stepjac.pullback(lambda th: problem.inputs(th), theta, g_qpos0, g_qvel0, g_ctrl)

The choice (issue 28, item 5), measured by `benchmarks/perf/c_values.py`
(benchmarks/results/c_values.json; 64 particles per task, float64, the shared
2-core CPU, C's colliders ported, no GPU drawn):

- Accuracy: no difference. Against central differences of C's own physics the
  median relative error of every method agrees with rollout AD to three digits
  on all six scenes measured (billiards 2.5e-9, pushing 1.9e-10, bank_shot
  1.1e-9, rolling_ball 1.9e-9, pachinko 1.5e-6, arm_strike 3.8e-10): with C's
  colliders MJX's own rollouts stay within 1e-8 m of C's, so C's values buy
  nothing there. They would where MJX still parts from C (a pair the ports do
  not cover), which no suite scene has now.
- Cost (µs per particle-step, C rollout included): the Jacobian methods cost
  1.2-2.9x rollout AD (sweep and scan alike: 2nv + nu forward tangents per
  step against one reverse pass); `build_vjp_sweep` with C's own constraint
  solution (`c+vjp[c]`, no solver loop) costs 0.35-0.80x rollout AD (arm_strike
  309 against 767, rolling_ball 95 against 270, billiards 28 against 35).
- On a GPU (analysis, not measured): C's rollouts stay on the host's cores;
  the VJP sweep is T sequential steps as rollout AD is, so it inherits the
  same latency-bound iteration; only the Jacobian form parallelises over time
  (`chain_scan`), at its higher arithmetic cost.

Chosen: the solve keeps reverse-mode AD of MJX rollouts with C's ported
colliders (`contacts`), one compiled program on the device, values and
gradients together. This module stays as the measured alternative and a
library for users who want C's values with MJX's local derivatives; wiring
`c+vjp[c]` into the STAMP loop (a host round trip per iteration for C's
rollouts) is the cheaper CPU path and is left to the scaling work.

References:
  STAMP §IV (gradients of the rollout cost); the adjoint (costate) recursion
  of discrete-time optimal control; Blelloch, "Prefix sums and their
  applications" (1990) for the scan over affine maps.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp._mjx import mjx
from mjstamp.errors import MjstampError, valid_list
from mjstamp.parallel import local_device
from mjstamp.scenes import gradsafe
from mjstamp.scenes.rollout import cast_floats, controls, replay

CHAININGS = ("sweep", "scan", "vjp")
SOLUTIONS = ("mjx", "c")

_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
_BALL = int(mujoco.mjtJoint.mjJNT_BALL)


class Trajectory(NamedTuple):
    """MuJoCo C's states 0..T and the controls that made them.

    Attributes:
      qpos: (n, T + 1, nq) positions; [:, 0] the initial state.
      qvel: (n, T + 1, nv) velocities.
      ctrl: (n, T, nu) controls; ctrl[:, t] takes state t to state t + 1.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray


class StepJacobians(NamedTuple):
    """MJX's step Jacobians at C's states, in tangent coordinates.

    Attributes:
      A: (n, T, 2nv, 2nv) ∂z_{t+1}/∂z_t, z = (dq, dv).
      B: (n, T, 2nv, nu) ∂z_{t+1}/∂u_t.
      qpos_next: (n, T, nq) MJX's step from C's state t (compare with C's t + 1:
        the one-step defect of the gradient model, `one_step_defect`).
      qvel_next: (n, T, nv) the same for velocities.
    """

    A: jax.Array
    B: jax.Array
    qpos_next: jax.Array
    qvel_next: jax.Array


# Tangent space of qpos --------------------------------------------------------


def _layout(m: mujoco.MjModel) -> tuple[tuple[int, int, int], ...]:
    """(joint type, qpos address, dof address) per joint, static for tracing."""
    return tuple((int(m.jnt_type[j]), int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]))
                 for j in range(m.njnt))


def _quat_mul(u, v):
    """Hamilton product of (w, x, y, z) quaternions."""
    w1, x1, y1, z1 = u[0], u[1], u[2], u[3]
    w2, x2, y2, z2 = v[0], v[1], v[2], v[3]
    return jnp.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def _quat_conj(q):
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], q.dtype)


def _quat_turn(q, w):
    """Turns a quaternion: q ⊗ exp(w / 2) to first order in w, exact derivative at w = 0.

    N.B. not `mjx.math.quat_integrate`: it normalises w, whose derivative at
    w = 0 (where every Jacobian here is taken) is 0/0.
    """
    d = jnp.concatenate([jnp.ones((1,), q.dtype), 0.5 * w])
    r = _quat_mul(q, d)
    return r / jnp.linalg.norm(r)


def retract(layout, qpos: jax.Array, dq: jax.Array) -> jax.Array:
    """Computes qpos ⊕ dq: (nq,) positions moved by a (nv,) tangent (mj_integratePos, dt 1)."""
    out = qpos
    for typ, qa, da in layout:
        if typ == _FREE:
            out = out.at[qa : qa + 3].add(dq[da : da + 3])
            turned = _quat_turn(qpos[qa + 3 : qa + 7], dq[da + 3 : da + 6])
            out = out.at[qa + 3 : qa + 7].set(turned)
        elif typ == _BALL:
            out = out.at[qa : qa + 4].set(_quat_turn(qpos[qa : qa + 4], dq[da : da + 3]))
        else:
            out = out.at[qa].add(dq[da])
    return out


def local(layout, qref: jax.Array, qpos: jax.Array, nv: int) -> jax.Array:
    """Computes qpos ⊖ qref: the (nv,) tangent at qref that reaches qpos, to first order.

    Quaternions: 2·vec(q_ref⁻¹ ⊗ q), the linearised logarithm; exact in value
    and derivative at q = q_ref, where every Jacobian here is read.
    """
    out = jnp.zeros((nv,), qpos.dtype)
    for typ, qa, da in layout:
        if typ == _FREE:
            out = out.at[da : da + 3].set(qpos[qa : qa + 3] - qref[qa : qa + 3])
            rel = _quat_mul(_quat_conj(qref[qa + 3 : qa + 7]), qpos[qa + 3 : qa + 7])
            out = out.at[da + 3 : da + 6].set(2.0 * rel[1:])
        elif typ == _BALL:
            rel = _quat_mul(_quat_conj(qref[qa : qa + 4]), qpos[qa : qa + 4])
            out = out.at[da : da + 3].set(2.0 * rel[1:])
        else:
            out = out.at[da].set(qpos[qa] - qref[qa])
    return out


# C's trajectory -----------------------------------------------------------------


def c_trajectory(scene, qpos0, qvel0, ctrl=None, *, horizon: int | None = None) -> Trajectory:
    """MuJoCo C's rollout with the scene's own solver (every core), states 0..T.

    Args:
      scene: a `Scene`.
      qpos0: (n, nq) initial positions.
      qvel0: (n, nv) initial velocities.
      ctrl: (n, T, nu) controls, or None with `horizon` for a scene without actuators.
      horizon: T, when `ctrl` is None.
    """
    qpos0 = np.asarray(qpos0, np.float64)
    qvel0 = np.asarray(qvel0, np.float64)
    ctrl = controls(ctrl, horizon, len(qpos0), scene.m.nu, who="c_trajectory")
    out = replay(scene, qpos0, qvel0, ctrl, fields=("qpos", "qvel"), solver="scene")
    return Trajectory(np.concatenate([qpos0[:, None], out["qpos"]], axis=1),
                      np.concatenate([qvel0[:, None], out["qvel"]], axis=1), ctrl)


# One MJX step at a given state, in tangent coordinates --------------------------


@contextlib.contextmanager
def _mjx_solver(fn):
    """Swaps MJX's `solver.solve` while a step is traced (`forward` looks it up then).

    N.B. a trace-time swap of a module attribute, as `gradsafe` installs its own:
    not thread-safe against another thread tracing `mjx.step` at the same time.
    """
    from mujoco.mjx._src import solver  # pylint: disable=g-import-not-at-top

    saved = solver.solve
    solver.solve = fn
    try:
        yield
    finally:
        solver.solve = saved


def _implicit_at_c(m, d, vnext):
    """The implicit solver derivative at C's solution, read from C's next velocity.

    `gradsafe`'s implicit model without its forward solve: the solution q* is
    C's (MuJoCo's own solver, converged to the MJCF's tolerance), held
    constant, and one Newton step from it, q⁺ = q* − H⁻¹∇f(q*; p), is
    differentiated: dq⁺/dp = −H⁻¹ ∂∇f/∂p, the implicit-function derivative
    where ∇f(q*) = 0. Forward values are q* and the constraint forces there.

    q* is recovered from C's step: semi-implicit Euler with implicit damping
    D (MuJoCo's and MJX's `euler`) sets v' = v + h (M + hD)⁻¹ M q*, so
    q* = Δv/h + M⁻¹ D Δv, with M factored at this state by MJX (exact to
    rounding; no C call per state).
    """
    from mujoco.mjx._src import smooth, solver  # pylint: disable=g-import-not-at-top
    from mujoco.mjx._src.types import DisableBit  # pylint: disable=g-import-not-at-top

    sg = jax.lax.stop_gradient
    ds = jax.tree_util.tree_map(sg, d)
    dv = sg(vnext) - ds.qvel
    q_star = dv / m.opt.timestep
    if not m.opt.disableflags & DisableBit.EULERDAMP:
        q_star = q_star + smooth.solve_m(m, ds, m.dof_damping * dv)
    ctx = solver.Context.create(m, d.replace(qacc=q_star))
    q_new = q_star - ctx.Mgrad
    new = solver.Context.create(m, d.replace(qacc=q_new), grad=False)

    def straight(value, differentiable):
        return sg(value) + (differentiable - sg(differentiable))

    return d.tree_replace({
        "qacc": straight(q_star, q_new),
        "qfrc_constraint": straight(ctx.qfrc_constraint, new.qfrc_constraint),
        "_impl.efc_force": straight(ctx.efc_force, new.efc_force),
    })


def _step_in_tangents(scene, solution: str):
    """f(qpos, qvel, u, vnext, w) -> (z', (qpos', qvel')): one MJX step, perturbed by w.

    The step starts from (qpos ⊕ dq, qvel + dv) with control u + du, where
    w = (dq, dv, du) of size 2nv + nu; z' = (qpos' ⊖ qpos'*, qvel'), the
    output read in tangent coordinates at MJX's own output qpos'* (held
    constant). The aux output is that step's state. `solution` "mjx": the
    scene's gradient model solves the constraint problem at this state
    (`GradOptions.gradient`); "c": C's solution, recovered from C's next
    velocity `vnext`, is taken as the solution and the implicit derivative read
    there (`_implicit_at_c`).
    """
    if solution not in SOLUTIONS:
        raise MjstampError(f"solution={solution!r} is not valid; valid: {valid_list(SOLUTIONS)}")
    m, mx, dtype = scene.m, scene.mx, scene.dtype
    nv = m.nv
    layout = _layout(m)
    mode = scene.grad_options.gradient
    if solution == "c" and scene.grad_options.solver != "newton":
        raise MjstampError("solution='c' needs the Newton solver (its Hessian gives the "
                           "implicit derivative)")
    if solution == "c" and m.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
        integrator = mujoco.mjtIntegrator(m.opt.integrator).name
        raise MjstampError("solution='c' recovers C's solution from its Euler step; scene "
                           f"{scene.name!r} integrates with {integrator}")
    # N.B. built eagerly, as in `rollout.build_rollout`: a traced d0 would leak.
    with jax.ensure_compile_time_eval():
        d0 = cast_floats(mjx.make_data(mx, device=local_device()), dtype)

    def f(qpos, qvel, u, vnext, w):
        dq, dv, du = w[:nv], w[nv : 2 * nv], w[2 * nv :]
        dx = d0.replace(qpos=retract(layout, qpos, dq), qvel=qvel + dv, ctrl=u + du)
        if solution == "c":
            def solve(m, d):
                # N.B. closes over this trace's vnext; installed while tracing only.
                return _implicit_at_c(m, d, vnext)

            with _mjx_solver(solve):
                dx = mjx.step(mx, dx)
        else:
            # N.B. read while tracing: how MJX's solver is differentiated (gradsafe).
            with gradsafe.gradient_mode(mode):
                dx = mjx.step(mx, dx)
        zq = local(layout, jax.lax.stop_gradient(dx.qpos), dx.qpos, nv)
        return jnp.concatenate([zq, dx.qvel]), (dx.qpos, dx.qvel)

    return f


def build_step_jacobians(scene, *, solution: str = "mjx",
                         batch: int = 64) -> Callable[[Trajectory], StepJacobians]:
    """Builds `jacobians(traj) -> StepJacobians` for `scene`'s gradient model.

    All n·T steps are independent: they run as one flat batch (`lax.map` over
    chunks of `batch` states, each chunk a vmap), by forward mode with
    2nv + nu tangents sharing one primal step. `jax.jit`-compiled, one
    executable per (n, T).

    Args:
      scene: a `Scene`; its `mx` and `grad_options` are used.
      solution: "mjx": MJX solves each step's constraint problem (the scene's
        gradient model, as a rollout would); "c": C's solved acceleration is
        the solution and only the implicit derivative is computed there (no
        solver loop; needs the Newton solver).
      batch: states per vmapped chunk. Memory: about batch · (2nv + nu) MJX
        step tangents at once. N.B. on a CPU small chunks cost less per state
        (bank_shot, 3200 states: 134 µs at 64, 226 µs at 256 with "mjx",
        whose solver loop runs every state of a chunk until its slowest has
        converged; 56 and 88 µs with "c"); a GPU wants them large.
    """
    m = scene.m
    nv, nu = m.nv, m.nu
    f = _step_in_tangents(scene, solution)

    def one(qpos, qvel, u, vnext):
        w0 = jnp.zeros((2 * nv + nu,), scene.dtype)
        jac, (qpos1, qvel1) = jax.jacfwd(lambda w: f(qpos, qvel, u, vnext, w), has_aux=True)(w0)
        return jac[:, : 2 * nv], jac[:, 2 * nv :], qpos1, qvel1

    @jax.jit
    def flat(qpos, qvel, ctrl):
        n, T = ctrl.shape[:2]
        k = n * T
        size = min(batch, k)
        chunks = -(-k // size)

        def chunked(x):
            # N.B. explicit shapes, not lax.map's batch_size (which reshapes with -1:
            # a size-0 ctrl of a scene without actuators cannot take it); the last
            # chunk is padded with copies of a real state, and dropped after.
            x = x.reshape(k, *x.shape[2:])
            if chunks * size > k:
                x = jnp.concatenate([x, jnp.repeat(x[-1:], chunks * size - k, axis=0)])
            return x.reshape(chunks, size, *x.shape[1:])

        xs = (chunked(qpos[:, :-1]), chunked(qvel[:, :-1]), chunked(ctrl), chunked(qvel[:, 1:]))
        out = jax.lax.map(lambda x: jax.vmap(one)(*x), xs)
        return StepJacobians(*(o.reshape(chunks * size, *o.shape[2:])[:k]
                               .reshape(n, T, *o.shape[2:]) for o in out))

    def jacobians(traj: Trajectory) -> StepJacobians:
        _check_traj(scene, traj)
        return flat(*(jnp.asarray(a, scene.dtype) for a in traj))

    jacobians.jitted = flat  # (qpos, qvel, ctrl) arrays -> StepJacobians; for lower()
    return jacobians


def one_step_defect(scene, traj: Trajectory, jac: StepJacobians) -> np.ndarray:
    """(n, T) largest |qpos| difference of MJX's step from C's state t and C's state t + 1.

    How far the gradient model's dynamics is from C's where the Jacobians are
    read: rounding (1e-15) where MJX steps as C does, larger where it collides
    or solves differently.
    """
    del scene
    return np.abs(np.asarray(jac.qpos_next) - traj.qpos[:, 1:]).max(axis=-1)


def _check_traj(scene, traj: Trajectory) -> None:
    m = scene.m
    n, T1 = traj.qpos.shape[:2]
    want = {"qpos": (n, T1, m.nq), "qvel": (n, T1, m.nv), "ctrl": (n, T1 - 1, m.nu)}
    for name, shape in want.items():
        if np.shape(getattr(traj, name)) != shape:
            raise MjstampError(f"trajectory {name} has shape {np.shape(getattr(traj, name))}; "
                               f"valid: {shape}")


# Cost gradients into tangent space and back ------------------------------------


@functools.partial(jax.jit, static_argnames=("layout",))
def _tangent_cotangents(qpos, dqpos, dqvel, *, layout):
    nv = dqvel.shape[-1]

    def pull(q, g):
        return jax.vjp(lambda dq: retract(layout, q, dq), jnp.zeros((nv,), q.dtype))[1](g)[0]

    return jnp.concatenate([jax.vmap(jax.vmap(pull))(qpos, dqpos), dqvel], axis=-1)


def tangent_cotangents(scene, traj: Trajectory, dqpos, dqvel=None) -> jax.Array:
    """(n, T, 2nv) ∇ℓ_t in tangent coordinates from gradients in raw coordinates.

    ∇_z ℓ = (∂(qpos ⊕ dq)/∂dqᵀ ∂F/∂qpos, ∂F/∂qvel) at C's states.

    Args:
      scene: the `Scene`.
      traj: C's trajectory.
      dqpos: (n, T, nq) ∂F/∂qpos_t of the states after steps 1..T.
      dqvel: (n, T, nv) ∂F/∂qvel_t, or None for none.
    """
    qpos = jnp.asarray(traj.qpos[:, 1:], scene.dtype)
    dqpos = jnp.asarray(dqpos, scene.dtype)
    dqvel = (jnp.zeros(qpos.shape[:2] + (scene.m.nv,), scene.dtype) if dqvel is None
             else jnp.asarray(dqvel, scene.dtype))
    return _tangent_cotangents(qpos, dqpos, dqvel, layout=_layout(scene.m))


@functools.partial(jax.jit, static_argnames=("layout",))
def _initial_gradients(qpos0, lam0, *, layout):
    nv = lam0.shape[-1] // 2

    def pull(q0, g):
        return jax.vjp(lambda q: local(layout, q0, q, nv), q0)[1](g)[0]

    return jax.vmap(pull)(qpos0, lam0[:, :nv]), lam0[:, nv:]


def initial_gradients(scene, qpos0, lam0) -> tuple[jax.Array, jax.Array]:
    """(∂F/∂qpos0 (n, nq), ∂F/∂qvel0 (n, nv)) from the tangent adjoint λ₀ (n, 2nv).

    ∂F/∂qpos0 = ∂(q ⊖ qpos0)/∂qᵀ λ₀: a gradient in raw coordinates, with the
    radial direction of every quaternion (which MuJoCo normalises away) 0.

    Args:
      scene: the `Scene`.
      qpos0: (n, nq) the initial positions (`Trajectory.qpos[:, 0]`).
      lam0: (n, 2nv) from `chain_sweep`, `chain_scan` or `build_vjp_sweep`.
    """
    return _initial_gradients(jnp.asarray(qpos0, scene.dtype), lam0, layout=_layout(scene.m))


# Chaining ------------------------------------------------------------------------


@jax.jit
def chain_sweep(A, B, G) -> tuple[jax.Array, jax.Array]:
    """Adjoint recursion by a sequential backward sweep (matrix-vector products).

    Args:
      A: (n, T, k, k) state Jacobians, k = 2nv.
      B: (n, T, k, nu) control Jacobians.
      G: (n, T, k) ∇ℓ at the states after steps 1..T.

    Returns:
      λ₀ (n, k), the gradient with respect to the initial tangent, and
      ∂F/∂u (n, T, nu).
    """
    G_prev = jnp.concatenate([jnp.zeros_like(G[:, :1]), G[:, :-1]], axis=1)

    def back(lam, t):  # lam = λ_{t+1}
        a, b, g = A[:, t], B[:, t], G_prev[:, t]
        gu = jnp.einsum("nki,nk->ni", b, lam)
        return jnp.einsum("nki,nk->ni", a, lam) + g, gu

    T = A.shape[1]
    lam0, gu = jax.lax.scan(back, G[:, -1], jnp.arange(T), reverse=True)
    return lam0, jnp.swapaxes(gu, 0, 1)


@jax.jit
def chain_scan(A, B, G) -> tuple[jax.Array, jax.Array]:
    """Adjoint recursion by an associative scan over affine maps: O(log T) depth.

    λ_t = A_tᵀ λ_{t+1} + ∇ℓ_t is the affine map e_t: λ ↦ M_t λ + b_t applied to
    λ_{t+1}; λ_t = (e_t ∘ e_{t+1} ∘ … ∘ e_{T−1})(λ_T), and composing affine maps
    is associative, so every λ_t comes from one `lax.associative_scan`
    (reverse: each output composes an element with everything after it).
    Arguments and returns as `chain_sweep`.
    """
    G_prev = jnp.concatenate([jnp.zeros_like(G[:, :1]), G[:, :-1]], axis=1)
    M = jnp.swapaxes(A, -1, -2)

    def compose(later, earlier):
        # N.B. with reverse=True, lax.associative_scan calls fn(accumulated later
        # elements, this element): the result is earlier ∘ later.
        m_l, b_l = later
        m_e, b_e = earlier
        return m_e @ m_l, jnp.einsum("...ij,...j->...i", m_e, b_l) + b_e

    Mh, bh = jax.lax.associative_scan(compose, (M, G_prev), reverse=True, axis=1)
    lam_T = G[:, -1]
    lam = jnp.einsum("ntij,nj->nti", Mh, lam_T) + bh  # λ_0 .. λ_{T-1}
    lam_next = jnp.concatenate([lam[:, 1:], lam_T[:, None]], axis=1)  # λ_1 .. λ_T
    gu = jnp.einsum("ntki,ntk->nti", B, lam_next)
    return lam[:, 0], gu


def build_vjp_sweep(scene, *, solution: str = "mjx") -> Callable:
    """Builds `sweep(traj, G) -> (λ₀, ∂F/∂u)` without Jacobians: one VJP of `mjx.step` per step.

    The backward sweep of `chain_sweep`, with each A_tᵀλ, B_tᵀλ a vector-Jacobian
    product of the MJX step at C's state t (vmap over particles, `lax.scan`
    over steps in reverse). Sequential in T; memory O(n) per step. `solution`
    as `build_step_jacobians`.
    """
    m = scene.m
    nv, nu = m.nv, m.nu
    f = _step_in_tangents(scene, solution)

    def one(qpos, qvel, u, vnext, lam):
        w0 = jnp.zeros((2 * nv + nu,), scene.dtype)
        _, pullback = jax.vjp(lambda w: f(qpos, qvel, u, vnext, w)[0], w0)
        (g,) = pullback(lam)
        return g[: 2 * nv], g[2 * nv :]

    @jax.jit
    def sweep(qpos, qvel, ctrl, G):
        G_prev = jnp.concatenate([jnp.zeros_like(G[:, :1]), G[:, :-1]], axis=1)

        def back(lam, t):
            gz, gu = jax.vmap(one)(qpos[:, t], qvel[:, t], ctrl[:, t], qvel[:, t + 1], lam)
            return gz + G_prev[:, t], gu

        T = ctrl.shape[1]
        lam0, gu = jax.lax.scan(back, G[:, -1], jnp.arange(T), reverse=True)
        return lam0, jnp.swapaxes(gu, 0, 1)

    def run(traj: Trajectory, G):
        _check_traj(scene, traj)
        return sweep(*(jnp.asarray(a, scene.dtype) for a in traj), G)

    run.jitted = sweep  # (qpos, qvel, ctrl, G) -> (λ₀, ∂F/∂u); for lower()
    return run


# All together ------------------------------------------------------------------------


def objective_gradients(objective: Callable, traj: Trajectory, dtype=jnp.float64):
    """F per particle on C's trajectory and its raw gradients ∂F/∂qpos_t, ∂F/∂qvel_t.

    Args:
      objective: (qpos (n, T, nq), qvel (n, T, nv)) -> (n,) JAX function of the
        states after steps 1..T.
      traj: C's trajectory.
      dtype: the float type of the evaluation (the scene's).

    Returns:
      value (n,), dqpos (n, T, nq), dqvel (n, T, nv).
    """
    return _objective_gradients(jnp.asarray(traj.qpos[:, 1:], dtype),
                                jnp.asarray(traj.qvel[:, 1:], dtype), objective=objective)


@functools.partial(jax.jit, static_argnames=("objective",))
def _objective_gradients(qpos, qvel, *, objective):
    # N.B. static: one compile per objective function object; reuse the object.
    value, vjp = jax.vjp(objective, qpos, qvel)
    dqpos, dqvel = vjp(jnp.ones_like(value))
    return value, dqpos, dqvel


def check_objective(c1, c2) -> Callable:
    """The objective of `scenes.check`: f = c₁·qpos_T + c₂·mean_t qpos_t, per particle."""
    c1, c2 = jnp.asarray(c1), jnp.asarray(c2)

    def objective(qpos, qvel):
        del qvel
        return qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2

    return objective


@functools.lru_cache(maxsize=16)
def _builders(scene, solution: str, batch: int):
    # N.B. keyed by the Scene object (hashed by identity): one compiled set per scene.
    return (build_step_jacobians(scene, solution=solution, batch=batch),
            build_vjp_sweep(scene, solution=solution))


def input_gradients(scene, traj: Trajectory, objective: Callable, *, chaining: str = "sweep",
                    solution: str = "mjx", batch: int = 64):
    """Gradient of an objective of C's trajectory with respect to the rollout's inputs.

    Args:
      scene: a `Scene` (its gradient model supplies the step Jacobians).
      traj: C's trajectory (`c_trajectory`).
      objective: (qpos (n, T, nq), qvel (n, T, nv)) -> (n,), a JAX function of
        the states after steps 1..T (`check_objective` for `scenes.check`'s).
      chaining: "sweep" or "scan" (Jacobians, then `chain_sweep` /
        `chain_scan`), or "vjp" (`build_vjp_sweep`, no Jacobians).
      solution: "mjx" (MJX solves each step's constraints with the scene's
        gradient model) or "c" (C's solution, the implicit derivative there);
        see `build_step_jacobians`.
      batch: states per vmapped chunk of the Jacobians.

    Returns:
      ∂F/∂qpos0 (n, nq), ∂F/∂qvel0 (n, nv), ∂F/∂ctrl (n, T, nu), and F (n,), C's value.
    """
    if chaining not in CHAININGS:
        raise MjstampError(f"chaining={chaining!r} is not valid; valid: {valid_list(CHAININGS)}")
    if solution not in SOLUTIONS:
        raise MjstampError(f"solution={solution!r} is not valid; valid: {valid_list(SOLUTIONS)}")
    jacobians, vjp_sweep = _builders(scene, solution, int(batch))
    value, dqpos, dqvel = objective_gradients(objective, traj, scene.dtype)
    G = tangent_cotangents(scene, traj, dqpos, dqvel)
    if chaining == "vjp":
        lam0, gu = vjp_sweep(traj, G)
    else:
        jac = jacobians(traj)
        lam0, gu = (chain_sweep if chaining == "sweep" else chain_scan)(jac.A, jac.B, G)
    g_qpos0, g_qvel0 = initial_gradients(scene, traj.qpos[:, 0], lam0)
    return g_qpos0, g_qvel0, gu, value


def pullback(to_inputs: Callable, theta, g_qpos0, g_qvel0, g_ctrl) -> jax.Array:
    """∂F/∂θ (n, d) from the inputs' gradients, through θ -> (qpos0, qvel0, ctrl).

    Args:
      to_inputs: θ (n, d) -> (qpos0, qvel0, ctrl), a JAX function
        (`check.Particles.to_inputs(θ, jnp)`, `Problem.inputs`).
      theta: (n, d) particles.
      g_qpos0: (n, nq) ∂F/∂qpos0, from `input_gradients`.
      g_qvel0: (n, nv) ∂F/∂qvel0.
      g_ctrl: (n, T, nu) ∂F/∂ctrl.
    """
    theta = jnp.asarray(theta)
    _, vjp = jax.vjp(to_inputs, theta)
    (g,) = vjp((g_qpos0.astype(theta.dtype), g_qvel0.astype(theta.dtype),
                g_ctrl.astype(theta.dtype)))
    return g


__all__ = [
    "CHAININGS", "SOLUTIONS", "StepJacobians", "Trajectory", "build_step_jacobians",
    "build_vjp_sweep",
    "c_trajectory", "chain_scan", "chain_sweep", "check_objective", "initial_gradients",
    "input_gradients", "local", "objective_gradients", "one_step_defect", "pullback", "retract",
    "tangent_cotangents",
]
