"""Replays of particles (MuJoCo C or MJX) with their poses, decoded and costed.

A `Replay` carries the states of n plans, the poses the planner reads off them
(MJX kinematics in the scene's precision: body and site positions) and which
geom pairs of the task's symbols touch at each state, as MuJoCo C's own
colliders say (`kinematics.touching`), all computed once when it is made;
`decode`, success predicates and action rules read those. The JAX signed
distances belong to the gradient model (the symbols' soft indicators); a
Replay computes them only when asked (`signed_distance`, and
`symbol_disagreements`, which counts the plans they would decode otherwise).
"""

from __future__ import annotations

import copy
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import kinematics
from mjstamp.distance import make_distance_bound
from mjstamp.errors import MjstampError, valid_list
from mjstamp.parallel import local_device
from mjstamp.scenes import mjx
from mjstamp.scenes.rollout import replay as replay_c
from mjstamp.tasks.problem import FIELDS, Decoded, Poses, Rollout, as_problem

SLACK = 1e-3
"""Where `Replay` asks MuJoCo C whether a pair touches: at the states whose distance
bound (`scenes.distance.make_distance_bound`, from MJX kinematics in the scene's
precision) is at most SLACK times the scene's size (`Scene.length_scale`) plus
ROUNDING float epsilons of the two geoms' distances from the origin (`poses`
subtracts that part from the bound, state by state). The first term covers the
rounding of the geoms' orientations over their extent, the second that of their
positions, which grows with their distance from the origin; so the bound never
hides a contact C sees, in float32 as in float64, wherever the scene is."""

ROUNDING = 64
"""Float epsilons, per metre of the geoms' distances from the origin, in `SLACK`."""


