"""Problem: a Task's declaration compiled once into pure functions and static metadata.

`task.build()` returns a `Problem`, an immutable value that `solve`, `verify`,
`modes`, `seeding`, `figures` and the baselines consume. Each function has one
signature:

- `logdensity(θ) -> (logp (n,), ψ (n, f))`: the relaxed log posterior (discrete
  actions as Γ̃) and the kernel features of the same rollout, in the way
  `jax.value_and_grad(has_aux=True)` reads; f = 0 where the kernel needs none;
- `log_target(θ) -> (logp, ψ)`: the same at the hard decode Γ(θ) (eq. 4's
  target p(Γ(θ)) and what the SGD phase ascends);
- `kernel`: the SVGD kernel (`mjstamp.svgd`);
- `init(key, n) -> θ (n, d)`: particles uniform in the bounds;
- `inputs(θ, xp=jnp, hard=True) -> (qpos0, qvel0, ctrl)`: what a rollout takes;
- `evaluate(θ, hard=...) -> (Rollout, {term: (n,)})`, `cost_total(values)`;
- `decode(replay, θ) -> Decoded`: task plans read off a replay.

References:
  STAMP eq. (4), (6)-(8); App. A (Γ, Γ̃), App. B-C / C-B (kernels).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import kinematics, relax, svgd
from mjstamp.distance import UnsupportedPairError, make_distance_fn
from mjstamp.errors import MjstampError
from mjstamp.scenes import uncertainty
from mjstamp.scenes.rollout import set_columns
from mjstamp.scenes.scene import Scene
from mjstamp.tasks.declaration import Contact, Kind, Term, Variable, distance_fn

# Rollout fields a cost may read.
FIELDS = ("qpos", "qvel", "xpos", "geom_xpos", "geom_xmat", "site_xpos")


class Poses:
    """Poses and contacts of n trajectories over T steps, by name.

    What a cost's `Rollout` (MJX, traced) and a MuJoCo C `verify.Replay`
    (numpy) both offer, so a success predicate or an action rule reads either.
    A subclass sets `scene` and `traj` ({field: (n, T, ...)}, `FIELDS`) and
    defines `signed_distance`.
    """

    scene: Scene
    traj: dict

    def signed_distance(self, geom1: str | int, geom2: str | int):
        """(n, T) signed distance between two geoms (negative in penetration)."""
        raise NotImplementedError

    def body_pos(self, body: str | int):
        """(n, T, 3) world position of a body."""
        return self.traj["xpos"][:, :, self.scene.body(body)]

    def site_pos(self, site: str | int):
        """(n, T, 3) world position of a site."""
        return self.traj["site_xpos"][:, :, self.scene.site(site)]

    def contact(self, geom1: str | int, geom2: str | int):
        """(n, T) whether two geoms touch at each step: signed distance < 0.

        MuJoCo makes a contact exactly then for geoms without margin. A
        `verify.Replay` answers from MuJoCo C's own colliders instead
        (`kinematics.touching`), for any pair C collides.
        """
        return self.signed_distance(geom1, geom2) < 0.0


class Rollout(Poses):
    """What a cost sees: the batched trajectory, θ's variables and the symbols.

    Attributes:
      scene: the `Scene`.
      traj: {field: (n, T, ...)} arrays (states after steps 1..T), `FIELDS`.
      params: {variable name: (n, size)}.
      symbols: {contact name: (n,)} soft indicators in (0, 1); reading one the
        gradient model cannot relax (`Problem.relaxes`) is its one-line error.
    """

    def __init__(self, problem: Problem, traj: dict, params: dict):
        self.problem = problem
        self.scene = problem.scene
        self.traj = traj
        self.params = params
        self.symbols: dict[str, jax.Array] = _Symbols(problem)
        self._sd: dict[tuple[int, int], jax.Array] = {}

    def signed_distance(self, geom1: str | int, geom2: str | int) -> jax.Array:
        """(n, T) signed distance between two geoms (negative in penetration)."""
        key = kinematics.pair_key(self.scene.geom(geom1), self.scene.geom(geom2))
        if key not in self._sd:
            fn = self.problem.distance_fn(*key)
            over_time = jax.vmap(jax.vmap(fn))
            self._sd[key] = over_time(self.traj["geom_xpos"], self.traj["geom_xmat"])
        return self._sd[key]

    def until_contact(self, geom1: str | int, geom2: str | int) -> jax.Array:
        """(n, T) mask of the steps up to and including the first contact."""
        return relax.first_contact_mask(self.signed_distance(geom1, geom2) <= 0.0)


class _Symbols(dict):
    """A rollout's soft indicators by symbol name; a symbol without one raises its reason."""

    def __init__(self, problem: Problem):
        super().__init__()
        self.problem = problem

    def __missing__(self, name: str):
        reason = self.problem.unrelaxed_reason(name)
        if reason is None:
            raise KeyError(name)
        raise MjstampError(reason)


