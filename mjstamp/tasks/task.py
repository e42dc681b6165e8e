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

import dataclasses
import hashlib
import json
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np

from mjstamp import kinematics, svgd
from mjstamp.distance import UnsupportedPairError
from mjstamp.errors import MjstampError
from mjstamp.scenes import uncertainty
from mjstamp.scenes.scene import Scene
from mjstamp.tasks import costs
from mjstamp.tasks import fingerprint as fp
from mjstamp.tasks.declaration import (
    Contact,
    Kind,
    SumOfSquares,
    Term,
    Variable,
    distance_fn,
    joint_width,
)
from mjstamp.tasks.problem import Problem, Rollout, default_kernel

#: Longest rollout a task may declare, in steps.
MAX_HORIZON = 100_000


def _is_joint(j) -> bool:
    """A joint reference: a name or an id (not a bool, which numbers.Integral admits)."""
    return isinstance(j, str) or (isinstance(j, numbers.Integral) and not isinstance(j, bool))


def _is_pair(j) -> bool:
    """(joint, k): a joint reference and an integer coordinate index."""
    return (isinstance(j, (tuple, list)) and len(j) == 2 and _is_joint(j[0])
            and _is_joint(j[1]) and not isinstance(j[1], str))


class Task:
    """A TAMP problem declared on a Scene; see the module docstring.

    A declaration only: `build()` compiles it into the `Problem` that solvers,
    plans and figures consume.

    Attributes:
      name: the task's name.
      scene: the `Scene`.
      horizon: rollout steps T.
      variables: declared `Variable`s, in θ order.
      contacts: declared `Contact` symbols, in task-plan bit order.
      costs, priors: weighted `Term`s.
      settings: the task's own settings (registered tasks: the config they
        were built from), recorded with results.
      extras: objects the task's code built and tools may want (pushing: the
        skill bank and the push timing); not part of the declaration.
      kernel_weights: weights of the default kernel's parts (`use_kernel`).
      bound_stiffness: weight of the soft box bounds, per unit of box width.
    """

    def __init__(
        self,
        name: str,
        scene: Scene,
        *,
        horizon: int,
        description: str = "",
        settings: Mapping[str, Any] | None = None,
        extras: Mapping[str, Any] | None = None,
    ):
        if not 1 <= int(horizon) <= MAX_HORIZON:
            raise MjstampError(f"task {name!r}: horizon={horizon} must be in 1..{MAX_HORIZON} "
                               "steps (a rollout keeps every step for its gradient)")
        self.name = name
        self.scene = scene
        self.horizon = int(horizon)
        self.description = description
        self.settings = dict(settings or {})
        self.extras = dict(extras or {})
        self.variables: list[Variable] = []
        self.contacts: list[Contact] = []
        self.costs: list[Term] = []
        self.priors: list[Term] = []
        self.controls_fn: Callable | None = None
        self.actions_fn: Callable | None = None
        self.success_fn: Callable | None = None
        self.kernel_weights = {"continuous": 1.0, "angles": 1.0, "actions": 1.0, "symbols": 1.0}
        self.kernel_override = None
        self.bound_stiffness = 100.0
        self.display_hints: dict[str, list] = {"trace": [], "force": []}
        self.uncertainties: tuple[uncertainty.Uncertain, ...] = ()
        self._distance_fns: dict[tuple[int, int], Callable] = {}
        self._built: tuple[str, Problem] | None = None
        # What each `costs` term and the success predicate measure (`costs.Bound.goal`).
        self._goals: dict[str, tuple | None] = {}
        self._success_goal: tuple | None = None

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
        """Addresses in qvel/qpos of joint coordinates: a joint, or (joint, index).

        A joint is a name or an id (a hand-written scene often leaves its joints
        unnamed); alone it means its first coordinate (all a slide or hinge has);
        (joint, k) is its k-th, for free and ball joints (qvel of a free joint: 3
        linear then 3 angular; qpos: 3 positions then a quaternion).
        """
        if joints is None:
            return None
        # N.B. a bare (name, k) tuple is one pair, as before joints had ids; a bare
        # (id, k) is one pair only for a single coordinate, else two joint ids.
        if _is_joint(joints) or (isinstance(joints, tuple) and _is_pair(joints) and (
                isinstance(joints[0], str) or size == 1)):
            joints = (joints,)
        try:
            joints = tuple(joints)
        except TypeError:
            raise MjstampError(
                f"task {self.name!r}: variable {var!r}: initial_{kind}={joints!r} is not a "
                "sequence of joints; valid: a joint name or id, or (joint, k), per coordinate"
            ) from None
        if len(joints) != size:
            raise MjstampError(
                f"task {self.name!r}: variable {var!r} has {size} coordinates but "
                f"initial_{kind} names {len(joints)} joints"
            )
        m = self.scene.m
        out = []
        for j in joints:
            if _is_joint(j):
                ref, k = j, 0
            elif _is_pair(j):
                ref, k = j[0], int(j[1])
            else:
                raise MjstampError(
                    f"task {self.name!r}: variable {var!r}: initial_{kind} entry {j!r} is "
                    "not a joint; valid: a joint name or id, or (joint, k) for its k-th "
                    "coordinate"
                )
            jid = self.scene.joint(ref)
            width = joint_width(int(m.jnt_type[jid]), kind)
            if not 0 <= k < width:
                raise MjstampError(
                    f"task {self.name!r}: variable {var!r}: joint {ref!r} has {width} "
                    f"{kind} coordinates; index {k} is not in 0..{width - 1}"
                )
            base = self.scene.dof_adr(jid) if kind == "qvel" else self.scene.qpos_adr(jid)
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
            per coordinate: a joint name or id, or (joint, k) for the k-th
            velocity of a free or ball joint (a free joint: vx, vy, vz, then
            ωx, ωy, ωz).
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
            name, Kind.BOX, size, low, high,
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
            name, Kind.ANGLE, size, np.full(size, float(low)), np.full(size, float(high)),
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
            name, Kind.DISCRETE, size, np.full(size, -bound), np.full(size, bound),
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

        Any pair of geoms MuJoCo C collides can be a symbol: plans decode it from
        C's colliders (`verify.Replay.contact`: distance < 0 at zero margin).
        STAMP relaxes it with the soft indicator of App. B-B, on the pair's JAX
        signed distance (`scenes.distance.SUPPORTED_PAIRS`); a pair without one
        (cylinder-box, a mesh against a cylinder) decodes all the same, but only
        solvers that need no soft indicator take the task (`Problem.relaxes`).

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
        pair = None
        if before is not None:
            pair = (self.scene.geom(before[0]), self.scene.geom(before[1]))
        for ids in ((g1, g2), pair):
            if ids is not None:
                self._symbol_pair(name, *ids)  # a pair C cannot collide fails here
        self.contacts.append(Contact(name, g1, g2, pair, float(alpha), float(beta)))

    def cost(self, name: str, fn: Callable[[Rollout], jax.Array], weight: float = 1.0, *,
             tolerance: float | None = None):
        """Adds weight · fn(rollout) to the cost C (likelihood, eq. 8); fn -> (n,).

        A cost of `mjstamp.tasks.costs` has its names looked up in the scene
        here; one that is a squared distance (`costs.reach`, `costs.box_target`)
        brings its residuals, which the solve's precision polish descends on.

        Args:
          name: the term's name.
          fn: the cost.
          weight: its weight.
          tolerance: for a cost with residuals, the goal's radius ‖r‖ (metres
            for a reach) within which the polish may stop; None: the cost's own
            or, for a reach, the radius of a `costs.reaches` success on the
            same body and goals.
        """
        residual = None
        if isinstance(fn, costs.Bound):
            residual = self._bind(fn, f"cost {name!r}", residuals=True)
            if tolerance is None:
                tolerance = fn.tolerance
            self._goals[name] = fn.goal
        if tolerance is not None and residual is None:
            raise MjstampError(f"task {self.name!r}: cost {name!r}: tolerance= is for a cost "
                               "with residuals (costs.reach, costs.box_target, or "
                               "task.residuals)")
        self._add_term(self.costs, name, self._bind(fn, f"cost {name!r}"), weight, "cost",
                       residual=residual, tolerance=tolerance)

    def residuals(self, name: str, fn: Callable[[Rollout], jax.Array], weight: float = 1.0, *,
                  tolerance: float | None = None):
        """Adds weight · Σ_j r_j² to the cost C, for residuals fn(rollout) -> r (n, m).

        The cost as the polish reads it: Gauss–Newton on r lands a plan on a
        precise goal in a few steps (`mjstamp.svgd.polish`).

        Args:
          name: the term's name.
          fn: the residuals, e.g. `lambda r: r.body_pos("ball")[:, -1, :2] - goal`.
          weight: the term's weight.
          tolerance: ‖r‖ within which the goal is met (its radius), where the
            polish may stop; None: it stops when its steps stall.
        """
        if isinstance(fn, costs.Bound):  # costs.reach, costs.box_target: their own residuals
            if fn.residuals is None:
                raise MjstampError(f"task {self.name!r}: residuals {name!r}: this cost of "
                                   "mjstamp.tasks.costs has no residuals; declare it with "
                                   "task.cost")
            self.cost(name, fn, weight, tolerance=tolerance)
            return
        fn = self._bind(fn, f"residuals {name!r}")
        if not callable(fn):
            raise MjstampError(f"task {self.name!r}: residuals {name!r} must be callable")
        where = f"task {self.name!r}: residuals {name!r}"
        self._add_term(self.costs, name, SumOfSquares(fn, where), weight, "residuals",
                       residual=fn, tolerance=tolerance)

    def prior(self, name: str, fn: Callable[[dict], jax.Array], weight: float = 1.0):
        """Adds weight · fn(params) to log p(θ) (eq. 7); fn({name: (n, size)}) -> (n,)."""
        self._add_term(self.priors, name, fn, weight, "prior")

    def _add_term(self, terms, name, fn, weight, what, *, residual=None, tolerance=None):
        self._check_new(name, what)
        if not callable(fn):
            raise MjstampError(f"task {self.name!r}: {what} {name!r} must be callable")
        if not (np.isfinite(weight) and weight >= 0):
            raise MjstampError(
                f"task {self.name!r}: {what} {name!r} weight={weight} must be finite and >= 0"
            )
        if tolerance is not None and (
                isinstance(tolerance, bool) or not isinstance(tolerance, numbers.Real)
                or not (math.isfinite(tolerance) and tolerance >= 0)):
            raise MjstampError(f"task {self.name!r}: {what} {name!r} tolerance={tolerance!r} "
                               "must be a number >= 0 (the goal's radius) or None")
        terms.append(Term(name, fn, float(weight), residual,
                          None if tolerance is None else float(tolerance)))

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
        """Sets the success predicate on a MuJoCo C replay; see `verify.Replay`.

        fn(replay) -> (ok (n,) bool, label (n,) str): whether each plan succeeds
        and a label that becomes part of its task plan (e.g. the pocket). A
        predicate of `mjstamp.tasks.costs` has its names looked up in the scene here.
        """
        self.success_fn = self._bind(fn, "success")
        self._success_goal = (fn.goal, fn.tolerance) if isinstance(fn, costs.Bound) else None

    def _bind(self, fn, what: str, *, residuals: bool = False):
        """The function with its scene names resolved, where it is a `costs.Bound`; else fn.

        `residuals`: the Bound's residual function instead (None if it has none).
        """
        if not isinstance(fn, costs.Bound):
            return fn
        try:
            return fn.bind_residuals(self.scene) if residuals else fn.bind(self.scene)
        except MjstampError as e:
            raise MjstampError(f"task {self.name!r}: {what}: {e}") from None

    def uncertain(
        self,
        kind: str | None = None,
        names: Sequence[str | int] | str | None = None,
        *,
        spread: float | None = None,
        distribution: str | None = None,
    ) -> None:
        """Declares physics the plans should survive; scored on every verified plan.

        `task.uncertain()` declares the defaults: ±20% friction on every geom,
        ±10% mass on every body, 5 mm initial position noise on every body
        with a free or slide joint. With a kind, it declares that one (kinds
        and what they scale: `mjstamp.scenes.uncertainty.KINDS`); a later
        declaration replaces what an earlier one said of the same elements. A
        task that declares nothing is scored under the defaults.

        Args:
          kind: "friction", "mass", "damping", "solref", "gain" or "position";
            None: the defaults above.
          names: MJCF names (or ids) of the geoms, bodies, joints or actuators;
            None: every one the kind applies to.
          spread: a share for relative kinds (0.2: ×(1 ± 0.2) uniform, or the
            standard deviation of a normal factor), metres for "position";
            None: the kind's default (`uncertainty.DEFAULT_SPREAD`).
          distribution: "uniform" or "normal"; None: normal for "position",
            uniform otherwise.
        """
        if kind is None:
            if names is not None or spread is not None or distribution is not None:
                raise MjstampError(f"task {self.name!r}: uncertain() without a kind declares "
                                   "the defaults and takes nothing else; valid kinds: "
                                   + ", ".join(uncertainty.KINDS))
            for u in uncertainty.defaults(self.scene, self.name):
                self.uncertainties = uncertainty.merge(self.uncertainties, u)
            return
        u = uncertainty.resolve(self.scene, self.name, kind, names, spread=spread,
                                distribution=distribution)
        self.uncertainties = uncertainty.merge(self.uncertainties, u)

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

    def use_kernel(self, kernel=None, *, weights: Mapping[str, float] | None = None) -> None:
        """Replaces the default SVGD kernel, or reweighs its parts.

        Args:
          kernel: an `mjstamp.svgd` Kernel, or a function `problem -> Kernel`
            (it may read `problem.param_features`, `feature_groups`); None
            keeps the default (see `problem.default_kernel`).
          weights: weights of the default kernel's parts, any of "continuous",
            "angles", "actions", "symbols" (1.0 each by default).
        """
        if weights is not None:
            unknown = sorted(set(weights) - set(self.kernel_weights))
            if unknown:
                raise MjstampError(
                    f"task {self.name!r}: kernel weight {unknown[0]!r} is not a part of the "
                    f"default kernel; valid: {', '.join(self.kernel_weights)}"
                )
            self.kernel_weights = {
                **self.kernel_weights, **{k: float(v) for k, v in weights.items()}
            }
        if kernel is not None:
            self.kernel_override = kernel


    def _symbol_pair(self, symbol: str, g1: int, g2: int) -> None:
        """Checks (at declaration) that MuJoCo C collides a symbol's geom pair.

        Its JAX signed distance, the symbol's soft indicator in the gradient
        model, is memoised where there is one; a pair of types without one
        (cylinder-box, a mesh against a cylinder) still decodes from C
        (`Problem.relaxes`). Any other error of the distance (a mesh without a
        convex hull) is raised here.
        """
        try:
            kinematics.check_touch_pair(self.scene.m, g1, g2)
        except MjstampError as e:
            raise MjstampError(f"task {self.name!r}: symbol {symbol!r}: {e}") from None
        key = kinematics.pair_key(g1, g2)
        if key not in self._distance_fns:
            try:
                self._distance_fns[key] = distance_fn(self.scene.m, self.name, *key)
            except UnsupportedPairError:
                pass  # N.B. decoded from C alone; `Problem.unrelaxed_reason` says why

    @property
    def dim(self) -> int:
        """Number of coordinates of θ."""
        return sum(v.size for v in self.variables)

    def check(self) -> None:
        """Validates the declaration as a whole (called before solving)."""
        if not self.variables:
            raise MjstampError(f"task {self.name!r} declares no variables")
        if not self.costs:
            raise MjstampError(f"task {self.name!r} declares no costs")



    # ------------------------------------------------------------------
    # Building.

    def _resolved_costs(self) -> tuple[Term, ...]:
        """The cost terms, a reach without a tolerance taking its `reaches` success's radius."""
        out = []
        goal, radius = self._success_goal or (None, None)
        for t in self.costs:
            if (t.residual is not None and t.tolerance is None and goal is not None
                    and self._goals.get(t.name) == goal):
                t = dataclasses.replace(t, tolerance=radius)
            out.append(t)
        return tuple(out)

    def fingerprint(self) -> str:
        """A hash of everything the declaration computes with.

        The scene's compiled model and gradient options, horizon, variables,
        symbols, every cost, prior, controls, actions and success function
        (their code, constants, closures and the globals they read, see
        `mjstamp.tasks.fingerprint`), the kernel, display hints and settings.
        Re-running a script or notebook cell gives the same value; changing a
        cost's code or constant gives another. Keys the trace cache.
        """
        h = hashlib.sha256()
        h.update(fp.model_digest(self.scene))
        # N.B. a residual enters only where declared: other terms keep the keys they had.
        terms = [(t.name, t.weight, fp.of(t.fn))
                 + (() if t.residual is None else (fp.of(t.residual), t.tolerance))
                 for t in self.costs + self.priors]
        h.update(json.dumps({
            "name": self.name, "horizon": self.horizon,
            "grad": dataclasses.asdict(self.scene.grad_options),
            "precision": self.scene.precision,
            "variables": [fp.of(dataclasses.astuple(v)) for v in self.variables],
            "contacts": [dataclasses.astuple(c) for c in self.contacts],
            "terms": terms,
            "functions": [fp.of(f) for f in (self.controls_fn, self.actions_fn, self.success_fn)],
            "kernel": [self.kernel_weights, fp.of(self.kernel_override)],
            "bounds": self.bound_stiffness, "display": self.display_hints,
            "settings": fp.of(self.settings),
            # N.B. only when declared: tasks without it keep the keys they had.
            **({"uncertain": [u.describe() for u in self.uncertainties]}
               if self.uncertainties else {}),
        }, sort_keys=True, default=str).encode())
        return h.hexdigest()[:32]

    def build(self) -> Problem:
        """Compiles the declaration into a `Problem` (memoised while it is unchanged).

        Raises:
          MjstampError: the declaration is incomplete (see `check`).
        """
        self.check()
        key = self.fingerprint()
        if self._built is not None and self._built[0] == key:
            return self._built[1]
        problem = Problem(
            name=self.name, scene=self.scene, horizon=self.horizon,
            variables=tuple(self.variables), contacts=tuple(self.contacts),
            costs=self._resolved_costs(), priors=tuple(self.priors),
            controls_fn=self.controls_fn, actions_fn=self.actions_fn,
            success_fn=self.success_fn, kernel=None, display=dict(self.display_hints),
            settings=dict(self.settings), description=self.description, fingerprint=key,
            extras=dict(self.extras), bound_stiffness=self.bound_stiffness,
            distance_fns=dict(self._distance_fns), declaration=self.describe(),
            uncertain=self.uncertainties or uncertainty.defaults(self.scene, self.name),
            uncertain_declared=bool(self.uncertainties),
        )
        override = self.kernel_override
        if override is None:
            kernel = default_kernel(problem, self.kernel_weights)
        elif isinstance(override, svgd.Kernel):
            kernel = override
        else:
            kernel = override(problem)
        problem = dataclasses.replace(problem, kernel=kernel)
        self._built = (key, problem)
        return problem

    def describe(self) -> dict[str, Any]:
        """A JSON-ready summary of the declaration."""
        return {
            "name": self.name,
            "scene": self.scene.name,
            "horizon": self.horizon,
            "timestep": float(self.scene.m.opt.timestep),
            "variables": [
                {"name": v.name, "kind": v.kind.value, "size": v.size,
                 "low": v.low.tolist(), "high": v.high.tolist(),
                 **({"options": list(v.options), "phases": v.phases} if v.options else {})}
                for v in self.variables
            ],
            "symbols": [c.name for c in self.contacts],
            "costs": {t.name: t.weight for t in self.costs},
            "priors": {t.name: t.weight for t in self.priors},
            "display": self.display_hints,
            "uncertain": [u.describe() for u in self.uncertainties],
        }


__all__ = ["Contact", "Kind", "Problem", "Rollout", "Task", "Term", "Variable"]