class Replay(Poses):
    """States of n plans over T steps, their poses and contacts (numpy, float64).

    Attributes:
      qpos: (n, T, nq) positions after steps 1..T.
      qvel: (n, T, nv) velocities after steps 1..T (C replays only, else None).
      ctrl: (n, T, nu) controls applied at steps 1..T (C replays only, else None).
      traj: {field: (n, T, ...)}: qpos, qvel (where known), xpos (body
        positions) and site_xpos (site positions).
      touch: {(g1, g2): (n, T) bool} whether the geom pairs decode reads
        (`Problem.contact_pairs`, low id first) touch at each state, by MuJoCo
        C's colliders (`kinematics.touching`: distance < 0 at zero margin).
    """

    def __init__(self, problem, qpos: np.ndarray, source: str, *, qvel=None, ctrl=None):
        problem = as_problem(problem)
        self.problem = problem
        self.scene = problem.scene
        self.source = source
        self.qpos = np.asarray(qpos, np.float64)
        self.qvel = None if qvel is None else np.asarray(qvel, np.float64)
        self.ctrl = None if ctrl is None else np.asarray(ctrl, np.float64)
        traj, bounds = poses(problem, self.qpos)
        states = {"qpos": self.qpos, "qvel": self.qvel}
        self.traj = {**{k: v for k, v in states.items() if v is not None}, **traj}
        self._pairs = problem.contact_pairs()
        slack = SLACK * self.scene.length_scale
        # (n, T, k): where the bound leaves contact possible; C is asked there only.
        # N.B. "not > slack", so that a NaN bound (a state that blew up) asks C too.
        self._near = (np.stack([~(bounds[p] > slack) for p in self._pairs], axis=-1)
                      if self._pairs else np.zeros((*self.qpos.shape[:2], 0), bool))
        touch = kinematics.touching(self.scene.m, self.qpos, self._pairs, self._near)
        self.touch = {p: touch[..., i] for i, p in enumerate(self._pairs)}
        self._distances: dict[tuple[int, int], np.ndarray] | None = None

    def rows(self, idx) -> Replay:
        """The replay of plans `idx` alone (an index array, list or mask), sliced, not redone."""
        out = copy.copy(self)
        out.qpos = self.qpos[idx]
        out.qvel = None if self.qvel is None else self.qvel[idx]
        out.ctrl = None if self.ctrl is None else self.ctrl[idx]
        out.traj = {k: v[idx] for k, v in self.traj.items()}
        out._near = self._near[idx]
        out.touch = {p: t[idx] for p, t in self.touch.items()}
        out._distances = (None if self._distances is None
                          else {p: v[idx] for p, v in self._distances.items()})
        return out

    @property
    def xpos(self) -> np.ndarray:
        """(n, T, nbody, 3) body positions."""
        return self.traj["xpos"]

    @property
    def site_xpos(self) -> np.ndarray:
        """(n, T, nsite, 3) site positions."""
        return self.traj["site_xpos"]

    def _key(self, geom1: str | int, geom2: str | int, what: str) -> tuple[int, int]:
        """The pair's key in `touch`, or one line naming it and the pairs a replay holds."""
        key = kinematics.pair_key(self.scene.geom(geom1), self.scene.geom(geom2))
        if key not in self.touch:
            m = self.scene.m

            def label(g):
                return repr(m.geom(g).name) if m.geom(g).name else f"#{g}"

            valid = [f"{label(a)}-{label(b)}" for a, b in self._pairs]
            raise MjstampError(f"a replay holds the {what} of the geom pairs decode reads "
                               f"(the symbols'); {label(key[0])}-{label(key[1])} is not one; "
                               f"valid: {valid_list(valid)}")
        return key

    def contact(self, geom1: str | int, geom2: str | int) -> np.ndarray:
        """(n, T) whether two geoms touch at each step, as MuJoCo C's colliders say.

        Distance < 0 at zero margin (`kinematics.touching`), for the pairs decode
        reads; any pair of geom types C collides.
        """
        return self.touch[self._key(geom1, geom2, "contacts")]

    def signed_distance(self, geom1: str | int, geom2: str | int) -> np.ndarray:
        """(n, T) JAX signed distance between two geoms, for the pairs decode reads.

        Computed on first call for every such pair with a JAX distance
        (`scenes.distance`), on MJX kinematics in the scene's precision.
        """
        key = self._key(geom1, geom2, "signed distances")
        self.problem.distance_fn(*key)  # N.B. a pair without one: its one-line error
        return self.distances[key]

    @property
    def distances(self) -> dict[tuple[int, int], np.ndarray]:
        """{(g1, g2): (n, T)} JAX signed distances of the pairs decode reads that have one."""
        if self._distances is None:
            fn, pairs = _distances_fn(self.problem)
            (dist,) = _batched(fn, self.problem, self.qpos)
            self._distances = {p: dist[..., i] for i, p in enumerate(pairs)}
        return self._distances

    def symbol_disagreements(self) -> np.ndarray:
        """(n,) plans whose symbols the JAX signed distances (sd < 0) decode otherwise than C.

        C's decode is the one `decode` reads. Compared: the symbols whose pairs
        (and `before` pair) have a JAX distance; the distances are computed at
        the states where the bound leaves contact possible (elsewhere both say
        apart), so the check costs a fraction of a full decode by distances.
        N.B. the first call for a declaration and precision compiles MJX
        kinematics with every relaxed pair's JAX distance (`_distances_fn`: no
        compiled function of the solve computes them on states; seconds on a
        CPU), and each new power of two of near states compiles again
        (`_batched`); a caller that needs it for a few plans takes `rows` first.
        """
        problem, (n, T) = self.problem, self.qpos.shape[:2]
        compared = [k for k, c in enumerate(problem.contacts) if problem.relaxes(c)]
        if not compared:
            return np.zeros(n, bool)
        fn, pairs = _distances_fn(problem)
        near = self._near[..., [self._pairs.index(p) for p in pairs]].any(-1).reshape(-1)
        rows = np.flatnonzero(near)
        touch = {p: np.zeros(n * T, bool) for p in pairs}
        if len(rows):
            (dist,) = _batched(fn, problem, self.qpos.reshape(n * T, 1, -1)[rows])
            for i, p in enumerate(pairs):
                touch[p][rows] = dist[:, 0, i] < 0.0
        touch = {p: t.reshape(n, T) for p, t in touch.items()}
        apart = np.zeros((n, T), bool)

        def jax_contact(g1, g2):  # N.B. a pair without a distance: its symbols are not compared
            return touch.get(kinematics.pair_key(g1, g2), apart)

        c_bits = problem.symbol_bits(self.contact, n, T)[:, compared]
        jax_bits = problem.symbol_bits(jax_contact, n, T)[:, compared]
        return (c_bits != jax_bits).any(axis=1)


# Compiled per declaration and precision: kinematics and distances do not depend on
# the gradient model's solver options, so a calibrated problem reuses them.
_KINEMATICS: dict[tuple[str, Any], Any] = {}
_DISTANCES: dict[tuple[str, Any], Any] = {}
_STATE_COSTS: dict[tuple[str, Any], Any] = {}
_STATE_RESIDUALS: dict[tuple[str, Any], Any] = {}


def _kinematics(problem):
    """The planner's poses of one state: qpos (nq,) -> `mjx.Data` after kinematics."""
    scene = problem.scene
    d0 = mjx.make_data(scene.mx, device=local_device())
    return lambda qpos: mjx.kinematics(scene.mx, d0.replace(qpos=qpos))