@dataclasses.dataclass(frozen=True)
class Decoded:
    """Task plans of n particles read off a replay.

    Attributes:
      ok: (n,) success predicate.
      label: (n,) success label ("" where none).
      bits: (n, n_symbols) int, the contact symbols.
      actions: (n, n_phases) option names of the discrete variables.
      plan: (n,) task-plan strings, e.g. "0110-top".
      code: (n,) the symbol bits alone, e.g. "0110".
    """

    ok: np.ndarray
    label: np.ndarray
    bits: np.ndarray
    actions: list[list[str]]
    plan: np.ndarray
    code: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A task compiled for solving; see the module docstring. Build with `Task.build()`.

    Attributes:
      name: the task's name.
      scene: the `Scene` whose gradient model the rollouts use (`on_scene`
        swaps it for a calibrated one).
      horizon: rollout steps T.
      variables: θ's blocks, in order (`Variable`, each of a `Kind`).
      contacts: the symbols, in task-plan bit order.
      costs, priors: weighted terms of eq. (8) and (7).
      controls_fn, actions_fn, success_fn: as declared (or None).
      kernel: the SVGD kernel.
      display: drawing hints {"trace": [...], "force": [[a, b], ...]}.
      settings: the task's own settings (registered tasks: their config).
      description: one line.
      fingerprint: a hash of the whole declaration (`Task.fingerprint`).
      extras: objects the task's code built (e.g. pushing's skill bank).
      bound_stiffness: weight of the soft box bounds per unit of box width.
      uncertain: the physics plans should survive (`Task.uncertain`), resolved;
        the defaults (`scenes.uncertainty.defaults`) when the task declared none.
      uncertain_declared: whether the task declared it.
      robust: None (plan for the nominal model), or K draws of `uncertain`
        (`scenes.uncertainty.Batch`): the log posterior is then minus the
        expected cost (or its CVaR) over K perturbed MJX rollouts per particle
        (`with_robust`).
      cost_scale: β, the inverse temperature of the log posterior,
        log ρ = −β·C (`with_cost_scale`); `cost_total` stays C.
    """

    name: str
    scene: Scene
    horizon: int
    variables: tuple[Variable, ...]
    contacts: tuple[Contact, ...]
    costs: tuple[Term, ...]
    priors: tuple[Term, ...]
    controls_fn: Callable | None
    actions_fn: Callable | None
    success_fn: Callable | None
    kernel: Any
    display: Mapping[str, list]
    settings: Mapping[str, Any]
    description: str
    fingerprint: str
    extras: Mapping[str, Any]
    bound_stiffness: float
    distance_fns: Mapping[tuple[int, int], Callable]
    declaration: Mapping[str, Any]
    uncertain: tuple = ()
    uncertain_declared: bool = False
    robust: Any = None
    cost_scale: float = 1.0

    # Layout of θ ---------------------------------------------------------------

    @property
    def dim(self) -> int:
        """Number of coordinates of θ."""
        return sum(v.size for v in self.variables)

    @property
    def symbols(self) -> tuple[str, ...]:
        """Names of the contact symbols, in bit order."""
        return tuple(c.name for c in self.contacts)

    @property
    def has_actions(self) -> bool:
        """Whether θ holds discrete actions; then STAMP runs discrete SVGD."""
        return any(v.kind is Kind.DISCRETE for v in self.variables)

    @property
    def low(self) -> np.ndarray:
        """(d,) lower bounds (angles: the start of their range)."""
        return np.concatenate([v.low for v in self.variables])

    @property
    def high(self) -> np.ndarray:
        """(d,) upper bounds."""
        return np.concatenate([v.high for v in self.variables])

    def slices(self) -> dict[str, slice]:
        """{variable name: slice of θ}."""
        out, start = {}, 0
        for v in self.variables:
            out[v.name] = slice(start, start + v.size)
            start += v.size
        return out

    def unpack(self, theta) -> dict[str, Any]:
        """θ (n, d) -> {variable name: (n, size)}."""
        return {name: theta[:, s] for name, s in self.slices().items()}

    def on_scene(self, scene: Scene) -> Problem:
        """The same problem on another gradient model of the same MJCF scene.

        `scene` must share this problem's C model (`Scene.with_grad_options`):
        names, geoms and sizes resolved at declaration stay valid.
        """
        if scene.m is not self.scene.m:
            raise MjstampError(
                f"task {self.name!r}: on_scene needs a scene made from the task's own "
                f"(Scene.with_grad_options of {self.scene.name!r})"
            )
        return dataclasses.replace(self, scene=scene)

    def with_robust(self, samples: int, seed: int, cvar: float = 1.0) -> Problem:
        """The problem planned for K = `samples` draws of its uncertain physics (0: nominal).

        The draws are made on the current gradient model, so call it after
        `on_scene`. MJX rollouts take the drawn friction, masses (with the
        quantities mj_setConst derives from them), damping, contact time
        constants and gains per row, and the initial-position noise.
        """
        if not samples:
            return dataclasses.replace(self, robust=None)
        draws = uncertainty.batch(self.scene.m_grad, self.uncertain, samples, seed, cvar)
        return dataclasses.replace(self, robust=draws)

    def with_cost_scale(self, scale: float) -> Problem:
        """The problem whose log posterior is −β·C with β = `scale` (> 0; 1: as declared)."""
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"cost_scale must be a finite number > 0; got {scale!r}")
        return dataclasses.replace(self, cost_scale=float(scale))

    def distance_fn(self, g1: int, g2: int) -> Callable:
        """Signed distance function of a geom pair (see scenes.distance), memoised.

        Raises:
          UnsupportedPairError: a pair of geom types without a JAX distance (one line).
        """
        key = kinematics.pair_key(g1, g2)
        if key not in self.distance_fns:
            # N.B. a memo, not state: the function of a pair never changes.
            self.distance_fns[key] = distance_fn(self.scene.m, self.name, *key)  # type: ignore[index]
        return self.distance_fns[key]

    def has_distance(self, g1: int, g2: int) -> bool:
        """Whether a geom pair has a JAX signed distance (`distance_fn` gives one)."""
        try:
            self.distance_fn(g1, g2)
        except UnsupportedPairError:
            return False
        return True

    def relaxes(self, contact: Contact) -> bool:
        """Whether the gradient model relaxes a symbol: its pairs have JAX distances.

        Every symbol decodes from MuJoCo C; only these have a soft indicator
        (App. B-B), which the gradient-based solvers read (STAMP's log density
        and kernel, the enumerate and blocking baselines).
        """
        return all(self.has_distance(*pair) for pair in ((contact.geom1, contact.geom2),
                                                         contact.before) if pair is not None)

    def unrelaxed_reason(self, name: str) -> str | None:
        """The one line saying why symbol `name` has no soft indicator; None if it has one.

        None too for a name that is no symbol.
        """
        contact = next((c for c in self.contacts if c.name == name), None)
        if contact is None or self.relaxes(contact):
            return None
        for pair in ((contact.geom1, contact.geom2), contact.before):
            try:
                if pair is not None:
                    make_distance_fn(self.scene.m, *pair)
            except MjstampError as e:
                why = " ".join(str(e).split())
                break
        return (f"task {self.name!r}: symbol {name!r} has no soft indicator in the gradient "
                f"model, which needs a JAX signed distance: {why}; it decodes from MuJoCo C "
                "(screen, verify), so cem, cmaes and random search solve the task, but STAMP and "
                "the enumerate and blocking baselines read every symbol's soft indicator")

    def check_relaxed(self) -> None:
        """Raises the one line of the first symbol the gradient model cannot relax, if any."""
        for c in self.contacts:
            reason = self.unrelaxed_reason(c.name)
            if reason is not None:
                raise MjstampError(reason)

    # θ -> rollout inputs -------------------------------------------------------

    def choices(self, params: dict, *, hard: bool) -> dict:
        """Params with each discrete variable as one-hots (n, phases, options).

        hard=False gives Γ̃ = softmax per phase (differentiable), hard=True Γ.
        """
        out = dict(params)
        for v in self.variables:
            if v.kind is Kind.DISCRETE:
                m = len(v.options)
                x = jnp.asarray(params[v.name])
                onehot = relax.hard_onehot(x, m) if hard else relax.soft_onehot(x, m)
                out[v.name] = onehot.reshape(x.shape[0], v.phases, m)
        return out

    def inputs(self, theta, *, xp=jnp, hard: bool = True):
        """θ (n, d) -> (qpos0 (n, nq), qvel0 (n, nv), ctrl (n, T, nu)).

        Args:
          theta: particles.
          xp: `jax.numpy` (rollouts) or `numpy` (MuJoCo C replay).
          hard: discrete actions reach the controls as Γ (True, what a plan
            means) or as Γ̃ (False, the planner's relaxation).
        """
        m = self.scene.m
        params = self.unpack(theta)
        n, dtype = theta.shape[0], theta.dtype
        state = {
            "qpos": xp.broadcast_to(xp.asarray(m.qpos0, dtype), (n, m.nq)),
            "qvel": xp.zeros((n, m.nv), dtype),
        }
        for v in self.variables:
            for field, adr in (("qpos", v.qpos), ("qvel", v.qvel)):
                if adr is not None:
                    state[field] = set_columns(state[field], np.asarray(adr), params[v.name])
        if self.controls_fn is not None:
            ctrl = self.controls_fn(self.choices(params, hard=hard) if self.has_actions else params)
            if xp is np:
                ctrl = np.asarray(ctrl)
        else:
            ctrl = xp.zeros((n, self.horizon, m.nu), dtype)
        return state["qpos"], state["qvel"], ctrl

    def init(self, key: jax.Array, n: int) -> jax.Array:
        """Draws n particles uniform in the bounds (discrete logits: App. A's uniform base)."""
        dtype = self.scene.dtype
        u = jax.random.uniform(key, (n, self.dim), dtype=dtype)
        return jnp.asarray(self.low, dtype) + u * jnp.asarray(self.high - self.low, dtype)

    # Costs and the log posterior ---------------------------------------------

    def evaluate(self, theta, *, hard: bool = False) -> tuple[Rollout, dict[str, jax.Array]]:
        """Rolls θ (n, d) out in MJX; returns the Rollout and each term's (n,) value.

        hard: discrete actions at Γ(θ) (the target of eq. 4) instead of Γ̃(θ).
        """
        rollout = self.scene.rollout_fn(self.horizon, fields=FIELDS)
        return self.score(rollout(*self.inputs(theta, hard=hard)), self.unpack(theta))

    def score(self, traj: dict, params: dict) -> tuple[Rollout, dict[str, jax.Array]]:
        """Symbols and every term's (n,) value on a trajectory of `FIELDS`.

        The trajectory is usually the MJX rollout of `evaluate`; plan repair
        passes a MuJoCo C replay's, to score a plan in the scene's own physics.
        """
        r = Rollout(self, traj, params)
        for c in self.contacts:
            if not self.relaxes(c):
                continue  # N.B. decoded from C only: reading its indicator raises why
            mask = None if c.before is None else r.until_contact(*c.before)
            r.symbols[c.name] = relax.soft_contact_indicator(
                r.signed_distance(c.geom1, c.geom2), alpha=c.alpha, beta=c.beta, mask=mask
            )
        values = {t.name: t.fn(r) for t in self.costs}
        values.update({t.name: t.fn(params) for t in self.priors})
        values["bounds"] = self._bounds_penalty(params)
        return r, values

    def _bounds_penalty(self, params) -> jax.Array:
        """Soft box bounds: κ Σ (relu(θ − high)² + relu(low − θ)²) / width²."""
        total = 0.0
        for v in self.variables:
            if v.kind is Kind.ANGLE:
                continue
            x = params[v.name]
            width = jnp.asarray(v.high - v.low, x.dtype)
            over = jax.nn.relu(x - v.high) + jax.nn.relu(v.low - x)
            total = total + jnp.sum((over / width) ** 2, axis=1)
        return self.bound_stiffness * total

    def cost_total(self, values: dict[str, jax.Array]) -> jax.Array:
        """C(θ) = Σ β_c C_c + bounds − Σ β_p log p_p, from `evaluate`'s values."""
        total = values["bounds"]
        for t in self.costs:
            total = total + t.weight * values[t.name]
        for t in self.priors:
            total = total - t.weight * values[t.name]
        return total

    def features(self, r: Rollout) -> jax.Array:
        """Kernel features ψ(θ) (n, f): continuous coordinates, angles, Γ̃ one-hots, symbols."""
        parts = [self.param_features(r.params)]
        parts += [r.symbols[c.name][:, None] for c in self.contacts]
        return jnp.concatenate(parts, axis=1)

    def param_features(self, params: dict) -> jax.Array:
        """The part of ψ(θ) that needs no rollout: θ with logits replaced by Γ̃."""
        parts = []
        for v in self.variables:
            x = params[v.name]
            if v.kind is Kind.DISCRETE:
                x = relax.soft_onehot(x, len(v.options))
            parts.append(x)
        return jnp.concatenate(parts, axis=1)

    def feature_groups(self) -> dict[str, list[list[int]]]:
        """Indices of ψ per kernel part: continuous (per variable), angles, actions, symbols."""
        groups: dict[str, list] = {"continuous": [], "angles": [], "actions": [], "symbols": []}
        part = {Kind.BOX: "continuous", Kind.ANGLE: "angles", Kind.DISCRETE: "actions"}
        start = 0
        for v in self.variables:
            groups[part[v.kind]].append(list(range(start, start + v.size)))
            start += v.size
        if self.contacts:
            groups["symbols"].append(list(range(start, start + len(self.contacts))))
        return groups

    @property
    def residual_terms(self) -> tuple[Term, ...]:
        """The cost terms with residuals (`Task.residuals`, `costs.reach`...), in order."""
        return tuple(t for t in self.costs if t.residual is not None)

    def residuals(self, theta) -> list[jax.Array]:
        """What the precision polish descends: [√β_c · r_c (n, m_c)] per residual term c.

        From one rollout at Γ(θ) on the nominal model; Σ_c ‖√β_c r_c‖² is the
        residual terms' part of C (a softmin reach counted at its nearest pass).
        """
        rollout = self.scene.rollout_fn(self.horizon, fields=FIELDS)
        r = Rollout(self, rollout(*self.inputs(theta, hard=True)), self.unpack(theta))
        return [jnp.sqrt(jnp.asarray(t.weight, theta.dtype)) * t.residual(r)
                for t in self.residual_terms]

    def residual_tolerances(self) -> list[float | None]:
        """Per residual term, its goal's radius in the units of `residuals` (√β_c · tol)."""
        return [None if t.tolerance is None else math.sqrt(t.weight) * t.tolerance
                for t in self.residual_terms]

    def _log_posterior(self, theta, hard: bool):
        if self.robust is not None:
            return self._robust_log_posterior(theta, hard)
        r, values = self.evaluate(theta, hard=hard)
        return -self.cost_scale * self.cost_total(values), self.features(r)

    def _robust_log_posterior(self, theta, hard: bool):
        """Minus the expected cost (or CVaR) over the K draws of `robust`, and ψ averaged."""
        draws = self.robust
        n, k = theta.shape[0], draws.samples
        rollout = self.scene.rollout_fn(self.horizon, fields=FIELDS,
                                        model_fields=tuple(sorted(draws.fields)))
        qpos0, qvel0, ctrl = self.inputs(theta, hard=hard)

        def rows(x):
            return jnp.repeat(x, k, axis=0)

        noise = jnp.asarray(draws.qpos_noise, qpos0.dtype)
        model = {f: jnp.tile(jnp.asarray(v), (n,) + (1,) * (v.ndim - 1))
                 for f, v in draws.fields.items()}
        traj = rollout(rows(qpos0) + jnp.tile(noise, (n, 1)), rows(qvel0), rows(ctrl), model)
        r, values = self.score(traj, {name: rows(x) for name, x in self.unpack(theta).items()})
        cost = self.cost_total(values).reshape(n, k)
        worst = draws.worst()
        if worst < k:
            cost = jnp.sort(cost, axis=1)[:, k - worst:]
        features = self.features(r).reshape(n, k, -1).mean(axis=1)
        return -self.cost_scale * cost.mean(axis=1), features

    def logdensity(self, theta) -> tuple[jax.Array, jax.Array]:
        """The log posterior log ρ(θ | O = 1) (n,) = −β·C(θ) at Γ̃(θ), and ψ (n, f): one rollout.

        References:
          STAMP eq. (6)-(8).
        """
        return self._log_posterior(theta, hard=False)

    def log_target(self, theta) -> tuple[jax.Array, jax.Array]:
        """The log posterior at the hard decode, log p(Γ(θ)) (n,), and ψ (n, f).

        The target of discrete SVGD (eq. 4) and what the SGD phase ascends: Γ
        has no gradient, so SGD leaves the logits alone (as App. E fixes them).
        """
        return self._log_posterior(theta, hard=True)

    def sgd_logdensity(self, theta) -> tuple[jax.Array, jax.Array]:
        """What the SGD phase ascends: `log_target` with discrete actions, else `logdensity`."""
        return self._log_posterior(theta, hard=self.has_actions)

    # Task plans --------------------------------------------------------------

    def contact_pairs(self) -> list[tuple[int, int]]:
        """Geom pairs (low id first) whose contacts decode reads: symbols and `before`s."""
        pairs = []
        for c in self.contacts:
            for pair in ((c.geom1, c.geom2), c.before):
                if pair is not None:
                    key = (min(pair), max(pair))
                    if key not in pairs:
                        pairs.append(key)
        return pairs

    def planned_actions(self, theta: np.ndarray) -> list[list[str]]:
        """The option Γ(θ) picks in each phase of each discrete variable, per particle."""
        n = len(theta)
        actions: list[list[str]] = [[] for _ in range(n)]
        params = self.unpack(np.asarray(theta))
        for v in self.variables:
            if v.kind is not Kind.DISCRETE:
                continue
            m = len(v.options)
            onehot = np.asarray(relax.hard_onehot(jnp.asarray(params[v.name]), m))
            choice = onehot.reshape(n, v.phases, m).argmax(axis=-1)
            for i in range(n):
                actions[i] += [v.options[j] for j in choice[i]]
        return actions

    def symbol_bits(self, contact: Callable, n: int, T: int) -> np.ndarray:
        """(n, S) int: each symbol's bit, from `contact(g1, g2) -> (n, T)` bool.

        A symbol is 1 where its pair touches at some step up to and including
        the first touch of its `before` pair (every step where that never touches).
        """
        bits = np.zeros((n, len(self.contacts)), int)
        for k, c in enumerate(self.contacts):
            touch = contact(c.geom1, c.geom2)
            if c.before is not None:
                first = contact(*c.before)
                t_c = np.where(first.any(axis=1), first.argmax(axis=1), T - 1)
                touch = touch & (np.arange(T)[None] <= t_c[:, None])
            bits[:, k] = touch.any(axis=1)
        return bits

    def decode(self, replay, theta: np.ndarray) -> Decoded:
        """Task plans read off a replay (`verify.Replay`): symbols, actions, success label.

        Which geoms touch is the replay's `contact`: MuJoCo C's colliders for a
        `verify.Replay` (C or MJX states alike), whatever the pair's types.
        """
        n, T = replay.qpos.shape[:2]
        bits = self.symbol_bits(replay.contact, n, T)
        actions = self.planned_actions(theta)
        if self.actions_fn is not None:
            actions = [list(a) for a in self.actions_fn(replay, actions)]
        if self.success_fn is not None:
            ok, label = self.success_fn(replay)
            ok = np.asarray(ok, bool)
            label = np.asarray(label, dtype=object)
        else:
            ok, label = np.ones(n, bool), np.full(n, "", dtype=object)
        code = np.array(["".join(map(str, b)) for b in bits], dtype=object)
        plan = []
        for i in range(n):
            parts = [p for p in (code[i], ",".join(actions[i]), label[i]) if p]
            plan.append("-".join(parts) or "-")
        return Decoded(ok, label, bits, actions, np.array(plan, dtype=object), code)

    def describe(self) -> dict[str, Any]:
        """A JSON-ready summary of the declaration."""
        return dict(self.declaration)


def as_problem(task) -> Problem:
    """The `Problem` of a `Task` (`task.build()`), or the `Problem` itself."""
    return task if isinstance(task, Problem) else task.build()


def default_kernel(problem: Problem, weights: Mapping[str, float]):
    """The default kernel on ψ(θ).

    With only continuous variables and symbols, one RBF with a median bandwidth
    per group: exp(−Σ_g ‖Δψ_g‖²/s_g²), App. B-C's kernel over [v, w(v)].
    Otherwise a weighted sum (App. C-B): RBF over the continuous coordinates (a
    bandwidth per variable), von Mises over angles, RBF over the softmax
    one-hots, RBF over the symbols, weighted by `weights`.
    """
    groups = problem.feature_groups()
    if not groups["angles"] and not groups["actions"]:
        base = svgd.rbf(groups=groups["continuous"] + groups["symbols"])
    else:
        terms = []
        for part, make in (
            ("continuous", svgd.rbf), ("angles", svgd.von_mises),
            ("actions", svgd.rbf), ("symbols", svgd.rbf),
        ):
            if not groups[part]:
                continue
            flat = [i for g in groups[part] for i in g]
            local, start = [], 0
            for g in groups[part]:
                local.append(slice(start, start + len(g)))
                start += len(g)
            terms.append((weights[part], make(groups=local), flat))
        base = svgd.sum_kernels(terms)
    if not problem.contacts:
        # ψ needs no rollout: a feature map of θ alone keeps the SVGD step at one
        # pullback through the rollout (features read off the rollout cost one
        # pullback, or one pushforward, per feature or coordinate).
        return svgd.feature_kernel(
            base, lambda theta: problem.param_features(problem.unpack(theta)),
            include_inputs=False, jacobian="fwd",
        )
    return svgd.feature_kernel(base, include_inputs=False)
