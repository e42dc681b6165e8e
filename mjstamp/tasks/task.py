"""Task: variables, symbols, costs and a success predicate declared on a Scene.

A user writes a task in plain Python on top of a `Scene`:

    task = Task("billiards", scene, horizon=150)
    task.box("cue_velocity", low=[-4, -4], high=[4, 4], initial_qvel=("cue_x", "cue_y"))
    for wall in ("wall_top", "wall_bottom", "wall_left", "wall_right"):
        task.contact(wall, "cue", wall, before=("cue", "target"))
    task.cost("aim", costs.aim("cue", "target"), weight=20.0)
    task.cost("target", costs.reach("target", ["pocket_top", "pocket_bottom"]), weight=50.0)
    task.success(costs.reaches("target", {"top": "pocket_top", ...}, radius=0.1))

From that declaration the task builds the batched log posterior over θ
(STAMP eq. 6-8: log ρ(θ) = −Σ_c β_c C_c(θ, x(θ)) + Σ_p log p_p(θ)), the kernel
(App. B-C / C-B), initial particles, and the MuJoCo C verification of plans.
A user never writes an SVGD update.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp import relax
from mjstamp.errors import MjstampError
from mjstamp.scenes.distance import make_distance_fn
from mjstamp.scenes.rollout import set_columns
from mjstamp.scenes.scene import Scene

KINDS = ("box", "angle", "logits")


def _joint_width(joint_type: int, kind: str) -> int:
    """Coordinates of a joint type in qvel or qpos."""
    free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
    if joint_type == free:
        return 6 if kind == "qvel" else 7
    if joint_type == ball:
        return 3 if kind == "qvel" else 4
    return 1


@dataclasses.dataclass(frozen=True)
class Variable:
    """A named block of θ.

    Attributes:
      name: unique name.
      kind: "box" (bounded reals), "angle" (wrap-around) or "logits" (a discrete
        choice of one of `options` in each of `phases` phases, relaxed to a
        softmax one-hot per phase; STAMP §IV-A).
      size: number of coordinates of θ it takes.
      low, high: (size,) bounds; particles start uniform inside them.
      qvel, qpos: addresses in qvel / qpos the variable sets at t = 0, or None.
      options: names of the m options of a "logits" variable.
      phases: K phases of a "logits" variable (size = m K).
    """

    name: str
    kind: str
    size: int
    low: np.ndarray
    high: np.ndarray
    qvel: tuple[int, ...] | None = None
    qpos: tuple[int, ...] | None = None
    options: tuple[str, ...] = ()
    phases: int = 1


@dataclasses.dataclass(frozen=True)
class Contact:
    """A symbol: "geom1 touches geom2" (up to the first contact of `before`).

    Relaxed to the soft indicator of App. B-B,
    w = sigmoid(Σ_t σ_t d_t), d_t = −α·sd_t + β, σ = softmax(d) over t ≤ t_c,
    with sd_t the signed distance of the two geoms at step t.
    """

    name: str
    geom1: int
    geom2: int
    before: tuple[int, int] | None
    alpha: float
    beta: float


@dataclasses.dataclass(frozen=True)
class Term:
    """A weighted cost or log-prior term."""

    name: str
    fn: Callable
    weight: float


class Rollout:
    """What a cost sees: the batched MJX trajectory, θ's variables and the symbols.

    Attributes:
      scene: the `Scene`.
      traj: {field: (n, T, ...)} arrays of the rollout (states after steps 1..T).
      params: {variable name: (n, size)}.
      symbols: {contact name: (n,)} soft indicators in (0, 1).
    """

    def __init__(self, task: Task, traj: dict, params: dict):
        self.task = task
        self.scene = task.scene
        self.traj = traj
        self.params = params
        self.symbols: dict[str, jax.Array] = {}
        self._sd: dict[tuple[int, int], jax.Array] = {}

    def signed_distance(self, geom1: str | int, geom2: str | int) -> jax.Array:
        """(n, T) signed distance between two geoms (negative in penetration)."""
        g1, g2 = self.scene.geom(geom1), self.scene.geom(geom2)
        key = (min(g1, g2), max(g1, g2))
        if key not in self._sd:
            fn = self.task.distance_fn(*key)
            over_time = jax.vmap(jax.vmap(fn))
            self._sd[key] = over_time(self.traj["geom_xpos"], self.traj["geom_xmat"])
        return self._sd[key]

    def until_contact(self, geom1: str | int, geom2: str | int) -> jax.Array:
        """(n, T) mask of the steps up to and including the first contact."""
        return relax.first_contact_mask(self.signed_distance(geom1, geom2) <= 0.0)

    def body_pos(self, body: str | int) -> jax.Array:
        """(n, T, 3) world position of a body."""
        return self.traj["xpos"][:, :, self.scene.body(body)]

    def site_pos(self, site: str | int) -> jax.Array:
        """(n, T, 3) world position of a site."""
        return self.traj["site_xpos"][:, :, self.scene.site(site)]


class Task:
    """A TAMP problem declared on a Scene; see the module docstring.

    Attributes:
      name: registry name.
      scene: the `Scene`.
      horizon: rollout steps T.
      variables: declared `Variable`s, in θ order.
      contacts: declared `Contact` symbols, in feature order.
      costs, priors: weighted `Term`s.
      kernel_weights: weights of the default kernel's parts ("continuous",
        "angles", "actions", "symbols"); see `kernel()`.
      bound_stiffness: weight of the soft box bounds, per unit of box width.
    """

    def __init__(self, name: str, scene: Scene, *, horizon: int, description: str = ""):
        if int(horizon) < 1:
            raise MjstampError(f"task {name!r}: horizon={horizon} must be >= 1")
        self.name = name
        self.scene = scene
        self.horizon = int(horizon)
        self.description = description
        self.variables: list[Variable] = []
        self.contacts: list[Contact] = []
        self.costs: list[Term] = []
        self.priors: list[Term] = []
        self.controls_fn: Callable | None = None
        self.actions_fn: Callable | None = None
        self.success_fn: Callable | None = None
        self.kernel_weights = {"continuous": 1.0, "angles": 1.0, "actions": 1.0, "symbols": 1.0}
        self.bound_stiffness = 100.0
        self.display_hints: dict[str, list] = {"trace": [], "force": []}
        self.cache_key: str | None = None  # set by tasks.load for registered tasks
        self.settings: dict[str, Any] = {}  # registered tasks: the settings they were built with
        self._distance_fns: dict[tuple[int, int], Callable] = {}

    # ------------------------------------------------------------------
    # Declarations.

    def _check_new(self, name: str, what: str) -> None:
        taken = [v.name for v in self.variables] + [c.name for c in self.contacts]
        taken += [t.name for t in self.costs + self.priors]
        if not isinstance(name, str) or not name:
            raise MjstampError(f"task {self.name!r}: {what} name must be a non-empty string")
        if name in taken:
            raise MjstampError(f"task {self.name!r}: {what} name {name!r} is already declared")

    def _joint_addresses(self, joints, kind: str, size: int, var: str):
        """Addresses in qvel/qpos of joint coordinates: a name, or (name, index).

        A name is the joint's first coordinate (all a slide or hinge has); (name, k)
        is its k-th, for free and ball joints (qvel of a free joint: 3 linear then
        3 angular; qpos: 3 positions then a quaternion).
        """
        if joints is None:
            return None
        if isinstance(joints, str) or (
            isinstance(joints, tuple) and len(joints) == 2 and isinstance(joints[1], int)
        ):
            joints = (joints,)
        joints = tuple(joints)
        if len(joints) != size:
            raise MjstampError(
                f"task {self.name!r}: variable {var!r} has {size} coordinates but "
                f"initial_{kind} names {len(joints)} joints"
            )
        m = self.scene.m
        out = []
        for j in joints:
            name, k = (j, 0) if isinstance(j, str) else (j[0], int(j[1]))
            jid = self.scene.joint(name)
            width = _joint_width(int(m.jnt_type[jid]), kind)
            if not 0 <= k < width:
                raise MjstampError(
                    f"task {self.name!r}: variable {var!r}: joint {name!r} has {width} "
                    f"{kind} coordinates; index {k} is not in 0..{width - 1}"
                )
            base = self.scene.dof_adr(name) if kind == "qvel" else self.scene.qpos_adr(name)
            out.append(base + k)
        return tuple(out)

    def box(
        self,
        name: str,
        low: Sequence[float],
        high: Sequence[float],
        *,
        initial_qvel: Sequence[str] | None = None,
        initial_qpos: Sequence[str] | None = None,
    ) -> None:
        """Declares bounded continuous coordinates (velocities, positions, goals).

        Args:
          name: variable name.
          low: lower bounds, one per coordinate.
          high: upper bounds, one per coordinate (high > low).
          initial_qvel: joints whose initial velocity this variable sets, one
            per coordinate: a joint name, or (name, k) for the k-th velocity of
            a free or ball joint (a free joint: vx, vy, vz, then ωx, ωy, ωz).
          initial_qpos: joints whose initial position this variable sets, named
            the same way.
        """
        self._check_new(name, "variable")
        low = np.atleast_1d(np.asarray(low, float))
        high = np.atleast_1d(np.asarray(high, float))
        if low.shape != high.shape or low.ndim != 1 or not np.all(high > low):
            raise MjstampError(
                f"task {self.name!r}: box {name!r} needs low < high of equal length; got "
                f"low={low.tolist()}, high={high.tolist()}"
            )
        size = low.size
        self.variables.append(Variable(
            name, "box", size, low, high,
            qvel=self._joint_addresses(initial_qvel, "qvel", size, name),
            qpos=self._joint_addresses(initial_qpos, "qpos", size, name),
        ))

    def angle(
        self,
        name: str,
        size: int = 1,
        *,
        low: float = -np.pi,
        high: float = np.pi,
        initial_qpos: Sequence[str] | None = None,
    ):
        """Declares angles (radians, wrap-around; von Mises kernel).

        Args:
          name: variable name.
          size: number of angles.
          low: lower end of the range particles start in (not a bound).
          high: upper end of that range; high - low <= 2π.
          initial_qpos: hinge joints whose initial position this variable sets.
        """
        self._check_new(name, "variable")
        size = int(size)
        if size < 1:
            raise MjstampError(f"task {self.name!r}: angle {name!r} size={size} must be >= 1")
        if not (low < high <= low + 2 * np.pi + 1e-12):
            raise MjstampError(f"task {self.name!r}: angle {name!r} needs low < high <= "
                               f"low + 2π; got low={low}, high={high}")
        self.variables.append(Variable(
            name, "angle", size, np.full(size, float(low)), np.full(size, float(high)),
            qpos=self._joint_addresses(initial_qpos, "qpos", size, name),
        ))

    def discrete(self, name: str, options: Sequence[str], *, phases: int = 1, bound: float = 3.0):
        """Declares a discrete action: one of `options` in each of `phases` phases.

        Relaxed to logits θ ∈ [−u, u]^{mK} with Γ̃ = softmax per phase and decoded
        with Γ = one-hot of the max (STAMP §IV-A, App. A, u = `bound`).
        """
        self._check_new(name, "variable")
        options = tuple(options)
        if len(options) < 2 or int(phases) < 1:
            raise MjstampError(
                f"task {self.name!r}: discrete {name!r} needs >= 2 options and >= 1 phase; "
                f"got {len(options)} options, phases={phases}"
            )
        size = len(options) * int(phases)
        self.variables.append(Variable(
            name, "logits", size, np.full(size, -bound), np.full(size, bound),
            options=options, phases=int(phases),
        ))

    def contact(
        self,
        name: str,
        geom1: str,
        geom2: str,
        *,
        before: tuple[str, str] | None = None,
        alpha: float | None = None,
        beta: float = 0.0,
    ) -> None:
        """Declares a symbol: geom1 touches geom2 (before the first `before` contact).

        Args:
          name: symbol name; its bit in the task plan follows declaration order.
          geom1: first geom name.
          geom2: second geom name.
          before: a geom pair; only steps up to its first contact count.
          alpha: α > 0 of App. B-B, in 1/m: the indicator saturates within
            about 5/α of contact. Default: 4 / r with r the bounding radius of
            the smaller geom (100 /m for a 4 cm ball), so the indicator turns
            from 1/2 to about 0 over one body size, wider than a step of travel.
          beta: β of App. B-B (shift; 0 puts w = 1/2 at touching distance).
        """
        self._check_new(name, "symbol")
        g1, g2 = self.scene.geom(geom1), self.scene.geom(geom2)
        if alpha is None:
            radii = [r for r in self.scene.m.geom_rbound[[g1, g2]] if r > 0]
            alpha = 4.0 / min(radii) if radii else 100.0  # two planes: no size to go by
        if not alpha > 0:
            raise MjstampError(f"task {self.name!r}: contact {name!r} alpha={alpha} must be > 0")
        self.distance_fn(g1, g2)  # unsupported geom pairs fail here, at declaration
        pair = None
        if before is not None:
            pair = (self.scene.geom(before[0]), self.scene.geom(before[1]))
            self.distance_fn(*pair)
        self.contacts.append(Contact(name, g1, g2, pair, float(alpha), float(beta)))

    def cost(self, name: str, fn: Callable[[Rollout], jax.Array], weight: float = 1.0):
        """Adds weight · fn(rollout) to the cost C (likelihood, eq. 8); fn -> (n,)."""
        self._add_term(self.costs, name, fn, weight, "cost")

    def prior(self, name: str, fn: Callable[[dict], jax.Array], weight: float = 1.0):
        """Adds weight · fn(params) to log p(θ) (eq. 7); fn({name: (n, size)}) -> (n,)."""
        self._add_term(self.priors, name, fn, weight, "prior")

    def _add_term(self, terms, name, fn, weight, what):
        self._check_new(name, what)
        if not callable(fn):
            raise MjstampError(f"task {self.name!r}: {what} {name!r} must be callable")
        if not (np.isfinite(weight) and weight >= 0):
            raise MjstampError(
                f"task {self.name!r}: {what} {name!r} weight={weight} must be finite and >= 0"
            )
        terms.append(Term(name, fn, float(weight)))

    def controls(self, fn: Callable[[dict], jax.Array]) -> None:
        """Sets the map params {name: (n, size)} -> controls (n, T, nu).

        A discrete variable reaches `fn` as one-hot weights (n, phases, options):
        Γ̃ (softmax) where the planner needs gradients, Γ (hard) where a plan is
        judged (the discrete target of eq. 4, the SGD phase, verification).
        """
        self.controls_fn = fn

    def actions_from(self, fn: Callable) -> None:
        """Sets how the discrete actions a plan *performed* are read off a replay.

        fn(replay, planned) -> list of n lists of option names, where `planned`
        holds the n lists Γ decodes from θ. Without it the task plan shows the
        planned actions; with it, what happened (e.g. which sides were pushed).
        """
        self.actions_fn = fn

    def success(self, fn: Callable) -> None:
        """Sets the success predicate on a MuJoCo C replay; see `plans.Replay`.

        fn(replay) -> (ok (n,) bool, label (n,) str): whether each plan succeeds
        and a label that becomes part of its task plan (e.g. the pocket).
        """
        self.success_fn = fn

    def display(
        self, *, trace: Sequence[str] = (), force: Sequence[tuple[str, str]] = ()
    ) -> None:
        """How plans are drawn (figures, meshcat playback); no effect on solving.

        Args:
          trace: bodies whose paths are drawn as lines.
          force: geom pairs (a, b) whose contact force on b is drawn as an
            arrow (e.g. the pusher on the block, Fig. 6).
        """
        for body in trace:
            self.scene.body(body)
        for a, b in force:
            self.scene.geom(a), self.scene.geom(b)
        self.display_hints = {"trace": list(trace), "force": [[a, b] for a, b in force]}

    def on_scene(self, scene: Scene) -> Task:
        """The same declaration on another gradient model of the same MJCF scene.

        `scene` must share this task's C model (`Scene.with_grad_options`): names,
        geoms and sizes resolved at declaration stay valid. The declaration is
        shared, not copied; this task is left as it is.
        """
        if scene.m is not self.scene.m:
            raise MjstampError(
                f"task {self.name!r}: on_scene needs a scene made from the task's own "
                f"(Scene.with_grad_options of {self.scene.name!r})"
            )
        other = copy.copy(self)
        other.scene = scene
        return other

    # ------------------------------------------------------------------
    # Layout of θ.

    @property
    def dim(self) -> int:
        """Number of coordinates of θ."""
        return sum(v.size for v in self.variables)

    def slices(self) -> dict[str, slice]:
        """{variable name: slice of θ}."""
        out, start = {}, 0
        for v in self.variables:
            out[v.name] = slice(start, start + v.size)
            start += v.size
        return out

    def unpack(self, theta: jax.Array) -> dict[str, jax.Array]:
        """θ (n, d) -> {variable name: (n, size)}."""
        return {name: theta[:, s] for name, s in self.slices().items()}

    def check(self) -> None:
        """Validates the declaration as a whole (called before solving)."""
        if not self.variables:
            raise MjstampError(f"task {self.name!r} declares no variables")
        if not self.costs:
            raise MjstampError(f"task {self.name!r} declares no costs")

    # ------------------------------------------------------------------
    # What the engine needs.

    def distance_fn(self, g1: int, g2: int) -> Callable:
        """Signed distance function of a geom pair (see scenes.distance)."""
        key = (min(g1, g2), max(g1, g2))
        if key not in self._distance_fns:
            try:
                self._distance_fns[key] = make_distance_fn(self.scene.m, *key)
            except (ValueError, KeyError) as e:
                raise MjstampError(f"task {self.name!r}: {' '.join(str(e).split())}") from None
        return self._distance_fns[key]

    def fields(self) -> tuple[str, ...]:
        """Rollout fields the costs may read."""
        return ("qpos", "qvel", "xpos", "geom_xpos", "geom_xmat", "site_xpos")

    @property
    def has_actions(self) -> bool:
        """Whether θ holds discrete actions (logits); then STAMP runs discrete SVGD."""
        return any(v.kind == "logits" for v in self.variables)

    def choices(self, params: dict, *, hard: bool) -> dict:
        """Params with each discrete variable as one-hots (n, phases, options).

        hard=False gives Γ̃ = softmax per phase (differentiable), hard=True Γ.
        """
        out = dict(params)
        for v in self.variables:
            if v.kind == "logits":
                m = len(v.options)
                x = jnp.asarray(params[v.name])
                onehot = relax.hard_onehot(x, m) if hard else relax.soft_onehot(x, m)
                out[v.name] = onehot.reshape(x.shape[0], v.phases, m)
        return out

    def inputs(self, params: dict, xp=jnp, *, hard: bool = True):
        """Params -> (qpos0 (n, nq), qvel0 (n, nv), ctrl (n, T, nu)).

        hard: discrete actions reach the controls as Γ (True, what a plan means)
        or as Γ̃ (False, the planner's relaxation).
        """
        m = self.scene.m
        n = next(iter(params.values())).shape[0]
        dtype = next(iter(params.values())).dtype
        state = {
            "qpos": xp.broadcast_to(xp.asarray(m.qpos0, dtype), (n, m.nq)),
            "qvel": xp.zeros((n, m.nv), dtype),
        }
        for v in self.variables:
            for field, adr in (("qpos", v.qpos), ("qvel", v.qvel)):
                if adr is not None:
                    state[field] = set_columns(state[field], np.asarray(adr), params[v.name])
        qpos, qvel = state["qpos"], state["qvel"]
        if self.controls_fn is not None:
            ctrl = self.controls_fn(self.choices(params, hard=hard) if self.has_actions else params)
            if xp is np:
                ctrl = np.asarray(ctrl)
        else:
            ctrl = xp.zeros((n, self.horizon, m.nu), dtype)
        return qpos, qvel, ctrl

    def evaluate(
        self, theta: jax.Array, *, hard: bool = False
    ) -> tuple[Rollout, dict[str, jax.Array]]:
        """Rolls θ (n, d) out in MJX; returns the Rollout and each term's (n,) value.

        hard: evaluate discrete actions at Γ(θ) (the target p(Γ(θ)) of eq. 4)
        instead of the relaxation Γ̃(θ).
        """
        params = self.unpack(theta)
        rollout = self.scene.rollout_fn(self.horizon, fields=self.fields())
        return self.score(rollout(*self.inputs(params, hard=hard)), params)

    def score(self, traj: dict, params: dict) -> tuple[Rollout, dict[str, jax.Array]]:
        """Symbols and every term's (n,) value on a trajectory of `fields()`.

        The trajectory is usually the MJX rollout of `evaluate`; plan repair
        passes a MuJoCo C replay's, to score a plan in the scene's own physics.
        """
        r = Rollout(self, traj, params)
        for c in self.contacts:
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
            if v.kind == "angle":
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
        """Kernel features ψ(θ): continuous coordinates, angles, Γ̃ one-hots, symbols."""
        parts = [self.param_features(r.params)]
        parts += [r.symbols[c.name][:, None] for c in self.contacts]
        return jnp.concatenate(parts, axis=1)

    def param_features(self, params: dict) -> jax.Array:
        """The part of ψ(θ) that needs no rollout: θ with logits replaced by Γ̃."""
        parts = []
        for v in self.variables:
            x = params[v.name]
            if v.kind == "logits":
                x = relax.soft_onehot(x, len(v.options))
            parts.append(x)
        return jnp.concatenate(parts, axis=1)

    def log_posterior(self, theta: jax.Array, *, hard: bool = False):
        """Batched log ρ(θ | O = 1) and kernel features, from one rollout.

        Args:
          theta: (n, d) particles.
          hard: discrete actions at Γ(θ) rather than Γ̃(θ) (see `evaluate`).

        Returns:
          logp: (n,) = −C(θ) (STAMP eq. 6-8).
          features: (n, f) ψ(θ), see `features`.
        """
        r, values = self.evaluate(theta, hard=hard)
        return -self.cost_total(values), self.features(r)

    def feature_groups(self) -> dict[str, list[int]]:
        """Indices of ψ per kernel part: continuous (per variable), angles, ..."""
        groups: dict[str, list] = {"continuous": [], "angles": [], "actions": [], "symbols": []}
        start = 0
        for v in self.variables:
            width = v.size
            idx = list(range(start, start + width))
            if v.kind == "box":
                groups["continuous"].append(idx)
            elif v.kind == "angle":
                groups["angles"].append(idx)
            else:
                groups["actions"].append(idx)
            start += width
        if self.contacts:
            groups["symbols"].append(list(range(start, start + len(self.contacts))))
        return groups

    def kernel(self):
        """The default kernel on ψ(θ) (overridable by assigning `task.kernel`).

        With only continuous variables and symbols, one RBF with a median
        bandwidth per group: exp(−Σ_g ‖Δψ_g‖²/s_g²), App. B-C's kernel over
        [v, w(v)]. Otherwise a weighted sum (App. C-B): RBF over the continuous
        coordinates (a bandwidth per variable), von Mises over angles, RBF over
        the softmax one-hots, RBF over the symbols, weighted by
        `kernel_weights`.
        """
        from mjstamp import svgd

        groups = self.feature_groups()
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
                terms.append((self.kernel_weights[part], make(groups=local), flat))
            base = svgd.sum_kernels(terms)
        if not self.contacts:
            # ψ needs no rollout: a feature map of θ alone keeps the SVGD step at one
            # pullback through the rollout (features read off the rollout cost one
            # pullback, or one pushforward, per feature or coordinate).
            return svgd.feature_kernel(
                base, lambda theta: self.param_features(self.unpack(theta)),
                include_inputs=False, jacobian="fwd",
            )
        return svgd.feature_kernel(base, include_inputs=False)

    def logdensity(self, *, hard: bool = False) -> Callable:
        """The batched log density STAMP moves particles with (see `kernel`).

        Returns (logp, ψ) from one rollout where the kernel reads features of the
        rollout (contact symbols), else logp alone.
        """
        if self.contacts:
            return lambda theta: self.log_posterior(theta, hard=hard)
        return lambda theta: self.log_posterior(theta, hard=hard)[0]

    def initial_particles(self, key: jax.Array, n: int) -> jax.Array:
        """N particles uniform in the bounds (logits: uniform base of App. A)."""
        low = np.concatenate([v.low for v in self.variables])
        high = np.concatenate([v.high for v in self.variables])
        u = jax.random.uniform(key, (n, self.dim), dtype=self.scene.dtype)
        return jnp.asarray(low, self.scene.dtype) + u * jnp.asarray(high - low, self.scene.dtype)

    def describe(self) -> dict[str, Any]:
        """A JSON-ready summary of the declaration."""
        return {
            "name": self.name,
            "scene": self.scene.name,
            "horizon": self.horizon,
            "timestep": float(self.scene.m.opt.timestep),
            "variables": [
                {"name": v.name, "kind": v.kind, "size": v.size,
                 "low": v.low.tolist(), "high": v.high.tolist(),
                 **({"options": list(v.options), "phases": v.phases} if v.options else {})}
                for v in self.variables
            ],
            "symbols": [c.name for c in self.contacts],
            "costs": {t.name: t.weight for t in self.costs},
            "priors": {t.name: t.weight for t in self.priors},
            "display": self.display_hints,
        }