def _pair_state_fn(cache: dict, problem, make, outputs):
    """jit(vmap): qpos (B, nq) -> outputs(d, pairs, (k,) values), memoised in `cache`.

    `make()` gives the pairs and their functions of (geom_xpos, geom_xmat);
    `d` is the `mjx.Data` after kinematics. Returns (the function, pairs).
    """
    key = (problem.fingerprint, problem.scene.dtype)
    if key not in cache:
        kinematics_one = _kinematics(problem)
        pairs, fns = make()

        def one(qpos):
            d = kinematics_one(qpos)
            values = jnp.stack([f(d.geom_xpos, d.geom_xmat) for f in fns]) if fns else (
                jnp.zeros(0, qpos.dtype))
            return outputs(d, pairs, values)

        cache[key] = (jax.jit(jax.vmap(one)), pairs)
    return cache[key]


def _kinematics_fn(problem):
    """jit(vmap): qpos (B, nq) -> body, site positions and the pairs' distance bounds.

    Each bound less the rounding its positions allow (`SLACK`'s second term).
    """
    def make():
        pairs = problem.contact_pairs()
        return pairs, [make_distance_bound(problem.scene.m, *p) for p in pairs]

    def outputs(d, pairs, bound):
        if pairs:
            eps = jnp.finfo(bound.dtype).eps
            norms = jnp.linalg.norm(d.geom_xpos, axis=-1)
            reach = jnp.stack([norms[a] + norms[b] for a, b in pairs])
            bound = bound - ROUNDING * eps * reach
        return d.xpos, d.site_xpos, bound

    return _pair_state_fn(_KINEMATICS, problem, make, outputs)


def _distances_fn(problem):
    """jit(vmap): qpos (B, nq) -> (k,) JAX signed distances of the decode's pairs that have one."""
    def make():
        pairs = [p for p in problem.contact_pairs() if problem.has_distance(*p)]
        return pairs, [problem.distance_fn(*p) for p in pairs]

    return _pair_state_fn(_DISTANCES, problem, make, lambda d, pairs, values: (values,))


def _batched(fn, problem, qpos: np.ndarray, chunk: int = 65536) -> list[np.ndarray]:
    """The outputs of fn over states (n, T, nq), in compiled batches: each (n, T, ...) float64."""
    n, T, nq = qpos.shape
    flat = qpos.reshape(-1, nq)
    outs = []
    # N.B. one compiled shape per power of two up to `chunk`: a caller whose batches vary
    # (landing's active particles) would otherwise compile the kinematics for each size.
    size = min(chunk, 1 << max(len(flat) - 1, 1).bit_length())
    for start in range(0, len(flat), size):
        part = flat[start : start + size]
        pad = size - len(part)
        if pad:
            part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
        out = jax.device_get(fn(jnp.asarray(part, problem.scene.dtype)))
        outs.append([np.asarray(o[: len(part) - pad], np.float64) for o in out])
    return [np.concatenate(parts).reshape(n, T, *parts[0].shape[1:])
            for parts in zip(*outs, strict=True)]


def poses(problem, qpos: np.ndarray, chunk: int = 65536):
    """The planner's poses of states: MJX kinematics in the scene's precision, float64.

    Args:
      problem: the `Problem`.
      qpos: (n, T, nq) positions.
      chunk: most states per compiled call (calls take a power of two of them).

    Returns:
      ({"xpos": (n, T, nbody, 3), "site_xpos": (n, T, nsite, 3)},
      {(g1, g2): (n, T) distance bound} for `Problem.contact_pairs`: where it is
      > 0 the pair is apart (`scenes.distance.make_distance_bound`, less the
      rounding of the geoms' positions: `SLACK`)).
    """
    if len(qpos) == 0 or qpos.shape[1] == 0:
        raise MjstampError(f"a replay needs at least one plan and one step; got qpos of "
                           f"shape {qpos.shape}")
    fn, pairs = _kinematics_fn(problem)
    xpos, site_xpos, bound = _batched(fn, problem, qpos, chunk)
    return {"xpos": xpos, "site_xpos": site_xpos}, {p: bound[..., i] for i, p in enumerate(pairs)}


def simulate_c(task, theta: np.ndarray) -> Replay:
    """Replays particles θ (n, d) of a Task or Problem in MuJoCo C (the scene's own solver).

    Discrete actions are taken at Γ(θ): the plan as decoded, not its relaxation.
    """
    problem = as_problem(task)
    theta = np.asarray(theta, np.float64)
    qpos0, qvel0, ctrl = problem.inputs(theta, xp=np)
    ctrl = np.asarray(ctrl, np.float64)
    states = replay_c(problem.scene, qpos0, qvel0, ctrl, fields=("qpos", "qvel"),
                      solver="scene")
    return Replay(problem, states["qpos"], source="mujoco", qvel=states["qvel"], ctrl=ctrl)


def simulate_mjx(task, theta) -> Replay:
    """Rolls particles θ (n, d) out in MJX (the planner's own gradient model)."""
    problem = as_problem(task)
    theta = jnp.asarray(theta, problem.scene.dtype)
    rollout = problem.scene.rollout_fn(problem.horizon, fields=("qpos",))
    qpos = rollout(*problem.inputs(theta, hard=True))["qpos"]
    return Replay(problem, np.asarray(qpos), source="mjx")


def _pose_fn(problem):
    """The poses a cost reads of one C state: qpos (nq,) -> {field: pose} (`FIELDS`)."""
    kinematics = _kinematics(problem)

    def pose(qpos):
        d = kinematics(qpos)
        return {f: getattr(d, f) for f in FIELDS if f not in ("qpos", "qvel")}

    return pose


def _state_cost_fn(problem):
    """jit: states (B, T, nq), (B, T, nv) and θ (B, d) -> the task's cost C (B,).

    The task's own costs (`Problem.score`) on a trajectory it did not roll out
    itself (a MuJoCo C replay). N.B. its poses are computed again inside this
    jit, not read off the Replay: XLA fuses kinematics with the costs, and
    costs of the Replay's own poses differ in the last bit (pushing: 4 of 40
    costs by 3e-14), which would move the screen's order and the scores.
    """
    key = (problem.fingerprint, problem.scene.dtype)
    if key not in _STATE_COSTS:
        pose = _pose_fn(problem)

        def cost(qpos, qvel, theta):
            traj = jax.vmap(jax.vmap(pose))(qpos)
            traj.update(qpos=qpos, qvel=qvel)
            _, values = problem.score(traj, problem.unpack(theta))
            return problem.cost_total(values)

        _STATE_COSTS[key] = jax.jit(cost)
    return _STATE_COSTS[key]


def cost_c(task, replay: Replay, theta: np.ndarray, *, chunk: int = 32) -> np.ndarray:
    """(n,) the task's cost C(θ) on a MuJoCo C replay of θ (n, d), in chunks.

    Non-finite costs (a state that blew up) are +inf.
    """
    problem = as_problem(task)
    fn = _state_cost_fn(problem)
    n = len(theta)
    out = np.empty(n)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        idx = np.arange(start, start + chunk).clip(max=n - 1)  # one compiled shape
        dtype = problem.scene.dtype
        value = fn(jnp.asarray(replay.qpos[idx], dtype), jnp.asarray(replay.qvel[idx], dtype),
                   jnp.asarray(theta[idx], dtype))
        out[start:stop] = np.asarray(value, np.float64)[: stop - start]
    return np.where(np.isfinite(out), out, np.inf)


def residuals_c(task, replay: Replay, theta: np.ndarray, *, chunk: int = 64) -> list:
    """[(n, m_k)] the task's residuals (`Problem.residuals`) on a MuJoCo C replay of θ (n, d).

    Rows of a state that blew up are +inf.
    """
    problem = as_problem(task)
    key = (problem.fingerprint, problem.scene.dtype)
    if key not in _STATE_RESIDUALS:
        pose = _pose_fn(problem)

        def residuals(qpos, qvel, theta):
            traj = jax.vmap(jax.vmap(pose))(qpos)
            traj.update(qpos=qpos, qvel=qvel)
            r = Rollout(problem, traj, problem.unpack(theta))
            return [jnp.sqrt(jnp.asarray(t.weight, theta.dtype)) * t.residual(r)
                    for t in problem.residual_terms]

        _STATE_RESIDUALS[key] = jax.jit(residuals)
    fn, n, dtype = _STATE_RESIDUALS[key], len(theta), problem.scene.dtype
    chunks = []
    for start in range(0, n, chunk):
        idx = np.arange(start, start + chunk).clip(max=n - 1)  # one compiled shape
        value = fn(jnp.asarray(replay.qpos[idx], dtype), jnp.asarray(replay.qvel[idx], dtype),
                   jnp.asarray(theta[idx], dtype))
        chunks.append([np.asarray(v, np.float64)[: min(chunk, n - start)] for v in value])
    parts = [np.concatenate(column) for column in zip(*chunks, strict=True)]
    finite = np.all([np.isfinite(p).all(axis=1) for p in parts], axis=0)
    return [np.where(finite[:, None], p, np.inf) for p in parts]


def decode(task, replay: Replay, theta: np.ndarray) -> Decoded:
    """Task plans of a Task's or Problem's particles θ read off a replay (`Problem.decode`)."""
    return as_problem(task).decode(replay, theta)
